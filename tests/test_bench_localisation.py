"""The localisation bench's own machinery: mask degradation, its worker pool and the choice of
mask conditions and camera poses."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from bench.localisation import degrade_to_iou, main, run_tasks
from roboseg.evaluation.metrics import binary_iou
from roboseg.recording import RecordingReader


def _disc(radius: int) -> np.ndarray:
    mask = np.zeros((180, 320), np.uint8)
    cv2.circle(mask, (160, 90), radius, 1, -1)
    return mask > 0


def test_degraded_masks_reach_the_target_iou_and_report_it() -> None:
    rng = np.random.default_rng(0)
    mask = _disc(50)
    out, iou = degrade_to_iou(mask, 0.73, rng)
    assert iou == binary_iou(out, mask)
    assert abs(iou - 0.73) < 0.03
    assert not np.array_equal(out, mask)
    empty = np.zeros_like(mask)
    same, one = degrade_to_iou(empty, 0.73, rng)
    assert one == 1.0 and not same.any()


def test_degradation_is_seeded() -> None:
    mask = _disc(40)
    a, _ = degrade_to_iou(mask, 0.73, np.random.default_rng(3))
    b, _ = degrade_to_iou(mask, 0.73, np.random.default_rng(3))
    assert np.array_equal(a, b)


def test_worker_pool_returns_results_in_task_order() -> None:
    # IoU of the diagonal against the diagonal with its first k rows filled: 4 / (4 + 3k)
    eye = np.eye(4, dtype=bool)
    tasks = []
    for k in range(4):
        filled = eye.copy()
        filled[:k] = True
        tasks.append((binary_iou, (eye, filled)))
    expected = [1.0, 4 / 7, 4 / 10, 4 / 13]
    assert run_tasks(tasks, 1) == expected
    assert run_tasks(tasks, 2) == expected


def test_only_the_chosen_mask_conditions_run_on_the_sites_camera_poses(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import bench.localisation as bench

    simulated: list[Path] = []
    simulate = bench.simulate

    def keep(folder: Path, *args: object) -> Path:
        path = simulate(folder, *args)  # type: ignore[arg-type]
        with RecordingReader(path) as r:
            simulated.append(path)
            meta = r.metadata()["roboseg_sim"]
        assert meta["site"] == "1" and meta["seed"] == "7000", meta
        return path

    monkeypatch.setattr(bench, "simulate", keep)
    missing = tmp_path / "missing.onnx"
    argv = ["--quick", "--cases", "c", "--site", "1", "--seed", "7000", "--poses", "1",
            "--frames", "3", "--placements", "0", "--skip-timing", "--jobs", "1",
            "--model3", str(missing), "--out", str(tmp_path)]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert len(simulated) == 1
    assert f"(c) skipped for {missing}: no such file" in out
    assert "(a) gt masks" not in out and "(b) degraded" not in out
    assert "degraded masks: achieved" not in out
    assert (tmp_path / "localisation.png").is_file()


def test_site_none_means_random_rooms() -> None:
    from bench.localisation import build_parser

    parser = build_parser()
    assert parser.parse_args(["--site", "none"]).site is None
    assert parser.parse_args(["--site", "null"]).site is None
    assert parser.parse_args(["--site", "3"]).site == 3
    with pytest.raises(SystemExit):
        parser.parse_args(["--site", "room"])
