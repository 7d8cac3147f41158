"""The scanline rasteriser as it was before the branch-free set-up and the row levels (commit
aa9b2f9), kept as a reference: the optimised :mod:`roboseg.render.raster` must give the same
silhouettes, depths and face ids bit for bit. Simple rather than fast; not used by the package.
"""

from __future__ import annotations

from collections.abc import Iterator

import torch

from roboseg.camera import project

_EMPTY_KEY = (0x7F800000 << 32) | 0xFFFFFFFF


def _pairs(count: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(item, offset within the item) over ``count[i]`` offsets of every item i."""
    item = torch.repeat_interleave(torch.arange(count.numel()), count)
    starts = count.cumsum(0) - count
    return item, torch.arange(item.numel()) - starts[item]


def _triangles(
    verts: torch.Tensor,
    faces: torch.Tensor,
    K: torch.Tensor,  # noqa: N803
    height: int,
    width: int,
    z_near: float,
    cull: bool,
) -> dict[str, torch.Tensor] | None:
    """Culled triangles of all views with their scanline edge table (per-corner gathers,
    ``torch.where`` selections)."""
    B, V = verts.shape[:2]
    F = faces.shape[0]
    uv = project(verts, K).movedim(-1, 0)
    uvz = torch.cat([uv, verts[..., 2].unsqueeze(0)])  # [3, B, V]
    vert = (faces.t()[:, None, :] + (torch.arange(B) * V)[None, :, None]).reshape(-1)
    x, y, z = uvz.reshape(3, B * V).index_select(1, vert).view(3, 3, B * F).unbind(0)
    area2 = (x[1] - x[0]) * (y[2] - y[0]) - (y[1] - y[0]) * (x[2] - x[0])
    lo_v = torch.ceil(torch.minimum(torch.minimum(y[0], y[1]), y[2]))
    hi_v = torch.floor(torch.maximum(torch.maximum(y[0], y[1]), y[2]))
    lo_u = torch.ceil(torch.minimum(torch.minimum(x[0], x[1]), x[2]))
    hi_u = torch.floor(torch.maximum(torch.maximum(x[0], x[1]), x[2]))
    keep = lo_u.clamp_min(0) <= hi_u.clamp_max(width - 1)
    keep &= lo_v.clamp_min(0) <= hi_v.clamp_max(height - 1)
    keep &= area2.abs() > 1e-9
    keep &= (z >= z_near).all(dim=0)
    if cull:
        keep &= area2 < 0
    idx = keep.nonzero().squeeze(1)
    if idx.numel() == 0:
        return None
    x, y, z, area2 = x[:, idx], y[:, idx], z[:, idx], area2[idx]
    row0 = lo_v[idx].clamp(min=0).to(torch.int64)
    row1 = hi_v[idx].clamp(max=height - 1).to(torch.int64)
    xj, yj = x.roll(-1, dims=0), y.roll(-1, dims=0)
    dx, dy = x.roll(-2, dims=0) - xj, y.roll(-2, dims=0) - yj
    flat = dy == 0
    slope = torch.where(flat, torch.zeros_like(dx), dx / torch.where(flat, 1.0, dy))
    start = xj + slope * (row0.to(xj.dtype) - yj)
    turn = dy * area2
    left, right = turn < 0, turn > 0
    zero = torch.zeros_like(start)
    edges = torch.cat(
        [
            torch.where(left, start, -torch.inf),
            torch.where(left, slope, zero),
            torch.where(right, start, torch.inf),
            torch.where(right, slope, zero),
        ]
    )
    w = 1.0 / (z * area2)
    depth = torch.stack(
        [x[0], y[0], 1.0 / z[0], -(dy * w).sum(dim=0), (dx * w).sum(dim=0)]
    )
    return {
        "view": torch.div(idx, F, rounding_mode="floor"),
        "face": idx % F,
        "row0": row0,
        "rows": row1 - row0 + 1,
        "edges": edges,
        "depth": depth,
    }


def _spans(tris: dict[str, torch.Tensor], width: int) -> Iterator[tuple[torch.Tensor, ...]]:
    """(triangle, row, first column, last column) of every non-empty span."""
    t, dv = _pairs(tris["rows"])
    e = tris["edges"].index_select(1, t)
    dv_f = dv.to(e.dtype)
    left = torch.maximum(torch.maximum(e[0] + e[3] * dv_f, e[1] + e[4] * dv_f), e[2] + e[5] * dv_f)
    right = torch.minimum(
        torch.minimum(e[6] + e[9] * dv_f, e[7] + e[10] * dv_f), e[8] + e[11] * dv_f
    )
    u0 = torch.ceil(left.clamp(-1.0, width)).to(torch.int64).clamp(min=0)
    u1 = torch.floor(right.clamp(-1.0, width)).to(torch.int64).clamp(max=width - 1)
    keep = u0 <= u1
    t, dv, u0, u1 = t[keep], dv[keep], u0[keep], u1[keep]
    yield t, tris["row0"][t] + dv, u0, u1


def render_hard(
    verts: torch.Tensor,
    faces: torch.Tensor,
    K: torch.Tensor,  # noqa: N803
    height: int,
    width: int,
    z_near: float = 0.01,
    cull_back_faces: bool = False,
) -> torch.Tensor:
    """Silhouettes [B, H, W]: +1 / -1 at each span's ends, running sum along the rows."""
    verts, K = verts.detach(), torch.as_tensor(K, dtype=verts.dtype)
    K = K.expand(verts.shape[0], 3, 3) if K.dim() == 2 else K
    B = verts.shape[0]
    diff = torch.zeros(B, height, width + 1, dtype=torch.int32)
    tris = _triangles(verts, faces, K, height, width, z_near, cull_back_faces)
    if tris is not None:
        flat = diff.view(-1)
        for t, row, u0, u1 in _spans(tris, width):
            start = (tris["view"][t] * height + row) * (width + 1) + u0
            ones = torch.ones_like(start, dtype=torch.int32)
            flat.index_add_(0, start, ones)
            flat.index_add_(0, start + (u1 - u0 + 1), -ones)
    return diff.cumsum(dim=2)[..., :width] > 0


def rasterize(
    verts: torch.Tensor,
    faces: torch.Tensor,
    K: torch.Tensor,  # noqa: N803
    height: int,
    width: int,
    z_near: float = 0.01,
    cull_back_faces: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(depth [B, H, W] float32, face id [B, H, W] int64): nearest surface by a 64-bit key."""
    verts, K = verts.detach(), torch.as_tensor(K, dtype=verts.dtype)
    K = K.expand(verts.shape[0], 3, 3) if K.dim() == 2 else K
    B = verts.shape[0]
    buffer = torch.full((B * height * width,), _EMPTY_KEY, dtype=torch.int64)
    tris = _triangles(verts, faces, K, height, width, z_near, cull_back_faces)
    if tris is not None:
        for t, row, u0, u1 in _spans(tris, width):
            d = tris["depth"][:, t]
            inv_z0 = d[2] + d[3] * (u0.to(d.dtype) - d[0]) + d[4] * (row - d[1])
            start = (tris["view"][t] * height + row) * width + u0
            s, du = _pairs(u1 - u0 + 1)
            inv_z = inv_z0[s] + d[3][s] * du
            z = (1.0 / inv_z.clamp_min(1e-30)).to(torch.float32)
            key = (z.view(torch.int32).to(torch.int64) << 32) | tris["face"][t][s]
            buffer.scatter_reduce_(0, start[s] + du, key, reduce="amin")
    depth = torch.where(buffer == _EMPTY_KEY, torch.inf, (buffer >> 32).to(torch.int32).view(
        torch.float32
    ))
    face_id = torch.where(buffer == _EMPTY_KEY, -1, buffer & 0xFFFFFFFF)
    return depth.view(B, height, width), face_id.view(B, height, width)
