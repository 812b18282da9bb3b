"""Limits that must hold exactly: consensus with enough rounds on a connected graph with doubly stochastic
weights reproduces the centralised solution.

* Braga: consensus on the sufficient statistics (Algorithm 3) with q -> infinity is the fusion centre's
  average (Eq. 19), so the whole online EM (RBPF, E-step, M-step) of ``consensus_200`` equals
  ``centralised`` on the same random streams; ``consensus_10`` is still a different estimator (closed form of
  its residual disagreement for the Eq. 26 matrix).
* Yu: hybrid consensus with omega = S, Metropolis weights and L -> infinity gives every node the centralised
  posterior (one step and a whole track); the uniform rule (row-stochastic only) converges to a
  degree-weighted average instead.
* Faults: the faults study without faults reproduces the plain Yu study for every fusion, omega included.
"""

from __future__ import annotations

import math

import pytest
import torch
from hydra import compose, initialize_config_dir

import dslearn.schemas  # noqa: F401  (the task schemas the configs name)
from dslearn.conf_paths import CONF_DIR
from dslearn.errors import ConfigError
from dslearn.fusion.strategies import make_fusion
from dslearn.fusion.weights import metropolis, uniform

D = torch.float64


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return compose("config", overrides=["progress=false", *overrides])


# ------------------------------------------------------------------ Braga: consensus on sufficient statistics
FINGER_FOUR = [[0, 1], [0, 2], [2, 3]]


def test_eq26_consensus_residual_closed_form():
    """Eq. (26) is A = I - L/4 for the path 1-0-2-3 (Laplacian eigenvalues 0, 2-sqrt2, 2, 2+sqrt2), so A's
    eigenvalues are 1, (2+sqrt2)/4, 1/2, (2-sqrt2)/4 and ||A^q - 11^T/4||_2 = ((2+sqrt2)/4)^q: after q = 10 rounds
    the nodes still hold 20.6 % of their initial disagreement; q = 200 leaves 1.9e-14."""
    from dslearn.fusion.statistics import combination_matrices, network_adjacency, weight_matrix

    a = weight_matrix(network_adjacency(4, FINGER_FOUR), "half_max_degree")
    eq26 = torch.tensor([[0.5, 0.25, 0.25, 0.0], [0.25, 0.75, 0.0, 0.0], [0.25, 0.0, 0.5, 0.25],
                         [0.0, 0.0, 0.25, 0.75]], dtype=D)
    assert torch.equal(a, eq26)
    r2 = math.sqrt(2.0)
    lam = [(2 - r2) / 4, 0.5, (2 + r2) / 4, 1.0]
    torch.testing.assert_close(torch.linalg.eigvalsh(a), torch.tensor(lam, dtype=D), rtol=0, atol=1e-15)
    cent, c10, c200 = combination_matrices(["centralised", "consensus_10", "consensus_200"], a)
    torch.testing.assert_close(cent, torch.full((4, 4), 0.25, dtype=D), rtol=0, atol=0)
    res10 = torch.linalg.matrix_norm(c10 - cent, ord=2).item()
    assert res10 == pytest.approx(((2 + r2) / 4) ** 10, rel=1e-12)
    assert 0.205 < res10 < 0.206
    assert torch.linalg.matrix_norm(c200 - cent, ord=2).item() < 2e-14
    # A^q stays doubly stochastic: the network average of the statistics is preserved by every round
    torch.testing.assert_close(c10.sum(0), torch.ones(4, dtype=D), rtol=0, atol=1e-15)


def test_m_step_same_for_sum_and_average_of_statistics():
    """Eq. (19) averages the local statistics where the global ones are their sum; the M-step (Eq. 8) is a ratio
    of statistics, so the factor 1/N_S cancels (the paper's remark). Closed form: statistics of occupancies n_k,
    means m_k and variances v_k, transition counts c_kl give mu = m, sigma = sqrt(v), pi = c / row sums."""
    from dslearn.models.jmnls import m_step, make_params

    n = torch.tensor([3.0, 1.5], dtype=D)
    m = torch.tensor([0.4, 19.0], dtype=D)
    v = torch.tensor([1.2, 15.0], dtype=D)
    c = torch.tensor([[2.0, 0.6], [0.9, 0.5]], dtype=D)
    stats = torch.cat([c.flatten(), n, n * m, n * (v + m * m)])
    prev = make_params([-5.0, 25.0], [5.0, 5.0], [[0.5, 0.5], [0.5, 0.5]])
    for scale in (0.25, 1.0, 4.0):
        th = m_step(scale * stats, prev)
        torch.testing.assert_close(th.mu, m, rtol=1e-14, atol=0)
        torch.testing.assert_close(th.sigma, v.sqrt(), rtol=1e-13, atol=0)
        torch.testing.assert_close(th.pi, c / c.sum(-1, keepdim=True), rtol=1e-14, atol=0)


def test_consensus_200_equals_centralised_online_em():
    """The whole distributed online EM (RBPF, E-step, Algorithm 3, M-step) with 200 consensus rounds equals the
    centralised EM on the same random streams (common random numbers), node by node, over a short run past the
    burn-in; 10 rounds give a different run (the M-step then differs from the first M-step on)."""
    from dslearn.compose import build_study
    from dslearn.learning.online_em import simulate_and_filter
    from dslearn.metrics.navigation import tbn_errors

    burn_in = 20
    cfg = _compose("experiment=braga_tbn", "seed=3", "task.mc_runs=2", "task.mc_batch=2", "task.workers=1",
                   "task.steps=80", "task.num_particles=30", f"task.em.burn_in={burn_in}", "task.steady_state_s=1.0",
                   "task.terrain.size_m=12000.0", "task.terrain.resolution_m=50.0", "task.record_every=20",
                   "task.zoom_s=0.5", "task.strategies=[centralised,consensus_200,consensus_10]")
    scn, res = simulate_and_filter(build_study(cfg).job(), [0, 1])
    cent, c200, c10 = (slice(i, i + 1) for i in range(3))
    for name in ("mu", "sigma", "pi"):
        v = getattr(res, name)  # (T, R, C, S, ...)
        torch.testing.assert_close(v[:, :, c200], v[:, :, cent], rtol=0, atol=1e-10, msg=name)
        # centralised: every node runs the M-step on the same average
        torch.testing.assert_close(v[:, :, cent], v[:, :, cent, :1].expand_as(v[:, :, cent]), rtol=0, atol=0)
    torch.testing.assert_close(res.est[:, :, c200], res.est[:, :, cent], rtol=1e-13, atol=1e-9)
    pos_se = tbn_errors(res, scn).pos_se
    torch.testing.assert_close(pos_se[:, :, c200], pos_se[:, :, cent], rtol=1e-9, atol=1e-9)
    # the M-step has run and moved the parameters (the comparison is not of the initial values)
    assert (res.mu[-1, :, 0] - torch.tensor([-5.0, 25.0], dtype=D)).abs().min() > 0.5
    # before the first M-step all strategies are one filter; after it, 10 rounds are not the average
    torch.testing.assert_close(res.est[:burn_in, :, c10], res.est[:burn_in, :, cent], rtol=0, atol=0)
    assert (res.mu[burn_in:, :, c10] - res.mu[burn_in:, :, cent]).abs().max() > 1e-2


# ------------------------------------------------------------------ Yu: hybrid consensus, L -> infinity
def _yu_network():
    from dslearn.sim.placement import make_network

    return make_network()  # conf/network/yu.yaml: 4 sensors + 6 relays, irregular graph


def _common_prior_and_novel(s, b=2, d=8, seed=0):
    """One prior pair shared by all nodes, and per-node novel pairs (random SPD information)."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(b, d, d, dtype=D, generator=g)
    o_pred = (a @ a.transpose(-1, -2) + d * torch.eye(d, dtype=D)).expand(s, b, d, d)
    q_pred = torch.randn(b, d, dtype=D, generator=g).expand(s, b, d)
    a = torch.randn(s, b, d, d, dtype=D, generator=g)
    do = 0.3 * (a @ a.transpose(-1, -2)) + torch.eye(d, dtype=D)
    return q_pred, o_pred, torch.randn(s, b, d, dtype=D, generator=g), do


def test_hybrid_nodes_metropolis_limit_is_centralized_step():
    """Metropolis weights are symmetric and doubly stochastic: W^L -> 11^T/S with ||W^L - 11^T/S||_2 = lam^L
    (lam the second largest eigenvalue modulus). With omega = S and a common prior, hybrid gives every node
    prior + S * mean(novel) = prior + sum(novel), the centralised posterior; its error is at most
    S lam^L ||novel - mean|| and shrinks by lam per round."""
    net = _yu_network()
    s = net.num_nodes
    w = metropolis(net.adjacency)
    ev = torch.linalg.eigvalsh(w)
    lam = max(abs(ev[0].item()), abs(ev[-2].item()))
    assert abs(ev[-1].item() - 1.0) < 1e-14 and lam < 1 - 1e-3  # connected
    args = _common_prior_and_novel(s)
    q_c, o_c = make_fusion("centralized", w, 0)(*args)
    q_pred, o_pred, dq, do = args
    torch.testing.assert_close(o_c, (o_pred[0] + do.sum(0)).expand_as(o_c), rtol=1e-14, atol=1e-12)  # by hand
    q, o = make_fusion("hybrid", w, 200, "nodes")(*args)
    scale = do.sum(0).abs().max().item()
    torch.testing.assert_close(o, o_c, rtol=0, atol=1e-12 * scale)
    torch.testing.assert_close(q, q_c, rtol=0, atol=1e-12 * dq.sum(0).abs().max().item())
    errs = []
    for L in (20, 21, 40, 41):
        qL, _ = make_fusion("hybrid", w, L, "nodes")(*args)
        err = (qL - q_c).flatten(1).norm(dim=0)  # per episode, over nodes and states
        spread = (dq - dq.mean(0)).flatten(1).norm(dim=0)
        assert (err <= s * lam ** L * spread * (1 + 1e-9)).all()
        errs.append(err)
    # the slowest mode dominates: the error shrinks by lam per round
    torch.testing.assert_close(errs[3] / errs[2], torch.full_like(errs[2], lam), rtol=2e-3, atol=0)
    # omega = 1 (hybrid's default) under-weights the novel information by S in the limit
    q1, o1 = make_fusion("hybrid", w, 200, "one")(*args)
    torch.testing.assert_close(o1, (o_pred[0] + do.mean(0)).expand_as(o1), rtol=0, atol=1e-12 * scale)


def test_hybrid_limit_needs_a_common_prior():
    """With different priors the limit is the average prior plus the summed novel information: the
    centralised filter of the averaged prior, not of each node's own."""
    net = _yu_network()
    s = net.num_nodes
    q_pred, o_pred, dq, do = _common_prior_and_novel(s, seed=1)
    g = torch.Generator().manual_seed(5)
    o_pred = o_pred + torch.diag_embed(torch.rand(s, 1, 8, dtype=D, generator=g) * 10)
    q_pred = q_pred + torch.randn(s, 1, 8, dtype=D, generator=g)
    q, o = make_fusion("hybrid", metropolis(net.adjacency), 200, "nodes")(q_pred, o_pred, dq, do)
    torch.testing.assert_close(o, (o_pred.mean(0) + do.sum(0)).expand_as(o), rtol=0, atol=1e-10)
    torch.testing.assert_close(q, (q_pred.mean(0) + dq.sum(0)).expand_as(q), rtol=0, atol=1e-10)
    q_c, o_c = make_fusion("centralized", metropolis(net.adjacency), 0)(q_pred, o_pred, dq, do)
    assert (o - o_c).abs().max() > 1.0


def test_uniform_weights_limit_star_graph_by_hand():
    """Star of 4 nodes (centre 0): uniform weights 1/(|N_i|+1) are row-stochastic only; W^L -> 1 pi^T with
    pi_i = (d_i + 1) / sum_j (d_j + 1) = (4, 2, 2, 2) / 10. With omega = S = 4 the novel information of a node
    seen by nobody else is counted 4 * 0.4 = 1.6 times at the centre and 4 * 0.2 = 0.8 times at a leaf; with
    Metropolis weights exactly once (the centralised filter)."""
    adj = torch.zeros(4, 4, dtype=torch.bool)
    adj[0, 1:] = adj[1:, 0] = True
    wu, wm = uniform(adj), metropolis(adj)
    torch.testing.assert_close(torch.linalg.matrix_power(wu, 200),
                               torch.tensor([[0.4, 0.2, 0.2, 0.2]], dtype=D).expand(4, 4), rtol=0, atol=1e-15)
    d = 4
    o_pred = torch.eye(d, dtype=D).expand(4, 1, d, d)
    q_pred = torch.zeros(4, 1, d, dtype=D)
    for node, factor in ((0, 1.6), (2, 0.8)):
        do = torch.zeros(4, 1, d, d, dtype=D)
        do[node] = torch.diag(torch.tensor([2.0, 3.0, 5.0, 7.0], dtype=D))
        dq = torch.zeros(4, 1, d, dtype=D)
        dq[node] = torch.tensor([1.0, -1.0, 0.5, 2.0], dtype=D)
        for w, f in ((wu, factor), (wm, 1.0)):
            q, o = make_fusion("hybrid", w, 200, "nodes")(q_pred, o_pred, dq, do)
            torch.testing.assert_close(o, (o_pred[0] + f * do[node]).expand_as(o), rtol=0, atol=1e-13)
            torch.testing.assert_close(q, (f * dq[node]).expand_as(q), rtol=0, atol=1e-13)


def test_uniform_weights_on_a_regular_graph_give_the_centralized_limit():
    """On a regular graph (ring of 6) the uniform weights are doubly stochastic, and their limit is the
    centralised posterior like Metropolis'; on the irregular Yu graph it is not."""
    s = 6
    ring = torch.zeros(s, s, dtype=torch.bool)
    for i in range(s):
        ring[i, (i + 1) % s] = ring[(i + 1) % s, i] = True
    args = _common_prior_and_novel(s, seed=2)
    q_c, o_c = make_fusion("centralized", uniform(ring), 0)(*args)
    q, o = make_fusion("hybrid", uniform(ring), 300, "nodes")(*args)
    torch.testing.assert_close(o, o_c, rtol=0, atol=1e-10)
    torch.testing.assert_close(q, q_c, rtol=0, atol=1e-10)
    net = _yu_network()
    args = _common_prior_and_novel(net.num_nodes, seed=2)
    q_c, o_c = make_fusion("centralized", uniform(net.adjacency), 0)(*args)
    _, o = make_fusion("hybrid", uniform(net.adjacency), 300, "nodes")(*args)
    assert (o - o_c).abs().max() > 1e-6 * o_c.abs().max()  # far above the 1e-12 of the converged limits


def _yu_track(consensus, *overrides, episodes=2):
    """Test episodes of the Yu configuration (LIN model, conf/network/yu.yaml) tracked with one fusion."""
    from dslearn.filters.distributed import initial_belief, track
    from dslearn import api

    cfg = _compose("model=lin", f"consensus={consensus}", "data.train_episodes=0", f"data.test_episodes={episodes}",
                   *overrides)
    p = api.build_study(cfg)
    test, _ = p.sample()
    ctx = p.scenario.ctx()
    init = initial_belief(test.measurements, p.network, ctx.dt, p.fusion, p.scenario.area,
                          cfg.filter.prior_pos_std, cfg.filter.prior_vel_std)
    return track(test.measurements, p.network, p.model, p.observation, p.fusion, ctx, init, predict_step=p.predict)


def test_track_hybrid_L200_metropolis_equals_centralized():
    """The distributed filter over a whole episode (LIN model, EKF, the Yu network) with hybrid consensus,
    L = 200, omega = S and Metropolis weights: every node's estimate and information at every step equal the
    centralised filter's (second eigenvalue modulus of W is 0.834, so W^200 is 11^T/S to 2e-16)."""
    central = _yu_track("centralized")
    hyb = _yu_track("hybrid_nodes", "consensus.iterations=200", "consensus.weights=metropolis")
    assert central.mean.shape[2] == 13  # K = 12 steps + the initial belief
    info_scale = central.info.abs().max().item()
    torch.testing.assert_close(hyb.info, central.info, rtol=0, atol=1e-11 * info_scale)
    torch.testing.assert_close(hyb.mean, central.mean, rtol=0, atol=1e-10)
    # the default L = 4 and the uniform rule's weighted limit are not the centralised filter
    short = _yu_track("hybrid_nodes", "consensus.iterations=4", "consensus.weights=metropolis")
    assert (short.mean - central.mean).abs().max() > 1e-3
    unif = _yu_track("hybrid_nodes", "consensus.iterations=200", "consensus.weights=uniform")
    assert (unif.info - central.info).abs().max() > 1e-3 * info_scale


# ------------------------------------------------------------------ faults study without faults = Yu study
FUSIONS = ["individual", "ce", "cm", "ci", "hybrid", "hybrid_nodes", "centralized"]
TRACK_METRICS = ["track_err", "track_rmse", "nees"]


@pytest.mark.parametrize("model", ["lin", "gp_increment"])
def test_faults_study_without_faults_equals_yu_study(model):
    """No link or node failures, no outliers: every fusion's rows of the faults study (node-averaged) equal the
    plain Yu study's with the same weights (Metropolis), L, omega, episodes and training (2 + 2 episodes), and
    hybrid_nodes (omega = S) differs from hybrid (omega = 1)."""
    from dslearn.schemas.core import validate_config
    from dslearn import api

    cfg = _compose("experiment=yu_faults", f"task.models=[{model}]", f"task.fusions=[{','.join(FUSIONS)}]",
                   "task.train_episodes=2", "task.test_episodes=2", "task.link_fail=[0.0]", "task.node_fail=[0.0]",
                   "task.joint=[]", "task.outlier_settings=false", "task.weights=metropolis")
    validate_config(cfg)
    faults = api.build_study(cfg).run()
    faults = faults[(faults.node == "all") & faults.metric.isin(TRACK_METRICS)]
    assert sorted(set(faults.consensus)) == sorted(FUSIONS) and (faults.link_fail == 0).all()
    got = {}
    for fname in FUSIONS:
        ycfg = _compose(f"model={model}", f"consensus={fname}", "consensus.weights=metropolis",
                        "data.train_episodes=2", "data.test_episodes=2")
        yu = api.build_study(ycfg).run()
        expect = yu[yu.metric.isin(TRACK_METRICS)].groupby(["episode", "metric"]).value.mean()  # over nodes
        got[fname] = faults[faults.consensus == fname].set_index(["episode", "metric"]).value.sort_index()
        assert got[fname].index.equals(expect.index) and len(expect) == 2 * len(TRACK_METRICS)
        assert ((got[fname] - expect).abs() <= 1e-12 * expect.abs().clip(lower=1.0)).all(), fname
    assert (got["hybrid_nodes"] - got["hybrid"]).abs().max() > 1e-3
    assert (got["hybrid"] - got["ci"]).abs().max() < 1e-12  # omega = 1: hybrid's W^L(q + dq) is CI's


def test_faults_study_refuses_a_root_omega():
    """A root consensus.omega would apply to no fusion of the grid (each takes its own option's): refused."""
    from dslearn.schemas.yu_faults import grid_fusion_nodes

    cfg = _compose("experiment=yu_faults", "task.fusions=[hybrid,hybrid_nodes]")
    fus = grid_fusion_nodes(cfg)
    assert fus["hybrid"].omega == "one" and fus["hybrid_nodes"].omega == "nodes"
    assert fus["hybrid_nodes"].iterations == cfg.consensus.iterations
    from dslearn.schemas import validate_config

    with pytest.raises(ConfigError, match="consensus.omega"):
        validate_config(_compose("experiment=yu_faults", "consensus.omega=nodes"))
