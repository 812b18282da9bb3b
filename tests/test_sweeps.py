"""Sweeps: completeness marker, gathering one table per sweep, launchers, kill-and-resume."""

import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pandas as pd
import pytest

from dslearn.callbacks import gather_sweep, parse_overrides
from dslearn.io import check_complete, load_results
from dslearn.app.record import execute

ROOT = Path(__file__).resolve().parents[1]
TINY = ["data.train_episodes=0", "data.test_episodes=2"]
GRID = ["model=lin,sfm", "consensus=individual,hybrid"]
KEYS = ["ov.model", "ov.consensus", "node", "episode", "metric"]


def _sweep(sweep_dir, *extra, wait=True):
    cmd = [sys.executable, "-m", "dslearn.run", "-m", *extra, f"hydra.sweep.dir={sweep_dir}"]
    env = {**os.environ, "CI": "1"}
    if wait:
        return subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    return subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)


def _table(sweep_dir):
    t = pd.read_csv(Path(sweep_dir) / "sweep_results.csv")
    return t.sort_values(["job", "node", "episode", "metric"]).reset_index(drop=True)


def test_parse_overrides():
    ov = parse_overrides(["model=lin", "+resume=true", "consensus.omega=one", "hydra.sweep.dir=x", "~foo", "seed=3"])
    assert ov == {"model": "lin", "consensus.omega": "one", "seed": "3"}


def test_completeness_marker_and_gather(tmp_path, make_cfg):
    """execute() writes meta (rows + hash) before results; broken job dirs are skipped with a warning."""
    for i, model in enumerate(["lin", "sfm"]):
        execute(make_cfg(f"model={model}", *TINY, "print_table=false"), tmp_path / str(i))
        assert check_complete(tmp_path / str(i)) == (True, "complete")
    meta = json.loads((tmp_path / "0" / "meta.json").read_text())
    for k in ("dslearn_version", "git_commit", "versions", "seed", "wall_time_s", "rows", "results_sha256"):
        assert k in meta
    good = pd.read_csv(tmp_path / "0" / "results.csv")
    # 2: truncated (half-written) results, 3: results but no marker, 4: killed before writing anything
    (tmp_path / "2").mkdir()
    (tmp_path / "2" / "meta.json").write_text((tmp_path / "0" / "meta.json").read_text())
    (tmp_path / "2" / "results.csv").write_text((tmp_path / "0" / "results.csv").read_text()[:500])
    (tmp_path / "3").mkdir()
    good.to_csv(tmp_path / "3" / "results.csv", index=False)
    (tmp_path / "4" / ".hydra").mkdir(parents=True)
    assert "does not match the hash" in check_complete(tmp_path / "2")[1]
    assert "no meta.json" in check_complete(tmp_path / "3")[1]
    assert check_complete(tmp_path / "4") == (False, "no results.csv")
    with pytest.warns(UserWarning, match="ignoring broken result"):
        table, s = gather_sweep(tmp_path)
    assert (s["done"], s["incomplete"], s["failed"]) == (2, 3, 0)
    assert sorted(table["job"].unique()) == [0, 1] and len(table) == 2 * len(good)
    assert (tmp_path / "sweep_results.csv").is_file() and (tmp_path / "sweep.json").is_file()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        loaded = load_results(tmp_path)  # the gathered table is what the report reads
    assert len(loaded) == len(table)


def _md_table(text, heading):
    """The cells of the first markdown table after ``heading``: {(fusion, node, model): (mean, std)} as strings."""
    lines = text[text.index(heading):].splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("|"))
    rows = []
    for line in lines[start:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip("|").split("|")])
    head, body = rows[0], rows[2:]
    assert head[:2] == ["fusion", "node"], head
    out = {}
    for r in body:
        fusion = r[0].split()[0]
        for model, cell in zip(head[2:], r[2:]):
            mean_s, std_s = (c.strip() for c in cell.split("±"))
            out[(fusion, r[1], model)] = (mean_s, std_s)
    return out


@pytest.fixture(scope="module")
def basic_sweep(tmp_path_factory):
    d = tmp_path_factory.mktemp("basic")
    r = _sweep(d, *GRID, *TINY, "hydra/launcher=basic")  # the default is joblib: compared below
    assert r.returncode == 0, r.stderr[-2000:]
    return d


def test_basic_sweep_one_table_and_report(basic_sweep):
    t = _table(basic_sweep)
    assert t["job"].nunique() == 4
    assert (t.groupby(["metric", "node", "episode"]).size() == 4).all()  # 4 rows per metric key
    assert set(zip(t["ov.model"], t["ov.consensus"])) == {(m, c) for m in ("lin", "sfm") for c in ("individual", "hybrid")}
    s = json.loads((basic_sweep / "sweep.json").read_text())
    assert (s["jobs"], s["done"], s["failed"]) == (4, 4, 0)
    if importlib.util.find_spec("pyarrow"):
        pd.testing.assert_frame_equal(
            pd.read_parquet(basic_sweep / "sweep_results.parquet").sort_values(["job", "node", "episode", "metric"])
            .reset_index(drop=True)[["job", "metric", "value"]], t[["job", "metric", "value"]])
    from dslearn.report import report

    text = report(basic_sweep)
    # the Table I cells, recomputed from the gathered rows: per sensor mean ± std (ddof 1) over the 2 episodes;
    # the sensor-average row as the paper forms it (mean of the sensors' means ± mean of their stds).
    # Each printed cell must agree to half a unit of its last printed digit.
    cells = _md_table(text, "### Tracking error")
    sensors = ("sensor1", "sensor2", "sensor3", "sensor4")
    assert sorted(cells) == sorted((c, n, m) for c in ("individual", "hybrid") for m in ("lin", "sfm")
                                   for n in (*sensors, "sensor average"))
    te = t[(t["metric"] == "track_err") & (t["node_kind"] == "sensor")]
    for (cons, node, model), (mean_s, std_s) in cells.items():
        g = te[(te["ov.consensus"] == cons) & (te["ov.model"] == model)]
        per_node = g.groupby("node")["value"].agg(["mean", "std", "count"])
        assert list(per_node.index) == list(sensors) and (per_node["count"] == 2).all()
        ref = per_node.mean() if node == "sensor average" else per_node.loc[node]
        for s, r in ((mean_s, ref["mean"]), (std_s, ref["std"])):
            assert abs(float(s) - r) <= 0.5 * 10.0 ** -len(s.partition(".")[2]) + 1e-12, (cons, node, model, s, r)
    for f in ("summary.csv", "tables.md", "tables.tex", "report.md", "figure.png", "figure_data.csv"):
        assert (basic_sweep / f).is_file(), f
    assert "\\begin{tabular}" in (basic_sweep / "tables.tex").read_text()
    # the default figure: every metric against the swept keys, one point per (model, consensus)
    fig = pd.read_csv(basic_sweep / "figure_data.csv")
    assert set(fig["metric"]) == {"track_err", "track_rmse", "nees", "pred_err"}
    assert len(fig) == 4 * 4 and (fig["n"] == 2).all() and (fig["error_bars"] == "std over episodes").all()
    sens = t[t["node_kind"] == "sensor"].groupby(["ov.model", "ov.consensus", "metric", "episode"])["value"].mean()
    ref = sens.groupby(["ov.model", "ov.consensus", "metric"]).agg(["mean", "std"])
    for _, row in fig.iterrows():
        m, sd = ref.loc[(row["ov.model"], row["ov.consensus"], row["metric"])]
        assert abs(row["mean"] - m) < 1e-12 and abs(row["err"] - sd) < 1e-12
    md = (basic_sweep / "report.md").read_text()
    assert "Open this file first" in md and "figure.png" in md and "- `yu_table1.csv`" in md


def test_default_launcher_is_parallel_and_identical_to_basic(basic_sweep, tmp_path):
    """The default launcher (joblib, one worker per core) gives the basic launcher's table."""
    r = _sweep(tmp_path, *GRID, *TINY)
    assert r.returncode == 0, r.stderr[-2000:]
    from omegaconf import OmegaConf

    launcher = OmegaConf.load(tmp_path / "multirun.yaml").hydra.launcher
    assert launcher._target_.endswith("JoblibLauncher") and launcher.n_jobs == -1
    assert r.returncode == 0, r.stderr[-2000:]
    a, b = _table(basic_sweep), _table(tmp_path)
    pd.testing.assert_frame_equal(a.drop(columns=["run_dir"]), b.drop(columns=["run_dir"]))


@pytest.mark.serial  # signals and timing: run alone, before the parallel run (the README's test command)
def test_kill_and_resume_equals_uninterrupted(tmp_path):
    """Start a sweep, SIGKILL it after the first job finished, resume: the table equals a clean run's."""
    grid = ["model=gp_increment,lin", "consensus=hybrid,individual", "data.train_episodes=3", "data.test_episodes=2"]
    killed = tmp_path / "killed"
    p = _sweep(killed, *grid, wait=False)
    t0 = time.time()
    try:
        while not (killed / "0" / "results.csv").exists():
            assert p.poll() is None, "sweep ended before its first job"
            assert time.time() - t0 < 300
            time.sleep(0.05)
    finally:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
    done_before = sum(check_complete(killed / str(i))[0] for i in range(4))
    assert done_before >= 1
    # a half-written result left by a non-atomic writer must be re-run too, never gathered
    broken = next(i for i in range(4) if not check_complete(killed / str(i))[0])
    (killed / str(broken)).mkdir(exist_ok=True)
    (killed / str(broken) / "results.csv").write_text("metric,value\ntrack_err,0.")
    # and so must a finished job whose results.csv got corrupted into binary (not UTF-8) bytes
    corrupt = next(i for i in range(4) if check_complete(killed / str(i))[0])
    (killed / str(corrupt) / "results.csv").write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\xff\xfe" * 20)
    r = _sweep(killed, *grid, "resume=true")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "Traceback" not in r.stderr and "UnicodeDecodeError" not in r.stderr
    assert f"job {corrupt}: resume: re-running" in r.stdout and "results.csv is not UTF-8 text" in r.stdout
    s = json.loads((killed / "sweep.json").read_text())
    assert (s["jobs"], s["skipped"], s["done"]) == (4, done_before - 1, 4 - done_before + 1)
    clean = tmp_path / "clean"
    r = _sweep(clean, *grid)
    assert r.returncode == 0, r.stderr[-2000:]
    pd.testing.assert_frame_equal(_table(killed).drop(columns=["run_dir"]), _table(clean).drop(columns=["run_dir"]))


def test_report_mean_std_over_seeds(tmp_path):
    """A gathered table with several seeds: per-seed means, then mean ± std over seeds; LaTeX + PNG."""
    from dslearn.report import report

    rows = [{"study": "s", "task": "none", "model": m, "consensus": "hybrid", "node": "avg", "metric": "track_err",
             "seed": seed, "episode": e, "value": v + 0.1 * seed + 0.01 * e, "job": seed, "ov.seed": seed}
            for m, v in (("lin", 1.0), ("gp", 0.5)) for seed in (0, 1, 2) for e in range(3)]
    p = tmp_path / "sweep_results.csv"
    pd.DataFrame(rows).to_csv(p, index=False)
    text = report(p)
    s = pd.read_csv(tmp_path / "summary_seeds.csv")
    lin = s[s.model == "lin"].iloc[0]
    assert lin["n_seeds"] == 3 and abs(lin["mean"] - 1.11) < 1e-12 and abs(lin["std"] - 0.1) < 1e-12
    assert "1.11 ± 0.1" in text
    assert (tmp_path / "figure.png").is_file() and "\\begin{tabular}" in (tmp_path / "tables.tex").read_text()
    fig = pd.read_csv(tmp_path / "figure_data.csv").set_index("model")
    assert list(fig.index) == ["lin", "gp"] and (fig["error_bars"] == "std over seeds").all()
    assert abs(fig.loc["lin", "mean"] - 1.11) < 1e-12 and abs(fig.loc["lin", "err"] - 0.1) < 1e-12
    assert abs(fig.loc["gp", "mean"] - 0.61) < 1e-12 and fig.loc["gp", "n"] == 3


def test_overrides_that_duplicate_a_result_column_are_not_separate_keys():
    """A gathered sweep carries ``ov.<key>`` columns; where the study already has the column
    (``ov.consensus.omega`` -> ``omega``), runs the study labels alike are pooled, and the
    Yu report's Table II layout (one column per model x fusion) stays well defined."""
    import pandas as pd

    from dslearn.report import summarize
    from dslearn.reports.yu import table_prediction

    rows = []
    for om, val in (("one", 1.0), ("nodes", 3.0)):
        for node in ("sensor1", "sensor2"):
            rows.append(dict(study="s", consensus="individual", omega="-", node=node, node_kind="sensor",
                             model="gp", metric="pred_err", value=val, episode=0, seed=0,
                             train_seen=1, iterations=0, **{"ov.consensus.omega": om, "ov.model.lengthscale": 2.0}))
    s = summarize(pd.DataFrame(rows))
    sens = s[s["node"] == "sensor1"]
    assert len(sens) == 1 and sens["n"].iloc[0] == 2 and sens["mean"].iloc[0] == 2.0
    assert "ov.model.lengthscale" in s.columns  # an override with no result column stays a key
    tab = table_prediction(s)
    assert list(tab["node"]) == ["sensor1", "sensor2", "sensor average"] and list(tab.columns) == ["node", "gp (ind.)"]
