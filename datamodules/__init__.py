"""Lightning DataModules of roboseg (``conf/data``)."""

from datamodules.recording import (
    IndexedFrames,
    Manifest,
    RecordingDataModule,
    StreamingFrames,
    read_manifest,
)

__all__ = ["IndexedFrames", "Manifest", "RecordingDataModule", "StreamingFrames", "read_manifest"]
