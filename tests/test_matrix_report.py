"""The matrix report's intervals, ranks, ties, notes and files on a small synthetic sweep, against direct numpy /
scipy computations (:mod:`dslearn.reports.matrix`)."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from dslearn.reports import matrix as rep

# per (seed, episode) unit the value of each method on scenario "yu" (the sensor average: the two sensors hold
# value -/+ 0.1, the relay 99, which must not count); seeds 0 and 1, episodes 0, 1, 2
UNITS = [(0, 0), (0, 1), (0, 2), (1, 0), (1, 1), (1, 2)]
A = np.array([1.0, 1.2, 0.9, 1.1, 1.3, 1.0])
B = A + np.array([0.05, -0.02, 0.10, 0.03, -0.01, 0.06])  # close to A: a tie
C = A + np.array([0.5, 0.6, 0.55, 0.45, 0.5, 0.6])  # clearly worse
NEES_A = np.array([0.8, 1.1, 0.9, 1.4, 1.0, 1.2])
REASON = "needs position measurements; scenario jiang has squared_range"


def _rows(method, scenario, values, metric="rmse", units="m"):
    rows = []
    for (seed, ep), v in zip(UNITS, values):
        for node, kind, x in (("s1", "sensor", v - 0.1), ("s2", "sensor", v + 0.1), ("relay", "comm", 99.0)):
            rows.append(dict(study="t", task="matrix", seed=seed, method=method, scenario=scenario, units=units,
                             node=node, node_kind=kind, episode=ep, metric=metric, value=x))
    return rows


def _runtime(method, scenario, per_seed):
    return [dict(study="t", task="matrix", seed=s, method=method, scenario=scenario, units="m", node="all",
                 node_kind="all", episode=-1, metric="runtime_s", value=t) for s, t in enumerate(per_seed)]


def _sweep(tmp_path):
    rows = (_rows("ekf a", "yu", A) + _rows("ekf a", "yu", NEES_A, "nees_pos") + _rows("ekf b", "yu", B)
            + _rows("ukf c", "yu", C) + _runtime("ekf a", "yu", [2.0, 4.0]) + _runtime("ekf b", "yu", [1.0, 1.0])
            + _runtime("ukf c", "yu", [5.0, 7.0]))
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    pd.DataFrame(rows).to_csv(sweep / "sweep_results.csv", index=False)
    cells = pd.DataFrame([
        dict(job=0, method="ekf a", scenario="yu", units="m", reason=None, overrides="method=ekf_a scenario=yu_two_agents"),
        dict(job=None, method="ekf a", scenario="jiang", units="m", reason=f"ekf a does not fit scenario jiang: {REASON}",
             overrides="method=ekf_a scenario=jiang"),
        dict(job=1, method="ekf b", scenario="yu", units="m", reason=None,
             overrides="method=ekf_b learner=none scenario=yu_two_agents"),
        dict(job=None, method="ekf b", scenario="jiang", units="m", reason=f"ekf b does not fit scenario jiang: {REASON}",
             overrides="method=ekf_b learner=none scenario=jiang"),
        dict(job=2, method="ukf c", scenario="yu", units="m", reason=None,
             overrides="filter=ukf model=lin scenario=yu_two_agents"),
        dict(job=3, method="ukf c", scenario="jiang", units="m", reason=None, overrides="filter=ukf model=lin scenario=jiang"),
    ])
    cells["job"] = cells["job"].astype("Int64")
    cells.to_csv(sweep / "matrix_cells.csv", index=False)
    cells[cells["reason"].notna()].drop(columns="job").to_csv(sweep / "skipped_cells.csv", index=False)
    (sweep / "3").mkdir()
    (sweep / "3" / "status.json").write_text(json.dumps({"status": "failed", "error": "boom"}))
    return sweep


def _t(x):
    x = np.asarray(x, dtype=float)
    half = stats.t.ppf(0.975, len(x) - 1) * x.std(ddof=1) / math.sqrt(len(x))
    return x.mean(), x.mean() - half, x.mean() + half


def test_t_interval_by_hand():
    # x = 1, 2, 3, 4: mean 2.5, s = sqrt(5/3), t_{0.975, 3} = 3.182446305284263
    m, lo, hi = rep.t_interval([1.0, 2.0, 3.0, 4.0])
    half = 3.182446305284263 * math.sqrt(5 / 3) / 2
    assert (m, lo, hi) == pytest.approx((2.5, 2.5 - half, 2.5 + half), rel=1e-12)
    m, lo, hi = rep.t_interval([3.0])
    assert m == 3.0 and math.isnan(lo) and math.isnan(hi)


def test_units_intervals_ranks_and_ties(tmp_path):
    sweep = _sweep(tmp_path)
    res = pd.read_csv(sweep / "sweep_results.csv")
    units = rep.unit_values(res)
    a = units[units["method"] == "ekf a"].set_index(["seed", "episode"])
    assert a["rmse"].to_numpy() == pytest.approx(A, rel=1e-12)  # the relay's 99 left out
    assert a["nees_pos"].to_numpy() == pytest.approx(NEES_A, rel=1e-12)
    vals = rep.matrix_values(res, sweep).set_index(["method", "scenario"])
    # labels: the options typed (preset, parts beside it, or parts alone) and the scenario option
    assert list(vals.index) == [("ekf_a", "yu_two_agents"), ("ekf_a", "jiang"), ("ekf_b learner=none", "yu_two_agents"),
                                ("ekf_b learner=none", "jiang"), ("filter=ukf model=lin", "yu_two_agents"),
                                ("filter=ukf model=lin", "jiang")]
    for key, x in ((("ekf_a", "yu_two_agents"), A), (("ekf_b learner=none", "yu_two_agents"), B),
                   (("filter=ukf model=lin", "yu_two_agents"), C)):
        r = vals.loc[key]
        assert (r["rmse_mean"], r["rmse_lo"], r["rmse_hi"]) == pytest.approx(_t(x), rel=1e-12)
        assert r["n_units"] == 6 and r["seeds"] == 2
    ra = vals.loc[("ekf_a", "yu_two_agents")]
    assert (ra["nees_pos_per_dim_mean"], ra["nees_pos_per_dim_lo"], ra["nees_pos_per_dim_hi"]) == pytest.approx(_t(NEES_A))
    # the consistent band: chi-square with 2 dof per unit, 12 in all, over 12
    assert (ra["nees_pos_per_dim_consistent_lo"], ra["nees_pos_per_dim_consistent_hi"]) == pytest.approx(
        (stats.chi2.ppf(0.025, 12) / 12, stats.chi2.ppf(0.975, 12) / 12), rel=1e-9)
    assert ra["runtime_s"] == 3.0 and math.isnan(vals.loc[("ekf_b learner=none", "yu_two_agents"), "nees_pos_per_dim_mean"])
    # ranks by mean, ties by the paired difference (B - A: its interval contains 0; C - A does not)
    _, dlo, dhi = _t(B - A)
    assert dlo < 0 < dhi
    _, clo, chi = _t(C - A)
    assert clo > 0
    rb, rc = vals.loc[("ekf_b learner=none", "yu_two_agents")], vals.loc[("filter=ukf model=lin", "yu_two_agents")]
    assert (ra["rank"], rb["rank"], rc["rank"]) == (1, 2, 3)
    assert bool(ra["tied"]) and bool(rb["tied"]) and not bool(rc["tied"])
    assert (rb["diff_to_best_lo"], rb["diff_to_best_hi"]) == pytest.approx((dlo, dhi), rel=1e-12)
    assert (rc["diff_to_best_lo"], rc["diff_to_best_hi"]) == pytest.approx((clo, chi), rel=1e-12)
    # the unpaired intervals of A and B overlap too, but C's does not; the statuses and notes
    assert list(vals["status"]) == ["ok", "skipped", "ok", "skipped", "ok", "failed"]
    assert list(vals["note"].astype("Float64").fillna(0).astype(int)) == [0, 1, 0, 1, 0, 2]  # one note per reason


def test_report_files_columns_and_notes(tmp_path):
    from dslearn.report import report

    sweep = _sweep(tmp_path)
    report(sweep)
    csv = pd.read_csv(sweep / "matrix.csv")
    assert list(csv.columns) == rep.VALUE_COLUMNS
    for c in ("rmse_mean", "rmse_lo", "rmse_hi", "n_units", "seeds", "nees_pos_per_dim_mean", "rank", "tied",
              "status", "note"):
        assert c in csv.columns
    assert csv["rmse_mean"].dtype == float
    md = (sweep / "matrix.md").read_text()
    m, lo, hi = _t(A)
    half = (hi - lo) / 2
    head = "| method | yu_two_agents [m] | jiang [m] |"
    assert head in md
    assert f"| ekf_a | **{rep.sig(m)} ± {rep.sig(half)}** ({rep.sig(NEES_A.mean())}) | – [1] |" in md
    mb, blo, bhi = _t(B)
    assert f"| ekf_b learner=none | ≈ {rep.sig(mb)} ± {rep.sig((bhi - blo) / 2)} | – [1] |" in md
    mc, clo, chi = _t(C)
    assert f"| filter=ukf model=lin | {rep.sig(mc)} ± {rep.sig((chi - clo) / 2)} | – [2] |" in md
    # the reason once, in its note (the scenario named by the column: "the scenario"), never in a cell
    short = REASON.replace("scenario jiang", "the scenario")
    assert f"[1] {short}" in md and "[2] the job failed" in md and md.count(short) == 1
    assert "position NEES / 2A" in md and "≈" in md and "**Bold**" in md
    board = pd.read_csv(sweep / "leaderboard.csv")
    assert list(board["method"]) == ["ekf_a", "ekf_b learner=none", "filter=ukf model=lin"]
    assert list(board["rank"]) == [1, 2, 3] and list(board["tied"]) == [True, True, False]
    lb = (sweep / "leaderboard.md").read_text()
    assert "## yu_two_agents" in lb and "consistent band" in lb
    assert (sweep / "matrix.png").stat().st_size > 10_000


def test_one_seed_one_unit_has_no_interval_and_no_tie():
    rows = []
    for method, v in (("a", 1.0), ("b", 1.5)):
        rows.append(dict(task="matrix", seed=0, method=method, scenario="yu", units="m", node="s1", node_kind="sensor",
                         episode=0, metric="rmse", value=v))
    vals = rep.matrix_values(pd.DataFrame(rows)).set_index("method")
    assert vals.loc["a", "rmse_mean"] == 1.0 and math.isnan(vals.loc["a", "rmse_lo"])
    assert bool(vals.loc["a", "tied"]) and not bool(vals.loc["b", "tied"]) and vals.loc["b", "rank"] == 2
    assert rep.cell_text(vals.reset_index().iloc[0]) == "**1.00**"


def test_a_single_run_folder_is_labelled_by_its_overrides(tmp_path):
    rows = _rows("ekf a", "yu", A)
    (tmp_path / "meta.json").write_text(json.dumps({"overrides": ["task=matrix", "method=ekf_a", "learner=none",
                                                                  "scenario=yu_two_agents", "task.seeds=2"]}))
    vals = rep.matrix_values(pd.DataFrame(rows), tmp_path)
    assert list(vals["method"]) == ["ekf_a learner=none"] and list(vals["scenario"]) == ["yu_two_agents"]
    assert list(vals["method_label"]) == ["ekf a"] and list(vals["scenario_name"]) == ["yu"]
    assert rep.option_labels(["filter=ukf", "model=lin", "consensus=ci", "scenario=liu_s1", "seed=3"]) == (
        "filter=ukf model=lin consensus=ci", "liu_s1")
    # the associator is a part too: a preset swept over it gives one row per associator
    assert rep.option_labels(["method=ekf_lin_hybrid_gnn", "associator=jpda", "scenario=yu_crowd_clutter"]) == (
        "ekf_lin_hybrid_gnn associator=jpda", "yu_crowd_clutter")
