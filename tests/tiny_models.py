"""A tiny synthetic segmentation dataset and a two-step training run, for tests that need a real
roboseg checkpoint (export, evaluation) without recordings."""

from __future__ import annotations

from pathlib import Path

import lightning.pytorch as pl
import torch
from torch.utils.data import DataLoader, Dataset

from roboseg.training import SegmentationModule

SIZE = 64


class Squares(Dataset):
    """Noise with one reddish square (the 'robot'); the prior is the mask shifted by 2 px."""

    def __len__(self) -> int:
        return 8

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        g = torch.Generator().manual_seed(i)
        image = torch.rand(3, SIZE, SIZE, generator=g) * 0.5
        mask = torch.zeros(1, SIZE, SIZE)
        top, left = (int(v) for v in torch.randint(0, SIZE - 24, (2,), generator=g))
        mask[:, top : top + 24, left : left + 24] = 1
        image = torch.where(mask.bool(), torch.tensor([0.9, 0.3, 0.2]).view(3, 1, 1), image)
        return {"image": image, "mask": mask, "prior": mask.roll(2, -1),
                "visible": torch.tensor(True), "index": torch.tensor(i)}


def train_checkpoint(path: Path, in_channels: int = 3, cmm: bool = False) -> Path:
    """Two optimizer steps of a ResNet-18 U-Net at 64 px, saved as a Lightning checkpoint."""
    torch.manual_seed(0)
    augment = None
    if cmm:
        augment = {"_target_": "roboseg.augment.AugmentationPipeline", "seed": 0,
                   "cmm": {"_target_": "roboseg.augment.CutMixMerge", "p": 0.5}}
    module = SegmentationModule(
        model={"name": "unet_resnet18", "in_channels": in_channels}, augment=augment, lr=1e-3,
        image_size=(SIZE, SIZE), dataset="synthetic",
    )
    trainer = pl.Trainer(max_steps=2, accelerator="cpu", logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False)
    trainer.fit(module, DataLoader(Squares(), batch_size=4))
    trainer.save_checkpoint(path)
    return path
