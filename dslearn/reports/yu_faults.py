r"""Tables and figures of the network-faults study (``task=yu_faults``), from its result table."""

from __future__ import annotations

from pathlib import Path

import pandas as pd


def report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path) -> str:
    """Curves (PNG) and tables (Markdown + CSV) of tracking error vs faults."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dslearn.reports.tables import markdown

    out_dir = Path(out_dir)
    r = results[(results.metric == "track_err") & (results.node == "alive")]
    keys = ["model", "consensus", "axis", "link_fail", "node_fail", "outlier_frac", "gating"]
    g = r.groupby(keys, sort=False)["value"].agg(mean="mean", std="std", n="count").reset_index()
    md = ["## Tracking error under network faults (mean ± std over test episodes, nodes alive at the end)"]

    def axis_rows(axis: str) -> pd.DataFrame:
        # the fault-free setting (p = 0, f = 0) is listed once (link axis) and belongs to both curves
        base = g[(g.axis == "link") & (g.link_fail == 0) & (g.node_fail == 0)]
        sub = g[g.axis == axis]
        return sub if axis == "link" else pd.concat([base, sub], ignore_index=True)

    def table(axis: str, col: str) -> pd.DataFrame:
        sub = axis_rows(axis).copy()
        sub["cell"] = sub["mean"].map("{:.3f}".format) + " ± " + sub["std"].map("{:.3f}".format)
        return sub.pivot_table(index=["model", "consensus"], columns=col, values="cell", aggfunc="first", sort=False)

    # the link axis includes p = 0 (no faults); the node axis too
    for axis, col, title in (("link", "link_fail", "vs link-failure probability p"),
                             ("node", "node_fail", "vs fraction of failed nodes")):
        tab = table(axis, col)
        if len(tab):
            tab.to_csv(out_dir / f"yu_faults_{axis}.csv")
            md.append(f"### {title}\n\n" + markdown(tab.reset_index()))
    other = g[g.axis.isin(["joint", "outliers", "joint+outliers"])].copy()
    if len(other):
        other["cell"] = other["mean"].map("{:.3f}".format) + " ± " + other["std"].map("{:.3f}".format)
        other["setting"] = (
            "p=" + other.link_fail.astype(str) + ", f=" + other.node_fail.astype(str)
            + ", outliers=" + other.outlier_frac.astype(str) + ", gate=" + other.gating
        )
        tab = other.pivot_table(index=["model", "consensus"], columns="setting", values="cell", aggfunc="first", sort=False)
        tab.to_csv(out_dir / "yu_faults_joint.csv")
        md.append("### joint faults and outliers\n\n" + markdown(tab.reset_index()))
    nf = results[results.metric == "nonfinite"]["value"].sum()
    mx = results[(results.metric == "track_err") & (results.node == "alive_max")]
    worst = mx.groupby(["model", "consensus", "axis", "link_fail", "node_fail", "outlier_frac", "gating"], sort=False)["value"].max()
    worst = worst.reset_index().rename(columns={"value": "worst alive-node track_err"})
    worst.to_csv(out_dir / "yu_faults_worst.csv", index=False)
    hyb = worst[(worst.consensus == "hybrid") & (worst.outlier_frac == 0)]
    md.append(
        f"non-finite estimates in the whole grid: {int(nf)}. Worst alive-node tracking error of hybrid consensus "
        f"over every test episode and fault setting without outliers: {hyb['worst alive-node track_err'].max():.3f} m "
        f"(per-setting maxima: yu_faults_worst.csv)."
    )
    text = "\n\n".join(md)
    (out_dir / "yu_faults.md").write_text(text + "\n")
    # figures: one panel per model, one curve per fusion
    models = list(dict.fromkeys(g.model))
    for axis, col, xl in (("link", "link_fail", "link-failure probability p"), ("node", "node_fail", "fraction of failed nodes")):
        sub = axis_rows(axis)
        if (sub.axis == axis).sum() == 0:
            continue
        fig, axs = plt.subplots(1, len(models), figsize=(4.6 * len(models), 3.6), squeeze=False, sharey=True)
        for ax, m in zip(axs[0], models):
            for fu, c in sub[sub.model == m].groupby("consensus", sort=False):
                c = c.sort_values(col)
                ax.errorbar(c[col], c["mean"], yerr=c["std"], marker="o", capsize=3, label=fu)
            ax.set_title(m)
            ax.set_xlabel(xl)
            ax.grid(alpha=0.3)
        axs[0][0].set_ylabel("tracking error [m] (alive nodes)")
        axs[0][-1].legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out_dir / f"yu_faults_{axis}.png", dpi=120)
        plt.close(fig)
    return text
