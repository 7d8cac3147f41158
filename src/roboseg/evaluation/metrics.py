"""IoU per frame, the paper's Table S4 (as Markdown and CSV), the errors by their distance to
the true outline, and the qualitative figure."""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

#: Table S4's columns, in the paper's order (plus the prior used for 4-channel models).
TABLE_COLUMNS = (
    "Architecture",
    "Encoder",
    "Param. [1e6]",
    "IoU [a.u.]",
    "CMM",
    "In-channels",
    "Dataset",
)


def binary_iou(pred: np.ndarray, target: np.ndarray) -> float:
    """Intersection over union of two boolean masks of the same shape.

    Two empty masks agree perfectly (IoU 1): a frame without robot predicted empty is right.
    """
    pred = np.asarray(pred, bool)
    target = np.asarray(target, bool)
    if pred.shape != target.shape:
        raise ValueError(f"mask shapes differ: {pred.shape} vs {target.shape}")
    union = np.logical_or(pred, target).sum()
    if union == 0:
        return 1.0
    return float(np.logical_and(pred, target).sum() / union)


#: Upper bounds (px, exclusive of the band before) of :func:`error_bands`' distance bands.
ERROR_BANDS_PX: tuple[float, ...] = (1.5, 3.5, 6.0, math.inf)


def band_labels(bands: Sequence[float] = ERROR_BANDS_PX) -> list[str]:
    """Column names of the distance bands, e.g. ``≤1.5 px``, ``1.5-3.5 px``, ``>6 px``."""
    labels, lo = [], 0.0
    for hi in bands:
        labels.append(f">{lo:g} px" if math.isinf(hi) else
                      f"≤{hi:g} px" if lo == 0 else f"{lo:g}-{hi:g} px")
        lo = hi
    return labels


def error_bands(
    pred: np.ndarray, target: np.ndarray, bands: Sequence[float] = ERROR_BANDS_PX
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel counts ``(misses, false_positives)``, each ``[len(bands)]``, of a boolean
    prediction against a boolean target, by the pixel's Euclidean distance (px) to the true
    outline: a missed robot pixel's to the nearest background pixel, a false positive's to the
    nearest robot pixel (1 for a pixel next to the outline). Band ``k`` holds distances in
    ``(bands[k-1], bands[k]]``. A false positive in a frame without robot pixels counts as
    infinitely far. Tells an outline drawn a pixel off (near bands) from a wrong object (far)."""
    pred = np.asarray(pred, bool)
    target = np.asarray(target, bool)
    if pred.shape != target.shape:
        raise ValueError(f"mask shapes differ: {pred.shape} vs {target.shape}")
    upper = np.asarray(bands, float)
    inside = cv2.distanceTransform(target.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    if target.any():
        outside = cv2.distanceTransform(
            (~target).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    else:
        outside = np.full(target.shape, np.inf, np.float32)

    def count(distances: np.ndarray) -> np.ndarray:
        band = np.searchsorted(upper, distances, side="left")  # first k with d <= bands[k]
        return np.bincount(band, minlength=len(upper))[: len(upper)].astype(np.int64)

    return count(inside[target & ~pred]), count(outside[pred & ~target])


def error_bands_markdown(
    rows: Sequence[tuple[str, np.ndarray, np.ndarray, int]],
    bands: Sequence[float] = ERROR_BANDS_PX,
) -> str:
    """Rows ``(name, misses, false_positives, true_pixels)`` (counts summed over frames) as a
    Markdown table of fractions of the true robot area."""
    labels = band_labels(bands)
    head = ["model"] + [f"missed {b}" for b in labels] + [f"false positive {b}" for b in labels]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    for name, misses, false_pos, area in rows:
        frac = [f"{v / area:.3f}" if area else "–" for v in (*misses, *false_pos)]
        lines.append("| " + " | ".join([name, *frac]) + " |")
    return "\n".join(lines) + "\n"


def encoder_label(name: str) -> str:
    """``mit_b3`` → ``MIT-B3``, ``resnet101`` → ``ResNet-101`` (the paper's spelling)."""
    n = name.lower()
    if n.startswith("mit_"):
        return "MIT-" + n[4:].upper()
    if n.startswith("resnet"):
        return "ResNet-" + n[6:]
    return name


@dataclass
class TableRow:
    """One evaluated model: a row of Table S4 plus where it came from."""

    model: str
    encoder: str
    params_m: float
    ious: list[float] = field(repr=False)
    cmm: bool | None
    in_channels: int
    dataset: str
    prior: str = "-"  # "-" (3 channels), "zero" or "perturbed" (4-channel models)
    architecture: str = "U-Net"

    @property
    def iou_mean(self) -> float:
        return float(np.mean(self.ious)) if self.ious else math.nan

    @property
    def iou_std(self) -> float:
        return float(np.std(self.ious)) if self.ious else math.nan

    def cells(self) -> list[str]:
        cmm = "?" if self.cmm is None else ("✓" if self.cmm else "✗")
        channels = str(self.in_channels) + ("" if self.prior == "-" else f" ({self.prior} prior)")
        return [
            self.architecture,
            encoder_label(self.encoder),
            f"{self.params_m:.1f}",
            f"{self.iou_mean:.2f} ± {self.iou_std:.2f}",
            cmm,
            channels,
            self.dataset,
        ]


def table_markdown(rows: Sequence[TableRow]) -> str:
    """Table S4 as a Markdown table (IoU mean ± std over frames)."""
    lines = [
        "| " + " | ".join(TABLE_COLUMNS) + " |",
        "|" + "|".join("---" for _ in TABLE_COLUMNS) + "|",
    ]
    lines += ["| " + " | ".join(r.cells()) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def table_csv(rows: Sequence[TableRow]) -> str:
    """Table S4 as CSV with numeric columns split (model file, IoU mean and std, frames)."""
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(
        [
            "model",
            "architecture",
            "encoder",
            "params_m",
            "iou_mean",
            "iou_std",
            "cmm",
            "in_channels",
            "prior",
            "dataset",
            "frames",
        ]
    )
    for r in rows:
        w.writerow(
            [
                r.model,
                r.architecture,
                encoder_label(r.encoder),
                f"{r.params_m:.1f}",
                f"{r.iou_mean:.4f}",
                f"{r.iou_std:.4f}",
                "" if r.cmm is None else int(r.cmm),
                r.in_channels,
                r.prior,
                r.dataset,
                len(r.ious),
            ]
        )
    return buf.getvalue()


def row_summary(row: TableRow) -> dict[str, object]:
    """A row as plain data (for logs and JSON)."""
    d = asdict(row)
    d.pop("ious")
    d.update(iou_mean=row.iou_mean, iou_std=row.iou_std, frames=len(row.ious))
    return d


def difference_image(pred: np.ndarray, target: np.ndarray) -> np.ndarray:
    """RGB uint8 picture of agreement: true positive white, false positive red, false negative
    blue."""
    pred = np.asarray(pred, bool)
    target = np.asarray(target, bool)
    out = np.zeros((*pred.shape, 3), np.uint8)
    out[pred & target] = (255, 255, 255)
    out[pred & ~target] = (230, 40, 40)
    out[~pred & target] = (40, 90, 230)
    return out


def qualitative_figure(
    images: Sequence[np.ndarray],
    targets: Sequence[np.ndarray],
    preds: Sequence[np.ndarray],
    path: str | Path,
    *,
    row_titles: Sequence[str] | None = None,
) -> Path:
    """Write the paper-style figure: one row per frame, columns image | ground truth |
    prediction | difference (TP white, FP red, FN blue)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(images)
    h, w = np.asarray(images[0]).shape[:2]
    fig, axes = plt.subplots(n, 4, figsize=(4 * 3.2, n * 3.2 * h / w + 0.6), squeeze=False)
    for i in range(n):
        img = np.asarray(images[i])
        pred = np.asarray(preds[i], bool)
        tgt = np.asarray(targets[i], bool)
        panels = [img, tgt, pred, difference_image(pred, tgt)]
        for j, (ax, p) in enumerate(zip(axes[i], panels, strict=True)):
            ax.imshow(
                p, cmap="gray" if p.ndim == 2 else None, vmin=0, vmax=1 if p.ndim == 2 else None
            )
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(("image", "ground truth", "prediction", "difference")[j])
        label = row_titles[i] if row_titles else ""
        axes[i][0].set_ylabel(f"{label}\nIoU {binary_iou(pred, tgt):.2f}".strip(), fontsize=9)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.part")
    fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
    tmp.replace(path)
    return path
