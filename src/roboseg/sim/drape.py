"""The sterile drape: a translucent, wrinkled second surface hanging around the robot.

The drape is built from the robot's own mesh: each link's vertices are wrapped in their convex
hull (a bag with no gaps at concave parts), remeshed to small triangles; every cloth vertex is
pushed out along its normal by a few centimetres plus a low-frequency wrinkle field fixed to the
material (a function of the link-local rest position, so wrinkles move with the link); vertices
whose normal points downwards are pulled down (hanging folds, modulated so the folds vary), and
Taubin smoothing turns the shape into cloth without shrinking it. Positions are in the robot base
frame (metres), ``down`` is gravity's direction in that frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import trimesh

from roboseg.sim.shading import plane_waves, random_waves, vertex_normals

#: Drape tints (linear RGB) and the normal-incidence opacity range of each kind of drape.
DRAPE_KINDS: dict[str, tuple[tuple[float, float, float], tuple[float, float]]] = {
    "clear": ((0.80, 0.85, 0.90), (0.50, 0.65)),
    "white": ((0.85, 0.85, 0.82), (0.70, 0.90)),
    "blue": ((0.18, 0.35, 0.65), (0.60, 0.90)),
}


@dataclass(frozen=True)
class DrapeParams:
    """Appearance and shape of one drape. Lengths in metres, alpha is opacity at normal
    incidence, ``tint`` linear RGB."""

    kind: str
    offset: float
    wrinkle: float
    sag: float
    alpha: float
    tint: tuple[float, float, float]
    specular: float
    shininess: float
    smooth_steps: int = 3


def sample_drape_params(rng: np.random.Generator) -> DrapeParams:
    """Random drape: kind clear/white/blue, push-out 4–7 cm, wrinkles 1.5–3 cm, folds 8–20 cm,
    alpha in the kind's range (overall 0.5–0.9), glossy plastic highlights."""
    kind = str(rng.choice(list(DRAPE_KINDS)))
    tint, (a_lo, a_hi) = DRAPE_KINDS[kind]
    jitter = rng.uniform(0.93, 1.07, size=3)
    return DrapeParams(
        kind=kind,
        offset=float(rng.uniform(0.04, 0.07)),
        wrinkle=float(rng.uniform(0.015, 0.03)),
        sag=float(rng.uniform(0.08, 0.2)),
        alpha=float(rng.uniform(a_lo, a_hi)),
        tint=tuple(float(np.clip(t * j, 0.0, 1.0)) for t, j in zip(tint, jitter, strict=True)),
        specular=float(rng.uniform(0.25, 0.6)),
        shininess=float(rng.uniform(20.0, 60.0)),
    )


def neighbour_average_matrix(faces: torch.Tensor, n_vertices: int) -> torch.Tensor:
    """Sparse row-stochastic ``[V, V]`` matrix averaging each vertex's edge neighbours
    (isolated vertices keep themselves)."""
    f = faces.long()
    src = torch.cat([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]])
    dst = torch.cat([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])
    loops = torch.arange(n_vertices)
    keys = torch.unique(torch.cat([src * n_vertices + dst, loops * n_vertices + loops]))
    rows, cols = keys // n_vertices, keys % n_vertices
    deg = torch.bincount(rows, minlength=n_vertices).to(torch.float32)
    vals = 1.0 / deg[rows]
    return torch.sparse_coo_tensor(
        torch.stack([rows, cols]), vals, (n_vertices, n_vertices), check_invariants=True
    ).coalesce()


def link_hull_mesh(
    vertices: np.ndarray,
    vertex_link: np.ndarray,
    rng: np.random.Generator,
    max_points: int = 400,
    max_edge: float = 0.05,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cloth mesh wrapping each link: convex hull of (at most ``max_points`` random) link-local
    vertices, split to edges ≤ ``max_edge`` m. Returns vertices ``[N,3]`` (link-local), faces
    ``[M,3]`` and link index ``[N]``; links with fewer than 4 distinct points are skipped."""
    out_v, out_f, out_l, offset = [], [], [], 0
    for link in np.unique(vertex_link):
        pts = vertices[vertex_link == link]
        if len(pts) > max_points:
            pts = pts[rng.choice(len(pts), max_points, replace=False)]
        if len(np.unique(np.round(pts, 6), axis=0)) < 4:
            continue
        try:
            hull = trimesh.convex.convex_hull(pts)
        except Exception:  # noqa: BLE001 - flat or degenerate link geometry: no bag for it
            continue
        v, f = trimesh.remesh.subdivide_to_size(hull.vertices, hull.faces, max_edge=max_edge)
        out_v.append(v)
        out_f.append(f + offset)
        out_l.append(np.full(len(v), link, dtype=np.int64))
        offset += len(v)
    if not out_v:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    return np.concatenate(out_v), np.concatenate(out_f), np.concatenate(out_l)


def laplacian_smooth(
    x: torch.Tensor, avg: torch.Tensor, steps: int, lam: float = 0.5
) -> torch.Tensor:
    """``steps`` of ``x ← (1 − λ)x + λ·avg·x`` on ``x [V, C]`` (umbrella-operator smoothing)."""
    for _ in range(steps):
        x = (1.0 - lam) * x + lam * torch.sparse.mm(avg, x)
    return x


def taubin_smooth(
    x: torch.Tensor, avg: torch.Tensor, steps: int, lam: float = 0.5, mu: float = -0.53
) -> torch.Tensor:
    """``steps`` pairs of umbrella smoothing with ``λ`` then ``μ`` < 0 (Taubin): smooths
    wrinkles' sharp edges without shrinking the shape."""
    for _ in range(steps):
        x = laplacian_smooth(x, avg, 1, lam)
        x = laplacian_smooth(x, avg, 1, mu)
    return x


def drape_offsets(
    normals: torch.Tensor,
    wrinkle: torch.Tensor,
    fold: torch.Tensor,
    down: torch.Tensor,
    params: DrapeParams,
) -> torch.Tensor:
    """Displacement ``[V, 3]`` of each drape vertex from the robot surface.

    ``normals [V,3]`` unit outward (posed), ``wrinkle [V]`` and ``fold [V]`` in [−1, 1] (material
    noise), ``down [3]`` unit gravity. Push-out ``offset + wrinkle·w`` along the normal, and for
    downward-facing vertices (``n·down > 0``) a pull ``sag·(n·down)²·(0.6 + 0.4·fold)`` along
    gravity.
    """
    push = params.offset + params.wrinkle * wrinkle
    facing_down = (normals @ down).clamp_min(0.0)
    pull = params.sag * facing_down**2 * (0.6 + 0.4 * fold)
    return normals * push[:, None] + down[None, :] * pull[:, None]


class Drape:
    """A drape fitted to one robot: cloth ``rest_vertices [N,3]`` in their links' frames,
    ``faces [M,3]``, ``vertex_link [N]`` (e.g. from :func:`link_hull_mesh`); :meth:`pose` gives
    the cloth in the base frame for the links' poses."""

    def __init__(
        self,
        rest_vertices: torch.Tensor,
        faces: torch.Tensor,
        vertex_link: torch.Tensor,
        params: DrapeParams,
        rng: np.random.Generator,
        down: tuple[float, float, float] = (0.0, 0.0, -1.0),
    ) -> None:
        self.rest = rest_vertices.to(torch.float32)
        self.faces = faces.long()
        self.vertex_link = vertex_link.long()
        self.params = params
        self.avg = neighbour_average_matrix(self.faces, self.rest.shape[0])
        w_dirs, w_phase = random_waves(8, (0.05, 0.15), rng)
        f_dirs, f_phase = random_waves(3, (0.10, 0.30), rng)
        self.wrinkle = (plane_waves(self.rest, w_dirs, w_phase) * 2.5).clamp(-1.0, 1.0)
        self.fold = (plane_waves(self.rest, f_dirs, f_phase) * 1.7).clamp(-1.0, 1.0)
        self.down = torch.tensor(down, dtype=torch.float32)

    @classmethod
    def around(
        cls,
        vertices: torch.Tensor,
        vertex_link: torch.Tensor,
        params: DrapeParams,
        rng: np.random.Generator,
    ) -> Drape:
        """A drape wrapping a robot mesh (link-local ``vertices``, ``vertex_link``)."""
        v, f, link = link_hull_mesh(vertices.double().numpy(), vertex_link.numpy(), rng)
        return cls(torch.as_tensor(v), torch.as_tensor(f), torch.as_tensor(link), params, rng)

    def pose(self, T_base_link: torch.Tensor, floor_z: float | None = None) -> torch.Tensor:
        """Drape vertices ``[N, 3]`` (base frame) for link poses ``T_base_link [L, 4, 4]``;
        with ``floor_z`` the cloth stops at that height (along −down)."""
        T = T_base_link.to(torch.float32)[self.vertex_link]
        x = (T[:, :3, :3] @ self.rest[:, :, None])[..., 0] + T[:, :3, 3]
        normals = vertex_normals(x, self.faces)
        out = x + drape_offsets(normals, self.wrinkle, self.fold, self.down, self.params)
        out = taubin_smooth(out, self.avg, self.params.smooth_steps)
        if floor_z is not None:
            height = -(out @ self.down)
            lift = (floor_z - height).clamp_min(0.0)
            out = out - self.down[None, :] * lift[:, None]
        return out
