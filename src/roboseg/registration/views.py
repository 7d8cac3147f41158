"""The cameras that observe the robot during registration, all rigidly tied to the left camera.

The registration unknown is ``T_cam_base`` of the *left* camera (reference frame). Every other
view (the right camera of a stereo pair) follows through a fixed, calibrated ``T_view_left``, so
``T_view_base = T_view_left @ T_cam_base``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from roboseg.camera import StereoRig
from roboseg.errors import CameraError
from roboseg.registration.pose import transform_points

__all__ = [
    "View",
    "stereo_views",
    "views_at_resolution",
    "vertices_in_view",
    "resize_masks",
    "crop_to_masks",
    "views_scaled",
    "views_for_width",
]


@dataclass(frozen=True)
class View:
    """One camera: intrinsics ``K`` [3, 3] (px) for a ``width × height`` image, and its fixed
    pose ``T_view_left`` [4, 4] relative to the left (reference) camera (identity for the left)."""

    name: str
    K: torch.Tensor
    width: int
    height: int
    T_view_left: torch.Tensor

    def __post_init__(self) -> None:
        if tuple(self.K.shape) != (3, 3) or tuple(self.T_view_left.shape) != (4, 4):
            raise CameraError(f"view {self.name!r}: K must be 3x3 and T_view_left 4x4")
        if self.width < 2 or self.height < 2:
            raise CameraError(f"view {self.name!r}: image too small ({self.width}x{self.height})")

    def resized(self, width: int, height: int) -> View:
        """The same camera imaging ``width × height`` pixels (pixel centres stay consistent)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.clone()
        K[0, 0], K[1, 1] = K[0, 0] * sx, K[1, 1] * sy
        # pixel centres are integers: u' + 1/2 = s·(u + 1/2)
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return View(self.name, K, int(width), int(height), self.T_view_left)


def stereo_views(rig: StereoRig, dtype: torch.dtype = torch.float32) -> list[View]:
    """``[left, right]`` views of a stereo rig at its native resolution."""
    left = View(
        "left",
        rig.left.as_tensor(dtype=dtype),
        rig.left.width,
        rig.left.height,
        torch.eye(4, dtype=dtype),
    )
    right = View(
        "right",
        rig.right.as_tensor(dtype=dtype),
        rig.right.width,
        rig.right.height,
        torch.tensor(np.array(rig.T_right_left), dtype=dtype),
    )
    return [left, right]


def views_at_resolution(views: Sequence[View], width: int) -> list[View]:
    """Every view resized to ``width`` pixels wide, keeping its aspect ratio (height rounded)."""
    return [v.resized(width, max(2, round(v.height * width / v.width))) for v in views]


def vertices_in_view(
    T_cam_base: torch.Tensor, view: View, vertices_base: torch.Tensor
) -> torch.Tensor:
    """Vertices ``[..., V, 3]`` (base frame) seen from ``view`` given the left ``T_cam_base``
    ``[..., 4, 4]`` (broadcast over leading dims)."""
    T = view.T_view_left.to(T_cam_base) @ T_cam_base
    return transform_points(T, vertices_base)


def resize_masks(masks: np.ndarray | torch.Tensor, width: int, height: int) -> np.ndarray:
    """Binary masks ``[N, H, W]`` resized to ``[N, height, width]`` (area average, then > 1/2)."""
    m = masks.detach().cpu().numpy() if isinstance(masks, torch.Tensor) else np.asarray(masks)
    if m.ndim != 3:
        raise CameraError(f"masks must be [N, H, W], got shape {m.shape}")
    m = m.astype(np.float32)
    if m.shape[1:] == (height, width):
        return m > 0.5
    return np.stack([cv2.resize(x, (width, height), interpolation=cv2.INTER_AREA) for x in m]) > 0.5


def crop_to_masks(
    views: Sequence[View], masks: Sequence[np.ndarray], margin: float = 0.3
) -> tuple[list[View], list[np.ndarray]]:
    """Each view and its masks ``[C, H, W]`` cropped to the bounding box of the union of its
    masks, grown by ``margin`` × box size per side and clipped to the image (the intrinsics
    shift by the crop origin: cx − tx, cy − ty). A view whose masks are all empty is kept whole.
    """
    out_views, out_masks = [], []
    for view, m in zip(views, masks, strict=True):
        m = np.asarray(m, dtype=bool)
        rows, cols = np.flatnonzero(m.any(axis=(0, 2))), np.flatnonzero(m.any(axis=(0, 1)))
        if len(rows) == 0:
            out_views.append(view)
            out_masks.append(m)
            continue
        y0, y1, x0, x1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
        gy, gx = round(margin * (y1 - y0)), round(margin * (x1 - x0))
        y0, y1 = max(0, y0 - gy), min(view.height, y1 + gy)
        x0, x1 = max(0, x0 - gx), min(view.width, x1 + gx)
        y1, x1 = max(y1, min(view.height, y0 + 2)), max(x1, min(view.width, x0 + 2))
        K = view.K.clone()
        K[0, 2], K[1, 2] = K[0, 2] - x0, K[1, 2] - y0
        out_views.append(View(view.name, K, int(x1 - x0), int(y1 - y0), view.T_view_left))
        out_masks.append(m[:, y0:y1, x0:x1])
    return out_views, out_masks


def views_scaled(views: Sequence[View], scale: float) -> list[View]:
    """Every view resized by ``scale`` (sizes rounded, at least 2 px)."""
    return [
        v.resized(max(2, round(v.width * scale)), max(2, round(v.height * scale))) for v in views
    ]


def views_for_width(views: Sequence[View], width: int | None) -> list[View]:
    """Views scaled alike so that the widest is at most ``width`` px (None: unchanged)."""
    widest = max(v.width for v in views)
    if width is None or widest <= width:
        return list(views)
    return views_scaled(views, width / widest)
