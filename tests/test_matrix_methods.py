"""Jiang et al.'s and Braga et al.'s methods and scenarios in the comparison matrix: a matrix cell equals the
paper's study's own computation on the same draws, the methods fit only their scenarios (with the reasons),
the composition refuses parts a method does not take, and the cell's metric rows match a hand computation."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf

from dslearn.episodes import ScenarioSpec
from dslearn.errors import ConfigError
from dslearn.fusion.stats_consensus import StatisticsConsensus
from dslearn.learning.factor_graph.engine import simulate
from dslearn.learning.learners import FactorGraphIdentification, OnlineEM
from dslearn.learning.online_em import run_tbn, simulate_and_filter
from dslearn.methods.dgpt import DGPTMethod
from dslearn.methods.distributed import DistributedFilter
from dslearn.methods.factor_graph import FactorGraphMethod
from dslearn.methods.rbpf import RBPFMethod
from dslearn.sim.braga import TerrainScenario
from dslearn.sim.jiang import SquaredRangeScenario
from dslearn.sim.scenario import episode_streams
from dslearn.sim.squared_range import SquaredRange, run_noise, run_seed
from dslearn.streams import Streams
from dslearn.studies.braga_tbn import BragaModes, BragaStudy, BragaTask, BragaTerrain
from dslearn.studies.jiang_fg import JiangFgStudy, JiangTask
from dslearn.studies.matrix import MatrixCell, MatrixSettings

F64, CPU = torch.float64, torch.device("cpu")


def _compose(*overrides):
    from dslearn import api

    return api.compose(*overrides)


def _cell_rows(scenario, method, seed, test, train=0):
    st = MatrixSettings(train_episodes=train, test_episodes=test)
    df = MatrixCell(st, scenario, scenario.network, method, seed, F64, CPU).run()
    return df


def _metric(df, name):
    d = df[df.metric == name].sort_values("episode")
    return torch.tensor(d.value.to_numpy(), dtype=F64)


# ------------------------------------------------------------------------------------------ Jiang
def test_jiang_scenario_draws_the_study_runs():
    """Episode b drawn from run_seed(seed, b) is the study's Monte Carlo run b (truth and samples)."""
    sc = SquaredRangeScenario(num_timings=6, num_samples=4)
    gens = [torch.Generator().manual_seed(run_seed(5, r)) for r in range(3)]
    ep = sc.sample(3, sc.network, Streams(gens, (3,)))
    drive, noise = run_noise(5, range(3), 6, 2, 3, 4)
    truth = torch.tensor([[0.05, 0.03, 6.0], [-0.02, 0.07, 0.0]], dtype=F64)
    k = torch.arange(1, 7, dtype=F64)[:, None]
    truth = truth[:, 0] * k**2 + truth[:, 1] * k + truth[:, 2] + 0.5**0.5 * drive  # Eqs. 20-21 by hand
    assert torch.equal(ep.states, truth)
    sensors = torch.tensor([[-30.0, 50.0], [10.0, 5.0], [60.0, 20.0]], dtype=F64)
    h = ((sensors[None, None] - truth[:, :, None]) ** 2).sum(-1)  # (B, K, N), Eq. 22
    torch.testing.assert_close(ep.meas[:, :, :, 0].permute(1, 2, 0, 3), h[..., None] + 5.0 * noise, rtol=0, atol=1e-12)
    assert ep.visible.all() and sc.positions(ep.states).shape == (3, 6, 1, 2)
    assert sc.spec == ScenarioSpec("jiang", "squared_range", 1, "param2d", 1.0, 5, networked=False)


def test_jiang_cell_equals_the_study_engine_and_rows_by_hand():
    """The matrix cell (default settings of conf/filter/fg_ekf.yaml and conf/scenario/jiang.yaml) on its test
    draws equals the study's engine (simulate, with the study's own settings, its grid of 3 configurations)
    bit for bit; its rmse / pos_err / nees_pos rows equal the hand computation (to 1e-12: mean orders)."""
    cfg = _compose("task=matrix", "method=fg_ekf", "scenario=jiang")
    from dslearn.compose import build_cell_parts

    scenario, network, method = build_cell_parts(cfg)
    assert isinstance(method, FactorGraphMethod) and isinstance(scenario, SquaredRangeScenario)
    seed, n = 4, 2
    df = _cell_rows(scenario, method, seed, n)
    # the study: its settings (conf/task/jiang_fg.yaml), its engine, on the cell's test draws
    task = OmegaConf.to_object(_compose("experiment=jiang_fg").task)
    assert isinstance(task, JiangTask) and task.tracker.obs_var == "convergence"
    study = JiangFgStudy(task, {}, seed, F64, CPU)
    drive, noise = scenario.draw(episode_streams(seed, "test", 0, n).gens)
    coeffs = torch.tensor(task.scenario.coefficients, dtype=F64)
    k = torch.arange(1, task.scenario.num_timings + 1, dtype=F64)[:, None]
    truth = coeffs[:, 0] * k**2 + coeffs[:, 1] * k + coeffs[:, 2] + task.scenario.drive_var**0.5 * drive
    h = SquaredRange(torch.tensor(task.scenario.sensors, dtype=F64))
    out = simulate(h, truth, noise, torch.tensor([0.5, task.sigma_y, 50.0], dtype=F64),
                   torch.tensor([3, task.max_iter, task.max_iter]), study.tracker_settings())
    ref = out.estimates["ekf_fg"][1]  # (B, K, 2)
    test = scenario.sample(n, network, episode_streams(seed, "test", 0, n))
    est = method.estimate(scenario, network, None, test.measurements, seed)
    assert torch.equal(est.mean[0, :, :, 0], ref) and est.nodes == ["fusion_center"]
    # rows by hand (t = 1..K-1: index 0 is the first timing, the metrics skip it as every cell's t = 0)
    e = (ref - truth)[:, 1:]
    var = est.cov[0, :, 1:, 0].diagonal(dim1=-2, dim2=-1)
    want = {"rmse": e.square().sum(-1).mean(-1).sqrt(), "pos_err": e.square().sum(-1).sqrt().mean(-1),
            "nees_pos": (e.square() / var).sum(-1).mean(-1) / 2}
    for name, v in want.items():
        torch.testing.assert_close(_metric(df, name), v, rtol=1e-12, atol=0)
    assert set(df.node) == {"fusion_center", "all"} and set(df.method) == {"fg_ekf t=10"}
    assert set(df.scenario) == {"jiang"} and len(df[df.metric == "runtime_s"]) == 1


def test_jiang_tracker_variance_is_the_ekf_fg_closed_form():
    """One timing from the start: P_{1|1} = 1 / (1 / (P0 + Pv0 + q_x) + 1 / sigma_e^2) (Eq. 18), sigma_e^2 >=
    the CRLB; with a huge obs variance (sigma_y) the refined mean stays at the prediction x0 + v0 = x0."""
    sc = SquaredRangeScenario(num_timings=2, num_samples=5, sigma_y=1.0e6)
    ep = sc.sample(1, sc.network, torch.Generator().manual_seed(0))
    m = FactorGraphMethod(tracker={"obs_var": "crlb"}, learner=FactorGraphIdentification(iterations=3))
    est = m.estimate(sc, sc.network, None, ep.measurements, 0)
    p_pred = 10.0 + 10.0 + 1.0
    v = est.cov[0, 0, 0, 0].diagonal()
    assert bool((v < p_pred).all()) and bool((v > p_pred * 0.999).all())
    torch.testing.assert_close(est.mean[0, 0, 0, 0], torch.tensor([2.0, -2.0], dtype=F64), rtol=0, atol=0.05)


# ------------------------------------------------------------------------------------------ Braga
SMALL = dict(steps=30, num_particles=24, terrain=8000.0)


def _braga(strategy="consensus_10", **kw):
    """A small scenario and the method; ``em`` / ``modes`` go to its learner (the online EM)."""
    sc = TerrainScenario(steps=SMALL["steps"], terrain={"size_m": SMALL["terrain"]}, seed=kw.pop("seed", 2))
    learner = OnlineEM(**{k: kw.pop(k) for k in ("em", "modes") if k in kw})
    m = RBPFMethod(StatisticsConsensus(sc.network.adjacency, strategy), num_particles=SMALL["num_particles"],
                   learner=learner, **kw)
    return sc, m


def test_braga_method_equals_the_study_on_its_runs():
    """The scenario's flights from the study's streams (seed, "truth", r) and the method (its filter streams
    (seed, "filter", i)) give the study's estimates bit for bit, for every strategy (the study runs them
    together in one batch; the method one at a time)."""
    seed, n = 2, 2
    strategies = ["noncooperative", "centralised", "consensus_3"]
    pi0 = [[0.9, 0.1], [0.2, 0.8]]  # rows that differ: the known start mode (init_mode=true) matters
    task = BragaTask(mc_runs=n, mc_batch=n, workers=1, steps=SMALL["steps"], num_particles=SMALL["num_particles"],
                     terrain=BragaTerrain(size_m=SMALL["terrain"]), strategies=strategies,
                     modes=BragaModes(pi_init=pi0))
    job = BragaStudy(task, seed, F64, CPU).job()
    scn, res = simulate_and_filter(job, list(range(n)))
    sc, _ = _braga(seed=seed)
    assert torch.equal(sc.terrain.z, job.terrain.z)
    ep = sc.sample(n, sc.network, Streams.from_keys([(seed, "truth", r) for r in range(n)], (n,)))
    assert torch.equal(sc.positions(ep.states), scn.x[..., :2].transpose(1, 2))
    idx = torch.arange(4)
    assert torch.equal(ep.meas[idx, :, :, idx, 0], scn.y.transpose(0, 1))  # node s reads platform s's altimeter
    assert torch.equal(ep.meas[idx, :, 0, idx, 1], scn.r[..., 0].T.to(F64))  # and knows its mode at t = 0
    assert int(ep.visible.sum()) == n * 4 * (SMALL["steps"] + 1)
    for c, strategy in enumerate(strategies):
        m = RBPFMethod(StatisticsConsensus(sc.network.adjacency, strategy), num_particles=SMALL["num_particles"],
                       learner=OnlineEM(modes={"pi_init": pi0}))
        est = m.estimate(sc, sc.network, None, ep.measurements, seed)
        assert torch.equal(est.mean[0, :, 1:], res.est[:, :, c, :, :2].permute(1, 0, 2, 3)), strategy
        assert torch.equal(est.mean[0, :, 0], scn.x[:, :, 0, :2])  # t = 0: the known start
        cov = res.pos_cov[:, :, c].permute(1, 0, 2, 3, 4)  # (B, K, S, 2, 2)
        assert torch.equal(est.cov[0, :, 1:], cov) and not est.cov[0, :, 0].any(), strategy  # t = 0: known
        assert est.nodes == ["onboard"]


def test_rbpf_position_covariance_is_the_particles_spread():
    """run_tbn's pos_cov: symmetric, positive semi-definite, its trace the squared weighted RMS spread of the
    particles about their mean (the diagnostics' ``spread``), and zero with a single particle."""
    seed, n = 2, 1
    sc, m = _braga(seed=seed)
    scn = sc.flights(n, episode_streams(seed, "test", 0, n))
    kw = dict(r0=scn.r[..., 0], gen=Streams.from_keys([(seed, "filter", 0)], (n, 1)))
    res = run_tbn(scn.y, scn.terrain, scn.x[:, :, 0], ["consensus_10"], m.fusion.weights, m.init, m_dyn(sc),
                  num_particles=SMALL["num_particles"], diagnostics=True, **kw)
    cov = res.pos_cov
    assert cov.shape == (*res.est.shape[:-1], 2, 2)
    torch.testing.assert_close(cov, cov.transpose(-1, -2), rtol=0, atol=0)
    assert bool((torch.linalg.eigvalsh(cov) > -1e-9).all())
    torch.testing.assert_close(cov.diagonal(dim1=-2, dim2=-1).sum(-1), res.diagnostics["spread"].square(),
                               rtol=1e-10, atol=1e-12)
    assert float(res.diagnostics["spread"].max()) > 1.0  # the check is not vacuous: the particles do spread
    one = run_tbn(scn.y, scn.terrain, scn.x[:, :, 0], ["consensus_10"], m.fusion.weights, m.init, m_dyn(sc),
                  num_particles=1, **{**kw, "gen": Streams.from_keys([(seed, "filter", 0)], (n, 1))})
    assert not one.pos_cov.any()


def test_braga_cell_rows_by_hand():
    """The cell's rows: the study's simulate + run_tbn on the cell's test streams, errors of every platform's
    own filter (node s -> platform s), RMSE over t = 1..K and the 4 platforms; NEES with the particles' covariance."""
    seed, n = 1, 2
    sc, m = _braga(seed=seed)
    df = _cell_rows(sc, m, seed, n, train=1)
    scn = sc.flights(n, episode_streams(seed, "test", 0, n))
    res = run_tbn(scn.y, scn.terrain, scn.x[:, :, 0], ["consensus_10"], m.fusion.weights, m.init,
                  m_dyn(sc), num_particles=SMALL["num_particles"], r0=scn.r[..., 0],
                  gen=Streams.from_keys([(seed, "filter", i) for i in range(n)], (n, 1)))
    d2 = (res.est[:, :, 0, :, :2] - scn.x[:, :, 1:, :2].permute(2, 0, 1, 3)).square().sum(-1)  # (K, B, S)
    torch.testing.assert_close(_metric(df, "rmse"), d2.mean((0, 2)).sqrt(), rtol=1e-12, atol=0)
    torch.testing.assert_close(_metric(df, "pos_err"), d2.sqrt().mean((0, 2)), rtol=1e-12, atol=0)
    e = (res.est[:, :, 0, :, :2] - scn.x[:, :, 1:, :2].permute(2, 0, 1, 3)).unsqueeze(-1)  # (K, B, S, 2, 1)
    p = res.pos_cov[:, :, 0]  # (K, B, S, 2, 2)
    nees = (e.transpose(-1, -2) @ torch.linalg.solve(p, e)).squeeze((-1, -2))  # (K, B, S)
    torch.testing.assert_close(_metric(df, "nees_pos"), nees.sum(-1).mean(0) / 8, rtol=1e-10, atol=0)  # 2A = 8
    assert set(df.method) == {"rbpf_em consensus_10"}


def m_dyn(sc):
    from dslearn.sim.terrain import cv_model

    return cv_model(sc.dt, 100.0, (1.0, 0.0), dtype=F64)


def test_braga_init_mode_uses_the_known_start_mode():
    """init_mode=true reads the t = 0 mode of the measurements: a wrong mode there changes the estimates (with an
    initial transition matrix whose rows differ: with the paper's uniform rows alpha_{1|0} is the same for any
    alpha_{0|0}); init_mode=uniform does not read it."""
    sc, m = _braga(modes={"pi_init": [[0.9, 0.1], [0.2, 0.8]]})
    ep = sc.sample(1, sc.network, torch.Generator().manual_seed(3))
    base = m.estimate(sc, sc.network, None, ep.measurements, 0).mean
    meas = ep.measurements
    flipped = meas.meas.clone()
    idx = torch.arange(4)
    flipped[idx, :, 0, idx, 1] = 1.0 - flipped[idx, :, 0, idx, 1]
    moved = m.estimate(sc, sc.network, None, type(meas)(flipped, meas.visible), 0).mean
    assert not torch.equal(base, moved)
    _, u = _braga(em={"init_mode": "uniform"}, modes={"pi_init": [[0.9, 0.1], [0.2, 0.8]]})
    a = u.estimate(sc, sc.network, None, meas, 0).mean
    b = u.estimate(sc, sc.network, None, type(meas)(flipped, meas.visible), 0).mean
    assert torch.equal(a, b)


# ------------------------------------------------------------------------------------------ fits
SPECS = {"yu": ScenarioSpec("yu", "position", 2, "pv2d", 0.25, 12),
         "jiang": ScenarioSpec("jiang", "squared_range", 1, "param2d", 1.0, 49, networked=False),
         "braga": ScenarioSpec("braga", "terrain_altitude", 4, "platform", 0.05, 1800)}


def test_fits_and_reasons():
    """Each method fits its own scenario only; the reason names what it needs and what the scenario has."""
    sc_adj = torch.tensor([[0, 1], [1, 0]], dtype=torch.bool)
    fg = FactorGraphMethod()
    rb = RBPFMethod(StatisticsConsensus(sc_adj, "centralised"))
    assert fg.fits(SPECS["jiang"]) is None and rb.fits(SPECS["braga"]) is None
    assert fg.fits(SPECS["braga"]).endswith("needs measurement squared_range; scenario braga has terrain_altitude")
    assert rb.fits(SPECS["jiang"]).endswith("needs measurement terrain_altitude; scenario jiang has squared_range")
    assert rb.fits(SPECS["yu"]).endswith("scenario yu has position")
    unnetworked = ScenarioSpec("b2", "terrain_altitude", 4, "platform", 0.05, 10, networked=False)
    assert rb.fits(unnetworked).endswith("needs networked True; scenario b2 has False")
    for name in ("jiang", "braga"):  # DGPT's reasons (its fits need no parts); the distributed filter's engine
        want = f"needs measurement position; scenario {name} has {SPECS[name].measurement}"  # reads them (sensor)
        why = DGPTMethod.fits(None, SPECS[name])
        assert why.startswith("Liu's DGPT " + want + ": ") and "fixes no position" in why, why  # and why (intrinsic)
        assert DistributedFilter.spec_misfit(SPECS[name]) is None


@pytest.mark.parametrize("overrides,needle", [
    (["method=fg_ekf", "scenario=braga"], "fg_ekf t=10 does not fit scenario braga: Jiang's"),
    (["method=rbpf_em", "scenario=jiang"], "rbpf_em consensus_10 does not fit scenario jiang: Braga"),
    (["method=ekf_lin_hybrid", "scenario=jiang"], "ekf lin hybrid does not fit scenario jiang: consensus=hybrid exchanges information"),
    (["method=dgpt_gpoe", "scenario=braga"], "dgpt gpoe does not fit scenario braga: Liu's DGPT"),
    (["method=ekf_lin_hybrid", "scenario=yu_two_agents", "consensus=statistics"],
     "consensus=statistics is a cooperation on sufficient statistics"),
    (["method=rbpf_em", "scenario=braga", "consensus=hybrid"], "consensus=statistics"),
    (["method=rbpf_em", "scenario=braga", "consensus.strategy=average"], "consensus.strategy='average'"),
    (["method=rbpf_em", "scenario=braga", "consensus.strategy=centralised", "consensus.weights=metropolis"],
     "apply to consensus_<q> only"),
    (["method=rbpf_em", "scenario=braga", "learner.em.init_mode=guess"], "learner.em.init_mode"),
    (["method=rbpf_em", "scenario=braga", "+learner.em.lr=1"], "learner.em: unknown key(s) ['lr']"),
    (["method=rbpf_em", "scenario=braga", "learner.modes.sigma_init=[5.0,-1.0]"], "learner.modes"),
    (["method=fg_ekf", "scenario=jiang", "learner.fg.schedule=random"], "learner.fg.schedule"),
    (["method=fg_ekf", "scenario=jiang", "filter.tracker.process_var=-1"], "filter.tracker.process_var=-1"),
    (["method=fg_ekf", "scenario=jiang", "learner.iterations=0"], "learner.iterations=0"),
    (["method=fg_ekf", "scenario=jiang", "scenario.coefficients=[[1,2,3]]"], "2 parameters"),
    (["method=rbpf_em", "scenario=braga", "scenario.edges=[[0,1],[2,3]]"], "scenario.edges"),
])
def test_refusals_name_the_key(overrides, needle):
    with pytest.raises(ConfigError) as e:
        _compose("task=matrix", *overrides)
    assert needle in str(e.value)


def test_parts_a_method_does_not_take_are_refused():
    """fg_ekf takes no fusion, motion or observation part; rbpf_em no motion or observation part: the command
    line may not set them (the start-up check of dslearn-run), and the scenarios place their own sensors."""
    from dslearn.schemas.base import check_overrides

    cfg = _compose("task=matrix", "method=fg_ekf", "scenario=jiang")
    for line in ("consensus=poe", "model=lin", "observation=gp", "network=yu"):
        with pytest.raises(ConfigError, match="does not use the root group"):
            check_overrides(cfg, [(line.split("=")[0], line)])
    cfg = _compose("task=matrix", "method=rbpf_em", "scenario=braga")
    check_overrides(cfg, [("consensus", "consensus=statistics")])
    for line in ("model=lin", "observation=gp", "network=yu"):
        with pytest.raises(ConfigError, match="does not use the root group"):
            check_overrides(cfg, [(line.split("=")[0], line)])
    assert OmegaConf.select(cfg, "consensus.strategy") == "consensus_10"
