"""Self-annotation of one recording: FK of the robot model + hard rendering in both cameras.

For every kept frame the union of all robots' silhouettes (full, undecimated model posed with
the interpolated joint states and placed by ``T_left_base``) is rendered in the left and right
camera at the recording's resolution and written as PNG mask topics next to raw copies of the
input's messages (image messages only for kept frames). With ``mesh_reduction`` a decimated
model is used instead where its masks agree with the full model's (IoU checked per recording).
"""

from __future__ import annotations

import copy
import logging
import time
import weakref
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, overload

import numpy as np
import torch
from mcap.data_stream import ReadDataStream
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import breakup_chunk

from roboseg.annotate.calibration import right_from_left, robot_poses
from roboseg.annotate.output import (
    AnnotatedWriter,
    cdr_frame_id,
    encode_mask_png,
    sha256_file,
)
from roboseg.annotate.parallel import MaskStream
from roboseg.annotate.selection import (
    joint_speed_at,
    phase_mask,
    thin_evenly,
)
from roboseg.errors import RecordingError, RobotModelError
from roboseg.recording import RecordingReader, msgs
from roboseg.recording.reader import MAGIC, message_stamp_ns
from roboseg.recording.topics import ROBOT_MASK, mask_topic
from roboseg.render import render_hard
from roboseg.robot import RobotModel
from roboseg.sim import SIM_METADATA
from roboseg.sim.simulate import is_closed

log = logging.getLogger(__name__)

SKIP_REASONS = (
    "no_joint_state",
    "unpaired_stereo",
    "corrupt",
    "low_motion",
    "subsampled",
    "unreadable",
    "phase",
)
_MASK_SCHEMA = Schema(
    id=0,
    name=msgs.COMPRESSED_IMAGE,
    encoding="ros2msg",
    data=msgs.MSGDEFS[msgs.COMPRESSED_IMAGE].encode(),
)
_RECORD_HEAD = 9  # opcode (1 byte) + record length (8 bytes)


@dataclass(frozen=True)
class AnnotateOptions:
    """How to annotate. ``fraction``: kept share of all frames (None: every moving frame);
    ``min_joint_speed`` in rad/s (or m/s); tolerances in ns; ``png_level`` zlib level 0-9;
    ``workers``: processes rendering masks (``<= 1``: in the calling process).

    ``mesh_reduction``: share of the robot mesh's faces removed for the masks (0: the full
    mesh). A reduced mesh renders faster; it is used for a recording only when its masks reach
    an IoU of ``mesh_min_iou`` against the full mesh's in both cameras of each of
    ``mesh_check_frames`` kept frames spread over the recording (otherwise the full mesh is
    used and a warning logged); the manifest records the outcome."""

    camera: str = "camera"
    fraction: float | None = None
    min_joint_speed: float = 0.01
    phase: str = "all"
    calibration: str | None = None
    tolerance_ns: int = 20_000_000
    stereo_tolerance_ns: int = 1_000_000
    png_level: int = 1
    workers: int = 1
    mesh_reduction: float = 0.0
    mesh_min_iou: float = 0.995
    mesh_check_frames: int = 8


@dataclass
class RecordingResult:
    """What :func:`annotate_recording` did to one recording (a manifest entry)."""

    file: str
    source: str
    split: str
    sha256: str = ""
    frames_total: int = 0
    frames_kept: int = 0
    skipped: dict[str, int] = field(default_factory=lambda: dict.fromkeys(SKIP_REASONS, 0))
    robots: list[str] = field(default_factory=list)
    calibration: str = "tf_static"
    draped_from_ns: int | None = None
    errors: list[str] = field(default_factory=list)
    #: with ``mesh_reduction`` > 0: reduction asked for, reduction used (0.0: the full mesh),
    #: worst IoU of the reduced mesh's masks against the full mesh's
    mesh: dict[str, float] | None = None
    #: wall-clock seconds before the first mask (reading, selecting, set-up) and in all
    #: (not part of the manifest, which stays the same for the same inputs)
    setup_seconds: float = 0.0
    seconds: float = 0.0

    def manifest_entry(self) -> dict[str, Any]:
        """The recording's entry of ``manifest.json``."""
        entry = {
            "file": self.file if self.sha256 else None,
            "source": self.source,
            "split": self.split,
            "sha256": self.sha256,
            "frames_total": self.frames_total,
            "frames_kept": self.frames_kept,
            "skipped": dict(self.skipped),
            "robots": list(self.robots),
            "calibration": self.calibration,
            "draped_from_ns": self.draped_from_ns,
            "errors": list(self.errors),
        }
        if self.mesh is not None:
            entry["mesh"] = dict(self.mesh)
        return entry


def is_mcap(path: Path) -> bool:
    """True when the file starts with the MCAP magic bytes."""
    with open(path, "rb") as f:
        return f.read(len(MAGIC)) == MAGIC


def is_complete(path: Path) -> bool:
    """True when the file also ends with the MCAP magic (not truncated)."""
    with open(path, "rb") as f:
        f.seek(0, 2)
        if f.tell() < 2 * len(MAGIC):
            return False
        f.seek(-len(MAGIC), 2)
        return f.read() == MAGIC


def joint_permutation(robot: RobotModel, names: list[str], where: str) -> list[int]:
    """Column order turning joint vectors in ``names`` order into the URDF's joint order."""
    if sorted(names) != sorted(robot.joint_names):
        raise RobotModelError(
            f"{where}: joint names {sorted(names)} do not match the URDF's "
            f"{sorted(robot.joint_names)} (robot {robot.name!r})"
        )
    return [names.index(n) for n in robot.joint_names]


def draped_from(metadata: dict[str, dict[str, str]]) -> int | None:
    """``drape_start_stamp_ns`` of the simulator's metadata (None if absent or negative)."""
    value = metadata.get(SIM_METADATA, {}).get("drape_start_stamp_ns")
    if value is None or int(value) < 0:
        return None
    return int(value)


_CLOSED: dict[int, tuple[weakref.ref, bool]] = {}


def mesh_is_closed(robot: RobotModel) -> bool:
    """:func:`roboseg.sim.simulate.is_closed` of the robot's mesh, cached per model."""
    hit = _CLOSED.get(id(robot))
    if hit is not None and hit[0]() is robot:
        return hit[1]
    closed = is_closed(
        robot.vertices.double().numpy(), robot.faces.numpy(), robot.vertex_link.numpy()
    )
    _CLOSED[id(robot)] = (weakref.ref(robot), closed)
    log.debug("robot %s: mesh %s", robot.name, "closed" if closed else "open (no culling)")
    return closed


_DECIMATED: dict[tuple[int, float], tuple[weakref.ref, RobotModel]] = {}


def decimated_model(robot: RobotModel, reduction: float) -> RobotModel:
    """``robot.decimated(reduction)``, kept per model and reduction (the recordings of a folder
    share it, and with it the cached :func:`mesh_is_closed`)."""
    key = (id(robot), float(reduction))
    hit = _DECIMATED.get(key)
    if hit is not None and hit[0]() is robot:
        return hit[1]
    reduced = robot.decimated(reduction)
    _DECIMATED[key] = (weakref.ref(robot), reduced)
    return reduced


class MaskRenderer:
    """Silhouettes of posed robots in a stereo camera (one hard render of both views).

    Back faces are culled when the robot's mesh is closed and outward-wound
    (:func:`roboseg.sim.simulate.is_closed`): every ray that meets such a mesh enters it
    through a front face, so the silhouette is the same at about half the cost.
    """

    def __init__(
        self,
        robot: RobotModel,
        poses: dict[str, np.ndarray],
        T_right_left: np.ndarray,
        K_left: np.ndarray,
        K_right: np.ndarray,
        size: tuple[int, int],
    ) -> None:
        self.robot = robot
        self.height, self.width = size
        f32 = torch.float32
        left = {r: torch.as_tensor(T, dtype=f32) for r, T in poses.items()}
        right_left = torch.as_tensor(T_right_left, dtype=f32)
        #: per robot: [2, 4, 4] T_view_base for (left, right)
        self.T = {r: torch.stack([T, right_left @ T]) for r, T in left.items()}
        self.K = torch.stack(
            [torch.as_tensor(K_left, dtype=f32), torch.as_tensor(K_right, dtype=f32)]
        )
        self.robots = list(poses)
        n_v = robot.vertices.shape[0]
        self.faces = torch.cat([robot.faces + k * n_v for k in range(len(self.robots))])
        self.cull = mesh_is_closed(robot)

    def render(self, joints: dict[str, np.ndarray]) -> np.ndarray:
        """Bool [2, H, W] (left, right) union silhouette for URDF-ordered joints per robot."""
        n_v = self.robot.vertices.shape[0]
        # both views' vertices, robot after robot, written in place (a contiguous [2, V, 3]
        # is also what the raster reads fastest)
        verts = torch.empty(2, n_v * len(self.robots), 3)
        for k, r in enumerate(self.robots):
            v = self.robot.posed_vertices(torch.as_tensor(joints[r]).unsqueeze(0))[0]
            T = self.T[r]
            rotated = torch.einsum("vj,bij->bvi", v, T[:, :3, :3])
            torch.add(rotated, T[:, None, :3, 3], out=verts[:, k * n_v : (k + 1) * n_v])
        with torch.no_grad():
            mask = render_hard(
                verts,
                self.faces,
                self.K,
                self.height,
                self.width,
                cull_back_faces=self.cull,
            )
        return mask.numpy()

    def encode(self, joints: dict[str, np.ndarray], level: int = 1) -> tuple[bytes, bytes]:
        """(left, right) PNG masks of :meth:`render` (``level``: zlib level 0-9)."""
        left, right = self.render(joints)
        return encode_mask_png(left, level), encode_mask_png(right, level)

    def with_robot(self, robot: RobotModel) -> MaskRenderer:
        """The same cameras and robot poses with another model of the robot (e.g. decimated;
        same kinematics)."""
        other = copy.copy(self)
        other.robot = robot
        n_v = robot.vertices.shape[0]
        other.faces = torch.cat([robot.faces + k * n_v for k in range(len(self.robots))])
        other.cull = mesh_is_closed(robot)
        return other


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two bool masks (1.0 when both are empty)."""
    union = int(np.count_nonzero(a | b))
    return 1.0 if union == 0 else int(np.count_nonzero(a & b)) / union


def reduced_mesh_renderer(
    full: MaskRenderer,
    joints: Sequence[dict[str, np.ndarray]],
    reduction: float,
    min_iou: float,
    check_frames: int,
) -> tuple[MaskRenderer, dict[str, float]]:
    """The renderer of the robot's mesh reduced by ``reduction`` (share of faces removed) if
    its masks reach ``min_iou`` against the full mesh's in both cameras of ``check_frames``
    frames of ``joints`` spread evenly over them, else ``full``; and what was found:
    ``{"reduction": asked, "used": reduction or 0.0, "min_iou": worst IoU}``."""
    reduced = full.with_robot(decimated_model(full.robot, reduction))
    worst = 1.0
    for k in thin_evenly(np.arange(len(joints)), max(1, check_frames)):
        ref, test = full.render(joints[int(k)]), reduced.render(joints[int(k)])
        worst = min(worst, mask_iou(ref[0], test[0]), mask_iou(ref[1], test[1]))
    ok = worst >= min_iou
    log.debug("mesh reduced by %g: worst IoU %.4f against the full mesh", reduction, worst)
    found = {"reduction": float(reduction), "used": float(reduction) if ok else 0.0}
    found["min_iou"] = round(worst, 6)
    return (reduced if ok else full), found


def annotate_recording(
    source: str | Path,
    out_path: str | Path,
    robot: RobotModel,
    options: AnnotateOptions,
    split: str = "train",
    target: int | None = None,
) -> RecordingResult:
    """Annotate ``source`` into ``out_path``; ``target`` frames kept at most (None: all moving).

    Damaged files are read as far as possible (counted in ``skipped.unreadable``); user errors
    (missing topic / CameraInfo / tf, joint-name mismatch) raise :class:`RobosegError`.
    """
    t_start = time.perf_counter()
    source, out_path = Path(source), Path(out_path)
    result = RecordingResult(out_path.name, str(source.resolve()), split)
    if not is_mcap(source):
        result.skipped["unreadable"] = 1
        result.errors.append(f"{source}: not an MCAP file (bad magic bytes)")
        log.warning("%s", result.errors[-1])
        return result
    try:
        reader = RecordingReader(
            source,
            camera=options.camera,
            tolerance_ns=options.tolerance_ns,
            stereo_tolerance_ns=options.stereo_tolerance_ns,
            on_error="skip",
        )
    except RecordingError as exc:
        if is_complete(source):
            raise  # a user error (e.g. missing topic), not damage
        result.skipped["unreadable"] = 1
        result.errors.append(f"{source}: truncated beyond use ({exc})")
        log.warning("%s", result.errors[-1])
        return result
    with reader:
        _annotate(reader, out_path, robot, options, target, result, t_start)
    result.sha256 = sha256_file(out_path)
    result.seconds = time.perf_counter() - t_start
    return result


class JointTable(Sequence[dict[str, np.ndarray]]):
    """Joint vectors of frames as one ``[N, D]`` array per robot; item ``k`` is the dict
    ``{robot: joints[k]}`` and slices are tables (a few bytes per frame, no per-frame
    objects)."""

    def __init__(self, arrays: dict[str, np.ndarray]) -> None:
        self.arrays = arrays
        self._n = len(next(iter(arrays.values()))) if arrays else 0

    def __len__(self) -> int:
        return self._n

    @overload
    def __getitem__(self, k: int) -> dict[str, np.ndarray]: ...

    @overload
    def __getitem__(self, k: slice) -> JointTable: ...

    def __getitem__(self, k: int | slice) -> dict[str, np.ndarray] | JointTable:
        if isinstance(k, slice):
            return JointTable({r: a[k] for r, a in self.arrays.items()})
        if not -self._n <= k < self._n:
            raise IndexError(f"frame {k} out of range ({self._n} frames)")
        return {r: a[k] for r, a in self.arrays.items()}


def _select(
    reader: RecordingReader,
    robot: RobotModel,
    options: AnnotateOptions,
    target: int | None,
    result: RecordingResult,
) -> tuple[np.ndarray, JointTable]:
    """Stamps (sorted) and URDF-ordered joints of the kept frames; fills ``result`` counts."""
    names = reader.joint_names()
    perms = {
        r: joint_permutation(robot, names[r], f"{reader.path} /{r}/joint_states")
        for r in reader.robots
    }
    stamps = np.empty(max(len(reader), 1), dtype=np.int64)
    table: dict[str, np.ndarray] = {}
    n = 0
    for frame in reader.frames(decode=False):
        if n == len(stamps):  # more frames than left images: grow (not expected)
            stamps = np.concatenate([stamps, np.empty_like(stamps)])
            table = {r: np.concatenate([a, np.empty_like(a)]) for r, a in table.items()}
        stamps[n] = frame.stamp_ns
        for r in reader.robots:
            q = frame.joints[r][perms[r]]
            if r not in table:
                table[r] = np.empty((len(stamps), len(q)), dtype=q.dtype)
            table[r][n] = q
        n += 1
    stats = reader.stats
    skipped = result.skipped
    skipped["no_joint_state"] = stats.skipped_no_joint_state
    skipped["unpaired_stereo"] = stats.skipped_unpaired
    skipped["corrupt"] = stats.skipped_corrupt
    skipped["unreadable"] = len(reader.errors)
    result.errors.extend(reader.errors)
    result.frames_total = len(reader)
    stamps_arr = stamps[:n]
    speed = np.zeros(len(stamps_arr))
    for r in reader.robots:
        s, q = reader.joint_samples(r)
        speed = np.maximum(speed, joint_speed_at(s, q, stamps_arr))
    in_phase = phase_mask(stamps_arr, options.phase, result.draped_from_ns)
    moving = speed >= options.min_joint_speed
    skipped["phase"] = int((~in_phase).sum())
    skipped["low_motion"] = int((in_phase & ~moving).sum())
    candidates = np.flatnonzero(in_phase & moving)
    kept = candidates if target is None else thin_evenly(candidates, target)
    skipped["subsampled"] = len(candidates) - len(kept)
    result.frames_kept = len(kept)
    joints = {r: (a[kept] if n else a[:0]) for r, a in table.items()}
    return stamps_arr[kept], JointTable(joints)


def _annotate(
    reader: RecordingReader,
    out_path: Path,
    robot: RobotModel,
    options: AnnotateOptions,
    target: int | None,
    result: RecordingResult,
    t_start: float,
) -> None:
    path = reader.path
    if not reader.robots:
        raise RecordingError(
            f"{path}: no /<robot>/joint_states topic (topics: {', '.join(sorted(reader.topics()))})"
        )
    result.robots = reader.robots
    result.draped_from_ns = draped_from(reader.metadata())
    left, right = reader.camera_infos("left"), reader.camera_infos("right")
    poses, result.calibration = robot_poses(
        reader, reader.robots, robot.root_link, options.calibration
    )
    T_right_left = right_from_left(reader)
    if (left.height, left.width) != (right.height, right.width):
        raise RecordingError(
            f"{path}: left and right cameras differ in size "
            f"({left.width}x{left.height} vs {right.width}x{right.height})"
        )
    if np.any(left.D != 0) or np.any(right.D != 0):
        log.warning("%s: distortion ignored; masks use the pinhole model of K", path)
    kept_stamps, kept_joints = _select(reader, robot, options, target, result)
    renderer = MaskRenderer(robot, poses, T_right_left, left.K, right.K, (left.height, left.width))
    if options.mesh_reduction > 0:
        renderer, result.mesh = reduced_mesh_renderer(
            renderer,
            kept_joints,
            options.mesh_reduction,
            options.mesh_min_iou,
            options.mesh_check_frames,
        )
        if result.mesh["used"] == 0.0:
            log.warning(
                "%s: masks of the mesh reduced by %g reach IoU %.4f < %g against the full "
                "mesh's; using the full mesh",
                path,
                options.mesh_reduction,
                result.mesh["min_iou"],
                options.mesh_min_iou,
            )
    topics = {
        reader.left_topic: mask_topic(options.camera, "left", ROBOT_MASK),
        reader.right_topic: mask_topic(options.camera, "right", ROBOT_MASK),
    }
    with (
        MaskStream(renderer, kept_joints, options.png_level, options.workers) as masks,
        AnnotatedWriter(out_path) as writer,
    ):
        result.setup_seconds = time.perf_counter() - t_start
        _copy_and_annotate(reader, writer, masks, kept_stamps, topics, options)
    log.info(
        "%s: kept %d of %d frames -> %s", path, result.frames_kept, result.frames_total, out_path
    )


def _nearest(sorted_stamps: np.ndarray, stamp: int, tolerance: int) -> int:
    """Index of the nearest stamp within ``tolerance`` ns, or -1."""
    if len(sorted_stamps) == 0:
        return -1
    i = int(np.searchsorted(sorted_stamps, stamp))
    near = [j for j in (i - 1, i) if 0 <= j < len(sorted_stamps)]
    j = min(near, key=lambda j: abs(int(sorted_stamps[j]) - stamp))
    return j if abs(int(sorted_stamps[j]) - stamp) <= tolerance else -1


def _copy_and_annotate(
    reader: RecordingReader,
    writer: AnnotatedWriter,
    masks: MaskStream,
    kept_stamps: np.ndarray,
    topics: dict[str, str],
    options: AnnotateOptions,
) -> None:
    """Walk the readable chunks: copy messages, keep images of kept frames, add their masks."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    own_masks = set(topics.values())
    pending: dict[int, list[bytes | None]] = {}  # kept frame -> [left png, right png]
    sides = {reader.left_topic: 0, reader.right_topic: 1}
    with open(reader.path, "rb") as f:
        for info in reader.chunk_index():
            f.seek(info.offset + _RECORD_HEAD)
            for record in breakup_chunk(Chunk.read(ReadDataStream(f)), validate_crc=False):
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message) and record.channel_id in channels:
                    channel = channels[record.channel_id]
                    if channel.topic in own_masks:
                        continue
                    schema = schemas.get(channel.schema_id)
                    if schema is None or schema.name != msgs.COMPRESSED_IMAGE:
                        writer.copy(channel, schema, record)
                        continue
                    stamp = message_stamp_ns(record.data, record.log_time)
                    k = _nearest(kept_stamps, stamp, options.stereo_tolerance_ns)
                    if k < 0:
                        continue
                    writer.copy(channel, schema, record)
                    side = sides.get(channel.topic)
                    if side is None:
                        continue
                    if k not in pending:
                        pending[k] = masks.get(k)
                    png = pending[k][side]
                    if png is None:
                        continue  # duplicate image message of the same frame
                    frame_id = cdr_frame_id(record.data)
                    writer.write_mask(
                        topics[channel.topic], _MASK_SCHEMA, stamp, frame_id, png, record.log_time
                    )
                    pending[k][side] = None
                    if pending[k] == [None, None]:
                        del pending[k]


__all__ = [
    "SKIP_REASONS",
    "AnnotateOptions",
    "MaskRenderer",
    "RecordingResult",
    "annotate_recording",
    "draped_from",
    "joint_permutation",
    "mask_iou",
    "reduced_mesh_renderer",
]
