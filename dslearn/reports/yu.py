"""Tables and figures of the Yu study, drawn from result tables only.

Cells are mean ± std over test episodes; the ``sensor average`` row (node ``avg`` in
``summary.csv``) is the papers' Average row: the mean over sensing nodes of their means and of
their standard deviations."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

from dslearn.reports.tables import save_figure  # noqa: E402


MODEL_ORDER = ["gp", "gp_increment", "lin", "sfm"]


def _cell(mean: float, std: float) -> str:
    return f"{mean:.3f} ± {std:.3f}" if mean < 0.1 else f"{mean:.2f} ± {std:.2f}"


def _final(summary: pd.DataFrame) -> pd.DataFrame:
    """Rows evaluated after all training episodes, sensing nodes and the average only."""
    s = summary
    if "train_seen" in s.columns and "train_episodes" in s.columns:
        s = s[s["train_seen"].astype(int) == s["train_episodes"].astype(int)]
    if "node_kind" in s.columns:
        s = s[s["node_kind"].isin(["sensor", "avg"])]
    return s


def _fusion_label(row) -> str:
    c = row["consensus"]
    om = row.get("omega", "-")
    if om not in ("-", None) and c in ("hybrid", "cm"):
        c = f"{c} (ω={'1' if om == 'one' else 'S' if om == 'nodes' else om})"
    it = row.get("iterations", None)
    if c.startswith(("hybrid", "cm", "ci", "ce")) and it not in (None, "-"):
        c = f"{c}, L={it}"
    return c


def _models(s):
    present = list(s["model"].unique())
    return [m for m in MODEL_ORDER if m in present] + [m for m in present if m not in MODEL_ORDER]


def _nodes(s):
    nodes = list(dict.fromkeys(s["node"]))
    return [n for n in nodes if n != "avg"] + (["avg"] if "avg" in nodes else [])


def _label_avg(tab: pd.DataFrame) -> pd.DataFrame:
    """The ``avg`` node shown as "sensor average" (the papers' Average row), after the nodes."""
    from dslearn.reports.tables import AVG_LABEL

    if "node" in tab.columns:
        tab["node"] = tab["node"].map(lambda n: AVG_LABEL if n == "avg" else n)
    return tab


def table_tracking(summary: pd.DataFrame, metric: str = "track_err") -> pd.DataFrame:
    """Table I shape: rows (fusion, node), columns model, cells mean ± std."""
    s = _final(summary)
    s = s[s["metric"] == metric].copy()
    if s.empty:
        return pd.DataFrame()
    s["fusion"] = s.apply(_fusion_label, axis=1)
    s["cell"] = [_cell(m, d) for m, d in zip(s["mean"], s["std"].fillna(0))]
    tab = s.pivot_table(index=["fusion", "node"], columns="model", values="cell", aggfunc="first")
    tab = tab.reindex(columns=_models(s))
    order = [(f, n) for f in dict.fromkeys(s["fusion"]) for n in _nodes(s) if (f, n) in tab.index]
    return _label_avg(tab.reindex(order).reset_index())


def table_prediction(summary: pd.DataFrame) -> pd.DataFrame:
    """Table II shape: rows node, columns GP (ind.) / GP (con.) per GP variant, LIN, SFM."""
    s = _final(summary)
    s = s[s["metric"] == "pred_err"].copy()
    if s.empty:
        return pd.DataFrame()
    s["fusion"] = s.apply(_fusion_label, axis=1)
    cols = {}
    for (model, fusion), g in s.groupby(["model", "fusion"], sort=False):
        if model.startswith("gp"):
            tag = "ind." if fusion == "individual" else f"con., {fusion}"
            label = f"{model} ({tag})"
        else:
            if fusion != "individual" and any(s[(s["model"] == model)]["consensus"] == "individual"):
                continue  # parametric models do not learn: one column is enough
            label = model
        cols[label] = g.set_index("node").apply(lambda r: _cell(r["mean"], r["std"] if r["std"] == r["std"] else 0), axis=1)
    tab = pd.DataFrame(cols).reindex(_nodes(s))
    return _label_avg(tab.reset_index().rename(columns={"index": "node"}))


def fig_training(summary: pd.DataFrame, out: Path) -> Path | None:
    """Fig. 2 shape: average tracking error vs training episodes, one line per model and L."""
    s = summary[(summary["metric"] == "track_err") & (summary["node"] == "avg")].copy()
    if "train_seen" not in s.columns or s["train_seen"].nunique() < 2:
        return None
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for (model, it), g in s.groupby(["model", "iterations"]):
        g = g.sort_values("train_seen")
        axes[0].errorbar(g["train_seen"], g["mean"], yerr=g["std"], capsize=2, marker="o", label=f"{model}, L={it}")
    axes[0].set_xlabel("training episodes")
    axes[0].set_ylabel("tracking error [m] (sensor average)")
    axes[0].legend(fontsize=7)
    last = s[s["train_seen"] == s["train_seen"].max()]
    for model, g in last.groupby("model"):
        g = g.sort_values("iterations")
        axes[1].errorbar(g["iterations"].astype(int), g["mean"], yerr=g["std"], capsize=2, marker="o", label=model)
    axes[1].set_xlabel("consensus iterations L")
    axes[1].set_ylabel(f"tracking error [m] after {int(s['train_seen'].max())} episodes")
    axes[1].legend(fontsize=7)
    return save_figure(fig, out / "yu_fig2.png")


def yu_report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path) -> str:
    from dslearn.reports.tables import write_table

    out_dir = Path(out_dir)
    parts = []
    for name, title, tab in (
        ("yu_table1", "Tracking error [m] (Table I shape; paper's formula, mean position error)", table_tracking(summary)),
        ("yu_table1_rmse", "Tracking RMSE [m]", table_tracking(summary, "track_rmse")),
        ("yu_table2", "Prediction error [m] from the true state at t=0 (Table II shape)", table_prediction(summary)),
        ("yu_nees", "NEES/Dx, averaged over time (1 = consistent)", table_tracking(summary, "nees")),
    ):
        if not tab.empty:
            parts.append(write_table(out_dir, name, title, tab))
    fig = fig_training(summary, out_dir)
    if fig is not None:
        parts.append(f"Figure: {fig.name}")
    return "\n\n".join(parts)


def report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path) -> str:
    """Tables I-II and Fig. 2 of Yu et al. (``task=yu``), from the result table."""
    return yu_report(results, summary, out_dir)
