"""``make reproduce``: the paper's pipeline end to end on a simulated study, with a results page.

``python -m roboseg.reproduce [out=DIR] [results=PAGE.md] [recipe=cpu|paper] [frames=N] ...``
(Hydra overrides of ``conf/reproduce.yaml``). Every step is a ``roboseg-*`` command (or a
benchmark) run in a subprocess, or a small evaluation in this process; each finished stage leaves
``out/.<stage>.done`` (the :class:`roboseg.stages.Stages` markers) so a rerun skips it. Each
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

import json
import logging
import os
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import hydra
import yaml
from omegaconf import DictConfig, OmegaConf

from roboseg.config import CONF_DIR
from roboseg.errors import ModelFileError
from roboseg.pipeline import best_checkpoint, hash_split
from roboseg.segmentor import check_scales
from roboseg.stages import Stages, Step, preimport, script

log = logging.getLogger("roboseg.reproduce")

PROJECT_ROOT = Path(CONF_DIR).resolve().parent
LAB_SEED_OFFSET = 10_000
#: what may segment the operating-room recordings' undraped phase (``undraped.segmentor``)
UNDRAPED_SEGMENTORS = ("model", "motion")


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
    walkers: list[Recording] = field(default_factory=list)  # see :func:`plan_walkers`

    def recording(self, rec: Recording) -> Path:
        if rec.role == "lab":
            return self.out / "recordings" / "lab" / f"{rec.stem}.mcap"
        # one folder per recording: roboseg-annotate annotates a folder with one calibration
        return self.out / "recordings" / "or" / rec.stem / f"{rec.stem}.mcap"

    @property
    def bootstrap(self) -> Path:
        return self.out / "bootstrap"

    @property
    def lab_dataset(self) -> Path:
        """The lab recordings annotated from their own ``/tf_static`` (the bootstrap's data)."""
        return self.bootstrap / "annotated"

    @property
    def bootstrap_ckpt(self) -> Path:
        return self.bootstrap / "model.ckpt"

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


def study_seed_offset(index: int) -> int:
    """Seed offset of a split's ``index``-th operating-room recording: stride 100 (the splits
    lie 1000 apart), then the half-way points (50, 150, ...) for the 11th to 20th."""
    return 100 * (index % 10) + 50 * (index // 10)


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
            f"or_{split}_{i:02d}", "or", split, seed + study_seed_offset(i) + hash_split(split),
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


def plan_walkers(cfg: DictConfig, study: Sequence[Recording]) -> list[Recording]:
    """The recordings of ``walkers.recordings`` again, with people walking through the undraped
    view: same seed (room, camera placement, robot motion), ``<stem>_walkers``."""
    spec = cfg.get("walkers") or {}
    by_stem = {r.stem: r for r in study}
    out = []
    for stem in spec.get("recordings") or []:
        if str(stem) not in by_stem:
            raise SystemExit(f"walkers.recordings: {stem} is not an operating-room recording "
                             f"(one of {', '.join(by_stem)})")
        rec = by_stem[str(stem)]
        out.append(Recording(f"{rec.stem}_walkers", rec.role, rec.split, rec.seed, rec.robots))
    if out and int(spec.get("people", 0)) < 1:
        raise SystemExit(f"walkers.people must be >= 1, got {spec.get('people')}")
    return out


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


def merge_dataset(layout: Layout, subset: str, lab: Path | None = None) -> None:
    """Gather the per-recording annotations of ``subset`` into one dataset folder: the files
    (hard links, else copies) and one ``manifest.json`` listing them all. ``lab``: an annotated
    lab dataset whose training recordings join the training split (its validation ones do not:
    the models are validated on the operating room's)."""
    from roboseg.annotate.batch import MANIFEST_NAME, write_json_atomic

    root = layout.dataset(subset)
    root.mkdir(parents=True, exist_ok=True)
    merged: dict[str, Any] | None = None
    parts = [(layout.part(subset, rec), None) for rec in layout.study]
    if lab is not None:
        parts.append((lab, "train"))
    for part, only in parts:
        manifest = json.loads((part / MANIFEST_NAME).read_text())
        if only is not None:
            manifest["recordings"] = [
                r for r in manifest["recordings"] if r["split"] == only]
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


def measure_walkers(layout: Layout, cfg: DictConfig) -> None:
    """``metrics/walkers.json``: the undraped estimates of each recording with people walking
    through the view beside those of the same recording without them (errors vs the truth)."""
    from roboseg.reproduce_report import registration_error
    from roboseg.robot import load_robot

    robot = load_robot(None)
    plain = {r.stem: r for r in layout.study}
    rows = []
    for rec in layout.walkers:
        alone = plain[rec.stem.removesuffix("_walkers")]
        for r, people in ((alone, 0), (rec, int(cfg.walkers.people))):
            for name in robots_of(r):
                pose = layout.undraped_pose(r, name)
                row = {"recording": r.stem, "people_walking": people, "robot": name}
                row.update(registration_error(pose, layout.recording(r), robot, "undraped")
                           if pose.is_file() else {"error": "no pose written"})
                rows.append(row)
    _write_json(layout.out / "metrics" / "walkers.json", {"rows": rows})


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


def draped_scales(cfg: DictConfig) -> list[float]:
    """``register.draped_scales`` of ``cfg``: the factors of the models' input size at which the
    draped test recording is segmented (its registrations' ``model_scales``, and a second
    evaluation); ``[1.0]`` when unset."""
    try:
        return list(check_scales(cfg.register.get("draped_scales") or [1.0],
                                 "register.draped_scales"))
    except ModelFileError as exc:
        raise SystemExit(str(exc)) from None


def draped_settings(cfg: DictConfig) -> list[str]:
    """roboseg-register overrides added for the draped test registrations:
    ``register.draped_overrides`` and ``model_scales`` from ``register.draped_scales``."""
    scales = draped_scales(cfg)
    return [*cfg.register.get("draped_overrides", []),
            *([f"model_scales={hydra_list(scales)}"] if scales != [1.0] else [])]


def hydra_list(values: Sequence[float]) -> str:
    """A Hydra list override's value: ``[1.25,1.5,2.0]``."""
    return "[" + ",".join(repr(float(v)) for v in values) + "]"


def undraped_segmentor(cfg: DictConfig) -> str:
    """``undraped.segmentor`` of ``cfg``: ``model`` (the lab bootstrap) or ``motion``."""
    kind = str(cfg.undraped.segmentor)
    if kind not in UNDRAPED_SEGMENTORS:
        raise SystemExit(
            f"undraped.segmentor={kind}: not one of {', '.join(UNDRAPED_SEGMENTORS)} (a prompt "
            "needs a person's clicks per recording, which a simulated study does not have)"
        )
    return kind


def model_init(cfg: DictConfig, warn: bool = True) -> str:
    """``model_init`` of ``cfg.recipe``: ``bootstrap`` (the recipe's models start from the lab
    bootstrap's weights) or ``scratch``; ``scratch`` when ``undraped.segmentor`` skips the lab
    bootstrap (logged as a warning when ``warn``: once, where the plan is made)."""
    init = str((cfg.get("model_init") or {}).get(str(cfg.recipe), "scratch"))
    if init not in ("bootstrap", "scratch"):
        raise SystemExit(f"model_init.{cfg.recipe}={init}: not one of bootstrap, scratch")
    if init == "bootstrap" and undraped_segmentor(cfg) != "model":
        if warn:
            log.warning("model_init.%s=bootstrap: no lab bootstrap with "
                        "undraped.segmentor=%s; the models start from scratch", cfg.recipe,
                        cfg.undraped.segmentor)
        return "scratch"
    return init


def lab_in_training(cfg: DictConfig) -> bool:
    """Whether the recipe's models also train on the lab bootstrap's annotated training
    recordings (``lab.in_training``; only where a lab stage runs: ``undraped.segmentor=model``)."""
    return bool(cfg.lab.get("in_training", False)) and undraped_segmentor(cfg) == "model"


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


def operating_room_size(cfg: DictConfig) -> tuple[int, int]:
    """Width and height (px) of the operating-room recordings: ``operating_room.width`` /
    ``height``, or the size of every recording (``width`` / ``height``) where those are null."""
    room = cfg.operating_room
    width = room.get("width") if room.get("width") is not None else cfg.width
    height = room.get("height") if room.get("height") is not None else cfg.height
    if int(width) < 16 or int(height) < 16:
        raise SystemExit(f"operating_room.width / height must be >= 16 px, got {width} x {height}")
    return int(width), int(height)


def build_plan(cfg: DictConfig, layout: Layout) -> list[Step]:
    """Every stage of the run, in order (all paths are known before anything runs)."""
    steps: list[Step] = []
    frames = int(cfg.frames)
    lab_size = (int(cfg.width), int(cfg.height))
    or_size = operating_room_size(cfg)

    def simulate(rec: Recording, extra: Sequence[str], size: tuple[int, int],
                 n_frames: int = frames) -> Step:
        path = layout.recording(rec)
        return Step(f"simulate_{rec.stem}", [
            script("roboseg-simulate"), f"out={path.parent}", f"name={rec.stem}",
            f"frames={n_frames}", f"seed={rec.seed}", f"robots={rec.robots}",
            f"camera.width={size[0]}", f"camera.height={size[1]}",
            *cfg.operating_room.simulate_overrides, *extra,
        ])

    # 1. bootstrap: the calibrated lab rig (only when a model segments the undraped phase)
    segmentor = undraped_segmentor(cfg)
    if segmentor == "model":
        lab_frames = frames if cfg.lab.get("frames") is None else int(cfg.lab.frames)
        for rec in layout.lab:
            steps.append(simulate(
                rec, [f"drape.undraped_fraction={float(cfg.lab.undraped_fraction)}"], lab_size,
                lab_frames,
            ))
        lab_root = layout.lab_dataset
        steps.append(Step("annotate_lab", [
            script("roboseg-annotate"), f"in={layout.recording(layout.lab[0]).parent}",
            f"out={lab_root}", "phase=undraped", *cfg.annotate.overrides,
            *cfg.lab.get("annotate_overrides", []),
        ]))
        steps += _train_steps(
            layout, "bootstrap", str(cfg.lab.experiment), lab_root,
            [f"trainer.max_steps={int(cfg.lab.steps)}", "data.val_phase=undraped",
             *cfg.lab.overrides],
            cfg, layout.bootstrap_ckpt, layout.bootstrap_onnx,
        )

    # 2. operating room: register undraped (no truth), self-annotate with the estimate
    undraped_model = layout.bootstrap_onnx if segmentor == "model" else None
    undraped_extra = [*([] if segmentor == "model" else [f"segmentor={segmentor}"]),
                      *cfg.undraped.overrides]
    site = cfg.operating_room.get("site")
    at_site = [] if site is None else [f"site={int(site)}"]
    for rec in layout.study:
        steps.append(simulate(rec, at_site, or_size))
    for rec in layout.walkers:  # walkers.people checked by plan_walkers
        steps.append(simulate(rec, [*at_site, f"walkers={int(cfg.walkers.people)}"], or_size))
    for rec in [*layout.study, *layout.walkers]:
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
    lab_training = layout.lab_dataset if lab_in_training(cfg) else None
    for subset in subsets:
        for rec in layout.study:
            steps.append(Step(f"annotate_{subset}_{rec.stem}", [
                script("roboseg-annotate"), f"in={layout.recording(rec).parent}",
                f"out={layout.part(subset, rec)}", f"calibration={layout.calibration(rec)}",
                f"phase={cfg.annotate.phase}", f"subset={subset}", *cfg.annotate.overrides,
            ]))
        steps.append(Step(f"dataset_{subset}",
                          fn=lambda s=subset: merge_dataset(layout, s, lab_training)))
    steps.append(Step("annotation_quality",
                      fn=lambda: measure_annotation(layout, subsets[0], cfg)))
    if layout.walkers:
        steps.append(Step("walkers_quality", fn=lambda: measure_walkers(layout, cfg)))

    # 3. the recipe's models: train, export, evaluate on the test recording
    init = model_init(cfg)
    start = [f"model.weights_path={layout.bootstrap_ckpt}"] if init == "bootstrap" else []
    for m in layout.models:
        steps += _train_steps(
            layout, m.name, m.experiment, layout.dataset(m.subset),
            [*start, *m.overrides, *cfg.train_overrides], cfg, layout.ckpt(m.name),
            layout.onnx(m.name),
        )
    models = ",".join(str(layout.onnx(m.name)) for m in layout.models)
    scales = draped_scales(cfg)
    evaluations = [("evaluate", "eval", [])]
    if scales != [1.0]:
        # the same models at the scales the draped registrations segment with
        evaluations.append(("evaluate_scales", "eval_scales", [f"scales={hydra_list(scales)}"]))
    for name, folder, extra in evaluations:
        steps.append(Step(name, [
            script("roboseg-eval"), f"models=[{models}]",
            f"data.root={layout.dataset(subsets[0])}", f"out={layout.out / folder}",
            f"labels={cfg.evaluate.labels}", "progress=false", f"threads={int(cfg.threads)}",
            *extra, *cfg.evaluate.overrides,
        ]))

    # 4. the draped test recording: SDR (3 channels) and SDR with prior (4 channels)
    chosen = cfg.localise[str(cfg.recipe)]
    for method in ("sdr", "sdr_prior"):
        for robot in robots_of(layout.test):
            steps.append(Step(
                f"register_draped_{method}_{robot}",
                _register_argv(cfg, layout.test, layout.recording(layout.test),
                               layout.onnx(str(chosen[method])), method, "draped", robot,
                               layout.draped_pose(method, robot).parent,
                               draped_settings(cfg)),
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
    site = cfg.operating_room.get("site")
    fields = {"models": layout.out / "models", "sdr_model": layout.onnx(str(chosen["sdr"])),
              "sdr_prior_model": layout.onnx(str(chosen["sdr_prior"])),
              "site": "none" if site is None else int(site),
              "or_width": or_size[0], "or_height": or_size[1],
              "bench_out": layout.out / "bench"}
    for bench in cfg.benches:
        argv = [sys.executable if a == "python" else str(a).format(**fields) for a in bench.cmd]
        steps.append(Step(f"bench_{bench.name}", argv, tolerant=True, cwd=PROJECT_ROOT))
    return steps


def plan_groups(plan: Sequence[Step]) -> list[list[str]]:
    """The plan's stage names in order, consecutive side-by-side stages in one group."""
    groups: list[list[str]] = []
    for i, step in enumerate(plan):
        if step.parallel and i > 0 and plan[i - 1].parallel:
            groups[-1].append(step.name)
        else:
            groups.append([step.name])
    return groups


def run_reproduce(cfg: DictConfig) -> Path:
    """Run (or resume) the whole study of ``cfg``; write the results page; return its path."""
    from roboseg.reproduce_report import write_page

    t0 = time.perf_counter()
    out = Path(str(cfg.out)).resolve()
    lab, study = plan_study(cfg)
    layout = Layout(out, Path(str(cfg.results)).resolve(), lab, study, model_specs(cfg),
                    plan_walkers(cfg, study))
    plan = build_plan(cfg, layout)
    stages = Stages(out, len(plan), str(cfg.runner))
    groups = plan_groups(plan)
    redone = stages.redo_after_pending(groups)
    if redone:
        print(f"reproduce: {len(redone)} finished stages follow an unfinished one and are "
              f"redone: {', '.join(redone)}", flush=True)
    pending = [s.name for s in plan if not stages.marker(s.name).exists()]
    if stages.runner == "fork" and pending:
        preimport()
    print(f"reproduce: {len(plan)} stages into {out} (recipe={cfg.recipe}); finished stages "
          "are skipped", flush=True)
    ran, jobs = 0, max(1, int(cfg.jobs))
    by_name = {s.name: s for s in plan}
    for names in groups:
        step = by_name[names[0]]
        if step.parallel:  # consecutive side-by-side stages
            ran += stages.run_side_by_side([by_name[n] for n in names], jobs)
            continue
        argv = step.argv if step.argv is not None else [step.name]
        ran += stages.run(step.name, argv, tolerant=step.tolerant, cwd=step.cwd, fn=step.fn)
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
