"""The draped operating-room simulator: maths pieces against hand values, then whole recordings."""

from __future__ import annotations

import importlib.util
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from hydra import compose, initialize_config_dir

from roboseg.cli.simulate import run
from roboseg.config import CONF_DIR
from roboseg.errors import RobosegError, RobotModelError
from roboseg.recording.reader import RecordingReader
from roboseg.render.raster import rasterize, render_hard
from roboseg.robot import load_robot
from roboseg.sim import SIM_METADATA, SimConfig, SimSummary, simulate_recording
from roboseg.sim.drape import (
    Drape,
    DrapeParams,
    drape_offsets,
    laplacian_smooth,
    neighbour_average_matrix,
    sample_drape_params,
)
from roboseg.sim.frame import Surface, ViewLight, composite_view
from roboseg.sim.lighting import drift, sample_lighting
from roboseg.sim.occluders import Capsule, catmull_rom, draw_capsules, sample_walkers
from roboseg.sim.scene import box_pixels, ray_box, ray_ellipsoid
from roboseg.sim.shading import (
    barycentric,
    blinn_phong,
    pixel_rays,
    srgb_encode,
    vertex_normals,
    view_opacity,
)
from roboseg.sim.simulate import (
    T0_NS,
    frame_stamps,
    front_faces,
    is_closed,
    protocol_trajectory,
    site_draws,
    undraped_count,
    yaw_transform,
)
from roboseg.sim.trajectory import min_jerk, random_joint_trajectory, waypoint_box

K_SMALL = np.array([[100.0, 0.0, 79.5], [0.0, 100.0, 47.5], [0.0, 0.0, 1.0]])


# --- trajectories -------------------------------------------------------------------------------


def test_min_jerk_hand_values():
    s = np.array([0.0, 0.5, 1.0, 0.25])
    # 10s³ − 15s⁴ + 6s⁵ at 1/4: 10/64 − 15/256 + 6/1024 = 0.103515625
    np.testing.assert_allclose(min_jerk(s), [0.0, 0.5, 1.0, 0.103515625])


def test_trajectory_within_limits_smooth_with_pauses():
    lower = np.array([-2.9, -2.0, -0.5, 0.0])
    upper = np.array([2.9, 2.0, 0.5, 0.1])
    q = random_joint_trajectory(lower, upper, 400, 15.0, np.random.default_rng(3))
    assert q.shape == (400, 4)
    assert np.all(q >= lower) and np.all(q <= upper)
    lo, hi = waypoint_box(lower, upper, 0.7)
    assert np.all(q >= lo - 1e-12) and np.all(q <= hi + 1e-12)
    step = np.abs(np.diff(q, axis=0))
    # a min-jerk move of ≥ 1.5 s (22 frames) peaks at 1.875 × mean speed
    assert np.all(step <= 1.875 * (hi - lo) / 22 + 1e-9)
    still = np.all(step == 0.0, axis=1)
    assert still.sum() >= 5  # pauses exist
    assert (~still).sum() >= 200  # and it mostly moves
    again = random_joint_trajectory(lower, upper, 400, 15.0, np.random.default_rng(3))
    np.testing.assert_array_equal(q, again)


def test_trajectory_rejects_inverted_limits():
    with pytest.raises(RobotModelError, match="joint 1"):
        waypoint_box(np.array([0.0, 1.0]), np.array([1.0, 0.0]))


# --- shading ------------------------------------------------------------------------------------


def test_vertex_normals_of_a_cube_point_outwards():
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    v = torch.tensor(box.vertices, dtype=torch.float32)
    n = vertex_normals(v, torch.tensor(box.faces))
    torch.testing.assert_close(n.norm(dim=1), torch.ones(8))
    # every corner's normal points outwards, into the corner's own octant
    assert torch.equal(torch.sign(n), torch.sign(v))
    # a flat quad: both triangles' normals are +z
    quad = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    nq = vertex_normals(quad, torch.tensor([[0, 1, 2], [0, 2, 3]]))
    torch.testing.assert_close(nq, torch.tensor([[0.0, 0.0, 1.0]]).expand(4, 3))


def test_barycentric_on_a_fronto_parallel_triangle():
    # triangle at z = 2 with vertices (0,0), (1,0), (0,1); ray to (0.25, 0.5, 2)
    verts = torch.tensor([[0.0, 0.0, 2.0], [1.0, 0.0, 2.0], [0.0, 1.0, 2.0]])
    faces = torch.tensor([[0, 1, 2]])
    rays = torch.tensor([[0.125, 0.25, 1.0]])
    bary = barycentric(rays, verts, faces, torch.tensor([0]))
    torch.testing.assert_close(bary, torch.tensor([[0.25, 0.25, 0.5]]))


def test_pixel_rays_hit_pixel_centres():
    K = torch.tensor(K_SMALL)
    rays = pixel_rays(K, 96, 160)
    assert rays.shape == (96, 160, 3)
    torch.testing.assert_close(rays[47, 79], torch.tensor([-0.005, -0.005, 1.0], dtype=K.dtype))
    torch.testing.assert_close(rays[0, 0], torch.tensor([-0.795, -0.475, 1.0], dtype=K.dtype))


def test_blinn_phong_hand_values():
    n = torch.tensor([[0.0, 0.0, -1.0]])  # facing the camera
    view = torch.tensor([[0.0, 0.0, -1.0]])
    light = torch.tensor([0.0, -0.6, -0.8])
    albedo = torch.tensor([[0.5, 0.5, 0.5]])
    out = blinn_phong(n, view, light, albedo, ambient=0.2, diffuse=0.8, specular=1.0, shininess=2)
    # n·l = 0.8; h = (0, −0.6, −1.8)/|·| → n·h = 1.8/√3.6; spec = 3.24/3.6 = 0.9
    expected = 0.5 * (0.2 + 0.8 * 0.8) + 0.9
    torch.testing.assert_close(out, torch.full((1, 3), expected))
    flipped = blinn_phong(
        -n, view, light, albedo, ambient=0.2, diffuse=0.8, specular=1.0, shininess=2
    )
    torch.testing.assert_close(flipped, out)  # back faces are lit like front faces


def test_view_opacity_grows_at_grazing_angles():
    a = torch.tensor([0.5, 0.5])
    out = view_opacity(a, torch.tensor([1.0, 0.5]))
    torch.testing.assert_close(out, torch.tensor([0.5, 0.75]))


def test_srgb_encode_known_points():
    np.testing.assert_allclose(
        srgb_encode(np.array([0.0, 1.0, 0.002, 0.5])), [0.0, 1.0, 0.02584, 0.735357], atol=1e-5
    )


# --- drape --------------------------------------------------------------------------------------


def _params(**kw) -> DrapeParams:
    base = dict(
        kind="white",
        offset=0.04,
        wrinkle=0.0,
        sag=0.0,
        alpha=0.8,
        tint=(0.9, 0.9, 0.9),
        specular=0.3,
        shininess=30.0,
        smooth_steps=0,
    )
    base.update(kw)
    return DrapeParams(**base)


def test_drape_offsets_push_out_and_pull_down():
    normals = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    zeros = torch.zeros(3)
    down = torch.tensor([0.0, 0.0, -1.0])
    d = drape_offsets(normals, zeros, zeros, down, _params(sag=0.1))
    # side vertex: 4 cm out; bottom vertex: 4 cm out + 0.1·1²·0.6 = 6 cm more down; top: 4 cm up
    torch.testing.assert_close(d, torch.tensor([[0.04, 0, 0], [0, 0, -0.10], [0, 0, 0.04]]))
    d = drape_offsets(normals, torch.tensor([1.0, 0, 0]), zeros, down, _params(wrinkle=0.01))
    assert d[0, 0].item() == pytest.approx(0.05)


def test_neighbour_average_and_smoothing():
    faces = torch.tensor([[0, 1, 2]])
    avg = neighbour_average_matrix(faces, 4).to_dense()
    assert torch.allclose(avg.sum(1), torch.ones(4))
    assert avg[3, 3] == 1.0 and avg[0, 1] == pytest.approx(1 / 3)
    x = torch.tensor([[3.0], [0.0], [0.0], [7.0]])
    out = laplacian_smooth(x, avg.to_sparse(), steps=1, lam=0.5)
    torch.testing.assert_close(out, torch.tensor([[2.0], [0.5], [0.5], [7.0]]))


def test_drape_is_larger_than_the_robot_and_hangs():
    mesh = trimesh.creation.cylinder(radius=0.06, height=0.4, sections=24).subdivide().subdivide()
    mesh.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [1, 0, 0]))
    v = torch.tensor(mesh.vertices, dtype=torch.float32)  # horizontal link along y
    rng = np.random.default_rng(0)
    params = sample_drape_params(rng)
    assert 0.5 <= params.alpha <= 0.9 and params.kind in ("clear", "white", "blue")
    drape = Drape.around(v, torch.zeros(len(v), dtype=torch.long), params, rng)
    assert drape.rest.shape[0] > 100  # the hull is remeshed into small triangles
    T = torch.eye(4)[None]
    out = drape.pose(T)
    # the cloth lies outside the link (radius 6 cm, ends at y = ±0.2 m) by centimetres
    radial = out[:, [0, 2]].norm(dim=1)
    side = out[:, 1].abs() < 0.15
    assert side.sum() > 50 and radial[side].min() > 0.06 + 0.02
    assert out[:, 1].abs().max() > 0.2 + 0.02
    assert out[:, 2].min() < v[:, 2].min() - 0.05  # folds hang below the link
    # the cloth is attached to the link: moving the link moves it rigidly (sag aside)
    shifted = drape.pose(
        torch.tensor([[[1.0, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]])
    )
    torch.testing.assert_close(
        shifted - out, torch.tensor([0.5, 0.0, 0.0]).expand_as(out), atol=1e-5, rtol=0
    )
    lifted = drape.pose(T, floor_z=-0.08)
    assert lifted[:, 2].min() >= -0.08 - 1e-6


# --- scene and occluders ------------------------------------------------------------------------


def test_ray_box_and_ellipsoid_hits():
    origin = np.array([0.0, 0.0, 5.0])
    dirs = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    t, n = ray_box(origin, dirs, np.array([-1.0, -1.0, 0.0]), np.array([1.0, 1.0, 1.0]))
    assert t[0] == pytest.approx(4.0) and math.isinf(t[1])
    np.testing.assert_allclose(n[0], [0, 0, 1])
    t, n = ray_ellipsoid(origin, dirs, np.zeros(3), np.array([1.0, 2.0, 0.5]))
    assert t[0] == pytest.approx(4.5) and math.isinf(t[1])
    np.testing.assert_allclose(n[0], [0, 0, 1], atol=1e-12)


def test_catmull_rom_passes_through_control_points():
    ctrl = np.array([[0.0, 0, 0], [1, 1, 0], [2, 0, 0], [3, 1, 1]])
    pts = catmull_rom(ctrl, 5)
    np.testing.assert_allclose(pts[::5], ctrl)


def test_draw_capsules_width_depth_and_order():
    T = np.eye(4)
    far = Capsule(np.array([-0.5, 0.0, 2.0]), np.array([0.5, 0.0, 2.0]), 0.05, (1.0, 0.0, 0.0))
    near = Capsule(np.array([0.0, -0.5, 1.0]), np.array([0.0, 0.5, 1.0]), 0.02, (0.0, 0.0, 1.0))
    rgb, depth, alpha = draw_capsules([near, far], K_SMALL, T, 96, 160)
    # far: horizontal line at v = 47.5, 2·100·0.05/2 = 5 px thick, depth 2
    assert depth[47, 60] == pytest.approx(2.0) and alpha[47, 60] == 1.0
    column = np.isfinite(depth[:, 60])
    assert 4 <= column.sum() <= 6
    # near (drawn last) wins where they cross
    assert depth[47, 79] == pytest.approx(1.0) and rgb[47, 79, 2] > 0.5
    assert np.isinf(depth[5, 5])


# --- whole recordings ---------------------------------------------------------------------------

LBR = Path(__file__).resolve().parents[2] / "shared" / "robots" / "lbr_med7" / "lbr_med7.urdf"
TINY = dict(width=160, height=96)
MASKS = ["left/robot_mask_gt", "right/robot_mask_gt"]


def _frames(path: Path) -> list:
    with RecordingReader(path, mask_topics=MASKS) as reader:
        return list(reader.frames())


@pytest.fixture(scope="module")
def one_robot(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, SimSummary]:
    path = tmp_path_factory.mktemp("sim") / "one.mcap"
    summary = simulate_recording(SimConfig(frames=5, seed=7, **TINY), path)
    return path, summary


def test_recording_has_every_topic_and_frame(one_robot):
    path, summary = one_robot
    assert summary.frames == 5 and summary.undraped_frames == 2
    with RecordingReader(path, mask_topics=MASKS) as reader:
        topics = reader.topics()
        for topic in (
            "/camera/left/image_raw/compressed",
            "/camera/right/image_raw/compressed",
            "/camera/left/camera_info",
            "/camera/right/camera_info",
            "/robot_0/joint_states",
            "/tf_static",
            "/camera/left/robot_mask_gt/compressed",
            "/camera/right/robot_mask_gt/compressed",
        ):
            assert topic in topics, topic
        meta = reader.metadata()[SIM_METADATA]
        frames = list(reader.frames())
        tf = reader.tf_static()
    assert len(frames) == 5
    assert int(meta["drape_start_stamp_ns"]) == frames[2].stamp_ns == summary.drape_start_stamp_ns
    assert frames[0].left.shape == (96, 160, 3)
    assert frames[0].left_frame_id == "camera_left_optical_frame"
    assert ("camera_left_optical_frame", "robot_0/link_0") in tf
    T_lr = tf[("camera_left_optical_frame", "camera_right_optical_frame")]
    np.testing.assert_allclose(T_lr[:3, 3], [0.12, 0.0, 0.0], atol=1e-9)  # right is at +x
    assert all(f.masks["left/robot_mask_gt"].any() for f in frames)  # the robot is in view


def test_gt_mask_is_a_fresh_render_from_fk_and_calibration(one_robot):
    path, _ = one_robot
    robot = load_robot()
    with RecordingReader(path, mask_topics=MASKS) as reader:
        K, width, height, _ = reader.camera_info("left")
        T_left_base = reader.lookup("camera_left_optical_frame", "robot_0/link_0")
        T_right_left = np.linalg.inv(
            reader.lookup("camera_left_optical_frame", "camera_right_optical_frame")
        )
        frames = list(reader.frames())
    for f in frames:
        q = robot.joints_from_names(f.joint_names["robot_0"], f.joints["robot_0"])
        v = robot.posed_vertices(q)
        for T, name in ((T_left_base, "left"), (T_right_left @ T_left_base, "right")):
            Tt = torch.as_tensor(T, dtype=torch.float32)
            mask = render_hard(
                v @ Tt[:3, :3].T + Tt[:3, 3],
                robot.faces,
                torch.as_tensor(K, dtype=torch.float32),
                height,
                width,
            )[0]
            np.testing.assert_array_equal(f.masks[f"{name}/robot_mask_gt"], mask.numpy())


def test_draped_frames_differ_from_undraped(one_robot):
    path, _ = one_robot
    frames = _frames(path)
    # frame 2 replays frame 0's joints under the drape: same label, different pixels
    np.testing.assert_allclose(frames[2].joints["robot_0"], frames[0].joints["robot_0"])
    m = frames[0].masks["left/robot_mask_gt"]
    np.testing.assert_array_equal(frames[2].masks["left/robot_mask_gt"], m)
    diff = np.abs(frames[2].left.astype(int) - frames[0].left.astype(int)).sum(-1)
    assert diff[m].mean() > 3 * diff[~m].mean() + 5


def test_same_seed_gives_identical_images(one_robot, tmp_path):
    path, _ = one_robot
    again = tmp_path / "again.mcap"
    simulate_recording(SimConfig(frames=5, seed=7, **TINY), again)
    with (
        RecordingReader(path, mask_topics=MASKS) as a,
        RecordingReader(again, mask_topics=MASKS) as b,
    ):
        for fa, fb in zip(a.frames(decode=False), b.frames(decode=False), strict=True):
            assert fa.left.tobytes() == fb.left.tobytes()
            assert fa.right.tobytes() == fb.right.tobytes()
    other = tmp_path / "other.mcap"
    simulate_recording(SimConfig(frames=1, seed=8, **TINY), other)
    assert _frames(other)[0].left.tobytes() != _frames(path)[0].left.tobytes()


def test_walkers_cross_the_line_of_sight_within_their_window():
    eye, target = np.array([2.0, 1.0, 1.2]), np.array([0.0, 0.0, 0.5])
    walkers = sample_walkers(np.random.default_rng(0), eye, target, -0.8, 20, (1.0, 3.0))
    view = (target - eye)[:2] / np.linalg.norm((target - eye)[:2])
    for w in walkers:
        assert 1.0 <= w.t_cross <= 3.0 and 0.8 <= w.speed <= 1.4
        at = w.position(w.t_cross)
        assert at[2] == -0.8  # on the floor
        off = at[:2] - eye[:2]
        assert abs(off[0] * view[1] - off[1] * view[0]) < 1e-9  # on the line of sight
        assert abs(float(w.direction[:2] @ view)) <= math.sin(0.6) + 1e-9  # across it
        # walking pace: 1 s later the person is `speed` m farther along the path
        assert np.linalg.norm(w.position(w.t_cross + 1.0) - at) == pytest.approx(w.speed)
        cap = w.capsules(w.t_cross)[-1]  # a person ~1.75 m tall, the cap on top
        assert cap.colour == w.cap and cap.p0[2] == pytest.approx(at[2] + 1.65)
    fractions = [np.linalg.norm(w.cross[:2] - eye[:2]) / np.linalg.norm((target - eye)[:2])
                 for w in walkers]
    assert min(fractions) < 1.0 < max(fractions)  # in front of the robot and behind it


def test_walkers_change_the_undraped_images_only(one_robot, tmp_path):
    path, _ = one_robot
    walked = tmp_path / "walked.mcap"
    simulate_recording(SimConfig(frames=5, seed=7, walkers=2, **TINY), walked)
    plain, busy = _frames(path), _frames(walked)
    for a, b in zip(plain, busy, strict=True):  # robots, joints and labels are the same
        np.testing.assert_array_equal(a.joints["robot_0"], b.joints["robot_0"])
        np.testing.assert_array_equal(a.masks["left/robot_mask_gt"],
                                      b.masks["left/robot_mask_gt"])
    changed = (plain[0].left.astype(int) - busy[0].left.astype(int)).any(-1)
    assert changed.mean() > 0.01  # someone walks through the undraped view


def test_worker_processes_write_the_same_bytes(one_robot, tmp_path):
    path, summary = one_robot
    assert 0.0 < summary.setup_seconds < summary.seconds
    pooled = tmp_path / "pooled.mcap"
    simulate_recording(SimConfig(frames=5, seed=7, workers=2, **TINY), pooled)
    assert pooled.read_bytes() == path.read_bytes()


def test_to_uint8_matches_the_numpy_pipeline():
    from roboseg.sim.shading import srgb_lut, to_uint8

    rng = np.random.default_rng(4)
    linear = rng.uniform(-0.1, 1.3, (12, 10, 3)).astype(np.float32)
    noise = rng.standard_normal((12, 10, 3), dtype=np.float32)
    wb = np.array([1.1, 1.0, 0.9])
    expected = srgb_lut(np.clip(linear * (1.2 * wb.astype(np.float32)), 0.0, 1.0))
    np.testing.assert_array_equal(
        to_uint8(linear, 1.2, wb), np.clip(np.rint(expected), 0, 255).astype(np.uint8)
    )
    noisy = expected + np.float32(2.5) * noise
    np.testing.assert_array_equal(
        to_uint8(linear, 1.2, wb, 2.5, noise), np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
    )


def test_two_robots(tmp_path):
    path = tmp_path / "two.mcap"
    simulate_recording(SimConfig(frames=2, seed=3, robots=2, **TINY), path)
    with RecordingReader(path, mask_topics=MASKS) as reader:
        assert reader.robots == ["robot_0", "robot_1"]
        tf = reader.tf_static()
        frames = list(reader.frames())
    T0 = tf[("camera_left_optical_frame", "robot_0/link_0")]
    T1 = tf[("camera_left_optical_frame", "robot_1/link_0")]
    assert 1.0 < np.linalg.norm(T0[:3, 3] - T1[:3, 3]) < 1.6  # bases across the table
    assert len(frames) == 2 and set(frames[0].joints) == {"robot_0", "robot_1"}


@pytest.mark.lbr
def test_real_robot_model(tmp_path):
    if not LBR.is_file():
        pytest.skip(f"{LBR} is absent (../shared/robots/lbr_med7)")
    path = tmp_path / "lbr.mcap"
    simulate_recording(SimConfig(frames=2, seed=1, urdf=str(LBR), **TINY), path)
    frames = _frames(path)
    assert frames[0].joint_names["robot_0"] == [f"A{i}" for i in range(1, 8)]
    assert frames[1].masks["left/robot_mask_gt"].any()


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "roboseg.cli.simulate", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_cli_writes_a_recording(tmp_path):
    proc = _cli(
        f"out={tmp_path / 'rec'}",
        "frames=2",
        "seed=4",
        "camera.width=96",
        "camera.height=64",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    path = tmp_path / "rec" / "sim_4.mcap"
    assert proc.stdout.strip().endswith(str(path)) and path.is_file()


def test_cli_nonexistent_urdf_is_one_line(tmp_path):
    proc = _cli(f"out={tmp_path}", "robot.urdf=/nonexistent/robot.urdf", cwd=tmp_path)
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ")
    assert "/nonexistent/robot.urdf" in lines[0]
    assert not list(tmp_path.glob("*.mcap"))


@pytest.mark.parametrize(
    ("override", "needle"),
    [
        ("frames=0", "frames"),
        ("robots=3", "robots"),
        ("scenario=party", "scenario"),
        ("camera.width=abc", "camera.width"),
        ("walkers=-1", "walkers"),
    ],
)
def test_cli_bad_values_exit_1_with_one_line(tmp_path, capsys, override, needle):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("simulate", overrides=[f"out={tmp_path}", override])
    with pytest.raises(SystemExit) as exc:
        run(cfg)
    assert exc.value.code == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0]
    assert not list(tmp_path.glob("*.mcap"))


# --- frame compositing and recording helpers ----------------------------------------------------


def _surface(z: float, albedo: tuple[float, float, float], K: torch.Tensor) -> Surface:
    """A fronto-parallel triangle at depth ``z`` covering the image centre, not the corners."""
    verts = torch.tensor([[-0.6, -0.6, z], [0.6, -0.6, z], [0.0, 0.6, z]])
    faces = torch.tensor([[0, 1, 2]])
    r = rasterize(verts[None], faces, K, 13, 17)
    normals = torch.tensor([[0.0, 0.0, -1.0]]).expand(3, 3)
    return Surface(
        verts, normals, faces, torch.tensor(albedo).expand(3, 3), r.depth[0], r.face_id[0]
    )


def test_composite_view_layers_by_hand():
    K = torch.tensor([[10.0, 0.0, 8.0], [0.0, 10.0, 6.0], [0.0, 0.0, 1.0]])
    static_rgb = np.full((13, 17, 3), 0.1, np.float32)
    static_depth = np.full((13, 17), 3.0, np.float32)
    robot = _surface(2.0, (0.8, 0.8, 0.8), K)
    drape = _surface(1.5, (0.2, 0.4, 0.6), K)
    params = _params(alpha=0.6, tint=(0.2, 0.4, 0.6), specular=0.0)
    occ_rgb = np.zeros((13, 17, 3), np.float32)
    occ_depth = np.full((13, 17), np.inf, np.float32)
    occ_alpha = np.zeros((13, 17), np.float32)
    occ_rgb[6, 9], occ_depth[6, 9], occ_alpha[6, 9] = (1.0, 0.0, 0.0), 1.0, 1.0
    # light from behind the surfaces: no diffuse and no highlight, ambient only
    light = ViewLight(torch.tensor([0.0, 0.0, 1.0]), intensity=0.5, ambient=1.0)
    rays = pixel_rays(K, 13, 17)
    out = composite_view(
        static_rgb, static_depth, robot, None, None, (occ_rgb, occ_depth, occ_alpha), rays, light
    )
    # ambient-only light: robot = albedo × intensity; the occluder pixel is its colour × 0.5
    np.testing.assert_allclose(out[6, 8], [0.4, 0.4, 0.4], rtol=1e-5)
    np.testing.assert_allclose(out[6, 9], [0.5, 0.0, 0.0], rtol=1e-5)
    out = composite_view(
        static_rgb, static_depth, robot, drape, params, (occ_rgb, occ_depth, occ_alpha), rays, light
    )
    # centre ray is normal to the drape: opacity = α; behind it the robot tinted 0.55 + 0.45·tint
    tint = np.array([0.2, 0.4, 0.6])
    expected = 0.6 * tint * 0.5 + 0.4 * 0.4 * (0.55 + 0.45 * tint)
    np.testing.assert_allclose(out[6, 8], expected, rtol=1e-5)
    np.testing.assert_allclose(out[0, 0], [0.05, 0.05, 0.05], rtol=1e-5)  # static × intensity


def test_recording_helpers():
    assert undraped_count(1, 0.35) == 0 and undraped_count(2, 0.0) == 1
    assert undraped_count(10, 0.35) == 4 and undraped_count(10, 0.99) == 9
    stamps = frame_stamps(4, 15.0)
    assert stamps[0] == T0_NS and stamps[3] - stamps[0] == 200_000_000
    lower, upper = np.array([-1.0, -2.0]), np.array([1.0, 2.0])
    q = protocol_trajectory(lower, upper, 25, 10, 15.0, np.random.default_rng(0))
    assert q.shape == (25, 2)
    np.testing.assert_array_equal(q[10:20], q[:10])  # draped phase replays the undraped one
    assert np.all(q >= lower) and np.all(q <= upper)
    T = yaw_transform(1.0, 2.0, math.pi / 2)
    np.testing.assert_allclose(T @ [1.0, 0.0, 0.0, 1.0], [1.0, 3.0, 0.0, 1.0], atol=1e-12)


def test_lighting_drifts_slowly_within_bounds():
    np.testing.assert_allclose(
        drift(1.0, np.array([0.1, 0.2]), np.array([math.pi / 2, 0.0]), np.zeros(2)), 1.1
    )
    light = sample_lighting(np.random.default_rng(5), 20.0)
    states = [light.at(t) for t in np.arange(0.0, 20.0, 1 / 15)]
    expo = np.array([s.exposure for s in states])
    assert np.all(np.abs(expo / light.exposure - 1.0) <= 0.15 + 1e-9)
    assert np.abs(np.diff(expo)).max() < 0.02 * light.exposure  # smooth frame to frame
    for s in states[::50]:
        assert s.light_dir[2] > 0 and np.linalg.norm(s.light_dir) == pytest.approx(1.0)


def test_box_pixels_bounds_the_projection():
    K = np.array([[100.0, 0.0, 50.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]])
    m = box_pixels(np.array([-0.1, -0.1, 1.9]), np.array([0.1, 0.1, 2.1]), K, np.eye(4), 80, 100)
    rows, cols = np.nonzero(m)
    # corners at z = 1.9 project to 50 ± 100·0.1/1.9 = 50 ± 5.26
    assert (cols.min(), cols.max(), rows.min(), rows.max()) == (44, 56, 34, 46)
    behind = box_pixels(np.array([-1.0, -1, -1]), np.array([1.0, 1, 1]), K, np.eye(4), 80, 100)
    assert behind.all()


def test_face_culling_only_for_closed_outward_meshes():
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    link = np.zeros(8, dtype=np.int64)
    assert is_closed(box.vertices, box.faces, link)
    assert not is_closed(box.vertices, box.faces[1:], link)  # a hole
    assert not is_closed(box.vertices, box.faces[:, ::-1], link)  # inward normals
    v = torch.tensor(box.vertices, dtype=torch.float32)
    f = torch.tensor(box.faces)
    front = front_faces(v, f, torch.tensor([[0.0, 0.0, 5.0]]))
    # seen from +z only the two triangles of the top face point at the camera
    assert front.sum() == 2
    assert torch.all(v[f[front]][..., 2] == 0.5)
    both = front_faces(v, f, torch.tensor([[0.0, 0.0, 5.0], [5.0, 0.0, 0.0]]))
    assert both.sum() == 4


def test_trivial_baseline_of_the_difficulty_bench():
    spec = importlib.util.spec_from_file_location(
        "bench_data", Path(__file__).resolve().parents[1] / "bench" / "data.py"
    )
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    assert bench.iou(np.array([1, 1, 0, 0], bool), np.array([1, 0, 1, 0], bool)) == 1 / 3
    assert bench.iou(np.zeros(3, bool), np.zeros(3, bool)) == 1.0
    # a white "robot" on a blue background is found exactly; under a blue "drape" it is lost
    images = np.zeros((2, 8, 8, 3), np.uint8)
    images[:] = (30, 60, 160)
    masks = np.zeros((2, 8, 8), bool)
    masks[:, 2:6, 3:5] = True
    images[masks] = (230, 230, 225)
    v, s, score = bench.tune_baseline(images, masks)
    assert score == 1.0
    draped = images.copy()
    draped[masks] = (60, 90, 190)
    value, sat = bench.value_saturation(draped)
    assert bench.iou(bench.threshold_baseline(value, sat, v, s), masks) == 0.0


def test_sessions_of_a_site_share_room_side_and_drape_kind(tmp_path):
    """A site fixes the drape kind and the side of the table the camera stands on; sessions
    (seeds) place the camera within ``site_azimuth_deg`` of that side."""
    draws = site_draws(4)
    kinds, azimuths = set(), []
    for seed in range(3):
        path = tmp_path / f"s{seed}.mcap"
        cfg = SimConfig(frames=1, seed=seed, site=4, site_azimuth_deg=20.0, distance=(2.0, 2.5),
                        **TINY)
        summary = simulate_recording(cfg, path)
        kinds.add(tuple(summary.drape_kinds))
        with RecordingReader(path, mask_topics=MASKS) as reader:
            assert reader.metadata()[SIM_METADATA]["site"] == "4"
            T = next(T for (p, c), T in reader.tf_static().items() if c.startswith("robot_0/"))
        eye = np.linalg.inv(T)[:3, 3]  # camera centre in the base frame of robot 0
        azimuths.append(math.atan2(eye[1] - 0.0, eye[0] - 0.1))
    assert len(kinds) == 1
    # a two-robot session of a site drapes both robots as its one-robot sessions (site 1: a
    # second draw from the site's drape stream would be another kind)
    one, two = (
        simulate_recording(
            SimConfig(frames=1, seed=9, site=1, robots=n, distance=(2.0, 2.5), **TINY),
            tmp_path / f"site1_{n}.mcap",
        ).drape_kinds
        for n in (1, 2)
    )
    assert two == one * 2
    for az in azimuths:  # target jitter of a few cm moves the azimuth by a few degrees
        off = math.degrees(math.remainder(az - draws.azimuth, 2 * math.pi))
        assert abs(off) <= 20.0 + 8.0
    assert len({round(a, 3) for a in azimuths}) == 3  # placements differ
    assert site_draws(4).azimuth == draws.azimuth != site_draws(5).azimuth
    with pytest.raises(RobosegError, match="site_azimuth_deg"):
        SimConfig(site=1, site_azimuth_deg=200.0).validate()
