"""Tables and figures of the ETH/UCY tracking study (``ethucy_tracking``), from result rows only.

* Table III analogue: tracking error per sensor and average, one column per model.
* Table IV analogue: prediction error per sensor and average, one column per model.
* Fig. 4 analogue: predicted trajectories (rows ``pred_x``/``pred_y``) against the truth.
* Fig. 5 analogue: GP vs LSTM prediction error by number of training episodes, mean ± std
  over seeds.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

from dslearn.io import atomic_write_csv, atomic_write_text  # noqa: E402
from dslearn.reports.tables import save_figure  # noqa: E402

ORDER = ["gp", "gp_increment", "gp_cv", "gp_increment_cv", "lin", "sfm", "sfm_fit", "lstm", "social_lstm"]
COLORS = {"truth": "black", "gp": "tab:blue", "gp_increment": "tab:blue", "gp_cv": "tab:cyan",
          "gp_increment_cv": "tab:cyan", "lin": "tab:orange", "sfm": "tab:green", "sfm_fit": "tab:green",
          "lstm": "tab:purple", "social_lstm": "tab:pink"}


def _cell(m: float, s: float) -> str:
    s = 0.0 if s != s else s
    return f"{m:.3f} ± {s:.3f}"


def _models(present) -> list[str]:
    present = list(dict.fromkeys(present))
    return [m for m in ORDER if m in present] + sorted(m for m in present if m not in ORDER)


def _scene_order(df: pd.DataFrame) -> list[str]:
    return list(dict.fromkeys(df["scene"]))


def per_sensor_table(results: pd.DataFrame, metric: str) -> pd.DataFrame:
    """Rows (scene, node = sensors + avg), columns model; cells mean ± std over test episodes.

    ``avg`` is formed as the paper forms its "Average" row: the mean over sensing nodes of
    their means ± the mean over sensing nodes of their standard deviations.
    """
    r = results[(results["metric"] == metric) & (results["node_kind"] == "sensor")]
    if "protocol" in r.columns:
        r = r[r["protocol"] == "tables"]
    if r.empty:
        return pd.DataFrame()
    g = r.groupby(["scene", "model", "node"], sort=False)["value"].agg(["mean", "std"]).reset_index()
    avg = g.groupby(["scene", "model"], sort=False)[["mean", "std"]].mean().reset_index()
    avg["node"] = "avg"
    allr = pd.concat([g, avg], ignore_index=True)
    allr["cell"] = [_cell(m, s) for m, s in zip(allr["mean"], allr["std"])]
    tab = allr.pivot_table(index=["scene", "node"], columns="model", values="cell", aggfunc="first")
    tab = tab.reindex(columns=_models(allr["model"]))
    nodes = [n for n in dict.fromkeys(r["node"])] + ["avg"]
    idx = [(s, n) for s in _scene_order(r) for n in nodes if (s, n) in tab.index]
    return tab.reindex(idx).reset_index().rename_axis(columns=None)


def average_table(results: pd.DataFrame) -> pd.DataFrame:
    """Rows scene (and ``all scenes``), columns ``<metric>: <model>``; sensor averages as the paper
    forms them: mean over sensing nodes (and scenes) of the per-sensor means ± of the per-sensor
    standard deviations over test episodes."""
    r = results[results["metric"].isin(["track_err", "pred_err"]) & (results["node_kind"] == "sensor")]
    if "protocol" in r.columns:
        r = r[r["protocol"] == "tables"]
    if r.empty:
        return pd.DataFrame()
    ep = r.groupby(["scene", "metric", "model", "node"], sort=False)["value"].agg(["mean", "std"]).reset_index()
    alls = ep.assign(scene="all scenes")
    ep = pd.concat([ep, alls], ignore_index=True) if ep["scene"].nunique() > 1 else ep
    g = ep.groupby(["scene", "metric", "model"], sort=False)[["mean", "std"]].mean().reset_index()
    g["cell"] = [_cell(m, s) for m, s in zip(g["mean"], g["std"])]
    g["col"] = g["metric"].map({"track_err": "tracking", "pred_err": "prediction"}) + ": " + g["model"]
    cols = [f"{k}: {m}" for k in ("tracking", "prediction") for m in _models(g["model"]) if f"{k}: {m}" in set(g["col"])]
    tab = g.pivot_table(index="scene", columns="col", values="cell", aggfunc="first").reindex(columns=cols)
    tab = tab.reindex(list(dict.fromkeys(ep["scene"])))
    return tab.reset_index().rename_axis(columns=None)


def info_table(results: pd.DataFrame) -> pd.DataFrame:
    """Per scene: episodes used and the fitted SFM parameters / LSTM final loss."""
    r = results[results["node_kind"] == "param"]
    if "protocol" in r.columns:
        r = r[r["protocol"] == "tables"]
    if r.empty:
        return pd.DataFrame()
    tab = r.pivot_table(index="scene", columns="metric", values="value", aggfunc="mean")
    n = r.groupby("scene")[["train_episodes", "test_episodes"]].first()
    tab = n.join(tab).reindex(_scene_order(r))
    return tab.round(4).reset_index().rename_axis(columns=None)


def data_size_table(results: pd.DataFrame) -> pd.DataFrame:
    """Fig. 5 numbers: rows (source, model), columns train_episodes; mean ± std over seeds of the
    per-seed prediction error (mean over sensors and test episodes)."""
    r = results[(results["metric"] == "pred_err") & (results["node_kind"] == "sensor")]
    if "protocol" not in r.columns:
        return pd.DataFrame()
    r = r[r["protocol"] == "data_size"]
    if r.empty:
        return pd.DataFrame()
    per_seed = r.groupby(["data", "scene", "model", "train_episodes", "seed"], sort=False)["value"].mean().reset_index()
    g = per_seed.groupby(["data", "scene", "model", "train_episodes"], sort=False)["value"].agg(["mean", "std", "count"]).reset_index()
    return g.rename(columns={"count": "seeds"})


def fig_data_size(tab: pd.DataFrame, out: Path) -> Path | None:
    if tab.empty:
        return None
    srcs = list(dict.fromkeys(zip(tab["data"], tab["scene"])))
    fig, axes = plt.subplots(1, len(srcs), figsize=(4.5 * len(srcs), 3.6), squeeze=False)
    for ax, (kind, scene) in zip(axes[0], srcs):
        g = tab[(tab["data"] == kind) & (tab["scene"] == scene)]
        for model in _models(g["model"]):
            h = g[g["model"] == model].sort_values("train_episodes")
            ax.errorbar(h["train_episodes"], h["mean"], yerr=h["std"].fillna(0), capsize=3, marker="o",
                        label=f"{model}" + (" (online, consensus EKF)" if model.startswith("gp") else " (offline, CM-fused)"))
        ax.set_xscale("log", base=2)
        ax.set_xlabel("training episodes")
        ax.set_ylabel("prediction error [m]")
        ax.set_title(f"{kind}: {scene}" if kind == "real" else "synthetic (Yu scenario)")
        ax.legend(fontsize=7)
    return save_figure(fig, Path(out) / "ethucy_fig5_gp_vs_lstm.png")


def fig_trajectories(results: pd.DataFrame, out: Path, max_episodes: int = 3) -> Path | None:
    """Fig. 4 analogue: one panel per (scene, test episode); truth solid, models dashed."""
    r = results[results["metric"].isin(["pred_x", "pred_y"])]
    if r.empty:
        return None
    r = r.pivot_table(index=["scene", "episode", "model", "agent", "step"], columns="metric", values="value").reset_index()
    scenes = list(dict.fromkeys(r["scene"]))
    neps = min(max_episodes, int(r["episode"].max()) + 1)
    fig, axes = plt.subplots(len(scenes), neps, figsize=(3.6 * neps, 3.4 * len(scenes)), squeeze=False)
    for i, scene in enumerate(scenes):
        for j in range(neps):
            ax = axes[i, j]
            e = r[(r["scene"] == scene) & (r["episode"] == j)]
            if e.empty:
                ax.axis("off")
                continue
            models = ["truth"] + [m for m in _models(e["model"]) if m != "truth"]
            for model in models:
                for agent, a in e[e["model"] == model].groupby("agent"):
                    a = a.sort_values("step")
                    color = COLORS.get(model, "tab:blue")
                    ax.plot(a["pred_x"], a["pred_y"], "-" if model == "truth" else "--", color=color,
                            lw=2 if model == "truth" else 1.2, marker="o" if model == "truth" else None, ms=2.5,
                            label=model if agent == e["agent"].min() else None)
                    if model == "truth":
                        ax.plot(a["pred_x"].iloc[0], a["pred_y"].iloc[0], "s", color="black", ms=5)
            ax.set_title(f"{scene}, test episode {j}", fontsize=9)
            ax.set_aspect("equal", adjustable="datalim")
            if i == 0 and j == 0:
                ax.legend(fontsize=7)
    return save_figure(fig, Path(out) / "ethucy_fig4_trajectories.png")


def real_report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path) -> str:
    """Write the tables (``.md`` + ``.csv``) and figures into ``out_dir``; return the Markdown."""
    from dslearn.reports.tables import markdown, write_table

    out_dir = Path(out_dir)
    parts = []
    for name, title, tab in (
        ("ethucy_table3", "Tracking error per sensor (Table III analogue; mean position error, m)", per_sensor_table(results, "track_err")),
        ("ethucy_table4", "Prediction error per sensor (Table IV analogue; roll-out from the true t=0 state, m)", per_sensor_table(results, "pred_err")),
        ("ethucy_averages", "Sensor averages by scene", average_table(results)),
        ("ethucy_info", "Episodes, fitted SFM parameters, LSTM final training loss", info_table(results)),
    ):
        if not tab.empty:
            parts.append(write_table(out_dir, name, title, tab))
    ds = data_size_table(results)
    if not ds.empty:
        show = ds.copy()
        show["cell"] = [_cell(m, s) for m, s in zip(show["mean"], show["std"])]
        wide = show.pivot_table(index=["data", "scene", "model"], columns="train_episodes", values="cell", aggfunc="first")
        wide = wide.reset_index().rename_axis(columns=None)
        wide.columns = [str(c) for c in wide.columns]
        md = "### Prediction error vs training episodes (Fig. 5 analogue; mean ± std over seeds, m)\n\n" + markdown(wide)
        atomic_write_csv(ds, out_dir / "ethucy_fig5.csv")
        atomic_write_text(out_dir / "ethucy_fig5.md", md + "\n")
        parts.append(md)
        fig = fig_data_size(ds, out_dir)
        if fig is not None:
            parts.append(f"Figure: {fig.name}")
    fig = fig_trajectories(results, out_dir)
    if fig is not None:
        parts.append(f"Figure: {fig.name}")
    return "\n\n".join(parts)


def report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path) -> str:
    """Tables III–IV analogue (Markdown + CSV), Fig. 4 and Fig. 5 analogues (PNG); the data sets
    are shown by their labels (``task.datasets.<name>.label`` in the runs' ``config.yaml``)."""
    from dslearn.schemas.datasets import run_labels

    labels = run_labels(out_dir)
    if "scene" in results.columns:
        results = results.assign(scene=results["scene"].map(lambda s: labels.get(s, s) if isinstance(s, str) else s))
    return real_report(results, summary, out_dir)
