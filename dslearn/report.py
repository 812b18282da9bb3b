"""``dslearn-report DIR``: gather a run or multirun directory into paper-shaped tables and figures.

``DIR`` is a run directory, a sweep directory (its gathered ``sweep_results.parquet``/``.csv`` is
used when present, else every complete job's ``results.csv``; broken job dirs are skipped with a
warning) or the path of a gathered table itself. Writes ``summary.csv`` (columns
``study, consensus, node, model, metric, mean, std, n`` plus every other key column), and when
several seeds are present ``summary_seeds.csv`` (per-seed means, then mean ± std over seeds),
the generic ``tables.md`` / ``tables.tex`` (one table per metric, mean ± std), ``figure.png``
(every metric against the swept keys, error bars over seeds or episodes, units on the axes;
its numbers in ``figure_data.csv``), each study's own Markdown/CSV tables and PNG figures, and
``report.md`` — the file to open first: the figure, the tables and a list of every file
written. Prints the Markdown, then which file to open and what was written.

Display conventions (tables, console, figures): the sensor average is labelled
``sensor average`` and set apart from the node rows; ``nees`` is shown as ``state NEES/Dx`` (the NEES of the
whole state, every target's position and velocity, over the state dimension Dx; the tracking figure and the
matrix show the position NEES / 2A instead, and say so); metrics
with a unit carry it in the header (:data:`METRIC_UNITS`). ``summary.csv`` keeps the machine
names (node ``avg``, metric ``nees``).
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import sys
from pathlib import Path

import pandas as pd

from dslearn.errors import DataFormatError
from dslearn.io import atomic_write_csv, atomic_write_text, load_results
from dslearn.reports.tables import AVG_LABEL, markdown, mean_std  # noqa: F401  (markdown: also the public helper)

#: units of the metrics (``"1"`` = dimensionless); names ending in ``_s`` / ``_m`` / ``_frac`` /
#: ``_kb`` get s / m / 1 / kB without an entry here
METRIC_UNITS: dict[str, str] = {
    "track_err": "m",
    "track_rmse": "m",
    "pred_err": "m",
    "nees": "1",
    "ade": "m",
    "fde": "m",
    "rmse_x_updated": "m",  # Liu et al.: position RMSE of the updated / predictive estimate
    "rmse_y_updated": "m",
    "rmse_x_predictive": "m",
    "rmse_y_predictive": "m",
    "lost_track_m": "m",
    "pos_err_max": "m",
    "time_s": "s",
    "wall_time_s": "s",
    "runtime_s": "s",
    "train_s": "s",
}
#: display names where the machine name would mislead
METRIC_NAMES: dict[str, str] = {"nees": "state NEES/Dx", "nees_pos": "position NEES/2A"}
#: what each NEES is, where a table shows it (a consistent filter gives 1)
NEES_NOTES: dict[str, str] = {
    "nees": ("state NEES/Dx: the NEES of the whole state estimate (every target's position and velocity) over the "
             "state dimension Dx, mean over the steps; 1 = consistent (tracking.png plots the position NEES / 2A "
             "over time, with the 95 % band of a consistent filter)"),
    "nees_pos": ("position NEES/2A: the NEES of the targets' positions over their 2A degrees of freedom (A targets), "
                 "mean over the steps; 1 = consistent (dslearn-report: its 95 % interval and the band of a "
                 "consistent filter)"),
}
#: display label of the ``avg`` node (the papers' "Average" row: the mean over sensing nodes)


def metric_unit(metric: str) -> str | None:
    """The unit of ``metric`` (``"1"`` for dimensionless, ``None`` when unknown)."""
    m = str(metric)
    if m in METRIC_UNITS:
        return METRIC_UNITS[m]
    for suffix, unit in (("_s", "s"), ("_m", "m"), ("_frac", "1"), ("_fraction", "1"), ("_kb", "kB")):
        if m.endswith(suffix):
            return unit
    return None


def metric_label(metric: str) -> str:
    """``track_err`` -> ``track_err [m]``, ``nees`` -> ``state NEES/Dx``: the name shown in headers and axes."""
    m = str(metric)
    name = METRIC_NAMES.get(m, m)
    unit = metric_unit(m)
    return f"{name} [{unit}]" if unit not in (None, "1") else name


def node_label(node) -> str:
    return AVG_LABEL if str(node) == "avg" else str(node)

#: columns that are not keys: values, replicates, and bookkeeping of gathered sweeps
NON_KEYS = {"value", "episode", "seed", "run_dir", "job", "ov.seed"}
REQUIRED = ["study", "consensus", "node", "model", "metric"]


def _redundant_override(c: str, columns) -> bool:
    """``ov.<key>`` of a gathered sweep that the results already carry as a column
    (``ov.model`` -> ``model``, ``ov.consensus.omega`` -> ``omega``): not a separate key, so that
    runs the study itself labels alike (e.g. ``individual`` under either ω) are pooled as before."""
    if not c.startswith("ov."):
        return False
    k = c[3:]
    return k in columns or k.split(".")[-1] in columns


def key_columns(df: pd.DataFrame) -> list[str]:
    keys = [c for c in df.columns if c not in NON_KEYS and not _redundant_override(c, df.columns)]
    return REQUIRED + [c for c in keys if c not in REQUIRED]


def summarize(results: pd.DataFrame) -> pd.DataFrame:
    """Mean, std, n over episodes (and seeds) for every key combination.

    Where a ``node_kind`` column marks sensing nodes, an ``avg`` node is added, formed as the
    papers form their "Average" rows: ``mean`` is the mean over sensing nodes of their means,
    ``std`` the mean over sensing nodes of their standard deviations. The spread of the
    sensor-averaged error itself (per episode the mean over sensing nodes, then the standard
    deviation over episodes) is a different quantity and has its own column,
    ``std_of_sensor_avg`` (empty for the other nodes).
    """
    df = results.copy()
    for c in REQUIRED:
        if c not in df.columns:
            df[c] = "-"
    keys = key_columns(df)
    for c in keys:
        if df[c].isna().any():
            df[c] = df[c].astype(object).where(df[c].notna(), "-")
    out = df.groupby(keys, dropna=False, sort=False)["value"].agg(mean="mean", std="std", n="count").reset_index()
    out["std_of_sensor_avg"] = float("nan")
    if "node_kind" in df.columns and (df["node_kind"] == "sensor").any():
        gk = [k for k in keys if k not in ("node", "node_kind")]
        per_sensor = out[out["node_kind"] == "sensor"]
        avg = per_sensor.groupby(gk, dropna=False, sort=False).agg(mean=("mean", "mean"), std=("std", "mean")).reset_index()
        sens = df[df["node_kind"] == "sensor"]
        rep = [c for c in ("episode", "seed") if c in df.columns]
        per_ep = sens.groupby(gk + rep, dropna=False, sort=False)["value"].mean().reset_index()
        spread = per_ep.groupby(gk, dropna=False, sort=False)["value"].agg(std_of_sensor_avg="std", n="count").reset_index()
        avg = avg.merge(spread, on=gk, how="left")
        avg["node"] = "avg"
        avg["node_kind"] = "avg"
        out = pd.concat([out, avg[out.columns]], ignore_index=True)
    cols = REQUIRED + ["mean", "std", "n", "std_of_sensor_avg"] + [k for k in keys if k not in REQUIRED]
    return out[cols]


def console_table(summary: pd.DataFrame) -> str:
    """A compact table of one run: rows node (the sensor average set apart, last), columns
    metric with units, cells mean ± std."""
    s = summary.copy()
    extra = [c for c in ("train_seen",) if c in s.columns]
    if extra:
        s = s[s[extra[0]] == s[extra[0]].max()]
    s["cell"] = [mean_std(m, d) for m, d in zip(s["mean"], s["std"])]  # 3 significant digits, "-" for no std
    head = ", ".join(f"{c}={s[c].iloc[0]}" for c in ("study", "model", "consensus") if c in s.columns)
    tab = s.pivot_table(index="node", columns="metric", values="cell", aggfunc="first", sort=False)
    nodes = [n for n in tab.index if n != "avg"]
    metrics = list(tab.columns)
    header = ["node"] + [metric_label(m) for m in metrics]
    rows = [[str(n)] + [str(tab.loc[n, m]) if pd.notna(tab.loc[n, m]) else "" for m in metrics] for n in nodes]
    avg = [AVG_LABEL] + [str(tab.loc["avg", m]) if pd.notna(tab.loc["avg", m]) else "" for m in metrics] if "avg" in tab.index else None
    widths = [max(len(r[i]) for r in [header] + rows + ([avg] if avg else [])) for i in range(len(header))]

    def fmt(r):
        return "  ".join(v.ljust(w) if i == 0 else v.rjust(w) for i, (v, w) in enumerate(zip(r, widths))).rstrip()

    lines = [head, fmt(header), "  ".join("-" * w for w in widths)] + [fmt(r) for r in rows]
    if avg:
        lines += ["  ".join("-" * w for w in widths), fmt(avg)]
    lines += [NEES_NOTES[m] for m in metrics if m in NEES_NOTES]
    return "\n".join(lines)


def _has_tabulate() -> bool:
    try:
        import tabulate  # noqa: F401

        return True
    except ImportError:
        return False


def seed_summary(results: pd.DataFrame) -> pd.DataFrame | None:
    """Mean ± std over seeds: per seed the mean over episodes, then across seeds (``None`` with one seed)."""
    if "seed" not in results.columns or results["seed"].nunique() < 2:
        return None
    df = results.copy()
    for c in REQUIRED:
        if c not in df.columns:
            df[c] = "-"
    keys = [k for k in key_columns(df)]
    for c in keys:
        if df[c].isna().any():
            df[c] = df[c].astype(object).where(df[c].notna(), "-")
    per_seed = df.groupby(keys + ["seed"], dropna=False, sort=False)["value"].mean().reset_index()
    out = per_seed.groupby(keys, dropna=False, sort=False)["value"].agg(mean="mean", std="std", n_seeds="count")
    return out.reset_index()


def metric_tables(summary: pd.DataFrame) -> dict[str, pd.DataFrame]:
    """One table per metric: rows = the key columns that vary, cell = ``mean ± std``.

    Where the summary has an ``avg`` node (the paper's "Average" row) only that node is shown.
    """
    s = summary.copy()
    if "node" in s.columns and (s["node"] == "avg").any():
        s = s[s["node"] == "avg"]
    keys = [c for c in s.columns if c not in ("metric", "mean", "std", "n", "n_seeds") and s[c].nunique(dropna=False) > 1]
    keys = [c for c in keys if not (c.startswith("ov.") and c[3:] in s.columns)]  # override = a column already
    out = {}
    for metric, g in s.groupby("metric", sort=False):
        cell = pd.Series([mean_std(m, d) for m, d in zip(g["mean"], g["std"])], index=g.index)
        t = g[keys].copy() if keys else pd.DataFrame(index=g.index)
        t["mean ± std"] = cell.values
        n = "n_seeds" if "n_seeds" in g.columns else "n"
        t[n] = g[n].values
        out[str(metric)] = t.reset_index(drop=True)
    return out


def to_latex(df: pd.DataFrame, caption: str) -> str:
    """A LaTeX table (``DataFrame.to_latex``; plain tabular fallback without jinja2)."""
    try:
        body = df.to_latex(index=False, caption=caption.replace("_", r"\_"), escape=True)
        return body.replace("±", r"$\pm$")
    except ImportError:
        cols = " & ".join(str(c) for c in df.columns)
        rows = " \\\n".join(" & ".join(str(v) for v in r) for r in df.itertuples(index=False))
        return f"\\begin{{tabular}}{{{'l' * len(df.columns)}}}\n{cols} \\\\\n\\hline\n{rows} \\\\\n\\end{{tabular}}\n"


def _plot_metric(table: pd.DataFrame, metric: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [c for c in table.columns if c not in ("mean ± std", "n", "n_seeds")]
    labels = [" ".join(str(v) for v in r) for r in table[keys].itertuples(index=False)] if keys else ["all"] * len(table)
    cells = table["mean ± std"].str.split(" ± ", expand=True)
    mean = pd.to_numeric(cells[0], errors="coerce")
    std = pd.to_numeric(cells[1], errors="coerce").fillna(0.0)
    fig, ax = plt.subplots(figsize=(max(4.0, 0.45 * len(table) + 2), 3.2))
    ax.bar(range(len(table)), mean, yerr=std, capsize=3, color="#4c72b0")
    ax.set_xticks(range(len(table)))
    ax.set_xticklabels(labels, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel(metric_label(metric))
    ax.set_title(f"{metric_label(metric)} (mean ± std)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def generic_tables(summary: pd.DataFrame, out_dir: Path, figures: bool = True) -> str:
    """``tables.md``, ``tables.tex`` and ``<metric>.png`` for any tidy summary; returns the Markdown."""
    md, tex = [], []
    written = []
    for metric, t in metric_tables(summary).items():
        md.append(f"### {metric_label(metric)}\n\n{markdown(t)}")
        tex.append(to_latex(t, f"{metric_label(metric)}: mean $\\pm$ std"))
        if figures:
            _plot_metric(t, metric, out_dir / f"{metric}.png")
            written.append(f"{metric}.png")
    text = "\n\n".join(md)
    atomic_write_text(out_dir / "tables.md", text + "\n")
    atomic_write_text(out_dir / "tables.tex", "\n\n".join(tex))
    generic_tables.written = ["tables.md", "tables.tex"] + written
    return text


# --------------------------------------------------------------------------------------------
# the default figure: every metric against the swept keys


def swept_keys(results: pd.DataFrame) -> list[str]:
    """The keys a sweep varied: the ``ov.*`` override columns with more than one value (seed
    aside), else the study's own key columns that vary (model, consensus, ...)."""
    ov = [c for c in results.columns if c.startswith("ov.") and c != "ov.seed" and results[c].nunique(dropna=False) > 1]
    if ov:
        return ov
    skip = {"node", "node_kind", "metric", "study", "task"}
    return [c for c in key_columns(results) if c in results.columns and c not in skip and results[c].nunique(dropna=False) > 1]


#: most lines (or bar groups) per panel of the default figure
MAX_LINES = 8


def _as_number(v):
    try:
        return float(v)
    except (TypeError, ValueError):
        return None


def figure_data(results: pd.DataFrame) -> tuple[pd.DataFrame, str]:
    """The numbers of the default figure and what its error bars are.

    One value per (metric, key combination, seed, episode): the mean over sensing nodes where
    ``node_kind`` marks them (the sensor average), the ``avg`` node where there is one, else the
    mean over the rows of that episode. Then per key combination: with several seeds, the mean
    over episodes per seed and mean ± std over seeds; with one seed, mean ± std over episodes.
    Returns columns ``metric, <keys...>, mean, err, n`` and ``"seeds"`` or ``"episodes"``."""
    df = results.copy()
    df["value"] = pd.to_numeric(df["value"], errors="coerce")
    if "node_kind" in df.columns and (df["node_kind"] == "sensor").any():
        df = df[df["node_kind"] == "sensor"]
    elif "node" in df.columns and (df["node"].astype(str) == "avg").any():
        df = df[df["node"].astype(str) == "avg"]
    keys = swept_keys(results)
    # other keys that vary inside the chosen rows would be pooled silently: keep them as keys
    skip = {"node", "node_kind", "metric", "study", "task", "run_dir", "job"}
    cand = [c for c in key_columns(df) if c in df.columns and c not in skip and c not in keys
            and df[c].nunique(dropna=False) > 1]
    if keys:  # only keys that vary within one combination of the swept keys (not their labels)
        filled = df[keys + cand].astype(object).where(df[keys + cand].notna(), "-")
        cand = [c for c in cand if filled.groupby(keys, sort=False)[c].nunique().max() > 1]
    fixed = {}
    for c in cand:  # a key with many values (time steps, iterations): shown at its most common value
        if df[c].nunique(dropna=False) > MAX_LINES and c not in keys:
            v = df[c].value_counts(dropna=False).index[0]
            df = df[df[c] == v]
            fixed[c] = v
    keys = keys + [c for c in cand if c not in fixed]
    for c in keys:
        df[c] = df[c].astype(object).where(df[c].notna(), "-")
    rep = [c for c in ("seed", "episode") if c in df.columns]
    per = df.groupby(["metric"] + keys + rep, dropna=False, sort=False)["value"].mean().reset_index()
    seeds = "seed" in per.columns and per["seed"].nunique() > 1
    if seeds:
        per = per.groupby(["metric"] + keys + ["seed"], dropna=False, sort=False)["value"].mean().reset_index()
    out = per.groupby(["metric"] + keys, dropna=False, sort=False)["value"].agg(mean="mean", err="std", n="count").reset_index()
    out.attrs["fixed"] = fixed
    return out, ("seeds" if seeds else "episodes")


def plot_figure(results: pd.DataFrame, path: Path, single: bool = True) -> pd.DataFrame | None:
    """``figure.png``: one panel per metric, the metric against the first swept key (lines =
    the other keys' combinations), error bars ± 1 std over seeds (or episodes with one seed),
    units on the axes. Returns the plotted numbers (also written as ``figure_data.csv``).
    ``single=False``: no figure (``None``) for a single configuration (one bar per panel)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import warnings

    data, over = figure_data(results)
    if data.empty or (not single and set(data.columns) <= {"metric", "mean", "err", "n"}):
        return None
    with warnings.catch_warnings():  # layout/legend notes of matplotlib are not the user's business
        warnings.simplefilter("ignore", UserWarning)
        return _draw_figure(plt, data, over, results, path)


def _draw_figure(plt, data, over, results, path):
    keys = [c for c in data.columns if c not in ("metric", "mean", "err", "n")]
    metrics = list(dict.fromkeys(data["metric"]))[:12]
    ncol = min(3, len(metrics))
    nrow = -(-len(metrics) // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.6 * ncol, 3.5 * nrow), squeeze=False)
    x_key, hue = (keys[0], keys[1:]) if keys else (None, [])
    legend = None
    for ax, metric in zip(axes.flat, metrics):
        g = data[data["metric"] == metric]
        if x_key is None:
            ax.bar([0], g["mean"], yerr=g["err"].fillna(0), capsize=3, color="#4c72b0")
            ax.set_xticks([0])
            ax.set_xticklabels(["all"])
        else:
            xs = list(dict.fromkeys(g[x_key]))
            nums = [_as_number(v) for v in xs]
            numeric = all(v is not None for v in nums) and len(xs) > 1
            order = sorted(xs, key=_as_number) if numeric else xs
            pos = {v: (_as_number(v) if numeric else i) for i, v in enumerate(order)}
            groups = list(g.groupby(hue, dropna=False, sort=False)) if hue else [((), g)]
            if len(groups) > MAX_LINES:
                ax.text(0.01, 0.99, f"first {MAX_LINES} of {len(groups)} lines (all in figure_data.csv)",
                        transform=ax.transAxes, fontsize=6, va="top")
                groups = groups[:MAX_LINES]
            width = 0.8 / max(1, len(groups))
            for j, (h, gg) in enumerate(groups):
                h = h if isinstance(h, tuple) else (h,)
                label = ", ".join(f"{k.removeprefix('ov.')}={v}" for k, v in zip(hue, h)) or None
                gg = gg.assign(_x=gg[x_key].map(pos)).sort_values("_x")
                if numeric:
                    ax.errorbar(gg["_x"], gg["mean"], yerr=gg["err"].fillna(0), capsize=3, marker="o", label=label)
                else:
                    ax.bar(gg["_x"] - 0.4 + width * (j + 0.5), gg["mean"], width, yerr=gg["err"].fillna(0), capsize=2, label=label)
            if not numeric:
                ax.set_xticks(range(len(order)))
                ax.set_xticklabels([str(v) for v in order], rotation=30, ha="right", fontsize=8)
            ax.set_xlabel(x_key.removeprefix("ov.") + (f" [{metric_unit(x_key.removeprefix('ov.'))}]"
                                                      if metric_unit(x_key.removeprefix("ov.")) not in (None, "1") else ""))
            if hue and len(groups) > 1 and legend is None:
                legend = ax.get_legend_handles_labels()
        ax.set_ylabel(metric_label(metric))
        ax.set_title(metric_label(metric), fontsize=10)
        pos_means = g["mean"][g["mean"] > 0]
        if len(pos_means) == len(g) and len(g) > 1 and pos_means.max() / pos_means.min() > 100:
            ax.set_yscale("log")  # e.g. NEES/Dx of an inconsistent filter next to consistent ones
    for ax in list(axes.flat)[len(metrics):]:
        ax.set_visible(False)
    fixed = data.attrs.get("fixed", {})
    note = ("; at " + ", ".join(f"{k}={v}" for k, v in fixed.items())) if fixed else ""
    fig.suptitle(f"mean ± 1 std over {over}" + (" (sensor average)" if "node_kind" in results.columns else "") + note,
                 fontsize=9)
    if legend is not None:  # one legend for all panels, below them
        ncol_leg = min(4, len(legend[1]))
        fig.legend(*legend, loc="lower center", ncol=ncol_leg, fontsize=7, frameon=False)
        rows_leg = -(-len(legend[1]) // ncol_leg)
        bottom = min(0.4, (0.2 * rows_leg + 0.15) / (3.5 * nrow))  # legend rows ~0.2 inch each
        fig.tight_layout(rect=(0, bottom, 1, 0.97))
    else:
        fig.tight_layout(rect=(0, 0, 1, 0.97))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    atomic_write_csv(data.assign(error_bars=f"std over {over}"), path.with_name("figure_data.csv"))
    return data


#: one line per file ``report`` may write (listed in report.md)
FILE_NOTES = {
    "report.md": "this report (open it first)",
    "figure.png": "every metric against the swept keys; error bars ± 1 std over seeds or episodes",
    "figure_data.csv": "the numbers plotted in figure.png",
    "summary.csv": "mean, std, n per key combination (machine names: node 'avg' = sensor average, 'nees' = state NEES/Dx)",
    "summary_seeds.csv": "per-seed means, then mean ± std over seeds",
    "tables.md": "one generic table per metric (Markdown)",
    "tables.tex": "the same tables (LaTeX)",
    "yu_table1.csv": "Yu Table I shape: tracking error per fusion x node x model (also .md)",
    "yu_table1_rmse.csv": "tracking RMSE in the Table I layout (also .md)",
    "yu_table2.csv": "Yu Table II shape: prediction error per node x model (also .md)",
    "yu_nees.csv": "state NEES/Dx (the whole state's NEES over its dimension) in the Table I layout (also .md)",
    "yu_fig2.png": "Yu Fig. 2 shape: tracking error against training episodes and L",
    "tracking.png": ("the sensor network, a test episode's true and estimated tracks, position error and position "
                     "NEES / 2A over time with the 95 % band of a consistent filter"),
    "matrix.md": "the matrix: RMSE ± 95 % half-interval (position NEES / 2A) per method and scenario, best bold, ties ≈",
    "matrix.csv": "the matrix's numbers, one row per method x scenario: means, 95 % intervals, rank, tied, notes",
    "leaderboard.md": "per scenario the methods best first, with the paired difference to the best (also .csv)",
    "leaderboard.csv": "the leaderboard's numbers",
    "matrix.png": "per scenario every method's RMSE with its 95 % interval, the best and the ties marked",
}


def _check_paths(root: Path, out: Path | None) -> None:
    if not root.exists():
        raise FileNotFoundError(f"{root}: no such file or folder (give a run or sweep output folder, or a sweep_results table)")
    if out is not None and out.exists() and not out.is_dir():
        raise NotADirectoryError(f"--out {out} is an existing file; give a folder")


def report(root: str | Path, out_dir: str | Path | None = None) -> str:
    """Write the tables, ``figure.png`` and ``report.md`` for ``root`` into ``out_dir`` (default:
    ``root``, or its folder for a table file); returns the Markdown of the tables. The files
    written are in ``report.written``."""
    root = Path(root)
    _check_paths(root, Path(out_dir) if out_dir is not None else None)
    results = load_results(root)  # before any folder is made: a bad input leaves nothing behind
    out = Path(out_dir) if out_dir is not None else (root.parent if root.is_file() else root)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    summary = summarize(results)
    atomic_write_csv(summary, out / "summary.csv")
    written.append("summary.csv")
    seeds = seed_summary(results)
    if seeds is not None:
        atomic_write_csv(seeds, out / "summary_seeds.csv")
        written.append("summary_seeds.csv")
    texts = []
    tasks = results["task"].dropna().unique() if "task" in results.columns else []
    before = {(p.name, p.stat().st_mtime_ns) for p in out.iterdir()} if out.is_dir() else set()
    for task in tasks:
        try:
            mod = importlib.import_module(f"dslearn.reports.{task}")
        except ModuleNotFoundError as e:
            if e.name != f"dslearn.reports.{task}":
                raise
            continue  # a task without its own tables: the generic ones below
        fn = getattr(mod, "report", None)
        if fn is not None:
            sub = results[results["task"] == task]
            kw = {"root": root} if "root" in inspect.signature(fn).parameters else {}  # the sweep's own files
            texts.append(fn(sub, summary[summary.get("task", task) == task] if "task" in summary else summary, out, **kw))
    # the files the study reports wrote (new or rewritten: a second report of a folder lists them again)
    study_files = sorted({n for n, _ in {(p.name, p.stat().st_mtime_ns) for p in out.iterdir()} - before}
                         - set(written) - {"report.md"})
    generic = generic_tables(seeds if seeds is not None else summary, out, figures=False)
    written += generic_tables.written
    own = [f for f in study_files if f.endswith(".png")]
    fig = plot_figure(results, out / "figure.png", single=not own)  # a single run: the study's figure instead
    if fig is not None:
        written += ["figure.png", "figure_data.csv"]
    text = "\n\n".join(t for t in texts if t) or generic
    files = ["report.md"] + written + [f for f in study_files if f not in written]
    def note(f: str) -> str:
        if f in FILE_NOTES:
            return FILE_NOTES[f]
        if f.endswith(".md") and f[:-3] + ".csv" in FILE_NOTES:
            return f"the Markdown of {f[:-3]}.csv"
        return "a table or figure of the study's own report"

    notes = "\n".join(f"- `{f}`: {note(f)}" for f in files)
    head = f"# dslearn report: {root}\n\nOpen this file first.\n\n"
    if fig is not None:
        head += "![every metric against the swept keys](figure.png)\n\n"
    elif own and not any(f"]({f})" in t for f in own for t in texts):
        head += f"![the study's figure]({own[0]})\n\n"
    atomic_write_text(out / "report.md", f"{head}{text}\n\n## Files written\n\n{notes}\n")
    report.written = [out / f for f in files]
    return text


def _not_a_run(root: Path, e: Exception) -> str:
    """For a folder that holds no result: what ``dslearn-report`` looks for, and what the folder holds."""
    if not isinstance(e, FileNotFoundError) or not root.is_dir():
        return ""
    import json

    status = ""
    try:
        st = json.loads((root / "status.json").read_text())
        status = f"; its status.json says {st.get('status')!r}" + (f" ({st['error']})" if st.get("error") else "")
    except (OSError, ValueError, AttributeError):
        pass
    try:
        names = sorted(p.name + ("/" if p.is_dir() else "") for p in root.iterdir())
    except OSError:
        names = []
    held = ", ".join(names[:8]) + (f", ... ({len(names)} entries)" if len(names) > 8 else "") if names else "nothing"
    return (f". Expected a dslearn-run output folder: a run folder holds results.csv (written last, beside "
            f"meta.json, config.yaml and status.json), a sweep folder holds sweep_results.csv or .parquet or job "
            f"folders with results.csv; or give the path of a results.csv / sweep_results table. "
            f"{root} holds: {held}{status}")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(
        prog="dslearn-report", description=__doc__.splitlines()[0].replace("``", ""),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="DIR: a run folder of dslearn-run (it holds results.csv), a sweep folder (sweep_results.csv /\n"
               ".parquet, or job folders with results.csv), or the path of such a table. Writes report.md (open it\n"
               "first), summary.csv, tables.md / tables.tex, figure.png and each study's own tables and figures.\n"
               "Exit codes: 0 done, 2 not a run / unreadable / cannot write (one line), 130 Ctrl-C.")
    p.add_argument("dir", help="a run or sweep output directory, or a gathered sweep_results.{parquet,csv}")
    p.add_argument("--out", default=None, help="write the tables/figures here (default: DIR)")
    a = p.parse_args(argv)
    import warnings

    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=r".*torch\.jit\.script.* is deprecated")
            text = report(a.dir, a.out)
    except (FileNotFoundError, NotADirectoryError, IsADirectoryError, DataFormatError) as e:
        print(f"dslearn-report: {' '.join(str(e).split())}{_not_a_run(Path(a.dir), e)}", file=sys.stderr)
        raise SystemExit(2)
    except PermissionError as e:
        print(f"dslearn-report: cannot write: {e.filename or e}", file=sys.stderr)
        raise SystemExit(2)
    except KeyboardInterrupt:
        print("dslearn-report: interrupted (Ctrl-C)", file=sys.stderr)
        raise SystemExit(130) from None
    print(text)
    files = report.written
    print(f"\nopen first: {files[0]}")
    print("wrote: " + ", ".join(f.name for f in files) + f" (in {files[0].parent})")


if __name__ == "__main__":
    main()
