"""MCAP + ROS 2 CDR recordings: writing, streaming stereo frames, joint-state synchronisation."""

from roboseg.recording.msgs import CameraCalib, CameraInfo, StereoFrame
from roboseg.recording.reader import ChunkInfo, ReadStats, RecordingReader
from roboseg.recording.topics import (
    DEFAULT_CAMERA,
    DEFAULT_ROBOTS,
    TF_STATIC,
    camera_info_topic,
    image_topic,
    joint_states_topic,
    mask_topic,
)
from roboseg.recording.writer import RecordingWriter

__all__ = [
    "DEFAULT_CAMERA",
    "DEFAULT_ROBOTS",
    "TF_STATIC",
    "CameraCalib",
    "CameraInfo",
    "ChunkInfo",
    "ReadStats",
    "RecordingReader",
    "RecordingWriter",
    "StereoFrame",
    "camera_info_topic",
    "image_topic",
    "joint_states_topic",
    "mask_topic",
]
