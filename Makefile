# roboseg — every target bootstraps the environment (.venv) first when it is missing.
#   make test       run the test suite
#   make train      the main job on its embedded default: simulate → annotate → train → IoU → export
#   make bench      every benchmark in bench/ (prints measured ratios side by side)
#   make reproduce  the paper's pipeline end to end on a simulated study → docs/results.md
#   make lint       ruff

SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
BIN := $(VENV)/bin
STAMP := $(VENV)/.roboseg-installed
OUT ?= outputs/default
REPRODUCE_OUT ?= outputs/reproduce
RESULTS ?= docs/results.md

.PHONY: test train bench lint env clean reproduce

env: $(STAMP)

# torch first, pinned: the wheels of this exact pair are the ones known to import together
# (torchvision's compiled ops must match torch), then the project with its dev extras.
$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.14.1 torchvision==0.29.1
	$(PY) -m pip install --quiet -e '.[dev]'
	@touch $(STAMP)

# the suite on TEST_WORKERS processes (pytest-xdist), each test file on one of them, one torch
# thread each unless OMP_NUM_THREADS says otherwise (TEST_WORKERS=0: one process)
TEST_WORKERS ?= 2
test: $(STAMP)
	OMP_NUM_THREADS=$${OMP_NUM_THREADS:-1} $(PY) -m pytest -q -p no:cacheprovider \
	  -n $(TEST_WORKERS) --dist loadfile

lint: $(STAMP)
	$(BIN)/ruff check .

bench: $(STAMP)
	@for b in bench/[a-z]*.py; do \
	  case $$b in bench/common.py|bench/__init__.py) continue;; esac; \
	  echo "== $$b"; $(PY) -m bench.$$(basename $$b .py) || exit 1; done

train: $(STAMP)
	$(PY) -m roboseg.pipeline out=$(OUT) $(ARGS)

# not part of `make test`; ARGS passes Hydra overrides, e.g. ARGS="recipe=paper frames=600"
reproduce: $(STAMP)
	$(PY) -m roboseg.reproduce out=$(REPRODUCE_OUT) results=$(RESULTS) $(ARGS)

clean:
	rm -rf outputs multirun .pytest_cache .ruff_cache
