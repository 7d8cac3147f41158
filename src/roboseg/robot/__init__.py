"""Robot model: URDF → serial kinematic chain + link meshes, batched FK in torch, decimation."""

from .default import default_urdf_path
from .model import RobotModel, load_robot

__all__ = ["RobotModel", "default_urdf_path", "load_robot"]
