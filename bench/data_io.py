"""MCAP read throughput: stereo frames per second streamed by :class:`RecordingReader`.

``measure_read_throughput(path)`` times opening a recording, its indexing pass (every chunk
decompressed once, joint states decoded) and streaming every frame with JPEG decoding.
Run ``python bench/data_io.py [recording.mcap ...]``; without a path it writes a synthetic
recording (``--frames`` stereo pairs of ``--width``×``--height`` noisy gradients, two robots
with 7 joints at 4× the frame rate) to a temporary folder first. Numbers depend on the machine
and its load.
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from roboseg.recording import RecordingReader, RecordingWriter
from roboseg.recording.topics import camera_info_topic, image_topic, joint_states_topic

log = logging.getLogger("bench.data_io")


def read_throughput(path: str | Path, *, decode: bool = True, **reader_kwargs: Any) -> dict:
    """Time one full streaming read of ``path``.

    Returns frames yielded, skipped, seconds for the indexing pass and for streaming, and
    frames/s over the whole read (open + index + stream).
    """
    t0 = time.perf_counter()
    with RecordingReader(path, **reader_kwargs) as reader:
        reader.chunk_index()  # forces the indexing pass
        t1 = time.perf_counter()
        n = sum(1 for _ in reader.frames(decode=decode))
        t2 = time.perf_counter()
        stats = reader.stats
    return {
        "path": str(path),
        "frames": n,
        "skipped": stats.skipped,
        "index_s": t1 - t0,
        "stream_s": t2 - t1,
        "frames_per_s": n / max(t2 - t0, 1e-9),
        "mb": Path(path).stat().st_size / 1e6,
    }


def measure_read_throughput(path: str | Path, **reader_kwargs: Any) -> float:
    """Stereo frames per second of one full decoded read of ``path`` (open, index, stream)."""
    return float(read_throughput(path, **reader_kwargs)["frames_per_s"])


def write_synthetic_recording(
    path: Path, frames: int, width: int, height: int, fps: float = 30.0, seed: int = 0
) -> Path:
    """A recording with the project's topics: textured stereo JPEGs, 2 robots × 7 joints."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    K = np.array([[width, 0, (width - 1) / 2], [0, width, (height - 1) / 2], [0, 0, 1.0]])
    t0, period = 1_700_000_000_000_000_000, int(1e9 / fps)
    names = [f"joint_{k}" for k in range(7)]
    noise = rng.normal(0, 8, (height, width, 3)).astype(np.float32)  # sensor noise, rolled
    with RecordingWriter(path) as w:
        for side in ("left", "right"):
            w.write_camera_info(
                camera_info_topic("camera", side), t0, f"camera_{side}", K, width, height
            )
        for i in range(frames):
            stamp = t0 + i * period
            for j in range(4):
                t = stamp + j * period // 4
                for r in range(2):
                    q = np.sin(t * 1e-9 + np.arange(7) + r)
                    w.write_joint_state(joint_states_topic(f"robot_{r}"), t, names, q)
            base = 128 + 60 * np.sin(xx / (17 + i % 5) + yy / 23 + i * 0.1)
            for side in ("left", "right"):
                shift = tuple(rng.integers(0, 64, 2))
                img = np.clip(base[..., None] + np.roll(noise, shift, (0, 1)), 0, 255)
                img = img.astype(np.uint8)
                w.write_image(image_topic("camera", side), stamp, f"camera_{side}", img)
        w.write_joint_state(joint_states_topic("robot_0"), t0 + frames * period, names, np.zeros(7))
        w.write_joint_state(joint_states_topic("robot_1"), t0 + frames * period, names, np.zeros(7))
    return path


def write_annotatable_recording(
    path: Path,
    frames: int,
    width: int,
    height: int,
    fps: float = 15.0,
    seed: int = 0,
    chunk_size: int = 4 * 1024 * 1024,
) -> Path:
    """A recording ``roboseg-annotate`` accepts, written fast (no rendering): one robot (the
    built-in arm's joint names, all joints moving) 1.5 m in front of the left camera, its
    calibration on ``/tf_static``, and small noisy stereo JPEGs of ``width``×``height``, in MCAP
    chunks of about ``chunk_size`` bytes."""
    from roboseg.robot import load_robot

    robot = load_robot(None)
    rng = np.random.default_rng(seed)
    left, right = "camera_left_optical_frame", "camera_right_optical_frame"
    K = np.array([[width, 0, (width - 1) / 2], [0, width, (height - 1) / 2], [0, 0, 1.0]])
    T_left_base = np.eye(4)
    T_left_base[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]  # base x forward -> camera z
    T_left_base[:3, 3] = [0.0, 0.4, 1.5]
    T_left_right = np.eye(4)
    T_left_right[0, 3] = 0.12
    lower, upper = robot.lower.double().numpy(), robot.upper.double().numpy()
    mid, amp = (lower + upper) / 2, 0.3 * np.minimum(upper - lower, 2.0)
    t0, period = 1_700_000_000_000_000_000, int(1e9 / fps)
    img = rng.integers(0, 255, (height, width, 3), dtype=np.uint8)
    with RecordingWriter(path, chunk_size=chunk_size) as w:
        w.write_tf_static(
            [(left, f"robot_0/{robot.root_link}", T_left_base), (left, right, T_left_right)], t0
        )
        for side, frame in (("left", left), ("right", right)):
            w.write_camera_info(camera_info_topic("camera", side), t0, frame, K, width, height)
        for i in range(frames):
            stamp = t0 + i * period
            q = mid + amp * np.sin(0.05 * i + np.arange(robot.dof))
            w.write_joint_state(joint_states_topic("robot_0"), stamp, robot.joint_names, q)
            for side, frame in (("left", left), ("right", right)):
                w.write_image(image_topic("camera", side), stamp, frame, img)
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="*", type=Path)
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=720)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        paths = args.paths
        if not paths:
            t = time.perf_counter()
            paths = [
                write_synthetic_recording(
                    Path(tmp) / "synthetic.mcap", args.frames, args.width, args.height
                )
            ]
            log.info("wrote %d synthetic frames in %.1f s", args.frames, time.perf_counter() - t)
        for path in paths:
            results.append(read_throughput(path))
            results.append({**read_throughput(path, decode=False), "decode": False})
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
