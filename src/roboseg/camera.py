"""Pinhole camera maths: intrinsics, the paper's projection matrix P, resize/crop, look-at, stereo.

Conventions (``docs/architecture.md``): OpenCV optical frames (x right, y down, z forward, metres);
pixel ``(u, v)`` is column u, row v and integer coordinates are pixel *centres*, so a camera-frame
point projects to ``u = fx·x/z + cx``, ``v = fy·y/z + cy``. Poses are ``T_<to>_<from>`` 4×4.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from roboseg.errors import CameraError

ArrayLike = np.ndarray | torch.Tensor | Sequence[float]


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels (no skew) for an image of ``width × height`` pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise CameraError(f"camera intrinsic {name} must be finite, got {value}")
            object.__setattr__(self, name, value)
        if self.fx <= 0 or self.fy <= 0:
            raise CameraError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if int(value) != value or int(value) <= 0:
                raise CameraError(f"image {name} must be a positive integer, got {value}")
            object.__setattr__(self, name, int(value))

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the paper's and OpenCV's name
        """Camera matrix [3, 3] float64."""
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64
        )

    @classmethod
    def from_K(cls, K: ArrayLike, width: int, height: int) -> Intrinsics:  # noqa: N803
        """Intrinsics from a 3×3 camera matrix (or its 9 numbers, row-major); skew must be 0."""
        k = _as_numpy(K).reshape(-1)
        if k.size != 9:
            raise CameraError(f"camera matrix K must have 9 numbers, got {k.size}")
        k = k.reshape(3, 3)
        if not np.allclose(k[2], [0.0, 0.0, 1.0]) or k[1, 0] != 0.0:
            raise CameraError(f"camera matrix K must be upper triangular with last row 0 0 1: {k}")
        if abs(k[0, 1]) > 1e-9 * abs(k[0, 0]):
            raise CameraError(f"camera matrix K has non-zero skew {k[0, 1]} (unsupported)")
        return cls(k[0, 0], k[1, 1], k[0, 2], k[1, 2], width, height)

    @classmethod
    def from_camera_info(cls, msg: Any) -> Intrinsics:
        """Intrinsics from a ROS ``sensor_msgs/CameraInfo`` message or a dict of its fields.

        Reads ``k`` (or ``K``: 9 numbers, row-major), ``width`` and ``height``.
        """

        def field(name: str) -> Any:
            if isinstance(msg, Mapping):
                return msg.get(name)
            return getattr(msg, name, None)

        k = field("k")
        if k is None:
            k = field("K")
        width, height = field("width"), field("height")
        if k is None or width is None or height is None:
            raise CameraError("CameraInfo needs fields k (or K), width and height")
        return cls.from_K(np.asarray(k, dtype=np.float64), int(width), int(height))

    def resized(self, width: int, height: int) -> Intrinsics:
        """Intrinsics after resizing the image to ``width × height`` (aspect may change).

        With centres at integer coordinates a pixel coordinate maps as u' = (u + 0.5)·sx − 0.5
        (sx = width'/width), hence fx' = fx·sx and cx' = (cx + 0.5)·sx − 0.5; likewise for v.
        """
        if width <= 0 or height <= 0:
            raise CameraError(f"resize target must be positive, got {width}x{height}")
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            self.fx * sx,
            self.fy * sy,
            (self.cx + 0.5) * sx - 0.5,
            (self.cy + 0.5) * sy - 0.5,
            width,
            height,
        )

    def cropped(self, tx: int, ty: int, width: int, height: int) -> Intrinsics:
        """Intrinsics of the region of interest whose top-left pixel is (tx, ty): cx − tx, cy − ty.

        The region may extend beyond the image (e.g. padded crops); only its size is validated.
        """
        return Intrinsics(self.fx, self.fy, self.cx - tx, self.cy - ty, width, height)

    def as_tensor(
        self, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
    ) -> torch.Tensor:
        """Camera matrix K as a [3, 3] tensor."""
        return torch.as_tensor(self.K, dtype=dtype, device=device)


def projection_matrix(intr: Intrinsics, z_min: float, z_max: float) -> np.ndarray:
    """The paper's perspective projection P [4, 4] (float64) from the camera frame to clip space.

    ``c = P @ [x, y, z, 1]`` has w = z and normalised device coordinates
    x_ndc = 2u/w_img − 1, y_ndc = 2v/h_img − 1 (y points down, like v), z_ndc ∈ [−1, 1] for
    z ∈ [z_min, z_max]. So NDC −1 … 1 spans the pixel coordinates 0 … width and OpenCV pixel
    centre i sits at x_ndc = 2i/width − 1. A rasteriser that samples at
    x_ndc = (2i + 1)/width − 1 (OpenGL, nvdiffrast) therefore samples u = i + 0.5; build P from
    ``Intrinsics(fx, fy, cx + 0.5, cy + 0.5, ...)`` to make its samples hit the pixel centres.
    """
    if not 0.0 < z_min < z_max:
        raise CameraError(f"need 0 < z_min < z_max, got z_min={z_min}, z_max={z_max}")
    w, h = intr.width, intr.height
    return np.array(
        [
            [2 * intr.fx / w, 0.0, 2 * intr.cx / w - 1, 0.0],
            [0.0, 2 * intr.fy / h, 2 * intr.cy / h - 1, 0.0],
            [0.0, 0.0, (z_max + z_min) / (z_max - z_min), 2 * z_max * z_min / (z_min - z_max)],
            [0.0, 0.0, 1.0, 0.0],
        ],
        dtype=np.float64,
    )


def project(points_cam: torch.Tensor, K: torch.Tensor) -> torch.Tensor:  # noqa: N803
    """Pixel coordinates [..., 2] (u, v) of camera-frame points [..., 3] (metres).

    ``K`` is [3, 3] or batched [B, 3, 3] matching the leading dimension of ``points_cam``
    (points [B, ..., 3]). Points at z = 0 give inf/nan; callers cull them.
    """
    K = torch.as_tensor(K, dtype=points_cam.dtype, device=points_cam.device)
    if K.dim() == 2:
        uvw = points_cam @ K.T
    elif K.dim() == 3 and points_cam.dim() >= 2 and points_cam.shape[0] == K.shape[0]:
        B = K.shape[0]
        flat = points_cam.reshape(B, -1, 3)
        uvw = torch.bmm(flat, K.transpose(1, 2)).reshape(points_cam.shape)
    else:
        raise ValueError(f"K {tuple(K.shape)} does not match points {tuple(points_cam.shape)}")
    return uvw[..., :2] / uvw[..., 2:3]


def look_at(eye: ArrayLike, target: ArrayLike, up: ArrayLike = (0.0, 0.0, 1.0)) -> Any:
    """``T_cam_world`` [..., 4, 4] of a camera at ``eye`` looking at ``target`` (world metres).

    OpenCV optical frame: z toward the target, x to the right, y down (i.e. along −``up``
    projected onto the image plane). Batched over leading dimensions; returns a float64 numpy
    array unless an input is a tensor (then a tensor of its dtype/device).
    """
    as_torch = any(isinstance(a, torch.Tensor) for a in (eye, target, up))
    ref = next((a for a in (eye, target, up) if isinstance(a, torch.Tensor)), None)
    dtype = ref.dtype if ref is not None and ref.is_floating_point() else torch.float64
    device = ref.device if ref is not None else None
    e, t, u = (
        torch.as_tensor(a if isinstance(a, torch.Tensor) else _as_numpy(a), dtype=dtype).to(device)
        for a in (eye, target, up)
    )
    e, t, u = torch.broadcast_tensors(e, t, u)
    z = t - e
    z_norm = z.norm(dim=-1, keepdim=True)
    x = torch.linalg.cross(z, u, dim=-1)
    x_norm = x.norm(dim=-1, keepdim=True)
    scale = torch.maximum(z_norm, torch.ones_like(z_norm)) * u.norm(dim=-1, keepdim=True)
    if bool((z_norm <= 1e-12).any()):
        raise CameraError("look_at: eye and target coincide")
    if bool((x_norm <= 1e-9 * scale).any()):
        raise CameraError("look_at: viewing direction is parallel to the up vector")
    z = z / z_norm
    x = x / x_norm
    y = torch.linalg.cross(z, x, dim=-1)
    R = torch.stack([x, y, z], dim=-2)  # rows: camera axes in world coordinates
    T = torch.zeros(*R.shape[:-2], 4, 4, dtype=dtype, device=device)
    T[..., :3, :3] = R
    T[..., :3, 3] = -(R @ e.unsqueeze(-1)).squeeze(-1)
    T[..., 3, 3] = 1.0
    return T if as_torch else T.numpy()


#: Horizontal field of view (degrees) of :meth:`StereoRig.zed2i_like`. The ZED 2i's wide lens is
#: specified as 110° horizontal at most; calibrations of the 16:9 modes report ~100°. 104° gives
#: fx = 0.5·960/tan(52°) ≈ 375 px at 960×540.
ZED2I_HFOV_DEG = 104.0


@dataclass(frozen=True)
class StereoRig:
    """Two cameras; ``T_right_left`` [4, 4] maps left-optical-frame points into the right one."""

    left: Intrinsics
    right: Intrinsics
    T_right_left: np.ndarray

    def __post_init__(self) -> None:
        T = _as_numpy(self.T_right_left).astype(np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise CameraError(f"T_right_left must be a finite 4x4 matrix, got shape {T.shape}")
        if not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(
            T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6
        ):
            raise CameraError("T_right_left must be a rigid transform (rotation + translation)")
        T.setflags(write=False)
        object.__setattr__(self, "T_right_left", T)

    @property
    def baseline(self) -> float:
        """Distance between the two optical centres (metres)."""
        return float(np.linalg.norm(self.T_right_left[:3, 3]))

    @classmethod
    def zed2i_like(cls, width: int = 960, height: int = 540, baseline: float = 0.12) -> StereoRig:
        """A rectified ZED 2i-like pair: square pixels, HFOV :data:`ZED2I_HFOV_DEG`, principal
        point at the image centre, right camera ``baseline`` metres along the left's +x axis."""
        if baseline <= 0:
            raise CameraError(f"stereo baseline must be positive, got {baseline}")
        f = 0.5 * width / math.tan(math.radians(ZED2I_HFOV_DEG) / 2)
        intr = Intrinsics(f, f, (width - 1) / 2, (height - 1) / 2, width, height)
        T = np.eye(4)
        T[0, 3] = -baseline  # a point at the right camera's centre has x = baseline on the left
        return cls(intr, intr, T)


def _as_numpy(a: ArrayLike) -> np.ndarray:
    if isinstance(a, torch.Tensor):
        return a.detach().cpu().numpy().astype(np.float64)
    try:
        return np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise CameraError(f"expected numbers, got {a!r}") from e
