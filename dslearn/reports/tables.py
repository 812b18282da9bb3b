"""Formatting shared by the reports: Markdown tables, figure files, the sensor-average label."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

#: the row label of the average over the sensing nodes
AVG_LABEL = "sensor average"


#: significant digits of the numbers in the tables
DIGITS = 3


def sig(value: float, digits: int = DIGITS) -> str:
    """``value`` with ``digits`` significant digits, trailing zeros kept (``0.0750``, ``1.20``, ``123``,
    ``1230`` for 1234.5), scientific below 0.001 and from 100 000 on (``1.23e-04``); ``-`` for a missing
    value (NaN, None)."""
    import math

    if value is None:
        return "-"
    v = float(value)
    if math.isnan(v):
        return "-"
    if math.isinf(v) or v == 0:
        return str(v) if math.isinf(v) else "0"
    r = float(f"{v:.{digits - 1}e}")  # rounded first: 0.9996 -> 1.00, not 1.000
    e = math.floor(math.log10(abs(r)))
    if e < -3 or e >= 5:
        return f"{v:.{digits - 1}e}"
    return f"{r:.{max(0, digits - 1 - e)}f}"


def mean_std(mean: float, std: float, digits: int = DIGITS) -> str:
    """A table cell ``mean ± std``, each with ``digits`` significant digits (:func:`sig`)."""
    return f"{sig(mean, digits)} ± {sig(std, digits)}"


def save_figure(fig, path: Path, dpi: int = 120) -> Path:
    """Lay out ``fig``, write it to ``path`` (creating its folder) and close it; return ``path``."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def markdown(df: pd.DataFrame) -> str:
    """DataFrame -> GitHub Markdown table (no extra dependency)."""
    cols = [str(c) for c in df.columns]
    lines = ["| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for row in df.itertuples(index=False):
        lines.append("| " + " | ".join(str(v) for v in row) + " |")
    return "\n".join(lines)


def write_table(out_dir: Path, name: str, title: str, tab: pd.DataFrame) -> str:
    """Write ``tab`` as ``<name>.csv`` and, under a ``### title`` heading, ``<name>.md`` (atomically);
    return the Markdown."""
    from dslearn.io import atomic_write_csv, atomic_write_text

    md = f"### {title}\n\n{markdown(tab)}"
    atomic_write_csv(tab, Path(out_dir) / f"{name}.csv")
    atomic_write_text(Path(out_dir) / f"{name}.md", md + "\n")
    return md
