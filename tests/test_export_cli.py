"""``roboseg-export``: a checkpoint of a tiny training run → verified ONNX with roboseg metadata,
fp16 / int8 variants, one-line errors for files that are not roboseg checkpoints."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from hydra import compose, initialize_config_dir
from tiny_models import SIZE, train_checkpoint

from export.checkpoint import file_sha256, load_for_export, meta_from_block, trained_on_hash
from export.cli import run, variant_path, verify_sizes
from roboseg.config import CONF_DIR
from roboseg.errors import ModelFileError, RobosegError
from roboseg.segmentor import METADATA_KEYS, OnnxSegmentor, preprocess


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return train_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.ckpt", cmm=True)


def export_cfg(**overrides: object):
    args = [f"{k}={v}" for k, v in overrides.items()]
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name="export", overrides=args)


def test_verify_sizes_default_and_checked() -> None:
    assert verify_sizes(None, (64, 96)) == [(64, 96), (96, 160)]
    assert verify_sizes([[32, 64], [64, 64]], (64, 64)) == [(32, 64), (64, 64)]
    with pytest.raises(RobosegError, match="multiples of 32"):
        verify_sizes([[30, 64], [64, 64]], (64, 64))
    with pytest.raises(RobosegError, match="two sizes"):
        verify_sizes([[64, 64]], (64, 64))
    assert variant_path(Path("a/m.onnx"), "fp16") == Path("a/m.fp16.onnx")


def test_meta_from_checkpoint(ckpt: Path, tmp_path: Path) -> None:
    module, meta = load_for_export(ckpt)
    assert (meta.encoder, meta.in_channels, meta.input_height, meta.input_width) == (
        "unet_resnet18", 3, SIZE, SIZE)
    assert meta.cmm is True and meta.dataset == "synthetic"
    assert meta.params_m == pytest.approx(sum(p.numel() for p in module.net.parameters()) / 1e6,
                                          abs=0.05)
    assert meta.trained_on == file_sha256(ckpt)
    (tmp_path / "manifest.json").write_text('{"format": "roboseg-annotations/1"}')
    assert trained_on_hash(ckpt, tmp_path) == file_sha256(tmp_path / "manifest.json")
    with pytest.raises(ModelFileError, match="lacks input_height.*threshold"):
        meta_from_block({k: 1 for k in ("encoder", "in_channels")}, "", "x.ckpt")


def test_export_command(ckpt: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "m.onnx"
    status = run(export_cfg(ckpt=ckpt, out=out, fp16="true", int8="true"))
    printed = capsys.readouterr().out
    assert status == 0
    # verification at two sizes, batch 2, numbers printed
    assert "input (2, 3, 64, 64): max |Δlogit|" in printed
    assert "input (2, 3, 96, 128): max |Δlogit|" in printed
    proto = onnx.load(str(out))
    onnx.checker.check_model(proto)
    props = {p.key: p.value for p in proto.metadata_props}
    assert set(METADATA_KEYS) <= set(props)
    assert props["trained_on"] == file_sha256(ckpt)
    assert (props["cmm"], props["dataset"], json.loads(props["mean"])[0]) == (
        "1", "synthetic", pytest.approx(0.485))
    dims = proto.graph.input[0].type.tensor_type.shape.dim
    assert [d.dim_param for d in dims] == ["batch", "", "height", "width"]
    # the ONNX model reproduces the checkpoint on a preprocessed image of another size
    module, meta = load_for_export(ckpt)
    img = np.random.default_rng(0).integers(0, 256, (1, 70, 90, 3), dtype=np.uint8)
    x = preprocess(img, meta)
    with torch.no_grad():
        ref = module.net(torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(OnnxSegmentor(out).logits(x), ref, atol=1e-4)
    for kind in ("fp16", "int8"):
        variant = tmp_path / f"m.{kind}.onnx"
        assert variant.is_file()
        assert OnnxSegmentor(variant).meta.encoder == "unet_resnet18"
        assert f"wrote {variant}: max |Δlogit| = " in printed
    assert not list(tmp_path.glob("*.part"))


def test_export_with_flip_tta_averages_mirror_views_at_any_batch(
        ckpt: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "tta.onnx"
    assert run(export_cfg(ckpt=ckpt, out=out, tta="flip")) == 0
    seg = OnnxSegmentor(out)
    assert seg.meta.tta == "flip"
    module, meta = load_for_export(ckpt)
    for batch in (1, 3):  # the verification ran at batch 2
        img = np.random.default_rng(batch).integers(0, 256, (batch, 64, 96, 3), dtype=np.uint8)
        x = torch.from_numpy(preprocess(img, meta))
        with torch.no_grad():
            ref = 0.5 * (module.net(x) + module.net(x.flip(-1)).flip(-1))
        np.testing.assert_allclose(seg.logits(x.numpy()), ref.numpy(), atol=1e-4)
    with pytest.raises(SystemExit) as exc:
        run(export_cfg(ckpt=ckpt, out=tmp_path / "bad.onnx", tta="rotate"))
    assert exc.value.code == 1
    assert "tta must be one of flip or null, got 'rotate'" in capsys.readouterr().err
    assert not (tmp_path / "bad.onnx").exists()


def test_export_fails_above_tolerance(ckpt: Path, tmp_path: Path,
                                      capsys: pytest.CaptureFixture) -> None:
    status = run(export_cfg(ckpt=ckpt, out=tmp_path / "m.onnx",
                             **{"verify.tolerance": 0.0, "verify.sizes": "[[32,32],[32,64]]"}))
    assert status == 1
    assert "differs from PyTorch" in capsys.readouterr().err


def test_bad_checkpoints_one_line(ckpt: Path, tmp_path: Path,
                                  capsys: pytest.CaptureFixture) -> None:
    foreign = tmp_path / "foreign.ckpt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(SystemExit) as exc:
        run(export_cfg(ckpt=foreign, out=tmp_path / "f.onnx"))
    assert exc.value.code == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "foreign.ckpt" in err and "not a Lightning" in err

    # weights that do not fit the checkpoint's own model config
    bad = torch.load(ckpt, map_location="cpu", weights_only=True)
    bad["hyper_parameters"]["model"]["in_channels"] = 4
    mismatched = tmp_path / "mismatch.ckpt"
    torch.save(bad, mismatched)
    with pytest.raises(ModelFileError, match="mismatch.ckpt"):
        load_for_export(mismatched)
    garbage = tmp_path / "garbage.ckpt"
    garbage.write_bytes(b"not a checkpoint")
    with pytest.raises(ModelFileError, match="garbage.ckpt: cannot be read") as bad_file:
        load_for_export(garbage)
    assert "\n" not in str(bad_file.value)
    assert not (tmp_path / "f.onnx").exists()
