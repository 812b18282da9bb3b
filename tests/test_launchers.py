"""The comparison matrix gives the same table on every Hydra launcher: one small matrix sub-sweep (2 jobs that fit,
2 n/a cells) run with the basic launcher (in-process), joblib (the default, worker processes) and submitit's
local mode (one process per job, its folder under the sweep dir), each reported with ``dslearn-report``; the
values of ``matrix.csv`` must be equal to the last bit (same seeds, same random streams), the run time
aside, and the n/a cells the same. Ray is not tested here (it stays out of CI: experiments/matrix/README.md).

Runs the installed commands in subprocesses, as tests/test_matrix.py's real sweep does."""

import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

pytest.importorskip("hydra_plugins.hydra_submitit_launcher",
                    reason="hydra-submitit-launcher is not installed (pip install -e \".[slurm]\")")

BIN = Path(sys.executable).parent  # the installed commands dslearn-run, dslearn-report (as in tests/test_matrix.py)

pytestmark = pytest.mark.slow

GRID = ["experiment=matrix_small", "method=ekf_lin_hybrid,dgpt_rbcm", "scenario=yu_two_agents,jiang",
        "task.train_episodes=2", "task.test_episodes=2", "task.seeds=1"]
LAUNCHERS = {
    "basic": ["hydra/launcher=basic"],
    "joblib": ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"],
    # the plugin's defaults (timeout 60 min, its folder ${hydra.sweep.dir}/.submitit/%j) are what a user gets
    "submitit_local": ["hydra/launcher=submitit_local"],
}
TIMES = ["runtime_s"]  # the only column that may differ between launchers


@pytest.fixture(scope="module")
def sweeps(tmp_path_factory):
    """launcher -> its sweep dir, swept and reported."""
    base = tmp_path_factory.mktemp("launchers")
    env = {**os.environ, "CI": "1"}
    out = {}
    for name, args in LAUNCHERS.items():
        sweep = base / name
        r = subprocess.run([str(BIN / "dslearn-run"), *GRID, *args, f"hydra.sweep.dir={sweep}"], cwd=base, env=env,
                           capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, (name, r.stderr[-3000:])
        r = subprocess.run([str(BIN / "dslearn-report"), str(sweep)], cwd=base, env=env, capture_output=True,
                           text=True, timeout=300)
        assert r.returncode == 0, (name, r.stderr[-3000:])
        out[name] = sweep
    return out


def _values(sweep):
    return pd.read_csv(sweep / "matrix.csv", keep_default_na=False, dtype=str)


def test_matrix_values_equal_on_every_launcher(sweeps):
    base = _values(sweeps["basic"])
    # the sweep's cells: 2 jobs on yu, the 2 on jiang dropped (position methods, squared-range sensors)
    assert list(zip(base["method"], base["scenario"], base["status"])) == [
        ("ekf_lin_hybrid", "yu_two_agents", "ok"), ("ekf_lin_hybrid", "jiang", "skipped"),
        ("dgpt_rbcm", "yu_two_agents", "ok"), ("dgpt_rbcm", "jiang", "skipped")]
    assert list(base["job"]) == ["0", "", "1", ""]
    for name, sweep in sweeps.items():
        vals = _values(sweep)
        assert list(vals.columns) == list(base.columns), name
        cols = [c for c in base.columns if c not in TIMES]
        # as text: the CSV writes every float at full precision, so equal text = equal float64 values
        pd.testing.assert_frame_equal(vals[cols], base[cols], obj=f"matrix.csv of {name} vs basic")
        ok = vals["status"] == "ok"
        assert (vals.loc[ok, "runtime_s"].astype(float) > 0).all(), name
        # each cell's RMSE is its job's own rows' (sensor average per episode, mean over episodes), to the bit
        for _, row in vals[ok].iterrows():
            res = pd.read_csv(sweep / row["job"] / "results.csv")
            sens = res[(res["node_kind"] == "sensor") & (res["metric"] == "rmse")]
            assert float(row["rmse_mean"]) == sens.groupby("episode")["value"].mean().mean(), (name, row["method"])
            assert int(row["n_units"]) == 2 == sens["episode"].nunique() and row["seeds"] == "1"
        # every job's rows equal the basic launcher's (the run time aside)
        for job in ("0", "1"):
            a, b = (pd.read_csv(s / job / "results.csv") for s in (sweep, sweeps["basic"]))
            keep = lambda d: d[d["metric"] != "runtime_s"].reset_index(drop=True)  # noqa: E731
            pd.testing.assert_frame_equal(keep(a), keep(b), check_exact=True, obj=f"{name} job {job}")


def test_na_cells_and_folders_equal_on_every_launcher(sweeps):
    tables = {n: _values(s).set_index(["method", "scenario"]) for n, s in sweeps.items()}
    for name, tab in tables.items():
        jiang = tab.xs("jiang", level="scenario")
        assert (jiang["status"] == "skipped").all() and (jiang["note"] != "").all(), (name, jiang)
        assert jiang["reason"].equals(tables["basic"].xs("jiang", level="scenario")["reason"]), name
        assert (tab.xs("yu_two_agents", level="scenario")["status"] == "ok").all(), name
        skipped = pd.read_csv(sweeps[name] / "skipped_cells.csv")
        assert skipped.equals(pd.read_csv(sweeps["basic"] / "skipped_cells.csv")), name
        jobs = sorted(p.name for p in sweeps[name].iterdir() if p.is_dir() and not p.name.startswith("."))
        assert jobs == ["0", "1"], (name, jobs)  # no folder for a dropped cell, whatever the launcher
    # submitit keeps its own files (pickles, logs) under the sweep dir, in .submitit/<job id>/, one per job
    sub = sweeps["submitit_local"] / ".submitit"
    assert sub.is_dir() and len([p for p in sub.iterdir() if p.is_dir() and p.name.isdigit()]) == 2
