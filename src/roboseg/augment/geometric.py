"""Geometric augmentation (paper step 2): unconditional flip, conditional affine.

The horizontal flip may hit any sample. The affine (rotation, translation, scale in [1.0, 1.8])
only hits samples whose robot is entirely visible (``batch["visible"]``): warping a robot cut by
the frame border would move the cut into the image. The image is resampled bilinearly, the mask
and the prior with nearest neighbour, so they stay binary; uncovered pixels become 0.

Pixel coordinates follow the project convention: integer coordinates are pixel centres, u is the
column (x), v the row (y, down). Angles are degrees, counter-clockwise as seen on screen.
"""

from __future__ import annotations

import torch
from kornia.geometry.transform import warp_affine
from torch import nn

Batch = dict[str, torch.Tensor]

#: Spatial entries of a batch and how each is resampled.
#: ``draped`` is the per-pixel kind of label (1: the pixel's frame is draped), see
#: :func:`roboseg.augment.pipeline.draped_map`.
SPATIAL_MODES: dict[str, str] = {"image": "bilinear", "mask": "nearest", "prior": "nearest",
                                 "draped": "nearest"}


def _uniform(
    n: int, low: float, high: float, generator: torch.Generator, dtype: torch.dtype
) -> torch.Tensor:
    """``n`` draws from U[low, high) on the generator's device."""
    u = torch.rand(n, generator=generator, device=generator.device, dtype=dtype)
    return low + (high - low) * u


class HorizontalFlip(nn.Module):
    """Mirror columns of image, mask and prior together, each sample with probability ``p``."""

    def __init__(self, p: float = 0.5) -> None:
        super().__init__()
        self.p = p

    def sample(self, batch_size: int, generator: torch.Generator) -> torch.Tensor:
        """Which samples flip: bool ``[B]``."""
        return torch.rand(batch_size, generator=generator, device=generator.device) < self.p

    @staticmethod
    def apply(batch: Batch, flip: torch.Tensor) -> Batch:
        """Flip the spatial entries of the samples selected by ``flip`` (bool ``[B]``)."""
        out = dict(batch)
        sel = flip.to(batch["image"].device).view(-1, 1, 1, 1)
        for key in SPATIAL_MODES:
            if key in batch:
                out[key] = torch.where(sel, batch[key].flip(-1), batch[key])
        return out

    def forward(self, batch: Batch, generator: torch.Generator) -> Batch:
        return self.apply(batch, self.sample(batch["image"].shape[0], generator))


def affine_matrix(
    angle_deg: torch.Tensor,
    translation: torch.Tensor,
    scale: torch.Tensor,
    center: tuple[float, float],
) -> torch.Tensor:
    """Forward pixel maps ``x' = R(θ) S (x - c) + c + t`` as ``[B, 2, 3]`` matrices.

    ``angle_deg`` ``[B]`` (counter-clockwise on screen), ``translation`` ``[B, 2]`` pixels
    (u, v), ``scale`` ``[B, 2]`` (s_u, s_v), ``center`` ``(u, v)`` pixels.
    """
    theta = torch.deg2rad(angle_deg)
    cos, sin = torch.cos(theta), torch.sin(theta)
    # y points down, so a counter-clockwise turn on screen is [[cos, sin], [-sin, cos]]
    rot = torch.stack([torch.stack([cos, sin], -1), torch.stack([-sin, cos], -1)], -2)
    lin = rot * scale.unsqueeze(-2)  # R @ diag(s)
    c = torch.tensor(center, dtype=lin.dtype, device=lin.device)
    offset = c + translation - (lin @ c.unsqueeze(-1)).squeeze(-1)
    return torch.cat([lin, offset.unsqueeze(-1)], dim=-1)


class ConditionalAffine(nn.Module):
    """Random affine warp, only for samples whose robot is entirely visible.

    Each visible sample is warped with probability ``p``: rotation U[-degrees, degrees] about the
    image centre, translation U[-translate, translate] × (W, H) pixels, scale U[scale]
    (the paper's [1.0, 1.8] offsets the 16:9 → 1:1 squash of training frames). With
    ``isotropic=False`` the column and row scales are drawn independently.
    """

    def __init__(
        self,
        p: float = 0.5,
        degrees: float = 20.0,
        translate: float = 0.1,
        scale: tuple[float, float] = (1.0, 1.8),
        isotropic: bool = True,
    ) -> None:
        super().__init__()
        if not 0 < scale[0] <= scale[1]:
            raise ValueError(f"affine scale range must be 0 < low <= high, got {tuple(scale)}")
        self.p, self.degrees, self.translate = p, degrees, translate
        self.scale = (float(scale[0]), float(scale[1]))
        self.isotropic = isotropic

    def sample(
        self, visible: torch.Tensor, height: int, width: int, generator: torch.Generator
    ) -> dict[str, torch.Tensor]:
        """Draw ``apply`` (bool ``[B]``, never true for a not-visible sample) and ``matrix``."""
        n, dtype = visible.shape[0], torch.float32
        chosen = torch.rand(n, generator=generator, device=generator.device) < self.p
        angle = _uniform(n, -self.degrees, self.degrees, generator, dtype)
        shift = torch.stack(
            [
                _uniform(n, -self.translate, self.translate, generator, dtype) * width,
                _uniform(n, -self.translate, self.translate, generator, dtype) * height,
            ],
            -1,
        )
        s_u = _uniform(n, *self.scale, generator, dtype)
        s_v = s_u if self.isotropic else _uniform(n, *self.scale, generator, dtype)
        center = ((width - 1) / 2.0, (height - 1) / 2.0)
        matrix = affine_matrix(angle, shift, torch.stack([s_u, s_v], -1), center)
        return {"apply": chosen & visible.to(chosen.device).bool(), "matrix": matrix}

    @staticmethod
    def apply(batch: Batch, params: dict[str, torch.Tensor]) -> Batch:
        """Warp the spatial entries of the selected samples; others pass unchanged."""
        out = dict(batch)
        idx = torch.nonzero(params["apply"], as_tuple=False).flatten().to(batch["image"].device)
        if idx.numel() == 0:
            return out
        matrix = params["matrix"].to(batch["image"].device)[idx]
        for key, mode in SPATIAL_MODES.items():
            if key not in batch:
                continue
            x = batch[key]
            h, w = x.shape[-2:]
            warped = warp_affine(
                x[idx], matrix.to(x.dtype), (h, w), mode=mode, padding_mode="zeros",
                align_corners=True,
            )
            out[key] = x.index_copy(0, idx, warped)
        return out

    def forward(self, batch: Batch, generator: torch.Generator) -> Batch:
        h, w = batch["image"].shape[-2:]
        return self.apply(batch, self.sample(batch["visible"], h, w, generator))


class RobotCrop(nn.Module):
    """A ``size = [h, w]`` window of every sample (image, mask, prior alike), for training on
    crops of a larger frame while the fully convolutional U-Net predicts whole frames.

    With probability ``p_robot`` a sample's window is centred on one of its robot pixels
    (uniformly drawn, so long links and near robots get most windows) shifted by up to
    ``jitter`` of the window size, else placed uniformly; windows stay inside the frame.
    ``visible`` stays true only where the whole robot of the frame lies inside the window.
    """

    def __init__(self, size: tuple[int, int] = (256, 256), p_robot: float = 0.8,
                 jitter: float = 0.35) -> None:
        super().__init__()
        if len(size) != 2 or min(int(v) for v in size) < 1:
            raise ValueError(f"crop size must be [h, w] > 0, got {list(size)}")
        if not 0.0 <= p_robot <= 1.0:
            raise ValueError(f"crop p_robot must be in [0, 1], got {p_robot}")
        self.size = (int(size[0]), int(size[1]))
        self.p_robot, self.jitter = float(p_robot), float(jitter)

    def sample(self, mask: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """Top-left corners ``[B, 2]`` (row, column; long) of the windows of masks ``[B,1,H,W]``."""
        n, (H, W), (h, w) = mask.shape[0], mask.shape[-2:], self.size
        if h > H or w > W:
            raise ValueError(f"crop {h}x{w} is larger than the frames ({H}x{W}); "
                             "lower the crop size or raise data.image_size")
        dev = generator.device
        u = torch.rand(n, 5, generator=generator, device=dev)
        top = (u[:, 0] * (H - h + 1)).long()
        left = (u[:, 1] * (W - w + 1)).long()
        flat = mask.to(dev).flatten(1) > 0.5
        counts = flat.sum(1)
        centred = (u[:, 2] < self.p_robot) & (counts > 0)
        if bool(centred.any()):
            # the k-th robot pixel of each sample, k uniform in [0, count)
            k = (u[:, 3] * counts.clamp(min=1)).long().clamp(max=flat.shape[1] - 1)
            rank = flat.cumsum(1) - 1
            pick = torch.argmax(((rank == k[:, None]) & flat).int(), dim=1)
            row, col = pick // W, pick % W
            shift = ((u[:, 4] - 0.5) * 2 * self.jitter)
            ctop = (row - h // 2 + (shift * h).long()).clamp(0, H - h)
            cleft = (col - w // 2 + (shift * w).long()).clamp(0, W - w)
            top = torch.where(centred, ctop, top)
            left = torch.where(centred, cleft, left)
        return torch.stack([top, left], 1)

    def apply(self, batch: Batch, corners: torch.Tensor) -> Batch:
        """Cut every spatial entry to its sample's window; update ``visible``."""
        h, w = self.size
        out = dict(batch)
        rows = corners[:, 0, None] + torch.arange(h, device=corners.device)  # [B, h]
        cols = corners[:, 1, None] + torch.arange(w, device=corners.device)  # [B, w]
        for key in SPATIAL_MODES:
            if key not in batch:
                continue
            x = batch[key]
            r = rows.to(x.device)[:, None, :, None].expand(-1, x.shape[1], -1, x.shape[-1])
            x = torch.gather(x, 2, r)
            c = cols.to(x.device)[:, None, None, :].expand(-1, x.shape[1], h, -1)
            out[key] = torch.gather(x, 3, c)
        if "visible" in batch:
            whole = batch["mask"].flatten(1).sum(1) == out["mask"].flatten(1).sum(1)
            out["visible"] = batch["visible"].bool() & whole.to(batch["visible"].device)
        return out

    def forward(self, batch: Batch, generator: torch.Generator) -> Batch:
        return self.apply(batch, self.sample(batch["mask"], generator))
