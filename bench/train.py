"""Training throughput and loader memory of the streaming DataModule.

``python bench/train.py [--data DIR] [--steps 8] [--model unet_mit_b0] [--size 256]
[--batch 8] [--workers 2] [--prior] [--stream 10000]``

1. images/s of the full pipeline (MCAP streaming, decoding, resizing, prior rendering with
   ``--prior``, GPU-side augmentation, forward/backward/AdamW step) against the bare step of the
   same model, batch and resolution on random tensors, in alternating blocks in one process;
   target ratio >= 0.85.
2. memory (RSS of this process, loader in-process) while streaming ``--stream`` frames at 64×64
   from small frames (96×54 recordings); target growth < 300 MB.

Without ``--data`` a small annotated dataset is simulated into a temporary folder (ground-truth
masks as the annotation). Timings on a shared machine are noisy.
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from bench.common import format_table  # noqa: E402
from datamodules.recording import RecordingDataModule  # noqa: E402
from roboseg.augment.pipeline import prepare  # noqa: E402
from roboseg.config import CONF_DIR  # noqa: E402
from roboseg.training import SegmentationModule  # noqa: E402

PAPER_AUGMENT = OmegaConf.to_container(OmegaConf.load(Path(CONF_DIR) / "augment" / "paper.yaml"))


def rss_mb() -> float:
    """Resident set size of this process, MB (Linux ``/proc``)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def make_data(root: Path, frames: int, width: int, height: int) -> Path:
    from test_datamodule import make_annotated_dataset

    return make_annotated_dataset(root, {"train": 2, "val": 1}, frames=frames, width=width,
                                  height=height, chunk_size=200_000)


def _step(module: SegmentationModule, opt: torch.optim.Optimizer, batch: dict) -> None:
    module.train()
    batch = module.augment(batch) if module.augment is not None else batch
    x, y = prepare(batch, module.hparams.mean, module.hparams.std, module.in_channels)
    loss = module.loss_fn(module(x), y)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()


def throughput(data: Path, args: argparse.Namespace) -> tuple[float, float]:
    """(full pipeline, bare step) images/s over ``args.steps`` steps each, in blocks."""
    channels = 4 if args.prior else 3
    module = SegmentationModule(model={"name": args.model, "in_channels": channels},
                                augment=PAPER_AUGMENT, image_size=[args.size, args.size])
    module.augment.reseed(0)
    opt = torch.optim.AdamW(module.parameters(), lr=1e-4)
    dm = RecordingDataModule(data, image_size=[args.size, args.size], batch_size=args.batch,
                             num_workers=args.workers, shuffle_buffer=64, with_prior=channels,
                             prior_probability=1.0 if args.prior else 0.0)
    dm.setup("fit")
    stream = iter(dm.train_dataloader())
    gen = torch.Generator().manual_seed(0)
    shape = (args.batch, 1, args.size, args.size)
    bare = {"image": torch.rand(args.batch, 3, args.size, args.size, generator=gen),
            "mask": (torch.rand(shape, generator=gen) > 0.7).float(),
            "prior": torch.zeros(shape), "visible": torch.ones(args.batch, dtype=torch.bool)}
    _step(module, opt, next(stream))  # warm-up: workers started, first chunks read
    _step(module, opt, bare)
    spent = {"full": 0.0, "bare": 0.0}
    # blocks A B B A: the loader's prefetching cannot hide behind bare steps except at one
    # boundary, and a drifting machine load affects both alike
    for name in ("full", "bare", "bare", "full"):
        t = time.perf_counter()
        for _ in range(args.steps // 2):
            _step(module, opt, next(stream) if name == "full" else bare)
        spent[name] += time.perf_counter() - t
    n = 2 * (args.steps // 2) * args.batch
    return n / spent["full"], n / spent["bare"]


def stream_memory(data: Path, n_frames: int) -> tuple[float, float, float]:
    """(RSS after 200 frames, RSS after ``n_frames``, frames/s) streaming 64×64 samples."""
    dm = RecordingDataModule(data, image_size=[64, 64], batch_size=1, num_workers=0,
                             shuffle_buffer=512)
    dm.setup("fit")
    it = iter(dm.datasets["train"])
    for _ in range(200):
        next(it)
    start, t = rss_mb(), time.perf_counter()
    for _ in range(n_frames - 200):
        next(it)
    return start, rss_mb(), (n_frames - 200) / (time.perf_counter() - t)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="annotated dataset folder")
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--model", default="unet_mit_b0")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--prior", action="store_true", help="4 channels, prior always rendered")
    parser.add_argument("--stream", type=int, default=10_000, help="frames for the memory part")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    torch.manual_seed(0)
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data or make_data(Path(tmp) / "big", 16, 480, 270)
        full, bare = throughput(data, args)
        small = make_data(Path(tmp) / "small", 24, 96, 54)
        rss0, rss1, fps = stream_memory(small, args.stream)
    ratio = full / bare
    rows = [
        [f"full pipeline images/s ({args.model}, {args.size}², batch {args.batch}, "
          f"prior={'on' if args.prior else 'off'})", round(full, 2)],
         ["bare step images/s (random tensors)", round(bare, 2)],
         ["ratio full / bare", round(ratio, 3)],
         ["loader RSS MB after 200 frames (64², from 96×54)", round(rss0, 1)],
         [f"loader RSS MB after {args.stream} frames", round(rss1, 1)],
         ["streaming frames/s (64², in-process)", round(fps, 1)]]
    print(format_table(["measure", "value"], [[m, f"{v:g}"] for m, v in rows]))
    print(f"{'PASS' if ratio >= 0.85 else 'FAIL'}  throughput ratio {ratio:.3f} (target >= 0.85)")
    growth = rss1 - rss0
    print(f"{'PASS' if growth < 300 else 'FAIL'}  loader memory growth {growth:.1f} MB over "
          f"{args.stream} frames (target < 300 MB)")


if __name__ == "__main__":
    main()
