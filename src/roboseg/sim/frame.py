"""Composite one camera view of the draped scene, back to front.

Layers: the static room (ray-cast once per recording), the robot (z-buffer raster, smooth
Lambert + Blinn-Phong shading), the translucent drape over it, then the occluders. All geometry
arrives in this camera's OpenCV optical frame (metres) together with its raster (depth and face
id per pixel); colours are linear RGB until the camera pipeline
(:func:`roboseg.sim.shading.to_uint8`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from roboseg.sim.drape import DrapeParams
from roboseg.sim.shading import view_opacity


@dataclass(frozen=True)
class Surface:
    """A triangle mesh seen by one camera: vertices, unit vertex normals and linear-RGB albedo
    per vertex (camera frame), and its raster ``depth [H,W]`` (inf empty), ``face_id [H,W]``
    (-1 empty)."""

    verts_cam: torch.Tensor  # [V, 3]
    normals_cam: torch.Tensor  # [V, 3]
    faces: torch.Tensor  # [F, 3]
    albedo: torch.Tensor  # [V, 3]
    depth: torch.Tensor  # [H, W]
    face_id: torch.Tensor  # [H, W]


@dataclass(frozen=True)
class ViewLight:
    """Light of one view: unit direction towards the key light in the camera frame, its
    strength and the ambient share."""

    direction: torch.Tensor  # [3]
    intensity: float
    ambient: float


@dataclass(frozen=True)
class ShadedPixels:
    """Shaded hits of a surface: flat pixel indices ``[N]``, depth ``[N]`` (m), linear RGB
    ``[N,3]``, ``|n·v|`` ``[N]`` and albedo ``[N,3]``."""

    index: torch.Tensor
    depth: torch.Tensor
    rgb: torch.Tensor
    cos_view: torch.Tensor
    albedo: torch.Tensor

    def select(self, keep: torch.Tensor) -> ShadedPixels:
        """The pixels where the bool ``keep [N]`` is set."""
        i = keep.nonzero().squeeze(1)
        return ShadedPixels(
            self.index.index_select(0, i),
            self.depth.index_select(0, i),
            self.rgb.index_select(0, i),
            self.cos_view.index_select(0, i),
            self.albedo.index_select(0, i),
        )


def _norm(x: torch.Tensor) -> torch.Tensor:
    """Euclidean norm ``[N]`` of the columns of ``x [3, N]``."""
    return (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt()


def shade_surface(
    surface: Surface, rays: torch.Tensor, light: ViewLight, *, specular: float, shininess: float
) -> ShadedPixels:
    """Smooth-shade every covered pixel of ``surface``: barycentrics of the pixel ray on its
    face interpolate normal and albedo, then Lambert + Blinn-Phong under ``light``.

    The maths of :func:`~roboseg.sim.shading.barycentric`, :func:`~roboseg.sim.shading.
    interpolate` and :func:`~roboseg.sim.shading.blinn_phong`, evaluated on ``[3, N]``
    component rows (1-D gathers and reductions over the leading axis are much faster on CPU
    than over a trailing axis of size 3).
    """
    face_id = surface.face_id.reshape(-1)
    idx = torch.nonzero(face_id >= 0).squeeze(1)
    fid = face_id.index_select(0, idx)
    ray = rays.reshape(-1, 3).index_select(0, idx).T  # [3, N]
    corner = surface.faces.T.contiguous().index_select(1, fid)  # [3, N] vertex per corner
    verts = surface.verts_cam.T.contiguous()
    a, b, c = (verts.index_select(1, corner[k]) for k in range(3))
    # barycentrics of the ray's hit on the face's plane (Moller-Trumbore, clamped)
    e1, e2 = b - a, c - a
    p = torch.linalg.cross(ray, e2, dim=0)
    det = (e1 * p).sum(0)
    det = torch.where(det.abs() < 1e-12, torch.full_like(det, 1e-12), det)
    s = -a
    beta = (s * p).sum(0) / det
    gamma = (ray * torch.linalg.cross(s, e1, dim=0)).sum(0) / det
    bary = torch.stack([1.0 - beta - gamma, beta, gamma]).clamp(0.0, 1.0)
    bary = bary / bary.sum(0).clamp_min(1e-12)

    def interpolate(attr: torch.Tensor) -> torch.Tensor:
        rows = attr.T.contiguous()
        return sum(rows.index_select(1, corner[k]) * bary[k] for k in range(3))

    n = interpolate(surface.normals_cam)
    n = n / _norm(n).clamp_min(1e-9)
    view = -ray / _norm(ray)
    albedo = interpolate(surface.albedo)
    # Lambert + Blinn-Phong; normals facing away from the camera are flipped
    n_dot_v = (n * view).sum(0)
    n_lit = torch.where(n_dot_v < 0, -n, n)
    direction = light.direction[:, None]
    ndl = (n_lit * direction).sum(0).clamp_min(0.0)
    h = view + direction
    h = h / _norm(h).clamp_min(1e-12)
    ndh = (n_lit * h).sum(0).clamp_min(0.0)
    diffuse = 1.0 - light.ambient
    rgb = albedo * (light.ambient + diffuse * ndl) + specular * ndh**shininess
    depth = surface.depth.reshape(-1).index_select(0, idx)
    rgb = (rgb * light.intensity).T.contiguous()
    return ShadedPixels(idx, depth, rgb, n_dot_v.abs(), albedo.T.contiguous())


def composite_view(
    static_rgb: np.ndarray,
    static_depth: np.ndarray,
    robot: Surface,
    drape: Surface | None,
    drape_params: DrapeParams | None,
    occluders: tuple[np.ndarray, np.ndarray, np.ndarray],
    rays: torch.Tensor,
    light: ViewLight,
) -> np.ndarray:
    """Linear RGB ``[H, W, 3]`` of one view: static scene, robot, drape, occluders by depth.

    ``static_rgb``/``static_depth`` are already lit by the recording's scene light and are
    scaled by ``light.intensity``; the drape is seen with opacity growing at grazing angles and
    tints what lies behind it; ``occluders`` is ``(rgb, depth, alpha)`` from
    :func:`roboseg.sim.occluders.draw_capsules`.
    """
    height, width = static_depth.shape
    out = torch.from_numpy(static_rgb).reshape(-1, 3) * light.intensity
    front = torch.from_numpy(static_depth).reshape(-1).clone()

    px = shade_surface(robot, rays, light, specular=0.35, shininess=24.0)
    px = px.select(px.depth < front.index_select(0, px.index))
    out.index_copy_(0, px.index, px.rgb)
    front.index_copy_(0, px.index, px.depth)

    if drape is not None and drape_params is not None:
        px = shade_surface(
            drape, rays, light, specular=drape_params.specular, shininess=drape_params.shininess
        )
        px = px.select(px.depth < front.index_select(0, px.index))
        a = view_opacity(torch.full_like(px.cos_view, drape_params.alpha), px.cos_view)[:, None]
        # light through tinted plastic
        behind = out.index_select(0, px.index) * (0.55 + 0.45 * px.albedo)
        out.index_copy_(0, px.index, a * px.rgb + (1.0 - a) * behind)
        front.index_copy_(0, px.index, px.depth)

    occ_rgb, occ_depth, occ_alpha = occluders
    hit = torch.nonzero(torch.from_numpy(occ_depth).reshape(-1) < front).squeeze(1)
    if hit.numel():
        a = torch.from_numpy(occ_alpha).reshape(-1).index_select(0, hit)[:, None]
        col = torch.from_numpy(occ_rgb).reshape(-1, 3).index_select(0, hit)
        lit = col * light.intensity * (light.ambient + (1.0 - light.ambient) * 0.8)
        out.index_copy_(0, hit, a * lit + (1.0 - a) * out.index_select(0, hit))
    return out.reshape(height, width, 3).numpy()
