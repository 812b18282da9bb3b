"""Table II (throughput and RMS errors per strategy) and Figs 3-6 of the ``braga_tbn`` study, from its
result table only."""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

#: Table II of the paper [kB/s]
PAPER_THROUGHPUT = {"noncooperative": 0.0, "centralised": 4.5, "consensus_1": 4.7, "consensus_5": 23.5,
                    "consensus_10": 46.9}


def _rms_over_runs(results: pd.DataFrame, metric: str) -> pd.Series:
    d = results[(results.metric == metric) & (results.time_s == -1.0)]
    return d.groupby("strategy", sort=False)["value"].apply(lambda v: math.sqrt((v ** 2).mean()))


def report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path) -> str:
    """Table II-shaped table (RMS errors + throughput per strategy) and Figs 3-6 from the results table."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    res = results[results.get("task", "braga_tbn") == "braga_tbn"] if "task" in results else results
    res = res[res.strategy != "all"]
    order = [s for s in ["noncooperative", "centralised"] if s in set(res.strategy)]
    order += sorted({s for s in res.strategy if str(s).startswith("consensus_")}, key=lambda s: int(s.split("_")[1]))
    n_runs = res[res.metric == "pos_rms"].groupby("strategy")["episode"].nunique()
    tab = pd.DataFrame(index=order)
    for m in ("pos_rms", "pos_rms_first5s", "mu_rms", "sigma_rms", "pi_rms"):
        tab[m] = _rms_over_runs(res, m)
    thr = res[(res.metric == "throughput_kBps")].groupby("strategy")["value"].mean()
    tab["throughput_kBps"] = thr
    tab["paper_throughput_kBps"] = [PAPER_THROUGHPUT.get(s, float("nan")) for s in order]
    deg = res[res.metric == "degenerate_events"].groupby("strategy")["value"].sum()
    tab["degenerate_events"] = deg
    tab["mc_runs"] = n_runs
    run_level = res[res.time_s == -1.0]
    med = {m: run_level[run_level.metric == m].groupby("strategy")["value"].median()
           for m in ("pos_rms", "mu_rms", "sigma_rms", "pi_rms")}
    for m, v in med.items():
        tab[f"{m}_median"] = v
    has_lost = "lost_track" in set(run_level.metric)  # results of older code have no lost-track metrics
    if has_lost:
        lost = run_level[run_level.metric == "lost_track"].groupby("strategy")["value"].sum()
        tab["lost_track_runs"] = lost
        kept = run_level[run_level.metric == "lost_track"].set_index(["strategy", "episode"])["value"] == 0
        mu = run_level[run_level.metric == "mu_rms"].set_index(["strategy", "episode"])["value"]
        mu_kept = mu[kept.reindex(mu.index).fillna(False).astype(bool)]
        tab["mu_rms_tracking_runs"] = mu_kept.groupby("strategy").apply(lambda v: math.sqrt((v ** 2).mean()))
    tab.index.name = "strategy"
    tab = tab.reset_index()
    tab.to_csv(out_dir / "braga_tbn_table2.csv", index=False)
    md = ["## braga_tbn — Table II (throughput) and RMS errors per strategy", "",
          "RMS over Monte Carlo runs (sqrt of the mean of the per-run mean squares); position and parameter errors "
          "over the steady-state window; throughput = what the network transmits (4-byte floats, 1 kB = "
          "1024 B as in the paper).", "",
          "| strategy | pos RMS [m] | pos RMS first 5 s [m] | mu RMS [m] | sigma RMS [m] | pi RMS | "
          "throughput [kB/s] | paper [kB/s] | degenerate | runs |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for _, r in tab.iterrows():
        md.append(f"| {r.strategy} | {r.pos_rms:.2f} | {r.pos_rms_first5s:.2f} | {r.mu_rms:.3f} | {r.sigma_rms:.3f} | "
                  f"{r.pi_rms:.4f} | {r.throughput_kBps:.2f} | {r.paper_throughput_kBps:.1f} | "
                  f"{int(r.degenerate_events)} | {int(r.mc_runs)} |")
    md += ["", "Per-run medians and lost tracks (a run has lost track when some node's steady-state position RMS "
           "exceeds `task.lost_track_m`):", "",
           "| strategy | median pos RMS [m] | median mu RMS [m] | median sigma RMS [m] | median pi RMS | "
           "lost-track runs | mu RMS without them [m] |", "|---|---|---|---|---|---|---|"]
    for _, r in tab.iterrows():
        lost_s = f"{int(r.lost_track_runs)}" if has_lost else "-"
        kept_s = f"{r.mu_rms_tracking_runs:.3f}" if has_lost and not math.isnan(r.mu_rms_tracking_runs) else "-"
        md.append(f"| {r.strategy} | {r.pos_rms_median:.2f} | {r.mu_rms_median:.3f} | {r.sigma_rms_median:.3f} | "
                  f"{r.pi_rms_median:.4f} | {lost_s} | {kept_s} |")
    if {"centralised", "consensus_10"} <= set(tab.strategy):
        mu_rms = tab.set_index("strategy")["mu_rms"]
        md += ["", f"Acceptance ratio consensus_10 / centralised mu RMS: "
               f"{mu_rms['consensus_10'] / mu_rms['centralised']:.2f}"]
    text = "\n".join(md) + "\n"
    (out_dir / "braga_tbn_table2.md").write_text(text)

    ts = res[res.time_s >= 0]
    if ts.empty:
        return text

    def rms_t(metric):
        d = ts[ts.metric == metric].groupby(["strategy", "time_s"])["value"].mean()
        return d.apply(math.sqrt)

    # Fig. 3: position RMS vs time (+ zoom)
    pos = rms_t("pos_se_t")
    fig, axs = plt.subplots(2, 1, figsize=(7, 7))
    for s in order:
        d = pos.loc[s]
        axs[0].plot(d.index, d.values, label=s)
        z = d[d.index <= 5.0]
        axs[1].plot(z.index, z.values, label=s)
    axs[0].set(xlabel="time [s]", ylabel="position RMS error [m]", title="Fig. 3 — position RMS error")
    axs[1].set(xlabel="time [s]", ylabel="position RMS error [m]", title="zoom on the first 5 s")
    axs[1].axvline(2.5, color="k", ls=":", lw=0.8)
    axs[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out_dir / "braga_tbn_fig3_position_rms.png", dpi=120)
    plt.close(fig)

    # Fig. 4: parameter estimates, mean and min/max bounds over runs
    k = len([m for m in set(ts.metric) if m.startswith("mu_") and m[3:].isdigit()])
    truth = {}
    fig, axs = plt.subplots(3, len(order), figsize=(3.2 * len(order), 7.5), sharey="row", squeeze=False)
    for ci, s in enumerate(order):
        for ri, base in enumerate(("mu", "sigma", "pi")):
            ax = axs[ri, ci]
            for j in range(1, k + 1):
                name = f"{base}_{j}" if base != "pi" else f"pi_{j}{j}"
                d = ts[(ts.metric == name) & (ts.strategy == s)].groupby("time_s")["value"]
                m, lo, hi = d.mean(), d.min(), d.max()
                ax.plot(m.index, m.values, lw=1)
                ax.fill_between(m.index, lo.values, hi.values, alpha=0.25)
            if ri == 0:
                ax.set_title(s, fontsize=9)
            if ci == 0:
                ax.set_ylabel({"mu": "mu [m]", "sigma": "sigma [m]", "pi": "pi_kk"}[base])
            if ri == 2:
                ax.set_xlabel("time [s]")
    fig.suptitle("Fig. 4 — parameter estimates (node average; lines: mean over runs, shaded: min/max)")
    fig.tight_layout()
    fig.savefig(out_dir / "braga_tbn_fig4_parameters.png", dpi=110)
    plt.close(fig)

    for fname, metric, ylabel, title in (
            ("braga_tbn_fig5_mu_rms.png", "mu_se_t", "noise mean RMS error [m]", "Fig. 5 — noise mean RMS error"),
            ("braga_tbn_fig6_sigma_rms.png", "sigma_se_t", "noise std RMS error [m]", "Fig. 6 — noise std RMS error")):
        d = rms_t(metric)
        fig, ax = plt.subplots(figsize=(7, 4))
        for s in order:
            ax.semilogy(d.loc[s].index, d.loc[s].values, label=s)
        ax.set(xlabel="time [s]", ylabel=ylabel, title=title)
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out_dir / fname, dpi=120)
        plt.close(fig)
    text += "\nFigures: braga_tbn_fig3_position_rms.png, braga_tbn_fig4_parameters.png, braga_tbn_fig5_mu_rms.png, " \
            "braga_tbn_fig6_sigma_rms.png\n"
    return text
