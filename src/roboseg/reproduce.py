"""``make reproduce``: the paper's pipeline end to end on a simulated study, with a results page.

``python -m roboseg.reproduce [out=DIR] [results=PAGE.md] [recipe=cpu|paper] [frames=N] ...``
(Hydra overrides of ``conf/reproduce.yaml``). Every step is a ``roboseg-*`` command (or a
benchmark) run in a subprocess, or a small evaluation in this process; each finished stage leaves
``out/.<stage>.done`` (the :class:`roboseg.pipeline.Stages` markers) so a rerun skips it. Each
command's output goes to the terminal and to ``out/logs/<stage>.log`` (its standard output alone
to ``out/logs/<stage>.stdout``).

The study (names: ``lab_*`` bootstrap recordings, ``or_*`` operating-room recordings):

1. bootstrap: ``lab_*`` recordings annotated from their own ``/tf_static`` (a calibrated lab
   rig), a small segmenter trained on their undraped frames and exported. It stands in for
   SAM 2, which the paper uses to segment undraped robots.
2. ``or_*``: the undraped phase of each recording registered (swarm + SDR) with the bootstrap
   segmenter, never reading the truth; the draped phase self-annotated with that estimate
   (``calibration=pose``). The annotation IoU against the simulator's masks and the estimates'
   errors against its ``/tf_static`` are measured (evaluation only).
3. the recipe's models trained, exported, evaluated on the two-robot draped test recording.
4. the draped test recording registered with SDR and SDR with prior; errors vs the truth.
5. tracking demo (breathing recording → ``roboseg-track``); 6. benchmarks; 7. the results page.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import io
import json
import logging
import math
import os
import shlex
import shutil
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, NoReturn

import hydra
import yaml
from omegaconf import DictConfig, OmegaConf

from roboseg.config import CONF_DIR
from roboseg.pipeline import Stages, best_checkpoint, hash_split, script
from roboseg.reproduce_report import machine_description, today

log = logging.getLogger("roboseg.reproduce")

PROJECT_ROOT = Path(CONF_DIR).resolve().parent
LAB_SEED_OFFSET = 10_000
#: what may segment the operating-room recordings' undraped phase (``undraped.segmentor``)
UNDRAPED_SEGMENTORS = ("model", "motion")


# --- stages ----------------------------------------------------------------------------------


@dataclass
class Step:
    """One stage: a command (``argv``, run in ``cwd``) or a Python callable (``fn``).

    A ``tolerant`` command that fails is recorded (exit status in its marker) and the run goes on:
    used where a failure is itself a result (a registration that does not converge, a bench).
    Consecutive ``parallel`` commands are independent and single-threaded: they run side by
    side, ``jobs`` at a time, each as its own process.
    """

    name: str
    argv: list[str] | None = None
    fn: Callable[[], None] | None = None
    tolerant: bool = False
    cwd: Path | None = None
    parallel: bool = False


def _pump(stream: IO[str], sinks: Sequence[IO[str]], lock: threading.Lock) -> None:
    for line in stream:
        with lock:
            for sink in sinks:
                sink.write(line)
                sink.flush()


class ReproduceStages(Stages):
    """:class:`Stages` with progress (``[k/N]``, elapsed minutes), output logged per stage,
    tolerant stages and in-process stages."""

    def __init__(self, root: Path, total: int, runner: str = "fork") -> None:
        super().__init__(root)
        if runner not in ("fork", "process") or (runner == "fork" and not hasattr(os, "fork")):
            runner = "process"
        self.runner = runner
        self.total = total
        self.count = 0
        self._count_lock = threading.Lock()
        self.t0 = time.perf_counter()
        self.logs = root / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)

    def _prefix(self, index: int) -> str:
        minutes = (time.perf_counter() - self.t0) / 60
        return f"[{index}/{self.total} {minutes:5.1f} min]"

    def status(self, name: str) -> tuple[float | None, int | None]:
        """``(seconds, exit status)`` from a stage's marker; ``(None, None)`` when not done."""
        marker = self.marker(name)
        if not marker.exists():
            return None, None
        lines = marker.read_text().splitlines()
        seconds = float(lines[0].split()[0]) if lines else None
        code = next((int(x.split()[-1]) for x in lines if x.startswith("exit status")), 0)
        return seconds, code

    def interval(self, name: str) -> tuple[float, float] | None:
        """``(start, end)`` (Unix time, s) of a finished stage, if its marker records it."""
        marker = self.marker(name)
        if not marker.exists():
            return None
        for line in marker.read_text().splitlines():
            if line.startswith("ran "):
                start, end = line.split()[1:3]
                return float(start), float(end)
        return None

    def _launch(
        self,
        argv: Sequence[str],
        cwd: Path | None,
        fn: Callable[[], Any] | None = None,
        process: bool = False,
    ) -> tuple[Callable[[], int], IO[str], IO[str]]:
        """Start a stage: ``(wait() -> exit status, stdout, stderr)``. With the fork runner a
        ``roboseg-*`` command (or ``fn``) runs in a forked child of this process, which has
        imported the libraries once (the same command, without its start-up cost); with
        ``process`` (stages running side by side: no fork from a threaded parent) the command
        runs as its own process."""
        if process and fn is not None:
            raise ValueError("a stage run as its own process must be a command, not a function")
        target = fn
        if target is None and self.runner == "fork" and cwd is None and not process:
            target = _entry_point(argv[0])
        if target is None:
            proc = subprocess.Popen(
                list(argv), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                cwd=cwd, bufsize=1, errors="replace",
            )
            assert proc.stdout is not None and proc.stderr is not None
            return proc.wait, proc.stdout, proc.stderr
        out_r, out_w = os.pipe()
        err_r, err_w = os.pipe()
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:  # child: never returns
            os.close(out_r)
            os.close(err_r)
            _run_child(target, list(argv), out_w, err_w)
        os.close(out_w)
        os.close(err_w)

        def wait() -> int:
            return os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])

        return wait, os.fdopen(out_r, errors="replace"), os.fdopen(err_r, errors="replace")

    def _execute(
        self,
        name: str,
        argv: Sequence[str],
        cwd: Path | None,
        fn: Callable[[], Any] | None,
        process: bool = False,
    ) -> int:
        """Run one stage, its output teed to the terminal and the stage's log files."""
        lock = threading.Lock()
        with (
            open(self.logs / f"{name}.log", "w") as full,
            open(self.logs / f"{name}.stdout", "w") as out,
        ):
            full.write(f"$ {shlex.join(argv)}\n# {today()} on {machine_description()}\n")
            full.flush()
            wait, stdout, stderr = self._launch(argv, cwd, fn, process)
            pumps = [
                threading.Thread(target=_pump, args=(stdout, [sys.stdout, full, out], lock)),
                threading.Thread(target=_pump, args=(stderr, [sys.stderr, full], lock)),
            ]
            for p in pumps:
                p.start()
            code = wait()
            for p in pumps:
                p.join()
            stdout.close()
            stderr.close()
        return code

    def run(  # type: ignore[override]
        self,
        name: str,
        argv: Sequence[str],
        *,
        tolerant: bool = False,
        cwd: Path | None = None,
        fn: Callable[[], Any] | None = None,
        process: bool = False,
    ) -> bool:
        """Run stage ``name`` (the command ``argv``, or ``fn`` in a child process) unless it
        already finished; a failure raises ``SystemExit`` unless ``tolerant`` (then it is
        recorded in the marker and the run goes on). ``process``: see :meth:`_launch`."""
        with self._count_lock:
            self.count += 1
            index = self.count  # this stage's number (others may start while it runs)
        if self.marker(name).exists():
            print(f"{self._prefix(index)} [{name}] done already, skipped", flush=True)
            return False
        shown = shlex.join(argv) if fn is None else "(in a child process)"
        print(f"{self._prefix(index)} [{name}] $ {shown}", flush=True)
        t0, started = time.perf_counter(), time.time()
        code = self._execute(name, argv, cwd, fn, process)
        seconds = time.perf_counter() - t0
        if code != 0 and not tolerant:
            raise SystemExit(
                f"[{name}] failed with exit status {code} (log: {self.logs / f'{name}.log'})"
            )
        self.marker(name).write_text(
            f"{seconds:.1f} s\n"
            + (f"exit status {code}\n" if code else "")
            + f"ran {started:.1f} {time.time():.1f}\n"
        )
        note = f", exit status {code} (recorded, continuing)" if code else ""
        print(f"{self._prefix(index)} [{name}] finished in {seconds:.0f} s{note}", flush=True)
        return True

    def run_side_by_side(self, steps: Sequence[Step], jobs: int) -> int:
        """Run independent command ``steps`` (see :attr:`Step.parallel`) ``jobs`` at a time,
        each as its own process; returns how many ran. A failing non-tolerant one raises
        ``SystemExit`` once the others have finished."""
        def one(step: Step) -> bool:
            assert step.argv is not None, f"{step.name}: only commands run side by side"
            return self.run(
                step.name, step.argv, tolerant=step.tolerant, cwd=step.cwd, process=jobs > 1
            )

        if jobs <= 1 or len(steps) <= 1:
            return sum(one(s) for s in steps)
        with ThreadPoolExecutor(max_workers=jobs) as pool:
            futures = [pool.submit(one, s) for s in steps]
        return sum(f.result() for f in futures)

    def wall_seconds(self, names: Sequence[str]) -> float:
        """Wall-clock time (s) covered by the recorded runs of stages ``names`` (the union of
        their intervals: stages side by side count once); stages without one add their
        duration."""
        spans, loose = [], 0.0
        for name in names:
            span = self.interval(name)
            if span is not None:
                spans.append(span)
            else:
                loose += self.status(name)[0] or 0.0
        total, end = 0.0, -math.inf
        for a, b in sorted(spans):
            if b > end:
                total += b - max(a, end)
                end = b
        return total + loose


def _entry_point(script: str) -> Callable[[], Any] | None:
    """The function behind the console script ``script`` (a path or a name), if installed."""
    name = Path(script).name
    for ep in importlib.metadata.entry_points(group="console_scripts", name=name):
        return ep.load()
    return None


def _run_child(target: Callable[[], Any], argv: list[str], out_fd: int, err_fd: int) -> NoReturn:
    """In a forked child: output to the given pipes, ``sys.argv = argv``, run, exit."""
    code = 0
    try:
        os.dup2(out_fd, 1)
        os.dup2(err_fd, 2)
        os.close(out_fd)
        os.close(err_fd)
        sys.stdout = sys.__stdout__ = io.TextIOWrapper(
            os.fdopen(1, "wb", closefd=False), line_buffering=True
        )
        sys.stderr = sys.__stderr__ = io.TextIOWrapper(
            os.fdopen(2, "wb", closefd=False), line_buffering=True
        )
        sys.argv = list(argv)
        from hydra.core.global_hydra import GlobalHydra

        GlobalHydra.instance().clear()  # this process's own Hydra run is not the child's
        target()
    except SystemExit as exc:
        if isinstance(exc.code, int):
            code = exc.code
        elif exc.code is not None:
            print(exc.code, file=sys.stderr)
            code = 1
    except BaseException:  # noqa: BLE001 - reported like an interpreter would, exit status 1
        traceback.print_exc()
        code = 1
    finally:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)


# --- the study -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Recording:
    """One simulated recording: ``stem`` (its name), ``role`` (lab | or), ``split``, seed."""

    stem: str
    role: str
    split: str
    seed: int
    robots: int


@dataclass(frozen=True)
class ModelSpec:
    """One trained model of the recipe."""

    name: str
    experiment: str
    subset: str
    overrides: tuple[str, ...] = ()


@dataclass
class Layout:
    """Where everything goes under ``out``."""

    out: Path
    page: Path
    lab: list[Recording] = field(default_factory=list)
    study: list[Recording] = field(default_factory=list)
    models: list[ModelSpec] = field(default_factory=list)

    def recording(self, rec: Recording) -> Path:
        if rec.role == "lab":
            return self.out / "recordings" / "lab" / f"{rec.stem}.mcap"
        # one folder per recording: roboseg-annotate annotates a folder with one calibration
        return self.out / "recordings" / "or" / rec.stem / f"{rec.stem}.mcap"

    @property
    def bootstrap(self) -> Path:
        return self.out / "bootstrap"

    @property
    def bootstrap_onnx(self) -> Path:
        return self.bootstrap / "model.onnx"

    def undraped_pose(self, rec: Recording, robot: str) -> Path:
        return self.out / "registration" / "undraped" / rec.stem / robot / "pose.yaml"

    def calibration(self, rec: Recording) -> Path:
        return self.out / "registration" / "undraped" / rec.stem / "calibration.yaml"

    def dataset(self, subset: str) -> Path:
        return self.out / "annotated" / subset

    def part(self, subset: str, rec: Recording) -> Path:
        return self.out / "annotated" / "parts" / subset / rec.stem

    def onnx(self, name: str) -> Path:
        return self.out / "models" / f"{name}.onnx"

    def ckpt(self, name: str) -> Path:
        return self.out / "models" / f"{name}.ckpt"

    def draped_pose(self, method: str, robot: str) -> Path:
        return self.out / "registration" / "draped" / method / robot / "pose.yaml"

    @property
    def test(self) -> Recording:
        return next(r for r in self.study if r.split == "test")

    @property
    def breathing(self) -> Path:
        return self.out / "recordings" / "breathing" / "breathing.mcap"

    @property
    def figures(self) -> Path:
        return self.page.parent / self.page.stem


def robots_of(rec: Recording) -> list[str]:
    """Robot namespaces of a simulated recording (``robot_0``, ``robot_1``)."""
    return [f"robot_{i}" for i in range(rec.robots)]


def plan_study(cfg: DictConfig) -> tuple[list[Recording], list[Recording]]:
    """The lab and operating-room recordings of ``cfg`` (names, splits, seeds, robots)."""
    seed = int(cfg.seed)
    lab = [  # stride 10: up to 100 lab recordings per split before seeds could repeat
        Recording(f"lab_{split}_{i:02d}", "lab", split,
                  seed + LAB_SEED_OFFSET + 10 * i + hash_split(split), 1)
        for split, count in cfg.lab.recordings.items() for i in range(int(count))
    ]
    study = [
        Recording(
            f"or_{split}_{i:02d}", "or", split, seed + 100 * i + hash_split(split),
            int(cfg.operating_room.test_robots) if split == "test" else 1,
        )
        for split, count in cfg.operating_room.recordings.items() for i in range(int(count))
    ]
    for name, group, needed in (("lab", lab, ("train", "val")),
                                ("operating_room", study, ("train", "val", "test"))):
        missing = [s for s in needed if not any(r.split == s for r in group)]
        if missing:
            raise SystemExit(f"{name}.recordings: needs at least one {missing} recording")
    seeds: dict[int, str] = {}
    for rec in lab + study:
        if rec.seed in seeds:
            raise SystemExit(
                f"recordings {seeds[rec.seed]} and {rec.stem} would share seed {rec.seed} "
                "(the same scene in two places); use fewer recordings per split"
            )
        seeds[rec.seed] = rec.stem
    return lab, study


def model_specs(cfg: DictConfig) -> list[ModelSpec]:
    """The trained models of ``cfg.recipe``."""
    recipe = str(cfg.recipe)
    if recipe not in cfg.recipes:
        raise SystemExit(f"recipe={recipe}: not one of {list(cfg.recipes)}")
    specs = [
        ModelSpec(str(m.name), str(m.experiment), str(m.get("subset", "full")),
                  tuple(str(o) for o in m.get("overrides", []) or []))
        for m in cfg.recipes[recipe]
    ]
    if not specs:
        raise SystemExit(f"recipes.{recipe}: no models")
    return specs


# --- in-process stages -----------------------------------------------------------------------


def write_calibration(layout: Layout, rec: Recording) -> None:
    """One calibration YAML (``robots: {name: {T_cam_base, camera_frame, base_frame}}``) from
    the undraped registrations of ``rec``'s robots."""
    robots = {}
    for robot in robots_of(rec):
        pose = layout.undraped_pose(rec, robot)
        if not pose.is_file():
            raise SystemExit(f"{pose}: registration of {rec.stem}/{robot} wrote no pose")
        doc = yaml.safe_load(pose.read_text())
        robots[robot] = {k: doc[k] for k in ("T_cam_base", "camera_frame", "base_frame")}
    path = layout.calibration(rec)
    text = "# T_cam_base: robot base -> left optical frame (metres), from roboseg-register\n"
    path.write_text(text + yaml.safe_dump({"robots": robots}, sort_keys=False))


def merge_dataset(layout: Layout, subset: str) -> None:
    """Gather the per-recording annotations of ``subset`` into one dataset folder: the files
    (hard links, else copies) and one ``manifest.json`` listing them all."""
    from roboseg.annotate.batch import MANIFEST_NAME, write_json_atomic

    root = layout.dataset(subset)
    root.mkdir(parents=True, exist_ok=True)
    merged: dict[str, Any] | None = None
    for rec in layout.study:
        part = layout.part(subset, rec)
        manifest = json.loads((part / MANIFEST_NAME).read_text())
        for entry in manifest["recordings"]:
            src, dst = part / entry["file"], root / entry["file"]
            dst.unlink(missing_ok=True)
            try:
                os.link(src, dst)
            except OSError:
                shutil.copy2(src, dst)
        if merged is None:
            merged = {k: v for k, v in manifest.items() if k not in ("recordings", "totals")}
            merged["recordings"] = []
        merged["recordings"] += manifest["recordings"]
    assert merged is not None
    recs = merged["recordings"]
    merged["totals"] = {
        "frames_total": sum(r["frames_total"] for r in recs),
        "frames_kept": sum(r["frames_kept"] for r in recs),
        "skipped": {k: sum(r["skipped"][k] for r in recs) for k in recs[0]["skipped"]},
    }
    write_json_atomic(root / MANIFEST_NAME, merged)


def measure_annotation(layout: Layout, subset: str, cfg: DictConfig) -> None:
    """``metrics/annotation.json``: per operating-room recording, the IoU of the self-annotated
    masks vs the simulator's and the error of each undraped estimate vs ``/tf_static``."""
    from roboseg.reproduce_report import annotation_iou, registration_error
    from roboseg.robot import load_robot

    robot = load_robot(None)
    rows = []
    for rec in layout.study:
        row: dict[str, Any] = {"recording": rec.stem, "split": rec.split, "robots": rec.robots}
        row["annotation"] = annotation_iou(layout.dataset(subset) / f"{rec.stem}.mcap")
        row["registration"] = [
            registration_error(layout.undraped_pose(rec, r), layout.recording(rec), robot,
                               "undraped")
            for r in robots_of(rec)
        ]
        rows.append(row)
    _write_json(layout.out / "metrics" / "annotation.json", {"subset": subset, "rows": rows})


def measure_localisation(layout: Layout, cfg: DictConfig) -> None:
    """``metrics/localisation.json``: errors of the draped test registrations vs the truth."""
    from roboseg.reproduce_report import registration_error
    from roboseg.robot import load_robot

    robot = load_robot(None)
    rows = []
    for method in ("sdr", "sdr_prior"):
        for r in robots_of(layout.test):
            pose = layout.draped_pose(method, r)
            if not pose.is_file():
                rows.append({"method": method, "robot": r, "error": "no pose written"})
                continue
            rows.append({"method": method, **registration_error(
                pose, layout.recording(layout.test), robot, "draped")})
    _write_json(layout.out / "metrics" / "localisation.json", {"rows": rows})


def _write_json(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    tmp.replace(path)


# --- the plan --------------------------------------------------------------------------------


def _register_argv(
    cfg: DictConfig, rec: Recording, recording: Path, model: Path | None, method: str,
    phase: str, robot: str, out: Path, extra: Sequence[str] = (),
) -> list[str]:
    """roboseg-register's command line; ``model`` None: ``extra`` names the segmentor."""
    two_robots = cfg.register.get("two_robot_overrides", []) if rec.robots > 1 else []
    return [
        script("roboseg-register"), f"recording={recording}",
        *([f"model={model}"] if model is not None else []), f"method={method}",
        f"phase={phase}", f"robot.name={robot}", f"configs={int(cfg.register.configs)}",
        f"threads={int(cfg.threads)}", f"out={out}", *cfg.register.overrides, *two_robots,
        *extra,
    ]


def undraped_segmentor(cfg: DictConfig) -> str:
    """``undraped.segmentor`` of ``cfg``: ``model`` (the lab bootstrap) or ``motion``."""
    kind = str(cfg.undraped.segmentor)
    if kind not in UNDRAPED_SEGMENTORS:
        raise SystemExit(
            f"undraped.segmentor={kind}: not one of {', '.join(UNDRAPED_SEGMENTORS)} (a prompt "
            "needs a person's clicks per recording, which a simulated study does not have)"
        )
    return kind


def _train_steps(
    layout: Layout, name: str, experiment: str, root: Path, overrides: Sequence[str],
    cfg: DictConfig, ckpt: Path, onnx: Path,
) -> list[Step]:
    """Train → copy the best checkpoint → export."""
    run_dir = layout.out / "train" / name

    def keep_best() -> None:
        ckpt.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(best_checkpoint(run_dir / "checkpoints"), ckpt)

    return [
        Step(f"train_{name}", [
            script("roboseg-train"), f"experiment={experiment}", f"data.root={root}",
            f"hydra.run.dir={run_dir}", f"seed={int(cfg.seed)}", *overrides,
        ]),
        Step(f"checkpoint_{name}", fn=keep_best),
        Step(f"export_{name}", [
            script("roboseg-export"), f"ckpt={ckpt}", f"out={onnx}", f"data.root={root}",
        ]),
    ]


def build_plan(cfg: DictConfig, layout: Layout) -> list[Step]:
    """Every stage of the run, in order (all paths are known before anything runs)."""
    steps: list[Step] = []
    frames, width, height = int(cfg.frames), int(cfg.width), int(cfg.height)

    def simulate(rec: Recording, extra: Sequence[str], n_frames: int = frames) -> Step:
        path = layout.recording(rec)
        return Step(f"simulate_{rec.stem}", [
            script("roboseg-simulate"), f"out={path.parent}", f"name={rec.stem}",
            f"frames={n_frames}", f"seed={rec.seed}", f"robots={rec.robots}",
            f"camera.width={width}", f"camera.height={height}",
            *cfg.operating_room.simulate_overrides, *extra,
        ])

    # 1. bootstrap: the calibrated lab rig (only when a model segments the undraped phase)
    segmentor = undraped_segmentor(cfg)
    if segmentor == "model":
        lab_frames = frames if cfg.lab.get("frames") is None else int(cfg.lab.frames)
        for rec in layout.lab:
            steps.append(simulate(
                rec, [f"drape.undraped_fraction={float(cfg.lab.undraped_fraction)}"], lab_frames
            ))
        lab_root = layout.bootstrap / "annotated"
        steps.append(Step("annotate_lab", [
            script("roboseg-annotate"), f"in={layout.recording(layout.lab[0]).parent}",
            f"out={lab_root}", "phase=undraped", *cfg.annotate.overrides,
            *cfg.lab.get("annotate_overrides", []),
        ]))
        steps += _train_steps(
            layout, "bootstrap", str(cfg.lab.experiment), lab_root,
            [f"trainer.max_steps={int(cfg.lab.steps)}", "data.val_phase=undraped",
             *cfg.lab.overrides],
            cfg, layout.bootstrap / "model.ckpt", layout.bootstrap_onnx,
        )

    # 2. operating room: register undraped (no truth), self-annotate with the estimate
    undraped_model = layout.bootstrap_onnx if segmentor == "model" else None
    undraped_extra = [*([] if segmentor == "model" else [f"segmentor={segmentor}"]),
                      *cfg.undraped.overrides]
    site = cfg.operating_room.get("site")
    for rec in layout.study:
        steps.append(simulate(rec, [] if site is None else [f"site={int(site)}"]))
    for rec in layout.study:
        for robot in robots_of(rec):
            steps.append(Step(
                f"register_undraped_{rec.stem}_{robot}",
                _register_argv(cfg, rec, layout.recording(rec), undraped_model, "sdr",
                               "undraped", robot, layout.undraped_pose(rec, robot).parent,
                               undraped_extra),
                tolerant=True,  # a poor fit still writes pose.yaml: it is used and reported
                parallel=True,
            ))
    for rec in layout.study:
        steps.append(Step(f"calibration_{rec.stem}", fn=lambda r=rec: write_calibration(layout, r)))
    subsets = list(dict.fromkeys(m.subset for m in layout.models))
    for subset in subsets:
        for rec in layout.study:
            steps.append(Step(f"annotate_{subset}_{rec.stem}", [
                script("roboseg-annotate"), f"in={layout.recording(rec).parent}",
                f"out={layout.part(subset, rec)}", f"calibration={layout.calibration(rec)}",
                f"phase={cfg.annotate.phase}", f"subset={subset}", *cfg.annotate.overrides,
            ]))
        steps.append(Step(f"dataset_{subset}", fn=lambda s=subset: merge_dataset(layout, s)))
    steps.append(Step("annotation_quality",
                      fn=lambda: measure_annotation(layout, subsets[0], cfg)))

    # 3. the recipe's models: train, export, evaluate on the test recording
    for m in layout.models:
        steps += _train_steps(
            layout, m.name, m.experiment, layout.dataset(m.subset),
            [*m.overrides, *cfg.train_overrides], cfg, layout.ckpt(m.name), layout.onnx(m.name),
        )
    models = ",".join(str(layout.onnx(m.name)) for m in layout.models)
    steps.append(Step("evaluate", [
        script("roboseg-eval"), f"models=[{models}]", f"data.root={layout.dataset(subsets[0])}",
        f"out={layout.out / 'eval'}", f"labels={cfg.evaluate.labels}", "progress=false",
        f"threads={int(cfg.threads)}", *cfg.evaluate.overrides,
    ]))

    # 4. the draped test recording: SDR (3 channels) and SDR with prior (4 channels)
    chosen = cfg.localise[str(cfg.recipe)]
    for method in ("sdr", "sdr_prior"):
        for robot in robots_of(layout.test):
            steps.append(Step(
                f"register_draped_{method}_{robot}",
                _register_argv(cfg, layout.test, layout.recording(layout.test),
                               layout.onnx(str(chosen[method])), method, "draped", robot,
                               layout.draped_pose(method, robot).parent),
                tolerant=True,
                parallel=True,
            ))
    steps.append(Step("localisation_errors", fn=lambda: measure_localisation(layout, cfg)))

    # 5. tracking demo
    steps.append(Step("simulate_breathing", [
        script("roboseg-simulate"), f"out={layout.breathing.parent}", "name=breathing",
        "scenario=breathing", f"frames={int(cfg.track.frames)}", f"seed={int(cfg.seed)}",
    ]))
    steps.append(Step("track", [
        script("roboseg-track"), f"recording={layout.breathing}", f"out={layout.out / 'track'}",
        *cfg.track.overrides,
    ], tolerant=True))

    # 6. benchmarks
    fields = {"models": layout.out / "models", "sdr_model": layout.onnx(str(chosen["sdr"])),
              "sdr_prior_model": layout.onnx(str(chosen["sdr_prior"]))}
    for bench in cfg.benches:
        argv = [sys.executable if a == "python" else str(a).format(**fields) for a in bench.cmd]
        steps.append(Step(f"bench_{bench.name}", argv, tolerant=True, cwd=PROJECT_ROOT))
    return steps


def _preimport() -> None:
    """Import what the commands import, once, before forking them (no computation here: the
    forked children start from a process that has not started any thread pool)."""
    for module in ("roboseg.cli.simulate", "roboseg.cli.annotate", "roboseg.cli.train",
                   "roboseg.cli.evaluate", "roboseg.cli.register", "roboseg.cli.track",
                   "export.cli", "roboseg.training", "datamodules"):
        try:
            importlib.import_module(module)
        except ImportError as exc:  # the command then imports it itself, or reports it
            log.debug("pre-import of %s failed: %s", module, exc)


def run_reproduce(cfg: DictConfig) -> Path:
    """Run (or resume) the whole study of ``cfg``; write the results page; return its path."""
    from roboseg.reproduce_report import write_page

    t0 = time.perf_counter()
    out = Path(str(cfg.out)).resolve()
    lab, study = plan_study(cfg)
    layout = Layout(out, Path(str(cfg.results)).resolve(), lab, study, model_specs(cfg))
    plan = build_plan(cfg, layout)
    stages = ReproduceStages(out, len(plan), str(cfg.runner))
    pending = [s.name for s in plan if not stages.marker(s.name).exists()]
    if stages.runner == "fork" and pending:
        _preimport()
    print(f"reproduce: {len(plan)} stages into {out} (recipe={cfg.recipe}); finished stages "
          "are skipped", flush=True)
    ran, jobs, i = 0, max(1, int(cfg.jobs)), 0
    while i < len(plan):
        step = plan[i]
        if step.parallel:  # the run of consecutive side-by-side stages starting here
            j = i
            while j < len(plan) and plan[j].parallel:
                j += 1
            ran += stages.run_side_by_side(plan[i:j], jobs)
            i = j
            continue
        argv = step.argv if step.argv is not None else [step.name]
        ran += stages.run(step.name, argv, tolerant=step.tolerant, cwd=step.cwd, fn=step.fn)
        i += 1
    page = write_page(cfg, layout, plan, stages)
    total = time.perf_counter() - t0
    stage_sum = sum(stages.status(s.name)[0] or 0.0 for s in plan)
    wall = stages.wall_seconds([s.name for s in plan])
    print(f"results page: {page}")
    print(f"total time: {total / 60:.1f} min this run ({ran} of {len(plan)} stages ran); "
          f"all stages: {wall / 60:.1f} min wall clock, {stage_sum / 60:.1f} min of stage "
          "time", flush=True)
    return page


@hydra.main(config_path=CONF_DIR, config_name="reproduce", version_base="1.3")
def main(cfg: DictConfig) -> None:
    log.debug("reproduce config:\n%s", OmegaConf.to_yaml(cfg))
    run_reproduce(cfg)


if __name__ == "__main__":
    main()
