"""Unscented (GP-UKF) prediction step: closed forms, linear-model equality with the EKF step,
Monte Carlo accuracy on a nonlinear model, GP shapes and small-covariance limit, dtypes, jitter."""

import dataclasses
import math

import pytest
import torch

from dslearn.errors import ConfigError
from dslearn.filters.information import predict
from dslearn.filters.ukf import UnscentedPredict, sigma_points, ukf_predict, unscented_weights
from dslearn.models import ConstantVelocity, GPMotionModel, SocialForce
from dslearn.models.base import MotionModel
from dslearn.types import JITTER, StepContext

D = torch.float64
CTX = StepContext(dt=0.25)


def spd(n, *batch, dtype=D, floor=0.5):
    a = torch.randn(*batch, n, n, dtype=dtype)
    return a @ a.transpose(-1, -2) / n + floor * torch.eye(n, dtype=dtype)


class SinModel(MotionModel):
    """f(x) = x + 0.1 sin(x) elementwise, Q = 0.01 I."""

    def __init__(self, state_dim: int):
        super().__init__()
        self.state_dim = state_dim

    def forward(self, x, ctx):
        return x + 0.1 * torch.sin(x)

    def noise_cov(self, x, ctx):
        q = 0.01 * torch.eye(self.state_dim, dtype=x.dtype, device=x.device)
        return q.expand(*x.shape[:-1], *q.shape)


def small_gp(dtype=D, points=25, seed=3):
    gp = GPMotionModel(
        state_dim=8, num_nodes=3, outputscale=1.0, lengthscale=2.0, noise_std=0.5, mean="identity",
        noise="latent", jacobian="closed_form", fit_every=0, fit_iters=1, fit_lr=0.05, dtype=dtype, device="cpu",
    )
    g = torch.Generator().manual_seed(seed)
    for _ in range(points):
        x = torch.randn(3, 8, generator=g, dtype=D)
        gp.add_data(x.to(dtype), (x + 0.25 * torch.tanh(x.roll(1, -1))).to(dtype))
    return gp


# ------------------------------------------------------------------ sigma points and weights
@pytest.mark.parametrize("alpha,beta,kappa", [(1.0, 2.0, 0.0), (0.5, 2.0, 1.0), (1e-3, 2.0, 0.0), (1.3, 0.0, -2.0)])
def test_sigma_points_reproduce_mean_and_covariance(alpha, beta, kappa):
    m, P = torch.randn(3, 2, 6, dtype=D), spd(6, 3, 2)
    pts, wm, wc = sigma_points(m, P, alpha, beta, kappa)
    assert pts.shape == (3, 2, 13, 6) and wm.shape == wc.shape == (13,)
    # rounding bound of a weighted sum: a few ulps of sum |w| (|w_0| ~ alpha^-2 for small alpha)
    ulp = 8 * torch.finfo(D).eps * float(wm.abs().sum())
    assert abs(float(wm.sum()) - 1.0) <= ulp
    c = alpha**2 * (6 + kappa)  # Dx + lambda
    assert float(wm[0]) == pytest.approx(1 - 6 / c, rel=1e-12, abs=1e-12)  # lambda / (Dx + lambda)
    assert float(wc[0] - wm[0]) == pytest.approx(1 - alpha**2 + beta, rel=1e-12, abs=ulp)
    assert torch.allclose(wm[1:], torch.full((12,), 0.5 / c, dtype=D), rtol=1e-12)
    assert torch.equal(pts[..., 0, :], m)
    mean = torch.einsum("k,...kd->...d", wm, pts)
    d = pts - m.unsqueeze(-2)
    cov = d.transpose(-1, -2) @ (wc.unsqueeze(-1) * d)
    assert torch.allclose(mean, m, rtol=0, atol=ulp * float(pts.abs().max()))
    assert torch.allclose(cov, P, atol=1e-12 * (1 + float(P.abs().max())))


def test_weights_closed_form_default():
    wm, wc, c = unscented_weights(8, 1.0, 2.0, 0.0)
    assert c == 8.0 and float(wm[0]) == 0.0 and float(wc[0]) == 2.0
    assert torch.allclose(wm[1:], torch.full((16,), 1 / 16, dtype=D))


def test_bad_parameters_raise_config_error():
    with pytest.raises(ConfigError, match=r"filter\.predict\.alpha.*> 0"):
        UnscentedPredict(alpha=0.0)
    with pytest.raises(ConfigError, match=r"filter\.predict\.beta.*>= 0"):
        UnscentedPredict(beta=-1.0)
    with pytest.raises(ConfigError, match=r"filter\.predict\.kappa"):
        UnscentedPredict(kappa=float("nan"))
    step = UnscentedPredict(kappa=-8.0)  # legal until the state dimension is known
    m, O = torch.zeros(1, 1, 8, dtype=D), torch.eye(8, dtype=D).expand(1, 1, 8, 8)

    class Boom(SinModel):
        def forward(self, x, ctx):
            raise AssertionError("the model must not be called with bad parameters")

    with pytest.raises(ConfigError, match=r"filter\.predict\.kappa=-8.0.*Dx=8.*> -8"):
        step(m, O, Boom(8), CTX)
    assert UnscentedPredict().name == "ukf"
    with pytest.raises(dataclasses.FrozenInstanceError):
        UnscentedPredict().alpha = 2.0


# ------------------------------------------------------------------ linear model: = EKF
def test_linear_model_equals_ekf_step():
    cv = ConstantVelocity(2, 0.3)
    m = torch.randn(3, 2, 8, dtype=D)
    omega = torch.linalg.inv(spd(8, 3, 2))
    ekf = predict(m, omega, cv, CTX, full=True)
    ukf = UnscentedPredict()(m, omega, cv, CTX, full=True)
    for name, a, b in zip(("y_pred", "q_pred", "omega_pred", "P_pred", "F", "Q"), ekf, ukf):
        assert a.shape == b.shape, name
        assert torch.allclose(a, b, rtol=0, atol=1e-10), (name, float((a - b).abs().max()))
    F = ukf[4]
    assert torch.allclose(F, cv.matrix(0.25).expand_as(F), atol=1e-10)
    short = ukf_predict(m, omega, cv, CTX)
    assert len(short) == 3 and all(torch.equal(a, b) for a, b in zip(short, ukf[:3]))


# ------------------------------------------------------------------ nonlinear: Monte Carlo
def _mc(m, P, n=200_000, seed=1):
    """Monte Carlo mean (with the exactly known E[X] = m as control variate) and covariance of
    f(X) + noise, X ~ N(m, P), and their standard errors."""
    g = torch.Generator().manual_seed(seed)
    X = m + torch.randn(n, m.shape[-1], generator=g, dtype=D) @ torch.linalg.cholesky(P).T
    Y = X + 0.1 * torch.sin(X)
    r = Y - X
    mean, se_mean = m + r.mean(0), r.std(0) / math.sqrt(n)
    d = Y - Y.mean(0)
    prod = d.unsqueeze(-1) * d.unsqueeze(-2)
    cov, se_cov = prod.mean(0) + 0.01 * torch.eye(m.shape[-1], dtype=D), prod.std(0) / math.sqrt(n)
    return mean, se_mean, cov, se_cov


M0 = torch.tensor([0.5, -1.0, 1.5, 0.2], dtype=D)
C0 = (lambda b: b @ b.T)(torch.tensor([[1, 0, 0, 0], [0.5, 1, 0, 0], [0, -0.3, 1, 0], [0.2, 0, 0.4, 1]], dtype=D))


def _moments(step, P):
    y, _, o = step(M0[None, None], torch.linalg.inv(P)[None, None], SinModel(4), CTX)
    return y[0, 0], torch.linalg.inv(o[0, 0])


def test_nonlinear_narrow_prior_matches_monte_carlo():
    """Prior std ~0.3: the unscented moments agree with 200k-sample Monte Carlo within 5 standard
    errors per entry (the UKF's own bias here is ~3e-5, under one standard error), while the EKF's
    mean is off by far more than that."""
    P = 0.3**2 * C0
    mc_m, se_m, mc_P, se_P = _mc(M0, P)
    exact = M0 + 0.1 * torch.sin(M0) * torch.exp(-P.diagonal() / 2)  # E[sin X] in closed form
    assert ((mc_m - exact).abs() <= 5 * se_m).all()  # the Monte Carlo itself is right
    y, Pp = _moments(ukf_predict, P)
    assert ((y - mc_m).abs() <= 5 * se_m).all(), (y - mc_m) / se_m
    assert ((Pp - mc_P).abs() <= 5 * se_P).all(), (Pp - mc_P) / se_P
    ye, _ = _moments(predict, P)
    assert ((ye - mc_m).abs() > 20 * se_m).any()


def test_nonlinear_wide_prior_ukf_closer_than_ekf():
    """Prior std ~2: neither is exact, the unscented mean and covariance are closer to Monte
    Carlo than the EKF's (whose errors are many standard errors, so the ordering is resolved)."""
    P = 2.0**2 * C0
    mc_m, se_m, mc_P, se_P = _mc(M0, P)
    yu, Pu = _moments(ukf_predict, P)
    ye, Pe = _moments(predict, P)
    eu, ee = (yu - mc_m).norm(), (ye - mc_m).norm()
    cu, ce = (Pu - mc_P).norm(), (Pe - mc_P).norm()
    assert ee > 10 * se_m.norm() and ce > 10 * se_P.norm()
    assert eu < 0.5 * ee and cu < 0.5 * ce, (eu, ee, cu, ce)


def test_differentiable():
    m = torch.randn(1, 2, 4, dtype=D, requires_grad=True)
    omega = torch.linalg.inv(spd(4, 1, 2))
    f = lambda x: ukf_predict(x, omega, SinModel(4), CTX)[0]  # noqa: E731
    assert torch.autograd.gradcheck(f, (m,))


# ------------------------------------------------------------------ GP motion model
def test_gp_shapes_spd_and_tiny_covariance_equals_ekf():
    gp = small_gp()
    m = torch.randn(3, 2, 8, dtype=D)
    omega = torch.linalg.inv(spd(8, 3, 2))
    y, q, o, P, F, Q = ukf_predict(m, omega, gp, CTX, full=True)
    assert y.shape == q.shape == (3, 2, 8) and o.shape == P.shape == F.shape == Q.shape == (3, 2, 8, 8)
    assert all(bool(torch.isfinite(t).all()) for t in (y, q, o, P, F, Q))
    assert torch.equal(o, o.transpose(-1, -2)) and bool((torch.linalg.eigvalsh(o) > 0).all())
    assert torch.allclose(o @ P, torch.eye(8, dtype=D).expand_as(P), atol=1e-9)
    # tiny prior covariance 1e-8 I: sigma offsets sqrt(8) 1e-4, so UKF - EKF = O(f'' * 1e-7)
    tiny = 1e8 * torch.eye(8, dtype=D).expand(3, 2, 8, 8)
    ekf = predict(m, tiny, gp, CTX, full=True)
    ukf = ukf_predict(m, tiny, gp, CTX, full=True)
    assert torch.allclose(ukf[0], gp(m, CTX), atol=1e-7)
    for name, a, b in zip(("y_pred", "q_pred", "omega_pred", "P_pred", "F", "Q"), ekf, ukf):
        tol = 1e-7 * (1 + float(a.abs().max()))
        assert torch.allclose(a, b, rtol=0, atol=tol), (name, float((a - b).abs().max()))


def test_gp_batch_equals_per_episode_calls():
    """Flattening (S, B, 2Dx+1, Dx) -> (S, B(2Dx+1), Dx) keeps every sigma point with its node and episode."""
    gp = small_gp()
    m = torch.randn(3, 4, 8, dtype=D)
    omega = torch.linalg.inv(spd(8, 3, 4))
    batched = ukf_predict(m, omega, gp, CTX, full=True)
    for b in range(4):
        single = ukf_predict(m[:, b : b + 1], omega[:, b : b + 1], gp, CTX, full=True)
        for a, s in zip(batched, single):
            assert torch.allclose(a[:, b : b + 1], s, rtol=1e-12, atol=1e-12)


def test_social_force_per_episode_desired_broadcasts():
    """The social force reads ctx.cov and may hold one desired-velocity set per episode (B, A, 2):
    both must broadcast against the sigma points; a tiny prior gives the EKF step."""
    sf = SocialForce([[1.0, -1.0], [-1.0, -1.0]], noise_std=0.05)
    sf.set_desired(torch.randn(3, 2, 2, dtype=D))
    m = torch.tensor([[0.0, 0.0, 1.0, -1.0, 0.6, 0.3, -1.0, -1.0]], dtype=D) + 0.1 * torch.randn(2, 3, 8, dtype=D)
    tiny = 1e10 * torch.eye(8, dtype=D).expand(2, 3, 8, 8)
    ukf = ukf_predict(m, tiny, sf, CTX, full=True)
    ekf = predict(m, tiny, sf, CTX, full=True)
    assert ukf[0].shape == (2, 3, 8)
    assert torch.allclose(ukf[0], ekf[0], atol=1e-8)
    assert torch.allclose(ukf[4], ekf[4], atol=1e-5)  # F: central-difference error O(1e-5 f''')
    wide = torch.linalg.inv(spd(8, 2, 3))
    for b in range(3):  # per-episode desired velocity kept with its episode
        sf_b = SocialForce([[1.0, -1.0], [-1.0, -1.0]], noise_std=0.05).set_desired(sf.desired[b])
        one = ukf_predict(m[:, b], wide[:, b], sf_b, CTX)
        assert torch.allclose(ukf_predict(m, wide, sf, CTX)[0][:, b], one[0], atol=1e-12)


# ------------------------------------------------------------------ dtypes, batch, jitter
@pytest.mark.parametrize("kind", ["cv", "gp"])
def test_float32_matches_float64(kind):
    m = torch.randn(3, 2, 8, dtype=D)
    P = spd(8, 3, 2)
    omega = torch.linalg.inv(P)
    mod64 = ConstantVelocity(2, 0.3) if kind == "cv" else small_gp(D)
    mod32 = ConstantVelocity(2, 0.3) if kind == "cv" else small_gp(torch.float32)
    r64 = ukf_predict(m, omega, mod64, CTX, full=True)
    r32 = ukf_predict(m.float(), omega.float(), mod32, CTX, full=True)
    for a, b in zip(r64, r32):
        assert b.dtype == torch.float32 and bool(torch.isfinite(b).all())
        assert torch.allclose(a, b.double(), rtol=1e-3, atol=1e-3 * (1 + float(a.abs().max())))


def test_singular_prior_covariance_jitters_not_crashes():
    m = torch.randn(2, 8, dtype=D)
    cov = torch.ones(2, 8, 8, dtype=D)  # rank one: Cholesky fails, jitter is added and counted
    before = JITTER.count
    pts, wm, wc = sigma_points(m, cov)
    assert JITTER.count == before + 2
    assert bool(torch.isfinite(pts).all())
    d = pts - m.unsqueeze(-2)
    assert torch.allclose(d.transpose(-1, -2) @ (wc.unsqueeze(-1) * d), cov, atol=1e-6)


def test_singular_predicted_covariance_jitters_not_crashes():
    """A model that forgets the velocity and adds no noise: P_pred is exactly singular."""

    class Project(MotionModel):
        state_dim = 4

        def forward(self, x, ctx):
            return torch.cat([x[..., :2], torch.zeros_like(x[..., 2:])], -1)

        def noise_cov(self, x, ctx):
            return x.new_zeros(*x.shape, 4)

    m, omega = torch.randn(1, 3, 4, dtype=D), torch.linalg.inv(spd(4, 1, 3))
    before = JITTER.count
    y, q, o = ukf_predict(m, omega, Project(), CTX)
    assert JITTER.count >= before + 3  # each of the 3 singular P_pred needed jitter
    assert all(bool(torch.isfinite(t).all()) for t in (y, q, o))
    assert torch.allclose(y[..., 2:], torch.zeros_like(y[..., 2:]))
