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
from the steady per-frame rate, and so is the annotation's (index, selection, mesh check). The
memory section measures the peak resident set of each process on its own (``VmHWM`` of a fresh
interpreter and of each of its workers), never the running maximum over all children that
``RUSAGE_CHILDREN`` keeps. A summary at the end puts every rate beside its target.
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


#: The paper's robot beside the checkout (73k faces, not closed): the annotation worst case.
MED7 = Path(__file__).resolve().parents[2] / "shared" / "robots" / "lbr_med7" / "lbr_med7.urdf"
ANNOTATION_TARGET_FPS = 30.0
SIMULATOR_TARGET_FPS = 5.0


def _annotation_robots(names: str, urdf: str | None) -> list[tuple[str, str | None]]:
    """(label, URDF or None) of ``--annotate-robots`` (``builtin``: ``--urdf`` or the built-in
    arm; ``med7``: :data:`MED7`, skipped when absent)."""
    out: list[tuple[str, str | None]] = []
    for name in (n.strip() for n in names.split(",") if n.strip()):
        if name == "builtin":
            out.append(("builtin" if urdf is None else Path(urdf).stem, urdf))
        elif name == "med7":
            if MED7.is_file():
                out.append(("lbr_med7", str(MED7)))
            else:
                log.warning("annotation: %s absent, lbr_med7 skipped", MED7)
        else:
            raise SystemExit(f"--annotate-robots: unknown robot {name!r} (builtin, med7)")
    return out


@section("annotation")
def bench_annotation(args: argparse.Namespace) -> dict[str, Any]:
    """Annotated stereo frames per second of :func:`annotate_recording` at ``--width``×
    ``--height`` on a simulated recording of ``--annotate-frames`` frames (all kept; includes
    raw copying, FK, render, PNG, MCAP) per robot of ``--annotate-robots``, with the full mesh
    and with the mesh reduced by each of ``--annotate-reductions`` (used only where its masks
    reach IoU 0.995 against the full mesh's), for each ``--workers`` count. Set-up (reading
    the index, selecting frames, the reduced mesh and its IoU check) is reported apart from
    the steady per-frame rate; a short untimed annotation first pays torch's one-off costs, as
    the first recording of a folder does. Also CPU milliseconds per frame over all processes
    and the worst IoU against the simulator's ground truth."""
    from roboseg.annotate import AnnotateOptions, annotate_recording
    from roboseg.robot import load_robot

    n = args.annotate_frames
    meshes = [0.0] + [r for r in (float(x) for x in args.annotate_reductions.split(",") if x) if r]
    robots: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for label, urdf in _annotation_robots(args.annotate_robots, args.urdf):
            robot = load_robot(urdf)
            source = Path(tmp) / f"{label}.mcap"
            cfg = SimConfig(
                frames=n, seed=args.seed, width=args.width, height=args.height, urdf=urdf
            )
            simulate_recording(cfg, source)
            warm = AnnotateOptions(min_joint_speed=0)
            annotate_recording(source, Path(tmp) / "warm.mcap", robot, warm, target=4)
            runs = []
            for workers in _worker_list(args.workers):
                for reduction in meshes:
                    out = Path(tmp) / f"{label}_w{workers}_r{reduction}.mcap"
                    options = AnnotateOptions(
                        min_joint_speed=0, workers=workers, mesh_reduction=reduction
                    )
                    cpu0 = _cpu_seconds()
                    result = annotate_recording(source, out, robot, options)
                    cpu = _cpu_seconds() - cpu0
                    kept = max(result.frames_kept, 1)
                    frames_s = result.seconds - result.setup_seconds
                    fps = result.frames_kept / frames_s
                    runs.append(
                        {
                            "workers": workers,
                            "mesh_reduction": reduction,
                            "mesh": result.mesh,
                            "frames": result.frames_kept,
                            "seconds_setup": round(result.setup_seconds, 2),
                            "seconds_frames": round(frames_s, 2),
                            "steady_stereo_frames_per_second": round(fps, 1),
                            "overall_stereo_frames_per_second": round(kept / result.seconds, 1),
                            "target": ANNOTATION_TARGET_FPS,
                            "meets_target": fps >= ANNOTATION_TARGET_FPS,
                            "cpu_ms_per_frame": round(1e3 * cpu / kept, 1),
                            "min_iou_vs_ground_truth": round(_min_iou_vs_ground_truth(out), 4),
                        }
                    )
            faces = len(robot.faces)
            robots[label] = {"faces": faces, "runs": runs}
    return {
        "width": args.width,
        "height": args.height,
        "torch_threads": torch.get_num_threads(),
        "robots": robots,
        "target_stereo_fps": ANNOTATION_TARGET_FPS,
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


#: Runs a measured snippet (``CODE``) in this process while a thread polls the ``VmHWM`` (peak
#: resident set) of every descendant process; prints this process's own ``VmHWM`` and each
#: descendant's last reading as JSON. ``VmHWM`` only grows, so the last reading is the child's
#: peak up to at most one poll interval before it exited.
_PEAK_RSS = """
import json, os, threading
import psutil

def vm_hwm_kb(pid):
    with open(f"/proc/{pid}/status") as f:
        return next(int(x.split()[1]) for x in f if x.startswith("VmHWM:"))

peaks, stop = {}, threading.Event()

def watch():
    me = psutil.Process()
    while True:
        for child in me.children(recursive=True):
            try:
                peaks[child.pid] = max(peaks.get(child.pid, 0), vm_hwm_kb(child.pid))
            except (OSError, StopIteration):
                pass  # exited between listing and reading
        if stop.wait(POLL_S):
            return

watcher = threading.Thread(target=watch, daemon=True)
watcher.start()
try:
    exec(compile(CODE, "<measured>", "exec"), {"__name__": "__measured__"})
finally:
    stop.set()
    watcher.join()
print(json.dumps({"self_mb": vm_hwm_kb(os.getpid()) / 1024,
                  "children_mb": [peaks[p] / 1024 for p in sorted(peaks)]}))
"""


def peak_rss(code: str, poll_s: float = 0.02) -> dict[str, Any]:
    """Peak resident set sizes (MB) of a fresh Python process running ``code``: its own
    (``self_mb``, from ``/proc/self/status`` ``VmHWM``: the peak of this process image, not
    the ``ru_maxrss`` that would carry the bench's size over from before ``exec``) and that of
    each process it started (``children_mb``, in the order they were started; read by polling
    their ``VmHWM`` every ``poll_s`` seconds), each process measured on its own. Linux only.
    """
    import subprocess
    import sys

    script = f"CODE = {code!r}\nPOLL_S = {float(poll_s)!r}\n" + _PEAK_RSS
    done = subprocess.run(
        [sys.executable, "-c", script], check=True, capture_output=True, text=True
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def _growth(short: float, long: float) -> dict[str, float]:
    return {"short": round(short, 1), "long": round(long, 1), "growth": round(long - short, 1)}


@section("memory")
def bench_memory(args: argparse.Namespace) -> dict[str, Any]:
    """Peak RSS of reading, and of annotating, a short and a long simulated recording of
    ``--memory-frames`` frames at ``--width``×``--height``, each in a fresh process, for each
    ``--memory-workers`` count: the annotating process's own peak and every worker's. Streaming
    keeps them flat: the growth from short to long should be small beside the size of the
    long recording's extra frames (``extra_data_mb``, what holding them would cost)."""
    short, long = (int(n) for n in args.memory_frames.split(","))
    out: dict[str, Any] = {"image": f"{args.width}x{args.height}", "frames": [short, long]}
    peaks: dict[str, dict[int, dict[str, Any]]] = {}
    sizes = {}
    with tempfile.TemporaryDirectory() as tmp:
        for n in (short, long):
            path = Path(tmp) / f"r{n}.mcap"
            cfg = SimConfig(
                frames=n, seed=args.seed, width=args.width, height=args.height, urdf=args.urdf
            )
            simulate_recording(cfg, path)
            sizes[n] = path.stat().st_size / 2**20
            read = (
                "from roboseg.recording import RecordingReader as R\n"
                f"with R({str(path)!r}) as r:\n"
                f"    assert sum(1 for _ in r.frames()) == {n}\n"
            )
            peaks.setdefault("read", {})[n] = peak_rss(read)
            for workers in _worker_list(args.memory_workers):
                annotate = (
                    "import torch\n"
                    "torch.set_num_threads(1)\n"
                    "from roboseg.annotate import AnnotateOptions, annotate_recording\n"
                    "from roboseg.robot import load_robot\n"
                    f"o = AnnotateOptions(min_joint_speed=0, workers={workers})\n"
                    f"r = annotate_recording({str(path)!r}, {str(Path(tmp) / 'a.mcap')!r},"
                    f" load_robot({args.urdf!r}), o)\n"
                    f"assert r.frames_kept == {n}, r\n"
                )
                peaks.setdefault(f"annotate_workers_{workers}", {})[n] = peak_rss(annotate)
    out["extra_data_mb"] = round(sizes[long] - sizes[short], 1)
    rows: dict[str, Any] = {}
    for what, by_n in peaks.items():
        rows[what] = {"process_mb": _growth(by_n[short]["self_mb"], by_n[long]["self_mb"])}
        kids_short, kids_long = by_n[short]["children_mb"], by_n[long]["children_mb"]
        if kids_short or kids_long:
            rows[what]["workers_mb"] = [
                _growth(a, b) for a, b in zip(kids_short, kids_long, strict=False)
            ]
    out["peak_rss_mb"] = rows
    growths = [r["process_mb"]["growth"] for r in rows.values()]
    growths += [w["growth"] for r in rows.values() for w in r.get("workers_mb", [])]
    out["largest_growth_mb"] = max(growths)
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
    p.add_argument(
        "--annotate-robots",
        default="builtin,med7",
        help="annotation section: builtin (--urdf or the built-in arm) and/or med7 (the LBR "
        "Med 7 beside the checkout, skipped when absent)",
    )
    p.add_argument(
        "--annotate-reductions",
        default="0.3,0.6",
        help="annotation section: mesh reductions timed besides the full mesh (each used only "
        "where its masks reach IoU 0.995 against the full mesh's)",
    )
    p.add_argument(
        "--memory-frames",
        default="120,480",
        help="memory section: short,long recording (both long enough to fill the reader's "
        "chunk cache at --width x --height, so that a growth is a growth, not a cache filling)",
    )
    p.add_argument(
        "--memory-workers", default="1,2", help="memory section: annotation process counts"
    )
    p.add_argument("--recordings", type=int, default=4, help="difficulty section: recordings")
    p.add_argument("--difficulty-frames", type=int, default=24)
    p.add_argument("--diff-width", type=int, default=480)
    p.add_argument("--diff-height", type=int, default=270)
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    p.add_argument("--json", type=Path, default=None, help="also write the results here")
    return p


def summary(results: dict[str, Any]) -> list[str]:
    """Plain-text lines of the rates beside their targets (PASS/FAIL) and the memory check."""
    lines = []
    sim = results.get("simulator")
    for run in sim["runs"] if sim else []:
        fps = run["steady_stereo_frames_per_second"]
        lines.append(
            f"{'PASS' if fps >= SIMULATOR_TARGET_FPS else 'FAIL'}  simulator "
            f"{sim['width']}x{sim['height']}, {run['workers']} worker(s): {fps:.1f} stereo "
            f"frames/s steady (target >= {SIMULATOR_TARGET_FPS:g}); set-up "
            f"{run['seconds_setup']:.2f} s apart"
        )
    ann = results.get("annotation")
    for label, robot in (ann or {}).get("robots", {}).items():
        for run in robot["runs"]:
            mesh = "full mesh"
            if run["mesh"] is not None:
                m = run["mesh"]
                mesh = (
                    f"mesh reduced {m['used']:g} (IoU {m['min_iou']:.4f} vs full)"
                    if m["used"]
                    else f"reduction {m['reduction']:g} refused (IoU {m['min_iou']:.4f}): full"
                )
            fps = run["steady_stereo_frames_per_second"]
            lines.append(
                f"{'PASS' if run['meets_target'] else 'FAIL'}  annotation {ann['width']}x"
                f"{ann['height']} {label} ({robot['faces']} faces), {mesh}, {run['workers']} "
                f"worker(s): {fps:.1f} stereo frames/s steady (target >= "
                f"{ANNOTATION_TARGET_FPS:g}); set-up {run['seconds_setup']:.2f} s apart"
            )
    mem = results.get("memory")
    if mem:
        short, long = mem["frames"]
        for what, row in mem["peak_rss_mb"].items():
            parts = [("process", row["process_mb"])]
            parts += [(f"worker {k}", w) for k, w in enumerate(row.get("workers_mb", []), 1)]
            for who, g in parts:
                lines.append(
                    f"memory  {what} {who}: peak RSS {g['short']:.0f} MB at {short} frames, "
                    f"{g['long']:.0f} MB at {long} frames ({g['growth']:+.1f} MB; the extra "
                    f"frames hold {mem['extra_data_mb']:.0f} MB)"
                )
    return lines


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
    lines = summary(results)
    if lines:
        print(f"\nsummary ({torch.get_num_threads()} torch thread(s) per process):")
        print("\n".join(lines))
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2))
    return results


if __name__ == "__main__":
    main()
