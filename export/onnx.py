"""Checkpoint → self-describing ONNX file, verified against PyTorch with onnxruntime.

The graph takes ``input`` ``[batch, C, height, width]`` (all three dynamic; height and width must
be multiples of 32 for the U-Nets) and returns ``logits`` ``[batch, 1, height, width]``. The
exporter is torch's TorchScript-based one at opset 17: the dynamo exporter specialises the batch
dimension of MiT encoders when traced with batch 1, so we trace with a batch of 2 regardless.
"""

from __future__ import annotations

import logging
import os
import tempfile
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import torch
from torch import nn

from roboseg.segmentor import SegmentorMeta

log = logging.getLogger(__name__)

INPUT_NAME = "input"
OUTPUT_NAME = "logits"


@dataclass
class Verification:
    """Max |Δlogit| between onnxruntime and PyTorch for each checked input shape, and the
    largest |logit| of that input: float32 rounding grows with the logits' magnitude, so a
    difference passes when it is within ``tolerance`` × max(1, max |logit|)."""

    shapes: list[tuple[int, int, int, int]]
    max_abs_diff: list[float]
    tolerance: float
    max_abs_logit: list[float] | None = None

    def bounds(self) -> list[float]:
        scales = self.max_abs_logit or [1.0] * len(self.shapes)
        return [self.tolerance * max(1.0, s) for s in scales]

    @property
    def ok(self) -> bool:
        return all(d <= b for d, b in zip(self.max_abs_diff, self.bounds(), strict=True))

    def lines(self) -> list[str]:
        scales = self.max_abs_logit or [float("nan")] * len(self.shapes)
        return [
            f"  input {tuple(sh)}: max |Δlogit| = {d:.3g} (max |logit| {s:.3g}, bound {b:.3g})"
            + ("" if d <= b else "  FAIL")
            for sh, d, s, b in zip(self.shapes, self.max_abs_diff, scales, self.bounds(),
                                   strict=True)
        ]


def _atomic_target(out: Path) -> Path:
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".part", dir=out.parent)
    os.close(fd)
    os.chmod(tmp, 0o644)  # mkstemp creates 0600; the model is an ordinary shareable file
    return Path(tmp)


def export_onnx(
    model: nn.Module,
    meta: SegmentorMeta,
    out: str | Path,
    *,
    opset: int = 17,
) -> Path:
    """Export ``model`` (logits out) to ``out`` with dynamic batch/height/width and metadata.

    The file is written under a temporary name and renamed when complete and checked.
    """
    out = Path(out)
    model = model.eval().cpu()
    example = torch.zeros(2, meta.in_channels, meta.input_height, meta.input_width)
    tmp = _atomic_target(out)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(
                model,
                (example,),
                str(tmp),
                dynamo=False,
                opset_version=opset,
                input_names=[INPUT_NAME],
                output_names=[OUTPUT_NAME],
                dynamic_axes={
                    INPUT_NAME: {0: "batch", 2: "height", 3: "width"},
                    OUTPUT_NAME: {0: "batch", 2: "height", 3: "width"},
                },
            )
        proto = onnx.load(str(tmp))
        set_metadata(proto, meta)
        onnx.checker.check_model(proto)
        onnx.save(proto, str(tmp))
        tmp.replace(out)
    finally:
        tmp.unlink(missing_ok=True)
    return out


def set_metadata(proto: onnx.ModelProto, meta: SegmentorMeta) -> None:
    """Replace the model's ``metadata_props`` by roboseg's description of it."""
    del proto.metadata_props[:]
    for key, value in meta.to_props().items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value


def verify_onnx(
    path: str | Path,
    model: nn.Module,
    shapes: Sequence[tuple[int, int, int, int]],
    *,
    tolerance: float = 1e-4,
    seed: int = 0,
) -> Verification:
    """Run random inputs of each shape through onnxruntime and PyTorch; compare logits
    (see :class:`Verification` for the bound)."""
    import onnxruntime as ort

    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    gen = torch.Generator().manual_seed(seed)
    model = model.eval().cpu()
    diffs, scales = [], []
    for shape in shapes:
        x = torch.randn(*shape, generator=gen)
        with torch.no_grad():
            ref = model(x).numpy()
        got = session.run(None, {INPUT_NAME: x.numpy()})[0]
        diffs.append(float(np.abs(got - ref).max()))
        scales.append(float(np.abs(ref).max()))
    return Verification([tuple(s) for s in shapes], diffs, tolerance, scales)


def quantize_int8(src: str | Path, out: str | Path) -> Path:
    """Dynamic int8 quantisation of the weights (onnxruntime.quantization); metadata kept."""
    from onnxruntime.quantization import QuantType, quantize_dynamic

    out = Path(out)
    tmp = _atomic_target(out)
    try:
        quantize_dynamic(str(src), str(tmp), weight_type=QuantType.QInt8)
        _copy_metadata(src, tmp)
        tmp.replace(out)
    finally:
        tmp.unlink(missing_ok=True)
    return out


def convert_fp16(src: str | Path, out: str | Path) -> Path:
    """FP16 weights and activations with FP32 inputs/outputs (onnxruntime's float16 converter)."""
    from onnxruntime.transformers.float16 import convert_float_to_float16

    out = Path(out)
    proto = onnx.load(str(src))
    half = convert_float_to_float16(proto, keep_io_types=True)
    tmp = _atomic_target(out)
    try:
        onnx.save(half, str(tmp))
        _copy_metadata(src, tmp)
        tmp.replace(out)
    finally:
        tmp.unlink(missing_ok=True)
    return out


def _copy_metadata(src: str | Path, dst: str | Path) -> None:
    props = {p.key: p.value for p in onnx.load(str(src), load_external_data=False).metadata_props}
    proto = onnx.load(str(dst))
    del proto.metadata_props[:]
    for key, value in props.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.save(proto, str(dst))
