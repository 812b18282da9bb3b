r"""Report of task ``matrix`` (the comparison matrix): rows methods, columns scenarios, with 95 % intervals.

**Units.** The unit of a cell is one (seed, test episode): its value is the per-episode metric averaged over
the reporting sensing nodes (the "sensor average"; every reporting node where none is marked sensing). A
cell reports the mean over its units and the 95 % t-interval of that mean (``mean ± t_{0.975, n-1} s / √n``;
no interval for one unit). ``task.seeds`` gives a cell several draws (seeds), so ``n = seeds × test
episodes``.

**Ranks and ties.** Per scenario the cells are ranked by their mean RMSE (1 = best). A cell is *tied* with
the best where the 95 % t-interval of the *paired* difference of its RMSE to the best's (matched on the same
seed and test episode: the same world, the same tracks) contains 0.

**NEES.** ``nees_pos`` is the position NEES of every target's position block over its ``2A`` degrees of
freedom (``A`` targets), averaged over the steps: 1 for a consistent estimator. The consistent band given is
the χ² 95 % band of the mean over the cell's units with ``2`` degrees of freedom per unit (one target: the
widest band; with more targets a consistent filter's band is narrower)
(:func:`dslearn.metrics.trajectories.nees_band`).

**Labels.** A row is the option a user types: the preset (``ekf_lin_hybrid`` of ``method=ekf_lin_hybrid``) and
any part chosen beside it, or the parts' options where no preset was used (``filter=ukf model=lin
consensus=ci``); a column is the scenario option (``liu_s1``). They are read from the sweep's
``matrix_cells.csv`` or the gathered table's ``ov.*`` columns; without either, the method's and the
scenario's own labels.

Files: ``matrix.md`` (RMSE ± 95 % half-interval and the NEES per cell; the best of each scenario bold, the
ties marked ≈; ``–`` with a numbered note per distinct reason a cell has no number), ``matrix.csv`` (one row
per method × scenario, numbers at full precision: :data:`VALUE_COLUMNS`), ``leaderboard.md`` /
``leaderboard.csv`` (per scenario the methods in rank order with the paired difference to the best) and
``matrix.png`` (per scenario every method's RMSE with its 95 % interval, the best and the ties marked).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd

from dslearn.io import atomic_write_csv, atomic_write_text, check_complete
from dslearn.reports.tables import markdown, save_figure, sig

TASK = "matrix"
#: the sweep's files (written by the matrix sweeper; see :mod:`dslearn.studies.matrix`)
CELLS_FILE, SKIPPED_FILE = "matrix_cells.csv", "skipped_cells.csv"
#: the name of the NEES the matrix reports, as every table, figure and CSV column says it
NEES_NAME = "position NEES/2A"
NEES_TEXT = ("position NEES / 2A: the NEES of the targets' positions over their 2A degrees of freedom (A targets), "
             "mean over the steps; 1 = consistent")
#: the parts of a method a row label names (beside the preset)
PART_GROUPS = ("method", "filter", "model", "observation", "consensus", "learner", "associator")
VALUE_COLUMNS = ["method", "scenario", "method_label", "scenario_name", "units", "status", "rmse_mean", "rmse_lo",
                 "rmse_hi", "n_units", "seeds", "nees_pos_per_dim_mean", "nees_pos_per_dim_lo",
                 "nees_pos_per_dim_hi", "nees_pos_per_dim_consistent_lo", "nees_pos_per_dim_consistent_hi",
                 "runtime_s", "rank", "tied", "diff_to_best_lo", "diff_to_best_hi", "note", "reason", "job"]
TIED_MARK = "≈"


# ------------------------------------------------------------------------------------------------------------
# numbers

def t_interval(x, level: float = 0.95) -> tuple[float, float, float]:
    """``(mean, lo, hi)``: the mean of ``x`` and the two-sided ``level`` t-interval of the mean (NaN bounds for
    fewer than two values; NaN values are left out)."""
    from scipy.stats import t

    a = np.asarray(x, dtype=float)
    a = a[np.isfinite(a)]
    n = len(a)
    if n == 0:
        return float("nan"), float("nan"), float("nan")
    m = float(a.mean())
    if n < 2:
        return m, float("nan"), float("nan")
    half = float(t.ppf(0.5 + level / 2, n - 1)) * float(a.std(ddof=1)) / math.sqrt(n)
    return m, m - half, m + half


def unit_values(results: pd.DataFrame) -> pd.DataFrame:
    """One row per (method, scenario, seed, test episode) of a matrix results table: ``rmse`` and ``nees_pos``,
    each the mean over the reporting sensing nodes (every reporting node where none is marked sensing; NaN
    where the metric is absent)."""
    return _units(_numeric(results))


def _numeric(results: pd.DataFrame) -> pd.DataFrame:
    """A copy of a results table with numeric ``value`` and a ``seed`` column (0 for results written before
    ``task.seeds``)."""
    df = results.copy()
    df["value"] = pd.to_numeric(df["value"], errors="coerce")
    if "seed" not in df.columns:
        df["seed"] = 0
    return df


def _units(df: pd.DataFrame) -> pd.DataFrame:
    """:func:`unit_values` of a table already made numeric (:func:`_numeric`)."""
    out = []
    for (method, scenario), g in df.groupby(["method", "scenario"], sort=False):
        nodes = g[g["node_kind"] == "sensor"] if (g["node_kind"] == "sensor").any() else g[g["node_kind"] != "all"]
        per = {m: nodes[nodes["metric"] == m].groupby(["seed", "episode"])["value"].mean()
               for m in ("rmse", "nees_pos")}
        idx = per["rmse"].index
        out.append(pd.DataFrame({"method": str(method), "scenario": str(scenario),
                                 "seed": idx.get_level_values(0).astype(int),
                                 "episode": idx.get_level_values(1).astype(int),
                                 "rmse": per["rmse"].to_numpy(),
                                 "nees_pos": per["nees_pos"].reindex(idx).to_numpy()}))
    cols = ["method", "scenario", "seed", "episode", "rmse", "nees_pos"]
    return pd.concat(out, ignore_index=True)[cols] if out else pd.DataFrame(columns=cols)


def cell_values(results: pd.DataFrame) -> pd.DataFrame:
    """One row per (method, scenario) with results: ``rmse_mean/lo/hi`` and ``nees_pos_per_dim_mean/lo/hi``
    (:func:`t_interval` over the cell's units, :func:`unit_values`), ``n_units``, ``seeds``, the consistent band
    of the NEES and ``runtime_s`` (the method's learning and estimation time, mean over the seeds)."""
    from dslearn.metrics.trajectories import nees_band

    df = _numeric(results)
    units = _units(df)
    out = []
    for (method, scenario), u in units.groupby(["method", "scenario"], sort=False):
        g = df[(df["method"].astype(str) == method) & (df["scenario"].astype(str) == scenario)]
        row = {"method_label": method, "scenario_name": scenario,
               "units": str(g["units"].iloc[0]) if "units" in g.columns and len(g) else ""}
        row["rmse_mean"], row["rmse_lo"], row["rmse_hi"] = t_interval(u["rmse"])
        row["n_units"], row["seeds"] = int(u["rmse"].notna().sum()), int(u["seed"].nunique())
        nees = u["nees_pos"].dropna()
        row["nees_pos_per_dim_mean"], row["nees_pos_per_dim_lo"], row["nees_pos_per_dim_hi"] = t_interval(nees)
        lo, hi = nees_band(2, len(nees)) if len(nees) else (float("nan"), float("nan"))
        row["nees_pos_per_dim_consistent_lo"], row["nees_pos_per_dim_consistent_hi"] = lo, hi
        rt = g[g["metric"] == "runtime_s"]
        row["runtime_s"] = float(rt.groupby("seed")["value"].mean().mean()) if len(rt) else float("nan")
        out.append(row)
    cols = ["method_label", "scenario_name", "units", "rmse_mean", "rmse_lo", "rmse_hi", "n_units", "seeds",
            "nees_pos_per_dim_mean", "nees_pos_per_dim_lo", "nees_pos_per_dim_hi", "nees_pos_per_dim_consistent_lo",
            "nees_pos_per_dim_consistent_hi", "runtime_s"]
    return pd.DataFrame(out, columns=cols)


def rank_and_ties(values: pd.DataFrame, units: pd.DataFrame) -> pd.DataFrame:
    """``values`` (one row per cell, :data:`VALUE_COLUMNS`' keys) with ``rank`` (per scenario, by mean RMSE, 1 =
    best, among the cells with a number), ``tied`` (the best, and every cell whose 95 % t-interval of the paired
    RMSE difference to the best, matched on seed and test episode, contains 0) and that interval
    (``diff_to_best_lo/hi``; 0 for the best; NaN with fewer than two matched units, then not tied)."""
    v = values.copy()
    v["rank"], v["tied"] = pd.array([pd.NA] * len(v), dtype="Int64"), pd.array([pd.NA] * len(v), dtype="boolean")
    v["diff_to_best_lo"], v["diff_to_best_hi"] = np.nan, np.nan
    key = units.set_index(["method", "scenario", "seed", "episode"])["rmse"].sort_index()
    for scen, g in v[(v["status"] == "ok") & v["rmse_mean"].notna()].groupby("scenario_name", sort=False):
        order = g.sort_values("rmse_mean", kind="stable").index
        best = order[0]
        b = key.loc[(v.at[best, "method_label"], scen)]
        for r, i in enumerate(order, start=1):
            v.at[i, "rank"] = r
            if i == best:
                v.at[i, "tied"], v.at[i, "diff_to_best_lo"], v.at[i, "diff_to_best_hi"] = True, 0.0, 0.0
                continue
            d = (key.loc[(v.at[i, "method_label"], scen)] - b).dropna()  # matched on (seed, episode)
            _, lo, hi = t_interval(d)
            v.at[i, "diff_to_best_lo"], v.at[i, "diff_to_best_hi"] = lo, hi
            v.at[i, "tied"] = bool(np.isfinite(lo) and lo <= 0.0 <= hi)
    return v


# ------------------------------------------------------------------------------------------------------------
# the cells of a sweep

def _sweep_dir(root: Path | None) -> Path | None:
    if root is None:
        return None
    root = Path(root)
    return root if root.is_dir() else root.parent


def _read_cells(sweep: Path | None, name: str) -> pd.DataFrame | None:
    if sweep is None or not (sweep / name).is_file():
        return None
    return pd.read_csv(sweep / name, dtype={"method": str, "scenario": str, "units": str, "reason": str,
                                            "overrides": str, "status": str, "error": str})


def _short_reason(reason: str, method: str, scenario: str) -> str:
    """The reason without the leading ``<method> does not fit scenario <scenario>: `` (the row and column say it)
    and with ``scenario <scenario>`` written ``the scenario``."""
    import re

    head = f"{method} does not fit scenario {scenario}: "
    reason = reason[len(head):] if reason.startswith(head) else reason
    # the column names the scenario: "scenario s1" -> "the scenario", so one note serves every column it fits
    return re.sub(rf"\bscenario {re.escape(scenario)}(?![\w.-])", "the scenario", reason)


def option_labels(lines) -> tuple[str | None, str | None]:
    """``(row, column)`` labels of a combination's override lines: the preset and the other parts' options
    (``ekf_gp_hybrid learner=none``; ``filter=ukf model=lin consensus=ci`` without a preset) and the scenario
    option; ``None`` for what the lines do not say."""
    opts = {}
    for line in lines:
        key, sep, value = str(line).partition("=")
        key = key.lstrip("+~")
        if sep and key in (*PART_GROUPS, "scenario"):
            opts[key] = value
    parts = [opts["method"]] if "method" in opts else []
    parts += [f"{g}={opts[g]}" for g in PART_GROUPS[1:] if g in opts]
    return (" ".join(parts) or None), opts.get("scenario")


def _label_maps(results: pd.DataFrame, cells: pd.DataFrame | None, run_dir: Path | None = None) -> dict:
    """``{(method label, scenario name): (row option, column option)}`` from the sweep's records, the gathered
    table's ``ov.*`` columns or a single run's ``meta.json`` (its overrides)."""
    out = {}
    one = len(results[["method", "scenario"]].drop_duplicates()) == 1
    if run_dir is not None and one and (run_dir / "meta.json").is_file():  # a single run's folder
        try:
            lines = json.loads((run_dir / "meta.json").read_text(encoding="utf-8")).get("overrides") or []
        except (OSError, ValueError, AttributeError):
            lines = []
        key = (str(results["method"].iloc[0]), str(results["scenario"].iloc[0]))
        out[key] = option_labels(lines)
    if cells is not None and "overrides" in cells.columns:
        for c in cells.to_dict("records"):
            lines = str(c.get("overrides") or "").split()
            out[(str(c["method"]), str(c["scenario"]))] = option_labels(lines)
    ov = [c for c in results.columns if str(c).startswith("ov.")]
    if ov:
        keys = results[["method", "scenario", *ov]].drop_duplicates(["method", "scenario"])
        for r in keys.to_dict("records"):
            lines = [f"{k[3:]}={r[k]}" for k in ov if pd.notna(r[k]) and str(r[k]) != ""]
            out.setdefault((str(r["method"]), str(r["scenario"])), option_labels(lines))
    return out


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


def _empty_row(method: str, scenario: str, units, status: str, reason, job) -> dict:
    return {"method_label": method, "scenario_name": scenario, "units": units, "status": status, "n_units": 0,
            "seeds": 0, "reason": reason, "job": job}


def matrix_values(results: pd.DataFrame, root: Path | None = None) -> pd.DataFrame:
    """Every cell of the matrix (:data:`VALUE_COLUMNS`): the cells with results (:func:`cell_values`, ranked,
    :func:`rank_and_ties`), the sweep's dropped combinations (``skipped``, shown ``–`` with their reason as a
    note) and its jobs without results (``failed`` / ``incomplete``), in the sweep's order (``matrix_cells.csv``;
    results-only cells after it). ``note``: the number of the cell's reason among the distinct reasons."""
    sweep = _sweep_dir(root)
    vals = cell_values(results)
    vals["status"], vals["reason"], vals["job"] = "ok", None, pd.NA
    cells = _read_cells(sweep, CELLS_FILE)
    if cells is None:  # no sweep record: the skipped list alone, where there is one
        cells = _read_cells(sweep, SKIPPED_FILE)
    labels = _label_maps(results, cells, sweep)
    rows = []
    have = {(m, s): i for i, (m, s) in enumerate(zip(vals["method_label"], vals["scenario_name"]))}
    used = set()
    for c in [] if cells is None else cells.to_dict("records"):
        key = (str(c["method"]), str(c["scenario"]))
        reason = c.get("reason")
        if _failed_up_front(c):  # its parts raised in the sweep's up-front check: not run, failed (not n/a)
            rows.append(_empty_row(*key, c.get("units", ""), "failed", f"{FAILED_UP_FRONT}: {c['error']}", pd.NA))
        elif isinstance(reason, str) and reason:
            rows.append(_empty_row(*key, c.get("units", ""), "skipped", _short_reason(reason, *key), pd.NA))
        elif key in have:
            if key not in used:
                r = vals.iloc[have[key]].to_dict()
                r["job"] = c.get("job", pd.NA)
                rows.append(r)
        else:
            rows.append(_empty_row(*key, c.get("units", ""), _job_status(sweep, c.get("job")), None,
                                   c.get("job", pd.NA)))
        used.add(key)
    rows += [vals.iloc[i].to_dict() for k, i in have.items() if k not in used]
    out = pd.DataFrame(rows)
    for c in VALUE_COLUMNS:
        if c not in out.columns:
            out[c] = np.nan
    out["method"] = [labels.get((m, s), (None, None))[0] or m for m, s in zip(out["method_label"], out["scenario_name"])]
    out["scenario"] = [labels.get((m, s), (None, None))[1] or s for m, s in zip(out["method_label"], out["scenario_name"])]
    out = rank_and_ties(out, unit_values(results))
    notes = {}
    for i, r in out.iterrows():
        why = _note_text(r)
        if why is not None:
            notes.setdefault(why, len(notes) + 1)
            out.at[i, "note"] = notes[why]
    out = out[VALUE_COLUMNS]
    out["job"] = pd.array(out["job"], dtype="Int64")
    out["note"] = pd.array(out["note"], dtype="Int64")
    out["n_units"], out["seeds"] = out["n_units"].fillna(0).astype(int), out["seeds"].fillna(0).astype(int)
    return out


# --- a cell that failed in the sweep's up-front check (matrix_cells.csv: status failed, with its error) --------
#: the note's head of such a cell (its error follows)
FAILED_UP_FRONT = "failed in the sweep's up-front check (not run)"


def _failed_up_front(c: dict) -> bool:
    """A record of ``matrix_cells.csv`` whose parts raised while the sweep's up-front check built them."""
    return str(c.get("status", "")) == "failed" and isinstance(c.get("error"), str) and bool(c["error"])
# ------------------------------------------------------------------------------------------------------------


def _note_text(r) -> str | None:
    """The footnote of a cell without a number (``None`` for a cell with one)."""
    if r["status"] == "skipped":
        return str(r["reason"])
    if r["status"] == "failed" and isinstance(r["reason"], str) and r["reason"]:  # failed up front: its error
        return str(r["reason"])
    if r["status"] == "failed":
        return "the job failed (its status.json and run.log say why)"
    if r["status"] == "incomplete":
        return "the job has no complete result (killed, or not run yet)"
    return None


# ------------------------------------------------------------------------------------------------------------
# tables

def cell_text(r) -> str:
    """The table's text of one cell of :func:`matrix_values`: ``RMSE ± half-interval (NEES)``, bold for the best
    of its scenario, ``≈`` for a tie with it; ``– [k]`` (note ``k``) for a cell without a number; ``✗ failed [k]``
    for one that failed in the sweep's up-front check (note ``k``: its error)."""
    if r["status"] == "failed" and str(r["reason"]).startswith(FAILED_UP_FRONT):  # a fault, not a verdict: a
        return f"✗ failed [{int(r['note'])}]" if pd.notna(r["note"]) else "✗ failed"  # marker; the note: the error
    if r["status"] != "ok":
        return f"– [{int(r['note'])}]" if pd.notna(r["note"]) else "–"
    half = (r["rmse_hi"] - r["rmse_lo"]) / 2
    txt = f"{sig(r['rmse_mean'])} ± {sig(half)}" if np.isfinite(half) else sig(r["rmse_mean"])
    if pd.notna(r["rank"]) and int(r["rank"]) == 1:
        txt = f"**{txt}**"
    elif pd.notna(r["tied"]) and bool(r["tied"]):
        txt = f"{TIED_MARK} {txt}"
    if pd.notna(r["nees_pos_per_dim_mean"]):
        txt += f" ({sig(r['nees_pos_per_dim_mean'])})"
    return txt


def _column_head(values: pd.DataFrame, scenario: str) -> str:
    u = [x for x in dict.fromkeys(values.loc[values["scenario"] == scenario, "units"].dropna().astype(str))
         if x and x != "1" and x != "nan"]
    return f"{scenario} [{'/'.join(u)}]" if u else scenario


def matrix_table(values: pd.DataFrame) -> pd.DataFrame:
    """Rows methods, columns scenarios (in first-seen order), cells :func:`cell_text`; an empty cell is a
    combination the sweep did not have."""
    methods = list(dict.fromkeys(values["method"]))
    scenarios = list(dict.fromkeys(values["scenario"]))
    text = {(r["method"], r["scenario"]): cell_text(r) for _, r in values.iterrows()}
    tab = pd.DataFrame({"method": methods})
    for s in scenarios:
        tab[_column_head(values, s)] = [text.get((m, s), "") for m in methods]
    return tab


def notes_text(values: pd.DataFrame) -> str:
    """The numbered notes of the cells without a number, one line each."""
    seen = values.dropna(subset=["note"]).drop_duplicates("note").sort_values("note")
    return "\n".join(f"[{int(r['note'])}] {_note_text(r)}" for _, r in seen.iterrows())


def legend_text(values: pd.DataFrame) -> str:
    ok = values[values["status"] == "ok"]
    n = "/".join(str(x) for x in sorted(set(ok["n_units"]))) or "0"
    s = "/".join(str(x) for x in sorted(set(ok["seeds"]))) or "0"
    return (f"Cell: RMSE ± 95 % half-interval ({NEES_NAME}). RMSE in the column's unit; the unit of a cell is one "
            f"(seed, test episode) ({n} units per cell: {s} seed(s) × test episodes), its value the per-episode "
            f"metric averaged over the sensing nodes; the interval is the 95 % t-interval of the mean. "
            f"**Bold**: the best (lowest mean RMSE) of the scenario; {TIED_MARK}: tied with the best (the 95 % "
            f"t-interval of the paired RMSE difference to the best, matched on seed and episode, contains 0). "
            f"In parentheses the {NEES_TEXT} (its consistent 95 % band for the cell's units is in matrix.csv); "
            f"none where the method gives no covariance. –: no number, for the numbered reason below.")


def leaderboard(values: pd.DataFrame) -> pd.DataFrame:
    """Per scenario (in order) its cells with a number, best first: rank, RMSE with its interval, the paired
    difference to the best, tied, the NEES with its consistent band."""
    ok = values[(values["status"] == "ok") & values["rank"].notna()].copy()
    order = {s: i for i, s in enumerate(dict.fromkeys(values["scenario"]))}
    ok["_o"] = ok["scenario"].map(order)
    ok = ok.sort_values(["_o", "rank"], kind="stable")
    cols = ["scenario", "rank", "method", "units", "rmse_mean", "rmse_lo", "rmse_hi", "diff_to_best_lo",
            "diff_to_best_hi", "tied", "n_units", "seeds", "nees_pos_per_dim_mean", "nees_pos_per_dim_lo",
            "nees_pos_per_dim_hi", "nees_pos_per_dim_consistent_lo", "nees_pos_per_dim_consistent_hi", "runtime_s"]
    return ok[cols].reset_index(drop=True)


def leaderboard_markdown(board: pd.DataFrame) -> str:
    parts = [f"# Leaderboard: per scenario, best first\n\nRMSE: mean and 95 % t-interval over the (seed, test episode) "
             f"units; Δ to best: the 95 % t-interval of the paired RMSE difference to the best (matched on seed and "
             f"episode); tied: it contains 0. {NEES_TEXT}; band: its consistent 95 % band for the cell's units."]
    for scen, g in board.groupby("scenario", sort=False):
        unit = str(g["units"].iloc[0]) if len(g) else ""
        rows = pd.DataFrame({
            "rank": g["rank"].astype(int),
            "method": g["method"],
            f"RMSE [{unit}]": [sig(m) for m in g["rmse_mean"]],
            "95 % interval": [f"[{sig(a)}, {sig(b)}]" for a, b in zip(g["rmse_lo"], g["rmse_hi"])],
            "Δ to best, 95 %": [f"[{sig(a)}, {sig(b)}]" for a, b in zip(g["diff_to_best_lo"], g["diff_to_best_hi"])],
            "tied": ["yes" if bool(t) else "no" for t in g["tied"]],
            NEES_NAME: [sig(m) for m in g["nees_pos_per_dim_mean"]],
            "consistent band": [f"[{sig(a)}, {sig(b)}]" if np.isfinite(a) else "-"
                                for a, b in zip(g["nees_pos_per_dim_consistent_lo"], g["nees_pos_per_dim_consistent_hi"])],
            "units": g["n_units"].astype(int),
        })
        parts.append(f"## {scen}\n\n{markdown(rows)}")
    return "\n\n".join(parts) + "\n"


# ------------------------------------------------------------------------------------------------------------
# figure

def plot_matrix(values: pd.DataFrame, path: Path) -> Path:
    """``matrix.png``: one panel per scenario, every method's mean RMSE with its 95 % interval (log scale), the
    best filled black, the ties filled blue, the others open; methods without a number listed as n/a."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    scenarios = list(dict.fromkeys(values["scenario"]))
    methods = list(dict.fromkeys(values["method"]))
    cols = min(4, max(1, len(scenarios)))
    nrows = math.ceil(len(scenarios) / cols) if scenarios else 1
    fig, axes = plt.subplots(nrows, cols, figsize=(3.6 * cols + 1.8, 0.8 + nrows * (0.9 + 0.24 * len(methods))),
                             squeeze=False, sharey=True)
    for k, ax in enumerate(axes.ravel()):
        if k >= len(scenarios):
            ax.axis("off")
            continue
        s = scenarios[k]
        g = values[values["scenario"] == s].set_index("method")
        for i, m in enumerate(methods):
            if m not in g.index:
                continue
            r = g.loc[m]
            if r["status"] != "ok" or not np.isfinite(r["rmse_mean"]):
                ax.text(0.02, i, "n/a" if r["status"] == "skipped" else str(r["status"]), va="center", fontsize=6.5,
                        color="red" if r["status"] == "failed" else "0.5", transform=ax.get_yaxis_transform())
                continue
            best = pd.notna(r["rank"]) and int(r["rank"]) == 1
            tied = pd.notna(r["tied"]) and bool(r["tied"]) and not best
            colour = "black" if best else ("#1f77b4" if tied else "0.45")
            lo, hi = r["rmse_lo"], r["rmse_hi"]
            if np.isfinite(lo) and np.isfinite(hi):
                ax.plot([max(lo, 1e-12), hi], [i, i], color=colour, lw=1.6)
            ax.plot(r["rmse_mean"], i, "o", ms=5, mec=colour, mfc=colour if (best or tied) else "white")
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:.4g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_title(_column_head(values, s), fontsize=9)
        ax.set_xlabel("RMSE (95 % interval)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(axis="x", color="0.9", lw=0.6)
        ax.set_ylim(len(methods) - 0.5, -0.5)
    for row in axes:
        row[0].set_yticks(range(len(methods)))
        row[0].set_yticklabels(methods, fontsize=7)
    fig.suptitle("RMSE per method and scenario: mean and 95 % t-interval over the (seed, test episode) units\n"
                 "● black: the best of the scenario; ● blue: tied with the best (the 95 % interval of the paired "
                 "difference contains 0); ○ grey: worse", fontsize=8.5)
    return save_figure(fig, path)


def relative_rmse(values: pd.DataFrame) -> pd.DataFrame:
    """Rows methods, columns scenarios: each cell's mean RMSE over the smallest of its scenario (NaN where the
    cell has no RMSE)."""
    ok = values[values["status"] == "ok"]
    best = ok.groupby("scenario")["rmse_mean"].min()
    rel = values.assign(rel=[r["rmse_mean"] / best[r["scenario"]] if r["status"] == "ok" else np.nan
                             for _, r in values.iterrows()])
    tab = rel.pivot_table(index="method", columns="scenario", values="rel", aggfunc="first", dropna=False)
    return tab.reindex(index=list(dict.fromkeys(values["method"])), columns=list(dict.fromkeys(values["scenario"])))


def report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path, root: Path | None = None) -> str:
    """Write ``matrix.md``, ``matrix.csv``, ``leaderboard.md``, ``leaderboard.csv`` and ``matrix.png`` into
    ``out_dir``; return the Markdown. ``root``: the sweep folder (or its gathered table) whose
    ``matrix_cells.csv`` / ``skipped_cells.csv`` give the n/a cells and the jobs without results (default:
    ``out_dir``)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    res = results[results["task"] == TASK] if "task" in results.columns else results
    values = matrix_values(res, out_dir if root is None else Path(root))
    atomic_write_csv(values, out_dir / "matrix.csv")
    board = leaderboard(values)
    atomic_write_csv(board, out_dir / "leaderboard.csv")
    atomic_write_text(out_dir / "leaderboard.md", leaderboard_markdown(board))
    counts = values["status"].value_counts()
    names = {"ok": "with numbers", "skipped": "n/a (the method does not fit the scenario, or left out)",
             "failed": "failed", "incomplete": "incomplete (no result)"}
    count = ", ".join(f"{counts[k]} {v}" for k, v in names.items() if k in counts)
    notes = notes_text(values)
    md = (f"# The matrix: RMSE ± 95 % half-interval ({NEES_NAME})\n\n{legend_text(values)}\n\n"
          f"{markdown(matrix_table(values))}\n\n" + (f"Notes:\n\n{notes}\n\n" if notes else "")
          + f"{len(values)} cells: {count}. Per-scenario ranking: leaderboard.md.\n")
    atomic_write_text(out_dir / "matrix.md", md)
    plot_matrix(values, out_dir / "matrix.png")
    return f"{md}\n![RMSE and 95 % intervals per scenario](matrix.png)"


__all__ = ["t_interval", "unit_values", "cell_values", "rank_and_ties", "matrix_values", "matrix_table",
           "leaderboard", "relative_rmse", "plot_matrix", "report", "markdown"]
