"""The streaming DataModule over annotated recordings (``roboseg-annotations/1``).

The annotated dataset is built from tiny simulated recordings whose ground-truth masks become the
``robot_mask`` topics (what self-annotation writes), with small MCAP chunks so that sharding by
(file, chunk) has several shards per file.
"""

from __future__ import annotations

import hashlib
import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch

from datamodules.recording import (
    RecordingDataModule,
    StreamingFrames,
    collate,
    is_draped,
    read_manifest,
    resize_frame,
    robot_inside,
    sample_seed,
    shard_order,
    shards_for,
)
from roboseg.errors import DatasetError
from roboseg.recording import (
    RecordingReader,
    RecordingWriter,
    camera_info_topic,
    image_topic,
    joint_states_topic,
    mask_topic,
    msgs,
)
from roboseg.sim import SimConfig, simulate_recording

GT = ("left/robot_mask_gt", "right/robot_mask_gt")


def annotate_from_gt(src: Path, dst: Path, chunk_size: int = 24_000) -> dict:
    """Copy a simulated recording, its ground-truth masks renamed ``robot_mask``; manifest entry."""
    reader = RecordingReader(src, mask_topics=GT)
    meta = reader.metadata()
    kept = 0
    with RecordingWriter(dst, metadata=meta, chunk_size=chunk_size) as w:
        tf = [(p, c, T) for (p, c), T in reader.tf_static().items()]
        w.write_tf_static(tf, 0)
        for robot in reader.robots:
            stamps, values = reader.joint_samples(robot)
            names = reader.joint_names()[robot]
            for s, v in zip(stamps, values, strict=True):
                w.write_joint_state(joint_states_topic(robot), int(s), names, v)
        for side in ("left", "right"):
            info = reader.camera_infos(side)
            w.write_camera_info(camera_info_topic(side=side), 0, info.frame_id, info.K,
                                info.width, info.height)
        for f in reader.frames(decode=False):
            for side, img, fid in (("left", f.left, f.left_frame_id),
                                   ("right", f.right, f.right_frame_id)):
                w.write_compressed(image_topic(side=side), f.stamp_ns, fid, img.tobytes(),
                                   msgs.JPEG_FORMAT)
                w.write_compressed(mask_topic(side=side), f.stamp_ns, fid,
                                   f.masks[f"{side}/robot_mask_gt"].tobytes(),
                                   msgs.PNG_MASK_FORMAT)
            kept += 1
    start = int(meta["roboseg_sim"]["drape_start_stamp_ns"])
    return {"file": dst.name, "source": str(src), "frames_total": len(reader),
            "frames_kept": kept, "robots": reader.robots, "calibration": "tf_static",
            "sha256": hashlib.sha256(dst.read_bytes()).hexdigest(),
            "draped_from_ns": None if start < 0 else start}


def make_annotated_dataset(root: Path, splits: dict[str, int], frames: int = 12,
                           width: int = 96, height: int = 54, seed: int = 0,
                           chunk_size: int = 24_000) -> Path:
    """Simulate ``splits[split]`` recordings per split and annotate them into ``root``."""
    raw = root / "raw"
    raw.mkdir(parents=True, exist_ok=True)
    records = []
    k = 0
    for split, n in splits.items():
        for i in range(n):
            src = raw / f"{split}_{i:02d}.mcap"
            simulate_recording(SimConfig(frames=frames, seed=seed + k, width=width,
                                         height=height), src)
            k += 1
            entry = annotate_from_gt(src, root / src.name, chunk_size)
            entry["split"] = split
            records.append(entry)
    manifest = {"format": "roboseg-annotations/1", "camera": "camera", "robot_urdf": None,
                "subset": "full", "subset_fraction": None, "recordings": records}
    (root / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return root


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_annotated_dataset(tmp_path_factory.mktemp("annotated"),
                                  {"train": 2, "val": 1})


# --- pure helpers ----------------------------------------------------------------------------


def test_shards_partition_order_for_ranks_times_workers() -> None:
    order = shard_order(23, seed=3, epoch=1)
    assert sorted(order.tolist()) == list(range(23))
    parts = [shards_for(order, r, 2, w, 3) for r in range(2) for w in range(3)]
    flat = [s for p in parts for s in p]
    assert sorted(flat) == list(range(23))  # each shard exactly once
    assert [len(p) for p in parts] == [4, 4, 4, 4, 4, 3]
    assert shards_for([10, 11, 12, 13, 14], rank=1, world_size=2, worker=0, num_workers=1) == [
        11, 13]


def test_shard_order_is_a_function_of_seed_and_epoch() -> None:
    a, b = shard_order(50, 0, 0), shard_order(50, 0, 0)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, shard_order(50, 0, 1))
    assert not np.array_equal(a, shard_order(50, 1, 0))
    assert sample_seed(0, 0, 5) == sample_seed(0, 0, 5) != sample_seed(0, 1, 5)


def test_robot_inside_and_resize() -> None:
    mask = np.zeros((9, 16), bool)
    mask[3:5, 4:9] = True
    assert robot_inside(mask)
    mask[8, 2] = True
    assert not robot_inside(mask)
    image = np.zeros((9, 16, 3), np.uint8)
    image[:, :8] = 200  # left half bright: area averaging keeps the half split
    img, msk = resize_frame(image, mask, (4, 4))
    assert img.shape == (4, 4, 3) and msk.shape == (4, 4) and msk.dtype == bool
    assert (img[:, :2] == 200).all() and (img[:, 2:] == 0).all()


def test_collate_drops_unreadable_samples() -> None:
    s = {"image": torch.zeros(3, 2, 2), "index": torch.tensor(4)}
    batch = collate([s, None, s])
    assert batch["image"].shape == (2, 3, 2, 2) and batch["index"].tolist() == [4, 4]


# --- manifest errors ---------------------------------------------------------------------------


def test_missing_root_and_manifest_name_the_path(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="nowhere"):
        read_manifest(tmp_path / "nowhere")
    with pytest.raises(DatasetError, match="manifest"):
        read_manifest(tmp_path)
    (tmp_path / "manifest.json").write_text('{"format": "x"}')
    with pytest.raises(DatasetError, match="format"):
        read_manifest(tmp_path)


def test_empty_split_names_split_and_path(dataset: Path, tmp_path: Path) -> None:
    doc = json.loads((dataset / "manifest.json").read_text())
    doc["recordings"] = [r for r in doc["recordings"] if r["split"] != "val"]
    root = tmp_path / "noval"
    root.mkdir()
    (root / "manifest.json").write_text(json.dumps(doc))
    for r in doc["recordings"]:
        (root / r["file"]).symlink_to(dataset / r["file"])
    dm = RecordingDataModule(root, image_size=[32, 32], batch_size=2, num_workers=0)
    with pytest.raises(DatasetError, match=r"split 'val'.*|'val'"):
        dm.setup("fit")
    (root / doc["recordings"][0]["file"]).unlink()
    dm = RecordingDataModule(root, image_size=[32, 32], batch_size=2, num_workers=0)
    with pytest.raises(DatasetError, match="train_00.mcap"):
        dm.setup("fit")


def test_recordings_that_kept_no_frames_are_skipped_by_name(
    dataset: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """An annotated recording with no frames (no image topics at all) is skipped with a warning;
    a split left with nothing raises, saying so."""
    doc = json.loads((dataset / "manifest.json").read_text())
    root = tmp_path / "with_empty"
    root.mkdir()
    for r in doc["recordings"]:
        (root / r["file"]).symlink_to(dataset / r["file"])
    with RecordingWriter(root / "still_00.mcap") as w:  # what annotation writes keeping nothing
        w.write_tf_static([], 0)
    empty = {**doc["recordings"][0], "file": "still_00.mcap", "frames_kept": 0}
    (root / "manifest.json").write_text(json.dumps({**doc, "recordings": [*doc["recordings"],
                                                                          empty]}))
    dm = RecordingDataModule(root, image_size=[32, 32], batch_size=2, num_workers=0)
    with caplog.at_level("WARNING", logger="datamodules.recording"):
        dm.setup("fit")
    assert "still_00.mcap" in caplog.text and "kept no frames" in caplog.text
    full = RecordingDataModule(dataset, image_size=[32, 32], batch_size=2, num_workers=0)
    full.setup("fit")
    assert dm.datasets["train"].n_frames() == full.datasets["train"].n_frames() > 0
    only_empty = {**doc, "recordings": [empty, *[r for r in doc["recordings"]
                                                 if r["split"] == "val"]]}
    (root / "manifest.json").write_text(json.dumps(only_empty))
    dm = RecordingDataModule(root, image_size=[32, 32], batch_size=2, num_workers=0)
    with pytest.raises(DatasetError, match="split 'train' has no recordings with frames"):
        dm.setup("fit")


# --- datasets ----------------------------------------------------------------------------------


def test_batches_follow_the_contract(dataset: Path) -> None:
    dm = RecordingDataModule(dataset, image_size=[32, 48], batch_size=4, num_workers=0,
                             shuffle_buffer=8, seed=1)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    assert batch["image"].shape == (4, 3, 32, 48) and batch["image"].dtype == torch.float32
    assert batch["image"].min() >= 0 and batch["image"].max() <= 1
    assert batch["mask"].shape == (4, 1, 32, 48)
    assert set(batch["mask"].unique().tolist()) <= {0.0, 1.0} and batch["mask"].sum() > 0
    assert batch["prior"].shape == (4, 1, 32, 48) and batch["prior"].abs().sum() == 0
    assert batch["visible"].dtype == torch.bool and batch["index"].dtype == torch.long


def test_one_epoch_visits_every_training_frame_once_across_ranks_and_workers(
    dataset: Path,
) -> None:
    dm = RecordingDataModule(dataset, image_size=[16, 16], num_workers=0, shuffle_buffer=5)
    dm.setup("fit")
    train: StreamingFrames = dm.datasets["train"]
    assert len(train.shards) >= 4  # small chunks: several shards per file
    seen: list[int] = []
    for rank in range(2):
        for worker in range(2):
            train.rank, train.world_size, train.max_epochs = rank, 2, 1
            it = train._shuffled(worker, 2)
            seen += [train.offsets[f] + fr.index for _, f, fr in it]
    assert sorted(seen) == list(range(train.n_frames()))


def test_stream_is_seeded_reshuffles_per_epoch_and_resumes_exactly(dataset: Path) -> None:
    def indices(seed: int, skip_batches: int = 0, n: int = 30) -> list[int]:
        dm = RecordingDataModule(dataset, image_size=[16, 16], batch_size=3, num_workers=0,
                                 shuffle_buffer=6, seed=seed)
        dm.setup("fit")
        ds = dm.datasets["train"]
        ds.batch_size, ds.skip_batches = 3, skip_batches
        it = iter(ds)
        return [int(next(it)["index"]) for _ in range(n)]

    a = indices(0)
    assert a == indices(0)
    assert a != indices(1)
    assert indices(0, skip_batches=4, n=18) == a[12:30]  # fast-forward = continuation
    n = 24
    epoch0, epoch1 = a[:n], (a + indices(0, 10, 12))[n:2 * n]
    assert sorted(epoch0) != epoch0 and epoch0 != epoch1[: len(epoch0)]


def test_val_is_deterministic_and_draped_only(dataset: Path) -> None:
    manifest = read_manifest(dataset)
    start = manifest.split("val")[0].draped_from_ns
    dm = RecordingDataModule(dataset, image_size=[16, 16], batch_size=3, num_workers=0)
    dm.setup("validate")
    val = dm.datasets["val"]
    reader = val.readers[0]
    draped = [f.index for f in reader.frames(decode=False) if f.stamp_ns >= start]
    assert [i for _, i, _ in val.items] == draped and 0 < len(draped) < len(reader)
    a, b = val[0], val[0]
    assert torch.equal(a["image"], b["image"]) and int(a["index"]) == draped[0]
    assert bool(a["draped"])  # the kind of label travels with the sample
    all_dm = RecordingDataModule(dataset, image_size=[16, 16], num_workers=0, val_phase="all")
    all_dm.setup("validate")
    every = all_dm.datasets["val"]
    assert len(every) == len(reader)
    kinds = [bool(every[k]["draped"]) for k in range(len(every))]
    frames = list(reader.frames(decode=False))
    assert kinds == [f.stamp_ns >= start for f in frames] and not kinds[0] and kinds[-1]


def test_training_samples_say_whether_their_frame_is_draped(dataset: Path) -> None:
    manifest = read_manifest(dataset)
    dm = RecordingDataModule(dataset, image_size=[16, 16], batch_size=4, num_workers=0)
    dm.setup("fit")
    train = dm.datasets["train"]
    starts = {e.path: e.draped_from_ns for e in manifest.split("train")}
    stamps = {}
    for f, reader in enumerate(train.readers):
        for frame in reader.frames(decode=False):
            stamps[train.offsets[f] + frame.index] = frame.stamp_ns >= starts[reader.path]
    seen = [s for _, s in zip(range(2 * len(stamps)), iter(train), strict=False)]
    assert all(bool(s["draped"]) == stamps[int(s["index"])] for s in seen)
    assert {bool(s["draped"]) for s in seen} == {True, False}
    assert is_draped(5, None) and is_draped(5, 5) and not is_draped(4, 5)


def test_prior_is_rendered_near_the_mask_with_probability(dataset: Path) -> None:
    dm = RecordingDataModule(dataset, image_size=[54, 96], batch_size=6, num_workers=0,
                             with_prior=4, prior_probability=1.0, prior_rotation_deg=0.0,
                             prior_translation=[0.0, 0.0])
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    prior, mask = batch["prior"] > 0, batch["mask"] > 0
    iou = (prior & mask).sum() / (prior | mask).sum()
    assert iou > 0.8  # unperturbed prior at the same size = the ground-truth silhouette
    dm0 = RecordingDataModule(dataset, image_size=[54, 96], batch_size=6, num_workers=0,
                              with_prior=4, prior_probability=0.0)
    dm0.setup("fit")
    assert next(iter(dm0.train_dataloader()))["prior"].sum() == 0
    half = RecordingDataModule(dataset, image_size=[16, 16], batch_size=40, num_workers=0,
                               with_prior=True, prior_probability=0.5)
    half.setup("fit")
    got = next(iter(half.train_dataloader()))["prior"].flatten(1).amax(1)
    assert 8 <= int(got.sum()) <= 32


def test_corrupt_frame_is_skipped_and_counted(dataset: Path, tmp_path: Path) -> None:
    doc = json.loads((dataset / "manifest.json").read_text())
    root = tmp_path / "corrupt"
    root.mkdir()
    for r in doc["recordings"]:
        (root / r["file"]).symlink_to(dataset / r["file"])
    (root / "manifest.json").write_text(json.dumps(doc))
    # replace one training recording by a copy (compressed chunks) whose first left image is
    # not a JPEG
    src = dataset / "train_00.mcap"
    (root / "train_00.mcap").unlink()
    reader = RecordingReader(src, mask_topics=("left/robot_mask",))
    frames = list(reader.frames(decode=False))
    bad = tmp_path / "bad.mcap"
    with RecordingWriter(bad, metadata=reader.metadata(), chunk_size=24_000) as w:
        w.write_tf_static([(p, c, T) for (p, c), T in reader.tf_static().items()], 0)
        for robot in reader.robots:
            s, v = reader.joint_samples(robot)
            for t, q in zip(s, v, strict=True):
                w.write_joint_state(joint_states_topic(robot), int(t),
                                    reader.joint_names()[robot], q)
        for side in ("left", "right"):
            info = reader.camera_infos(side)
            w.write_camera_info(camera_info_topic(side=side), 0, info.frame_id, info.K,
                                info.width, info.height)
        for k, f in enumerate(frames):
            left = b"not a jpeg" if k == 0 else f.left.tobytes()
            for side, img in (("left", left), ("right", f.right.tobytes())):
                w.write_compressed(image_topic(side=side), f.stamp_ns, f.left_frame_id,
                                   img, msgs.JPEG_FORMAT)
                w.write_compressed(mask_topic(side=side), f.stamp_ns, f.left_frame_id,
                                   f.masks["left/robot_mask"].tobytes(),
                                   msgs.PNG_MASK_FORMAT)
    (root / "train_00.mcap").symlink_to(bad)
    dm = RecordingDataModule(root, image_size=[16, 16], batch_size=1, num_workers=0)
    dm.setup("fit")
    train = dm.datasets["train"]
    train.max_epochs = 1
    got = [int(s["index"]) for s in train]
    assert len(got) == train.n_frames() - 1 and 0 not in got
    assert train.skipped_corrupt == 1
    assert Counter(got).most_common(1)[0][1] == 1


# --- prior rendering and loader memory ----------------------------------------------------------


def test_priors_rendered_per_batch_equal_priors_rendered_one_by_one(dataset: Path) -> None:
    dm = RecordingDataModule(dataset, image_size=[27, 48], num_workers=0, with_prior=4,
                             prior_probability=0.7, seed=3)
    dm.setup("fit")
    train: StreamingFrames = dm.datasets["train"]
    codec = train.codec
    assert codec.robot.reduction == 0.95  # the prior renders decimated meshes by default
    reader = train.readers[0]
    items = [(reader, fr, train.offsets[0] + fr.index, 2) for fr in reader.frames(decode=False)]
    together = codec.samples(items)
    alone = [codec.sample(*item) for item in items]
    drawn = [bool(s["prior"].any()) for s in together]
    assert 0 < sum(drawn) < len(items)  # some zero priors, some rendered
    for a, b in zip(together, alone, strict=True):
        assert torch.equal(a["prior"], b["prior"]) and torch.equal(a["image"], b["image"])


def test_stream_is_the_same_whatever_the_render_group(dataset: Path) -> None:
    def stream(group: int) -> list[dict[str, torch.Tensor]]:
        dm = RecordingDataModule(dataset, image_size=[16, 16], num_workers=0, shuffle_buffer=4,
                                 with_prior=4, prior_probability=1.0, seed=2)
        dm.setup("fit")
        ds = dm.datasets["train"]
        ds.batch_size = group  # samples are built (and priors rendered) this many at a time
        it = iter(ds)
        return [next(it) for _ in range(11)]

    one, five = stream(1), stream(5)
    assert [int(s["index"]) for s in one] == [int(s["index"]) for s in five]
    assert all(torch.equal(a["prior"], b["prior"]) for a, b in zip(one, five, strict=True))


def test_stream_releases_chunks_and_buffers_no_right_images(dataset: Path) -> None:
    dm = RecordingDataModule(dataset, image_size=[16, 16], num_workers=0, shuffle_buffer=5)
    dm.setup("fit")
    train: StreamingFrames = dm.datasets["train"]
    train.max_epochs = 1
    buffered = list(train._source(0, 1))
    assert len(buffered) == train.n_frames()
    assert all(fr.right.size == 0 and fr.left.size > 0 for _, _, fr in buffered)
    assert all(len(r._cache) == 0 for r in train.readers)  # no decoded chunk kept per file
