"""Small helpers shared by the benchmarks: wall-clock timing and a plain-text table."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence


def time_calls(
    fns: dict[str, Callable[[], object]], repeats: int = 5, warmup: int = 1
) -> dict[str, dict[str, float]]:
    """Wall-clock seconds of each ``fn()``: ``median`` and ``min`` over ``repeats``.

    The functions run interleaved (one of each per round) so that a changing machine load
    affects them alike, after ``warmup`` untimed rounds.
    """
    times: dict[str, list[float]] = {name: [] for name in fns}
    for round_ in range(warmup + repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            fn()
            if round_ >= warmup:
                times[name].append(time.perf_counter() - start)
    return {n: {"median": statistics.median(t), "min": min(t)} for n, t in times.items()}


def format_table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """Right-aligned columns; floats with one decimal."""
    cells = [[f"{c:.1f}" if isinstance(c, float) else str(c) for c in row] for row in rows]
    widths = [max([len(h), *(len(r[i]) for r in cells)]) for i, h in enumerate(headers)]
    lines = ["  ".join(h.rjust(w) for h, w in zip(headers, widths, strict=True))]
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)) for r in cells]
    return "\n".join(lines)


def verdict(name: str, value: float, limit: float, unit: str) -> str:
    """``PASS``/``FAIL`` line for ``value <= limit``."""
    status = "PASS" if value <= limit else "FAIL"
    return f"{status}  {name}: {value:.1f} {unit} (target <= {limit:g} {unit})"
