"""Self-training: the recording being registered teaches the segmenter that registers it.

One round: render the robot's silhouette at the current estimate ``T_cam_base`` (base frame →
left OpenCV optical frame, metres) with the recorded joint states in both cameras of the frames
of the registered phase (the labels, rendered with the self-annotation renderer
:class:`~roboseg.annotate.MaskRenderer`), fine-tune a U-Net on those frames and labels
(:class:`~roboseg.training.SegmentationModule` under a ``lightning`` Trainer), take its masks of
the same frames, and refine the estimate by SDR from where it was (no camera swarm). Rounds
repeat until ``rounds`` are done or the mean residual IoU (estimate's silhouette against the
masks, mean over views) gains less than ``min_gain``; the round with the highest mean residual
IoU is kept. Each round's figures are the ``self_training`` list of ``pose.yaml``.

With ``masks="grabcut"`` a round does not fine-tune a network: each image's silhouette at the
estimate becomes a GrabCut trimap (robot for sure well inside it, background for sure well
outside, probable in a band about its outline), and the cut, driven by the image's own colours
and edges, gives the masks. A network fine-tuned on the estimate's silhouettes learns them back,
misplaced outlines included; the cut cannot carry the estimate's outline over, it follows the
image, so the estimate moves from round to round. Where the cut departs from the silhouette on
a pixel whose colour does not back it (a faint edge, which GrabCut's smoothness term shaves),
the silhouette stands (``grabcut_defer``).

The fine-tuned model learns only the registered robot (other robots and people are background
in its labels) and sees zeros as the in-context prior of a 4-channel model.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import lightning.pytorch as pl
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from roboseg.annotate import MaskRenderer, thin_evenly
from roboseg.errors import CameraError, ModelFileError, SegmentationError
from roboseg.recording import RecordingReader, StereoFrame
from roboseg.registration.grabcut import (
    grabcut,
    grabcut_deferring,
    keep_out_background,
    silhouette_trimap,
)
from roboseg.registration.pose import rotation_angle
from roboseg.registration.register import (
    Configuration,
    RegisterConfig,
    Registration,
    refit_on_own_pixels,
    spread_configurations,
)
from roboseg.registration.sdr import RegistrationResult, sdr
from roboseg.registration.segmentors import window_frames
from roboseg.registration.views import View, crop_to_masks, views_for_width
from roboseg.robot import RobotModel

__all__ = [
    "SelfTrainingConfig",
    "SelfTrainingError",
    "SelfTrainingResult",
    "PredictedMasks",
    "FramePairs",
    "pose_change",
    "stop_reason",
    "kept_round",
    "render_labels",
    "build_module",
    "fine_tune",
    "predict_probabilities",
    "grabcut_masks",
    "refine_registration",
    "self_train",
]

log = logging.getLogger(__name__)


#: How a round turns the estimate's silhouettes into masks (``SelfTrainingConfig.masks``).
MASK_SOURCES = ("model", "grabcut")


class SelfTrainingError(SegmentationError, ValueError):
    """A self-training setting is invalid (one line naming the setting)."""


@dataclass(frozen=True)
class SelfTrainingConfig:
    """How to self-train (``self_training:`` in ``conf/register.yaml``).

    ``rounds``: fine-tune → register rounds after the first registration (0: off);
    ``min_gain``: stop when a round raises the mean residual IoU by less than this (IoU, 0-1);
    ``steps``: optimizer steps of each fine-tuning, ``batch_size`` samples (one camera image
    each) a step, ``lr`` AdamW's learning rate (cosine schedule after ``warmup_steps``);
    ``model`` / ``decoder_channels`` / ``image_size`` ``[H, W]`` px: the U-Net trained from
    scratch, unless ``init_ckpt`` names a roboseg training checkpoint to start from (its model
    and input size are then used); ``augment``: an :class:`~roboseg.augment.AugmentationPipeline`
    Hydra config or None; ``max_frames``: stereo frames of the phase used, evenly strided;
    ``precision``: the Trainer's (``32-true``, ``bf16-mixed``); ``seed``: weights, sample order.
    ``masks``: ``model`` (fine-tune a U-Net on the silhouettes) or ``grabcut`` (cut each image
    from a trimap of its silhouette: robot for sure ``grabcut_inner_px`` inside the outline,
    background for sure ``grabcut_outer_px`` outside it, at the images' own size;
    ``grabcut_iterations`` GrabCut iterations; ``grabcut_keep_out``: pixels outside the
    silhouette that round 0's masks call background are background for sure, except within
    ``grabcut_keep_out_margin_px`` of those masks
    (:func:`~roboseg.registration.grabcut.keep_out_background`);
    ``grabcut_defer``: where the cut departs from the silhouette, it is kept only where the
    pixel's colour backs it by this log-likelihood ratio (nats) under the cut's colour models,
    see :func:`~roboseg.registration.grabcut.grabcut_deferring`; None: the cut as it is); the
    training settings are then unused.
    """

    rounds: int = 0
    min_gain: float = 0.005
    steps: int = 300
    batch_size: int = 8
    lr: float = 1e-3
    warmup_steps: int = 20
    model: str = "unet_regnety_004"
    decoder_channels: tuple[int, ...] | None = (64, 32, 16, 16, 8)
    image_size: tuple[int, int] = (144, 256)
    init_ckpt: str | None = None
    augment: Mapping[str, Any] | None = None
    max_frames: int = 200
    precision: str = "32-true"
    seed: int = 0
    masks: str = "model"
    grabcut_inner_px: int = 2
    grabcut_outer_px: int = 10
    grabcut_iterations: int = 3
    grabcut_keep_out: bool = True
    grabcut_keep_out_margin_px: int = 0
    grabcut_defer: float | None = 1.0

    def __post_init__(self) -> None:
        def bad(name: str, rule: str, value: Any) -> SelfTrainingError:
            return SelfTrainingError(f"self_training.{name} must be {rule}, got {value!r}")

        if self.rounds < 0:
            raise bad("rounds", ">= 0 (0: off)", self.rounds)
        if self.masks not in MASK_SOURCES:
            raise bad("masks", " or ".join(MASK_SOURCES), self.masks)
        if self.grabcut_inner_px < 0 or self.grabcut_outer_px < 1:
            raise bad("grabcut_inner_px / grabcut_outer_px", ">= 0 / >= 1 px",
                      (self.grabcut_inner_px, self.grabcut_outer_px))
        if self.grabcut_keep_out_margin_px < 0:
            raise bad("grabcut_keep_out_margin_px", ">= 0 px", self.grabcut_keep_out_margin_px)
        if self.grabcut_iterations < 1:
            raise bad("grabcut_iterations", ">= 1", self.grabcut_iterations)
        if self.grabcut_defer is not None and not (
            self.grabcut_defer >= 0 and math.isfinite(self.grabcut_defer)
        ):
            raise bad("grabcut_defer", "null or a log-likelihood ratio >= 0 (nats)",
                      self.grabcut_defer)
        for name in ("steps", "batch_size", "max_frames"):
            if getattr(self, name) < 1:
                raise bad(name, ">= 1", getattr(self, name))
        if self.warmup_steps < 0:
            raise bad("warmup_steps", ">= 0", self.warmup_steps)
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise bad("lr", "a positive number", self.lr)
        if not math.isfinite(self.min_gain):
            raise bad("min_gain", "a finite IoU difference", self.min_gain)
        if len(self.image_size) != 2 or min(self.image_size) < 32:
            raise bad("image_size", "[H, W] with both at least 32 px", list(self.image_size))
        if self.init_ckpt is not None and not Path(self.init_ckpt).is_file():
            raise ModelFileError(f"self_training.init_ckpt: no such file {self.init_ckpt}")


# --------------------------------------------------------------------------------------------
# pure rules


def pose_change(T_prev: np.ndarray, T_new: np.ndarray) -> tuple[float, float]:
    """``(translation mm, rotation deg)`` from ``T_prev`` to ``T_new`` (both ``T_cam_base``
    [4, 4], metres): how far the base origin moved in the camera frame, and the angle of the
    relative rotation ``R_prevᵀ R_new``."""
    a, b = np.asarray(T_prev, np.float64), np.asarray(T_new, np.float64)
    mm = 1000.0 * float(np.linalg.norm(b[:3, 3] - a[:3, 3]))
    rad = float(rotation_angle(torch.as_tensor(a[:3, :3]), torch.as_tensor(b[:3, :3])))
    return mm, math.degrees(rad)


def stop_reason(mean_ious: Sequence[float], rounds: int, min_gain: float) -> str | None:
    """Why self-training stops after the rounds so far, or None to run another.

    ``mean_ious``: the mean residual IoU of round 0 (the first registration), 1, 2, ...
    """
    done = len(mean_ious) - 1
    if done >= 1:
        gain = mean_ious[-1] - mean_ious[-2]
        if gain < min_gain:
            return f"mean residual IoU gained {gain:+.4f} < min_gain {min_gain:g}"
    if done >= rounds:
        return f"{rounds} rounds done"
    return None


def kept_round(mean_ious: Sequence[float]) -> int:
    """The round whose estimate is kept: the highest mean residual IoU, the latest on ties."""
    best = max(mean_ious)
    return max(i for i, v in enumerate(mean_ious) if v == best)


# --------------------------------------------------------------------------------------------
# data: frames of the phase, labels, dataset


def render_labels(
    robot_model: RobotModel,
    robot: str,
    views: Sequence[View],
    T_cam_base: np.ndarray,
    joints: np.ndarray,
    size: tuple[int, int],
) -> np.ndarray:
    """Silhouettes ``[N, 2, H, W]`` bool (left, right) of ``robot`` with joints ``[N, D]`` (URDF
    order) at ``T_cam_base``, rendered for images resized to ``size`` ``[H, W]`` (intrinsics
    scaled alike, pixel centres kept) by the self-annotation renderer."""
    h, w = int(size[0]), int(size[1])
    left, right = (v.resized(w, h) for v in views)
    renderer = MaskRenderer(
        robot_model,
        {robot: np.asarray(T_cam_base, np.float64)},
        right.T_view_left.double().numpy(),
        left.K.double().numpy(),
        right.K.double().numpy(),
        (h, w),
    )
    out = np.zeros((len(joints), 2, h, w), bool)
    for i, q in enumerate(np.asarray(joints, np.float64)):
        out[i] = renderer.render({robot: q})
    return out


def _resize_image(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """RGB ``[H, W, 3]`` uint8 → ``size`` ``[h, w]`` by area averaging (as in training)."""
    return cv2.resize(image, (int(size[1]), int(size[0])), interpolation=cv2.INTER_AREA)


def _read(reader: RecordingReader, index: int) -> StereoFrame:
    frame = next(reader.frames(index, index + 1), None)
    if frame is None:
        raise CameraError(f"{reader.path}: frame {index} cannot be read")
    return frame


class FramePairs(Dataset):
    """In-memory samples of the recording: ``images`` ``[M, H, W, 3]`` uint8 RGB and ``masks``
    ``[M, H, W]`` bool, as the dicts :class:`~roboseg.training.SegmentationModule` takes
    (``image`` [3, H, W] in 0-1, ``mask`` [1, H, W], ``visible`` robot inside the frame,
    ``index``; ``prior`` zeros [1, H, W] for a 4-channel model)."""

    def __init__(self, images: np.ndarray, masks: np.ndarray, in_channels: int = 3) -> None:
        if images.shape[:3] != masks.shape:
            raise CameraError(f"images {images.shape} and masks {masks.shape} do not match")
        self.images, self.masks, self.in_channels = images, masks, int(in_channels)

    def __len__(self) -> int:
        return len(self.images)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        m = self.masks[i]
        border = m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any()
        mask = torch.from_numpy(m.astype(np.float32))[None]
        sample = {
            "image": torch.from_numpy(self.images[i]).permute(2, 0, 1).float() / 255.0,
            "mask": mask,
            "visible": torch.tensor(not border),
            "index": torch.tensor(i),
        }
        if self.in_channels == 4:
            sample["prior"] = torch.zeros_like(mask)
        return sample


class _Data(pl.LightningDataModule):
    """Shuffled (seeded) training batches and ordered prediction batches of one
    :class:`FramePairs`."""

    def __init__(self, data: FramePairs, batch_size: int, seed: int) -> None:
        super().__init__()
        self.data, self.batch_size, self.seed = data, batch_size, seed

    def train_dataloader(self) -> DataLoader:
        g = torch.Generator().manual_seed(self.seed)
        size = min(self.batch_size, len(self.data))
        return DataLoader(self.data, batch_size=size, shuffle=True, drop_last=True, generator=g)

    def predict_dataloader(self) -> DataLoader:
        return DataLoader(self.data, batch_size=self.batch_size, shuffle=False)


# --------------------------------------------------------------------------------------------
# model


def build_module(cfg: SelfTrainingConfig) -> Any:
    """The :class:`~roboseg.training.SegmentationModule` to fine-tune: ``cfg.init_ckpt``'s
    weights, model and input size when given, else ``cfg.model`` from scratch (seeded)."""
    from roboseg.training import SegmentationModule

    common = {
        "augment": None if cfg.augment is None else dict(cfg.augment),
        "lr": cfg.lr,
        "dataset": "self_training",
        "seed": cfg.seed,
        "lr_schedule": "cosine",
        "warmup_steps": min(cfg.warmup_steps, cfg.steps // 2),
    }
    with torch.random.fork_rng():
        torch.manual_seed(cfg.seed)
        if cfg.init_ckpt is None:
            channels = cfg.decoder_channels
            model = {
                "name": cfg.model,
                "in_channels": 3,
                "decoder_channels": None if channels is None else [int(c) for c in channels],
            }
            return SegmentationModule(model=model, image_size=list(cfg.image_size), **common)
        start = SegmentationModule.load_from_checkpoint(cfg.init_ckpt, map_location="cpu")
        h = start.hparams
        module = SegmentationModule(
            model=dict(h.model),
            image_size=list(h.image_size),
            mean=list(h.mean),
            std=list(h.std),
            threshold=float(h.threshold),
            **common,
        )
    module.net.load_state_dict(start.net.state_dict())
    log.info("self-training starts from %s (%s)", cfg.init_ckpt, h.model["name"])
    return module


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """Lightning's banner lines and the warnings that do not apply to an in-memory set of a
    few dozen frames (no validation loop, no loader workers) stay out of the command's log."""
    lightning_log = logging.getLogger("lightning.pytorch")
    level = lightning_log.level
    lightning_log.setLevel(logging.WARNING)
    try:
        with warnings.catch_warnings():
            for text in ("val_dataloader", "on_after_batch_transfer", "many workers", "LeafSpec"):
                warnings.filterwarnings("ignore", message=f".*{text}")
            yield
    finally:
        lightning_log.setLevel(level)


def _trainer(
    cfg: SelfTrainingConfig, steps: int, callbacks: Sequence[pl.Callback] = ()
) -> pl.Trainer:
    from roboseg.training import training_precision

    precision = training_precision(cfg.precision, "cpu", setting="self_training.precision")
    return pl.Trainer(
        callbacks=list(callbacks),
        accelerator="cpu",
        devices=1,
        max_steps=steps,
        precision=precision,  # type: ignore[arg-type]
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        limit_val_batches=0,
    )


def fine_tune(
    module: Any, images: np.ndarray, masks: np.ndarray, cfg: SelfTrainingConfig
) -> tuple[pl.Trainer, float]:
    """Train ``module`` for ``cfg.steps`` steps on ``images`` ``[M, H, W, 3]`` uint8 and
    ``masks`` ``[M, H, W]`` bool (at the module's input size); returns the Trainer (it can save
    the module) and the mean training loss of the last 10 % of the steps."""
    data = _Data(FramePairs(images, masks, module.in_channels), cfg.batch_size, cfg.seed)
    losses: list[float] = []

    class _Losses(pl.Callback):
        def on_train_batch_end(self, trainer: Any, pl_module: Any, outputs: Any, *_: Any) -> None:
            losses.append(float(outputs["loss"]))

    with _quiet(), torch.random.fork_rng():
        torch.manual_seed(cfg.seed)
        trainer = _trainer(cfg, cfg.steps, [_Losses()])
        trainer.fit(module, datamodule=data)
    tail = losses[-max(1, len(losses) // 10) :]
    return trainer, float(np.mean(tail)) if tail else float("nan")


def predict_probabilities(
    module: Any,
    images: np.ndarray,
    cfg: SelfTrainingConfig,
    trainer: pl.Trainer | None = None,
) -> np.ndarray:
    """Robot probabilities ``[M, H, W]`` float32 of ``images`` ``[M, H, W, 3]`` uint8 (at the
    module's input size), by ``Trainer.predict`` (``trainer``, default a new one; the module's
    own normalisation)."""
    blank = np.zeros(images.shape[:3], bool)
    data = _Data(FramePairs(images, blank, module.in_channels), cfg.batch_size, cfg.seed)
    with _quiet():
        out = (trainer or _trainer(cfg, 1)).predict(module, datamodule=data)
    return torch.cat([p.float() for p in out])[:, 0].numpy()  # type: ignore[union-attr]


def grabcut_masks(
    images: np.ndarray,
    silhouettes: np.ndarray,
    cfg: SelfTrainingConfig,
    background: np.ndarray | None = None,
) -> np.ndarray:
    """Masks ``[N, H, W]`` bool of RGB ``images`` ``[N, H, W, 3]`` uint8, each cut by GrabCut
    from the trimap of its silhouette (``[N, H, W]`` bool; :func:`silhouette_trimap`, with
    ``background`` ``[N, H, W]`` bool as sure background outside it), deferring to the
    silhouette where the colours cannot tell when ``cfg.grabcut_defer`` is set. An empty
    silhouette, or one whose band leaves no background to learn from, is kept as it is."""
    out = np.zeros(silhouettes.shape, bool)
    for i, (img, sil) in enumerate(zip(images, silhouettes, strict=True)):
        if not sil.any():
            continue
        trimap = silhouette_trimap(sil, cfg.grabcut_inner_px, cfg.grabcut_outer_px,
                                   None if background is None else background[i])
        try:
            cv2.setRNGSeed(cfg.seed)  # GrabCut's colour models start from k-means
            if cfg.grabcut_defer is None:
                out[i] = grabcut(img, trimap, cfg.grabcut_iterations, margin=0.05)
            else:
                out[i] = grabcut_deferring(img, trimap, sil, cfg.grabcut_iterations,
                                           margin=0.05, defer_nats=cfg.grabcut_defer)
        except SegmentationError:
            out[i] = sil
    return out


class PredictedMasks:
    """A :data:`~roboseg.registration.register.MaskSource` of the fine-tuned model's masks:
    probabilities ``[N, 2, h, w]`` uint8 (0-255, at the model's input size) of the frames
    ``indices`` [N], resized to each image's size (bilinear) and thresholded."""

    def __init__(self, indices: Sequence[int], probs: np.ndarray, threshold: float) -> None:
        self.row = {int(i): k for k, i in enumerate(indices)}
        self.probs, self.threshold = probs, float(threshold)

    @property
    def frames(self) -> list[int]:
        return list(self.row)

    def mask(self, index: int, camera: int, shape: tuple[int, ...]) -> np.ndarray:
        """Mask ``[H, W]`` bool of frame ``index``, camera 0 (left) or 1 (right)."""
        p = self.probs[self.row[int(index)], camera].astype(np.float32) / 255.0
        p = cv2.resize(p, (int(shape[1]), int(shape[0])), interpolation=cv2.INTER_LINEAR)
        return p > self.threshold

    def __call__(self, frame: StereoFrame) -> tuple[np.ndarray, np.ndarray]:
        if frame.index not in self.row:
            raise SegmentationError(f"self-training did not segment frame {frame.index}")
        return self.mask(frame.index, 0, frame.left.shape), self.mask(
            frame.index, 1, frame.right.shape
        )


# --------------------------------------------------------------------------------------------
# registration from the previous estimate


def _fit_warnings(res: RegistrationResult, used: list[Configuration], min_iou: float) -> list[str]:
    out = []
    if res.reason == "diverged":
        out.append("SDR diverged (robot left the images, non-finite cost or IoU collapse)")
    mean_iou = res.mean_iou
    if mean_iou < min_iou:
        out.append(f"poor fit: mean IoU {mean_iou:.3f} < {min_iou}")
    for c, row in zip(used, res.per_frame_iou, strict=False):
        if float(row.min()) < min_iou:
            out.append(f"frame {c.index}: IoU {row.round(3).tolist()} (left, right)")
    return out


def refine_registration(
    recording: Path,
    robot_model: RobotModel,
    previous: Registration,
    masks: PredictedMasks,
    joints: Mapping[int, np.ndarray],
    cfg: RegisterConfig,
) -> Registration:
    """Register again on ``masks``: ``cfg.configs`` configurations spread over the joints
    (``{frame index: [D]}``) of the frames ``masks`` covers (those whose mask covers less than
    ``cfg.min_mask_fraction`` of an image left out), SDR at ``cfg.width`` from
    ``previous.T_cam_base`` with every link (no swarm); trimmed near the estimate as
    :func:`~roboseg.registration.register.register` does when the masks may hold other robots.
    Without the stereo disparity term (``sdr.disparity_weight``): a round's masks are drawn
    from the estimate's own silhouettes, so their disparity echoes the estimate instead of
    measuring it (with the term, GrabCut rounds walked away from the truth: or_train_01 of
    ``make reproduce`` 59 → 31 → 63 → 74 mm instead of converging)."""
    t0 = time.perf_counter()
    cfg = replace(cfg, sdr=replace(cfg.sdr, disparity_weight=0.0))
    indices = [i for i in masks.frames if i in joints]
    q_all = np.stack([joints[i] for i in indices])
    scale = (robot_model.upper - robot_model.lower).double().numpy()
    order = spread_configurations(q_all, len(indices), scale)
    views = previous.views
    used: list[Configuration] = []
    imgs: list[list[np.ndarray]] = [[], []]
    msks: list[list[np.ndarray]] = [[], []]
    dropped: list[str] = []
    with RecordingReader(
        recording,
        robots=[previous.robot],
        joint_order={previous.robot: robot_model.joint_names},
        on_error="skip",
    ) as reader:
        for k in order:
            if len(used) == cfg.configs:
                break
            frame = _read(reader, indices[k])
            pair = masks(frame)
            fraction = min(float(m.mean()) for m in pair)
            if fraction < cfg.min_mask_fraction:
                dropped.append(
                    f"frame {frame.index} at {frame.stamp_ns} ns: self-trained mask covers "
                    f"{100 * fraction:.2f} % of an image"
                )
                continue
            used.append(Configuration(frame.index, frame.stamp_ns, joints[indices[k]].copy()))
            for i, (img, m) in enumerate(zip((frame.left, frame.right), pair, strict=True)):
                imgs[i].append(img)
                msks[i].append(m)
    if not used:
        raise CameraError(
            f"{recording}: the self-trained masks cover less than "
            f"{100 * cfg.min_mask_fraction:.2f} % of an image in every frame"
        )
    mask_stacks = [np.stack(m) for m in msks]
    t1 = time.perf_counter()
    fine = robot_model.decimated(cfg.sdr_reduction) if cfg.sdr_reduction > 0 else robot_model
    verts = fine.posed_vertices(
        torch.as_tensor(np.stack([c.joints for c in used]), dtype=fine.dtype)
    )
    roi_views, roi_masks = crop_to_masks(views, mask_stacks, cfg.roi_margin)
    res = sdr(
        verts,
        fine.faces,
        views_for_width(roi_views, cfg.width),
        roi_masks,
        previous.T_cam_base,
        cfg.sdr,
    )
    trim = cfg.other_robots_margin > 0 and (len(previous.robots_in_masks) > 1 or cfg.trim_masks)
    if trim and res.reason != "diverged":
        from roboseg.registration.sdr_prior import render_prior

        res, mask_stacks = refit_on_own_pixels(
            verts, fine.faces, views, mask_stacks, res,
            [render_prior(verts, fine.faces, v, res.T_cam_base) > 0.5 for v in views],
            [cfg.other_robots_margin * v.width for v in views], cfg,
        )
    t2 = time.perf_counter()
    warnings = _fit_warnings(res, used, cfg.min_iou)
    if len(used) < cfg.configs:
        warnings.insert(0, f"only {len(used)} of {cfg.configs} configurations usable")
    return replace(
        previous,
        T_cam_base=res.T_cam_base,
        method="sdr",
        result=res,
        sdr=res,
        prior=None,
        configurations=used,
        dropped=list(previous.dropped) + dropped,
        warnings=warnings,
        images=[np.stack(x) for x in imgs],
        masks=mask_stacks,
        seconds={"read_segment": t1 - t0, "sdr": t2 - t1, "total": t2 - t0},
        links=None,
    )


# --------------------------------------------------------------------------------------------
# the loop


@dataclass
class SelfTrainingResult:
    """``registration``: the kept round's (round 0: the one given); ``rounds``: one dict per
    round for ``pose.yaml`` (round 0 first); ``kept``: its round; ``frames``: the frame indices
    trained on and segmented; ``masks``: the kept round's fine-tuned masks of those frames;
    ``module`` / ``trainer`` / ``state``: the fine-tuned module, its last Trainer and the kept
    round's weights (None when round 0 is kept)."""

    registration: Registration
    rounds: list[dict[str, Any]]
    kept: int
    frames: list[int] = field(default_factory=list)
    masks: PredictedMasks | None = None
    module: Any | None = None
    trainer: pl.Trainer | None = None
    state: dict[str, torch.Tensor] | None = None

    def save_checkpoint(self, path: Path) -> Path | None:
        """Write the kept round's fine-tuned model as a roboseg training checkpoint (weights
        only; ``roboseg-export ckpt=PATH`` turns it into ONNX). None when round 0 was kept."""
        if self.trainer is None or self.module is None or self.state is None:
            return None
        self.module.load_state_dict(self.state)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.trainer.save_checkpoint(path, weights_only=True)
        return path


def _entry(
    k: int, reg: Registration, source: dict[str, Any], prev: Registration | None
) -> dict[str, Any]:
    change = None
    if prev is not None:
        mm, deg = pose_change(prev.T_cam_base, reg.T_cam_base)
        change = {"translation_mm": round(mm, 2), "rotation_deg": round(deg, 3)}
    return {
        "round": k,
        "masks": source,
        "method": reg.method,
        "residual_iou": {v: round(float(x), 4) for v, x in reg.result.per_view_iou.items()},
        "mean_residual_iou": round(reg.result.mean_iou, 4),
        "converged": reg.converged,
        "configurations": [c.index for c in reg.configurations],
        "T_cam_base": [[round(float(x), 6) for x in row] for row in reg.T_cam_base],
        "pose_change": change,
    }


def self_train(
    recording: str | Path,
    robot_model: RobotModel,
    first: Registration,
    reg_cfg: RegisterConfig,
    cfg: SelfTrainingConfig,
    source: dict[str, Any] | None = None,
    first_masks: Callable[[StereoFrame], tuple[np.ndarray, np.ndarray]] | None = None,
) -> SelfTrainingResult:
    """Self-train from ``first`` (the registration of ``reg_cfg``'s phase whose masks came from
    ``source``, e.g. ``{"kind": "motion"}``) for up to ``cfg.rounds`` rounds; see the module
    docstring. ``first_masks`` (frame → left, right masks) is round 0's segmentor, used by
    ``grabcut_keep_out``. A first registration that did not converge is not trained on (its
    labels would teach the wrong silhouette): it is returned as it is, with a warning."""
    path = Path(recording)
    src = dict(source or {"kind": "model"})
    history = [first.result.mean_iou]
    regs = [first]
    entries = [_entry(0, first, src, None)]
    log.info(
        "self-training round 0: masks from %s, mean residual IoU %.4f",
        src.get("kind"),
        history[0],
    )
    if cfg.rounds == 0:
        return SelfTrainingResult(first, entries, 0)
    if not first.converged:
        note = "self-training skipped: the first registration did not converge"
        log.warning("%s", note)
        entries[0]["stopped"] = note
        first.warnings.append(note)
        return SelfTrainingResult(first, entries, 0)

    t0 = time.perf_counter()
    wf = window_frames(path, robot_model, replace(reg_cfg, robot=first.robot))
    rows = thin_evenly(np.flatnonzero(wf.inside), cfg.max_frames)
    indices = [int(i) for i in wf.indices[rows]]
    joints = {int(i): wf.joints[r] for i, r in zip(indices, rows, strict=True)}
    module = build_module(cfg) if cfg.masks == "model" else None
    keep_out = module is None and cfg.grabcut_keep_out
    if keep_out and first_masks is None:
        raise SelfTrainingError("self_training.grabcut_keep_out needs round 0's segmentor")
    # the model's input size, or the left images' own (those round 0 registered on)
    size = (tuple(int(s) for s in module.hparams.image_size) if module is not None
            else tuple(int(s) for s in first.images[0].shape[1:3]))
    images = np.zeros((len(indices), 2, *size, 3), np.uint8)
    background = np.zeros((len(indices), 2, *size), bool) if keep_out else None
    with wf.reader(robot_model) as reader:
        for n, i in enumerate(indices):
            frame = _read(reader, i)
            images[n, 0] = _resize_image(frame.left, size)  # type: ignore[arg-type]
            images[n, 1] = _resize_image(frame.right, size)  # type: ignore[arg-type]
            if background is not None:  # keep_out: first_masks is set
                for c, m in enumerate(first_masks(frame)):  # type: ignore[misc]
                    m8 = cv2.resize(np.asarray(m, np.uint8), (size[1], size[0]),
                                    interpolation=cv2.INTER_NEAREST)
                    background[n, c] = keep_out_background(m8, cfg.grabcut_keep_out_margin_px)
    flat = images.reshape(-1, *size, 3)
    q = np.stack([joints[i] for i in indices])
    read_s = time.perf_counter() - t0
    log.info("self-training on %d stereo frames at %dx%d", len(indices), size[1], size[0])

    states: list[dict[str, torch.Tensor] | None] = [None]
    trainer: pl.Trainer | None = None
    predicted: list[PredictedMasks | None] = [None]
    stop = None
    while stop is None:
        k, prev = len(regs), regs[-1]
        t1 = time.perf_counter()
        labels = render_labels(robot_model, first.robot, first.views, prev.T_cam_base, q, size)
        t2 = time.perf_counter()
        if module is None:  # GrabCut from each silhouette
            cut = grabcut_masks(flat, labels.reshape(-1, *size), cfg,
                                None if background is None else background.reshape(-1, *size))
            t3 = time.perf_counter()
            masks = PredictedMasks(
                indices, (255 * cut).astype(np.uint8).reshape(len(indices), 2, *size), 0.5
            )
            label_iou = _pooled(cut.reshape(labels.shape), labels)
            how = {
                "kind": "grabcut",
                "frames": len(indices),
                "inner_px": cfg.grabcut_inner_px,
                "outer_px": cfg.grabcut_outer_px,
                "keep_out": bool(keep_out),
                "keep_out_margin_px": cfg.grabcut_keep_out_margin_px if keep_out else None,
                "defer_nats": cfg.grabcut_defer,
                "label_iou": round(label_iou, 4),
            }
        else:
            trainer, loss = fine_tune(module, flat, labels.reshape(-1, *size), cfg)
            t3 = time.perf_counter()
            probs = predict_probabilities(module, flat, cfg, trainer)
            masks = PredictedMasks(
                indices,
                np.round(255 * probs).astype(np.uint8).reshape(len(indices), 2, *size),
                float(module.hparams.threshold),
            )
            label_iou = _pooled(probs.reshape(labels.shape) > masks.threshold, labels)
            start = "init_ckpt" if cfg.init_ckpt else "scratch"
            how = {
                "kind": "self_trained",
                "model": str(module.hparams.model["name"]),
                "from": start if k == 1 else f"round {k - 1}",
                "frames": len(indices),
                "steps": cfg.steps,
                "train_loss": round(loss, 4),
                "label_iou": round(label_iou, 4),
            }
        t4 = time.perf_counter()
        try:
            reg = refine_registration(path, robot_model, prev, masks, joints, reg_cfg)
        except CameraError as exc:  # e.g. the fine-tuned masks are empty everywhere
            entries.append({"round": k, "masks": how, "failed": str(exc), "kept": False})
            stop = f"round {k} failed"
            log.warning("self-training round %d failed: %s", k, exc)
            break
        t5 = time.perf_counter()
        entry = _entry(k, reg, how, prev)
        masks_s = (
            {"grabcut": round(t4 - t2, 2)} if module is None
            else {"train": round(t3 - t2, 2), "predict": round(t4 - t3, 2)}
        )
        entry["seconds"] = {
            "labels": round(t2 - t1 + (read_s if k == 1 else 0.0), 2),
            **masks_s,
            "register": round(t5 - t4, 2),
        }
        regs.append(reg)
        entries.append(entry)
        states.append(None if module is None
                      else {n: t.detach().clone() for n, t in module.state_dict().items()})
        predicted.append(masks)
        history.append(reg.result.mean_iou)
        change = entry["pose_change"]
        log.info(
            "self-training round %d: masks from %s (IoU with the estimate's silhouettes "
            "%.3f), mean residual IoU %.4f (%+.4f), pose change %.1f mm %.2f deg",
            k,
            "GrabCut" if module is None else f"the model fine-tuned for {cfg.steps} steps",
            label_iou,
            history[-1],
            history[-1] - history[-2],
            change["translation_mm"],
            change["rotation_deg"],
        )
        stop = stop_reason(history, cfg.rounds, cfg.min_gain)
    best = kept_round(history)
    entries[-1]["stopped"] = stop
    for k, e in enumerate(entries):
        e["kept"] = k == best and "failed" not in e
    kept = regs[best]
    log.info("self-training stopped (%s); keeping round %d", stop, best)
    kept.seconds = {**first.seconds, "self_training": round(time.perf_counter() - t0, 2)}
    if best == 0 or module is None:
        return SelfTrainingResult(kept, entries, best, indices,
                                  None if best == 0 else predicted[best])
    return SelfTrainingResult(
        kept, entries, best, indices, predicted[best], module, trainer, states[best]
    )


def _pooled(pred: np.ndarray, target: np.ndarray) -> float:
    """IoU of two boolean arrays, pooled over all their pixels (1 when both are empty)."""
    union = np.count_nonzero(pred | target)
    return float(np.count_nonzero(pred & target) / union) if union else 1.0
