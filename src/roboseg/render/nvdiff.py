"""Optional nvdiffrast backend of the silhouette renderer (CUDA only, imported lazily).

nvdiffrast rasterises in clip space; the OpenCV intrinsics map to it so that pixel centres stay
at integer pixel coordinates: nvdiffrast samples pixel ``i`` at NDC ``(2i + 1) / W - 1`` and
stores NDC y = -1 in row 0, so with ``u = fx·x/z + s·y/z + cx``

    x_clip = (2 fx / W) x + (2 s / W) y + ((2 cx + 1) / W - 1) z,
    y_clip = (2 fy / H) y + ((2 cy + 1) / H - 1) z,
    w_clip = z,

and no vertical flip is needed. Depth uses an OpenGL-style near/far mapping (metres).
The soft silhouette is nvdiffrast's ``antialias`` of the hard coverage, the method that
:mod:`roboseg.render.soft` follows on the CPU.
"""

from __future__ import annotations

import importlib.util
from typing import Any

import torch
from torch import Tensor

Z_FAR = 100.0
"""Far plane (metres) of the clip-space depth mapping."""


def available() -> bool:
    """True when nvdiffrast is installed and CUDA is usable."""
    return importlib.util.find_spec("nvdiffrast") is not None and torch.cuda.is_available()


def clip_space(verts_cam: Tensor, K: Tensor, height: int, width: int, z_near: float) -> Tensor:
    """Homogeneous clip coordinates ``[B, V, 4]`` of camera-frame vertices ``[B, V, 3]``."""
    Kb = K.to(verts_cam) if K.dim() == 3 else K.to(verts_cam).unsqueeze(0)
    fx, s, cx = Kb[:, 0, 0, None], Kb[:, 0, 1, None], Kb[:, 0, 2, None]
    fy, cy = Kb[:, 1, 1, None], Kb[:, 1, 2, None]
    x, y, z = verts_cam.unbind(-1)
    a = (Z_FAR + z_near) / (Z_FAR - z_near)
    b = -2.0 * Z_FAR * z_near / (Z_FAR - z_near)
    return torch.stack(
        [
            (2 * fx / width) * x + (2 * s / width) * y + ((2 * cx + 1) / width - 1) * z,
            (2 * fy / height) * y + ((2 * cy + 1) / height - 1) * z,
            a * z + b,
            z,
        ],
        dim=-1,
    )


class NvdiffSilhouette:
    """Hard and antialiased silhouettes of one mesh with nvdiffrast on CUDA."""

    def __init__(self, faces: Tensor, height: int, width: int, z_near: float) -> None:
        import nvdiffrast.torch as dr  # optional dependency

        self._dr: Any = dr
        self._ctx: Any = None
        self.faces = faces.to(torch.int32)
        self.height, self.width, self.z_near = height, width, z_near

    def _raster(self, verts_cam: Tensor, K: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        if self._ctx is None:
            self._ctx = self._dr.RasterizeCudaContext(device=verts_cam.device)
        faces = self.faces.to(verts_cam.device)
        pos = clip_space(verts_cam.float(), K, self.height, self.width, self.z_near).contiguous()
        rast, _ = self._dr.rasterize(self._ctx, pos, faces, resolution=[self.height, self.width])
        return rast, pos, faces

    def hard(self, verts_cam: Tensor, K: Tensor) -> Tensor:
        """Hard silhouettes ``[B, H, W]`` bool."""
        with torch.no_grad():
            rast, _, _ = self._raster(verts_cam.detach(), K)
        return rast[..., 3] > 0

    def soft(self, verts_cam: Tensor, K: Tensor) -> Tensor:
        """Antialiased silhouettes ``[B, H, W]`` in [0, 1], differentiable w.r.t. the vertices."""
        rast, pos, faces = self._raster(verts_cam, K)
        coverage = (rast[..., 3:4] > 0).float()
        soft = self._dr.antialias(coverage, rast, pos, faces)
        return soft[..., 0].to(verts_cam.dtype)
