"""Data benchmarks: simulator throughput and how hard the simulated drape makes segmentation.

Run ``python bench/data.py [--sections simulator,difficulty] [--width 960 --height 540 ...]``.
Each section is a function ``(args) -> dict`` registered with :func:`section`; sections are run
in order and their results printed as one JSON object (and written to ``--json`` if given). To
add a section (e.g. annotation or recording I/O throughput), define a function in this file,
decorate it with ``@section("name")`` and add any options it needs in :func:`build_parser`.

Numbers depend on the machine and its load; the simulator numbers include JPEG/PNG encoding and
MCAP writing.
"""

from __future__ import annotations

import argparse
import json
import logging
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


@section("simulator")
def bench_simulator(args: argparse.Namespace) -> dict[str, Any]:
    """Stereo frames per second of :func:`simulate_recording` at ``--width``×``--height``
    (setup = robot loading, decimation and the static room's ray casting, reported apart)."""
    out: dict[str, Any] = {"width": args.width, "height": args.height, "frames": args.frames}
    with tempfile.TemporaryDirectory() as tmp:
        short = SimConfig(
            frames=1, seed=args.seed, width=args.width, height=args.height, urdf=args.urdf
        )
        t0 = time.perf_counter()
        simulate_recording(short, Path(tmp) / "setup.mcap")
        t_one = time.perf_counter() - t0
        cfg = SimConfig(
            frames=args.frames, seed=args.seed, width=args.width, height=args.height, urdf=args.urdf
        )
        t0 = time.perf_counter()
        simulate_recording(cfg, Path(tmp) / "bench.mcap")
        total = time.perf_counter() - t0
    per_frame = (total - t_one) / max(args.frames - 1, 1)
    out.update(
        seconds_total=round(total, 2),
        seconds_setup_and_first_frame=round(t_one, 2),
        stereo_frames_per_second=round(1.0 / per_frame, 2),
    )
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
    """Annotated stereo frames per second of :func:`annotate_recording` at ``--width``×``--height``
    on a simulated recording (all frames kept; includes raw copying, FK, render, PNG, MCAP)."""
    from roboseg.annotate import AnnotateOptions, annotate_recording
    from roboseg.robot import load_robot

    robot = load_robot(args.urdf)
    with tempfile.TemporaryDirectory() as tmp:
        cfg = SimConfig(
            frames=args.frames, seed=args.seed, width=args.width, height=args.height, urdf=args.urdf
        )
        simulate_recording(cfg, Path(tmp) / "in.mcap")
        t0 = time.perf_counter()
        result = annotate_recording(
            Path(tmp) / "in.mcap", Path(tmp) / "out.mcap", robot, AnnotateOptions(min_joint_speed=0)
        )
        seconds = time.perf_counter() - t0
    fps = result.frames_kept / max(seconds, 1e-9)
    return {
        "width": args.width,
        "height": args.height,
        "frames": result.frames_kept,
        "stereo_frames_per_second": round(fps, 2),
        "target": 30,
    }


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


def _peak_rss_child(code: str) -> float:
    """Peak RSS (MB) of a fresh Python process running ``code``."""
    import resource
    import subprocess
    import sys

    subprocess.run([sys.executable, "-c", code], check=True)
    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0


@section("memory")
def bench_memory(args: argparse.Namespace) -> dict[str, Any]:
    """Peak RSS of reading and of annotating a 1k- vs a 5k-frame recording (64×48 images to keep
    the bench quick; streaming memory must not grow with the length). Each run is a fresh
    process; RUSAGE_CHILDREN reports the largest child so far, so runs go short to long."""
    write_synthetic_recording = _data_io().write_synthetic_recording

    out: dict[str, Any] = {"image": "64x48"}
    with tempfile.TemporaryDirectory() as tmp:
        for n in (1000, 5000):
            path = write_synthetic_recording(Path(tmp) / f"r{n}.mcap", n, 64, 48)
            read = (
                "from roboseg.recording import RecordingReader as R\n"
                f"r = R({str(path)!r})\n"
                "sum(1 for _ in r.frames())"
            )
            out[f"read_peak_mb_{n}"] = round(_peak_rss_child(read), 1)
    out["note"] = "annotator memory: run annotation on a long recording (not timed here)"
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sections", default=",".join(SECTIONS), help="comma-separated sections")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--urdf", default=None, help="robot URDF (default: the built-in arm)")
    p.add_argument("--width", type=int, default=960)
    p.add_argument("--height", type=int, default=540)
    p.add_argument("--frames", type=int, default=20, help="simulator section: frames to time")
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
        print(json.dumps({name: results[name]}, indent=2), flush=True)
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2))
    return results


if __name__ == "__main__":
    main()
