"""``roboseg-export``: checkpoint → verified, self-describing ONNX model (``conf/export.yaml``).

``roboseg-export ckpt=PATH out=FILE.onnx [fp16=true] [int8=true] [data.root=DIR]`` exports with
dynamic batch / height / width at opset 17, checks the graph, runs onnxruntime against PyTorch at
two input sizes with batch 2 (max |Δlogit| printed; exit 1 above ``verify.tolerance``) and
optionally writes ``FILE.fp16.onnx`` / ``FILE.int8.onnx``, reporting how much each changes the
result: the IoU on ``data.root``'s frames when given, else logits / probabilities on random inputs.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from export.checkpoint import load_for_export
from export.onnx import convert_fp16, export_onnx, quantize_int8, verify_onnx
from roboseg.cli._main import user_errors_exit
from roboseg.config import CONF_DIR
from roboseg.errors import RobosegError
from roboseg.models import with_tta
from roboseg.segmentor import OnnxSegmentor, _sigmoid

log = logging.getLogger("roboseg.export")


def verify_sizes(
    sizes: Sequence[Sequence[int]] | None, input_hw: tuple[int, int]
) -> list[tuple[int, int]]:
    """Checked ``(H, W)`` sizes: given ones (multiples of 32), or training size and +[32, 64]."""
    if sizes is None:
        h, w = input_hw
        return [(h, w), (h + 32, w + 64)]
    out = []
    for s in sizes:
        h, w = (int(v) for v in s)
        if h <= 0 or w <= 0 or h % 32 or w % 32:
            raise RobosegError(f"verify.sizes: {list(s)} is not [H, W] in positive multiples of 32")
        out.append((h, w))
    if len(out) < 2:
        raise RobosegError(f"verify.sizes: need at least two sizes, got {len(out)}")
    return out


def variant_path(out: Path, kind: str) -> Path:
    """``FILE.onnx`` → ``FILE.<kind>.onnx``."""
    return out.with_name(f"{out.stem}.{kind}{out.suffix or '.onnx'}")


def random_change(reference: Path, variant: Path, shape: tuple[int, ...], seed: int = 0) -> str:
    """Max |Δlogit| and |Δprobability| of ``variant`` against ``reference`` on random inputs."""
    a, b = OnnxSegmentor(reference), OnnxSegmentor(variant)
    x = np.random.default_rng(seed).standard_normal(shape).astype(np.float32)
    la, lb = a.logits(x), b.logits(x)
    d_logit = float(np.abs(la - lb).max())
    d_prob = float(np.abs(_sigmoid(la) - _sigmoid(lb)).max())
    return f"max |Δlogit| = {d_logit:.3g}, max |Δprob| = {d_prob:.3g} (random input {shape})"


def iou_change(reference: Path, variant: Path, cfg: DictConfig) -> str:
    """Mean IoU of ``variant`` minus that of ``reference`` on ``cfg.data``'s frames."""
    from roboseg.evaluation.run import iter_frames, load_manifest, predict_probs, split_recordings

    root = Path(str(cfg.data.root))
    files = split_recordings(load_manifest(root), root, str(cfg.data.split))
    models = [OnnxSegmentor(reference), OnnxSegmentor(variant)]
    ious: list[list[float]] = [[], []]
    from roboseg.evaluation.metrics import binary_iou

    for frame in iter_frames(files, labels=str(cfg.data.labels), max_frames=cfg.data.max_frames):
        for model, scores in zip(models, ious, strict=True):
            pred = predict_probs(model, frame.image, None) > model.meta.threshold
            scores.append(binary_iou(pred, frame.target))
    ref, var = float(np.mean(ious[0])), float(np.mean(ious[1]))
    return f"IoU {var:.4f} vs {ref:.4f} (Δ {var - ref:+.4f}) on {len(ious[0])} frames"


@user_errors_exit
def run(cfg: DictConfig) -> int:
    """Export, verify and optionally convert; return the exit status (0 ok, 1 mismatch)."""
    if cfg.threads is not None:
        torch.set_num_threads(max(1, int(cfg.threads)))
    out = Path(str(cfg.out))
    if out.suffix != ".onnx":
        raise RobosegError(f"out: {out} should end in .onnx")
    if out.is_dir():
        raise RobosegError(f"out: {out} is a folder")
    data_root = None if cfg.data.root is None else str(cfg.data.root)
    module, meta = load_for_export(str(cfg.ckpt), data_root)
    tta = str(cfg.get("tta") or "")
    net = with_tta(module.net, tta)  # ModelConfigError: one line
    meta = replace(meta, tta=tta)
    export_onnx(net, meta, out, opset=int(cfg.opset))
    print(f"wrote {out} ({meta.encoder}, {meta.in_channels} channels, "
          f"{meta.input_height}x{meta.input_width}, {meta.params_m:.1f} M parameters"
          f"{', test-time ' + meta.tta if meta.tta else ''})")
    batch = int(cfg.verify.batch)
    sizes = verify_sizes(
        None if cfg.verify.sizes is None else OmegaConf.to_container(cfg.verify.sizes),
        (meta.input_height, meta.input_width),
    )
    shapes = [(batch, meta.in_channels, h, w) for h, w in sizes]
    check = verify_onnx(out, net, shapes, tolerance=float(cfg.verify.tolerance),
                        seed=int(cfg.verify.seed))
    print("onnxruntime vs PyTorch:")
    print("\n".join(check.lines()))
    if not check.ok:
        print(f"error: {out}: onnxruntime differs from PyTorch by more than "
              f"{float(cfg.verify.tolerance):g} x max(1, max |logit|)", file=sys.stderr)
        return 1
    for kind, enabled, convert in (("fp16", cfg.fp16, convert_fp16),
                                   ("int8", cfg.int8, quantize_int8)):
        if not enabled:
            continue
        logging.disable(logging.INFO)  # the int8 quantiser logs a line per tensor at INFO
        try:
            path = convert(out, variant_path(out, kind))
        finally:
            logging.disable(logging.NOTSET)
        if data_root is not None:
            change = iou_change(out, path, cfg)
        else:
            change = random_change(out, path, shapes[0], int(cfg.verify.seed))
        print(f"wrote {path}: {change}")
    return 0


@hydra.main(config_path=CONF_DIR, config_name="export", version_base="1.3")
def main(cfg: DictConfig) -> None:
    status = run(cfg)
    if status:
        sys.exit(status)


if __name__ == "__main__":
    main()
