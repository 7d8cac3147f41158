"""Stereo AprilTag tracking, the breathing-motion model and the breathing-compensated command."""

from roboseg.tracking.breathing import BreathingFit, BreathingModel, fit_breathing
from roboseg.tracking.control import (
    alignment_angular_velocity,
    compensated_linear_velocity,
    geometric_jacobian,
    min_norm_joint_velocities,
)
from roboseg.tracking.tags import (
    FrameTags,
    Roi,
    StereoTagTracker,
    TagObservation,
    TagStatus,
    TagTracks,
    detect_tags,
    roi_intrinsics,
    tag_centre,
    triangulate_dlt,
)

#: The architecture table's name for the stereo tracker.
TagTracker = StereoTagTracker

__all__ = [
    "BreathingFit",
    "BreathingModel",
    "FrameTags",
    "Roi",
    "StereoTagTracker",
    "TagObservation",
    "TagStatus",
    "TagTracker",
    "TagTracks",
    "alignment_angular_velocity",
    "compensated_linear_velocity",
    "detect_tags",
    "fit_breathing",
    "geometric_jacobian",
    "min_norm_joint_velocities",
    "roi_intrinsics",
    "tag_centre",
    "triangulate_dlt",
]
