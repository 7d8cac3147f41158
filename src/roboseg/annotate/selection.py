"""Which frames of a recording are annotated: joint motion, drape phase, even thinning, splits.

The paper's medium / large training subsets hold 4 % / 8 % of the frames and consider only
frames with non-negligible joint motion; here the motion is the joint speed (rad/s or m/s)
of the joint states around each frame stamp.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Mapping, Sequence

import numpy as np

from roboseg.errors import RobosegError

#: Named subsets -> fraction of all frames (None: every moving frame).
SUBSETS: dict[str, float | None] = {"full": None, "medium": 0.04, "large": 0.08}
PHASES = ("all", "draped", "undraped")
DEFAULT_SPLITS: dict[str, list[str]] = {"val": ["*val*"], "test": ["*test*"]}


def joint_speed_at(stamps_ns: np.ndarray, q: np.ndarray, query_ns: np.ndarray) -> np.ndarray:
    """Largest absolute joint speed (units of ``q`` per second) at each query stamp.

    ``stamps_ns`` [N] sorted unique int64 ns, ``q`` [N, D] joint positions. The velocity of a
    query is the finite difference of the sample interval containing it (the first/last
    interval outside the samples); fewer than two samples give speed 0.
    """
    query_ns = np.atleast_1d(np.asarray(query_ns, dtype=np.int64))
    q = np.asarray(q, dtype=np.float64).reshape(len(stamps_ns), -1)
    if len(stamps_ns) < 2:
        return np.zeros(len(query_ns))
    dt = np.diff(stamps_ns).astype(np.float64) * 1e-9
    velocity = np.diff(q, axis=0) / dt[:, None]  # [N-1, D]
    interval = np.clip(np.searchsorted(stamps_ns, query_ns, side="right") - 1, 0, len(dt) - 1)
    return np.abs(velocity[interval]).max(axis=1) if q.shape[1] else np.zeros(len(query_ns))


def thin_evenly(candidates: np.ndarray, count: int) -> np.ndarray:
    """``count`` entries of ``candidates`` spread evenly (centre of each of ``count`` equal
    runs); all of them when ``count`` is at least their number."""
    candidates = np.asarray(candidates)
    n = len(candidates)
    if count >= n:
        return candidates.copy()
    if count <= 0:
        return candidates[:0]
    picks = ((np.arange(count) + 0.5) * n / count).astype(np.int64)
    return candidates[picks]


def subset_fraction(subset: str, fraction: float | None) -> float | None:
    """Fraction of frames to keep: the explicit ``fraction`` or the named ``subset``'s."""
    if fraction is not None:
        fraction = float(fraction)
        if not 0.0 < fraction <= 1.0:
            raise RobosegError(f"subset_fraction must be in (0, 1], got {fraction}")
        return fraction
    if subset not in SUBSETS:
        raise RobosegError(f"subset must be one of {sorted(SUBSETS)}, got {subset!r}")
    return SUBSETS[subset]


def target_count(frames_total: int, fraction: float | None) -> int | None:
    """Frames to keep out of ``frames_total`` (None: no thinning); at least 1 if any."""
    if fraction is None:
        return None
    return max(1, round(fraction * frames_total)) if frames_total else 0


def phase_mask(stamps_ns: np.ndarray, phase: str, draped_from_ns: int | None) -> np.ndarray:
    """Bool [N]: frames in the drape ``phase`` (draped = stamp >= ``draped_from_ns``)."""
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    if phase not in PHASES:
        raise RobosegError(f"phase must be one of {PHASES}, got {phase!r}")
    if phase == "all":
        return np.ones(len(stamps_ns), dtype=bool)
    draped = (
        np.zeros(len(stamps_ns), dtype=bool)
        if draped_from_ns is None
        else stamps_ns >= int(draped_from_ns)
    )
    return draped if phase == "draped" else ~draped


def assign_split(file_name: str, splits: Mapping[str, Sequence[str]] | None = None) -> str:
    """Split of a recording: the first split with a glob matching ``file_name``, else train."""
    for split, patterns in (DEFAULT_SPLITS if splits is None else splits).items():
        if any(fnmatch.fnmatch(file_name, str(p)) for p in patterns):
            return str(split)
    return "train"
