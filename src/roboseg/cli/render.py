"""``roboseg-render``: binary silhouette (or overlay) of a robot pose in one camera.

``roboseg-render robot.urdf=PATH 'robot.joints=[...]' camera.width=W camera.height=H
'camera.K=[9 numbers]' 'T_cam_base=[16 numbers]' out=mask.png [image=PATH]`` (``conf/render.yaml``)
writes an 8-bit image (255 robot, 0 background; or the image with the robot tinted and outlined)
and prints its path.
"""

from __future__ import annotations

import logging
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from roboseg.camera import Intrinsics, StereoRig, look_at
from roboseg.cli._main import user_errors_exit
from roboseg.config import CONF_DIR
from roboseg.errors import CameraError, RobosegError, RobotModelError
from roboseg.render import render_hard
from roboseg.robot import load_robot

log = logging.getLogger("roboseg.render")

TINT_BGR = (60, 200, 60)  # overlay colour of the robot
TINT_ALPHA = 0.45
CONTOUR_BGR = (0, 255, 255)


def _numbers(value: Any, key: str, n: int | None, error: type[RobosegError]) -> np.ndarray:
    """``value`` as a float64 vector (of length ``n`` if given); ``error`` names ``key``."""
    try:
        seq = OmegaConf.to_container(value) if OmegaConf.is_config(value) else value
        arr = np.asarray(seq, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise error(f"{key} must be a list of numbers, got {value!r}") from None
    if n is not None and arr.size != n:
        raise error(f"{key} must have {n} numbers, got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise error(f"{key} must be finite, got {arr.tolist()}")
    return arr


def intrinsics_from_cfg(cfg: DictConfig) -> Intrinsics:
    """``camera.K`` at ``camera.width × camera.height``, or ZED 2i-like intrinsics if K is null."""
    try:
        width, height = int(cfg.camera.width), int(cfg.camera.height)
    except (TypeError, ValueError):
        raise CameraError(
            f"camera.width / camera.height must be integers, got "
            f"{cfg.camera.width!r} / {cfg.camera.height!r}"
        ) from None
    if cfg.camera.K is None:
        if width <= 0 or height <= 0:
            raise CameraError(f"camera size must be positive, got {width}x{height}")
        return StereoRig.zed2i_like(width, height).left
    return Intrinsics.from_K(_numbers(cfg.camera.K, "camera.K", 9, CameraError), width, height)


def pose_from_cfg(cfg: DictConfig) -> np.ndarray:
    """``T_cam_base`` [4, 4]: the given rigid transform, or a look-at from ``view``."""
    if cfg.T_cam_base is None:
        eye = _numbers(cfg.view.eye, "view.eye", 3, CameraError)
        target = _numbers(cfg.view.target, "view.target", 3, CameraError)
        return look_at(eye, target)
    T = _numbers(cfg.T_cam_base, "T_cam_base", 16, CameraError).reshape(4, 4)
    R = T[:3, :3]
    if not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(R @ R.T, np.eye(3), atol=1e-5):
        raise CameraError("T_cam_base must be a rigid transform (rotation, translation, 0 0 0 1)")
    if np.linalg.det(R) < 0:
        raise CameraError("T_cam_base has a reflection (det R = -1), not a rotation")
    return T


def render_mask(cfg: DictConfig) -> np.ndarray:
    """Silhouette [H, W] bool of ``cfg.robot`` at ``cfg.robot.joints`` seen by ``cfg.camera``."""
    urdf = cfg.robot.urdf
    if urdf is not None and not Path(str(urdf)).is_file():
        raise RobotModelError(f"robot.urdf: no such file {urdf}")
    robot = load_robot(None if urdf is None else str(urdf), geometry=str(cfg.robot.geometry))
    joints = cfg.robot.joints
    if joints is None:
        q = torch.zeros(1, robot.dof, dtype=robot.dtype)
    else:
        q = robot.check_joints(_numbers(joints, "robot.joints", None, RobotModelError))
    intr = intrinsics_from_cfg(cfg)
    T = torch.as_tensor(pose_from_cfg(cfg), dtype=torch.float64)
    verts = robot.posed_vertices(q).double()
    verts_cam = verts @ T[:3, :3].T + T[:3, 3]
    mask = render_hard(
        verts_cam,
        robot.faces,
        intr.as_tensor(dtype=torch.float64),
        intr.height,
        intr.width,
        z_near=float(cfg.z_near),
    )[0]
    log.info(
        "robot covers %.2f %% of the %dx%d image",
        100 * mask.float().mean(),
        intr.width,
        intr.height,
    )
    return mask.numpy()


def overlay(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``image`` (BGR uint8) with the ``mask`` region tinted and its contour drawn."""
    out = image.copy()
    tint = np.array(TINT_BGR, dtype=np.float32)
    out[mask] = ((1 - TINT_ALPHA) * image[mask] + TINT_ALPHA * tint).round().astype(np.uint8)
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, CONTOUR_BGR, thickness=1)
    return out


def write_image(path: Path, image: np.ndarray) -> None:
    """Encode ``image`` by the suffix of ``path`` and write it atomically (temp name + rename)."""
    ok, data = cv2.imencode(path.suffix or ".png", image)
    if not ok:
        raise RobosegError(f"out: cannot encode an image as {path.suffix!r} ({path})")
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.name}.", delete=False) as f:
        f.write(data.tobytes())
    os.replace(f.name, path)


def _read_background(path: str, size: Sequence[int]) -> np.ndarray:
    image = cv2.imread(path, cv2.IMREAD_COLOR)
    if image is None:
        raise RobosegError(f"image: cannot read {path}")
    if image.shape[1] != size[0] or image.shape[0] != size[1]:
        raise CameraError(
            f"image {path} is {image.shape[1]}x{image.shape[0]} but the camera is "
            f"{size[0]}x{size[1]} (set camera.width / camera.height)"
        )
    return image


@user_errors_exit
def run(cfg: DictConfig) -> Path:
    """Render the mask (or overlay) ``cfg`` describes, write it to ``cfg.out``; return the path."""
    out = Path(str(cfg.out))
    mask = render_mask(cfg)
    if cfg.image is None:
        result = mask.astype(np.uint8) * 255
    else:
        result = overlay(_read_background(str(cfg.image), mask.shape[::-1]), mask)
    write_image(out, result)
    print(out)
    return out


@hydra.main(config_path=CONF_DIR, config_name="render", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
