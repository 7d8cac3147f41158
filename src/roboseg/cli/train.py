"""``roboseg-train``: train a U-Net robot segmentor on annotated recordings (``conf/train.yaml``).

``roboseg-train experiment=smoke data.root=DIR hydra.run.dir=RUN [ckpt_path=RUN/checkpoints/
last.ckpt]`` seeds everything, fits, validates the best checkpoint and writes
``RUN/checkpoints/best.ckpt`` and ``last.ckpt`` (the final state). The last two lines are
``steps=N/M`` (optimiser steps done / ``trainer.max_steps``: fewer when ``trainer.max_time`` came
first or the schedule was fitted to it, which is also logged as a warning) and
``val/iou=0.xxx``: the per-frame mean IoU of the best checkpoint over the validation frames
(draped ones by default, see ``data.val_phase``; all of them, whatever
``trainer.limit_val_batches``), on rank zero. ``-m model=unet_mit_b0,unet_resnet18`` runs a sweep.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import hydra
import lightning.pytorch as pl
import numpy as np
import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue

from roboseg.cli._main import user_errors_exit
from roboseg.config import CONF_DIR
from roboseg.errors import ModelFileError, RobosegError
from roboseg.time_budget import FitScheduleToTime
from roboseg.training import SegmentationModule, per_frame_iou, training_precision

log = logging.getLogger("roboseg.train")


def _build(cfg: DictConfig, key: str) -> Any:
    """Instantiate ``cfg[key]``; user errors inside the target surface as themselves."""
    try:
        return instantiate(cfg[key])
    except MissingMandatoryValue as exc:
        raise RobosegError(f"{key}: a required value is missing ({exc.full_key} = ???)") from None
    except InstantiationException as exc:
        cause = exc.__cause__
        while cause is not None and not isinstance(cause, RobosegError):
            cause = cause.__cause__
        if cause is not None:
            raise cause from None
        raise RobosegError(f"{key}: {exc}") from None


@torch.no_grad()
def mean_frame_iou(module: SegmentationModule, loader: Any) -> float:
    """Mean over frames of the IoU of ``sigmoid(logits) > threshold`` with the mask."""
    module.eval()
    ious: list[float] = []
    for batch in loader:
        if not batch:
            continue
        batch = module.on_after_batch_transfer(batch, 0)
        pred = torch.sigmoid(module(batch["input"])) > module.hparams.threshold
        target = batch["target"] > 0.5
        ious += per_frame_iou(pred, target).tolist()
    return float(np.mean(ious)) if ious else float("nan")


def _checkpoint_callback(trainer: pl.Trainer) -> pl.callbacks.ModelCheckpoint | None:
    for cb in trainer.callbacks:
        if isinstance(cb, pl.callbacks.ModelCheckpoint):
            return cb
    return None


def _configured_steps(trainer: pl.Trainer) -> int:
    """``trainer.max_steps`` as configured, before :class:`FitScheduleToTime` fitted it."""
    for cb in trainer.callbacks:
        if isinstance(cb, FitScheduleToTime) and cb.configured is not None:
            return cb.configured.steps
    return int(trainer.max_steps)


def _fall_back_from_slow_bf16(cfg: DictConfig) -> None:
    """``trainer.precision`` bf16 on a CPU without native bfloat16 becomes ``32-true`` (logged),
    unless ``bf16_fallback`` is false: there bf16 autocast trains 15-20x slower than float32."""
    asked = OmegaConf.select(cfg, "trainer.precision", default=None)
    if asked is None or not bool(cfg.get("bf16_fallback", True)):
        return
    cfg.trainer.precision = training_precision(
        asked, str(OmegaConf.select(cfg, "trainer.accelerator", default="cpu")),
        setting="trainer.precision", hint=f" (bf16_fallback=false keeps {asked})")


@user_errors_exit
def run(cfg: DictConfig) -> float:
    """Fit, validate the best checkpoint, return (and print) its validation IoU."""
    pl.seed_everything(int(cfg.seed), workers=True)
    ckpt_path = OmegaConf.select(cfg, "ckpt_path", default=None)
    if ckpt_path is not None and not Path(str(ckpt_path)).is_file():
        raise ModelFileError(f"ckpt_path {ckpt_path}: no such checkpoint")
    _fall_back_from_slow_bf16(cfg)
    data = _build(cfg, "data")
    module = _build(cfg, "module")
    trainer: pl.Trainer = _build(cfg, "trainer")
    trainer.fit(module, datamodule=data, ckpt_path=None if ckpt_path is None else str(ckpt_path))
    if trainer.interrupted:
        raise RobosegError("training was interrupted; checkpoints so far are kept")
    steps, wanted = int(trainer.global_step), int(trainer.max_steps)  # wanted: as fitted
    configured = _configured_steps(trainer)
    if wanted > 0 and steps < wanted:
        # a slower machine meets trainer.max_time first: a different (less trained) model
        log.warning(
            "stopped at step %d of trainer.max_steps=%d (trainer.max_time=%s or max_epochs came "
            "first; the learning-rate schedule did not end): raise trainer.max_time for the "
            "full run", steps, wanted, OmegaConf.select(cfg, "trainer.max_time", default=None))
    elif steps < configured:
        log.warning("the schedule was fitted to trainer.max_time: %d of trainer.max_steps=%d "
                    "steps (raise trainer.max_time for the full run)", steps, configured)
    wanted = configured
    callback = _checkpoint_callback(trainer)
    best = ""
    if callback is not None and callback.dirpath:
        # Lightning keeps last.ckpt of the last *saved* step (the last improvement of the
        # monitor); rewrite it with the final state so that ckpt_path=last.ckpt resumes there
        trainer.save_checkpoint(Path(callback.dirpath) / f"{callback.CHECKPOINT_NAME_LAST}.ckpt")
        best = callback.best_model_path or str(Path(callback.dirpath) / "last.ckpt")
    results = trainer.validate(module, datamodule=data, ckpt_path=best or None, verbose=False)
    pooled = float(results[0].get("val/iou", float("nan"))) if results else float("nan")
    if not trainer.is_global_zero:
        return pooled
    if best:
        module = SegmentationModule.load_from_checkpoint(best, map_location="cpu")
    iou = mean_frame_iou(module.cpu(), data.val_dataloader())
    log.info("best checkpoint %s; val IoU over pooled pixels %.3f", best or "(none)", pooled)
    print(f"steps={steps}" + (f"/{wanted}" if wanted > 0 else ""))
    print(f"val/iou={iou:.3f}")
    return iou


@hydra.main(config_path=CONF_DIR, config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> float:
    return run(cfg)


if __name__ == "__main__":
    main()
