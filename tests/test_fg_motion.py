"""The factor-graph identification of a motion model on position sensors (filter=fg_ekf_lin, method=fg_ekf_lin):
the Kalman filter against the batch Gaussian posterior computed with numpy, its slopes against autograd, the factor
graph's messages against the weighted least-squares posterior, the identification's fixed point and its recovery of
a simulated model, the method's verdicts and refusals, and one matrix cell end to end."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dslearn import api
from dslearn.episodes import Measurements, ScenarioSpec
from dslearn.errors import ConfigError
from dslearn.learning.factor_graph.identification import identify
from dslearn.learning.factor_graph.messages import LinearMeasurement, linearize
from dslearn.learning.factor_graph.motion import (fuse, identify_motion, kalman, process_cov, track_messages,
                                                  transition)
from dslearn.learning.learners import FactorGraphIdentification, OnlineLearning
from dslearn.methods.factor_graph import FactorGraphMotionMethod

F64 = torch.float64
DT, SIGMA = 0.4, 0.3
LIN_FG = {"init_guess": [1.0, 0.0], "taylor_point": "guess", "measurement_var": "known"}


def _np_model(a: float, q: float, dt: float):
    f = np.array([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, a, 0], [0, 0, 0, a]], dtype=float)
    g = np.array([[dt * dt / 2, 0], [0, dt * dt / 2], [dt, 0], [0, dt]], dtype=float)
    return f, q * g @ g.T


def test_the_model_is_the_damped_constant_velocity_model():
    th = torch.tensor([0.8, math.log(0.5)], dtype=F64)
    f, q = _np_model(0.8, 0.5, DT)
    np.testing.assert_allclose(transition(th, DT).numpy(), f, rtol=0, atol=1e-15)
    np.testing.assert_allclose(process_cov(th, DT).numpy(), q, rtol=1e-14, atol=0)


def test_fuse_takes_the_mean_of_the_nodes_that_see_a_target():
    meas = torch.zeros(3, 1, 2, 2, 2, dtype=F64)  # (S, B, T, A, 2)
    vis = torch.zeros(3, 1, 2, 2, dtype=torch.bool)
    meas[0, 0, 0, 1], meas[2, 0, 0, 1] = torch.tensor([1.0, 2.0]), torch.tensor([3.0, 6.0])
    vis[0, 0, 0, 1] = vis[2, 0, 0, 1] = True
    meas[1, 0, 1, 0], vis[1, 0, 1, 0] = torch.tensor([5.0, -1.0]), True
    meas[0, 0, 1, 0] = 99.0  # not visible: never read
    z, n = fuse(meas, vis)  # tracks: (episode 0, target 0), (episode 0, target 1)
    assert n.tolist() == [[0.0, 1.0], [2.0, 0.0]]
    assert z[1, 0].tolist() == [2.0, 4.0] and z[0, 1].tolist() == [5.0, -1.0]


def _batch_posterior(f, q, z, n, m0, p0, sigma):
    """The posterior of the last state of one track by numpy: the joint Gaussian of x_0..x_{T-1} (prior,
    transitions) conditioned on every measurement of every node at once (n[t] nodes at step t, each its own row)."""
    t_len, d = len(n), 4
    # joint prior: x_t = f^t x_0 + sum_{j<t} f^{t-1-j} w_j
    mean = np.concatenate([np.linalg.matrix_power(f, t) @ m0 for t in range(t_len)])
    cov = np.zeros((t_len * d, t_len * d))
    for s in range(t_len):
        for t in range(t_len):
            c = np.linalg.matrix_power(f, s) @ p0 @ np.linalg.matrix_power(f, t).T
            for j in range(min(s, t)):
                c = c + np.linalg.matrix_power(f, s - 1 - j) @ q @ np.linalg.matrix_power(f, t - 1 - j).T
            cov[s * d:(s + 1) * d, t * d:(t + 1) * d] = c
    rows, ys = [], []
    for t in range(t_len):
        for node in range(int(n[t])):
            h = np.zeros((2, t_len * d))
            h[0, t * d], h[1, t * d + 1] = 1.0, 1.0
            rows.append(h)
            ys.append(z[t][node])
    h, y = np.concatenate(rows), np.concatenate(ys)
    s = h @ cov @ h.T + sigma ** 2 * np.eye(len(y))
    gain = cov @ h.T @ np.linalg.inv(s)
    post_mean = mean + gain @ (y - h @ mean)
    post_cov = cov - gain @ h @ cov
    return post_mean[-d:], post_cov[-d:, -d:]


def test_the_kalman_filter_is_the_batch_gaussian_posterior_with_masked_steps_and_several_nodes():
    """Two nodes at some steps, one at others, none at step 2: the filter's last mean and covariance equal the
    batch posterior of the stacked states given every node's own measurement (the fused mean is exact)."""
    rng = np.random.default_rng(0)
    a, q = 0.85, 0.7
    f, qm = _np_model(a, q, DT)
    n = [2, 1, 0, 2, 1]
    per_node = [rng.normal(size=(k, 2)) + t for t, k in enumerate(n)]
    m0, p0 = np.array([0.5, -0.2, 0.1, 0.3]), np.diag([4.0, 3.0, 2.0, 1.0])
    want_m, want_p = _batch_posterior(f, qm, per_node, n, m0, p0, SIGMA)
    z = torch.tensor(np.array([x.mean(0) if len(x) else np.zeros(2) for x in per_node]), dtype=F64)[None]
    kp = kalman(torch.tensor([a, math.log(q)], dtype=F64), z, torch.tensor([n], dtype=F64), DT, SIGMA,
                torch.tensor(m0, dtype=F64)[None], torch.tensor(p0, dtype=F64)[None])
    np.testing.assert_allclose(kp.mean[0, -1].numpy(), want_m, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(kp.cov[0, -1].numpy(), want_p, rtol=1e-10, atol=1e-12)
    assert torch.equal(kp.cov, kp.cov.transpose(-1, -2))


def test_the_filters_slopes_are_the_derivatives_of_its_predictions():
    gen = torch.Generator().manual_seed(3)
    z = torch.randn(5, 7, 2, generator=gen, dtype=F64)
    n = (torch.rand(5, 7, generator=gen) > 0.3).to(F64) * 2
    m0 = torch.randn(5, 4, generator=gen, dtype=F64)
    p0 = torch.eye(4, dtype=F64).expand(5, 4, 4) * 2.0
    th = torch.tensor([0.9, -0.4], dtype=F64)
    kp = kalman(th, z, n, DT, SIGMA, m0, p0, slopes=True)
    auto = torch.func.jacfwd(lambda t: kalman(t, z, n, DT, SIGMA, m0, p0).pred)(th)
    torch.testing.assert_close(kp.slopes, auto, rtol=1e-10, atol=1e-12)
    assert kp.slopes.abs().max() > 0.1  # not trivially zero


def _rows(seed=5, num=40, m=2):
    gen = torch.Generator().manual_seed(seed)
    lam = torch.randn(num, m, generator=gen, dtype=F64)
    y = torch.randn(num, generator=gen, dtype=F64)
    s = torch.rand(num, generator=gen, dtype=F64) + 0.2
    track = torch.randint(0, 6, (num,), generator=gen)
    return lam, y, s, track


@pytest.mark.parametrize("graph,iterations,tol", [("joint", 1, 1e-12), ("scalar", 200, 1e-9)])
@pytest.mark.parametrize("prior_var", [float("inf"), 0.5])
def test_the_factor_graph_mean_is_the_batch_gaussian_posterior(graph, iterations, tol, prior_var):
    """The tracks' messages (:func:`track_messages`) through the factor graph's messages: the marginal mean is the
    weighted least-squares posterior of the rows by numpy (with the prior node N(beta, prior_var) where given)."""
    lam, y, s, track = _rows()
    slopes, values = track_messages(lam, y, s, track, 6)
    info = (slopes.T @ slopes).numpy()
    np.testing.assert_allclose(info, (lam.T @ (lam / s[:, None])).numpy(), rtol=1e-12)  # the tracks' information
    beta = torch.tensor([0.2, -0.1], dtype=F64)
    out = identify(LinearMeasurement(slopes), values, torch.ones_like(values), beta, beta, iterations,
                   prior_var=prior_var, graph=graph)
    L, Y, S = lam.numpy(), y.numpy(), s.numpy()
    a = L.T @ (L / S[:, None])
    b = L.T @ (Y / S)
    if math.isfinite(prior_var):
        a, b = a + np.eye(2) / prior_var, b + beta.numpy() / prior_var
    np.testing.assert_allclose(out.mean[-1].numpy(), np.linalg.solve(a, b), rtol=tol, atol=tol)


def test_a_linear_measurement_gives_its_own_taylor_coefficients():
    lam, _, _, _ = _rows()
    off = torch.linspace(-1, 1, lam.shape[0], dtype=F64)
    h = LinearMeasurement(lam, off)
    beta = torch.tensor([[0.3, 2.0]], dtype=F64)
    got, gamma = linearize(h, beta)
    assert torch.equal(got[0], lam) and torch.equal(gamma[0], off)
    auto, auto_gamma = linearize(lambda x: h(x), beta)  # autograd agrees
    torch.testing.assert_close(auto, got, rtol=0, atol=1e-14)
    torch.testing.assert_close(auto_gamma, gamma, rtol=0, atol=1e-13)


def _simulate(a, q, tracks, steps, seed):
    gen = torch.Generator().manual_seed(seed)
    th = torch.tensor([a, math.log(q)], dtype=F64)
    f, qm = transition(th, DT), process_cov(th, DT)
    chol = torch.linalg.cholesky(qm + 1e-14 * torch.eye(4, dtype=F64))
    x = torch.cat([torch.randn(tracks, 2, generator=gen, dtype=F64) * 3,
                   torch.randn(tracks, 2, generator=gen, dtype=F64)], -1)
    xs = []
    for t in range(steps):
        if t:
            x = x @ f.T + torch.randn(tracks, 4, generator=gen, dtype=F64) @ chol.T
        xs.append(x)
    pos = torch.stack(xs, 1)[..., :2]
    n = torch.randint(0, 3, (tracks, steps), generator=gen).to(F64)  # 0, 1 or 2 nodes see the target
    noise = torch.randn(tracks, steps, 2, generator=gen, dtype=F64) * SIGMA / n.clamp_min(1).sqrt()[..., None]
    return torch.where(n[..., None] > 0, pos + noise, torch.zeros_like(pos)), n


def _start(tracks):
    return torch.zeros(tracks, 4, dtype=F64), torch.eye(4, dtype=F64).expand(tracks, 4, 4) * 1e6


def test_the_identification_recovers_a_simulated_model_and_stops_at_its_fixed_point():
    a, q = 0.9, 0.6
    z, n = _simulate(a, q, 60, 25, seed=11)
    m0, p0 = _start(60)
    out = identify_motion(z, n, DT, SIGMA, m0, p0, [1.0, 0.0], iterations=20, rounds=30, init_var=100.0,
                          prior_var=float("inf"), schedule="flooding", damping=0.0, graph="joint", lambda_tol=1e-8,
                          converge_tol=1e-9)
    # the truth within three of the factor graph's posterior standard deviations (0.011 for a, 0.12 for ln q here)
    err = (out.theta - torch.tensor([a, math.log(q)], dtype=F64)).abs()
    assert (err < 3 * out.var.sqrt()).all() and (out.var.sqrt() < torch.tensor([0.02, 0.2], dtype=F64)).all(), (
        out.theta, out.var)
    assert out.rows == int(2 * (n > 0).sum()) and torch.equal(out.path[-1], out.theta) and len(out.path) > 2
    # the fixed point: the criterion sum (y - h(theta))^2 / s, s frozen at the estimate, is stationary there
    seen = (n > 0)[..., None].expand(-1, -1, 2)

    def crit(th, s):
        kp = kalman(th, z, n, DT, SIGMA, m0, p0)
        return ((z - kp.pred).square() / s)[seen].sum()

    s_hat = kalman(out.theta, z, n, DT, SIGMA, m0, p0).var
    th = out.theta.clone().requires_grad_(True)
    grad = torch.autograd.grad(crit(th, s_hat), th)[0]
    assert grad.abs().max() < 1e-6 * float(crit(out.theta, s_hat)), grad
    # the scalar graph (the paper's) reaches the same estimate
    scalar = identify_motion(z, n, DT, SIGMA, m0, p0, [1.0, 0.0], iterations=50, rounds=30, init_var=100.0,
                             prior_var=float("inf"), schedule="flooding", damping=0.0, graph="scalar",
                             lambda_tol=1e-8, converge_tol=1e-9)
    torch.testing.assert_close(scalar.theta, out.theta, rtol=0, atol=1e-6)


def test_a_round_from_the_fixed_point_stops_once_its_step_is_below_the_tolerance(monkeypatch):
    """Started at its own estimate, the identification's line search halves a step that cannot lower the criterion
    only until it is shorter than converge_tol (then it stays there), not max_halvings times."""
    import dslearn.learning.factor_graph.motion as M

    z, n = _simulate(0.9, 0.6, 30, 20, seed=3)
    m0, p0 = _start(30)
    kw = dict(iterations=20, rounds=30, init_var=100.0, prior_var=float("inf"), schedule="flooding", damping=0.0,
              graph="joint", lambda_tol=1e-8)
    first = identify_motion(z, n, DT, SIGMA, m0, p0, [1.0, 0.0], converge_tol=1e-12, **kw)
    calls = []
    real = M.kalman
    monkeypatch.setattr(M, "kalman", lambda *a, **k: calls.append(k.get("slopes", False)) or real(*a, **k))
    again = identify_motion(z, n, DT, SIGMA, m0, p0, first.theta.tolist(), converge_tol=1e-3, **kw)
    torch.testing.assert_close(again.theta, first.theta, rtol=0, atol=1e-3)
    # one pass with slopes per round, and at most a few halvings from a step of the order of the tolerance
    assert calls.count(True) <= 2 and calls.count(False) <= 12, calls


def test_the_identification_without_measurements_keeps_its_guess():
    z, n = torch.zeros(2, 3, 2, dtype=F64), torch.zeros(2, 3, dtype=F64)
    out = identify_motion(z, n, DT, SIGMA, *_start(2), [0.7, -1.0], iterations=3, rounds=2, init_var=1.0,
                          prior_var=float("inf"), schedule="flooding", damping=0.0, graph="scalar", lambda_tol=1e-8,
                          converge_tol=1e-3)
    assert out.theta.tolist() == [0.7, -1.0] and out.rows == 0


# ------------------------------------------------------------------------------------------ the method
def test_fits_position_sensor_scenarios_and_refuses_the_others_for_a_person():
    m = FactorGraphMotionMethod()
    assert m.fits(ScenarioSpec("yu", "position", 2, "pv2d", 0.25, 12)) is None
    assert m.fits(ScenarioSpec("s1", "position", 1, "pv2d", 1.0, 60)) is None
    assert m.fits(ScenarioSpec("jiang", "squared_range", 1, "param2d", 1.0, 10, networked=False)) == (
        "the factor-graph identification of a motion model + EKF on position sensors (sensors that measure the "
        "positions of targets with a [px, py, vx, vy] state) needs measurement position; scenario jiang has "
        "squared_range")
    assert "needs measurement position; scenario braga has terrain_altitude" in m.fits(
        ScenarioSpec("braga", "terrain_altitude", 4, "platform", 0.05, 10, kind="self"))
    assert m.label == "fg_ekf_lin t=10" and m.learner.fg["init_guess"] == [1.0, 0.0]


@pytest.mark.parametrize("fg,match", [
    ({"taylor_point": "prediction"}, r"learner\.fg\.taylor_point='prediction' does not apply to filter=fg_ekf_lin: .*"
                                     r"allowed: guess"),
    ({"init_guess_mode": "prediction"}, r"learner\.fg\.init_guess_mode='prediction' .* allowed: fixed"),
    ({"measurement_var": "sample"}, r"learner\.fg\.measurement_var='sample' .* allowed: known"),
    ({"relinearize": True}, r"learner\.fg\.relinearize=True .* allowed: false"),
    ({"crlb_form": "paper_eq33"}, r"learner\.fg\.crlb_form='paper_eq33' .* takes no CRLB; allowed: trace_inverse"),
])
def test_a_learner_setting_the_position_form_cannot_use_is_refused(fg, match):
    with pytest.raises(ConfigError, match=match):
        FactorGraphMotionMethod(learner=FactorGraphIdentification(fg={**LIN_FG, **fg}))


def test_bad_settings_and_another_learner_are_refused():
    with pytest.raises(ConfigError, match=r"filter\.rounds=0 must be an integer >= 1"):
        FactorGraphMotionMethod(rounds=0)
    with pytest.raises(ConfigError, match=r"filter\.prior_pos_std=-1\.0 must be > 0"):
        FactorGraphMotionMethod(prior_pos_std=-1.0)
    with pytest.raises(ConfigError, match=r"learner=online: .*allowed: learner=fg_identification"):
        FactorGraphMotionMethod(learner=OnlineLearning())


def test_the_method_tracks_with_the_identified_model_and_the_scenarios_sensors():
    """estimate: the identification on the training measurements, then the filter on the test ones, each target of
    each episode its own track (the fused measurement of the nodes that see it)."""
    meas = torch.zeros(2, 1, 3, 2, 2, dtype=F64)
    vis = torch.zeros(2, 1, 3, 2, dtype=torch.bool)
    meas[0, 0, :, 0] = torch.tensor([[0.0, 0.0], [1.0, 0.5], [2.0, 1.0]], dtype=F64)
    vis[0, 0, :, 0] = True
    meas[1, 0, 1:, 1] = torch.tensor([[5.0, 5.0], [5.5, 5.0]], dtype=F64)
    vis[1, 0, 1:, 1] = True
    m = FactorGraphMotionMethod(prior_pos_std=100.0, prior_vel_std=10.0)
    th = torch.tensor([1.0, 0.0], dtype=F64)
    mean, cov = m.track(Measurements(meas, vis), th, SIGMA, 1.0, (0.0, 8.0, 0.0, 8.0))
    assert mean.shape == (1, 3, 2, 2) and cov.shape == (1, 3, 2, 2, 2)
    from dslearn.filters.distributed import prior_means

    p0 = torch.diag(torch.tensor([1e4, 1e4, 100.0, 100.0], dtype=F64))
    for a in (0, 1):
        z, n = fuse(meas[:, :, :, a:a + 1], vis[:, :, :, a:a + 1])
        kp = kalman(th, z, n, 1.0, SIGMA, prior_means(2, (0.0, 8.0, 0.0, 8.0))[a:a + 1], p0[None])
        torch.testing.assert_close(mean[0, :, a], kp.mean[0, :, :2], rtol=0, atol=0)
        torch.testing.assert_close(cov[0, :, a], kp.cov[0, :, :2, :2], rtol=0, atol=0)
    # target 1 is not seen at step 0: the prior's mean, its variance
    assert mean[0, 0, 1].tolist() == prior_means(2, (0.0, 8.0, 0.0, 8.0))[1, :2].tolist()
    assert cov[0, 0, 1, 0, 0].item() == pytest.approx(1e4)


def test_a_matrix_cell_end_to_end_on_yu_two_agents():
    """dslearn-run task=matrix method=fg_ekf_lin scenario=yu_two_agents task.train_episodes=2 task.test_episodes=2:
    a finite RMSE of the fusion centre, and a consistent filter's NEES order."""
    df = api.run("task=matrix", "method=fg_ekf_lin", "scenario=yu_two_agents", "task.train_episodes=2",
                 "task.test_episodes=2")
    rmse = df[df["metric"] == "rmse"]
    assert set(rmse["node"]) == {"fusion_center"} and len(rmse) == 2 and set(df["method"]) == {"fg_ekf_lin t=10"}
    assert np.isfinite(rmse["value"]).all() and (rmse["value"] < 1.0).all()  # 0.2 m sensors, an 8 m area
