"""Report of the ``ethucy_forecast`` task: the leave-one-scene-out ADE/FDE table beside the
published Social GAN figures, a bar chart, and the LSTM convergence table and learning curves,
from the result rows and the files the run wrote (``learning_curves.csv``, ``config.yaml`` for the
data sets' labels)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pandas as pd

from dslearn.reports.tables import save_figure
from dslearn.schemas.datasets import run_labels

log = logging.getLogger(__name__)

PREDICTORS = ("cv", "lstm", "social_lstm", "gp", "gp_state")
LABELS = {"cv": "CV", "lstm": "LSTM", "social_lstm": "S-LSTM", "gp": "GP (vel.)", "gp_state": "GP (state)"}
LSTM_MODELS = ("lstm", "social_lstm")
#: the benchmark's five test scenes, in the order the papers print them (the AVG row is their mean)
BENCHMARK = ("eth", "hotel", "univ", "zara1", "zara2")
#: the previous default schedule's epoch count (6 epochs, batch 64): the report compares the
#: validation loss there with the best one reached by early stopping
OLD_EPOCHS = 6

#: Published 8 -> 12 ADE / FDE in metres: Gupta et al., "Social GAN", CVPR 2018, Table 1
#: (t_pred = 12 rows; "Linear" there is a least-squares linear regressor, not constant velocity).
#: See experiments/ethucy_forecast/README.md for how each figure was checked.
PUBLISHED_SGAN = {
    "Linear": {"eth": (1.33, 2.94), "hotel": (0.39, 0.72), "univ": (0.82, 1.59), "zara1": (0.62, 1.21), "zara2": (0.77, 1.48), "avg": (0.79, 1.59)},
    "LSTM": {"eth": (1.09, 2.41), "hotel": (0.86, 1.91), "univ": (0.61, 1.31), "zara1": (0.41, 0.88), "zara2": (0.52, 1.11), "avg": (0.70, 1.52)},
    "S-LSTM": {"eth": (1.09, 2.35), "hotel": (0.79, 1.76), "univ": (0.67, 1.40), "zara1": (0.47, 1.00), "zara2": (0.56, 1.17), "avg": (0.72, 1.54)},
}


def forecast_table(results: pd.DataFrame) -> pd.DataFrame:
    """Tidy table ``scene, model, ade, fde`` (mean over seeds) with an ``AVG`` row per model
    (the mean over the five benchmark scenes, as the papers report it) when all five are there."""
    r = results[results.metric.isin(["ade", "fde"])]
    tab = r.groupby(["scene", "model", "metric"], sort=False)["value"].mean().unstack("metric").reset_index()
    seen = list(dict.fromkeys(tab.scene))
    order = [s for s in BENCHMARK if s in seen] + [s for s in seen if s not in BENCHMARK]
    tab["scene"] = pd.Categorical(tab.scene, order, ordered=True)
    tab = tab.sort_values(["scene", "model"]).reset_index(drop=True)
    if set(BENCHMARK) <= set(order):
        avg = tab[tab.scene.isin(BENCHMARK)].groupby("model", sort=False)[["ade", "fde"]].mean().reset_index()
        avg["scene"] = "avg"
        tab["scene"] = tab.scene.astype(str)
        tab = pd.concat([tab, avg[["scene", "model", "ade", "fde"]]], ignore_index=True)
    tab["scene"] = tab.scene.astype(str)
    return tab[["scene", "model", "ade", "fde"]]


def _wide(tab: pd.DataFrame, labels: dict) -> pd.DataFrame:
    models = [m for m in PREDICTORS if m in set(tab.model)]
    out = tab.assign(cell=tab.ade.map("{:.2f}".format) + " / " + tab.fde.map("{:.2f}".format))
    w = out.pivot_table(index="scene", columns="model", values="cell", aggfunc="first", sort=False)[models]
    w.columns = [LABELS[m] for m in models]
    w.index = [labels.get(s, "AVG" if s == "avg" else s) for s in w.index]
    return w.reset_index(names="scene")


def published_table(labels: dict | None = None) -> pd.DataFrame:
    labels = {**{s: s.upper() for s in BENCHMARK}, **(labels or {}), "avg": "AVG"}
    rows = []
    for scene in list(BENCHMARK) + ["avg"]:
        row = {"scene": labels[scene]}
        for model, d in PUBLISHED_SGAN.items():
            row[model] = f"{d[scene][0]:.2f} / {d[scene][1]:.2f}"
        rows.append(row)
    return pd.DataFrame(rows)


def load_curves(out_dir: Path) -> pd.DataFrame | None:
    """``learning_curves.csv`` of a run directory, or of every run below a sweep directory
    (column ``run`` = its folder relative to ``out_dir``); ``None`` if there is none."""
    out_dir = Path(out_dir)
    files = [out_dir / "learning_curves.csv"] if (out_dir / "learning_curves.csv").is_file() else sorted(out_dir.rglob("learning_curves.csv"))
    if not files:
        return None
    frames = [pd.read_csv(f).assign(run=str(f.parent.relative_to(out_dir)) if f.parent != out_dir else ".") for f in files]
    return pd.concat(frames, ignore_index=True)


def convergence_table(curves: pd.DataFrame, ref_epoch: int = OLD_EPOCHS) -> pd.DataFrame:
    """Per (run, scene, model): epochs run, best epoch, validation loss at ``ref_epoch`` (the old
    fixed schedule's last epoch), best validation loss, and how far above the best the former is."""
    rows = []
    for (run, fold, scene, model), g in curves.groupby(["run", "fold", "scene", "model"], sort=True):
        g = g.sort_values("epoch")
        i_best = int(g.val_loss.to_numpy().argmin())
        ref = g.loc[g.epoch == ref_epoch, "val_loss"]
        best = float(g.val_loss.iloc[i_best])
        v_ref = float(ref.iloc[0]) if len(ref) else float("nan")
        rows.append(dict(run=run, fold=int(fold), scene=scene, model=model, epochs_run=int(g.epoch.max()),
                         best_epoch=int(g.epoch.iloc[i_best]), val_ref=v_ref, val_best=best,
                         excess_pct=100.0 * (v_ref - best) / best, final_lr=float(g.lr.iloc[-1])))
    return pd.DataFrame(rows)


def report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path) -> str:
    """Five-scene ADE/FDE table (``ethucy_forecast.md`` / ``.csv``), the published
    Social GAN figures beside it, and a bar chart (``ethucy_forecast.png``); with the run's
    ``learning_curves.csv`` also the convergence table (``ethucy_forecast_convergence.csv``)
    and the learning curves (``learning_curves.png``)."""
    from dslearn.io import atomic_write_csv, atomic_write_text
    from dslearn.reports.tables import markdown

    out_dir = Path(out_dir)
    labels = run_labels(out_dir)
    tab = forecast_table(results)
    atomic_write_csv(tab, out_dir / "ethucy_forecast.csv")
    wide = _wide(tab, labels)
    secs = results[results.metric == "train_s"].groupby("model")["value"].sum()
    lines = [
        "## ETH/UCY leave-one-scene-out forecasting, 8 -> 12 steps (ADE / FDE, m)",
        "",
        markdown(wide),
        "",
        "Training + prediction seconds over all folds: "
        + ", ".join(f"{LABELS.get(m, m)} {secs[m]:.0f}" for m in PREDICTORS if m in secs.index),
        "",
        "### Published (Gupta et al., Social GAN, CVPR 2018, Table 1, t_pred = 12)",
        "",
        markdown(published_table(labels)),
        "",
        "'Linear' there is a least-squares linear regressor over the 8 observed points, not the "
        "constant-velocity model above. See experiments/ethucy_forecast/README.md.",
    ]
    curves = load_curves(out_dir)
    if curves is not None and not curves.empty:
        conv = convergence_table(curves)
        atomic_write_csv(conv, out_dir / "ethucy_forecast_convergence.csv")
        def fmt(f):
            return lambda v: f.format(v) if np.isfinite(v) else "-"

        show = conv.assign(
            scene=conv.scene.map(lambda v: labels.get(v, v)), model=conv.model.map(lambda v: LABELS.get(v, v)),
            val_ref=conv.val_ref.map(fmt("{:.4f}")), val_best=conv.val_best.map(fmt("{:.4f}")),
            excess_pct=conv.excess_pct.map(fmt("{:+.1f} %")), final_lr=conv.final_lr.map(fmt("{:.2g}")),
        ).rename(columns={"epochs_run": "epochs run", "best_epoch": "best epoch", "val_ref": f"val loss @ epoch {OLD_EPOCHS}",
                          "val_best": "best val loss", "excess_pct": f"epoch {OLD_EPOCHS} above best", "final_lr": "last lr"})
        if show.run.nunique() == 1:
            show = show.drop(columns="run")
        lines += ["", "### LSTM training (validation = the training files' benchmark val parts)", "",
                  markdown(show.drop(columns="fold")), "",
                  f"Epoch {OLD_EPOCHS} of this run = where the previous fixed schedule (6 epochs, batch 64) "
                  "stopped; the first epochs of an early-stopping run equal a fixed run with the same batch "
                  "size and seed while the learning rate is unchanged (not for a different batch size)."]
        try:
            _plot_curves(curves, out_dir / "learning_curves.png", labels)
        except Exception as e:  # figures never break the tables
            log.warning("learning-curve figure failed: %s", e)
    text = "\n".join(lines)
    atomic_write_text(out_dir / "ethucy_forecast.md", text + "\n")
    try:
        _plot(tab, out_dir / "ethucy_forecast.png", labels)
    except Exception as e:  # figures never break the tables
        log.warning("ethucy_forecast figure failed: %s", e)
    return text


def _plot_curves(curves: pd.DataFrame, path: Path, labels: dict) -> None:
    """Train (dashed) and validation (solid) loss per epoch, one panel per fold, both LSTMs;
    a dot marks the best validation epoch (the weights kept), a grey line the old epoch 6."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = curves[curves.run == curves.run.iloc[0]]
    folds = c.drop_duplicates("fold").sort_values("fold")
    fig, axes = plt.subplots(1, len(folds), figsize=(3.3 * len(folds), 3.2), squeeze=False, sharey=False)
    for ax, (_, f) in zip(axes[0], folds.iterrows()):
        for j, m in enumerate(LSTM_MODELS):
            g = c[(c.fold == f.fold) & (c.model == m)].sort_values("epoch")
            if g.empty:
                continue
            col = f"C{j}"
            ax.plot(g.epoch, g.val_loss, "-", color=col, label=f"{LABELS[m]} val")
            ax.plot(g.epoch, g.train_loss, "--", color=col, alpha=0.7, label=f"{LABELS[m]} train")
            b = g.loc[g.val_loss.idxmin()]
            ax.plot([b.epoch], [b.val_loss], "o", color=col)
        later = c[(c.fold == f.fold) & (c.epoch >= 2)][["train_loss", "val_loss"]].to_numpy()
        if later.size and np.isfinite(later).any():  # the first epoch's loss would squash the rest
            lo, hi = np.nanmin(later), np.nanmax(later)
            ax.set_ylim(0.95 * lo, 1.05 * hi)
        ax.axvline(OLD_EPOCHS, color="0.6", lw=0.8)
        ax.set_title(f"test {labels.get(f.scene, f.scene)}")
        ax.set_xlabel("epoch")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("loss (MSE per coordinate, m$^2$)")
    axes[0][0].legend(fontsize=7)
    save_figure(fig, path, dpi=110)


def _plot(tab: pd.DataFrame, path: Path, labels: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    models = [m for m in PREDICTORS if m in set(tab.model)]
    scenes = list(dict.fromkeys(tab.scene))
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.6))
    width = 0.8 / max(1, len(models))
    for ax, metric in zip(axes, ("ade", "fde")):
        for i, m in enumerate(models):
            sub = tab[tab.model == m].set_index("scene").reindex(scenes)
            ax.bar(np.arange(len(scenes)) + i * width, sub[metric].to_numpy(), width, label=LABELS[m])
        ax.set_xticks(np.arange(len(scenes)) + 0.4 - width / 2)
        ax.set_xticklabels([labels.get(s, "AVG" if s == "avg" else s) for s in scenes])
        ax.set_ylabel(f"{metric.upper()} [m]")
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("ETH/UCY leave-one-scene-out, 8 -> 12 steps")
    save_figure(fig, path)
