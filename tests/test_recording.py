"""MCAP recording I/O: message round trips, stereo/joint synchronisation, bad input, sharding."""

from __future__ import annotations

import io
import logging
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from roboseg.errors import RecordingError
from roboseg.recording import (
    CameraCalib,
    CameraInfo,
    RecordingReader,
    RecordingWriter,
    camera_info_topic,
    image_topic,
    joint_states_topic,
    mask_topic,
    msgs,
)
from roboseg.recording.sync import interpolate_at, prepare_samples
from roboseg.recording.tf import (
    invert_transform,
    lookup_transform,
    make_transform,
    matrix_to_quaternion,
    quaternion_to_matrix,
)
from roboseg.recording.topics import resolve_mask_topic, robots_from_topics

W, H = 64, 48
LEFT, RIGHT = image_topic("camera", "left"), image_topic("camera", "right")
T0 = 1_700_000_000_123_456_789  # a realistic epoch stamp (ns): exercises sec/nanosec split
MS = 1_000_000
K = np.array([[50.0, 0.0, 31.5], [0.0, 52.0, 23.5], [0.0, 0.0, 1.0]])
NAMES = ["joint_a", "joint_b"]


def _image(i: int) -> np.ndarray:
    """Deterministic smooth RGB test image (JPEG-friendly) that differs per frame."""
    rng = np.random.default_rng(i)
    yy, xx = np.mgrid[0:H, 0:W]
    base = np.stack([xx * 4, yy * 5, (xx + yy) * 2], axis=-1) + rng.integers(0, 60, 3)
    return np.clip(base, 0, 255).astype(np.uint8)


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    q = np.r_[axis * np.sin(angle / 2), np.cos(angle / 2)]
    return quaternion_to_matrix(q)


T_LEFT_BASE = make_transform(_rotation([0.3, -1.0, 0.2], 2.1), [0.1, -0.2, 1.5])
T_RIGHT_LEFT = make_transform(_rotation([0.0, 1.0, 0.0], -0.05), [-0.06, 0.0, 0.001])


def write_recording(
    path: Path,
    n_frames: int = 12,
    *,
    frame_period_ns: int = 33 * MS,
    joint_period_ns: int = 10 * MS,
    chunk_size: int = 4 * 1024 * 1024,
    drop_right: tuple[int, ...] = (),
    corrupt_left: tuple[int, ...] = (),
    masks: tuple[int, ...] | None = None,
    joint_start_ns: int = 0,
) -> list[int]:
    """A tiny stereo recording with two robots; returns the image stamps (ns).

    Joint ``k`` of robot_0 is ``(t - T0) / 10 ms + k`` (linear in time, so interpolation is
    exact); robot_1 holds ``-(t - T0) / 10 ms``. Images start 5 ms after T0.
    """
    stamps = [T0 + 5 * MS + i * frame_period_ns for i in range(n_frames)]
    end = stamps[-1] + 2 * joint_period_ns
    with RecordingWriter(path, metadata={"rig": {"name": "test"}}, chunk_size=chunk_size) as w:
        calib = CameraCalib(
            "camera",
            CameraInfo(K, W, H, "camera_left_optical_frame", np.array([0.1, -0.01, 0, 0, 0])),
            CameraInfo(K, W, H, "camera_right_optical_frame"),
            T_RIGHT_LEFT,
        )
        w.write_camera_calib(calib, T0)
        w.write_tf_static([("camera_left_optical_frame", "robot_0/link_0", T_LEFT_BASE)], T0)
        t_joint = T0 + joint_start_ns
        events: list[tuple[int, str, int]] = []
        while t_joint <= end:
            events.append((t_joint, "joints", 0))
            t_joint += joint_period_ns
        events += [(s, "image", i) for i, s in enumerate(stamps)]
        for t, kind, i in sorted(events):
            if kind == "joints":
                x = (t - T0) / (10 * MS)
                w.write_joint_state(joint_states_topic("robot_0"), t, NAMES, [x, x + 1.0])
                w.write_joint_state(joint_states_topic("robot_1"), t, NAMES, [-x, 0.5])
                continue
            img = _image(i)
            if i in corrupt_left:
                w.write_compressed(
                    image_topic("camera", "left"),
                    t,
                    "camera_left_optical_frame",
                    b"\xff\xd8 not really a jpeg",
                    msgs.JPEG_FORMAT,
                )
            else:
                w.write_image(image_topic("camera", "left"), t, "camera_left_optical_frame", img)
            if i not in drop_right:
                w.write_image(
                    image_topic("camera", "right"),
                    t,
                    "camera_right_optical_frame",
                    img[:, ::-1].copy(),
                )
            if masks is None or i in masks:
                w.write_mask(
                    mask_topic("camera", "left"),
                    t,
                    "camera_left_optical_frame",
                    _image(i)[..., 0] > 128,
                )
    return stamps


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[int]]:
    path = tmp_path_factory.mktemp("rec") / "rec.mcap"
    return path, write_recording(path)


# -- pure functions ----------------------------------------------------------------------------
def test_interpolation_hand_computed() -> None:
    stamps = np.array([0, 10 * MS], dtype=np.int64)
    values = np.array([[0.0, 5.0], [1.0, 3.0]])
    out, valid = interpolate_at(stamps, values, np.array([int(2.5 * MS), 0, 10 * MS]), 10 * MS)
    assert valid.tolist() == [True, True, True]
    np.testing.assert_allclose(out, [[0.25, 4.5], [0.0, 5.0], [1.0, 3.0]])


def test_interpolation_tolerance_and_edges() -> None:
    stamps = np.array([0, 10 * MS, 50 * MS], dtype=np.int64)
    values = np.array([[0.0], [1.0], [2.0]])
    query = np.array([-1, 5 * MS, 30 * MS, 50 * MS, 51 * MS], dtype=np.int64)
    out, valid = interpolate_at(stamps, values, query, tolerance_ns=10 * MS)
    # before the first sample, inside a 40 ms gap and after the last sample are invalid
    assert valid.tolist() == [False, True, False, True, False]
    np.testing.assert_allclose(out[[1, 3], 0], [0.5, 2.0])
    assert np.isnan(out[[0, 2, 4]]).all()


def test_prepare_samples_sorts_and_dedupes() -> None:
    s, v = prepare_samples(np.array([20, 10, 20]), np.array([[1.0], [2.0], [3.0]]))
    assert s.tolist() == [10, 20]
    assert v[:, 0].tolist() == [2.0, 3.0]
    s, v = prepare_samples(np.zeros(0, np.int64), np.zeros((0, 7)))
    assert s.shape == (0,) and v.shape == (0, 7)


def test_quaternion_hand_values() -> None:
    half = np.sqrt(0.5)
    R = quaternion_to_matrix(np.array([0.0, 0.0, half, half]))  # +90 deg about z
    np.testing.assert_allclose(R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(matrix_to_quaternion(R), [0, 0, half, half], atol=1e-12)
    R180 = np.diag([1.0, -1.0, -1.0])  # 180 deg about x: trace < 0 branch
    np.testing.assert_allclose(matrix_to_quaternion(R180), [1, 0, 0, 0], atol=1e-12)
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[3] >= 0 else -q
        np.testing.assert_allclose(matrix_to_quaternion(quaternion_to_matrix(q)), q, atol=1e-12)


def test_tf_chain_lookup() -> None:
    T_a_b = make_transform(_rotation([1, 0, 0], 0.3), [1.0, 0, 0])
    T_b_c = make_transform(_rotation([0, 0, 1], -1.2), [0, 2.0, 0])
    T_d_b = make_transform(np.eye(3), [0, 0, 3.0])
    edges = {("a", "b"): T_a_b, ("b", "c"): T_b_c, ("d", "b"): T_d_b}
    np.testing.assert_allclose(lookup_transform(edges, "a", "c"), T_a_b @ T_b_c, atol=1e-12)
    np.testing.assert_allclose(
        lookup_transform(edges, "c", "a"), invert_transform(T_a_b @ T_b_c), atol=1e-12
    )
    # sibling branch: c -> b -> d
    np.testing.assert_allclose(lookup_transform(edges, "d", "c"), T_d_b @ T_b_c, atol=1e-12)
    # point check of the convention: p_a = T_a_b p_b
    p_b = np.array([0.0, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(lookup_transform(edges, "a", "b") @ p_b, [1, 0, 0, 1])
    with pytest.raises(RecordingError, match="'x'"):
        lookup_transform(edges, "a", "x")


def test_cdr_header_stamp_matches_decoder() -> None:
    from mcap_ros2.writer import Writer

    buf = io.BytesIO()
    writer = Writer(buf)
    schema = writer.register_msgdef(msgs.COMPRESSED_IMAGE, msgs.MSGDEFS[msgs.COMPRESSED_IMAGE])
    message = {"header": msgs.header(T0, "f"), "format": "x", "data": b"\x00"}
    writer.write_message("/t", schema, message, log_time=1)
    writer.finish()
    buf.seek(0)
    ((_, _, raw, decoded),) = make_reader(
        buf, decoder_factories=[DecoderFactory()]
    ).iter_decoded_messages()
    assert msgs.cdr_header_stamp_ns(raw.data) == T0 == msgs.stamp_to_ns(decoded.header.stamp)


def test_topic_helpers() -> None:
    assert resolve_mask_topic("left/robot_mask_gt") == "/camera/left/robot_mask_gt/compressed"
    assert resolve_mask_topic("/x/y") == "/x/y"
    with pytest.raises(ValueError, match="middle/x"):
        resolve_mask_topic("middle/x")
    topics = ["/robot_1/joint_states", "/robot_0/joint_states", "/a/b/joint_states", "/tf"]
    assert robots_from_topics(topics) == ["robot_0", "robot_1"]


# -- round trips -------------------------------------------------------------------------------
def test_message_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "one.mcap"
    img = _image(3)
    mask = np.zeros((H, W), dtype=bool)
    mask[10:20, 5:40] = True
    T = make_transform(_rotation([1, 2, 3], 0.7), [0.25, -1.5, 2.0])
    with RecordingWriter(path, metadata={"sim": {"seed": "7"}}) as w:
        w.write_metadata("robot", {"urdf": "lbr_med7.urdf"})
        w.write_image(LEFT, T0, "cam", img, fmt="png")
        w.write_image(RIGHT, T0, "cam", img, fmt="jpeg", quality=95)
        w.write_mask("/mask", T0, "cam", mask)
        w.write_camera_info("/info", T0, "cam", K, W, H, D=[0.1, 0.2, 0.0, 0.0, 0.3])
        w.write_joint_state("/r/joint_states", T0, NAMES, [0.125, -2.5], velocities=[1.0, 2.0])
        w.write_tf_static([("parent", "child", T)], stamp_ns=T0)
    assert path.is_file() and not (tmp_path / "one.mcap.part").exists()

    decoded = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, ros in reader.iter_decoded_messages():
            decoded[channel.topic] = (schema.name, message.log_time, ros)
    assert decoded[LEFT][0] == "sensor_msgs/msg/CompressedImage"
    assert decoded["/info"][0] == "sensor_msgs/msg/CameraInfo"
    assert decoded["/r/joint_states"][0] == "sensor_msgs/msg/JointState"
    assert decoded["/tf_static"][0] == "tf2_msgs/msg/TFMessage"
    assert all(log_time == T0 for _, log_time, _ in decoded.values())

    from roboseg.recording.reader import decode_image, decode_mask

    np.testing.assert_array_equal(decode_image(decoded[LEFT][2].data), img)  # PNG: lossless
    jpg = decode_image(decoded[RIGHT][2].data)
    assert jpg.shape == img.shape and np.abs(jpg.astype(int) - img).mean() < 3
    np.testing.assert_array_equal(decode_mask(decoded["/mask"][2].data), mask)
    assert decoded["/mask"][2].format == msgs.PNG_MASK_FORMAT

    info = decoded["/info"][2]
    assert (info.width, info.height, info.header.frame_id) == (W, H, "cam")
    assert msgs.stamp_to_ns(info.header.stamp) == T0
    assert list(info.k) == K.ravel().tolist() and list(info.d) == [0.1, 0.2, 0.0, 0.0, 0.3]
    js = decoded["/r/joint_states"][2]
    assert list(js.name) == NAMES and list(js.position) == [0.125, -2.5]
    assert list(js.velocity) == [1.0, 2.0]
    (ts,) = decoded["/tf_static"][2].transforms
    assert (ts.header.frame_id, ts.child_frame_id) == ("parent", "child")

    reader = RecordingReader(path, robots=["r"])
    assert reader.metadata() == {"sim": {"seed": "7"}, "robot": {"urdf": "lbr_med7.urdf"}}
    np.testing.assert_allclose(reader.tf_static()[("parent", "child")], T, atol=1e-12)
    stamps, positions = reader.joint_samples("r")
    assert stamps.tolist() == [T0] and positions.tolist() == [[0.125, -2.5]]


def test_reader_calibration_and_metadata(recording: tuple[Path, list[int]]) -> None:
    path, _ = recording
    reader = RecordingReader(path)
    assert reader.robots == ["robot_0", "robot_1"]
    assert reader.metadata() == {"rig": {"name": "test"}}
    K_read, width, height, frame_id = reader.camera_info("left")
    np.testing.assert_array_equal(K_read, K)
    assert (width, height, frame_id) == (W, H, "camera_left_optical_frame")
    calib = reader.camera_calib()
    np.testing.assert_allclose(calib.left.D, [0.1, -0.01, 0, 0, 0])
    np.testing.assert_allclose(calib.T_right_left, T_RIGHT_LEFT, atol=1e-12)
    # chain: base -> left optical -> right optical
    np.testing.assert_allclose(
        reader.lookup("camera_right_optical_frame", "robot_0/link_0"),
        T_RIGHT_LEFT @ T_LEFT_BASE,
        atol=1e-12,
    )
    topics = reader.topics()
    assert topics[image_topic()] == "sensor_msgs/msg/CompressedImage"
    assert topics["/tf_static"] == "tf2_msgs/msg/TFMessage"
    # the same answers after the full index pass (summary-free code path)
    assert len(reader) == 12
    assert reader.topics() == topics and reader.metadata() == {"rig": {"name": "test"}}
    np.testing.assert_allclose(reader.camera_calib().T_right_left, T_RIGHT_LEFT, atol=1e-12)


# -- frames ------------------------------------------------------------------------------------
def test_frames_sync_and_interpolation(recording: tuple[Path, list[int]]) -> None:
    path, stamps = recording
    reader = RecordingReader(path, mask_topics=["left/robot_mask"])
    frames = list(reader.frames())
    assert [f.stamp_ns for f in frames] == stamps
    assert reader.stats.yielded == 12 and reader.stats.skipped == 0
    for i, f in enumerate(frames):
        assert f.index == i and f.left.shape == (H, W, 3) and f.left.dtype == np.uint8
        assert np.abs(f.left.astype(int) - _image(i)).mean() < 3
        assert np.abs(f.right.astype(int) - _image(i)[:, ::-1]).mean() < 3
        np.testing.assert_array_equal(f.masks["left/robot_mask"], _image(i)[..., 0] > 128)
        assert f.joint_names == {"robot_0": NAMES, "robot_1": NAMES}
        x = (f.stamp_ns - T0) / (10 * MS)  # image stamps fall between 10 ms joint samples
        np.testing.assert_allclose(f.joints["robot_0"], [x, x + 1.0], atol=1e-9)
        np.testing.assert_allclose(f.joints["robot_1"], [-x, 0.5], atol=1e-9)
        assert (f.left_frame_id, f.right_frame_id) == (
            "camera_left_optical_frame",
            "camera_right_optical_frame",
        )
    # first frame at 5 ms: halfway between the joint samples at 0 and 10 ms
    np.testing.assert_allclose(frames[0].joints["robot_0"], [0.5, 1.5], atol=1e-12)


def test_frames_slicing_and_raw(recording: tuple[Path, list[int]]) -> None:
    path, stamps = recording
    reader = RecordingReader(path)
    assert [f.index for f in reader.frames(2, 9, 3)] == [2, 5, 8]
    raw = next(reader.frames(decode=False))
    assert raw.left.ndim == 1 and bytes(raw.left[:2]) == b"\xff\xd8"  # JPEG SOI marker


def test_joint_order_and_missing_joint(recording: tuple[Path, list[int]]) -> None:
    path, _ = recording
    reader = RecordingReader(path, robots=["robot_0"], joint_order={"robot_0": NAMES[::-1]})
    frame = next(reader.frames())
    assert list(frame.joints) == ["robot_0"]
    np.testing.assert_allclose(frame.joints["robot_0"], [1.5, 0.5], atol=1e-12)
    bad = RecordingReader(path, robots=["robot_0"], joint_order={"robot_0": ["joint_z"]})
    with pytest.raises(RecordingError, match="joint_z.*robot_0/joint_states"):
        next(bad.frames())


def test_skip_counting(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "gaps.mcap"
    # joint states start 40 ms after T0: frames at 5 and 38 ms have no joint state before them
    write_recording(
        path,
        n_frames=8,
        joint_start_ns=40 * MS,
        drop_right=(4,),
        corrupt_left=(6,),
        masks=(0, 1, 2, 3, 4, 5, 6),
    )
    reader = RecordingReader(path)
    with caplog.at_level(logging.WARNING, logger="roboseg.recording.reader"):
        got = [f.index for f in reader.frames()]
    # frames 0, 1: no joint state; 4: no right image; 6: corrupt JPEG (masks not requested)
    assert got == [2, 3, 5, 7]
    s = reader.stats
    assert (s.yielded, s.skipped_no_joint_state, s.skipped_unpaired, s.skipped_corrupt) == (
        4,
        2,
        1,
        1,
    )
    assert "does not decode" in caplog.text
    masked = RecordingReader(path, mask_topics=["left/robot_mask"])
    assert [f.index for f in masked.frames()] == [2, 3, 5]
    assert masked.stats.skipped_no_mask == 1


def test_stereo_tolerance(tmp_path: Path) -> None:
    path = tmp_path / "offset.mcap"
    with RecordingWriter(path) as w:
        for i, dt in enumerate([0, 400_000, 3 * MS]):  # right image 0, 0.4 ms, 3 ms late
            t = T0 + i * 100 * MS
            w.write_image(image_topic("camera", "left"), t, "l", _image(i))
            w.write_image(image_topic("camera", "right"), t + dt, "r", _image(i))
    reader = RecordingReader(path, stereo_tolerance_ns=MS)
    assert reader.robots == []
    assert [f.index for f in reader.frames()] == [0, 1]
    assert reader.stats.skipped_unpaired == 1


# -- bad input ---------------------------------------------------------------------------------
def test_missing_topic_and_camera_info(recording: tuple[Path, list[int]], tmp_path: Path) -> None:
    path, _ = recording
    with pytest.raises(
        RecordingError,
        match=r"/stereo/left/image_raw/compressed.*topics: .*"
        r"/camera/left/image_raw/compressed",
    ):
        RecordingReader(path, camera="stereo")
    with pytest.raises(RecordingError, match="robot_7/joint_states"):
        RecordingReader(path, robots=["robot_7"])
    no_info = tmp_path / "noinfo.mcap"
    with RecordingWriter(no_info) as w:
        w.write_image(image_topic("camera", "left"), T0, "l", _image(0))
        w.write_image(image_topic("camera", "right"), T0, "r", _image(0))
    with pytest.raises(RecordingError, match="camera 'camera' left"):
        RecordingReader(no_info).camera_info("left")
    with pytest.raises(RecordingError, match="does not exist"):
        RecordingReader(tmp_path / "nope.mcap")
    (tmp_path / "text.mcap").write_text("hello")
    with pytest.raises(RecordingError, match="not an MCAP"):
        RecordingReader(tmp_path / "text.mcap")


def _chunk_spans(path: Path) -> list[tuple[int, int]]:
    from mcap.reader import SeekingReader

    with open(path, "rb") as f:
        summary = SeekingReader(f).get_summary()
    return [(c.chunk_start_offset, c.chunk_length) for c in summary.chunk_indexes]


def test_truncated_file(tmp_path: Path) -> None:
    path = tmp_path / "full.mcap"
    stamps = write_recording(path, n_frames=12, chunk_size=8 * 1024)
    spans = _chunk_spans(path)
    assert len(spans) >= 4
    start, length = spans[len(spans) // 2]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: start + length // 2])  # cut in the middle of a chunk

    with pytest.raises(RecordingError, match=r"cut\.mcap.*last good timestamp \d+ ns"):
        RecordingReader(cut)
    reader = RecordingReader(cut, on_error="skip")
    frames = list(reader.frames())
    assert 0 < len(frames) < len(stamps)
    assert [f.stamp_ns for f in frames] == stamps[: len(frames)]
    assert reader.stats.errors and "cut.mcap" in reader.stats.errors[0]
    assert reader.errors == reader.stats.errors


def test_corrupt_chunk_crc(tmp_path: Path) -> None:
    path = tmp_path / "flip.mcap"
    write_recording(path, n_frames=12, chunk_size=8 * 1024)
    data = bytearray(path.read_bytes())
    start, length = _chunk_spans(path)[1]
    data[start + length - 100] ^= 0xFF  # flip bits inside the compressed records of chunk 1
    path.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match="flip.mcap"):
        RecordingReader(path).chunk_index()
    reader = RecordingReader(path, on_error="skip")
    frames = list(reader.frames())
    assert len(reader.errors) == 1 and len(frames) < 12
    assert len(reader.chunk_index()) == len(_chunk_spans(path)) - 1


def test_atomic_write(tmp_path: Path) -> None:
    path = tmp_path / "atomic.mcap"
    with pytest.raises(RuntimeError, match="boom"), RecordingWriter(path) as w:
        w.write_image(image_topic(), T0, "l", _image(0))
        assert (tmp_path / "atomic.mcap.part").is_file() and not path.exists()
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    with RecordingWriter(path) as w:
        w.write_camera_info(camera_info_topic(), T0, "l", K, W, H)
    assert [p.name for p in tmp_path.iterdir()] == ["atomic.mcap"]


# -- sharding ----------------------------------------------------------------------------------
def test_chunk_sharding_covers_every_frame_once(tmp_path: Path) -> None:
    path = tmp_path / "sharded.mcap"
    write_recording(path, n_frames=24, chunk_size=6 * 1024, drop_right=(7,))
    reader = RecordingReader(path)
    chunks = reader.chunk_index()
    assert len(chunks) >= 5
    assert sum(c.n_frames for c in chunks) == 24
    all_frames = [f.index for f in reader.frames(decode=False)]
    assert len(all_frames) == 23
    world = 3
    seen: list[int] = []
    for rank in range(world):
        shard = RecordingReader(path)  # a fresh reader per rank / worker
        ids = [c.id for c in chunks if c.id % world == rank]
        seen += [f.index for f in shard.frames_in_chunks(ids, decode=False)]
    assert sorted(seen) == all_frames  # every frame exactly once
    # a frame whose right image lies in the next chunk is still complete
    full = {f.index: f for f in reader.frames()}
    for c in chunks:
        for f in RecordingReader(path).frames_in_chunks([c.id]):
            np.testing.assert_array_equal(f.right, full[f.index].right)
    with pytest.raises(RecordingError, match="chunk id"):
        list(reader.frames_in_chunks([len(chunks)]))


def test_reader_pickles_for_workers(recording: tuple[Path, list[int]]) -> None:
    import pickle

    path, stamps = recording
    reader = RecordingReader(path)
    first = next(reader.frames())
    clone = pickle.loads(pickle.dumps(reader))  # e.g. sent to a DataLoader worker
    frames = list(clone.frames(decode=False))
    assert [f.stamp_ns for f in frames] == stamps and first.index == 0
    assert len(clone._cache) <= 4  # streaming: only a few decompressed chunks held


def test_masks_are_1_bit_pngs_decoding_to_0_and_255() -> None:
    import cv2

    from roboseg.recording.reader import decode_mask
    from roboseg.recording.writer import encode_mask

    mask = np.random.default_rng(2).integers(0, 3, (9, 13)).astype(np.uint8)  # nonzero: robot
    data = encode_mask(mask)
    assert data[24] == 1 and data[25] == 0  # IHDR: bit depth 1, greyscale
    gray = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(gray, np.where(mask != 0, 255, 0))
    np.testing.assert_array_equal(decode_mask(data), mask != 0)
