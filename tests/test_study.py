"""End-to-end runs of the Yu study, config errors, runner and report."""

import itertools
import json
import math

import numpy as np
import pandas as pd
import torch
import pytest

from dslearn.errors import ConfigError
from dslearn.report import summarize
from dslearn.app.record import execute
from dslearn import api
from dslearn.studies.yu import YuStudy

TINY = ("data.train_episodes=2", "data.test_episodes=2")


SIGMA_NU = 0.2  # network.meas_std: the measurement noise std per coordinate [m]
# NEES / Dx of a consistent filter: the per-step NEES is chi-square with Dx = 8 degrees of freedom (2 agents x
# 4); an episode's value averages 12 time-correlated steps, so it spreads at most as one step does: 99 % band
# of chi2(8) / 8 (0.5 % and 99.5 % points 1.344 and 21.955)
NEES_BAND = (1.344 / 8, 21.955 / 8)
_RUNS: dict = {}


def _tiny_run(make_cfg, model, consensus):
    """The TINY run of a (model, fusion) pair, once per session (the individual run is also the
    reference of the consensus runs)."""
    if (model, consensus) not in _RUNS:
        cfg = make_cfg(f"model={model}", f"consensus={consensus}", *TINY)
        _RUNS[model, consensus] = api.build_study(cfg).run()
    return _RUNS[model, consensus]


@pytest.mark.parametrize(
    "model,consensus",
    list(itertools.product(["lin", "sfm", "gp", "gp_increment"], ["individual", "ce", "cm", "ci", "hybrid", "centralized"])),
)
def test_every_model_and_fusion_runs(make_cfg, model, consensus):
    """Each pair runs and its numbers hold what the fusion and the model promise (2 training, 2 test
    episodes of the default scenario: 4 sensors with sigma_nu = 0.2 m, 6 communication-only nodes)."""
    df = _tiny_run(make_cfg, model, consensus)
    assert set(df["metric"]) == {"track_err", "track_rmse", "nees", "pred_err"}
    assert np.isfinite(df["value"]).all()
    assert len(df) == 4 * 10 * 2  # metrics x nodes x test episodes
    assert (df["model"] == model).all() and (df["consensus"] == consensus).all()
    per = df.pivot_table(index=["node_kind", "node", "episode"], columns="metric", values="value")
    assert (per["track_rmse"] >= per["track_err"]).all()  # RMS >= mean of the same position errors
    if consensus == "centralized":  # every node holds the centralised filter (and learns the same data)
        spread = per.groupby("episode").agg(lambda v: v.max() - v.min())
        assert (spread.to_numpy() <= 1e-12 * per.abs().max().max()).all(), spread
    if consensus != "individual":  # what consensus brings to the nodes that never measure
        ind = _tiny_run(make_cfg, model, "individual")
        comm, comm_ind = (d[(d["node_kind"] == "comm") & (d["metric"] == "track_err")]["value"].mean() for d in (df, ind))
        assert comm < comm_ind, (comm, comm_ind)
    if consensus in ("cm", "ci", "hybrid", "centralized") and model != "gp":
        # every node fuses every sensor's information with a model that predicts the walk (the zero-mean GP
        # after 2 episodes falls back to the origin, metres off: pred_err): each node beats the error of
        # one raw measurement, E|nu| = sigma_nu sqrt(pi / 2) for nu ~ N(0, sigma_nu^2 I_2)
        bound = SIGMA_NU * math.sqrt(math.pi / 2)
        assert (per["track_err"] < bound).all(), per["track_err"].max()
    if model == "lin" and consensus != "ce":  # the linear model is consistent; CE keeps local information
        # while averaging estimates (over-confident by design). Consensus with row-stochastic weights counts
        # at most the information of the centralised filter: below the band's top; centralised: inside it
        assert (per["nees"] < NEES_BAND[1]).all(), per["nees"].max()
        if consensus == "centralized":
            assert (per["nees"] > NEES_BAND[0]).all(), per["nees"].min()


def test_learned_observation_model_runs(make_cfg):
    """observation=gp before learning is its prior, h(y) = position (identity mean), C = [I 0] and
    R = (sigma_f^2 + sigma_eps^2) I: the run at 0 training episodes equals the linear observation model
    with noise_std = sqrt(1 + 0.2^2), metric by metric. Learning then feeds the sensors' GPs only."""
    cfg = make_cfg("model=gp_increment", "observation=gp", *TINY, "data.eval_at=[0,2]")
    study = api.build_study(cfg)
    df = study.run()
    assert np.isfinite(df["value"]).all()
    lin = api.build_study(make_cfg("model=gp_increment", "observation=linear",
                                       f"observation.noise_std={math.sqrt(1.0 + 0.2**2)}",
                                       "data.train_episodes=0", "data.test_episodes=2")).run()
    key = ["metric", "node", "episode"]
    prior = df[df["train_seen"] == 0].sort_values(key)["value"].to_numpy()
    np.testing.assert_allclose(prior, lin.sort_values(key)["value"].to_numpy(), rtol=1e-9, atol=0)
    learned = df[df["train_seen"] == 2].sort_values(key)["value"].to_numpy()
    assert np.abs(learned - prior).max() > 1e-3  # the learned models changed the result
    gp = study.observation.gp
    net = study.network
    seen = gp.mask[:, : gp.n].sum(1)  # valid (estimate, measurement) pairs per node
    assert (seen[net.is_sensor] > 0).all() and (seen[~net.is_sensor] == 0).all()


def test_consensus_beats_individual_and_sfm_predicts_best(make_cfg):
    res = {}
    for model, fusion in itertools.product(["lin", "sfm"], ["individual", "hybrid"]):
        cfg = make_cfg(f"model={model}", f"consensus={fusion}", "data.train_episodes=0", "data.test_episodes=10")
        df = api.build_study(cfg).run()
        sens = df[(df["node_kind"] == "sensor")]
        res[model, fusion] = sens.groupby("metric")["value"].mean()
    for model in ("lin", "sfm"):
        assert res[model, "hybrid"]["track_err"] < res[model, "individual"]["track_err"]
    assert res["sfm", "hybrid"]["pred_err"] < 0.01 < res["lin", "hybrid"]["pred_err"]


def test_runs_are_reproducible(make_cfg):
    cfg = make_cfg("model=gp_increment", *TINY)
    a, b = api.build_study(cfg).run(), api.build_study(cfg).run()
    pd.testing.assert_frame_equal(a, b)


@pytest.mark.parametrize(
    "override,field",
    [
        ("+model.kind=mlp", "model.kind"),
        ("consensus.name=gossip", "consensus.name"),
        ("model.noise_std=-0.1", "model.noise_std"),
        ("network.sensing_range=0", "network.sensing_range"),
        ("network.meas_std=-1", "network.meas_std"),
        ("consensus.iterations=-1", "consensus.iterations"),
        ("consensus.omega=half", "consensus.omega"),
        ("network.comm_radius=0.5", "disconnected"),
        ("data.eval_at=[5]", "data.eval_at"),
        ("dtype=float16", "dtype"),
        ("scenario.dt=0.35", "scenario.horizon"),
    ],
)
def test_bad_config_is_a_clear_error(make_cfg, override, field):
    cfg = make_cfg(override, *TINY, "network.positions=null")
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        api.build_study(cfg)


def test_unknown_model_group_is_rejected_by_hydra(make_cfg):
    from hydra.errors import MissingConfigException

    with pytest.raises(MissingConfigException):
        make_cfg("model=mlp")


def test_too_few_training_episodes(make_cfg):
    cfg = make_cfg("data.train_episodes=3", "data.min_train_episodes=10", "data.test_episodes=1")
    with pytest.raises(ConfigError, match="too few"):
        api.build_study(cfg)


def test_runner_writes_results_and_report(make_cfg, tmp_path):
    for fusion in ("individual", "hybrid"):
        cfg = make_cfg("model=lin", f"consensus={fusion}", *TINY, "study=unit")
        execute(cfg, tmp_path / fusion)
    for fusion in ("individual", "hybrid"):
        d = tmp_path / fusion
        assert (d / "results.csv").exists() and (d / "config.yaml").exists()
        meta = json.loads((d / "meta.json").read_text())
        assert meta["seed"] == 0 and "torch" in meta["versions"]
    from dslearn.report import report

    text = report(tmp_path)
    summary = pd.read_csv(tmp_path / "summary.csv")
    for col in ("study", "consensus", "node", "model", "metric", "mean", "std", "n"):
        assert col in summary.columns
    avg = summary[(summary["node"] == "avg") & (summary["metric"] == "track_err")]
    assert len(avg) == 2 and (avg["n"] == 2).all()
    assert "Table I" in text and (tmp_path / "yu_table1.md").exists()


def test_interrupted_run_leaves_no_results(make_cfg, tmp_path, monkeypatch):
    cfg = make_cfg("model=lin", *TINY)

    def boom(self, progress=False, diagnostics=None):
        raise KeyboardInterrupt

    monkeypatch.setattr(YuStudy, "run", boom)
    with pytest.raises(KeyboardInterrupt):
        execute(cfg, tmp_path)
    assert not (tmp_path / "results.csv").exists()


def test_summary_average_row():
    df = pd.DataFrame(
        {
            "study": "s", "model": "m", "consensus": "c", "metric": "track_err",
            "node": ["sensor1", "sensor2", "comm1"] * 2, "node_kind": ["sensor", "sensor", "comm"] * 2,
            "episode": [0, 0, 0, 1, 1, 1], "value": [1.0, 3.0, 100.0, 2.0, 4.0, 100.0],
        }
    )
    s = summarize(df).set_index("node")
    assert s.loc["avg", "mean"] == pytest.approx(2.5)  # mean of per-episode sensor means 2 and 3
    assert s.loc["avg", "n"] == 2


def test_learning_gate_skips_uninformed_pairs(make_cfg):
    """With the gate, a node whose estimate is the diffuse prior appends nothing (invalid points)."""
    from dslearn.filters.distributed import initial_belief, track

    cfg = make_cfg("model=gp", "consensus=individual", "data.train_episodes=1", "data.test_episodes=1")
    study = api.build_study(cfg)
    scenario, network, model, obs, fusion = study.scenario, study.network, study.model, study.observation, study.fusion
    import torch

    ep = scenario.sample(1, network, torch.Generator().manual_seed(0))
    init = initial_belief(ep.measurements, network, 0.25, fusion, scenario.area)
    track(ep.measurements, network, model, obs, fusion, scenario.ctx(), init, learn=True, learn_gate_std=0.5)
    mask = model.gp.mask[:, : model.gp.n]
    assert model.gp.n == scenario.steps
    # communication-only nodes never measure, so under individual fusion they never learn
    assert not mask[~network.is_sensor].any()
    # without the gate every node appends every step
    model2 = api.build_study(cfg).model  # a fresh model, built like the first
    track(ep.measurements, network, model2, obs, fusion, scenario.ctx(), init, learn=True, learn_gate_std=None)
    assert model2.gp.mask[:, : model2.gp.n].all()


@pytest.mark.gpu
def test_cuda_run_matches_cpu(make_cfg):
    import torch

    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    cpu = api.build_study(make_cfg("model=gp_increment", *TINY)).run()
    gpu = api.build_study(make_cfg("model=gp_increment", "device=cuda", *TINY)).run()
    assert (cpu["value"] - gpu["value"]).abs().max() < 1e-8


def test_cuda_requested_without_device_is_a_config_error(make_cfg):
    import torch

    if torch.cuda.is_available():
        pytest.skip("a CUDA device is present")
    with pytest.raises(ConfigError, match="device=cuda"):
        api.build_study(make_cfg("device=cuda", *TINY))


def test_eval_at_checkpoints_equal_separate_runs(make_cfg):
    """Evaluating after 0, 2 and 3 training episodes in one run gives exactly what separate runs
    with 0, 2 and 3 training episodes give (the test set does not depend on the training size)."""
    base = ("model=gp_increment", "consensus=hybrid", "data.test_episodes=3")
    one = api.build_study(make_cfg(*base, "data.train_episodes=3", "data.eval_at=[0,2,3]")).run()
    assert sorted(one["train_seen"].unique()) == [0, 2, 3]
    for k in (0, 2, 3):
        sep = api.build_study(make_cfg(*base, f"data.train_episodes={k}")).run()
        got = one[one["train_seen"] == k].sort_values(["metric", "node", "episode"])["value"].to_numpy()
        exp = sep.sort_values(["metric", "node", "episode"])["value"].to_numpy()
        assert got.shape == exp.shape and abs(got - exp).max() < 1e-12, k


def test_an_episode_is_the_same_whatever_the_data_set_size(make_cfg):
    """One random stream per episode: test episode 2 is the same with 3 or 5 test episodes, and a
    test episode's results do not depend on the episodes tracked beside it."""
    a = api.build_study(make_cfg("model=lin", "consensus=hybrid", "data.train_episodes=0", "data.test_episodes=3"))
    b = api.build_study(make_cfg("model=lin", "consensus=hybrid", "data.train_episodes=0", "data.test_episodes=5"))
    ta, _ = a.sample()
    tb, _ = b.sample()
    assert torch.equal(ta.states, tb.states[:3]) and torch.equal(ta.meas, tb.meas[:, :3])
    ra, rb = a.run(), b.run()
    key = ["metric", "node", "episode"]
    ra = ra.sort_values(key)["value"].to_numpy()
    rb = rb[rb["episode"] < 3].sort_values(key)["value"].to_numpy()
    assert abs(ra - rb).max() < 1e-12
