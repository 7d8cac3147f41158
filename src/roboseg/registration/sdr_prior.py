"""SDR with the in-context prior: alternate segmentation and stereo differentiable rendering.

A 4-channel segmentation model takes, besides the RGB image, a *prior*: the hard silhouette of
the robot rendered at the current estimate of ``T_cam_base`` at the image's own resolution. The
paper's refinement alternates the two: segment with the prior of the current estimate, run SDR
against that segmentation for ``refresh_every`` iterations, render a new prior, segment again, …
for ``iterations`` SDR iterations in total (200, refreshed every 50, by default).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from roboseg.errors import CameraError
from roboseg.registration.sdr import Reason, RegistrationResult, SDRConfig, sdr
from roboseg.registration.views import View, crop_to_masks, vertices_in_view, views_for_width
from roboseg.render.raster import render_hard

__all__ = ["PriorConfig", "PriorResult", "Segmenter", "render_prior", "sdr_with_prior"]

log = logging.getLogger(__name__)

#: ``segment(images [C, H, W, 3] uint8 RGB, prior [C, H, W] float32 in {0, 1}) -> [C, H, W] bool``
Segmenter = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class PriorConfig:
    """``iterations`` SDR iterations in total; a new prior and segmentation every
    ``refresh_every`` of them (the first before iteration 1). ``sdr`` holds the optimiser
    settings of each round (its ``max_iterations`` is replaced by the round length); SDR renders
    the region of interest of each segmentation at most ``width`` pixels wide (priors are
    always rendered over the whole image at its resolution)."""

    iterations: int = 200
    refresh_every: int = 50
    sdr: SDRConfig = field(default_factory=SDRConfig)
    width: int | None = None  # widest SDR render in px (None: native)
    roi_margin: float = 0.3  # SDR renders the segmentation's bounding box grown by this per side

    def __post_init__(self) -> None:
        if self.iterations < 1 or self.refresh_every < 1:
            raise CameraError(
                f"SDR with prior needs iterations >= 1 and refresh_every >= 1, got "
                f"{self.iterations}, {self.refresh_every}"
            )

    @property
    def rounds(self) -> int:
        """Number of segmentations (= SDR rounds)."""
        return math.ceil(self.iterations / self.refresh_every)


@dataclass(frozen=True)
class PriorResult:
    """Final estimate (``result``), the number of segmentations run (``refreshes``), the last
    segmentation per view ``[C, H, W]`` bool, and the mean IoU per view after each round."""

    result: RegistrationResult
    refreshes: int
    masks: list[np.ndarray]
    round_iou: list[dict[str, float]]


def render_prior(
    vertices_base: torch.Tensor,
    faces: torch.Tensor,
    view: View,
    T_cam_base: np.ndarray | torch.Tensor,
) -> np.ndarray:
    """Hard silhouettes ``[C, H, W]`` float32 (1 robot, 0 background) of the robot in its C
    configurations (``vertices_base`` [C, V, 3], base frame, metres) seen by ``view`` at its own
    resolution when the left camera is at ``T_cam_base``. Robots behind the camera render empty."""
    T = torch.as_tensor(T_cam_base, dtype=vertices_base.dtype)
    with torch.no_grad():
        verts = vertices_in_view(T, view, vertices_base)
        out = torch.zeros(verts.shape[0], view.height, view.width, dtype=torch.bool)
        visible = (verts[..., 2] > 0).any(dim=1)
        if bool(visible.any()):
            out[visible] = render_hard(
                verts[visible], faces, view.K.to(verts), view.height, view.width
            )
    return out.numpy().astype(np.float32)


def sdr_with_prior(
    vertices_base: torch.Tensor,
    faces: torch.Tensor,
    views: Sequence[View],
    images: Sequence[np.ndarray],
    segment: Segmenter,
    T_cam_base_init: np.ndarray | torch.Tensor,
    config: PriorConfig | None = None,
) -> PriorResult:
    """Refine ``T_cam_base`` by alternating prior-conditioned segmentation and SDR.

    ``views`` are the cameras at the *image* resolution (left first); ``images[i]``
    ``[C, H, W, 3]`` uint8 RGB the frames seen by ``views[i]`` in the C configurations whose
    vertices are ``vertices_base`` [C, V, 3]. A round that
    diverges ends the refinement with the estimate before it (CameraError if the first fails).
    """
    cfg = config or PriorConfig()
    for view, imgs in zip(views, images, strict=True):
        if imgs.shape[1:3] != (view.height, view.width):
            raise CameraError(
                f"view {view.name!r}: images are {imgs.shape[2]}x{imgs.shape[1]} but the "
                f"camera is {view.width}x{view.height}"
            )
    T = np.asarray(T_cam_base_init, dtype=np.float64)
    done, refreshes = 0, 0
    history: list[float] = []
    round_iou: list[dict[str, float]] = []
    last: RegistrationResult | None = None
    masks: list[np.ndarray] = []
    reason: Reason = "max_iterations"
    for r in range(cfg.rounds):
        priors = [render_prior(vertices_base, faces, v, T) for v in views]
        masks = [
            np.asarray(segment(imgs, prior), dtype=bool)
            for imgs, prior in zip(images, priors, strict=True)
        ]
        refreshes += 1
        empty = [v.name for v, m in zip(views, masks, strict=True) if not m.any()]
        if empty:
            log.warning("SDR with prior: segmentation empty in every frame of %s", empty)
            reason = "diverged"
            break
        budget = min(cfg.refresh_every, cfg.iterations - r * cfg.refresh_every)
        roi_views, roi_masks = crop_to_masks(views, masks, cfg.roi_margin)
        sdr_views = views_for_width(roi_views, cfg.width)
        # the L-BFGS polish only after the last refresh: earlier rounds' masks are superseded
        polish = cfg.sdr.polish_iterations if r == cfg.rounds - 1 else 0
        round_cfg = replace(cfg.sdr, max_iterations=budget, polish_iterations=polish)
        res = sdr(vertices_base, faces, sdr_views, roi_masks, T, round_cfg)
        done += res.iterations
        history.extend(res.history)
        if res.reason == "diverged":
            log.warning("SDR with prior: round %d diverged; keeping the previous estimate", r + 1)
            reason = "diverged"
            break
        T, last, reason = res.T_cam_base, res, res.reason
        round_iou.append(dict(res.per_view_iou))
        log.info("SDR with prior round %d: %d iterations, IoU %s", r + 1, done, res.per_view_iou)
    if last is None:  # no round succeeded
        raise CameraError(
            "SDR with prior: no refinement round succeeded from the initial estimate "
            f"(the model's segmentation was empty or SDR diverged after {refreshes} rounds)"
        )
    final = replace(last, T_cam_base=T, reason=reason, iterations=done, history=tuple(history))
    return PriorResult(final, refreshes, masks, round_iou)
