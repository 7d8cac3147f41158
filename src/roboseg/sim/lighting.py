"""Lighting and camera exposure that drift within a recording.

Each quantity is a per-recording base value times a slow drift ``1 + Σ_k a_k sin(ω_k t + φ_k)``,
plus, with some probability, one step change (a lamp switched or moved). Light directions are
unit vectors in the world frame (z up) pointing towards the light.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def drift(t: float, amplitudes: np.ndarray, omegas: np.ndarray, phases: np.ndarray) -> float:
    """Multiplicative drift ``1 + Σ a_k sin(ω_k t + φ_k)`` at time ``t`` (s)."""
    return 1.0 + float(np.sum(amplitudes * np.sin(omegas * t + phases)))


@dataclass(frozen=True)
class LightingState:
    """Lighting of one frame: key light direction (world), its strength, ambient share,
    exposure gain and per-channel white balance."""

    light_dir: np.ndarray
    intensity: float
    ambient: float
    exposure: float
    white_balance: np.ndarray


@dataclass(frozen=True)
class Lighting:
    """Per-recording lighting model; :meth:`at` gives the state at time ``t`` (s)."""

    azimuth: float
    elevation: float
    intensity: float
    ambient: float
    exposure: float
    white_balance: np.ndarray
    amps: np.ndarray  # [4, K] drift amplitudes: intensity, exposure, azimuth (rad), wb
    omegas: np.ndarray  # [4, K] rad/s
    phases: np.ndarray  # [4, K]
    step_time: float  # s, inf if the lights never change abruptly
    step_gain: float

    def at(self, t: float) -> LightingState:
        az = self.azimuth + (drift(t, self.amps[2], self.omegas[2], self.phases[2]) - 1.0)
        el = self.elevation
        light = np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
        gain = self.step_gain if t >= self.step_time else 1.0
        wb_drift = drift(t, self.amps[3], self.omegas[3], self.phases[3])
        wb = self.white_balance * np.array([wb_drift, 1.0, 2.0 - wb_drift])
        return LightingState(
            light_dir=light,
            intensity=self.intensity
            * gain
            * drift(t, self.amps[0], self.omegas[0], self.phases[0]),
            ambient=self.ambient,
            exposure=self.exposure * drift(t, self.amps[1], self.omegas[1], self.phases[1]),
            white_balance=wb,
        )


def sample_lighting(rng: np.random.Generator, duration: float) -> Lighting:
    """Random lighting for a recording of ``duration`` seconds: key light 35–80° high,
    intensity ±25 %, exposure 0.7–1.2 drifting ±15 %, white balance ±10 % per channel,
    a 30 % chance of one step change of 0.6–1.5× at a random time."""
    k = 3
    amps = rng.uniform(0.0, 1.0, (4, k)) * np.array([[0.08], [0.05], [0.15], [0.02]])
    omegas = rng.uniform(0.05, 0.6, (4, k))
    phases = rng.uniform(0.0, 2.0 * math.pi, (4, k))
    step = rng.random() < 0.3
    return Lighting(
        azimuth=float(rng.uniform(-math.pi, math.pi)),
        elevation=float(rng.uniform(math.radians(35), math.radians(80))),
        intensity=float(rng.uniform(0.8, 1.25)),
        ambient=float(rng.uniform(0.25, 0.45)),
        exposure=float(rng.uniform(0.7, 1.2)),
        white_balance=rng.uniform(0.9, 1.1, 3),
        amps=amps,
        omegas=omegas,
        phases=phases,
        step_time=float(rng.uniform(0.2, 0.9) * duration) if step else math.inf,
        step_gain=float(rng.uniform(0.6, 1.5)),
    )
