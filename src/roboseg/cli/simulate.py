"""``roboseg-simulate``: write a simulated draped-robot stereo recording (``conf/simulate.yaml``).

``roboseg-simulate out=DIR frames=N seed=S [robots=1|2] [robot.urdf=PATH] [camera.width=W
camera.height=H] [scenario=default|breathing]`` writes ``DIR/<name>.mcap`` and prints its path.
"""

from __future__ import annotations

import importlib
import inspect
import logging
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from roboseg.cli._main import user_errors_exit
from roboseg.config import CONF_DIR
from roboseg.errors import RobosegError
from roboseg.sim import SimConfig, simulate_recording

log = logging.getLogger("roboseg.simulate")
SCENARIOS = ("default", "breathing")


def _number(cfg: DictConfig, key: str, kind: type) -> Any:
    value = OmegaConf.select(cfg, key)
    try:
        return kind(value)
    except (TypeError, ValueError):
        raise RobosegError(f"{key} must be {kind.__name__}, got {value!r}") from None


def sim_config(cfg: DictConfig) -> SimConfig:
    """The :class:`SimConfig` of a ``simulate.yaml`` tree (one-line errors for bad values)."""
    urdf = OmegaConf.select(cfg, "robot.urdf")
    if urdf is not None and not Path(str(urdf)).is_file():
        raise RobosegError(f"robot.urdf: no such file {urdf}")
    distance = OmegaConf.select(cfg, "camera.distance")
    try:
        lo, hi = (float(x) for x in distance)
    except (TypeError, ValueError):
        raise RobosegError(
            f"camera.distance must be [near, far] in metres, got {distance}"
        ) from None
    return SimConfig(
        frames=_number(cfg, "frames", int),
        seed=_number(cfg, "seed", int),
        robots=_number(cfg, "robots", int),
        urdf=None if urdf is None else str(urdf),
        width=_number(cfg, "camera.width", int),
        height=_number(cfg, "camera.height", int),
        baseline=_number(cfg, "camera.baseline", float),
        fps=_number(cfg, "camera.fps", float),
        undraped_fraction=_number(cfg, "drape.undraped_fraction", float),
        distance=(lo, hi),
        jpeg_quality=_number(cfg, "render.jpeg_quality", int),
        workers=_number(cfg, "workers", int),
        site=None if OmegaConf.select(cfg, "site") is None else _number(cfg, "site", int),
        site_azimuth_deg=float(OmegaConf.select(cfg, "site_azimuth_deg", default=60.0)),
        walkers=int(OmegaConf.select(cfg, "walkers", default=0)),
    )


def _breathing(path: Path, sim: SimConfig) -> None:
    """Delegate ``scenario=breathing`` to ``roboseg.tracking.simulate``."""
    try:
        module = importlib.import_module("roboseg.tracking.simulate")
    except ModuleNotFoundError as exc:
        if exc.name != "roboseg.tracking.simulate":
            raise
        raise RobosegError(
            "scenario=breathing: roboseg.tracking.simulate is not available"
        ) from None
    fn = module.write_breathing_recording
    # that scene fixes its own camera (AprilTags need full resolution) and frame rate
    offered = {"frames": sim.frames, "jpeg_quality": sim.jpeg_quality}
    params = inspect.signature(fn).parameters
    fn(path, sim.seed, **{k: v for k, v in offered.items() if k in params})


@user_errors_exit
def run(cfg: DictConfig) -> Path:
    """Simulate the recording ``cfg`` describes; return its path."""
    scenario = str(cfg.scenario)
    if scenario not in SCENARIOS:
        raise RobosegError(f"scenario must be one of {SCENARIOS}, got {scenario!r}")
    sim = sim_config(cfg)
    sim.validate()
    threads = OmegaConf.select(cfg, "threads")
    if threads is not None:
        torch.set_num_threads(max(1, _number(cfg, "threads", int)))
    out = Path(str(cfg.out))
    if out.exists() and not out.is_dir():
        raise RobosegError(f"out: {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    name = str(cfg.name) if cfg.name is not None else f"sim_{sim.seed}"
    path = out / f"{name}.mcap"
    if scenario == "breathing":
        _breathing(path, sim)
    else:
        simulate_recording(sim, path)
    print(path)
    return path


@hydra.main(config_path=CONF_DIR, config_name="simulate", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
