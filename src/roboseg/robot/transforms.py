"""Small pure functions for rigid transforms of the kinematic chain (metres, radians).

URDF ``rpy`` is roll about x, then pitch about y, then yaw about z, all about the fixed parent
axes: ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``. A joint's motion is
``M(q) = I + f1(q) A + f2(q) A2`` with, for a revolute joint about unit axis ``a`` (Rodrigues),
``A = [a]x``, ``A2 = [a]x^2``, ``f1 = sin q``, ``f2 = 1 - cos q``, and for a prismatic joint
``A`` = translation along ``a``, ``f1 = q``, ``f2 = 0``.
"""

from __future__ import annotations

import numpy as np
import torch


def rpy_matrix(rpy: np.ndarray) -> np.ndarray:
    """Rotation [3, 3] of URDF roll-pitch-yaw angles (rad): ``Rz(y) @ Ry(p) @ Rx(r)``."""
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def origin_matrix(xyz: np.ndarray, rpy: np.ndarray) -> np.ndarray:
    """Homogeneous ``T`` [4, 4] of a URDF ``<origin xyz rpy>``: ``p_parent = T @ p_child``."""
    T = np.eye(4)
    T[:3, :3] = rpy_matrix(rpy)
    T[:3, 3] = np.asarray(xyz, dtype=np.float64)
    return T


def skew(a: np.ndarray) -> np.ndarray:
    """Cross-product matrix [3, 3]: ``skew(a) @ v == a × v``."""
    x, y, z = (float(v) for v in a)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def motion_basis(joint_type: str, axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(A, A2)`` [4, 4] of the joint motion ``M(q) = I + f1(q) A + f2(q) A2`` (module doc)."""
    A, A2 = np.zeros((4, 4)), np.zeros((4, 4))
    if joint_type in ("revolute", "continuous"):
        K = skew(axis)
        A[:3, :3], A2[:3, :3] = K, K @ K
    elif joint_type == "prismatic":
        A[:3, 3] = axis
    return A, A2


def motion_coefficients(
    q: torch.Tensor, revolute: torch.Tensor, prismatic: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(f1, f2)`` of joint values ``q`` [..., N] per joint kind masks [N] (module doc)."""
    zero = torch.zeros_like(q)
    f1 = torch.where(revolute, torch.sin(q), torch.where(prismatic, q, zero))
    f2 = torch.where(revolute, 1.0 - torch.cos(q), zero)
    return f1, f2
