"""Breathing-motion model: a 3-harmonic Fourier series fitted over a sliding horizon.

Paper, Methods "Sensorimotor breathing compensation":
``z(t) = a0 + Σ_{n=1..3} a_n cos(n ω0 t) + b_n sin(n ω0 t)``, fitted to the observed motion
``z̃(t)`` over the last ``T0 = 15 s`` by least squares. For a fixed ``ω0`` the coefficients are a
linear least-squares problem; ``ω0`` (rad/s) is found by a 1-D search: a coarse grid over
``[omega_min, omega_max]`` followed by a bounded scalar refinement around the best grid point.
Because a series at ``ω0 / k`` also contains ``ω0`` as its k-th harmonic, the search prefers the
highest multiple of the best frequency that fits as well (see :func:`fit_breathing`).

Signals may be scalar (``[N]``) or ``D``-dimensional (``[N, D]``, e.g. ML/CC/AP positions in
metres); all axes share ``ω0`` and have their own coefficients. Times are seconds.

**Amplitude** (as in the paper's Table S1): half the peak-to-peak excursion of the fitted periodic
part over one period, per axis, in the signal's units. The **signed amplitude** carries the sign of
the axis's in-phase correlation with a reference axis (default: the last one, AP): negative means
the axis moves opposite to the reference axis during a breath.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

log = logging.getLogger(__name__)

N_HARMONICS = 3
HORIZON_S = 15.0


def fourier_design(t: np.ndarray, omega0: float, n_harmonics: int = N_HARMONICS) -> np.ndarray:
    """Design matrix ``[N, 1 + 2n]``: columns ``1, cos(ω0 t), sin(ω0 t), …, sin(nω0 t)``."""
    t = np.asarray(t, dtype=np.float64).reshape(-1, 1)
    n = np.arange(1, n_harmonics + 1, dtype=np.float64).reshape(1, -1)
    phase = omega0 * t * n
    cols = np.empty((t.shape[0], 1 + 2 * n_harmonics))
    cols[:, 0] = 1.0
    cols[:, 1::2] = np.cos(phase)
    cols[:, 2::2] = np.sin(phase)
    return cols


def fit_coefficients(
    t: np.ndarray, z: np.ndarray, omega0: float, n_harmonics: int = N_HARMONICS
) -> tuple[np.ndarray, float]:
    """Least-squares Fourier coefficients for fixed ``ω0``.

    ``z``: ``[N, D]``. Returns (``coef [1 + 2n, D]`` ordered ``a0, a1, b1, a2, b2, …``, summed
    squared residual over all axes).
    """
    X = fourier_design(t, omega0, n_harmonics)
    coef, *_ = np.linalg.lstsq(X, z, rcond=None)
    r = z - X @ coef
    return coef, float(np.sum(r * r))


def _grid_costs(t: np.ndarray, z: np.ndarray, omegas: np.ndarray, n_harmonics: int) -> np.ndarray:
    """Residual sum of squares at every grid frequency (batched QR, one design per frequency)."""
    X = np.stack([fourier_design(t, w, n_harmonics) for w in omegas])  # [G, N, P]
    Q, _ = np.linalg.qr(X)  # reduced: [G, N, P]
    proj = np.einsum("gnp,nd->gpd", Q, z)
    return float(np.sum(z * z)) - np.sum(proj * proj, axis=(1, 2))


@dataclass(frozen=True)
class BreathingFit:
    """Result of :func:`fit_breathing`. When ``fitted`` is False, ``reason`` says why and the
    numeric fields are empty; ``predict``/``velocity`` must not be called then."""

    fitted: bool
    reason: str = ""
    omega0: float = float("nan")  # rad/s
    coef: np.ndarray | None = None  # [1 + 2n, D]: a0, a1, b1, a2, b2, a3, b3
    t_ref: float = 0.0  # s; the series is evaluated at t - t_ref
    rms_residual: float = float("nan")  # per sample and axis, signal units
    n_samples: int = 0
    span: float = 0.0  # s, time covered by the fitted samples

    @property
    def period(self) -> float:
        """Breathing period ``2π / ω0`` in seconds."""
        return 2.0 * np.pi / self.omega0

    @property
    def n_harmonics(self) -> int:
        assert self.coef is not None
        return (self.coef.shape[0] - 1) // 2

    def _require(self) -> np.ndarray:
        if not self.fitted or self.coef is None:
            raise RuntimeError(f"breathing model is not fitted: {self.reason}")
        return self.coef

    def predict(self, t: np.ndarray | float) -> np.ndarray:
        """``z(t)``: ``[N, D]`` for an array of times, ``[D]`` for a scalar time."""
        coef = self._require()
        tt = np.atleast_1d(np.asarray(t, dtype=np.float64)) - self.t_ref
        z = fourier_design(tt, self.omega0, self.n_harmonics) @ coef
        return z[0] if np.ndim(t) == 0 else z

    def velocity(self, t: np.ndarray | float) -> np.ndarray:
        """``ż(t)`` (signal units per second), same shapes as :meth:`predict`."""
        coef = self._require()
        tt = np.atleast_1d(np.asarray(t, dtype=np.float64)).reshape(-1, 1) - self.t_ref
        n = np.arange(1, self.n_harmonics + 1, dtype=np.float64).reshape(1, -1)
        w = self.omega0 * n
        d = np.empty((tt.shape[0], coef.shape[0]))
        d[:, 0] = 0.0
        d[:, 1::2] = -w * np.sin(w * tt)
        d[:, 2::2] = w * np.cos(w * tt)
        v = d @ coef
        return v[0] if np.ndim(t) == 0 else v

    def _one_period(self, samples: int = 512) -> np.ndarray:
        t = self.t_ref + np.linspace(0.0, self.period, samples, endpoint=False)
        return self.predict(t)

    def amplitudes(self) -> np.ndarray:
        """Half peak-to-peak of the fitted periodic part per axis, ``[D]`` (signal units)."""
        z = self._one_period()
        return 0.5 * (z.max(axis=0) - z.min(axis=0))

    def signed_amplitudes(self, reference_axis: int = -1) -> np.ndarray:
        """:meth:`amplitudes` signed by each axis's in-phase correlation with ``reference_axis``."""
        z = self._one_period()
        z = z - z.mean(axis=0)
        ref = z[:, reference_axis]
        sign = np.where(z.T @ ref >= 0.0, 1.0, -1.0)
        return sign * self.amplitudes()


def fit_breathing(
    t: np.ndarray,
    z: np.ndarray,
    omega_min: float = 2 * np.pi * 0.1,
    omega_max: float = 2 * np.pi * 1.0,
    grid_step: float | None = None,
    n_harmonics: int = N_HARMONICS,
    min_samples: int = 20,
    min_periods: float = 1.5,
    min_span: float = 0.0,
    harmonic_tolerance: float = 0.05,
    omega_guess: float | None = None,
) -> BreathingFit:
    """Fit the breathing model to samples ``(t [N] s, z [N] or [N, D])`` (all given samples).

    ``ω0`` is searched in ``[omega_min, omega_max]`` rad/s, restricted so that the samples span at
    least ``min_periods`` periods (and at least ``min_span`` seconds). The grid step defaults to a
    fifth of the narrowest cost dip, ``2π / (5 n T)`` for span ``T``; the best grid point is
    refined by a bounded scalar minimisation within ± one step. If a multiple ``k ω0`` (k = 2 … n)
    fits within
    ``harmonic_tolerance`` (relative cost), it is taken instead (a series at ``ω0`` reproduces
    one at ``k ω0``). ``omega_guess`` (e.g. the previous fit of a sliding window) narrows the
    grid to ± 15 % around it. Returns a not-fitted :class:`BreathingFit` with a reason when there
    are fewer than ``min_samples`` finite samples or the span is too short.
    """
    t = np.asarray(t, dtype=np.float64).ravel()
    z_arr = np.asarray(z, dtype=np.float64)
    z2 = z_arr.reshape(len(t), -1) if z_arr.ndim == 1 else z_arr
    if z2.shape[0] != t.shape[0]:
        raise ValueError(f"{t.shape[0]} times but {z2.shape[0]} samples")
    finite = np.isfinite(t) & np.all(np.isfinite(z2), axis=1)
    t, z2 = t[finite], z2[finite]
    n_params = 1 + 2 * n_harmonics
    if len(t) < max(min_samples, n_params + 1):
        return BreathingFit(
            False, f"{len(t)} samples, need at least {max(min_samples, n_params + 1)}"
        )
    span = float(t.max() - t.min())
    if span < min_span:
        return BreathingFit(False, f"horizon {span:.2f} s shorter than {min_span:.2f} s")
    lo = max(omega_min, 2 * np.pi * min_periods / span) if span > 0 else np.inf
    if lo >= omega_max:
        return BreathingFit(
            False,
            f"horizon {span:.2f} s too short for {min_periods} periods below {omega_max:.3f} rad/s",
        )
    t_ref = float(t.max())
    tt = t - t_ref
    zc = z2 - z2.mean(axis=0)  # the constant column absorbs the mean anyway; improves conditioning
    step = grid_step or 2 * np.pi / (5 * n_harmonics * span)
    g_lo, g_hi = lo, omega_max
    if omega_guess is not None and lo <= omega_guess <= omega_max:
        g_lo, g_hi = max(lo, 0.85 * omega_guess), min(omega_max, 1.15 * omega_guess)
    omegas = np.arange(g_lo, g_hi + step, step)
    omegas = omegas[omegas <= g_hi]
    costs = _grid_costs(tt, zc, omegas, n_harmonics)
    energy = float(np.sum(zc * zc))

    def refine(w0: float) -> tuple[float, float]:
        a, b = max(lo, w0 - step), min(omega_max, w0 + step)
        res = minimize_scalar(
            lambda w: fit_coefficients(tt, zc, w, n_harmonics)[1],
            bounds=(a, b),
            method="bounded",
            options={"xatol": 1e-7},
        )
        return float(res.x), float(res.fun)

    best_w, best_cost = refine(float(omegas[int(np.argmin(costs))]))
    for k in range(n_harmonics, 1, -1):
        wk = k * best_w
        if wk > omega_max:
            continue
        wk, ck = refine(wk)
        if ck <= best_cost * (1.0 + harmonic_tolerance) + 1e-12 * energy:
            log.debug("breathing fit: %.4f rad/s preferred over its subharmonic %.4f", wk, best_w)
            best_w, best_cost = wk, ck
            break
    coef, sse = fit_coefficients(tt, z2, best_w, n_harmonics)
    rms = float(np.sqrt(sse / z2.size))
    return BreathingFit(True, "", best_w, coef, t_ref, rms, int(len(t)), span)


class BreathingModel:
    """Online breathing model over a sliding window of the last ``horizon`` seconds.

    ``update(t, z)`` appends a sample (``z``: scalar or ``[D]``) and drops samples older than
    ``t - horizon``; the model is refitted at most every ``refit_interval`` seconds, once the
    window spans ``min_span`` seconds (default half the horizon), searching ``ω0`` near the
    previous estimate once a fit over a nearly full window exists.
    ``predict``/``velocity`` return ``None`` while no fit exists (see :attr:`fit`'s ``reason``).
    """

    def __init__(
        self,
        horizon: float = HORIZON_S,
        refit_interval: float = 0.5,
        min_span: float | None = None,
        **fit_kwargs: float,
    ) -> None:
        self.horizon = float(horizon)
        self.min_span = 0.5 * self.horizon if min_span is None else float(min_span)
        self.refit_interval = float(refit_interval)
        self.fit_kwargs = fit_kwargs
        self._t: deque[float] = deque()
        self._z: deque[np.ndarray] = deque()
        self._last_fit_t = -np.inf
        self.fit: BreathingFit = BreathingFit(False, "no samples yet")

    def __len__(self) -> int:
        return len(self._t)

    def update(self, t: float, z: float | np.ndarray) -> BreathingFit:
        """Add one sample at time ``t`` (s); refit if due. Returns the current fit."""
        z = np.atleast_1d(np.asarray(z, dtype=np.float64))
        if not np.all(np.isfinite(z)) or not np.isfinite(t):
            log.debug("breathing model: non-finite sample at t=%s skipped", t)
            return self.fit
        if self._t and t <= self._t[-1]:
            log.debug("breathing model: out-of-order sample at t=%s skipped", t)
            return self.fit
        self._t.append(float(t))
        self._z.append(z)
        while self._t and self._t[0] < t - self.horizon:
            self._t.popleft()
            self._z.popleft()
        if t - self._last_fit_t >= self.refit_interval:
            self.refit()
        return self.fit

    def refit(self) -> BreathingFit:
        """Fit the current window now."""
        if not self._t:
            self.fit = BreathingFit(False, "no samples yet")
            return self.fit
        self._last_fit_t = self._t[-1]
        settled = self.fit.fitted and self.fit.span >= 0.9 * self.horizon
        self.fit = fit_breathing(
            np.asarray(self._t),
            np.stack(self._z),
            min_span=self.min_span,
            omega_guess=self.fit.omega0 if settled else None,
            **self.fit_kwargs,
        )
        return self.fit

    def predict(self, t: float) -> np.ndarray | None:
        """``z(t)`` ``[D]``, or ``None`` when not fitted."""
        return self.fit.predict(t) if self.fit.fitted else None

    def velocity(self, t: float) -> np.ndarray | None:
        """``ż(t)`` ``[D]`` per second, or ``None`` when not fitted."""
        return self.fit.velocity(t) if self.fit.fitted else None
