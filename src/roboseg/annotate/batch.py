"""Annotate a folder of recordings and write ``manifest.json`` (``roboseg-annotations/1``)."""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from roboseg.annotate.core import (
    SKIP_REASONS,
    AnnotateOptions,
    RecordingResult,
    annotate_recording,
)
from roboseg.annotate.selection import assign_split, target_count
from roboseg.errors import DatasetError
from roboseg.recording import RecordingReader
from roboseg.robot import RobotModel

log = logging.getLogger(__name__)

MANIFEST_FORMAT = "roboseg-annotations/1"
MANIFEST_NAME = "manifest.json"


def write_json_atomic(path: Path, data: dict[str, Any]) -> None:
    """Write JSON to ``<path>.part`` and rename it to ``path``."""
    part = path.with_name(path.name + ".part")
    part.write_text(json.dumps(data, indent=2) + "\n")
    os.replace(part, path)


def count_left_frames(path: Path, camera: str) -> int:
    """Left images of a recording (0 when it cannot be opened)."""
    try:
        with RecordingReader(path, camera=camera, robots=[], on_error="skip") as reader:
            return len(reader)
    except Exception as exc:  # noqa: BLE001 - unreadable files are reported by annotation
        log.debug("%s: cannot count frames (%s)", path, exc)
        return 0


def totals(results: Sequence[RecordingResult]) -> dict[str, Any]:
    """Summed counts over recordings."""
    return {
        "frames_total": sum(r.frames_total for r in results),
        "frames_kept": sum(r.frames_kept for r in results),
        "skipped": {k: sum(r.skipped[k] for r in results) for k in SKIP_REASONS},
    }


def annotate_folder(
    in_dir: str | Path,
    out_dir: str | Path,
    robot: RobotModel,
    options: AnnotateOptions,
    *,
    subset: str = "full",
    subset_fraction: float | None = None,
    subset_splits: Sequence[str] = ("train",),
    splits: Mapping[str, Sequence[str]] | None = None,
    urdf: str | None = None,
) -> dict[str, Any]:
    """Annotate every ``in_dir/*.mcap`` into ``out_dir`` and write the manifest; return it.

    ``options.fraction`` is the share of frames kept in recordings of ``subset_splits`` (the
    others keep every moving frame); the target is that share of the frames of all those
    recordings, spread over them in proportion to their length.
    """
    in_dir, out_dir = Path(in_dir), Path(out_dir)
    if not in_dir.is_dir():
        raise DatasetError(f"in: no such folder {in_dir}")
    sources = sorted(in_dir.glob("*.mcap"))
    if not sources:
        raise DatasetError(f"in: no .mcap recordings in {in_dir}")
    if out_dir.resolve() == in_dir.resolve():
        raise DatasetError(f"out: {out_dir} must differ from in (outputs keep the input names)")
    out_dir.mkdir(parents=True, exist_ok=True)
    results = []
    for n, source in enumerate(sources, 1):
        split = assign_split(source.name, splits)
        target = None
        if options.fraction is not None and split in subset_splits:
            target = target_count(count_left_frames(source, options.camera), options.fraction)
        log.info("[%d/%d] annotating %s (split %s)", n, len(sources), source.name, split)
        results.append(
            annotate_recording(source, out_dir / source.name, robot, options, split, target)
        )
    manifest = {
        "format": MANIFEST_FORMAT,
        "camera": options.camera,
        "robot_urdf": urdf,
        "subset": subset,
        "subset_fraction": options.fraction,
        "recordings": [r.manifest_entry() for r in results],
        "totals": totals(results),
    }
    write_json_atomic(out_dir / MANIFEST_NAME, manifest)
    return manifest
