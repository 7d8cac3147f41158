"""ROS 2 (Humble/Jazzy) message definitions used by roboseg recordings.

Each schema is the ``.msg`` text of the type followed by its dependencies, separated by a line
of 80 ``=`` and ``MSG: <package>/<Type>`` headers: the concatenated format ``ros2 bag record``
stores in MCAP schema records and mcap-ros2-support parses. Comments are omitted; field types,
names, array bounds and constants are those of the upstream ``.msg`` files.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

_SEPARATOR = "=" * 80

TIME = "int32 sec\nuint32 nanosec\n"
HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"
REGION_OF_INTEREST = (
    "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n"
)
VECTOR3 = "float64 x\nfloat64 y\nfloat64 z\n"
QUATERNION = "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"
TRANSFORM = "Vector3 translation\nQuaternion rotation\n"
TRANSFORM_STAMPED = "std_msgs/Header header\nstring child_frame_id\nTransform transform\n"

COMPRESSED_IMAGE_DEF = "std_msgs/Header header\nstring format\nuint8[] data\n"
CAMERA_INFO_DEF = (
    "std_msgs/Header header\n"
    "uint32 height\n"
    "uint32 width\n"
    "string distortion_model\n"
    "float64[] d\n"
    "float64[9] k\n"
    "float64[9] r\n"
    "float64[12] p\n"
    "uint32 binning_x\n"
    "uint32 binning_y\n"
    "RegionOfInterest roi\n"
)
JOINT_STATE_DEF = (
    "std_msgs/Header header\n"
    "string[] name\n"
    "float64[] position\n"
    "float64[] velocity\n"
    "float64[] effort\n"
)
TF_MESSAGE_DEF = "geometry_msgs/TransformStamped[] transforms\n"


def concatenate(main: str, deps: list[tuple[str, str]]) -> str:
    """Join a message definition and its dependencies ``[(package/Type, text)]``."""
    parts = [main.rstrip("\n")]
    for name, text in deps:
        parts.append(f"{_SEPARATOR}\nMSG: {name}\n{text.rstrip(chr(10))}")
    return "\n".join(parts) + "\n"


_HEADER_DEPS = [("std_msgs/Header", HEADER), ("builtin_interfaces/Time", TIME)]

COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
JOINT_STATE = "sensor_msgs/msg/JointState"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"

#: schema name -> concatenated message definition
MSGDEFS: dict[str, str] = {
    COMPRESSED_IMAGE: concatenate(COMPRESSED_IMAGE_DEF, _HEADER_DEPS),
    CAMERA_INFO: concatenate(
        CAMERA_INFO_DEF,
        [*_HEADER_DEPS, ("sensor_msgs/RegionOfInterest", REGION_OF_INTEREST)],
    ),
    JOINT_STATE: concatenate(JOINT_STATE_DEF, _HEADER_DEPS),
    TF_MESSAGE: concatenate(
        TF_MESSAGE_DEF,
        [
            ("geometry_msgs/TransformStamped", TRANSFORM_STAMPED),
            *_HEADER_DEPS,
            ("geometry_msgs/Transform", TRANSFORM),
            ("geometry_msgs/Vector3", VECTOR3),
            ("geometry_msgs/Quaternion", QUATERNION),
        ],
    ),
}

#: ``CompressedImage.format`` strings as written by ROS image_transport's compressed plugin.
JPEG_FORMAT = "rgb8; jpeg compressed bgr8"
PNG_MASK_FORMAT = "mono8; png compressed mono8"


def stamp_to_ns(stamp: object) -> int:
    """``builtin_interfaces/Time`` (decoded message) -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)  # type: ignore[attr-defined]


def ns_to_stamp(stamp_ns: int) -> dict[str, int]:
    """Integer nanoseconds -> ``builtin_interfaces/Time`` fields (``nanosec`` in [0, 1e9))."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    if not -(2**31) <= sec < 2**31:
        raise ValueError(f"stamp {stamp_ns} ns does not fit builtin_interfaces/Time")
    return {"sec": sec, "nanosec": nanosec}


def header(stamp_ns: int, frame_id: str) -> dict[str, object]:
    """``std_msgs/Header`` fields for a stamp in nanoseconds and a frame id."""
    return {"stamp": ns_to_stamp(stamp_ns), "frame_id": frame_id}


def cdr_header_stamp_ns(data: bytes) -> int:
    """Stamp (ns) of a CDR-serialised message whose first field is ``std_msgs/Header``.

    Reads the two 32-bit integers after the 4-byte encapsulation header without decoding the
    rest of the message (cheap for images). Byte order follows the encapsulation id.
    """
    if len(data) < 12:
        raise ValueError("CDR message shorter than a header stamp")
    order = "<" if data[1] & 1 else ">"
    sec = int.from_bytes(data[4:8], "little" if order == "<" else "big", signed=True)
    nanosec = int.from_bytes(data[8:12], "little" if order == "<" else "big", signed=False)
    return sec * 1_000_000_000 + nanosec


@dataclass(frozen=True)
class CameraInfo:
    """One camera's calibration from ``sensor_msgs/CameraInfo``.

    ``K`` is the 3x3 intrinsic matrix in pixels (pixel centres at integer coordinates),
    ``D`` the distortion coefficients of ``distortion_model``, ``frame_id`` the optical frame.
    """

    K: np.ndarray
    width: int
    height: int
    frame_id: str
    D: np.ndarray = field(default_factory=lambda: np.zeros(5))
    distortion_model: str = "plumb_bob"


@dataclass(frozen=True)
class CameraCalib:
    """A stereo camera: both sides' intrinsics and ``T_right_left`` (4x4, metres) if known."""

    name: str
    left: CameraInfo
    right: CameraInfo
    T_right_left: np.ndarray | None = None


@dataclass
class StereoFrame:
    """One synchronised stereo frame.

    ``left``/``right`` are ``HxWx3`` uint8 RGB images (or the raw encoded bytes as a 1-D uint8
    array when read with ``decode=False``); ``joints[robot]`` the joint positions (rad / m)
    interpolated to ``stamp_ns`` in the order ``joint_names[robot]``; ``masks[name]`` ``HxW``
    bool masks of the requested mask topics. ``index`` is the frame's position among all left
    images of the recording in stamp order.
    """

    stamp_ns: int
    left: np.ndarray
    right: np.ndarray
    joints: dict[str, np.ndarray]
    joint_names: dict[str, list[str]]
    masks: dict[str, np.ndarray] = field(default_factory=dict)
    index: int = -1
    left_frame_id: str = ""
    right_frame_id: str = ""
