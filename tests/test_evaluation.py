"""IoU, Table S4 formatting and the qualitative figure."""

from __future__ import annotations

import numpy as np
import pytest

from roboseg.evaluation import (
    TableRow,
    binary_iou,
    difference_image,
    qualitative_figure,
    table_csv,
    table_markdown,
)


def test_binary_iou_hand_computed():
    a = np.array([[1, 1, 0, 0]], bool)
    b = np.array([[0, 1, 1, 0]], bool)
    assert binary_iou(a, b) == pytest.approx(1 / 3)
    assert binary_iou(a, a) == 1.0
    assert binary_iou(np.zeros((2, 2)), np.zeros((2, 2))) == 1.0
    assert binary_iou(a, ~a) == 0.0
    with pytest.raises(ValueError):
        binary_iou(a, np.zeros((2, 2)))


def test_table_has_paper_columns_and_mean_std():
    rows = [
        TableRow("a.onnx", "mit_b3", 47.4, [0.6, 0.7, 0.8], True, 3, "medium"),
        TableRow("b.ckpt", "resnet101", 51.5, [0.3, 0.4], False, 4, "large", prior="zero"),
    ]
    md = table_markdown(rows)
    header = md.splitlines()[0]
    for col in (
        "Architecture",
        "Encoder",
        "Param. [1e6]",
        "IoU [a.u.]",
        "CMM",
        "In-channels",
        "Dataset",
    ):
        assert col in header
    assert "| U-Net | MIT-B3 | 47.4 | 0.70 ± 0.08 | ✓ | 3 | medium |" in md
    assert "ResNet-101" in md and "4 (zero prior)" in md and "0.35 ± 0.05" in md
    csv = table_csv(rows).splitlines()
    assert csv[0].startswith("model,architecture,encoder")
    assert csv[1].split(",")[4] == "0.7000" and csv[2].split(",")[-1] == "2"


def test_difference_colours():
    pred = np.array([[1, 1, 0, 0]], bool)
    gt = np.array([[1, 0, 1, 0]], bool)
    d = difference_image(pred, gt)
    assert tuple(d[0, 0]) == (255, 255, 255)  # TP
    assert d[0, 1, 0] > d[0, 1, 2]  # FP red
    assert d[0, 2, 2] > d[0, 2, 0]  # FN blue
    assert tuple(d[0, 3]) == (0, 0, 0)


def test_qualitative_figure_png(tmp_path):
    rng = np.random.default_rng(0)
    imgs = [rng.integers(0, 256, (40, 64, 3), dtype=np.uint8) for _ in range(2)]
    gts = [rng.random((40, 64)) > 0.5 for _ in range(2)]
    path = qualitative_figure(imgs, gts, gts[::-1], tmp_path / "fig.png", row_titles=["x", "y"])
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
