"""Batched training augmentation on the training device, in the paper's order.

(1) in-context prior at a perturbed pose (:mod:`.prior`, rendered where the batch is built),
(2) geometric (:mod:`.geometric`), (3) cut-mix-merge (:mod:`.cmm`), (4) photometric
(:mod:`.photometric`); :mod:`.pipeline` chains (2)-(4). Every transform is an ``nn.Module`` whose
random parameters are drawn by ``sample(...)`` from a ``torch.Generator`` and used by
``apply(...)``, so one draw moves image, mask and prior alike.

Batches are dicts: ``image`` float ``[B,3,H,W]`` in [0, 1], ``mask`` float ``[B,1,H,W]`` in {0, 1},
``prior`` float ``[B,1,H,W]`` (zeros when absent), ``visible`` bool ``[B]`` (robot entirely inside
the frame), ``index`` long ``[B]``, optionally ``draped`` (bool ``[B]`` per frame, made a float
``[B,1,H,W]`` map of the kind of label per pixel before the steps).
"""

from roboseg.augment.cmm import CutMixMerge
from roboseg.augment.geometric import ConditionalAffine, HorizontalFlip, RobotCrop
from roboseg.augment.photometric import Photometric
from roboseg.augment.pipeline import AugmentationPipeline, to_model_input
from roboseg.augment.prior import InContextPrior

__all__ = [
    "AugmentationPipeline",
    "ConditionalAffine",
    "CutMixMerge",
    "HorizontalFlip",
    "InContextPrior",
    "Photometric",
    "RobotCrop",
    "to_model_input",
]
