"""Inference bench: onnxruntime vs PyTorch eager latency of the same U-Net on CPU.

Run as ``python -m bench.infer`` (or ``python bench/infer.py``). Exports U-Nets with MIT-B0 and
ResNet-18 encoders (random weights) through :func:`export.onnx.export_onnx` and times batch 1 at
256² and 512² in both runtimes (same thread count), interleaved. Target: onnxruntime at least
1.3× faster than torch eager for every case. Wall-clock numbers depend on machine load; the
median of several repeats is shown.
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

if __package__ in (None, ""):  # run as a script: make ``bench`` and ``export`` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import format_table, time_calls  # noqa: E402
from export.onnx import export_onnx  # noqa: E402
from roboseg.models import build_unet  # noqa: E402
from roboseg.segmentor import SegmentorMeta  # noqa: E402

SPEEDUP_TARGET = 1.3
MODELS = ("unet_mit_b0", "unet_resnet18")
SIZES = (256, 512)
log = logging.getLogger("bench.infer")


def speedup(torch_s: float, ort_s: float) -> float:
    """How many times faster onnxruntime is than torch (>1: onnxruntime faster)."""
    return torch_s / ort_s


def bench_model(name: str, sizes: tuple[int, ...], threads: int, repeats: int,
                folder: Path) -> list[list[object]]:
    """Rows ``[model, size, torch ms, onnxruntime ms, speed-up]`` for one encoder."""
    import onnxruntime as ort

    torch.manual_seed(0)
    net = build_unet(name, 3).eval()
    meta = SegmentorMeta(encoder=name, in_channels=3, input_height=sizes[0],
                         input_width=sizes[0], mean=(0.485, 0.456, 0.406),
                         std=(0.229, 0.224, 0.225), threshold=0.5)
    path = export_onnx(net, meta, folder / f"{name}.onnx")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    rows: list[list[object]] = []
    for size in sizes:
        x = np.random.default_rng(0).standard_normal((1, 3, size, size)).astype(np.float32)
        xt = torch.from_numpy(x)

        def run_torch(xt: torch.Tensor = xt) -> None:
            with torch.inference_mode():
                net(xt)

        def run_ort(x: np.ndarray = x) -> None:
            session.run(None, {"input": x})

        t = time_calls({"torch": run_torch, "ort": run_ort}, repeats=repeats, warmup=1)
        torch_ms, ort_ms = 1e3 * t["torch"]["median"], 1e3 * t["ort"]["median"]
        rows.append([name, f"{size}²", torch_ms, ort_ms, f"{speedup(torch_ms, ort_ms):.2f}×"])
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2, help="intra-op threads of both runtimes")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    torch.set_num_threads(args.threads)
    rows: list[list[object]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in MODELS:
            rows += bench_model(name, tuple(args.sizes), args.threads, args.repeats, Path(tmp))
    print(format_table(["model", "input", "torch ms", "onnxruntime ms", "speed-up"], rows))
    worst = min(speedup(float(r[2]), float(r[3])) for r in rows)
    status = "PASS" if worst >= SPEEDUP_TARGET else "FAIL"
    print(f"{status}  slowest onnxruntime speed-up over torch eager: {worst:.2f}× "
          f"(target >= {SPEEDUP_TARGET:g}×, batch 1, {args.threads} threads)")
    return 0 if status == "PASS" else 1


if __name__ == "__main__":
    sys.exit(main())
