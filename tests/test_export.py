"""ONNX export, its verification and the light runtime segmentor."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import onnx
import pytest
import torch
from torch import nn

from export.onnx import convert_fp16, export_onnx, quantize_int8, verify_onnx
from roboseg.errors import ModelFileError
from roboseg.segmentor import OnnxSegmentor, SegmentorMeta, preprocess


class TinyNet(nn.Module):
    """A fully convolutional stand-in: the prior channel (if any) adds to the logit directly."""

    def __init__(self, in_channels: int) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.conv = nn.Conv2d(in_channels, 1, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(x)


def meta_for(in_channels: int) -> SegmentorMeta:
    return SegmentorMeta(
        encoder="tiny",
        in_channels=in_channels,
        input_height=64,
        input_width=64,
        mean=(0.5, 0.5, 0.5),
        std=(0.25, 0.25, 0.25),
        threshold=0.5,
        trained_on="sha256:abc",
        roboseg_version="0.1.0",
        params_m=0.001,
        cmm=True,
        dataset="medium",
    )


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = {}
    for c in (3, 4):
        model = TinyNet(c)
        path = export_onnx(model, meta_for(c), tmp_path_factory.mktemp(f"m{c}") / "model.onnx")
        out[c] = (model, path)
    return out


def test_export_metadata_and_dynamic_axes(exported):
    model, path = exported[4]
    proto = onnx.load(str(path))
    props = {p.key: p.value for p in proto.metadata_props}
    assert props["in_channels"] == "4" and props["input_height"] == "64"
    assert props["encoder"] == "tiny" and props["trained_on"] == "sha256:abc"
    dims = proto.graph.input[0].type.tensor_type.shape.dim
    assert [d.dim_param for d in dims] == ["batch", "", "height", "width"]
    assert dims[1].dim_value == 4
    v = verify_onnx(path, model, [(2, 4, 64, 64), (2, 4, 32, 96)])
    assert v.ok and max(v.max_abs_diff) < 1e-5


def test_verification_catches_a_different_model(exported):
    _, path = exported[3]
    other = TinyNet(3)
    with torch.no_grad():
        other.conv.bias += 1.0
    assert not verify_onnx(path, other, [(2, 3, 32, 32)]).ok


def test_meta_roundtrip():
    m = meta_for(4)
    assert SegmentorMeta.from_props(m.to_props()) == m


def test_segmentor_matches_torch_at_original_size(exported):
    model, path = exported[3]
    seg = OnnxSegmentor(path)
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (3, 90, 160, 3), dtype=np.uint8)
    probs = seg.predict(images, batch_size=2)
    assert probs.shape == (3, 90, 160) and probs.dtype == np.float32
    assert np.all((probs >= 0) & (probs <= 1))
    x = torch.from_numpy(preprocess(images, seg.meta))
    with torch.no_grad():
        ref = torch.sigmoid(model(x))[:, 0].numpy()
    import cv2

    ref_full = np.stack([cv2.resize(r, (160, 90), interpolation=cv2.INTER_LINEAR) for r in ref])
    assert np.abs(probs - ref_full).max() < 1e-4
    assert seg.predict_mask(images).dtype == bool


def test_preprocess_normalises_and_adds_prior():
    meta = meta_for(4)
    img = np.full((1, 32, 32, 3), 255, np.uint8)
    x = preprocess(img, meta)
    assert x.shape == (1, 4, 64, 64)
    np.testing.assert_allclose(x[0, :3], (1.0 - 0.5) / 0.25)
    assert np.all(x[0, 3] == 0)  # no prior → zero channel
    prior = np.zeros((1, 32, 32), np.float32)
    prior[:, :, :16] = 1  # left half of the columns
    x = preprocess(img, meta, prior)
    assert x[0, 3, :, :32].min() == 1 and x[0, 3, :, 32:].max() == 0


def test_four_channel_segmentor_uses_prior(exported):
    _, path = exported[4]
    seg = OnnxSegmentor(path)
    img = np.full((1, 64, 64, 3), 128, np.uint8)
    p0 = seg.predict(img)
    p1 = seg.predict(img, prior=np.ones((1, 64, 64), np.float32))
    assert not np.allclose(p0, p1)


def test_onnx_without_metadata_needs_overrides(tmp_path):
    path = tmp_path / "plain.onnx"
    torch.onnx.export(
        TinyNet(3),
        (torch.zeros(2, 3, 32, 32),),
        str(path),
        dynamo=False,
        opset_version=17,
        input_names=["input"],
        output_names=["logits"],
    )
    with pytest.raises(ModelFileError, match="not a roboseg ONNX model"):
        OnnxSegmentor(path)
    seg = OnnxSegmentor(
        path, overrides={**meta_for(3).to_props(), "input_height": "32", "input_width": "32"}
    )
    assert seg.predict(np.zeros((2, 32, 32, 3), np.uint8)).shape == (2, 32, 32)


def test_multi_scale_averages_the_sizes(exported):
    _, path = exported[4]
    seg = OnnxSegmentor(path, scales=(1.0, 1.5, 1.25))
    assert seg.sizes() == [(64, 64), (96, 96), (80, 80)]
    rng = np.random.default_rng(2)
    images = rng.integers(0, 256, (2, 90, 160, 3), dtype=np.uint8)
    prior = (rng.random((2, 90, 160)) > 0.5).astype(np.float32)
    each = [OnnxSegmentor(path, scales=(s,)).predict(images, prior) for s in seg.scales]
    # the sizes really differ in what they predict, and the mean is what comes out
    assert np.abs(each[0] - each[1]).max() > 1e-3
    np.testing.assert_allclose(seg.predict(images, prior), np.mean(each, 0), atol=1e-6)


def test_scales_must_be_positive_and_need_a_dynamic_graph(exported, tmp_path):
    _, path = exported[3]
    for bad in ((), (0.0,), (1.0, -1.0), (float("nan"),)):
        with pytest.raises(ModelFileError, match="scales must be"):
            OnnxSegmentor(path, scales=bad)
    fixed = tmp_path / "fixed.onnx"
    torch.onnx.export(
        TinyNet(3), (torch.zeros(1, 3, 64, 64),), str(fixed), dynamo=False, opset_version=17,
        input_names=["input"], output_names=["logits"],
    )
    props = meta_for(3).to_props()
    assert OnnxSegmentor(fixed, overrides=props).sizes() == [(64, 64)]
    with pytest.raises(ModelFileError, match="fixed"):
        OnnxSegmentor(fixed, overrides=props, scales=(1.0, 1.5))


def test_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(ModelFileError, match="no such ONNX file"):
        OnnxSegmentor(tmp_path / "nope.onnx")


def test_fp16_and_int8_variants_keep_metadata(exported, tmp_path):
    _, path = exported[3]
    img = np.random.default_rng(1).integers(0, 256, (2, 64, 64, 3), dtype=np.uint8)
    ref = OnnxSegmentor(path).predict(img)
    for fn, name in ((convert_fp16, "fp16.onnx"), (quantize_int8, "int8.onnx")):
        seg = OnnxSegmentor(fn(path, tmp_path / name))
        assert seg.meta == OnnxSegmentor(path).meta
        assert np.abs(seg.predict(img) - ref).max() < 0.05


def test_segmentor_import_is_light():
    code = (
        "import sys, roboseg.segmentor\n"
        "heavy = [m for m in ('torch', 'lightning', 'segmentation_models_pytorch', 'kornia', "
        "'hydra') if m in sys.modules]\n"
        "print(','.join(heavy))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_verification_bound_scales_with_the_logits():
    from export.onnx import Verification

    shapes = [(2, 3, 32, 32), (2, 3, 32, 64)]
    # 8e-4 off on logits up to 12: within 1e-4 x 12; 2e-4 off on logits below 1: not within 1e-4
    check = Verification(shapes, [8e-4, 2e-4], 1e-4, [12.0, 0.5])
    assert check.bounds() == pytest.approx([1.2e-3, 1e-4])
    assert not check.ok
    assert check.lines()[0].endswith("bound 0.0012)") and check.lines()[1].endswith("FAIL")
    assert Verification(shapes, [8e-4, 5e-5], 1e-4, [12.0, 0.5]).ok
    assert not Verification(shapes, [8e-4, 5e-5], 1e-4).ok  # no scales: absolute bound
