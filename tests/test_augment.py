"""Batched augmentation: geometry keeps labels aligned, CMM merges right, photometrics spare the
prior, draws are reproducible, values stay in range; in-context prior perturbations."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from roboseg.augment import (
    AugmentationPipeline,
    ConditionalAffine,
    CutMixMerge,
    HorizontalFlip,
    InContextPrior,
    Photometric,
    RobotCrop,
    to_model_input,
)
from roboseg.augment.geometric import affine_matrix
from roboseg.augment.photometric import (
    BoxBlur,
    ChannelDropout,
    ColorJitter,
    Contrast,
    GaussianNoise,
    Grayscale,
    SaltAndPepper,
    paper_ops,
)
from roboseg.augment.pipeline import draped_map, prepare
from roboseg.augment.prior import (
    axis_angle_to_matrix,
    perturb_pose,
    sample_pose_perturbation,
    transform_points,
)

H, W = 48, 64


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def painted_batch(n: int = 4, seed: int = 0) -> dict[str, torch.Tensor]:
    """Robot masks = random rectangles; image red inside the mask, blue outside; prior = mask
    shifted by 3 columns (a perturbed silhouette)."""
    g = gen(seed)
    mask = torch.zeros(n, 1, H, W)
    for i in range(n):
        top, left = (int(v) for v in torch.randint(4, 20, (2,), generator=g))
        mask[i, 0, top : top + 16 + 2 * i, left : left + 20] = 1
    image = torch.cat([mask, torch.zeros_like(mask), 1 - mask], dim=1)
    prior = torch.roll(mask, 3, dims=-1)
    return {
        "image": image,
        "mask": mask,
        "prior": prior,
        "visible": torch.ones(n, dtype=torch.bool),
        "index": torch.arange(n),
    }


def interior(m: torch.Tensor) -> torch.Tensor:
    """Pixels whose whole 3×3 neighbourhood is 1 in the {0,1} map ``m`` [B,1,H,W]; frame-border
    pixels never count (there bilinear sampling meets the zero padding)."""
    return (-F.max_pool2d(-F.pad(m, (1, 1, 1, 1)), 3, stride=1)) > 0.5


def assert_aligned(batch: dict[str, torch.Tensor], robot_red: float = 0.9) -> None:
    red, mask = batch["image"][:, :1], batch["mask"]
    assert set(mask.unique().tolist()) <= {0.0, 1.0}
    assert (red[interior(mask)] > robot_red).all()
    assert (red[interior(1 - mask)] < 0.1).all()


# --- geometric ---------------------------------------------------------------------------


def test_affine_matrix_hand_values():
    # translation by (+2, +1) pixels
    m = affine_matrix(torch.tensor([0.0]), torch.tensor([[2.0, 1.0]]), torch.ones(1, 2), (3, 2))
    torch.testing.assert_close(m[0], torch.tensor([[1.0, 0, 2], [0, 1, 1]]))
    # 90° counter-clockwise on screen about (3, 2): (4, 2) (right of centre) → (3, 1) (above)
    m = affine_matrix(torch.tensor([90.0]), torch.zeros(1, 2), torch.ones(1, 2), (3, 2))
    p = m[0, :, :2] @ torch.tensor([4.0, 2.0]) + m[0, :, 2]
    torch.testing.assert_close(p, torch.tensor([3.0, 1.0]), atol=1e-5, rtol=0)
    # scale 2 about the centre keeps the centre fixed and doubles offsets
    m = affine_matrix(torch.tensor([0.0]), torch.zeros(1, 2), torch.full((1, 2), 2.0), (3, 2))
    p = m[0, :, :2] @ torch.tensor([4.0, 3.0]) + m[0, :, 2]
    torch.testing.assert_close(p, torch.tensor([5.0, 4.0]))


def test_flip_moves_image_mask_and_prior_together():
    batch = painted_batch()
    flip = torch.tensor([True, False, True, False])
    out = HorizontalFlip().apply(batch, flip)
    for key in ("image", "mask", "prior"):
        assert torch.equal(out[key][0], batch[key][0].flip(-1))
        assert torch.equal(out[key][1], batch[key][1])
    assert_aligned(out)


def test_affine_keeps_mask_on_the_robot_pixels_and_binary():
    batch = painted_batch()
    affine = ConditionalAffine(p=1.0, degrees=30, translate=0.1, scale=(1.0, 1.8))
    params = affine.sample(batch["visible"], H, W, gen(3))
    assert params["apply"].all()
    out = affine.apply(batch, params)
    assert not torch.equal(out["mask"], batch["mask"])
    assert_aligned(out)
    assert set(out["prior"].unique().tolist()) <= {0.0, 1.0}
    # the prior moved with the same warp: warping the source prior on its own gives the same
    alone = affine.apply({"image": batch["image"], "mask": batch["prior"]}, params)
    assert torch.equal(out["prior"], alone["mask"])


def test_affine_never_touches_samples_with_a_cut_robot():
    batch = painted_batch()
    batch["visible"] = torch.tensor([True, False, True, False])
    affine = ConditionalAffine(p=1.0)
    for seed in range(10):
        params = affine.sample(batch["visible"], H, W, gen(seed))
        assert not params["apply"][~batch["visible"]].any()
        out = affine(batch, gen(seed))
        for key in ("image", "mask", "prior"):
            assert torch.equal(out[key][1], batch[key][1])
            assert torch.equal(out[key][3], batch[key][3])
        assert not torch.equal(out["mask"][0], batch["mask"][0])


def test_affine_scale_range_is_the_papers_and_validated():
    affine = ConditionalAffine(p=1.0, degrees=0.0, translate=0.0)
    m = affine.sample(torch.ones(500, dtype=torch.bool), H, W, gen())["matrix"]
    s = m[:, 0, 0]
    assert s.min() >= 1.0 and s.max() <= 1.8 and s.max() > 1.7 and s.min() < 1.1
    torch.testing.assert_close(m[:, 0, 0], m[:, 1, 1])  # isotropic by default
    with pytest.raises(ValueError, match="scale range"):
        ConditionalAffine(scale=(1.8, 1.0))


# --- cut-mix-merge ------------------------------------------------------------------------


def test_cmm_label_is_the_union_and_pixels_come_from_the_right_images():
    batch = painted_batch()
    g = torch.Generator().manual_seed(0)
    batch["image"] = torch.rand(4, 3, H, W, generator=g)
    perm = torch.tensor([2, 0, 3, 1])
    out = CutMixMerge(p=1.0).apply(batch, perm)
    for i, j in enumerate(perm.tolist()):
        guest = batch["mask"][j, 0] > 0.5
        assert torch.equal(out["mask"][i], torch.maximum(batch["mask"][i], batch["mask"][j]))
        assert torch.equal(out["prior"][i], torch.maximum(batch["prior"][i], batch["prior"][j]))
        assert torch.equal(out["image"][i][:, guest], batch["image"][j][:, guest])
        assert torch.equal(out["image"][i][:, ~guest], batch["image"][i][:, ~guest])
    assert torch.equal(out["index"], batch["index"])


def test_cmm_pastes_the_guests_kind_of_label_with_its_robot():
    batch = painted_batch()
    batch["draped"] = draped_map(torch.tensor([True, False, True, False]), (H, W))
    perm = torch.tensor([1, 0, 3, 2])
    out = CutMixMerge(p=1.0).apply(batch, perm)
    for i, j in enumerate(perm.tolist()):
        guest = batch["mask"][j, 0] > 0.5
        assert torch.equal(out["draped"][i, 0][guest], batch["draped"][j, 0][guest])
        assert torch.equal(out["draped"][i, 0][~guest], batch["draped"][i, 0][~guest])
    assert 0 < out["draped"][0].mean() < 1  # a draped frame hosting an undraped robot


def test_pipeline_moves_the_kind_of_label_with_the_mask():
    batch = painted_batch(8)
    flags = torch.tensor([True, False] * 4)
    batch["draped"] = flags
    pipe = AugmentationPipeline(HorizontalFlip(1.0), None, None, None,
                                crop=RobotCrop((H // 2, W // 2), p_robot=1.0))
    out = pipe(batch, gen(3))
    assert out["draped"].shape == out["mask"].shape
    # no merge: every pixel keeps its own frame's kind
    assert torch.equal(out["draped"].amax((1, 2, 3)).bool(), flags)
    assert torch.equal(out["draped"].amin((1, 2, 3)).bool(), flags)
    with pytest.raises(ValueError, match="draped must be"):
        draped_map(torch.zeros(2, 3), (H, W))


def test_cmm_probability_and_permutation():
    assert CutMixMerge(p=0.0).sample(4, gen()) is None
    perm = CutMixMerge(p=1.0).sample(6, gen())
    assert sorted(perm.tolist()) == list(range(6))
    hits = sum(CutMixMerge(p=0.3).sample(4, g) is not None for g in [gen(s) for s in range(400)])
    assert 80 < hits < 160
    with pytest.raises(ValueError, match="probability"):
        CutMixMerge(p=1.5)


def test_cmm_visible_flag_needs_both_robots():
    batch = painted_batch()
    batch["visible"] = torch.tensor([True, False, True, True])
    out = CutMixMerge(1.0).apply(batch, torch.tensor([1, 0, 3, 2]))
    assert out["visible"].tolist() == [False, False, True, True]


# --- photometric --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "op", [ColorJitter(1.0), Grayscale(1.0), BoxBlur(1.0), Contrast(1.0), SaltAndPepper(1.0),
           GaussianNoise(1.0), ChannelDropout(1.0)], ids=lambda o: type(o).__name__,
)
def test_each_photometric_op_changes_rgb_and_stays_in_range(op):
    rgb = torch.rand(3, 3, H, W, generator=gen(1))
    out = op.apply(rgb, op.sample(rgb.shape, gen(2)))
    assert out.shape == rgb.shape and not torch.equal(out, rgb)
    assert out.min() >= 0 and out.max() <= 1
    skip = type(op)(0.0) if not isinstance(op, ColorJitter) else ColorJitter(0.0)
    assert torch.equal(skip.apply(rgb, skip.sample(rgb.shape, gen(2))), rgb)


def test_photometric_op_semantics():
    rgb = torch.rand(2, 3, H, W, generator=gen(1))
    gray = Grayscale(1.0).apply(rgb, {"apply": torch.ones(2, dtype=torch.bool)})
    assert torch.equal(gray[:, 0], gray[:, 1]) and torch.equal(gray[:, 1], gray[:, 2])
    drop = ChannelDropout(1.0)
    params = {"apply": torch.ones(2, dtype=torch.bool), "channel": torch.tensor([0, 2])}
    out = drop.apply(rgb, params)
    assert not out[0, 0].any() and torch.equal(out[0, 1:], rgb[0, 1:])
    assert not out[1, 2].any() and torch.equal(out[1, :2], rgb[1, :2])
    sp = SaltAndPepper(1.0)
    prm = sp.sample(rgb.shape, gen(5))
    out = sp.apply(rgb, prm)
    noisy = prm["noisy"].expand_as(rgb)
    assert set(out[noisy].unique().tolist()) <= {0.0, 1.0}
    assert torch.equal(out[~noisy], rgb[~noisy])
    assert 0.005 < prm["noisy"].float().mean() < 0.07
    box = BoxBlur(1.0).apply(rgb, {"apply": torch.ones(2, dtype=torch.bool)})
    torch.testing.assert_close(box[0, 0, 10, 10], rgb[0, 0, 9:12, 9:12].mean())


def test_photometrics_spare_mask_and_prior_and_clamp():
    batch = painted_batch()
    batch["image"] = torch.rand(4, 3, H, W, generator=gen(4))
    out = Photometric(paper_ops(p=1.0))(batch, gen(0))
    assert torch.equal(out["prior"], batch["prior"]) and torch.equal(out["mask"], batch["mask"])
    assert out["image"].min() >= 0 and out["image"].max() <= 1
    assert not torch.equal(out["image"], batch["image"])


# --- the pipeline -------------------------------------------------------------------------


def full_pipeline(seed: int = 0) -> AugmentationPipeline:
    return AugmentationPipeline(
        HorizontalFlip(0.5), ConditionalAffine(0.5), CutMixMerge(1.0), Photometric(), seed=seed
    )


def test_pipeline_is_deterministic_per_seed_and_keeps_ranges():
    batch = painted_batch(8)
    a, b, c = full_pipeline(7)(batch), full_pipeline(7)(batch), full_pipeline(8)(batch)
    for key in ("image", "mask", "prior", "visible"):
        assert torch.equal(a[key], b[key])
    assert not torch.equal(a["image"], c["image"])
    assert a["image"].min() >= 0 and a["image"].max() <= 1
    for key in ("mask", "prior"):
        assert set(a[key].unique().tolist()) <= {0.0, 1.0}
    pipe = full_pipeline(7)
    first = pipe(batch)
    second = pipe(batch)  # the stream goes on
    assert not torch.equal(first["image"], second["image"])
    pipe.reseed(7)
    assert torch.equal(pipe(batch)["image"], first["image"])


def test_pipeline_without_photometrics_keeps_mask_on_robot_and_fills_defaults():
    batch = painted_batch(8)
    del batch["prior"], batch["visible"]
    pipe = AugmentationPipeline(HorizontalFlip(0.5), ConditionalAffine(1.0), CutMixMerge(1.0))
    out = pipe(batch)
    # a pasted robot's edge pixels carry its own bilinear blend (nearest source pixel ≥ 1/4)
    assert_aligned(out, robot_red=0.24)
    assert not out["prior"].any() and out["visible"].dtype == torch.bool


def test_model_input_normalises_rgb_and_appends_the_raw_prior():
    image = torch.full((2, 3, 4, 4), 0.75)
    prior = torch.zeros(2, 1, 4, 4)
    prior[:, :, :2] = 1
    x = to_model_input(image, prior, (0.5, 0.5, 0.25), (0.25, 0.5, 0.5), 4)
    assert x.shape == (2, 4, 4, 4)
    torch.testing.assert_close(x[:, 0], torch.full((2, 4, 4), 1.0))
    torch.testing.assert_close(x[:, 2], torch.full((2, 4, 4), 1.0))
    assert torch.equal(x[:, 3:], prior)
    assert to_model_input(image, prior, (0.5,) * 3, (0.5,) * 3, 3).shape == (2, 3, 4, 4)
    assert not to_model_input(image, None, (0.5,) * 3, (0.5,) * 3, 4)[:, 3].any()
    x, y = prepare({"image": image, "mask": prior, "prior": prior}, (0,) * 3, (1,) * 3, 3)
    assert torch.equal(y, prior) and torch.equal(x, image)


# --- in-context prior ----------------------------------------------------------------------


def test_axis_angle_hand_values():
    r = axis_angle_to_matrix(torch.tensor([[0.0, 0.0, math.pi / 2]]))[0]
    torch.testing.assert_close(r @ torch.tensor([1.0, 0, 0]), torch.tensor([0.0, 1, 0]))
    r = axis_angle_to_matrix(torch.tensor([[math.pi, 0.0, 0.0]]))[0]
    torch.testing.assert_close(r, torch.diag(torch.tensor([1.0, -1, -1])), atol=1e-6, rtol=0)


def test_perturbations_are_exactly_five_degrees_and_within_five_cm():
    dr, dx = sample_pose_perturbation(2000, gen(0), dtype=torch.float64)
    angle = torch.rad2deg(torch.acos((dr.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2))
    torch.testing.assert_close(angle, torch.full_like(angle, 5.0), atol=1e-6, rtol=0)
    torch.testing.assert_close(dr @ dr.transpose(-1, -2), torch.eye(3).expand(2000, 3, 3).double())
    assert (dx >= 0).all() and (dx <= 0.05).all()
    assert dx.mean(0).sub(0.025).abs().max() < 0.002
    axis = torch.stack([dr[:, 2, 1] - dr[:, 1, 2], dr[:, 0, 2] - dr[:, 2, 0],
                        dr[:, 1, 0] - dr[:, 0, 1]], -1)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    assert axis.mean(0).abs().max() < 0.06  # uniform on the sphere: no preferred direction
    again = sample_pose_perturbation(2000, gen(0), dtype=torch.float64)
    assert torch.equal(again[0], dr) and torch.equal(again[1], dx)


def test_perturb_pose_and_transform_points_hand_values():
    T = torch.eye(4).unsqueeze(0)
    T[0, :3, 3] = torch.tensor([0.0, 0.0, 2.0])
    rz = axis_angle_to_matrix(torch.tensor([[0.0, 0.0, math.pi / 2]]))
    T2 = perturb_pose(T, rz, torch.tensor([[0.01, 0.0, 0.0]]))
    p = transform_points(T2, torch.tensor([[[1.0, 0.0, 0.0]]]))
    # base point (1,0,0) turns to (0,1,0) about the base origin, then t + Δx = (0.01, 0, 2)
    torch.testing.assert_close(p[0, 0], torch.tensor([0.01, 1.0, 2.0]))


def splat_renderer(verts_cam, faces, K, height, width):
    """A tiny stand-in rasteriser: marks the pixel nearest to each projected vertex."""
    uv = verts_cam[..., :2] / verts_cam[..., 2:] * torch.stack([K[0, 0], K[1, 1]]) + K[:2, 2]
    out = torch.zeros(verts_cam.shape[0], height, width, dtype=torch.bool)
    for b in range(verts_cam.shape[0]):
        u, v = uv[b].round().long().unbind(-1)
        out[b, v.clamp(0, height - 1), u.clamp(0, width - 1)] = True
    return out


def test_in_context_prior_renders_at_the_perturbed_pose():
    K = torch.tensor([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    verts = torch.zeros(2, 1, 3)  # the base origin
    T = torch.eye(4).repeat(2, 1, 1)
    T[:, 2, 3] = 1.0  # 1 m in front of the camera
    prior = InContextPrior(renderer=splat_renderer)
    params = {"delta_r": torch.eye(3).repeat(2, 1, 1),
              "delta_x": torch.tensor([[0.05, 0.0, 0.0], [0.0, 0.03, 0.0]])}
    out = prior.apply(verts, torch.zeros(0, 3, dtype=torch.long), K, T, H, W, params)
    assert out.shape == (2, 1, H, W) and out.dtype == torch.float32
    # 5 cm right at 1 m, f = 100 px → 5 px right of the principal point (31.5 → 36.5 ≈ 36/37)
    v, u = torch.nonzero(out[0, 0])[0].tolist()
    assert v == 24 and u in (36, 37)
    v, u = torch.nonzero(out[1, 0])[0].tolist()
    assert v in (26, 27) and u in (31, 32)
    drawn = prior(verts, torch.zeros(0, 3, dtype=torch.long), K, T, H, W, gen(0))
    assert drawn.sum() == 2


def test_in_context_prior_with_the_project_rasteriser():
    raster = pytest.importorskip("roboseg.render.raster", reason="rasteriser not available")
    # a 20 cm square (two triangles) facing the camera, 1 m ahead, base frame = camera frame
    verts = torch.tensor([[[-0.1, -0.1, 0.0], [0.1, -0.1, 0.0], [0.1, 0.1, 0.0],
                           [-0.1, 0.1, 0.0]]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    K = torch.tensor([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    T = torch.eye(4).unsqueeze(0)
    T[0, 2, 3] = 1.0
    prior = InContextPrior(renderer=raster.render_hard)
    still = {"delta_r": torch.eye(3).unsqueeze(0), "delta_x": torch.zeros(1, 3)}
    moved = {"delta_r": torch.eye(3).unsqueeze(0), "delta_x": torch.tensor([[0.05, 0.0, 0.0]])}
    a = prior.apply(verts, faces, K, T, H, W, still)
    b = prior.apply(verts, faces, K, T, H, W, moved)
    assert a.shape == (1, 1, H, W) and set(a.unique().tolist()) == {0.0, 1.0}
    # ±10 cm at 1 m with f = 100 px → columns 21.5..41.5, i.e. 20 pixels wide; +5 cm → +5 px
    assert int(a[0, 0, 23].sum()) == 20 and int(b[0, 0, 23].sum()) == 20
    cols_a = torch.nonzero(a[0, 0, 23]).flatten()
    cols_b = torch.nonzero(b[0, 0, 23]).flatten()
    assert int(cols_b.min() - cols_a.min()) == 5


def test_in_context_prior_renders_many_views_at_once_as_unions_per_sample():
    raster = pytest.importorskip("roboseg.render.raster", reason="rasteriser not available")
    square = torch.tensor([[-0.1, -0.1, 0.0], [0.1, -0.1, 0.0], [0.1, 0.1, 0.0],
                           [-0.1, 0.1, 0.0]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    K = torch.tensor([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]]).expand(3, 3, 3)
    T = torch.eye(4).repeat(3, 1, 1)
    T[:, 2, 3] = 1.0
    params = {"delta_r": torch.eye(3).repeat(3, 1, 1),
              "delta_x": torch.tensor([[0.0, 0.0, 0.0], [0.15, 0.0, 0.0], [0.0, 0.1, 0.0]])}
    prior = InContextPrior(renderer=raster.render_hard)
    verts = square.expand(3, 4, 3)
    # views 0 and 1 (two robots) belong to sample 0, view 2 to sample 2; sample 1 has none
    out = prior.render_union(verts, faces, K, T, H, W, params, torch.tensor([0, 0, 2]), 3)
    each = prior.apply(verts, faces, K, T, H, W, params)
    assert out.shape == (3, 1, H, W) and out.dtype == torch.float32
    assert torch.equal(out[0], torch.maximum(each[0], each[1])) and not out[1].any()
    assert torch.equal(out[2], each[2])
    assert int(out[0, 0, 23].sum()) == 35  # two 20-px squares 15 px apart: 35 columns
    empty = prior.render_union(verts[:0], faces, K[:0], T[:0], H, W,
                               {k: v[:0] for k, v in params.items()},
                               torch.zeros(0, dtype=torch.long), 2)
    assert empty.shape == (2, 1, H, W) and not empty.any()


# --- training crops and the augmentation ramp ------------------------------------------------


def test_robot_crop_cuts_image_mask_and_prior_alike():
    batch = painted_batch(6)
    crop = RobotCrop((24, 32), p_robot=1.0, jitter=0.0)
    corners = crop.sample(batch["mask"], gen(3))
    out = crop.apply(batch, corners)
    for i, (top, left) in enumerate(corners.tolist()):
        assert 0 <= top <= H - 24 and 0 <= left <= W - 32
        for key in ("image", "mask", "prior"):
            assert torch.equal(out[key][i], batch[key][i, :, top:top + 24, left:left + 32])
        assert out["mask"][i].sum() > 0  # centred on a robot pixel
    # the robot of sample 0 (16x20 px) fits a 24x32 window centred on one of its pixels only
    # when that pixel lies near its middle; visible stays true exactly when nothing was cut
    whole = batch["mask"].flatten(1).sum(1) == out["mask"].flatten(1).sum(1)
    assert torch.equal(out["visible"], whole)


def test_robot_crop_centres_on_robot_pixels_with_probability_p():
    batch = painted_batch(4)
    mask = torch.zeros(400, 1, H, W)
    mask[:, :, 40:44, 56:60] = 1  # a small robot in the bottom-right corner
    far = RobotCrop((16, 16), p_robot=0.0).sample(mask, gen(0))
    near = RobotCrop((16, 16), p_robot=1.0, jitter=0.0).sample(mask, gen(0))
    hit = lambda c: ((c[:, 0] <= 40) & (c[:, 0] + 16 >= 44) & (c[:, 1] <= 56)  # noqa: E731
                     & (c[:, 1] + 16 >= 60)).float().mean()
    assert hit(near) == 1.0
    assert hit(far) < 0.2  # uniform windows seldom hold it
    with pytest.raises(ValueError, match="larger than the frames"):
        RobotCrop((H + 1, 8)).sample(batch["mask"], gen(0))


def test_ramp_gates_the_ramped_steps_by_training_step():
    batch = painted_batch(4)
    pipe = AugmentationPipeline(photometric=Photometric([Grayscale(p=1.0)]), ramp_steps=100)
    pipe.set_step(0)
    assert pipe.strength() == 0.0
    assert torch.equal(pipe(batch, gen(0))["image"], batch["image"])  # nothing applied yet
    pipe.set_step(100)
    assert pipe.strength() == 1.0
    assert not torch.equal(pipe(batch, gen(0))["image"], batch["image"])
    pipe.set_step(50)
    changed = [not torch.equal(pipe(batch, gen(s))["image"], batch["image"]) for s in range(200)]
    assert 0.35 < sum(changed) / len(changed) < 0.65
    with pytest.raises(ValueError):
        AugmentationPipeline(ramp_steps=-1)
