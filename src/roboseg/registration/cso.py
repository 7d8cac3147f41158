"""Camera swarm optimisation (CSO): particle swarm over virtual cameras to initialise SDR.

Each particle is a virtual left camera ``x = [eye (3), centre (3), roll (1)]`` in the robot base
frame (metres, radians): the camera sits at ``eye``, looks at ``centre`` and is rolled about its
optical axis; ``T_cam_base = look_at(eye, centre, roll)``. Eyes start uniformly distributed in a
hollow sphere ``r_min ≤ |eye − about| ≤ r_max`` (optionally only the band of elevations
``elevation_range`` above the horizontal plane through ``about``, base z up: cameras that look
down at the robot), centres uniformly in the ball
``|centre − about| ≤ centre_radius``, rolls uniformly in ``[−roll_range, roll_range]``.

Fitness = IoU of hard silhouettes of the (decimated) robot, rendered at low resolution, against
the target masks, averaged over views (right camera through the fixed stereo transform) and
joint configurations (the paper's sum, divided by the number of terms). Standard PSO update
(Kennedy & Eberhart) with inertia ``w``, cognitive ``c1`` and social ``c2`` coefficients:
``v ← w v + c1 r1 (p_best − x) + c2 r2 (g_best − x)``, ``x ← project(x + v)``, where ``project``
keeps every particle inside its initial domain. The initial swarm is scored before the first
velocity update. The best few mutually distinct personal bests are returned for multi-start SDR.

A swarm can settle in a wrong basin whose fitness stays well below the truth's (measured at
1.5 m with ground-truth masks: 0.83 against the truth's 0.97; other seeds of the same swarm
reached 0.97). ``restarts`` further independent swarms (run ``r`` seeded ``seed + r``) run
while the best fitness so far is below ``restart_below``; the candidates are picked from the
personal bests of every run.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from roboseg.errors import CameraError
from roboseg.registration.losses import iou
from roboseg.registration.pose import look_at_T_cam_base, rotation_angle
from roboseg.registration.views import View, resize_masks, vertices_in_view, views_at_resolution
from roboseg.render.raster import render_hard

__all__ = ["CSOConfig", "Candidate", "CSOResult", "SwarmFitness", "cso", "sample_particles"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CSOConfig:
    """Swarm settings. Distances in metres (base frame), angles in radians.

    ``about``: centre of the eye shell and of the look-at ball; ``width``: render width in pixels
    (height follows each view's aspect ratio); ``chunk``: renders per rasteriser call;
    ``v_max``: largest step per iteration as a fraction of each coordinate's domain width;
    ``n_candidates`` distinct results whose poses differ by more than ``min_separation`` metres
    or ``min_separation_angle`` radians, far enough apart to start SDR in different basins
    (measured on a noisy segmentation: 4 candidates 5 cm / 5° apart screened within 0.1 % of each
    other and ended 96° off; 0.3 m / 0.5 rad apart, one of them led SDR to the truth, 4.3° off).
    ``elevation_range``: the eye's elevation (radians) above the horizontal plane through
    ``about`` (base z up); the default allows every direction. ``restarts``: at most this many
    further swarms (seeds ``seed + 1``, ``seed + 2``, …) run while the best fitness is below
    ``restart_below`` (mean IoU; a clean mask of the true pose scores ~0.95 at 48 px, so the
    restarts cost time only on poor fits and on poor masks).
    """

    n_particles: int = 2000
    iterations: int = 30
    r_min: float = 1.0
    r_max: float = 3.0
    centre_radius: float = 0.5
    about: tuple[float, float, float] = (0.0, 0.0, 0.5)
    roll_range: float = math.pi
    elevation_range: tuple[float, float] = (-math.pi / 2, math.pi / 2)
    inertia: float = 0.7
    cognitive: float = 1.5
    social: float = 1.5
    v_max: float = 0.2
    width: int = 80
    chunk: int = 2048
    n_candidates: int = 4
    min_separation: float = 0.3
    min_separation_angle: float = 0.5
    seed: int = 0
    restarts: int = 0
    restart_below: float = 0.9

    def __post_init__(self) -> None:
        if not 0.0 < self.r_min < self.r_max:
            raise CameraError(f"CSO needs 0 < r_min < r_max, got {self.r_min}, {self.r_max}")
        if self.centre_radius < 0 or self.roll_range < 0:
            raise CameraError("CSO centre_radius and roll_range must be non-negative")
        if self.n_particles < 1 or self.iterations < 0 or self.n_candidates < 1:
            raise CameraError("CSO needs n_particles >= 1, iterations >= 0, n_candidates >= 1")
        if self.restarts < 0:
            raise CameraError(f"CSO restarts must be >= 0, got {self.restarts}")
        if self.width < 8:
            raise CameraError(f"CSO render width must be at least 8 px, got {self.width}")
        lo, hi = self.elevation_range
        if not -math.pi / 2 <= lo < hi <= math.pi / 2:
            raise CameraError(
                "CSO elevation_range must satisfy -pi/2 <= lo < hi <= pi/2 (radians), "
                f"got {lo}, {hi}"
            )


@dataclass(frozen=True)
class Candidate:
    """A virtual camera found by CSO: its ``T_cam_base`` [4, 4] float64 and fitness (mean IoU)."""

    T_cam_base: np.ndarray
    fitness: float
    particle: np.ndarray  # [7]: eye, centre, roll


@dataclass(frozen=True)
class CSOResult:
    """Best distinct candidates (best first), the global best fitness after each iteration
    (``history[0]`` is the scored initial swarm; with restarts, each run's iterations follow the
    previous run's, still the best over all runs so far) and the number of swarms run."""

    candidates: list[Candidate]
    history: list[float] = field(default_factory=list)
    runs: int = 1

    @property
    def best(self) -> Candidate:
        return self.candidates[0]


def _uniform_ball(
    n: int,
    r_min: float,
    r_max: float,
    g: torch.Generator,
    elevation: tuple[float, float] | None = None,
) -> torch.Tensor:
    """``n`` points ``[n, 3]`` uniform (by volume) in the shell ``r_min ≤ |p| ≤ r_max``, or in its
    part whose elevation ``asin(p_z / |p|)`` lies in ``elevation`` (radians)."""
    if elevation is None:
        direction = torch.randn(n, 3, generator=g, dtype=torch.float64)
        direction = direction / direction.norm(dim=1, keepdim=True).clamp_min(1e-12)
    else:  # uniform on the sphere's band: z uniform in [sin lo, sin hi] (Archimedes)
        z_lo, z_hi = math.sin(elevation[0]), math.sin(elevation[1])
        z = z_lo + (z_hi - z_lo) * torch.rand(n, generator=g, dtype=torch.float64)
        phi = 2 * math.pi * torch.rand(n, generator=g, dtype=torch.float64)
        rho = (1 - z * z).clamp_min(0).sqrt()
        direction = torch.stack([rho * phi.cos(), rho * phi.sin(), z], dim=1)
    u = torch.rand(n, 1, generator=g, dtype=torch.float64)
    r = (r_min**3 + u * (r_max**3 - r_min**3)) ** (1.0 / 3.0)
    return direction * r


def sample_particles(n: int, cfg: CSOConfig, g: torch.Generator) -> torch.Tensor:
    """Initial particles ``[n, 7]`` (float64): eye in the shell, centre in the ball, roll."""
    about = torch.tensor(cfg.about, dtype=torch.float64)
    full = tuple(cfg.elevation_range) == (-math.pi / 2, math.pi / 2)
    band = None if full else cfg.elevation_range  # full sphere: the historical draws
    eye = about + _uniform_ball(n, cfg.r_min, cfg.r_max, g, band)
    centre = (
        about + _uniform_ball(n, 0.0, cfg.centre_radius, g)
        if cfg.centre_radius > 0
        else (about.expand(n, 3).clone())
    )
    roll = (2.0 * torch.rand(n, 1, generator=g, dtype=torch.float64) - 1.0) * cfg.roll_range
    return torch.cat([eye, centre, roll], dim=1)


def project_particles(x: torch.Tensor, cfg: CSOConfig) -> torch.Tensor:
    """Particles ``[n, 7]`` moved back into the domain: eye radius clamped to ``[r_min, r_max]``
    and its elevation to ``elevation_range`` (azimuth kept), centre radius to
    ``centre_radius``, roll to ``±roll_range``."""
    about = torch.tensor(cfg.about, dtype=x.dtype)
    e = x[:, 0:3] - about
    r = e.norm(dim=1, keepdim=True).clamp_min(1e-12)
    lo, hi = cfg.elevation_range
    elevation = torch.asin((e[:, 2:3] / r).clamp(-1.0, 1.0))
    clamped = elevation.clamp(lo, hi)
    horizontal = e[:, 0:2].norm(dim=1, keepdim=True)
    azimuth = torch.where(horizontal > 1e-12, e[:, 0:2] / horizontal.clamp_min(1e-12),
                          torch.tensor([1.0, 0.0], dtype=x.dtype))
    moved = (clamped != elevation).squeeze(1)  # rebuilt only there: the rest keep exact values
    e = torch.where(
        moved[:, None],
        torch.cat([azimuth * r * clamped.cos(), r * clamped.sin()], dim=1),
        e,
    )
    e = e * (r.clamp(cfg.r_min, cfg.r_max) / r)
    c = x[:, 3:6] - about
    rc = c.norm(dim=1, keepdim=True).clamp_min(1e-12)
    c = c * (rc.clamp(max=cfg.centre_radius) / rc)
    roll = x[:, 6:7].clamp(-cfg.roll_range, cfg.roll_range)
    return torch.cat([about + e, about + c, roll], dim=1)


def particles_to_T_cam_base(x: torch.Tensor) -> torch.Tensor:
    """``T_cam_base`` ``[n, 4, 4]`` of particles ``[n, 7]``."""
    return look_at_T_cam_base(x[:, 0:3], x[:, 3:6], x[:, 6])


class SwarmFitness:
    """Mean IoU of many candidate ``T_cam_base`` against fixed targets, by batched hard renders.

    Args:
        vertices_base: ``[C, V, 3]`` robot vertices (base frame) per configuration, ideally of a
            decimated mesh.
        faces: ``[F, 3]``.
        views: full-resolution views (left first); rendered at ``width`` pixels wide.
        masks: per view, target masks ``[C, H, W]`` (resized to the render resolution).
    """

    def __init__(
        self,
        vertices_base: torch.Tensor,
        faces: torch.Tensor,
        views: Sequence[View],
        masks: Sequence[np.ndarray | torch.Tensor],
        width: int = 80,
        chunk: int = 2048,
    ) -> None:
        if len(views) != len(masks):
            raise ValueError(f"{len(views)} views but {len(masks)} target mask stacks")
        self.vertices_base = vertices_base.to(torch.float32)
        self.faces = faces
        self.views = views_at_resolution(views, width)
        self.targets = [
            torch.from_numpy(resize_masks(m, v.width, v.height))
            for v, m in zip(self.views, masks, strict=True)
        ]
        for v, t in zip(self.views, self.targets, strict=True):
            if t.shape[0] != self.vertices_base.shape[0]:
                raise ValueError(
                    f"view {v.name!r}: {t.shape[0]} masks for "
                    f"{self.vertices_base.shape[0]} configurations"
                )
        self.chunk = max(1, int(chunk))

    def __call__(self, T_cam_base: torch.Tensor) -> torch.Tensor:
        """Fitness ``[n]`` in [0, 1] of poses ``[n, 4, 4]``."""
        n, n_conf = T_cam_base.shape[0], self.vertices_base.shape[0]
        total = torch.zeros(n, dtype=torch.float64)
        per_chunk = max(1, self.chunk // n_conf)
        T_all = T_cam_base.to(torch.float32)
        for view, target in zip(self.views, self.targets, strict=True):
            K = view.K.to(torch.float32)
            for s in range(0, n, per_chunk):
                T = T_all[s : s + per_chunk]
                verts = vertices_in_view(T[:, None], view, self.vertices_base[None])
                verts = verts.reshape(-1, *self.vertices_base.shape[1:])  # [n_chunk*C, V, 3]
                visible = (verts[..., 2] > 0).any(dim=1)
                masks = torch.zeros(verts.shape[0], view.height, view.width, dtype=torch.bool)
                if bool(visible.any()):
                    masks[visible] = render_hard(
                        verts[visible], self.faces, K, view.height, view.width
                    )
                scores = iou(masks.view(T.shape[0], n_conf, view.height, view.width), target)
                total[s : s + T.shape[0]] += scores.to(torch.float64).sum(dim=1)
        return total / (len(self.views) * n_conf)


def _distinct_best(x: torch.Tensor, fitness: torch.Tensor, cfg: CSOConfig) -> list[Candidate]:
    """Greedy pick of the fittest particles whose poses differ pairwise by the separations."""
    order = torch.argsort(fitness, descending=True)
    T = particles_to_T_cam_base(x)
    chosen: list[int] = []
    for i in order.tolist():
        distinct = all(
            float((T[i, :3, 3] - T[j, :3, 3]).norm()) > cfg.min_separation
            or float(rotation_angle(T[i, :3, :3], T[j, :3, :3])) > cfg.min_separation_angle
            for j in chosen
        )
        if distinct:
            chosen.append(i)
        if len(chosen) == cfg.n_candidates:
            break
    return [
        Candidate(T[i].numpy().astype(np.float64), float(fitness[i]), x[i].numpy().copy())
        for i in chosen
    ]


def _swarm(
    fit: SwarmFitness, cfg: CSOConfig, seed: int
) -> tuple[torch.Tensor, torch.Tensor, list[float]]:
    """One particle swarm: personal bests ``[n, 7]``, their fitness ``[n]`` and the run's global
    best after each iteration (the initial swarm first)."""
    g = torch.Generator().manual_seed(seed)
    x = sample_particles(cfg.n_particles, cfg, g)
    v = torch.zeros_like(x)
    span = torch.tensor(
        [2 * cfg.r_max] * 3 + [2 * max(cfg.centre_radius, 1e-6)] * 3 + [2 * cfg.roll_range],
        dtype=torch.float64,
    )
    v_max = cfg.v_max * span
    f = fit(particles_to_T_cam_base(x))
    p_best, p_fit = x.clone(), f.clone()
    g_idx = int(torch.argmax(p_fit))
    history = [float(p_fit[g_idx])]
    log.info("CSO seed %d: %d particles, initial best IoU %.3f", seed, cfg.n_particles, history[0])
    for it in range(1, cfg.iterations + 1):
        r1 = torch.rand(x.shape, generator=g, dtype=torch.float64)
        r2 = torch.rand(x.shape, generator=g, dtype=torch.float64)
        g_best = p_best[g_idx]
        v = cfg.inertia * v + cfg.cognitive * r1 * (p_best - x) + cfg.social * r2 * (g_best - x)
        v = torch.maximum(torch.minimum(v, v_max), -v_max)
        x_new = project_particles(x + v, cfg)
        v = x_new - x  # the step actually taken (no momentum through the bounds)
        x = x_new
        f = fit(particles_to_T_cam_base(x))
        better = f > p_fit
        p_best[better], p_fit[better] = x[better], f[better]
        g_idx = int(torch.argmax(p_fit))
        history.append(float(p_fit[g_idx]))
        log.debug("CSO %d: best IoU %.4f, mean %.4f", it, history[-1], float(f.mean()))
    return p_best, p_fit, history


def cso(
    vertices_base: torch.Tensor,
    faces: torch.Tensor,
    views: Sequence[View],
    masks: Sequence[np.ndarray | torch.Tensor],
    config: CSOConfig | None = None,
) -> CSOResult:
    """Search ``T_cam_base`` of the left camera by camera swarm optimisation.

    ``vertices_base`` [C, V, 3] are the robot's vertices in its C configurations (base frame,
    metres; decimate the mesh first, e.g. ``robot.decimated(0.95)``), ``masks[i]`` [C, H, W] the
    segmentations seen by ``views[i]``. Deterministic for a given ``config.seed``.
    """
    cfg = config or CSOConfig()
    fit = SwarmFitness(vertices_base, faces, views, masks, cfg.width, cfg.chunk)
    bests: list[torch.Tensor] = []
    fits: list[torch.Tensor] = []
    history: list[float] = []
    for run in range(cfg.restarts + 1):
        if run:
            if history[-1] >= cfg.restart_below:
                break
            log.info(
                "CSO best IoU %.3f < %.3f: restarting with seed %d",
                history[-1],
                cfg.restart_below,
                cfg.seed + run,
            )
        p_best, p_fit, run_history = _swarm(fit, cfg, cfg.seed + run)
        bests.append(p_best)
        fits.append(p_fit)
        floor = history[-1] if history else -math.inf
        history.extend(max(floor, h) for h in run_history)
    candidates = _distinct_best(torch.cat(bests), torch.cat(fits), cfg)
    log.info(
        "CSO done: best IoU %.3f (%d candidates, %d run%s)",
        candidates[0].fitness,
        len(candidates),
        len(bests),
        "" if len(bests) == 1 else "s",
    )
    return CSOResult(candidates, history, runs=len(bests))
