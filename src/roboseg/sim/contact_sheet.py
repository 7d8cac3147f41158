"""Contact sheet of simulated recordings: ``python -m roboseg.sim.contact_sheet [OUT.png]``.

One row per recording (different seeds, one and two robots, the built-in arm and, when
``--urdf`` is given, that robot): the undraped frame, a draped frame replaying the same joints,
the same draped frame with the ground-truth silhouette outlined in green, and the right view.
Default output: ``docs/contact_sheet.png`` of the source tree.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
from pathlib import Path

import cv2
import numpy as np

from roboseg.recording.reader import RecordingReader
from roboseg.sim.simulate import SimConfig, simulate_recording

DEFAULT_OUT = Path(__file__).resolve().parents[3] / "docs" / "contact_sheet.png"
MASKS = ["left/robot_mask_gt"]


def outline(
    image: np.ndarray, mask: np.ndarray, colour: tuple[int, int, int] = (0, 255, 0)
) -> np.ndarray:
    """``image`` (RGB uint8) with the contour of ``mask`` drawn 1 px wide in ``colour``."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    out = image.copy()
    cv2.drawContours(out, contours, -1, colour, 1)
    return out


def sheet_row(path: Path) -> np.ndarray:
    """The four panels of one recording, side by side (RGB uint8)."""
    with RecordingReader(path, mask_topics=MASKS) as reader:
        frames = list(reader.frames())
        n_undraped = int(reader.metadata()["roboseg_sim"]["undraped_frames"])
    undraped, draped = frames[0], frames[n_undraped]  # the draped phase replays the motion
    mask = draped.masks["left/robot_mask_gt"]
    panels = [undraped.left, draped.left, outline(draped.left, mask), draped.right]
    return np.concatenate(panels, axis=1)


def make_contact_sheet(
    out: Path, seeds: list[int], urdf: str | None, width: int, height: int, frames: int = 6
) -> Path:
    """Simulate one short recording per seed (every third with two robots; ``urdf`` for every
    other row if given) and write the sheet to ``out`` (PNG)."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k, seed in enumerate(seeds):
            cfg = SimConfig(
                frames=frames,
                seed=seed,
                width=width,
                height=height,
                robots=2 if k % 3 == 2 else 1,
                urdf=urdf if (urdf and k % 2 == 1) else None,
            )
            path = Path(tmp) / f"sheet_{seed}.mcap"
            simulate_recording(cfg, path)
            rows.append(sheet_row(path))
    sheet = np.concatenate(rows, axis=0)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out", nargs="?", type=Path, default=DEFAULT_OUT)
    p.add_argument("--seeds", default="1,2,3,4,5,6", help="comma-separated seeds, one per row")
    p.add_argument("--urdf", default=None, help="robot for every other row (default: built-in)")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=180)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    seeds = [int(s) for s in args.seeds.split(",")]
    print(make_contact_sheet(args.out, seeds, args.urdf, args.width, args.height))


if __name__ == "__main__":
    main()
