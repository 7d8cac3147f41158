"""Cut-mix-merge (paper step 3): paste each sample's robot into another image of the batch.

With ``j = shuffle(i)`` (a uniform permutation) the merged batch is
``I_i ← (1 - M'_j) ⊙ I'_i + M'_j ⊙ I'_j`` with label ``M_i ← M'_i ∨ M'_j``, where the primes mark
the geometrically augmented images and masks. The robot of ``j`` is pasted where it already
is in its own frame, so it stays physically placed (cut by the border only where it was).

The in-context prior is merged like the label, ``P_i ← P'_i ∨ P'_j``: the prior is a silhouette
at a pose estimate of the robots in view, and after the merge robot ``j`` is in view of image
``i`` at exactly the pixels of its own frame. A zero prior stays zero when merged with a zero
prior. ``visible`` becomes ``visible_i ∧ visible_j``; ``index`` keeps the host ``i``. The kind
of label per pixel (``draped`` ``[B,1,H,W]``) is pasted like the image: the guest's robot pixels
keep the guest frame's kind.
The whole batch is merged with probability ``p`` (``p = 0`` disables it).
"""

from __future__ import annotations

import torch
from torch import nn

Batch = dict[str, torch.Tensor]


def merge_images(host: torch.Tensor, guest: torch.Tensor, guest_mask: torch.Tensor) -> torch.Tensor:
    """``(1 - M) ⊙ host + M ⊙ guest`` for images ``[B,C,H,W]`` and a {0,1} mask ``[B,1,H,W]``."""
    return (1 - guest_mask) * host + guest_mask * guest


def union(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Pixel-wise OR of two {0,1} float maps (max, so soft maps stay in [0, 1])."""
    return torch.maximum(a, b)


class CutMixMerge(nn.Module):
    """Cut-mix-merge of a whole batch with probability ``p`` (see module doc)."""

    def __init__(self, p: float = 0.5) -> None:
        super().__init__()
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"cut-mix-merge probability must be in [0, 1], got {p}")
        self.p = p

    def sample(self, batch_size: int, generator: torch.Generator) -> torch.Tensor | None:
        """The permutation ``j = shuffle(i)`` (long ``[B]``), or None when the batch is skipped."""
        if self.p <= 0.0:
            return None
        draw = torch.rand(1, generator=generator, device=generator.device)
        if draw.item() >= self.p:
            return None
        return torch.randperm(batch_size, generator=generator, device=generator.device)

    @staticmethod
    def apply(batch: Batch, perm: torch.Tensor | None) -> Batch:
        """Merge sample ``perm[i]``'s robot into sample ``i`` (no-op for ``perm`` None)."""
        if perm is None:
            return dict(batch)
        perm = perm.to(batch["image"].device)
        guest_mask = batch["mask"][perm]
        out = dict(batch)
        out["image"] = merge_images(batch["image"], batch["image"][perm], guest_mask)
        out["mask"] = union(batch["mask"], guest_mask)
        if "prior" in batch:
            out["prior"] = union(batch["prior"], batch["prior"][perm])
        if "visible" in batch:
            out["visible"] = batch["visible"] & batch["visible"][perm]
        if "draped" in batch and batch["draped"].dim() == 4:
            out["draped"] = merge_images(batch["draped"], batch["draped"][perm], guest_mask)
        return out

    def forward(self, batch: Batch, generator: torch.Generator) -> Batch:
        return self.apply(batch, self.sample(batch["image"].shape[0], generator))
