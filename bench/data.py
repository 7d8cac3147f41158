"""Data benchmarks: simulator and annotation throughput, MCAP reading, streaming memory, and
how hard the simulated drape makes segmentation.

Run ``python -m bench.data [--sections simulator,annotation,memory,mcap_read,difficulty]
[--width 960 --height 540] [--workers 1,2] ...``. Each section is a function
``(args) -> dict`` registered with :func:`section`; sections are run in order and their results
printed as JSON (and written to ``--json`` if given), each with the machine's 1-minute load
average. To add a section, define a function in this file, decorate it with
``@section("name")`` and add any options it needs in :func:`build_parser`.

Numbers depend on the machine and its load: wall-clock rates suffer on a shared machine, CPU
milliseconds per frame (summed over all processes) less so. The simulator numbers include
JPEG/PNG encoding and MCAP writing; setup (robots, drapes, the static room) is reported apart
from the steady per-frame rate.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from roboseg.recording.reader import RecordingReader
from roboseg.sim import SIM_METADATA, SimConfig, simulate_recording

log = logging.getLogger("bench.data")

Section = Callable[[argparse.Namespace], dict[str, Any]]
SECTIONS: dict[str, Section] = {}


def section(name: str) -> Callable[[Section], Section]:
    """Register a benchmark section under ``name`` (run order = definition order)."""

    def register(fn: Section) -> Section:
        SECTIONS[name] = fn
        return fn

    return register


# --- trivial baseline ---------------------------------------------------------------------------


def iou(pred: np.ndarray, gt: np.ndarray) -> float:
    """Pooled intersection over union of boolean masks (1.0 when both are empty)."""
    union = np.logical_or(pred, gt).sum()
    return 1.0 if union == 0 else float(np.logical_and(pred, gt).sum() / union)


def value_saturation(images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """HSV value and saturation in [0, 255] of RGB uint8 images ``[N, H, W, 3]``."""
    hsv = np.stack([cv2.cvtColor(im, cv2.COLOR_RGB2HSV) for im in images])
    return hsv[..., 2], hsv[..., 1]


def threshold_baseline(
    value: np.ndarray, sat: np.ndarray, v_min: float, s_max: float
) -> np.ndarray:
    """The trivial robot detector: bright (value ≥ ``v_min``) and unsaturated (saturation ≤
    ``s_max``) pixels, i.e. white/grey paint."""
    return (value >= v_min) & (sat <= s_max)


def tune_baseline(
    images: np.ndarray,
    masks: np.ndarray,
    v_grid: np.ndarray | None = None,
    s_grid: np.ndarray | None = None,
) -> tuple[float, float, float]:
    """Grid-search ``(v_min, s_max)`` maximising the pooled IoU on ``images``/``masks``;
    returns ``(v_min, s_max, iou)``."""
    v_grid = np.arange(40, 256, 8) if v_grid is None else v_grid
    s_grid = np.arange(8, 256, 8) if s_grid is None else s_grid
    value, sat = value_saturation(images)
    best = (0.0, 255.0, -1.0)
    for v in v_grid:
        bright = value >= v
        for s in s_grid:
            score = iou(bright & (sat <= s), masks)
            if score > best[2]:
                best = (float(v), float(s), score)
    return best


def read_phases(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Left images ``[N,H,W,3]``, gt masks ``[N,H,W]`` and a draped flag ``[N]`` of a simulated
    recording (draped from the ``drape_start_stamp_ns`` of its metadata)."""
    with RecordingReader(path, mask_topics=["left/robot_mask_gt"]) as reader:
        start = int(reader.metadata()[SIM_METADATA]["drape_start_stamp_ns"])
        frames = list(reader.frames())
    images = np.stack([f.left for f in frames])
    masks = np.stack([f.masks["left/robot_mask_gt"] for f in frames])
    draped = np.array([start >= 0 and f.stamp_ns >= start for f in frames])
    return images, masks, draped


# --- sections -----------------------------------------------------------------------------------


def _cpu_seconds() -> float:
    """CPU seconds (user + system) of this process and of its finished children."""
    import resource

    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _worker_list(text: str) -> list[int]:
    return [int(w) for w in str(text).split(",") if w.strip()]


@section("simulator")
def bench_simulator(args: argparse.Namespace) -> dict[str, Any]:
    """Stereo frames per second of :func:`simulate_recording` at ``--width``×``--height`` for
    each ``--workers`` count, run side by side on the same seed: one-off setup (robot loading,
    drapes, the static room's ray casting) apart from the steady-state per-frame rate, plus CPU
    seconds per frame (all processes) and whether the files are byte-identical."""
    out: dict[str, Any] = {"width": args.width, "height": args.height, "frames": args.frames}
    runs, digests = [], set()
    with tempfile.TemporaryDirectory() as tmp:
        for workers in _worker_list(args.workers):
            cfg = SimConfig(
                frames=args.frames,
                seed=args.seed,
                width=args.width,
                height=args.height,
                urdf=args.urdf,
                workers=workers,
            )
            path = Path(tmp) / f"sim_w{workers}.mcap"
            cpu0 = _cpu_seconds()
            summary = simulate_recording(cfg, path)
            cpu = _cpu_seconds() - cpu0
            frame_s = summary.seconds - summary.setup_seconds
            digests.add(hashlib.sha256(path.read_bytes()).hexdigest())
            runs.append(
                {
                    "workers": workers,
                    "seconds_setup": round(summary.setup_seconds, 2),
                    "seconds_frames": round(frame_s, 2),
                    "steady_stereo_frames_per_second": round(args.frames / frame_s, 2),
                    "overall_stereo_frames_per_second": round(args.frames / summary.seconds, 2),
                    "cpu_ms_per_frame_incl_setup": round(1e3 * cpu / args.frames, 1),
                }
            )
    out["runs"] = runs
    out["identical_output"] = len(digests) == 1
    out["target_steady_stereo_fps"] = 5
    return out


@section("difficulty")
def bench_difficulty(args: argparse.Namespace) -> dict[str, Any]:
    """IoU of the trivial colour/brightness baseline, tuned on each recording's undraped frames,
    on its draped frames (should be poor: the drape hides the robot's white paint)."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.recordings):
            seed = args.seed + k
            cfg = SimConfig(
                frames=args.difficulty_frames,
                seed=seed,
                width=args.diff_width,
                height=args.diff_height,
                urdf=args.urdf,
            )
            path = Path(tmp) / f"d{seed}.mcap"
            simulate_recording(cfg, path)
            images, masks, draped = read_phases(path)
            v, s, iou_undraped = tune_baseline(images[~draped], masks[~draped])
            value, sat = value_saturation(images[draped])
            iou_draped = iou(threshold_baseline(value, sat, v, s), masks[draped])
            rows.append(
                {
                    "seed": seed,
                    "v_min": v,
                    "s_max": s,
                    "iou_undraped_tuned": round(iou_undraped, 3),
                    "iou_draped": round(iou_draped, 3),
                }
            )
    return {
        "recordings": rows,
        "mean_iou_undraped_tuned": round(
            float(np.mean([r["iou_undraped_tuned"] for r in rows])), 3
        ),
        "mean_iou_draped": round(float(np.mean([r["iou_draped"] for r in rows])), 3),
    }


def _data_io() -> Any:
    """``bench.data_io`` whether run as ``python bench/data.py`` or ``python -m bench.data``."""
    import importlib

    try:
        return importlib.import_module("bench.data_io")
    except ModuleNotFoundError:
        return importlib.import_module("data_io")


@section("annotation")
def bench_annotation(args: argparse.Namespace) -> dict[str, Any]:
    """Annotated stereo frames per second of :func:`annotate_recording` at ``--width``×
    ``--height`` on a simulated recording of ``--annotate-frames`` frames (all kept; includes
    raw copying, FK, render, PNG, MCAP), for each ``--workers`` count side by side, with CPU
    milliseconds per frame over all processes and the worst IoU against the simulator's ground
    truth."""
    from roboseg.annotate import AnnotateOptions, annotate_recording
    from roboseg.robot import load_robot

    robot = load_robot(args.urdf)
    n = args.annotate_frames
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        cfg = SimConfig(
            frames=n,
            seed=args.seed,
            width=args.width,
            height=args.height,
            urdf=args.urdf,
            workers=max(_worker_list(args.workers)),
        )
        simulate_recording(cfg, Path(tmp) / "in.mcap")
        for workers in _worker_list(args.workers):
            out = Path(tmp) / f"out_w{workers}.mcap"
            options = AnnotateOptions(min_joint_speed=0, workers=workers)
            cpu0, t0 = _cpu_seconds(), time.perf_counter()
            result = annotate_recording(Path(tmp) / "in.mcap", out, robot, options)
            seconds = time.perf_counter() - t0
            cpu = _cpu_seconds() - cpu0
            runs.append(
                {
                    "workers": workers,
                    "frames": result.frames_kept,
                    "seconds": round(seconds, 2),
                    "stereo_frames_per_second": round(result.frames_kept / seconds, 2),
                    "cpu_ms_per_frame": round(1e3 * cpu / max(result.frames_kept, 1), 1),
                }
            )
        min_iou = _min_iou_vs_ground_truth(out)
    return {
        "width": args.width,
        "height": args.height,
        "runs": runs,
        "min_iou_vs_ground_truth": round(min_iou, 4),
        "target": 30,
    }


def _min_iou_vs_ground_truth(path: Path) -> float:
    """Worst per-frame, per-camera IoU of the annotated masks against the simulator's."""
    topics = [f"{s}/{k}" for s in ("left", "right") for k in ("robot_mask", "robot_mask_gt")]
    worst = 1.0
    with RecordingReader(path, mask_topics=topics) as reader:
        for frame in reader.frames():
            for side in ("left", "right"):
                pred, gt = frame.masks[f"{side}/robot_mask"], frame.masks[f"{side}/robot_mask_gt"]
                worst = min(worst, iou(pred, gt))
    return worst


@section("mcap_read")
def bench_mcap_read(args: argparse.Namespace) -> dict[str, Any]:
    """Decoded stereo frames per second of :class:`RecordingReader` (bench.data_io)."""
    data_io = _data_io()
    measure_read_throughput = data_io.measure_read_throughput
    write_synthetic_recording = data_io.write_synthetic_recording

    with tempfile.TemporaryDirectory() as tmp:
        path = write_synthetic_recording(
            Path(tmp) / "r.mcap", args.frames * 5, args.width, args.height
        )
        fps = measure_read_throughput(path)
    return {"frames": args.frames * 5, "frames_per_s": round(fps, 1)}


_PEAK_RSS = """
import json, resource
def _hwm_mb():
    try:  # this process image's own high-water mark (ru_maxrss survives exec on Linux)
        with open("/proc/self/status") as f:
            return next(int(x.split()[1]) for x in f if x.startswith("VmHWM:")) / 1024
    except (OSError, StopIteration):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
print(json.dumps({"self_mb": _hwm_mb(), "children_mb": kids}))
"""


def _peak_rss_child(code: str) -> dict[str, float]:
    """Peak RSS (MB) of a fresh Python process running ``code`` (``self_mb``: ``VmHWM`` on
    Linux, since ``ru_maxrss`` would carry over the bench's own size from before ``exec``) and
    of the largest process it started (``children_mb``, 0 without children), reported by the
    process itself, so every measurement is independent of the others."""
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-c", code + "\n" + _PEAK_RSS],
        check=True,
        capture_output=True,
        text=True,
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


@section("memory")
def bench_memory(args: argparse.Namespace) -> dict[str, Any]:
    """Peak RSS of reading, and of annotating, a ``--memory-frames`` short vs long recording,
    each in a fresh process, and the growth from short to long (streaming: about 0).

    The recordings are small (``--memory-width``×``--memory-height`` JPEGs;
    :func:`bench.data_io.write_annotatable_recording`, not rendered) so that writing thousands
    of frames stays quick, in chunks of ``--memory-chunk-kb``; the annotation uses
    ``--memory-workers`` processes (``children_mb``: the largest worker)."""
    data_io = _data_io()
    short, long = (int(n) for n in args.memory_frames.split(","))
    w, h = args.memory_width, args.memory_height
    out: dict[str, Any] = {"image": f"{w}x{h} (small to keep generation quick)"}
    rows: dict[str, dict[int, dict[str, float]]] = {"read": {}, "annotate": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for n in (short, long):
            path = data_io.write_annotatable_recording(
                Path(tmp) / f"r{n}.mcap", n, w, h, chunk_size=args.memory_chunk_kb * 1024
            )
            read = (
                "from roboseg.recording import RecordingReader as R\n"
                f"with R({str(path)!r}) as r:\n"
                "    assert sum(1 for _ in r.frames()) > 0\n"
            )
            rows["read"][n] = _peak_rss_child(read)
            annotate = (
                "import torch\n"
                "torch.set_num_threads(1)\n"
                "from roboseg.annotate import AnnotateOptions, annotate_recording\n"
                "from roboseg.robot import load_robot\n"
                f"o = AnnotateOptions(min_joint_speed=0, workers={args.memory_workers})\n"
                f"r = annotate_recording({str(path)!r}, {str(Path(tmp) / 'a.mcap')!r},"
                " load_robot(None), o)\n"
                f"assert r.frames_kept == {n}, r\n"
            )
            rows["annotate"][n] = _peak_rss_child(annotate)
    for what, by_n in rows.items():
        for key in ("self_mb", "children_mb"):
            if what == "read" and key == "children_mb":
                continue
            a, b = by_n[short][key], by_n[long][key]
            out[f"{what}_{key}"] = {
                f"{short}_frames": round(a, 1),
                f"{long}_frames": round(b, 1),
                "growth_mb": round(b - a, 1),
            }
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sections", default=",".join(SECTIONS), help="comma-separated sections")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--urdf", default=None, help="robot URDF (default: the built-in arm)")
    p.add_argument("--width", type=int, default=960)
    p.add_argument("--height", type=int, default=540)
    p.add_argument("--frames", type=int, default=20, help="simulator section: frames to time")
    p.add_argument(
        "--workers", default="1,2", help="simulator/annotation: process counts, side by side"
    )
    p.add_argument("--annotate-frames", type=int, default=60, help="annotation section: frames")
    p.add_argument("--memory-frames", default="1000,5000", help="memory section: short,long")
    p.add_argument("--memory-width", type=int, default=64)
    p.add_argument("--memory-height", type=int, default=48)
    p.add_argument("--memory-workers", type=int, default=2, help="memory section: annotation")
    p.add_argument(
        "--memory-chunk-kb",
        type=int,
        default=256,
        help="memory section: MCAP chunk size, small so that both recordings fill the reader's "
        "chunk cache (otherwise the short one shows less cache, not less growth)",
    )
    p.add_argument("--recordings", type=int, default=4, help="difficulty section: recordings")
    p.add_argument("--difficulty-frames", type=int, default=24)
    p.add_argument("--diff-width", type=int, default=480)
    p.add_argument("--diff-height", type=int, default=270)
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    p.add_argument("--json", type=Path, default=None, help="also write the results here")
    return p


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    torch.set_num_threads(args.threads)
    results: dict[str, Any] = {}
    for name in args.sections.split(","):
        if name not in SECTIONS:
            raise SystemExit(f"unknown section {name!r}; known: {', '.join(SECTIONS)}")
        t0 = time.perf_counter()
        results[name] = SECTIONS[name](args)
        results[name]["bench_seconds"] = round(time.perf_counter() - t0, 1)
        # other processes' load: wall-clock rates above are shared with it (os.cpu_count() cores)
        results[name]["load_average_1min"] = round(os.getloadavg()[0], 1)
        print(json.dumps({name: results[name]}, indent=2), flush=True)
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2))
    return results


if __name__ == "__main__":
    main()
