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

from dslearn.io import TRACKS_FILE  # noqa: E402
from dslearn.reports.tables import AVG_LABEL, mean_std, save_figure, sig  # noqa: E402


MODEL_ORDER = ["gp", "gp_increment", "lin", "sfm"]


def _cell(mean: float, std: float) -> str:
    return mean_std(mean, std)


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


#: the tracking figure of a single run (drawn from its ``tracks.npz``)
TRACKING_FIG = "tracking.png"


def default_nodes(names, sensing) -> list[int]:
    """The nodes a tracking figure shows: the first sensing node and the first relay (a node that does
    not sense), where there is one."""
    sensing = [bool(v) for v in sensing]
    picks = [sensing.index(True)] if True in sensing else [0]
    if False in sensing:
        picks.append(sensing.index(False))
    return picks


def fig_tracking(tracks: Path, out: Path, nodes: list[str] | None = None) -> Path:
    """``tracking.png`` of one run from its ``tracks.npz`` (:func:`dslearn.metrics.trajectories.track_record`),
    three panels:

    1. the sensor network (sensing nodes ▲ with their sensing ranges, relays ■, communication links) with
       the true tracks of test episode 0 and the tracks the chosen ``nodes`` estimated (default: the first
       sensing node and the first relay), with 95 % position ellipses at a few steps;
    2. the position error over time (mean over the test episodes) of those nodes and the sensor average;
    3. the position NEES over its degrees of freedom over time (mean over the test episodes) with the
       chi-square 95 % band of a consistent filter for that many episodes.
    """
    import numpy as np
    from matplotlib.patches import Circle, Ellipse

    z = np.load(tracks)
    names = [str(n) for n in z["nodes"]]
    sensing = z["sensing"].astype(bool)
    if nodes is None:
        picks = default_nodes(names, sensing)
    else:
        unknown = [n for n in nodes if n not in names]
        if unknown:
            raise ValueError(f"fig_tracking: nodes {unknown} are not in {tracks} (its nodes: {names})")
        picks = [names.index(n) for n in nodes]
    unit = str(z["units"]) if "units" in z.files else "m"
    episodes = int(z["episodes"])
    colours = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b"]
    fig, axes = plt.subplots(1, 3, figsize=(16, 5.2), gridspec_kw={"width_ratios": [1.25, 1, 1]})

    ax = axes[0]
    extent = [z["truth"].reshape(-1, 2)]
    if "positions" in z.files:
        pos, is_sensor, adj = z["positions"], z["is_sensor"].astype(bool), z["adjacency"].astype(bool)
        extent.append(pos)
        for e, (i, j) in enumerate(zip(*np.nonzero(np.triu(adj, 1)))):
            ax.plot(pos[[i, j], 0], pos[[i, j], 1], color="0.75", lw=0.8, zorder=1,
                    label="communication link" if e == 0 else None)
        for c, i in enumerate(np.nonzero(is_sensor)[0]):
            ax.add_patch(Circle(pos[i], float(z["sensing_range"]), fill=True, fc="#ffd70014", ec="#b8860b",
                                ls="--", lw=0.7, zorder=0, label="sensing range" if c == 0 else None))
        ax.scatter(*pos[is_sensor].T, marker="^", s=70, c="#b8860b", ec="k", zorder=4, label="sensing node")
        if (~is_sensor).any():
            ax.scatter(*pos[~is_sensor].T, marker="s", s=45, c="0.55", ec="k", zorder=4, label="relay (no sensing)")
        for i, n in enumerate(names[: len(pos)]):
            ax.annotate(n, pos[i], textcoords="offset points", xytext=(4, 4), fontsize=6.5, color="0.25", zorder=5)
    truth = z["truth"]  # (K+1, A, 2)
    for a in range(truth.shape[1]):
        ax.plot(truth[:, a, 0], truth[:, a, 1], "k-", lw=1.8, zorder=3, label="true track" if a == 0 else None)
        ax.plot(*truth[0, a], "ko", ms=5, zorder=3)
        ax.plot(*truth[-1, a], "k>", ms=5, zorder=3)
        ax.annotate(f"target {a + 1}", truth[0, a], textcoords="offset points", xytext=(-10, 6), fontsize=7)
    k1 = truth.shape[0]
    every = max(1, (k1 - 1) // 4)
    scale = float(np.sqrt(-2.0 * np.log(0.05)))  # 95 % of a 2-d Gaussian
    for c, i in enumerate(picks):
        col = colours[c % len(colours)]
        m = z["mean"][i]  # (K+1, A, 2); step 0 is the prior belief: drawn from step 1
        for a in range(m.shape[1]):
            ax.plot(m[1:, a, 0], m[1:, a, 1], "--", color=col, lw=1.3, marker=".", ms=4, zorder=3,
                    label=f"estimate of {names[i]}" if a == 0 else None)
            if "cov" in z.files:
                for t in range(1, k1, every):
                    w, v = np.linalg.eigh(z["cov"][i, t, a])
                    ang = float(np.degrees(np.arctan2(v[1, -1], v[0, -1])))
                    ax.add_patch(Ellipse(m[t, a], 2 * scale * np.sqrt(max(w[-1], 0)), 2 * scale * np.sqrt(max(w[0], 0)),
                                         angle=ang, fill=False, ec=col, lw=0.6, alpha=0.7, zorder=2))
    pts = np.concatenate(extent)
    pad = 0.08 * max(float(np.ptp(pts[:, 0])), float(np.ptp(pts[:, 1])), 1e-9)
    ax.set_xlim(pts[:, 0].min() - pad, pts[:, 0].max() + pad)
    ax.set_ylim(pts[:, 1].min() - pad, pts[:, 1].max() + pad)
    ax.set_aspect("equal")
    ax.set_xlabel(f"x [{unit}]")
    ax.set_ylabel(f"y [{unit}]")
    ax.set_title(f"sensor network and tracks (test episode {int(z['episode'])})", fontsize=10)
    ax.legend(fontsize=6.5, loc="best", framealpha=0.85)

    t = z["time"]
    for ax, key, title, ylabel in (
        (axes[1], "pos_err", f"position error (mean over {episodes} test episodes)", f"position error [{unit}]"),
        (axes[2], "nees_pos", f"position NEES / {int(z['nees_dof'])} (mean over {episodes} test episodes)",
         f"position NEES / 2A (2A = {int(z['nees_dof'])}) [1]"),
    ):
        ax.set_xlabel("time [s]")
        ax.set_ylabel(ylabel)
        ax.set_title(title, fontsize=10)
        if key not in z.files:
            ax.text(0.5, 0.5, "no covariances: NEES not defined", ha="center", transform=ax.transAxes)
            continue
        series = z[key]
        for c, i in enumerate(picks):
            ax.plot(t, series[i], "-", marker=".", color=colours[c % len(colours)], label=names[i])
        if sensing.any():
            ax.plot(t, series[sensing].mean(0), "k--", lw=1.2, label=f"{AVG_LABEL} ({int(sensing.sum())} nodes)")
        if key == "nees_pos" and "nees_band" in z.files:
            lo, hi = (float(v) for v in z["nees_band"])
            ax.axhspan(lo, hi, color="#2ca02c", alpha=0.15,
                       label=f"95 % band, consistent filter [{sig(lo)}, {sig(hi)}]")
            ax.axhline(1.0, color="#2ca02c", lw=0.8)
            vals = np.concatenate([series[picks].ravel(), [lo, hi]])
            vals = vals[vals > 0]
            if len(vals) and vals.max() / vals.min() > 100:
                ax.set_yscale("log")
        else:
            ax.set_ylim(bottom=0)
        ax.legend(fontsize=7)
    labels = ", ".join(f"{k}={z[k]}" for k in ("model", "consensus", "train_seen") if k in z.files)
    if labels:
        fig.suptitle(labels, fontsize=10)
    return save_figure(fig, out / TRACKING_FIG)


def yu_report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path) -> str:
    from dslearn.reports.tables import write_table

    out_dir = Path(out_dir)
    parts = []
    for name, title, tab in (
        ("yu_table1", "Tracking error [m] (Table I shape; paper's formula, mean position error)", table_tracking(summary)),
        ("yu_table1_rmse", "Tracking RMSE [m]", table_tracking(summary, "track_rmse")),
        ("yu_table2", "Prediction error [m] from the true state at t=0 (Table II shape)", table_prediction(summary)),
        ("yu_nees", "state NEES/Dx: the NEES of the whole state (every target's position and velocity) over the "
                    "state dimension Dx, averaged over time (1 = consistent; tracking.png plots the position NEES / 2A "
                    "with the 95 % band of a consistent filter)", table_tracking(summary, "nees")),
    ):
        if not tab.empty:
            parts.append(write_table(out_dir, name, title, tab))
    fig = fig_training(summary, out_dir)
    if fig is not None:
        parts.append(f"Figure: {fig.name}")
    if (out_dir / TRACKS_FILE).is_file():  # a single run's folder: the tracking figure from its tracks.npz
        fig = fig_tracking(out_dir / TRACKS_FILE, out_dir)
        parts.insert(0, f"![the sensor network, true and estimated tracks, error and NEES over time]({fig.name})\n\n"
                        f"Figure: {fig.name}: the network and test episode 0's true and estimated tracks (95 % ellipses); "
                        "position error and position NEES over time, mean over the test episodes, with the "
                        "chi-square 95 % band of a consistent filter.")
    return "\n\n".join(parts)


def report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path) -> str:
    """Tables I-II and Fig. 2 of Yu et al. (``task=yu``), from the result table."""
    return yu_report(results, summary, out_dir)
