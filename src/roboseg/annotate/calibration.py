"""Camera ← robot-base calibration: ``/tf_static`` of the recording or a registration YAML.

The YAML (as ``roboseg-register`` writes it) holds ``T_cam_base`` (16 numbers row-major or a
4×4 nested list, metres), ``camera_frame`` and ``base_frame``; several robots go under
``robots: {<name>: {...}}``. ``T_cam_base`` maps base-frame points into the camera frame.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from roboseg.errors import RecordingError, RobosegError
from roboseg.recording import RecordingReader


def base_frame_name(robot: str, root_link: str) -> str:
    """tf frame of a robot's base: ``<robot namespace>/<root link>``."""
    return f"{robot}/{root_link}"


def parse_pose(value: Any, where: str) -> np.ndarray:
    """16 numbers (row-major) or a 4×4 nested list -> rigid 4×4 float64 matrix."""
    try:
        T = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise RobosegError(f"{where}: T_cam_base is not a list of numbers") from None
    if T.size != 16 or not np.isfinite(T).all():
        raise RobosegError(f"{where}: T_cam_base must be 16 finite numbers, got {T.size}")
    T = T.reshape(4, 4)
    if not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-5) or not np.allclose(
        T[3], [0, 0, 0, 1]
    ):
        raise RobosegError(f"{where}: T_cam_base is not a rigid transform")
    return T


def load_calibration_file(path: str | Path) -> dict[str, dict[str, Any]]:
    """``{key: {"T_cam_base", "camera_frame", "base_frame"}}`` from a calibration YAML; the key
    is the robot name under ``robots:`` or ``"*"`` for a single top-level entry."""
    path = Path(path)
    if not path.is_file():
        raise RobosegError(f"calibration: no such file {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise RobosegError(f"calibration {path}: not valid YAML ({exc})") from None
    if not isinstance(data, dict):
        raise RobosegError(f"calibration {path}: expected a mapping with T_cam_base")
    entries = data.get("robots", {"*": data})
    if not isinstance(entries, dict):
        raise RobosegError(f"calibration {path}: robots must map robot names to entries")
    out = {}
    for key, entry in entries.items():
        if not isinstance(entry, dict) or "T_cam_base" not in entry:
            raise RobosegError(f"calibration {path}: entry {key!r} has no T_cam_base")
        out[str(key)] = {
            "T_cam_base": parse_pose(entry["T_cam_base"], f"calibration {path} ({key})"),
            "camera_frame": entry.get("camera_frame"),
            "base_frame": entry.get("base_frame"),
        }
    return out


def _file_pose(
    reader: RecordingReader,
    entries: Mapping[str, Mapping[str, Any]],
    robot: str,
    base: str,
    left: str,
    source: str,
) -> np.ndarray:
    """``T_left_base`` of one robot from calibration-file entries (camera frame -> left)."""
    entry = entries.get(robot)
    if entry is None:
        matching = [e for e in entries.values() if e.get("base_frame") == base]
        entry = matching[0] if matching else entries.get("*") if len(entries) == 1 else None
    if entry is None:
        raise RobosegError(
            f"calibration {source}: no entry for robot {robot} (base frame {base}); "
            f"entries: {', '.join(entries)}"
        )
    camera = entry.get("camera_frame") or left
    T = np.asarray(entry["T_cam_base"])
    return T if camera == left else reader.lookup(left, str(camera)) @ T


def robot_poses(
    reader: RecordingReader,
    robots: Sequence[str],
    root_link: str,
    calibration: str | Path | None = None,
) -> tuple[dict[str, np.ndarray], str]:
    """``{robot: T_left_base}`` (left optical frame ← robot base, 4×4 metres) and the source
    (``"tf_static"`` or ``"file"``)."""
    left = reader.camera_infos("left").frame_id
    poses = {}
    if calibration is not None:
        entries = load_calibration_file(calibration)
        for robot in robots:
            base = base_frame_name(robot, root_link)
            poses[robot] = _file_pose(reader, entries, robot, base, left, str(calibration))
        return poses, "file"
    for robot in robots:
        base = base_frame_name(robot, root_link)
        try:
            poses[robot] = reader.lookup(left, base)
        except RecordingError:
            raise RecordingError(
                f"{reader.path}: no /tf_static transform from camera frame '{left}' to robot "
                f"base '{base}'; pass calibration=PATH (YAML with T_cam_base)"
            ) from None
    return poses, "tf_static"


def right_from_left(reader: RecordingReader) -> np.ndarray:
    """``T_right_left`` of the stereo camera from ``/tf_static`` (names both frames if absent)."""
    left = reader.camera_infos("left").frame_id
    right = reader.camera_infos("right").frame_id
    try:
        return reader.lookup(right, left)
    except RecordingError:
        raise RecordingError(
            f"{reader.path}: no /tf_static transform between '{left}' and '{right}' "
            "(the stereo extrinsics)"
        ) from None
