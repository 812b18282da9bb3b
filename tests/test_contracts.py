"""Contract tests: every option of every config group composes and its part instantiates, every
experiment composes and passes the validation layer, and every implementation of a role keeps
the role's contract (shapes, symmetry, positive definiteness, finite-difference Jacobians)."""

from __future__ import annotations

import inspect
import math

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import get_object
from omegaconf import OmegaConf

from dslearn.compose import build, build_fusion, build_motion_model, build_network, build_observation, build_scenario
from dslearn.data.ethucy import data_available as ethucy_data_available
from dslearn.schemas.core import CONF_DIR, validate_config
from dslearn.models.base import MotionModel, ObservationModel

GROUPS = sorted(p.name for p in CONF_DIR.iterdir() if p.is_dir() and not p.name.startswith("_"))


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return compose("config", overrides=list(overrides))


ALL_OPTIONS = [(g, o) for g in GROUPS if g != "experiment" for o in _options(g)]


def test_every_group_has_options():
    assert {"model", "observation", "consensus", "network", "scenario", "filter", "task", "experiment"} <= set(GROUPS)
    assert all(_options(g) for g in GROUPS), [g for g in GROUPS if not _options(g)]


# ----------------------------------------------------------------- what every option sets and builds
S = 10  # nodes of the default layout: 4 sensors + 6 communication-only
CPU, F64 = torch.device("cpu"), torch.float64
LIU = ["experiment=liu_table1"]  # the study whose scenario options s1-s3 narrow task.scenarios

# The context an option is composed in: the default study unless the group belongs to another study.
CONTEXT: dict[str, list[str]] = {}
PLUS = {"dataset", "folds", "lstm"}  # groups outside the root defaults ('+group=option')


def _uniform(adj):
    """The paper's weights by hand: 1 / (|N_i| + 1) on N_i and i, 0 elsewhere."""
    n = adj.shape[0]
    w = torch.zeros(n, n, dtype=F64)
    for i in range(n):
        nbrs = [j for j in range(n) if j == i or bool(adj[i, j])]
        for j in nbrs:
            w[i, j] = 1.0 / len(nbrs)
    return w


def _plan(cfg):
    from dslearn import api
    from dslearn.schemas import validate_task

    validate_task(cfg)
    return api.build_study(cfg).plan()


def _check_data(option, cfg, world):  # Yu et al. V-D: 200 + 50 episodes; small: 30 + 20
    from dslearn.learning.online import checkpoints

    train, test = {"paper": (200, 50), "small": (30, 20)}[option]
    assert (cfg.data.train_episodes, cfg.data.test_episodes, cfg.data.eval_at) == (train, test, None)
    assert checkpoints(cfg.data) == [train]  # evaluated once, after all training episodes


DATASETS = {  # label, files, frame rate (the physical step is 10 frames / fps), first validation frame per file
    "eth": ("ETH", ("biwi_eth.txt",), 15.0, (10240,)),
    "hotel": ("HOTEL", ("biwi_hotel.txt",), 25.0, (14400,)),
    "univ": ("UNIV", ("students001.txt", "students003.txt"), 25.0, (3550, 4320)),
    "zara1": ("ZARA1", ("crowds_zara01.txt",), 25.0, (7110,)),
    "zara2": ("ZARA2", ("crowds_zara02.txt",), 25.0, (8420,)),
    "zara3": ("ZARA3", ("crowds_zara03.txt",), 25.0, (6030,)),
    "uni_examples": ("UNI-EX", ("uni_examples.txt",), 25.0, (5940,)),
}


def _check_dataset(option, cfg, world):
    from dslearn.schemas.datasets import spec_from_config

    label, files, fps, val = DATASETS[option]
    spec = spec_from_config(option, cfg.dataset)
    assert (spec.label, spec.files, spec.frame_step, spec.units, spec.root) == (label, files, 10, "m", None)
    assert spec.step("benchmark") == 0.4 and spec.step("physical") == pytest.approx(10.0 / fps, rel=1e-15)
    assert spec.split() == dict(zip(files, val))


def _check_folds(option, cfg, world):  # the leave-one-scene-out benchmark, as the forecasting task composes it
    assert list(cfg.folds.test) == ["eth", "hotel", "univ", "zara1", "zara2"]
    assert list(cfg.folds.pool) == ["eth", "hotel", "zara1", "zara2", "univ", "zara3", "uni_examples"]
    assert cfg.folds == _compose("experiment=ethucy_forecast").task.folds


def _check_lstm(option, cfg, world):
    """Yu et al. VI-C, as ``dslearn-train-lstm`` composes it; the tracking study's copy agrees key by key."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        node = compose("train_lstm").lstm
    assert node == cfg.lstm
    want = dict(embed=64, hidden=64, obs_len=2, pred_len=10, schedule="fixed", epochs=50, batch_size=8, lr=1e-3,
                pooling="none")
    assert {k: node[k] for k in want} == want
    option = _compose("model=lstm").model  # the motion-model option (Yu study, real-data tracking) agrees key by key
    # (weights_dtype: the motion model's own; the training app has its run-wide dtype)
    assert set(option) - set(node) == {"_target_", "_partial_", "name", "val_fraction", "process_noise", "train_on",
                                       "weights_dtype"}
    assert set(node) <= set(option) and {k: option[k] for k in node} == dict(node)


TASKS = {"braga_tbn": "BragaTask", "ethucy_forecast": "EthucyForecastTask", "ethucy_tracking": "EthucyTrackingTask",
         "jiang_fg": "JiangTask", "liu_dgpt": "LiuDgpt", "yu": "YuTask", "yu_faults": "FaultTask",
         "matrix": "MatrixSettings", "gp_bayes_filters": "GPBayesTask"}


def _check_task(option, cfg, world):  # the study's schema and its class in dslearn.studies.<task>
    import importlib

    assert cfg.task.name == option and OmegaConf.get_type(cfg.task).__name__ == TASKS[option]
    module, _, name = cfg.task._target_.rpartition(".")  # a component: a class with a run(diagnostics, progress)
    assert module == f"dslearn.studies.{option}"
    assert callable(getattr(getattr(importlib.import_module(module), name), "run"))
    validate_config(cfg)


def _check_filter(option, cfg, world):
    from dslearn.compose import build_predict
    from dslearn.filters.information import ExtendedPredict
    from dslearn.filters.ukf import UnscentedPredict

    if option == "dgpt":  # Liu et al.'s tracker: a method of its own (task=matrix), no prediction step
        from dslearn.methods.dgpt import DGPTMethod

        assert get_object(cfg.filter._target_) is DGPTMethod and "predict" not in cfg.filter
        assert (cfg.filter.window, cfg.filter.gp_input) == (10, "temporal") and "hyper" not in cfg.filter
        return
    if option in ("fg_ekf", "rbpf_em"):  # Jiang's FG + EKF-FG, Braga's RBPF + online EM: the studies' values
        from dslearn.methods.factor_graph import FactorGraphMethod
        from dslearn.methods.rbpf import RBPFMethod

        f = cfg.filter
        assert get_object(f._target_) is {"fg_ekf": FactorGraphMethod, "rbpf_em": RBPFMethod}[option]
        assert "predict" not in f
        if option == "fg_ekf":  # conf/task/jiang_fg.yaml: max_iter, scenario.initial_state, fg, tracker
            task = _compose("experiment=jiang_fg").task
            assert list(f.initial_state) == list(task.scenario.initial_state) and f.tracker == task.tracker
            assert "fg" not in f and "iterations" not in f  # the identification's: learner=fg_identification
        else:  # conf/task/braga_tbn.yaml: particles, filter noise, resampling, EM, initial modes, kernel
            task = _compose("experiment=braga_tbn").task
            assert (f.num_particles, f.process_noise, f.ess_threshold, f.regularise) == (
                task.num_particles, task.process_noise, task.ess_threshold, task.resampling.regularise)
            assert f.backward_kernel == task.backward_kernel
            assert "em" not in f and "modes" not in f  # the online EM's: learner=online_em
        return
    if option == "fg_ekf_lin":  # the FG identification of a motion model + a Kalman filter on position sensors
        from dslearn.methods.factor_graph import FactorGraphMotionMethod

        f = cfg.filter
        assert get_object(f._target_) is FactorGraphMotionMethod and "predict" not in f
        assert (f.rounds, f.prior_pos_std, f.prior_vel_std) == (10, 1000.0, 1000.0)
        assert "fg" not in f and "iterations" not in f  # the identification's: learner=fg_identification
        return
    if option == "rbpf_em_lin":  # the RBPF over noise modes (any tracking sensor): its own values, the EM the learner's
        from dslearn.methods.rbpf_modes import RBPFModesMethod

        f = cfg.filter
        assert get_object(f._target_) is RBPFModesMethod and "predict" not in f
        assert (f.num_particles, f.process_noise, f.ess_threshold, f.prior_pos_std, f.prior_vel_std,
                f.ekf_iterations) == (64, 1.0, 0.5, 1000.0, 1000.0, None)  # None: 5 with a nonlinear sensor
        assert "em" not in f and "modes" not in f  # the online EM's: learner=online_em_sensor
        return
    f = cfg.filter  # ukf, ukf_mm and adf inherit the priors and the learning gate of the default
    assert (f.prior_pos_std, f.prior_vel_std, f.learn_gate_std) == (1000.0, 1000.0, 2.0)
    step = build_predict(cfg)
    if option == "default":
        assert type(step) is ExtendedPredict
    elif option == "adf":  # the GP-ADF: no settings of its own
        from dslearn.filters.adf import MomentMatchingPredict

        assert type(step) is MomentMatchingPredict and set(f.predict) == {"_target_"} and step.name == "adf"
    elif option == "pf":  # the GP-PF's prediction: 500 particles, its generator seeded from the run's seed
        from dslearn.filters.particle import ParticlePredict

        assert type(step) is ParticlePredict and set(f.predict) == {"_target_", "particles", "seed"}
        assert (step.particles, step.seed, step.name) == (500, int(cfg.seed), "pf")
    else:  # ukf_mm: the ukf's parameters, the latent variance averaged over the sigma points
        assert type(step) is UnscentedPredict and (step.alpha, step.beta, step.kappa) == (1.0, 2.0, 0.0)
        assert step.expected_variance is (option == "ukf_mm") and step.name == option


GP_MODELS = {  # variant, prior mean, process noise, aggregation rule (None: each node its own GP)
    "gp": ("exact", "zero", "latent", None), "gp_increment": ("exact", "identity", "latent", None),
    "gp_adaptive": ("exact", "identity", "adaptive", None), "gp_window": ("window", "identity", "latent", None),
    "gp_sgpr": ("sgpr", "identity", "latent", None), "gp_ssgp": ("ssgp", "identity", "latent", None),
    "gp_rbcm": ("exact", "zero", "latent", "rbcm"), "gp_increment_rbcm": ("exact", "identity", "latent", "rbcm"),
}


def _check_model(option, cfg, world):
    from dslearn.models import ConstantVelocity, GPMotionModel, SocialForce
    from dslearn.models.aggregated import AggregatedGPMotion

    _, scenario, network = world
    assert cfg.model.name == option or option == "gp_cv"  # gp_rbcm / gp_increment_rbcm: the label names the rule
    m = build_motion_model(cfg.model, scenario, network, F64, CPU)
    assert m.state_dim == 8  # 2 agents x (position, velocity)
    if option == "lin":  # the paper's LIN: Q = 0.1^2 I
        assert type(m) is ConstantVelocity and m.noise_std == 0.1
        return
    if option == "cv_damped":  # the damped constant-velocity model; a = 1, q = null: LIN (its values)
        from dslearn.models.constant_velocity import DampedConstantVelocity

        assert type(m) is DampedConstantVelocity and (m.a, m.q, m.noise_std) == (1.0, None, 0.1)
        assert not m.learnable and not m.learns_offline
        return
    if option == "gp_cv":  # the increment GP's keys with the constant-velocity prior mean at the scenario's dt
        assert type(m) is GPMotionModel and cfg.model.name == "gp_increment_cv" and (m.variant, m.noise_mode) == ("exact", "latent")
        assert m.gp.mean_type == "constant_velocity" and m.gp.num_nodes == S
        x = torch.randn(S, 3, 8, dtype=F64, generator=torch.Generator().manual_seed(4))
        torch.testing.assert_close(m(x, scenario.ctx()), x @ ConstantVelocity(2).matrix(0.25).T)  # no data: the CV step
        return
    if option == "sfm_fit":  # the social force whose (tau, alpha, beta) a fit sets; before it (1, 0, 1), v* = 0
        from dslearn.learning.sfm_fit import FittedSocialForce

        assert type(m) is FittedSocialForce and m.learns_offline and m.train_on == "truth" and m.noise_std == 0.1
        assert m.params() == {"tau": 1.0, "alpha": 0.0, "beta": 1.0} and m.fit_settings["refine_iters"] == 150
        assert m.fit_settings["tau_grid"] == (0.25, 0.5, 1.0, 2.0, 4.0, 8.0) and m.fit_settings["desired_steps"] == 1
        return
    if option in ("lstm", "social_lstm"):  # the paper's VI-C network, sized by the scenario, trained offline
        from dslearn.models.lstm import SocialLSTM

        assert type(m) is SocialLSTM and m.learns_offline and not m.learnable
        assert (m.num_agents, m.dt, m.obs_len, m.pred_len, m.embed, m.hidden) == (2, 0.25, 2, 10, 64, 64)
        assert m.pooling == {"lstm": "none", "social_lstm": "social"}[option] and (m.grid, m.neighbourhood) == (4, 2.0)
        assert {k: m.offline[k] for k in ("schedule", "epochs", "batch_size", "lr", "process_noise", "train_on")} == {
            "schedule": "fixed", "epochs": 50, "batch_size": 8, "lr": 1e-3, "process_noise": "residuals", "train_on": None}
        x = torch.zeros(1, 8, dtype=F64)
        torch.testing.assert_close(m.noise_cov(x, scenario.ctx())[0], 0.01 * torch.eye(8, dtype=F64))  # before a fit
        return
    if option == "sfm":  # the true model with the simulation's parameters (scenario yu_two_agents)
        assert type(m) is SocialForce and m.noise_std == 0.001
        x = scenario.sample(1, network, torch.Generator().manual_seed(0)).states[:, 0].to(F64)
        torch.testing.assert_close(m(x, scenario.ctx()), scenario.sfm(x, scenario.ctx()), rtol=0, atol=1e-15)
        return
    variant, mean, noise, rule = GP_MODELS[option]
    if rule is not None:
        assert type(m) is AggregatedGPMotion and m.method == rule and m.normalise_beta is False
        m = m.base
    assert type(m) is GPMotionModel and (m.variant, m.gp.mean_type, m.noise_mode) == (variant, mean, noise)
    assert m.gp.num_nodes == S and m.gp.input_dim == m.gp.output_dim == 8
    size = {"window": ("window", 500), "sgpr": ("M", 128), "ssgp": ("features", 200)}.get(variant)
    if size is not None:
        assert getattr(m.gp, size[0]) == size[1]
    # sigma_f^2 = 1, l = 2, sigma_eps^2 = 0.5^2 (the exact GP holds them rounded to float32: ~5e-8 relative)
    hyp = torch.stack([m.gp.outputscale.flatten(), m.gp.lengthscale.flatten(), m.gp.noise_var.flatten()])
    torch.testing.assert_close(hyp, torch.tensor([[1.0], [2.0], [0.25]], dtype=F64).expand(3, S), rtol=1e-7, atol=0)


def _check_observation(option, cfg, world):
    """Both give h(y) = position, C = [I 0] before any learning; R = sigma_nu^2 I (linear) or the GP's prior
    predictive variance (sigma_f^2 + sigma_nu^2) I = 1.04 I (gp); sigma_nu from network.meas_std = 0.2.
    The nonlinear sensors: sized by the scenario of their measurement kind (Jiang's squared ranges: its sensors,
    samples and sigma_y; Braga's terrain: its map and its nominal noise; range and bearing: Jiang's sensors)."""
    from dslearn.models import observation as O
    from dslearn.models.observation import GPObservation, LinearPositionObservation

    if option == "bearing":  # one sample per step: Yu's nodes as the sensors, sigma_nu their noise
        _, yu, net = world
        obs = build_observation(cfg.observation, net, F64, CPU, yu)
        assert type(obs) is O.BearingObservation and obs.sensors.equal(net.positions) and obs.noise_std == 0.2
        return
    if option in ("squared_range", "range", "terrain", "sensor"):
        name = "braga" if option == "terrain" else "jiang"
        sc = build_scenario(_compose("task=matrix", "method=fg_ekf", f"scenario={name}"))
        obs = build_observation(cfg.observation, sc.network, F64, CPU, sc)
        cls = {"squared_range": O.SquaredRangeObservation, "range": O.RangeObservation, "sensor":
               O.SquaredRangeObservation, "bearing": O.BearingObservation, "terrain": O.TerrainAltitudeObservation}
        assert type(obj := obs) is cls[option] and obj.noise_std == sc.network.meas_std
        if option == "terrain":
            assert obs.elevation.equal(sc.terrain.z) and obs.resolution == sc.terrain.resolution and obs.noise_std == 4.0
        else:
            assert obs.sensors.equal(sc.sensors) and obs.noise_std == 5.0
            assert obs.samples == sc.num_samples
        if option == "sensor":  # on Yu's scenario: the linear position sensor, sigma_nu its sensors'
            _, yu, net = world
            lin = build_observation(cfg.observation, net, F64, CPU, yu)
            assert type(lin) is LinearPositionObservation and lin.noise_std == 0.2
        return
    _, scenario, network = world
    obs = build_observation(cfg.observation, network, F64, CPU)
    assert type(obs) is {"linear": LinearPositionObservation, "gp": GPObservation}[option]
    y = torch.randn(S, 2, 4, dtype=F64, generator=torch.Generator().manual_seed(2))
    h, C, R = obs.linearize(y)
    eye = torch.eye(2, dtype=F64)
    torch.testing.assert_close(h, y[..., :2], rtol=0, atol=1e-15)
    torch.testing.assert_close(C, torch.cat([eye, torch.zeros(2, 2, dtype=F64)], -1).expand(S, 2, 2, 4), rtol=0, atol=1e-15)
    r = 0.2**2 + (1.0 if option == "gp" else 0.0)  # the GP's hyperparameters: float32-rounded, ~5e-8 relative
    torch.testing.assert_close(R, r * eye.expand(S, 2, 2, 2), rtol=1e-7, atol=0)


FUSION_CLASSES = {"individual": "Individual", "ce": "ConsensusOnEstimates", "cm": "ConsensusOnMeasurements",
                  "ci": "ConsensusOnInformation", "hybrid": "HybridConsensus", "hybrid_nodes": "HybridConsensus",
                  "centralized": "Centralized"}
#: the fusion centre's aggregation rules of Liu et al.'s DGPT (filter=dgpt): kind "aggregation"
AGGREGATIONS = {"poe", "gpoe", "bcm", "rbcm"}


def _check_consensus(option, cfg, world):  # L = 4 rounds of the paper's weights; hybrid_nodes: omega = S
    _, _, network = world
    c = cfg.consensus
    if option == "statistics":  # Braga et al.'s cooperation on sufficient statistics: 10 rounds, Eq. 26 weights
        from dslearn.fusion.weights import half_max_degree

        f = build_fusion(c, network)
        assert type(f).__name__ == "StatisticsConsensus" and f.kind == "statistics"
        assert (f.strategy, f.iterations, f.rule, f.name) == ("consensus_10", 10, "half_max_degree", "consensus_10")
        w = half_max_degree(network.adjacency.to(torch.bool))
        torch.testing.assert_close(f.weights, w, rtol=0, atol=0)
        torch.testing.assert_close(f.matrix(), torch.linalg.matrix_power(w, 10), rtol=1e-12, atol=1e-15)
        return
    if option in AGGREGATIONS:  # an aggregation rule: the rule it names, raw Eq. 7 weights
        f = build_fusion(c, network)
        assert type(f).__name__ == "AggregationRule" and f.kind == "aggregation"
        assert (f.rule, f.name, f.normalise_beta) == (option, option, False)
        return
    assert (c.name, c.iterations, c.weights) == (option.replace("_nodes", ""), 4, "uniform")
    assert c.omega == ("nodes" if option == "hybrid_nodes" else "one")
    f = build_fusion(c, network)
    assert type(f).__name__ == FUSION_CLASSES[option] and f.iterations == 4
    assert f.omega == (float(S) if option == "hybrid_nodes" else 1.0)
    torch.testing.assert_close(f.weights, _uniform(network.adjacency), rtol=0, atol=1e-15)


BLIND = [[4.0, 6.0], [2.5, 4.0], [5.5, 4.0], [4.0, 1.25], [1.0, 6.0], [7.0, 6.0], [1.5, 2.0], [6.5, 2.0],
         [4.0, 3.0], [4.0, 7.5]]


def _check_network(option, cfg, world):
    """4 sensors (first) + 6 communication-only nodes in the 8 x 8 area, sensing range 4 m, sigma_nu = 0.2 m;
    nodes closer than the radius are linked (yu: 4 m, placement seed 0; yu_blind: the listed layout, 3.2 m)."""
    net = build(cfg.network, "network")
    assert net.num_nodes == S and net.is_sensor.tolist() == [True] * 4 + [False] * 6
    assert (net.sensing_range, net.meas_std) == (4.0, 0.2)
    pos = net.positions
    if option == "yu_blind":
        torch.testing.assert_close(pos, torch.tensor(BLIND, dtype=pos.dtype), rtol=0, atol=0)
    assert bool(((pos >= 0) & (pos <= 8)).all())
    radius = {"yu": 4.0, "yu_blind": 3.2}[option]
    want = [[i != j and math.dist(pos[i].tolist(), pos[j].tolist()) < radius for j in range(S)] for i in range(S)]
    assert net.adjacency.tolist() == want


def _check_scenario(option, cfg, world):
    if option == "yu_two_agents":  # Yu et al. V-A: 2 agents, T = 3 s, dt = 0.25 s (12 steps), the 8 x 8 area
        sc = build_scenario(cfg)
        assert (sc.num_agents, sc.dt, sc.steps, tuple(sc.area), sc.process_std) == (2, 0.25, 12, (0.0, 8.0, 0.0, 8.0), 0.001)
        return
    if option == "yu_crowd_clutter":  # Yu's crowd as unlabelled detections: four walkers, P_D 0.9, 1 false per step
        sc = build_scenario(cfg)
        spec = sc.spec
        assert (spec.name, spec.measurement, spec.num_agents, spec.labelled, sc.dt, sc.steps) == \
            ("yu_crowd_clutter", "position", 4, False, 0.25, 12)
        assert (sc.p_detect, sc.clutter_rate, sc.start_velocity_std, sc.network) == (0.9, 1.0, 1.0, None)
        assert spec.match_distance == 2.0
        assert not sc.births and not getattr(spec, "births", False)
        return
    if option == "yu_crowd_births":  # the crowd with targets that enter and leave: 6 s (24 steps), declared births
        sc = build_scenario(cfg)
        spec = sc.spec
        assert (spec.name, spec.measurement, spec.num_agents, spec.labelled, spec.births, sc.dt, sc.steps) == \
            ("yu_crowd_births", "position", 4, False, True, 0.25, 24)
        assert (sc.p_detect, sc.clutter_rate, sc.start_velocity_std, sc.birth_until, sc.death_from, sc.network) == \
            (0.9, 1.0, 1.0, 0.4, 0.6, None)
        assert spec.match_distance == 2.0
        return
    if option == "liu_s1_clutter":  # Liu's S1 field as unlabelled detections: P_D 0.9, 1 false per sensor and step
        cfg = _compose("task=matrix", "method=ekf_lin_hybrid_gnn", f"scenario={option}")
        sc = build_scenario(cfg)
        spec = sc.spec
        assert (spec.name, spec.measurement, spec.num_agents, spec.state, spec.labelled, sc.dt, sc.steps) == \
            ("liu_s1_clutter", "position", 1, "pv2d", False, 1.0, 60)
        assert (sc.p_detect, sc.clutter_rate, sc.start_velocity_std, sc.start_draws, spec.match_distance) == \
            (0.9, 1.0, 1.0, 256, 50.0)
        net = sc.network  # liu_s1's own field
        assert (net.num_nodes, int(net.is_sensor.sum()), net.sensing_range, net.meas_std) == (200, 200, 50.0, 2.0)
        assert cfg.scenario.trajectory._target_ == "dslearn.sim.manoeuvres.generate_s1"
        return
    if option.startswith("liu_"):  # Liu et al.'s S1-S3 as a matrix scenario: one target, 200 sensors, its own field
        cfg = _compose("task=matrix", "method=dgpt_gpoe", f"scenario={option}")
        sc = build_scenario(cfg)
        spec = sc.spec
        assert (spec.name, spec.measurement, spec.num_agents, spec.state, spec.dt) == \
            (option[4:], "position", 1, "pv2d", 1.0)
        net = sc.network  # the scenario's own sensor field: 200 sensors with a 50 m range, sigma 2 m, in 1000 m
        assert (net.num_nodes, int(net.is_sensor.sum()), net.sensing_range, net.meas_std) == (200, 200, 50.0, 2.0)
        assert sc.area == (-500.0, 500.0, -500.0, 500.0) and bool((net.positions.abs() <= 500.0).all())
        assert cfg.scenario.trajectory._target_ == f"dslearn.sim.manoeuvres.generate_{option[4:]}"
        return
    if option.endswith("_crowd"):  # a recorded scene with every pedestrian, unlabelled detections, 4 LiDARs around it
        cfg = _compose("task=matrix", "method=ekf_lin_hybrid_gnn", f"scenario={option}")
        assert cfg.scenario.name == option and cfg.scenario.dataset.files == \
            _compose("task=matrix", "method=ekf_lin_hybrid", f"scenario={option[:-len('_crowd')]}").scenario.dataset.files
        if not ethucy_data_available():
            pytest.skip("the ETH/UCY data are absent")
        sc = build_scenario(cfg)
        spec, net = sc.spec, sc.network
        cap = 60 if option == "eth_univ_crowd" else 12  # UNIV holds 25-83 pedestrians at a time
        assert (spec.name, spec.measurement, spec.num_agents, spec.state, spec.dt, spec.steps, spec.source,
                spec.labelled, spec.births) == (option, "position", cap, "pv2d", 0.4, 15, "recorded", False, True)
        assert (net.num_nodes, int(net.is_sensor.sum()), net.sensing_range, net.meas_std) == (4, 4, 8.0, 0.2)
        assert (sc.p_detect, sc.clutter_rate, sc.start_velocity_std, spec.match_distance) == (0.9, 0.5, 1.0, 2.0)
        # windows of 16 states every 8 steps, at most `cap` pedestrians, the last 20 % of each recording the test pool
        pools = {"eth_zara1_crowd": (83, 20), "eth_zara2_crowd": (57, 14), "eth_eth_crowd": (142, 23),
                 "eth_hotel_crowd": (120, 22), "eth_univ_crowd": (72, 20)}[option]
        assert (sc.pool_size("train"), sc.pool_size("test")) == pools
        return
    if option.startswith("eth_") or option == "corridor":  # a recorded data set: 2 pedestrians, 4 LiDARs around it
        cfg = _compose("task=matrix", "method=ekf_lin_hybrid", f"scenario={option}")
        files = {"eth_zara1": ["crowds_zara01.txt"], "eth_zara2": ["crowds_zara02.txt"], "eth_eth": ["biwi_eth.txt"],
                 "eth_hotel": ["biwi_hotel.txt"], "eth_univ": ["students001.txt", "students003.txt"],
                 "corridor": ["corridor.txt"]}[option]
        assert list(cfg.scenario.dataset.files) == files and cfg.scenario.name == option
        if option.startswith("eth_") and not ethucy_data_available():
            pytest.skip("the ETH/UCY data are absent")
        sc = build_scenario(cfg)
        spec, net = sc.spec, sc.network
        assert (spec.name, spec.measurement, spec.num_agents, spec.state, spec.dt, spec.steps, spec.source) == \
            (option, "position", 2, "pv2d", 0.4, 11, "recorded")
        assert (net.num_nodes, int(net.is_sensor.sum()), net.sensing_range, net.meas_std) == (4, 4, 8.0, 0.2)
        # the pools of the tracking study's cut (pairs of mutual nearest neighbours, 12 states, the last 20 % of each
        # recording the test pool), as the scenario files state them
        pools = {"eth_zara1": (233, 37), "eth_zara2": (278, 71), "eth_eth": (179, 130), "eth_hotel": (95, 33),
                 "eth_univ": (1355, 215), "corridor": (71, 28)}[option]
        assert (sc.pool_size("train"), sc.pool_size("test")) == pools
        return
    if option in ("jiang", "braga"):  # Jiang's and Braga's settings as matrix scenarios: the studies' values
        method = {"jiang": "fg_ekf", "braga": "rbpf_em"}[option]
        cfg = _compose("task=matrix", f"method={method}", f"scenario={option}")
        sc = build_scenario(cfg)
        spec = sc.spec
        if option == "jiang":  # conf/task/jiang_fg.yaml task.scenario, num_samples, sigma_y
            task = _compose("experiment=jiang_fg").task
            assert (spec.name, spec.measurement, spec.num_agents, spec.state, spec.dt, spec.steps, spec.networked) == \
                ("jiang", "squared_range", 1, "param2d", 1.0, task.scenario.num_timings - 1, False)
            assert sc.sensors.tolist() == task.scenario.sensors and sc.coefficients.tolist() == task.scenario.coefficients
            assert (sc.drive_var, sc.num_samples, sc.sigma_y) == (task.scenario.drive_var, task.num_samples, task.sigma_y)
            assert (sc.network.num_sensors, sc.network.meas_std) == (3, task.sigma_y)
        else:  # conf/task/braga_tbn.yaml: steps, dt, the flights, the true modes, the map, the graph
            task = _compose("experiment=braga_tbn").task
            assert (spec.name, spec.measurement, spec.num_agents, spec.state, spec.dt, spec.steps, spec.networked) == \
                ("braga", "terrain_altitude", 4, "platform", task.dt, task.steps, True)
            for key in ("truth_process_noise", "v0", "start", "formation_spacing", "terrain"):
                assert cfg.scenario[key] == task[key], key
            for key in ("mu_true", "sigma_true", "pi_true"):
                assert cfg.scenario[key] == task.modes[key], key
            assert cfg.scenario.edges == task.network.edges and int(sc.network.adjacency.sum()) == 6
        return
    # a Liu et al. scenario: restricts the study to its generator, run with task.scenario_params.<option>
    cfg = _compose(*LIU, f"scenario={option}")
    target = f"dslearn.sim.manoeuvres.generate_{option}"
    assert cfg.scenario._target_ == cfg.task.scenario_params[option]._target_ == target
    assert _plan(cfg).scenarios == [option]


PRESET_FILTERS = {"ekf": "default", "ukf": "ukf", "dgpt": "dgpt", "adf": "adf", "ukf_mm": "ukf_mm", "pf": "pf"}
PRESET_MODELS = {"lin": "lin", "sfm": "sfm", "gp": "gp_increment", "lstm": "lstm", "social_lstm": "social_lstm"}
PRESET_FUSIONS = {"individual", "hybrid", "centralized"}


def _check_method(option, cfg, world):
    """A preset selects the parts its name says: <filter>_<model>_<fusion> (dgpt_<aggregation rule>)."""
    head, _, rest = option.partition("_")
    if option.startswith("ukf_mm_"):  # the GP-UKF with moment matching: a filter word with an underscore
        head, rest = "ukf_mm", option.removeprefix("ukf_mm_")
    if option.endswith("_backprop"):  # a preset's parts, its numbers learned by backpropagation
        base = option.removesuffix("_backprop")
        assert {k: cfg[k] for k in ("filter", "model", "consensus")} == \
            {k: _compose(f"method={base}")[k] for k in ("filter", "model", "consensus")}
        assert cfg.observation == _compose().observation  # the linear position sensor (whose R it learns)
        plain = _compose("learner=backprop").learner
        if option == "ekf_lin_hybrid_backprop":
            assert cfg.learner == plain
            return
        # the motion model's own parameters with R, the weights and omega (and Q where the model has one)
        assert {k: v for k, v in cfg.learner.items() if k not in ("learn", "model_lr", "chunk")} == \
            {k: v for k, v in plain.items() if k not in ("learn", "model_lr", "chunk")}
        q = [] if "_gp_" in option else ["q"]
        assert list(cfg.learner.learn) == ["model", *q, "r", "weights", "omega"]
        assert cfg.learner.model_lr == (1e-4 if "_lstm_" in option else None)
        assert cfg.learner.chunk is None  # every episode of a step in one backward pass (learner.chunk: the option)
        return
    if option.endswith("_calibrated"):  # a preset's parts, a scale of Q and of R fitted to the training innovations
        base = option.removesuffix("_calibrated")
        assert {k: cfg[k] for k in ("filter", "model", "consensus")} == \
            {k: _compose(f"method={base}")[k] for k in ("filter", "model", "consensus")}
        assert cfg.observation == _compose().observation  # the linear position sensor (whose R it learns)
        assert cfg.learner == _compose("learner=calibrate").learner  # the learner's own settings, unchanged
        return
    if option.endswith(("_gnn", "_jpda")):  # a preset's parts on unlabelled detections: its base and an associator
        base, _, assoc = option.rpartition("_")
        assert {k: cfg[k] for k in ("filter", "model", "observation", "consensus", "learner")} == \
            {k: _compose(f"method={base}")[k] for k in ("filter", "model", "observation", "consensus", "learner")}
        assert cfg.associator == _compose(f"associator={assoc}").associator
        return
    assert cfg.associator == _compose().associator  # every other preset: the labels given (the default)
    if option in ("fg_ekf", "rbpf_em"):  # Jiang's / Braga's method: its filter option (and the statistics part)
        assert cfg.filter == _compose(f"filter={option}").filter
        assert option == "fg_ekf" or cfg.consensus == _compose("consensus=statistics").consensus
        learner = {"fg_ekf": "fg_identification", "rbpf_em": "online_em"}[option]
        assert cfg.learner == _compose(f"learner={learner}").learner  # its own learner, set explicitly
        return
    if option == "fg_ekf_lin":  # its filter option and learner=fg_identification started at constant velocity
        assert cfg.filter == _compose("filter=fg_ekf_lin").filter
        plain = _compose("learner=fg_identification").learner
        assert cfg.learner.iterations == plain.iterations
        assert dict(cfg.learner.fg) == {**plain.fg, "init_guess": [1.0, 0.0], "taylor_point": "guess",
                                        "measurement_var": "known"}
        return
    if option == "ekf_cv_fg_individual":  # the EKF with model=cv_damped, its (a, q) from learner=fg_identification
        assert {k: cfg[k] for k in ("filter", "observation", "consensus")} == \
            {k: _compose("method=ekf_lin_individual")[k] for k in ("filter", "observation", "consensus")}
        assert cfg.model == _compose("model=cv_damped").model
        plain = _compose("learner=fg_identification").learner
        assert cfg.learner.iterations == plain.iterations
        assert dict(cfg.learner.fg) == {**plain.fg, "init_guess": [1.0, 0.0], "taylor_point": "guess",
                                        "measurement_var": "known"}
        return
    if option == "rbpf_em_lin":  # the RBPF over noise modes: its filter option, the scenario's own sensor model,
        assert cfg.filter == _compose("filter=rbpf_em_lin").filter  # the statistics part, its learner
        assert cfg.observation == _compose("observation=sensor").observation
        assert cfg.consensus == _compose("consensus=statistics").consensus
        assert cfg.learner == _compose("learner=online_em_sensor").learner
        return
    filt = _compose(f"filter={PRESET_FILTERS[head]}").filter
    assert cfg.filter == filt  # the filter option, every key
    if head == "dgpt":
        assert rest in AGGREGATIONS and cfg.consensus == _compose(f"consensus={rest}").consensus
        assert cfg.learner == _compose("learner=online_hyperparameters").learner
        return
    model, _, fusion = rest.rpartition("_")
    # the model's natural learner: online for the GP, offline for the LSTMs, none for the fixed models
    learner = {"gp": "online", "lstm": "offline", "social_lstm": "offline", "sfm_fit": "offline"}.get(model, "none")
    model_option = {**PRESET_MODELS, "sfm_fit": "sfm_fit"}[model]  # the fitted social force: one preset (EKF, hybrid)
    assert cfg.learner == _compose(f"learner={learner}").learner
    assert fusion in PRESET_FUSIONS and cfg.consensus == _compose(f"consensus={fusion}").consensus
    # the LSTMs: the matrix's recipe (early stopping, float32 weights), every other key the model option's
    recipe = {"schedule": "early_stopping", "patience": 5, "weights_dtype": "float32"} if "lstm" in model else {}
    assert cfg.model == {**_compose(f"model={model_option}").model, **recipe}
    assert not recipe or all(cfg.model[k] != _compose(f"model={model_option}").model[k] for k in recipe)
    # LIN and the learned models: the scenario's own sensor model (observation=sensor); the social force (the walkers'
    # simulator's own model, fixed or fitted): the linear position sensor
    own = model in ("lin", "gp", "lstm", "social_lstm")
    assert cfg.observation == (_compose("observation=sensor").observation if own else _compose().observation)


LEARNER_CLASSES = {"online": "OnlineLearning", "offline": "OfflineLearning", "none": "NoLearning",
                   "online_em": "OnlineEM", "online_em_sensor": "OnlineEMSensor",
                   "online_hyperparameters": "OnlineHyperparameters",
                   "fg_identification": "FactorGraphIdentification", "backprop": "BackpropLearning",
                   "calibrate": "CalibrateLearning"}


def _check_learner(option, cfg, world):
    """A matrix method's learner: its class, and the paper's settings where it moves them from the study."""
    from dslearn.learning import learners

    obj = build(cfg.learner, "learner")
    assert type(obj).__name__ == LEARNER_CLASSES[option] and obj.name == option
    assert learners.LEARNERS[option] is type(obj)
    if option == "online_em":  # conf/task/braga_tbn.yaml: the EM and its initial modes
        task = _compose("experiment=braga_tbn").task
        assert cfg.learner.em == task.em
        assert dict(cfg.learner.modes) == {k: task.modes[k] for k in ("mu_init", "sigma_init", "pi_init")}
    elif option == "online_em_sensor":  # its defaults (position sensors): the option's values are the class's
        assert obj == learners.OnlineEMSensor() and obj.units == "sensor_std" and obj.em["init_mode"] == "uniform"
    elif option == "fg_identification":  # conf/task/jiang_fg.yaml: max_iter, fg
        task = _compose("experiment=jiang_fg").task
        assert cfg.learner.iterations == task.max_iter and cfg.learner.fg == task.fg
    elif option == "online_hyperparameters":  # conf/task/liu_dgpt.yaml task.hyper
        task = _compose("experiment=liu_table1").task
        assert cfg.learner.hyper == task.hyper
    elif option == "backprop":  # its settings (conf/learner/backprop.yaml) as the learner holds them
        assert set(cfg.learner) == {"_target_", "epochs", "lr", "batch", "loss", "learn", "train_fusion", "model_lr",
                                    "chunk"}
        assert (obj.epochs, obj.lr, obj.batch, obj.loss, obj.learn, obj.train_fusion, obj.model_lr, obj.chunk) == (
            30, 0.05, None, "innovation", ["q", "r", "weights", "omega"], "consensus", None, None)
    elif option == "calibrate":  # its settings (conf/learner/calibrate.yaml) as the learner holds them
        assert (obj.fit, obj.points, obj.decades, obj.zooms, obj.shifts, obj.warmup, obj.tolerance, obj.holdout,
                obj.max_batch) == (["q", "r"], 9, 4.0, 3, 4, 2, 1.92, 0.5, 20000)
    else:  # no settings of its own
        assert set(cfg.learner) == {"_target_"}


ASSOCIATOR_CLASSES = {"labels": "LabelsAssociator", "gnn": "GNNAssociator", "jpda": "JPDAAssociator"}


def _check_associator(option, cfg, world):
    """A matrix method's associator: its class, the default ``labels`` (today's behaviour), every key listed."""
    obj = build(cfg.associator, "associator")
    assert type(obj).__name__ == ASSOCIATOR_CLASSES[option] and obj.name == option
    assert _compose().associator._target_.endswith("LabelsAssociator")  # the root default
    keys = {"labels": set(), "gnn": {"gate_probability", "detection_probability", "clutter_density", "cost", "tracks"},
            "jpda": {"gate_probability", "detection_probability", "clutter_density", "max_joint_events",
                     "marginals", "info_update", "tracks"}}[option]
    assert set(cfg.associator) - {"_target_"} == keys == set(type(obj).config_reads)
    if option != "labels":
        assert (obj.gate_probability, obj.detection_probability, obj.clutter_density) == (0.99, None, None)
        assert getattr(obj, "cost", "likelihood") == "likelihood"
        # track management (targets that enter and leave): every key listed, managed only where births are declared
        from dslearn.association.multitrack import KEYS, TrackSettings

        assert set(cfg.associator.tracks) == set(KEYS)
        assert obj.tracks == TrackSettings(manage="auto", initiation="two_point", confirm_m=2, confirm_n=3,
                                           delete_after=3, max_speed=None, velocity_std=None,
                                           t2ta_gate_probability=0.99, adopt=True)


CHECKS = {"data": _check_data, "associator": _check_associator, "learner": _check_learner, "method": _check_method, "dataset": _check_dataset, "folds": _check_folds,
          "lstm": _check_lstm, "task": _check_task, "filter": _check_filter, "model": _check_model,
          "observation": _check_observation, "consensus": _check_consensus, "network": _check_network,
          "scenario": _check_scenario}
EXPECTED_OPTIONS = {"data": {"paper", "small"}, "associator": set(ASSOCIATOR_CLASSES), "learner": set(LEARNER_CLASSES), "dataset": set(DATASETS), "folds": {"ethucy"}, "lstm": {"default"},
                    "task": set(TASKS), "filter": {"default", "ukf", "ukf_mm", "adf", "pf", "dgpt", "fg_ekf", "rbpf_em",
                                                       "rbpf_em_lin", "fg_ekf_lin"},
                    "method": {f"{f}_{m}_{c}" for f in ("ekf", "ukf") for m in PRESET_MODELS for c in PRESET_FUSIONS}
                    | {"dgpt_gpoe", "dgpt_rbcm", "fg_ekf", "fg_ekf_lin", "rbpf_em", "rbpf_em_lin", "ekf_lin_hybrid_backprop", "adf_gp_hybrid",
                       "ukf_mm_gp_hybrid", "pf_gp_hybrid", "ekf_sfm_hybrid_backprop", "ekf_gp_hybrid_backprop",
                       "ekf_lstm_hybrid_backprop", "ekf_lin_hybrid_calibrated", "ekf_sfm_hybrid_calibrated",
                       "ekf_gp_hybrid_calibrated", "ekf_lstm_hybrid_calibrated", "ekf_lin_hybrid_gnn",
                       "ekf_lin_hybrid_jpda", "ekf_gp_hybrid_gnn", "ekf_gp_hybrid_jpda", "ekf_lstm_hybrid_gnn",
                       "ekf_lstm_hybrid_jpda", "ekf_cv_fg_individual", "ekf_sfm_fit_hybrid"},
                    "model": set(GP_MODELS) | {"lin", "sfm", "lstm", "social_lstm", "gp_cv", "sfm_fit", "cv_damped"},
                    "observation": {"linear", "gp", "sensor", "squared_range", "range", "bearing", "terrain"}, "consensus": set(FUSION_CLASSES) | AGGREGATIONS | {"statistics"},
                    "network": {"yu", "yu_blind"},
                    "scenario": {"s1", "s2", "s3", "yu_two_agents", "liu_s1", "liu_s2", "liu_s3", "eth_zara1", "eth_zara2",
                                 "eth_eth", "eth_hotel", "eth_univ",
                                 "corridor", "jiang", "braga", "yu_crowd_clutter", "yu_crowd_births", "liu_s1_clutter"}
                    | {f"eth_{s}_crowd" for s in ("eth", "hotel", "univ", "zara1", "zara2")}}


def test_every_option_has_its_expected_values():
    """A new option (or group) needs its expectations here before its test can pass."""
    assert {g: set(_options(g)) for g in GROUPS if g != "experiment"} == EXPECTED_OPTIONS


@pytest.mark.parametrize("group,option", ALL_OPTIONS, ids=[f"{g}={o}" for g, o in ALL_OPTIONS])
def test_every_option_composes_and_names_an_importable_part(group, option, yu_world):
    """Composes in its study's context, sets what it names (the composed values; the built part's class and
    parameters) and every ``_target_`` it names imports and takes its keys."""
    sel = f"+{group}={option}" if group in PLUS else f"{group}={option}"
    cfg = _compose(*CONTEXT.get(group, []), sel)
    CHECKS[group](option, cfg, yu_world)
    node = OmegaConf.select(cfg, group)
    if node is None:  # an option that writes into another package (e.g. '@package task'): checked above
        return
    spec = OmegaConf.to_container(node, resolve=False)
    targets = []

    def walk(x, where):
        if isinstance(x, dict):
            if "_target_" in x:
                targets.append((where, x))
            for k, v in x.items():
                walk(v, f"{where}.{k}")

    walk(spec, group)
    if group == "task" and "_target_" in spec:  # a study: its parameters are slots the composition root fills
        from dslearn.compose import SLOTS

        params = inspect.signature(get_object(spec["_target_"])).parameters
        assert set(params) <= set(SLOTS), sorted(set(params) - set(SLOTS))
        targets = [(w, t) for w, t in targets if w != "task"]
    for where, t in targets:
        fn = get_object(t["_target_"])  # importable
        params = inspect.signature(fn).parameters
        if not any(p.kind is p.VAR_KEYWORD for p in params.values()):
            keys = {k for k in t if not k.startswith("_") and k != "name" and not isinstance(t[k], dict)}
            assert keys <= set(params), (where, sorted(keys - set(params)))


@pytest.mark.parametrize("experiment", _options("experiment"))
def test_every_experiment_composes_and_validates(experiment):
    cfg = _compose(f"experiment={experiment}")
    validate_config(cfg)  # the whole validation layer, before any work


@pytest.fixture(scope="module")
def yu_world():
    cfg = _compose()
    scenario, network = build_scenario(cfg), build_network(cfg)
    return cfg, scenario, network


# ------------------------------------------------------------------------------- motion models
MODELS = _options("model")


@pytest.mark.parametrize("option", MODELS)
def test_motion_model_contract(option, yu_world):
    cfg, scenario, network = yu_world
    node = _compose(f"model={option}").model
    model = build_motion_model(node, scenario, network, torch.float64, torch.device("cpu"))
    assert isinstance(model, MotionModel)
    s, b, dx = network.num_nodes, 3, scenario.state_dim
    gen = torch.Generator().manual_seed(0)
    x = scenario.sample(b, network, gen).states[:, 0].to(torch.float64)  # (B, Dx) true start states
    if model.learnable:  # learn a few pairs so the GP is not at its prior
        for t in range(3):
            xi = x[t % b].expand(s, dx).contiguous()
            model.add_data(xi, xi + 0.05)
    xs = x.expand(s, b, dx).contiguous()
    ctx = scenario.ctx()
    mean, F, Q = model.linearize(xs, ctx)
    assert mean.shape == (s, b, dx) and F.shape == (s, b, dx, dx) and Q.shape == (s, b, dx, dx)
    assert torch.isfinite(mean).all() and torch.isfinite(F).all()
    torch.testing.assert_close(Q, Q.transpose(-1, -2), rtol=0, atol=1e-12)
    assert torch.linalg.eigvalsh(Q).min() > 0  # process noise positive definite
    # Jacobian against central finite differences of the mean
    eps = 1e-6
    fd = torch.stack([(model(xs + eps * e, ctx) - model(xs - eps * e, ctx)) / (2 * eps)
                      for e in torch.eye(dx, dtype=xs.dtype)], -1)
    torch.testing.assert_close(F, fd, rtol=1e-4, atol=1e-5)


# ------------------------------------------------------------------------- observation models
@pytest.mark.parametrize("option", _options("observation"))
def test_observation_model_contract(option, yu_world):
    cfg, scenario, network = yu_world
    if option == "terrain":  # the map is Braga's
        scenario = build_scenario(_compose("task=matrix", "method=rbpf_em", "scenario=braga"))
        network = scenario.network
    obs = build_observation(_compose(f"observation={option}").observation, network, torch.float64, torch.device("cpu"),
                            scenario)
    assert isinstance(obs, ObservationModel)
    s, a = network.num_nodes, scenario.num_agents
    y = torch.randn(s, a, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) + 4.0
    h, C, R = obs.linearize(y)
    assert h.shape == (s, a, obs.meas_dim) and C.shape == (s, a, obs.meas_dim, 4) and R.shape[-2:] == (obs.meas_dim, obs.meas_dim)
    torch.testing.assert_close(R, R.transpose(-1, -2), rtol=0, atol=1e-12)
    assert torch.linalg.eigvalsh(R).min() > 0


# --------------------------------------------------------------------------------------- fusion
@pytest.mark.parametrize("option", [o for o in _options("consensus") if o not in AGGREGATIONS | {"statistics"}])
def test_fusion_contract(option, yu_world):
    """Every fusion: row-stochastic weights (doubly stochastic for the symmetric rules; the paper's
    uniform 1/(|N_i|+1) rule is not); SPD symmetric fused information; when every node
    holds the same prior and the same novel information, it keeps the prior plus a positive
    multiple of it (consensus of equal beliefs changes nothing but the weighting)."""
    cfg, scenario, network = yu_world
    fusion = build_fusion(_compose(f"consensus={option}").consensus, network)
    w = fusion.weights
    torch.testing.assert_close(w.sum(1), torch.ones_like(w.sum(1)))
    from dslearn.fusion.weights import consensus_weights

    for rule in ("metropolis", "max_degree"):
        wd = consensus_weights(network.adjacency, rule)
        torch.testing.assert_close(wd.sum(0), torch.ones_like(wd.sum(0)))
        torch.testing.assert_close(wd, wd.T)
    torch.testing.assert_close(w, _uniform(network.adjacency), rtol=0, atol=1e-15)  # every option: weights=uniform
    s, dx = network.num_nodes, 4
    o = torch.eye(dx, dtype=torch.float64).expand(s, 1, dx, dx).clone()
    q = torch.ones(s, 1, dx, dtype=torch.float64)
    q2, o2 = fusion(q, o, 0.5 * q, 0.5 * o)
    torch.testing.assert_close(o2, o2.transpose(-1, -2), rtol=0, atol=1e-12)
    assert torch.linalg.eigvalsh(o2).min() > 0
    ratio = o2[..., 0, 0]
    torch.testing.assert_close(q2[..., 0], ratio)  # q / Omega keeps the common mean 1


# ---------------------------------------------------------------------------- filter: predict
@pytest.mark.parametrize("option", [o for o in _options("filter") if o not in ("dgpt", "fg_ekf", "fg_ekf_lin",
                                                                                "rbpf_em", "rbpf_em_lin")])  # no prediction step
def test_predict_step_contract(option, yu_world):
    """Every prediction step equals the Kalman prediction for the linear (constant-velocity) model. A step for GP
    motion models only (``adf``, ``ukf_mm``) refuses it, and is checked on the GP that is that linear model: the
    constant-velocity prior mean with no data, f(y) = F y + w, w ~ N(0, sigma_f^2 I). The particle step (``pf``,
    200000 particles) equals it within its Monte Carlo error: the mean within 4.5 standard errors of a sample mean,
    the covariance within 5 sqrt(2/N) sd_i sd_j (the standard error of a Gaussian sample covariance is at most
    sqrt(2/N) sd_i sd_j)."""
    from dslearn.compose import build_predict
    from dslearn.errors import ConfigError
    from dslearn.models import GPMotionModel
    from dslearn.models.constant_velocity import ConstantVelocity
    from dslearn.models.gp_backends import ConstantVelocityMean

    cfg, scenario, network = yu_world
    step = build_predict(_compose(f"filter={option}", *(["filter.predict.particles=200000"] if option == "pf" else [])))
    model = ConstantVelocity(scenario.num_agents, 0.1)
    ctx = scenario.ctx()
    dx = scenario.state_dim
    gen = torch.Generator().manual_seed(3)
    a = torch.randn(2, 3, dx, dx, dtype=torch.float64, generator=gen)
    P = a @ a.transpose(-1, -2) + torch.eye(dx, dtype=torch.float64)
    mean = torch.randn(2, 3, dx, dtype=torch.float64, generator=gen)
    misfit = getattr(step, "model_misfit", None)
    if misfit is not None and misfit(model) is not None:
        with pytest.raises(ConfigError, match=f"filter={option}"):
            step(mean, torch.linalg.inv(P), model, ctx)
        model = GPMotionModel(dx, 2, outputscale=0.1, mean=ConstantVelocityMean(ctx.dt))
    y, q, om = step(mean, torch.linalg.inv(P), model, ctx)
    F = model.jacobian(mean, ctx)
    Pp = F @ P @ F.transpose(-1, -2) + model.noise_cov(mean, ctx)
    if option == "pf":  # Monte Carlo: within its error only
        n, sd = step.particles, Pp.diagonal(dim1=-2, dim2=-1).sqrt()
        assert ((y - model(mean, ctx)).abs() <= 4.5 * sd / math.sqrt(n)).all()
        assert ((torch.linalg.inv(om) - Pp).abs() <= 5 * math.sqrt(2 / n) * sd.unsqueeze(-1) * sd.unsqueeze(-2)).all()
    else:
        torch.testing.assert_close(y, model(mean, ctx))
        torch.testing.assert_close(torch.linalg.inv(om), Pp, rtol=1e-8, atol=1e-8)
    torch.testing.assert_close(q, (om @ y.unsqueeze(-1)).squeeze(-1))


# ------------------------------------------------------------------------------- network parts
@pytest.mark.parametrize("option", _options("network"))
def test_network_contract(option):
    net = build(_compose(f"network={option}").network, "network")
    adj = net.adjacency
    assert torch.equal(adj, adj.T) and not adj.diagonal().any()
    assert net.num_nodes == len(net.names) and int(net.is_sensor.sum()) >= 1
