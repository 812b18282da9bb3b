"""Property-based invariants (hypothesis): consensus weight rules and fusion strategies on random
connected graphs, and the exact online GP's inverse Cholesky factor over random appends.

Graphs are a random spanning tree (every node after the first, in a random order, links to an
earlier one) plus random extra edges, ``S`` in 2..8. Beliefs are random SPD information matrices
with eigenvalues over four decades and rank-deficient PSD novel information.
"""

import math

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dslearn.fusion.strategies import FUSIONS, make_fusion
from dslearn.fusion.weights import WEIGHT_METHODS, consensus_weights
from dslearn.models.gp_backends.exact import OnlineGP
from dslearn.network import is_connected

D = torch.float64
DOUBLY = [m for m in WEIGHT_METHODS if m != "uniform"]


@st.composite
def connected_graphs(draw, min_nodes=2, max_nodes=8):
    s = draw(st.integers(min_nodes, max_nodes))
    order = draw(st.permutations(range(s)))
    adj = torch.zeros(s, s, dtype=torch.bool)
    for k in range(1, s):
        p = draw(st.integers(0, k - 1))
        adj[order[k], order[p]] = adj[order[p], order[k]] = True
    pairs = [(i, j) for i in range(s) for j in range(i + 1, s)]
    extra = draw(st.lists(st.sampled_from(pairs), max_size=len(pairs)))
    for i, j in extra:
        adj[i, j] = adj[j, i] = True
    return adj


def spd(g, *batch, dx, decades=4.0):
    """Random SPD matrices with eigenvalues log-uniform over ``decades`` decades (from 10^-2)."""
    q, _ = torch.linalg.qr(torch.randn(*batch, dx, dx, generator=g, dtype=D))
    lam = 10.0 ** (-2.0 + decades * torch.rand(*batch, dx, generator=g, dtype=D))
    return (q * lam.unsqueeze(-2)) @ q.transpose(-1, -2)


def random_beliefs(seed, s, b, dx, rank):
    """Priors (q, Omega SPD) and novel information (dq, dOmega = H^T H of rank ``rank``), nodes first."""
    g = torch.Generator().manual_seed(seed)
    o_pred = spd(g, s, b, dx=dx)
    o_pred = 0.5 * (o_pred + o_pred.transpose(-1, -2))
    h = torch.randn(s, b, rank, dx, generator=g, dtype=D)
    return (torch.randn(s, b, dx, generator=g, dtype=D), o_pred,
            torch.randn(s, b, dx, generator=g, dtype=D), h.transpose(-1, -2) @ h)


def stationary(adj, rule):
    """Left Perron vector of the rule's matrix: 1/S for doubly stochastic rules; for the uniform
    rule W = (D + I)^-1 (A + I) (D: the degrees) is reversible with pi_i proportional to |N_i| + 1."""
    s = adj.shape[0]
    if rule == "uniform":
        p = (adj.sum(1) + 1).to(D)
        return p / p.sum()
    return torch.full((s,), 1.0 / s, dtype=D)


# --- weight rules -----------------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None, database=None)
@given(adj=connected_graphs(), rule=st.sampled_from(WEIGHT_METHODS))
def test_weight_rules_are_stochastic_and_live_on_the_graph(adj, rule):
    s = adj.shape[0]
    w = consensus_weights(adj, rule)
    ones = torch.ones(s, dtype=D)
    assert w.dtype == D and w.shape == (s, s)
    torch.testing.assert_close(w.sum(1), ones, rtol=0, atol=1e-14)
    assert (w >= 0).all()
    support = adj | torch.eye(s, dtype=torch.bool)
    assert (w[~support] == 0).all()  # nothing off the graph
    assert (w[support] > 0).all()  # every link and every self-weight used: consensus on a connected graph converges
    if rule == "uniform":
        # equal weight on N_i and i, so the rows are constant on their support
        for i in range(s):
            row = w[i][support[i]]
            torch.testing.assert_close(row, torch.full_like(row, 1.0 / int(support[i].sum())), rtol=0, atol=1e-15)
    else:
        torch.testing.assert_close(w.sum(0), ones, rtol=0, atol=1e-14)
        assert torch.equal(w, w.T)
    # the left Perron vector: pi^T W = pi^T
    pi = stationary(adj, rule)
    torch.testing.assert_close(pi @ w, pi, rtol=0, atol=1e-15)


@settings(max_examples=40, deadline=None, database=None)
@given(adj=connected_graphs(), rule=st.sampled_from(WEIGHT_METHODS))
def test_many_rounds_reach_the_stationary_weighting(adj, rule):
    """W^L -> 1 pi^T on a connected graph: the plain average for doubly stochastic rules, the
    (|N_i| + 1)-weighted one for the uniform rule."""
    assert is_connected(adj)
    w = consensus_weights(adj, rule)
    wl = torch.linalg.matrix_power(w, 100_000)
    pi = stationary(adj, rule)
    torch.testing.assert_close(wl, pi.expand_as(wl), rtol=0, atol=1e-10)


# --- fusion strategies -----------------------------------------------------------------------------------


@settings(max_examples=40, deadline=None, database=None)
@given(adj=connected_graphs(), rule=st.sampled_from(WEIGHT_METHODS), name=st.sampled_from(FUSIONS),
       rounds=st.integers(0, 5), omega=st.sampled_from(["one", "nodes", 0.3]), dx=st.integers(1, 6),
       rank=st.integers(0, 3), seed=st.integers(0, 2**31 - 1))
def test_fused_information_is_symmetric_positive_definite(adj, rule, name, rounds, omega, dx, rank, seed):
    """Every strategy keeps the information matrix symmetric and at least as large (Loewner order) as
    the smallest prior one: each fused matrix is a convex combination of priors plus PSD terms."""
    s = adj.shape[0]
    qp, op, dq, do = random_beliefs(seed, s, 2, dx, rank)
    q, o = make_fusion(name, consensus_weights(adj, rule), rounds, omega)(qp, op, dq, do)
    assert q.shape == (s, 2, dx) and o.shape == (s, 2, dx, dx)
    assert torch.isfinite(q).all()
    assert torch.equal(o, o.transpose(-1, -2))
    floor = float(torch.linalg.eigvalsh(op).min())
    assert float(torch.linalg.eigvalsh(o).min()) >= floor * (1 - 1e-9)


@settings(max_examples=40, deadline=None, database=None)
@given(adj=connected_graphs(), rule=st.sampled_from(WEIGHT_METHODS), omega=st.sampled_from(["one", "nodes"]),
       dx=st.integers(1, 4), seed=st.integers(0, 2**31 - 1))
def test_many_rounds_of_consensus_reach_the_weighted_average(adj, rule, omega, dx, seed):
    """L -> infinity: every node holds the pi-weighted averages (pi: :func:`stationary`)."""
    s = adj.shape[0]
    w = consensus_weights(adj, rule)
    om = 1.0 if omega == "one" else float(s)
    pi = stationary(adj, rule)
    qp, op, dq, do = random_beliefs(seed, s, 2, dx, 2)

    def avg(x):
        return torch.einsum("i,i...->...", pi, x).expand_as(x)

    o_loc, q_loc = op + do, qp + dq
    y_loc = torch.linalg.solve(o_loc, q_loc.unsqueeze(-1)).squeeze(-1)
    expected = {
        "ci": (avg(q_loc), avg(o_loc)),
        "hybrid": (avg(qp) + om * avg(dq), avg(op) + om * avg(do)),
        "cm": (qp + om * avg(dq), op + om * avg(do)),
        "ce": ((o_loc @ avg(y_loc).unsqueeze(-1)).squeeze(-1), o_loc),
    }
    for name, (eq, eo) in expected.items():
        q, o = make_fusion(name, w, 100_000, omega)(qp, op, dq, do)
        scale_q, scale_o = 1.0 + float(eq.abs().max()), 1.0 + float(eo.abs().max())
        torch.testing.assert_close(q, eq, rtol=0, atol=1e-9 * scale_q, msg=name)
        torch.testing.assert_close(o, eo, rtol=0, atol=1e-9 * scale_o, msg=name)
    if rule != "uniform" and omega == "nodes":  # doubly stochastic, omega = S: hybrid = centralised
        qc, oc = make_fusion("centralized", w, 0)(avg(qp), avg(op), dq, do)
        q, o = make_fusion("hybrid", w, 100_000, omega)(qp, op, dq, do)
        torch.testing.assert_close(q, qc, rtol=0, atol=1e-9 * (1.0 + float(qc.abs().max())))
        torch.testing.assert_close(o, oc, rtol=0, atol=1e-9 * (1.0 + float(oc.abs().max())))


# --- the exact online GP: inverse Cholesky factor = Cholesky factor = dense solve on the valid points -------

OUTPUTSCALE, LENGTHSCALE, NOISE = 1.1, 1.4, 0.3
# what happens to one node at one append
KINDS = ("valid", "masked", "x_nan", "x_inf", "y_nan", "y_inf")


def dense_gp(x, y, valid, xq, mean_identity, sf2, ls, noise_var):
    """The exact GP posterior on the valid points only, one node, by a dense solve:
    mean m(x*) + k*^T (K + s^2 I)^-1 (y - m(X)), latent variance k** - k*^T (K + s^2 I)^-1 k*, with
    k(a, b) = sf2 exp(-|a - b|^2 / 2 ls^2)."""
    def k(a, b):
        d2 = ((a.unsqueeze(-2) - b.unsqueeze(-3)) ** 2).sum(-1)
        return sf2 * torch.exp(-0.5 * d2 / ls ** 2)

    def m(a):
        return a[..., : y.shape[-1]] if mean_identity else torch.zeros(a.shape[0], y.shape[-1], dtype=D)

    xv, yv = x[valid], y[valid]
    prior_var = torch.full((xq.shape[0],), sf2, dtype=D)
    if xv.shape[0] == 0:
        return m(xq), prior_var
    kxx = k(xv, xv) + noise_var * torch.eye(xv.shape[0], dtype=D)
    ks = k(xv, xq)  # (n, N)
    mean = m(xq) + ks.T @ torch.linalg.solve(kxx, yv - m(xv))
    var = prior_var - (ks * torch.linalg.solve(kxx, ks)).sum(0)
    return mean, var


@settings(max_examples=30, deadline=None, database=None)
@given(nodes=st.integers(1, 3), dx=st.integers(1, 3), mean=st.sampled_from(["zero", "identity"]),
       steps=st.lists(st.tuples(st.lists(st.sampled_from(KINDS), min_size=3, max_size=3),
                                st.sampled_from(["none", "same", "other"])), min_size=1, max_size=24),
       seed=st.integers(0, 2**31 - 1))
def test_inverse_factor_equals_cholesky_and_the_dense_gp(nodes, dx, mean, steps, seed):
    """Random appends, each preceded by no prediction, one at the same input (whose solves the append
    reuses) or one elsewhere, with points left out by the mask or by non-finite inputs or outputs:
    both factor forms give the dense GP on the valid points, and the inverse factor is the inverse
    of the Cholesky one."""
    g = torch.Generator().manual_seed(seed)
    gps = [OnlineGP(nodes, dx, dx, outputscale=OUTPUTSCALE, lengthscale=LENGTHSCALE, noise_std=NOISE, mean=mean,
                    capacity=4, factor=f) for f in ("inverse", "cholesky")]
    xs, ys, oks = [], [], []
    for kinds, before in steps:
        x = 1.5 * torch.randn(nodes, dx, generator=g, dtype=D)
        y = x + 0.3 * torch.sin(x) + 0.1 * torch.randn(nodes, dx, generator=g, dtype=D)
        mask = torch.ones(nodes, dtype=torch.bool)
        for i, kind in enumerate(kinds[:nodes]):
            if kind == "masked":
                mask[i] = False
            elif kind != "valid":
                (x if kind[0] == "x" else y)[i, -1] = math.nan if kind.endswith("nan") else math.inf
        for gp in gps:
            if before == "same":
                gp.predict(x.unsqueeze(1))
            elif before == "other":
                gp.predict(torch.zeros(nodes, 1, dx, dtype=D))
            gp.append(x, y, mask)
        xs.append(x)
        ys.append(y)
        oks.append(mask & torch.isfinite(x).all(-1) & torch.isfinite(y).all(-1))
    inv, chol = gps
    n = len(steps)
    assert inv.inverse and not chol.inverse and inv.n == chol.n == n
    assert torch.equal(inv.mask[:, :n], torch.stack(oks, 1)) and torch.equal(chol.mask[:, :n], inv.mask[:, :n])
    M, L = inv.L[:, :n, :n], chol.L[:, :n, :n]
    assert torch.isfinite(M).all() and torch.isfinite(L).all()
    assert torch.equal(M, torch.tril(M))
    torch.testing.assert_close(M @ L, torch.eye(n, dtype=D).expand(nodes, n, n), rtol=0, atol=1e-10)
    xq = 1.5 * torch.randn(nodes, 5, dx, generator=g, dtype=D)
    X, Y, V = torch.stack(xs, 1), torch.stack(ys, 1), torch.stack(oks, 1)
    # the hyperparameters as stored (GPyTorch keeps them through a softplus, rounded in float32)
    sf2, ls, nv = (float(t[0]) for t in (inv.outputscale, inv.lengthscale, inv.noise_var))
    assert abs(sf2 - OUTPUTSCALE ** 2) < 1e-6 and abs(ls - LENGTHSCALE) < 1e-6 and abs(nv - NOISE ** 2) < 1e-6
    for gp in gps:
        mu, var, _ = gp.predict(xq)
        for s in range(nodes):
            em, ev = dense_gp(X[s], Y[s], V[s], xq[s], mean == "identity", sf2, ls, nv)
            torch.testing.assert_close(mu[s], em, rtol=0, atol=1e-9)
            torch.testing.assert_close(var[s], ev, rtol=0, atol=1e-9)
    torch.testing.assert_close(inv.alpha, chol.alpha, rtol=0, atol=1e-9)
