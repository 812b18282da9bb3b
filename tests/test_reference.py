"""The fast path (dslearn.studies.yu) against the independent reference (dslearn.reference): every model
the reference supports, every fusion strategy and weight rule, on a tiny protocol (6 nodes: 4 sensors +
2 relays, 1 training + 1 test episode); and the reference's own pieces against values by hand.

Tolerance: dslearn.reference.REFERENCE_TOL on |fast - ref| / max(1, |fast|, |ref|) for every metric
value of every node and episode (both float64; they differ in summation order only)."""

import math

import pytest
import torch

from dslearn.reference import (REFERENCE_TOL, ReferenceFusion, ReferenceYu, compare_results, reference_initial_belief,
                               reference_tracking_metrics, reference_weights)

D = torch.float64
NET = {"network.num_comm": 2, "network.comm_radius": 6.0}  # degrees 4 and 5: Metropolis weights differ from max-degree
SHORT = {"scenario.horizon": 1.5}  # 6 steps: the GP runs (the reference refactorises its GP at every step)


def _cfg(model, consensus, **kw):
    """The composed (validated) configuration of a tiny Yu run: 1 training + 1 test episode."""
    from dslearn import api

    opts = {"data.train_episodes": 1, "data.test_episodes": 1, **NET, **kw}
    return api.compose("task=yu", f"model={model}", f"consensus={consensus}", *(f"{k}={v}" for k, v in opts.items()))


def _assert_equal_to_reference(model, consensus, **kw):
    from dslearn import api

    cfg = _cfg(model, consensus, **kw)
    fast = api.build_study(cfg).run()
    ref = ReferenceYu.from_config(cfg).run()
    r = compare_results(fast, ref)
    assert r["max_diff"] <= REFERENCE_TOL, r["worst"]
    return fast


FUSIONS = [  # (consensus option, extra overrides): every strategy, omega one / nodes / a number, every weight rule
    ("individual", {}),
    ("centralized", {}),
    ("ce", {}),
    ("ce", {"consensus.weights": "metropolis"}),
    ("cm", {"consensus.weights": "max_degree"}),
    ("cm", {"consensus.omega": "nodes"}),
    ("ci", {"consensus.weights": "half_max_degree"}),
    ("hybrid", {}),
    ("hybrid", {"consensus.weights": "metropolis"}),
    ("hybrid", {"consensus.weights": "half_max_degree", "consensus.iterations": 2}),
    ("hybrid_nodes", {}),
    ("hybrid", {"consensus.omega": 2.5}),
]


@pytest.mark.parametrize("consensus,kw", FUSIONS, ids=[f"{c}-{'-'.join(map(str, k.values())) or 'default'}" for c, k in FUSIONS])
def test_lin_every_fusion_and_weight_rule(consensus, kw):
    _assert_equal_to_reference("lin", consensus, **kw)


@pytest.mark.parametrize("consensus", ["individual", "centralized", "ce", "cm", "ci", "hybrid", "hybrid_nodes"])
def test_sfm_every_fusion(consensus):
    """SFM softens interactions by the node's covariance (StepContext.cov): under individual fusion
    the relays hold the diffuse prior, where that softening decides the prediction."""
    _assert_equal_to_reference("sfm", consensus)


@pytest.mark.parametrize("model,consensus,kw", [
    ("gp", "individual", {}),
    ("gp", "hybrid", {"model.noise": "predictive"}),
    ("gp_increment", "individual", {}),
    ("gp_increment", "ce", {}),
    ("gp_increment", "ci", {"model.factor": "cholesky"}),
    ("gp_increment", "centralized", {"model.jacobian": "autograd"}),
    ("gp_increment", "hybrid", {"data.eval_at": "[0,1]"}),
    ("gp_window", "individual", {"model.window": 4}),
    ("gp_window", "hybrid", {"model.window": 4}),
])
def test_gp_models(model, consensus, kw):
    """The learned models: the reference's GPyTorch ExactGP refit on every change (the window GP:
    on its last 4 slots, dropped from the 6 steps of the training episode) equals the fast GP."""
    fast = _assert_equal_to_reference(model, consensus, **SHORT, **kw)
    if "data.eval_at" in kw:
        assert sorted(fast.train_seen.unique()) == [0, 1]


def test_reference_refuses_what_it_does_not_implement():
    from dslearn.errors import ConfigError

    for model, kw, field in (("gp_adaptive", {}, "model.noise"),
                             ("gp_sgpr", {}, "model: the reference implementation supports the exact and window GPs"),
                             ("gp_increment", {"filter": "ukf"}, "filter.predict")):
        with pytest.raises(ConfigError, match=field):
            ReferenceYu.from_config(_cfg(model, "hybrid", **kw)).run()


# --- the reference's own pieces against values by hand --------------------------------------------------------
def test_reference_weights_by_hand():
    """Edges 0-1, 1-2, 1-3, 2-3 (degrees 1, 3, 2, 2)."""
    adj = torch.zeros(4, 4, dtype=torch.bool)
    for i, j in ((0, 1), (1, 2), (1, 3), (2, 3)):
        adj[i, j] = adj[j, i] = True
    t = 1 / 3
    expected = {
        "uniform": [[1 / 2, 1 / 2, 0, 0], [1 / 4] * 4, [0, t, t, t], [0, t, t, t]],
        "metropolis": [[3 / 4, 1 / 4, 0, 0], [1 / 4] * 4, [0, 1 / 4, 5 / 12, t], [0, 1 / 4, t, 5 / 12]],
        "max_degree": [[3 / 4, 1 / 4, 0, 0], [1 / 4] * 4, [0, 1 / 4, 1 / 2, 1 / 4], [0, 1 / 4, 1 / 4, 1 / 2]],
        "half_max_degree": [[5 / 6, 1 / 6, 0, 0], [1 / 6, 1 / 2, 1 / 6, 1 / 6], [0, 1 / 6, 2 / 3, 1 / 6], [0, 1 / 6, 1 / 6, 2 / 3]],
    }
    for rule, w in expected.items():
        assert torch.allclose(torch.tensor(reference_weights(adj, rule), dtype=D), torch.tensor(w, dtype=D), atol=1e-15), rule


def test_fast_weights_equal_reference_weights_on_the_study_network():
    from dslearn.compose import build_network
    from dslearn.fusion.weights import consensus_weights

    network = build_network(_cfg("lin", "hybrid"))
    for rule in ("uniform", "metropolis", "max_degree", "half_max_degree"):
        ref = torch.tensor(reference_weights(network.adjacency, rule), dtype=D)
        assert torch.allclose(consensus_weights(network.adjacency, rule), ref, atol=1e-14), rule


def test_reference_rounds_by_hand():
    """Two nodes linked, uniform weights (1/2 each): one round averages; L = 2 rounds of a
    hybrid fusion with omega = 2 give q = mean(q^-) + 2 mean(dq)."""
    adj = torch.tensor([[0, 1], [1, 0]], dtype=torch.bool)
    f = ReferenceFusion("hybrid", adj, "uniform", 2, 2.0)
    q, o = f([torch.tensor([1.0], dtype=D), torch.tensor([3.0], dtype=D)], [torch.eye(1, dtype=D)] * 2,
             [torch.tensor([4.0], dtype=D), torch.zeros(1, dtype=D)], [torch.eye(1, dtype=D), torch.zeros(1, 1, dtype=D)])
    assert [float(v) for v in q] == [2.0 + 2 * 2.0] * 2 and [float(m) for m in o] == [1.0 + 2 * 0.5] * 2


def test_reference_initial_belief_by_hand():
    """One target, area [0, 8]^2 (prior at (4.5, 4)), sigma = 0.2, dt = 0.25, prior std 10 / 5: node 0
    saw the target at t = 0, 1, node 1 did not; individual fusion. Per coordinate the posterior
    is the information-weighted mean of prior and pseudo-measurement."""
    meas = torch.zeros(2, 1, 2, 1, 2, dtype=D)
    meas[0, 0, 0, 0] = torch.tensor([1.0, 2.0])
    meas[0, 0, 1, 0] = torch.tensor([1.5, 1.0])
    visible = torch.zeros(2, 1, 2, 1, dtype=torch.bool)
    visible[0] = True
    adj = torch.tensor([[0, 1], [1, 0]], dtype=torch.bool)
    means, infos = reference_initial_belief(meas, visible, 0, 0.2, 0.25, (0, 8, 0, 8), ReferenceFusion("individual", adj),
                                            pos_std=10.0, vel_std=5.0)
    prior_info = torch.tensor([1 / 100, 1 / 100, 1 / 25, 1 / 25], dtype=D)
    obs_info = torch.tensor([25.0, 25.0, 0.0625 / 0.08, 0.0625 / 0.08], dtype=D)
    prior = torch.tensor([4.5, 4.0, 0.0, 0.0], dtype=D)
    pseudo = torch.tensor([1.0, 2.0, 2.0, -4.0], dtype=D)
    post = (prior_info * prior + obs_info * pseudo) / (prior_info + obs_info)
    assert torch.allclose(means[0], post, atol=1e-12) and torch.allclose(infos[0], torch.diag(prior_info + obs_info), atol=1e-12)
    assert torch.allclose(means[1], prior, atol=1e-12) and torch.allclose(infos[1], torch.diag(prior_info), atol=1e-15)


def test_reference_metrics_by_hand():
    """One node, one episode, one target, K = 2: errors (3, 4, 0, 0) then (0, 0, 1, 0), information I."""
    truth = torch.zeros(1, 3, 4, dtype=D)
    means = torch.zeros(1, 1, 3, 4, dtype=D)
    means[0, 0, 1] = torch.tensor([3.0, 4.0, 0.0, 0.0])
    means[0, 0, 2] = torch.tensor([0.0, 0.0, 1.0, 0.0])
    infos = torch.eye(4, dtype=D).expand(1, 1, 3, 4, 4)
    m = reference_tracking_metrics(means, infos, truth)
    assert m["track_err"] == [[2.5]] and m["track_rmse"] == [[math.sqrt(12.5)]] and m["nees"] == [[(25 + 1) / 2 / 4]]


def test_compare_results_flags_a_wrong_value_and_a_wrong_label():
    from dslearn import api

    fast = api.build_study(_cfg("lin", "individual")).run()
    ref = fast.copy()
    ref.loc[5, "value"] = ref.loc[5, "value"] * (1 + 10 * REFERENCE_TOL) + 10 * REFERENCE_TOL
    assert compare_results(fast, ref)["max_diff"] > REFERENCE_TOL
    ref = fast.copy()
    ref.loc[3, "node"] = "comm9"
    r = compare_results(fast, ref)
    assert r["max_diff"] == math.inf and "node" in r["worst"]
