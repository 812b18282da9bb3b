r"""Report of task ``matrix`` (the comparison matrix): rows methods (their labels), columns scenarios.

A cell is ``RMSE unit (NEES/Dx) time``: the RMSE is the mean over the test episodes (and seeds) of each
episode's RMSE averaged over the sensing nodes (the "sensor average"; every reporting node where none is
marked sensing); the position NEES/Dx likewise (left out where the method gives no covariance); the time is
the cell's ``runtime_s`` (the method's learning and estimation, mean over seeds). Every number has three
significant digits. A combination the matrix sweeper dropped is ``n/a: <reason>`` (``skipped_cells.csv`` of
the sweep folder); a cell whose job has no complete result is ``failed`` (its ``status.json`` says it failed)
or ``incomplete`` (killed, or not run yet).

Files: ``matrix.md`` / ``matrix.csv`` (the table), ``matrix_values.csv`` (one row per cell: the numbers at
full precision, ``status`` = ``ok`` / ``skipped`` (shown "n/a") / ``failed`` / ``incomplete``, the reason, the job) and
``matrix.png`` (the RMSE of each cell relative to the best method of its scenario, log colour scale; n/a and
failed cells hatched).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from dslearn.io import atomic_write_csv, check_complete
from dslearn.reports.tables import markdown, save_figure, sig, write_table

TASK = "matrix"
#: the sweep's files (written by the matrix sweeper; see :mod:`dslearn.studies.matrix`)
CELLS_FILE, SKIPPED_FILE = "matrix_cells.csv", "skipped_cells.csv"
VALUE_COLUMNS = ["method", "scenario", "units", "status", "rmse", "nees_pos", "runtime_s", "episodes", "reason", "job"]


def _sweep_dir(root: Path | None) -> Path | None:
    if root is None:
        return None
    root = Path(root)
    return root if root.is_dir() else root.parent


def _read_cells(sweep: Path | None, name: str) -> pd.DataFrame | None:
    if sweep is None or not (sweep / name).is_file():
        return None
    return pd.read_csv(sweep / name, dtype={"method": str, "scenario": str, "units": str, "reason": str})


def _short_reason(reason: str, method: str, scenario: str) -> str:
    """The reason without the leading ``<method> does not fit scenario <scenario>: `` (the row and column say it)."""
    head = f"{method} does not fit scenario {scenario}: "
    return reason[len(head):] if reason.startswith(head) else reason


def cell_values(results: pd.DataFrame) -> pd.DataFrame:
    """One row per (method, scenario) of a matrix results table: ``rmse`` and ``nees_pos`` (per episode and seed
    the mean over the sensing nodes, then the mean over episodes and seeds; NaN where the metric is absent),
    ``runtime_s`` (mean over seeds), ``units`` and ``episodes`` (the number of episode x seed replicates)."""
    df = results.copy()
    df["value"] = pd.to_numeric(df["value"], errors="coerce")
    rep = [c for c in ("seed", "episode") if c in df.columns]
    if "seed" not in df.columns:
        df["seed"] = 0
        rep = ["seed", "episode"]
    out = []
    for (method, scenario), g in df.groupby(["method", "scenario"], sort=False):
        row = {"method": str(method), "scenario": str(scenario),
               "units": str(g["units"].iloc[0]) if "units" in g.columns else ""}
        nodes = g[g["node_kind"] == "sensor"] if (g["node_kind"] == "sensor").any() else g[g["node_kind"] != "all"]
        for metric in ("rmse", "nees_pos"):
            m = nodes[nodes["metric"] == metric]
            per_ep = m.groupby(rep, sort=False)["value"].mean()
            row[metric] = float(per_ep.mean()) if len(per_ep) else float("nan")
            if metric == "rmse":
                row["episodes"] = int(len(per_ep))
        rt = g[g["metric"] == "runtime_s"]
        row["runtime_s"] = float(rt.groupby("seed")["value"].mean().mean()) if len(rt) else float("nan")
        out.append(row)
    return pd.DataFrame(out, columns=["method", "scenario", "units", "rmse", "nees_pos", "runtime_s", "episodes"])


def _job_status(sweep: Path | None, job) -> str:
    """``failed`` where the job's ``status.json`` records a failure, ``incomplete`` otherwise (no complete result)."""
    if sweep is not None and pd.notna(job):
        d = sweep / str(int(job))
        try:
            if json.loads((d / "status.json").read_text(encoding="utf-8")).get("status") == "failed":
                return "failed"
        except (OSError, ValueError, AttributeError):
            pass
        if d.is_dir() and check_complete(d)[0]:
            return "failed"  # a complete result that the gathered table lacks: not gathered (a failed gather)
    return "incomplete"


def matrix_values(results: pd.DataFrame, root: Path | None = None) -> pd.DataFrame:
    """Every cell of the matrix (:data:`VALUE_COLUMNS`): the cells with results, the sweep's dropped
    combinations (``n/a``) and its jobs without results (``failed`` / ``incomplete``), in the sweep's order
    (``matrix_cells.csv``; results-only cells after it)."""
    sweep = _sweep_dir(root)
    vals = cell_values(results)
    vals["status"], vals["reason"], vals["job"] = "ok", None, pd.NA
    cells = _read_cells(sweep, CELLS_FILE)
    if cells is None:  # no sweep record: the skipped list alone, where there is one
        cells = _read_cells(sweep, SKIPPED_FILE)
    rows = []
    have = {(m, s): i for i, (m, s) in enumerate(zip(vals["method"], vals["scenario"]))}
    used = set()
    for c in [] if cells is None else cells.to_dict("records"):
        key = (str(c["method"]), str(c["scenario"]))
        reason = c.get("reason")
        if isinstance(reason, str) and reason:
            rows.append({"method": key[0], "scenario": key[1], "units": c.get("units", ""), "status": "skipped",
                         "rmse": np.nan, "nees_pos": np.nan, "runtime_s": np.nan, "episodes": 0,
                         "reason": _short_reason(reason, *key), "job": pd.NA})
        elif key in have:
            if key not in used:
                r = vals.iloc[have[key]].to_dict()
                r["job"] = c.get("job", pd.NA)
                rows.append(r)
        else:
            rows.append({"method": key[0], "scenario": key[1], "units": c.get("units", ""),
                         "status": _job_status(sweep, c.get("job")), "rmse": np.nan, "nees_pos": np.nan,
                         "runtime_s": np.nan, "episodes": 0, "reason": None, "job": c.get("job", pd.NA)})
        used.add(key)
    rows += [vals.iloc[i].to_dict() for k, i in have.items() if k not in used]
    out = pd.DataFrame(rows, columns=VALUE_COLUMNS)
    out["job"] = out["job"].astype("Int64")
    out["episodes"] = out["episodes"].astype(int)
    return out


def cell_text(r) -> str:
    """The table's text of one cell of :func:`matrix_values`."""
    if r["status"] == "skipped":
        return f"n/a: {r['reason']}"
    if r["status"] != "ok":
        return str(r["status"])
    unit = f" {r['units']}" if isinstance(r["units"], str) and r["units"] and r["units"] != "1" else ""
    nees = f" ({sig(r['nees_pos'])})" if pd.notna(r["nees_pos"]) else ""
    return f"{sig(r['rmse'])}{unit}{nees} {sig(r['runtime_s'])} s"


def matrix_table(values: pd.DataFrame) -> pd.DataFrame:
    """Rows methods, columns scenarios (in first-seen order), cells :func:`cell_text`; an empty cell is a
    combination the sweep did not have."""
    methods = list(dict.fromkeys(values["method"]))
    scenarios = list(dict.fromkeys(values["scenario"]))
    text = {(r["method"], r["scenario"]): cell_text(r) for _, r in values.iterrows()}
    tab = pd.DataFrame({"method": methods})
    for s in scenarios:
        tab[s] = [text.get((m, s), "") for m in methods]
    return tab


def relative_rmse(values: pd.DataFrame) -> pd.DataFrame:
    """Rows methods, columns scenarios: each cell's RMSE over the smallest RMSE of its scenario (NaN where the
    cell has no RMSE)."""
    ok = values[values["status"] == "ok"]
    best = ok.groupby("scenario")["rmse"].min()
    rel = values.assign(rel=[r["rmse"] / best[r["scenario"]] if r["status"] == "ok" else np.nan
                             for _, r in values.iterrows()])
    tab = rel.pivot_table(index="method", columns="scenario", values="rel", aggfunc="first", dropna=False)
    return tab.reindex(index=list(dict.fromkeys(values["method"])), columns=list(dict.fromkeys(values["scenario"])))


def plot_matrix(values: pd.DataFrame, path: Path) -> Path:
    """``matrix.png``: the RMSE of each cell relative to the best of its scenario, log colour scale, the ratio
    written in the cell; n/a cells grey and hatched, failed / incomplete ones light red and hatched."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm
    from matplotlib.patches import Rectangle

    rel = relative_rmse(values)
    methods, scenarios = list(rel.index), list(rel.columns)
    status = {(r["method"], r["scenario"]): r["status"] for _, r in values.iterrows()}
    units = {s: values.loc[values["scenario"] == s, "units"].dropna().astype(str) for s in scenarios}
    fig, ax = plt.subplots(figsize=(2.0 + 1.5 * len(scenarios), 1.2 + 0.32 * len(methods)))
    data = np.ma.masked_invalid(rel.to_numpy(dtype=float))
    vmax = max(2.0, float(np.nanmax(rel.to_numpy(dtype=float)))) if np.isfinite(rel.to_numpy(dtype=float)).any() else 2.0
    im = ax.imshow(data, cmap="viridis_r", norm=LogNorm(vmin=1.0, vmax=vmax), aspect="auto")
    for i, m in enumerate(methods):
        for j, s in enumerate(scenarios):
            st = status.get((m, s))
            v = rel.iloc[i, j]
            if st == "ok" and np.isfinite(v):
                dark = np.log(v) > 0.5 * np.log(vmax)
                ax.text(j, i, f"{sig(v)}×", ha="center", va="center", fontsize=7, color="white" if dark else "black")
            else:
                face, label = ("#bbbbbb", "n/a") if st == "skipped" else (("#f4b6b6", st) if st else ("white", ""))
                ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, facecolor=face, hatch="///", edgecolor="white", lw=0))
                ax.text(j, i, label, ha="center", va="center", fontsize=7, color="#333333")
    ax.set_xticks(range(len(scenarios)))
    ax.set_xticklabels([f"{s} [{'/'.join(dict.fromkeys(units[s]))}]" if len(units[s]) else s for s in scenarios],
                       fontsize=8)
    ax.xaxis.tick_top()
    ax.set_yticks(range(len(methods)))
    ax.set_yticklabels(methods, fontsize=8)
    ax.set_xticks(np.arange(-0.5, len(scenarios)), minor=True)
    ax.set_yticks(np.arange(-0.5, len(methods)), minor=True)
    ax.grid(which="minor", color="white", lw=1)
    ax.tick_params(which="minor", length=0)
    cb = fig.colorbar(im, ax=ax, fraction=0.05, pad=0.02)
    cb.set_label("RMSE / best RMSE of the scenario", fontsize=8)
    ticks = [t for t in (1, 1.5, 2, 3, 5, 10, 20, 50, 100, 1000) if t <= vmax]
    cb.set_ticks(ticks, labels=[f"{t:g}×" for t in ticks], fontsize=7)
    cb.minorticks_off()
    ax.set_title("RMSE relative to the best method of each scenario (grey: n/a, red: failed)", fontsize=9)
    return save_figure(fig, path)


def report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path, root: Path | None = None) -> str:
    """Write ``matrix.md``, ``matrix.csv``, ``matrix_values.csv`` and ``matrix.png`` into ``out_dir``; return the
    Markdown. ``root``: the sweep folder (or its gathered table) whose ``matrix_cells.csv`` /
    ``skipped_cells.csv`` give the n/a cells and the jobs without results (default: ``out_dir``)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    res = results[results["task"] == TASK] if "task" in results.columns else results
    values = matrix_values(res, out_dir if root is None else Path(root))
    atomic_write_csv(values, out_dir / "matrix_values.csv")
    tab = matrix_table(values)
    ok = values[values["status"] == "ok"]
    eps = sorted(set(ok["episodes"]))
    n = "/".join(str(e) for e in eps) if eps else "0"
    title = (f"The matrix: RMSE (NEES/Dx) runtime per method and scenario; RMSE and NEES/Dx averaged over the "
             f"sensing nodes, mean over {n} test episodes")
    md = write_table(out_dir, "matrix", title, tab)
    counts = values["status"].value_counts()
    names = {"ok": "ok", "skipped": "n/a (the method does not fit the scenario)", "failed": "failed",
             "incomplete": "incomplete (no result)"}
    note = ", ".join(f"{counts[k]} {v}" for k, v in names.items() if k in counts)
    plot_matrix(values, out_dir / "matrix.png")
    blank = ok["nees_pos"].isna().any()
    note += ". No NEES/Dx in parentheses: the method gives no covariance" if blank else ""
    return f"{md}\n\n{len(values)} cells: {note}.\n\n![RMSE relative to the best of each scenario](matrix.png)"


__all__ = ["cell_values", "matrix_values", "matrix_table", "relative_rmse", "plot_matrix", "report", "markdown"]
