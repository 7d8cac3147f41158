"""Evaluation: IoU tables like the paper's Table S4, per-frame IoU, errors by distance to the
true outline and qualitative figures."""

from roboseg.evaluation.metrics import (
    ERROR_BANDS_PX,
    TABLE_COLUMNS,
    TableRow,
    band_labels,
    binary_iou,
    difference_image,
    error_bands,
    qualitative_figure,
    table_csv,
    table_markdown,
)

__all__ = [
    "ERROR_BANDS_PX",
    "TABLE_COLUMNS",
    "TableRow",
    "band_labels",
    "binary_iou",
    "difference_image",
    "error_bands",
    "qualitative_figure",
    "table_csv",
    "table_markdown",
]
