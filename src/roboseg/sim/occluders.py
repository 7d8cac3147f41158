"""Occluders in front of (and around) the robot: cables, instruments, staff in scrubs (standing
or walking across the room), tape.

Every occluder is a set of 3D capsules (segment + radius, world frame, metres) that move over
time. A capsule projects to a thick round-capped line whose width is 2·f·radius/z, so each
stereo view draws the same 3D objects; :func:`draw_capsules` returns a colour, depth and alpha
layer (painter's order, far to near) that the frame composites by depth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

Rgb = tuple[float, float, float]

SCRUBS: tuple[Rgb, ...] = (
    (0.05, 0.30, 0.32),
    (0.10, 0.20, 0.45),
    (0.12, 0.35, 0.20),
    (0.30, 0.08, 0.15),
    (0.25, 0.40, 0.55),
)
CABLE_COLOURS: tuple[Rgb, ...] = (
    (0.03, 0.03, 0.03),
    (0.45, 0.46, 0.48),
    (0.80, 0.80, 0.78),
    (0.10, 0.20, 0.50),
)
TAPE_COLOURS: tuple[Rgb, ...] = ((0.85, 0.85, 0.80), (0.80, 0.72, 0.45), (0.70, 0.80, 0.85))
STEEL: Rgb = (0.55, 0.57, 0.60)


@dataclass(frozen=True)
class Capsule:
    """Segment ``p0``–``p1`` (world, m) swept by a sphere of ``radius`` (m); ``alpha`` < 1 is
    see-through (tape)."""

    p0: np.ndarray
    p1: np.ndarray
    radius: float
    colour: Rgb
    alpha: float = 1.0


def catmull_rom(points: np.ndarray, samples_per_segment: int) -> np.ndarray:
    """Points ``[M, 3]`` on the centripetal-free (uniform) Catmull-Rom spline through control
    points ``points [N, 3]`` (end points duplicated), ``samples_per_segment`` per span."""
    p = np.concatenate([points[:1], points, points[-1:]], axis=0)
    s = np.linspace(0.0, 1.0, samples_per_segment, endpoint=False)[:, None]
    out = []
    for i in range(1, len(p) - 2):
        p0, p1, p2, p3 = p[i - 1], p[i], p[i + 1], p[i + 2]
        out.append(
            0.5
            * (
                2 * p1
                + (-p0 + p2) * s
                + (2 * p0 - 5 * p1 + 4 * p2 - p3) * s**2
                + (-p0 + 3 * p1 - 3 * p2 + p3) * s**3
            )
        )
    out.append(points[-1:])
    return np.concatenate(out, axis=0)


@dataclass(frozen=True)
class Cable:
    """A hanging cable through ``control [N, 3]`` swaying by ``sway`` m at ``omega`` rad/s."""

    control: np.ndarray
    radius: float
    colour: Rgb
    sway: float
    omega: float
    phase: float

    def capsules(self, t: float) -> list[Capsule]:
        """Capsules of the cable at time ``t`` (s); the end points stay put."""
        n = len(self.control)
        w = np.sin(np.linspace(0.0, math.pi, n))[:, None]
        offset = self.sway * np.array(
            [math.sin(self.omega * t + self.phase), math.cos(0.7 * self.omega * t), 0.0]
        )
        pts = catmull_rom(self.control + w * offset, 8)
        return [
            Capsule(a, b, self.radius, self.colour) for a, b in zip(pts[:-1], pts[1:], strict=True)
        ]


@dataclass(frozen=True)
class Instrument:
    """A straight steel instrument with a dark handle, tip at ``tip`` pointing along ``axis``,
    pivoting by ``wobble`` rad around the tip."""

    tip: np.ndarray
    axis: np.ndarray
    length: float
    wobble: float
    omega: float
    phase: float

    def capsules(self, t: float) -> list[Capsule]:
        a = self.wobble * math.sin(self.omega * t + self.phase)
        c, s = math.cos(a), math.sin(a)
        d = np.array(
            [c * self.axis[0] - s * self.axis[1], s * self.axis[0] + c * self.axis[1], self.axis[2]]
        )
        mid = self.tip + d * self.length * 0.6
        end = self.tip + d * self.length
        return [
            Capsule(self.tip, mid, 0.004, STEEL),
            Capsule(mid, end, 0.012, (0.05, 0.05, 0.06)),
        ]


def person_capsules(
    base: np.ndarray, direction: np.ndarray, swing: float, scrubs: Rgb, cap: Rgb
) -> list[Capsule]:
    """A person in scrubs standing at floor point ``base`` facing across ``direction`` (unit,
    horizontal): legs, torso, arms, head with cap; one hand ``swing`` m along ``direction``."""
    up = np.array([0.0, 0.0, 1.0])
    side = np.cross(up, direction)
    hip, chest, neck = base + up * 0.85, base + up * 1.25, base + up * 1.45
    hand = chest + side * 0.25 + direction * swing - up * 0.3
    return [
        Capsule(base + side * 0.1, hip + side * 0.08, 0.09, scrubs),
        Capsule(base - side * 0.1, hip - side * 0.08, 0.09, scrubs),
        Capsule(hip, chest, 0.2, scrubs),
        Capsule(chest + side * 0.22, hand, 0.06, scrubs),
        Capsule(chest - side * 0.22, chest - side * 0.25 - up * 0.35, 0.06, scrubs),
        Capsule(neck + up * 0.12, neck + up * 0.14, 0.11, (0.60, 0.45, 0.38)),
        Capsule(neck + up * 0.2, neck + up * 0.22, 0.1, cap),
    ]


@dataclass(frozen=True)
class Staff:
    """A person in scrubs standing at ``foot`` (floor point) who drifts by ``drift`` m along
    ``direction`` at ``omega`` rad/s: legs, torso, arms, head with cap."""

    foot: np.ndarray
    direction: np.ndarray
    drift: float
    omega: float
    phase: float
    scrubs: Rgb
    cap: Rgb

    def capsules(self, t: float) -> list[Capsule]:
        base = self.foot + self.direction * self.drift * math.sin(self.omega * t + self.phase)
        swing = 0.15 * math.sin(1.3 * self.omega * t)
        return person_capsules(base, self.direction, swing, self.scrubs, self.cap)


@dataclass(frozen=True)
class Walker:
    """A person walking straight across the room at ``speed`` m/s along ``direction`` (unit,
    horizontal), at floor point ``cross`` at time ``t_cross`` s (where the path crosses the
    camera's line of sight); arms swing with the stride."""

    cross: np.ndarray
    direction: np.ndarray
    speed: float
    t_cross: float
    scrubs: Rgb
    cap: Rgb

    def position(self, t: float) -> np.ndarray:
        """Floor point (world, m) at time ``t`` s."""
        return self.cross + self.direction * self.speed * (t - self.t_cross)

    def capsules(self, t: float) -> list[Capsule]:
        swing = 0.2 * math.sin(2.0 * math.pi * 0.9 * t)  # ~0.9 strides a second
        return person_capsules(self.position(t), self.direction, swing, self.scrubs, self.cap)


def sample_walkers(
    rng: np.random.Generator,
    eye: np.ndarray,
    target: np.ndarray,
    floor_z: float,
    n: int,
    window: tuple[float, float],
) -> list[Walker]:
    """``n`` people walking across the view at 0.8-1.4 m/s, each crossing the camera's line of
    sight (in front of the robot or behind it) at a time drawn from ``window`` (s), on a path
    within 35° of square to the line of sight."""
    view = target - eye
    reach = float(np.linalg.norm(view[:2]))
    horizontal = np.array([view[0], view[1], 0.0]) / max(reach, 1e-9)
    lateral = np.array([-horizontal[1], horizontal[0], 0.0])
    out = []
    for _ in range(n):
        f = rng.uniform(0.4, 0.85) if rng.uniform() < 0.7 else rng.uniform(1.2, 1.6)
        p = eye + horizontal * f * reach
        angle = rng.uniform(-0.6, 0.6)
        d = lateral * math.cos(angle) + horizontal * math.sin(angle)
        d *= rng.choice([-1.0, 1.0])
        out.append(Walker(
            np.array([p[0], p[1], floor_z]), d, float(rng.uniform(0.8, 1.4)),
            float(rng.uniform(*window)), _choice(rng, SCRUBS), _choice(rng, SCRUBS),
        ))
    return out


Occluder = Cable | Instrument | Staff | Walker


def _choice(rng: np.random.Generator, items: tuple[Rgb, ...]) -> Rgb:
    return items[int(rng.integers(len(items)))]


def sample_occluders(
    rng: np.random.Generator,
    eye: np.ndarray,
    target: np.ndarray,
    floor_z: float,
    site: np.ndarray,
) -> list[Occluder]:
    """Random occluders for a camera at ``eye`` looking at ``target`` (world, m): 1–4 cables
    hanging through the view, 0–2 instruments at the surgical ``site``, 0–2 staff standing
    between the camera and the robot or beyond it, off the line of sight by a lateral offset."""
    out: list[Occluder] = []
    view = target - eye
    horizontal = np.array([view[0], view[1], 0.0])
    horizontal /= max(np.linalg.norm(horizontal), 1e-9)
    lateral = np.array([-horizontal[1], horizontal[0], 0.0])
    for _ in range(int(rng.integers(1, 5))):
        f = rng.uniform(0.35, 0.9)
        through = eye + f * view + lateral * rng.uniform(-0.6, 0.6)
        top = through + np.array([*rng.uniform(-0.5, 0.5, 2), rng.uniform(0.6, 1.2)])
        bottom = np.array(
            [*(through[:2] + rng.uniform(-0.6, 0.6, 2)), floor_z + rng.uniform(0, 0.9)]
        )
        ctrl = np.stack([top, 0.5 * (top + through), through, 0.5 * (through + bottom), bottom])
        ctrl[1:-1] += rng.normal(0.0, 0.08, (3, 3))
        out.append(
            Cable(
                ctrl,
                float(rng.uniform(0.004, 0.01)),
                _choice(rng, CABLE_COLOURS),
                float(rng.uniform(0.01, 0.06)),
                float(rng.uniform(0.3, 1.2)),
                float(rng.uniform(0, 2 * math.pi)),
            )
        )
    for _ in range(int(rng.integers(0, 3))):
        axis = np.array([*rng.uniform(-0.6, 0.6, 2), 1.0])
        out.append(
            Instrument(
                site + np.array([*rng.uniform(-0.08, 0.08, 2), 0.0]),
                axis / np.linalg.norm(axis),
                float(rng.uniform(0.2, 0.35)),
                float(rng.uniform(0.05, 0.3)),
                float(rng.uniform(0.3, 1.0)),
                float(rng.uniform(0, 2 * math.pi)),
            )
        )
    for _ in range(int(rng.integers(0, 3))):
        f = rng.uniform(0.45, 1.4)
        side = rng.choice([-1.0, 1.0]) * rng.uniform(0.3, 1.0)
        p = eye + f * horizontal * np.linalg.norm(view[:2]) + lateral * side
        out.append(
            Staff(
                np.array([p[0], p[1], floor_z]),
                lateral,
                float(rng.uniform(0.1, 0.6)),
                float(rng.uniform(0.1, 0.4)),
                float(rng.uniform(0, 2 * math.pi)),
                _choice(rng, SCRUBS),
                _choice(rng, SCRUBS),
            )
        )
    return out


def draw_capsules(
    capsules: list[Capsule],
    K: np.ndarray,
    T_cam_world: np.ndarray,
    height: int,
    width: int,
    z_near: float = 0.05,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Draw capsules into a layer: linear RGB ``[H,W,3]``, depth ``[H,W]`` (camera z of the
    capsule axis, ``inf`` where empty) and alpha ``[H,W]``. Far capsules first, nearer ones
    overwrite; a lighter inner core gives thick capsules a rounded look."""
    rgb = np.zeros((height, width, 3), np.float32)
    depth = np.full((height, width), np.inf, np.float32)
    alpha = np.zeros((height, width), np.float32)
    if not capsules:
        return rgb, depth, alpha
    R, t = T_cam_world[:3, :3], T_cam_world[:3, 3]
    p0 = np.stack([c.p0 for c in capsules]) @ R.T + t
    p1 = np.stack([c.p1 for c in capsules]) @ R.T + t
    zmid = 0.5 * (p0[:, 2] + p1[:, 2])
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    shift = 4  # sub-pixel bits for cv2 drawing
    scale = float(1 << shift)
    # every capsule's end points (pixels, then fixed point) and thickness at once
    with np.errstate(divide="ignore", invalid="ignore"):
        ends = np.stack(
            [fx * p0[:, 0] / p0[:, 2] + cx, fy * p0[:, 1] / p0[:, 2] + cy,
             fx * p1[:, 0] / p1[:, 2] + cx, fy * p1[:, 1] / p1[:, 2] + cy],
            axis=1,
        )  # fmt: skip
        radius = np.array([c.radius for c in capsules])
        # cv2 draws thickness t about t + 1 pixels wide
        thick = np.maximum(1, np.rint(2.0 * fx * radius / zmid).astype(np.int64) - 1)
    usable = (p0[:, 2] >= z_near) & (p1[:, 2] >= z_near) & (np.abs(ends).max(axis=1) <= 1e5)
    fixed = np.zeros(ends.shape, np.int64)
    fixed[usable] = np.rint(ends[usable] * scale).astype(np.int64)
    for i in np.argsort(-zmid, kind="stable"):
        if not usable[i]:
            continue
        cap = capsules[i]
        pa, pb = (int(fixed[i, 0]), int(fixed[i, 1])), (int(fixed[i, 2]), int(fixed[i, 3]))
        th = int(thick[i])
        col = np.asarray(cap.colour, np.float32)
        cv2.line(rgb, pa, pb, tuple((col * 0.7).tolist()), th, cv2.LINE_8, shift)
        if th >= 3:
            light = tuple(np.minimum(col * 1.15, 1.0).tolist())
            cv2.line(rgb, pa, pb, light, max(1, th // 2), cv2.LINE_8, shift)
        cv2.line(depth, pa, pb, float(zmid[i]), th, cv2.LINE_8, shift)
        cv2.line(alpha, pa, pb, float(cap.alpha), th, cv2.LINE_8, shift)
    return rgb, depth, alpha
