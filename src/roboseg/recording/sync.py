"""Synchronisation of joint states to image stamps (linear interpolation with a tolerance)."""

from __future__ import annotations

import numpy as np


def prepare_samples(stamps_ns: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sort samples by stamp and keep the last of duplicated stamps.

    ``stamps_ns`` [N] int64 nanoseconds, ``values`` [N, D] -> (stamps [M], values [M, D]).
    """
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 2:
        values = values.reshape(len(stamps_ns), -1)
    order = np.argsort(stamps_ns, kind="stable")
    stamps_ns, values = stamps_ns[order], values[order]
    keep = np.ones(len(stamps_ns), dtype=bool)
    keep[:-1] = stamps_ns[1:] != stamps_ns[:-1]
    return stamps_ns[keep], values[keep]


def interpolate_at(
    stamps_ns: np.ndarray, values: np.ndarray, query_ns: np.ndarray, tolerance_ns: int
) -> tuple[np.ndarray, np.ndarray]:
    """Linearly interpolate samples to query stamps.

    ``stamps_ns`` [N] sorted unique int64 ns, ``values`` [N, D], ``query_ns`` [Q] int64 ns.
    A query is valid when a sample at or before it and a sample at or after it both lie within
    ``tolerance_ns`` (an exact hit needs only itself). Returns (values [Q, D] with NaN where
    invalid, valid [Q] bool).
    """
    query_ns = np.atleast_1d(np.asarray(query_ns, dtype=np.int64))
    n, d = values.shape if values.ndim == 2 else (len(values), 1)
    values = values.reshape(n, d)
    out = np.full((len(query_ns), d), np.nan)
    valid = np.zeros(len(query_ns), dtype=bool)
    if n == 0:
        return out, valid
    after = np.searchsorted(stamps_ns, query_ns, side="left")  # first sample >= query
    exact = (after < n) & (stamps_ns[np.minimum(after, n - 1)] == query_ns)
    before = np.where(exact, after, after - 1)
    has_both = (before >= 0) & (after < n)
    lo = np.clip(before, 0, n - 1)
    hi = np.clip(after, 0, n - 1)
    gap_lo = query_ns - stamps_ns[lo]
    gap_hi = stamps_ns[hi] - query_ns
    valid = has_both & (gap_lo <= tolerance_ns) & (gap_hi <= tolerance_ns)
    span = (stamps_ns[hi] - stamps_ns[lo]).astype(np.float64)
    weight = np.divide(gap_lo.astype(np.float64), span, out=np.zeros_like(span), where=span > 0)
    interp = values[lo] + weight[:, None] * (values[hi] - values[lo])
    out[valid] = interp[valid]
    return out, valid
