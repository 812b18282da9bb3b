"""Reductions: information filter vs closed-form KF; consensus limits vs the centralised filter."""

import pytest
import torch

from dslearn.fusion.strategies import make_fusion
from dslearn.fusion.weights import metropolis, uniform
from dslearn.filters.information import novel_information, predict, to_information, to_moment
from dslearn.models import ConstantVelocity, LinearPositionObservation
from dslearn.sim.placement import make_network
from dslearn.sim.scenario import SocialForceScenario
from dslearn.filters.distributed import initial_belief, track
from dslearn.types import StepContext

D = torch.float64
CTX = StepContext(dt=0.25)


def spd(n, *batch):
    a = torch.randn(*batch, n, n, dtype=D)
    return a @ a.transpose(-1, -2) + n * torch.eye(n, dtype=D)


def test_information_roundtrip():
    m, P = torch.randn(3, 4, dtype=D), spd(4, 3)
    q, O = to_information(m, P)
    m2, P2 = to_moment(q, O)
    assert torch.allclose(m, m2, atol=1e-10) and torch.allclose(P, P2, atol=1e-10)


def test_information_ekf_equals_kalman_filter():
    """One node, linear model: information-form predict + update = the textbook KF."""
    lin, obs = ConstantVelocity(1, 0.3), LinearPositionObservation(0.2)
    m, P = torch.randn(1, 1, 4, dtype=D), spd(4, 1, 1)
    z = torch.randn(1, 1, 1, 2, dtype=D)
    vis = torch.ones(1, 1, 1, dtype=torch.bool)
    y_pred, q_pred, O_pred = predict(m, torch.linalg.inv(P), lin, CTX)
    dq, dO = novel_information(y_pred, z, vis, obs)
    post_m, post_P = to_moment(q_pred + dq, O_pred + dO)
    F, Q, H, R = lin.matrix(0.25), 0.09 * torch.eye(4, dtype=D), obs.matrix(), 0.04 * torch.eye(2, dtype=D)
    mp, Pp = F @ m[0, 0], F @ P[0, 0] @ F.T + Q
    K = Pp @ H.T @ torch.linalg.inv(H @ Pp @ H.T + R)
    m_kf, P_kf = mp + K @ (z[0, 0, 0] - H @ mp), (torch.eye(4, dtype=D) - K @ H) @ Pp
    assert torch.allclose(post_m[0, 0], m_kf, atol=1e-10)
    assert torch.allclose(post_P[0, 0], P_kf, atol=1e-10)


def _linear_run(fusion_name, weights_fn, iterations, omega):
    scen = SocialForceScenario(process_std=1e-3)
    net = make_network(seed=1, sensing_range=3.0)
    ep = scen.sample(3, net, torch.Generator().manual_seed(5))
    lin, obs = ConstantVelocity(2, 0.1), LinearPositionObservation(0.2)
    fusion = make_fusion(fusion_name, weights_fn(net.adjacency), iterations, omega)
    init = initial_belief(ep.measurements, net, 0.25, fusion, scen.area)  # the same rule for every fusion
    return track(ep.measurements, net, lin, obs, fusion, CTX, init)


def test_hybrid_metropolis_many_iterations_equals_centralized():
    """Doubly stochastic weights, omega = S, L -> infinity: every node = centralised filter."""
    central = _linear_run("centralized", metropolis, 0, "one")
    hybrid = _linear_run("hybrid", metropolis, 400, "nodes")
    assert torch.allclose(hybrid.mean, central.mean, atol=1e-8)
    assert torch.allclose(hybrid.info, central.info, rtol=1e-8, atol=1e-6)
    # and the CM strategy reaches the same limit
    cm = _linear_run("cm", metropolis, 400, "nodes")
    assert torch.allclose(cm.mean, central.mean, atol=1e-8)


def test_uniform_weights_limit_is_degree_weighted_average():
    """With the paper's uniform weights W^L -> 1 pi^T, pi_i proportional to |N_i| + 1."""
    net = make_network(seed=2)
    w = uniform(net.adjacency)
    s = net.num_nodes
    pi = (net.adjacency.sum(1) + 1).to(D)
    pi = pi / pi.sum()
    q_pred, O_pred = torch.randn(s, 2, 8, dtype=D), spd(8, s, 2)
    dq, dO = torch.randn(s, 2, 8, dtype=D), spd(8, s, 2)
    q, O = make_fusion("hybrid", w, 500, "nodes")(q_pred, O_pred, dq, dO)
    exp_q = torch.einsum("i,i...->...", pi, q_pred) + s * torch.einsum("i,i...->...", pi, dq)
    exp_O = torch.einsum("i,i...->...", pi, O_pred) + s * torch.einsum("i,i...->...", pi, dO)
    assert torch.allclose(q, exp_q.expand_as(q), atol=1e-9)
    assert torch.allclose(O, exp_O.expand_as(O), atol=1e-9)


@pytest.mark.parametrize("name", ["individual", "ce", "cm", "ci", "hybrid", "centralized"])
def test_fusions_keep_information_symmetric_positive_definite(name):
    net = make_network(seed=0)
    s = net.num_nodes
    fusion = make_fusion(name, uniform(net.adjacency), 3, "one")
    q, O = fusion(torch.randn(s, 2, 8, dtype=D), spd(8, s, 2), torch.randn(s, 2, 8, dtype=D), spd(8, s, 2) * 0.1)
    assert torch.allclose(O, O.transpose(-1, -2))
    assert (torch.linalg.eigvalsh(O) > 0).all()
    assert q.shape == (s, 2, 8)


def test_zero_iterations_hybrid_is_individual():
    net = make_network(seed=0)
    s = net.num_nodes
    args = (torch.randn(s, 1, 8, dtype=D), spd(8, s, 1), torch.randn(s, 1, 8, dtype=D), spd(8, s, 1))
    a = make_fusion("hybrid", uniform(net.adjacency), 0, "one")(*args)
    b = make_fusion("individual", uniform(net.adjacency), 0, "one")(*args)
    assert torch.allclose(a[0], b[0]) and torch.allclose(a[1], b[1])


def test_safe_cholesky_jitters_only_the_failing_matrix():
    from dslearn.types import JitterLog, safe_cholesky

    good = torch.tensor([[4.0, 1.0], [1.0, 3.0]], dtype=torch.float64)
    big = 1e12 * torch.eye(2, dtype=torch.float64)
    singular = torch.tensor([[1.0, 1.0], [1.0, 1.0]], dtype=torch.float64)
    m = torch.stack([good, big, singular])
    log = JitterLog()
    L = safe_cholesky(m, log=log)
    # the matrices that factor cleanly are untouched, bit for bit
    torch.testing.assert_close(L[:2], torch.linalg.cholesky(m[:2]), rtol=0, atol=0)
    # the singular one gets a small jitter scaled by its own diagonal, not by the batch's (1e12)
    rec = L[2] @ L[2].T
    assert torch.isfinite(L).all()
    assert (rec - singular).abs().max() < 1e-6
    assert log.count == 1 and 0 < log.max_jitter < 1e-6
    # a clean batch records nothing
    safe_cholesky(m[:2], log=log)
    assert log.count == 1


def _local_posteriors(s, b=2, d=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(s, b, d, d, dtype=D, generator=g)
    O_pred = a @ a.transpose(-1, -2) + d * torch.eye(d, dtype=D)
    a = torch.randn(s, b, d, d, dtype=D, generator=g)
    dO = 0.3 * (a @ a.transpose(-1, -2)) + torch.eye(d, dtype=D)
    return torch.randn(s, b, d, dtype=D, generator=g), O_pred, torch.randn(s, b, d, dtype=D, generator=g), dO


@pytest.mark.parametrize("graph", ["complete", "ring"])
def test_ci_is_the_average_of_local_posterior_information(graph):
    """CI, complete graph (one round = the average) or a ring with Metropolis weights and many
    rounds: every node holds (1/S) sum_i (q_i, Omega_i) of the local posteriors, so its estimate is
    the information-weighted average of the local estimates."""
    s = 6
    if graph == "complete":
        adj, rounds = ~torch.eye(s, dtype=torch.bool), 1
        w = uniform(adj)
    else:
        adj = torch.zeros(s, s, dtype=torch.bool)
        for i in range(s):
            adj[i, (i + 1) % s] = adj[(i + 1) % s, i] = True
        w, rounds = metropolis(adj), 300
    q_pred, O_pred, dq, dO = _local_posteriors(s)
    q, O = make_fusion("ci", w, rounds, "one")(q_pred, O_pred, dq, dO)
    q_loc, O_loc = q_pred + dq, O_pred + dO
    assert torch.allclose(O, O_loc.mean(0, keepdim=True).expand_as(O), atol=1e-9)
    y = torch.linalg.solve(O, q.unsqueeze(-1)).squeeze(-1)
    y_exp = torch.linalg.solve(O_loc.sum(0), q_loc.sum(0).unsqueeze(-1)).squeeze(-1)
    assert torch.allclose(y, y_exp.expand_as(y), atol=1e-9)


def test_ce_averages_the_local_estimates_and_keeps_local_information():
    """CE on a complete graph (uniform weights 1/S, one round): every node's estimate is the plain
    average of the local posterior estimates; its information stays its own local posterior's."""
    s = 5
    w = uniform(~torch.eye(s, dtype=torch.bool))
    q_pred, O_pred, dq, dO = _local_posteriors(s, seed=1)
    q, O = make_fusion("ce", w, 1, "one")(q_pred, O_pred, dq, dO)
    O_loc = O_pred + dO
    y_loc = torch.linalg.solve(O_loc, (q_pred + dq).unsqueeze(-1)).squeeze(-1)
    assert torch.allclose(O, O_loc, atol=1e-12)
    y = torch.linalg.solve(O, q.unsqueeze(-1)).squeeze(-1)
    assert torch.allclose(y, y_loc.mean(0, keepdim=True).expand_as(y), atol=1e-9)


def test_tracking_metrics_by_hand():
    from dslearn.filters.distributed import TrackResult
    from dslearn.metrics import tracking_metrics

    # one node, one episode, K = 2 steps, two agents; errors chosen by hand
    truth = torch.zeros(1, 3, 8, dtype=D)
    mean = torch.zeros(1, 1, 3, 8, dtype=D)
    mean[0, 0, 0, 0] = 100.0  # t = 0 is not scored
    mean[0, 0, 1, 0:2] = torch.tensor([3.0, 4.0], dtype=D)  # agent 1, t = 1: position error 5
    mean[0, 0, 1, 6] = 7.0  # a velocity error: not in the position errors, in the NEES
    mean[0, 0, 2, 4:6] = torch.tensor([0.0, 1.0], dtype=D)  # agent 2, t = 2: position error 1
    info = torch.diag_embed(torch.full((1, 1, 3, 8), 2.0, dtype=D))
    m = tracking_metrics(TrackResult(mean, info), truth)
    # position errors over (t, agent): t1 (5, 0), t2 (0, 1)
    assert m["track_err"].item() == pytest.approx((5 + 0 + 0 + 1) / 4)
    assert m["track_rmse"].item() == pytest.approx(((25 + 0 + 0 + 1) / 4) ** 0.5)
    # NEES: t1: 2 * (9 + 16 + 49) = 148, t2: 2 * 1 = 2; mean over t / Dx
    assert m["nees"].item() == pytest.approx((148 + 2) / 2 / 8)


def test_prediction_error_by_hand():
    from dslearn.metrics import prediction_error

    lin = ConstantVelocity(1, 0.1)
    ctx = StepContext(dt=0.5)
    # truth: an agent that moves at (1, 0) for one step, then stops
    truth = torch.tensor([[[0.0, 0.0, 1.0, 0.0], [0.5, 0.0, 0.0, 0.0], [0.5, 0.0, 0.0, 0.0]]], dtype=D)
    err = prediction_error(lin, truth, num_nodes=3, ctx=ctx, per_node=False)
    # CV from the true t = 0 state: (0.5, 0) then (1.0, 0): errors 0 and 0.5
    assert err.shape == (3, 1)
    assert torch.allclose(err, torch.full((3, 1), 0.25, dtype=D))
