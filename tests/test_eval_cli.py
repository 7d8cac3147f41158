"""``roboseg-eval`` on a tiny annotated dataset: a simulated two-robot draped recording run
through ``roboseg.annotate`` (``robot_mask`` topics + manifest, the shared contract)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest
from hydra import compose, initialize_config_dir
from tiny_models import SIZE, train_checkpoint

from export.checkpoint import load_for_export
from export.onnx import export_onnx
from roboseg.annotate import AnnotateOptions, annotate_folder
from roboseg.cli.evaluate import run
from roboseg.config import CONF_DIR
from roboseg.errors import DatasetError, ModelFileError
from roboseg.evaluation.metrics import binary_iou
from roboseg.evaluation.run import (
    PriorRenderer,
    aspect_differs,
    figure_indices,
    iter_frames,
    load_manifest,
    split_recordings,
)
from roboseg.robot import load_robot
from roboseg.sim import SimConfig, simulate_recording

FRAMES = 5


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``roboseg.annotate`` output of one simulated two-robot draped test recording."""
    base = tmp_path_factory.mktemp("eval")
    raw, root = base / "raw", base / "annotated"
    raw.mkdir()
    simulate_recording(
        SimConfig(frames=FRAMES, seed=3, robots=2, width=160, height=96), raw / "test_00.mcap"
    )
    manifest = annotate_folder(raw, root, load_robot(None), AnnotateOptions(min_joint_speed=0.0))
    assert manifest["recordings"][0]["frames_kept"] == FRAMES
    # a train recording that is not there: only the test split may be read
    manifest["recordings"].append({**manifest["recordings"][0], "file": "train_00.mcap",
                                   "split": "train"})
    (root / "manifest.json").write_text(json.dumps(manifest))
    return root


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A 4-channel checkpoint, its ONNX export, and a 3-channel ONNX model without metadata."""
    base = tmp_path_factory.mktemp("models")
    ckpt4 = train_checkpoint(base / "four.ckpt", 4)
    module, meta = load_for_export(ckpt4)
    onnx4 = export_onnx(module.net, meta, base / "four.onnx")
    module3, meta3 = load_for_export(train_checkpoint(base / "three.ckpt", 3))
    foreign = export_onnx(module3.net, meta3, base / "foreign.onnx")
    proto = onnx.load(str(foreign))
    del proto.metadata_props[:]
    onnx.save(proto, str(foreign))
    return {"ckpt4": ckpt4, "onnx4": onnx4, "foreign": foreign}


def eval_cfg(**overrides: object):
    args = [f"{k}={v}" for k, v in overrides.items()]
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name="eval", overrides=args)


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_figure_indices_and_aspect() -> None:
    assert figure_indices(None, 10) == {0, 4, 9}
    assert figure_indices(2, 5) == {0, 4}
    assert figure_indices(1, 5) == {0}
    assert figure_indices([1, 7, 99], 8) == {1, 7}
    assert figure_indices(3, 0) == set()
    assert not aspect_differs((270, 480), (540, 960))
    assert aspect_differs((256, 256), (540, 960))


def test_manifest_and_split(dataset: Path, tmp_path: Path) -> None:
    files = split_recordings(load_manifest(dataset), dataset, "test")
    assert [f.name for f in files] == ["test_00.mcap"]
    with pytest.raises(DatasetError, match="train_00.mcap"):
        split_recordings(load_manifest(dataset), dataset, "train")
    with pytest.raises(DatasetError, match="val"):
        split_recordings(load_manifest(dataset), dataset, "val")
    with pytest.raises(DatasetError, match="manifest.json"):
        load_manifest(tmp_path)


def test_perturbed_prior_near_the_robots(dataset: Path) -> None:
    files = split_recordings(load_manifest(dataset), dataset, "test")
    frames = list(iter_frames(files, prior=PriorRenderer(seed=0)))
    assert len(frames) == FRAMES
    for f in frames:
        assert f.image.shape == (96, 160, 3) and f.target.shape == (96, 160)
        assert f.prior is not None and f.prior.shape == (96, 160)
        # a pose a few cm / 5° off: overlapping, not identical to the true silhouette
        assert 0.2 < binary_iou(f.prior > 0.5, f.target) < 0.999
    again = list(iter_frames(files, prior=PriorRenderer(seed=0), max_frames=2))
    assert len(again) == 2
    np.testing.assert_array_equal(again[1].prior, frames[1].prior)  # seeded


def test_eval_command(dataset: Path, models: dict[str, Path], tmp_path: Path,
                      capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "eval"
    cfg = eval_cfg(models=f"[{models['onnx4']},{models['ckpt4']}]", **{"data.root": dataset},
                   out=out, figure_frames=2, progress="false")
    rows = run(cfg)
    printed = capsys.readouterr().out
    assert "| Architecture | Encoder |" in printed and "zero prior" in printed
    # a 4-channel model: one row with a zero prior, one with the perturbed-pose prior
    assert [(r.model, r.prior) for r in rows] == [
        ("four.onnx", "zero"), ("four.onnx", "perturbed"),
        ("four.ckpt", "zero"), ("four.ckpt", "perturbed")]
    table = read_csv(out / "iou_table.csv")
    assert list(table[0]) == ["model", "architecture", "encoder", "params_m", "iou_mean",
                              "iou_std", "cmm", "in_channels", "prior", "dataset", "frames"]
    assert [t["frames"] for t in table] == [str(FRAMES)] * 4
    assert (out / "iou_table.md").read_text().startswith("| Architecture |")
    per_frame = read_csv(out / "per_frame_iou.csv")
    assert list(per_frame[0]) == ["model", "prior", "file", "stamp", "iou"]
    assert len(per_frame) == 4 * FRAMES
    # the checkpoint goes through the ONNX path's preprocessing: the same IoU per frame
    by = {(r["model"], r["prior"], r["stamp"]): float(r["iou"]) for r in per_frame}
    for (model, prior, stamp), iou in by.items():
        if model == "four.onnx":
            assert by[("four.ckpt", prior, stamp)] == pytest.approx(iou, abs=0.01)
        assert 0.0 <= iou <= 1.0
    # errors by distance to the true outline: a row per table row, fractions of the true area
    bands = (out / "error_bands.md").read_text().splitlines()
    assert bands[0].startswith("| model | missed ≤1.5 px |") and len(bands) == 2 + 4
    assert bands[2].startswith("| four.onnx (zero prior) |")
    for line in bands[2:]:
        fractions = [float(v) for v in line.strip("| ").split(" | ")[1:]]
        assert len(fractions) == 8 and min(fractions) >= 0.0
    for name in ("four_zero", "four_perturbed"):
        png = cv2.imread(str(out / f"qualitative_{name}.png"))
        assert png is not None and png.shape[0] > 100 and png.shape[1] > 4 * 100


def test_eval_options_and_errors(dataset: Path, models: dict[str, Path], tmp_path: Path,
                                 capsys: pytest.CaptureFixture,
                                 caplog: pytest.LogCaptureFixture) -> None:
    foreign = models["foreign"]
    with pytest.raises(SystemExit) as exc:
        run(eval_cfg(models=f"[{foreign}]", **{"data.root": dataset}, out=tmp_path / "x"))
    assert exc.value.code == 1
    err = capsys.readouterr().err.strip()
    assert "foreign.onnx" in err and "overrides" in err and "\n" not in err
    meta = {"encoder": "unet_resnet18", "in_channels": 3, "input_height": SIZE,
            "input_width": SIZE, "mean": [0.485, 0.456, 0.406], "std": [0.229, 0.224, 0.225],
            "threshold": 0.5, "trained_on": ""}
    override = "{" + ",".join(f"{k}:{json.dumps(v)}" for k, v in meta.items()) + "}"
    out = tmp_path / "eval"
    rows = run(eval_cfg(models=f"[{foreign}]", **{"data.root": dataset}, out=out, max_frames=3,
                        labels="gt", overrides=override, progress="false",
                        train_size="[96,96]"))
    assert [(r.prior, len(r.ious)) for r in rows] == [("-", 3)]
    # 160x96 test images squashed to 64x64, trained from 96x96 sources: warned once
    warnings = [r for r in caplog.records if "training images were 96x96" in r.getMessage()]
    assert len(warnings) == 1
    assert len(read_csv(out / "per_frame_iou.csv")) == 3
    with pytest.raises(ModelFileError, match="nothing.onnx"):
        from roboseg.evaluation.run import load_model

        load_model(tmp_path / "nothing.onnx")


def test_phase_keeps_draped_or_undraped_frames(dataset: Path, models: dict[str, Path],
                                               tmp_path: Path) -> None:
    start = load_manifest(dataset)["recordings"][0]["draped_from_ns"]
    assert start is not None
    stamps = {}
    for phase in ("draped", "undraped"):
        out = tmp_path / phase
        run(eval_cfg(models=f"[{models['onnx4']}]", **{"data.root": dataset}, out=out,
                     phase=phase, progress="false", figure_frames=1))
        per_frame = read_csv(out / "per_frame_iou.csv")
        stamps[phase] = {int(r["stamp"]) for r in per_frame}
        assert read_csv(out / "iou_table.csv")[0]["frames"] == str(len(stamps[phase]))
    assert stamps["draped"] and stamps["undraped"]
    assert min(stamps["draped"]) >= start > max(stamps["undraped"])
    assert len(stamps["draped"]) + len(stamps["undraped"]) == FRAMES
    with pytest.raises(SystemExit):
        run(eval_cfg(models=f"[{models['onnx4']}]", **{"data.root": dataset},
                     out=tmp_path / "bad", phase="wet", progress="false"))


def test_scales_average_the_models_probabilities(dataset: Path, models: dict[str, Path],
                                                 tmp_path: Path,
                                                 capsys: pytest.CaptureFixture) -> None:
    from roboseg.segmentor import OnnxSegmentor

    scales = [1.0, 2.0]
    ious = {}
    for name, s in (("one", "[1.0]"), ("two", "[1.0,2.0]")):
        out = tmp_path / name
        run(eval_cfg(models=f"[{models['onnx4']},{models['ckpt4']}]",
                     **{"data.root": dataset}, out=out, scales=s, progress="false",
                     figure_frames=1))
        ious[name] = {(r["model"], r["prior"], r["stamp"]): float(r["iou"])
                      for r in read_csv(out / "per_frame_iou.csv")}
    assert "[1.0, 2.0] x the model's input size" in capsys.readouterr().out
    # what the registration runtime's multi-scale segmentor draws, scored against the labels
    seg = OnnxSegmentor(models["onnx4"], scales=scales)
    files = split_recordings(load_manifest(dataset), dataset, "test")
    for frame in iter_frames(files):
        pred = seg.predict(frame.image)[0] > seg.meta.threshold
        key = ("four.onnx", "zero", str(frame.stamp_ns))
        assert ious["two"][key] == pytest.approx(binary_iou(pred, frame.target), abs=1e-6)
        # the checkpoint is run at the same sizes
        assert ious["two"][("four.ckpt", "zero", key[2])] == pytest.approx(
            ious["two"][key], abs=0.01)
    assert any(abs(ious["two"][k] - ious["one"][k]) > 1e-4 for k in ious["one"])
    for bad in ("[0]", "[x]"):
        with pytest.raises(SystemExit):
            run(eval_cfg(models=f"[{models['onnx4']}]", **{"data.root": dataset},
                         out=tmp_path / "bad", scales=bad, progress="false"))
        assert "scales" in capsys.readouterr().err
