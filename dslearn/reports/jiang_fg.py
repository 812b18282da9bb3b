"""Paper-shaped tables and figures of the ``jiang_fg`` study (Figs. 2-5 and diagnostics), from its
result table only."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from dslearn.schemas.jiang_fg import MAIN_VARIANT as MAIN


def _pooled(df: pd.DataFrame, keys: list[str]) -> pd.DataFrame:
    """Monte Carlo RMSE ``sqrt(mean over episodes of rmse^2)`` per key combination."""
    return df.assign(sq=df["value"].astype(float) ** 2).groupby(keys, dropna=False)["sq"].mean().pow(0.5).rename("rmse")


def _fmt(x: float) -> str:
    return "nan" if not np.isfinite(x) else (f"{x:.3g}" if abs(x) < 1e4 else f"{x:.2e}")


def _md(table: pd.DataFrame, index_name: str) -> str:
    cols = [str(c) for c in table.columns]
    lines = ["| " + index_name + " | " + " | ".join(cols) + " |", "|" + "---|" * (len(cols) + 1)]
    for idx, row in table.iterrows():
        lines.append(f"| {idx} | " + " | ".join(_fmt(float(v)) for v in row.values) + " |")
    return "\n".join(lines)


def report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path) -> str:
    """Paper-shaped tables (``.md``/``.csv``) and figures (``.png``) for Figs. 2-5 from ``results``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    r = results[results["task"] == "jiang_fg"] if "task" in results else results
    rm = r[r["metric"] == "rmse"]
    md = ["## jiang_fg: factor-graph identification and EKF-FG tracking (Jiang et al., ISITA 2022)", "",
          "RMSE per parameter, pooled over Monte Carlo runs as sqrt(mean square); CRLB = sqrt(tr F^-1 / M) "
          "at the true state (Eq. 27).", ""]

    # Fig. 2
    f2 = rm[rm["figure"] == "fig2"]
    f2 = f2.assign(series=f2["model"] + np.where(f2["variant"] == MAIN, "", "[" + f2["variant"] + "]"))
    t_main = int(f2.loc[f2["variant"] == MAIN, "iteration"].max())
    tab2 = _pooled(f2[(f2["iteration"] >= 0) & (f2["iteration"] <= t_main)], ["iteration", "series"]).unstack("series")
    refs = _pooled(f2[f2["iteration"] < 0], ["series"])
    tab2.to_csv(out_dir / "jiang_fg_fig2.csv")
    fig, ax = plt.subplots(figsize=(9, 4.5))
    colors = plt.get_cmap("tab20").colors
    for i, col in enumerate(tab2.columns):
        y = tab2[col].dropna()
        tracker = str(col).startswith("ekf_fg")
        ax.semilogy(y.index, y.values, ls=("--" if tracker else "-") if len(y) > 1 else "none",
                    marker="s" if tracker else "o", ms=4, color=colors[i % len(colors)], label=col)
    for name, v in refs.items():
        ax.axhline(v, ls=":" if name == "crlb" else "--", lw=1, color="k" if name == "crlb" else "gray", label=name)
    ax.set_xlabel("FG iterations"); ax.set_ylabel("RMSE"); ax.set_title("Fig. 2: convergence")
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5)); fig.tight_layout()
    fig.savefig(out_dir / "jiang_fg_fig2.png", dpi=120); plt.close(fig)
    md += ["### Fig. 2: RMSE vs FG iterations (t = 0 is the initial guess)", "", _md(tab2, "iteration"), "",
           "Reference (all timings): " + ", ".join(f"{k} = {_fmt(v)}" for k, v in refs.items()), ""]
    # variants (ablations) at their own final iteration count
    fin = f2[f2["model"].isin(["fg_identification", "ekf_fg"])]
    last = fin.groupby(["variant", "model"])["iteration"].transform("max")
    tabv = _pooled(fin[fin["iteration"] == last], ["variant", "model"]).unstack("model")
    tabv["iterations"] = fin[fin["model"] == "ekf_fg"].groupby("variant")["iteration"].max()
    tabv.to_csv(out_dir / "jiang_fg_variants.csv")
    md += ["### Variants: RMSE at the final iteration (same data)", "", _md(tabv, "variant"), ""]

    # Fig. 3
    f3 = r[(r["figure"] == "fig3") & (r["metric"] == "estimate") & (r["episode"] == r["episode"].min())]
    if len(f3):
        params = sorted(f3["param"].unique())
        fig, axes = plt.subplots(1, len(params), figsize=(5 * len(params), 4))
        axes = np.atleast_1d(axes)
        for ax, prm in zip(axes, params):
            for model, g in f3[f3["param"] == prm].groupby("model"):
                g = g.sort_values("timing")
                ax.plot(g["timing"], g["value"], "k-" if model == "truth" else "--", marker=None if model == "truth"
                        else ".", label=model, lw=1)
            ax.set_xlabel("timing k"); ax.set_ylabel(prm); ax.legend(fontsize=7)
        fig.suptitle("Fig. 3: estimates vs truth (episode 0)"); fig.tight_layout()
        fig.savefig(out_dir / "jiang_fg_fig3.png", dpi=120); plt.close(fig)
        wide = f3.pivot_table(index=["param", "timing"], columns="model", values="value")
        wide.to_csv(out_dir / "jiang_fg_fig3.csv")
        dev = r[(r["figure"] == "fig3") & (r["metric"] == "estimate")].pivot_table(
            index=["episode", "param", "timing"], columns="model", values="value")
        gaps = {m: float((dev[m] - dev["truth"]).abs().max()) for m in dev.columns if m != "truth"}
        md += ["### Fig. 3: tracking vs truth", "", "Max |estimate - truth| over the stored episodes: "
               + ", ".join(f"{k} = {_fmt(v)}" for k, v in gaps.items()), ""]

    # Fig. 4
    f4 = rm[(rm["figure"] == "fig4") & (rm["variant"] == MAIN)]
    tab4 = _pooled(f4, ["timing", "model"]).unstack("model")
    tab4.to_csv(out_dir / "jiang_fg_fig4.csv")
    fig, ax = plt.subplots(figsize=(6, 4))
    for col in tab4.columns:
        ax.semilogy(tab4.index, tab4[col], label=col, ls=":" if col == "crlb" else "-")
    ax.set_xlabel("timing index k"); ax.set_ylabel("RMSE"); ax.set_title("Fig. 4: RMSE vs timing")
    ax.legend(fontsize=7); fig.tight_layout(); fig.savefig(out_dir / "jiang_fg_fig4.png", dpi=120); plt.close(fig)
    sel = [k for k in (1, 2, 3, 5, 10, 20, 30, 40, 50) if k in tab4.index]
    md += ["### Fig. 4: RMSE vs timing index (selected k; full table in jiang_fg_fig4.csv)", "",
           _md(tab4.loc[sel], "k"), "", "Average over k: " + ", ".join(
               f"{c} = {_fmt(v)}" for c, v in _pooled(f4.assign(timing=0), ["model"]).items()), ""]

    # Fig. 5
    f5 = rm[(rm["figure"] == "fig5") & (rm["variant"] == MAIN)]
    tab5 = _pooled(f5, ["sigma_y", "model"]).unstack("model")
    tab5.to_csv(out_dir / "jiang_fg_fig5.csv")
    fig, ax = plt.subplots(figsize=(6, 4))
    for col in tab5.columns:
        ax.loglog(tab5.index, tab5[col], marker="o", label=col, ls=":" if col == "crlb" else "-")
    ax.set_xlabel("sigma_y"); ax.set_ylabel("average RMSE"); ax.set_title("Fig. 5: RMSE vs sigma_y")
    ax.legend(fontsize=7); fig.tight_layout(); fig.savefig(out_dir / "jiang_fg_fig5.png", dpi=120); plt.close(fig)
    md += ["### Fig. 5: average RMSE vs sigma_y", "", _md(tab5, "sigma_y"), ""]

    # diagnostics
    dg = r[r["figure"] == "diag"]
    dg = dg[dg["metric"] != "runtime_s"]
    if len(dg):
        tabd = dg.groupby(["sigma_y", "iteration", "metric"])["value"].mean().unstack("metric")
        tabd.to_csv(out_dir / "jiang_fg_diagnostics.csv")
        tabd.index = [f"sigma_y={s:g}, T={t}" for s, t in tabd.index]
        md += ["### Diagnostics (mean per episode)", "", _md(tabd, "config"), ""]
    rt = r[r["metric"] == "runtime_s"]["value"]
    if len(rt):
        md += [f"Run time: {float(rt.max()):.1f} s per run."]
    text = "\n".join(md) + "\n"
    (out_dir / "jiang_fg.md").write_text(text)
    return text
