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

import sys
from collections.abc import Iterator
from dataclasses import dataclass

import torch

from roboseg.camera import project
from roboseg.errors import CameraError

#: (triangle, row) spans or covered pixels handled at once; bounds the working memory.
PAIR_CHUNK = 1 << 20
#: Triangles (views × faces) set up at once.
TRIANGLE_CHUNK = 1 << 20
#: Key of an empty pixel: +inf depth above face -1 (0xFFFFFFFF), larger than any surface's key.
_EMPTY_KEY = (0x7F800000 << 32) | 0xFFFFFFFF
_LOW, _HIGH = (0, 1) if sys.byteorder == "little" else (1, 0)  # int32 halves of an int64


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
    edges: torch.Tensor  # [12, T] float, see :func:`_edge_table`
    depth: torch.Tensor | None  # [5, T] (u0, v0, 1/z0, d(1/z)/du, d(1/z)/dv) or None
    first_view: int  # views first_view ... first_view + views - 1 are set up here
    views: int


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
            d = tris.depth.index_select(1, spans.tri)  # [5, S]
            u0 = spans.u0.to(d.dtype)
            inv_z0 = d[2] + d[3] * (u0 - d[0]) + d[4] * (spans.row - d[1])
            start = (tris.view.index_select(0, spans.tri) * height + spans.row) * width + spans.u0
            face = tris.face.index_select(0, spans.tri)
            for s, du in _pixel_chunks(spans.u1 - spans.u0 + 1):
                inv_z = inv_z0.index_select(0, s) + d[3].index_select(0, s) * du
                z = (1.0 / inv_z.clamp_min(1e-30)).to(torch.float32)  # > 0: keys order by depth
                key = (z.view(torch.int32).to(torch.int64) << 32) | face.index_select(0, s)
                pix = start.index_select(0, s) + du
                buffer.scatter_reduce_(0, pix, key, reduce="amin")
    # the high word of a key is the depth's float32 bits (+inf when empty), the low word the
    # face index (-1 when empty)
    halves = buffer.view(torch.int32).view(B, height, width, 2)
    depth = halves[..., _HIGH].view(torch.float32).contiguous()
    face_id = halves[..., _LOW].to(torch.int64)
    return Raster(depth=depth, face_id=face_id, mask=face_id >= 0)


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

    Every span adds +1 at its first column and -1 after its last one in a [B, rows, W + 1]
    difference image (the rows the triangles cross); a pixel is covered iff the running sum
    along its row is positive. The running sum is only taken inside the box of rows and
    columns the spans touch (outside it the difference image is zero), which is most of the
    work saved for small silhouettes.
    """
    verts_cam, faces, K = _check_inputs(verts_cam, faces, K, height, width, z_near)
    B = verts_cam.shape[0]
    stride = width + 1
    device = verts_cam.device
    covered = torch.zeros(B, height, width, dtype=torch.bool, device=device)
    for tris in _triangle_chunks(
        verts_cam, faces, K, height, width, z_near, False, cull_back_faces
    ):
        # the difference image of this chunk's views spans only the rows its triangles cross
        top, bottom = torch.stack([tris.row0.min(), (tris.row0 + tris.rows).max()]).tolist()
        rows = bottom - top
        diff = torch.zeros(tris.views, rows, stride, dtype=torch.int32, device=device)
        flat = diff.view(-1)
        lows, highs = [], []  # (row, column) bounds of the spans of each chunk
        for spans in _span_chunks(tris, width):
            view = tris.view.index_select(0, spans.tri) - tris.first_view
            start = (view * rows + spans.row - top) * stride + spans.u0
            ones = torch.ones_like(start, dtype=torch.int32)
            flat.index_add_(0, start, ones)
            flat.index_add_(0, start + (spans.u1 - spans.u0 + 1), -ones)
            lows.append(torch.stack([spans.row.min(), spans.u0.min()]))
            highs.append(torch.stack([spans.row.max(), spans.u1.max()]))
        if not lows:
            continue
        r0, c0 = torch.stack(lows).amin(dim=0).tolist()
        r1, c1 = torch.stack(highs).amax(dim=0).tolist()
        v0, v1 = tris.first_view, tris.first_view + tris.views
        block = diff[:, r0 - top : r1 - top + 1, c0 : c1 + 1]
        covered[v0:v1, r0 : r1 + 1, c0 : c1 + 1] = block.cumsum(dim=2, dtype=torch.int32) > 0
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
    corners = torch.stack(faces.unbind(1))  # [3, F] vertex of each face's first, second, third
    views = max(1, TRIANGLE_CHUNK // F)
    for b0 in range(0, B, views):
        b1 = min(B, b0 + views)
        v = verts_cam[b0:b1]
        uv = project(v, K[b0:b1]).movedim(-1, 0)  # [2, b, V]
        uvz = torch.cat([uv, v[..., 2].unsqueeze(0)])  # [3, b, V] rows u, v, z
        tris = _setup(uvz, corners, b0, height, width, z_near, with_depth, cull_back_faces)
        if tris is not None:
            yield tris


def _setup(
    uvz: torch.Tensor,
    corners: torch.Tensor,
    first_view: int,
    height: int,
    width: int,
    z_near: float,
    with_depth: bool,
    cull_back_faces: bool,
) -> _Triangles | None:
    """Cull the triangles ``corners`` [3, F] (vertex indices) of views ``uvz`` [(u, v, z), b, V]
    and set up their edges.

    A triangle survives iff its pixel-centre bounds ceil(min) <= floor(max) meet the image on
    both axes, all its corners have z >= z_near, and it is not degenerate (|2·area| <= 1e-9
    px²); with ``cull_back_faces`` also iff its image-space area is negative: with every
    z > 0, sign(2·area) = sign(a · ((b - a) × (c - a))) for the camera-frame corners a, b, c.
    Every decision is taken on all (view, face) pairs at once from per-corner coordinates
    gathered row-wise ([k, n] tensors gather fast along dim 1); survivors are compacted once.
    """
    _, nb, V = uvz.shape
    F = corners.shape[1]
    n = nb * F  # (view, face) pairs, view-major
    base = torch.arange(nb, device=uvz.device) * V
    vert = (corners[:, None, :] + base[None, :, None]).view(-1)  # [corner, view, face]
    x, y, z = uvz.reshape(3, nb * V).index_select(1, vert).view(3, 3, n).unbind(0)  # [corner, n]
    x0, x1, x2 = x.unbind(0)
    y0, y1, y2 = y.unbind(0)
    area2 = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)  # twice the signed area
    lo_v = torch.ceil(torch.minimum(torch.minimum(y0, y1), y2))
    hi_v = torch.floor(torch.maximum(torch.maximum(y0, y1), y2))
    lo_u = torch.ceil(torch.minimum(torch.minimum(x0, x1), x2))
    hi_u = torch.floor(torch.maximum(torch.maximum(x0, x1), x2))
    keep = lo_u.clamp_min(0) <= hi_u.clamp_max(width - 1)
    keep &= lo_v.clamp_min(0) <= hi_v.clamp_max(height - 1)
    keep &= area2.abs() > 1e-9
    keep &= (z >= z_near).all(dim=0)
    if cull_back_faces:
        keep &= area2 < 0
    idx = keep.nonzero().squeeze(1)
    if idx.numel() == 0:
        return None
    parts = [x, y, z] if with_depth else [x, y]
    table = torch.cat([*parts, area2[None], lo_v[None], hi_v[None]]).index_select(1, idx)
    x, y, z, (area2, lo_v, hi_v) = _split(table, 3 * len(parts))
    row0 = lo_v.clamp_(min=0).to(torch.int64)
    row1 = hi_v.clamp_(max=height - 1).to(torch.int64)
    b = torch.div(idx, F, rounding_mode="floor")
    f = idx - b * F
    xj, yj = x.roll(-1, dims=0), y.roll(-1, dims=0)  # start of edge j -> k: 1 -> 2, 2 -> 0, 0 -> 1
    dx, dy = x.roll(-2, dims=0) - xj, y.roll(-2, dims=0) - yj  # [3, T]
    edges = _edge_table(xj, yj, dx, dy, area2, row0)
    depth = None
    if with_depth:
        assert z is not None
        # 1/z = sum_i l_i / z_i with barycentrics l_i = E_i / (2·area): affine in (u, v)
        w = 1.0 / (z * area2)  # [3, T]
        d_du = -(dy * w).sum(dim=0)
        d_dv = (dx * w).sum(dim=0)
        depth = torch.stack([x[0], y[0], 1.0 / z[0], d_du, d_dv])
    return _Triangles(b + first_view, f, row0, row1 - row0 + 1, edges, depth, first_view, nb)


def _split(
    table: torch.Tensor, rows: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """(x [3, T], y [3, T], z [3, T] or None, [area2, lo_v, hi_v] [3, T]) of a compacted table
    whose first ``rows`` rows are x, y (and z), followed by area2, lo_v and hi_v."""
    x, y = table[0:3], table[3:6]
    z = table[6:9] if rows == 9 else None
    return x, y, z, table[rows:]


def _span_chunks(tris: _Triangles, width: int) -> Iterator[_Spans]:
    """Non-empty spans of every row of every triangle, at most :data:`PAIR_CHUNK` rows at a
    time (a triangle with more rows forms its own chunk)."""
    for t, dv in _pixel_chunks(tris.rows):
        e = tris.edges.index_select(1, t)  # [12, P]
        dv_f = dv.to(e.dtype)
        left = torch.maximum(
            torch.maximum(e[0] + e[3] * dv_f, e[1] + e[4] * dv_f), e[2] + e[5] * dv_f
        )
        right = torch.minimum(
            torch.minimum(e[6] + e[9] * dv_f, e[7] + e[10] * dv_f), e[8] + e[11] * dv_f
        )
        u0 = torch.ceil(left.clamp_(-1.0, width)).to(torch.int64).clamp_(min=0)
        u1 = torch.floor(right.clamp_(-1.0, width)).to(torch.int64).clamp_(max=width - 1)
        keep = (u0 <= u1).nonzero().squeeze(1)
        if keep.numel() == 0:
            continue
        if keep.numel() < t.numel():
            t, dv, u0, u1 = (a.index_select(0, keep) for a in (t, dv, u0, u1))
        yield _Spans(t, tris.row0.index_select(0, t) + dv, u0, u1)


def _edge_table(
    xj: torch.Tensor,
    yj: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    area2: torch.Tensor,
    row0: torch.Tensor,
) -> torch.Tensor:
    """[12, T] per-triangle table of the bounds of the spans, in pixels: (left u at ``row0``
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
    left, right = turn < 0, turn > 0
    zero = torch.zeros_like(start)
    return torch.cat(
        [
            torch.where(left, start, -torch.inf),
            torch.where(left, slope, zero),
            torch.where(right, start, torch.inf),
            torch.where(right, slope, zero),
        ],
        dim=0,
    )


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
