"""Smooth random joint trajectories within limits, with pauses (the recorded robot motion).

A trajectory visits random waypoints inside the joint limits, moves between them with a
minimum-jerk profile (zero velocity and acceleration at each waypoint) and rests at some of them,
like a robot driven through a set of configurations. Joint values are radians (or metres for
prismatic joints), one row per frame.
"""

from __future__ import annotations

import numpy as np

from roboseg.errors import RobotModelError


def min_jerk(s: np.ndarray) -> np.ndarray:
    """Minimum-jerk blend 10s³ − 15s⁴ + 6s⁵ of a phase ``s`` in [0, 1] (0 → 0, 1 → 1, flat ends)."""
    s = np.clip(s, 0.0, 1.0)
    return s**3 * (10.0 - 15.0 * s + 6.0 * s**2)


def waypoint_box(
    lower: np.ndarray, upper: np.ndarray, spread: float = 0.7, max_half_range: float = 2.0
) -> tuple[np.ndarray, np.ndarray]:
    """Box ``(lo, hi)`` waypoints are drawn from: the central ``spread`` fraction of each joint's
    range, at most ``max_half_range`` (rad) either side of the middle. Raises on inverted limits."""
    lower = np.asarray(lower, dtype=np.float64)
    upper = np.asarray(upper, dtype=np.float64)
    bad = np.nonzero(~(upper >= lower))[0]
    if bad.size:
        j = int(bad[0])
        raise RobotModelError(f"joint {j}: upper limit {upper[j]} is below lower limit {lower[j]}")
    mid = 0.5 * (lower + upper)
    half = np.minimum(0.5 * (upper - lower) * spread, max_half_range)
    return mid - half, mid + half


def random_joint_trajectory(
    lower: np.ndarray,
    upper: np.ndarray,
    n_frames: int,
    fps: float,
    rng: np.random.Generator,
    *,
    move_seconds: tuple[float, float] = (1.5, 4.0),
    pause_seconds: tuple[float, float] = (0.3, 1.5),
    pause_probability: float = 0.6,
    spread: float = 0.7,
    start: np.ndarray | None = None,
) -> np.ndarray:
    """Joint positions ``[n_frames, D]`` sampled at ``fps`` Hz.

    Starts at ``start`` (default: a random waypoint), then alternates minimum-jerk moves of
    ``move_seconds`` to uniform random waypoints in :func:`waypoint_box` with pauses of
    ``pause_seconds`` (each with ``pause_probability``). Every value lies within the limits.
    """
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    lo, hi = waypoint_box(lower, upper, spread)
    dof = lo.shape[0]
    current = rng.uniform(lo, hi) if start is None else np.clip(np.asarray(start, float), lo, hi)
    out = np.empty((n_frames, dof), dtype=np.float64)
    filled = 0
    while filled < n_frames:
        if rng.random() < pause_probability:
            n_pause = max(1, round(rng.uniform(*pause_seconds) * fps))
            take = min(n_pause, n_frames - filled)
            out[filled : filled + take] = current
            filled += take
        target = rng.uniform(lo, hi)
        n_move = max(2, round(rng.uniform(*move_seconds) * fps))
        s = min_jerk(np.arange(1, n_move + 1) / n_move)[:, None]
        segment = current + s * (target - current)
        take = min(n_move, n_frames - filled)
        out[filled : filled + take] = segment[:take]
        filled += take
        current = target
    return np.clip(out, np.asarray(lower, float), np.asarray(upper, float))
