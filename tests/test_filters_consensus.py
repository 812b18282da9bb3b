"""Reductions: information filter vs closed-form KF; consensus limits vs the centralised filter."""

import pytest
import torch

from dslearn.consensus.fusion import make_fusion
from dslearn.consensus.weights import metropolis, uniform
from dslearn.filters.information import novel_information, predict, to_information, to_moment
from dslearn.models import ConstantVelocity, LinearPositionObservation
from dslearn.sim.network import make_network
from dslearn.sim.scenario import SocialForceScenario
from dslearn.tracker import initial_belief, track
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


def _linear_run(fusion_name, weights_fn, iterations, omega, pooled):
    scen = SocialForceScenario(process_std=1e-3)
    net = make_network(seed=1, sensing_range=3.0)
    ep = scen.sample(3, net, torch.Generator().manual_seed(5))
    lin, obs = ConstantVelocity(2, 0.1), LinearPositionObservation(0.2)
    fusion = make_fusion(fusion_name, weights_fn(net.adjacency), iterations, omega)
    centre = torch.tensor([4.0, 4.0], dtype=D)
    init = initial_belief(ep, net, 0.25, centre, 4.0, 2.0, pooled=pooled)
    return track(ep, net, lin, obs, fusion, CTX, init)


def test_hybrid_metropolis_many_iterations_equals_centralized():
    """Doubly stochastic weights, omega = S, L -> infinity: every node = centralised filter."""
    central = _linear_run("centralized", metropolis, 0, "one", pooled=True)
    hybrid = _linear_run("hybrid", metropolis, 400, "nodes", pooled=True)
    assert torch.allclose(hybrid.mean, central.mean, atol=1e-8)
    assert torch.allclose(hybrid.info, central.info, rtol=1e-8, atol=1e-6)
    # and the CM strategy reaches the same limit
    cm = _linear_run("cm", metropolis, 400, "nodes", pooled=True)
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
