"""Shared fixtures: the KUKA LBR Med 7 URDF beside the checkout, the built-in robot, a
per-session decimation cache so tests never write to the user's cache, and one torch thread for
the modules of small renders."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

from roboseg.robot import RobotModel, load_robot

SHARED_DIR = Path(__file__).resolve().parents[1].parent / "shared"
LBR_URDF = SHARED_DIR / "robots" / "lbr_med7" / "lbr_med7.urdf"


@pytest.fixture(scope="session", autouse=True)
def _session_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """Point ``$ROBOSEG_CACHE`` at a temporary folder for the whole test session."""
    with pytest.MonkeyPatch.context() as mp:
        cache = tmp_path_factory.mktemp("roboseg_cache")
        mp.setenv("ROBOSEG_CACHE", str(cache))
        yield cache


@pytest.fixture(scope="session")
def lbr_urdf() -> Path:
    """Path of the LBR Med 7 URDF (with its STL meshes); skips when the folder is absent."""
    if not LBR_URDF.is_file():
        pytest.skip(f"LBR Med 7 model not found at {LBR_URDF}")
    return LBR_URDF


@pytest.fixture(scope="session")
def default_robot() -> RobotModel:
    """The built-in primitive 7-DoF arm (float32, CPU); treat as read-only."""
    return load_robot(None)


@pytest.fixture(scope="module")
def one_torch_thread() -> Iterator[None]:
    """Small renders run fastest on one thread; on a loaded machine extra threads only contend.
    A module opts in with ``pytestmark = pytest.mark.usefixtures("one_torch_thread")``."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
