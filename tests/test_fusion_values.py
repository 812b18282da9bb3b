"""Fusion strategies and consensus weight rules checked entry by entry against hand computations.

The graphs have unequal degrees, so the paper's uniform weights are row- but not column-stochastic
and not symmetric: a transposed weight matrix, a missing round or a mixed-in prior changes the
result. The references below run the consensus rounds ``y_i <- sum_j w_ij y_j`` with explicit loops
over rounds and nodes (never ``mix`` or ``matrix_power`` of the code under test), and the weight
matrices are written out as fractions.
"""

import pytest
import torch

from dslearn.fusion.faults import FaultyFusion, draw_live_graph, live_weights
from dslearn.fusion.strategies import make_fusion, mix
from dslearn.fusion.weights import consensus_weights, half_max_degree, max_degree, metropolis, uniform
from dslearn.network import adjacency_from_edges

D = torch.float64

# star + tail: 0 is linked to 1, 2, 3 and 3 to 4; degrees (3, 1, 1, 2, 1), d_max = 3
STAR_TAIL = adjacency_from_edges(5, [[0, 1], [0, 2], [0, 3], [3, 4]])
# path 0 - 1 - 2 - 3; degrees (1, 2, 2, 1), d_max = 2
PATH = adjacency_from_edges(4, [[0, 1], [1, 2], [2, 3]])

# the weight rules on STAR_TAIL, by hand
STAR_TAIL_RULES = {
    # 1 / (|N_i| + 1) on N_i and i
    "uniform": [[1 / 4, 1 / 4, 1 / 4, 1 / 4, 0],
                [1 / 2, 1 / 2, 0, 0, 0],
                [1 / 2, 0, 1 / 2, 0, 0],
                [1 / 3, 0, 0, 1 / 3, 1 / 3],
                [0, 0, 0, 1 / 2, 1 / 2]],
    # 1 / (1 + max(d_i, d_j)): 1/4 on node 0's links, 1/3 on 3-4; the rest on the diagonal
    "metropolis": [[1 / 4, 1 / 4, 1 / 4, 1 / 4, 0],
                   [1 / 4, 3 / 4, 0, 0, 0],
                   [1 / 4, 0, 3 / 4, 0, 0],
                   [1 / 4, 0, 0, 5 / 12, 1 / 3],
                   [0, 0, 0, 1 / 3, 2 / 3]],
    # 1 / (1 + d_max) = 1/4 on every link
    "max_degree": [[1 / 4, 1 / 4, 1 / 4, 1 / 4, 0],
                   [1 / 4, 3 / 4, 0, 0, 0],
                   [1 / 4, 0, 3 / 4, 0, 0],
                   [1 / 4, 0, 0, 1 / 2, 1 / 4],
                   [0, 0, 0, 1 / 4, 3 / 4]],
    # 1 / (2 d_max) = 1/6 on every link
    "half_max_degree": [[1 / 2, 1 / 6, 1 / 6, 1 / 6, 0],
                        [1 / 6, 5 / 6, 0, 0, 0],
                        [1 / 6, 0, 5 / 6, 0, 0],
                        [1 / 6, 0, 0, 2 / 3, 1 / 6],
                        [0, 0, 0, 1 / 6, 5 / 6]],
}

# the weight rules on PATH, by hand
PATH_RULES = {
    "uniform": [[1 / 2, 1 / 2, 0, 0],
                [1 / 3, 1 / 3, 1 / 3, 0],
                [0, 1 / 3, 1 / 3, 1 / 3],
                [0, 0, 1 / 2, 1 / 2]],
    "metropolis": [[2 / 3, 1 / 3, 0, 0],
                   [1 / 3, 1 / 3, 1 / 3, 0],
                   [0, 1 / 3, 1 / 3, 1 / 3],
                   [0, 0, 1 / 3, 2 / 3]],
    "max_degree": [[2 / 3, 1 / 3, 0, 0],
                   [1 / 3, 1 / 3, 1 / 3, 0],
                   [0, 1 / 3, 1 / 3, 1 / 3],
                   [0, 0, 1 / 3, 2 / 3]],
    "half_max_degree": [[3 / 4, 1 / 4, 0, 0],
                        [1 / 4, 1 / 2, 1 / 4, 0],
                        [0, 1 / 4, 1 / 2, 1 / 4],
                        [0, 0, 1 / 4, 3 / 4]],
}

# a hand-written row-stochastic, non-symmetric, not column-stochastic matrix on PATH
PATH_SKEWED = [[0.7, 0.3, 0, 0],
               [0.2, 0.5, 0.3, 0],
               [0, 0.6, 0.1, 0.3],
               [0, 0, 0.45, 0.55]]

RULES = {"uniform": uniform, "metropolis": metropolis, "max_degree": max_degree, "half_max_degree": half_max_degree}


def _t(rows):
    return torch.tensor(rows, dtype=D)


# --- hand references: explicit loops over rounds and nodes ----------------------------------------------


def rounds_by_loops(w, values, rounds):
    """``rounds`` times ``y_i <- sum_j w[i][j] y_j``; ``values``: one tensor per node."""
    y = list(values)
    s = len(y)
    for _ in range(rounds):
        y = [sum(float(w[i][j]) * y[j] for j in range(s)) for i in range(s)]
    return y


def power_by_loops(w, rounds):
    """``W^L`` as nested lists by scalar loops (for the per-episode ``wl`` argument)."""
    s = len(w)
    p = [[1.0 if i == j else 0.0 for j in range(s)] for i in range(s)]
    for _ in range(rounds):
        p = [[sum(float(w[i][k]) * p[k][j] for k in range(s)) for j in range(s)] for i in range(s)]
    return p


def fused_by_hand(name, w, rounds, omega, qp, op, dq, do):
    """One episode's fused pair at every node: ``qp, dq`` lists of (Dx,), ``op, do`` lists of (Dx, Dx)."""
    s = len(qp)
    if name == "individual":
        return [qp[i] + dq[i] for i in range(s)], [op[i] + do[i] for i in range(s)]
    if name == "centralized":
        sq, so = sum(dq), sum(do)
        return [qp[i] + sq for i in range(s)], [op[i] + so for i in range(s)]
    if name == "cm":
        mq, mo = rounds_by_loops(w, dq, rounds), rounds_by_loops(w, do, rounds)
        return [qp[i] + omega * mq[i] for i in range(s)], [op[i] + omega * mo[i] for i in range(s)]
    if name == "ci":
        return (rounds_by_loops(w, [qp[i] + dq[i] for i in range(s)], rounds),
                rounds_by_loops(w, [op[i] + do[i] for i in range(s)], rounds))
    if name == "hybrid":
        pq, po = rounds_by_loops(w, qp, rounds), rounds_by_loops(w, op, rounds)
        mq, mo = rounds_by_loops(w, dq, rounds), rounds_by_loops(w, do, rounds)
        return [pq[i] + omega * mq[i] for i in range(s)], [po[i] + omega * mo[i] for i in range(s)]
    if name == "ce":
        o_loc = [op[i] + do[i] for i in range(s)]
        est = [torch.linalg.solve(o_loc[i], qp[i] + dq[i]) for i in range(s)]
        avg = rounds_by_loops(w, est, rounds)
        return [o_loc[i] @ avg[i] for i in range(s)], o_loc
    raise AssertionError(name)


def beliefs(s, b=2, dx=4, seed=0):
    """Distinct random priors ``(q, Omega)`` (SPD) and novel information (PSD, rank 2) per node and episode."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(s, b, dx, dx, generator=g, dtype=D)
    o_pred = a @ a.transpose(-1, -2) + 0.5 * torch.eye(dx, dtype=D)
    h = torch.randn(s, b, 2, dx, generator=g, dtype=D)
    d_o = h.transpose(-1, -2) @ h  # H^T R^-1 H with R = I
    q_pred = 3.0 * torch.randn(s, b, dx, generator=g, dtype=D)
    d_q = torch.randn(s, b, dx, generator=g, dtype=D)
    return q_pred, o_pred, d_q, d_o


def _per_episode(x, e):
    return [x[i, e] for i in range(x.shape[0])]


def _check_against_hand(name, ws, rounds, omega_value, args, q, o):
    """``ws``: one hand weight matrix per episode."""
    qp, op, dq, do = args
    for e, w in enumerate(ws):
        eq, eo = fused_by_hand(name, w, rounds, omega_value, *(_per_episode(x, e) for x in (qp, op, dq, do)))
        torch.testing.assert_close(q[:, e], torch.stack(eq), rtol=1e-11, atol=1e-11)
        torch.testing.assert_close(o[:, e], torch.stack(eo), rtol=1e-11, atol=1e-11)


# --- fusion strategies by value -------------------------------------------------------------------------

STRATEGIES = [("individual", "one"), ("centralized", "one"), ("ce", "one"), ("cm", "one"), ("cm", "nodes"),
              ("ci", "one"), ("hybrid", "one"), ("hybrid", "nodes")]
WEIGHTS = {"star_tail_uniform": STAR_TAIL_RULES["uniform"], "path_skewed": PATH_SKEWED}


@pytest.mark.parametrize("rounds", [1, 2, 3])
@pytest.mark.parametrize("weights", list(WEIGHTS))
@pytest.mark.parametrize("name,omega", STRATEGIES)
def test_fusion_equals_hand_rounds(name, omega, weights, rounds):
    """Every strategy on a non-symmetric row-stochastic matrix, L = 1, 2, 3, against loops by hand."""
    w = WEIGHTS[weights]
    s = len(w)
    for dx, b in ((4, 2), (8, 1)):
        args = beliefs(s, b, dx, seed=10 * rounds + dx)
        q, o = make_fusion(name, _t(w), rounds, omega)(*args)
        assert q.shape == (s, b, dx) and o.shape == (s, b, dx, dx)
        _check_against_hand(name, [w] * b, rounds, 1.0 if omega == "one" else float(s), args, q, o)


def test_hand_weights_are_not_symmetric():
    """The premise of the tests above: their matrices are row- but not column-stochastic."""
    for w in WEIGHTS.values():
        wt = _t(w)
        torch.testing.assert_close(wt.sum(1), torch.ones(len(w), dtype=D), rtol=0, atol=1e-15)
        assert (wt.sum(0) - 1).abs().max() > 0.1


@pytest.mark.parametrize("rounds", [1, 3])
@pytest.mark.parametrize("name,omega", [("ce", "one"), ("cm", "nodes"), ("ci", "one"), ("hybrid", "nodes")])
def test_per_episode_weights_equal_hand_rounds(name, omega, rounds):
    """A ``(B, S, S)`` ``wl`` (one W^L per episode, as on a faulty network) mixes episode by episode."""
    ws = [STAR_TAIL_RULES["uniform"], STAR_TAIL_RULES["metropolis"], STAR_TAIL_RULES["half_max_degree"]]
    s, b = 5, len(ws)
    args = beliefs(s, b, 4, seed=3)
    wl = torch.stack([_t(power_by_loops(w, rounds)) for w in ws])
    # the nominal W^L (uniform weights, 7 rounds) must be ignored when wl is given
    fusion = make_fusion(name, _t(STAR_TAIL_RULES["uniform"]), 7, omega)
    q, o = fusion(*args, wl=wl)
    _check_against_hand(name, ws, rounds, 1.0 if omega == "one" else float(s), args, q, o)


def test_mix_with_per_episode_weights_equals_hand_rounds():
    ws = [PATH_SKEWED, PATH_RULES["uniform"]]
    y = torch.randn(4, 2, 3, 3, generator=torch.Generator().manual_seed(2), dtype=D)
    out = mix(torch.stack([_t(w) for w in ws]), y)
    for e, w in enumerate(ws):
        torch.testing.assert_close(out[:, e], torch.stack(rounds_by_loops(w, _per_episode(y, e), 1)),
                                   rtol=1e-13, atol=1e-13)


# --- weight rules entry by entry ------------------------------------------------------------------------


@pytest.mark.parametrize("graph,table", [(STAR_TAIL, STAR_TAIL_RULES), (PATH, PATH_RULES)], ids=["star_tail", "path"])
@pytest.mark.parametrize("rule", list(RULES))
def test_weight_rules_entry_by_entry(graph, table, rule):
    expected = _t(table[rule])
    torch.testing.assert_close(RULES[rule](graph), expected, rtol=0, atol=1e-15)
    torch.testing.assert_close(consensus_weights(graph, rule), expected, rtol=0, atol=1e-15)


# live graphs of STAR_TAIL, by hand. Link 0-3 down: 0-1, 0-2 and 3-4 remain, degrees (2, 1, 1, 1, 1).
LINK_03_DOWN = {
    "metropolis": [[1 / 3, 1 / 3, 1 / 3, 0, 0],
                   [1 / 3, 2 / 3, 0, 0, 0],
                   [1 / 3, 0, 2 / 3, 0, 0],
                   [0, 0, 0, 1 / 2, 1 / 2],
                   [0, 0, 0, 1 / 2, 1 / 2]],
    "uniform": [[1 / 3, 1 / 3, 1 / 3, 0, 0],
                [1 / 2, 1 / 2, 0, 0, 0],
                [1 / 2, 0, 1 / 2, 0, 0],
                [0, 0, 0, 1 / 2, 1 / 2],
                [0, 0, 0, 1 / 2, 1 / 2]],
}
# node 3 failed: 0-1 and 0-2 remain, 3 and 4 are cut off and keep their own beliefs
NODE_3_DOWN = {
    "metropolis": [[1 / 3, 1 / 3, 1 / 3, 0, 0],
                   [1 / 3, 2 / 3, 0, 0, 0],
                   [1 / 3, 0, 2 / 3, 0, 0],
                   [0, 0, 0, 1, 0],
                   [0, 0, 0, 0, 1]],
    "uniform": [[1 / 3, 1 / 3, 1 / 3, 0, 0],
                [1 / 2, 1 / 2, 0, 0, 0],
                [1 / 2, 0, 1 / 2, 0, 0],
                [0, 0, 0, 1, 0],
                [0, 0, 0, 0, 1]],
}
# node 0 failed: only 3-4 remains
NODE_0_DOWN = {
    "metropolis": [[1, 0, 0, 0, 0],
                   [0, 1, 0, 0, 0],
                   [0, 0, 1, 0, 0],
                   [0, 0, 0, 1 / 2, 1 / 2],
                   [0, 0, 0, 1 / 2, 1 / 2]],
}
NODE_0_DOWN["uniform"] = NODE_0_DOWN["metropolis"]


@pytest.mark.parametrize("method", ["metropolis", "uniform"])
def test_live_weights_under_failures_entry_by_entry(method):
    full = STAR_TAIL.clone()
    link_down = STAR_TAIL.clone()
    link_down[0, 3] = link_down[3, 0] = False
    live = torch.stack([full, link_down, torch.zeros(5, 5, dtype=torch.bool)])
    w = live_weights(live, method)
    torch.testing.assert_close(w[0], _t(STAR_TAIL_RULES[method]), rtol=0, atol=1e-15)
    torch.testing.assert_close(w[1], _t(LINK_03_DOWN[method]), rtol=0, atol=1e-15)
    torch.testing.assert_close(w[2], torch.eye(5, dtype=D), rtol=0, atol=0)  # no link works: W = I
    # failed nodes: draw_live_graph cuts their links, live_weights isolates them
    alive = torch.ones(3, 5, dtype=torch.bool)
    alive[1, 3] = False
    alive[2, 0] = False
    w = live_weights(draw_live_graph(STAR_TAIL, alive, 0.0, torch.Generator().manual_seed(0)), method)
    torch.testing.assert_close(w[0], _t(STAR_TAIL_RULES[method]), rtol=0, atol=1e-15)
    torch.testing.assert_close(w[1], _t(NODE_3_DOWN[method]), rtol=0, atol=1e-15)
    torch.testing.assert_close(w[2], _t(NODE_0_DOWN[method]), rtol=0, atol=1e-15)
    # every link down: identity
    w = live_weights(draw_live_graph(STAR_TAIL, alive, 1.0, torch.Generator().manual_seed(0)), method)
    torch.testing.assert_close(w, torch.eye(5, dtype=D).expand(3, 5, 5), rtol=0, atol=0)


@pytest.mark.parametrize("method", ["metropolis", "uniform"])
@pytest.mark.parametrize("name,omega", [("ci", "one"), ("hybrid", "nodes"), ("cm", "one"), ("ce", "one")])
def test_faulty_fusion_with_failed_nodes_equals_hand_rounds(name, omega, method):
    """FaultyFusion, no link failures, node 3 down in episode 1 and node 0 in episode 2, L = 2: every
    episode mixes with its own live weights (written out above)."""
    ws = [STAR_TAIL_RULES[method], NODE_3_DOWN[method], NODE_0_DOWN[method]]
    args = beliefs(5, 3, 4, seed=7)
    alive = torch.ones(5, 3, 1, dtype=torch.bool)
    alive[3, 1, 0] = False
    alive[0, 2, 0] = False
    # the base strategy's own (metropolis) weights must not be used: the live weights replace them
    ff = FaultyFusion(make_fusion(name, metropolis(STAR_TAIL), 2, omega), STAR_TAIL, 0.0, method)
    ff.begin(alive)
    q, o = ff(*args)
    _check_against_hand(name, ws, 2, 1.0 if omega == "one" else 5.0, args, q, o)
