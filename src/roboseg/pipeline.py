"""``make train``: the main job on its embedded default, as the commands a user would type.

simulate → annotate → train → export → evaluate, each stage a ``roboseg-*`` command
(:class:`roboseg.stages.Stages`: forked from this process, which imports the libraries once; its
output also in ``out/logs/<stage>.log``), each finished stage marked with a ``.done`` file so an
interrupted run resumes where it stopped. Run:
``python -m roboseg.pipeline [out=DIR] [key=value ...]`` (Hydra overrides of
``conf/pipeline.yaml``).
"""

from __future__ import annotations

import csv
import logging
import shutil
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from roboseg.config import CONF_DIR
from roboseg.stages import Stages, preimport, script

log = logging.getLogger("roboseg.pipeline")


def session_names(split: str, count: int) -> list[str]:
    """The recordings of one split: ``<split>_00``, ``<split>_01``, ..."""
    return [f"{split}_{i:02d}" for i in range(count)]


def prepare_data(cfg: DictConfig, stages: Stages, out: Path) -> Path:
    """Simulate the study of ``cfg.simulate`` into ``out/recordings`` and self-annotate it into
    ``out/annotated`` (stages that finished are skipped); return the annotated folder."""
    raw, annotated = out / "recordings", out / "annotated"
    sim = cfg.simulate
    site = sim.get("site")
    for split, count in sim.recordings.items():
        frames = sim.frames[split] if OmegaConf.is_dict(sim.frames) else sim.frames
        for i, name in enumerate(session_names(split, int(count))):
            robots = 2 if split == "test" else 1
            stages.run(
                f"simulate_{name}",
                [script("roboseg-simulate"), f"out={raw}", f"name={name}", f"frames={int(frames)}",
                 f"seed={session_seed(int(sim.seed), split, i)}", f"robots={robots}",
                 f"camera.width={sim.width}", f"camera.height={sim.height}",
                 *([] if site is None else [f"site={int(site)}"]),
                 *sim.get("overrides", [])],
            )
    stages.run(
        "annotate",
        [script("roboseg-annotate"), f"in={raw}", f"out={annotated}", *cfg.annotate.overrides],
    )
    return annotated


def run_pipeline(cfg: DictConfig) -> Path:
    """Run the stages of ``cfg`` (see ``conf/pipeline.yaml``); return the model's ONNX path."""
    out = Path(cfg.out).resolve()
    total = sum(int(n) for n in cfg.simulate.recordings.values()) + 3 + len(cfg.evaluate.runs)
    stages = Stages(out, total, str(cfg.get("runner", "fork")))
    simulations = [f"simulate_{name}" for split, count in cfg.simulate.recordings.items()
                   for name in session_names(split, int(count))]
    evaluations = [f"evaluate_{name}" for name in cfg.evaluate.runs]
    redone = stages.redo_after_pending(
        [simulations, ["annotate"], ["train"], ["export"], evaluations]
    )
    if redone:
        log.info("finished stages after an unfinished one are redone: %s", ", ".join(redone))
    if stages.runner == "fork" and not stages.marker(f"evaluate_{cfg.evaluate.headline}").exists():
        preimport()
    train_dir = out / "train"
    annotated = prepare_data(cfg, stages, out)
    stages.run(
        "train",
        [script("roboseg-train"), f"experiment={cfg.train.experiment}", f"data.root={annotated}",
         f"hydra.run.dir={train_dir}", f"seed={cfg.seed}", *cfg.train.overrides],
    )
    ckpt = out / "model.ckpt"
    best = best_checkpoint(train_dir / "checkpoints")
    if not ckpt.exists() or best.stat().st_mtime > ckpt.stat().st_mtime:
        shutil.copy2(best, ckpt)
    onnx = out / "model.onnx"
    stages.run("export", [script("roboseg-export"), f"ckpt={ckpt}", f"out={onnx}",
                          *cfg.get("export", {}).get("overrides", [])])
    results = {}
    for name, spec in cfg.evaluate.runs.items():
        folder = out / str(name)
        stages.run(
            f"evaluate_{name}",
            [script("roboseg-eval"), f"models=[{onnx}]", f"data.root={annotated}",
             f"out={folder}", f"split={spec.split}", f"phase={spec.phase}",
             *cfg.evaluate.overrides],
        )
        results[str(name)] = (spec, table_iou(folder / "iou_table.csv"))
    print(f"model checkpoint: {ckpt}\nONNX model:       {onnx}", flush=True)
    for name, (spec, (mean, std, n)) in results.items():
        print(f"{spec.split} IoU, {spec.phase} frames: {mean:.3f} ± {std:.3f} over {n} frames "
              f"({out / name / 'iou_table.md'})", flush=True)
    headline = results.get(str(cfg.evaluate.headline))
    if headline is not None:
        print(f"val/iou={headline[1][0]:.3f}", flush=True)
    return onnx


def table_iou(path: Path) -> tuple[float, float, int]:
    """Per-frame mean IoU, its standard deviation and the frame count of the first row of an
    ``iou_table.csv`` written by ``roboseg-eval``."""
    with path.open(newline="") as f:
        row = next(csv.DictReader(f), None)
    if row is None:
        raise SystemExit(f"{path}: no rows")
    return float(row["iou_mean"]), float(row["iou_std"]), int(row["frames"])


def session_seed(seed: int, split: str, index: int) -> int:
    """Simulator seed of recording ``index`` of ``split``: distinct for up to 1000 recordings per
    split, so no validation or test session repeats a training one."""
    if not 0 <= index < 1000:
        raise SystemExit(f"simulate.recordings.{split}: at most 1000 recordings per split")
    return seed + hash_split(split) + index


def hash_split(split: str) -> int:
    """A small stable offset per split so train/val/test recordings never share a seed."""
    return {"train": 0, "val": 1000, "test": 2000}.get(split, 3000)


def best_checkpoint(folder: Path) -> Path:
    """``best.ckpt`` (best validation IoU, written by ``roboseg-train``), else ``last.ckpt``."""
    for name in ("best.ckpt", "last.ckpt"):
        if (folder / name).exists():
            return folder / name
    raise SystemExit(f"no checkpoint in {folder}: did training finish?")


@hydra.main(config_path=CONF_DIR, config_name="pipeline", version_base="1.3")
def main(cfg: DictConfig) -> None:
    log.debug("pipeline config:\n%s", OmegaConf.to_yaml(cfg))
    run_pipeline(cfg)


if __name__ == "__main__":
    main()
