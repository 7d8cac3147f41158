"""Self-annotation: recordings + robot model + calibration -> mask topics, subsets, manifest.

:func:`annotate_recording` renders the robot's silhouette (forward kinematics of the interpolated
joint states, hard rasterisation of the full model) into both cameras of every kept frame;
:func:`annotate_folder` does so for a folder and writes ``manifest.json``.
"""

from roboseg.annotate.batch import MANIFEST_FORMAT, MANIFEST_NAME, annotate_folder
from roboseg.annotate.calibration import load_calibration_file, robot_poses
from roboseg.annotate.core import (
    SKIP_REASONS,
    AnnotateOptions,
    MaskRenderer,
    RecordingResult,
    annotate_recording,
)
from roboseg.annotate.selection import (
    SUBSETS,
    assign_split,
    joint_speed_at,
    phase_mask,
    subset_fraction,
    target_count,
    thin_evenly,
)

__all__ = [
    "MANIFEST_FORMAT",
    "MANIFEST_NAME",
    "SKIP_REASONS",
    "SUBSETS",
    "AnnotateOptions",
    "MaskRenderer",
    "RecordingResult",
    "annotate_folder",
    "annotate_recording",
    "assign_split",
    "joint_speed_at",
    "load_calibration_file",
    "phase_mask",
    "robot_poses",
    "subset_fraction",
    "target_count",
    "thin_evenly",
]
