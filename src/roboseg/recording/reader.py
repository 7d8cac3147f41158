"""Stream stereo frames with synchronised joint states out of a roboseg MCAP recording.

One indexing pass reads every chunk once (validating CRCs) and keeps only small things: joint
states, ``/tf_static``, CameraInfo, metadata and, for every image/mask message, its header stamp
and location (chunk, position). Frames are then streamed chunk by chunk through a small cache,
so memory does not grow with the recording length.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import os
import struct
from array import array
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, Literal

import cv2
import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk
from mcap_ros2.decoder import DecoderFactory

from roboseg.errors import RecordingError
from roboseg.recording import msgs
from roboseg.recording.msgs import CameraCalib, CameraInfo, StereoFrame
from roboseg.recording.sync import interpolate_at, prepare_samples
from roboseg.recording.tf import lookup_transform, make_transform, quaternion_to_matrix
from roboseg.recording.topics import (
    DEFAULT_CAMERA,
    TF_STATIC,
    camera_info_topic,
    image_topic,
    joint_states_topic,
    resolve_mask_topic,
    robots_from_topics,
)

logger = logging.getLogger(__name__)

MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = struct.Struct("<BQ")


@dataclass(frozen=True)
class ChunkInfo:
    """One MCAP chunk: file ``offset`` of its record, log-time range (ns), left frames in it."""

    id: int
    offset: int
    start_ns: int
    end_ns: int
    n_frames: int


@dataclass
class ReadStats:
    """What the last :meth:`RecordingReader.frames` call yielded and skipped, and why."""

    yielded: int = 0
    skipped_no_joint_state: int = 0
    skipped_unpaired: int = 0
    skipped_corrupt: int = 0
    skipped_no_mask: int = 0
    errors: list[str] = field(default_factory=list)

    @property
    def skipped(self) -> int:
        """Total number of skipped frames."""
        return (
            self.skipped_no_joint_state
            + self.skipped_unpaired
            + self.skipped_corrupt
            + self.skipped_no_mask
        )


@dataclass
class _ImageRefs:
    """Header stamps (ns) and locations of the messages of one image/mask topic."""

    stamps: array = field(default_factory=lambda: array("q"))
    chunks: array = field(default_factory=lambda: array("q"))
    positions: array = field(default_factory=lambda: array("q"))

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        order = np.argsort(np.asarray(self.stamps, dtype=np.int64), kind="stable")
        return (
            np.asarray(self.stamps, dtype=np.int64)[order],
            np.asarray(self.chunks, dtype=np.int64)[order],
            np.asarray(self.positions, dtype=np.int64)[order],
        )


@dataclass
class _Index:
    """Everything the indexing pass keeps (small; no image data)."""

    topics: dict[str, str] = field(default_factory=dict)
    chunks: list[ChunkInfo] = field(default_factory=list)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    images: dict[str, _ImageRefs] = field(default_factory=dict)
    image_schemas: dict[str, Schema] = field(default_factory=dict)
    joint_names: dict[str, list[str]] = field(default_factory=dict)
    joint_stamps: dict[str, array] = field(default_factory=dict)  # 'q': ns
    joint_values: dict[str, array] = field(default_factory=dict)  # 'd': row-major [N, D]
    joint_errors: dict[str, str] = field(default_factory=dict)
    small: dict[str, list[tuple[Schema | None, bytes]]] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)


def message_stamp_ns(data: bytes, log_time: int) -> int:
    """Header stamp of a CDR message, falling back to the MCAP log time when it is zero."""
    try:
        stamp = msgs.cdr_header_stamp_ns(data)
    except ValueError:
        return log_time
    return stamp if stamp != 0 else log_time


def decode_image(data: bytes) -> np.ndarray | None:
    """JPEG/PNG bytes -> ``HxWx3`` uint8 RGB, or None when the bytes do not decode."""
    bgr = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if bgr is None or bgr.ndim != 3:
        return None
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def decode_mask(data: bytes) -> np.ndarray | None:
    """PNG mask bytes -> ``HxW`` bool (pixel > 127), or None when the bytes do not decode."""
    gray = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
    if gray is None:
        return None
    return gray > 127


class RecordingReader:
    """Read a roboseg recording (MCAP, ROS 2 CDR) as a stream of :class:`StereoFrame`.

    Stereo pairs match by header stamp within ``stereo_tolerance_ns``; each robot's joint
    positions are linearly interpolated to the left image stamp from the neighbouring
    ``JointState`` messages, which must both lie within ``tolerance_ns`` (else the frame is
    skipped and counted in :attr:`stats`). ``mask_topics`` are names like ``"left/robot_mask"``
    (or absolute topics); frames lacking one of them are skipped and counted. ``joint_order``
    optionally fixes each robot's joint order (e.g. the URDF's movable joints).

    A truncated or corrupt file raises :class:`RecordingError` naming the file and the last good
    timestamp with ``on_error="raise"``; with ``on_error="skip"`` the readable part is used and
    the problem is logged and reported in :attr:`errors` and :attr:`stats`.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        camera: str = DEFAULT_CAMERA,
        robots: Sequence[str] | None = None,
        tolerance_ns: int = 20_000_000,
        stereo_tolerance_ns: int = 1_000_000,
        mask_topics: Sequence[str] = (),
        joint_order: dict[str, Sequence[str]] | None = None,
        on_error: Literal["raise", "skip"] = "raise",
        cache_chunks: int = 4,
    ) -> None:
        self.path = Path(path)
        if on_error not in ("raise", "skip"):
            raise ValueError(f"on_error must be 'raise' or 'skip', got {on_error!r}")
        if not self.path.is_file():
            raise RecordingError(f"{self.path}: recording does not exist")
        self.camera = camera
        self.tolerance_ns = int(tolerance_ns)
        self.stereo_tolerance_ns = int(stereo_tolerance_ns)
        self.on_error = on_error
        self._cache_size = max(1, int(cache_chunks))
        self._file: BinaryIO | None = None
        self._index: _Index | None = None
        self._summary_checked = False
        self._summary: Any = None
        self._decoders = DecoderFactory()
        self._plan: dict[str, Any] | None = None
        self._cache: OrderedDict[int, list[bytes]] = OrderedDict()
        self._camera_infos: dict[str, CameraInfo] = {}  # side -> first CameraInfo
        self._tf_edges: dict[tuple[str, str], np.ndarray] | None = None
        self.stats = ReadStats()
        with open(self.path, "rb") as f:
            if f.read(len(MAGIC)) != MAGIC:
                raise RecordingError(f"{self.path}: not an MCAP file (bad magic bytes)")

        self._joint_order = {r: list(n) for r, n in (joint_order or {}).items()}
        self._joint_perms: dict[tuple[str, tuple[str, ...]], list[int] | None] = {}
        self.left_topic = image_topic(camera, "left")
        self.right_topic = image_topic(camera, "right")
        self.mask_topics = {name: resolve_mask_topic(name, camera) for name in mask_topics}
        available = self.topics()
        self._require(available, [self.left_topic, self.right_topic])
        self._require(available, list(self.mask_topics.values()))
        self._robots = list(robots) if robots is not None else robots_from_topics(available)
        self._require(available, [joint_states_topic(r) for r in self._robots])
        if not self._robots:
            logger.warning("%s: no /<robot>/joint_states topic; frames carry no joints", path)

    # -- resource handling -------------------------------------------------------------------
    def __enter__(self) -> RecordingReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the file handle and drop cached chunks."""
        if self._file is not None:
            self._file.close()
            self._file = None
        self._cache.clear()

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_file"] = None  # re-opened lazily (e.g. in a DataLoader worker)
        state["_cache"] = OrderedDict()
        state["_decoders"] = DecoderFactory()  # generated decoders do not pickle
        return state

    def _handle(self) -> BinaryIO:
        if self._file is None:
            self._file = open(self.path, "rb")  # noqa: SIM115 - closed in close()
        return self._file

    def _require(self, available: dict[str, str], wanted: Iterable[str]) -> None:
        missing = [t for t in wanted if t not in available]
        if missing:
            raise RecordingError(
                f"{self.path}: missing topic {', '.join(missing)} "
                f"(topics: {', '.join(sorted(available)) or 'none'})"
            )

    # -- summary (cheap) and index (one pass) ------------------------------------------------
    def _read_summary(self) -> Any:
        """The MCAP summary section, or None for files without one (e.g. truncated)."""
        if not self._summary_checked:
            self._summary_checked = True
            try:
                with open(self.path, "rb") as f:
                    summary = SeekingReader(f).get_summary()
                if summary is not None and summary.chunk_indexes and summary.channels:
                    self._summary = summary
            except Exception as exc:  # noqa: BLE001 - any failure means "no usable summary"
                logger.debug("%s: no usable summary (%s)", self.path, exc)
        return self._summary

    def _fail(self, index: _Index, message: str) -> None:
        if self.on_error == "raise":
            raise RecordingError(message)
        logger.warning("%s", message)
        index.errors.append(message)

    def _build_index(self) -> _Index:
        """Read every chunk once; keep stamps/locations of images and the small messages."""
        index = _Index()
        channels: dict[int, Channel] = {}
        schemas: dict[int, Schema] = {}
        wanted_small = self._small_topics()
        size = self.path.stat().st_size
        last_good: int | None = None
        pos = len(MAGIC)
        with open(self.path, "rb") as f:
            while True:
                where = f"{self.path}: truncated or corrupt MCAP at byte {pos}"
                good = (
                    f"last good timestamp {last_good} ns"
                    if last_good is not None
                    else ("no complete message before it")
                )
                if pos + _RECORD_HEAD.size > size:
                    self._fail(index, f"{where} (file ends without a footer); {good}")
                    break
                f.seek(pos)
                opcode, length = _RECORD_HEAD.unpack(f.read(_RECORD_HEAD.size))
                end = pos + _RECORD_HEAD.size + length
                if end > size:
                    self._fail(index, f"{where} (record of {length} bytes cut off); {good}")
                    break
                if opcode in (Opcode.DATA_END, Opcode.FOOTER):
                    break
                try:
                    if opcode == Opcode.CHUNK:
                        chunk = Chunk.read(ReadDataStream(f))
                        records = breakup_chunk(chunk, validate_crc=True)
                        self._index_chunk(
                            index, pos, chunk, records, channels, schemas, wanted_small
                        )
                        last_good = chunk.message_end_time
                    elif opcode == Opcode.METADATA:
                        meta = Metadata.read(ReadDataStream(f))
                        index.metadata[meta.name] = dict(meta.metadata)
                    elif opcode == Opcode.SCHEMA:
                        schema = Schema.read(ReadDataStream(f))
                        schemas[schema.id] = schema
                    elif opcode == Opcode.CHANNEL:
                        channel = Channel.read(ReadDataStream(f))
                        channels[channel.id] = channel
                    elif opcode == Opcode.MESSAGE:
                        raise RecordingError(f"{self.path}: unchunked MCAP files are not supported")
                except RecordingError:
                    raise
                except Exception as exc:  # noqa: BLE001 - corrupt bytes raise many kinds
                    self._fail(index, f"{where} ({type(exc).__name__}: {exc}); {good}")
                pos = end
        return index

    def _small_topics(self) -> set[str]:
        return {
            TF_STATIC,
            camera_info_topic(self.camera, "left"),
            camera_info_topic(self.camera, "right"),
        }

    def _decode(self, schema: Schema | None, data: bytes) -> Any:
        if schema is None:
            raise ValueError("message without schema")
        decoder = self._decoders.decoder_for("cdr", schema)
        if decoder is None:
            raise ValueError(f"no CDR decoder for schema {schema.name}")
        return decoder(data)

    def _index_chunk(
        self,
        index: _Index,
        offset: int,
        chunk: Chunk,
        records: list[Any],
        channels: dict[int, Channel],
        schemas: dict[int, Schema],
        wanted_small: set[str],
    ) -> None:
        chunk_id = len(index.chunks)
        n_left = 0
        position = 0
        image_topics = {self.left_topic, self.right_topic, *self.mask_topics.values()}
        for record in records:
            if isinstance(record, Schema):
                schemas[record.id] = record
                continue
            if isinstance(record, Channel):
                channels[record.id] = record
                schema = schemas.get(record.schema_id)
                index.topics[record.topic] = schema.name if schema else ""
                continue
            if not isinstance(record, Message):
                continue
            channel = channels[record.channel_id]
            topic = channel.topic
            if topic in image_topics:
                refs = index.images.setdefault(topic, _ImageRefs())
                if topic not in index.image_schemas and channel.schema_id in schemas:
                    index.image_schemas[topic] = schemas[channel.schema_id]
                refs.stamps.append(message_stamp_ns(record.data, record.log_time))
                refs.chunks.append(chunk_id)
                refs.positions.append(position)
                n_left += topic == self.left_topic
            elif topic.endswith("/joint_states") and robots_from_topics([topic]):
                robot = topic.split("/")[1]
                try:
                    js = self._decode(schemas.get(channel.schema_id), record.data)
                except Exception as exc:  # noqa: BLE001
                    logger.warning("%s: undecodable message on %s (%s)", self.path, topic, exc)
                else:
                    stamp = msgs.stamp_to_ns(js.header.stamp) or record.log_time
                    self._store_joint_state(index, robot, stamp, js.name, js.position)
            elif topic in wanted_small:  # kept encoded: decoded messages do not pickle
                kept = index.small.setdefault(topic, [])
                if topic == TF_STATIC or not kept:  # only the first CameraInfo is ever used
                    kept.append((schemas.get(channel.schema_id), record.data))
            position += 1
        index.chunks.append(
            ChunkInfo(chunk_id, offset, chunk.message_start_time, chunk.message_end_time, n_left)
        )

    def _store_joint_state(
        self,
        index: _Index,
        robot: str,
        stamp: int,
        names: Sequence[str],
        positions: Sequence[float],
    ) -> None:
        """Append one JointState, reordered to the robot's joint order, to the index."""
        order = index.joint_names.setdefault(robot, self._joint_order.get(robot, list(names)))
        key = (robot, tuple(names))
        perm = self._joint_perms.get(key, [])
        if perm == []:
            lookup = {n: k for k, n in enumerate(names)}
            missing = [n for n in order if n not in lookup]
            perm = None if missing or len(positions) != len(names) else [lookup[n] for n in order]
            self._joint_perms[key] = perm
            if perm is None and robot not in index.joint_errors:
                what = f"joint '{missing[0]}' missing" if missing else "names/positions differ"
                index.joint_errors[robot] = (
                    f"{self.path}: {what} in {joint_states_topic(robot)} at {stamp} ns "
                    f"(names: {', '.join(names)})"
                )
        if perm is None:
            return
        index.joint_stamps.setdefault(robot, array("q")).append(stamp)
        index.joint_values.setdefault(robot, array("d")).extend(positions[k] for k in perm)

    def _get_index(self) -> _Index:
        if self._index is None:
            self._index = self._build_index()
        return self._index

    # -- small, summary-level queries --------------------------------------------------------
    def topics(self) -> dict[str, str]:
        """``{topic: schema name}`` of every channel in the recording."""
        summary = self._read_summary()
        if summary is not None and self._index is None:
            return {
                ch.topic: (summary.schemas[ch.schema_id].name if ch.schema_id else "")
                for ch in summary.channels.values()
            }
        return dict(self._get_index().topics)

    def metadata(self) -> dict[str, dict[str, str]]:
        """MCAP metadata records ``{name: {key: value}}``."""
        summary = self._read_summary()
        if summary is not None and self._index is None:
            with open(self.path, "rb") as f:
                return {m.name: dict(m.metadata) for m in SeekingReader(f).iter_metadata()}
        return dict(self._get_index().metadata)

    def _small_messages(self, topic: str, first: bool = False) -> list[Any]:
        """Decoded messages of a small topic (only the first one with ``first``), via the
        summary when the index is not built."""
        summary = self._read_summary()
        if summary is not None and self._index is None:
            try:
                with open(self.path, "rb") as f:
                    reader = SeekingReader(f, decoder_factories=[self._decoders])
                    decoded = (m.decoded_message for m in reader.iter_decoded_messages([topic]))
                    return list(itertools.islice(decoded, 1 if first else None))
            except Exception as exc:  # noqa: BLE001 - corrupt chunk: the index pass reports it
                logger.debug("%s: summary read of %s failed (%s)", self.path, topic, exc)
        stored = self._get_index().small.get(topic, [])
        return [self._decode(schema, data) for schema, data in stored[: 1 if first else None]]

    @property
    def robots(self) -> list[str]:
        """Robot namespaces whose joint states are read."""
        return list(self._robots)

    @property
    def errors(self) -> list[str]:
        """Problems found in the file (only non-empty with ``on_error="skip"``)."""
        return list(self._get_index().errors)

    def camera_info(self, side: str = "left") -> tuple[np.ndarray, int, int, str]:
        """``(K 3x3, width, height, frame_id)`` of one side of the camera (first message)."""
        info = self.camera_infos(side)
        return info.K, info.width, info.height, info.frame_id

    def camera_infos(self, side: str = "left") -> CameraInfo:
        """Full :class:`CameraInfo` (with distortion) of one side of the camera (the first
        message; decoded once)."""
        if side not in self._camera_infos:
            self._camera_infos[side] = self._first_camera_info(side)
        info = self._camera_infos[side]
        return dataclasses.replace(info, K=info.K.copy(), D=info.D.copy())

    def _first_camera_info(self, side: str) -> CameraInfo:
        topic = camera_info_topic(self.camera, side)
        found = self._small_messages(topic, first=True)
        if not found:
            raise RecordingError(
                f"{self.path}: no CameraInfo for camera '{self.camera}' {side} (topic {topic})"
            )
        m = found[0]
        return CameraInfo(
            K=np.asarray(m.k, dtype=np.float64).reshape(3, 3),
            width=int(m.width),
            height=int(m.height),
            frame_id=str(m.header.frame_id),
            D=np.asarray(m.d, dtype=np.float64),
            distortion_model=str(m.distortion_model),
        )

    def camera_calib(self) -> CameraCalib:
        """Both sides' intrinsics and ``T_right_left`` from ``/tf_static`` (None if absent)."""
        left, right = self.camera_infos("left"), self.camera_infos("right")
        try:
            T_right_left = self.lookup(right.frame_id, left.frame_id)
        except RecordingError:
            T_right_left = None
        return CameraCalib(self.camera, left, right, T_right_left)

    def tf_static(self) -> dict[tuple[str, str], np.ndarray]:
        """``{(parent, child): T_parent_child}`` (4x4, metres) from every ``/tf_static`` msg."""
        if self._tf_edges is None:
            self._tf_edges = self._read_tf_static()
        return {edge: T.copy() for edge, T in self._tf_edges.items()}

    def _read_tf_static(self) -> dict[tuple[str, str], np.ndarray]:
        edges: dict[tuple[str, str], np.ndarray] = {}
        for message in self._small_messages(TF_STATIC):
            for ts in message.transforms:
                t, q = ts.transform.translation, ts.transform.rotation
                R = quaternion_to_matrix(np.array([q.x, q.y, q.z, q.w]))
                edges[(ts.header.frame_id, ts.child_frame_id)] = make_transform(
                    R, np.array([t.x, t.y, t.z])
                )
        return edges

    def lookup(self, target: str, source: str) -> np.ndarray:
        """``T_target_source`` (maps source-frame points into ``target``) through /tf_static."""
        return lookup_transform(self.tf_static(), target, source, where=str(self.path))

    def chunk_index(self) -> list[ChunkInfo]:
        """Chunks of the file in file order; shard them across ranks/workers by ``id``."""
        return list(self._get_index().chunks)

    def __len__(self) -> int:
        """Number of left images (candidate frames) in the readable part of the file."""
        refs = self._get_index().images.get(self.left_topic)
        return 0 if refs is None else len(refs.stamps)

    # -- frame plan ---------------------------------------------------------------------------
    def joint_names(self) -> dict[str, list[str]]:
        """Joint order per robot: ``joint_order`` if given, else the first message's order."""
        index = self._get_index()
        return {
            r: list(index.joint_names.get(r, self._joint_order.get(r, []))) for r in self._robots
        }

    def joint_samples(self, robot: str) -> tuple[np.ndarray, np.ndarray]:
        """All joint states of a robot: (stamps [N] ns sorted, positions [N, D] rad or m).

        Raises :class:`RecordingError` naming the joint if a message lacks one of the joints.
        """
        index = self._get_index()
        if robot in index.joint_errors:
            raise RecordingError(index.joint_errors[robot])
        n_joints = len(self.joint_names()[robot])
        stamps = np.frombuffer(index.joint_stamps.get(robot, array("q")), dtype=np.int64)
        values = np.frombuffer(index.joint_values.get(robot, array("d")), dtype=np.float64)
        return prepare_samples(stamps.copy(), values.reshape(len(stamps), n_joints).copy())

    def _get_plan(self) -> dict[str, Any]:
        """Per left image (stamp order): partner locations and interpolated joints."""
        if self._plan is not None:
            return self._plan
        index = self._get_index()
        left = index.images.get(self.left_topic, _ImageRefs()).arrays()
        stamps = left[0]
        plan: dict[str, Any] = {"stamps": stamps, "left": left, "partners": {}, "joints": {}}
        partner_topics = {"right": self.right_topic, **self.mask_topics}
        for name, topic in partner_topics.items():
            p_stamps, p_chunks, p_pos = index.images.get(topic, _ImageRefs()).arrays()
            plan["partners"][name] = _match_stamps(
                stamps, p_stamps, p_chunks, p_pos, self.stereo_tolerance_ns
            )
        valid = np.ones(len(stamps), dtype=bool)
        for robot in self._robots:
            s, v = self.joint_samples(robot)
            values, ok = interpolate_at(s, v, stamps, self.tolerance_ns)
            plan["joints"][robot] = values
            valid &= ok
        plan["joints_valid"] = valid
        self._plan = plan
        return plan

    # -- streaming ----------------------------------------------------------------------------
    def _chunk_messages(self, chunk_id: int) -> list[bytes]:
        """Message payloads of a chunk (image/mask/joint/small topics), through an LRU cache."""
        cached = self._cache.get(chunk_id)
        if cached is not None:
            self._cache.move_to_end(chunk_id)
            return cached
        info = self._get_index().chunks[chunk_id]
        f = self._handle()
        f.seek(info.offset + _RECORD_HEAD.size)
        chunk = Chunk.read(ReadDataStream(f))
        payloads = [r.data for r in breakup_chunk(chunk) if isinstance(r, Message)]
        self._cache[chunk_id] = payloads
        while len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return payloads

    def _payload(self, chunk_id: int, position: int) -> bytes:
        return self._chunk_messages(chunk_id)[position]

    def frames(
        self, start: int = 0, stop: int | None = None, step: int = 1, decode: bool = True
    ) -> Iterator[StereoFrame]:
        """Stream frames ``start:stop:step`` of the left images in stamp order.

        Resets :attr:`stats`. With ``decode=False`` images and masks stay encoded bytes.
        """
        n = len(self._get_plan()["stamps"])
        return self._iterate(range(n)[slice(start, stop, step)], decode)

    def frames_in_chunks(
        self, chunk_ids: Iterable[int], decode: bool = True
    ) -> Iterator[StereoFrame]:
        """Stream the frames whose left image lies in the given chunks (stamp order).

        Every frame belongs to exactly one chunk, so disjoint chunk sets give disjoint frames.
        """
        plan = self._get_plan()
        wanted = np.zeros(len(self._get_index().chunks), dtype=bool)
        ids = np.asarray(list(chunk_ids), dtype=np.int64)
        if ids.size and (ids.min() < 0 or ids.max() >= len(wanted)):
            raise RecordingError(f"{self.path}: chunk id out of range 0..{len(wanted) - 1}")
        wanted[ids] = True
        selected = np.flatnonzero(wanted[plan["left"][1]]) if len(wanted) else np.array([], int)
        return self._iterate(selected.tolist(), decode)

    def _iterate(self, indices: Iterable[int], decode: bool) -> Iterator[StereoFrame]:
        plan = self._get_plan()
        stats = ReadStats(errors=list(self._get_index().errors))
        self.stats = stats
        names = self.joint_names()
        decode_fn: Callable[[bytes], Any] = decode_image
        for i in indices:
            right = plan["partners"]["right"][i]
            if right[0] < 0:
                stats.skipped_unpaired += 1
                continue
            if not plan["joints_valid"][i]:
                stats.skipped_no_joint_state += 1
                continue
            mask_refs = {m: plan["partners"][m][i] for m in self.mask_topics}
            if any(ref[0] < 0 for ref in mask_refs.values()):
                stats.skipped_no_mask += 1
                continue
            try:
                left_msg = self._image_message(
                    self.left_topic, plan["left"][1][i], plan["left"][2][i]
                )
                right_msg = self._image_message(self.right_topic, *right)
                masks_msg = {
                    m: self._image_message(self.mask_topics[m], *ref)
                    for m, ref in mask_refs.items()
                }
            except Exception as exc:  # noqa: BLE001 - file changed or corrupt since indexing
                message = f"{self.path}: cannot read frame {i} ({type(exc).__name__}: {exc})"
                if self.on_error == "raise":
                    raise RecordingError(message) from exc
                stats.errors.append(message)
                stats.skipped_corrupt += 1
                continue
            if decode:
                left_img, right_img = decode_fn(left_msg.data), decode_fn(right_msg.data)
                masks = {m: decode_mask(msg.data) for m, msg in masks_msg.items()}
            else:
                left_img = np.frombuffer(left_msg.data, np.uint8)
                right_img = np.frombuffer(right_msg.data, np.uint8)
                masks = {m: np.frombuffer(msg.data, np.uint8) for m, msg in masks_msg.items()}
            if left_img is None or right_img is None or any(v is None for v in masks.values()):
                stats.skipped_corrupt += 1
                logger.warning(
                    "%s: frame %d at %d ns does not decode; skipped",
                    self.path,
                    i,
                    int(plan["stamps"][i]),
                )
                continue
            stats.yielded += 1
            yield StereoFrame(
                stamp_ns=int(plan["stamps"][i]),
                left=left_img,
                right=right_img,
                joints={r: plan["joints"][r][i].copy() for r in self._robots},
                joint_names={r: list(v) for r, v in names.items()},
                masks=masks,
                index=int(i),
                left_frame_id=str(left_msg.header.frame_id),
                right_frame_id=str(right_msg.header.frame_id),
            )

    def _image_message(self, topic: str, chunk_id: int, position: int) -> Any:
        """Decoded ``CompressedImage`` of a topic at a location (the pixels stay encoded)."""
        data = self._payload(int(chunk_id), int(position))
        return self._decode(self._get_index().image_schemas.get(topic), data)


def _match_stamps(
    stamps: np.ndarray,
    other: np.ndarray,
    chunks: np.ndarray,
    positions: np.ndarray,
    tolerance_ns: int,
) -> np.ndarray:
    """For each stamp the (chunk, position) of the nearest ``other`` stamp within tolerance.

    ``stamps`` [N], ``other`` [M] sorted ns -> [N, 2] int64, ``(-1, -1)`` where none matches.
    """
    out = np.full((len(stamps), 2), -1, dtype=np.int64)
    if len(other) == 0 or len(stamps) == 0:
        return out
    after = np.clip(np.searchsorted(other, stamps), 0, len(other) - 1)
    before = np.clip(after - 1, 0, len(other) - 1)
    nearest = np.where(
        np.abs(other[after] - stamps) <= np.abs(other[before] - stamps), after, before
    )
    ok = np.abs(other[nearest] - stamps) <= tolerance_ns
    out[ok, 0] = chunks[nearest[ok]]
    out[ok, 1] = positions[nearest[ok]]
    return out
