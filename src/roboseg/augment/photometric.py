"""Photometric augmentation (paper step 4) on the RGB channels only, values in [0, 1].

Each operation hits a sample with probability ``p`` (paper: 0.2): colour jitter, grayscale,
box blur, contrast, salt-and-pepper, Gaussian noise, channel dropout, in that order. Colour ops
use ``kornia.enhance`` / ``kornia.filters``; the random fields are drawn here from the caller's
``torch.Generator`` (kornia's random modules draw from the global RNG and reject 4-channel
input, and its noise does not clip), and every result is clamped to [0, 1]. The prior channel
never enters this module. Hue jitter is the slowest op on a CPU; its default range is small.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence

import kornia
import torch
from torch import nn

Params = dict[str, torch.Tensor]


def _uniform(n: int, low: float, high: float, generator: torch.Generator) -> torch.Tensor:
    return low + (high - low) * torch.rand(n, generator=generator, device=generator.device)


class PhotometricOp(nn.Module, ABC):
    """One photometric operation: draws ``apply`` per sample, then values for those samples."""

    def __init__(self, p: float = 0.2) -> None:
        super().__init__()
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"{type(self).__name__}: probability must be in [0, 1], got {p}")
        self.p = p

    def sample(self, shape: torch.Size, generator: torch.Generator) -> Params:
        """``apply`` (bool ``[B]``) and the values of the selected samples (first dim = count)."""
        chosen = torch.rand(shape[0], generator=generator, device=generator.device) < self.p
        n = int(chosen.sum())
        params = self.sample_values(n, shape, generator) if n else {}
        return {"apply": chosen, **params}

    def sample_values(self, n: int, shape: torch.Size, generator: torch.Generator) -> Params:
        """Random values of ``n`` selected samples of an RGB batch of ``shape``."""
        return {}

    @abstractmethod
    def transform(self, rgb: torch.Tensor, params: Params) -> torch.Tensor:
        """The operation on the selected samples ``rgb`` ``[n,3,H,W]``."""

    def apply(self, rgb: torch.Tensor, params: Params) -> torch.Tensor:
        """Transform the selected samples of ``rgb`` ``[B,3,H,W]``, clamp them to [0, 1]."""
        idx = torch.nonzero(params["apply"], as_tuple=False).flatten().to(rgb.device)
        if idx.numel() == 0:
            return rgb
        values = {k: v.to(rgb.device) for k, v in params.items() if k != "apply"}
        done = self.transform(rgb[idx], values).clamp(0.0, 1.0)
        return rgb.index_copy(0, idx, done.to(rgb.dtype))


class ColorJitter(PhotometricOp):
    """Brightness (additive ±b), contrast (×[1-c, 1+c]), saturation (×[1-s, 1+s]), hue (±h turn)."""

    def __init__(
        self,
        p: float = 0.2,
        brightness: float = 0.2,
        contrast: float = 0.2,
        saturation: float = 0.2,
        hue: float = 0.02,
    ) -> None:
        super().__init__(p)
        self.brightness, self.contrast = brightness, contrast
        self.saturation, self.hue = saturation, hue

    def sample_values(self, n: int, shape: torch.Size, generator: torch.Generator) -> Params:
        return {
            "brightness": _uniform(n, -self.brightness, self.brightness, generator),
            "contrast": _uniform(n, 1 - self.contrast, 1 + self.contrast, generator),
            "saturation": _uniform(n, 1 - self.saturation, 1 + self.saturation, generator),
            "hue": _uniform(n, -self.hue, self.hue, generator) * 2 * torch.pi,  # radians
        }

    def transform(self, rgb: torch.Tensor, params: Params) -> torch.Tensor:
        x = kornia.enhance.adjust_brightness(rgb, params["brightness"], clip_output=True)
        x = kornia.enhance.adjust_contrast(x, params["contrast"], clip_output=True)
        x = kornia.enhance.adjust_saturation(x, params["saturation"])
        if self.hue > 0:
            x = kornia.enhance.adjust_hue(x, params["hue"])
        return x


class Grayscale(PhotometricOp):
    """Replace RGB by its luma (ITU-R 601 weights), repeated on the three channels."""

    def transform(self, rgb: torch.Tensor, params: Params) -> torch.Tensor:
        return kornia.color.rgb_to_grayscale(rgb).expand_as(rgb)


class BoxBlur(PhotometricOp):
    """Mean filter of ``kernel_size`` × ``kernel_size`` pixels (reflected borders)."""

    def __init__(self, p: float = 0.2, kernel_size: int = 3) -> None:
        super().__init__(p)
        self.kernel_size = kernel_size

    def transform(self, rgb: torch.Tensor, params: Params) -> torch.Tensor:
        return kornia.filters.box_blur(rgb, (self.kernel_size, self.kernel_size))


class Contrast(PhotometricOp):
    """Contrast about each image's mean grey level, factor U[contrast]."""

    def __init__(self, p: float = 0.2, contrast: tuple[float, float] = (0.6, 1.4)) -> None:
        super().__init__(p)
        self.contrast = (float(contrast[0]), float(contrast[1]))

    def sample_values(self, n: int, shape: torch.Size, generator: torch.Generator) -> Params:
        return {"factor": _uniform(n, *self.contrast, generator)}

    def transform(self, rgb: torch.Tensor, params: Params) -> torch.Tensor:
        return kornia.enhance.adjust_contrast_with_mean_subtraction(rgb, params["factor"])


class SaltAndPepper(PhotometricOp):
    """A fraction U[amount] of pixels set to white (salt, share U[salt]) or black (pepper)."""

    def __init__(
        self,
        p: float = 0.2,
        amount: tuple[float, float] = (0.01, 0.06),
        salt: tuple[float, float] = (0.4, 0.6),
    ) -> None:
        super().__init__(p)
        self.amount = (float(amount[0]), float(amount[1]))
        self.salt = (float(salt[0]), float(salt[1]))

    def sample_values(self, n: int, shape: torch.Size, generator: torch.Generator) -> Params:
        h, w = shape[-2:]
        amount = _uniform(n, *self.amount, generator).view(n, 1, 1, 1)
        salt = _uniform(n, *self.salt, generator).view(n, 1, 1, 1)
        hit = torch.rand(n, 1, h, w, generator=generator, device=generator.device)
        coin = torch.rand(n, 1, h, w, generator=generator, device=generator.device)
        return {"noisy": hit < amount, "white": coin < salt}

    def transform(self, rgb: torch.Tensor, params: Params) -> torch.Tensor:
        value = params["white"].to(rgb.dtype).expand_as(rgb)
        return torch.where(params["noisy"].expand_as(rgb), value, rgb)


class GaussianNoise(PhotometricOp):
    """Additive zero-mean Gaussian noise of standard deviation ``std`` (clamped to [0, 1])."""

    def __init__(self, p: float = 0.2, std: float = 0.03) -> None:
        super().__init__(p)
        self.std = std

    def sample_values(self, n: int, shape: torch.Size, generator: torch.Generator) -> Params:
        noise = torch.randn(n, *shape[1:], generator=generator, device=generator.device)
        return {"noise": noise * self.std}

    def transform(self, rgb: torch.Tensor, params: Params) -> torch.Tensor:
        return rgb + params["noise"].to(rgb.dtype)


class ChannelDropout(PhotometricOp):
    """Set one uniformly chosen colour channel to 0."""

    def sample_values(self, n: int, shape: torch.Size, generator: torch.Generator) -> Params:
        channel = torch.randint(shape[1], (n,), generator=generator, device=generator.device)
        return {"channel": channel}

    def transform(self, rgb: torch.Tensor, params: Params) -> torch.Tensor:
        keep = torch.arange(rgb.shape[1], device=rgb.device) != params["channel"].view(-1, 1)
        return rgb * keep.to(rgb.dtype).view(*keep.shape, 1, 1)


def paper_ops(p: float = 0.2) -> list[PhotometricOp]:
    """The paper's seven photometric operations, each with probability ``p``."""
    return [
        ColorJitter(p),
        Grayscale(p),
        BoxBlur(p),
        Contrast(p),
        SaltAndPepper(p),
        GaussianNoise(p),
        ChannelDropout(p),
    ]


class Photometric(nn.Module):
    """Apply ``ops`` in order to the RGB image of a batch (default: :func:`paper_ops`)."""

    def __init__(self, ops: Sequence[PhotometricOp] | None = None) -> None:
        super().__init__()
        self.ops = nn.ModuleList(list(ops) if ops is not None else paper_ops())

    def sample(self, shape: torch.Size, generator: torch.Generator) -> list[Params]:
        """One parameter draw per operation for an RGB batch of ``shape``."""
        return [op.sample(shape, generator) for op in self.ops]

    def apply(self, rgb: torch.Tensor, params: list[Params]) -> torch.Tensor:
        for op, prm in zip(self.ops, params, strict=True):
            rgb = op.apply(rgb, prm)
        return rgb

    def forward(self, batch: dict[str, torch.Tensor], generator: torch.Generator) -> dict:
        """Augment ``batch["image"]`` only; mask and prior pass untouched."""
        out = dict(batch)
        out["image"] = self.apply(batch["image"], self.sample(batch["image"].shape, generator))
        return out
