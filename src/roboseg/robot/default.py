"""The built-in robot: a 7-DoF arm with the KUKA LBR Med 7's kinematics (joint names A1..A7,
links link_0..link_7 and link_ee, origins, axes and limits) whose links are approximated by
URDF primitives (cylinders with sphere caps), so no mesh files are needed."""

from __future__ import annotations

from pathlib import Path

_DEFAULT_URDF = Path(__file__).resolve().parent / "data" / "default_arm.urdf"


def default_urdf_path() -> Path:
    """Path of the shipped ``default_arm.urdf``."""
    return _DEFAULT_URDF
