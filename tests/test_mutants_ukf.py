"""dslearn/filters/ukf.py against an independent unscented transform written out here: the defaults
(alpha, beta, kappa) = (1, 2, 0), the per-node route (node dimension first, the prior covariance
repeated per sigma point), ctx.cov at the sigma points and in noise_cov, several batch dimensions,
the belief's dtype, and the Dx + lambda refusal (benchmarks/mutation: survivors of the mutation run)."""

import math

import pytest
import torch

from dslearn.errors import ConfigError
from dslearn.filters.ukf import check_unscented, sigma_points, ukf_predict, unscented_weights
from dslearn.models.base import MotionModel
from dslearn.types import StepContext

D = torch.float64
CTX = StepContext(dt=0.25)
S, DX = 2, 4


def spd(n, *batch, seed=0):
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(*batch, n, n, generator=g, dtype=D)
    return a @ a.transpose(-1, -2) / n + 0.5 * torch.eye(n, dtype=D)


def randn(*shape, seed=1):
    return torch.randn(*shape, generator=torch.Generator().manual_seed(seed), dtype=D)


SCALE = torch.tensor([0.1, -0.2], dtype=D)  # per node


def f_ref(x, node_cov, node):
    """The test models' motion, written out: x + a_s sin(x) + 0.05 diag(P) (P the prior covariance)."""
    return x + SCALE[node] * torch.sin(x) + 0.05 * node_cov.diagonal(dim1=-2, dim2=-1)


def q_ref(P):
    return 0.01 * torch.eye(P.shape[-1], dtype=P.dtype) + 0.1 * P


class _NodeFirst(MotionModel):
    """Node ``s``'s queries are ``x[s]``; insists on ``(S, N, Dx)`` queries with ``ctx.cov (S, N, Dx, Dx)``,
    one prior covariance per query."""

    state_dim = DX

    def forward(self, x, ctx):
        assert x.ndim == 3 and x.shape[0] == S and ctx.cov.shape == (*x.shape, DX), (x.shape, ctx.cov.shape)
        return torch.stack([f_ref(x[s], ctx.cov[s], s) for s in range(S)])

    def noise_cov(self, x, ctx):
        return q_ref(ctx.cov)


class PerNode(_NodeFirst):
    """Per node by its ``num_nodes`` class attribute (not learnable)."""

    num_nodes = S


class Learnable(_NodeFirst):
    """Per node because it learns (no ``num_nodes``)."""

    def __init__(self):
        super().__init__()
        self.learnable = True


class Parametric(MotionModel):
    """A broadcasting model (sigma dimension first) that reads the prior covariance at every sigma
    point and keeps its noise in float64 whatever the belief's dtype."""

    state_dim = DX

    def forward(self, x, ctx):  # x (K, *B, Dx), ctx.cov (*B, Dx, Dx)
        assert ctx.cov.shape == (*x.shape[1:], DX)
        return x + 0.1 * torch.sin(x) + 0.05 * ctx.cov.diagonal(dim1=-2, dim2=-1)

    def noise_cov(self, x, ctx):
        return q_ref(ctx.cov).to(D)


def unscented_ref(m, P, f, alpha=1.0, beta=2.0, kappa=0.0):
    """The scaled unscented transform, point by point (float64, one belief ``m (Dx,)``, ``P``)."""
    n = m.shape[-1]
    c = alpha**2 * (n + kappa)
    L = torch.linalg.cholesky(P)
    pts = [m] + [m + math.sqrt(c) * L[:, i] for i in range(n)] + [m - math.sqrt(c) * L[:, i] for i in range(n)]
    wm = [(c - n) / c] + [0.5 / c] * (2 * n)
    wc = [wm[0] + 1 - alpha**2 + beta] + wm[1:]
    ys = [f(p) for p in pts]
    y = sum(w * v for w, v in zip(wm, ys))
    cov = sum(w * torch.outer(v - y, v - y) for w, v in zip(wc, ys))
    cross = sum(w * torch.outer(p - m, v - y) for w, p, v in zip(wc, pts, ys))
    return y, cov, cross


def test_sigma_point_defaults_closed_form():
    """alpha = 1, beta = 2, kappa = 0: points at +-sqrt(Dx) along the Cholesky columns, w^m_0 = 0, w^c_0 = 2."""
    m, P = randn(3, DX), spd(DX, 3)
    pts, wm, wc = sigma_points(m, P)
    L = torch.linalg.cholesky(P)
    off = math.sqrt(DX) * L.transpose(-1, -2)
    torch.testing.assert_close(pts, torch.cat([m[:, None], m[:, None] + off, m[:, None] - off], -2),
                               rtol=1e-14, atol=1e-14)
    assert float(wm[0]) == 0.0 and float(wc[0]) == 2.0
    assert torch.equal(wm[1:], torch.full((2 * DX,), 1 / (2 * DX), dtype=D)) and torch.equal(wc[1:], wm[1:])


@pytest.mark.parametrize("params", [{}, {"alpha": 0.7, "beta": 0.5, "kappa": 1.0}])
def test_prediction_equals_pointwise_unscented_transform(params):
    """Per-node and broadcasting models, the defaults and other parameters, against unscented_ref."""
    m, P = randn(S, 3, DX), spd(DX, S, 3)
    for model in (PerNode(), Parametric()):
        y, q, o, P_pred, F, Q = ukf_predict(m, torch.linalg.inv(P), model, CTX, full=True, **params)
        for s in range(S):
            for b in range(3):
                node = s if isinstance(model, PerNode) else None
                f = (lambda x: f_ref(x, P[s, b], s)) if node is not None else (
                    lambda x: x + 0.1 * torch.sin(x) + 0.05 * P[s, b].diagonal())
                y_r, cov_r, cross_r = unscented_ref(m[s, b], P[s, b], f, **params)
                tol = dict(rtol=1e-9, atol=1e-9)
                torch.testing.assert_close(y[s, b], y_r, **tol)
                torch.testing.assert_close(Q[s, b], q_ref(P[s, b]), **tol)
                torch.testing.assert_close(P_pred[s, b], cov_r + q_ref(P[s, b]), **tol)
                torch.testing.assert_close(F[s, b], cross_r.T @ torch.linalg.inv(P[s, b]), **tol)
                torch.testing.assert_close(o[s, b] @ P_pred[s, b], torch.eye(DX, dtype=D), **tol)


def test_which_models_get_node_first_queries():
    """Learnable models and models with a ``num_nodes`` class attribute are per node (their forward
    asserts (S, N, Dx)); both give the same prediction."""
    m, omega = randn(S, 3, DX), torch.linalg.inv(spd(DX, S, 3))
    learnable = Learnable()
    assert not hasattr(type(learnable), "num_nodes") and learnable.learnable and not PerNode().learnable
    a = ukf_predict(m, omega, PerNode(), CTX, full=True)
    b = ukf_predict(m, omega, learnable, CTX, full=True)
    assert all(torch.equal(x, z) for x, z in zip(a, b))


@pytest.mark.parametrize("model", [PerNode(), Parametric()], ids=["per_node", "parametric"])
def test_several_batch_dims_equal_the_flattened_batch(model):
    """(S, B1, B2, Dx) beliefs: every sigma point stays with its node and episode."""
    m, P = randn(S, 2, 3, DX), spd(DX, S, 2, 3)
    out = ukf_predict(m, torch.linalg.inv(P), model, CTX, full=True)
    flat = ukf_predict(m.reshape(S, 6, DX), torch.linalg.inv(P).reshape(S, 6, DX, DX), model, CTX, full=True)
    for a, b in zip(out, flat):
        assert a.shape[:3] == (S, 2, 3)
        torch.testing.assert_close(a.reshape(b.shape), b, rtol=1e-12, atol=1e-12)


def test_outputs_in_the_belief_dtype():
    """A model whose noise is float64 does not promote a float32 belief."""
    m, P = randn(S, 3, DX), spd(DX, S, 3)
    out = ukf_predict(m.float(), torch.linalg.inv(P).float(), Parametric(), CTX, full=True)
    ref = ukf_predict(m, torch.linalg.inv(P), Parametric(), CTX, full=True)
    for a, b in zip(out, ref):
        assert a.dtype == torch.float32
        torch.testing.assert_close(a.double(), b, rtol=1e-3, atol=1e-3 * (1 + float(b.abs().max())))


def test_unscented_weights_refuse_a_non_positive_scale():
    """Dx + lambda = alpha^2 (Dx + kappa) <= 0 is refused by the weights themselves, naming the key and
    the value of alpha^2 (Dx + kappa)."""
    with pytest.raises(ConfigError, match=r"^filter\.predict\.kappa=-10\.0 with state dimension Dx=8 .* = -0\.5; "
                                          r"it must be > 0: use filter\.predict\.kappa > -8$"):
        unscented_weights(8, 0.5, 2.0, -10.0)
    with pytest.raises(ConfigError, match=r"= -0\.5; it must be > 0"):
        check_unscented(0.5, 2.0, -10.0, 8)
    wm, wc, c = unscented_weights(8, 0.5, 2.0, -7.0)  # Dx + kappa = 1 > 0: legal
    assert c == 0.25 and float(wm[0]) == pytest.approx(1 - 8 / 0.25)
