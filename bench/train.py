"""Training throughput (3 and 4 channels) and loader memory of the streaming DataModule.

``python -m bench.train [--data DIR] [--steps 6] [--model unet_mit_b0] [--size 256] [--batch 8]
[--workers 2] [--stream 10000] [--memory-files 24] [--no-memory]``

1. **Throughput**, in one process, for 3 channels (no prior) and 4 channels (in-context prior
   rendered for every sample): images/s of the full pipeline (MCAP streaming, decoding,
   resizing, prior rendering, device-side augmentation, forward/backward/AdamW step) against the
   bare step of the same model, batch and resolution on random tensors (no loading, no
   augmentation). Blocks of steps run in the order F3 B3 F4 B4 B4 F4 B3 F3 (F: full, B: bare),
   so a drifting machine load affects all alike. Before each full block the batches the loader
   workers prefetched meanwhile are discarded: every timed batch was produced while training
   ran, as in a real run. Besides wall-clock images/s the bench reports images per CPU-second
   (this process plus the loader workers), which does not depend on how busy the machine is:
   the loader's cost shows there even where idle cores would hide it. Target ratio >= 0.85.
2. **Loader memory**, in a fresh subprocess: the training loader (``--workers`` processes, the
   configured shuffle buffer, prior on) streams ``--stream`` frames from ``--memory-files``
   recordings of the throughput frames (replicated, many chunks); growth = peak RSS
   (``VmHWM``) minus RSS at the first batch, summed over the loader processes. Target < 300 MB.

Without ``--data`` a small annotated dataset (480×270 frames, the size ``make train`` records)
is simulated into a temporary folder (ground-truth masks as the annotation). Timings on a shared
machine are noisy; the CPU-time ratio is the steadier figure.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import psutil
import torch
from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import format_table  # noqa: E402
from datamodules.recording import MASKS, RecordingDataModule, read_manifest  # noqa: E402
from roboseg.annotate import AnnotateOptions, annotate_folder  # noqa: E402
from roboseg.augment.pipeline import prepare  # noqa: E402
from roboseg.config import CONF_DIR  # noqa: E402
from roboseg.recording import (  # noqa: E402
    RecordingReader,
    RecordingWriter,
    camera_info_topic,
    image_topic,
    joint_states_topic,
    mask_topic,
    msgs,
)
from roboseg.robot import load_robot  # noqa: E402
from roboseg.sim import SimConfig, simulate_recording  # noqa: E402
from roboseg.training import SegmentationModule  # noqa: E402

PAPER_AUGMENT = OmegaConf.to_container(OmegaConf.load(Path(CONF_DIR) / "augment" / "paper.yaml"))
DATA_DEFAULTS = OmegaConf.load(Path(CONF_DIR) / "data" / "default.yaml")
TARGET_RATIO, TARGET_GROWTH_MB = 0.85, 300.0
log = logging.getLogger("bench.train")


# --- data ------------------------------------------------------------------------------------


def make_data(root: Path, frames: int, width: int, height: int) -> Path:
    """Simulated, annotated dataset (2 training recordings, 1 validation) in ``root``."""
    raw = root / "raw"
    raw.mkdir(parents=True, exist_ok=True)
    for seed, name in enumerate(("train_00", "train_01", "val_00")):
        cfg = SimConfig(frames=frames, seed=seed, width=width, height=height, workers=1)
        simulate_recording(cfg, raw / f"{name}.mcap")
    # every frame is kept (short recordings may hold the robot still): throughput, not selection
    annotate_folder(raw, root, load_robot(), AnnotateOptions(min_joint_speed=0.0))
    return root


def replicate_dataset(src: Path, dst: Path, files: int, frames_per_file: int,
                      chunk_size: int = 1 << 20) -> Path:
    """An annotated dataset of ``files`` training recordings of ``frames_per_file`` frames each,
    cycling through the (encoded) frames of ``src``'s first training recording at 30 Hz, with
    ``chunk_size``-byte chunks; ``src``'s validation recordings are linked unchanged."""
    manifest = read_manifest(src)
    source = manifest.split("train")[0].path
    reader = RecordingReader(source, mask_topics=MASKS)
    frames = list(reader.frames(decode=False))
    names = reader.joint_names()
    tf = [(p, c, T) for (p, c), T in reader.tf_static().items()]
    infos = {side: reader.camera_infos(side) for side in ("left", "right")}
    dst.mkdir(parents=True, exist_ok=True)
    records = []
    period = 33_333_333
    for k in range(files):
        path = dst / f"train_{k:03d}.mcap"
        with RecordingWriter(path, metadata=reader.metadata(), chunk_size=chunk_size) as w:
            w.write_tf_static(tf, 0)
            for side, info in infos.items():
                w.write_camera_info(camera_info_topic(side=side), 0, info.frame_id, info.K,
                                    info.width, info.height)
            for i in range(frames_per_file):
                f = frames[(k * frames_per_file + i) % len(frames)]
                stamp = (i + 1) * period
                for robot, q in f.joints.items():
                    w.write_joint_state(joint_states_topic(robot), stamp, names[robot], q)
                mask = f.masks[MASKS[0]].tobytes()
                for side, img in (("left", f.left), ("right", f.right)):
                    w.write_compressed(image_topic(side=side), stamp, f.left_frame_id,
                                       img.tobytes(), msgs.JPEG_FORMAT)
                    w.write_compressed(mask_topic(side=side), stamp, f.left_frame_id, mask,
                                       msgs.PNG_MASK_FORMAT)
        records.append({"file": path.name, "split": "train", "draped_from_ns": None,
                        "robots": list(reader.robots)})
    for entry in manifest.split("val"):
        (dst / entry.path.name).symlink_to(entry.path.resolve())
        records.append({"file": entry.path.name, "split": "val",
                        "draped_from_ns": entry.draped_from_ns, "robots": list(entry.robots)})
    doc = {"format": "roboseg-annotations/1", "camera": manifest.camera,
           "robot_urdf": manifest.robot_urdf, "subset": manifest.subset, "recordings": records}
    (dst / "manifest.json").write_text(json.dumps(doc, indent=1))
    return dst


# --- throughput ------------------------------------------------------------------------------


def _step(module: SegmentationModule, opt: torch.optim.Optimizer, batch: dict,
          augment: bool) -> None:
    """One training step; ``augment``: the device-side augmentation first (full pipeline)."""
    module.train()
    if augment and module.augment is not None:
        batch = module.augment(batch)
    x, y = prepare(batch, module.hparams.mean, module.hparams.std, module.in_channels)
    loss = module.loss_fn(module(x), y)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()


def cpu_seconds(children: bool = True) -> float:
    """CPU seconds (user + system) of this process and, with ``children``, of its live children
    (the loader workers)."""
    me = psutil.Process()
    total = sum(me.cpu_times()[:2])
    for child in me.children(recursive=True) if children else ():
        with contextlib.suppress(psutil.Error):  # a child that just ended
            total += sum(child.cpu_times()[:2])
    return total


def throughput(data: Path, args: argparse.Namespace) -> dict[int, dict[str, float]]:
    """Per channel count: ``full`` / ``bare`` images/s, ``full_cpu`` / ``bare_cpu`` images
    per CPU-second over ``args.steps`` timed steps of each kind (see module doc), and the CPU
    seconds per step of the bare step, of this process in full steps and of the loader
    workers in full steps (``cpu_bare``, ``cpu_main``, ``cpu_workers``)."""
    size, batch = [args.size, args.size], args.batch
    setups: dict[int, dict[str, Any]] = {}
    for ch in (3, 4):
        module = SegmentationModule(model={"name": args.model, "in_channels": ch},
                                    augment=PAPER_AUGMENT, image_size=size)
        module.augment.reseed(0)
        dm = RecordingDataModule(data, image_size=size, batch_size=batch,
                                 num_workers=args.workers, shuffle_buffer=64, with_prior=ch,
                                 prior_probability=1.0 if ch == 4 else 0.0)
        dm.setup("fit")
        gen = torch.Generator().manual_seed(ch)
        shape = (batch, 1, *size)
        bare = {"image": torch.rand(batch, 3, *size, generator=gen),
                "mask": (torch.rand(shape, generator=gen) > 0.7).float(),
                "prior": (torch.rand(shape, generator=gen) > 0.7).float(),
                "visible": torch.ones(batch, dtype=torch.bool)}
        setups[ch] = {"module": module, "opt": torch.optim.AdamW(module.parameters(), lr=1e-4),
                      "stream": iter(dm.train_dataloader()), "bare": bare}
    for s in setups.values():  # warm-up: workers started, robot loaded, first chunks read
        _step(s["module"], s["opt"], next(s["stream"]), True)
        _step(s["module"], s["opt"], s["bare"], False)
    prefetched = max(1, args.workers) * 2  # DataLoader prefetch_factor 2 per worker
    spent = {(ch, kind): [0.0, 0.0, 0.0] for ch in (3, 4) for kind in ("full", "bare")}
    order = [(3, "full"), (3, "bare"), (4, "full"), (4, "bare")]
    per_block = max(1, args.steps // 2)
    for kind_ch in order + order[::-1]:
        ch, kind = kind_ch
        s = setups[ch]
        if kind == "full":
            for _ in range(prefetched if args.workers > 0 else 0):
                next(s["stream"])  # made while other blocks ran: not timed, not used
        # bare steps use no loader: their CPU time excludes the workers' (which may refill
        # their prefetch queues meanwhile, batches discarded above)
        full = kind == "full"
        wall, cpu, own = time.perf_counter(), cpu_seconds(full), cpu_seconds(False)
        for _ in range(per_block):
            _step(s["module"], s["opt"], next(s["stream"]) if full else s["bare"], full)
        spent[kind_ch][0] += time.perf_counter() - wall
        spent[kind_ch][1] += cpu_seconds(full) - cpu
        spent[kind_ch][2] += cpu_seconds(False) - own
    steps = 2 * per_block
    n = steps * batch
    out = {}
    for ch in (3, 4):
        full, bare = spent[(ch, "full")], spent[(ch, "bare")]
        out[ch] = {"full": n / full[0], "bare": n / bare[0], "full_cpu": n / full[1],
                   "bare_cpu": n / bare[1], "cpu_bare": bare[1] / steps,
                   "cpu_main": full[2] / steps, "cpu_workers": (full[1] - full[2]) / steps}
    return out


# --- loader memory ---------------------------------------------------------------------------


def _status_mb(pid: int, key: str) -> float:
    """``VmRSS`` / ``VmHWM`` (peak RSS) of a process from ``/proc/<pid>/status``, MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"/proc/{pid}/status has no {key}")


def stream_memory(data: Path, n_frames: int, size: int, batch: int, workers: int
                  ) -> dict[str, float]:
    """Stream ``n_frames`` training frames through the training loader (prior on); RSS of the
    loader processes at the first batch and their peak RSS (``VmHWM``) at the end, MB."""
    dm = RecordingDataModule(data, image_size=[size, size], batch_size=batch,
                             num_workers=workers,
                             shuffle_buffer=int(DATA_DEFAULTS.shuffle_buffer), with_prior=4,
                             prior_probability=1.0)
    dm.setup("fit")
    before = _status_mb(os.getpid(), "VmRSS")
    it = iter(dm.train_dataloader())
    seen = len(next(it)["index"])
    pids = [os.getpid()] + [p.pid for p in psutil.Process().children(recursive=True)]
    start = {pid: _status_mb(pid, "VmRSS") for pid in pids}
    t = time.perf_counter()
    while seen < n_frames:
        seen += len(next(it)["index"])
    fps = (seen - batch) / (time.perf_counter() - t)
    peak = {pid: _status_mb(pid, "VmHWM") for pid in pids}
    return {"frames": seen, "processes": len(pids), "rss_before_mb": before,
            "rss_start_mb": sum(start.values()), "peak_mb": sum(peak.values()),
            "growth_mb": sum(peak[p] - start[p] for p in pids),
            "worst_process_growth_mb": max(peak[p] - start[p] for p in pids),
            "frames_per_s": fps, "shards": len(dm.datasets["train"].shards)}


def memory_subprocess(data: Path, args: argparse.Namespace) -> dict[str, float]:
    """:func:`stream_memory` in a fresh interpreter (nothing else allocated in it)."""
    cmd = [sys.executable, "-m", "bench.train", "--memory-child", str(data), "--stream",
           str(args.stream), "--size", str(args.size), "--batch", str(args.batch),
           "--workers", str(args.workers)]
    proc = subprocess.run(cmd, cwd=Path(__file__).resolve().parents[1], capture_output=True,
                          text=True, check=False)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("MEMORY ")]
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"memory measurement failed:\n{proc.stderr[-3000:]}")
    return json.loads(lines[-1][len("MEMORY "):])


# --- main ------------------------------------------------------------------------------------


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="annotated dataset folder")
    parser.add_argument("--steps", type=int, default=6, help="timed steps per kind and channels")
    parser.add_argument("--model", default="unet_mit_b0")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--stream", type=int, default=10_000, help="frames for the memory part")
    parser.add_argument("--memory-files", type=int, default=24,
                        help="recordings the memory part streams from")
    parser.add_argument("--no-memory", action="store_true", help="skip the memory part")
    parser.add_argument("--no-throughput", action="store_true", help="skip the throughput part")
    parser.add_argument("--memory-child", type=Path, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    torch.manual_seed(0)
    if args.memory_child is not None:
        print("MEMORY " + json.dumps(stream_memory(args.memory_child, args.stream, args.size,
                                                   args.batch, args.workers)), flush=True)
        return
    rows: list[list[str]] = []
    verdicts: list[str] = []
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data or make_data(Path(tmp) / "data", 16, 480, 270)
        if not args.no_throughput:
            res = throughput(data, args)
            head = f"{args.model}, {args.size}², batch {args.batch}, {args.workers} workers"
            for ch in (3, 4):
                r = res[ch]
                what = "3 channels" if ch == 3 else "4 channels, prior every sample"
                ratio, ratio_cpu = r["full"] / r["bare"], r["full_cpu"] / r["bare_cpu"]
                rows += [[f"full pipeline images/s ({what})", f"{r['full']:.3f}"],
                         [f"bare step images/s ({ch} channels)", f"{r['bare']:.3f}"],
                         [f"ratio full / bare, wall clock ({ch} ch)", f"{ratio:.3f}"],
                         [f"ratio full / bare, images per CPU-s ({ch} ch)", f"{ratio_cpu:.3f}"],
                         [f"CPU-s per step: bare / full, this process / full, loader workers "
                          f"({ch} ch)",
                          f"{r['cpu_bare']:.2f} / {r['cpu_main']:.2f} / {r['cpu_workers']:.3f}"]]
                verdicts.append(f"{'PASS' if ratio >= TARGET_RATIO else 'FAIL'}  throughput "
                                f"ratio {ch} channels {ratio:.3f} wall, {ratio_cpu:.3f} CPU "
                                f"(target >= {TARGET_RATIO}; {head})")
        if not args.no_memory:
            frames_per_file = -(-min(args.stream, 2400) // args.memory_files)
            many = replicate_dataset(data, Path(tmp) / "many", args.memory_files,
                                     frames_per_file)
            m = memory_subprocess(many, args)
            rows += [[f"loader processes (main + {args.workers} workers), training shards",
                      f"{m['processes']} , {m['shards']}"],
                     ["loader RSS MB at the first batch (sum)", f"{m['rss_start_mb']:.1f}"],
                     [f"loader peak RSS MB over {m['frames']} frames (sum)",
                      f"{m['peak_mb']:.1f}"],
                     ["largest growth of one process MB", f"{m['worst_process_growth_mb']:.1f}"],
                     ["streaming frames/s (prior on)", f"{m['frames_per_s']:.1f}"]]
            verdicts.append(f"{'PASS' if m['growth_mb'] < TARGET_GROWTH_MB else 'FAIL'}  loader "
                            f"memory growth {m['growth_mb']:.1f} MB over {m['frames']} frames "
                            f"from {args.memory_files} recordings (target < "
                            f"{TARGET_GROWTH_MB:g} MB)")
    print(format_table(["measure", "value"], rows))
    print("\n".join(verdicts))


if __name__ == "__main__":
    main()
