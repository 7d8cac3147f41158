"""Continuous 9D pose of the robot base in a camera frame, and a batched look-at.

The optimised pose is ``T_cam_base`` (maps base-frame points into the OpenCV optical frame of the
left camera, ``p_cam = T_cam_base @ p_base``; metres). It is parametrised by 9 numbers
``[a1 (3), a2 (3), t (3)]``: ``a1, a2`` are the first two *columns* of the rotation matrix in the
6D representation of Zhou et al. (CVPR 2019), mapped back to SO(3) by Gram–Schmidt, and ``t`` is
the translation in metres. Every map here is batched over leading dimensions and differentiable.
"""

from __future__ import annotations

import torch

from roboseg.errors import CameraError

__all__ = [
    "gram_schmidt",
    "rotation_6d_to_matrix",
    "matrix_to_rotation_6d",
    "pose9d_to_matrix",
    "matrix_to_pose9d",
    "invert_transform",
    "transform_points",
    "look_at_T_cam_base",
    "rotation_angle",
]

_EPS = 1e-8


def gram_schmidt(a1: torch.Tensor, a2: torch.Tensor) -> torch.Tensor:
    """Orthonormal frame ``[b1 b2 b3]`` (as columns, ``[..., 3, 3]``) from two vectors ``[..., 3]``.

    ``b1 = a1/|a1|``, ``b2 = (a2 - (b1·a2) b1)/|…|``, ``b3 = b1 × b2`` (right-handed).
    """
    b1 = a1 / a1.norm(dim=-1, keepdim=True).clamp_min(_EPS)
    a2_perp = a2 - (b1 * a2).sum(dim=-1, keepdim=True) * b1
    b2 = a2_perp / a2_perp.norm(dim=-1, keepdim=True).clamp_min(_EPS)
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-1)


def rotation_6d_to_matrix(d6: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``[..., 3, 3]`` from 6D vectors ``[..., 6]`` = first two columns."""
    return gram_schmidt(d6[..., 0:3], d6[..., 3:6])


def matrix_to_rotation_6d(R: torch.Tensor) -> torch.Tensor:
    """6D vectors ``[..., 6]`` (first two columns of ``R`` ``[..., 3, 3]``, concatenated)."""
    return torch.cat([R[..., :, 0], R[..., :, 1]], dim=-1)


def pose9d_to_matrix(pose: torch.Tensor) -> torch.Tensor:
    """Homogeneous transforms ``[..., 4, 4]`` from 9D poses ``[..., 9]`` (6D rotation, t in m)."""
    R = rotation_6d_to_matrix(pose[..., :6])
    T = torch.zeros(*pose.shape[:-1], 4, 4, dtype=pose.dtype, device=pose.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = pose[..., 6:9]
    T[..., 3, 3] = 1.0
    return T


def matrix_to_pose9d(T: torch.Tensor) -> torch.Tensor:
    """9D poses ``[..., 9]`` from homogeneous transforms ``[..., 4, 4]``."""
    return torch.cat([matrix_to_rotation_6d(T[..., :3, :3]), T[..., :3, 3]], dim=-1)


def invert_transform(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms ``[..., 4, 4]`` (``T_b_a`` → ``T_a_b``): ``[Rᵀ, −Rᵀt]``."""
    R_t = T[..., :3, :3].transpose(-1, -2)
    out = torch.zeros_like(T)
    out[..., :3, :3] = R_t
    out[..., :3, 3] = -(R_t @ T[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def transform_points(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply ``T`` ``[..., 4, 4]`` to ``points`` ``[..., N, 3]`` (broadcast over leading dims)."""
    return points @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]


def look_at_T_cam_base(
    eye: torch.Tensor,
    centre: torch.Tensor,
    roll: torch.Tensor,
    up: tuple[float, float, float] = (0.0, 0.0, 1.0),
) -> torch.Tensor:
    """``T_cam_base`` ``[..., 4, 4]`` of OpenCV cameras at ``eye`` looking at ``centre``.

    ``eye``, ``centre``: ``[..., 3]`` in the base frame (m); ``roll``: ``[...]`` rad, a rotation of
    the camera about its own optical axis (z). With ``roll = 0`` the camera's ``-y`` (image up) lies
    in the plane of the optical axis and the base-frame ``up`` vector; where the axis is parallel
    to ``up``, the base x axis is used instead so the frame stays defined.
    """
    z = centre - eye
    dist = z.norm(dim=-1, keepdim=True)
    if bool((dist < 1e-9).any()):
        raise CameraError("look_at: eye and centre coincide; the viewing direction is undefined")
    z = z / dist
    up_t = torch.tensor(up, dtype=eye.dtype, device=eye.device).expand_as(z)
    x = torch.linalg.cross(z, up_t, dim=-1)
    degenerate = x.norm(dim=-1, keepdim=True) < 1e-6
    alt = torch.tensor((1.0, 0.0, 0.0), dtype=eye.dtype, device=eye.device).expand_as(z)
    x = torch.where(degenerate, torch.linalg.cross(z, alt, dim=-1), x)
    x = x / x.norm(dim=-1, keepdim=True)
    y = torch.linalg.cross(z, x, dim=-1)
    c, s = torch.cos(roll)[..., None], torch.sin(roll)[..., None]
    # R_base_cam' = R_base_cam @ Rz(roll): columns x' = c·x + s·y, y' = -s·x + c·y.
    x_r = c * x + s * y
    y_r = -s * x + c * y
    R_base_cam = torch.stack([x_r, y_r, z], dim=-1)
    T_base_cam = torch.zeros(*eye.shape[:-1], 4, 4, dtype=eye.dtype, device=eye.device)
    T_base_cam[..., :3, :3] = R_base_cam
    T_base_cam[..., :3, 3] = eye
    T_base_cam[..., 3, 3] = 1.0
    return invert_transform(T_base_cam)


def rotation_angle(R_a: torch.Tensor, R_b: torch.Tensor) -> torch.Tensor:
    """Geodesic angle (rad) between rotations ``[..., 3, 3]``: ``acos((tr(R_aᵀR_b) − 1)/2)``."""
    tr = (R_a.transpose(-1, -2) @ R_b).diagonal(dim1=-2, dim2=-1).sum(-1)
    return torch.acos(((tr - 1.0) / 2.0).clamp(-1.0, 1.0))
