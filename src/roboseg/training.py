"""LightningModule of the paper's segmentation training: U-Net, focal + Dice, AdamW, IoU.

Batches are dicts (see :mod:`roboseg.augment`). After transfer to the device, training batches
pass the augmentation pipeline (never validation / test ones); every batch then becomes the model
input (normalised RGB [+ prior]) and the target mask. Logged: ``train/loss``, ``train/iou``,
``val/loss``, ``val/iou``, ``test/loss``, ``test/iou`` (IoU of the mask ``sigmoid > threshold``).

Hyperparameters are plain containers, so a checkpoint rebuilds its model with
``SegmentationModule.load_from_checkpoint(path)`` under ``weights_only=True``. They carry what the
ONNX export needs (:meth:`SegmentationModule.export_metadata`): model name, input channels,
input size ``[H, W]``, normalisation mean / std, threshold.
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import torch
from hydra.utils import instantiate
from lightning.pytorch.utilities import rank_zero_only
from omegaconf import DictConfig, ListConfig, OmegaConf
from torchmetrics import MeanMetric
from torchmetrics.classification import BinaryJaccardIndex

from roboseg.augment.pipeline import IMAGENET_MEAN, IMAGENET_STD, AugmentationPipeline, prepare
from roboseg.errors import DatasetError, ModelFileError, RobosegError
from roboseg.losses import FocalDiceLoss
from roboseg.models import ModelConfigError, build_unet, count_params

log = logging.getLogger(__name__)

Batch = dict[str, torch.Tensor]

#: Only callables under this prefix may be instantiated from an augmentation config (a
#: checkpoint's hyperparameters are untrusted input).
AUGMENT_TARGET_PREFIX = "roboseg.augment."
MODEL_TARGET = "roboseg.models.build_unet"


#: Learning-rate schedules of :func:`lr_factor`.
LR_SCHEDULES = ("constant", "cosine")


def lr_factor(
    step: int, warmup_steps: int, total_steps: int, schedule: str = "constant",
    final: float = 0.05,
) -> float:
    """Multiplier of the base learning rate at optimizer step ``step`` (0-based).

    Linear warm-up over ``warmup_steps`` (factor ``(step + 1) / warmup_steps``), then constant,
    or for ``"cosine"`` a half cosine from 1 down to ``final`` at ``total_steps`` (constant when
    ``total_steps`` is not positive, e.g. a run bounded by time only).
    """
    warm = min(1.0, (step + 1) / warmup_steps) if warmup_steps > 0 else 1.0
    if schedule == "constant" or total_steps <= 0:
        return warm
    progress = min(1.0, max(0, step - warmup_steps) / max(1, total_steps - warmup_steps))
    return warm * (final + (1 - final) * 0.5 * (1 + math.cos(math.pi * progress)))


def cpu_bf16_native() -> bool:
    """Whether this CPU runs bfloat16 arithmetic at speed, as oneDNN (PyTorch's CPU kernels)
    reports it: x86 with AVX-512, aarch64 with its bf16 extension. Without it bf16 autocast
    converts every operand and training crawls: MIT-B0 at 8 windows of 144×256 took 5.6-6.9 s a
    step against 0.35-0.37 s in float32 on an AVX2-only EPYC. ``True`` where torch cannot tell."""
    probe = getattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", None)
    try:
        return bool(probe()) if probe is not None else True
    except (RuntimeError, AttributeError):
        return True


def training_precision(
    precision: str, accelerator: str = "cpu", bf16_native: bool | None = None,
    setting: str | None = None, hint: str = "",
) -> str:
    """The Lightning ``precision`` to train with: ``precision`` itself, except a bfloat16 one
    (``bf16-mixed``, ``bf16-true``) on a CPU without native bfloat16 (``bf16_native``; ``None``:
    :func:`cpu_bf16_native`), which becomes ``32-true``. ``accelerator`` ``auto`` counts as the
    CPU when CUDA is not available. With ``setting`` (the config key, e.g.
    ``trainer.precision``), a change is logged once on rank zero, ``hint`` appended."""
    precision = str(precision)
    on_cpu = accelerator == "cpu" or (accelerator == "auto" and not torch.cuda.is_available())
    if not precision.startswith("bf16") or not on_cpu:
        return precision
    native = cpu_bf16_native() if bf16_native is None else bf16_native
    if native:
        return precision
    if setting is not None and rank_zero_only.rank == 0:
        log.warning("%s=%s: this CPU has no native bfloat16 (oneDNN reports none), where bf16 "
                    "autocast trains 15-20x slower than float32; training in 32-true%s",
                    setting, precision, hint)
    return "32-true"


def per_frame_iou(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """IoU ``[B]`` of boolean masks ``[B, ...]``; a frame where both are empty scores 1."""
    pred, target = pred.flatten(1).bool(), target.flatten(1).bool()
    inter = (pred & target).sum(1).float()
    union = (pred | target).sum(1).float()
    return torch.where(union > 0, inter / union.clamp(min=1), torch.ones_like(union))


class NonFiniteLossError(RobosegError, FloatingPointError):
    """The training loss became NaN or infinite; the run stops, saved checkpoints stay intact."""


def _plain(value: Any) -> Any:
    """OmegaConf containers → dicts / lists (resolved); anything else unchanged."""
    if isinstance(value, DictConfig | ListConfig):
        return OmegaConf.to_container(value, resolve=True)
    return copy.deepcopy(value)


def _check_targets(cfg: Any, prefix: str, where: str) -> None:
    """Raise :class:`ModelFileError` if any ``_target_`` in ``cfg`` lies outside ``prefix``."""
    if isinstance(cfg, Mapping):
        target = cfg.get("_target_")
        if target is not None and not str(target).startswith(prefix):
            raise ModelFileError(f"{where}: _target_ {target!r} is not under {prefix!r}")
        for v in cfg.values():
            _check_targets(v, prefix, where)
    elif isinstance(cfg, list | tuple):
        for v in cfg:
            _check_targets(v, prefix, where)


def build_augmentation(cfg: Mapping[str, Any] | None) -> AugmentationPipeline | None:
    """Instantiate an :class:`AugmentationPipeline` config (None → no augmentation)."""
    if not cfg:
        return None
    _check_targets(cfg, AUGMENT_TARGET_PREFIX, "augment config")
    pipeline = instantiate(cfg, _convert_="all")
    if not isinstance(pipeline, AugmentationPipeline):
        raise ModelFileError(f"augment config builds {type(pipeline).__name__}, not a pipeline")
    return pipeline


class SegmentationModule(pl.LightningModule):
    """Binary robot segmentation with a registered U-Net preset (:mod:`roboseg.models`).

    ``model``: ``{"name": preset, "in_channels": 3|4, "weights_path": local file or None}``;
    ``augment``: a Hydra config of :class:`AugmentationPipeline` (None: no augmentation);
    ``loss``: keyword arguments of :class:`FocalDiceLoss`; ``lr`` / ``weight_decay``: AdamW;
    ``image_size``: model input ``[H, W]`` pixels; ``mean`` / ``std``: RGB normalisation;
    ``threshold``: probability above which a pixel is robot; ``dataset``: subset name (medium,
    large, ...); ``seed``: augmentation seed (plus the DDP rank); ``lr_schedule`` /
    ``warmup_steps``: see :func:`lr_factor` (the paper's recipe: constant, no warm-up);
    ``channels_last``: train and validate in NHWC memory layout (oneDNN's fast path on CPU: ~1.6x
    a step for the CNN presets; the weights are saved and exported in the usual layout). Under
    ``trainer.precision=bf16-mixed`` the loss is still computed in float32.
    """

    def __init__(
        self,
        model: Mapping[str, Any] | None = None,
        augment: Mapping[str, Any] | None = None,
        loss: Mapping[str, Any] | None = None,
        lr: float = 1.5e-5,
        weight_decay: float = 1e-2,
        image_size: Sequence[int] = (512, 512),
        mean: Sequence[float] = IMAGENET_MEAN,
        std: Sequence[float] = IMAGENET_STD,
        threshold: float = 0.5,
        dataset: str = "",
        seed: int = 0,
        lr_schedule: str = "constant",
        warmup_steps: int = 0,
        channels_last: bool = False,
    ) -> None:
        super().__init__()
        model = dict(_plain(model) or {"name": "unet_mit_b0"})
        target = model.pop("_target_", MODEL_TARGET)
        if target != MODEL_TARGET:
            raise ModelFileError(f"model config: _target_ {target!r} is not {MODEL_TARGET!r}")
        model.setdefault("in_channels", 3)
        model.setdefault("weights_path", None)
        model.setdefault("decoder_channels", None)
        unknown = set(model) - {"name", "in_channels", "weights_path", "decoder_channels"}
        if unknown:
            raise ModelFileError(f"model config: unknown keys {sorted(unknown)}")
        if lr_schedule not in LR_SCHEDULES:
            raise ModelConfigError(
                f"lr_schedule must be one of {LR_SCHEDULES}, got {lr_schedule!r}"
            )
        if len(tuple(image_size)) != 2 or len(tuple(mean)) != 3 or len(tuple(std)) != 3:
            raise ModelConfigError("image_size must be [H, W]; mean and std three RGB values")
        self.save_hyperparameters(
            {
                "model": model,
                "augment": _plain(augment),
                "loss": _plain(loss) or {},
                "lr": float(lr),
                "weight_decay": float(weight_decay),
                "image_size": [int(v) for v in image_size],
                "mean": [float(v) for v in mean],
                "std": [float(v) for v in std],
                "threshold": float(threshold),
                "dataset": str(dataset),
                "seed": int(seed),
                "lr_schedule": str(lr_schedule),
                "warmup_steps": int(warmup_steps),
                "channels_last": bool(channels_last),
            }
        )
        self.net = build_unet(
            model["name"],
            model["in_channels"],
            model["weights_path"],
            model["decoder_channels"],
        )
        self.loss_fn = FocalDiceLoss(**self.hparams.loss)
        self.augment = build_augmentation(self.hparams.augment)
        # steps of the learning-rate schedule: trainer.max_steps (set with the optimiser) unless
        # a callback fits the schedule to the time budget (roboseg.time_budget)
        self.schedule_steps: int | None = None
        self.train_iou = BinaryJaccardIndex(threshold=float(threshold))
        self.val_iou = BinaryJaccardIndex(threshold=float(threshold))
        self.test_iou = BinaryJaccardIndex(threshold=float(threshold))
        self.val_frame_iou = MeanMetric()
        self.test_frame_iou = MeanMetric()

    # --- properties -----------------------------------------------------------------------

    @property
    def in_channels(self) -> int:
        return int(self.hparams.model["in_channels"])

    def export_metadata(self) -> dict[str, Any]:
        """What an exported model must carry (keys of ``roboseg.segmentor.SegmentorMeta``)."""
        h, w = self.hparams.image_size
        return {
            "encoder": self.hparams.model["name"],
            "in_channels": self.in_channels,
            "input_height": int(h),
            "input_width": int(w),
            "mean": tuple(self.hparams.mean),
            "std": tuple(self.hparams.std),
            "threshold": float(self.hparams.threshold),
            "params_m": round(count_params(self.net) / 1e6, 1),
            "cmm": bool(self.augment is not None and self.augment.uses_cmm),
            "dataset": self.hparams.dataset,
        }

    # --- data path ------------------------------------------------------------------------

    def setup(self, stage: str) -> None:
        if self.augment is not None:
            self.augment.reseed(self.hparams.seed + self.global_rank)

    def on_fit_start(self) -> None:
        if self.hparams.get("channels_last", False):
            self.net.to(memory_format=torch.channels_last)

    def on_fit_end(self) -> None:
        self.net.to(memory_format=torch.contiguous_format)  # export and inference as usual

    def on_after_batch_transfer(self, batch: Batch, dataloader_idx: int) -> Batch:
        """Augment (training only), then add ``input`` and ``target`` to the batch dict."""
        bad = ~torch.isfinite(batch["image"]).flatten(1).all(1)
        if bool(bad.any()):
            where = batch.get("index", torch.arange(len(bad), device=bad.device))[bad]
            raise DatasetError(f"batch samples {where.tolist()} have non-finite image values")
        training = self._trainer is not None and self.trainer.training
        if training and self.augment is not None:
            self.augment.set_step(self.global_step)
            batch = self.augment(batch)
        batch = dict(batch)
        batch["input"], batch["target"] = prepare(
            batch, self.hparams.mean, self.hparams.std, self.in_channels
        )
        if self.hparams.get("channels_last", False):
            batch["input"] = batch["input"].contiguous(memory_format=torch.channels_last)
        return batch

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Logits ``[B,1,H,W]`` of a model input ``[B,C,H,W]``."""
        return self.net(x)

    # --- steps ----------------------------------------------------------------------------

    def _shared_step(self, batch: Batch, stage: str, iou: BinaryJaccardIndex) -> torch.Tensor:
        if "input" not in batch:  # called outside a Trainer
            batch = self.on_after_batch_transfer(batch, 0)
        logits = self(batch["input"]).float()  # the loss in float32, also under bf16-mixed
        target = batch["target"]
        loss = self.loss_fn(logits, target, batch.get("draped"))
        probs, n = torch.sigmoid(logits.detach()), target.shape[0]
        if stage == "train":  # per-step value (streaming data may have no epochs) + epoch value
            iou(probs, target.int())
            self.log("train/loss", loss, prog_bar=True, batch_size=n)
            self.log("train/iou", iou, on_step=True, on_epoch=True, batch_size=n)
        else:  # per-frame mean and pooled IoU, synchronised over DDP ranks by torchmetrics
            iou.update(probs, target.int())
            frame_iou = self.val_frame_iou if stage == "val" else self.test_frame_iou
            frame_iou.update(per_frame_iou(probs > self.hparams.threshold, target > 0.5))
            self.log(f"{stage}/loss", loss, prog_bar=True, batch_size=n, sync_dist=True)
            self.log(f"{stage}/iou", frame_iou, prog_bar=True, on_step=False, on_epoch=True,
                     batch_size=n)
            self.log(f"{stage}/iou_pooled", iou, on_step=False, on_epoch=True, batch_size=n)
        return loss

    def training_step(self, batch: Batch, batch_idx: int) -> torch.Tensor:
        loss = self._shared_step(batch, "train", self.train_iou)
        if not torch.isfinite(loss):
            lr = self.optimizers().param_groups[0]["lr"] if self._trainer else self.hparams.lr
            raise NonFiniteLossError(
                f"training loss is {loss.item()} at step {self.global_step} (lr={lr:g}); "
                "stopping, the checkpoints written so far are intact"
            )
        return loss

    def validation_step(self, batch: Batch, batch_idx: int) -> torch.Tensor:
        return self._shared_step(batch, "val", self.val_iou)

    def test_step(self, batch: Batch, batch_idx: int) -> torch.Tensor:
        return self._shared_step(batch, "test", self.test_iou)

    def predict_step(self, batch: Batch, batch_idx: int) -> torch.Tensor:
        """Robot probabilities ``[B,1,H,W]``."""
        return torch.sigmoid(self(batch["input"]))

    def configure_optimizers(self) -> dict[str, Any]:
        """AdamW; its learning rate follows :func:`lr_factor` per optimizer step."""
        optimizer = torch.optim.AdamW(
            self.net.parameters(), lr=self.hparams.lr, weight_decay=self.hparams.weight_decay
        )
        # a FitScheduleToTime callback may shorten it later (on_train_start comes after this)
        self.schedule_steps = self.trainer.max_steps if self._trainer is not None else -1
        schedule, warmup = self.hparams.lr_schedule, self.hparams.warmup_steps
        scheduler = torch.optim.lr_scheduler.LambdaLR(  # the horizon is read at every step
            optimizer, lambda step: lr_factor(step, warmup, int(self.schedule_steps), schedule)
        )
        return {
            "optimizer": optimizer,
            "lr_scheduler": {"scheduler": scheduler, "interval": "step", "frequency": 1},
        }

    # --- checkpoints ----------------------------------------------------------------------

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Make the checkpoint self-contained: its weights replace any pretrained-weights file."""
        hparams = copy.deepcopy(dict(checkpoint.get("hyper_parameters", {})))
        if "model" in hparams:
            pretrained = hparams["model"].get("weights_path")
            hparams["model"]["weights_path"] = None
            checkpoint["hyper_parameters"] = hparams
            checkpoint["roboseg"] = {
                "pretrained_weights": str(pretrained) if pretrained else "",
                **{k: list(v) if isinstance(v, tuple) else v
                   for k, v in self.export_metadata().items()},
            }

    @classmethod
    def load_from_checkpoint(  # type: ignore[override]
        cls,
        checkpoint_path: str | Path,
        map_location: Any = None,
        weights_only: bool = True,
        **kwargs: Any,
    ) -> SegmentationModule:
        """Rebuild a module from a checkpoint, by default with ``torch.load(weights_only=True)``.

        Raises :class:`ModelFileError` naming the file when it is missing or unreadable.
        """
        path = Path(checkpoint_path)
        if not path.is_file():
            raise ModelFileError(f"checkpoint {path}: no such file")
        try:
            return super().load_from_checkpoint(
                path, map_location=map_location, weights_only=weights_only, **kwargs
            )
        except RobosegError:
            raise
        except Exception as exc:  # noqa: BLE001 - corrupt / foreign / unsafe checkpoint
            raise ModelFileError(f"checkpoint {path}: cannot be loaded ({exc})") from exc

