"""The factor-graph identification as the distributed filter's learner (learner=fg_identification with
model=cv_damped, method=ekf_cv_fg_individual): the damped constant-velocity model (LIN at a = 1 and q = null, the
identification's model otherwise, its Jacobian against finite differences), the identified (a, q) in the model the
filter tracks with (the identification on the true tracks, recovering a simulated model), the refusals, and one
matrix cell end to end on Braga's scenario."""

from __future__ import annotations

import math
import types

import numpy as np
import pytest
import torch

from dslearn import api
from dslearn.compose import _Slots
from dslearn.episodes import Episodes, Measurements
from dslearn.errors import ConfigError
from dslearn.learning import learners
from dslearn.learning.factor_graph.motion import identify_motion, process_cov, transition, truth_tracks
from dslearn.models.constant_velocity import ConstantVelocity, DampedConstantVelocity
from dslearn.streams import stream_seed
from dslearn.types import StepContext

F64 = torch.float64


def _ctx(dt: float) -> StepContext:
    return StepContext(dt=dt)


# ------------------------------------------------------------------------------------------------ the model
def test_with_a_one_and_no_q_it_is_lin():
    """model=cv_damped with its defaults against model=lin, as built from their options: the same predictions,
    Jacobians and process noise, exactly."""
    cfg = api.compose("task=matrix", "method=ekf_lin_individual", "scenario=yu_two_agents")
    slots = _Slots(cfg)
    lin = slots["method"].model
    damped = _Slots(api.compose("task=matrix", "method=ekf_lin_individual", "scenario=yu_two_agents",
                                "model=cv_damped"))["method"].model
    assert type(lin) is ConstantVelocity and type(damped) is DampedConstantVelocity
    x = torch.randn(3, 5, lin.state_dim, dtype=F64, generator=torch.Generator().manual_seed(2))
    ctx = slots["scenario"].ctx()
    for a, b in zip(lin.linearize(x, ctx), damped.linearize(x, ctx)):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    torch.testing.assert_close(damped.matrix(ctx.dt), lin.matrix(ctx.dt), rtol=0, atol=0)


def test_it_is_the_identifications_model_per_agent():
    """a, q set: per agent block the transition and the noise of the identification (motion.transition,
    motion.process_cov), the agents independent; the Jacobian against central finite differences."""
    m = DampedConstantVelocity(3, a=0.8, q=0.5)
    dt = 0.4
    theta = torch.tensor([0.8, math.log(0.5)], dtype=F64)
    torch.testing.assert_close(m.matrix(dt), torch.block_diag(*[transition(theta, dt)] * 3), rtol=0, atol=0)
    torch.testing.assert_close(m.noise_matrix(dt), torch.block_diag(*[process_cov(theta, dt)] * 3), rtol=1e-15,
                               atol=0)
    x = torch.randn(4, 12, dtype=F64, generator=torch.Generator().manual_seed(3))
    mean, jac, q = m.linearize(x, _ctx(dt))
    assert mean.shape == (4, 12) and jac.shape == q.shape == (4, 12, 12)
    torch.testing.assert_close(q, q.transpose(-1, -2), rtol=0, atol=0)
    # by hand: p + v dt, a v
    xa = x.view(4, 3, 4)
    want = torch.cat([xa[..., :2] + dt * xa[..., 2:], 0.8 * xa[..., 2:]], -1).view(4, 12)
    torch.testing.assert_close(mean, want, rtol=0, atol=1e-15)
    eps = 1e-6
    fd = torch.stack([(m(x + eps * e, _ctx(dt)) - m(x - eps * e, _ctx(dt))) / (2 * eps)
                      for e in torch.eye(12, dtype=F64)], -1)
    torch.testing.assert_close(jac, fd, rtol=1e-7, atol=1e-8)
    # the velocity's noise: q dt^2 per coordinate; the position's q dt^4 / 4; their covariance q dt^3 / 2
    assert q[0, 2, 2].item() == pytest.approx(0.5 * dt**2, rel=1e-14)
    assert q[0, 0, 0].item() == pytest.approx(0.5 * dt**4 / 4, rel=1e-14)
    assert q[0, 0, 2].item() == pytest.approx(0.5 * dt**3 / 2, rel=1e-14) and q[0, 0, 1].item() == 0.0


@pytest.mark.parametrize("override,match", [
    ("model.a=nan", r"^model\.a=nan must be a finite number"),
    ("model.a=fast", r"^model\.a='fast' must be a finite number"),
    ("model.q=-1.0", r"^model\.q=-1\.0 must be > 0"),
    ("model.q=0", r"^model\.q=0 must be > 0"),
    ("model.noise_std=0", r"^model\.noise_std=0 must be > 0"),
])
def test_bad_model_values_are_refused_up_front(override, match):
    with pytest.raises(ConfigError, match=match):
        api.compose("task=matrix", "method=ekf_cv_fg_individual", "scenario=yu_two_agents", override)


# ------------------------------------------------------------------------------------------ the learner path
DT = 0.25  # yu_two_agents' step


def _simulate(a: float, q: float, episodes: int, steps: int, agents: int, seed: int) -> torch.Tensor:
    """True joint states ``(B, K+1, 4A)`` of the damped constant-velocity model (a, q), every agent alone."""
    gen = torch.Generator().manual_seed(seed)
    th = torch.tensor([a, math.log(q)], dtype=F64)
    f, qm = transition(th, DT), process_cov(th, DT)
    chol = torch.linalg.cholesky(qm + 1e-14 * torch.eye(4, dtype=F64))
    x = torch.cat([torch.randn(episodes, agents, 2, generator=gen, dtype=F64) * 3,
                   torch.randn(episodes, agents, 2, generator=gen, dtype=F64)], -1)
    xs = [x]
    for _ in range(steps):
        x = x @ f.T + torch.randn(episodes, agents, 4, generator=gen, dtype=F64) @ chol.T
        xs.append(x)
    return torch.stack(xs, 1).flatten(-2)


class Caught(Exception):
    pass


def _method(*extra):
    slots = _Slots(api.compose("task=matrix", "method=ekf_cv_fg_individual", "scenario=yu_two_agents", *extra))
    return slots["method"], slots["scenario"], slots["scenario_network"]


def _tracked_model(monkeypatch, method, scenario, network, states):
    """Run the method's estimate on training episodes of true ``states`` and return the motion model the filter
    tracks the test episodes with, as it is when the tracking starts."""
    from dslearn.methods import distributed as dist_mod

    seen = {}

    def learner(network, model, obs, fusion, ctx, **kw):
        def estimate(test):
            seen.update(model=model, a=model.a, q=model.q, dt=ctx.dt)
            raise Caught

        return types.SimpleNamespace(learnable=False, estimate=estimate)

    monkeypatch.setattr(dist_mod, "OnlineLearner", learner)
    s, b, t1, a = network.num_nodes, states.shape[0], states.shape[1], scenario.spec.num_agents
    meas = torch.zeros(s, b, t1, a, 2, dtype=F64)
    vis = torch.zeros(s, b, t1, a, dtype=torch.bool)
    with pytest.raises(Caught):
        method.estimate(scenario, network, Episodes(states, meas, vis), Measurements(meas[:, :1], vis[:, :1]), 0)
    return seen


def test_the_filter_tracks_with_the_model_identified_from_the_true_tracks(monkeypatch):
    """On true tracks of a known damped model (a = 0.9, q = 0.6): the model the filter tracks with holds the
    identification's (a, exp ln q) on those tracks (the same call, bit for bit), the truth within three of the factor
    graph's posterior standard deviations; the measurements (here all unseen) play no part. The true positions carry
    the declared noise (learners.TRUTH_STD, from the run's seed's stream): without it q is not identified."""
    a, q = 0.9, 0.6
    method, scenario, network = _method()
    assert scenario.spec.dt == DT
    states = _simulate(a, q, episodes=30, steps=25, agents=2, seed=7)
    seen = _tracked_model(monkeypatch, method, scenario, network, states)
    assert seen["model"] is method.model and seen["dt"] == DT
    # the identification by hand: the same tracks, start, settings
    gen = torch.Generator().manual_seed(stream_seed(0, "fg_identification"))  # the run's seed: 0
    z, n = truth_tracks(states, 2, learners.TRUTH_STD, gen)
    m0 = torch.cat([z[:, 0], torch.zeros_like(z[:, 0])], -1)
    p0 = torch.diag(torch.tensor([1e6, 1e6, 1e6, 1e6], dtype=F64)).expand(z.shape[0], 4, 4)
    fg = method.learner.fg
    ref = identify_motion(z, n, DT, learners.TRUTH_STD, m0, p0, [1.0, 0.0], iterations=10,
                          rounds=learners.MOTION_ROUNDS, init_var=100.0, prior_var=float("inf"), schedule=fg["schedule"],
                          damping=0.0, graph=fg["graph"], lambda_tol=1e-8, converge_tol=1e-3)
    assert (seen["a"], seen["q"]) == (float(ref.theta[0]), float(ref.theta[1].exp()))
    assert method.learned["a"] == seen["a"] and method.learned["q"] == seen["q"]
    assert method.learned["rows"] == 2 * 30 * 2 * 26 == ref.rows
    truth = torch.tensor([a, math.log(q)], dtype=F64)
    err, sd = (ref.theta - truth).abs(), ref.var.sqrt()
    assert (err < 3 * sd).all() and (sd < torch.tensor([0.02, 0.2], dtype=F64)).all(), (ref.theta, sd)
    # exact positions: the predictions depend on q only through q / r; ln q is not informed (why the noise is there)
    exact = identify_motion(*truth_tracks(states, 2), DT, 1e-6, m0, p0, [1.0, 0.0], iterations=10, rounds=10,
                            init_var=100.0, prior_var=float("inf"), schedule=fg["schedule"], damping=0.0,
                            graph=fg["graph"], lambda_tol=1e-8, converge_tol=1e-3)
    assert float(exact.var[1].sqrt()) > 100.0 and abs(float(exact.theta[0]) - a) < 0.05, (exact.theta, exact.var)
    # the model predicts with those values
    x = states[0, 3][None]
    want = torch.cat([x.view(1, 2, 4)[..., :2] + DT * x.view(1, 2, 4)[..., 2:],
                      seen["a"] * x.view(1, 2, 4)[..., 2:]], -1).view(1, 8)
    torch.testing.assert_close(method.model(x, scenario.ctx()), want, rtol=0, atol=1e-14)


def test_the_truth_is_read_per_agent_and_an_unknown_position_is_unseen():
    states = torch.arange(2 * 3 * 8, dtype=F64).view(2, 3, 8)
    states[1, 2, 4] = float("nan")
    z, n = truth_tracks(states, 2)
    assert z.shape == (4, 3, 2) and n.shape == (4, 3)
    assert z[0, 1].tolist() == states[0, 1, :2].tolist() and z[1, 1].tolist() == states[0, 1, 4:6].tolist()
    assert z[2, 0].tolist() == states[1, 0, :2].tolist()
    assert n[3, 2].item() == 0.0 and z[3, 2].tolist() == [0.0, 0.0] and int(n.sum()) == 11


# ---------------------------------------------------------------------------------------------- refusals
def test_another_motion_model_is_refused_naming_the_learner_and_the_allowed_ones():
    with pytest.raises(ConfigError, match=r"learner=fg_identification: the factor-graph identification sets the damped "
                                          r"constant-velocity model's \(a, q\) \(model=cv_damped\), not "
                                          r"ConstantVelocity's; allowed: learner=none(\||$)"):
        api.compose("task=matrix", "method=ekf_cv_fg_individual", "scenario=yu_two_agents", "model=lin")
    with pytest.raises(ConfigError, match=r"learner=fg_identification: .*not GPMotionModel's; allowed: learner=online"):
        api.compose("task=matrix", "method=ekf_gp_individual", "scenario=yu_two_agents", "learner=fg_identification",
                    "learner.fg.taylor_point=guess", "learner.fg.measurement_var=known")
    # the damped model takes none (LIN's values) or the identification, not a learner it has nothing for
    with pytest.raises(ConfigError, match=r"learner=offline: .*allowed: learner=none\|.*fg_identification"):
        api.compose("task=matrix", "method=ekf_lin_individual", "scenario=yu_two_agents", "model=cv_damped",
                    "learner=offline")


@pytest.mark.parametrize("override,match", [
    ("learner.fg.taylor_point=prediction", r"learner\.fg\.taylor_point='prediction' does not apply to the distributed "
                                           r"filter \(filter=default\|ukf\): .*allowed: guess"),
    ("learner.fg.init_guess_mode=prediction", r"learner\.fg\.init_guess_mode='prediction' .* allowed: fixed"),
    ("learner.fg.measurement_var=sample", r"learner\.fg\.measurement_var='sample' .* allowed: known"),
    ("learner.fg.relinearize=true", r"learner\.fg\.relinearize=True .* allowed: false"),
    ("learner.fg.crlb_form=paper_eq33", r"learner\.fg\.crlb_form='paper_eq33' .* takes no CRLB; allowed: trace_inverse"),
    ("+learner.fg.rounds=3", r"learner\.fg: unknown key\(s\) \['rounds'\]"),
    ("learner.iterations=0", r"learner\.iterations=0 must be an integer >= 1"),
])
def test_a_setting_the_identification_cannot_use_is_refused_up_front(override, match):
    with pytest.raises(ConfigError, match=match):
        api.compose("task=matrix", "method=ekf_cv_fg_individual", "scenario=braga", override)


def test_the_damped_model_allows_the_identification_and_names_it():
    from dslearn.methods.distributed import allowed_learners

    method, _, _ = _method()
    assert "fg_identification" in allowed_learners(method.model, method.observation)
    assert "fg_identification" not in allowed_learners(ConstantVelocity(2), method.observation)
    assert method.label == "ekf cv_damped individual learner=fg_identification"


# -------------------------------------------------------------------------------------------- end to end
def test_a_matrix_cell_end_to_end_on_braga():
    """dslearn-run task=matrix method=ekf_cv_fg_individual scenario=braga (2 + 2 short flights): every aircraft's
    own estimate, a finite RMSE well inside the map's scale."""
    df = api.run("task=matrix", "method=ekf_cv_fg_individual", "scenario=braga", "task.train_episodes=2",
                 "task.test_episodes=2", "scenario.steps=200")
    rmse = df[df["metric"] == "rmse"]
    assert set(rmse["node"]) == {"onboard"} and len(rmse) == 2
    assert set(df["method"]) == {"ekf cv_damped individual learner=fg_identification"}
    assert np.isfinite(rmse["value"]).all() and (rmse["value"] < 200.0).all()


def test_with_learner_none_the_cell_is_lins():
    """model=cv_damped learner=none and model=lin: the same estimates' metrics on the same cell."""
    common = ("task=matrix", "scenario=yu_two_agents", "task.train_episodes=1", "task.test_episodes=2")
    lin = api.run(*common, "method=ekf_lin_individual")
    damped = api.run(*common, "method=ekf_lin_individual", "model=cv_damped")
    cols = ["node", "metric", "episode", "value"]
    key = [c for c in cols if c in lin.columns and c != "value"]
    a = lin[lin["metric"] != "runtime_s"].sort_values(key)[cols].reset_index(drop=True)
    b = damped[damped["metric"] != "runtime_s"].sort_values(key)[cols].reset_index(drop=True)
    assert len(a) > 0
    pd_equal = a.equals(b)
    assert pd_equal, (a, b)
