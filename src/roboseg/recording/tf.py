"""Rigid transforms of ``/tf_static``: quaternion <-> matrix and chained frame lookup.

A ``geometry_msgs/TransformStamped`` with ``header.frame_id = parent`` and
``child_frame_id = child`` holds ``T_parent_child``: it maps points in the child frame into the
parent frame (translation in metres, rotation as a unit quaternion ``(x, y, z, w)``).
"""

from __future__ import annotations

from collections import deque

import numpy as np

from roboseg.errors import RecordingError


def quaternion_to_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)`` -> 3x3 rotation matrix (normalises the input)."""
    x, y, z, w = np.asarray(q_xyzw, dtype=np.float64) / np.linalg.norm(q_xyzw)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """3x3 rotation matrix -> unit quaternion ``(x, y, z, w)`` with ``w >= 0``."""
    R = np.asarray(R, dtype=np.float64)
    trace = np.trace(R)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, s / 4]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [s / 4, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 1] + R[1, 0]) / s, s / 4, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, s / 4, (R[1, 0] - R[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 homogeneous matrix from a 3x3 rotation and a translation (metres)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform: ``T_a_b -> T_b_a``."""
    R, t = T[:3, :3], T[:3, 3]
    return make_transform(R.T, -R.T @ t)


def lookup_transform(
    edges: dict[tuple[str, str], np.ndarray], target: str, source: str, *, where: str = "tf"
) -> np.ndarray:
    """``T_target_source`` by chaining (and inverting) ``{(parent, child): T_parent_child}``.

    Raises :class:`RecordingError` naming both frames when they are not connected.
    """
    graph: dict[str, list[tuple[str, np.ndarray]]] = {}
    for (parent, child), T in edges.items():
        graph.setdefault(child, []).append((parent, T))  # child -> parent: T_parent_child
        graph.setdefault(parent, []).append((child, invert_transform(T)))
    if target == source:
        return np.eye(4)
    # Breadth-first search from the source; T_frame_source accumulates along the path.
    found: dict[str, np.ndarray] = {source: np.eye(4)}
    queue = deque([source])
    while queue:
        frame = queue.popleft()
        for neighbour, T_neighbour_frame in graph.get(frame, []):
            if neighbour not in found:
                found[neighbour] = T_neighbour_frame @ found[frame]
                if neighbour == target:
                    return found[neighbour]
                queue.append(neighbour)
    raise RecordingError(
        f"{where}: no transform chain from frame '{source}' to '{target}' "
        f"(frames: {', '.join(sorted(graph)) or 'none'})"
    )
