"""``roboseg-eval``: IoU of ONNX models and checkpoints on an annotated test split (``eval.yaml``).

``roboseg-eval 'models=[A.onnx,B.ckpt]' data.root=DIR out=OUT`` writes ``OUT/iou_table.md``,
``OUT/iou_table.csv``, ``OUT/per_frame_iou.csv``, ``OUT/error_bands.md`` (missed and false-positive
pixels by distance to the true outline) and ``OUT/qualitative_*.png`` and prints the table.
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig, ListConfig, OmegaConf

from roboseg.cli._main import parse_scales, user_errors_exit
from roboseg.config import CONF_DIR
from roboseg.errors import RobosegError
from roboseg.evaluation.metrics import TableRow, table_markdown
from roboseg.evaluation.run import PriorRenderer, evaluate_models, load_manifest

log = logging.getLogger("roboseg.eval")


def _model_list(value: object) -> list[str]:
    if isinstance(value, str):
        return [value]
    if isinstance(value, ListConfig | list) and value:
        return [str(v) for v in value]
    raise RobosegError(f"models must be a non-empty list of .onnx/.ckpt files, got {value!r}")


def _pair(value: object, key: str) -> tuple[float, float] | None:
    if value is None:
        return None
    try:
        a, b = (float(v) for v in value)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise RobosegError(f"{key} must be a pair of numbers, got {value!r}") from None
    return a, b


@user_errors_exit
def run(cfg: DictConfig) -> list[TableRow]:
    """Evaluate the configured models; print and return the table rows."""
    if cfg.threads is not None:
        torch.set_num_threads(max(1, int(cfg.threads)))
    root = Path(str(cfg.data.root))
    urdf = cfg.prior.urdf
    if urdf is None:
        urdf = load_manifest(root).get("robot_urdf")
    translation = _pair(cfg.prior.translation, "prior.translation")
    prior = PriorRenderer(
        urdf=None if urdf is None else str(urdf),
        translation_range=translation or (0.0, 0.05),
        rotation_deg=float(cfg.prior.rotation_deg),
        reduction=float(cfg.prior.reduction),
        seed=int(cfg.seed),
    )
    train_size = _pair(cfg.train_size, "train_size")
    figure_frames = cfg.figure_frames
    if isinstance(figure_frames, ListConfig):
        figure_frames = [int(v) for v in figure_frames]
    overrides = OmegaConf.to_container(cfg.overrides) if cfg.overrides else None
    scales = parse_scales(cfg.get("scales"), "scales")
    rows = evaluate_models(
        _model_list(cfg.models),
        root,
        Path(str(cfg.out)),
        split=str(cfg.split),
        labels=str(cfg.labels),
        max_frames=None if cfg.max_frames is None else int(cfg.max_frames),
        figure_frames=figure_frames,
        overrides=overrides,
        prior=prior,
        source_size=None if train_size is None else (int(train_size[0]), int(train_size[1])),
        progress=bool(cfg.progress),
        phase=str(cfg.phase),
        scales=scales,
    )
    print(table_markdown(rows), end="")
    for r in rows:
        prior = "" if r.prior == "-" else f" ({r.prior} prior)"
        print(f"{r.model}{prior}: IoU {r.iou_mean:.4f} ± {r.iou_std:.4f} over {len(r.ious)} frames")
    if scales != [1.0]:
        print(f"each image segmented at {scales} x the model's input size, probabilities averaged")
    print(f"written to {cfg.out}/ (iou_table.md, iou_table.csv, per_frame_iou.csv, "
          "error_bands.md, figures)")
    return rows


@hydra.main(config_path=CONF_DIR, config_name="eval", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
