"""bench/learning.py: every recipe is a valid training config, and the curve arithmetic."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.learning import RECIPES, iou_at  # noqa: E402
from roboseg.config import CONF_DIR  # noqa: E402
from roboseg.pipeline import session_seed, table_iou  # noqa: E402


@pytest.mark.parametrize("name", sorted(RECIPES))
def test_recipe_builds_a_module(name: str) -> None:
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("train", overrides=["experiment=default", "data.root=x",
                                          "paths.output_dir=/tmp", *RECIPES[name]])
    module = instantiate(cfg.module)
    assert module.hparams.image_size == list(cfg.data.image_size)
    crop = module.augment.crop
    assert (crop is None) == ("augment.crop=null" in RECIPES[name])
    if crop is not None:  # windows fit the frames they are cut from
        assert all(c <= s for c, s in zip(crop.size, cfg.data.image_size, strict=True))
    if "augment.photometric.ops=[]" in RECIPES[name]:  # no augmentation: nothing fires
        assert module.augment.affine.p == module.augment.cmm.p == 0.0
    fp32 = "trainer.precision=32-true" in RECIPES[name]
    assert cfg.trainer.precision == ("32-true" if fp32 else "bf16-mixed")
    assert module.hparams.channels_last is not fp32


def test_iou_at_is_the_best_value_reached_by_then():
    points = [[50.0, 100, 0.2], [110.0, 200, 0.5], [170.0, 300, 0.4], [240.0, 400, 0.6]]
    assert iou_at(points, 60) == 0.2
    assert iou_at(points, 180) == 0.5  # best so far, not the last
    assert iou_at(points, 240) == 0.6
    assert iou_at(points, 300) is None  # not trained that long
    assert iou_at([], 60) is None


def test_session_seeds_never_repeat_across_splits(tmp_path: Path):
    seeds = [session_seed(0, split, i) for split in ("train", "val", "test")
             for i in range(100)]
    assert len(set(seeds)) == len(seeds)
    csv = tmp_path / "iou_table.csv"
    csv.write_text("model,iou_mean,iou_std,frames\nm.onnx,0.7512,0.1,42\n")
    assert table_iou(csv) == (0.7512, 0.1, 42)
