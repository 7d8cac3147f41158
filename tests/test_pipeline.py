"""``make train`` (``python -m roboseg.pipeline``) end to end on a tiny study: every stage runs
once (forked from the pipeline's process), logs its output, and a rerun resumes from markers."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TINY = [
    "simulate.recordings={train:1,val:1,test:1}", "simulate.frames=6", "simulate.width=96",
    "simulate.height=64", "train.experiment=smoke",
]
STAGES = ["simulate_train_00", "simulate_val_00", "simulate_test_00", "annotate", "train",
          "export", "evaluate_eval", "evaluate_eval_val_undraped", "evaluate_eval_val"]


def _pipeline(out: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "roboseg.pipeline", f"out={out}", *TINY, *args],
        cwd=ROOT, capture_output=True, text=True, timeout=600,
    )


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("pipeline")
    proc = _pipeline(out)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out, proc.stdout


def test_every_stage_runs_once_logged_and_ends_on_val_iou(tiny_run: tuple[Path, str]) -> None:
    out, stdout = tiny_run
    lines = stdout.strip().splitlines()
    assert lines[-1].startswith("val/iou=")
    assert 0.0 <= float(lines[-1].split("=", 1)[1]) <= 1.0
    for k, name in enumerate(STAGES, start=1):
        assert (out / f".{name}.done").exists(), name
        assert f"[{k}/{len(STAGES)}" in stdout  # progress: stage k of all
        assert f"[{name}] finished in" in stdout
        assert (out / "logs" / f"{name}.log").stat().st_size > 0, name
    assert (out / "model.onnx").exists() and (out / "model.ckpt").exists()


def test_a_rerun_skips_finished_stages_and_reports_the_same_figures(
    tiny_run: tuple[Path, str],
) -> None:
    out, first = tiny_run
    proc = _pipeline(out)
    assert proc.returncode == 0, proc.stderr[-3000:]
    for name in STAGES:
        assert f"[{name}] done already, skipped" in proc.stdout
        assert f"[{name}] $ " not in proc.stdout
    assert proc.stdout.strip().splitlines()[-1] == first.strip().splitlines()[-1]


def test_the_same_seed_gives_the_same_recordings_labels_and_figures(
    tiny_run: tuple[Path, str], tmp_path: Path,
) -> None:
    out, first = tiny_run
    proc = _pipeline(tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    for rec in sorted((out / "annotated").glob("*.mcap")):
        assert (tmp_path / "annotated" / rec.name).read_bytes() == rec.read_bytes(), rec.name
    for name in ("eval", "eval_val_undraped", "eval_val"):
        a = (out / name / "per_frame_iou.csv").read_text()
        assert (tmp_path / name / "per_frame_iou.csv").read_text() == a, name
    assert proc.stdout.strip().splitlines()[-1] == first.strip().splitlines()[-1]
