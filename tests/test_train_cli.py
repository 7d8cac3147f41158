"""``roboseg-train``: the smoke experiment end to end, resumption, and one-line user errors."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

import roboseg.training
from roboseg.cli.train import _fall_back_from_slow_bf16, run
from roboseg.config import CONF_DIR

sys.path.insert(0, str(Path(__file__).parent))
from test_datamodule import make_annotated_dataset  # noqa: E402

TRAIN = [sys.executable, "-m", "roboseg.cli.train"]


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "OMP_NUM_THREADS": "2", "PYTHONHASHSEED": "0"}
    return subprocess.run(TRAIN + args, cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=300)


@pytest.fixture(scope="module")
def smoke(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, str]:
    root = tmp_path_factory.mktemp("train_cli")
    data = make_annotated_dataset(root / "data", {"train": 2, "val": 1}, frames=10, seed=5)
    run = root / "run"
    proc = _run(["experiment=smoke", f"data.root={data}", f"hydra.run.dir={run}"], root)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return data, run, proc.stdout


def test_smoke_writes_checkpoints_and_prints_val_iou(smoke: tuple[Path, Path, str]) -> None:
    _, run, stdout = smoke
    lines = re.findall(r"^val/iou=(\d\.\d{3})$", stdout, flags=re.M)
    assert len(lines) == 1 and 0.0 <= float(lines[0]) <= 1.0
    assert stdout.strip().splitlines()[-2:] == ["steps=12/12", f"val/iou={lines[0]}"]
    last = torch.load(run / "checkpoints" / "last.ckpt", weights_only=True, map_location="cpu")
    assert last["global_step"] == 12
    assert (run / "checkpoints" / "best.ckpt").is_file()
    assert last["hyper_parameters"]["image_size"] == [64, 64]


def test_resume_continues_from_last_checkpoint(smoke: tuple[Path, Path, str],
                                               tmp_path: Path) -> None:
    data, run, _ = smoke
    run2 = tmp_path / "run2"
    proc = _run(["experiment=smoke", f"data.root={data}", f"hydra.run.dir={run2}",
                 f"+ckpt_path={run / 'checkpoints' / 'last.ckpt'}", "trainer.max_steps=14",
                 "trainer.val_check_interval=2"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "resuming the training stream after 12 batches" in proc.stderr + proc.stdout
    last = torch.load(run2 / "checkpoints" / "last.ckpt", weights_only=True, map_location="cpu")
    assert last["global_step"] == 14


def test_a_time_limit_before_max_steps_is_reported(smoke: tuple[Path, Path, str],
                                                   tmp_path: Path) -> None:
    data, _, _ = smoke
    proc = _run(["experiment=smoke", f"data.root={data}", f"hydra.run.dir={tmp_path / 'run'}",
                 "trainer.max_steps=100000", "trainer.max_time=00:00:00:02"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    steps = re.findall(r"^steps=(\d+)/100000$", proc.stdout, flags=re.M)
    assert len(steps) == 1 and 0 < int(steps[0]) < 100000
    assert "raise trainer.max_time" in proc.stdout + proc.stderr
    assert proc.stdout.strip().splitlines()[-1].startswith("val/iou=")


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["data.root=/nonexistent/annotated"], "/nonexistent/annotated"),
        (["+ckpt_path=/nonexistent/last.ckpt", "data.root=."], "/nonexistent/last.ckpt"),
        (["data.val_phase=wet", "data.root=."], "data.val_phase"),
    ],
)
def test_user_errors_are_one_line_exit_1(
    args: list[str], expected: str, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    overrides = ["experiment=smoke", f"paths.output_dir={tmp_path}", *args]
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("train", overrides=overrides)
    with pytest.raises(SystemExit) as exit_info:
        run(cfg)
    assert exit_info.value.code == 1
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 1 and errors[0].startswith("error:") and expected in errors[0]


def test_ddp_sim_sees_every_training_frame_once_per_epoch(
    smoke: tuple[Path, Path, str], tmp_path: Path
) -> None:
    """Two CPU processes (gloo): the ranks' epoch-0 samples partition the training frames.

    5 steps of batch 4 per rank consume 20 samples per rank, as many as there are training
    frames, so epoch 0 is complete on each rank whatever the shard split. One OpenMP thread per
    rank: two ranks with two threads each on two cores oversubscribe them (several times slower).
    """
    data, _, _ = smoke
    seen = tmp_path / "seen.txt"
    args = ["experiment=smoke", "trainer=ddp_sim", f"data.root={data}",
            f"hydra.run.dir={tmp_path / 'run'}", f"data.seen_log={seen}",
            "data.shuffle_buffer=1",  # epochs do not interleave: epoch 0 comes first
            "data.batch_size=4", "trainer.max_steps=5", "trainer.val_check_interval=5",
            "trainer.limit_val_batches=1"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONHASHSEED": "0"}
    proc = subprocess.run(TRAIN + args, cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert len(re.findall(r"^val/iou=", proc.stdout, flags=re.M)) == 1  # rank zero only
    rows = [tuple(map(int, line.split())) for line in seen.read_text().splitlines()]
    epoch0 = [(rank, index) for rank, _, epoch, index in rows if epoch == 0]
    indices = [index for _, index in epoch0]
    assert {rank for rank, _ in epoch0} == {0, 1}
    assert sorted(indices) == list(range(20))  # 2 recordings x 10 frames, each exactly once
    assert {i for r, i in epoch0 if r == 0}.isdisjoint({i for r, i in epoch0 if r == 1})


@pytest.mark.parametrize(("native", "fallback", "expected"), [
    (False, True, "32-true"), (False, False, "bf16-mixed"), (True, True, "bf16-mixed")])
def test_default_recipe_trains_in_float32_where_the_cpu_has_no_bf16(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, native: bool,
        fallback: bool, expected: str) -> None:
    """make train's recipe asks for bf16-mixed; on a CPU without native bfloat16 (15-20x slower
    there) it trains in float32 and says so, unless bf16_fallback=false."""
    monkeypatch.setattr(roboseg.training, "cpu_bf16_native", lambda: native)
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("train", overrides=["experiment=default", "data.root=x",
                                          f"bf16_fallback={str(fallback).lower()}"])
    assert cfg.trainer.precision == "bf16-mixed"
    with caplog.at_level("WARNING", logger="roboseg.train"):
        _fall_back_from_slow_bf16(cfg)
    assert cfg.trainer.precision == expected
    warned = "no native bfloat16" in caplog.text
    assert warned == (expected != "bf16-mixed")
    if warned:
        assert "trainer.precision=bf16-mixed" in caplog.text and "32-true" in caplog.text
