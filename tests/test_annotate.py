"""Self-annotation: masks vs simulator ground truth, motion subsets, manifest, bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from roboseg.annotate import (
    AnnotateOptions,
    annotate_folder,
    annotate_recording,
    assign_split,
    joint_speed_at,
    phase_mask,
    target_count,
    thin_evenly,
)
from roboseg.errors import RecordingError, RobosegError, RobotModelError
from roboseg.recording import RecordingReader, RecordingWriter
from roboseg.recording.topics import camera_info_topic, image_topic, joint_states_topic
from roboseg.robot import load_robot
from roboseg.sim import SimConfig, simulate_recording

LEFT, RIGHT = "camera_left_optical_frame", "camera_right_optical_frame"
T0 = 1_700_000_000_000_000_000
STEP = 50_000_000  # 20 fps


@pytest.fixture(scope="module")
def robot():
    return load_robot(None)


@pytest.fixture(scope="module")
def sim_path(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("sim") / "sim.mcap"
    simulate_recording(SimConfig(frames=12, width=160, height=96, seed=3), path)
    return path


def T_left_base() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]  # base x forward -> camera z
    T[:3, 3] = [0.0, 0.4, 2.0]
    return T


def write_synthetic(
    path: Path,
    robot,
    frames: int = 40,
    still: int = 10,
    names: list[str] | None = None,
    tf: bool = True,
    camera_info: bool = True,
    chunk_size: int = 4 * 1024 * 1024,
) -> Path:
    """Tiny recording: ``still`` motionless frames, then every joint moving at 0.5 rad/s."""
    K = np.array([[40.0, 0, 15.5], [0, 40.0, 11.5], [0, 0, 1]])
    T_lr = np.eye(4)
    T_lr[0, 3] = 0.1
    img = np.random.default_rng(0).integers(0, 255, (24, 32, 3), dtype=np.uint8)
    with RecordingWriter(path, chunk_size=chunk_size) as w:
        if tf:
            w.write_tf_static(
                [(LEFT, f"robot_0/{robot.root_link}", T_left_base()), (LEFT, RIGHT, T_lr)], T0
            )
        for i in range(frames):
            stamp = T0 + i * STEP
            q = np.full(robot.dof, 0.3) + 0.5 * max(0, i - still) * STEP * 1e-9
            w.write_joint_state(joint_states_topic("robot_0"), stamp, names or robot.joint_names, q)
            for side, frame in (("left", LEFT), ("right", RIGHT)):
                w.write_image(image_topic(side=side), stamp, frame, img)
                if camera_info:
                    w.write_camera_info(camera_info_topic(side=side), stamp, frame, K, 32, 24)
    return path


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)


# -- pure functions --------------------------------------------------------------------------


def test_joint_speed_hand_computed():
    stamps = np.array([0, 1_000_000_000, 2_000_000_000], dtype=np.int64)
    q = np.array([[0.0, 0.0], [0.5, -1.0], [0.5, -1.0]])
    speed = joint_speed_at(stamps, q, np.array([0, 500_000_000, 1_000_000_000, 3_000_000_000]))
    np.testing.assert_allclose(speed, [1.0, 1.0, 0.0, 0.0])


def test_thin_evenly_and_targets():
    np.testing.assert_array_equal(thin_evenly(np.arange(10), 2), [2, 7])
    np.testing.assert_array_equal(thin_evenly(np.arange(3), 5), [0, 1, 2])
    assert target_count(1000, 0.04) == 40 and target_count(10, 0.04) == 1
    assert target_count(10, None) is None


def test_phase_and_split():
    stamps = np.array([1, 2, 3])
    np.testing.assert_array_equal(phase_mask(stamps, "draped", 2), [False, True, True])
    np.testing.assert_array_equal(phase_mask(stamps, "undraped", 2), [True, False, False])
    assert phase_mask(stamps, "all", None).all()
    assert assign_split("run_val_2.mcap") == "val"
    assert assign_split("a_test.mcap") == "test"
    assert assign_split("x.mcap") == "train"
    assert assign_split("x.mcap", {"val": ["x*"]}) == "val"
    with pytest.raises(RobosegError, match="phase"):
        phase_mask(stamps, "wet", None)


# -- simulated recordings ---------------------------------------------------------------------


def test_masks_match_simulator_ground_truth(sim_path, robot, tmp_path):
    out = tmp_path / "a.mcap"
    result = annotate_recording(sim_path, out, robot, AnnotateOptions(min_joint_speed=0.0))
    assert result.frames_kept == result.frames_total == 12
    assert result.calibration == "tf_static" and result.draped_from_ns is not None
    masks = [f"{s}/{k}" for s in ("left", "right") for k in ("robot_mask", "robot_mask_gt")]
    with RecordingReader(out, mask_topics=masks) as reader:
        frames = list(reader.frames())
    assert len(frames) == 12
    for f in frames:
        for side in ("left", "right"):
            gt = f.masks[f"{side}/robot_mask_gt"]
            assert gt.any()
            assert iou(f.masks[f"{side}/robot_mask"], gt) >= 0.99


def test_worker_processes_write_the_same_file(sim_path, robot, tmp_path):
    one, two = tmp_path / "one.mcap", tmp_path / "two.mcap"
    annotate_recording(sim_path, one, robot, AnnotateOptions(min_joint_speed=0.0))
    annotate_recording(sim_path, two, robot, AnnotateOptions(min_joint_speed=0.0, workers=2))
    assert one.read_bytes() == two.read_bytes()


class _CountingEncoder:
    """Stands in for MaskRenderer: the PNG pair of a frame is its joint value as text."""

    def __init__(self) -> None:
        self.calls = 0

    def encode(self, joints: dict[str, np.ndarray], level: int) -> tuple[bytes, bytes]:
        self.calls += 1
        k = int(joints["r"][0])
        return (b"L%d" % k, b"R%d" % k)


@pytest.mark.parametrize("workers", [1, 2])
def test_mask_stream_in_order_out_of_order_and_again(workers):
    from roboseg.annotate.parallel import MaskStream

    encoder = _CountingEncoder()
    joints = [{"r": np.array([k])} for k in range(23)]
    with MaskStream(encoder, joints, level=1, workers=workers, batch=3, ahead=1) as stream:
        order = [0, 2, 1, *range(3, 23), 5, 22]  # a late frame and repeats are re-rendered
        got = [stream.get(k) for k in order]
    assert got == [[b"L%d" % k, b"R%d" % k] for k in order]
    if workers == 1:
        assert encoder.calls == len(order)


def test_phase_filter_and_calibration_file(sim_path, robot, tmp_path):
    with RecordingReader(sim_path) as reader:
        T = reader.lookup(LEFT, f"robot_0/{robot.root_link}")
    calib = tmp_path / "calib.yaml"
    calib.write_text(
        yaml.safe_dump(
            {
                "T_cam_base": T.ravel().tolist(),
                "camera_frame": LEFT,
                "base_frame": f"robot_0/{robot.root_link}",
            }
        )
    )
    opts = AnnotateOptions(min_joint_speed=0.0, phase="draped", calibration=str(calib))
    result = annotate_recording(sim_path, tmp_path / "d.mcap", robot, opts)
    assert result.calibration == "file"
    with RecordingReader(tmp_path / "d.mcap", mask_topics=["left/robot_mask"]) as reader:
        stamps = [f.stamp_ns for f in reader.frames()]
    assert len(stamps) == result.frames_kept == 12 - result.skipped["phase"]
    assert result.skipped["phase"] > 0
    assert min(stamps) >= result.draped_from_ns


# -- motion subsets, manifest ---------------------------------------------------------------


def test_only_moving_frames_and_subset_fraction(robot, tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    write_synthetic(src / "train_a.mcap", robot, frames=50, still=10)
    write_synthetic(src / "b_val.mcap", robot, frames=20, still=5)
    opts = AnnotateOptions(fraction=0.2, min_joint_speed=0.1)
    manifest = annotate_folder(src, tmp_path / "out", robot, opts, subset="custom")
    on_disk = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert on_disk == manifest and manifest["format"] == "roboseg-annotations/1"
    rec = {r["file"]: r for r in manifest["recordings"]}
    train, val = rec["train_a.mcap"], rec["b_val.mcap"]
    assert train["split"] == "train" and val["split"] == "val"
    assert abs(train["frames_kept"] - 0.2 * 50) <= 1
    # frame i moves iff i > still (speed of the interval starting at it)
    assert train["skipped"]["low_motion"] == 10
    assert train["skipped"]["subsampled"] == 40 - train["frames_kept"]
    assert val["frames_kept"] == 15 and val["skipped"]["low_motion"] == 5  # not thinned
    with RecordingReader(tmp_path / "out" / "train_a.mcap") as reader:
        stamps = [f.stamp_ns for f in reader.frames()]
    assert len(stamps) == train["frames_kept"]
    assert min(stamps) >= T0 + 10 * STEP
    assert manifest["totals"]["frames_kept"] == train["frames_kept"] + 15
    assert len(train["sha256"]) == 64


# -- bad input --------------------------------------------------------------------------------


def test_truncated_and_garbage_files_do_not_stop_the_batch(robot, tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    good = write_synthetic(src / "good.mcap", robot, frames=30, chunk_size=8192)
    data = good.read_bytes()
    (src / "cut.mcap").write_bytes(data[: len(data) // 3])
    (src / "stub.mcap").write_bytes(data[:40])
    (src / "junk.mcap").write_bytes(b"not an mcap at all")
    manifest = annotate_folder(src, tmp_path / "out", robot, AnnotateOptions(min_joint_speed=0))
    rec = {r["source"].split("/")[-1]: r for r in manifest["recordings"]}
    assert rec["good.mcap"]["frames_kept"] == 30
    assert rec["junk.mcap"]["skipped"]["unreadable"] == 1 and rec["junk.mcap"]["file"] is None
    assert rec["cut.mcap"]["skipped"]["unreadable"] >= 1
    assert 0 < rec["cut.mcap"]["frames_kept"] < 30
    assert rec["stub.mcap"]["skipped"]["unreadable"] == 1 and rec["stub.mcap"]["file"] is None
    with RecordingReader(tmp_path / "out" / "cut.mcap") as reader:
        assert len(list(reader.frames())) == rec["cut.mcap"]["frames_kept"]


def test_missing_topic_lists_existing(robot, tmp_path):
    path = write_synthetic(tmp_path / "a.mcap", robot, frames=3)
    with pytest.raises(RecordingError, match=r"missing topic .*topics: .*joint_states"):
        annotate_recording(path, tmp_path / "o.mcap", robot, AnnotateOptions(camera="zed"))


def test_joint_name_mismatch_lists_both(robot, tmp_path):
    names = [f"j{k}" for k in range(robot.dof)]
    path = write_synthetic(tmp_path / "a.mcap", robot, frames=3, names=names)
    with pytest.raises(RobotModelError, match=rf"j0.*{robot.joint_names[0]}"):
        annotate_recording(path, tmp_path / "o.mcap", robot, AnnotateOptions())
    assert not (tmp_path / "o.mcap").exists()


def test_missing_camera_info_names_camera(robot, tmp_path):
    path = write_synthetic(tmp_path / "a.mcap", robot, frames=3, camera_info=False)
    with pytest.raises(RecordingError, match="CameraInfo for camera 'camera' left"):
        annotate_recording(path, tmp_path / "o.mcap", robot, AnnotateOptions())


def test_missing_tf_names_frames_and_suggests_calibration(robot, tmp_path):
    path = write_synthetic(tmp_path / "a.mcap", robot, frames=3, tf=False)
    with pytest.raises(RecordingError, match=rf"'{LEFT}'.*robot_0/.*calibration="):
        annotate_recording(path, tmp_path / "o.mcap", robot, AnnotateOptions())


def test_cli_exits_with_one_line_on_user_error(tmp_path, capsys):
    from omegaconf import OmegaConf

    from roboseg.cli.annotate import run

    cfg = OmegaConf.load(Path(__file__).parents[1] / "conf" / "annotate.yaml")
    cfg["in"], cfg.out, cfg.subset = str(tmp_path / "none"), str(tmp_path / "o"), "huge"
    with pytest.raises(SystemExit) as exc:
        run(cfg)
    assert exc.value.code == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "subset" in err
    shutil.rmtree(tmp_path / "o", ignore_errors=True)


def test_reduced_mesh_masks_agree_with_the_full_mesh_or_are_not_used(robot, tmp_path):
    sim = tmp_path / "sim.mcap"  # large enough for a silhouette of thousands of pixels
    simulate_recording(SimConfig(frames=6, width=480, height=270, seed=3), sim)
    full, reduced, refused = (tmp_path / f"{n}.mcap" for n in ("full", "reduced", "refused"))
    opts = AnnotateOptions(min_joint_speed=0.0)
    annotate_recording(sim, full, robot, opts)
    opts_reduced = AnnotateOptions(min_joint_speed=0.0, mesh_reduction=0.3, mesh_check_frames=2)
    result = annotate_recording(sim, reduced, robot, opts_reduced)
    assert result.mesh is not None and result.mesh["used"] == 0.3
    assert result.mesh["min_iou"] >= 0.995
    assert result.manifest_entry()["mesh"] == result.mesh
    masks = [f"{s}/robot_mask" for s in ("left", "right")]
    with (
        RecordingReader(full, mask_topics=masks) as a,
        RecordingReader(reduced, mask_topics=masks) as b,
    ):
        pairs = list(zip(a.frames(), b.frames(), strict=True))
    assert len(pairs) == 6
    for fa, fb in pairs:  # every frame, not only the two checked ones
        for m in masks:
            assert fa.masks[m].sum() > 1000
            assert iou(fa.masks[m], fb.masks[m]) >= 0.995
    # a reduction whose masks cannot reach the bar: the full mesh, the same file
    strict = AnnotateOptions(min_joint_speed=0.0, mesh_reduction=0.9, mesh_min_iou=1.0)
    result = annotate_recording(sim, refused, robot, strict)
    assert result.mesh is not None and result.mesh["used"] == 0.0
    assert result.mesh["min_iou"] < 1.0
    assert refused.read_bytes() == full.read_bytes()
    # without a reduction the manifest entry is what it was
    assert "mesh" not in annotate_recording(sim, full, robot, opts).manifest_entry()


def test_config_reaches_the_mesh_reduction_options():
    from omegaconf import OmegaConf

    from roboseg.cli.annotate import options_from_config

    cfg = OmegaConf.load(Path(__file__).parents[1] / "conf" / "annotate.yaml")
    default = options_from_config(cfg)
    assert (default.mesh_reduction, default.mesh_min_iou, default.mesh_check_frames) == (
        0.0, 0.995, 8)
    cfg.mesh.reduction, cfg.mesh.min_iou, cfg.mesh.check_frames = 0.6, 0.99, 3
    asked = options_from_config(cfg)
    assert (asked.mesh_reduction, asked.mesh_min_iou, asked.mesh_check_frames) == (0.6, 0.99, 3)
