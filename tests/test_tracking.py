"""roboseg.tracking: tags (ROI detection, DLT), breathing model, compensated command, simulation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from roboseg.errors import CameraError
from roboseg.tracking.breathing import BreathingModel, fit_breathing, fourier_design
from roboseg.tracking.control import (
    alignment_angular_velocity,
    compensated_linear_velocity,
    geometric_jacobian,
    min_norm_joint_velocities,
)
from roboseg.tracking.simulate import (
    BreathingTruth,
    breathing_scene,
    simulate_compensation,
    tag_corners_image,
    write_breathing_recording,
)
from roboseg.tracking.tags import (
    Roi,
    StereoTagTracker,
    TagStatus,
    TagTracks,
    camera_to_base,
    detect_tags,
    roi_intrinsics,
    stereo_projection_matrices,
    tag_centre,
    triangulate_dlt,
)

LBR = Path("/work/shared/robots/lbr_med7/lbr_med7.urdf")
# ROI around the three default tags in the 1920x1080 breathing scene (left / right images)
ROI_LEFT = Roi(760, 330, 460, 420)
ROI_RIGHT = Roi(600, 330, 460, 420)


# ------------------------------------------------------------------ tags: pure maths


def test_roi_intrinsics_shifts_principal_point() -> None:
    K = np.array([[1000.0, 0, 960.5], [0, 990.0, 540.25], [0, 0, 1]])
    K2 = roi_intrinsics(K, 100, 40)
    assert np.allclose(K2, [[1000, 0, 860.5], [0, 990, 500.25], [0, 0, 1]])
    assert K[0, 2] == 960.5  # input untouched
    assert Roi(-10, 5, 100, 50).clip(60, 40) == Roi(0, 5, 60, 35)
    with pytest.raises(CameraError, match="outside"):
        Roi(100, 100, 10, 10).clip(50, 50)


def test_tag_centre_is_homography_image_of_centre() -> None:
    H = np.array([[40.0, 5.0, 300.0], [-3.0, 35.0, 200.0], [0.02, 0.01, 1.0]])
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)
    img = np.array([(H @ [x, y, 1])[:2] / (H @ [x, y, 1])[2] for x, y in square])
    c = H @ [0, 0, 1.0]
    assert np.allclose(tag_centre(img), c[:2] / c[2], atol=1e-9)
    assert np.linalg.norm(img.mean(axis=0) - c[:2] / c[2]) > 0.5  # corner mean is biased


def test_dlt_triangulation_recovers_points_and_camera_to_base() -> None:
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    T_rl = np.eye(4)
    T_rl[0, 3] = -0.12
    P_l, P_r = stereo_projection_matrices(K, K, T_rl)
    X = np.array([[0.1, -0.05, 1.0], [-0.2, 0.1, 0.8], [0.0, 0.0, 2.5]])
    proj = lambda P: (np.c_[X, np.ones(3)] @ P.T)[:, :2] / (np.c_[X, np.ones(3)] @ P.T)[:, 2:]  # noqa: E731
    assert np.allclose(triangulate_dlt(P_l, P_r, proj(P_l), proj(P_r)), X, atol=1e-9)
    # p_base = T_cam_base^-1 p_cam: rotation 90° about z and translation (1, 2, 3)
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    T[:3, 3] = [1, 2, 3]
    assert np.allclose(camera_to_base(np.array([[1.0, 3.0, 3.0]]), T), [[1.0, 0.0, 0.0]])


# ------------------------------------------------------------------ tags: rendered images


@pytest.fixture(scope="module")
def scene():
    return breathing_scene(seed=3)


def test_detection_in_roi_matches_projected_corners(scene) -> None:
    left, _ = scene.render(0.7)
    det = detect_tags(left, ROI_LEFT)
    assert sorted(det) == [5, 10, 12]
    pos = scene.tag_positions_base(0.7)
    for spec in scene.tags:
        truth = tag_corners_image(
            scene.K_left, scene.T_cam_base, spec.R_base_tag, pos[spec.tag_id], scene.tag_size
        )
        found = det[spec.tag_id] + [ROI_LEFT.tx, ROI_LEFT.ty]
        assert np.max(np.linalg.norm(found - truth, axis=1)) < 0.3  # px
        assert np.linalg.norm(tag_centre(found) - tag_centre(truth)) < 0.05


def test_no_tags_and_one_sided_tags_are_explicit(scene) -> None:
    tracker = StereoTagTracker(scene.K_left, scene.K_right, scene.T_right_left, ROI_LEFT, ROI_RIGHT)
    blank = scene._background.copy()
    empty = tracker.process(0, blank, blank)
    assert empty.observations == {} and empty.triangulated == {}
    left, right = scene.render(0.0, hidden={"right": {12}})
    frame = tracker.process(1, left, right)
    assert frame.observations[12].status is TagStatus.LEFT_ONLY
    assert frame.observations[12].position_cam is None
    assert sorted(frame.triangulated) == [5, 10]
    tracks = TagTracks([empty, frame])
    assert tracks.visibility() == {5: 0.5, 10: 0.5, 12: 0.0}
    stamps, pos = tracks.trajectory(12)
    assert stamps.shape == (0,) and pos.shape == (0, 3)


def test_triangulated_motion_matches_truth_submillimetre(scene) -> None:
    """3 cm tags at ~1 m: triangulated motion vs truth RMS ≤ 0.3 mm (paper: 0.12/0.13/0.27)."""
    tracker = StereoTagTracker(scene.K_left, scene.K_right, scene.T_right_left, ROI_LEFT, ROI_RIGHT)
    errors, base_errors = [], []
    for k, t in enumerate(np.linspace(0.0, 4.0, 16, endpoint=False)):
        left, right = scene.render(t)
        frame = tracker.process(k, left, right)
        truth, truth_base = scene.tag_positions_cam(t), scene.tag_positions_base(t)
        assert sorted(frame.triangulated) == [5, 10, 12]
        for i, p in frame.triangulated.items():
            errors.append(p - truth[i])
            base = camera_to_base(p[None], scene.T_cam_base)[0]
            base_errors.append(base - truth_base[i])
    e = np.asarray(errors)
    depth = np.linalg.norm(list(scene.tag_positions_cam(0.0).values()), axis=1)
    assert depth.min() > 0.9 and depth.max() < 1.1
    motion_rms = np.sqrt(np.mean(np.sum((e - e.mean(axis=0)) ** 2, axis=1)))
    assert motion_rms <= 0.3e-3
    assert np.linalg.norm(e.mean(axis=0)) < 0.5e-3  # no large bias either
    assert np.allclose(np.linalg.norm(base_errors, axis=1), np.linalg.norm(e, axis=1), atol=1e-9)


# ------------------------------------------------------------------ breathing model


def test_fourier_design_columns() -> None:
    X = fourier_design(np.array([0.0, 0.5]), np.pi, 2)
    assert np.allclose(X[0], [1, 1, 0, 1, 0])
    assert np.allclose(X[1], [1, 0, 1, -1, 0], atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fit_recovers_frequency_and_amplitudes_on_noisy_signal(seed: int) -> None:
    rng = np.random.default_rng(seed)
    truth = BreathingTruth(
        omega0=float(rng.uniform(1.0, 2.5)),
        amplitudes=(0.3e-3, -1.3e-3, 4.5e-3),
        harmonics=(1.0, 0.3, 0.1),
        phases=tuple(rng.uniform(-np.pi, np.pi, 3)),
    )
    t = np.sort(rng.uniform(0.0, 15.0, 450))
    z = truth.displacement(t) + rng.normal(0.0, 0.15e-3, (len(t), 3))
    fit = fit_breathing(t, z)
    assert fit.fitted
    assert abs(fit.omega0 / truth.omega0 - 1) < 0.02
    amp = np.abs(truth.amplitudes)
    assert np.all(np.abs(fit.amplitudes()[1:] / amp[1:] - 1) < 0.05)
    assert abs(fit.amplitudes()[0] - amp[0]) < 0.05 * amp[2]  # small ML: 5 % of the largest
    assert np.array_equal(np.sign(fit.signed_amplitudes()), [1, -1, 1])
    # velocity is the derivative of the prediction
    tq = np.array([3.3, 9.1])
    fd = (fit.predict(tq + 1e-5) - fit.predict(tq - 1e-5)) / 2e-5
    assert np.allclose(fit.velocity(tq), fd, rtol=1e-5, atol=1e-9)


def test_fit_prefers_fundamental_over_subharmonic() -> None:
    t = np.linspace(0.0, 15.0, 300)
    fit = fit_breathing(t, 2.0 + np.sin(2.4 * t))
    assert abs(fit.omega0 - 2.4) < 1e-4
    assert np.allclose(fit.amplitudes(), [1.0], atol=1e-4)
    assert np.allclose(fit.predict(t)[:, 0], 2.0 + np.sin(2.4 * t), atol=1e-6)


def test_not_fitted_results() -> None:
    few = fit_breathing(np.arange(10.0), np.zeros(10))
    assert not few.fitted and "samples" in few.reason
    short = fit_breathing(np.linspace(0, 1.0, 50), np.zeros(50))
    assert not short.fitted and "too short" in short.reason
    with pytest.raises(RuntimeError, match="not fitted"):
        short.predict(0.0)


def test_online_model_sliding_window() -> None:
    model = BreathingModel(horizon=15.0, refit_interval=1.0)
    assert model.predict(0.0) is None and model.velocity(0.0) is None
    w0 = 1.3
    for t in np.arange(0.0, 30.0, 0.05):
        model.update(t, np.array([np.cos(w0 * t), 2 * np.sin(w0 * t)]))
        if t < 7.0:
            assert not model.fit.fitted  # window shorter than half the horizon
    assert model.fit.fitted and len(model) <= int(15.0 / 0.05) + 1
    assert model._t[0] >= 30.0 - 0.05 - 15.0
    assert abs(model.fit.omega0 - w0) < 1e-6
    assert np.allclose(model.predict(31.0), [np.cos(w0 * 31), 2 * np.sin(w0 * 31)], atol=1e-6)
    model.update(10.0, np.zeros(2))  # out of order: ignored
    model.update(40.0, np.array([np.nan, 0.0]))  # non-finite: ignored
    assert model._t[-1] < 30.0


# ------------------------------------------------------------------ control


def test_compensated_velocity_hand_computed() -> None:
    R = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # tip frame rotated 90° about base z
    v = compensated_linear_velocity(
        R,
        np.array([0.01, -0.02, 0.5]),
        feed_velocity=-0.001,
        f_desired=15.0,
        f_measured=10.0,
        k=2.0,
        c=1e-4,
        breathing_velocity=0.003,
    )
    # local = [0.02, -0.04, -0.001 - 1e-4 * 5] = [0.02, -0.04, -0.0015]; R local = [0.04, 0.02, ..]
    assert np.allclose(v, [0.04, 0.02, -0.0015 + 0.003])


def test_alignment_angular_velocity() -> None:
    w = alignment_angular_velocity([1, 0, 0], [0, 2, 0], gain=0.5)
    assert np.allclose(w, [0, 0, 0.5 * np.pi / 2])
    assert np.allclose(alignment_angular_velocity([0, 0, 1], [0, 0, 3], 1.0), 0)
    anti = alignment_angular_velocity([0, 0, 1], [0, 0, -1], 1.0)
    assert np.isclose(np.linalg.norm(anti), np.pi) and abs(anti[2]) < 1e-12


def test_min_norm_joint_velocities() -> None:
    J = np.array([[1.0, 0, 0], [0, 1, 1]])
    assert np.allclose(min_norm_joint_velocities(J, np.array([1.0, 2.0])), [1, 1, 1])
    damped = min_norm_joint_velocities(J, np.array([1.0, 2.0]), damping=0.1)
    # Jᵀ (JJᵀ + λ²I)⁻¹ x = [1/1.01, 2/2.01, 2/2.01]
    assert np.allclose(damped, [1 / 1.01, 2 / 2.01, 2 / 2.01])


def _planar_fk(Q: np.ndarray, l1: float = 0.4, l2: float = 0.3) -> np.ndarray:
    T = np.tile(np.eye(4), (len(Q), 1, 1))
    a, b = Q[:, 0], Q[:, 0] + Q[:, 1]
    T[:, 0, 3] = l1 * np.cos(a) + l2 * np.cos(b)
    T[:, 1, 3] = l1 * np.sin(a) + l2 * np.sin(b)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = np.cos(b), -np.sin(b), np.sin(b), np.cos(b)
    return T


def test_geometric_jacobian_planar_arm() -> None:
    q = np.array([0.3, 0.7])
    J = geometric_jacobian(_planar_fk, q)
    s1, s12, c1, c12 = np.sin(0.3), np.sin(1.0), np.cos(0.3), np.cos(1.0)
    expected = np.array(
        [
            [-0.4 * s1 - 0.3 * s12, -0.3 * s12],
            [0.4 * c1 + 0.3 * c12, 0.3 * c12],
            [0, 0],
            [0, 0],
            [0, 0],
            [1, 1],
        ]
    )
    assert np.allclose(J, expected, atol=1e-8)


def _robot_tool_fk(urdf: Path | None):
    import torch

    from roboseg.robot import load_robot

    robot = load_robot(urdf, dtype=torch.float64)
    tip = torch.eye(4, dtype=torch.float64)
    tip[2, 3] = 0.1  # drill tip 10 cm along the flange z axis

    def fk(Q: np.ndarray) -> np.ndarray:
        T = robot.frame_transforms(torch.as_tensor(Q, dtype=torch.float64))[:, -1] @ tip
        return T.numpy()

    return robot, fk


def test_robot_jacobian_predicts_motion() -> None:
    if not LBR.is_file():
        pytest.skip("needs /work/shared/robots/lbr_med7 (KUKA LBR Med 7 URDF)")
    robot, fk = _robot_tool_fk(LBR)
    q = np.array([0.2, 0.5, -0.1, -1.2, 0.1, 0.8, 0.0])
    J = geometric_jacobian(fk, q)
    dq = 1e-4 * np.array([1.0, -2, 0.5, 1, -1, 2, 1])
    T_minus, T_plus = fk((q - dq)[None])[0], fk((q + dq)[None])[0]
    assert np.allclose(J[:3] @ dq, 0.5 * (T_plus[:3, 3] - T_minus[:3, 3]), atol=1e-10)
    twist = np.array([0.01, -0.02, 0.005, 0.0, 0.05, 0.0])
    qd = min_norm_joint_velocities(J, twist)
    assert np.allclose(J @ qd, twist, atol=1e-10)
    # minimum norm: orthogonal to the null space of J (7 dof, 6 constraints)
    null = np.linalg.svd(J)[2][-1]
    assert abs(null @ qd) < 1e-10


# ------------------------------------------------------------------ closed loop


def test_compensation_cuts_relative_tip_motion_point_mass() -> None:
    off = simulate_compensation(False, duration=26.0, seed=4)
    on = simulate_compensation(True, duration=26.0, seed=4)
    assert off.relative_rms_ap > 1.0e-3  # the breathing shows up uncompensated (AP 4.5 mm)
    assert on.relative_rms_ap <= 0.2 * off.relative_rms_ap
    assert on.relative_rms_3d < off.relative_rms_3d
    late = on.t >= on.evaluated_from
    assert abs(on.forces[late].mean() - 15.0) < 1.5  # force regulated near f_d


def test_compensation_through_robot_jacobian() -> None:
    if not LBR.is_file():
        pytest.skip("needs /work/shared/robots/lbr_med7 (KUKA LBR Med 7 URDF)")
    _, fk = _robot_tool_fk(LBR)
    q0 = np.array([0.0, 0.6, 0.0, -1.3, 0.0, -0.9, 0.0])  # tool pointing roughly along -z
    kw = dict(duration=24.0, dt=0.02, seed=5, robot_fk=fk, q0=q0)
    off = simulate_compensation(False, **kw)
    on = simulate_compensation(True, **kw)
    assert on.relative_rms_ap <= 0.2 * off.relative_rms_ap


# ------------------------------------------------------------------ recording + command


def test_track_command_on_breathing_recording(tmp_path: Path) -> None:
    from omegaconf import OmegaConf

    from roboseg.cli.track import run
    from roboseg.recording import RecordingReader

    rec = write_breathing_recording(tmp_path / "b.mcap", seed=2, frames=44, fps=4.0)
    truth = RecordingReader(rec).metadata()["roboseg_truth"]
    cfg = OmegaConf.load(Path(__file__).parents[1] / "conf" / "track.yaml")
    cfg.recording, cfg.out = str(rec), str(tmp_path / "out")
    cfg.roi.left, cfg.roi.right = [760, 330, 460, 420], [600, 330, 460, 420]
    cfg.breathing.reference_tag = 10
    out = run(cfg)
    result = yaml.safe_load((out / "breathing.yaml").read_text())
    assert result["fitted"] and result["reference_tag"] == 10
    assert abs(result["omega0"] / float(truth["omega0"]) - 1) < 0.02
    for axis in ("CC", "AP"):
        want = float(truth[f"amplitude_{axis}_mm"])
        assert abs(result["amplitudes_mm"][axis] - want) < 0.05 * abs(want) + 0.05
    want_visibility = float(truth["visibility_tag_12"])
    assert result["tags"][12]["visibility"] == pytest.approx(want_visibility, abs=1e-4)
    rows = (out / "tags.csv").read_text().splitlines()
    assert len(rows) == 1 + 44 * 3
    assert any(",12,left_only,,,," in r for r in rows)
    assert "nan" not in "".join(rows).lower()
    assert (out / "breathing.png").stat().st_size > 10_000
