"""The table of the ``gp_bayes_filters`` study (Deisenroth et al., ICML 2009, Sec. 5.1), from its result
table only: per filter the mean and standard error over the cases of ``nll_x``, ``maha_x``, ``rmse_x``,
``nll_z`` (and the median, which a few degenerate cases of a particle filter cannot move)."""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from dslearn.studies.gp_bayes_filters import FILTERS, LABELS, METRICS

HEADS = {"nll_x": "NLL_x", "maha_x": "Maha_x", "rmse_x": "RMSE_x", "nll_z": "NLL_z"}


def _fmt(x: float) -> str:
    if not math.isfinite(x):
        return str(x)
    return f"{x:.3g}" if abs(x) < 1e4 else f"{x:.2e}"


def table(results: pd.DataFrame) -> pd.DataFrame:
    """Rows: filters (in :data:`FILTERS` order); columns ``<metric>_mean``, ``<metric>_se`` (standard error
    ``std / sqrt(n)``), ``<metric>_median`` and ``cases``."""
    r = results[(results["episode"] >= 0) & results["metric"].isin(METRICS)]
    g = r.groupby(["node", "metric"])["value"]
    stats = pd.DataFrame({"mean": g.mean(), "se": g.std(ddof=1) / g.count().pow(0.5), "median": g.median(),
                          "n": g.count()}).reset_index()
    order = [f for f in FILTERS if f in set(stats["node"])]
    out = pd.DataFrame(index=order)
    for m in METRICS:
        s = stats[stats["metric"] == m].set_index("node")
        for c in ("mean", "se", "median"):
            out[f"{m}_{c}"] = s[c]
    out["cases"] = stats.groupby("node")["n"].max()
    out.index.name = "filter"
    return out


def report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path) -> str:
    """``gp_bayes_filters.md`` / ``.csv``: the table of :func:`table`, and the trained hyperparameters."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    res = results[results["task"] == "gp_bayes_filters"] if "task" in results else results
    tab = table(res)
    tab.to_csv(out_dir / "gp_bayes_filters.csv")
    n = int(tab["cases"].max()) if len(tab) else 0
    md = ["## gp_bayes_filters: GP-Bayes filters on the scalar benchmark (Deisenroth et al., ICML 2009)", "",
          f"One predict + update step from {n} priors; mean ± standard error over the cases (median in brackets).",
          "", "| filter | " + " | ".join(HEADS[m] for m in METRICS) + " |", "|---|" + "---|" * len(METRICS)]
    for f, row in tab.iterrows():
        cells = [f"{_fmt(row[f'{m}_mean'])} ± {_fmt(row[f'{m}_se'])} ({_fmt(row[f'{m}_median'])})" for m in METRICS]
        md.append(f"| {LABELS.get(f, f)} | " + " | ".join(cells) + " |")
    hyp = res[res["episode"] < 0]
    if len(hyp):
        md += ["", "Trained GPs (GPyTorch, exact marginal likelihood):", "",
               "| GP | lengthscale | signal variance | noise variance |", "|---|---|---|---|"]
        for node, h in hyp.groupby("node", sort=False):
            v = h.set_index("metric")["value"]
            md.append(f"| {node} | {_fmt(v.get('lengthscale', math.nan))} | {_fmt(v.get('signal_var', math.nan))} | "
                      f"{_fmt(v.get('noise_var', math.nan))} |")
    text = "\n".join(md) + "\n"
    (out_dir / "gp_bayes_filters.md").write_text(text)
    return text
