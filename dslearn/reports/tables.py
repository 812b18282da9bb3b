"""Formatting shared by the reports: Markdown tables, the sensor-average label."""

from __future__ import annotations

import pandas as pd

#: the row label of the average over the sensing nodes
AVG_LABEL = "sensor average"


def markdown(df: pd.DataFrame) -> str:
    """DataFrame -> GitHub Markdown table (no extra dependency)."""
    cols = [str(c) for c in df.columns]
    lines = ["| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for row in df.itertuples(index=False):
        lines.append("| " + " | ".join(str(v) for v in row) + " |")
    return "\n".join(lines)
