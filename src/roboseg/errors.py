"""User-facing errors: one clear line naming the file, topic, link, joint or value at fault.

Commands catch :class:`RobosegError`, print its message and exit with status 1 (no traceback).
"""

from __future__ import annotations


class RobosegError(Exception):
    """Base class of errors caused by user input (files, configs, recordings)."""


class RobotModelError(RobosegError, ValueError):
    """A URDF, mesh, joint name or joint vector is malformed or does not match the model."""


class CameraError(RobosegError, ValueError):
    """Intrinsics, image size or a camera pose is invalid (e.g. the robot is behind the camera)."""


class RecordingError(RobosegError):
    """An MCAP recording is missing, truncated, corrupt or lacks a topic / message."""


class DatasetError(RobosegError):
    """A dataset root, split or manifest is missing or empty."""


class ModelFileError(RobosegError):
    """A checkpoint or ONNX file does not match what it claims to be."""


class SegmentationError(RobosegError):
    """A segmentor cannot make masks: bad settings, a missing optional package or checkpoint."""


class NoMotionError(SegmentationError):
    """Motion segmentation found no robot motion (joints or pixels) in the recording's window."""


class PromptError(SegmentationError, ValueError):
    """A prompt file is malformed, names an unknown camera or points outside the image."""
