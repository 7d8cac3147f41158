"""Streaming training data from self-annotated MCAP recordings (``roboseg-annotations/1``).

``root/manifest.json`` lists the recordings and their split. Training frames stream from an
:class:`~torch.utils.data.IterableDataset` sharded by (file, chunk) over DDP ranks and loader
workers; the shard order is reshuffled per epoch from ``(seed, epoch)`` and a seeded shuffle
buffer of *encoded* frames mixes neighbouring frames. The stream is endless (epoch after epoch):
training is bounded by ``trainer.max_steps``. Validation / test sets are map-style and
deterministic, restricted by default to the draped frames (``draped_from_ns``).

Every sample: the left image resized 16:9 → ``image_size`` (area interpolation), its robot mask
(nearest), ``visible`` (no mask pixel on the border of the full-size mask), ``draped`` (the
frame is draped, or its recording does not say: the loss may weigh the two kinds of label
apart, ``module.loss.alpha_undraped``), and for 4-channel
models the in-context prior: the robot silhouette rendered at a perturbed ``T_cam_base``
(from ``/tf_static``) with the resized intrinsics, or zeros with probability
``1 - prior_probability``. The prior is rendered at the model input size from the robot's meshes
decimated by ``prior_mesh_reduction`` (disk-cached), for a whole loader batch in one rasteriser
call, in the loader workers, i.e. before the (device-side) geometric augmentation.

Memory: the shuffle buffer holds encoded frames without their right image, and a recording's
decoded chunk cache is dropped as soon as the stream leaves its chunk, so a worker's memory does
not grow with the number of recordings.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import lightning.pytorch as pl
import numpy as np
import torch
from torch.utils.data import (
    DataLoader,
    Dataset,
    IterableDataset,
    default_collate,
    get_worker_info,
)

from roboseg.augment.prior import InContextPrior
from roboseg.camera import Intrinsics
from roboseg.errors import DatasetError, RobosegError
from roboseg.recording import RecordingReader, StereoFrame
from roboseg.recording.reader import decode_image, decode_mask
from roboseg.robot import RobotModel, load_robot

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
MANIFEST_FORMAT = "roboseg-annotations/1"
SPLITS = ("train", "val", "test")
VAL_PHASES = ("draped", "undraped", "all")
MASKS = ("left/robot_mask",)
Sample = dict[str, torch.Tensor]
#: One view of a sample's prior, drawn but not rendered: joints ``[D]`` (model order),
#: ``T_cam_base`` ``[4,4]``, ``K`` ``[3,3]`` (model input size), ``delta_r`` ``[3,3]``,
#: ``delta_x`` ``[3]`` (metres).
PriorView = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]
_NO_PIXELS = np.zeros(0, np.uint8)


# --- manifest ------------------------------------------------------------------------------


@dataclass(frozen=True)
class RecordingEntry:
    """One annotated recording of the manifest (``draped_from_ns``: first draped stamp, ns;
    ``frames``: frames kept by the annotation, None when the manifest does not say)."""

    path: Path
    split: str
    draped_from_ns: int | None
    robots: tuple[str, ...]
    frames: int | None = None


@dataclass(frozen=True)
class Manifest:
    """What a DataModule needs from ``manifest.json``."""

    root: Path
    camera: str
    robot_urdf: str | None
    subset: str
    recordings: tuple[RecordingEntry, ...]

    def split(self, name: str) -> list[RecordingEntry]:
        return [r for r in self.recordings if r.split == name]


def read_manifest(root: str | Path) -> Manifest:
    """Parse ``root/manifest.json``; :class:`DatasetError` names the path and what is wrong."""
    root = Path(root)
    path = root / MANIFEST
    if not root.is_dir():
        raise DatasetError(f"data.root {root}: no such folder")
    if not path.is_file():
        raise DatasetError(f"{path}: no manifest (is {root} an annotated dataset?)")
    try:
        doc = json.loads(path.read_text())
        if doc.get("format") != MANIFEST_FORMAT:
            raise DatasetError(f"{path}: format {doc.get('format')!r} is not {MANIFEST_FORMAT!r}")
        entries = []
        for rec in doc["recordings"]:
            split = str(rec["split"])
            draped = rec.get("draped_from_ns")
            kept = rec.get("frames_kept")
            entries.append(
                RecordingEntry(
                    path=root / str(rec["file"]),
                    split=split,
                    draped_from_ns=None if draped is None else int(draped),
                    robots=tuple(str(r) for r in rec.get("robots") or ()),
                    frames=None if kept is None else int(kept),
                )
            )
    except RobosegError:
        raise
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise DatasetError(f"{path}: malformed manifest ({type(exc).__name__}: {exc})") from None
    urdf = doc.get("robot_urdf")
    return Manifest(
        root=root,
        camera=str(doc.get("camera") or "camera"),
        robot_urdf=None if urdf in (None, "") else str(urdf),
        subset=str(doc.get("subset") or "full"),
        recordings=tuple(entries),
    )


def open_readers(entries: Sequence[RecordingEntry], camera: str, split: str) -> list[Any]:
    """Indexed readers (``on_error="skip"``) of a split's recordings; missing files raise."""
    readers = []
    for entry in entries:
        if not entry.path.is_file():
            raise DatasetError(f"{entry.path}: recording of split {split!r} does not exist")
        reader = RecordingReader(entry.path, camera=camera, mask_topics=MASKS, on_error="skip")
        reader.chunk_index()  # build the index here once (small: stamps and locations only)
        readers.append(reader)
    return readers


# --- pure helpers --------------------------------------------------------------------------


def shard_order(n_shards: int, seed: int, epoch: int) -> np.ndarray:
    """Permutation of ``range(n_shards)`` for an epoch, a function of ``(seed, epoch)`` only."""
    return np.random.default_rng([int(seed), int(epoch)]).permutation(n_shards)


def shards_for(order: Sequence[int], rank: int, world_size: int, worker: int,
               num_workers: int) -> list[int]:
    """The shards of one (rank, worker): every ``world_size·num_workers``-th entry of ``order``
    starting at ``rank·num_workers + worker``; all (rank, worker) pairs partition ``order``."""
    slot, slots = rank * num_workers + worker, world_size * num_workers
    return [int(s) for s in order[slot::slots]]


def sample_seed(seed: int, epoch: int, index: int) -> int:
    """A 63-bit seed of one sample's random draws (prior), independent of who loads it."""
    return int(np.random.SeedSequence([int(seed), int(epoch), int(index)]).generate_state(2,
               np.uint64)[0] >> np.uint64(1))


def resize_frame(image: np.ndarray, mask: np.ndarray, size: Sequence[int]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """``HxWx3`` uint8 image (area interpolation) and ``HxW`` bool mask (nearest) → ``size``."""
    h, w = int(size[0]), int(size[1])
    img = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
    msk = cv2.resize(mask.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
    return img, msk


def is_draped(stamp_ns: int, draped_from_ns: int | None) -> bool:
    """Whether a frame stamped ``stamp_ns`` is draped; a recording that does not say
    (``draped_from_ns`` None, real data) counts as draped throughout."""
    return draped_from_ns is None or int(stamp_ns) >= int(draped_from_ns)


def robot_inside(mask: np.ndarray) -> bool:
    """True iff the mask has no pixel on the image border (robot entirely inside the frame)."""
    return not (mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())


def collate(samples: Sequence[Sample | None]) -> dict[str, torch.Tensor]:
    """Stack sample dicts, dropping ``None`` (frames that could not be read).

    In a loader worker the stacked tensors are allocated in shared memory directly (as
    ``default_collate`` does): no private copy per batch is made and freed, which would grow the
    worker's heap.
    """
    kept = [s for s in samples if s is not None]
    if not kept:
        return {}
    return default_collate(kept)


# --- sample building -----------------------------------------------------------------------


class FrameCodec:
    """Turn a :class:`StereoFrame` of one reader into a training sample (shared by datasets).

    ``prior_mesh_reduction``: fraction of mesh faces removed for the prior render (0: full
    meshes; the prior is a perturbed pose anyway, so a decimated silhouette costs no accuracy
    that matters and renders several times faster).
    """

    def __init__(self, image_size: Sequence[int], with_prior: bool, prior_probability: float,
                 prior_translation: Sequence[float], prior_rotation_deg: float,
                 robot_urdf: str | None, seed: int, prior_mesh_reduction: float = 0.0) -> None:
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.with_prior = bool(with_prior)
        self.prior_probability = float(prior_probability)
        self.prior = InContextPrior((float(prior_translation[0]), float(prior_translation[1])),
                                    float(prior_rotation_deg))
        self.robot_urdf = robot_urdf
        self.seed = int(seed)
        self.prior_mesh_reduction = float(prior_mesh_reduction)
        self._robot: RobotModel | None = None
        self._calib: dict[tuple[str, str], Any] = {}

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_robot"], state["_calib"] = None, {}  # rebuilt lazily in a loader worker
        return state

    @property
    def robot(self) -> RobotModel:
        """The robot model of the prior renders (meshes decimated, loaded on first use)."""
        if self._robot is None:
            self._robot = load_robot(self.robot_urdf, reduction=self.prior_mesh_reduction)
        return self._robot

    def _pose_and_K(self, reader: Any, robot: str, frame_id: str) -> tuple[np.ndarray, Any]:
        key = (str(reader.path), robot)
        if key not in self._calib:
            info = reader.camera_infos("left")
            K = Intrinsics.from_K(info.K, info.width, info.height).resized(
                self.image_size[1], self.image_size[0]).as_tensor()
            child = f"{robot}/{self.robot.root_link}"
            try:
                T = reader.lookup(frame_id or info.frame_id, child)
            except RobosegError as exc:
                raise DatasetError(f"{reader.path}: no calibration for {child} ({exc})") from None
            self._calib[key] = (torch.as_tensor(T, dtype=torch.float32), K)
        return self._calib[key]

    def draw_prior(self, reader: Any, frame: StereoFrame, index: int, epoch: int
                   ) -> list[PriorView]:
        """The sample's prior views (one per robot; none for a zero prior), drawn from
        ``sample_seed(seed, epoch, index)``: whether to render, then ``ΔR``, ``Δx`` per robot."""
        if not self.with_prior:
            return []
        gen = torch.Generator().manual_seed(sample_seed(self.seed, epoch, index))
        if float(torch.rand((), generator=gen)) >= self.prior_probability:
            return []
        views = []
        for robot, q in frame.joints.items():
            T, K = self._pose_and_K(reader, robot, frame.left_frame_id)
            q_model = self.robot.joints_from_names(frame.joint_names[robot], q)
            params = self.prior.sample(1, gen)
            views.append((q_model, T, K, params["delta_r"][0], params["delta_x"][0]))
        return views

    def render_priors(self, views: Sequence[Sequence[PriorView]]) -> torch.Tensor:
        """Priors ``[n,1,H,W]`` (float {0,1}) of n samples' views: per sample the union over its
        robots of silhouettes at the perturbed poses; all views in one rasteriser call."""
        h, w = self.image_size
        flat = [(k, v) for k, vs in enumerate(views) for v in vs]
        if not flat:
            return torch.zeros(len(views), 1, h, w)
        owner = torch.tensor([k for k, _ in flat], dtype=torch.long)
        q, T, K, delta_r, delta_x = (torch.stack(parts) for parts in zip(*(v for _, v in flat),
                                                                          strict=True))
        verts = self.robot.posed_vertices(q.to(self.robot.dtype))
        return self.prior.render_union(verts, self.robot.faces, K, T, h, w,
                                       {"delta_r": delta_r, "delta_x": delta_x}, owner,
                                       len(views))

    def _decoded(self, reader: Any, frame: StereoFrame, index: int) -> Sample | None:
        """Sample without its prior; None when the frame does not decode (logged)."""
        image = frame.left if frame.left.ndim == 3 else decode_image(frame.left.tobytes())
        mask = frame.masks[MASKS[0]]
        if mask.ndim == 1:
            mask = decode_mask(mask.tobytes())
        if image is None or mask is None:
            log.warning("%s: frame %d does not decode; skipped", reader.path, frame.index)
            return None
        visible = robot_inside(mask)
        img, msk = resize_frame(image, mask, self.image_size)
        return {
            "image": torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1).float() / 255,
            "mask": torch.from_numpy(msk)[None].float(),
            "visible": torch.tensor(visible),
            "index": torch.tensor(index, dtype=torch.long),
        }

    def samples(self, items: Sequence[tuple[Any, StereoFrame, int, int]]
                ) -> list[Sample | None]:
        """Samples of ``(reader, frame, index, epoch)`` items, priors rendered together."""
        decoded = [self._decoded(reader, frame, index) for reader, frame, index, _ in items]
        views = [self.draw_prior(reader, frame, index, epoch) if s is not None else []
                 for s, (reader, frame, index, epoch) in zip(decoded, items, strict=True)]
        priors = self.render_priors(views)
        for k, s in enumerate(decoded):
            if s is not None:
                s["prior"] = priors[k]
        return decoded

    def sample(self, reader: Any, frame: StereoFrame, index: int, epoch: int) -> Sample | None:
        """Decoded, resized sample with its prior; None when the frame does not decode."""
        return self.samples([(reader, frame, index, epoch)])[0]


# --- datasets ------------------------------------------------------------------------------


class StreamingFrames(IterableDataset):
    """Endless stream of training samples, sharded by (file, chunk) over ranks and workers.

    Epoch ``e`` visits this (rank, worker)'s shards of ``shard_order(n, seed, e)``; across all
    ranks and workers every frame of the split appears exactly once per epoch. ``skip`` samples
    are fast-forwarded (not decoded) per worker, for exact resumption. ``max_epochs`` bounds the
    stream (None: endless). ``seen_log``: optional file receiving ``rank worker epoch index``
    lines of yielded samples (for checks of the sharding in multi-process runs).
    ``draped_from_ns``: per reader, the first draped stamp (ns) or None; each sample carries
    ``draped`` (bool: its frame is draped, or the recording does not say).
    """

    def __init__(self, readers: Sequence[Any], codec: FrameCodec, shuffle_buffer: int = 512,
                 seed: int = 0, max_epochs: int | None = None,
                 seen_log: str | None = None,
                 draped_from_ns: Sequence[int | None] | None = None) -> None:
        super().__init__()
        self.readers = list(readers)
        # per reader: the first draped stamp (ns); None: every frame counts as draped
        self.draped_from_ns = (list(draped_from_ns) if draped_from_ns is not None
                               else [None] * len(self.readers))
        if len(self.draped_from_ns) != len(self.readers):
            raise ValueError(f"{len(self.draped_from_ns)} draped_from_ns for "
                             f"{len(self.readers)} readers")
        self.codec = codec
        self.shuffle_buffer = max(1, int(shuffle_buffer))
        self.seed = int(seed)
        self.max_epochs = max_epochs
        self.seen_log = seen_log
        self.rank, self.world_size = 0, 1
        self.skip_batches, self.batch_size = 0, 1
        self.offsets = np.cumsum([0] + [len(r) for r in self.readers])[:-1].tolist()
        self.shards = [(f, c.id) for f, r in enumerate(self.readers)
                       for c in r.chunk_index() if c.n_frames > 0]
        self.skipped_corrupt = 0

    def n_frames(self) -> int:
        """Candidate frames per epoch over all ranks (no ``__len__``: the stream is endless)."""
        return int(sum(c.n_frames for r in self.readers for c in r.chunk_index()))

    def _worker(self) -> tuple[int, int]:
        info = get_worker_info()
        return (0, 1) if info is None else (info.id, info.num_workers)

    def _source(self, worker: int, num_workers: int) -> Iterator[tuple[int, int, StereoFrame]]:
        """(epoch, file, encoded frame) of this worker's shards, epoch after epoch."""
        epoch = 0
        while self.max_epochs is None or epoch < self.max_epochs:
            mine = shards_for(shard_order(len(self.shards), self.seed, epoch), self.rank,
                              self.world_size, worker, num_workers)
            if not mine:
                return
            for s in mine:
                f, chunk = self.shards[s]
                reader = self.readers[f]
                for frame in reader.frames_in_chunks([chunk], decode=False):
                    # the buffer holds what a sample needs: no right image
                    yield epoch, f, dataclasses.replace(frame, right=_NO_PIXELS)
                reader.close()  # drop the decoded chunk: the stream is done with it
                stats = reader.stats
                if stats.skipped_corrupt:
                    self.skipped_corrupt += stats.skipped_corrupt
                    log.warning("%s: chunk %d: %d corrupt frame(s) skipped (total %d)",
                                reader.path, chunk, stats.skipped_corrupt, self.skipped_corrupt)
            epoch += 1

    def _shuffled(self, worker: int, num_workers: int
                  ) -> Iterator[tuple[int, int, StereoFrame]]:
        rng = np.random.default_rng([self.seed, self.rank, worker, 7])
        buffer: list[tuple[int, int, StereoFrame]] = []
        for item in self._source(worker, num_workers):
            if len(buffer) < self.shuffle_buffer:
                buffer.append(item)
                continue
            j = int(rng.integers(len(buffer)))
            buffer[j], item = item, buffer[j]
            yield item
        rng.shuffle(buffer)
        yield from buffer

    def worker_skip(self, worker: int, num_workers: int) -> int:
        """Samples this worker produced for the ``skip_batches`` already-consumed batches
        (the loader takes batches from its workers in turn)."""
        batches = max(0, math.ceil((self.skip_batches - worker) / num_workers))
        return batches * self.batch_size

    def __iter__(self) -> Iterator[Sample]:
        """Samples in stream order, built ``batch_size`` at a time (one prior render call)."""
        worker, num_workers = self._worker()
        skip = self.worker_skip(worker, num_workers)
        log_file = open(self.seen_log, "a") if self.seen_log else None  # noqa: SIM115
        group: list[tuple[Any, StereoFrame, int, int]] = []
        flags: list[bool] = []
        try:
            for epoch, f, frame in self._shuffled(worker, num_workers):
                index = self.offsets[f] + frame.index
                if skip > 0:
                    skip -= 1
                    continue
                group.append((self.readers[f], frame, index, epoch))
                flags.append(is_draped(frame.stamp_ns, self.draped_from_ns[f]))
                if len(group) >= self.batch_size:
                    yield from self._emit(group, flags, worker, log_file)
                    group, flags = [], []
            yield from self._emit(group, flags, worker, log_file)
        finally:
            if log_file is not None:
                log_file.close()

    def _emit(self, group: Sequence[tuple[Any, StereoFrame, int, int]], flags: Sequence[bool],
              worker: int, log_file: Any) -> Iterator[Sample]:
        for (_, _, index, epoch), draped, sample in zip(group, flags, self.codec.samples(group),
                                                       strict=True):
            if sample is None:
                self.skipped_corrupt += 1
                continue
            sample["draped"] = torch.tensor(draped)
            if log_file is not None:
                log_file.write(f"{self.rank} {worker} {epoch} {index}\n")
                log_file.flush()
            yield sample


class IndexedFrames(Dataset):
    """Map-style, deterministic frames ``(file, frame)`` of a split, optionally of one phase.

    The index is built once from the readers (images stay encoded); ``phase`` keeps frames at or
    after ``draped_from_ns`` (``"draped"``), before it (``"undraped"``) or all. Recordings with
    no ``draped_from_ns`` (real data) keep all their frames.
    """

    def __init__(self, readers: Sequence[Any], entries: Sequence[RecordingEntry],
                 codec: FrameCodec, phase: str = "draped") -> None:
        if phase not in VAL_PHASES:
            raise DatasetError(f"val_phase must be one of {VAL_PHASES}, got {phase!r}")
        self.readers, self.codec = list(readers), codec
        self.offsets = np.cumsum([0] + [len(r) for r in self.readers])[:-1].tolist()
        items: list[tuple[int, int, bool]] = []
        for f, (reader, entry) in enumerate(zip(self.readers, entries, strict=True)):
            for frame in reader.frames(decode=False):
                draped = is_draped(frame.stamp_ns, entry.draped_from_ns)
                if phase == "all" or (phase == "draped") == draped:
                    items.append((f, frame.index, draped))
        self.items = items

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, k: int) -> Sample | None:
        f, i, draped = self.items[k]
        reader = self.readers[f]
        frame = next(iter(reader.frames(start=i, stop=i + 1)), None)
        if frame is None:
            log.warning("%s: frame %d cannot be read; skipped", reader.path, i)
            return None
        sample = self.codec.sample(reader, frame, self.offsets[f] + i, epoch=0)
        if sample is not None:
            sample["draped"] = torch.tensor(draped)
        return sample


# --- the DataModule ------------------------------------------------------------------------


class RecordingDataModule(pl.LightningDataModule):
    """Train / val / test data of an annotated dataset folder (see module doc).

    ``image_size``: model input ``[H, W]``; ``with_prior``: render the prior channel (4-channel
    models); ``prior_translation``: ``[low, high]`` metres per axis; ``prior_rotation_deg``: the
    rotation's angle; ``prior_mesh_reduction``: fraction of mesh faces removed for the prior
    render; ``subset``: expected manifest subset (``all`` accepts any);
    ``val_phase``: ``draped`` | ``undraped`` | ``all`` frames of val and test.
    """

    def __init__(
        self,
        root: str | Path,
        image_size: Sequence[int] = (256, 256),
        batch_size: int = 8,
        num_workers: int = 2,
        shuffle_buffer: int = 512,
        subset: str = "all",
        subset_fraction: float | None = None,
        prior_probability: float = 0.0,
        prior_translation: Sequence[float] = (0.0, 0.05),
        prior_rotation_deg: float = 5.0,
        prior_mesh_reduction: float = 0.95,
        with_prior: bool | int = False,
        val_phase: str = "draped",
        seed: int = 0,
        seen_log: str | None = None,
    ) -> None:
        super().__init__()
        if len(tuple(image_size)) != 2 or min(int(v) for v in image_size) <= 0:
            raise DatasetError(f"data.image_size must be [H, W] > 0, got {list(image_size)}")
        if val_phase not in VAL_PHASES:
            raise DatasetError(f"data.val_phase must be one of {VAL_PHASES}, got {val_phase!r}")
        if not 0.0 <= float(prior_probability) <= 1.0:
            raise DatasetError(f"data.prior_probability must be in [0, 1], got {prior_probability}")
        if not 0.0 <= float(prior_mesh_reduction) < 1.0:
            raise DatasetError("data.prior_mesh_reduction must be in [0, 1), got "
                               f"{prior_mesh_reduction}")
        self.root = Path(str(root))
        self.image_size = [int(v) for v in image_size]
        self.batch_size, self.num_workers = int(batch_size), int(num_workers)
        self.shuffle_buffer, self.seed = int(shuffle_buffer), int(seed)
        self.subset, self.subset_fraction = str(subset), subset_fraction
        # the model config's in_channels may be interpolated here: 4 means "with prior"
        self.with_prior = with_prior is True or (not isinstance(with_prior, bool)
                                                 and int(with_prior) == 4)
        self.prior_args = (float(prior_probability), tuple(float(v) for v in prior_translation),
                           float(prior_rotation_deg))
        self.prior_mesh_reduction = float(prior_mesh_reduction)
        self.val_phase, self.seen_log = val_phase, seen_log
        self.manifest: Manifest = read_manifest(self.root)  # fail early, naming the path
        self._check_subset()
        self.datasets: dict[str, Any] = {}

    def _codec(self) -> FrameCodec:
        p, t, r = self.prior_args
        return FrameCodec(self.image_size, self.with_prior, p, t, r, self.manifest.robot_urdf,
                          self.seed, self.prior_mesh_reduction)

    def _entries(self, split: str) -> list[RecordingEntry]:
        entries = self.manifest.split(split)
        empty = [e for e in entries if e.frames == 0]
        if empty:
            log.warning("%s: %d recording(s) of split %r kept no frames when annotated; "
                        "skipped: %s", self.root / MANIFEST, len(empty), split,
                        ", ".join(e.path.name for e in empty))
            entries = [e for e in entries if e.frames != 0]
        if not entries:
            raise DatasetError(f"{self.root / MANIFEST}: split {split!r} has no recordings"
                               + (" with frames" if empty else ""))
        return entries

    def _check_subset(self) -> None:
        if self.subset not in ("all", self.manifest.subset):
            raise DatasetError(
                f"{self.root / MANIFEST}: subset is {self.manifest.subset!r}, data.subset asks "
                f"for {self.subset!r} (annotate that subset, or use data.subset=all)"
            )
        if self.subset_fraction is not None:
            raise DatasetError("data.subset_fraction: subsets are chosen when annotating "
                               "(roboseg-annotate subset_fraction=...), leave it null here")

    def _split(self, split: str) -> Any:
        if split in self.datasets:
            return self.datasets[split]
        entries = self._entries(split)
        readers = open_readers(entries, self.manifest.camera, split)
        if split == "train":
            ds: Any = StreamingFrames(readers, self._codec(), self.shuffle_buffer, self.seed,
                                      seen_log=self.seen_log,
                                      draped_from_ns=[e.draped_from_ns for e in entries])
            n = ds.n_frames()
        else:
            ds = IndexedFrames(readers, entries, self._codec(), self.val_phase)
            n = len(ds)
        if n == 0:
            what = "" if split == "train" else f" ({self.val_phase} frames)"
            raise DatasetError(f"{self.root}: split {split!r} has no usable frames{what}")
        log.info("%s split: %d recordings, %d frames", split, len(readers), n)
        self.datasets[split] = ds
        return ds

    def setup(self, stage: str | None = None) -> None:
        splits = {"fit": ("train", "val"), "validate": ("val",), "test": ("test",),
                  "predict": ("test",)}.get(stage or "fit", SPLITS)
        for split in splits:
            self._split(split)
        train = self.datasets.get("train")
        if train is not None and self.trainer is not None:
            train.rank, train.world_size = self.trainer.global_rank, self.trainer.world_size
            slots = train.world_size * max(1, self.num_workers)
            if len(train.shards) < train.world_size:
                raise DatasetError(
                    f"{self.root}: {len(train.shards)} training chunks for "
                    f"{train.world_size} ranks (need at least one per rank)")
            if len(train.shards) < slots:
                log.warning("%d training chunks for %d loader workers: some stay idle",
                            len(train.shards), slots)

    def train_dataloader(self) -> DataLoader:
        ds = self._split("train")
        ds.batch_size = self.batch_size
        ds.skip_batches = 0
        if self.trainer is not None:  # resuming: fast-forward the batches already trained on
            acc = int(getattr(self.trainer, "accumulate_grad_batches", 1) or 1)
            ds.skip_batches = int(self.trainer.global_step) * acc
            if ds.skip_batches:
                log.info("resuming the training stream after %d batches", ds.skip_batches)
        return DataLoader(ds, batch_size=self.batch_size, num_workers=self.num_workers,
                          collate_fn=collate, persistent_workers=False)

    def _eval_loader(self, split: str) -> DataLoader:
        return DataLoader(self._split(split), batch_size=self.batch_size, shuffle=False,
                          num_workers=self.num_workers, collate_fn=collate,
                          persistent_workers=self.num_workers > 0)

    def val_dataloader(self) -> DataLoader:
        return self._eval_loader("val")

    def test_dataloader(self) -> DataLoader:
        return self._eval_loader("test")
