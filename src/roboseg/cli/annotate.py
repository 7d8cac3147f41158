"""``roboseg-annotate in=DIR out=DIR [robot.urdf=PATH] [subset=medium] [calibration=YAML]``:
self-annotate recordings (``conf/annotate.yaml``) and print kept/skipped per recording."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from roboseg.annotate import (
    SKIP_REASONS,
    AnnotateOptions,
    annotate_folder,
    subset_fraction,
)
from roboseg.cli._main import user_errors_exit
from roboseg.config import CONF_DIR
from roboseg.errors import RobosegError
from roboseg.robot import load_robot

log = logging.getLogger("roboseg.annotate")


def options_from_config(cfg: DictConfig) -> AnnotateOptions:
    """:class:`AnnotateOptions` of an ``annotate.yaml`` tree (one-line errors)."""
    calibration = cfg.calibration
    if calibration is not None and not Path(str(calibration)).is_file():
        raise RobosegError(f"calibration: no such file {calibration}")
    try:
        return AnnotateOptions(
            camera=str(cfg.camera),
            fraction=subset_fraction(str(cfg.subset), cfg.subset_fraction),
            min_joint_speed=float(cfg.min_joint_speed),
            phase=str(cfg.phase),
            calibration=None if calibration is None else str(calibration),
            tolerance_ns=round(float(cfg.tolerance_ms) * 1e6),
            stereo_tolerance_ns=round(float(cfg.stereo_tolerance_ms) * 1e6),
            png_level=int(cfg.png_level),
            workers=int(OmegaConf.select(cfg, "workers", default=1)),
            mesh_reduction=float(OmegaConf.select(cfg, "mesh.reduction", default=0.0)),
            mesh_min_iou=float(OmegaConf.select(cfg, "mesh.min_iou", default=0.995)),
            mesh_check_frames=int(OmegaConf.select(cfg, "mesh.check_frames", default=8)),
        )
    except (TypeError, ValueError) as exc:
        raise RobosegError(f"annotate config: {exc}") from None


def summary_table(manifest: dict[str, Any]) -> str:
    """Plain-text table: kept / total and skip counts per recording."""
    head = ["file", "split", "kept", "total", *SKIP_REASONS]
    rows = [
        [r["file"], r["split"], r["frames_kept"], r["frames_total"], *r["skipped"].values()]
        for r in manifest["recordings"]
    ]
    t = manifest["totals"]
    rows.append(["TOTAL", "", t["frames_kept"], t["frames_total"], *t["skipped"].values()])
    widths = [max(len(str(x)) for x in col) for col in zip(head, *rows, strict=True)]
    return "\n".join(
        "  ".join(str(x).rjust(w) for x, w in zip(row, widths, strict=True))
        for row in [head, *rows]
    )


@user_errors_exit
def run(cfg: DictConfig) -> dict[str, Any]:
    """Annotate ``cfg["in"]`` into ``cfg.out``; print the summary table; return the manifest."""
    options = options_from_config(cfg)
    if cfg.threads is not None:
        torch.set_num_threads(max(1, int(cfg.threads)))
    urdf = OmegaConf.select(cfg, "robot.urdf")
    if urdf is not None and not Path(str(urdf)).is_file():
        raise RobosegError(f"robot.urdf: no such file {urdf}")
    robot = load_robot(None if urdf is None else str(urdf))
    splits = OmegaConf.to_container(cfg.splits) if cfg.splits is not None else None
    manifest = annotate_folder(
        Path(str(cfg["in"])),
        Path(str(cfg.out)),
        robot,
        options,
        subset=str(cfg.subset) if cfg.subset_fraction is None else "custom",
        subset_fraction=cfg.subset_fraction,
        subset_splits=list(cfg.subset_splits),
        splits=splits,  # type: ignore[arg-type]
        urdf=None if urdf is None else str(Path(str(urdf)).resolve()),
    )
    print(summary_table(manifest))
    return manifest


@hydra.main(config_path=CONF_DIR, config_name="annotate", version_base="1.3")
def main(cfg: DictConfig) -> None:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    run(cfg)


if __name__ == "__main__":
    main()
