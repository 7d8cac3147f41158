"""Evaluation: IoU tables like the paper's Table S4, per-frame IoU and qualitative figures."""

from roboseg.evaluation.metrics import (
    TABLE_COLUMNS,
    TableRow,
    binary_iou,
    difference_image,
    qualitative_figure,
    table_csv,
    table_markdown,
)

__all__ = [
    "TABLE_COLUMNS",
    "TableRow",
    "binary_iou",
    "difference_image",
    "qualitative_figure",
    "table_csv",
    "table_markdown",
]
