"""The particle step's shortcut for GPs without data (``filter=pf``, :mod:`dslearn.filters.particle`).

Where no node's GP holds a valid point (Liu's 200 sensors, whose learning gate admits nothing), the GP predictive
is the prior at every particle: an affine mean and a constant noise, so the moment-matched cloud has a known law
(sample mean Gaussian, scatter Wishart) and is drawn from it directly. Checked here: that law against the
straightforward particle cloud and against the closed-form moments, the full outputs, and that wherever some node
holds data the step still draws every particle, bit for bit as the straightforward computation written out below.
"""

from __future__ import annotations

import math

import pytest
import torch

from dslearn.filters import particle
from dslearn.filters.particle import ParticlePredict, pf_predict
from dslearn.models.gp import GPMotionModel
from dslearn.models.gp_backends.means import ConstantVelocityMean
from dslearn.types import StepContext, safe_cholesky, spd_inverse, symmetrize

D = torch.float64
CTX = StepContext(dt=0.25)


def void_gp(mean="identity", noise="latent", nodes=2, appended=0):
    """A GP motion model with no valid point: empty, or ``appended`` invalid points per node."""
    model = GPMotionModel(4, nodes, outputscale=1.3, noise_std=0.4, mean=mean, noise=noise, dtype=D)
    if noise == "adaptive":
        model.q_noise.copy_(torch.tensor([[0.3, 0.1], [2.0, 0.05]], dtype=D)[:nodes])
    g = torch.Generator().manual_seed(9)
    for _ in range(appended):
        x = torch.randn(nodes, 4, generator=g, dtype=D)
        model.add_data(x, x + 0.1, torch.zeros(nodes, dtype=torch.bool))
    return model


def replicated_beliefs(s=2, b=1, seed=0):
    """One random belief per node, repeated over ``b`` episodes: ``(S, b, 4)``, ``(S, b, 4, 4)``."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(s, 1, 4, 4, generator=g, dtype=D)
    P = (a @ a.transpose(-1, -2) / 4 + 0.5 * torch.eye(4, dtype=D)).expand(s, b, 4, 4).contiguous()
    m = torch.randn(s, 1, 4, generator=g, dtype=D).expand(s, b, 4).contiguous()
    return m, P


def straightforward(mean, omega, model, n, generator, full=False):
    """The GP-PF's prediction written out particle by particle: every draw first (particles, then noise), each
    particle through the GP's predictive, the cloud moment-matched (the step's computation before the shortcut)."""
    P = spd_inverse(omega)
    L = safe_cholesky(P)
    s, b, dx = mean.shape
    z = torch.randn((s, b, 2, n, dx), generator=generator, dtype=mean.dtype, device=mean.device)
    x = mean.unsqueeze(-2) + z[..., 0, :, :] @ L.transpose(-1, -2)
    w = z[..., 1, :, :]
    mu, var, _ = model.gp.predict(x.reshape(s, b * n, dx), jacobian=False, variance=True)
    if model.noise_mode == "predictive":
        var = var + model.gp.noise_var.to(var).unsqueeze(-1)
    d = var.unsqueeze(-1) + model.extra_noise(var).to(var).unsqueeze(1)
    f = mu.reshape(x.shape).to(x.dtype)
    y = f + d.clamp_min(0.0).sqrt().reshape(x.shape).to(x.dtype) * w
    y_pred = y.mean(-2)
    dy = y - y_pred.unsqueeze(-2)
    P_pred = symmetrize(dy.transpose(-1, -2) @ dy / (n - 1))
    omega_pred = spd_inverse(P_pred)
    q_pred = (omega_pred @ y_pred.unsqueeze(-1)).squeeze(-1)
    if not full:
        return y_pred, q_pred, omega_pred
    dxp = x - x.mean(-2, keepdim=True)
    df = f - f.mean(-2, keepdim=True)
    C_xx = symmetrize(dxp.transpose(-1, -2) @ dxp)
    F = torch.cholesky_solve(dxp.transpose(-1, -2) @ df, safe_cholesky(C_xx)).transpose(-1, -2)
    return y_pred, q_pred, omega_pred, P_pred, F, particle._psd_floor(symmetrize(P_pred - F @ P @ F.transpose(-1, -2)))


def cloud_law(model, m, P):
    """The particles' exact law through a GP without data: mean f(m), covariance A P A^T + diag(noise)."""
    gp = model.gp
    A = gp.prior_mean_jacobian(m)
    var = gp.prior_variance().unsqueeze(-1)
    if model.noise_mode == "predictive":
        var = var + gp.noise_var.unsqueeze(-1)
    d = var + model.extra_noise(var)  # (S, Dx)
    return gp.prior_mean(m), A @ P @ A.transpose(-1, -2) + torch.diag_embed(d).unsqueeze(1), A


def zscores(a: torch.Tensor, b: torch.Tensor) -> float:
    """Largest two-sample z-score of the means over the replicates (dimension 1) of ``a`` and ``b``."""
    r = a.shape[1]
    return float(((a.mean(1) - b.mean(1)).abs() / ((a.var(1) + b.var(1)) / r).sqrt()).max())


# ------------------------------------------------------------------------------------------ the law
@pytest.mark.parametrize("mean,noise", [("identity", "latent"), ("zero", "predictive"), ("constant", "latent"),
                                        ("identity", "adaptive")])
def test_the_void_shortcut_draws_the_moments_of_the_particle_cloud(mean, noise):
    """GPs without data, few particles (N = 10, where the sample covariance is far from Gaussian), 20000 replicate
    episodes: the shortcut's y_pred and P_pred have the closed-form moments of a sample of N from
    N(f(m), Sigma) (E y_pred = f(m), Cov y_pred = Sigma / N, E P_pred = Sigma,
    Var P_pred_jk = (Sigma_jk^2 + Sigma_jj Sigma_kk) / (N - 1)) and the first two moments of the straightforward
    particle cloud's (two-sample z-scores); a cloud without the process noise is far off (the check sees it)."""
    model = void_gp(mean, noise, appended=3)
    n, reps = 10, 20000
    m, P = replicated_beliefs(b=reps)
    om = torch.linalg.inv(P)
    y, _, _, P_pred, F, Q = pf_predict(m, om, model, CTX, True, particles=n, generator=torch.Generator().manual_seed(1))
    ref = straightforward(m, om, model, n, torch.Generator().manual_seed(2), full=True)
    f, S, A = cloud_law(model, m[:, :1], P[:, :1])
    # closed form
    sd = S.diagonal(dim1=-2, dim2=-1).sqrt()
    se_y = sd / math.sqrt(n * reps)
    assert ((y.mean(1, keepdim=True) - f).abs() <= 5 * se_y).all()
    dy = y - y.mean(1, keepdim=True)
    cov_y = dy.transpose(-1, -2) @ dy / (reps - 1)
    var_S = (S**2 + sd.unsqueeze(-1) ** 2 * sd.unsqueeze(-2) ** 2) / (n - 1)  # Var of P_pred's entries
    se_cov_y = (var_S / n**2 * (n - 1) / reps).sqrt()  # Cov(y_pred) = Sigma / N, itself estimated from reps
    assert ((cov_y - S[:, 0] / n).abs() <= 5 * se_cov_y[:, 0]).all()
    assert ((P_pred.mean(1, keepdim=True) - S).abs() <= 5 * (var_S / reps).sqrt()).all()
    assert ((P_pred.var(1, keepdim=True) - var_S).abs() <= 0.1 * var_S).all()
    # against the particles: first and second moments
    assert zscores(y, ref[0]) < 5 and zscores(P_pred, ref[3]) < 5
    assert zscores(dy.unsqueeze(-1) * dy.unsqueeze(-2), (ref[0] - ref[0].mean(1, keepdim=True)).unsqueeze(-1)
                   * (ref[0] - ref[0].mean(1, keepdim=True)).unsqueeze(-2)) < 5
    assert zscores((P_pred - P_pred.mean(1, keepdim=True)) ** 2, (ref[3] - ref[3].mean(1, keepdim=True)) ** 2) < 5
    assert zscores(Q, ref[5]) < 5
    # F: the prior mean's (constant) Jacobian, which the particles' regression recovers up to rounding
    assert torch.equal(F, A.expand_as(F))
    torch.testing.assert_close(ref[4], F, rtol=0, atol=1e-9)
    # a cloud without the noise (Sigma = A P A^T) is far outside the bounds
    assert not ((P_pred.mean(1, keepdim=True) - A @ P[:, :1] @ A.transpose(-1, -2)).abs()
                <= 5 * (var_S / reps).sqrt()).all()


def test_full_outputs_on_void_nodes_are_consistent():
    """F P F^T + Q = P_pred (Q needs no floor here), omega_pred = P_pred^-1, q_pred = omega_pred y_pred; shapes and
    dtype as the particle path's."""
    model = void_gp("identity", "latent")
    m, P = replicated_beliefs(b=3)
    y, q, om, P_pred, F, Q = ParticlePredict(500, seed=3)(m, torch.linalg.inv(P), model, CTX, full=True)
    assert [tuple(t.shape) for t in (y, q, om, P_pred, F, Q)] == [(2, 3, 4), (2, 3, 4)] + [(2, 3, 4, 4)] * 4
    assert all(t.dtype == D and torch.isfinite(t).all() for t in (y, q, om, P_pred, F, Q))
    torch.testing.assert_close(F @ P @ F.transpose(-1, -2) + Q, P_pred, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(torch.linalg.inv(om), P_pred, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(q, (om @ y.unsqueeze(-1)).squeeze(-1))
    assert not torch.equal(y[:, 0], y[:, 1])  # each episode its own draw


def test_the_constant_velocity_prior_mean_takes_the_shortcut():
    """An affine prior mean module (constant velocity): F is its matrix, the cloud's mean its image of m within the
    Monte Carlo bound."""
    model = GPMotionModel(4, 2, outputscale=1.0, mean=ConstantVelocityMean(0.5), dtype=D)
    m, P = replicated_beliefs(b=2000)
    y, _, _, P_pred, F, _ = pf_predict(m, torch.linalg.inv(P), model, CTX, True, particles=50,
                                       generator=torch.Generator().manual_seed(4))
    Fcv = model.gp.mean_module.F.to(D)
    assert torch.equal(F, Fcv.expand_as(F))
    f, S, _ = cloud_law(model, m[:, :1], P[:, :1])
    se = S.diagonal(dim1=-2, dim2=-1).sqrt() / math.sqrt(50 * 2000)
    assert ((y.mean(1, keepdim=True) - f).abs() <= 5 * se).all()


def test_reproducible_from_the_seed_and_advanced_per_call():
    """The shortcut's draws come from the step's generator: fresh steps with one seed agree bit for bit, a second
    call draws anew, another seed differs; the global RNG is not touched."""
    model = void_gp("identity", "latent")
    m, P = replicated_beliefs(b=2)
    om = torch.linalg.inv(P)
    torch.manual_seed(5)
    before = torch.random.get_rng_state()
    a, b, c = ParticlePredict(500, seed=4), ParticlePredict(500, seed=4), ParticlePredict(500, seed=5)
    ra, rb, rc = (st(m, om, model, CTX, full=True) for st in (a, b, c))
    assert all(torch.equal(x, y) for x, y in zip(ra, rb))
    assert not torch.equal(ra[0], rc[0]) and not torch.equal(ra[3], rc[3])
    ra2 = a(m, om, model, CTX)
    assert not torch.equal(ra2[0], ra[0])
    assert torch.equal(torch.random.get_rng_state(), before)


# ------------------------------------------------------------------------------------------ unchanged paths
@pytest.mark.parametrize("valid_nodes", ["all", "one"])
@pytest.mark.parametrize("full", [False, True])
def test_a_node_with_data_keeps_every_particle_bit_for_bit(valid_nodes, full):
    """Where some node's GP holds a valid point (every node, or one of two), the step draws every particle as
    before: bit-identical to the straightforward computation from the same generator."""
    model = GPMotionModel(4, 2, outputscale=1.3, noise_std=0.4, mean="identity", noise="predictive", dtype=D)
    g = torch.Generator().manual_seed(0)
    for _ in range(6):
        x = torch.randn(2, 4, generator=g, dtype=D)
        valid = torch.tensor([True, valid_nodes == "all"])
        model.add_data(x, x + 0.3 * torch.sin(x), valid)
    assert model.gp.void_nodes().tolist() == [False, valid_nodes != "all"]
    m, P = replicated_beliefs(b=3, seed=2)
    m = m + 0.1 * torch.randn(m.shape, generator=g, dtype=D)
    om = torch.linalg.inv(P)
    got = pf_predict(m, om, model, CTX, full, particles=64, generator=torch.Generator().manual_seed(7))
    ref = straightforward(m, om, model, 64, torch.Generator().manual_seed(7), full=full)
    assert len(got) == len(ref)
    for a, b in zip(got, ref):
        assert torch.equal(a, b)


def test_other_models_and_too_few_particles_draw_particles():
    """No shortcut where the law is not the affine prior's: a non-GP model (the constant-velocity model keeps its
    draws), or N <= 2 Dx (fewer particles than the Bartlett factor has dimensions)."""
    m, P = replicated_beliefs(b=2)
    om = torch.linalg.inv(P)
    model = void_gp("identity", "latent")
    assert particle._void_prior(model, m, 500) is not None
    assert particle._void_prior(model, m, 9) is not None and particle._void_prior(model, m, 8) is None
    got = pf_predict(m, om, model, CTX, particles=8, generator=torch.Generator().manual_seed(3))
    ref = straightforward(m, om, model, 8, torch.Generator().manual_seed(3))
    assert all(torch.equal(a, b) for a, b in zip(got, ref))
    from dslearn.models import ConstantVelocity

    assert particle._void_prior(ConstantVelocity(1, 1.0), m, 500) is None


def test_void_nodes_predict_the_prior():
    """The backend's ``void_nodes``/``prior_variance``: where a node holds no valid point its prediction is the prior
    mean and the prior variance at any input, exactly."""
    model = void_gp("identity", "latent", appended=2)
    gp = model.gp
    x = torch.randn(2, 7, 4, generator=torch.Generator().manual_seed(1), dtype=D)
    mu, var, _ = gp.predict(x, jacobian=False)
    assert gp.void_nodes().all()
    assert torch.equal(mu, gp.prior_mean(x)) and torch.equal(var, gp.prior_variance().unsqueeze(-1).expand_as(var))
    assert void_gp().gp.void_nodes().all()  # no point at all
