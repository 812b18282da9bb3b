"""Filters against independent references (benchmarks/mutation: survivors of the mutation run): the GP-ADF
prediction's node-dimension refusal, the GP-Bayes helpers (Jacobian over several batch dimensions, the Kalman
gain of the Gaussian update with Cov[x, z] not square, the UKF's documented default (alpha, beta, kappa) =
(1, 0, 2)), the exact GP moments' noisy-target default and the RBPF resampling's time index."""

import math

import numpy as np
import pytest
import torch

from dslearn.filters.adf import adf_predict
from dslearn.filters.gp_bayes import AdditiveModel, gaussian_update, jacobian, ukf_step
from dslearn.filters.gp_moments import predictive_moments
from dslearn.filters.rbpf import RBPFState, resample
from dslearn.models import GPMotionModel
from dslearn.types import StepContext

D = torch.float64


# ------------------------------------------------------------------------------------------ adf
def test_adf_predict_refuses_a_node_dimension_not_first_naming_shape_and_nodes():
    """A belief batch whose first dimension is not the node count is refused with a message that says what
    was expected and gives the shape and S (the user's fix: put the node dimension first)."""
    s, dx = 2, 4
    model = GPMotionModel(dx, s, outputscale=0.6, lengthscale=0.9, noise_std=0.2, mean="identity", noise="latent")
    mean = torch.zeros(3, dx, dtype=D)  # 3 beliefs, no node dimension
    omega = torch.eye(dx, dtype=D).expand(3, dx, dx).clone()
    with pytest.raises(ValueError, match=r"node dimension first.*\(3, 4\).*S=2"):
        adf_predict(mean, omega, model, StepContext(dt=0.25))


# ------------------------------------------------------------------------------------------ gp_bayes
def test_jacobian_over_two_batch_dimensions_is_the_matrix_of_a_linear_map():
    """fn(v) = A v + sin(v_0) e_0 at x (2, 3, D): J = A + cos(x_0) e_0 e_0^T per entry, shape (2, 3, E, D)
    (closed form; the batch dimension of size 3 differs from D = 2)."""
    A = torch.tensor([[1.0, 2.0], [3.0, -1.0], [0.5, 4.0]], dtype=D)  # E = 3, D = 2

    def fn(v):
        return A @ v + torch.stack([torch.sin(v[0]), v[0] * 0, v[0] * 0])

    x = torch.randn(2, 3, 2, generator=torch.Generator().manual_seed(0), dtype=D)
    J = jacobian(fn, x)
    assert J.shape == (2, 3, 3, 2)
    ref = A.expand(2, 3, 3, 2).clone()
    ref[..., 0, 0] += torch.cos(x[..., 0])
    torch.testing.assert_close(J, ref, rtol=1e-12, atol=1e-12)
    # one unbatched input (D,) too
    torch.testing.assert_close(jacobian(fn, x[0, 0]), ref[0, 0], rtol=1e-12, atol=1e-12)


def _np_update(m_p, P_p, z_mean, z_cov, cross, z):
    K = cross @ np.linalg.inv(z_cov)
    return m_p + K @ (z - z_mean), P_p - K @ z_cov @ K.T


def test_gaussian_update_is_the_kalman_update_for_a_non_square_cross_covariance():
    """K = C S^{-1} with C = Cov[x, z] (D, E): against numpy for D = 3, E = 2 and for D = E = 2 with C not
    symmetric (C^T S^{-1} would differ)."""
    rng = np.random.default_rng(3)
    for d, e in [(3, 2), (2, 2)]:
        a = rng.standard_normal((d + e, d + e))
        J = a @ a.T + 0.5 * np.eye(d + e)  # a valid joint covariance of (x, z)
        P_p, cross, z_cov = J[:d, :d], J[:d, d:], J[d:, d:]
        m_p, z_mean, z = rng.standard_normal(d), rng.standard_normal(e), rng.standard_normal(e)
        ref_m, ref_P = _np_update(m_p, P_p, z_mean, z_cov, cross, z)
        mean, cov = gaussian_update(*(torch.tensor(t, dtype=D) for t in (m_p, P_p, z_mean, z_cov, cross, z)))
        np.testing.assert_allclose(mean.numpy(), ref_m, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(cov.numpy(), 0.5 * (ref_P + ref_P.T), rtol=1e-10, atol=1e-12)


def test_ukf_step_defaults_are_exact_for_a_quadratic_in_one_dimension():
    """Default (alpha, beta, kappa) = (1, 0, 2): for D = 1, D + kappa = 3 matches the Gaussian's fourth moment,
    so the unscented prediction of f(x) = x^2 at N(m, P) is exact: mean m^2 + P, variance 4 m^2 P + 2 P^2
    (+ the noise Q). Then the update with z = x + v is the scalar Kalman update (closed form)."""
    m, P, Q, R = 1.0, 1.0, 0.1, 0.2
    f = AdditiveModel(lambda x: x * x, torch.tensor([[Q]], dtype=D))
    g = AdditiveModel(lambda x: x, torch.tensor([[R]], dtype=D))
    z = torch.tensor([2.5], dtype=D)
    res = ukf_step(f, g, torch.tensor([m], dtype=D), torch.tensor([[P]], dtype=D), z)
    m_p, P_p = m * m + P, 4 * m * m * P + 2 * P * P + Q  # 2, 6.1
    assert res.pred_mean.item() == pytest.approx(m_p, rel=1e-12)
    assert res.pred_cov.item() == pytest.approx(P_p, rel=1e-12)
    S = P_p + R
    assert res.z_cov.item() == pytest.approx(S, rel=1e-12)
    k = P_p / S
    assert res.mean.item() == pytest.approx(m_p + k * (2.5 - m_p), rel=1e-12)
    assert res.cov.item() == pytest.approx(P_p - k * S * k, rel=1e-12)


# ------------------------------------------------------------------------------------------ gp_moments
def test_predictive_moments_default_includes_the_noise_of_the_target():
    """At a point input (S = 0) the exact moments are the GP's predictive mean and variance; by default the
    variance is that of a noisy target, sigma_f^2 - k^T (K + s^2 I)^{-1} k + s^2 (numpy, per output), with
    include_noise=False without s^2."""
    rng = np.random.default_rng(5)
    n, d, e = 7, 2, 2
    X = rng.standard_normal((n, d))
    Y = rng.standard_normal((n, e))
    ls = np.array([[0.8, 1.3], [1.1, 0.6]])
    sf2 = np.array([0.7, 1.4])
    sn2 = np.array([0.05, 0.2])
    x = np.array([0.3, -0.4])
    mean_ref, var_ref, alphas, chols = [], [], [], []
    for a in range(e):
        def k(A, B):
            dd = (A[:, None, :] - B[None, :, :]) / ls[a]
            return sf2[a] * np.exp(-0.5 * (dd * dd).sum(-1))
        K = k(X, X) + sn2[a] * np.eye(n)
        al = np.linalg.solve(K, Y[:, a])
        ks = k(X, x[None])[:, 0]
        mean_ref.append(ks @ al)
        var_ref.append(sf2[a] - ks @ np.linalg.solve(K, ks))
        alphas.append(al)
        chols.append(np.linalg.cholesky(K))
    t = lambda v: torch.tensor(np.asarray(v), dtype=D)  # noqa: E731
    args = (t(x), torch.zeros(d, d, dtype=D), t(X), t(np.stack(alphas)), t(ls), t(sf2), t(sn2), t(np.stack(chols)))
    mean, cov, cross = predictive_moments(*args)
    np.testing.assert_allclose(mean.numpy(), mean_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(cov.numpy(), np.diag(np.array(var_ref) + sn2), rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(cross.numpy(), 0.0, atol=1e-14)
    _, cov_latent, _ = predictive_moments(*args, include_noise=False)
    np.testing.assert_allclose(cov_latent.numpy(), np.diag(var_ref), rtol=1e-8, atol=1e-10)


# ------------------------------------------------------------------------------------------ rbpf
def test_resample_keeps_the_time_index():
    """Resampling (some batch entries below the ESS threshold) changes the particles, not the time of the
    last processed measurement."""
    n = 8
    g = torch.Generator().manual_seed(2)
    x = torch.randn(2, n, 3, generator=g, dtype=D)
    logw = torch.stack([torch.log_softmax(3.0 * torch.randn(n, generator=g, dtype=D), -1),
                        torch.full((n,), -math.log(n), dtype=D)])
    st = RBPFState(x, logw, torch.ones(2, n, 1, dtype=D), torch.zeros(2, n, 1, 1, dtype=D), t=5)
    new, mask = resample(st, 0.9, torch.Generator().manual_seed(4))
    assert mask.tolist() == [True, False]
    assert new.t == 5
    torch.testing.assert_close(new.logw[0], torch.full((n,), -math.log(n), dtype=D))
