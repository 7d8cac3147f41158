"""Hard z-buffer rasteriser of triangle meshes in batched torch (CPU or CUDA; not differentiable).

Coverage rule: pixel (u, v) is covered by a triangle iff its centre (integer coordinates, see
``docs/architecture.md``) lies inside or on the projected triangle, whatever its winding.
Triangles with any vertex closer than ``z_near`` are culled whole (no near-plane clipping).

Algorithm (scanline spans): project the vertices, cull triangles whose pixel-centre bounding box
is empty or off-image, and intersect every pixel row a triangle crosses with its three edges (in
the vertices' float dtype), which gives the span ``[ceil(left), floor(right)]`` of covered pixel
centres. The first rows of all triangles are intersected level by level over the whole edge
table (most triangles of a detailed mesh cover one to three rows), the other rows as gathered
(triangle, row) pairs. :func:`render_hard` only marks span ends in a difference image and takes
a cumulative sum along the rows; :func:`rasterize` enumerates the pixels of the spans, evaluates
1/z (affine in screen space) and resolves visibility with one ``scatter_reduce(amin)`` on a
64-bit key packing the float32 depth above the face index (positive floats order like their bit
patterns), so the nearest surface wins and ties go to the lower face index. Both functions use
the same spans, so their silhouettes are identical.
"""

from __future__ import annotations

import math
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
    face: torch.Tensor | None  # [T] int64 face index (with depth only)
    row0: torch.Tensor  # [T] int64 first pixel row (inside the image)
    rows: torch.Tensor  # [T] int64 number of pixel rows (>= 1)
    edges: torch.Tensor  # [12, T] float, see :func:`_edge_table`
    finite: bool  # every start and slope of ``edges`` is finite (unused slots aside)
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
        assert tris.depth is not None and tris.face is not None
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
    along its row is positive. Empty spans (and the rows a triangle does not have, see
    :func:`_span_bounds`) add their +1 and -1 at the same place, so no span is filtered out.
    The running sum is only taken inside the box of rows and columns the spans touch (outside
    it the difference image is zero), which is most of the work saved for small silhouettes.
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
        diff = torch.zeros(tris.views * rows * stride, dtype=torch.int32, device=device)
        # flat index of column 0 of each triangle's first row
        first = ((tris.view - tris.first_view) * rows + tris.row0 - top) * stride
        lows, highs = [], []  # column bounds of the spans of each block
        for b in _span_bounds(tris, width):
            at = first if b.tri is None else first.index_select(0, b.tri)
            at = at + b.dv * stride
            start = at + b.u0
            end = at + torch.maximum(b.u1 + 1, b.u0)
            if b.valid is not None:  # a row the triangle lacks: +1 and -1 both at 0
                start.mul_(b.valid)
                end.mul_(b.valid)
            ones = torch.ones(start.shape, dtype=torch.int32, device=device)
            diff.index_add_(0, start, ones)
            diff.index_add_(0, end, ones.neg_())
            lows.append(b.u0.min())
            highs.append(b.u1.max())
        c0 = int(torch.stack(lows).min())
        c1 = int(torch.stack(highs).max())
        if c1 < c0:
            continue
        v0, v1 = tris.first_view, tris.first_view + tris.views
        block = diff.view(tris.views, rows, stride)[:, :, c0 : c1 + 1]
        covered[v0:v1, top:bottom, c0 : c1 + 1] = block.cumsum(dim=2, dtype=torch.int32) > 0
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
    corners = faces.t()  # [3, F] vertex of each face's first, second, third corner
    views = max(1, TRIANGLE_CHUNK // F)
    for b0 in range(0, B, views):
        b1 = min(B, b0 + views)
        v = verts_cam[b0:b1]
        uv = project(v, K[b0:b1]).movedim(-1, 0)  # [2, b, V]
        tris = _setup(
            uv, v[..., 2], corners, b0, height, width, z_near, with_depth, cull_back_faces
        )
        if tris is not None:
            yield tris


def _setup(
    uv: torch.Tensor,
    z: torch.Tensor,
    corners: torch.Tensor,
    first_view: int,
    height: int,
    width: int,
    z_near: float,
    with_depth: bool,
    cull_back_faces: bool,
) -> _Triangles | None:
    """Cull the triangles ``corners`` [3, F] (vertex indices) of views with projected vertices
    ``uv`` [(u, v), b, V] (pixels) and camera-frame depths ``z`` [b, V] (metres), and set up
    their edges.

    A triangle survives iff its pixel-centre bounds ceil(min) <= floor(max) meet the image on
    both axes, all its corners have z >= z_near, and it is not degenerate (|2·area| <= 1e-9
    px²); with ``cull_back_faces`` also iff its image-space area is negative: with every
    z > 0, sign(2·area) = sign(a · ((b - a) × (c - a))) for the camera-frame corners a, b, c.
    Every decision is taken on all (view, face) pairs at once from per-corner coordinates
    gathered row-wise into one table ([k, n] tensors gather fast along dim 1); survivors are
    compacted once. Depths are gathered per corner only for the z-buffer; the silhouette tests
    z >= z_near per vertex and gathers the flags only when a vertex fails it.
    """
    _, nb, V = uv.shape
    F = corners.shape[1]
    n = nb * F  # (view, face) pairs, view-major
    base = torch.arange(nb, device=uv.device, dtype=corners.dtype) * V
    vert = torch.empty(3, nb, F, dtype=corners.dtype, device=uv.device)  # [corner, view, face]
    vert = torch.add(corners[:, None, :], base[None, :, None], out=vert).view(-1)
    k = 3 if with_depth else 2  # gathered coordinates: u, v (, z)
    coords = torch.cat([uv, z[None]]) if with_depth else uv
    # rows: u of corners 0-2, v of corners 0-2 (, z of corners 0-2), area2, lo_v, hi_v
    table = torch.empty(3 * k + 3, n, dtype=uv.dtype, device=uv.device)
    torch.index_select(coords.reshape(k, nb * V), 1, vert, out=table[: 3 * k].view(k, 3 * n))
    x0, x1, x2, y0, y1, y2 = table[:6].unbind(0)
    area2, lo_v, hi_v = table[3 * k :].unbind(0)
    torch.sub((x1 - x0) * (y2 - y0), (y1 - y0) * (x2 - x0), out=area2)  # twice the signed area
    torch.ceil(torch.minimum(torch.minimum(y0, y1), y2), out=lo_v)
    torch.floor(torch.maximum(torch.maximum(y0, y1), y2), out=hi_v)
    lo_u = torch.ceil(torch.minimum(torch.minimum(x0, x1), x2))
    hi_u = torch.floor(torch.maximum(torch.maximum(x0, x1), x2))
    keep = lo_u.clamp_min_(0) <= hi_u.clamp_max_(width - 1)
    keep &= lo_v.clamp_min_(0) <= hi_v.clamp_max_(height - 1)  # the rows, clamped to the image
    keep &= area2.abs() > 1e-9
    if with_depth:
        keep &= (table[6:9] >= z_near).all(dim=0)
    else:
        far = z >= z_near
        if not bool(far.all()):
            keep &= far.reshape(-1).index_select(0, vert).view(3, n).all(dim=0)
    if cull_back_faces:
        keep &= area2 < 0
    idx = keep.nonzero().squeeze(1)
    if idx.numel() == 0:
        return None
    table = table.index_select(1, idx)
    x, y = table[0:3], table[3:6]
    area2, lo_v, hi_v = table[3 * k :].unbind(0)
    row0 = lo_v.to(torch.int64)
    rows = hi_v.to(torch.int64) - row0 + 1
    view = _view_of(idx, F, nb)  # idx is sorted: views are runs
    dx, dy = _extents(x), _extents(y)
    edges, finite = _edge_table(x, y, dx, dy, area2, row0)
    face, depth = None, None
    if with_depth:
        z = table[6:9]
        face = idx - view * F
        # 1/z = sum_i l_i / z_i with barycentrics l_i = E_i / (2·area): affine in (u, v)
        w = 1.0 / (z * area2)  # [3, T]
        d_du = -(dy * w).sum(dim=0)
        d_dv = (dx * w).sum(dim=0)
        depth = torch.stack([x[0], y[0], 1.0 / z[0], d_du, d_dv])
    return _Triangles(view + first_view, face, row0, rows, edges, finite, depth, first_view, nb)


def _view_of(idx: torch.Tensor, faces: int, views: int) -> torch.Tensor:
    """View (0 ... ``views`` - 1) of each sorted view-major pair index ``idx`` (int64)."""
    if views == 1:
        return torch.zeros_like(idx)
    ends = torch.searchsorted(idx, torch.arange(1, views + 1, device=idx.device) * faces)
    counts = torch.diff(ends, prepend=ends.new_zeros(1))
    return torch.repeat_interleave(
        torch.arange(views, device=idx.device), counts, output_size=idx.numel()
    )


@dataclass
class _Bounds:
    """Span bounds ``u0 <= u <= u1`` (int64, empty where u0 > u1) of a block of (triangle, row)
    pairs: row ``row0 + dv`` of triangle ``tri`` (None: every triangle of the chunk, in order,
    with a scalar ``dv``), pairs with ``valid`` False (the triangle has no such row) ignored."""

    tri: torch.Tensor | None
    dv: int | torch.Tensor
    u0: torch.Tensor
    u1: torch.Tensor
    valid: torch.Tensor | None


#: At most this many row levels are evaluated for every triangle at once (see _span_bounds).
MAX_LEVELS = 8


def _span_bounds(tris: _Triangles, width: int) -> Iterator[_Bounds]:
    """Bounds of the spans of every row of every triangle.

    The first rows of all triangles are evaluated level by level over the whole edge table
    (level d: row ``row0 + d`` of every triangle; no gathers), as long as at least half of the
    triangles have that row; the remaining rows of the taller triangles are enumerated as
    (triangle, row) pairs, at most :data:`PAIR_CHUNK` at a time. Either way a row's bounds are
    ``max_j(left_j + d·dleft_j)`` and ``min_j(right_j + d·dright_j)`` (see
    :func:`_edge_table`), computed with the same float operations.
    """
    e, rows = tris.edges, tris.rows
    levels = _dense_levels(rows)
    for d in range(levels):
        if d == 0 and tris.finite:  # + finite slope·0 is + ±0: the same columns
            left = torch.maximum(torch.maximum(e[0], e[1]), e[2])
            right = torch.minimum(torch.minimum(e[6], e[7]), e[8])
        else:
            left = torch.maximum(
                torch.maximum(e[0] + e[3] * d, e[1] + e[4] * d), e[2] + e[5] * d
            )
            right = torch.minimum(
                torch.minimum(e[6] + e[9] * d, e[7] + e[10] * d), e[8] + e[11] * d
            )
        u0, u1 = _columns(left, right, width)
        yield _Bounds(None, d, u0, u1, None if d == 0 else rows > d)
    tall = (rows > levels).nonzero().squeeze(1)
    if tall.numel() == 0:
        return
    for i, off in _pixel_chunks(rows.index_select(0, tall) - levels):
        t = tall.index_select(0, i)
        et = e.index_select(1, t)  # [12, P]
        dv = off + levels
        dv_f = dv.to(et.dtype)
        left = torch.maximum(
            torch.maximum(et[0] + et[3] * dv_f, et[1] + et[4] * dv_f), et[2] + et[5] * dv_f
        )
        right = torch.minimum(
            torch.minimum(et[6] + et[9] * dv_f, et[7] + et[10] * dv_f), et[8] + et[11] * dv_f
        )
        u0, u1 = _columns(left, right, width)
        yield _Bounds(t, dv, u0, u1, None)


def _dense_levels(rows: torch.Tensor) -> int:
    """Row levels worth evaluating for every triangle: 1 + the levels d >= 1 that at least
    half of the triangles reach (``rows > d``), at most :data:`MAX_LEVELS`."""
    hist = torch.bincount(rows.clamp(max=MAX_LEVELS + 1), minlength=MAX_LEVELS + 2)
    taller = rows.numel() - hist.cumsum(0)  # taller[d]: triangles with rows > d
    return 1 + int((taller[1:MAX_LEVELS] * 2 >= rows.numel()).cumprod(0).sum())


def _columns(left: torch.Tensor, right: torch.Tensor, width: int) -> tuple[torch.Tensor, ...]:
    """First and last covered column (int64) of rows bounded by ``left <= u <= right``."""
    u0 = torch.ceil(left.clamp_(-1.0, width)).to(torch.int64).clamp_(min=0)
    u1 = torch.floor(right.clamp_(-1.0, width)).to(torch.int64).clamp_(max=width - 1)
    return u0, u1


def _span_chunks(tris: _Triangles, width: int) -> Iterator[_Spans]:
    """Non-empty spans of every row of every triangle (:func:`_span_bounds`, compacted)."""
    for b in _span_bounds(tris, width):
        ok = b.u0 <= b.u1
        if b.valid is not None:
            ok &= b.valid
        keep = ok.nonzero().squeeze(1)
        if keep.numel() == 0:
            continue
        t = keep if b.tri is None else b.tri.index_select(0, keep)
        dv = b.dv if isinstance(b.dv, int) else b.dv.index_select(0, keep)
        u0, u1 = b.u0.index_select(0, keep), b.u1.index_select(0, keep)
        yield _Spans(t, tris.row0.index_select(0, t) + dv, u0, u1)


def _extents(c: torch.Tensor) -> torch.Tensor:
    """[3, T] extents c_k - c_j of the edges j -> k (1 -> 2, 2 -> 0, 0 -> 1) of corner
    coordinates ``c`` [3, T]."""
    out = torch.empty_like(c)
    for j, (a, b) in enumerate(((1, 2), (2, 0), (0, 1))):
        torch.sub(c[b], c[a], out=out[j])
    return out


def _edge_table(
    x: torch.Tensor,
    y: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    area2: torch.Tensor,
    row0: torch.Tensor,
) -> tuple[torch.Tensor, bool]:
    """[12, T] per-triangle table of the bounds of the spans, in pixels: (left u at ``row0``
    [3], left du/dv [3], right u at ``row0`` [3], right du/dv [3]) of the edges j -> k
    (1 -> 2, 2 -> 0, 0 -> 1) of the corners (x, y) [3, T], starting at (xj, yj) with extent
    (dx, dy) [3, T] (:func:`_extents`), so that a row ``row0 + dv`` spans
    ``max(left + dv·dleft) <= u <= min(right + dv·dright)``.

    A centre is inside edge j -> k iff E = dx·(v - yj) - dy·(u - xj) has the sign of the
    doubled area ``area2``: the edge's u at row v, xj + dx/dy·(v - yj), bounds the span on the
    left where dy·area2 < 0 and on the right where dy·area2 > 0. Horizontal edges bound no
    span (the rows already stop at the triangle's top and bottom); unused slots hold -inf on
    the left, +inf on the right, with slope 0.

    The slots are filled without data-dependent branches (``torch.where`` on a random mask
    costs a mispredicted branch per element) from the signs of dy and dy·area2: with finite
    starts, slopes and areas, ``min(start, ±inf)`` and ``slope·flag`` (flag 1.0 or 0.0) give the
    same values as selecting them (an unused slope may be -0 instead of 0, which leaves -inf /
    +inf unchanged). Non-finite values, which only arise from non-finite, huge or nearly
    coincident vertices, take the selecting path; the second value says which path was taken
    (True: every start and slope is finite).
    """
    sloped = torch.sign(dy).abs_()  # 1.0 on edges with dy != 0, 0.0 on horizontal ones
    slope = dx / (dy + (1.0 - sloped))  # dy + 0 is dy; dy + 1 on horizontal edges
    slope.mul_(sloped)  # ±0 on horizontal edges
    start = _starts(x, y, slope, row0)
    turn = dy * area2
    table = torch.empty((12, *start.shape[1:]), dtype=start.dtype, device=start.device)
    # a sum is finite iff every term is (or, rarely, it overflows: then the selecting path)
    if all(math.isfinite(float(t.sum())) for t in (start, slope, area2)):
        inf = torch.tensor(torch.inf, dtype=start.dtype, device=start.device)
        right = torch.sign(turn)  # -1 left edge, +1 right edge, 0 neither
        left = torch.neg(right).clamp_(min=0.0)  # 1.0 on left edges, 0.0 elsewhere
        right.clamp_(min=0.0)  # 1.0 on right edges, 0.0 elsewhere
        torch.minimum(start, torch.copysign(inf, left - 0.5), out=table[0:3])  # else -inf
        torch.mul(slope, left, out=table[3:6])
        torch.maximum(start, torch.copysign(inf, 0.5 - right), out=table[6:9])  # else +inf
        torch.mul(slope, right, out=table[9:12])
        return table, True
    flat = dy == 0
    slope = torch.where(flat, torch.zeros_like(dx), dx / torch.where(flat, 1.0, dy))
    start = _starts(x, y, slope, row0)
    on_left, on_right = turn < 0, turn > 0
    zero = torch.zeros_like(start)
    torch.cat(
        [
            torch.where(on_left, start, -torch.inf),
            torch.where(on_left, slope, zero),
            torch.where(on_right, start, torch.inf),
            torch.where(on_right, slope, zero),
        ],
        dim=0,
        out=table,
    )
    return table, False


def _starts(
    x: torch.Tensor, y: torch.Tensor, slope: torch.Tensor, row0: torch.Tensor
) -> torch.Tensor:
    """[3, T] u of the edges j -> k (1 -> 2, 2 -> 0, 0 -> 1) at row ``row0``:
    xj + slope·(row0 - yj)."""
    r = row0.to(x.dtype)
    out = torch.empty_like(slope)
    for k, j in enumerate((1, 2, 0)):
        torch.add(x[j], slope[k] * (r - y[j]), out=out[k])
    return out


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
