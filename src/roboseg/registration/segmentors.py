"""Where registration's masks come from: one interface, one small class per kind.

``roboseg-register segmentor=<kind>`` (``conf/register.yaml``) picks one of :data:`SEGMENTORS`:

* ``model``: the exported ONNX segmentation model (:class:`~roboseg.segmentor.OnnxSegmentor`;
  the only kind SDR with prior can use);
* ``motion``: static cameras, moving robot: a background model of the recording
  (:mod:`.motion`); only the links that moved are rendered and compared;
* ``prompt``: a prompt file (:mod:`.prompts`) drives GrabCut on one frame, tracked through the
  recording (:mod:`.grabcut`);
* ``sam2``: the same prompt file drives SAM 2's video predictor (optional ``sam2`` package and
  a local checkpoint; never downloaded).

A segmentor is a :data:`~roboseg.registration.register.MaskSource`: ``seg(frame)`` returns the
``(left, right)`` masks ``[H, W]`` bool of a :class:`~roboseg.recording.StereoFrame`. Before use,
``seg.prepare(recording, robot_model, config)`` reads what it needs from the recording (the
frames of ``config``'s phase window); afterwards ``seg.frames`` lists the frame indices it can
segment (None: any) and ``seg.links`` the links registration should render (None: all):
``register(recording, robot, masks=seg, frames=seg.frames, links=seg.links, config=...)``.
"""

from __future__ import annotations

import importlib
import logging
import math
import tempfile
from abc import ABC, abstractmethod
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar

import cv2
import numpy as np

from roboseg.errors import NoMotionError, RecordingError, SegmentationError
from roboseg.recording import RecordingReader, StereoFrame
from roboseg.registration.grabcut import GrabCutConfig, GrabCutTracker
from roboseg.registration.motion import BackgroundModel, MotionConfig, link_motion
from roboseg.registration.prompts import CAMERAS, Prompt, load_prompt, resolve_prompt_frame
from roboseg.registration.register import (
    RegisterConfig,
    phase_window,
    spread_configurations,
)
from roboseg.robot import RobotModel

__all__ = [
    "SEGMENTORS",
    "Segmentor",
    "ModelSegmentor",
    "MotionSegmentor",
    "PromptSegmentor",
    "Sam2Segmentor",
    "WindowFrames",
    "make_segmentor",
    "window_frames",
    "SAM2_INSTALL",
]

log = logging.getLogger(__name__)

#: what to install for ``segmentor=sam2``
SAM2_INSTALL = (
    "segmentor=sam2 needs the sam2 package: pip install 'roboseg[sam2]' (or pip install sam2, "
    "or Meta's sources: pip install git+https://github.com/facebookresearch/sam2)"
)


class Segmentor(ABC):
    """Masks of the registered frames; see the module docstring."""

    kind: ClassVar[str]
    #: the masks may hold more than the robot: registration trims them near its estimate
    trims: ClassVar[bool] = False
    #: frame indices this segmentor can segment (None: any), set by :meth:`prepare`
    frames: list[int] | None = None
    #: links registration renders and compares (None: all), set by :meth:`prepare`
    links: list[str] | None = None

    def prepare(self, recording: Path, robot_model: RobotModel, config: RegisterConfig) -> None:
        """Read what the segmentor needs from ``recording`` (default: nothing)."""
        return None

    @abstractmethod
    def __call__(self, frame: StereoFrame) -> tuple[np.ndarray, np.ndarray]:
        """``(left, right)`` robot masks ``[H, W]`` bool of ``frame``."""

    def describe(self) -> dict[str, Any]:
        """What pose.yaml records about the segmentation."""
        return {"kind": self.kind}


SEGMENTORS: dict[str, type[Segmentor]] = {}


def _registered(cls: type[Segmentor]) -> type[Segmentor]:
    SEGMENTORS[cls.kind] = cls
    return cls


def make_segmentor(kind: str, **options: Any) -> Segmentor:
    """A segmentor of ``kind`` (a key of :data:`SEGMENTORS`) built with ``options``."""
    if kind not in SEGMENTORS:
        raise SegmentationError(f"segmentor must be one of {', '.join(SEGMENTORS)}, got {kind!r}")
    return SEGMENTORS[kind](**options)


# --------------------------------------------------------------------------------------------
# frames of the window


class WindowFrames:
    """The usable frames of a recording for one robot (stereo pair and joint states), in stamp
    order: ``indices`` [N], ``stamps`` [N] ns, ``joints`` [N, D] (URDF order) and ``inside``
    [N] bool (within ``config``'s phase window)."""

    def __init__(
        self,
        path: Path,
        robot: str,
        indices: np.ndarray,
        stamps: np.ndarray,
        joints: np.ndarray,
        inside: np.ndarray,
        window: tuple[int | None, int | None],
    ) -> None:
        self.path, self.robot, self.window = path, robot, window
        self.indices, self.stamps, self.joints, self.inside = indices, stamps, joints, inside

    def reader(self, robot_model: RobotModel) -> RecordingReader:
        """A reader yielding exactly these frames (same robot and joint order)."""
        return RecordingReader(
            self.path,
            robots=[self.robot],
            joint_order={self.robot: robot_model.joint_names},
            on_error="skip",
        )


def window_frames(recording: Path, robot_model: RobotModel, config: RegisterConfig) -> WindowFrames:
    """The usable frames of ``recording`` for the robot :func:`register` would use, and which
    of them lie in ``config``'s phase window. Raises :class:`RecordingError` when none do."""
    with RecordingReader(recording, on_error="skip") as probe:
        robots = probe.robots
        metadata = probe.metadata()
    if not robots:
        raise RecordingError(f"{recording}: no /<robot>/joint_states topic")
    robot = config.robot or robots[0]
    if robot not in robots:
        raise RecordingError(f"{recording}: robot={robot} not found (robots: {robots})")
    window = phase_window(metadata, config.phase, config.start_ns, config.stop_ns, str(recording))
    lo, hi = window
    idx, stamps, joints = [], [], []
    with RecordingReader(
        recording, robots=[robot], joint_order={robot: robot_model.joint_names}, on_error="skip"
    ) as reader:
        for f in reader.frames(decode=False):
            idx.append(f.index)
            stamps.append(f.stamp_ns)
            joints.append(f.joints[robot])
    st = np.asarray(stamps, np.int64)
    inside = np.ones(len(st), bool)
    if lo is not None:
        inside &= st >= lo
    if hi is not None:
        inside &= st < hi
    if not inside.any():
        raise RecordingError(
            f"{recording}: no usable stereo frame with joint states in phase={config.phase} "
            f"window {window}"
        )
    q = np.asarray(joints, np.float64).reshape(len(st), robot_model.dof)
    return WindowFrames(recording, robot, np.asarray(idx, np.int64), st, q, inside, window)


def _read(reader: RecordingReader, index: int) -> StereoFrame:
    frame = next(reader.frames(index, index + 1), None)
    if frame is None:
        raise RecordingError(f"{reader.path}: frame {index} cannot be read")
    return frame


def _pack(mask: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
    return np.packbits(mask, axis=None), (int(mask.shape[0]), int(mask.shape[1]))


def _unpack(packed: tuple[np.ndarray, tuple[int, int]], shape: tuple[int, ...]) -> np.ndarray:
    bits, (h, w) = packed
    m = np.unpackbits(bits, count=h * w).reshape(h, w).astype(bool)
    H, W = shape[:2]
    if (h, w) == (H, W):
        return m
    return cv2.resize(m.astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR) > 0.5


# --------------------------------------------------------------------------------------------
# model


@_registered
class ModelSegmentor(Segmentor):
    """The exported ONNX model (``model=FILE.onnx``); ``onnx`` is the
    :class:`~roboseg.segmentor.OnnxSegmentor` that SDR with prior needs."""

    kind = "model"

    def __init__(self, model_file: str | Path, threads: int | None = None) -> None:
        from roboseg import segmentor as onnx_module

        self.model_file = Path(model_file)
        self.onnx = onnx_module.OnnxSegmentor(str(model_file), threads=threads)

    def __call__(self, frame: StereoFrame) -> tuple[np.ndarray, np.ndarray]:
        masks = self.onnx.predict_mask(np.stack([frame.left, frame.right]))
        return masks[0], masks[1]

    def describe(self) -> dict[str, Any]:
        return {"kind": self.kind, "model": str(self.model_file.resolve())}


# --------------------------------------------------------------------------------------------
# motion


@_registered
class MotionSegmentor(Segmentor):
    """Background subtraction with static cameras (:mod:`.motion`); registration renders only
    the links that moved (``links``) and trims the masks near its estimate (people walking)."""

    kind = "motion"
    trims = True

    def __init__(self, config: MotionConfig | None = None, **options: Any) -> None:
        self.cfg = config or MotionConfig(**options)
        self.models: list[BackgroundModel] = []
        self.motion: dict[str, float] = {}

    def prepare(self, recording: Path, robot_model: RobotModel, config: RegisterConfig) -> None:
        wf = window_frames(recording, robot_model, config)
        rows = np.flatnonzero(wf.inside)
        where = f"{recording}: phase={config.phase}"
        if len(rows) < 3:
            raise NoMotionError(
                f"{where}: {len(rows)} usable frames; segmentor=motion needs at least 3"
            )
        q = wf.joints[rows]
        self.motion = link_motion(robot_model, q)
        moved = [n for n, d in self.motion.items() if d >= self.cfg.link_motion]
        if not moved:
            name = max(self.motion, key=lambda n: self.motion[n])
            raise NoMotionError(
                f"{where}: the robot does not move (no link moved {1000 * self.cfg.link_motion:.0f}"
                f" mm over {len(rows)} frames; most: {name} {1000 * self.motion[name]:.0f} mm); "
                "segmentor=motion needs a moving robot, use segmentor=prompt"
            )
        scale = (robot_model.upper - robot_model.lower).double().cpu().numpy()
        picked = rows[spread_configurations(q, self.cfg.background_frames, scale)]
        images: list[list[np.ndarray]] = [[], []]
        with wf.reader(robot_model) as reader:
            for i in sorted(int(wf.indices[r]) for r in picked):
                frame = _read(reader, i)
                images[0].append(frame.left)
                images[1].append(frame.right)
        self.models = [BackgroundModel(x, self.cfg) for x in images]
        for cam, model in zip(CAMERAS, self.models, strict=True):
            if model.fitted_foreground < self.cfg.min_area:
                raise NoMotionError(
                    f"{where}: no moving pixels in the {cam} camera although links "
                    f"{moved} moved (robot out of view, or the camera moved)"
                )
        self.frames = [int(i) for i in wf.indices[rows]]
        self.links = moved
        log.info("motion: background of %d frames per camera; moving links %s", len(picked), moved)

    def __call__(self, frame: StereoFrame) -> tuple[np.ndarray, np.ndarray]:
        if not self.models:
            raise SegmentationError("motion segmentor used before prepare()")
        return self.models[0].segment(frame.left), self.models[1].segment(frame.right)

    def describe(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "background": self.cfg.background,
            "link_motion_mm": {n: round(1000 * d, 1) for n, d in self.motion.items()},
            "frames_with_dropped_blobs": [m.dropped_frames for m in self.models],
        }


# --------------------------------------------------------------------------------------------
# prompted kinds


def strided_span(positions: np.ndarray, start: int, max_frames: int) -> tuple[list[int], list[int]]:
    """Positions to segment from the prompted one, ``start``, through the span covering it and
    ``positions`` (sorted, e.g. the window's), at most ``max_frames`` evenly strided:
    ``(forward, backward)`` in processing order, both beginning at ``start``."""
    lo, hi = min(int(positions.min()), start), max(int(positions.max()), start)
    stride = max(1, math.ceil((hi - lo + 1) / max_frames))
    return list(range(start, hi + 1, stride)), list(range(start, lo - 1, -stride))


class _Prompted(Segmentor):
    """Shared by the prompt-driven kinds: the prompt file, the frames to segment and the
    stored masks (bit-packed) by frame index."""

    def __init__(self, prompt: str | Path | None, max_frames: int) -> None:
        if prompt is None:
            raise SegmentationError(
                f"segmentor={self.kind} needs a prompt file (prompt=FILE.yaml: per camera a box "
                "and/or clicks in one frame)"
            )
        self.prompt: Prompt = load_prompt(prompt)
        self.max_frames = int(max_frames)
        self.masks: dict[int, tuple[Any, Any]] = {}
        self.prompt_frame: int | None = None

    def _plan(
        self, recording: Path, robot_model: RobotModel, config: RegisterConfig
    ) -> tuple[WindowFrames, list[int], list[int]]:
        """The window's frames and the frame indices to segment (forward, backward)."""
        wf = window_frames(recording, robot_model, config)
        k = resolve_prompt_frame(self.prompt, wf.indices, wf.stamps)
        pos = int(np.flatnonzero(wf.indices == k)[0])
        forward, backward = strided_span(np.flatnonzero(wf.inside), pos, self.max_frames)
        self.prompt_frame = k
        in_window = set(np.flatnonzero(wf.inside).tolist())
        self.frames = sorted({int(wf.indices[p]) for p in forward + backward if p in in_window})
        log.info(
            "%s: prompt on frame %d; segmenting %d frames (%d in the window)",
            self.kind,
            k,
            len(set(forward + backward)),
            len(self.frames),
        )
        return wf, [int(wf.indices[p]) for p in forward], [int(wf.indices[p]) for p in backward]

    def _check_prompt(self, frame: StereoFrame) -> None:
        sizes = {
            "left": (frame.left.shape[1], frame.left.shape[0]),
            "right": (frame.right.shape[1], frame.right.shape[0]),
        }
        self.prompt.check_inside(sizes)

    def __call__(self, frame: StereoFrame) -> tuple[np.ndarray, np.ndarray]:
        if frame.index not in self.masks:
            raise SegmentationError(
                f"segmentor={self.kind} did not segment frame {frame.index} "
                "(prepare() first; only the frames in `frames`)"
            )
        left, right = self.masks[frame.index]
        return _unpack(left, frame.left.shape), _unpack(right, frame.right.shape)

    def describe(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "prompt": str(self.prompt.path.resolve()),
            "prompt_frame": self.prompt_frame,
            "frames_segmented": len(self.masks),
        }


@_registered
class PromptSegmentor(_Prompted):
    """GrabCut from the prompt file, tracked through the recording (:mod:`.grabcut`)."""

    kind = "prompt"

    def __init__(
        self, prompt: str | Path | None, config: GrabCutConfig | None = None, **options: Any
    ) -> None:
        self.cfg = config or GrabCutConfig(**options)
        super().__init__(prompt, self.cfg.max_frames)
        self.fallbacks = 0

    def prepare(self, recording: Path, robot_model: RobotModel, config: RegisterConfig) -> None:
        wf, forward, backward = self._plan(recording, robot_model, config)
        trackers = [GrabCutTracker(self.cfg) for _ in CAMERAS]
        with wf.reader(robot_model) as reader:
            first = _read(reader, forward[0])
            self._check_prompt(first)
            for t, cam, img in zip(trackers, CAMERAS, (first.left, first.right), strict=True):
                t.start(img, self.prompt.cameras[cam], where=f"{self.prompt.path}: {cam}")
            start = [(t.image, t.mask) for t in trackers]
            self._store(first.index, trackers)
            for order in (forward[1:], backward[1:]):
                for t, (image, mask) in zip(trackers, start, strict=True):
                    t.image, t.mask = image, mask
                for i in order:
                    frame = _read(reader, i)
                    trackers[0].step(frame.left)
                    trackers[1].step(frame.right)
                    self._store(i, trackers)
        self.fallbacks = sum(t.fallbacks for t in trackers)
        if self.fallbacks:
            log.warning(
                "prompt: %d of %d masks kept the tracked mask (GrabCut's area jumped)",
                self.fallbacks,
                2 * len(self.masks),
            )

    def _store(self, index: int, trackers: list[GrabCutTracker]) -> None:
        assert all(t.mask is not None for t in trackers)
        self.masks[index] = (_pack(trackers[0].mask), _pack(trackers[1].mask))  # type: ignore[arg-type]

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "tracking_fallbacks": self.fallbacks}


@_registered
class Sam2Segmentor(_Prompted):
    """SAM 2's video predictor from the prompt file: one video per camera, the prompt on its
    frame, propagated forward and backward through the frames to segment.

    ``predictor``: an object with SAM 2's video-predictor methods (``init_state``,
    ``add_new_points_or_box``, ``propagate_in_video``); None builds one from ``checkpoint`` (a
    local file) and ``model_config`` with the ``sam2`` package (``build``: how, for tests).
    """

    kind = "sam2"

    def __init__(
        self,
        prompt: str | Path | None,
        checkpoint: str | Path | None = None,
        model_config: str = "configs/sam2.1/sam2.1_hiera_t.yaml",
        device: str = "cpu",
        max_frames: int = 200,
        predictor: Any | None = None,
        build: Callable[[str, Path, str], Any] | None = None,
    ) -> None:
        if predictor is None:
            try:
                importlib.import_module("sam2.build_sam")
            except ImportError as exc:
                raise SegmentationError(SAM2_INSTALL) from exc
            if checkpoint is None:
                raise SegmentationError(
                    "sam2.checkpoint: required: a local SAM 2 checkpoint file (.pt; roboseg "
                    "never downloads one)"
                )
            if not Path(checkpoint).is_file():
                raise SegmentationError(f"sam2.checkpoint: no such file {checkpoint}")
        super().__init__(prompt, max_frames)
        self.checkpoint = None if checkpoint is None else Path(checkpoint)
        self.model_config, self.device = str(model_config), str(device)
        self.predictor = predictor
        self.build = build or build_sam2_predictor

    def prepare(self, recording: Path, robot_model: RobotModel, config: RegisterConfig) -> None:
        wf, forward, backward = self._plan(recording, robot_model, config)
        order = sorted(set(forward + backward))
        local = {idx: n for n, idx in enumerate(order)}
        with tempfile.TemporaryDirectory(prefix="roboseg_sam2_") as tmp:
            folders = [Path(tmp) / cam for cam in CAMERAS]
            for folder in folders:
                folder.mkdir()
            with wf.reader(robot_model) as reader:
                for idx in order:
                    frame = _read(reader, idx)
                    if idx == forward[0]:
                        self._check_prompt(frame)
                    for folder, img in zip(folders, (frame.left, frame.right), strict=True):
                        path = str(folder / f"{local[idx]:05d}.jpg")
                        bgr = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
                        cv2.imwrite(path, bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
            if self.predictor is None:
                assert self.checkpoint is not None
                self.predictor = self.build(self.model_config, self.checkpoint, self.device)
            per_camera = [
                self._track(folder, self.prompt.cameras[cam], local[forward[0]], len(order))
                for cam, folder in zip(CAMERAS, folders, strict=True)
            ]
        for idx in order:
            left, right = (masks.get(local[idx]) for masks in per_camera)
            if left is None or right is None:
                raise SegmentationError(
                    f"sam2: the predictor returned no mask for frame {idx} "
                    f"(local {local[idx]} of {len(order)})"
                )
            self.masks[idx] = (left, right)

    def _track(
        self, folder: Path, prompt: Any, start: int, n_frames: int
    ) -> dict[int, tuple[np.ndarray, tuple[int, int]]]:
        """Packed masks by local frame number, of one camera's video in ``folder``."""
        predictor = self.predictor
        state = predictor.init_state(video_path=str(folder))
        points, labels = prompt.points_and_labels()
        box = None if prompt.box is None else np.asarray(prompt.box, np.float32)
        predictor.add_new_points_or_box(
            inference_state=state,
            frame_idx=start,
            obj_id=1,
            points=points if len(points) else None,
            labels=labels if len(points) else None,
            box=box,
        )
        out: dict[int, tuple[np.ndarray, tuple[int, int]]] = {}
        for reverse in (False, True):
            for idx, _obj_ids, logits in predictor.propagate_in_video(state, reverse=reverse):
                out[int(idx)] = _pack(_first_mask(logits) > 0.0)
        if hasattr(predictor, "reset_state"):
            predictor.reset_state(state)
        return out

    def describe(self) -> dict[str, Any]:
        return {
            **super().describe(),
            "checkpoint": None if self.checkpoint is None else str(self.checkpoint.resolve()),
            "model_config": self.model_config,
        }


def _first_mask(logits: Any) -> np.ndarray:
    """The first object's mask logits ``[H, W]`` from SAM 2's ``[objects, 1, H, W]`` output (a
    torch tensor or an array)."""
    if hasattr(logits, "detach"):
        logits = logits.detach().float().cpu().numpy()
    x = np.asarray(logits, np.float32)
    while x.ndim > 2:
        x = x[0]
    return x


def build_sam2_predictor(model_config: str, checkpoint: Path, device: str) -> Any:
    """SAM 2's video predictor from a local ``checkpoint`` and a ``model_config`` of the
    ``sam2`` package (its own Hydra configs, composed outside the running roboseg app)."""
    try:
        from hydra import initialize_config_module
        from hydra.core.global_hydra import GlobalHydra
        from hydra.initialize import get_gh_backup, restore_gh_from_backup
        from sam2.build_sam import build_sam2_video_predictor
    except ImportError as exc:
        raise SegmentationError(SAM2_INSTALL) from exc
    backup = get_gh_backup()
    GlobalHydra.instance().clear()
    try:
        with initialize_config_module("sam2", version_base="1.2"):
            return build_sam2_video_predictor(model_config, str(checkpoint), device=device)
    except Exception as exc:  # noqa: BLE001 - sam2/hydra/torch raise their own types
        raise SegmentationError(
            f"sam2: cannot build {model_config} from {checkpoint} ({type(exc).__name__}: {exc})"
        ) from exc
    finally:
        restore_gh_from_backup(backup)
