"""Registration: 9D pose maths, the paper's costs (hand-computed), CSO and SDR on synthetic data."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from roboseg.registration.losses import (
    RegistrationTarget,
    distance_mse_loss,
    exp_dice_loss,
    inside_distance,
    iou,
    outside_distance,
)
from roboseg.registration.pose import (
    gram_schmidt,
    invert_transform,
    look_at_T_cam_base,
    matrix_to_pose9d,
    pose9d_to_matrix,
    rotation_angle,
    transform_points,
)

# --------------------------------------------------------------------------------------------
# pose


def test_gram_schmidt_hand_computed() -> None:
    # a1 = (1, 1, 0), a2 = (0, 1, 0): b1 = (1, 1, 0)/√2, b2 = (−1, 1, 0)/√2, b3 = (0, 0, 1)
    R = gram_schmidt(torch.tensor([1.0, 1.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]))
    s = 1 / math.sqrt(2)
    expected = torch.tensor([[s, -s, 0.0], [s, s, 0.0], [0.0, 0.0, 1.0]])
    torch.testing.assert_close(R, expected)


def test_pose9d_identity_and_scaling_invariance() -> None:
    p = torch.tensor([2.0, 0.0, 0.0, 1.0, 3.0, 0.0, 0.1, -0.2, 1.5])
    T = pose9d_to_matrix(p)
    expected = torch.eye(4)
    expected[:3, 3] = torch.tensor([0.1, -0.2, 1.5])
    torch.testing.assert_close(T, expected)


def test_pose9d_round_trip_and_so3() -> None:
    g = torch.Generator().manual_seed(0)
    p = torch.randn(16, 9, generator=g, dtype=torch.float64)
    T = pose9d_to_matrix(p)
    R = T[:, :3, :3]
    eye = torch.eye(3, dtype=torch.float64).expand(16, 3, 3)
    torch.testing.assert_close(R @ R.transpose(1, 2), eye)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(16, dtype=torch.float64))
    torch.testing.assert_close(pose9d_to_matrix(matrix_to_pose9d(T)), T)


def test_pose9d_is_differentiable() -> None:
    p = torch.tensor([1.0, 0.1, 0.0, 0.0, 1.0, 0.2, 0.0, 0.0, 1.0], requires_grad=True)
    pts = torch.tensor([[0.1, 0.2, 0.3]])
    transform_points(pose9d_to_matrix(p), pts).sum().backward()
    assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0


def test_invert_and_transform_points() -> None:
    T = pose9d_to_matrix(torch.tensor([0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 1.0, 2.0, 3.0]))
    # R: x → y, y → −x (90° about z); p = (1, 0, 0) → R p + t = (0, 1, 0) + (1, 2, 3)
    out = transform_points(T, torch.tensor([[1.0, 0.0, 0.0]]))
    torch.testing.assert_close(out, torch.tensor([[1.0, 3.0, 3.0]]))
    torch.testing.assert_close(invert_transform(T) @ T, torch.eye(4))


def test_look_at_hand_computed() -> None:
    # camera at (2, 0, 0) looking at the origin, z up: base origin is 2 m straight ahead,
    # the base +z point appears above the centre (−y), the base +y point to the right (+x).
    T = look_at_T_cam_base(torch.tensor([2.0, 0, 0]), torch.zeros(3), torch.tensor(0.0))
    pts = torch.tensor([[0.0, 0, 0], [0, 0, 1], [0, 1, 0]])
    expected = torch.tensor([[0.0, 0, 2], [0, -1, 2], [1, 0, 2]])
    torch.testing.assert_close(transform_points(T, pts), expected)
    # a roll keeps the optical axis and rotates the image plane
    T_r = look_at_T_cam_base(torch.tensor([2.0, 0, 0]), torch.zeros(3), torch.tensor(math.pi / 2))
    out = transform_points(T_r, pts)
    torch.testing.assert_close(out[0], torch.tensor([0.0, 0, 2]))
    torch.testing.assert_close(out[1:, :2].norm(dim=1), torch.ones(2))
    assert rotation_angle(T[:3, :3], T_r[:3, :3]).item() == pytest.approx(math.pi / 2, abs=1e-6)


def test_look_at_matches_camera_module_and_handles_vertical_axis() -> None:
    from roboseg.camera import look_at

    g = torch.Generator().manual_seed(1)
    eye = torch.randn(8, 3, generator=g, dtype=torch.float64) * 2
    centre = torch.randn(8, 3, generator=g, dtype=torch.float64) * 0.2
    ours = look_at_T_cam_base(eye, centre, torch.zeros(8, dtype=torch.float64))
    torch.testing.assert_close(ours, look_at(eye, centre))
    straight_down = look_at_T_cam_base(torch.tensor([0.0, 0, 2]), torch.zeros(3), torch.tensor(0.0))
    assert torch.isfinite(straight_down).all()
    torch.testing.assert_close(
        transform_points(straight_down, torch.zeros(1, 3)), torch.tensor([[0.0, 0, 2]])
    )


# --------------------------------------------------------------------------------------------
# losses (hand-computed)


def _square_mask() -> np.ndarray:
    m = np.zeros((5, 5), dtype=bool)
    m[1:4, 1:4] = True
    return m


def test_inside_distance_hand_computed() -> None:
    d = inside_distance(_square_mask())
    expected = np.zeros((5, 5), dtype=np.float32)
    expected[1:4, 1:4] = 1.0
    expected[2, 2] = 2.0
    np.testing.assert_allclose(d, expected)


def test_outside_distance_hand_computed() -> None:
    m = np.zeros((5, 5), dtype=bool)
    m[2, 2] = True
    d = outside_distance(m)
    assert d[2, 2] == 0.0
    assert d[2, 0] == pytest.approx(2.0)
    assert d[1, 1] == pytest.approx(math.sqrt(2))
    assert d[0, 0] == pytest.approx(math.sqrt(8))
    assert d[0, 1] == pytest.approx(math.sqrt(5))
    assert np.isinf(outside_distance(np.zeros((3, 3), bool))).all()


def test_distance_mse_hand_computed() -> None:
    target = RegistrationTarget.from_masks(_square_mask()[None])
    render = torch.from_numpy(_square_mask()[None].astype(np.float32))
    # only the centre differs: (1 − 2)² / 25
    assert distance_mse_loss(render, target.d_inside).item() == pytest.approx(1 / 25)
    # empty render: Σ d² / 25 = (8·1 + 4) / 25
    empty = torch.zeros(1, 5, 5)
    assert target.loss(empty, "mse").item() == pytest.approx(12 / 25)


def test_exp_dice_hand_computed() -> None:
    s = np.zeros((3, 3), dtype=bool)
    s[1, 1] = True
    target = RegistrationTarget.from_masks(s[None], sigma=2.0)
    # E: 1 at the centre, e^(−1/2) at the 4 edge neighbours, e^(−√2/2) at the corners
    e_sq = 1 + 4 * math.exp(-1.0) + 4 * math.exp(-math.sqrt(2))
    render = torch.from_numpy(s[None].astype(np.float32))
    expected = 1 - 2 * 1.0 / (1.0 + e_sq + 1e-6)
    assert exp_dice_loss(render, target.decay).item() == pytest.approx(expected, rel=1e-6)
    # a render covering the whole image: ‖M ⊙ E‖₁ = 1 + 4e^(−1/2) + 4e^(−√2/2), ‖M‖² = 9
    full = torch.ones(1, 3, 3)
    l1 = 1 + 4 * math.exp(-0.5) + 4 * math.exp(-math.sqrt(2) / 2)
    assert target.loss(full).item() == pytest.approx(1 - 2 * l1 / (9 + e_sq + 1e-6), rel=1e-6)


def test_dice_gradient_pulls_render_towards_target() -> None:
    mask = np.zeros((1, 9, 9), dtype=bool)
    mask[0, 3:6, 3:6] = True
    target = RegistrationTarget.from_masks(mask)
    render = torch.full((1, 9, 9), 0.5, requires_grad=True)
    target.loss(render).sum().backward()
    assert render.grad[0, 4, 4] < 0 < render.grad[0, 0, 0]  # grow inside, shrink far outside


def test_target_from_probabilities_and_iou() -> None:
    probs = np.zeros((1, 4, 4), dtype=np.float32)
    probs[0, :2, :2] = 0.9
    probs[0, 3, 3] = 0.4
    target = RegistrationTarget.from_masks(probs)
    assert target.masks.sum().item() == 4
    render = torch.zeros(1, 4, 4, dtype=torch.bool)
    render[0, :2, :] = True  # 8 pixels, 4 overlapping
    assert iou(render, target.masks).item() == pytest.approx(0.5)
    assert iou(torch.zeros(1, 2, 2), torch.zeros(1, 2, 2)).item() == 1.0
    with pytest.raises(ValueError, match="unknown registration loss"):
        target.loss(render.float(), "l1")  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------------
# views, CSO and SDR on synthetic stereo views of the default robot (noiseless)

WIDTH, HEIGHT = 160, 90


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def scene() -> dict:
    """Default robot (95 % decimated) in 2 configurations seen by a 160×90 stereo pair."""
    from roboseg.camera import Intrinsics, StereoRig
    from roboseg.registration.views import stereo_views, vertices_in_view
    from roboseg.render.raster import render_hard
    from roboseg.robot import load_robot

    torch.manual_seed(0)
    full = load_robot(None)
    robot = full.decimated(0.95)
    q = robot.random_joints(2, torch.Generator().manual_seed(0))
    vertices = robot.posed_vertices(q)
    intr = Intrinsics(160.0, 160.0, (WIDTH - 1) / 2, (HEIGHT - 1) / 2, WIDTH, HEIGHT)
    T_right_left = np.eye(4)
    T_right_left[0, 3] = -0.12
    views = stereo_views(StereoRig(intr, intr, T_right_left))
    T_true = look_at_T_cam_base(
        torch.tensor([1.6, 0.8, 1.2]), torch.tensor([0.0, 0.0, 0.5]), torch.tensor(0.1)
    )
    masks = [
        render_hard(vertices_in_view(T_true, v, vertices), robot.faces, v.K, v.height, v.width)
        for v in views
    ]
    coarse = full.decimated(0.98)
    return {
        "q": q,
        "vertices": vertices,
        "faces": robot.faces,
        "views": views,
        "T_true": T_true,
        "masks": masks,
        "coarse_vertices": coarse.posed_vertices(q),
        "coarse_faces": coarse.faces,
    }


def _pose_errors(T: np.ndarray | torch.Tensor, T_true: torch.Tensor) -> tuple[float, float]:
    """(translation error in m, rotation error in degrees)."""
    T = torch.as_tensor(T, dtype=T_true.dtype)
    dt = float((T[:3, 3] - T_true[:3, 3]).norm())
    return dt, math.degrees(float(rotation_angle(T[:3, :3], T_true[:3, :3])))


def test_view_resize_matches_intrinsics_resize(scene: dict) -> None:
    from roboseg.camera import Intrinsics

    left = scene["views"][0]
    small = left.resized(64, 36)
    ref = Intrinsics.from_K(left.K.double().numpy(), WIDTH, HEIGHT).resized(64, 36)
    torch.testing.assert_close(small.K.double(), torch.from_numpy(ref.K))
    torch.testing.assert_close(scene["views"][1].T_view_left[0, 3], torch.tensor(-0.12))


def test_sdr_recovers_pose_from_2cm_3deg(scene: dict) -> None:
    from roboseg.registration.sdr import SDRConfig, sdr

    T_true = scene["T_true"]
    g = torch.Generator().manual_seed(3)
    axis = torch.randn(3, generator=g)
    axis = axis / axis.norm()
    angle = math.radians(3.0)
    k = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R = torch.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k
    offset = torch.randn(3, generator=g)
    T0 = T_true.clone()
    T0[:3, :3] = R @ T_true[:3, :3]
    T0[:3, 3] += offset / offset.norm() * 0.02
    assert _pose_errors(T0, T_true) == pytest.approx((0.02, 3.0), rel=1e-3)

    res = sdr(
        scene["vertices"],
        scene["faces"],
        scene["views"],
        scene["masks"],
        T0,
        SDRConfig(max_iterations=200),
    )
    dt, dr = _pose_errors(res.T_cam_base, T_true)
    # measured (noiseless, 160×90 px, ~1.2 cm per pixel at the robot): ≈1.5 mm, ≈0.6°
    assert res.reason in ("converged", "max_iterations")
    assert dt < 0.006 and dr < 1.0, (dt, dr)
    assert min(res.per_view_iou.values()) > 0.97
    assert res.per_frame_iou.shape == (2, 2)
    assert res.loss <= res.history[0]


def test_sdr_reports_divergence_when_robot_is_out_of_view(scene: dict) -> None:
    from roboseg.registration.sdr import SDRConfig, sdr

    T0 = scene["T_true"].clone()
    T0[0, 3] += 5.0  # 5 m to the side: nothing of the robot in either image
    res = sdr(
        scene["vertices"],
        scene["faces"],
        scene["views"],
        scene["masks"],
        T0,
        SDRConfig(max_iterations=20),
    )
    assert res.reason == "diverged"
    assert res.iterations == 1
    assert all(v == 0.0 for v in res.per_view_iou.values())


def test_swarm_fitness_is_one_at_truth_and_lower_elsewhere(scene: dict) -> None:
    from roboseg.registration.cso import SwarmFitness

    fit = SwarmFitness(scene["vertices"], scene["faces"], scene["views"], scene["masks"], 80)
    T_true = scene["T_true"]
    T_off = T_true.clone()
    T_off[0, 3] += 0.1
    behind = T_true.clone()
    behind[2, 3] = -5.0  # robot entirely behind both cameras
    f = fit(torch.stack([T_true, T_off, behind]))
    assert f[0].item() > 0.9  # 160 px targets area-downsampled to 80 px vs direct 80 px renders
    assert 0.0 < f[1].item() < f[0].item()
    assert f[2].item() == 0.0


def test_particles_sampled_and_projected_inside_domain() -> None:
    from roboseg.registration.cso import CSOConfig, project_particles, sample_particles

    cfg = CSOConfig(r_min=1.0, r_max=2.0, centre_radius=0.3, about=(0.0, 0.0, 0.5), roll_range=0.4)
    x = sample_particles(500, cfg, torch.Generator().manual_seed(0))
    about = torch.tensor(cfg.about, dtype=torch.float64)
    r_eye = (x[:, :3] - about).norm(dim=1)
    assert r_eye.min() >= 1.0 and r_eye.max() <= 2.0 + 1e-9
    assert (x[:, 3:6] - about).norm(dim=1).max() <= 0.3 + 1e-9
    assert x[:, 6].abs().max() <= 0.4
    # uniform by volume: the fraction inside radius 1.5 is (1.5³ − 1)/(2³ − 1) ≈ 0.339
    assert (r_eye < 1.5).double().mean().item() == pytest.approx((1.5**3 - 1) / 7, abs=0.06)
    far = torch.tensor(
        [[5.0, 0, 0.5, 0, 0, 2.0, 3.0], [0.1, 0, 0.5, 0, 0, 0.5, -3.0]], dtype=torch.float64
    )
    p = project_particles(far, cfg)
    torch.testing.assert_close(p[:, 0], torch.tensor([2.0, 1.0], dtype=torch.float64))
    torch.testing.assert_close(p[:, 5], torch.tensor([0.8, 0.5], dtype=torch.float64))
    torch.testing.assert_close(p[:, 6], torch.tensor([0.4, -0.4], dtype=torch.float64))


def test_eye_elevation_band_is_sampled_uniformly_and_projected() -> None:
    """Eyes in the band of elevations 0.2-1.0 rad above ``about``: every one inside, uniform on
    the sphere's band (z/r uniform in [sin 0.2, sin 1.0]); projection clamps the elevation and
    keeps the azimuth and radius."""
    import math

    from roboseg.errors import CameraError
    from roboseg.registration.cso import CSOConfig, project_particles, sample_particles

    cfg = CSOConfig(r_min=1.0, r_max=2.0, about=(0.0, 0.0, 0.5), elevation_range=(0.2, 1.0))
    x = sample_particles(4000, cfg, torch.Generator().manual_seed(0))
    e = x[:, :3] - torch.tensor(cfg.about, dtype=torch.float64)
    r = e.norm(dim=1)
    sin_el = e[:, 2] / r
    assert r.min() >= 1.0 and r.max() <= 2.0 + 1e-9
    assert sin_el.min() >= math.sin(0.2) - 1e-9 and sin_el.max() <= math.sin(1.0) + 1e-9
    # uniform on the band: the lower half of its z range holds half of the eyes
    mid = 0.5 * (math.sin(0.2) + math.sin(1.0))
    assert (sin_el < mid).double().mean().item() == pytest.approx(0.5, abs=0.03)
    assert (r < 1.5).double().mean().item() == pytest.approx((1.5**3 - 1) / 7, abs=0.03)
    # an eye below the band (elevation -0.5 rad, azimuth 90°, radius 1.5) is lifted to 0.2 rad
    below = torch.tensor([[0.0, 1.5 * math.cos(-0.5), 0.5 + 1.5 * math.sin(-0.5),
                           0, 0, 0.5, 0.0]], dtype=torch.float64)
    p = project_particles(below, cfg)[0]
    expected = [0.0, 1.5 * math.cos(0.2), 0.5 + 1.5 * math.sin(0.2)]
    torch.testing.assert_close(p[:3], torch.tensor(expected, dtype=torch.float64))
    inside = x[:5].clone()
    torch.testing.assert_close(project_particles(inside, cfg), inside)
    with pytest.raises(CameraError, match="elevation_range"):
        CSOConfig(elevation_range=(1.0, 0.2))


def test_swarm_candidates_come_from_different_basins() -> None:
    """Multi-start candidates: the fittest particle, then the fittest one at least 0.3 m or 0.5 rad
    from it (default separations), not its near neighbours (eyes 0.2 m to the side)."""
    from roboseg.registration.cso import CSOConfig, _distinct_best, particles_to_T_cam_base
    from roboseg.registration.pose import rotation_angle

    centre = [0.0, 0.0, 0.5, 0.0]
    x = torch.tensor(
        [[1.5, 0.0, 1.0, *centre], [1.5, 0.2, 1.0, *centre], [1.5, -0.2, 1.0, *centre],
         [-1.5, 0.0, 1.0, *centre]],
        dtype=torch.float64,
    )
    fitness = torch.tensor([0.9, 0.89, 0.88, 0.5], dtype=torch.float64)
    T = particles_to_T_cam_base(x)
    # the neighbours look at the robot from 7° aside: distinct at 5 cm / 5° ...
    assert math.radians(5.0) < float(rotation_angle(T[0, :3, :3], T[1, :3, :3])) < 0.5
    picked = _distinct_best(x, fitness, CSOConfig(n_candidates=2))
    assert [c.fitness for c in picked] == [0.9, 0.5]  # ... but one basin at 0.3 m / 0.5 rad
    torch.testing.assert_close(torch.as_tensor(picked[1].particle), x[3])
    close = _distinct_best(
        x, fitness, CSOConfig(n_candidates=2, min_separation=0.05, min_separation_angle=0.087)
    )
    assert [c.fitness for c in close] == [0.9, 0.89]


def test_cso_is_seeded_and_scores_initial_swarm(scene: dict) -> None:
    from roboseg.registration.cso import CSOConfig, cso

    cfg = CSOConfig(
        n_particles=24,
        iterations=2,
        r_min=1.2,
        r_max=2.5,
        centre_radius=0.3,
        width=32,
        n_candidates=3,
        seed=7,
    )
    args = (scene["coarse_vertices"], scene["coarse_faces"], scene["views"], scene["masks"])
    a, b = cso(*args, cfg), cso(*args, cfg)
    assert a.history == b.history and len(a.history) == 3
    np.testing.assert_array_equal(a.best.T_cam_base, b.best.T_cam_base)
    assert all(x <= y for x, y in zip(a.history, a.history[1:], strict=False))
    assert a.history[0] > 0  # the initial swarm was scored
    fits = [c.fitness for c in a.candidates]
    assert fits == sorted(fits, reverse=True) and fits[0] == a.history[-1]


def test_cso_restarts_only_while_fitness_is_low(scene: dict) -> None:
    """A swarm that reaches ``restart_below`` is the only one run (the same result as without
    restarts); one that does not is followed by swarms seeded ``seed + 1``, ``seed + 2``, whose
    personal bests join the candidates, so the pooled best is the best of the single runs."""
    from dataclasses import replace

    from roboseg.errors import CameraError
    from roboseg.registration.cso import CSOConfig, cso

    cfg = CSOConfig(
        n_particles=16, iterations=1, r_min=1.2, r_max=2.5, centre_radius=0.3, width=32, seed=4
    )
    args = (scene["coarse_vertices"], scene["coarse_faces"], scene["views"], scene["masks"])
    single = [cso(*args, replace(cfg, seed=s)) for s in (4, 5, 6)]
    easy = cso(*args, replace(cfg, restarts=2, restart_below=0.0))
    assert easy.runs == 1 and easy.history == single[0].history
    np.testing.assert_array_equal(easy.best.T_cam_base, single[0].best.T_cam_base)
    hard = cso(*args, replace(cfg, restarts=2, restart_below=1.01))
    assert hard.runs == 3 and len(hard.history) == 3 * (cfg.iterations + 1)
    assert all(x <= y for x, y in zip(hard.history, hard.history[1:], strict=False))
    best = max(r.best.fitness for r in single)
    assert best > single[0].best.fitness  # measured 0.25, 0.38, 0.42: the restarts found better
    assert hard.best.fitness == best == hard.history[-1]
    assert hard.history[:2] == single[0].history
    with pytest.raises(CameraError, match="restarts"):
        CSOConfig(restarts=-1)


def test_cso_then_sdr_registers_from_random_start(scene: dict) -> None:
    from roboseg.registration.cso import CSOConfig, cso
    from roboseg.registration.sdr import SDRConfig, sdr_multistart

    cfg = CSOConfig(
        n_particles=192,
        iterations=12,
        r_min=1.2,
        r_max=2.5,
        centre_radius=0.3,
        roll_range=0.5,
        width=48,
        seed=0,
    )
    found = cso(
        scene["coarse_vertices"], scene["coarse_faces"], scene["views"], scene["masks"], cfg
    )
    assert found.history[-1] > found.history[0]
    assert found.best.fitness > 0.8
    out_of_view = found.best.T_cam_base.copy()
    out_of_view[0, 3] += 5.0  # a start that diverges at once must not be picked
    res = sdr_multistart(
        scene["vertices"],
        scene["faces"],
        scene["views"],
        scene["masks"],
        [out_of_view, found.best.T_cam_base],
        SDRConfig(max_iterations=200),
    )
    dt, dr = _pose_errors(res.T_cam_base, scene["T_true"])
    # measured: CSO best ≈3 cm / ≈20° off, SDR from there ≈0.5 mm / ≈0.1°
    assert res.reason != "diverged"
    assert dt < 0.006 and dr < 1.0, (dt, dr)


# --------------------------------------------------------------------------------------------
# boundary offsets: robustness to segmentations that are too fat or too thin


def _disc(radius: float, size: int = 41) -> np.ndarray:
    yy, xx = np.mgrid[:size, :size]
    c = (size - 1) / 2
    return (yy - c) ** 2 + (xx - c) ** 2 <= radius**2


def test_signed_distance_and_shifted_target_hand_computed() -> None:
    from roboseg.registration.losses import signed_distance

    m = _square_mask()
    phi = signed_distance(m)
    # inside: d(S) − ½ (rim 0.5, centre 1.5); outside: ½ − d(1 − S) (edge neighbours −0.5)
    assert phi[2, 2] == pytest.approx(1.5) and phi[1, 1] == pytest.approx(0.5)
    assert phi[0, 2] == pytest.approx(-0.5) and phi[0, 0] == pytest.approx(0.5 - math.sqrt(2))
    target = RegistrationTarget.from_masks(m[None])
    np.testing.assert_allclose(target.phi.numpy()[0], phi)
    render = torch.rand(1, 5, 5, generator=torch.Generator().manual_seed(0))
    for name in ("mse", "dice"):  # offset 0 is exactly the paper's cost
        torch.testing.assert_close(
            target.loss(render, name, torch.zeros(1)), target.loss(render, name)
        )
    # offset +1 erodes the 3×3 square to its centre pixel: d(S_1) = 1 there, 0 elsewhere
    centre = np.zeros((5, 5), dtype=bool)
    centre[2, 2] = True
    eroded = RegistrationTarget.from_masks(centre[None])
    torch.testing.assert_close(
        target.loss(render, "mse", torch.ones(1)), eroded.loss(render, "mse")
    )


def test_best_offsets_undo_dilation_and_erosion() -> None:
    render = torch.from_numpy(np.stack([_disc(8.0), _disc(8.0), _disc(8.0), _disc(8.0)]))
    masks = np.stack([_disc(10.0), _disc(6.0), _disc(8.0), np.zeros((41, 41), bool)])
    e = RegistrationTarget.from_masks(masks).best_offsets(render, max_offset=4.0)
    assert e[0].item() == pytest.approx(2.0, abs=0.5)  # target 2 px too fat: erode it by 2
    assert e[1].item() == pytest.approx(-2.0, abs=0.5)  # 2 px too thin: dilate it by 2
    assert e[2].item() == 0.0  # exact: no shift
    assert e[3].item() == 0.0  # empty segmentation: no shift
    small = RegistrationTarget.from_masks(masks[:1]).best_offsets(render[:1], max_offset=1.0)
    assert small.item() == pytest.approx(1.0)  # bounded by max_offset


def _degrade(mask: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Dilate or erode by 2 px (at random) and stamp a 3 px blob on the boundary."""
    import cv2

    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    m = mask.astype(np.uint8)
    out = cv2.dilate(m, k) if rng.random() < 0.5 else cv2.erode(m, k)
    edge = np.argwhere(cv2.morphologyEx(m, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0)
    y, x = edge[rng.integers(len(edge))]
    cv2.circle(out, (int(x), int(y)), 3, int(rng.random() < 0.5), -1)
    return out > 0


def test_sdr_with_boundary_offsets_registers_degraded_masks(scene: dict) -> None:
    from roboseg.registration.losses import iou as mask_iou
    from roboseg.registration.sdr import SDRConfig, sdr

    rng = np.random.default_rng(0)
    degraded = [np.stack([_degrade(x.numpy(), rng) for x in m]) for m in scene["masks"]]
    achieved = [
        mask_iou(torch.from_numpy(d), m).mean().item()
        for d, m in zip(degraded, scene["masks"], strict=True)
    ]
    assert min(achieved) > 0.6 and max(achieved) < 0.9, achieved
    T0 = scene["T_true"].clone()
    T0[:3, 3] += torch.tensor([0.01, -0.01, 0.02])
    errors = {}
    for offset in (0.0, 3.0):
        res = sdr(
            scene["vertices"],
            scene["faces"],
            scene["views"],
            degraded,
            T0,
            SDRConfig(max_iterations=120, lr=4e-3, boundary_offset=offset),
        )
        assert res.reason != "diverged"
        errors[offset] = _pose_errors(res.T_cam_base, scene["T_true"])
    dt, dr = errors[3.0]
    assert dt < 0.012 and dr < 1.5, errors
    assert dt < errors[0.0][0], errors


def test_multistart_screening_refines_only_the_best_start(scene: dict) -> None:
    from roboseg.registration.sdr import SDRConfig, sdr_multistart

    near = scene["T_true"].clone()
    near[:3, 3] += torch.tensor([0.01, 0.0, -0.01])
    far = scene["T_true"].clone()
    far[:3, 3] += torch.tensor([0.15, 0.1, 0.3])
    res = sdr_multistart(
        scene["vertices"],
        scene["faces"],
        scene["views"],
        scene["masks"],
        [far, near],
        SDRConfig(max_iterations=150, lr=4e-3),
        screen_iterations=10,
        keep=1,
    )
    dt, dr = _pose_errors(res.T_cam_base, scene["T_true"])
    assert dt < 0.006 and dr < 1.0, (dt, dr)
    with pytest.raises(ValueError, match="keep"):
        sdr_multistart(
            scene["vertices"], scene["faces"], scene["views"], scene["masks"], [near], keep=0
        )


def test_objective_cost_is_float64_and_resolves_sub_ulp_differences(scene: dict) -> None:
    """The cost is a large constant plus small boundary terms: in float64 two poses 0.1 mm
    apart get different costs (in float32 their difference drowns in rounding)."""
    from roboseg.registration.sdr import StereoObjective

    obj = StereoObjective(scene["vertices"], scene["faces"], scene["views"], scene["masks"], "mse")
    loss, ious, _ = obj(scene["T_true"])
    assert loss.dtype == torch.float64
    assert float(ious.min()) == 1.0
    moved = scene["T_true"].clone()
    moved[0, 3] += 1e-4
    assert obj.plain_cost(moved) != obj.plain_cost(scene["T_true"])


def test_polish_reaches_the_cost_minimum_adamw_stops_short_of(scene: dict) -> None:
    """At 640×360 (sub-millimetre pixels' worth of boundary), from 6 mm off AdamW alone stops
    with a cost above the truth's; the L-BFGS polish then reaches a cost at or below it (the
    objective's own optimum) and ends closer to the truth."""
    from roboseg.registration.sdr import SDRConfig, StereoObjective, sdr
    from roboseg.registration.views import vertices_in_view, views_scaled
    from roboseg.render.raster import render_hard

    views = views_scaled(scene["views"], 4.0)
    masks = [
        render_hard(
            vertices_in_view(scene["T_true"], v, scene["vertices"]),
            scene["faces"],
            v.K,
            v.height,
            v.width,
        )
        for v in views
    ]
    T0 = scene["T_true"].clone()
    T0[:3, 3] += torch.tensor([0.004, -0.003, 0.0035])
    obj = StereoObjective(scene["vertices"], scene["faces"], views, masks, "mse")
    truth_cost = obj.plain_cost(scene["T_true"])
    results = {
        n: sdr(
            scene["vertices"],
            scene["faces"],
            views,
            masks,
            T0,
            SDRConfig(max_iterations=60, lr=4e-3, polish_iterations=n),
            obj,
        )
        for n in (0, 20)
    }
    plain, polished = results[0], results[20]
    assert plain.loss > truth_cost, (plain.loss, truth_cost)
    assert polished.loss <= truth_cost + 1e-9, (polished.loss, truth_cost)
    assert polished.loss < plain.loss
    dt_plain, _ = _pose_errors(plain.T_cam_base, scene["T_true"])
    dt_polished, _ = _pose_errors(polished.T_cam_base, scene["T_true"])
    assert dt_polished < dt_plain, (dt_polished, dt_plain)
    assert polished.reason == plain.reason != "diverged"


def test_centroid_disparity_hand_computed(scene: dict) -> None:
    """Left block centred at x = 11, right at x = 7 (px), fx = 160: disparity 4 / 160 along the
    baseline (the right camera sits at +x, so nearer points shift left in its image)."""
    from roboseg.registration.sdr import StereoObjective

    obj = StereoObjective(scene["vertices"], scene["faces"], scene["views"], scene["masks"], "mse")
    left = torch.zeros(1, HEIGHT, WIDTH)
    right = torch.zeros(1, HEIGHT, WIDTH)
    left[0, 20:30, 10:13] = 1.0
    right[0, 40:50, 6:9] = 1.0
    assert float(obj.disparities([left, right])[0]) == pytest.approx(4.0 / 160.0)


def test_disparity_term_keeps_fat_masks_from_pulling_the_robot_closer(scene: dict) -> None:
    """Both views' masks dilated by 3 px (a blurry model's errors are alike in the two images of
    a pair): their centroid disparity is still the truth's, while their outline pulls SDR
    towards the camera. With the disparity term the distance error shrinks fourfold or more;
    at the truth the term is ~0."""
    import cv2

    from roboseg.registration.sdr import SDRConfig, StereoObjective, sdr

    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7))
    fat = [
        np.stack([cv2.dilate(x.numpy().astype(np.uint8), k) > 0 for x in m])
        for m in scene["masks"]
    ]
    plain = StereoObjective(scene["vertices"], scene["faces"], scene["views"], fat, "mse")
    with_term = StereoObjective(
        scene["vertices"], scene["faces"], scene["views"], fat, "mse", disparity_weight=1.0
    )
    assert with_term.plain_cost(scene["T_true"]) - plain.plain_cost(scene["T_true"]) < 0.05
    ray = scene["T_true"][:3, 3] / scene["T_true"][:3, 3].norm()
    depth_error = {}
    for w in (0.0, 1.0):
        res = sdr(
            scene["vertices"],
            scene["faces"],
            scene["views"],
            fat,
            scene["T_true"],
            SDRConfig(max_iterations=150, lr=4e-3, disparity_weight=w),
        )
        assert res.reason != "diverged"
        delta = torch.as_tensor(res.T_cam_base[:3, 3]).float() - scene["T_true"][:3, 3]
        depth_error[w] = float(delta @ ray)
    # measured: 165 mm too close without the term, 17 mm with it
    assert depth_error[0.0] < -0.08, depth_error
    assert abs(depth_error[1.0]) < 0.25 * abs(depth_error[0.0]), depth_error
