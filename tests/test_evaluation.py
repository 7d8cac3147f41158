"""IoU, errors by distance to the outline, Table S4 formatting and the qualitative figure."""

from __future__ import annotations

import numpy as np
import pytest

from roboseg.evaluation import (
    TableRow,
    band_labels,
    binary_iou,
    difference_image,
    error_bands,
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


def test_error_bands_hand_computed():
    target = np.zeros((40, 40), bool)
    target[10:20, 10:20] = True  # 100 robot pixels
    pred = np.zeros_like(target)
    pred[10:20, 11:21] = True  # one pixel to the right
    pred[10:12, 32:34] = True  # a blob 13 px right of the robot
    misses, false_pos = error_bands(pred, target)
    # the left column is missed, each pixel next to the background
    np.testing.assert_array_equal(misses, [10, 0, 0, 0])
    # the column right of the robot touches it; the blob's pixels are 13-14 px away
    np.testing.assert_array_equal(false_pos, [10, 0, 0, 4])
    thick = np.zeros_like(target)
    thick[14:16, 14:16] = True  # only the robot's core: misses 1-4 px inside its outline
    misses, false_pos = error_bands(thick, target)
    assert misses.sum() == 96 and false_pos.sum() == 0
    assert misses[0] == 36 and misses[1] == 28 + 20 and misses[2] == 12
    assert band_labels() == ["≤1.5 px", "1.5-3.5 px", "3.5-6 px", ">6 px"]
    # no robot in the frame: every false positive is far
    _, far = error_bands(pred, np.zeros_like(target))
    np.testing.assert_array_equal(far, [0, 0, 0, pred.sum()])
    with pytest.raises(ValueError, match="shapes differ"):
        error_bands(pred, target[:5])
