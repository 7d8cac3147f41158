"""Hard z-buffer rasteriser of triangle meshes in batched torch (CPU or CUDA; not differentiable).

Coverage rule: pixel (u, v) is covered by a triangle iff its centre (integer coordinates, see
``docs/architecture.md``) lies inside or on the projected triangle, whatever its winding.
Triangles with any vertex closer than ``z_near`` are culled whole (no near-plane clipping).

Algorithm: project the vertices, bound every triangle by the pixel centres of its bounding box
(clipped to the image), enumerate (triangle, pixel) pairs in chunks (``repeat_interleave``),
evaluate barycentric coordinates as affine functions of the pixel offset from the box corner,
and resolve visibility with one ``scatter_reduce(amin)`` on a 64-bit key packing the float32
depth above the face index (positive floats order like their bit patterns), so the nearest
surface wins and ties go to the lower face index.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import torch

from roboseg.camera import project
from roboseg.errors import CameraError

#: (triangle, pixel) pairs evaluated at once; bounds the working memory (~100 B per pair).
PAIR_CHUNK = 1 << 20
#: Triangles (views × faces) set up at once.
TRIANGLE_CHUNK = 1 << 20
_EMPTY_KEY = torch.iinfo(torch.int64).max


@dataclass(frozen=True)
class Raster:
    """Result of :func:`rasterize`; every field is [B, H, W]."""

    depth: torch.Tensor  # float32, camera-frame z (metres) of the nearest surface, inf if empty
    face_id: torch.Tensor  # int64, index into ``faces`` of the nearest surface, -1 if empty
    mask: torch.Tensor  # bool, pixel centre covered by the mesh


@dataclass
class _Triangles:
    """Triangles that survived culling, set up for pixel enumeration."""

    origin: torch.Tensor  # [T] int64 flat index (view, vmin, umin) of the box's first pixel
    box_w: torch.Tensor  # [T] int64 bounding-box width in pixels
    count: torch.Tensor  # [T] int64 pixels in the bounding box
    coef: torch.Tensor  # [T, 9 or 12] barycentrics (and 1/z) at the box corner, d/du, d/dv
    face: torch.Tensor  # [T] int64 face index


def rasterize(
    verts_cam: torch.Tensor,
    faces: torch.Tensor,
    K: torch.Tensor,  # noqa: N803
    height: int,
    width: int,
    z_near: float = 0.01,
) -> Raster:
    """Depth, face id and silhouette of meshes seen by pinhole cameras.

    Args:
        verts_cam: [B, V, 3] vertices in each view's camera (OpenCV optical) frame, metres.
        faces: [F, 3] vertex indices (int64), shared by all views.
        K: [3, 3] or [B, 3, 3] camera matrices (pixels).
        height, width: image size in pixels.
        z_near: triangles with a vertex at z < z_near (metres) are culled.

    Raises:
        CameraError: bad image size / z_near, or every vertex of a view is at z <= 0.
    """
    verts_cam, faces, K = _check_inputs(verts_cam, faces, K, height, width, z_near)
    B = verts_cam.shape[0]
    device = verts_cam.device
    buffer = torch.full((B * height * width,), _EMPTY_KEY, dtype=torch.int64, device=device)
    for tris in _triangle_chunks(verts_cam, faces, K, height, width, z_near, with_depth=True):
        for t, du, dv in _pair_chunks(tris.count, tris.box_w):
            c = tris.coef[t]
            lam = c[:, 0:3] + c[:, 3:6] * du[:, None] + c[:, 6:9] * dv[:, None]
            inside = (lam >= 0).all(dim=1)
            t, du, dv, c = t[inside], du[inside], dv[inside], c[inside]
            inv_z = c[:, 9] + c[:, 10] * du + c[:, 11] * dv
            z = (1.0 / inv_z.clamp_min(1e-30)).to(torch.float32)  # > 0: keys order by depth
            key = (z.view(torch.int32).to(torch.int64) << 32) | tris.face[t]
            pix = tris.origin[t] + dv.to(torch.int64) * width + du.to(torch.int64)
            buffer.scatter_reduce_(0, pix, key, reduce="amin")
    buffer = buffer.view(B, height, width)
    mask = buffer != _EMPTY_KEY
    depth = (buffer >> 32).to(torch.int32).view(torch.float32)
    depth = torch.where(mask, depth, torch.full_like(depth, float("inf")))
    face_id = torch.where(mask, buffer & 0xFFFFFFFF, torch.full_like(buffer, -1))
    return Raster(depth=depth, face_id=face_id, mask=mask)


def render_hard(
    verts_cam: torch.Tensor,
    faces: torch.Tensor,
    K: torch.Tensor,  # noqa: N803
    height: int,
    width: int,
    z_near: float = 0.01,
) -> torch.Tensor:
    """Silhouette [B, H, W] bool only (no depth test); same inputs and rule as :func:`rasterize`."""
    verts_cam, faces, K = _check_inputs(verts_cam, faces, K, height, width, z_near)
    B = verts_cam.shape[0]
    mask = torch.zeros(B * height * width, dtype=torch.bool, device=verts_cam.device)
    for tris in _triangle_chunks(verts_cam, faces, K, height, width, z_near, with_depth=False):
        for t, du, dv in _pair_chunks(tris.count, tris.box_w):
            c = tris.coef[t]
            lam = c[:, 0:3] + c[:, 3:6] * du[:, None] + c[:, 6:9] * dv[:, None]
            inside = (lam >= 0).all(dim=1)
            pix = tris.origin[t[inside]] + dv[inside].to(torch.int64) * width
            mask[pix + du[inside].to(torch.int64)] = True
    return mask.view(B, height, width)


def _check_inputs(
    verts_cam: torch.Tensor,
    faces: torch.Tensor,
    K: torch.Tensor,  # noqa: N803
    height: int,
    width: int,
    z_near: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    if int(height) != height or int(width) != width or height <= 0 or width <= 0:
        raise CameraError(f"image size must be positive integers, got {width}x{height}")
    if not z_near > 0:
        raise CameraError(f"z_near must be positive, got {z_near}")
    if verts_cam.dim() != 3 or verts_cam.shape[-1] != 3:
        raise ValueError(f"verts_cam must be [B, V, 3], got {tuple(verts_cam.shape)}")
    verts_cam = verts_cam.detach()  # hard rasterisation has no gradient
    if not verts_cam.is_floating_point():
        verts_cam = verts_cam.float()
    faces = torch.as_tensor(faces, device=verts_cam.device).to(torch.int64)
    if faces.dim() != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must be [F, 3], got {tuple(faces.shape)}")
    V = verts_cam.shape[1]
    if faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= V):
        raise ValueError(f"faces index vertices outside [0, {V})")
    K = torch.as_tensor(K, dtype=verts_cam.dtype, device=verts_cam.device)
    if K.shape == (3, 3):
        K = K.expand(verts_cam.shape[0], 3, 3)
    if K.shape != (verts_cam.shape[0], 3, 3):
        raise ValueError(f"K must be [3, 3] or [B, 3, 3], got {tuple(K.shape)}")
    if V:
        in_front = (verts_cam[..., 2] > 0).any(dim=1)
        if not bool(in_front.all()):
            view = int((~in_front).nonzero()[0, 0])
            raise CameraError(f"robot entirely behind the camera in view {view} (all z <= 0)")
    return verts_cam, faces, K


def _triangle_chunks(
    verts_cam: torch.Tensor,
    faces: torch.Tensor,
    K: torch.Tensor,  # noqa: N803
    height: int,
    width: int,
    z_near: float,
    with_depth: bool,
) -> Iterator[_Triangles]:
    """Set up the triangles of groups of views, at most :data:`TRIANGLE_CHUNK` at a time."""
    B, F = verts_cam.shape[0], faces.shape[0]
    if F == 0:
        return
    corners = faces.T.reshape(-1)  # corner-major: all first corners, then second, third
    views = max(1, TRIANGLE_CHUNK // F)
    for b0 in range(0, B, views):
        b1 = min(B, b0 + views)
        v = verts_cam[b0:b1]
        uvz = torch.cat([project(v, K[b0:b1]), v[..., 2:3]], dim=-1)  # [b, V, 3]
        tris = _setup(uvz, faces, corners, b0, height, width, z_near, with_depth)
        if tris is not None:
            yield tris


def _setup(
    uvz: torch.Tensor,
    faces: torch.Tensor,
    corners: torch.Tensor,
    first_view: int,
    height: int,
    width: int,
    z_near: float,
    with_depth: bool,
) -> _Triangles | None:
    """Cull the triangles of views ``uvz`` [b, V, (u, v, z)] and express their barycentrics
    (and 1/z) as affine maps of the pixel offset from their bounding box's first pixel centre.

    Culling works on small integers: per vertex, the pixel-centre bounds ceil/floor of u and v
    (clamped to [-1, size], which keeps every decision) and, if any vertex is nearer than
    z_near, a flag z >= z_near; a triangle survives iff min ceil <= max floor on both axes
    inside the image and all its flags are set.
    """
    nb, V, _ = uvz.shape
    F = faces.shape[0]
    small = torch.int16 if max(height, width) < 32000 else torch.int32
    u, v = uvz[..., 0].nan_to_num(-1.0), uvz[..., 1].nan_to_num(-1.0)
    good = uvz[..., 2] >= z_near
    bounds = [torch.ceil(u).clamp_(-1, width), torch.ceil(v).clamp_(-1, height)]
    bounds += [torch.floor(u).clamp_(-1, width), torch.floor(v).clamp_(-1, height)]
    if not bool(good.all()):  # the flag needs a channel of its own (min over the corners)
        bounds.append(good.to(uvz.dtype))
    rounded = torch.stack(bounds, dim=1).to(small)  # [b, 4 or 5, V]
    nc = rounded.shape[1]
    tri = rounded.view(nb * nc, V).index_select(1, corners).view(nb, nc, 3, F)
    lo = torch.minimum(torch.minimum(tri[:, :2, 0], tri[:, :2, 1]), tri[:, :2, 2])  # [b, 2, F]
    hi = torch.maximum(torch.maximum(tri[:, 2:4, 0], tri[:, 2:4, 1]), tri[:, 2:4, 2])
    keep = lo[:, 0].clamp_min(0) <= hi[:, 0].clamp_max(width - 1)
    keep &= lo[:, 1].clamp_min(0) <= hi[:, 1].clamp_max(height - 1)
    if nc == 5:
        keep &= torch.minimum(torch.minimum(tri[:, 4, 0], tri[:, 4, 1]), tri[:, 4, 2]) > 0
    idx = keep.view(-1).nonzero().squeeze(1)
    if idx.numel() == 0:
        return None
    b, f = torch.div(idx, F, rounding_mode="floor"), idx % F
    box = b * 2 * F + f  # survivors' first (u, v) and last (u, v) pixel centres [T, 2]
    first = torch.stack([lo.view(-1)[box], lo.view(-1)[box + F]], dim=1).to(uvz.dtype)
    last = torch.stack([hi.view(-1)[box], hi.view(-1)[box + F]], dim=1).to(uvz.dtype)
    first.clamp_(min=0)
    last[:, 0].clamp_(max=width - 1)
    last[:, 1].clamp_(max=height - 1)
    p = uvz.reshape(nb * V, 3)[(b * V)[:, None] + faces[f]].transpose(1, 2)  # [T, uvz, corner]
    x0, x1, x2 = p[:, 0].unbind(1)
    y0, y1, y2 = p[:, 1].unbind(1)
    area2 = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)  # twice the signed area
    sel = (area2.abs() > 1e-9).nonzero().squeeze(1)
    if sel.numel() < area2.numel():
        x0, x1, x2, y0, y1, y2, area2 = (a[sel] for a in (x0, x1, x2, y0, y1, y2, area2))
        b, f, first, last, p = b[sel], f[sel], first[sel], last[sel], p[sel]
    # Edge function opposite vertex i over the edge j -> k, (i, j, k) cyclic:
    # E_i(u, v) = (x_k - x_j)(v - y_j) - (y_k - y_j)(u - x_j); barycentric l_i = E_i / (2·area).
    xj, yj = torch.stack([x1, x2, x0], dim=1), torch.stack([y1, y2, y0], dim=1)  # [T, 3]
    ex = torch.stack([x2 - x1, x0 - x2, x1 - x0], dim=1) / area2[:, None]
    ey = torch.stack([y2 - y1, y0 - y2, y1 - y0], dim=1) / area2[:, None]
    lam0 = ex * (first[:, 1:2] - yj) - ey * (first[:, 0:1] - xj)
    parts = [lam0, -ey, ex]
    if with_depth:
        inv_z = 1.0 / p[:, 2]  # 1/z is affine in screen space: sum_i l_i / z_i
        parts += [(c * inv_z).sum(dim=1, keepdim=True) for c in parts]
    coef = torch.cat(parts, dim=1).to(torch.float32)
    first, last = first.to(torch.int64), last.to(torch.int64)
    box_w = last[:, 0] - first[:, 0] + 1
    count = box_w * (last[:, 1] - first[:, 1] + 1)
    origin = ((b + first_view) * height + first[:, 1]) * width + first[:, 0]
    return _Triangles(origin, box_w, count, coef, f)


def _pair_chunks(
    count: torch.Tensor, box_w: torch.Tensor
) -> Iterator[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
    """Yield (triangle index, du, dv) over every pixel of every triangle's box, at most
    :data:`PAIR_CHUNK` pairs at a time (a larger box forms its own chunk); du, dv are float32."""
    cum = count.cumsum(0)
    starts = cum - count  # pair index of each triangle's first pixel
    T = count.numel()
    start, done = 0, 0
    while start < T:
        end = max(int(torch.searchsorted(cum, done + PAIR_CHUNK, right=True)), start + 1)
        cnt = count[start:end]
        total = int(cum[end - 1])
        t = torch.repeat_interleave(
            torch.arange(start, end, device=count.device), cnt, output_size=total - done
        )
        local = torch.arange(done, total, device=count.device) - starts[t]
        w = box_w[t]
        dv = torch.div(local, w, rounding_mode="floor")
        du = local - dv * w
        yield t, du.to(torch.float32), dv.to(torch.float32)
        done, start = total, end
