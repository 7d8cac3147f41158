"""A training checkpoint → the module it describes and the ONNX metadata of its export.

A roboseg checkpoint (written by :class:`roboseg.training.SegmentationModule`) holds the module's
hyperparameters and a ``"roboseg"`` block with what the export needs (encoder, channels, input
size, normalisation, threshold, parameter count, cut-mix-merge, dataset). Everything is read with
``torch.load(weights_only=True)``: a checkpoint is untrusted input.
"""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path
from typing import Any

import torch

import roboseg
from roboseg.errors import ModelFileError
from roboseg.segmentor import SegmentorMeta
from roboseg.training import SegmentationModule

log = logging.getLogger(__name__)

#: Keys of a checkpoint's ``"roboseg"`` block that :class:`SegmentorMeta` takes.
META_FIELDS = (
    "encoder", "in_channels", "input_height", "input_width", "mean", "std", "threshold",
    "params_m", "cmm", "dataset",
)


def file_sha256(path: str | Path, chunk: int = 1 << 20) -> str:
    """``sha256:<hex>`` of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            digest.update(block)
    return "sha256:" + digest.hexdigest()


def load_failure(exc: BaseException) -> str:
    """A one-line reason why ``torch.load(weights_only=True)`` failed."""
    text = str(exc)
    if "Weights only load failed" in text:
        return "not a checkpoint, or it holds objects a weights-only load refuses"
    first = text.strip().splitlines()[0] if text.strip() else type(exc).__name__
    return first[:160]


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """The checkpoint dict (CPU tensors), checked to be roboseg's; else :class:`ModelFileError`."""
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"checkpoint {path}: no such file")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - corrupt, foreign or unsafe pickle
        raise ModelFileError(f"checkpoint {path}: cannot be read ({load_failure(exc)})") from exc
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt:
        raise ModelFileError(f"checkpoint {path}: not a Lightning checkpoint (no state_dict)")
    hparams = ckpt.get("hyper_parameters")
    if not isinstance(hparams, dict) or "model" not in hparams or "roboseg" not in ckpt:
        raise ModelFileError(
            f"checkpoint {path}: not a roboseg checkpoint (no roboseg hyperparameters)"
        )
    return ckpt


def meta_from_block(block: dict[str, Any], trained_on: str, source: str) -> SegmentorMeta:
    """:class:`SegmentorMeta` of a checkpoint's ``"roboseg"`` block."""
    missing = [k for k in META_FIELDS if k not in block]
    if missing:
        raise ModelFileError(f"checkpoint {source}: roboseg block lacks {', '.join(missing)}")
    try:
        return SegmentorMeta(
            encoder=str(block["encoder"]),
            in_channels=int(block["in_channels"]),
            input_height=int(block["input_height"]),
            input_width=int(block["input_width"]),
            mean=tuple(float(v) for v in block["mean"]),  # type: ignore[arg-type]
            std=tuple(float(v) for v in block["std"]),  # type: ignore[arg-type]
            threshold=float(block["threshold"]),
            trained_on=trained_on,
            roboseg_version=roboseg.__version__ if hasattr(roboseg, "__version__") else "",
            params_m=float(block["params_m"]),
            cmm=None if block["cmm"] is None else bool(block["cmm"]),
            dataset=str(block["dataset"]),
        )
    except (TypeError, ValueError) as exc:
        raise ModelFileError(f"checkpoint {source}: malformed roboseg block ({exc})") from exc


def trained_on_hash(ckpt_path: str | Path, data_root: str | Path | None) -> str:
    """Hash of the training data's ``manifest.json`` when known, else of the checkpoint file."""
    if data_root is not None:
        manifest = Path(data_root) / "manifest.json"
        if manifest.is_file():
            return file_sha256(manifest)
        log.warning("%s: no manifest.json; trained_on is the checkpoint's hash", data_root)
    return file_sha256(ckpt_path)


def load_for_export(
    path: str | Path, data_root: str | Path | None = None
) -> tuple[SegmentationModule, SegmentorMeta]:
    """The module of a checkpoint (eval mode, CPU) and the metadata its ONNX export carries.

    Raises :class:`ModelFileError` with one line naming the file when it is not a roboseg
    checkpoint or its weights do not match its model config.
    """
    path = Path(path)
    ckpt = read_checkpoint(path)
    module = SegmentationModule.load_from_checkpoint(path, map_location="cpu", weights_only=True)
    meta = meta_from_block(dict(ckpt["roboseg"]), trained_on_hash(path, data_root), str(path))
    if meta.in_channels != module.in_channels or meta.encoder != module.hparams.model["name"]:
        raise ModelFileError(
            f"checkpoint {path}: roboseg block says {meta.encoder}/{meta.in_channels} channels "
            f"but the model config is {module.hparams.model['name']}/{module.in_channels}"
        )
    return module.eval().cpu(), meta
