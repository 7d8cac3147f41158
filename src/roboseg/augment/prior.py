"""In-context prior (paper step 1): the robot's silhouette rendered at a perturbed pose.

The perturbation modifies the pose of the robot in the camera frame, ``T_cam_base = [R | t]``
(metres, OpenCV optical frame), like the paper's deviations of the pose parameters:

- translation ``Δx`` with each component ``Δx_i ~ U[0, 5] cm`` (the paper's range; configurable),
  added in camera axes: ``t' = t + Δx``;
- rotation ``ΔR`` of axis-angle ``ω`` with ``‖ω‖ = 5°`` exactly about a uniformly random axis,
  composed in camera axes: ``R' = ΔR R`` (a turn about the robot base origin).

The render must happen before the geometric augmentation, with intrinsics already scaled to the
training size. The rasteriser is ``roboseg.render.raster.render_hard`` unless one is injected.
Several views (robots of one frame, frames of one batch) render in one call with
:meth:`InContextPrior.render_union`, which is much cheaper per view than one call each.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import nn

#: Renderer ``(verts_cam [B,V,3], faces [F,3], K [B,3,3] or [3,3], H, W) -> silhouettes``.
Renderer = Callable[..., torch.Tensor]


def axis_angle_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """Rodrigues: axis-angle vectors ``[B,3]`` (radians) → rotation matrices ``[B,3,3]``."""
    angle = rotvec.norm(dim=-1, keepdim=True)
    axis = rotvec / angle.clamp_min(1e-12)
    x, y, z = axis.unbind(-1)
    zero = torch.zeros_like(x)
    skew = torch.stack(
        [torch.stack([zero, -z, y], -1), torch.stack([z, zero, -x], -1),
         torch.stack([-y, x, zero], -1)], -2,
    )
    s, c = torch.sin(angle)[..., None], torch.cos(angle)[..., None]
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device).expand_as(skew)
    return eye + s * skew + (1 - c) * (skew @ skew)


def sample_pose_perturbation(
    batch_size: int,
    generator: torch.Generator,
    translation_range: tuple[float, float] = (0.0, 0.05),
    rotation_deg: float = 5.0,
    dtype: torch.dtype = torch.float32,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``ΔR`` ``[B,3,3]`` (angle exactly ``rotation_deg``, uniform axis), ``Δx`` ``[B,3]`` (m)."""
    dev = generator.device
    axis = torch.randn(batch_size, 3, generator=generator, device=dev, dtype=dtype)
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)  # uniform on the sphere
    delta_r = axis_angle_to_matrix(axis * math.radians(rotation_deg))
    low, high = translation_range
    u = torch.rand(batch_size, 3, generator=generator, device=dev, dtype=dtype)
    return delta_r, low + (high - low) * u


def perturb_pose(
    T_cam_base: torch.Tensor, delta_r: torch.Tensor, delta_x: torch.Tensor
) -> torch.Tensor:
    """``[ΔR R | t + Δx]`` for poses ``[B,4,4]`` (see module doc for the frames)."""
    out = T_cam_base.clone()
    out[..., :3, :3] = delta_r.to(T_cam_base) @ T_cam_base[..., :3, :3]
    out[..., :3, 3] = T_cam_base[..., :3, 3] + delta_x.to(T_cam_base)
    return out


def transform_points(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """``p' = R p + t`` for poses ``[B,4,4]`` and points ``[B,V,3]``."""
    return points @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]


def _default_renderer() -> Renderer:
    from roboseg.render.raster import render_hard  # the rasteriser module of this project

    return render_hard


class InContextPrior(nn.Module):
    """Render robot silhouettes at randomly perturbed poses as the prior channel ``[B,1,H,W]``."""

    def __init__(
        self,
        translation_range: tuple[float, float] = (0.0, 0.05),
        rotation_deg: float = 5.0,
        renderer: Renderer | None = None,
    ) -> None:
        super().__init__()
        self.translation_range = (float(translation_range[0]), float(translation_range[1]))
        self.rotation_deg = float(rotation_deg)
        self.renderer = renderer

    def sample(self, batch_size: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """Draw ``delta_r`` ``[B,3,3]`` and ``delta_x`` ``[B,3]`` (metres)."""
        delta_r, delta_x = sample_pose_perturbation(
            batch_size, generator, self.translation_range, self.rotation_deg
        )
        return {"delta_r": delta_r, "delta_x": delta_x}

    def apply(
        self,
        verts_base: torch.Tensor,
        faces: torch.Tensor,
        K: torch.Tensor,
        T_cam_base: torch.Tensor,
        height: int,
        width: int,
        params: dict[str, torch.Tensor],
    ) -> torch.Tensor:
        """Silhouettes (float {0,1} ``[B,1,H,W]``) of ``verts_base`` ``[B,V,3]`` (base frame, m)
        seen through ``K`` at the perturbed ``T_cam_base`` ``[B,4,4]``."""
        T = perturb_pose(T_cam_base, params["delta_r"], params["delta_x"])
        verts_cam = transform_points(T, verts_base.to(T))
        render = self.renderer or _default_renderer()
        sil = render(verts_cam, faces, K, height, width)
        sil = sil.to(torch.float32)
        return sil.unsqueeze(1) if sil.ndim == 3 else sil

    def render_union(
        self,
        verts_base: torch.Tensor,
        faces: torch.Tensor,
        K: torch.Tensor,
        T_cam_base: torch.Tensor,
        height: int,
        width: int,
        params: dict[str, torch.Tensor],
        owner: torch.Tensor,
        n_out: int,
    ) -> torch.Tensor:
        """Union per output of views rendered in one call: ``[n_out,1,H,W]`` float {0,1}.

        ``verts_base`` ``[N,V,3]``, ``K`` ``[N,3,3]``, ``T_cam_base`` ``[N,4,4]`` and ``params``
        describe N views as in :meth:`apply`; view ``n`` belongs to output ``owner[n]`` (long
        ``[N]`` in ``[0, n_out)``). Outputs without a view are zero.
        """
        out = torch.zeros(n_out, 1, height, width)
        if verts_base.shape[0] == 0:
            return out
        sil = self.apply(verts_base, faces, K, T_cam_base, height, width, params)
        index = owner.to(torch.long).view(-1, 1, 1, 1).expand_as(sil)
        return out.to(sil).scatter_reduce_(0, index, sil, reduce="amax")

    def forward(
        self,
        verts_base: torch.Tensor,
        faces: torch.Tensor,
        K: torch.Tensor,
        T_cam_base: torch.Tensor,
        height: int,
        width: int,
        generator: torch.Generator,
    ) -> torch.Tensor:
        params = self.sample(verts_base.shape[0], generator)
        return self.apply(verts_base, faces, K, T_cam_base, height, width, params)
