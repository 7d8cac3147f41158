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
from roboseg.sim.shading import barycentric, blinn_phong, interpolate, view_opacity


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
        return ShadedPixels(
            self.index[keep],
            self.depth[keep],
            self.rgb[keep],
            self.cos_view[keep],
            self.albedo[keep],
        )


def shade_surface(
    surface: Surface, rays: torch.Tensor, light: ViewLight, *, specular: float, shininess: float
) -> ShadedPixels:
    """Smooth-shade every covered pixel of ``surface``: barycentrics of the pixel ray on its
    face interpolate normal and albedo, then Lambert + Blinn-Phong under ``light``."""
    face_id = surface.face_id.reshape(-1)
    idx = torch.nonzero(face_id >= 0).squeeze(1)
    fid = face_id[idx]
    ray = rays.reshape(-1, 3)[idx]
    bary = barycentric(ray, surface.verts_cam, surface.faces, fid)
    n = interpolate(surface.normals_cam, surface.faces, fid, bary)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    view = -ray / ray.norm(dim=-1, keepdim=True)
    albedo = interpolate(surface.albedo, surface.faces, fid, bary)
    rgb = blinn_phong(
        n,
        view,
        light.direction,
        albedo,
        ambient=light.ambient,
        diffuse=1.0 - light.ambient,
        specular=specular,
        shininess=shininess,
    )
    depth = surface.depth.reshape(-1)[idx]
    return ShadedPixels(idx, depth, rgb * light.intensity, (n * view).sum(-1).abs(), albedo)


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
    px = px.select(px.depth < front[px.index])
    out[px.index] = px.rgb
    front[px.index] = px.depth

    if drape is not None and drape_params is not None:
        px = shade_surface(
            drape, rays, light, specular=drape_params.specular, shininess=drape_params.shininess
        )
        px = px.select(px.depth < front[px.index])
        a = view_opacity(torch.full_like(px.cos_view, drape_params.alpha), px.cos_view)[:, None]
        behind = out[px.index] * (0.55 + 0.45 * px.albedo)  # light through tinted plastic
        out[px.index] = a * px.rgb + (1.0 - a) * behind
        front[px.index] = px.depth

    occ_rgb, occ_depth, occ_alpha = occluders
    hit = torch.nonzero(torch.from_numpy(occ_depth).reshape(-1) < front).squeeze(1)
    if hit.numel():
        a = torch.from_numpy(occ_alpha).reshape(-1)[hit][:, None]
        col = torch.from_numpy(occ_rgb).reshape(-1, 3)[hit]
        lit = col * light.intensity * (light.ambient + (1.0 - light.ambient) * 0.8)
        out[hit] = a * lit + (1.0 - a) * out[hit]
    return out.reshape(height, width, 3).numpy()
