"""Hard z-buffer rasteriser of triangle meshes in batched torch (CPU or CUDA; not differentiable).

Coverage rule: pixel (u, v) is covered by a triangle iff its centre (integer coordinates, see
``docs/architecture.md``) lies inside or on the projected triangle, whatever its winding.
Triangles with any vertex closer than ``z_near`` are culled whole (no near-plane clipping).

Algorithm (scanline spans): project the vertices, cull triangles whose pixel-centre bounding box
is empty or off-image, and intersect every pixel row a triangle crosses with its three edges (in
the vertices' float dtype), which gives the span ``[ceil(left), floor(right)]`` of covered pixel
centres. :func:`render_hard` only marks span ends in a difference image and takes a cumulative
sum along the rows; :func:`rasterize` enumerates the pixels of the spans, evaluates 1/z (affine
in screen space) and resolves visibility with one ``scatter_reduce(amin)`` on a 64-bit key
packing the float32 depth above the face index (positive floats order like their bit patterns),
so the nearest surface wins and ties go to the lower face index. Both functions use the same
spans, so their silhouettes are identical.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import torch

from roboseg.camera import project
from roboseg.errors import CameraError

#: (triangle, row) spans or covered pixels handled at once; bounds the working memory.
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
    """Triangles that survived culling, set up for scanline spans (vertices' dtype, pixels)."""

    view: torch.Tensor  # [T] int64 view index in the whole batch
    face: torch.Tensor  # [T] int64 face index
    row0: torch.Tensor  # [T] int64 first pixel row (inside the image)
    rows: torch.Tensor  # [T] int64 number of pixel rows (>= 1)
    edges: torch.Tensor  # [T, 12] float, see :func:`_edge_table`
    depth: torch.Tensor | None  # [T, 5] (u0, v0, 1/z0, d(1/z)/du, d(1/z)/dv) or None


@dataclass
class _Spans:
    """Non-empty (triangle, row) spans of covered pixel centres ``u0 <= u <= u1``."""

    tri: torch.Tensor  # [S] int64 index into the chunk's triangles
    row: torch.Tensor  # [S] int64 pixel row v
    u0: torch.Tensor  # [S] int64 first covered column
    u1: torch.Tensor  # [S] int64 last covered column


def rasterize(
    verts_cam: torch.Tensor,
    faces: torch.Tensor,
    K: torch.Tensor,  # noqa: N803
    height: int,
    width: int,
    z_near: float = 0.01,
    cull_back_faces: bool = False,
) -> Raster:
    """Depth, face id and silhouette of meshes seen by pinhole cameras.

    Args:
        verts_cam: [B, V, 3] vertices in each view's camera (OpenCV optical) frame, metres.
        faces: [F, 3] vertex indices (int64), shared by all views.
        K: [3, 3] or [B, 3, 3] camera matrices (pixels).
        height, width: image size in pixels.
        z_near: triangles with a vertex at z < z_near (metres) are culled.
        cull_back_faces: skip, per view, the faces whose counter-clockwise (outward) normal
            points away from the camera. Exact only for closed meshes with outward winding,
            where a back face never decides a pixel; about halves the work.

    Raises:
        CameraError: bad image size / z_near, or every vertex of a view is at z <= 0.
    """
    verts_cam, faces, K = _check_inputs(verts_cam, faces, K, height, width, z_near)
    B = verts_cam.shape[0]
    device = verts_cam.device
    buffer = torch.full((B * height * width,), _EMPTY_KEY, dtype=torch.int64, device=device)
    for tris in _triangle_chunks(verts_cam, faces, K, height, width, z_near, True, cull_back_faces):
        assert tris.depth is not None
        for spans in _span_chunks(tris, width):
            # per span: flat index, 1/z at its first pixel and d(1/z)/du; face in the low word
            d = tris.depth.index_select(0, spans.tri)  # [S, 5]
            u0 = spans.u0.to(d.dtype)
            inv_z0 = d[:, 2] + d[:, 3] * (u0 - d[:, 0]) + d[:, 4] * (spans.row - d[:, 1])
            start = (tris.view.index_select(0, spans.tri) * height + spans.row) * width + spans.u0
            face = tris.face.index_select(0, spans.tri)
            for s, du in _pixel_chunks(spans.u1 - spans.u0 + 1):
                inv_z = inv_z0.index_select(0, s) + d[:, 3].index_select(0, s) * du
                z = (1.0 / inv_z.clamp_min(1e-30)).to(torch.float32)  # > 0: keys order by depth
                key = (z.view(torch.int32).to(torch.int64) << 32) | face.index_select(0, s)
                pix = start.index_select(0, s) + du
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
    cull_back_faces: bool = False,
) -> torch.Tensor:
    """Silhouette [B, H, W] bool only (no depth test); same inputs and rule as :func:`rasterize`.

    Every span adds +1 at its first column and -1 after its last one in a [B, H, W + 1]
    difference image; a pixel is covered iff the running sum along its row is positive.
    """
    verts_cam, faces, K = _check_inputs(verts_cam, faces, K, height, width, z_near)
    B = verts_cam.shape[0]
    stride = width + 1
    diff = torch.zeros(B * height * stride, dtype=torch.int32, device=verts_cam.device)
    for tris in _triangle_chunks(
        verts_cam, faces, K, height, width, z_near, False, cull_back_faces
    ):
        for spans in _span_chunks(tris, width):
            start = (tris.view.index_select(0, spans.tri) * height + spans.row) * stride + spans.u0
            ones = torch.ones_like(start, dtype=torch.int32)
            diff.index_add_(0, start, ones)
            diff.index_add_(0, start + (spans.u1 - spans.u0 + 1), -ones)
    covered = diff.view(B, height, stride).cumsum(dim=2, dtype=torch.int32)[..., :width] > 0
    return covered


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
    cull_back_faces: bool,
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
        tris = _setup(uvz, faces, corners, b0, height, width, z_near, with_depth, cull_back_faces)
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
    cull_back_faces: bool,
) -> _Triangles | None:
    """Cull the triangles of views ``uvz`` [b, V, (u, v, z)] and set up their edges.

    Culling works on small integers: per vertex, the pixel-centre bounds ceil/floor of u and v
    (clamped to [-1, size], which keeps every decision) and, if any vertex is nearer than
    z_near, a flag z >= z_near; a triangle survives iff min ceil <= max floor on both axes
    inside the image and all its flags are set. Degenerate triangles (|2·area| <= 1e-9 px²)
    are dropped, and with ``cull_back_faces`` those with positive image-space area: with every
    z > 0, sign(2·area) = sign(a · ((b - a) × (c - a))) for the camera-frame corners a, b, c.
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
    rounded = torch.stack(bounds, dim=-1).to(small)  # [b, V, 4 or 5]
    nc = rounded.shape[-1]
    tri = rounded.index_select(1, corners).view(nb, 3, F, nc)
    lo = torch.minimum(torch.minimum(tri[:, 0], tri[:, 1]), tri[:, 2])  # [b, F, nc]
    hi = torch.maximum(torch.maximum(tri[:, 0], tri[:, 1]), tri[:, 2])
    keep = lo[..., 0].clamp_min(0) <= hi[..., 2].clamp_max(width - 1)
    keep &= lo[..., 1].clamp_min(0) <= hi[..., 3].clamp_max(height - 1)
    if nc == 5:
        keep &= lo[..., 4] > 0
    idx = keep.view(-1).nonzero().squeeze(1)
    if idx.numel() == 0:
        return None
    b, f = torch.div(idx, F, rounding_mode="floor"), idx % F
    row0 = lo[..., 1].reshape(-1).index_select(0, idx).to(torch.int64).clamp_(min=0)
    row1 = hi[..., 3].reshape(-1).index_select(0, idx).to(torch.int64).clamp_(max=height - 1)
    T = idx.numel()
    vert = (b * V).repeat(3) + faces.index_select(0, f).T.reshape(-1)  # corner-major [3T]
    p = uvz.reshape(nb * V, 3).index_select(0, vert).T.reshape(3, 3, T)
    x, y = p[0], p[1]  # [corner, T]
    xj, yj = x.roll(-1, dims=0), y.roll(-1, dims=0)  # start of edge j -> k: 1 -> 2, 2 -> 0, 0 -> 1
    dx, dy = x.roll(-2, dims=0) - xj, y.roll(-2, dims=0) - yj  # [3, T]
    area2 = dx[2] * (y[2] - y[0]) - dy[2] * (x[2] - x[0])  # twice the signed area
    ok = area2.abs() > 1e-9
    if cull_back_faces:
        ok &= area2 < 0
    sel = ok.nonzero().squeeze(1)
    if sel.numel() == 0:
        return None
    if sel.numel() < 0.9 * T:  # drop many (back faces); give a few (degenerate) no rows
        b, f, row0, row1 = (a.index_select(0, sel) for a in (b, f, row0, row1))
        xj, yj, dx, dy, p = (a.index_select(-1, sel) for a in (xj, yj, dx, dy, p))
        area2 = area2.index_select(0, sel)
    elif sel.numel() < T:
        row1 = torch.where(ok, row1, row0 - 1)
    edges = _edge_table(xj, yj, dx, dy, area2, row0)
    depth = None
    if with_depth:
        # 1/z = sum_i l_i / z_i with barycentrics l_i = E_i / (2·area): affine in (u, v)
        w = 1.0 / (p[2] * area2)  # [3, T]
        d_du = -(dy * w).sum(dim=0)
        d_dv = (dx * w).sum(dim=0)
        depth = torch.stack([p[0, 0], p[1, 0], 1.0 / p[2, 0], d_du, d_dv], dim=1)
    return _Triangles(b + first_view, f, row0, row1 - row0 + 1, edges, depth)


def _span_chunks(tris: _Triangles, width: int) -> Iterator[_Spans]:
    """Non-empty spans of every row of every triangle, at most :data:`PAIR_CHUNK` rows at a
    time (a triangle with more rows forms its own chunk)."""
    for t, dv in _pixel_chunks(tris.rows):
        e = tris.edges.index_select(0, t)
        dv_f = dv.to(e.dtype)[:, None]
        left = (e[:, 0:3] + e[:, 3:6] * dv_f).amax(dim=1)
        right = (e[:, 6:9] + e[:, 9:12] * dv_f).amin(dim=1)
        row = tris.row0.index_select(0, t) + dv
        u0 = torch.ceil(left.clamp(-1.0, width)).to(torch.int64).clamp_(min=0)
        u1 = torch.floor(right.clamp(-1.0, width)).to(torch.int64).clamp_(max=width - 1)
        keep = (u0 <= u1).nonzero().squeeze(1)
        if keep.numel():
            yield _Spans(t[keep], row[keep], u0[keep], u1[keep])


def _edge_table(
    xj: torch.Tensor,
    yj: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    area2: torch.Tensor,
    row0: torch.Tensor,
) -> torch.Tensor:
    """[T, 12] per-triangle table of the bounds of the spans, in pixels: (left u at ``row0``
    [3], left du/dv [3], right u at ``row0`` [3], right du/dv [3]) of the edges j -> k starting
    at (xj, yj) [3, T] with extent (dx, dy) [3, T], so that a row ``row0 + dv`` spans
    ``max(left + dv·dleft) <= u <= min(right + dv·dright)``.

    A centre is inside edge j -> k iff E = dx·(v - yj) - dy·(u - xj) has the sign of the
    doubled area ``area2``: the edge's u at row v, xj + dx/dy·(v - yj), bounds the span on the
    left where dy·area2 < 0 and on the right where dy·area2 > 0. Horizontal edges bound no
    span (the rows already stop at the triangle's top and bottom); unused slots hold -inf on
    the left, +inf on the right, with slope 0.
    """
    flat = dy == 0
    slope = torch.where(flat, torch.zeros_like(dx), dx / torch.where(flat, 1.0, dy))
    start = xj + slope * (row0.to(xj.dtype) - yj)
    turn = dy * area2
    zero = torch.zeros_like(start)
    return torch.cat(
        [
            torch.where(turn < 0, start, -torch.inf),
            torch.where(turn < 0, slope, zero),
            torch.where(turn > 0, start, torch.inf),
            torch.where(turn > 0, slope, zero),
        ],
        dim=0,
    ).T.contiguous()


def _pixel_chunks(count: torch.Tensor) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
    """Yield (item index, offset within the item) over ``count[i]`` offsets of every item i,
    at most :data:`PAIR_CHUNK` at a time (a larger item forms its own chunk); int64."""
    cum = count.cumsum(0)
    starts = cum - count  # flat index of each item's first offset
    n = count.numel()
    start, done = 0, 0
    while start < n:
        end = max(int(torch.searchsorted(cum, done + PAIR_CHUNK, right=True)), start + 1)
        total = int(cum[end - 1])
        if total > done:
            i = torch.repeat_interleave(
                torch.arange(start, end, device=count.device),
                count[start:end],
                output_size=total - done,
            )
            yield i, torch.arange(done, total, device=count.device) - starts[i]
        done, start = total, end
