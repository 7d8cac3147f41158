"""The batch-level augmentation of the paper, in its order, and the model-input builder.

Order (paper, Methods): the in-context prior is already in the batch (rendered at a perturbed
pose where the batch is built, step 1), then (2) geometric: flip for any sample, affine only for
entirely visible robots; (3) cut-mix-merge; (4) photometric on the RGB channels. The model input
is the normalised RGB image, plus the prior (unnormalised, in [0, 1]) as 4th channel for
4-channel models; the target is the mask.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from roboseg.augment.cmm import CutMixMerge
from roboseg.augment.geometric import ConditionalAffine, HorizontalFlip, RobotCrop
from roboseg.augment.photometric import Photometric

Batch = dict[str, torch.Tensor]

#: ImageNet statistics, the usual normalisation of smp encoders (RGB, values in [0, 1]).
IMAGENET_MEAN: tuple[float, float, float] = (0.485, 0.456, 0.406)
IMAGENET_STD: tuple[float, float, float] = (0.229, 0.224, 0.225)


class AugmentationPipeline(nn.Module):
    """Steps (2)-(4) on a batch dict; a step given as None is skipped.

    ``crop`` (optional, first) cuts training windows out of larger frames (:class:`RobotCrop`).
    ``ramp_steps`` > 0 ramps the augmentation in: at training step ``t`` (see :meth:`set_step`)
    the affine, cut-mix-merge and photometric steps each run on a batch with probability
    ``min(1, t / ramp_steps)`` (crop and flip always run); 0 gives the paper's strength from the
    first step.

    Random draws come from a ``torch.Generator`` on the batch's device seeded with ``seed``
    (see :meth:`reseed`), or from the generator passed to :meth:`forward`.
    """

    def __init__(
        self,
        flip: HorizontalFlip | None = None,
        affine: ConditionalAffine | None = None,
        cmm: CutMixMerge | None = None,
        photometric: Photometric | None = None,
        seed: int = 0,
        crop: RobotCrop | None = None,
        ramp_steps: int = 0,
    ) -> None:
        super().__init__()
        if ramp_steps < 0:
            raise ValueError(f"ramp_steps must be >= 0, got {ramp_steps}")
        self.crop, self.ramp_steps, self.step = crop, int(ramp_steps), 0
        self.flip, self.affine, self.cmm, self.photometric = flip, affine, cmm, photometric
        self.seed = int(seed)
        self._generators: dict[str, torch.Generator] = {}

    @property
    def uses_cmm(self) -> bool:
        """Whether cut-mix-merge can happen (a Table S4 column)."""
        return self.cmm is not None and self.cmm.p > 0

    def set_step(self, step: int) -> None:
        """The training step the next batches belong to (drives :meth:`strength`)."""
        self.step = int(step)

    def strength(self) -> float:
        """Probability in [0, 1] that each ramped step runs on the current batch."""
        return 1.0 if self.ramp_steps <= 0 else min(1.0, self.step / self.ramp_steps)

    def reseed(self, seed: int) -> None:
        """Restart the random streams from ``seed`` (e.g. base seed + DDP rank)."""
        self.seed = int(seed)
        self._generators.clear()

    def generator_for(self, device: torch.device | str) -> torch.Generator:
        """This pipeline's generator on ``device`` (created and seeded on first use)."""
        device = torch.device(device)
        key = str(device)
        if key not in self._generators:
            gen = torch.Generator(device=device)
            gen.manual_seed(self.seed)
            self._generators[key] = gen
        return self._generators[key]

    @torch.no_grad()
    def forward(self, batch: Batch, generator: torch.Generator | None = None) -> Batch:
        """The augmented batch (same keys, shapes and value ranges as the input)."""
        gen = generator if generator is not None else self.generator_for(batch["image"].device)
        out = dict(batch)
        out.setdefault("prior", torch.zeros_like(batch["mask"]))
        out.setdefault("visible", torch.ones(batch["image"].shape[0], dtype=torch.bool,
                                             device=batch["image"].device))
        if "draped" in out:
            out["draped"] = draped_map(out["draped"], batch["image"].shape[-2:])
        strength = self.strength()
        for step in (self.crop, self.flip, self.affine, self.cmm, self.photometric):
            if step is None:
                continue
            ramped = step is not self.crop and step is not self.flip
            if ramped and strength < 1.0:
                gate = torch.rand((), generator=gen, device=gen.device)
                if float(gate) >= strength:
                    continue
            out = step(out, gen)
        return out


def draped_map(draped: torch.Tensor, size: Sequence[int]) -> torch.Tensor:
    """The kind of label per pixel, float ``[B,1,H,W]`` (1: draped frame), from per-sample
    flags ``[B]`` (a map passes unchanged): the geometric steps move it with the mask and
    cut-mix-merge pastes it with the robot, so every pixel keeps the kind of its frame."""
    if draped.dim() == 4:
        return draped
    if draped.dim() != 1:
        raise ValueError(f"draped must be [B] flags or a [B,1,H,W] map, got {tuple(draped.shape)}")
    h, w = int(size[0]), int(size[1])
    return draped.float().view(-1, 1, 1, 1).expand(-1, 1, h, w).contiguous()


def to_model_input(
    image: torch.Tensor,
    prior: torch.Tensor | None,
    mean: Sequence[float],
    std: Sequence[float],
    in_channels: int,
) -> torch.Tensor:
    """``[B, in_channels, H, W]``: ``(image - mean) / std`` then, for 4 channels, the prior.

    ``image`` is RGB ``[B,3,H,W]`` in [0, 1]; ``prior`` ``[B,1,H,W]`` in [0, 1] or None (zeros).
    """
    m = torch.as_tensor(mean, dtype=image.dtype, device=image.device).view(1, 3, 1, 1)
    s = torch.as_tensor(std, dtype=image.dtype, device=image.device).view(1, 3, 1, 1)
    x = (image - m) / s
    if in_channels == 3:
        return x
    if in_channels != 4:
        raise ValueError(f"in_channels must be 3 or 4, got {in_channels}")
    if prior is None:
        prior = image.new_zeros(image.shape[0], 1, *image.shape[-2:])
    return torch.cat([x, prior.to(image.dtype)], dim=1)


def prepare(
    batch: Batch, mean: Sequence[float], std: Sequence[float], in_channels: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Model input (:func:`to_model_input`) and target mask ``[B,1,H,W]`` of a batch dict."""
    x = to_model_input(batch["image"], batch.get("prior"), mean, std, in_channels)
    return x, batch["mask"].to(x.dtype)
