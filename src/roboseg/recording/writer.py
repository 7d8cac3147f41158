"""Write roboseg recordings: MCAP files of ROS 2 CDR messages (``ros2 bag`` compatible)."""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from mcap.records import Schema
from mcap.writer import CompressionType
from mcap_ros2.writer import Writer as Ros2Writer

from roboseg.errors import RecordingError
from roboseg.recording import msgs
from roboseg.recording.atomic import AtomicMcapFile
from roboseg.recording.msgs import CameraCalib
from roboseg.recording.tf import invert_transform, matrix_to_quaternion
from roboseg.recording.topics import TF_STATIC, camera_info_topic

logger = logging.getLogger(__name__)


def encode_image(image: np.ndarray, fmt: str = "jpeg", quality: int = 90) -> bytes:
    """Encode an ``HxWx3`` uint8 RGB image as JPEG (``quality`` 0-100) or PNG bytes."""
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image must be HxWx3 uint8 RGB, got {image.dtype} {image.shape}")
    bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    if fmt == "jpeg":
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    elif fmt == "png":
        ok, buf = cv2.imencode(".png", bgr)
    else:
        raise ValueError(f"image format {fmt!r} is not 'jpeg' or 'png'")
    if not ok:
        raise ValueError(f"cv2 could not encode a {image.shape} image as {fmt}")
    return buf.tobytes()


def encode_mask(mask: np.ndarray, level: int = 1) -> bytes:
    """Encode an ``HxW`` bool/uint8 mask (nonzero = robot) as a 1-bit grayscale PNG, which
    decodes to values 0/255 (``level``: zlib compression 0-9; bilevel is ~5× faster to encode
    than 8-bit)."""
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"mask must be HxW, got shape {mask.shape}")
    params = [cv2.IMWRITE_PNG_COMPRESSION, int(level), cv2.IMWRITE_PNG_BILEVEL, 1]
    ok, buf = cv2.imencode(".png", (mask != 0).view(np.uint8), params)
    if not ok:
        raise ValueError(f"cv2 could not encode a {mask.shape} mask as PNG")
    return buf.tobytes()


class RecordingWriter(AtomicMcapFile):
    """Context manager writing one recording to ``path`` atomically.

    Messages go to ``<path>.part``; :meth:`close` (or leaving the ``with`` block normally)
    finishes the MCAP and renames it to ``path``. If the block raises, the partial file is
    deleted and no file appears at ``path``. Stamps are integer nanoseconds; the MCAP log time
    of each message equals its header stamp.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        metadata: dict[str, dict[str, str]] | None = None,
        chunk_size: int = 4 * 1024 * 1024,
        compression: str = "zstd",
    ) -> None:
        if not Path(path).parent.is_dir():
            raise RecordingError(f"{Path(path)}: output folder does not exist")
        compressions = {
            "zstd": CompressionType.ZSTD,
            "lz4": CompressionType.LZ4,
            "none": CompressionType.NONE,
        }
        if compression not in compressions:
            raise ValueError(f"compression {compression!r} not in {sorted(compressions)}")
        self._writer = Ros2Writer(
            self._open_part(path), chunk_size=chunk_size, compression=compressions[compression]
        )
        self._schemas: dict[str, Schema] = {}
        for name, data in (metadata or {}).items():
            self.write_metadata(name, data)

    # -- messages --------------------------------------------------------------------------
    def _write(self, topic: str, schema_name: str, message: dict[str, Any], stamp_ns: int) -> None:
        if self._closed:
            raise RecordingError(f"{self.path}: writer is closed (topic {topic})")
        schema = self._schemas.get(schema_name)
        if schema is None:
            schema = self._writer.register_msgdef(schema_name, msgs.MSGDEFS[schema_name])
            self._schemas[schema_name] = schema
        stamp_ns = int(stamp_ns)
        self._writer.write_message(topic, schema, message, log_time=stamp_ns, publish_time=stamp_ns)

    def write_compressed(
        self, topic: str, stamp_ns: int, frame_id: str, data: bytes, fmt: str
    ) -> None:
        """Write already encoded image bytes as ``sensor_msgs/CompressedImage``."""
        message = {"header": msgs.header(stamp_ns, frame_id), "format": fmt, "data": bytes(data)}
        self._write(topic, msgs.COMPRESSED_IMAGE, message, stamp_ns)

    def write_image(
        self,
        topic: str,
        stamp_ns: int,
        frame_id: str,
        image: np.ndarray,
        fmt: str = "jpeg",
        quality: int = 90,
    ) -> None:
        """Write an ``HxWx3`` uint8 RGB image as a JPEG (or PNG) ``CompressedImage``."""
        data = encode_image(image, fmt, quality)
        fmt_string = msgs.JPEG_FORMAT if fmt == "jpeg" else "rgb8; png compressed bgr8"
        self.write_compressed(topic, stamp_ns, frame_id, data, fmt_string)

    def write_mask(self, topic: str, stamp_ns: int, frame_id: str, mask: np.ndarray) -> None:
        """Write an ``HxW`` bool/uint8 mask as a PNG (0/255) ``CompressedImage``."""
        self.write_compressed(topic, stamp_ns, frame_id, encode_mask(mask), msgs.PNG_MASK_FORMAT)

    def write_camera_info(
        self,
        topic: str,
        stamp_ns: int,
        frame_id: str,
        K: np.ndarray,
        width: int,
        height: int,
        D: Sequence[float] | None = None,
        distortion_model: str = "plumb_bob",
    ) -> None:
        """Write ``sensor_msgs/CameraInfo``: intrinsics ``K`` (3x3, pixels), size, distortion.

        ``R`` is the identity and ``P = [K | 0]`` (unrectified monocular convention).
        """
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must be 3x3, got {K.shape}")
        P = np.hstack([K, np.zeros((3, 1))])
        message = {
            "header": msgs.header(stamp_ns, frame_id),
            "height": int(height),
            "width": int(width),
            "distortion_model": distortion_model,
            "d": [float(v) for v in (D if D is not None else [0.0] * 5)],
            "k": K.ravel().tolist(),
            "r": np.eye(3).ravel().tolist(),
            "p": P.ravel().tolist(),
            "binning_x": 0,
            "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
        }
        self._write(topic, msgs.CAMERA_INFO, message, stamp_ns)

    def write_joint_state(
        self,
        topic: str,
        stamp_ns: int,
        names: Sequence[str],
        positions: Sequence[float] | np.ndarray,
        velocities: Sequence[float] | np.ndarray | None = None,
    ) -> None:
        """Write ``sensor_msgs/JointState`` (positions in rad or m, velocities per second)."""
        positions = np.asarray(positions, dtype=np.float64).ravel()
        if len(names) != len(positions):
            raise ValueError(f"{topic}: {len(names)} joint names but {len(positions)} positions")
        vel = [] if velocities is None else np.asarray(velocities, np.float64).ravel().tolist()
        if vel and len(vel) != len(names):
            raise ValueError(f"{topic}: {len(names)} joint names but {len(vel)} velocities")
        message = {
            "header": msgs.header(stamp_ns, ""),
            "name": [str(n) for n in names],
            "position": positions.tolist(),
            "velocity": vel,
            "effort": [],
        }
        self._write(topic, msgs.JOINT_STATE, message, stamp_ns)

    def write_tf_static(
        self, transforms: Sequence[tuple[str, str, np.ndarray]], stamp_ns: int = 0
    ) -> None:
        """Write ``tf2_msgs/TFMessage`` on ``/tf_static`` from ``(parent, child, T_parent_child)``.

        ``T_parent_child`` (4x4, metres) maps child-frame points into the parent frame.
        """
        entries = []
        for parent, child, T in transforms:
            T = np.asarray(T, dtype=np.float64)
            if T.shape != (4, 4):
                raise ValueError(f"transform {parent} -> {child} must be 4x4, got {T.shape}")
            q = matrix_to_quaternion(T[:3, :3])
            x, y, z = T[:3, 3].tolist()
            entries.append(
                {
                    "header": msgs.header(stamp_ns, parent),
                    "child_frame_id": child,
                    "transform": {
                        "translation": {"x": x, "y": y, "z": z},
                        "rotation": dict(zip("xyzw", q.tolist(), strict=True)),
                    },
                }
            )
        self._write(TF_STATIC, msgs.TF_MESSAGE, {"transforms": entries}, stamp_ns)

    def write_camera_calib(self, calib: CameraCalib, stamp_ns: int = 0) -> None:
        """Write both sides' CameraInfo and, if known, ``T_left_right`` on ``/tf_static``."""
        for side, info in (("left", calib.left), ("right", calib.right)):
            self.write_camera_info(
                camera_info_topic(calib.name, side),
                stamp_ns,
                info.frame_id,
                info.K,
                info.width,
                info.height,
                info.D,
                info.distortion_model,
            )
        if calib.T_right_left is not None:
            T_left_right = invert_transform(np.asarray(calib.T_right_left, dtype=np.float64))
            self.write_tf_static(
                [(calib.left.frame_id, calib.right.frame_id, T_left_right)], stamp_ns
            )

    def write_metadata(self, name: str, data: dict[str, str]) -> None:
        """Write an MCAP metadata record (string keys and values)."""
        self._writer.add_metadata(name, {str(k): str(v) for k, v in data.items()})
