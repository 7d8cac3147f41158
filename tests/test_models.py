"""U-Net registry/factory: paper parameter counts, 4-channel input, local weights only."""

from __future__ import annotations

import pytest
import torch

from roboseg.errors import ModelFileError
from roboseg.models import (
    DECODER_CHANNELS,
    PRESETS,
    ModelConfigError,
    adapt_in_channels,
    available_models,
    build_unet,
    count_params,
    with_tta,
)


def test_registry_lists_the_paper_presets():
    expected = {f"unet_mit_b{i}" for i in range(6)} | {"unet_resnet18", "unet_resnet101",
                                                      "unet_regnety_004"}
    assert set(available_models()) == expected
    assert PRESETS["unet_mit_b3"].encoder == "mit_b3"


@pytest.mark.parametrize("name", ["unet_mit_b3", "unet_mit_b5", "unet_resnet101"])
def test_parameter_counts_match_the_paper(name):
    torch.manual_seed(0)
    n = count_params(build_unet(name, in_channels=3)) / 1e6
    assert n == pytest.approx(PRESETS[name].paper_params_m, rel=0.01)


@pytest.mark.parametrize("name", ["unet_mit_b0", "unet_resnet18", "unet_regnety_004"])
@pytest.mark.parametrize("in_channels", [3, 4])
def test_forward_shape_and_decoder(name, in_channels):
    torch.manual_seed(0)
    model = build_unet(name, in_channels=in_channels).eval()
    with torch.no_grad():
        out = model(torch.rand(2, in_channels, 64, 96))
    assert out.shape == (2, 1, 64, 96)
    assert torch.isfinite(out).all()
    convs = [m for m in model.decoder.modules() if isinstance(m, torch.nn.Conv2d)]
    assert [c.out_channels for c in convs][-1] == DECODER_CHANNELS[-1]
    assert model.segmentation_head[0].out_channels == 1


def test_decoder_channels_override_sets_every_block_width():
    torch.manual_seed(0)
    model = build_unet("unet_mit_b0", decoder_channels=[128, 64, 32, 16, 8]).eval()
    blocks = [b.conv2[0].out_channels for b in model.decoder.blocks]
    assert blocks == [128, 64, 32, 16, 8]
    with torch.no_grad():
        assert model(torch.rand(1, 3, 64, 64)).shape == (1, 1, 64, 64)
    assert count_params(model) < count_params(build_unet("unet_mit_b0"))
    with pytest.raises(ModelConfigError, match="five positive widths|5 positive widths"):
        build_unet("unet_mit_b0", decoder_channels=[64, 32])


def test_four_channel_model_uses_the_prior_channel():
    torch.manual_seed(0)
    model = build_unet("unet_mit_b0", in_channels=4).eval()
    x = torch.rand(1, 4, 64, 64)
    x[:, 3] = 0
    with torch.no_grad():
        a = model(x)
        x[:, 3, 16:48, 16:48] = 1
        b = model(x)
    assert not torch.allclose(a, b)


def test_unknown_preset_and_channels_are_rejected():
    with pytest.raises(ModelConfigError, match="unknown model 'unet_vgg'"):
        build_unet("unet_vgg")
    with pytest.raises(ModelConfigError, match="in_channels must be 3 or 4"):
        build_unet("unet_mit_b0", in_channels=5)


def test_adapt_in_channels_zero_pads_the_prior():
    w = torch.arange(2 * 3 * 1 * 1, dtype=torch.float32).reshape(2, 3, 1, 1)
    out = adapt_in_channels(w, 4)
    assert out.shape == (2, 4, 1, 1)
    assert torch.equal(out[:, :3], w) and torch.equal(out[:, 3], torch.zeros(2, 1, 1))


def test_local_weights_load_into_three_and_four_channels(tmp_path):
    torch.manual_seed(1)
    src = build_unet("unet_resnet18", in_channels=3)
    path = tmp_path / "w.pt"
    torch.save({"state_dict": {f"net.{k}": v for k, v in src.state_dict().items()}}, path)
    same = build_unet("unet_resnet18", in_channels=3, weights_path=path)
    for k, v in src.state_dict().items():
        assert torch.equal(same.state_dict()[k], v), k
    # encoder-only file into a 4-channel model: RGB kernels copied, prior kernel zero
    enc_path = tmp_path / "enc.pt"
    torch.save(src.encoder.state_dict(), enc_path)
    four = build_unet("unet_resnet18", in_channels=4, weights_path=enc_path)
    w4 = four.encoder.conv1.weight
    assert torch.equal(w4[:, :3], src.encoder.conv1.weight) and not w4[:, 3].any()
    x = torch.rand(1, 3, 64, 64)
    src.eval(), four.eval()
    with torch.no_grad():
        ref = src.encoder(x)[-1]
        got = four.encoder(torch.cat([x, torch.zeros(1, 1, 64, 64)], 1))[-1]
    torch.testing.assert_close(got, ref)


def test_bad_weight_files_are_clear_errors(tmp_path):
    with pytest.raises(ModelFileError, match="nope.pt: no such file"):
        build_unet("unet_resnet18", weights_path=tmp_path / "nope.pt")
    other = tmp_path / "other.pt"
    torch.save({"foo.bar": torch.zeros(3)}, other)
    with pytest.raises(ModelFileError, match="no parameter names match"):
        build_unet("unet_resnet18", weights_path=other)
    wrong = tmp_path / "wrong.pt"
    torch.save({"encoder.conv1.weight": torch.zeros(64, 3, 3, 3)}, wrong)
    with pytest.raises(ModelFileError, match=r"encoder.conv1.weight has shape \(64, 3, 3, 3\)"):
        build_unet("unet_resnet18", weights_path=wrong)
    hostile = tmp_path / "hostile.pt"
    torch.save({"x": object()}, hostile)
    with pytest.raises(ModelFileError, match="cannot be read safely"):
        build_unet("unet_resnet18", weights_path=hostile)


def test_flip_averaged_is_the_mean_of_the_two_views_and_mirror_equivariant():
    torch.manual_seed(0)
    net = torch.nn.Conv2d(3, 1, (1, 3), padding=(0, 1))  # not mirror-symmetric by itself
    tta = with_tta(net, "flip").eval()
    x = torch.rand(3, 3, 8, 10)
    with torch.no_grad():
        expected = 0.5 * (net(x) + net(x.flip(-1)).flip(-1))
        torch.testing.assert_close(tta(x), expected)
        torch.testing.assert_close(tta(x.flip(-1)), tta(x).flip(-1))
        assert not torch.allclose(net(x.flip(-1)), net(x).flip(-1))
    assert with_tta(net, None) is net
    with pytest.raises(ModelConfigError, match="tta must be one of flip or null, got 'scale'"):
        with_tta(net, "scale")
