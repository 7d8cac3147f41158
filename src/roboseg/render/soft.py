"""Differentiable silhouettes: the hard raster plus antialiased contour edges.

The forward value of :func:`render_soft` is the hard silhouette (pixel centre covered or not);
only pixels next to the silhouette boundary change, and only they carry gradient. For every pair
of 4-neighbouring pixels whose hard values differ, the contour edge of the mesh that crosses the
segment between the two pixel centres is found; its crossing position ``d`` (0 at the outside
pixel's centre, 1 at the inside pixel's centre) is a differentiable function of the edge's two
projected vertices. The pair is blended linearly:

* outside pixel: ``+ max(1/2 - d, 0)`` (the surface reaches past the midpoint into its half),
* inside pixel: ``- max(d - 1/2, 0)`` (the background reaches past the midpoint into its half),

so the soft value is continuous and piecewise linear in the vertex positions, thresholding it at
1/2 gives back the hard mask, and the boundary coverage moves linearly with the edge. As in
nvdiffrast's antialiasing, mostly-vertical edges blend horizontal pixel pairs and mostly-
horizontal edges vertical pairs; edges within a band around 45° blend both, with weights that
ramp linearly with the edge direction, so the image does not jump when an edge turns through 45°.
When several contour edges cross one pair, the one nearest the outside pixel (the first entry
into the surface) is used.

Contour edges of a view are edges whose (up to) two adjacent triangles lie on the same side of
the projected edge (one front-, one back-facing), plus open edges. This test uses the projected
2D geometry only, so it does not depend on the mesh's winding order.

Conventions: vertices are in the OpenCV optical frame of the camera (metres, z forward); pixel
``(u, v)`` is column ``u``, row ``v`` and integer coordinates are pixel centres.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal, Protocol

import torch
from torch import Tensor

from roboseg.camera import project
from roboseg.errors import CameraError, RobotModelError
from roboseg.render.raster import render_hard

logger = logging.getLogger(__name__)

Z_NEAR = 0.01
"""Default near plane (metres): vertices closer than this are not projected."""

INSIDE_MIN = 0.5 + 2.0**-10
"""Lowest soft value of a covered pixel (one thin enough to lose more than half to its
neighbours), so that ``soft > 0.5`` is exactly the hard silhouette."""

DIAGONAL_BAND = 0.1
"""Half-width, in ``|dv| / (|du| + |dv|)``, of the band around 45° where an edge blends both
horizontal and vertical pixel pairs (see :func:`row_pair_weight`)."""

Backend = Literal["auto", "torch", "nvdiffrast"]


class _HasMask(Protocol):
    mask: Tensor


@dataclass(frozen=True)
class MeshEdges:
    """Edge topology of a triangle mesh, computed once per mesh.

    Attributes:
        edges: ``[E, 2]`` long, vertex ids of each undirected edge (``edges[:, 0] < edges[:, 1]``).
        opposite: ``[E, 2]`` long, the third vertex of the first two adjacent triangles;
            ``opposite[:, 1] == -1`` for open (boundary) edges.
        open: ``[E]`` bool, edges with exactly one adjacent triangle.
    """

    edges: Tensor
    opposite: Tensor
    open: Tensor

    def to(self, device: torch.device | str) -> MeshEdges:
        """The same topology on ``device``."""
        return MeshEdges(self.edges.to(device), self.opposite.to(device), self.open.to(device))


def mesh_edges(faces: Tensor) -> MeshEdges:
    """Undirected edges of ``faces`` ``[F, 3]`` with the opposite vertex of each adjacent face.

    Edges shared by more than two triangles (non-manifold) keep their first two triangles.
    """
    faces = _check_faces(faces)
    f = faces.shape[0]
    a = faces[:, [0, 1, 2]].reshape(-1)
    b = faces[:, [1, 2, 0]].reshape(-1)
    opp = faces[:, [2, 0, 1]].reshape(-1)
    lo, hi = torch.minimum(a, b), torch.maximum(a, b)
    n_vert = int(faces.max().item()) + 1 if f else 1
    key = lo * n_vert + hi
    key_sorted, order = torch.sort(key, stable=True)
    unique, counts = torch.unique_consecutive(key_sorted, return_counts=True)
    first = torch.cumsum(counts, 0) - counts  # position of each edge's first half-edge
    opposite = torch.full((unique.shape[0], 2), -1, dtype=torch.long, device=faces.device)
    opposite[:, 0] = opp[order[first]]
    has_two = counts >= 2
    opposite[has_two, 1] = opp[order[first[has_two] + 1]]
    edges = torch.stack([unique // n_vert, unique % n_vert], dim=1)
    n_nonmanifold = int((counts > 2).sum())
    if n_nonmanifold:
        logger.debug("%d non-manifold edges keep only two adjacent triangles", n_nonmanifold)
    return MeshEdges(edges=edges, opposite=opposite, open=counts == 1)


def project_valid(verts_cam: Tensor, K: Tensor, z_near: float = Z_NEAR) -> tuple[Tensor, Tensor]:
    """Pixel coordinates of camera-frame points, with a gradient-safe near plane.

    Args:
        verts_cam: ``[B, V, 3]`` points in the OpenCV optical frame (metres).
        K: ``[3, 3]`` or ``[B, 3, 3]`` intrinsics (pixels).
        z_near: points with ``z < z_near`` are invalid; they project to the principal point and
            get zero gradient (no inf/nan in the backward pass).

    Returns:
        ``uv`` ``[B, V, 2]`` (column, row; pixel centres at integers) and ``valid`` ``[B, V]``.
    """
    valid = verts_cam[..., 2] >= z_near
    on_axis = torch.tensor([0.0, 0.0, 1.0], dtype=verts_cam.dtype, device=verts_cam.device)
    safe = torch.where(valid[..., None], verts_cam, on_axis)
    return project(safe, K), valid


def _cross2(a: Tensor, b: Tensor) -> Tensor:
    """z component of the 2D cross product ``a × b`` over the last dimension."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def contour_edges(uv: Tensor, valid: Tensor, topo: MeshEdges) -> tuple[Tensor, Tensor]:
    """Contour edges of each view and the side of each edge the surface lies on.

    Args:
        uv: ``[B, V, 2]`` projected vertices (pixels).
        valid: ``[B, V]`` vertices in front of the near plane.
        topo: the mesh's :class:`MeshEdges`.

    Returns:
        ``is_contour`` ``[B, E]`` bool and ``side`` ``[B, E]`` in {-1, 0, +1}: the sign of
        ``cross(p1 - p0, q - p0)`` for the points ``q`` of the adjacent triangle(s) near the edge.
    """
    e0, e1 = topo.edges[:, 0], topo.edges[:, 1]
    o0, o1 = topo.opposite[:, 0], topo.opposite[:, 1].clamp(min=0)
    p0, p1 = uv.index_select(1, e0), uv.index_select(1, e1)
    d = p1 - p0
    s0 = torch.sign(_cross2(d, uv.index_select(1, o0) - p0))
    s1 = torch.sign(_cross2(d, uv.index_select(1, o1) - p0))
    ok = d.abs().amax(dim=-1) > 0
    if not bool(valid.all()):  # skip four gathers in the common case
        ok = ok & valid.index_select(1, e0) & valid.index_select(1, e1)
        ok = ok & valid.index_select(1, o0) & (topo.open | valid.index_select(1, o1))
    is_contour = ok & (s0 != 0) & (topo.open | (s0 == s1))
    return is_contour, s0


def row_pair_weight(direction: Tensor) -> Tensor:
    """Share of an edge's blending done on horizontal pixel pairs (crossings of pixel rows).

    ``direction`` ``[..., 2]`` is the projected edge ``p1 - p0`` (pixels). Mostly-vertical edges
    (``|dv| / (|du| + |dv|) >= 1/2 + DIAGONAL_BAND``) blend horizontal pairs only, mostly-
    horizontal ones vertical pairs only (the remainder, ``1 - weight``); in between the share
    ramps linearly so the soft image stays continuous when an edge turns through 45°.
    """
    du, dv = direction[..., 0].abs(), direction[..., 1].abs()
    ratio = dv / (du + dv).clamp(min=torch.finfo(direction.dtype).tiny)
    return ((ratio - 0.5) / (2 * DIAGONAL_BAND) + 0.5).clamp(0.0, 1.0)


@dataclass(frozen=True)
class _Crossings:
    """Crossings of candidate edges with pixel-centre lines (all detached, one row each)."""

    cand: Tensor  # index into the candidate edge list
    line: Tensor  # integer row (horizontal pairs) or column (vertical pairs)
    lower: Tensor  # the pair is (lower, lower + 1) along the other axis
    frac: Tensor  # crossing position minus ``lower``, in [0, 1)


def _crossings(p0: Tensor, p1: Tensor, axis: int, n_lines: int, n_across: int) -> _Crossings:
    """Where segments ``p0 → p1`` ``[N, 2]`` cross the integer lines ``coord[axis] = k``.

    ``axis = 1`` enumerates rows (crossings give horizontal pixel pairs), ``axis = 0`` columns.
    Only lines inside the image and pairs with both pixels inside the image are returned.
    """
    other = 1 - axis
    a_al, b_al = p0[:, axis], p1[:, axis]
    lo = torch.ceil(torch.minimum(a_al, b_al)).clamp(min=0)
    hi = torch.floor(torch.maximum(a_al, b_al)).clamp(max=n_lines - 1)
    count = (hi - lo + 1).clamp(min=0).long()
    count = torch.where((b_al - a_al).abs() > 0, count, torch.zeros_like(count))
    cand = torch.repeat_interleave(torch.arange(p0.shape[0], device=p0.device), count)
    start = torch.cumsum(count, 0) - count
    step = torch.arange(cand.shape[0], device=p0.device) - start[cand]
    line = lo.long()[cand] + step
    s = (line.to(p0.dtype) - a_al[cand]) / (b_al[cand] - a_al[cand])
    c = p0[cand, other] + s * (p1[cand, other] - p0[cand, other])
    lower = torch.floor(c)
    keep = (lower >= 0) & (lower <= n_across - 2)
    return _Crossings(cand[keep], line[keep], lower[keep].long(), (c - lower)[keep])


def _crossing_position(p0: Tensor, p1: Tensor, line: Tensor, axis: Tensor) -> Tensor:
    """Differentiable crossing coordinate of segments ``p0 → p1`` ``[N, 2]`` with integer lines.

    Row ``i`` crosses the line ``coord[axis[i]] = line[i]``; the result is the other coordinate.
    """
    along = axis[:, None]
    across = 1 - along
    a0, a1 = p0.gather(1, along).squeeze(1), p1.gather(1, along).squeeze(1)
    c0, c1 = p0.gather(1, across).squeeze(1), p1.gather(1, across).squeeze(1)
    return c0 + (line.to(p0.dtype) - a0) / (a1 - a0) * (c1 - c0)


@dataclass(frozen=True)
class _PairBlend:
    """Candidate (edge, pixel pair) blends of one pair orientation (detached, one row each)."""

    key: Tensor  # pixel pair id: 2·(first pixel's flat index) + (1 horizontal, 0 vertical)
    out_pix: Tensor  # flat index of the outside pixel
    in_pix: Tensor  # flat index of the inside pixel
    d_out: Tensor  # crossing distance from the outside pixel's centre, [0, 1]
    cand: Tensor  # index into the view's contour edge list
    line: Tensor  # pixel row (horizontal pairs) or column (vertical pairs) crossed
    lower: Tensor  # the pair's first pixel along the other axis

    @staticmethod
    def cat(parts: list[_PairBlend]) -> _PairBlend:
        return _PairBlend(*(torch.cat([getattr(p, f) for p in parts]) for f in _PAIR_FIELDS))

    def take(self, rows: Tensor) -> _PairBlend:
        return _PairBlend(*(getattr(self, f)[rows] for f in _PAIR_FIELDS))


_PAIR_FIELDS = ("key", "out_pix", "in_pix", "d_out", "cand", "line", "lower")


def _pair_blends(
    mask: Tensor, q0: Tensor, q1: Tensor, view: Tensor, side: Tensor, sel: Tensor, axis: int
) -> _PairBlend:
    """Boundary pixel pairs crossed by the contour edges ``sel`` (``q0 → q1``, pixels).

    ``axis = 1`` crosses pixel rows (horizontal pairs), ``axis = 0`` columns (vertical pairs).
    A crossing counts when the pair's hard values differ and the inside pixel lies on the
    edge's surface ``side``.
    """
    _, height, width = mask.shape
    n_lines, n_across = (height, width) if axis == 1 else (width, height)
    cr = _crossings(q0[sel], q1[sel], axis, n_lines, n_across)
    cand = sel[cr.cand]
    if axis == 1:
        pix0 = (view[cand] * height + cr.line) * width + cr.lower
        pix1 = pix0 + 1
    else:
        pix0 = (view[cand] * height + cr.lower) * width + cr.line
        pix1 = pix0 + width
    flat = mask.reshape(-1)
    first_inside = flat[pix0]
    lower = cr.lower.to(q0.dtype)
    across_in = torch.where(first_inside, lower, lower + 1)
    line = cr.line.to(q0.dtype)
    p_in = torch.stack([across_in, line] if axis == 1 else [line, across_in], 1)
    side_in = torch.sign(_cross2(q1[cand] - q0[cand], p_in - q0[cand]))
    keep = (first_inside != flat[pix1]) & (side_in == side[cand])
    first_inside, pix0, pix1, frac = first_inside[keep], pix0[keep], pix1[keep], cr.frac[keep]
    return _PairBlend(
        key=pix0 * 2 + axis,
        out_pix=torch.where(first_inside, pix1, pix0),
        in_pix=torch.where(first_inside, pix0, pix1),
        d_out=torch.where(first_inside, 1 - frac, frac),
        cand=cand[keep],
        line=cr.line[keep],
        lower=cr.lower[keep],
    )


def _first_entry(key: Tensor, d_out: Tensor) -> Tensor:
    """Rows to keep: per ``key``, the one with the smallest ``d_out`` (ties: the last row)."""
    unique, group = torch.unique(key, return_inverse=True)
    n = unique.shape[0]
    best = torch.full((n,), 2.0, dtype=d_out.dtype, device=d_out.device)
    best = best.scatter_reduce(0, group, d_out, reduce="amin")
    winner = d_out == best[group]
    row = torch.arange(key.shape[0], device=key.device)
    pick = torch.full((n,), -1, dtype=torch.long, device=key.device)
    pick = pick.scatter_reduce(0, group[winner], row[winner], reduce="amax")
    return row[winner & (pick[group] == row)]


def antialias_silhouette(mask: Tensor, uv: Tensor, valid: Tensor, topo: MeshEdges) -> Tensor:
    """Soft silhouette from a hard ``mask`` ``[B, H, W]`` and projected vertices ``uv``.

    Differentiable w.r.t. ``uv`` ``[B, V, 2]`` (pixels). See the module docstring for the method.
    """
    bsz, height, width = mask.shape
    with torch.no_grad():
        is_contour, side = contour_edges(uv.detach(), valid, topo)
        view, edge = torch.nonzero(is_contour, as_tuple=True)
        q0 = uv.detach()[view, topo.edges[edge, 0]]
        q1 = uv.detach()[view, topo.edges[edge, 1]]
        w_rows = row_pair_weight(q1 - q0)
        parts = [
            _pair_blends(mask, q0, q1, view, side[view, edge], torch.nonzero(use)[:, 0], axis)
            for axis, use in ((1, w_rows > 0), (0, w_rows < 1))
        ]
        pairs = _PairBlend.cat(parts)
        pairs = pairs.take(_first_entry(pairs.key, pairs.d_out))
    # differentiable part: crossing positions and blend weights of the chosen edges
    axis = pairs.key % 2
    e, b = edge[pairs.cand], view[pairs.cand]
    p0, p1 = uv[b, topo.edges[e, 0]], uv[b, topo.edges[e, 1]]
    frac = _crossing_position(p0, p1, pairs.line, axis) - pairs.lower.to(uv.dtype)
    d = torch.where(pairs.out_pix < pairs.in_pix, frac, 1 - frac)
    w_rows = row_pair_weight(p1 - p0)
    weight = torch.where(axis == 1, w_rows, 1 - w_rows)
    # accumulate the pair blends on the boundary pixels only, then write them into the image
    pix, slot = torch.unique(torch.cat([pairs.out_pix, pairs.in_pix]), return_inverse=True)
    change = torch.cat([weight * torch.relu(0.5 - d), -weight * torch.relu(d - 0.5)])
    acc = torch.zeros(pix.shape[0], dtype=uv.dtype, device=uv.device).index_add(0, slot, change)
    inside = mask.reshape(-1)[pix]
    value = torch.where(inside, (1 + acc).clamp(INSIDE_MIN, 1.0), acc.clamp(0.0, 0.5))
    soft = mask.reshape(-1).to(uv.dtype).index_put((pix,), value)
    logger.debug("antialiased %d pixel pairs, %d pixels", pairs.key.shape[0], pix.shape[0])
    return soft.view(bsz, height, width)


def render_soft(
    verts_cam: Tensor,
    faces: Tensor,
    K: Tensor,
    height: int,
    width: int,
    *,
    edges: MeshEdges | None = None,
    raster: _HasMask | Tensor | None = None,
    z_near: float = Z_NEAR,
) -> Tensor:
    """Differentiable silhouettes ``[B, H, W]`` in [0, 1] of a mesh seen by pinhole cameras.

    Args:
        verts_cam: ``[B, V, 3]`` vertices in each camera's OpenCV optical frame (metres); may
            require grad (gradients reach them only through boundary pixels).
        faces: ``[F, 3]`` long vertex ids.
        K: ``[3, 3]`` or ``[B, 3, 3]`` intrinsics (pixels).
        height, width: image size (pixels).
        edges: the mesh's :func:`mesh_edges` (computed here when omitted).
        raster: a precomputed hard raster of the same views (an object with a ``mask``
            ``[B, H, W]`` bool attribute, or the mask itself); rasterised here when omitted.
        z_near: near plane (metres).

    Returns:
        Soft silhouettes whose values above 1/2 are exactly the hard silhouette.
    """
    _check_inputs(verts_cam, K, height, width)
    faces = _check_faces(faces, verts_cam.shape[1])
    if edges is None:
        edges = mesh_edges(faces)
    edges = edges.to(verts_cam.device)
    if raster is None:
        raster = render_hard(verts_cam.detach(), faces, K, height, width, z_near=z_near)
    mask = raster if isinstance(raster, Tensor) else raster.mask
    if mask.shape != (verts_cam.shape[0], height, width):
        raise CameraError(
            f"hard raster has shape {tuple(mask.shape)}, expected "
            f"{(verts_cam.shape[0], height, width)}"
        )
    uv, valid = project_valid(verts_cam, K.to(verts_cam.device), z_near)
    return antialias_silhouette(mask.to(torch.bool), uv, valid, edges)


def _check_inputs(verts_cam: Tensor, K: Tensor, height: int, width: int) -> None:
    """Raise :class:`CameraError` for malformed vertices, intrinsics or image size."""
    if verts_cam.dim() != 3 or verts_cam.shape[-1] != 3:
        raise CameraError(f"verts_cam must be [B, V, 3], got {tuple(verts_cam.shape)}")
    if K.shape not in ((3, 3), (verts_cam.shape[0], 3, 3)):
        raise CameraError(f"K must be [3, 3] or [B, 3, 3], got {tuple(K.shape)}")
    if height < 2 or width < 2:
        raise CameraError(f"image size must be at least 2x2, got {height}x{width}")


def _check_faces(faces: Tensor, n_verts: int | None = None) -> Tensor:
    """Faces as a long ``[F, 3]`` tensor; :class:`RobotModelError` when malformed."""
    if faces.dim() != 2 or faces.shape[1] != 3:
        raise RobotModelError(f"faces must be [F, 3], got {tuple(faces.shape)}")
    faces = faces.long()
    if faces.numel() and (
        int(faces.min()) < 0 or (n_verts is not None and int(faces.max()) >= n_verts)
    ):
        lo, hi = int(faces.min()), int(faces.max())
        raise RobotModelError(f"face vertex ids must lie in [0, {n_verts}), got {lo}..{hi}")
    return faces


class SilhouetteRenderer:
    """Hard and differentiable silhouettes of one mesh topology at one image size.

    The edge topology is computed once; per call only projection, contour classification and
    the boundary blending run. ``backend="auto"`` uses nvdiffrast for CUDA tensors when it is
    installed, the torch implementation otherwise.
    """

    def __init__(
        self,
        faces: Tensor,
        height: int,
        width: int,
        backend: Backend = "auto",
        z_near: float = Z_NEAR,
    ) -> None:
        if backend not in ("auto", "torch", "nvdiffrast"):
            raise ValueError(f"unknown render backend {backend!r}")
        if height < 2 or width < 2:
            raise CameraError(f"image size must be at least 2x2, got {height}x{width}")
        self.faces = _check_faces(faces)
        self.height, self.width, self.z_near = int(height), int(width), z_near
        self.backend: Backend = backend
        self.edges = mesh_edges(self.faces)
        self._nvdiff = None
        if backend == "nvdiffrast":
            from roboseg.render import nvdiff

            if not nvdiff.available():
                raise RuntimeError("render backend 'nvdiffrast' needs nvdiffrast and CUDA")
            self._nvdiff = nvdiff.NvdiffSilhouette(self.faces, self.height, self.width, z_near)

    def _use_nvdiffrast(self, verts_cam: Tensor) -> bool:
        if self.backend == "nvdiffrast":
            return True
        if self.backend == "torch" or not verts_cam.is_cuda:
            return False
        if self._nvdiff is None:
            from roboseg.render import nvdiff

            if not nvdiff.available():
                return False
            self._nvdiff = nvdiff.NvdiffSilhouette(self.faces, self.height, self.width, self.z_near)
        return True

    def _faces_on(self, device: torch.device) -> Tensor:
        if self.faces.device != device:
            self.faces = self.faces.to(device)
            self.edges = self.edges.to(device)
        return self.faces

    def hard(self, verts_cam: Tensor, K: Tensor) -> Tensor:
        """Hard silhouettes ``[B, H, W]`` bool of ``verts_cam`` ``[B, V, 3]`` (camera frame)."""
        _check_inputs(verts_cam, K, self.height, self.width)
        if self._use_nvdiffrast(verts_cam):
            return self._nvdiff.hard(verts_cam, K)
        faces = self._faces_on(verts_cam.device)
        return render_hard(
            verts_cam.detach(), faces, K, self.height, self.width, z_near=self.z_near
        )

    def soft(self, verts_cam: Tensor, K: Tensor) -> Tensor:
        """Differentiable silhouettes ``[B, H, W]`` in [0, 1] (see :func:`render_soft`)."""
        if self._use_nvdiffrast(verts_cam):
            _check_inputs(verts_cam, K, self.height, self.width)
            return self._nvdiff.soft(verts_cam, K)
        faces = self._faces_on(verts_cam.device)
        return render_soft(
            verts_cam, faces, K, self.height, self.width, edges=self.edges, z_near=self.z_near
        )
