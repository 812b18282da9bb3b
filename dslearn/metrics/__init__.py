r"""Metrics: the only code that sees the ground truth next to what the methods estimated, and the one
writer of tidy result rows (:mod:`.rows`). A module per kind of comparison: :mod:`.tracking` (the
distributed filters' beliefs: tracking error, RMSE, NEES, prediction error)."""

from dslearn.metrics.rows import metric_rows, rows
from dslearn.metrics.tracking import prediction_error, tracking_metrics

__all__ = ["metric_rows", "prediction_error", "rows", "tracking_metrics"]
