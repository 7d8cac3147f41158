"""The paper's registration costs f(M, S) between a silhouette render M and a segmentation S.

``M`` is a render in [0, 1] (``[..., H, W]``), ``S`` a binary segmentation. Distances are exact
Euclidean distance transforms in pixels between pixel centres (scipy), computed once per target
mask in numpy and then held as tensors (:class:`RegistrationTarget`).

* ``d(S)``: for a pixel inside S, the distance to the nearest pixel outside S; 0 outside.
* ``d(1 − S)``: 0 inside S, the distance to the nearest pixel of S outside it.

(a) boundary MSE  ``f = (1/hw) ‖M − d(S)‖²₂``
(b) Dice variant  ``f = 1 − 2‖M ⊙ E‖₁ / (‖M‖²₂ + ‖E‖²₂ + ε)``, ``E = exp(−d(1 − S)/σ)``,
    σ = 2 px, ε = 1e-6.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from scipy import ndimage

__all__ = [
    "inside_distance",
    "outside_distance",
    "distance_mse_loss",
    "exp_dice_loss",
    "RegistrationTarget",
    "LossName",
    "iou",
]

LossName = Literal["dice", "mse"]
SIGMA = 2.0
EPSILON = 1e-6


def inside_distance(mask: np.ndarray) -> np.ndarray:
    """``d(S)`` ``[H, W]`` float32 px: distance of each pixel of S to the nearest pixel not in S.

    A mask covering the whole image has no boundary inside the image; its distances are then
    measured to the image border (as if the image were surrounded by background).
    """
    s = np.asarray(mask).astype(bool)
    if s.all():
        return ndimage.distance_transform_edt(np.pad(s, 1))[1:-1, 1:-1].astype(np.float32)
    return ndimage.distance_transform_edt(s).astype(np.float32)


def outside_distance(mask: np.ndarray) -> np.ndarray:
    """``d(1 − S)`` ``[H, W]`` float32 px: 0 on S, distance to the nearest pixel of S elsewhere.

    An empty mask gives ``inf`` everywhere (no robot pixel to be near).
    """
    s = np.asarray(mask).astype(bool)
    if not s.any():
        return np.full(s.shape, np.inf, dtype=np.float32)
    return ndimage.distance_transform_edt(~s).astype(np.float32)


def distance_mse_loss(render: torch.Tensor, d_inside: torch.Tensor) -> torch.Tensor:
    """Cost (a): ``(1/hw)‖M − d(S)‖²₂`` per image, ``[...]`` from ``[..., H, W]`` inputs."""
    return (render - d_inside).square().mean(dim=(-2, -1))


def exp_dice_loss(
    render: torch.Tensor, decay: torch.Tensor, epsilon: float = EPSILON
) -> torch.Tensor:
    """Cost (b) per image ``[...]``; ``decay`` is ``E = exp(−d(1 − S)/σ)`` ``[..., H, W]``."""
    overlap = (render * decay).abs().sum(dim=(-2, -1))
    denom = render.square().sum(dim=(-2, -1)) + decay.square().sum(dim=(-2, -1)) + epsilon
    return 1.0 - 2.0 * overlap / denom


def iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Intersection over union of boolean masks ``[..., H, W]`` → ``[...]`` (1 if both empty)."""
    a, b = a.bool(), b.bool()
    inter = (a & b).sum(dim=(-2, -1)).to(torch.float32)
    union = (a | b).sum(dim=(-2, -1)).to(torch.float32)
    return torch.where(union > 0, inter / union.clamp_min(1.0), torch.ones_like(union))


@dataclass(frozen=True)
class RegistrationTarget:
    """Target segmentations and their precomputed distance maps, ``[B, H, W]`` tensors."""

    masks: torch.Tensor  # bool, S
    d_inside: torch.Tensor  # float32 px, d(S)
    decay: torch.Tensor  # float32, exp(-d(1 - S) / sigma)

    @classmethod
    def from_masks(
        cls, masks: np.ndarray | torch.Tensor, sigma: float = SIGMA, threshold: float = 0.5
    ) -> RegistrationTarget:
        """Binarise ``masks`` ``[B, H, W]`` (bool, {0,1} or probabilities; ``> threshold``)."""
        m = masks.detach().cpu().numpy() if isinstance(masks, torch.Tensor) else np.asarray(masks)
        if m.ndim != 3:
            raise ValueError(f"target masks must be [B, H, W], got shape {m.shape}")
        s = m > threshold if m.dtype != bool else m
        d_in = np.stack([inside_distance(x) for x in s])
        decay = np.exp(-np.stack([outside_distance(x) for x in s]) / sigma)
        return cls(torch.from_numpy(s), torch.from_numpy(d_in), torch.from_numpy(decay))

    def loss(self, render: torch.Tensor, name: LossName = "dice") -> torch.Tensor:
        """Per-image cost ``[B]`` of a render ``[B, H, W]`` against these targets."""
        if name == "dice":
            return exp_dice_loss(render, self.decay.to(render))
        if name == "mse":
            return distance_mse_loss(render, self.d_inside.to(render))
        raise ValueError(f"unknown registration loss {name!r}; expected 'dice' or 'mse'")
