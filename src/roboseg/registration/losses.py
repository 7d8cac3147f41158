"""The paper's registration costs f(M, S) between a silhouette render M and a segmentation S.

``M`` is a render in [0, 1] (``[..., H, W]``), ``S`` a binary segmentation. Distances are exact
Euclidean distance transforms in pixels between pixel centres (scipy), computed once per target
mask in numpy and then held as tensors (:class:`RegistrationTarget`).

* ``d(S)``: for a pixel inside S, the distance to the nearest pixel outside S; 0 outside.
* ``d(1 − S)``: 0 inside S, the distance to the nearest pixel of S outside it.

(a) boundary MSE  ``f = (1/hw) ‖M − d(S)‖²₂``
(b) Dice variant  ``f = 1 − 2‖M ⊙ E‖₁ / (‖M‖²₂ + ‖E‖²₂ + ε)``, ``E = exp(−d(1 − S)/σ)``,
    σ = 2 px, ε = 1e-6.

Boundary offset (robustness to over- and under-segmentation): with the signed distance
``φ = d(S) − ½`` inside S and ``½ − d(1 − S)`` outside (boundary at ``φ = 0``, px), the target
shifted by ``e`` px is ``S_e = {φ > e}`` (``e > 0`` erodes, ``e < 0`` dilates) and both distance
maps follow from ``φ``: ``d(S_e) = relu(φ − e + ½)``, ``d(1 − S_e) ≈ relu(e − φ + ½)`` (exact at
``e = 0``, and wherever the nearest boundary point moves straight along its normal).
:meth:`RegistrationTarget.best_offsets` picks, per mask, the ``e`` whose ``S_e``
best matches a hard render (fewest differing pixels), so a segmentation that is uniformly too
fat or too thin no longer pulls the pose towards or away from the camera.
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
    "signed_distance",
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


def signed_distance(mask: np.ndarray) -> np.ndarray:
    """``φ`` ``[H, W]`` float32 px: ``d(S) − ½`` on S, ``½ − d(1 − S)`` elsewhere (boundary at 0).

    An empty mask gives ``−inf`` everywhere.
    """
    s = np.asarray(mask).astype(bool)
    return np.where(s, inside_distance(s) - 0.5, 0.5 - outside_distance(s)).astype(np.float32)


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
    phi: torch.Tensor | None = None  # float32 px, signed distance (see module docstring)
    sigma: float = SIGMA

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
        d_out = np.stack([outside_distance(x) for x in s])
        decay = np.exp(-d_out / sigma)
        phi = np.where(s, d_in - 0.5, 0.5 - d_out).astype(np.float32)
        return cls(
            torch.from_numpy(s),
            torch.from_numpy(d_in),
            torch.from_numpy(decay),
            torch.from_numpy(phi),
            sigma,
        )

    def best_offsets(
        self, render: torch.Tensor, max_offset: float, step: float = 0.25, penalty: float = 0.01
    ) -> torch.Tensor:
        """Per mask, the boundary offset ``e`` ``[B]`` (px, ``|e| ≤ max_offset``, multiple of
        ``step``) whose shifted target ``S_e = {φ > e}`` differs from the hard ``render``
        ``[B, H, W]`` in the fewest pixels, plus ``penalty·|e|·perimeter`` to prefer ``e = 0``
        among ties. A mask with an empty segmentation or render keeps ``e = 0``."""
        if self.phi is None:
            raise ValueError("boundary offsets need the signed distance (RegistrationTarget.phi)")
        n = int(round(max_offset / step))
        grid = torch.arange(-n, n + 1, dtype=torch.float32) * step  # [G]
        phi = self.phi.flatten(1)  # [B, P]
        m = render.detach().bool().flatten(1)
        B, G = phi.shape[0], grid.numel()
        # bin b of a pixel: number of grid values strictly below its φ, so φ > grid[g] ⟺ b > g
        bins = torch.bucketize(phi.contiguous(), grid)  # [B, P] in 0..G (-inf -> 0)
        offsets = (torch.arange(B) * (G + 1))[:, None]
        count_all = torch.bincount((bins + offsets).flatten(), minlength=B * (G + 1))
        count_in = torch.bincount((bins + offsets)[m], minlength=B * (G + 1))
        # |S_e| and |M ∧ S_e| for each grid value: pixels in bins above g
        above_all = count_all.view(B, G + 1).flip(1).cumsum(1).flip(1)[:, 1:]  # [B, G]
        above_in = count_in.view(B, G + 1).flip(1).cumsum(1).flip(1)[:, 1:]
        area = m.sum(1, keepdim=True)
        mismatch = (area + above_all - 2 * above_in).to(torch.float32)
        perimeter = (phi.abs() < 1.0).sum(1, keepdim=True).to(torch.float32)
        mismatch = mismatch + penalty * grid.abs()[None] * perimeter
        e = grid[mismatch.argmin(1)]
        valid = (area[:, 0] > 0) & torch.isfinite(phi).any(1)
        return torch.where(valid, e, torch.zeros_like(e))

    def loss(
        self, render: torch.Tensor, name: LossName = "dice", offsets: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Per-image cost ``[B]`` of a render ``[B, H, W]`` against these targets, each shifted
        by its boundary offset ``offsets`` ``[B]`` (px; None: unshifted)."""
        if name not in ("dice", "mse"):
            raise ValueError(f"unknown registration loss {name!r}; expected 'dice' or 'mse'")
        if offsets is None or self.phi is None or not bool(offsets.any()):
            if name == "dice":
                return exp_dice_loss(render, self.decay.to(render))
            return distance_mse_loss(render, self.d_inside.to(render))
        phi = self.phi.to(render)
        e = offsets.to(render)[:, None, None]
        if name == "dice":
            decay = torch.exp(-torch.relu(e - phi + 0.5) / self.sigma)
            return exp_dice_loss(render, decay)
        return distance_mse_loss(render, torch.relu(phi - e + 0.5))
