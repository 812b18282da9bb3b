"""The comparison matrix: a cell's rows, the refusal of a cell that does not fit, the sweeper's job list
(experiment=matrix, experiment=matrix_small), the report's table, and one real sweep through the commands."""

import inspect
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import get_object

from dslearn import api
from dslearn.compose import build
from dslearn.episodes import Episodes, Estimates, ScenarioSpec
from dslearn.errors import ConfigError
from dslearn.reports import matrix as rep
from dslearn.schemas.matrix import select_cells
from dslearn.studies.matrix import MatrixCell, MatrixSettings

ROOT = Path(__file__).resolve().parents[1]
CONF = str(ROOT / "conf")
BIN = Path(sys.executable).parent


# ----------------------------------------------------------------------------------- one cell by hand
K, A, S = 4, 2, 3  # steps, targets, reporting nodes (the last one does not sense)
OFFSET = torch.tensor([0.3, 0.4], dtype=torch.float64)  # |OFFSET| = 0.5


def _truth(b: int) -> torch.Tensor:
    """Positions (b, K+1, A, 2) of episode indices 0..b-1: a known function of the episode and the step."""
    e = torch.arange(b, dtype=torch.float64).view(b, 1, 1, 1)
    k = torch.arange(K + 1, dtype=torch.float64).view(1, K + 1, 1, 1)
    a = torch.arange(A, dtype=torch.float64).view(1, 1, A, 1)
    return torch.cat([e + k + a, 2 * k - a + 0 * e], -1)


class FakeScenario:
    owns_network, network, area = True, None, (0.0, 1.0, 0.0, 1.0)

    def __init__(self, measurement="position"):
        self.spec = ScenarioSpec("fake", measurement, A, "pv2d", 1.0, K, units="m")
        self.samples = 0

    def sample(self, num, network, generator):
        self.samples += 1
        pos = _truth(num)
        states = torch.cat([pos, torch.zeros_like(pos)], -1).flatten(-2)  # per agent [px, py, vx, vy]
        return Episodes(states, torch.zeros(S, num, K + 1, A, 2), torch.zeros(S, num, K + 1, A, dtype=torch.bool))

    def positions(self, states):
        return states.unflatten(-1, (A, 4))[..., :2]


class FakeMethod:
    """Node i of episode b misses every target by (i+1)(b+1) OFFSET at odd steps and 3 (i+1)(b+1) OFFSET at
    even ones (and by 1000 at step 0, which the metrics leave out), covariance SIGMA2 * I."""

    label, SIGMA2 = "fake method", 0.25

    def __init__(self, cov=True):
        self.cov = cov

    def fits(self, spec):
        return None if spec.measurement == "position" else f"the fake needs measurement position; {spec.measurement}"

    def estimate(self, scenario, network, train, test, seed):
        b = test.meas.shape[1]
        i = torch.arange(S, dtype=torch.float64).view(S, 1, 1, 1, 1)
        e = torch.arange(b, dtype=torch.float64).view(1, b, 1, 1, 1)
        step = torch.tensor([1000.0] + [1.0 if k % 2 else 3.0 for k in range(1, K + 1)], dtype=torch.float64).view(1, 1, K + 1, 1, 1)
        mean = _truth(b).unsqueeze(0) + (i + 1) * (e + 1) * step * OFFSET
        cov = self.SIGMA2 * torch.eye(2, dtype=torch.float64).expand(S, b, K + 1, A, 2, 2) if self.cov else None
        return Estimates(mean, cov, ["n1", "n2", "relay"], torch.tensor([True, True, False]))


def _cell(method, scenario=None, test=3):
    return MatrixCell(MatrixSettings(train_episodes=2, test_episodes=test), scenario or FakeScenario(), None,
                      method, 0, torch.float64, torch.device("cpu"))


def test_cell_rows_by_hand():
    df = _cell(FakeMethod()).run()
    assert list(df.columns[-5:]) == ["node", "node_kind", "episode", "metric", "value"]
    assert set(df["method"]) == {"fake method"} and set(df["scenario"]) == {"fake"} and set(df["units"]) == {"m"}
    for (node, ep), g in df[df["node"] != "all"].groupby(["node", "episode"]):
        i, c = ["n1", "n2", "relay"].index(node), 0.5 * (["n1", "n2", "relay"].index(node) + 1) * (ep + 1)
        v = g.set_index("metric")["value"]
        assert g["node_kind"].iloc[0] == ("comm" if node == "relay" else "sensor"), node
        # errors c and 3c at alternate steps (K = 4: two of each): RMSE sqrt((c^2 + 9c^2)/2), mean error 2c;
        # NEES per step sum_a |e|^2 / sigma^2 / (2A) = |e|^2 / (2 sigma^2), averaged over the steps
        assert v["rmse"] == pytest.approx(c * math.sqrt(5.0), rel=1e-12), (node, ep, i)
        assert v["pos_err"] == pytest.approx(2 * c, rel=1e-12)
        assert v["nees_pos"] == pytest.approx(5 * c * c / (2 * FakeMethod.SIGMA2), rel=1e-12)
    assert len(df[df["node"] != "all"]) == 3 * 3 * 3  # nodes x episodes x metrics
    rt = df[df["metric"] == "runtime_s"]
    assert len(rt) == 1 and rt["node"].iloc[0] == "all" and 0 <= rt["value"].iloc[0] < 5
    # the report's cell value: per episode the mean over the SENSING nodes, then the mean over episodes
    vals = rep.cell_values(df).iloc[0]
    rmse = sum(0.5 * math.sqrt(5) * (i + 1) * (b + 1) for i in (0, 1) for b in range(3)) / 6
    assert vals["rmse_mean"] == pytest.approx(rmse, rel=1e-12) and vals["n_units"] == 3 and vals["seeds"] == 1
    nees = sum(5 * (0.5 * (i + 1) * (b + 1)) ** 2 / 0.5 for i in (0, 1) for b in range(3)) / 6
    assert vals["nees_pos_per_dim_mean"] == pytest.approx(nees, rel=1e-12)
    no_cov = _cell(FakeMethod(cov=False)).run()
    assert "nees_pos" not in set(no_cov["metric"])
    assert math.isnan(rep.cell_values(no_cov)["nees_pos_per_dim_mean"].iloc[0])


def test_a_cell_that_does_not_fit_is_refused_before_any_work():
    sc = FakeScenario("squared_range")
    with pytest.raises(ConfigError, match="fake method does not fit scenario fake: the fake needs measurement position"):
        _cell(FakeMethod(), sc).run()
    assert sc.samples == 0  # refused before any episode was drawn
    # the real methods' verdicts on a spec they cannot use name what is missing
    from dslearn.methods.dgpt import DGPTMethod
    from dslearn.methods.distributed import DistributedFilter

    from dslearn.fusion.strategies import HybridConsensus
    from dslearn.models.observation import LinearPositionObservation

    spec = ScenarioSpec("jiang_like", "squared_range", 1, "param2d", 1.0, 10, networked=False)
    assert "needs measurement position; scenario jiang_like has squared_range" in DGPTMethod.fits(None, spec)
    from dslearn.methods.factor_graph import FactorGraphMotionMethod

    assert FactorGraphMotionMethod.spec_misfit(spec) == (  # the FG family on position sensors: for a person
        "the factor-graph identification of a motion model + EKF on position sensors (sensors that measure the "
        "positions of targets with a [px, py, vx, vy] state) needs measurement position; scenario jiang_like has "
        "squared_range")
    # why, intrinsically: a sensor's own GP expert regresses positions that one scalar reading does not fix
    assert "a sensor alone has no position to regress" in DGPTMethod.fits(None, spec)
    # the distributed filter takes squared ranges (its observation part declares which readings it explains)
    assert DistributedFilter.spec_misfit(spec) is None
    assert "observation=linear explains readings of the targets' positions; scenario jiang_like measures " \
           "squared_range" in LinearPositionObservation.spec_misfit(spec)
    assert "needs measurement position or squared_range or range or bearing or terrain_altitude; scenario x has " \
           "sonar" in DistributedFilter.spec_misfit(ScenarioSpec("x", "sonar", 2, "pv2d", 1.0, 5))
    # a consensus over the links needs a graph (the fusion part declares it)
    assert "the sensors of scenario x have none" in HybridConsensus.spec_misfit(
        ScenarioSpec("x", "position", 2, "pv2d", 1.0, 5, networked=False))


def test_dslearn_run_refuses_a_cell_that_does_not_fit():
    from dslearn.app.precheck import precheck

    msg = precheck(["task=matrix", "method=ekf_sfm_hybrid", "scenario=liu_s1"])
    assert msg is not None and "model=sfm is the true social-force model" in msg and \
        "which scenario s1 does not have" in msg, msg  # the part's own refusal names what the scenario lacks
    assert precheck(["task=matrix", "method=ekf_lin_hybrid", "scenario=liu_s1", "task.train_episodes=1"]) is None


# ----------------------------------------------------------------------------------- the job lists
def _options(group):
    return sorted(p.stem for p in (ROOT / "conf" / group).glob("*.yaml"))


def _matrix_scenarios():
    """The scenario options that are matrix scenarios (a class declaring a spec; Liu's study options s1-s3
    are trajectory generators)."""
    out = []
    for o in _options("scenario"):
        target = yaml.safe_load((ROOT / "conf" / "scenario" / f"{o}.yaml").read_text())["_target_"]
        if inspect.isclass(get_object(target)):
            out.append(o)
    return out


def _expected_fit(preset_cfg, scenario) -> bool:
    """The design's rules, independent of the methods' code: the distributed filter needs position
    measurements of 2-D [p, v] agents on a network, and its social force model a scenario that simulates
    social forces; Liu's DGPT needs position measurements."""
    spec = scenario.spec
    engine = str(preset_cfg.filter._target_)
    # unlabelled detections: only the distributed filter with an associator (GNN, JPDA); an associator of unlabelled
    # detections is refused on a labelled scenario (the full matrix keeps each associator on its own column)
    assoc = str(preset_cfg.get("associator", {}).get("_target_", "")).rsplit(".", 1)[-1]
    if assoc in ("GNNAssociator", "JPDAAssociator") or not getattr(spec, "labelled", True):
        # targets that enter and leave (declared births): managed tracks, along which nothing learns (learner=none
        # with a model that learns nothing: LIN)
        managed_ok = not getattr(spec, "births", False) or (
            str(preset_cfg.learner._target_).endswith("NoLearning") and str(preset_cfg.model.name) == "lin")
        return (not spec.labelled and assoc in ("GNNAssociator", "JPDAAssociator")
                and engine.endswith("DistributedFilter") and spec.measurement == "position" and managed_ok)
    if engine.endswith("DGPTMethod"):
        return spec.measurement == "position"
    if engine.endswith("FactorGraphMethod"):  # Jiang's identification + EKF-FG: squared-range sensors
        return spec.measurement == "squared_range"
    if engine.endswith("FactorGraphMotionMethod"):  # the FG identification of a [p, v] motion model: position sensors
        return spec.measurement == "position" and spec.state == "pv2d" and spec.kind == "targets"
    if engine.endswith("RBPFMethod"):  # Braga's RBPF + online EM: terrain altimeters on a network
        return spec.measurement == "terrain_altitude" and spec.networked
    if engine.endswith("RBPFModesMethod"):  # a Kalman filter of [p, v] per particle: position sensors; with the
        # scenario's own sensor model (observation=sensor) an iterated EKF per particle at a fusion centre: Jiang's
        # squared ranges (Braga's platforms navigate themselves: rbpf_em's)
        sensor = str(preset_cfg.observation._target_).endswith("scenario_sensor")
        return (spec.measurement == "position" and spec.state == "pv2d") or (
            sensor and spec.measurement == "squared_range" and spec.state == "param2d")
    # the distributed filter: its observation model must explain the scenario's readings (observation=sensor is the
    # scenario's own kind, linear explains positions); consensus needs a graph between nodes that see the same
    # targets (Jiang's sensors report to a centre, Braga's aircraft each navigate themselves); one squared range per
    # node cannot fix a 2-D position alone (individual on Jiang)
    sensor = str(preset_cfg.observation._target_).endswith("scenario_sensor")
    fusion = str(preset_cfg.consensus.name)
    if spec.measurement == "position":
        ok = spec.state == "pv2d" and spec.networked
    elif spec.measurement == "squared_range":
        ok = sensor and fusion == "centralized"
    elif spec.measurement == "terrain_altitude":
        ok = sensor and fusion in ("individual", "centralized")
    else:
        ok = False
    return ok and (str(preset_cfg.model.name) != "sfm" or hasattr(scenario, "sfm"))


def master_left_out(experiment) -> list:
    """The experiment's ``task.left_out`` entries, as written in its file."""
    import yaml

    return yaml.safe_load((Path(CONF) / "experiment" / f"{experiment}.yaml").read_text())["task"].get("left_out", [])


def _jobs(experiment, judge=True):
    from dslearn.app.composer import sweep_combinations

    with initialize_config_dir(config_dir=CONF, version_base=None):
        combos, multirun, master = sweep_combinations([f"experiment={experiment}"])
        assert multirun and master.hydra.sweeper._target_.endswith("MatrixSweeper")
        if not judge:
            return combos, None, None
        # the app's cache of compositions (each preset and each scenario composed once: the up-front check's;
        # test_the_sweeper_takes_the_up_front_checks_judgement holds it to Hydra's own composition)
        from dslearn.app.composer import composed_job, sweep_composer

        composer = sweep_composer(combos, lambda ov: compose("config", overrides=list(ov)))
        kept, records = select_cells(combos, lambda ov: composed_job(composer, ov))
        ov = [dict(x.split("=") for x in c if not x.startswith("experiment=")) for c in combos]
        scen = {s: build(compose("config", overrides=["task=matrix", f"scenario={s}"]).scenario, "scenario")
                for s in {o["scenario"] for o in ov}}
        presets = {m: compose("config", overrides=["task=matrix", f"method={m}"]) for m in {o["method"] for o in ov}}
    return combos, (kept, records), (scen, presets)


def test_experiment_matrix_lists_every_preset_on_every_matrix_scenario():
    combos, _, _ = _jobs("matrix", judge=False)
    combos = [[x for x in c if not x.startswith("experiment=")] for c in combos]
    pairs = [tuple(sorted(c)) for c in combos]
    assert len(pairs) == len(set(pairs))
    want = {(f"method={m}", f"scenario={s}") for m in _options("method") for s in _matrix_scenarios()}
    have = {tuple(sorted(c)) for c in combos}
    missing = sorted({x for p in want - have for x in p} - {x for p in have for x in p})
    assert have == want, f"add to conf/experiment/matrix.yaml: {missing}"  # every preset on every matrix scenario
    small, _, _ = _jobs("matrix_small", judge=False)
    assert {tuple(sorted(x for x in c if not x.startswith("experiment="))) for c in small} <= want


def test_experiment_matrix_small_jobs_are_exactly_the_fitting_cells():
    from dslearn.data.ethucy import data_available

    if not data_available():  # matrix_small has a recorded column (eth_zara1): its cells are built up front
        pytest.skip("the ETH/UCY data are absent")
    combos, (kept, records), (scen, presets) = _jobs("matrix_small")
    ov = [dict(x.split("=") for x in c if not x.startswith("experiment=")) for c in combos]
    # every family on every scenario without external data
    own = ("dgpt", "fg_ekf", "rbpf_em")  # engines of their own (no motion-model slot)
    models = {str(presets[o["method"]].model.name) for o in ov if not o["method"].startswith(own)}
    assert {"lin", "sfm", "gp_increment", "lstm"} <= models
    assert all(any(o["method"].startswith(e) for o in ov) for e in own)
    assert {o["scenario"] for o in ov} == {"yu_two_agents", "liu_s1", "liu_s2", "liu_s3", "jiang", "braga", "corridor",
                                           "eth_zara1", "yu_crowd_clutter"}  # every simulated scenario, a recorded one
    # the cells the small sweep leaves out for its budget (task.left_out), each with its reason
    left = {(m, s) for e in master_left_out("matrix_small") for m in [e["method"]] for s in e["scenarios"]}
    assert left == {("rbpf_em_lin", "liu_s1"), ("rbpf_em_lin", "liu_s2")} | {
        ("ekf_cv_fg_individual", s) for s in ("yu_two_agents", "liu_s1", "liu_s2", "liu_s3", "corridor", "eth_zara1")}
    steps = {str(presets[o["method"]].filter.predict._target_).rsplit(".", 1)[-1] for o in ov
             if not o["method"].startswith(own)}
    assert steps == {"ExtendedPredict", "UnscentedPredict"}
    fit = [_expected_fit(presets[o["method"]], scen[o["scenario"]]) for o in ov]
    out = [(o["method"], o["scenario"]) in left for o in ov]
    assert all(f for f, x in zip(fit, out) if x)  # a left-out cell is one that fits
    assert kept == [c for c, f, x in zip(combos, fit, out) if f and not x]  # every fitting cell a job, in order
    assert len(records) == len(combos)
    for r, f, x, c in zip(records, fit, out, combos):
        assert r["overrides"] == " ".join(c)
        assert (r["reason"] is None) == (f and not x) and (r["job"] is not None) == (f and not x), r
        if not f:  # the social force model on Liu's scenarios: no social forces simulated there
            assert r["reason"].startswith(f"{r['method']} does not fit scenario {r['scenario']}: "), r
        elif x:
            assert r["status"] == "left_out" and ("minute per cell" in r["reason"] or "stands for" in r["reason"]), r
    assert [r["job"] for r in records if r["job"] is not None] == list(range(len(kept)))
    assert 0 < len(kept) < len(combos)
    # a job in each family x paper block but DGPT's two intrinsic ones (a squared range or a terrain altitude per
    # sensor fixes no position for its GP experts to regress)
    paper = {"yu_two_agents": "yu", "corridor": "yu", "eth_zara1": "yu", "yu_crowd_clutter": "yu", "liu_s1": "liu",
             "liu_s2": "liu", "liu_s3": "liu", "jiang": "jiang", "braga": "braga"}

    def family(m):
        learner = str((presets[m].get("learner") or {}).get("_target_", ""))
        return ("dgpt" if m.startswith("dgpt") else "fg" if m.startswith("fg_ekf") or "FactorGraph" in learner
                else "rbpf" if m.startswith("rbpf") else "yu")

    blocks = {(family(o["method"]), paper[o["scenario"]]) for o, f, x in zip(ov, fit, out) if f and not x}
    every = {(f, p) for f in ("yu", "dgpt", "fg", "rbpf") for p in ("yu", "liu", "jiang", "braga")}
    assert blocks == every - {("dgpt", "jiang"), ("dgpt", "braga")}, sorted(every - blocks)


# ----------------------------------------------------------------------------------- the report
def _synthetic(tmp_path):
    """Two methods x three scenarios: A on yu and s1 (rows by hand), B on yu (no covariance), A on jiang
    dropped (n/a), B on s1 failed, B on jiang incomplete (no job folder)."""
    rows = []

    def add(method, scen, units, metric, per_node_ep, runtime):
        for (node, kind), vals in per_node_ep.items():
            for ep, v in enumerate(vals):
                rows.append(dict(study="m", task="matrix", seed=0, method=method, scenario=scen, units=units,
                                 node=node, node_kind=kind, episode=ep, metric=metric, value=v))
        if runtime is not None:
            rows.append(dict(study="m", task="matrix", seed=0, method=method, scenario=scen, units=units, node="all",
                             node_kind="all", episode=-1, metric="runtime_s", value=runtime))

    add("A", "yu", "m", "rmse", {("s1", "sensor"): [1.0, 3.0], ("s2", "sensor"): [2.0, 5.0], ("c", "comm"): [99, 99]}, 12.345)
    add("A", "yu", "m", "nees_pos", {("s1", "sensor"): [0.5, 1.0], ("s2", "sensor"): [1.5, 1.0], ("c", "comm"): [9, 9]}, None)
    add("A", "s1", "km", "rmse", {("centre", "sensor"): [0.001234, 0.001238]}, 0.5)
    add("B", "yu", "m", "rmse", {("s1", "sensor"): [4.0, 4.0], ("s2", "sensor"): [4.0, 4.0]}, 100.0)
    res = pd.DataFrame(rows)
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    res.to_csv(sweep / "sweep_results.csv", index=False)
    reason = "A does not fit scenario jiang: A needs measurement position; scenario jiang has squared_range"
    cells = pd.DataFrame([
        dict(job=0, method="A", scenario="yu", units="m", reason=None, overrides="method=a scenario=yu"),
        dict(job=1, method="A", scenario="s1", units="km", reason=None, overrides="method=a scenario=s1"),
        dict(job=None, method="A", scenario="jiang", units="m", reason=reason, overrides="method=a scenario=jiang"),
        dict(job=2, method="B", scenario="yu", units="m", reason=None, overrides="method=b scenario=yu"),
        dict(job=3, method="B", scenario="s1", units="km", reason=None, overrides="method=b scenario=s1"),
        dict(job=4, method="B", scenario="jiang", units="m", reason=None, overrides="method=b scenario=jiang"),
    ])
    cells["job"] = cells["job"].astype("Int64")
    cells.to_csv(sweep / "matrix_cells.csv", index=False)
    cells[cells["reason"].notna()].drop(columns="job").to_csv(sweep / "skipped_cells.csv", index=False)
    (sweep / "3").mkdir()
    (sweep / "3" / "status.json").write_text(json.dumps({"status": "failed", "error": "boom"}))
    return sweep


def test_report_table_on_a_synthetic_sweep(tmp_path):
    from dslearn.report import report

    sweep = _synthetic(tmp_path)
    text = report(sweep)
    vals = pd.read_csv(sweep / "matrix.csv")
    # rows and columns: the options of the sweep's combinations (method=a, scenario=yu, ...)
    assert list(zip(vals["method"], vals["scenario"])) == [("a", "yu"), ("a", "s1"), ("a", "jiang"), ("b", "yu"),
                                                           ("b", "s1"), ("b", "jiang")]
    assert list(vals["status"]) == ["ok", "ok", "skipped", "ok", "failed", "incomplete"]
    # A on yu: per episode the mean over the sensors (1.5, 4.0; the comm node left out), mean 2.75, the
    # t-interval 2.75 -/+ t_{0.975,1} * s / sqrt(2) with s = 2.5 / sqrt(2): half-width 12.706 * 1.25 = 15.9
    half = 12.706204736174707 * 1.25
    assert (vals.loc[0, "rmse_mean"], vals.loc[0, "rmse_lo"], vals.loc[0, "rmse_hi"]) == pytest.approx(
        (2.75, 2.75 - half, 2.75 + half), rel=1e-12)
    assert vals.loc[0, "nees_pos_per_dim_mean"] == 1.0 and vals.loc[0, "runtime_s"] == 12.345
    assert vals.loc[1, "rmse_mean"] == pytest.approx(0.001236, rel=1e-12)
    md = (sweep / "matrix.md").read_text()
    # the best of yu bold (A: 2.75 < B: 4.00, paired differences 2.5, 0 -> interval [-14.4, 16.4]: tied)
    assert "| a | **2.75 ± 15.9** (1.00) | **0.00124 ± 2.54e-05** | – [1] |" in md
    assert "| b | ≈ 4.00 ± 0 | – [2] | – [3] |" in md and "| a | **2.75" in text
    assert "[1] A needs measurement position; the scenario has squared_range" in md
    assert "[2] the job failed" in md and "[3] the job has no complete result" in md
    rel = rep.relative_rmse(rep.matrix_values(pd.read_csv(sweep / "sweep_results.csv"), sweep))
    assert rel.loc["b", "yu"] == pytest.approx(4.0 / 2.75) and rel.loc["a", "yu"] == 1.0
    assert math.isnan(rel.loc["a", "jiang"]) and math.isnan(rel.loc["b", "s1"])
    assert (sweep / "matrix.png").stat().st_size > 10_000
    # --out elsewhere: the n/a and failed cells still come from the sweep folder
    report(sweep / "sweep_results.csv", tmp_path / "elsewhere")
    assert pd.read_csv(tmp_path / "elsewhere" / "matrix.csv", dtype=str).equals(pd.read_csv(sweep / "matrix.csv", dtype=str))


# ----------------------------------------------------------------------------------- a real sweep
def test_a_real_matrix_sweep_and_its_report(tmp_path):
    """Four combinations, three fit (the social force model has no social forces to simulate on Liu's S1):
    run from outside the repository (the installed commands find the matrix sweeper there too)."""
    sweep = tmp_path / "sweep"
    env = {**os.environ, "CI": "1"}
    cmd = [str(BIN / "dslearn-run"), "-m", "experiment=matrix", "method=ekf_lin_hybrid,ekf_sfm_hybrid",
           "scenario=yu_two_agents,liu_s1", "task.train_episodes=1", "task.test_episodes=2", "task.seeds=1",
           "hydra/launcher=basic", f"hydra.sweep.dir={sweep}"]
    r = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    cells = pd.read_csv(sweep / "matrix_cells.csv")
    assert list(zip(cells["method"], cells["scenario"])) == [
        ("ekf lin hybrid", "yu"), ("ekf lin hybrid", "s1"), ("ekf sfm hybrid", "yu"), ("ekf sfm hybrid", "s1")]
    assert cells["job"].tolist()[:3] == [0, 1, 2] and pd.isna(cells["job"].iloc[3])
    skipped = pd.read_csv(sweep / "skipped_cells.csv")
    assert list(zip(skipped["method"], skipped["scenario"])) == [("ekf sfm hybrid", "s1")]
    assert skipped["reason"].iloc[0].startswith("ekf sfm hybrid does not fit scenario s1: ")
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir() and p.name.isdigit()) == ["0", "1", "2"]
    r = subprocess.run([str(BIN / "dslearn-report"), str(sweep)], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    vals = pd.read_csv(sweep / "matrix.csv").set_index(["method", "scenario"])
    assert vals.loc[("ekf_sfm_hybrid", "liu_s1"), "status"] == "skipped"
    note = int(vals.loc[("ekf_sfm_hybrid", "liu_s1"), "note"])
    assert f"[{note}] model=sfm is the true social-force model" in (sweep / "matrix.md").read_text()
    for job, (m, s) in enumerate([("ekf_lin_hybrid", "yu_two_agents"), ("ekf_lin_hybrid", "liu_s1"),
                                  ("ekf_sfm_hybrid", "yu_two_agents")]):
        res = pd.read_csv(sweep / str(job) / "results.csv")  # the job's own rows, recomputed here
        sens = res[res["node_kind"] == "sensor"]
        rmse = sens[sens["metric"] == "rmse"].groupby("episode")["value"].mean().mean()
        nees = sens[sens["metric"] == "nees_pos"].groupby("episode")["value"].mean().mean()
        t = res.loc[res["metric"] == "runtime_s", "value"].iloc[0]
        assert vals.loc[(m, s), "rmse_mean"] == pytest.approx(rmse, rel=1e-12)
        assert vals.loc[(m, s), "nees_pos_per_dim_mean"] == pytest.approx(nees, rel=1e-12)
        assert vals.loc[(m, s), "runtime_s"] == pytest.approx(t, rel=1e-12)
        assert vals.loc[(m, s), "n_units"] == 2 and vals.loc[(m, s), "seeds"] == 1


def test_a_cell_whose_model_learns_online(make_cfg):
    """The online GP learns from the training episodes' measurements (Algorithm 1 without evaluations at its
    checkpoints) before it tracks the test episodes: with one training episode the estimates differ from those
    of the GP at its prior (no training episode), on the same test episodes."""
    from dslearn.compose import build_study

    out = {}
    for n in (0, 1):
        cfg = make_cfg("task=matrix", "method=ekf_gp_hybrid", "scenario=yu_two_agents", f"task.train_episodes={n}",
                       "task.test_episodes=1")
        df = build_study(cfg).run()
        out[n] = df[df["metric"] == "rmse"].sort_values("node")["value"].to_numpy()
    assert len(out[0]) == len(out[1]) > 0 and all(math.isfinite(v) for v in out[1])
    assert abs(out[1] - out[0]).max() > 1e-6


def test_left_out_cells_are_dropped_with_their_reason_and_a_bad_entry_is_refused():
    """task.left_out: a fitting cell the sweep leaves out is recorded with the entry's reason, no job; the other
    cells are untouched; an entry naming no preset, no scenario or no reason is refused before any job."""
    from dslearn.schemas.matrix import select_cells

    def compose_with(entries):
        return lambda lines: api.compose("task=matrix", *lines, f"task.left_out={entries}")

    combos = [["method=ekf_lin_hybrid", "scenario=yu_two_agents"], ["method=ekf_lin_hybrid", "scenario=corridor"]]
    entry = "[{method: ekf_lin_hybrid, scenarios: [corridor], why: 'too slow here'}]"
    kept, records = select_cells(combos, compose_with(entry))
    assert kept == [combos[0]]
    assert records[0]["reason"] is None and records[0]["job"] == 0
    assert records[1]["job"] is None
    assert records[1]["reason"] == ("ekf lin hybrid on scenario corridor is left out of this sweep (task.left_out): "
                                    "too slow here")
    kept, _ = select_cells(combos, compose_with("[]"))
    assert kept == combos
    for bad, message in (("[{method: ekf_lin_hybird, scenarios: [corridor], why: x}]", r"left_out\[0\].method"),
                         ("[{method: ekf_lin_hybrid, scenarios: [corridr], why: x}]", r"left_out\[0\].scenarios"),
                         ("[{method: ekf_lin_hybrid, scenarios: [corridor], why: ''}]", r"left_out\[0\].why")):
        with pytest.raises(ConfigError, match=message):
            select_cells(combos, compose_with(bad))


def test_experiment_matrix_left_out_entries_name_its_own_presets_and_scenarios():
    from dslearn.conf_paths import CONF_DIR

    exp = yaml.safe_load((CONF_DIR / "experiment" / "matrix.yaml").read_text())
    params = exp["hydra"]["sweeper"]["params"]
    methods = {m.strip() for m in params["method"].split(",")}
    scenarios = {x.strip() for x in params["scenario"].split(",")}
    entries = exp["task"]["left_out"]
    assert entries and all(e["method"] in methods and set(e["scenarios"]) <= scenarios and e["why"] for e in entries)


def test_the_sweeper_takes_the_up_front_checks_judgement(tmp_path):
    """dslearn-run's up-front check judges a matrix sweep's combinations once (each preset and scenario composed
    once, each cell built once on the meta device) and the matrix sweeper takes that judgement for the same
    combinations instead of judging them again; taken once, and none for other combinations; the cells it
    judged are those Hydra's own composition of each combination gives."""
    from dslearn.app.precheck import precheck
    from dslearn.schemas import matrix

    argv = ["experiment=matrix_small", "method=ekf_lin_hybrid,dgpt_rbcm", "scenario=yu_two_agents,jiang",
            "task.train_episodes=2", f"hydra.sweep.dir={tmp_path / 'sweep'}"]
    assert precheck(argv) is None
    assert len(matrix._JUDGED) == 1
    (select, combos), judged = next(iter(matrix._JUDGED.items()))
    assert select is matrix.select_cells and len(combos) == 4
    with initialize_config_dir(config_dir=CONF, version_base=None):
        plain = matrix.select_cells([list(c) for c in combos], lambda ov: compose("config", overrides=list(ov)))
    assert judged == plain  # the cached compositions judge as Hydra's own do
    assert matrix.take_judgement(select, [list(c) for c in combos[:3]]) is None  # other combinations: none
    assert matrix.take_judgement(select, [list(c) for c in combos]) is judged
    assert matrix.take_judgement(select, [list(c) for c in combos]) is None  # once
