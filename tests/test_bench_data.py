"""bench/data.py: the memory check reads each process's own peak RSS, and the summary lines."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.data import peak_rss, summary  # noqa: E402

#: Touches ``mb`` MiB (every page), frees them.
_TOUCH = "import numpy as np\nnp.ones({mb} << 18, dtype=np.float32).sum()\n"


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="needs Linux /proc")
def test_peak_rss_is_each_process_own_peak() -> None:
    base = peak_rss("import numpy as np\n")
    assert 5 < base["self_mb"] < 200 and base["children_mb"] == []
    # the process's own peak stays even though the memory was freed
    big = peak_rss(_TOUCH.format(mb=160))
    assert big["self_mb"] - base["self_mb"] > 150
    # two children started after that: each is measured on its own (not the parent's peak,
    # not the larger child's for both, as a running maximum over children would give)
    code = (
        _TOUCH.format(mb=160)
        + "import multiprocessing as mp, time\n"
        + "def child(mb):\n"
        + "    np.ones(mb << 18, dtype=np.float32).sum()\n"
        + "    time.sleep(0.3)\n"
        + "ctx = mp.get_context('fork')\n"
        + "for mb in (40, 100):\n"
        + "    p = ctx.Process(target=child, args=(mb,))\n"
        + "    p.start()\n"
        + "    p.join()\n"
    )
    got = peak_rss(code)
    assert got["self_mb"] - base["self_mb"] > 150
    small, large = got["children_mb"]
    assert small > 40 and large > 100  # each holds its own allocation at its peak
    assert 50 < large - small < 70  # 100 - 40 MiB: neither is the other's peak
    assert large < got["self_mb"] - 30  # nor the parent's (160 MiB)


def test_summary_puts_rates_beside_targets() -> None:
    results = {
        "simulator": {
            "width": 960,
            "height": 540,
            "runs": [{"workers": 1, "steady_stereo_frames_per_second": 4.0, "seconds_setup": 1.0}],
        },
        "annotation": {
            "width": 960,
            "height": 540,
            "robots": {
                "arm": {
                    "faces": 10,
                    "runs": [
                        {
                            "workers": 1,
                            "mesh": {"reduction": 0.5, "used": 0.0, "min_iou": 0.99},
                            "steady_stereo_frames_per_second": 31.0,
                            "meets_target": True,
                            "seconds_setup": 0.2,
                        }
                    ],
                }
            },
        },
        "memory": {
            "frames": [60, 240],
            "extra_data_mb": 30.0,
            "peak_rss_mb": {
                "read": {"process_mb": {"short": 80.0, "long": 81.0, "growth": 1.0}},
            },
        },
    }
    lines = summary(results)
    assert lines[0].startswith("FAIL  simulator") and "target >= 5" in lines[0]
    assert lines[1].startswith("PASS  annotation") and "refused" in lines[1]
    assert "+1.0 MB" in lines[2] and "30 MB" in lines[2]
