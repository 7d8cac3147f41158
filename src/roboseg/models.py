"""U-Net presets of the paper (segmentation_models_pytorch) behind a registry and one factory.

Every preset is a U-Net with decoder channels [256, 128, 64, 32, 16] (the paper's; a run may
choose other widths) and one logit channel (binary robot / background). Inputs are
``[B, C, H, W]`` with ``C = 3`` (normalised RGB) or ``C = 4`` (RGB + in-context prior).
Encoders start random (``encoder_weights=None``: nothing is ever downloaded); pretrained
weights come only from a local file the user names.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import segmentation_models_pytorch as smp
import torch
from torch import nn

from roboseg.errors import ModelFileError, RobosegError

log = logging.getLogger(__name__)


class ModelConfigError(RobosegError, ValueError):
    """A model configuration names an unknown preset or an unsupported channel count."""

#: Decoder feature channels of the five U-Net decoder blocks (paper, Methods).
DECODER_CHANNELS: tuple[int, ...] = (256, 128, 64, 32, 16)
#: Input channels a model may take: RGB, or RGB + in-context prior.
IN_CHANNELS: tuple[int, ...] = (3, 4)


@dataclass(frozen=True)
class UnetPreset:
    """One registered U-Net: its smp encoder name and the paper's parameter count (if any)."""

    encoder: str
    paper_params_m: float | None = None


#: Registry of U-Net presets by name (``unet_<encoder>``).
PRESETS: dict[str, UnetPreset] = {}


def register_preset(name: str, preset: UnetPreset) -> None:
    """Add ``preset`` to :data:`PRESETS` under ``name`` (names are unique)."""
    if name in PRESETS:
        raise ValueError(f"model preset {name!r} is registered already")
    PRESETS[name] = preset


for _encoder, _params in (
    ("mit_b0", None),
    ("mit_b1", None),
    ("mit_b2", None),
    ("mit_b3", 47.4),
    ("mit_b4", None),
    ("mit_b5", 84.7),
    ("resnet18", None),
    ("resnet101", 51.5),
):
    register_preset(f"unet_{_encoder}", UnetPreset(_encoder, _params))
# a light CNN encoder of timm (RegNetY-400MF) through smp's ``tu-`` bridge: the CPU default
register_preset("unet_regnety_004", UnetPreset("tu-regnety_004"))


class FlipAveraged(nn.Module):
    """Test-time augmentation: the mean of ``net``'s logits for each image and for its mirror
    image (mirrored back). Training flips images horizontally, so both views are in
    distribution; the cost is twice ``net``'s. (Two calls rather than one batch of ``2B``: a
    traced split of the batch would fix the exported model's batch size.)"""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Logits ``[B, 1, H, W]`` of an input ``[B, C, H, W]``."""
        return 0.5 * (self.net(x) + self.net(x.flip(-1)).flip(-1))


#: Test-time augmentations ``roboseg-export tta=`` may bake into a model.
TTA: dict[str, type[nn.Module]] = {"flip": FlipAveraged}


def with_tta(net: nn.Module, tta: str | None) -> nn.Module:
    """``net`` wrapped in the test-time augmentation ``tta`` (a key of :data:`TTA`; None or "":
    as is)."""
    if not tta:
        return net
    if tta not in TTA:
        raise ModelConfigError(f"tta must be one of {', '.join(TTA)} or null, got {tta!r}")
    return TTA[tta](net)


def available_models() -> list[str]:
    """Names accepted by :func:`build_unet`, sorted."""
    return sorted(PRESETS)


def build_unet(
    name: str,
    in_channels: int = 3,
    weights_path: str | Path | None = None,
    decoder_channels: Sequence[int] | None = None,
) -> nn.Module:
    """Build the U-Net preset ``name`` with ``in_channels`` inputs and one logit output channel.

    ``decoder_channels`` (five widths) replaces the paper's :data:`DECODER_CHANNELS`, e.g. a
    half-width decoder for CPU-sized runs.

    ``weights_path`` optionally names a local file (``torch.save`` of a state dict, a Lightning
    checkpoint, or an encoder-only state dict) loaded with ``weights_only=True``; see
    :func:`load_weights`. Raises :class:`ModelConfigError` for an unknown name or channel count.
    """
    if name not in PRESETS:
        raise ModelConfigError(
            f"unknown model {name!r}; choose one of {', '.join(available_models())}"
        )
    if in_channels not in IN_CHANNELS:
        raise ModelConfigError(f"in_channels must be 3 or 4, got {in_channels}")
    decoder = list(DECODER_CHANNELS if decoder_channels is None else decoder_channels)
    if len(decoder) != len(DECODER_CHANNELS) or min(decoder) < 1:
        raise ModelConfigError(
            f"decoder_channels must be {len(DECODER_CHANNELS)} positive widths, got {decoder}"
        )
    model = smp.Unet(
        encoder_name=PRESETS[name].encoder,
        encoder_weights=None,
        in_channels=in_channels,
        classes=1,
        decoder_channels=decoder,
        activation=None,
    )
    if weights_path is not None:
        load_weights(model, weights_path)
    return model


def count_params(model: nn.Module, trainable_only: bool = False) -> int:
    """Number of parameters of ``model`` (all, or only those requiring gradients)."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad or not trainable_only)


def _unwrap_state_dict(obj: object, source: str) -> dict[str, torch.Tensor]:
    """The tensor state dict inside a loaded file (plain, ``state_dict`` or ``model`` entry)."""
    if isinstance(obj, Mapping):
        for key in ("state_dict", "model"):
            if key in obj and isinstance(obj[key], Mapping):
                obj = obj[key]
                break
    if not isinstance(obj, Mapping) or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise ModelFileError(f"{source}: not a state dict of tensors")
    return dict(obj)


def _match_keys(
    state: dict[str, torch.Tensor], target_keys: set[str]
) -> dict[str, torch.Tensor]:
    """Rename ``state`` keys onto the model's: strip Lightning's ``net.``, add ``encoder.``."""
    for prefix in ("", "net.", "model."):
        renamed = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
        if renamed and set(renamed) & target_keys:
            return renamed
    encoder_only = {f"encoder.{k}": v for k, v in state.items()}
    return encoder_only if set(encoder_only) & target_keys else {}


def adapt_in_channels(weight: torch.Tensor, in_channels: int) -> torch.Tensor:
    """A 3-channel conv kernel ``[O, 3, k, k]`` widened to ``[O, in_channels, k, k]``.

    The extra (prior) channels get zero weights, so a zero prior leaves the pretrained
    RGB response unchanged.
    """
    extra = weight.new_zeros(weight.shape[0], in_channels - weight.shape[1], *weight.shape[2:])
    return torch.cat([weight, extra], dim=1)


def load_weights(model: nn.Module, weights_path: str | Path) -> None:
    """Load a local weights file into ``model`` (in place), never downloading anything.

    Keys may be the model's own, prefixed by ``net.`` / ``model.`` (Lightning checkpoints), or an
    encoder's alone. A 3-channel first convolution is widened for a 4-channel model
    (:func:`adapt_in_channels`). Raises :class:`ModelFileError` naming the file and key when the
    file is missing, not a state dict, shares no key with the model, or a shape does not fit.
    """
    path = Path(weights_path)
    if not path.is_file():
        raise ModelFileError(f"weights file {path}: no such file")
    try:
        raw = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is a bad file
        raise ModelFileError(f"weights file {path}: cannot be read safely ({exc})") from exc
    own = model.state_dict()
    state = _match_keys(_unwrap_state_dict(raw, f"weights file {path}"), set(own))
    if not state:
        raise ModelFileError(f"weights file {path}: no parameter names match this model")
    for key, value in state.items():
        if key not in own or value.shape == own[key].shape:
            continue
        target = own[key].shape
        widen = value.ndim == 4 and value.shape[1] == 3 and target[1] == 4
        if widen and value.shape[0] == target[0] and value.shape[2:] == target[2:]:
            state[key] = adapt_in_channels(value, 4)
        else:
            raise ModelFileError(
                f"weights file {path}: {key} has shape {tuple(value.shape)}, "
                f"model expects {tuple(target)}"
            )
    result = model.load_state_dict(state, strict=False)
    log.info(
        "loaded %d tensors from %s (%d model tensors left at their initialisation)",
        len(state) - len(result.unexpected_keys),
        path,
        len(result.missing_keys),
    )
