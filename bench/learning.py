"""Learning curves: validation IoU against training seconds for a matrix of training recipes.

``python -m bench.learning [--study site random] [--recipes NAME ...] [--budget 240] [--steps N]
[--val-every 40] [--val-frames 48] [--out outputs/bench/learning]``

Every recipe is a set of Hydra overrides of ``conf/train.yaml`` on top of ``experiment=default``
(the ``make train`` recipe), trained by the project's LightningModule on the same annotated data
with the same seed, one after the other on this machine, for ``--budget`` seconds of training
each. Every ``--val-every`` steps the per-frame mean IoU on the draped validation frames (the
first ``--val-frames`` of them, a fixed set) is recorded with the training seconds spent so far
(validation time excluded). Printed: a table of IoU at fixed times per recipe and study; drawn:
``learning_curves.png`` (a panel per study, a curve per recipe); written: ``curves.json``.

Studies (``make train``'s, ``conf/pipeline.yaml``, cached under ``--out``): ``site`` is one
operating room in several sessions (camera placements, people, tools, light), validated on
sessions not trained on; ``random`` is the same with every recording its own random room (domain
randomisation), validated on rooms not trained on.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import format_table  # noqa: E402
from roboseg.config import CONF_DIR  # noqa: E402
from roboseg.pipeline import prepare_data  # noqa: E402
from roboseg.stages import Stages  # noqa: E402
from roboseg.training import training_precision  # noqa: E402

log = logging.getLogger("bench.learning")

#: Seconds at which the table reports each curve.
REPORT_AT = (60, 120, 180, 240, 300, 420, 600)

_WHOLE = ["data.image_size=[144,256]", "augment.crop=null"]
_FP32 = ["trainer.precision=32-true", "module.channels_last=false"]
_OLD = ["model=unet_mit_b0", "model.decoder_channels=[128,64,32,16,16]",
        "data.image_size=[256,256]", "augment=paper", "augment.crop=null",
        "augment.affine.scale=[1.0,1.8]", *_FP32]
_NOAUG = ["augment.flip.p=0", "augment.affine.p=0", "augment.cmm.p=0",
          "augment.photometric.ops=[]"]
#: Recipe name → Hydra overrides on top of ``experiment=default`` (``make train``'s recipe:
#: MIT-B0, decoder [64, 32, 16, 16, 8], 144×256 windows of native 270×480 frames with whole
#: frames predicted, NHWC + bf16, lr 1e-3 cosine, the paper's augmentation ramped in).
RECIPES: dict[str, list[str]] = {
    "default": [],
    # augmentation schedule (the windows stay)
    "default_noaug": _NOAUG,
    "default_aug_from_step_0": ["augment.ramp_steps=0"],
    # ramped over 1600 steps: with --steps 800, half the paper's strength by the end
    "default_aug_ramp_1600": ["augment.ramp_steps=1600"],
    # encoder (same decoder, input and schedule)
    "regnety_004": ["model=unet_regnety_004"],
    "resnet18": ["model=unet_resnet18"],
    # input: whole frames squashed to 144×256 instead of windows of native frames
    "whole_144x256": _WHOLE,
    "regnety_004_whole_144x256": ["model=unet_regnety_004", *_WHOLE],
    # input: frames upsampled 2× (540×960) before the 144×256 windows, so the encoder's
    # stride-4 features fall every 2 native pixels (links are 5-12 px wide at 270×480)
    "default_input_2x": ["data.image_size=[540,960]"],
    # windows: 80 % centred on a robot pixel (default 50 %)
    "default_robot_windows_0.8": ["augment.crop.p_robot=0.8"],
    # learning rate
    "default_lr3e-3": ["module.lr=3.0e-3"],
    # arithmetic: float32 in the usual NCHW layout
    "default_fp32": _FP32,
    # make train's recipe before this bench: MIT-B0, half-width decoder, 256² squashed frames,
    # the paper's augmentation from step 0, float32
    "old_default": _OLD,
}


# --- data ------------------------------------------------------------------------------------


def make_study(root: Path, study: str, seed: int = 0) -> Path:
    """Simulate and annotate ``make train``'s study (``conf/pipeline.yaml``) into ``root``;
    ``random`` makes every recording its own random room. Stages that finished are skipped;
    returns the annotated folder."""
    overrides = [f"simulate.seed={seed}"] + (["simulate.site=null"] if study == "random" else [])
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("pipeline", overrides=overrides)
    return prepare_data(cfg, Stages(root), root)


# --- one curve -------------------------------------------------------------------------------


class Curve(pl.Callback):
    """Records ``(training seconds, step, val/iou)`` at every validation; validation time and
    the first step (workers starting, robot loading) are not counted as training seconds."""

    def __init__(self, budget: float) -> None:
        self.budget, self.points = budget, []
        self.seconds, self._t = 0.0, None

    def on_train_batch_start(self, trainer: pl.Trainer, *args: Any) -> None:
        self._t = time.perf_counter()

    def on_train_batch_end(self, trainer: pl.Trainer, *args: Any) -> None:
        if self._t is not None and trainer.global_step > 1:
            self.seconds += time.perf_counter() - self._t
        if self.seconds >= self.budget:
            trainer.should_stop = True

    def on_validation_end(self, trainer: pl.Trainer, module: pl.LightningModule) -> None:
        if trainer.sanity_checking:
            return
        iou = float(trainer.callback_metrics.get("val/iou", float("nan")))
        self.points.append((round(self.seconds, 1), int(trainer.global_step), round(iou, 4)))
        log.info("  %6.0f s  step %4d  val IoU %.3f", self.seconds, trainer.global_step, iou)


def run_recipe(data: Path, overrides: list[str], budget: float, val_every: int,
               val_frames: int, seed: int, steps: int | None = None) -> dict[str, Any]:
    """Train one recipe for ``budget`` seconds (or ``steps``, whichever ends first); its curve
    and final step time. ``steps`` (default: the experiment's ``trainer.max_steps``) is also
    the length of the learning-rate schedule and of the augmentation ramp."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("train", overrides=[
            "experiment=default", f"data.root={data}", f"seed={seed}", "paths.output_dir=/tmp",
            *overrides, *([] if steps is None else [f"trainer.max_steps={steps}"])])
    pl.seed_everything(seed, workers=True)
    batch = int(cfg.data.batch_size)
    curve = Curve(budget)
    # the recipe's precision (bf16 only where the CPU has it natively, as roboseg-train does)
    precision = training_precision(str(cfg.trainer.precision), "cpu")
    trainer = pl.Trainer(
        accelerator="cpu", devices=1, precision=precision,  # type: ignore[arg-type]
        max_steps=int(cfg.trainer.max_steps), max_time=None,
        max_epochs=-1,
        val_check_interval=val_every, check_val_every_n_epoch=None,
        limit_val_batches=max(1, val_frames // batch), num_sanity_val_steps=0,
        callbacks=[curve], logger=False, enable_checkpointing=False,
        enable_progress_bar=False, enable_model_summary=False)
    module = instantiate(cfg.module)
    dm = instantiate(cfg.data)
    t0 = time.perf_counter()
    trainer.fit(module, datamodule=dm)
    wall = time.perf_counter() - t0
    trainer.validate(module, datamodule=dm, verbose=False)
    iou = float(trainer.callback_metrics.get("val/iou", float("nan")))
    curve.points.append((round(curve.seconds, 1), int(trainer.global_step), round(iou, 4)))
    return {"overrides": overrides, "precision": precision, "points": curve.points,
            "steps": int(trainer.global_step),
            "s_per_step": curve.seconds / max(1, trainer.global_step - 1), "wall": wall}


def iou_at(points: list[list[float]], seconds: float) -> float | None:
    """Best validation IoU reached within ``seconds`` of training (None: not run that long)."""
    within = [p[2] for p in points if p[0] <= seconds + 1e-6]
    if not points or points[-1][0] < seconds * 0.97:
        return None
    return max(within) if within else None


def plot(results: dict[str, dict[str, dict[str, Any]]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    studies = list(results)
    fig, axes = plt.subplots(1, len(studies), figsize=(6.5 * len(studies), 4.5), squeeze=False)
    for ax, study in zip(axes[0], studies, strict=True):
        for name, res in results[study].items():
            pts = res["points"]
            ax.plot([p[0] for p in pts], [p[2] for p in pts], marker="o", ms=3, label=name)
        ax.set_title(f"study: {study} (draped validation frames)")
        ax.set_xlabel("training seconds (2 CPU cores)")
        ax.set_ylabel("val IoU (per-frame mean)")
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--study", nargs="+", default=["site", "random"], choices=["site", "random"])
    ap.add_argument("--recipes", nargs="+", default=list(RECIPES), choices=list(RECIPES))
    ap.add_argument("--budget", type=float, default=240.0, help="training seconds per recipe")
    ap.add_argument("--val-every", type=int, default=100, help="steps between validations")
    ap.add_argument("--val-frames", type=int, default=10_000,
                    help="at most this many draped val frames scored (default: all)")
    ap.add_argument("--steps", type=int, default=None,
                    help="steps per recipe, also the length of its lr schedule and augmentation "
                         "ramp (default: the experiment's trainer.max_steps)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("outputs/bench/learning"))
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for noisy in ("lightning", "lightning.pytorch", "roboseg", "datamodules"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    args.out.mkdir(parents=True, exist_ok=True)
    store = args.out / "curves.json"
    results: dict[str, dict[str, Any]] = json.loads(store.read_text()) if store.exists() else {}
    for study in args.study:
        data = make_study(args.out / study, study, args.seed)
        for name in args.recipes:
            log.info("[%s] %s: %s", study, name, " ".join(RECIPES[name]))
            res = run_recipe(data, RECIPES[name], args.budget, args.val_every, args.val_frames,
                             args.seed, args.steps)
            res["budget"], res["schedule_steps"] = args.budget, args.steps
            results.setdefault(study, {})[name] = res
            store.write_text(json.dumps(results, indent=1))
    rows = []
    for study, recipes in results.items():
        for name, res in recipes.items():
            best = max(p[2] for p in res["points"])
            # curves stored before the precision was recorded ran in float32
            rows.append([study, name, res.get("precision", "32-true"),
                         f"{res['s_per_step']:.2f}", res["steps"],
                         *("-" if (v := iou_at(res["points"], t)) is None else f"{v:.2f}"
                           for t in REPORT_AT), f"{best:.2f}"])
    print(format_table(["study", "recipe", "precision", "s/step", "steps",
                        *(f"{t} s" for t in REPORT_AT), "best"], rows))
    plot(results, args.out / "learning_curves.png")
    print(f"curves: {store}\nplot:   {args.out / 'learning_curves.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
