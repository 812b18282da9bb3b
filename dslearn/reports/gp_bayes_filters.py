"""The table of the ``gp_bayes_filters`` study (Deisenroth et al., ICML 2009, Sec. 5.1), from its result
table only: per filter the mean and standard error over the cases of ``nll_x``, ``maha_x``, ``rmse_x``,
``nll_z`` (and the median, which a few degenerate cases of a particle filter cannot move). Rows of the network
version (a ``sensor`` column, ``task.nodes > 1``) get their own table (:func:`network_table`): per filter and
fusion, each case's metric averaged over the sensors, then mean and standard error over the cases."""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from dslearn.fusion.strategies import FUSIONS
from dslearn.studies.gp_bayes_filters import FILTERS, LABELS, METRICS

#: the columns that name a network configuration (rows of ``task.nodes > 1``)
NETWORK_COLS = ("consensus", "graph", "rounds", "weights", "omega")

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


def _is_network(results: pd.DataFrame) -> pd.Series:
    """Which rows are of the network version (``sensor`` set); none of a single-node run."""
    if "sensor" not in results.columns:
        return pd.Series(False, index=results.index)
    return results["sensor"].notna()


def _network_rows(results: pd.DataFrame) -> pd.DataFrame:
    return results[_is_network(results)]


def _label(v) -> str:
    """A configuration cell: a whole number without its ``.0`` (a column a gathered table made float)."""
    return str(int(v)) if isinstance(v, float) and v.is_integer() else str(v)


def network_table(results: pd.DataFrame) -> pd.DataFrame:
    """Rows: (filter, fusion configuration), filters in :data:`FILTERS` order, fusions in
    :data:`~dslearn.fusion.strategies.FUSIONS` order; columns ``nodes``, ``<metric>_mean``, ``<metric>_se`` (over the
    cases of each case's sensor average), ``<metric>_median``, ``cases`` and ``slr_clamped`` (cases where the
    regression's effective noise was floored). The sensors of one case see the same truth, so the standard error
    is over the cases, not over sensors x cases."""
    r = _network_rows(results)
    r = r[r["episode"] >= 0]
    conf = [c for c in NETWORK_COLS if c in r.columns]
    keys = ["node", *conf]
    per = r[(r["sensor"] >= 0) & r["metric"].isin(METRICS)]
    case = per.groupby(keys + ["metric", "episode"], sort=False)["value"].mean().reset_index()
    g = case.groupby(keys + ["metric"], sort=False)["value"]
    stats = pd.DataFrame({"mean": g.mean(), "se": g.std(ddof=1) / g.count().pow(0.5), "median": g.median(),
                          "n": g.count()}).reset_index()
    out = per.groupby(keys, sort=False)["sensor"].nunique().rename("nodes").to_frame()
    for m in METRICS:
        s = stats[stats["metric"] == m].set_index(keys)
        for c in ("mean", "se", "median"):
            out[f"{m}_{c}"] = s[c]
    out["cases"] = stats.groupby(keys, sort=False)["n"].max()
    cl = r[r["metric"] == "slr_clamped"].groupby(keys, sort=False)["value"].sum()
    out["slr_clamped"] = cl.reindex(out.index).fillna(0).astype(int)
    rank = {**{f: i for i, f in enumerate(FILTERS)}, **{f: i for i, f in enumerate(FUSIONS)}}
    out = out.reset_index()
    out = out.sort_values(["node", *conf], kind="mergesort",
                          key=lambda col: col.map(rank) if col.name in ("node", "consensus") else col.astype(str))
    return out.rename(columns={"node": "filter"}).reset_index(drop=True)


def _network_markdown(tab: pd.DataFrame) -> list[str]:
    conf = [c for c in NETWORK_COLS if c in tab.columns]
    n = int(tab["cases"].max()) if len(tab) else 0
    md = ["## gp_bayes_filters on a network: each node's posterior after the fusion", "",
          f"Every node measures the same state; one predict + update step from {n} priors; per case the metric is "
          "averaged over the nodes, then mean ± standard error over the cases (median in brackets). "
          "`clamped`: cases where the regression's effective noise was floored.", "",
          "| filter | nodes | " + " | ".join(conf) + " | " + " | ".join(HEADS[m] for m in METRICS) + " | clamped |",
          "|---|---|" + "---|" * len(conf) + "---|" * len(METRICS) + "---|"]
    for _, row in tab.iterrows():
        cells = ([str(int(row["nodes"]))] + [_label(row[c]) for c in conf]
                 + [f"{_fmt(row[f'{m}_mean'])} ± {_fmt(row[f'{m}_se'])} ({_fmt(row[f'{m}_median'])})" for m in METRICS]
                 + [str(int(row["slr_clamped"]))])
        md.append(f"| {LABELS.get(row['filter'], row['filter'])} | " + " | ".join(cells) + " |")
    return md


def report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path) -> str:
    """``gp_bayes_filters.md``: the table of :func:`table` (``gp_bayes_filters.csv``) for single-node rows, that of
    :func:`network_table` (``gp_bayes_filters_network.csv``) for network rows, and the trained hyperparameters."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    res = results[results["task"] == "gp_bayes_filters"] if "task" in results else results
    is_net = _is_network(res)
    net, single = res[is_net], res[~is_net & res["node"].isin(FILTERS)]
    md = []
    if len(single):
        tab = table(single)
        tab.to_csv(out_dir / "gp_bayes_filters.csv")
        n = int(tab["cases"].max()) if len(tab) else 0
        md += ["## gp_bayes_filters: GP-Bayes filters on the scalar benchmark (Deisenroth et al., ICML 2009)", "",
               f"One predict + update step from {n} priors; mean ± standard error over the cases (median in brackets).",
               "", "| filter | " + " | ".join(HEADS[m] for m in METRICS) + " |", "|---|" + "---|" * len(METRICS)]
        for f, row in tab.iterrows():
            cells = [f"{_fmt(row[f'{m}_mean'])} ± {_fmt(row[f'{m}_se'])} ({_fmt(row[f'{m}_median'])})" for m in METRICS]
            md.append(f"| {LABELS.get(f, f)} | " + " | ".join(cells) + " |")
    if len(net[net["node"].isin(FILTERS)]):
        ntab = network_table(net)
        ntab.to_csv(out_dir / "gp_bayes_filters_network.csv", index=False)
        md += ([""] if md else []) + _network_markdown(ntab)
    hyp = res[(res["episode"] < 0) & ~res["node"].isin(FILTERS)].drop_duplicates(["node", "metric"])
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
