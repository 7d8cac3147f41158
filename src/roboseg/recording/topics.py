"""Default topic names of a roboseg recording (all configurable by the caller).

``/<camera>/<side>/image_raw/compressed`` (JPEG), ``/<camera>/<side>/camera_info``,
``/<camera>/<side>/<mask>/compressed`` (PNG), ``/<robot>/joint_states`` and ``/tf_static``.
"""

from __future__ import annotations

DEFAULT_CAMERA = "camera"
DEFAULT_ROBOTS = ("robot_0", "robot_1")
SIDES = ("left", "right")
TF_STATIC = "/tf_static"
ROBOT_MASK = "robot_mask"
ROBOT_MASK_GT = "robot_mask_gt"
_JOINT_STATES_SUFFIX = "/joint_states"


def image_topic(camera: str = DEFAULT_CAMERA, side: str = "left") -> str:
    """JPEG image topic of one side of a stereo camera."""
    return f"/{camera}/{side}/image_raw/compressed"


def camera_info_topic(camera: str = DEFAULT_CAMERA, side: str = "left") -> str:
    """CameraInfo topic of one side of a stereo camera."""
    return f"/{camera}/{side}/camera_info"


def mask_topic(camera: str = DEFAULT_CAMERA, side: str = "left", kind: str = ROBOT_MASK) -> str:
    """PNG mask topic (``robot_mask`` from self-annotation, ``robot_mask_gt`` from simulation)."""
    return f"/{camera}/{side}/{kind}/compressed"


def resolve_mask_topic(name: str, camera: str = DEFAULT_CAMERA) -> str:
    """``"left/robot_mask"`` -> ``/<camera>/left/robot_mask/compressed``; absolute topics pass."""
    if name.startswith("/"):
        return name
    side, _, kind = name.partition("/")
    if side not in SIDES or not kind:
        raise ValueError(f"mask name {name!r} is not '<left|right>/<kind>' or an absolute topic")
    return mask_topic(camera, side, kind)


def joint_states_topic(robot: str) -> str:
    """JointState topic of one robot namespace."""
    return f"/{robot}{_JOINT_STATES_SUFFIX}"


def robots_from_topics(topics: list[str] | dict[str, str]) -> list[str]:
    """Robot namespaces with a ``/<robot>/joint_states`` topic, sorted."""
    robots = []
    for topic in topics:
        if topic.endswith(_JOINT_STATES_SUFFIX) and topic.count("/") == 2:
            robots.append(topic[1 : -len(_JOINT_STATES_SUFFIX)])
    return sorted(robots)
