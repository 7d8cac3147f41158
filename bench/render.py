"""Render bench: hard vs differentiable silhouettes of a stereo batch of robot configurations.

Run as ``python -m bench.render`` (or ``python bench/render.py``). Times, per view, the hard
silhouette and one differentiable iteration (soft forward including the hard raster, an MSE
loss and the backward pass to the vertices) for 2 views × 9 configurations at 256² and 512²,
with the KUKA LBR Med 7 decimated by 95 % (the built-in robot when the Med 7 is absent).
Targets: a full differentiable iteration at 256² within 300 ms, and differentiable / hard
within 10×. A second table times the annotation-scale case, the hard silhouette and the z-buffer
of the full (undecimated) model at 540×960 per view (target <= 12 ms per silhouette, i.e. 30
stereo frames/s after FK and I/O) and the silhouette of the model reduced by ``--reduction``
(with its worst IoU against the full model's; annotation uses a reduced mesh only where that
IoU reaches 0.995), and a camera swarm of 2000 views at 64×64 of the decimated model (target
<= 1 s). Wall-clock numbers depend on machine load; the median of several repeats
is shown.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path

import torch

if __package__ in (None, ""):  # run as a script: make ``bench`` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import format_table, time_calls, verdict  # noqa: E402
from roboseg.camera import look_at  # noqa: E402
from roboseg.render import rasterize, render_hard  # noqa: E402
from roboseg.render.soft import SilhouetteRenderer  # noqa: E402
from roboseg.robot import load_robot  # noqa: E402

MED7 = Path(__file__).resolve().parents[2] / "shared" / "robots" / "lbr_med7" / "lbr_med7.urdf"
ITERATION_TARGET_MS = 300.0
FULL_VIEW_TARGET_MS = 12.0
SWARM_TARGET_S = 1.0
RATIO_TARGET = 10.0
BASELINE_M = 0.12
log = logging.getLogger("bench.render")


def stereo_views(
    urdf: Path | None,
    n_configs: int,
    size: int,
    seed: int = 0,
    reduction: float = 0.95,
    height: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, str]:
    """Vertices ``[2·n, V, 3]`` in the left then right optical frames, faces, ``K``, robot name,
    for images ``height`` (default ``size``) × ``size`` pixels."""
    height = height or size
    robot = load_robot(urdf)
    if reduction > 0:
        robot = robot.decimated(reduction)
    q = robot.random_joints(n_configs, torch.Generator().manual_seed(seed))
    verts_base = robot.posed_vertices(q)
    T_left_base = look_at(torch.tensor([1.3, 0.9, 0.9]), torch.tensor([0.0, 0.0, 0.55]))
    T_right_left = torch.eye(4)
    T_right_left[0, 3] = -BASELINE_M
    views = []
    for T in (T_left_base, T_right_left @ T_left_base):
        views.append(verts_base @ T[:3, :3].T + T[:3, 3])
    f = size / (2 * math.tan(math.radians(27.5)))  # 55° field of view
    K = torch.tensor([[f, 0.0, (size - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return torch.cat(views), robot.faces, K, f"{robot.name} ({len(robot.faces)} faces)"


def bench_size(
    verts: torch.Tensor, faces: torch.Tensor, K: torch.Tensor, size: int, repeats: int
) -> dict[str, float]:
    """Milliseconds for the whole batch: hard render and differentiable forward+backward."""
    renderer = SilhouetteRenderer(faces, size, size, backend="torch")
    target = renderer.hard(verts, K).float()

    def differentiable() -> None:
        v = verts.detach().requires_grad_(True)
        loss = ((renderer.soft(v, K) - target) ** 2).mean()
        loss.backward()

    t = time_calls({"hard": lambda: renderer.hard(verts, K), "soft": differentiable}, repeats)
    return {name: 1e3 * t[name]["median"] for name in t}


def bench_annotation_scale(
    urdf: Path | None, repeats: int, swarm: int, reduction: float = 0.0
) -> tuple[list[list[object]], list[str]]:
    """Rows (case, ms per view, total) and verdict lines: full model at 540×960 (hard
    silhouette, z-buffer), the model reduced by ``reduction`` (0: skipped) at 540×960 (hard
    silhouette, with its IoU against the full model's), decimated model in ``swarm`` views at
    64×64 (hard silhouette)."""
    verts, faces, K, name = stereo_views(urdf, 1, 960, reduction=0.0, height=540)
    calls = {
        "hard": lambda: render_hard(verts, faces, K, 540, 960),
        "zbuf": lambda: rasterize(verts, faces, K, 540, 960),
    }
    if reduction > 0:  # same configurations and cameras (same seed)
        rv, rf, _, rname = stereo_views(urdf, 1, 960, reduction=reduction, height=540)
        calls["reduced"] = lambda: render_hard(rv, rf, K, 540, 960)
    t = time_calls(calls, repeats)
    hard_ms, zbuf_ms = 1e3 * t["hard"]["median"] / 2, 1e3 * t["zbuf"]["median"] / 2
    rows: list[list[object]] = [
        [f"{name} 540x960 silhouette", hard_ms, 2 * hard_ms],
        [f"{name} 540x960 z-buffer", zbuf_ms, 2 * zbuf_ms],
    ]
    if reduction > 0:
        full, reduced = render_hard(verts, faces, K, 540, 960), render_hard(rv, rf, K, 540, 960)
        iou = min(
            float((a & b).sum() / (a | b).sum()) for a, b in zip(full, reduced, strict=True)
        )
        ms = 1e3 * t["reduced"]["median"] / 2
        rows.append([f"{rname} 540x960 silhouette, IoU {iou:.4f} vs full", ms, 2 * ms])
    sv, sf, sk, sname = stereo_views(urdf, swarm // 2, 64)
    ts = time_calls({"swarm": lambda: render_hard(sv, sf, sk, 64, 64)}, max(1, repeats // 2))
    swarm_s = ts["swarm"]["median"]
    rows.append([f"{sname} {len(sv)} views 64x64", 1e3 * swarm_s / len(sv), 1e3 * swarm_s])
    lines = [
        verdict("full-model silhouette 540x960", hard_ms, FULL_VIEW_TARGET_MS, "ms/view"),
        verdict(f"swarm {len(sv)} views 64x64", swarm_s, SWARM_TARGET_S, "s"),
    ]
    return rows, lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", type=int, default=9, help="robot configurations")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    parser.add_argument("--swarm", type=int, default=2000, help="views of the swarm case (0: skip)")
    parser.add_argument(
        "--reduction",
        type=float,
        default=0.6,
        help="annotation-scale case: also time the model with this share of faces removed "
        "(0: skip)",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    if args.threads:
        torch.set_num_threads(args.threads)
    urdf = MED7 if MED7.exists() else None
    if urdf is None:
        print(f"note: {MED7} absent, using the built-in default robot")
    n_views = 2 * args.configs
    rows, results = [], {}
    for size in args.sizes:
        verts, faces, K, name = stereo_views(urdf, args.configs, size)
        r = bench_size(verts, faces, K, size, args.repeats)
        results[size] = r
        rows.append(
            [
                f"{size}x{size}",
                r["hard"] / n_views,
                r["soft"] / n_views,
                f"{r['soft'] / r['hard']:.1f}x",
                r["soft"],
            ]
        )
    print(
        f"{name}, {n_views} views (stereo x {args.configs} configurations), "
        f"{torch.get_num_threads()} torch threads, median of {args.repeats}"
    )
    headers = ["size", "hard ms/view", "diff f+b ms/view", "diff/hard", "diff ms/iteration"]
    print(format_table(headers, rows))
    ok = True
    if 256 in results:
        line = verdict("differentiable iteration 256²", results[256]["soft"], 300.0, "ms")
        ok &= line.startswith("PASS")
        print(line)
    for size, r in results.items():
        line = verdict(f"differentiable/hard {size}²", r["soft"] / r["hard"], RATIO_TARGET, "x")
        ok &= line.startswith("PASS")
        print(line)
    if args.swarm:
        rows, lines = bench_annotation_scale(urdf, args.repeats, args.swarm, args.reduction)
        print(format_table(["case", "ms/view", "ms total"], rows))
        for line in lines:
            ok &= line.startswith("PASS")
            print(line)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
