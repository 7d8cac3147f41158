"""Focal + Dice loss against hand-computed values on 2×2 examples."""

from __future__ import annotations

import math

import pytest
import torch

from roboseg.losses import FocalDiceLoss, dice_loss, focal_loss

LN3 = math.log(3.0)
# logits 0, 0, ln 3, -ln 3  →  p = 0.5, 0.5, 0.75, 0.25
LOGITS = torch.tensor([[[[0.0, 0.0], [LN3, -LN3]]]])
TARGET = torch.tensor([[[[1.0, 0.0], [1.0, 0.0]]]])


def test_focal_matches_hand_computation():
    # p_t = 0.5, 0.5, 0.75, 0.75; α_t = 0.25, 0.75, 0.25, 0.75; FL = α_t (1-p_t)^2 (-ln p_t)
    terms = [
        0.25 * 0.25 * math.log(2),
        0.75 * 0.25 * math.log(2),
        0.25 * 0.0625 * math.log(4 / 3),
        0.75 * 0.0625 * math.log(4 / 3),
    ]
    expected = sum(terms) / 4  # = 0.0478167...
    assert expected == pytest.approx(0.0478167, abs=1e-6)
    assert focal_loss(LOGITS, TARGET).item() == pytest.approx(expected, rel=1e-6)


def test_focal_gamma_zero_alpha_half_is_half_bce():
    bce = torch.nn.functional.binary_cross_entropy_with_logits(LOGITS, TARGET)
    assert focal_loss(LOGITS, TARGET, alpha=0.5, gamma=0.0).item() == pytest.approx(
        0.5 * bce.item(), rel=1e-6
    )


def test_dice_matches_hand_computation():
    # Σp = 2, Σy = 2, Σp·y = 0.5 + 0.75 = 1.25 → Dice = 2.5 / 4 = 0.625
    assert dice_loss(LOGITS, TARGET).item() == pytest.approx(0.375, abs=1e-6)


def test_per_image_versus_batch_dice():
    # image 0: small robot, perfectly predicted; image 1: large robot, prediction misses half.
    big = 20.0
    logits = torch.full((2, 1, 2, 2), -big)
    target = torch.zeros(2, 1, 2, 2)
    target[0, 0, 0, 0] = 1
    logits[0, 0, 0, 0] = big
    target[1] = 1
    logits[1, 0, 0] = big  # top row right, bottom row wrong
    # per image: dice0 = 1, dice1 = 2·2 / (2 + 4) = 2/3 → loss = (0 + 1/3) / 2 = 1/6
    assert dice_loss(logits, target, per_image=True).item() == pytest.approx(1 / 6, abs=1e-5)
    # batch: Σp·y = 3, Σp = 3, Σy = 5 → 1 - 6/8 = 0.25
    assert dice_loss(logits, target, per_image=False).item() == pytest.approx(0.25, abs=1e-5)


def test_empty_targets_leave_dice_to_the_focal_term():
    logits = torch.tensor([[[[2.0, -2.0], [0.0, 0.0]]]], requires_grad=True)
    empty = torch.zeros_like(logits)
    assert dice_loss(logits, empty).item() == 0.0
    loss = FocalDiceLoss()(logits, empty)
    loss.backward()
    # focal still pushes the false positive down
    assert loss.item() == pytest.approx(0.3 * focal_loss(logits, empty).item(), rel=1e-6)
    assert logits.grad[0, 0, 0, 0] > 0


def test_weighted_sum_and_shape_check():
    loss = FocalDiceLoss(w_focal=0.3, w_dice=0.7)(LOGITS, TARGET)
    expected = 0.3 * focal_loss(LOGITS, TARGET).item() + 0.7 * 0.375
    assert loss.item() == pytest.approx(expected, rel=1e-6)
    with pytest.raises(ValueError, match="differ"):
        FocalDiceLoss()(LOGITS, TARGET[..., :1])


def test_extreme_logits_stay_finite():
    logits = torch.tensor([[[[1e4, -1e4], [1e4, -1e4]]]], requires_grad=True)
    loss = FocalDiceLoss()(logits, TARGET)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(logits.grad).all()


def test_undraped_frames_take_their_own_focal_balance():
    # two copies of the 2×2 example: image 0 draped (α 0.25), image 1 undraped (α 0.5)
    logits, target = LOGITS.repeat(2, 1, 1, 1), TARGET.repeat(2, 1, 1, 1)
    loss = FocalDiceLoss(w_focal=1.0, w_dice=0.0, alpha_undraped=0.5)
    # α = 0.5 on every pixel: FL = 0.5 (1-p_t)^2 (-ln p_t), two pixels at p_t = 1/2 and two at
    # 3/4 → mean 0.5·(2·0.25 ln 2 + 2·0.0625 ln 4/3)/4
    half = 0.5 * (2 * 0.25 * math.log(2) + 2 * 0.0625 * math.log(4 / 3)) / 4
    expected = (0.0478167 + half) / 2
    flags = torch.tensor([True, False])
    assert loss(logits, target, flags).item() == pytest.approx(expected, rel=1e-5)
    per_pixel = flags.float().view(2, 1, 1, 1).expand(2, 1, 2, 2)
    assert loss(logits, target, per_pixel).item() == pytest.approx(expected, rel=1e-5)
    # without flags, or without alpha_undraped, every pixel takes alpha
    assert loss(logits, target).item() == pytest.approx(0.0478167, rel=1e-5)
    same = FocalDiceLoss(w_focal=1.0, w_dice=0.0)(logits, target, flags)
    assert same.item() == pytest.approx(0.0478167, rel=1e-5)
    with pytest.raises(ValueError, match="alpha_undraped must be in"):
        FocalDiceLoss(alpha_undraped=1.5)
