"""``roboseg-render``: pixel-exact masks of a toy box robot, overlays, one-line errors."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from roboseg.cli.render import render_mask, run
from roboseg.config import CONF_DIR

SCRIPT = Path(sys.executable).with_name("roboseg-render")

# A 0.4 m cube centred on the base origin; one revolute joint to a link without geometry.
BOX_URDF = """<?xml version="1.0"?>
<robot name="box_bot">
  <link name="base"><visual><geometry><box size="0.4 0.4 0.4"/></geometry></visual></link>
  <link name="tip"/>
  <joint name="j1" type="revolute">
    <parent link="base"/><child link="tip"/><origin xyz="0 0 0.2"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
</robot>
"""
# Camera 2 m in front of the cube, looking along the base's +z: the near face is at z = 1.8 m.
# With f = 90 px and c = 49.5 it spans u, v = 49.5 ± 90·0.2/1.8 = [39.5, 59.5] -> centres 40..59.
OVERRIDES = [
    "camera.width=100",
    "camera.height=100",
    "camera.K=[90,0,49.5,0,90,49.5,0,0,1]",
    "T_cam_base=[1,0,0,0,0,1,0,0,0,0,1,2,0,0,0,1]",
    "robot.joints=[0.3]",
]


def _expected() -> np.ndarray:
    mask = np.zeros((100, 100), dtype=bool)
    mask[40:60, 40:60] = True
    return mask


@pytest.fixture
def box_urdf(tmp_path: Path) -> Path:
    path = tmp_path / "box_bot.urdf"
    path.write_text(BOX_URDF)
    return path


def _cfg(overrides: list[str]) -> DictConfig:
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name="render", overrides=overrides)


def test_box_seen_head_on_covers_expected_pixels(box_urdf: Path, tmp_path: Path) -> None:
    cfg = _cfg([*OVERRIDES, f"robot.urdf={box_urdf}", f"out={tmp_path / 'm.png'}"])
    assert np.array_equal(render_mask(cfg), _expected())
    path = run(cfg)
    png = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint8 and png.shape == (100, 100)
    assert np.array_equal(png, _expected().astype(np.uint8) * 255)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temp left


def test_overlay_tints_robot_and_keeps_background(box_urdf: Path, tmp_path: Path) -> None:
    background = np.full((100, 100, 3), 128, dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "bg.png"), background)
    out = tmp_path / "overlay.png"
    cfg = _cfg([*OVERRIDES, f"robot.urdf={box_urdf}", f"image={tmp_path / 'bg.png'}", f"out={out}"])
    run(cfg)
    image = cv2.imread(str(out), cv2.IMREAD_COLOR)
    changed = np.any(image != background, axis=2)
    assert np.all(changed[41:59, 41:59])  # tinted interior
    assert not changed[:38].any() and not changed[62:].any()  # background untouched
    assert np.all(changed[40, 40:60])  # contour on the boundary


def test_defaults_render_the_default_robot(tmp_path: Path) -> None:
    mask = render_mask(_cfg([f"out={tmp_path / 'd.png'}"]))
    assert mask.shape == (540, 960)
    assert 0.005 < mask.mean() < 0.5
    rows, cols = np.nonzero(mask)
    assert rows.min() > 0 and rows.max() < 539 and cols.min() > 0 and cols.max() < 959


def test_console_script_writes_mask_and_reports_errors(box_urdf: Path, tmp_path: Path) -> None:
    if not SCRIPT.is_file():
        pytest.skip(f"console script {SCRIPT} is not installed")
    out = tmp_path / "sub" / "mask.png"
    ok = subprocess.run(
        [str(SCRIPT), *OVERRIDES, f"robot.urdf={box_urdf}", f"out={out}"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
    )
    assert ok.returncode == 0, ok.stderr
    assert ok.stdout.strip().splitlines()[-1] == str(out)
    assert np.array_equal(cv2.imread(str(out), cv2.IMREAD_UNCHANGED) > 0, _expected())

    bad = subprocess.run(
        [
            str(SCRIPT),
            *OVERRIDES,
            f"robot.urdf={box_urdf}",
            "robot.joints=[0.1,0.2]",
            f"out={tmp_path / 'x.png'}",
        ],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
    )
    assert bad.returncode == 1
    lines = bad.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and "j1" in lines[0]
    assert not (tmp_path / "x.png").exists()


@pytest.mark.parametrize(
    "override, match",
    [
        ("robot.urdf=/nonexistent/robot.urdf", "robot.urdf"),
        ("camera.K=[90,0,49.5,0,90,49.5]", "camera.K"),
        ("camera.K=[-90,0,49.5,0,90,49.5,0,0,1]", "focal"),
        ("T_cam_base=[2,0,0,0,0,1,0,0,0,0,1,2,0,0,0,1]", "T_cam_base"),
        ("T_cam_base=[1,0,0,0,0,1,0,0,0,0,1,-2,0,0,0,1]", "behind the camera"),
        ("robot.joints=[abc]", "robot.joints"),
    ],
)
def test_user_errors_are_one_line_exit_1(
    box_urdf: Path, tmp_path: Path, override: str, match: str, capsys: pytest.CaptureFixture
) -> None:
    cfg = _cfg([*OVERRIDES, f"robot.urdf={box_urdf}", override, f"out={tmp_path / 'e.png'}"])
    with pytest.raises(SystemExit) as exc:
        run(cfg)
    assert exc.value.code == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and match in err[0]
