"""Breathing-compensated drilling command and its minimum-norm joint velocities.

Paper, Methods "Sensorimotor breathing compensation": the joint velocities solve the QP
``min ½ q̇ᵀq̇  s.t.  L_J ≤ J q̇ ≤ U_J`` with ``L_J = U_J = [v; ω]`` (equality bounds), where ``J``
(6×D, base frame, at the drill tip) stacks linear over angular rows and

``v = R [k x_ep; k y_ep; ż_tip − c (f_d − f_m)] + [0; 0; ż(t)]``

with the entry point ``(x_ep, y_ep)`` in the tip frame (m), gains ``k`` (1/s) and ``c`` (m/(N·s)),
feed velocity ``ż_tip`` along the tool axis (m/s), desired/measured forces ``f_d``/``f_m`` (N),
``R = R_base_tip`` and the breathing velocity ``ż(t)`` (m/s, base z unless another axis is given).
With equality bounds the QP is the minimum-norm solution of ``J q̇ = [v; ω]``: ``q̇ = J⁺ [v; ω]``,
here computed as damped least squares ``Jᵀ (J Jᵀ + λ² I)⁻¹ [v; ω]`` (``λ = 0`` → exact
pseudo-inverse via ``lstsq``; a small ``λ`` bounds ``|q̇|`` near singularities at the cost of an
error ``O(λ²/σ_min²)`` in the achieved twist).

Sign convention of the force term, taken literally from the paper: a force deficit
``f_m < f_d`` moves the tip along ``−z_tip``, i.e. the tip frame's z axis points out of the tissue.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

#: Breathing direction in the robot base frame (the paper's ``[0; 0; ż(t)]``).
BASE_Z = np.array([0.0, 0.0, 1.0])


def compensated_linear_velocity(
    R_base_tip: np.ndarray,
    entry_point_tip: np.ndarray,
    feed_velocity: float,
    f_desired: float,
    f_measured: float,
    k: float,
    c: float,
    breathing_velocity: float = 0.0,
    breathing_axis: np.ndarray = BASE_Z,
) -> np.ndarray:
    """Linear velocity ``v`` (m/s, base frame) of the breathing-compensated command.

    ``entry_point_tip``: entry point in the tip frame (its x, y are used; m). ``breathing_velocity``
    is ``ż(t)`` from the breathing model along ``breathing_axis`` (unit vector, base frame).
    """
    ep = np.asarray(entry_point_tip, dtype=np.float64)
    local = np.array([k * ep[0], k * ep[1], feed_velocity - c * (f_desired - f_measured)])
    return np.asarray(R_base_tip, np.float64) @ local + breathing_velocity * np.asarray(
        breathing_axis, np.float64
    )


def alignment_angular_velocity(
    tool_axis: np.ndarray, planned_axis: np.ndarray, gain: float
) -> np.ndarray:
    """Angular velocity (rad/s, base frame) turning ``tool_axis`` onto ``planned_axis``.

    ``ω = gain · θ · n`` with the rotation angle ``θ = atan2(|a × d|, a · d)`` and axis
    ``n = (a × d) / |a × d|`` (both inputs normalised first). Zero when aligned; for anti-parallel
    axes any perpendicular axis is valid and one is chosen deterministically.
    """
    a = np.asarray(tool_axis, np.float64)
    d = np.asarray(planned_axis, np.float64)
    a, d = a / np.linalg.norm(a), d / np.linalg.norm(d)
    cross = np.cross(a, d)
    s, cth = float(np.linalg.norm(cross)), float(a @ d)
    theta = np.arctan2(s, cth)
    if s < 1e-12:
        if cth > 0:
            return np.zeros(3)
        helper = np.eye(3)[int(np.argmin(np.abs(a)))]
        cross = np.cross(a, helper)
        s = float(np.linalg.norm(cross))
    return gain * theta * cross / s


def min_norm_joint_velocities(J: np.ndarray, twist: np.ndarray, damping: float = 0.0) -> np.ndarray:
    """Minimum-norm ``q̇`` with ``J q̇ = twist`` (the paper's QP with equal bounds).

    ``J``: ``[6, D]`` (rows: linear then angular, base frame); ``twist``: ``[v; ω]`` ``[6]``.
    ``damping`` λ > 0 gives damped least squares ``Jᵀ(JJᵀ + λ²I)⁻¹ twist``.
    """
    J = np.asarray(J, np.float64)
    twist = np.asarray(twist, np.float64)
    if damping <= 0.0:
        return np.linalg.lstsq(J, twist, rcond=None)[0]
    m = J.shape[0]
    return J.T @ np.linalg.solve(J @ J.T + damping**2 * np.eye(m), twist)


def vee(S: np.ndarray) -> np.ndarray:
    """Vector ``w`` of a (near-)skew-symmetric 3×3 matrix ``S ≈ [w]×`` (its skew part is used)."""
    A = 0.5 * (S - S.T)
    return np.array([A[2, 1], A[0, 2], A[1, 0]])


def geometric_jacobian(
    fk: Callable[[np.ndarray], np.ndarray], q: np.ndarray, eps: float = 1e-6
) -> np.ndarray:
    """Base-frame geometric Jacobian ``[6, D]`` of a tool pose by central finite differences.

    ``fk`` maps joint vectors ``[B, D]`` (rad) to tool poses ``T_base_tool`` ``[B, 4, 4]``; it is
    called once with the ``2D`` perturbed configurations. Linear rows are ``∂p/∂q_i``; angular
    rows are ``vee(∂R/∂q_i Rᵀ)``.
    """
    q = np.asarray(q, np.float64).ravel()
    D = q.shape[0]
    dq = eps * np.eye(D)
    Q = np.concatenate([q + dq, q - dq, q[None]], axis=0)
    T = np.asarray(fk(Q), np.float64)
    T_plus, T_minus, T0 = T[:D], T[D : 2 * D], T[2 * D]
    J = np.empty((6, D))
    J[:3] = ((T_plus[:, :3, 3] - T_minus[:, :3, 3]) / (2 * eps)).T
    for i in range(D):
        dR = (T_plus[i, :3, :3] - T_minus[i, :3, :3]) / (2 * eps)
        J[3:, i] = vee(dR @ T0[:3, :3].T)
    return J
