"""The GP averaged over a Gaussian belief (``OnlineGP.predict_belief``, ``GPMotionModel(inputs="belief")``):
expectations against Gauss-Hermite quadrature of the point prediction, the limits of a point and of a
diffuse belief, the exact posterior after appends that follow it, and the filter step it was made for
(an observed neighbour must not localise a target the node knows nothing about)."""

import numpy as np
import pytest
import torch

from dslearn.errors import ConfigError
from dslearn.filters.information import novel_information, predict
from dslearn.models.gp_backends.exact import OnlineGP
from dslearn.models.gp_backends.means import ConstantVelocityMean
from dslearn.models import ConstantVelocity, LinearPositionObservation
from dslearn.models.gp import GPMotionModel
from dslearn.types import StepContext, safe_cholesky

D64 = torch.float64


def _gp2(factor="auto", n=25, seed=0):
    """A 2-D-input GP (identity prior mean) with ``n`` points of a nonlinear map, two nodes."""
    g = torch.Generator().manual_seed(seed)
    gp = OnlineGP(2, 2, 2, outputscale=1.3, lengthscale=0.9, noise_std=0.2, mean="identity", factor=factor)
    X = 2.0 * torch.randn(2, n, 2, dtype=D64, generator=g)
    Y = X + torch.stack([torch.sin(X[..., 1]), 0.5 * torch.cos(X[..., 0]) * X[..., 1]], -1)
    for i in range(n):
        gp.append(X[:, i], Y[:, i])
    return gp


def _hermite_expectation(gp, x, P, deg=60):
    """E[mu(y)], E[d mu/dy], Cov(mu(y), y) P^-1 for y ~ N(x, P) by tensor Gauss-Hermite quadrature of
    the point prediction (``predict`` at every node), x (S, 1, 2), P (S, 1, 2, 2)."""
    t, w = np.polynomial.hermite.hermgauss(deg)
    tt = torch.tensor(np.stack(np.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2), dtype=D64)  # (G, 2)
    ww = torch.tensor(np.outer(w, w).reshape(-1) / np.pi, dtype=D64)  # (G,)
    L = torch.linalg.cholesky(P[:, 0])  # (S, 2, 2)
    dy = np.sqrt(2.0) * tt @ L.transpose(-1, -2)  # (S, G, 2)
    mu, _, jac = gp.predict(x + dy)  # (S, G, 2), (S, G, 2, 2)
    e_mu = (ww[:, None] * mu).sum(1)
    e_jac = (ww[:, None, None] * jac).sum(1)
    cov_mu_y = ((ww[:, None] * (mu - e_mu.unsqueeze(1))).unsqueeze(-1) * dy.unsqueeze(-2)).sum(1)  # (S, 2, 2)
    slr = cov_mu_y @ torch.linalg.inv(P[:, 0])
    return e_mu, e_jac, slr


@pytest.mark.parametrize("factor", ["inverse", "cholesky"])
def test_belief_mean_and_jacobian_are_the_expectations_over_the_belief(factor):
    gp = _gp2(factor)
    x = torch.tensor([[[0.3, -0.7]], [[1.1, 0.4]]], dtype=D64)
    A = torch.tensor([[[0.8, 0.3], [-0.2, 0.5]], [[1.4, 0.0], [0.6, 0.9]]], dtype=D64)
    P = (A @ A.transpose(-1, -2)).unsqueeze(1)  # correlated, std ~0.5-1.7 against l = 0.9
    mean, var, jac = gp.predict_belief(x, P)
    e_mu, e_jac, slr = _hermite_expectation(gp, x, P)
    torch.testing.assert_close(mean[:, 0], e_mu, rtol=0, atol=1e-9)
    torch.testing.assert_close(jac[:, 0], e_jac, rtol=0, atol=1e-8)  # E[d mu / dy]
    torch.testing.assert_close(jac[:, 0], slr, rtol=0, atol=1e-8)  # = Cov(mu, y) P^-1 (Stein)
    # the learned part is not negligible here: the averaged mean differs from the point mean
    assert (mean - gp.predict(x)[0]).abs().max() > 0.05
    # the variance is the latent variance at the mean
    torch.testing.assert_close(var, gp.predict(x, jacobian=False)[1], rtol=0, atol=1e-12)


def test_belief_limits_point_and_diffuse():
    gp = OnlineGP(3, 8, 8, 1.0, 2.0, 0.5, mean=ConstantVelocityMean(0.4))
    g = torch.Generator().manual_seed(3)
    X = torch.randn(3, 40, 8, dtype=D64, generator=g)
    for i in range(40):
        gp.append(X[:, i], X[:, i] @ ConstantVelocity(2).matrix(0.4).T + 0.3 * torch.tanh(X[:, i]))
    x = X[:, :4] + 0.1  # near the data: the learned part matters
    m0, v0, j0 = gp.predict(x)
    m1, v1, j1 = gp.predict_belief(x, torch.zeros(3, 4, 8, 8, dtype=D64))
    torch.testing.assert_close(m1, m0, rtol=0, atol=1e-12)
    torch.testing.assert_close(j1, j0, rtol=0, atol=1e-12)
    torch.testing.assert_close(v1, v0, rtol=0, atol=1e-12)
    F = ConstantVelocity(2).matrix(0.4)
    assert (m0 - x @ F.T).abs().max() > 0.1 and (j0 - F).abs().max() > 0.05
    # a belief of 1 km std knows nothing: the prior mean and its Jacobian, whatever the data near x
    m2, _, j2 = gp.predict_belief(x, 1e6 * torch.eye(8, dtype=D64).expand(3, 4, 8, 8))
    torch.testing.assert_close(m2, x @ F.T, rtol=0, atol=1e-9)
    torch.testing.assert_close(j2, F.expand(3, 4, 8, 8), rtol=0, atol=1e-9)
    # without data: the prior, variance sigma_f^2
    empty = OnlineGP(1, 8, 8, 1.3, 2.0, 0.5, mean=ConstantVelocityMean(0.4))
    m3, v3, j3 = empty.predict_belief(x[:1], torch.eye(8, dtype=D64).expand(1, 4, 8, 8))
    torch.testing.assert_close(m3, x[:1] @ F.T)
    torch.testing.assert_close(v3, torch.full((1, 4), 1.69, dtype=D64))


@pytest.mark.parametrize("factor", ["inverse", "cholesky"])
def test_appends_after_belief_predictions_give_the_exact_posterior(factor):
    """Algorithm 1 predicts at y^{t-1} over the belief, then appends at y^{t-1}: the reused solve must
    leave the exact GP posterior (alpha = (K + s^2 I)^-1 (Y - m(X)), built here by hand)."""
    g = torch.Generator().manual_seed(5)
    gp = OnlineGP(2, 3, 3, 1.1, 1.5, 0.3, mean="identity", factor=factor)
    X = torch.randn(2, 20, 3, dtype=D64, generator=g)
    Y = X + 0.4 * torch.sin(2 * X)
    for i in range(20):
        A = torch.randn(2, 3, 3, dtype=D64, generator=g)
        gp.predict_belief(X[:, i : i + 1], (0.2 * A @ A.transpose(-1, -2)).unsqueeze(1))
        gp.append(X[:, i], Y[:, i])
    # by hand with the hyperparameters as stored (GPyTorch keeps them through a float32 softplus)
    sf2, ls, s2 = (v.reshape(2, 1, 1) for v in (gp.outputscale, gp.lengthscale, gp.noise_var))
    d2 = ((X.unsqueeze(2) - X.unsqueeze(1)) ** 2).sum(-1)
    K = sf2 * torch.exp(-0.5 * d2 / ls**2) + s2 * torch.eye(20, dtype=D64)
    alpha = torch.linalg.solve(K, Y - X)
    torch.testing.assert_close(gp.alpha, alpha, rtol=1e-9, atol=1e-10)


def _interacting_gp(inputs: str) -> GPMotionModel:
    """Two agents; agent 1's next position depends on agent 0's position (slope 0.5 along x),
    data around the origin."""
    F = ConstantVelocity(2).matrix(0.4)
    model = GPMotionModel(8, 1, 1.0, 2.0, 0.1, mean=ConstantVelocityMean(0.4), inputs=inputs)
    g = torch.Generator().manual_seed(7)
    for _ in range(60):
        y = torch.randn(1, 8, dtype=D64, generator=g)
        y[:, 4] += 1.0  # agent 1 beside agent 0
        nxt = y @ F.T
        nxt[:, 4] += 0.5 * y[:, 0]
        model.add_data(y, nxt)
    return model


@pytest.mark.parametrize("inputs", ["mean", "belief"])
def test_an_observed_neighbour_does_not_localise_an_unknown_target(inputs):
    """A node knows agent 1 to 0.1 m and nothing about agent 0 (1 km, 1 km/s); it measures agent 1
    only. Linearised at the mean, the learned slope of agent 1's motion in agent 0's position is
    extrapolated over a kilometre and the measurement of agent 1 moves agent 0 by metres (the ETH
    divergence); averaged over the belief, agent 0 keeps its prior, as with any model without
    interaction (LIN), and agent 1's update is LIN-like."""
    model = _interacting_gp(inputs)
    mean = torch.zeros(1, 1, 8, dtype=D64)
    mean[..., 4] = 1.0
    std = torch.tensor([1e3, 1e3, 1e3, 1e3, 0.1, 0.1, 0.2, 0.2], dtype=D64)
    omega = torch.diag(std**-2).expand(1, 1, 8, 8).clone()
    ctx = StepContext(dt=0.4)
    y_pred, q_pred, o_pred = predict(mean, omega, model, ctx)
    obs = LinearPositionObservation(0.2)
    z = torch.tensor([[[[0.0, 0.0], [2.0, -0.2]]]], dtype=D64)  # agent 1 measured ~1 m off its prediction
    vis = torch.tensor([[[False, True]]])
    dq, do = novel_information(y_pred, z, vis, obs)
    o = o_pred + do
    y = torch.cholesky_solve((q_pred + dq).unsqueeze(-1), safe_cholesky(o)).squeeze(-1)
    moved = (y[0, 0, :2] - y_pred[0, 0, :2]).norm()
    if inputs == "mean":
        # the failure the belief average removes: innovation / slope, ~1.1 m / 0.73
        assert moved > 1.0
    else:
        assert moved < 1e-6
        # and agent 1 is updated like a CV model with the GP's variance as process noise
        _, var, _ = model.gp.predict(mean.reshape(1, 1, 8), jacobian=False)
        cv = ConstantVelocity(2, 1.0)
        P = torch.diag(std**2)
        F = cv.matrix(0.4)
        Pp = F @ P @ F.T + var[0, 0] * torch.eye(8, dtype=D64)
        S = Pp[4:6, 4:6] + 0.04 * torch.eye(2, dtype=D64)
        gain = Pp[4:6, 4:6] @ torch.linalg.inv(S)
        expect = (mean[0, 0] @ F.T)[4:6] + gain @ (z[0, 0, 1] - (mean[0, 0] @ F.T)[4:6])
        torch.testing.assert_close(y[0, 0, 4:6], expect, rtol=0, atol=1e-6)


def test_belief_option_is_checked():
    with pytest.raises(ConfigError, match=r"model\.inputs"):
        GPMotionModel(8, 1, inputs="sideways")
    with pytest.raises(ConfigError, match=r"model\.inputs=belief.*model\.variant=sgpr"):
        GPMotionModel(8, 1, inputs="belief", variant="sgpr", inducing=8)
    with pytest.raises(ConfigError, match=r"model\.jacobian=closed_form"):
        GPMotionModel(8, 1, inputs="belief", jacobian="autograd")
