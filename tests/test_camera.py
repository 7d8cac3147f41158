"""Camera maths against hand-computed values."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from roboseg.camera import Intrinsics, StereoRig, look_at, project, projection_matrix
from roboseg.errors import CameraError


def test_K_and_from_K_round_trip() -> None:
    intr = Intrinsics(500.0, 510.0, 319.5, 239.5, 640, 480)
    np.testing.assert_array_equal(
        intr.K, [[500.0, 0.0, 319.5], [0.0, 510.0, 239.5], [0.0, 0.0, 1.0]]
    )
    assert Intrinsics.from_K(intr.K, 640, 480) == intr
    assert Intrinsics.from_K(intr.K.reshape(-1).tolist(), 640, 480) == intr
    assert intr.as_tensor(dtype=torch.float64).dtype == torch.float64
    torch.testing.assert_close(intr.as_tensor(), torch.tensor(intr.K, dtype=torch.float32))


def test_from_camera_info_message_and_dicts() -> None:
    k = [400.0, 0.0, 300.0, 0.0, 410.0, 200.0, 0.0, 0.0, 1.0]
    expected = Intrinsics(400.0, 410.0, 300.0, 200.0, 600, 400)
    assert Intrinsics.from_camera_info(SimpleNamespace(k=k, width=600, height=400)) == expected
    assert Intrinsics.from_camera_info({"k": k, "width": 600, "height": 400}) == expected
    assert Intrinsics.from_camera_info({"K": k, "width": 600, "height": 400}) == expected
    with pytest.raises(CameraError, match="k"):
        Intrinsics.from_camera_info({"width": 600, "height": 400})
    with pytest.raises(CameraError, match="9 numbers"):
        Intrinsics.from_camera_info({"k": k[:6], "width": 600, "height": 400})


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"fx": -1.0}, "focal"),
        ({"fy": 0.0}, "focal"),
        ({"width": 0}, "width"),
        ({"height": -5}, "height"),
        ({"width": 10.5}, "width"),
        ({"cx": float("nan")}, "cx"),
    ],
)
def test_intrinsics_validation(kwargs: dict, match: str) -> None:
    args = {"fx": 100.0, "fy": 100.0, "cx": 50.0, "cy": 50.0, "width": 100, "height": 100}
    args.update(kwargs)
    with pytest.raises(CameraError, match=match):
        Intrinsics(**args)


def test_resized_follows_pixel_centre_convention() -> None:
    intr = Intrinsics(100.0, 100.0, 49.5, 49.5, 100, 100)
    half = intr.resized(50, 50)
    # centre of a 100-pixel image (49.5) is the centre of a 50-pixel one (24.5)
    assert (half.fx, half.fy, half.cx, half.cy) == (50.0, 50.0, 24.5, 24.5)
    # anisotropic 16:9 -> 1:1 squash: sx = 512/1920, sy = 512/1080
    hd = Intrinsics(1000.0, 1000.0, 960.0, 540.0, 1920, 1080)
    sq = hd.resized(512, 512)
    sx, sy = 512 / 1920, 512 / 1080
    assert sq.fx == pytest.approx(1000 * sx) and sq.fy == pytest.approx(1000 * sy)
    assert sq.cx == pytest.approx(960.5 * sx - 0.5) and sq.cy == pytest.approx(540.5 * sy - 0.5)
    # a projected point moves exactly like its pixel coordinate: u' = (u + 0.5)·sx − 0.5
    p = torch.tensor([0.3, -0.2, 2.0], dtype=torch.float64)
    u = project(p, torch.as_tensor(hd.K))
    u2 = project(p, torch.as_tensor(sq.K))
    torch.testing.assert_close(u2, (u + 0.5) * torch.tensor([sx, sy], dtype=torch.float64) - 0.5)
    with pytest.raises(CameraError):
        hd.resized(0, 10)


def test_cropped_shifts_principal_point() -> None:
    intr = Intrinsics(300.0, 300.0, 320.0, 240.0, 640, 480)
    roi = intr.cropped(100, 50, 200, 120)
    assert (roi.fx, roi.fy, roi.cx, roi.cy, roi.width, roi.height) == (
        300.0,
        300.0,
        220.0,
        190.0,
        200,
        120,
    )
    with pytest.raises(CameraError):
        intr.cropped(0, 0, 0, 10)


def test_projection_matrix_is_the_papers_P() -> None:
    intr = Intrinsics(200.0, 220.0, 63.5, 47.5, 128, 96)
    P = projection_matrix(intr, 0.1, 10.0)
    expected = np.array(
        [
            [400 / 128, 0, 127 / 128 - 1, 0],
            [0, 440 / 96, 95 / 96 - 1, 0],
            [0, 0, 10.1 / 9.9, 2 * 1.0 / (0.1 - 10.0)],
            [0, 0, 1, 0],
        ]
    )
    np.testing.assert_allclose(P, expected, rtol=1e-12)
    # clip -> NDC: x_ndc = 2u/w − 1, so OpenCV pixel u = (x_ndc + 1)·w/2
    pts = np.array([[0.2, -0.1, 0.1], [0.0, 0.3, 10.0], [-0.5, 0.4, 2.0]])
    clip = np.c_[pts, np.ones(3)] @ P.T
    ndc = clip[:, :3] / clip[:, 3:]
    uv = project(torch.as_tensor(pts), torch.as_tensor(intr.K)).numpy()
    np.testing.assert_allclose((ndc[:, 0] + 1) * 128 / 2, uv[:, 0], rtol=1e-12)
    np.testing.assert_allclose((ndc[:, 1] + 1) * 96 / 2, uv[:, 1], rtol=1e-12)
    np.testing.assert_allclose(ndc[:2, 2], [-1.0, 1.0], atol=1e-12)  # z_min, z_max
    with pytest.raises(CameraError):
        projection_matrix(intr, 1.0, 0.5)


def test_project_hand_values_and_batched_K() -> None:
    K = torch.tensor([[100.0, 0.0, 50.0], [0.0, 200.0, 40.0], [0.0, 0.0, 1.0]])
    p = torch.tensor([[0.5, -0.25, 2.0]])
    torch.testing.assert_close(project(p, K), torch.tensor([[75.0, 15.0]]))
    Kb = torch.stack([K, 2 * K])
    Kb[1, 2] = torch.tensor([0.0, 0.0, 1.0])
    pts = torch.tensor([[[0.5, -0.25, 2.0]], [[0.5, -0.25, 2.0]]])
    torch.testing.assert_close(project(pts, Kb), torch.tensor([[[75.0, 15.0]], [[150.0, 30.0]]]))


def test_look_at_axes_follow_opencv() -> None:
    T = look_at([2.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    np.testing.assert_allclose(T[:3, :3], [[0, 1, 0], [0, 0, -1], [-1, 0, 0]], atol=1e-15)
    p = T @ np.array([0.0, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(p[:3], [0.0, 0.0, 2.0], atol=1e-15)  # target straight ahead
    above = T @ np.array([0.0, 0.0, 1.0, 1.0])
    assert above[1] < 0  # world up is image up (negative y)
    right = T @ np.array([0.0, 1.0, 0.0, 1.0])  # world +y is to the right when looking along -x
    assert right[0] > 0
    np.testing.assert_allclose(np.linalg.det(T[:3, :3]), 1.0)


def test_look_at_batched_torch_matches_numpy() -> None:
    g = torch.Generator().manual_seed(0)
    eyes = torch.rand(5, 3, generator=g, dtype=torch.float64) * 2 + 1
    target = torch.tensor([0.1, -0.2, 0.5], dtype=torch.float64)
    T = look_at(eyes, target, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    assert isinstance(T, torch.Tensor) and T.shape == (5, 4, 4)
    for i in range(5):
        np.testing.assert_allclose(T[i].numpy(), look_at(eyes[i].numpy(), target.numpy()))
        eye_cam = T[i] @ torch.cat([eyes[i], torch.ones(1, dtype=torch.float64)])
        torch.testing.assert_close(eye_cam[:3], torch.zeros(3, dtype=torch.float64))


def test_look_at_degenerate() -> None:
    with pytest.raises(CameraError, match="coincide"):
        look_at([1.0, 1.0, 1.0], [1.0, 1.0, 1.0])
    with pytest.raises(CameraError, match="parallel"):
        look_at([0.0, 0.0, 2.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0])


def test_stereo_rig_zed2i_like() -> None:
    rig = StereoRig.zed2i_like()
    assert rig.baseline == pytest.approx(0.12)
    assert (rig.left.width, rig.left.height) == (960, 540)
    f = 480 / math.tan(math.radians(52.0))
    assert rig.left.fx == pytest.approx(f) and 350 < f < 400
    assert (rig.left.cx, rig.left.cy) == (479.5, 269.5)
    # the right camera's centre, expressed in the left frame, maps to the right origin
    centre_right = rig.T_right_left @ np.array([0.12, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(centre_right[:3], 0.0, atol=1e-15)
    with pytest.raises(CameraError):
        StereoRig(rig.left, rig.right, np.eye(3))
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(CameraError, match="rigid"):
        StereoRig(rig.left, rig.right, bad)
    with pytest.raises(CameraError):
        StereoRig.zed2i_like(baseline=0.0)
