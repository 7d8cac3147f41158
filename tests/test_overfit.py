"""Sanity before tuning: every model preset a default uses fits a tiny annotated set.

One simulated recording (16 frames), no augmentation, the default experiment's optimiser,
loss and schedule, the datamodule and the LightningModule as ``roboseg-train`` builds them: the
per-frame IoU on those same frames must reach 0.95 within a bounded number of steps. A failure
here is a bug in the data path (labels misaligned with images after resizing, normalisation, the
loss's reduction, the schedule), not a figure to report.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import lightning.pytorch as pl
import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

from roboseg.config import CONF_DIR

sys.path.insert(0, str(Path(__file__).parent))
from test_datamodule import annotate_from_gt  # noqa: E402

from roboseg.sim import SimConfig, simulate_recording  # noqa: E402

#: Frames of the tiny set and the model input they are trained at ([H, W], 16:9 kept).
FRAMES, SIZE = 16, (96, 160)
#: Step bound of the sanity check and the IoU it must reach.
MAX_STEPS, TARGET = 200, 0.95


def default_presets() -> list[str]:
    """Model presets of ``make train`` (experiment default), of ``make reproduce``'s CPU
    recipe (bootstrap and models) and of roboseg-register's self-training, read from the
    configs so the test follows the defaults."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        train = compose("train", overrides=["experiment=default", "data.root=x"])
        repro = compose("reproduce")
        register = compose("register")
    names = {str(train.model.name), str(register.self_training.model)}
    overrides = list(repro.lab.overrides)
    for model in repro.recipes.cpu:
        overrides += list(model.overrides)
    names |= {o.split("=", 1)[1] for o in overrides if o.startswith("model=")}
    return sorted(names)


@pytest.fixture(scope="module")
def tiny_set(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One recording, annotated with its ground truth, listed as both train and val split."""
    root = tmp_path_factory.mktemp("overfit")
    data = root / "data"
    data.mkdir()
    # a near camera: the arm some 8-15 px wide at the model input
    sim = SimConfig(frames=FRAMES, seed=11, width=192, height=108, distance=(0.8, 1.0))
    simulate_recording(sim, root / "train_00.mcap")
    entry = dict(annotate_from_gt(root / "train_00.mcap", data / "train_00.mcap", 24_000),
                 split="train")
    shutil.copy(data / "train_00.mcap", data / "val_00.mcap")
    manifest = {"format": "roboseg-annotations/1", "camera": "camera", "robot_urdf": None,
                "subset": "full", "subset_fraction": None,
                "recordings": [entry, dict(entry, split="val", file="val_00.mcap")]}
    (data / "manifest.json").write_text(json.dumps(manifest))
    return data


class Best(pl.Callback):
    """Stops the run once val/iou reaches the target; remembers the best value and step."""

    def __init__(self) -> None:
        self.best, self.step = 0.0, -1

    def on_validation_end(self, trainer: pl.Trainer, module: pl.LightningModule) -> None:
        iou = float(trainer.callback_metrics.get("val/iou", 0.0))
        if iou > self.best:
            self.best, self.step = iou, trainer.global_step
        if iou >= TARGET:
            trainer.should_stop = True


def test_default_presets_are_read_from_the_configs():
    presets = default_presets()
    assert presets and all(p.startswith("unet_") for p in presets)


@pytest.mark.slow
@pytest.mark.parametrize("preset", default_presets())
def test_every_default_preset_overfits_one_recording(tiny_set: Path, preset: str) -> None:
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("train", overrides=[
            "experiment=default", f"model={preset}", "augment=none", f"data.root={tiny_set}",
            f"data.image_size=[{SIZE[0]},{SIZE[1]}]", "data.val_phase=all",
            "data.num_workers=0", "data.shuffle_buffer=16", "paths.output_dir=/tmp"])
    pl.seed_everything(0, workers=True)
    module = instantiate(cfg.module)
    assert module.augment is None
    data = instantiate(cfg.data)
    best = Best()
    trainer = pl.Trainer(
        accelerator="cpu", devices=1, max_steps=MAX_STEPS, val_check_interval=25,
        check_val_every_n_epoch=None, num_sanity_val_steps=0, callbacks=[best], logger=False,
        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False)
    trainer.fit(module, datamodule=data)
    lr = OmegaConf.select(cfg, "module.lr")
    assert best.best >= TARGET, (
        f"{preset} reached only IoU {best.best:.3f} on its own {FRAMES} training frames in "
        f"{MAX_STEPS} steps (lr {lr})")
