"""Segmentation loss of the paper: L = w_focal · L_focal(α, γ) + w_dice · L_dice, on logits.

Focal term (Lin et al., α-balanced): per pixel ``FL = -α_t (1 - p_t)^γ log p_t`` with
``p_t = p`` and ``α_t = α`` on robot pixels, ``p_t = 1 - p`` and ``α_t = 1 - α`` on background,
averaged over all pixels of the batch.

Dice term: soft Dice ``1 - (2 Σ p·y + ε) / (Σ p + Σ y + ε)`` on probabilities. With
``per_image=True`` (default) it is computed per image and averaged over the images whose target
is not empty: every frame counts the same whatever the robot's size on screen (a robot 2.6 m away
is as important as one filling the frame, like the per-frame IoU the models are judged by), and
frames without robot pixels are left to the focal term, which already penalises every false
positive there (a per-image Dice of an empty target would be 1 for almost any prediction).
With ``per_image=False`` the sums run over the whole batch (smp's binary ``DiceLoss``), which
lets large silhouettes dominate.

Two kinds of label: on a draped frame the label is the robot's silhouette *under* the drape, so
the visible drape around it is background; on an undraped frame the label's outline is the
robot's visible one. ``alpha_undraped`` (None: ``alpha`` everywhere) sets the focal balance of
the pixels of undraped frames apart (``draped``: float map ``[B,1,H,W]`` or flags ``[B]``, 1 on
draped frames).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def focal_loss(
    logits: torch.Tensor,
    target: torch.Tensor,
    alpha: float | torch.Tensor = 0.25,
    gamma: float = 2.0,
) -> torch.Tensor:
    """Mean α-balanced binary focal loss of ``logits`` against a {0,1} ``target`` (same shape);
    ``alpha`` a number or a tensor broadcasting to the target (α per pixel)."""
    target = target.to(logits.dtype)
    log_p = F.logsigmoid(logits)  # log p, numerically stable
    log_not_p = F.logsigmoid(-logits)  # log (1 - p)
    log_pt = target * log_p + (1 - target) * log_not_p
    alpha_t = target * alpha + (1 - target) * (1 - alpha)
    return (-alpha_t * (1 - log_pt.exp()).pow(gamma) * log_pt).mean()


def dice_loss(
    logits: torch.Tensor, target: torch.Tensor, per_image: bool = True, eps: float = 1e-6
) -> torch.Tensor:
    """Soft Dice loss of ``logits`` ``[B, ...]`` against a {0,1} ``target`` (see module doc)."""
    prob = torch.sigmoid(logits).flatten(1)
    target = target.to(prob.dtype).flatten(1)
    if not per_image:
        prob, target = prob.reshape(1, -1), target.reshape(1, -1)
    inter = (prob * target).sum(1)
    total = prob.sum(1) + target.sum(1)
    dice = 1 - (2 * inter + eps) / (total + eps)
    if per_image:
        has_robot = target.sum(1) > 0
        if not bool(has_robot.any()):
            return logits.sum() * 0.0  # keeps the graph; focal carries the signal
        dice = dice[has_robot]
    return dice.mean()


class FocalDiceLoss(nn.Module):
    """``w_focal · focal(α, γ) + w_dice · Dice`` on logits ``[B,1,H,W]``, targets {0,1} alike."""

    def __init__(
        self,
        w_focal: float = 0.3,
        w_dice: float = 0.7,
        alpha: float = 0.25,
        gamma: float = 2.0,
        per_image: bool = True,
        eps: float = 1e-6,
        alpha_undraped: float | None = None,
    ) -> None:
        super().__init__()
        for name, a in (("alpha", alpha), ("alpha_undraped", alpha_undraped)):
            if a is not None and not 0.0 <= float(a) <= 1.0:
                raise ValueError(f"loss {name} must be in [0, 1], got {a}")
        self.w_focal, self.w_dice = w_focal, w_dice
        self.alpha, self.gamma = alpha, gamma
        self.per_image, self.eps = per_image, eps
        self.alpha_undraped = None if alpha_undraped is None else float(alpha_undraped)

    def pixel_alpha(
        self, target: torch.Tensor, draped: torch.Tensor | None
    ) -> float | torch.Tensor:
        """The focal balance: ``alpha``, or per pixel ``alpha`` on draped frames' pixels and
        ``alpha_undraped`` on undraped ones (``draped`` flags ``[B]`` or a map like target)."""
        if self.alpha_undraped is None or draped is None:
            return self.alpha
        kind = draped.to(target.dtype)
        if kind.dim() == 1:
            kind = kind.view(-1, *([1] * (target.dim() - 1)))
        return self.alpha_undraped + (self.alpha - self.alpha_undraped) * kind

    def forward(
        self, logits: torch.Tensor, target: torch.Tensor, draped: torch.Tensor | None = None
    ) -> torch.Tensor:
        if logits.shape != target.shape:
            raise ValueError(
                f"logits {tuple(logits.shape)} and target {tuple(target.shape)} differ"
            )
        alpha = self.pixel_alpha(target, draped)
        focal = focal_loss(logits, target, alpha, self.gamma)
        dice = dice_loss(logits, target, self.per_image, self.eps)
        return self.w_focal * focal + self.w_dice * dice
