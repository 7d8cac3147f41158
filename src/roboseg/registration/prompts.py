"""Prompt files: where a person clicked on the robot in one stereo frame.

A prompt file is YAML (read with a safe loader) naming one frame of the recording, by ``frame``
(index among the recording's left images in stamp order) or ``stamp_ns`` (nearest frame), and
for each camera (``left``, ``right``) a ``box`` ``[x0, y0, x1, y1]`` around the robot and/or
``foreground`` / ``background`` clicks ``[[x, y], ...]``. Coordinates are pixels of that camera's
image (x right, y down, pixel centres at integers) and must lie inside it::

    frame: 40
    left:
      box: [212, 80, 530, 470]
      foreground: [[380, 300]]
    right:
      box: [150, 82, 470, 468]
      background: [[100, 400]]

Every problem is a :class:`~roboseg.errors.PromptError` naming the file and the entry.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from roboseg.errors import PromptError

__all__ = ["CAMERAS", "CameraPrompt", "Prompt", "load_prompt", "resolve_prompt_frame"]

#: the cameras of a stereo recording, as prompt files name them
CAMERAS = ("left", "right")
_CAMERA_KEYS = ("box", "foreground", "background")


@dataclass(frozen=True)
class CameraPrompt:
    """One camera's prompt in pixels: ``box`` ``(x0, y0, x1, y1)`` or None, clicks ``[P, 2]``."""

    camera: str
    box: tuple[float, float, float, float] | None
    foreground: np.ndarray
    background: np.ndarray

    def scaled(self, sx: float, sy: float) -> CameraPrompt:
        """The prompt for the image resized by ``sx``, ``sy`` (pixel centres stay consistent:
        ``u' + 1/2 = s (u + 1/2)``)."""

        def map_xy(p: np.ndarray) -> np.ndarray:
            return (np.asarray(p, np.float64).reshape(-1, 2) + 0.5) * (sx, sy) - 0.5

        box = None
        if self.box is not None:
            b = map_xy(np.asarray(self.box).reshape(2, 2)).ravel()
            box = (float(b[0]), float(b[1]), float(b[2]), float(b[3]))
        return CameraPrompt(self.camera, box, map_xy(self.foreground), map_xy(self.background))

    def points_and_labels(self) -> tuple[np.ndarray, np.ndarray]:
        """Clicks ``[P, 2]`` (x, y px) and labels ``[P]`` (1 foreground, 0 background)."""
        points = np.concatenate([self.foreground, self.background]).reshape(-1, 2)
        labels = np.r_[np.ones(len(self.foreground)), np.zeros(len(self.background))]
        return points.astype(np.float32), labels.astype(np.int32)


@dataclass(frozen=True)
class Prompt:
    """A parsed prompt file: the frame (``frame`` index or ``stamp_ns``) and each camera's
    prompt."""

    path: Path
    frame: int | None
    stamp_ns: int | None
    cameras: dict[str, CameraPrompt]

    def check_inside(self, sizes: dict[str, tuple[int, int]]) -> None:
        """Raise :class:`PromptError` for a box or click outside its camera's ``(width,
        height)`` image, or a camera of the file that ``sizes`` lacks."""
        for name, cam in self.cameras.items():
            if name not in sizes:
                raise PromptError(
                    f"{self.path}: {name}: no such camera in the recording "
                    f"(cameras: {', '.join(sizes)})"
                )
            w, h = sizes[name]
            entries: list[tuple[str, np.ndarray]] = []
            if cam.box is not None:
                entries.append((f"{name}.box", np.asarray(cam.box).reshape(2, 2)))
            for key in ("foreground", "background"):
                for i, p in enumerate(getattr(cam, key)):
                    entries.append((f"{name}.{key}[{i}]", np.asarray(p).reshape(1, 2)))
            for entry, xy in entries:
                if (xy < 0).any() or (xy[:, 0] > w - 1).any() or (xy[:, 1] > h - 1).any():
                    raise PromptError(
                        f"{self.path}: {entry}: {_fmt(xy)} lies outside the {w}x{h} image of "
                        f"camera {name} (x in [0, {w - 1}], y in [0, {h - 1}])"
                    )


def _fmt(xy: np.ndarray) -> str:
    values = [f"{v:g}" for v in np.asarray(xy, np.float64).ravel()]
    return "[" + ", ".join(values) + "]"


def _number_list(value: Any, n: int | None, where: str) -> list[float]:
    if not isinstance(value, Sequence) or isinstance(value, str | bytes):
        raise PromptError(f"{where}: expected a list of numbers, got {value!r}")
    if n is not None and len(value) != n:
        raise PromptError(f"{where}: expected {n} numbers, got {len(value)}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(v):
            raise PromptError(f"{where}: {v!r} is not a finite number")
        out.append(float(v))
    return out


def _camera_prompt(name: str, entry: Any, where: str) -> CameraPrompt:
    if not isinstance(entry, dict):
        raise PromptError(f"{where}: expected box / foreground / background, got {entry!r}")
    unknown = sorted(set(map(str, entry)) - set(_CAMERA_KEYS))
    if unknown:
        raise PromptError(f"{where}.{unknown[0]}: unknown key (expected {', '.join(_CAMERA_KEYS)})")
    box = None
    if entry.get("box") is not None:
        b = _number_list(entry["box"], 4, f"{where}.box")
        if not (b[0] < b[2] and b[1] < b[3]):
            raise PromptError(f"{where}.box: {_fmt(np.asarray(b))} needs x0 < x1 and y0 < y1")
        box = (b[0], b[1], b[2], b[3])
    clicks = {}
    for key in ("foreground", "background"):
        raw = entry.get(key) or []
        if not isinstance(raw, Sequence) or isinstance(raw, str | bytes):
            raise PromptError(f"{where}.{key}: expected a list of [x, y] points, got {raw!r}")
        pts = [_number_list(p, 2, f"{where}.{key}[{i}]") for i, p in enumerate(raw)]
        clicks[key] = np.asarray(pts, np.float64).reshape(-1, 2)
    if box is None and len(clicks["foreground"]) == 0:
        raise PromptError(f"{where}: needs a box or at least one foreground point")
    return CameraPrompt(name, box, clicks["foreground"], clicks["background"])


def load_prompt(path: str | Path, cameras: Sequence[str] = CAMERAS) -> Prompt:
    """Parse and check a prompt file (structure only; :meth:`Prompt.check_inside` checks it
    against the image sizes). Every camera of ``cameras`` needs an entry."""
    p = Path(path)
    try:
        doc = yaml.safe_load(p.read_text())
    except OSError as exc:
        raise PromptError(f"{p}: cannot read the prompt file ({exc.strerror or exc})") from exc
    except yaml.YAMLError as exc:
        line = getattr(getattr(exc, "problem_mark", None), "line", None)
        at = "" if line is None else f" at line {line + 1}"
        raise PromptError(f"{p}: not a YAML prompt file{at}") from exc
    if not isinstance(doc, dict):
        raise PromptError(f"{p}: expected a mapping with frame (or stamp_ns) and {cameras}")
    frame, stamp = doc.get("frame"), doc.get("stamp_ns")
    if (frame is None) == (stamp is None):
        raise PromptError(f"{p}: frame: give exactly one of frame (index) or stamp_ns")
    for key, value in (("frame", frame), ("stamp_ns", stamp)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int)):
            raise PromptError(f"{p}: {key}: expected an integer, got {value!r}")
    if frame is not None and frame < 0:
        raise PromptError(f"{p}: frame: {frame} is negative")
    parsed: dict[str, CameraPrompt] = {}
    for key, entry in doc.items():
        name = str(key)
        if name in ("frame", "stamp_ns"):
            continue
        if name not in cameras:
            raise PromptError(
                f"{p}: {name}: no such camera (cameras: {', '.join(cameras)}; "
                "other keys: frame, stamp_ns)"
            )
        parsed[name] = _camera_prompt(name, entry, f"{p}: {name}")
    missing = [c for c in cameras if c not in parsed]
    if missing:
        raise PromptError(f"{p}: {missing[0]}: no prompt for this camera (every camera needs one)")
    return Prompt(
        p, None if frame is None else int(frame), None if stamp is None else int(stamp), parsed
    )


def resolve_prompt_frame(prompt: Prompt, indices: np.ndarray, stamps: np.ndarray) -> int:
    """The recording frame index the prompt names, among the usable frames ``indices`` [N]
    (stamps [N] ns). A stamp picks the nearest frame within half the median frame interval."""
    indices, stamps = np.asarray(indices), np.asarray(stamps, np.int64)
    if len(indices) == 0:
        raise PromptError(f"{prompt.path}: frame: the recording has no usable frame")
    if prompt.frame is not None:
        if prompt.frame not in set(indices.tolist()):
            raise PromptError(
                f"{prompt.path}: frame: {prompt.frame} is not a usable frame of the recording "
                f"(frames {int(indices.min())}..{int(indices.max())} with both images and "
                "joint states)"
            )
        return int(prompt.frame)
    assert prompt.stamp_ns is not None
    k = int(np.argmin(np.abs(stamps - prompt.stamp_ns)))
    interval = float(np.median(np.diff(stamps))) if len(stamps) > 1 else 0.0
    if abs(int(stamps[k]) - prompt.stamp_ns) > max(interval / 2, 1e6):
        raise PromptError(
            f"{prompt.path}: stamp_ns: no frame at {prompt.stamp_ns} ns (nearest "
            f"{int(stamps[k])} ns, frames {int(stamps.min())}..{int(stamps.max())} ns)"
        )
    return int(indices[k])
