"""The static operating room: floor, walls, operating table, draped patient, equipment, lamp.

Static geometry is analytic (planes, axis-aligned boxes, ellipsoids in the world frame = the base
frame of robot 0, z up, metres) and ray-cast once per camera per recording; the result is a linear
RGB image and a depth image (camera z, metres, ``inf`` where nothing is hit) that the per-frame
layers composite against. Textures are functions of the world position, so both stereo views
see the same surface.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

Rgb = tuple[float, float, float]

#: Palettes the scene draws from (linear RGB).
FLOOR_COLOURS: tuple[Rgb, ...] = (
    (0.30, 0.32, 0.30),
    (0.22, 0.28, 0.30),
    (0.40, 0.38, 0.34),
    (0.18, 0.24, 0.20),
    (0.45, 0.45, 0.45),
)
WALL_COLOURS: tuple[Rgb, ...] = (
    (0.45, 0.60, 0.55),
    (0.60, 0.62, 0.60),
    (0.35, 0.45, 0.55),
    (0.70, 0.70, 0.66),
    (0.50, 0.55, 0.45),
)
SURGICAL_DRAPE_COLOURS: tuple[Rgb, ...] = (
    (0.10, 0.25, 0.45),
    (0.10, 0.35, 0.30),
    (0.15, 0.30, 0.55),
    (0.20, 0.40, 0.35),
)
EQUIPMENT_COLOURS: tuple[Rgb, ...] = (
    (0.85, 0.85, 0.82),
    (0.08, 0.08, 0.09),
    (0.55, 0.57, 0.60),
    (0.75, 0.78, 0.80),
    (0.20, 0.30, 0.45),
    (0.60, 0.50, 0.35),
)
SKIN: Rgb = (0.65, 0.42, 0.33)


@dataclass(frozen=True)
class Box:
    """Axis-aligned box ``lo``–``hi`` (world, m); ``emissive`` boxes are lamps (no shading)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    albedo: Rgb
    emissive: bool = False


@dataclass(frozen=True)
class Ellipsoid:
    """Ellipsoid with ``centre`` and semi-axes ``radii`` (world, m) and a skin-coloured window
    (the surgical site) ``site = (x, y, half_x, half_y)`` in the drape over it."""

    centre: tuple[float, float, float]
    radii: tuple[float, float, float]
    albedo: Rgb
    site: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class StaticScene:
    """Room (floor height, half side of the square room, colours), boxes, ellipsoids and the
    key light (unit direction towards the light, world) with its ambient share."""

    floor_z: float
    room_half: float
    floor_albedo: Rgb
    wall_albedo: Rgb
    light_dir: tuple[float, float, float]
    ambient: float
    boxes: tuple[Box, ...] = field(default_factory=tuple)
    ellipsoids: tuple[Ellipsoid, ...] = field(default_factory=tuple)
    tile: float = 0.5
    table_top: float = 0.0


def _pick(rng: np.random.Generator, colours: tuple[Rgb, ...], jitter: float = 0.08) -> Rgb:
    c = np.asarray(colours[int(rng.integers(len(colours)))]) * rng.uniform(
        1 - jitter, 1 + jitter, 3
    )
    return tuple(float(x) for x in np.clip(c, 0.0, 1.0))


def unit(v: np.ndarray) -> np.ndarray:
    """``v`` scaled to unit length along the last axis."""
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def sample_scene(
    rng: np.random.Generator, bases: list[np.ndarray], camera_xy: np.ndarray
) -> StaticScene:
    """Random room around robots whose base origins are ``bases`` (world, m): the operating table
    with a draped patient beside robot 0, equipment and a lamp away from the camera (whose
    horizontal position is ``camera_xy``) so nothing static stands between camera and robots."""
    floor_z = -float(rng.uniform(0.7, 0.95))
    table_top = float(rng.uniform(-0.12, 0.05))
    table_x = (float(rng.uniform(0.18, 0.3)), 0.0)
    table_x = (table_x[0], table_x[0] + float(rng.uniform(0.5, 0.65)))
    y_len = float(rng.uniform(1.8, 2.2))
    y0 = float(rng.uniform(-0.6, 0.2))
    drape_colour = _pick(rng, SURGICAL_DRAPE_COLOURS)
    boxes = [
        # table top covered by the patient drape, hanging down the sides
        Box(
            (table_x[0], y0 - y_len / 2, floor_z + 0.25),
            (table_x[1], y0 + y_len / 2, table_top),
            drape_colour,
        ),
        # dark table column
        Box(
            (table_x[0] + 0.15, y0 - 0.3, floor_z),
            (table_x[1] - 0.15, y0 + 0.3, floor_z + 0.25),
            (0.06, 0.06, 0.07),
        ),
    ]
    patient_colour = _pick(rng, SURGICAL_DRAPE_COLOURS)
    xc = 0.5 * (table_x[0] + table_x[1])
    yc = y0 + float(rng.uniform(-0.2, 0.2))
    site = (
        xc + float(rng.uniform(-0.05, 0.05)),
        yc + float(rng.uniform(-0.3, 0.3)),
        float(rng.uniform(0.04, 0.08)),
        float(rng.uniform(0.08, 0.15)),
    )
    ellipsoids = [
        Ellipsoid(
            (xc, yc, table_top + 0.05),
            (
                float(rng.uniform(0.2, 0.26)),
                float(rng.uniform(0.65, 0.85)),
                float(rng.uniform(0.12, 0.18)),
            ),
            patient_colour,
            site=site,
        ),
    ]
    cam_dir = unit(np.asarray(camera_xy, float) - np.asarray(bases[0][:2], float))
    room_half = float(rng.uniform(3.5, 5.0))
    for _ in range(int(rng.integers(2, 6))):
        # equipment on the far side of the robots, seen behind them
        ang = np.arctan2(-cam_dir[1], -cam_dir[0]) + rng.uniform(-1.2, 1.2)
        r = rng.uniform(1.6, 3.0)
        c = np.array([np.cos(ang), np.sin(ang)]) * r
        half = rng.uniform([0.15, 0.15], [0.45, 0.45])
        height = rng.uniform(0.6, 1.9)
        boxes.append(
            Box(
                (c[0] - half[0], c[1] - half[1], floor_z),
                (c[0] + half[0], c[1] + half[1], floor_z + height),
                _pick(rng, EQUIPMENT_COLOURS),
            )
        )
    # ceiling lamp: a bright emissive disc-like box above the table
    lx, ly = xc + rng.uniform(-0.8, 0.8), y0 + rng.uniform(-0.8, 0.8)
    lz = float(rng.uniform(1.3, 1.7))
    boxes.append(
        Box(
            (lx - 0.3, ly - 0.3, lz),
            (lx + 0.3, ly + 0.3, lz + 0.08),
            (1.0, 0.98, 0.92),
            emissive=True,
        )
    )
    light = unit(np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), 1.0]))
    return StaticScene(
        floor_z=floor_z,
        room_half=room_half,
        floor_albedo=_pick(rng, FLOOR_COLOURS),
        wall_albedo=_pick(rng, WALL_COLOURS),
        light_dir=tuple(float(x) for x in light),
        ambient=float(rng.uniform(0.3, 0.5)),
        boxes=tuple(boxes),
        ellipsoids=tuple(ellipsoids),
        tile=float(rng.uniform(0.3, 0.6)),
        table_top=table_top,
    )


def ray_box(
    origin: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Slab test: ray parameter ``t [N]`` of the first hit in front of ``origin`` (``inf`` if
    none) and the outward unit normal ``[N, 3]`` of the face hit."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
        t0 = (lo - origin) * inv
        t1 = (hi - origin) * inv
    tmin = np.nanmax(np.minimum(t0, t1), axis=1)
    tmax = np.nanmin(np.maximum(t0, t1), axis=1)
    axis = np.nanargmax(np.minimum(t0, t1), axis=1)
    hit = (tmax >= tmin) & (tmin > 1e-6)
    t = np.where(hit, tmin, np.inf)
    normal = np.zeros_like(dirs)
    rows = np.arange(dirs.shape[0])
    normal[rows, axis] = -np.sign(dirs[rows, axis])
    return t, normal


def ray_ellipsoid(
    origin: np.ndarray, dirs: np.ndarray, centre: np.ndarray, radii: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """First hit ``t [N]`` (``inf`` if none) of rays with an axis-aligned ellipsoid and the
    outward unit normal ``[N, 3]`` there (gradient of Σ(x_i/r_i)²)."""
    o = (origin - centre) / radii
    d = dirs / radii
    a = (d * d).sum(1)
    b = 2.0 * (o * d).sum(1)
    c = (o * o).sum() - 1.0
    disc = b * b - 4 * a * c
    sq = np.sqrt(np.maximum(disc, 0.0))
    t = (-b - sq) / (2 * a)
    t = np.where((disc >= 0) & (t > 1e-6), t, np.inf)
    p = origin + dirs * np.where(np.isfinite(t), t, 0.0)[:, None]
    normal = unit((p - centre) / radii**2)
    return t, normal


def _stripes(x: np.ndarray, period: float, width: float) -> np.ndarray:
    """1 on thin lines every ``period`` metres (lines ``width`` m wide), else 0."""
    f = np.mod(x, period)
    return ((f < width) | (f > period - width)).astype(np.float64)


def _grain(p: np.ndarray, seed: float) -> np.ndarray:
    """Deterministic smooth texture noise in [−1, 1] at world points ``p [N, 3]``."""
    k = np.array([[7.1, 3.3, 5.2], [-4.4, 8.7, 2.9], [2.3, -6.1, 9.4]]) * (1.0 + 0.1 * seed)
    return np.sin(p @ k.T + seed * np.array([1.3, 2.1, 0.7])).mean(1)


def box_pixels(
    lo: np.ndarray, hi: np.ndarray, K: np.ndarray, T_cam_world: np.ndarray, height: int, width: int
) -> np.ndarray:
    """Bool ``[H, W]`` of the pixels that can see the axis-aligned box ``lo``–``hi`` (world):
    the bounding rectangle of its projected corners (all pixels if a corner is behind the
    camera)."""
    corners = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    cam = corners @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    out = np.zeros((height, width), bool)
    if np.any(cam[:, 2] <= 1e-6):
        out[:] = True
        return out
    u = K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2]
    v = K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]
    u0, u1 = max(int(np.floor(u.min())), 0), min(int(np.ceil(u.max())), width - 1)
    v0, v1 = max(int(np.floor(v.min())), 0), min(int(np.ceil(v.max())), height - 1)
    if u0 <= u1 and v0 <= v1:
        out[v0 : v1 + 1, u0 : u1 + 1] = True
    return out


def render_static(
    scene: StaticScene, K: np.ndarray, T_cam_world: np.ndarray, height: int, width: int
) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast the static scene: linear RGB ``[H, W, 3]`` float32 and depth ``[H, W]`` (camera z,
    metres) for a pinhole camera ``K`` at pose ``T_cam_world`` (OpenCV optical frame)."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rays_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    rays_cam = rays_cam.reshape(-1, 3)
    R_wc = T_cam_world[:3, :3].T
    origin = -R_wc @ T_cam_world[:3, 3]
    dirs = rays_cam @ R_wc.T  # z_cam = 1 along each ray, so t is the camera depth
    n_px = dirs.shape[0]
    best_t = np.full(n_px, np.inf)
    normal = np.zeros((n_px, 3))
    obj = np.full(n_px, -1)  # -1 room, k ≥ 0: boxes then ellipsoids

    # room: floor, ceiling and four walls as the inside of one big box
    lo = np.array([-scene.room_half, -scene.room_half, scene.floor_z])
    hi = np.array([scene.room_half, scene.room_half, scene.floor_z + 3.2])
    with np.errstate(divide="ignore", invalid="ignore"):
        t_far = np.maximum((lo - origin) / dirs, (hi - origin) / dirs)
    t_far = np.where(np.isnan(t_far), np.inf, t_far)
    axis = np.argmin(t_far, axis=1)
    rows = np.arange(n_px)
    best_t[:] = t_far[rows, axis]
    normal[rows, axis] = -np.sign(dirs[rows, axis])

    shapes = [(np.asarray(b.lo), np.asarray(b.hi), ray_box) for b in scene.boxes]
    shapes += [(np.asarray(e.centre), np.asarray(e.radii), ray_ellipsoid) for e in scene.ellipsoids]
    for k, (a, b, fn) in enumerate(shapes):
        lo, hi = (a, b) if fn is ray_box else (a - b, a + b)
        rows = np.flatnonzero(box_pixels(lo, hi, K, T_cam_world, height, width).reshape(-1))
        t, nrm = fn(origin, dirs[rows], a, b)
        closer = t < best_t[rows]
        sel = rows[closer]
        best_t[sel] = t[closer]
        normal[sel] = nrm[closer]
        obj[sel] = k

    p = origin + dirs * best_t[:, None]
    albedo = np.empty((n_px, 3))
    room = obj == -1
    floor = room & (axis == 2) & (dirs[:, 2] < 0)
    ceiling = room & (axis == 2) & (dirs[:, 2] > 0)
    wall = room & ~floor & ~ceiling
    pf = p[floor]
    tiles = np.clip(
        _stripes(pf[:, 0], scene.tile, 0.006) + _stripes(pf[:, 1], scene.tile, 0.006), 0.0, 1.0
    )
    albedo[floor] = (
        np.asarray(scene.floor_albedo)
        * (1.0 + 0.08 * _grain(pf, 1.0))[:, None]
        * (1.0 - 0.4 * tiles)[:, None]
    )
    pw = p[wall]
    panels = _stripes(pw[:, 0] + pw[:, 1], 1.2, 0.01)
    albedo[wall] = (
        np.asarray(scene.wall_albedo)
        * (1.0 + 0.05 * _grain(pw * 0.5, 2.0))[:, None]
        * (1.0 - 0.25 * panels)[:, None]
    )
    albedo[ceiling] = 0.8
    emissive = np.zeros(n_px, bool)
    n_boxes = len(scene.boxes)
    for k, box in enumerate(scene.boxes):
        sel = obj == k
        albedo[sel] = np.asarray(box.albedo) * (1.0 + 0.06 * _grain(p[sel] * 3.0, 3.0))[:, None]
        emissive[sel] = box.emissive
    for k, ell in enumerate(scene.ellipsoids):
        sel = obj == n_boxes + k
        ps = p[sel]
        alb = np.asarray(ell.albedo) * (1.0 + 0.12 * _grain(ps * 4.0, 4.0))[:, None]
        site = (np.abs(ps[:, 0] - ell.site[0]) < ell.site[2]) & (
            np.abs(ps[:, 1] - ell.site[1]) < ell.site[3]
        )
        skin = np.asarray(SKIN) * (1.0 + 0.1 * _grain(ps * 30.0, 5.0))[:, None]
        albedo[sel] = np.where(site[:, None], skin, alb)

    light = np.asarray(scene.light_dir)
    lambert = np.clip(np.abs(normal @ light), 0.0, 1.0)
    rgb = albedo * (scene.ambient + (1.0 - scene.ambient) * lambert)[:, None]
    rgb[emissive] = albedo[emissive] * 1.6
    depth = best_t.astype(np.float32).reshape(height, width)
    return rgb.astype(np.float32).reshape(height, width, 3), depth
