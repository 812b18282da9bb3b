"""The RBPF over noise modes (dslearn/filters/mkf.py, dslearn/methods/rbpf_modes.py): the filter against an
independent brute force over every mode sequence (plain NumPy Kalman filters), the EM statistics and the M-step
against hand computations, the matrix cells on Yu's and Liu's scenarios, and the declared fits."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from dslearn.errors import ConfigError
from dslearn.filters.mkf import LinearGaussianState, init_state, local_stats, mkf_step, moments
from dslearn.fusion.stats_consensus import StatisticsConsensus
from dslearn.compose import build
from dslearn.learning.learners import OnlineEM, OnlineEMSensor
from dslearn.methods.rbpf import RBPFMethod
from dslearn.methods.rbpf_modes import RBPFModesMethod
from dslearn.models.jmnls import NoiseParams, m_step, stats_dim
from dslearn.models.observation import LinearPositionObservation

F64 = torch.float64
DT, Q = 0.5, 0.3
SIGMA = np.array([0.5, 1.5])  # unequal modes
PI = np.array([[0.85, 0.15], [0.4, 0.6]])  # not symmetric
ALPHA0 = np.array([0.7, 0.3])  # unequal initial mode probabilities
ETA_EXP = 0.7


def _cv():
    f = np.array([[1, 0, DT, 0], [0, 1, 0, DT], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    g = np.array([[DT * DT / 2, 0], [0, DT * DT / 2], [DT, 0], [0, DT]])
    h = np.array([[1, 0, 0, 0], [0, 1, 0, 0.0]])
    return f, Q * g @ g.T, h


def _data():
    """Four position measurements of a target near (0, 0) moving right, the third an outlier (the wide mode)."""
    return np.array([[0.1, -0.2], [0.6, 0.1], [2.0, -1.0], [1.9, 0.6]])


M0 = np.array([0.0, 0.0, 1.0, 0.0])
P0 = np.diag([1.0, 1.0, 0.5, 0.5])


def _kf(seq, ys):
    """Plain Kalman filter along one mode sequence (predict before every step): the means, covariances, the
    predictive densities of each step under both modes and the per-mode updated moments of the residual."""
    f, qd, h = _cv()
    m, p = M0.copy(), P0.copy()
    out = []
    for t, y in enumerate(ys):
        m, p = f @ m, f @ p @ f.T + qd
        per = []
        for l in range(2):
            s = h @ p @ h.T + SIGMA[l] ** 2 * np.eye(2)
            v = y - h @ m
            lik = math.exp(-0.5 * v @ np.linalg.solve(s, v)) / (2 * math.pi * math.sqrt(np.linalg.det(s)))
            k = p @ h.T @ np.linalg.inv(s)
            ml, pl = m + k @ v, (np.eye(4) - k @ h) @ p
            res = y - h @ ml
            per.append((lik, ml, pl, res @ res + np.trace(h @ pl @ h.T)))
        out.append(per)
        if t < len(seq):
            _, m, p, _ = per[seq[t]]
    return out, m, p


def _exact(ys):
    """The exact posterior over the 2^K mode sequences: the mixture mean of the state and P(r_K = 1 | y)."""
    post, means = [], []
    for seq in itertools.product((0, 1), repeat=len(ys)):
        per, m, _ = _kf(seq, ys)
        prior = sum(ALPHA0[r0] * PI[r0, seq[0]] for r0 in (0, 1))
        prior *= np.prod([PI[seq[t - 1], seq[t]] for t in range(1, len(seq))])
        post.append(prior * np.prod([per[t][seq[t]][0] for t in range(len(seq))]))
        means.append(m)
    w = np.array(post) / sum(post)
    last = np.array([s[-1] for s in itertools.product((0, 1), repeat=len(ys))])
    return (w[:, None] * np.array(means)).sum(0), float(w[last == 1].sum())


def _setup(n, batch=()):
    f, qd, h = _cv()
    model = LinearGaussianState(torch.tensor(f), torch.tensor(qd), torch.tensor(h))
    theta = NoiseParams(torch.zeros(*batch, 2, dtype=F64), torch.tensor(SIGMA).expand(*batch, 2),
                        torch.tensor(PI).expand(*batch, 2, 2))
    st = init_state(torch.tensor(M0).expand(*batch, 4), torch.tensor(P0).expand(*batch, 4, 4), torch.tensor(ALPHA0),
                    n, stats_dim(2))
    return model, theta, st


def test_particles_follow_the_brute_force_kalman_filter_of_their_mode_sequence():
    """No resampling: every particle's Kalman mean and covariance, its weight and its path statistics T equal the
    plain Kalman filter along its drawn mode sequence (weights: prod_t sum_l P(r_t = l | r_{t-1}) N_l(y_t), with
    alpha_0 before the first step; T_t = (1 - eta_t) T_{t-1} + eta_t s_t with s_t by hand from the per-mode moments)."""
    ys = _data()
    n = 40
    model, theta, st = _setup(n)
    gen = torch.Generator().manual_seed(3)
    paths = []
    for t, y in enumerate(ys):
        st, _ = mkf_step(st, torch.tensor(y), torch.tensor(True), model, theta, gen, eta=(t + 1) ** -ETA_EXP,
                         ess_threshold=0.0, learn_mean=True)
        paths.append(st.alpha.argmax(-1))
    paths = torch.stack(paths, -1).tolist()
    assert len({tuple(p) for p in paths}) > 4  # several distinct sequences drawn
    logw = []
    for i, seq in enumerate(paths):
        per, m, p = _kf(seq, ys)
        np.testing.assert_allclose(st.mean[i].numpy(), m, rtol=0, atol=1e-10)
        np.testing.assert_allclose(st.cov[i].numpy(), p, rtol=0, atol=1e-10)
        lw, prev, tstat = 0.0, ALPHA0, np.zeros(stats_dim(2))
        for t in range(len(ys)):
            g = np.array([(prev @ PI)[l] * per[t][l][0] for l in (0, 1)])
            lw += math.log(g.sum())
            post = g / g.sum()
            s1 = np.array([[prev[k] * PI[k, l] * per[t][l][0] for l in (0, 1)] for k in (0, 1)]) / g.sum()
            res = [ys[t] - np.array([[1, 0, 0, 0], [0, 1, 0, 0]]) @ per[t][l][1] for l in (0, 1)]
            s = np.concatenate([s1.ravel(), 2 * post, post * np.array([r.sum() for r in res]),
                                post * np.array([per[t][l][3] for l in (0, 1)])])
            eta = (t + 1) ** -ETA_EXP
            tstat = (1 - eta) * tstat + eta * s
            prev = np.eye(2)[seq[t]]
        np.testing.assert_allclose(st.T[i].numpy(), tstat, rtol=1e-10, atol=1e-12)
        logw.append(lw)
    w = np.exp(np.array(logw) - np.logaddexp.reduce(logw))
    np.testing.assert_allclose(st.logw.exp().numpy(), w, rtol=1e-10, atol=0)


def test_many_particles_approach_the_exact_mixture_of_kalman_filters():
    """With resampling and 20000 particles per entry (4 independent entries pooled), the mixture mean of the
    state and P(r_K = wide | y_1:K) are within Monte Carlo error of the exact mixture over all 2^4 sequences."""
    ys = _data()
    exact_mean, exact_p1 = _exact(ys)
    assert 0.05 < exact_p1 < 0.95  # the last mode is uncertain: the test sees the mixture, not one sequence
    model, theta, st = _setup(20000, (4,))
    gen = torch.Generator().manual_seed(0)
    for t, y in enumerate(ys):
        st, _ = mkf_step(st, torch.tensor(y).expand(4, 2), torch.ones(4, dtype=torch.bool), model, theta, gen,
                         eta=1.0, ess_threshold=0.5)
    mean, _ = moments(st)
    p1 = (st.logw.exp() * st.alpha[..., 1]).sum(-1)
    np.testing.assert_allclose(mean.mean(0).numpy(), exact_mean, rtol=0, atol=0.02)
    assert abs(float(p1.mean()) - exact_p1) < 0.01
    # a wrong transition matrix is seen: the exact answer with pi transposed differs by more than the tolerance
    global PI
    saved, PI = PI, PI.T.copy() / PI.T.sum(1, keepdims=True)
    try:
        assert abs(_exact(ys)[1] - exact_p1) > 0.03
    finally:
        PI = saved


def test_invisible_steps_predict_only():
    """Where no measurement arrives the particles predict (F m, F P F^T + Q), the mode probabilities move by pi,
    and the weights and the statistics stay."""
    model, theta, st = _setup(5)
    st.T = torch.rand(5, stats_dim(2), dtype=F64)
    new, info = mkf_step(st, torch.zeros(2, dtype=F64), torch.tensor(False), model, theta, torch.Generator(), eta=0.5)
    f, qd, _ = _cv()
    np.testing.assert_allclose(new.mean[0].numpy(), f @ M0, atol=1e-14)
    np.testing.assert_allclose(new.cov[0].numpy(), f @ P0 @ f.T + qd, atol=1e-14)
    np.testing.assert_allclose(new.alpha[0].numpy(), ALPHA0 @ PI, atol=1e-15)
    assert torch.equal(new.T, st.T) and torch.equal(new.logw, st.logw) and float(info["loglik"]) == 0.0


def test_em_statistics_consensus_and_m_step_by_hand():
    """Two nodes, two particles each: the local statistics sum_i w_i T_i, the centralised combination (the average)
    and the M-step (sigma_l^2 = S3b_l / S2_l with zero-mean modes, pi_kl = S1_kl / sum_j S1_kj) by hand."""
    t = torch.zeros(2, 2, stats_dim(2), dtype=F64)
    # node 0: particle 0 (w 0.25) S1 = [[.5,.1],[.1,.3]], S2 = [1.2, .8], S3a = 0, S3b = [.3, 1.6]; particle 1 (w .75)
    t[0, 0] = torch.tensor([.5, .1, .1, .3, 1.2, .8, 0, 0, .3, 1.6], dtype=F64)
    t[0, 1] = torch.tensor([.7, .1, .0, .2, 1.6, .4, 0, 0, .2, 1.0], dtype=F64)
    t[1, 0] = torch.tensor([.6, .2, .1, .1, 1.6, .4, 0, 0, .4, .4], dtype=F64)
    t[1, 1] = torch.tensor([.6, .2, .1, .1, 1.6, .4, 0, 0, .4, .4], dtype=F64)
    w = torch.tensor([[.25, .75], [.5, .5]], dtype=F64)
    st = init_state(torch.zeros(2, 4, dtype=F64), torch.eye(4, dtype=F64).expand(2, 4, 4), torch.tensor([.5, .5]), 2,
                    stats_dim(2))
    st.T, st.logw = t, w.log()
    loc = local_stats(st)
    node0 = [.25 * .5 + .75 * .7, .1, .25 * .1, .25 * .3 + .75 * .2, .25 * 1.2 + .75 * 1.6, .25 * .8 + .75 * .4, 0, 0,
             .25 * .3 + .75 * .2, .25 * 1.6 + .75 * 1.0]
    torch.testing.assert_close(loc[0], torch.tensor(node0, dtype=F64), rtol=0, atol=1e-14)
    comb = StatisticsConsensus(torch.tensor([[False, True], [True, False]]), "centralised").matrix()
    glob = comb @ loc
    g = (torch.tensor(node0, dtype=F64) + torch.tensor([.6, .2, .1, .1, 1.6, .4, 0, 0, .4, .4], dtype=F64)) / 2
    torch.testing.assert_close(glob[1], g, rtol=0, atol=1e-14)
    prev = NoiseParams(torch.zeros(2, 2, dtype=F64), torch.ones(2, 2, dtype=F64), torch.full((2, 2, 2), .5, dtype=F64))
    th = m_step(glob, prev)
    s1 = g[:4].view(2, 2)
    torch.testing.assert_close(th.pi[0], s1 / s1.sum(1, keepdim=True), rtol=1e-14, atol=0)
    torch.testing.assert_close(th.sigma[0], (g[8:] / g[4:6]).sqrt(), rtol=1e-14, atol=0)
    assert torch.equal(th.mu, torch.zeros(2, 2, dtype=F64))
    # by the numbers: mode 1 of the average, S3b = (0.4 + 0.75 + 0.4) / 2, S2 = (0.2 + 0.3 + 0.4) / 2: 0.775 / 0.45
    assert abs(float(th.sigma[0, 1]) ** 2 - ((.25 * 1.6 + .75 * 1.0 + .4) / 2) / ((.25 * .8 + .75 * .4 + .4) / 2)) < 1e-14


# ------------------------------------------------------------------------------------------ the method
def _compose(*overrides):
    from dslearn import api

    return api.compose(*overrides)


def _cell(scenario_name, seed=0, n=2):
    from dslearn.compose import build_cell_parts
    from dslearn.sim.scenario import episode_streams

    cfg = _compose("task=matrix", "method=rbpf_em_lin", f"scenario={scenario_name}")
    scenario, network, method = build_cell_parts(cfg)
    assert isinstance(method, RBPFModesMethod)
    test = scenario.sample(n, network, episode_streams(seed, "test", 0, n))
    return scenario, network, method, test


@pytest.mark.parametrize("name", ["yu_two_agents", "liu_s1"])
def test_cells_on_position_scenarios_track_within_the_bounds(name):
    """On Yu's and Liu's scenarios: finite estimates; every estimate at a step where its node has seen the target
    at this and the three steps before is within 5 sensor stds (RMS) of the truth (a filter that tracks averages its
    measurements down, never above a few of their stds); a sensing node's RMSE is below the area's half-diagonal
    (the error of knowing nothing, placed inside the area); and the EM learns the sensors' noise: the wider mode
    occupies little and the narrow mode's sigma of a node that saw the target is within a factor 2 of the truth."""
    scenario, network, method, test = _cell(name)
    est = method.estimate(scenario, network, None, test.measurements, 0)
    assert torch.isfinite(est.mean).all() and torch.isfinite(est.cov).all()
    truth = scenario.positions(test.states)  # (B, K+1, A, 2)
    err = (est.mean - truth[None]).square().sum(-1)  # (S, B, K+1, A)
    vis = test.visible
    seen = vis.clone()
    for lag in range(1, 4):
        seen[:, :, lag:] &= vis[:, :, :-lag]
    seen[:, :, :3] = False
    assert int(seen.sum()) > 10
    sd = float(network.meas_std)
    assert float(err[seen].mean().sqrt()) < 5 * sd
    x0, x1, y0, y1 = (float(v) for v in scenario.area)
    half_diag = 0.5 * math.hypot(x1 - x0, y1 - y0)
    rmse = err[:, :, 1:].mean((-1, -2)).sqrt()[est.sensing]
    assert bool((rmse < half_diag).all())
    _, _, hist = method.track(test.measurements, network, scenario.spec.dt, scenario.area, 0)
    saw = vis.any(2).any(-1).T  # (B, S)
    sig = hist.sigma[-1][saw]  # (n, 2)
    assert bool(((sig[:, 0] > 0.5 * sd) & (sig[:, 0] < 2.0 * sd)).all()), sig


def test_declared_fits_and_refusals():
    """The RBPF over noise modes fits the position-sensor scenarios and, with the scenario's own sensor model
    (observation=sensor), Jiang's squared ranges; it says why not on Braga's platforms (each navigates itself: Braga's
    own engine), on a sensor it has no model of and on a state whose position it cannot read, and, with the linear
    position sensor, on squared ranges; its learner is the online EM with the modes in sensor stds, zero-mean, no
    known initial mode (the altimeter's online EM refused, and Braga's RBPF refuses this one)."""
    from dslearn.episodes import ScenarioSpec
    from dslearn.models.observation import GPObservation, LinearPositionObservation, SquaredRangeObservation
    from dslearn.sim.braga import TerrainScenario
    from dslearn.sim.jiang import SquaredRangeScenario

    jiang = SquaredRangeScenario()
    assert RBPFModesMethod.spec_misfit(jiang.spec) is None
    why = RBPFModesMethod.spec_misfit(TerrainScenario(steps=5).spec)
    assert "scenario braga every node navigates itself" in why and "method=rbpf_em" in why
    why = RBPFModesMethod.spec_misfit(ScenarioSpec("x", "sonar", 2, "pv2d", 1.0, 5))
    assert "needs measurement position or squared_range or range or bearing; scenario x has sonar" in why
    why = RBPFModesMethod.spec_misfit(ScenarioSpec("x", "position", 2, "platform", 1.0, 5))
    assert "needs state pv2d or param2d; scenario x has platform" in why
    fusion = StatisticsConsensus(torch.tensor([[False, True], [True, False]]), "centralised")
    sq = SquaredRangeObservation(jiang.sensors, jiang.sigma_y, jiang.num_samples)
    assert RBPFModesMethod(fusion, observation=sq).fits(jiang.spec) is None
    assert RBPFModesMethod(fusion, observation=sq).centre and not RBPFModesMethod(fusion).centre
    for obs in (None, LinearPositionObservation(0.2)):
        why = RBPFModesMethod(fusion, observation=obs).fits(jiang.spec)
        assert "cannot read scenario jiang's squared_range: observation=sensor" in why
    with pytest.raises(ConfigError, match="observation=GPObservation is not a sensor model .*observation=sensor"):
        RBPFModesMethod(fusion, observation=GPObservation(2))
    with pytest.raises(ConfigError, match="filter.ekf_iterations=0 must be an integer >= 1"):
        RBPFModesMethod(fusion, observation=sq, ekf_iterations=0)
    # the count is the iterated EKF's: read with a nonlinear sensor (None: 5), refused with the linear position sensor
    assert RBPFModesMethod(fusion, observation=sq).iterations == 5
    assert RBPFModesMethod(fusion, observation=sq, ekf_iterations=2).iterations == 2
    for obs in (None, LinearPositionObservation(0.2)):
        with pytest.raises(ConfigError, match="filter.ekf_iterations=3: the linear position sensor's Kalman update is "
                                              "exact and reads no linearisation count; drop the key"):
            RBPFModesMethod(fusion, observation=obs, ekf_iterations=3)
    m = RBPFModesMethod(fusion)
    assert isinstance(m.learner, OnlineEMSensor) and m.label == "rbpf_em_lin centralised"
    assert m.learner == build(_compose("learner=online_em_sensor").learner, "learner")  # the defaults are the option's
    with pytest.raises(ConfigError, match="learner=online_em: .*units of their noise std"):
        RBPFModesMethod(fusion, learner=OnlineEM(em={"init_mode": "uniform"}, modes={"mu_init": [0.0, 0.0]}))
    with pytest.raises(ConfigError, match="init_mode=uniform"):
        OnlineEMSensor(em={"init_mode": "true"})
    with pytest.raises(ConfigError, match="zero-mean"):
        OnlineEMSensor(modes={"mu_init": [0.0, 0.1]})
    with pytest.raises(ConfigError, match="learner=online_em_sensor: .*metres"):
        RBPFMethod(fusion, learner=OnlineEMSensor())
    with pytest.raises(ConfigError, match="consensus=statistics"):
        RBPFModesMethod(object())
    # the sigma_init of the learner are multiples of the sensors' std
    th = m.initial_modes(0.2, F64, torch.device("cpu"))
    torch.testing.assert_close(th.sigma, torch.tensor([0.2, 0.6], dtype=F64), rtol=1e-15, atol=0)


# ------------------------------------------------------------------------------------------ nonlinear sensors
def test_on_jiangs_squared_ranges_a_fusion_centre_tracks_the_source_and_learns_the_readings_noise():
    """Jiang's cell (observation=sensor: the squared range, a fusion centre's iterated EKF per particle): one report
    (the centre's), finite; the source within 1 m RMS of the truth over each episode (its squared ranges fix it to
    centimetres, the CV model's prediction to about a metre) and the start within 0.05 m (the first fix); every
    sensor's narrow mode learned between 0.8 and 1.5 times the std of one averaged reading, sigma_y / sqrt(L) (not
    sigma_y, the std of one sample: 7.7 times more; the EM's residuals under the filtered, not the smoothed, state
    read it high); the consensus
    over the complete graph gives every sensor the same modes."""
    scenario, network, method, test = _cell("jiang")
    assert method.centre and method.fits(scenario.spec) is None
    est = method.estimate(scenario, network, None, test.measurements, 0)
    assert est.nodes == ["fusion"] and est.mean.shape == (1, 2, scenario.num_timings, 1, 2)
    assert torch.isfinite(est.mean).all() and torch.isfinite(est.cov).all()
    truth = scenario.positions(test.states)
    err = (est.mean[0] - truth).square().sum(-1)  # (B, K, 1)
    assert float(err[:, 0].max().sqrt()) < 0.05
    assert bool((err.mean((1, 2)).sqrt() < 1.0).all()), err.mean((1, 2)).sqrt()
    _, _, hist = method.track(test.measurements, network, scenario.spec.dt, scenario.area, 0)
    reading = scenario.sigma_y / math.sqrt(scenario.num_samples)
    sig = hist.sigma[-1]  # (B, S, 2)
    assert bool(((sig[..., 0] > 0.8 * reading) & (sig[..., 0] < 1.5 * reading)).all()), sig[..., 0]
    torch.testing.assert_close(sig, sig[:, :1].expand_as(sig), rtol=1e-6, atol=0)


def test_on_position_sensors_the_observation_part_changes_nothing():
    """rbpf_em_lin on Yu's scenario with observation=sensor (the linear position sensor with the network's noise)
    gives the estimates of the method without an observation part (the network's meas_std) bit for bit."""
    scenario, network, method, test = _cell("yu_two_agents")
    assert isinstance(method.observation, LinearPositionObservation) and not method.centre
    plain = RBPFModesMethod(method.fusion, method.num_particles, method.process_noise, method.ess_threshold,
                            method.prior_pos_std, method.prior_vel_std, learner=method.learner)
    a = method.track(test.measurements, network, scenario.spec.dt, scenario.area, 0)
    b = plain.track(test.measurements, network, scenario.spec.dt, scenario.area, 0)
    for x, y in zip(a[:2], b[:2]):
        assert torch.equal(x, y)
    assert torch.equal(a[2].sigma, b[2].sigma) and torch.equal(a[2].pi, b[2].pi)


def test_a_matrix_run_on_jiang():
    """task=matrix method=rbpf_em_lin scenario=jiang with 2 training and 2 test episodes: finite RMSE of the
    fusion centre's estimates on every test episode, below a metre."""
    from dslearn.compose import build_study

    cfg = _compose("task=matrix", "method=rbpf_em_lin", "scenario=jiang", "task.train_episodes=2",
                   "task.test_episodes=2")
    df = build_study(cfg).run()
    rmse = df[df["metric"] == "rmse"]
    assert len(rmse) == 2 and set(rmse["node"]) == {"fusion"} and set(rmse["scenario"]) == {"jiang"}
    assert bool(((rmse["value"] > 0) & (rmse["value"] < 1.0)).all()), rmse["value"].tolist()
