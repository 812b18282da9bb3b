"""GP-ADF moments, the GP-Bayes filters and the ``gp_bayes_filters`` study (Deisenroth et al., ICML 2009).

Oracles: a Monte Carlo estimate (the moments), GPyTorch's own predictive (the trained arrays), filterpy's
Kalman filter (a near-linear GP fit to a linear-Gaussian model), values by hand (EKF step, metrics)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from dslearn.errors import ConfigError
from dslearn.filters.gp_bayes import AdditiveModel, GPModel, adf_step, ekf_step, pf_step, ukf_step
from dslearn.filters.gp_moments import GPPosterior, fit_gps
from dslearn.metrics.filtering import filter_step_metrics
from dslearn.schemas.core import CONF_DIR, validate_config

F64 = torch.float64


def _gp(D: int, E: int, seed: int = 0) -> GPPosterior:
    g = torch.Generator().manual_seed(seed)
    n = 25
    X = 2.0 * torch.randn(n, D, generator=g, dtype=F64)
    Y = torch.stack([torch.sin((e + 1) * X.sum(-1)) + 0.3 * X[:, 0] for e in range(E)], -1)
    Y = Y + 0.1 * torch.randn(n, E, generator=g, dtype=F64)
    ls = 0.6 + torch.rand(E, D, generator=g, dtype=F64)
    sv = 0.5 + torch.rand(E, generator=g, dtype=F64)
    nv = torch.tensor([0.01, 0.02][:E], dtype=F64)
    return GPPosterior.from_data(X, Y, ls, sv, nv)


# ------------------------------------------------------------------------------------------ moments
@pytest.mark.parametrize("D,E", [(1, 1), (2, 2)])
def test_moments_equal_monte_carlo(D, E):
    """Mean, covariance and cross-covariance of the prediction at N(m, S) equal a 1e5-sample estimate
    within 4 standard errors (per entry: the standard error of the sample mean of its per-sample term)."""
    gp = _gp(D, E)
    g = torch.Generator().manual_seed(1)
    m = torch.tensor([[0.3, -0.5][:D], [1.0, 0.2][:D]], dtype=F64)
    A = 0.6 * torch.randn(2, D, D, generator=g, dtype=F64)
    S = A @ A.mT + 0.05 * torch.eye(D, dtype=F64)
    mean, cov, cross = gp.moments(m, S)
    assert mean.shape == (2, E) and cov.shape == (2, E, E) and cross.shape == (2, D, E)
    N = 100_000
    x = m[:, None] + (torch.linalg.cholesky(S)[:, None] @ torch.randn(2, N, D, 1, generator=g, dtype=F64)).squeeze(-1)
    mu, var = gp.mean_variance(x)                                  # (2, N, E): f(x) | x ~ N(mu, var)
    se = lambda t: t.std(1) / math.sqrt(N)                         # noqa: E731
    assert ((mean - mu.mean(1)).abs() <= 4 * se(mu)).all()
    d = mu - mu.mean(1, keepdim=True)
    # Cov[f_a, f_b] = E[(mu_a - E mu_a)(mu_b - E mu_b)] + delta_ab E[var_a]: per-sample term
    term = d.unsqueeze(-1) * d.unsqueeze(-2) + torch.diag_embed(var)
    assert ((cov - term.mean(1)).abs() <= 4 * se(term)).all(), (cov, term.mean(1))
    xterm = (x - m[:, None]).unsqueeze(-1) * d.unsqueeze(-2)       # (2, N, D, E)
    assert ((cross - xterm.mean(1)).abs() <= 4 * se(xterm)).all()
    assert torch.allclose(cov, cov.mT) and (torch.linalg.eigvalsh(cov) > 0).all()


def test_moments_at_a_point_are_the_gp_prediction():
    """S = 0: the mean is the GP mean, the variance the GP variance, no output covariance, no cross term."""
    gp = _gp(2, 2)
    m = torch.tensor([[0.4, -1.2], [2.0, 0.5]], dtype=F64)
    mean, cov, cross = gp.moments(m, torch.zeros(2, 2, 2, dtype=F64))
    mu, var = gp.mean_variance(m)
    torch.testing.assert_close(mean, mu, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(cov, torch.diag_embed(var), rtol=1e-10, atol=1e-12)
    assert cross.abs().max() == 0.0
    _, cov_f, _ = gp.moments(m, torch.zeros(2, 2, 2, dtype=F64), include_noise=False)
    torch.testing.assert_close(torch.diagonal(cov - cov_f, dim1=-2, dim2=-1), gp.noise_var.expand(2, 2))


def test_trained_arrays_give_gpytorch_predictive():
    """``fit_gps`` trains with GPyTorch; its arrays reproduce GPyTorch's own predictive mean and variance."""
    import gpytorch

    g = torch.Generator().manual_seed(3)
    X = 4.0 * torch.rand(40, 2, generator=g, dtype=F64) - 2.0
    Y = torch.stack([X[:, 0] * X[:, 1], torch.cos(X[:, 0])], -1) + 0.05 * torch.randn(40, 2, generator=g, dtype=F64)
    gp = fit_gps(X, Y, iterations=60, lr=0.1)
    assert gp.lengthscales.shape == (2, 2) and (gp.noise_var > 0).all()
    xs = torch.randn(7, 2, generator=g, dtype=F64)
    mu, var = gp.mean_variance(xs, include_noise=True)
    for e in range(2):
        lik = gpytorch.likelihoods.GaussianLikelihood(noise_constraint=gpytorch.constraints.GreaterThan(1e-8)).double()

        class M(gpytorch.models.ExactGP):
            def __init__(self):
                super().__init__(X, Y[:, e], lik)
                self.covar_module = gpytorch.kernels.ScaleKernel(gpytorch.kernels.RBFKernel(ard_num_dims=2))

            def forward(self, x):
                return gpytorch.distributions.MultivariateNormal(torch.zeros_like(x[:, 0]), self.covar_module(x))

        model = M().double()
        model.covar_module.base_kernel.lengthscale = gp.lengthscales[e]
        model.covar_module.outputscale = gp.signal_var[e]
        lik.noise = gp.noise_var[e]
        model.eval()
        lik.eval()
        with torch.no_grad(), gpytorch.settings.fast_pred_var(False), gpytorch.settings.max_cholesky_size(10 ** 9):
            pred = lik(model(xs))
        torch.testing.assert_close(mu[:, e], pred.mean, rtol=1e-8, atol=1e-8)
        torch.testing.assert_close(var[:, e], pred.variance, rtol=1e-8, atol=1e-8)


# ------------------------------------------------------------------------------------------ filters by hand
def test_ekf_step_by_hand():
    """f = x^2, g = x, m = 1, P = 0.1, Q = 0.01, R = 0.04, z = 1.2: F = 2, P_p = 0.41, S = 0.45."""
    f = AdditiveModel(lambda x: x * x, torch.tensor([[0.01]], dtype=F64))
    g = AdditiveModel(lambda x: x, torch.tensor([[0.04]], dtype=F64))
    r = ekf_step(f, g, torch.tensor([[1.0]], dtype=F64), torch.tensor([[[0.1]]], dtype=F64), torch.tensor([[1.2]], dtype=F64))
    k = 0.41 / 0.45
    assert r.pred_mean.item() == pytest.approx(1.0, abs=1e-15) and r.pred_cov.item() == pytest.approx(0.41, rel=1e-14)
    assert r.z_cov.item() == pytest.approx(0.45, rel=1e-14)
    assert r.mean.item() == pytest.approx(1.0 + k * 0.2, rel=1e-14)
    assert r.cov.item() == pytest.approx(0.41 - 0.41 ** 2 / 0.45, rel=1e-13)


def test_metrics_by_hand():
    """x = 1, m = 0, P = 4: NLL = log(2 pi 4)/2 + 1/8, Mahalanobis 1/2, RMSE 1; z = 3 under N(1, 2)."""
    t = lambda v: torch.tensor([[v]], dtype=F64)  # noqa: E731
    out = filter_step_metrics(t(1.0), t(0.0), torch.tensor([[[4.0]]], dtype=F64), t(3.0), t(1.0),
                              torch.tensor([[[2.0]]], dtype=F64))
    assert out["nll_x"].item() == pytest.approx(0.5 * math.log(2 * math.pi * 4) + 0.125, rel=1e-14)
    assert out["maha_x"].item() == pytest.approx(0.5, rel=1e-14)
    assert out["rmse_x"].item() == pytest.approx(1.0, rel=1e-14)
    assert out["nll_z"].item() == pytest.approx(0.5 * math.log(2 * math.pi * 2) + 1.0, rel=1e-14)
    deg = filter_step_metrics(t(1.0), t(0.0), torch.zeros(1, 1, 1, dtype=F64), t(3.0), t(1.0), t(2.0)[..., None])
    assert math.isinf(deg["nll_x"].item()) and math.isinf(deg["maha_x"].item())  # reported, never floored


# ------------------------------------------------------------------------------------------ linear-Gaussian: Kalman
A, C, SW, SV, P0 = 0.8, 1.5, 0.1, 0.2, 0.3 ** 2
PRIORS = [-2.0, -0.7, 0.0, 1.1, 2.0]


@pytest.fixture(scope="module")
def linear_gps():
    """GPs trained (GPyTorch) on 200 noisy samples each of x' = 0.8 x + w, z = 1.5 x + v on [-6, 6]."""
    g = torch.Generator().manual_seed(11)
    Xf = 12.0 * torch.rand(200, 1, generator=g, dtype=F64) - 6.0
    Xg = 12.0 * torch.rand(200, 1, generator=g, dtype=F64) - 6.0
    gf = fit_gps(Xf, A * Xf + SW * torch.randn(200, 1, generator=g, dtype=F64))
    gg = fit_gps(Xg, C * Xg + SV * torch.randn(200, 1, generator=g, dtype=F64))
    return GPModel(gf), GPModel(gg)


def _kalman(m0: float, z: float, q: float, r: float):
    from filterpy.kalman import KalmanFilter

    kf = KalmanFilter(dim_x=1, dim_z=1)
    kf.x, kf.P, kf.F, kf.Q, kf.H, kf.R = (np.array([[m0]]), np.array([[P0]]), np.array([[A]]), np.array([[q]]),
                                          np.array([[C]]), np.array([[r]]))
    kf.predict()
    pm, pp = float(kf.x[0, 0]), float(kf.P[0, 0])
    kf.update([[z]])
    return pm, pp, float(kf.x[0, 0]), float(kf.P[0, 0])


def _deviation(model: GPModel, slope: float, mean: float, var: float, sigma_points: bool) -> tuple[float, float, float]:
    """How far the GP is from the linear map ``slope x`` under the distribution a filter averages over: the
    Gaussian N(mean, var) (quadrature on +-8 std, 4001 points) or, with ``sigma_points``, the three sigma
    points (alpha = 1, beta = 0, kappa = 2: mean +- sqrt(3 var), weights 2/3, 1/6, 1/6). With
    ``e(x)`` = GP mean - slope x: returns ``|E e|``, the standard deviation of ``e`` and the latent
    (epistemic) GP variance the filter adds (its mean; at the sigma points: its value at the mean, the
    GP-UKF's noise)."""
    sd = math.sqrt(var)
    if sigma_points:
        x = torch.tensor([[mean], [mean - math.sqrt(3.0) * sd], [mean + math.sqrt(3.0) * sd]], dtype=F64)
        w = torch.tensor([2 / 3, 1 / 6, 1 / 6], dtype=F64)
    else:
        x = torch.linspace(mean - 8 * sd, mean + 8 * sd, 4001, dtype=F64).unsqueeze(-1)
        w = torch.exp(-0.5 * ((x[:, 0] - mean) / sd) ** 2)
        w = w / w.sum()
    mu, v = model.gp.mean_variance(x, include_noise=False)
    e = mu[:, 0] - slope * x[:, 0]
    e_mean = float((w * e).sum())
    e_sd = float((w * (e - e_mean) ** 2).sum().sqrt())
    return abs(e_mean), e_sd, float(v[0, 0]) if sigma_points else float((w * v[:, 0]).sum())


@pytest.mark.parametrize("name", ["gp_adf", "gp_ukf", "gp_pf"])
def test_near_linear_gp_filters_agree_with_kalman(name, linear_gps):
    """The Kalman filter (filterpy) with F = 0.8, H = 1.5 and the GPs' learned noise variances is the oracle.

    Tolerance, per case, from the GPs' measured deviation e(x) from the linear maps under the distribution
    each filter averages over (:func:`_deviation`; the sigma points' weights are positive for alpha = 1,
    beta = 0, kappa = 2, so they are a distribution of the same mean and variance): for any expectation
    over a distribution of variance P, dm_p = E e_f, |dP_p| = |2 a Cov(x, e_f) + Var e_f + E v_f|
    <= 2|a| sqrt(P) sd(e_f) + sd(e_f)^2 + E v_f (Cauchy-Schwarz; v: the latent variance, which the GP adds
    to the noise); likewise, given the prediction, mu_z, S_z (with c and the filter's predicted variance)
    and |dC_xz| <= sqrt(P_p) sd(e_g).
    These propagate to the posterior to first order (m = m_p + K (z - c m_p), K = c P_p / S,
    P = P_p - (c P_p)^2 / S, S = c^2 P_p + R); the bound is doubled for the second-order terms (products
    of the deviations). The GP-PF adds 4 Monte Carlo standard errors (sqrt(P/ESS) for the mean, P sqrt(2/ESS)
    for the variance)."""
    gf, gg = linear_gps
    q, r = float(gf.gp.noise_var[0]), float(gg.gp.noise_var[0])
    assert abs(q - SW ** 2) < 0.5 * SW ** 2 and abs(r - SV ** 2) < 0.5 * SV ** 2  # the noise was learned
    B = len(PRIORS)
    m = torch.tensor(PRIORS, dtype=F64).unsqueeze(-1)
    P = torch.full((B, 1, 1), P0, dtype=F64)
    z = torch.tensor([[1.5 * A * v + 0.3 * (-1) ** i] for i, v in enumerate(PRIORS)], dtype=F64)
    if name == "gp_adf":
        res = adf_step(gf, gg, m, P, z)
    elif name == "gp_ukf":
        res = ukf_step(gf, gg, m, P, z, alpha=1.0, beta=0.0, kappa=2.0, noise="mean")
    else:
        res = pf_step(gf, gg, m, P, z, 20_000, torch.Generator().manual_seed(5))
    sig = name == "gp_ukf"
    for i, m0 in enumerate(PRIORS):
        pm, pp, km, kp = _kalman(m0, float(z[i, 0]), q, r)
        d1f, d2f, vf = _deviation(gf, A, m0, P0, sig)
        e_mp = d1f
        e_pp = 2 * A * math.sqrt(P0) * d2f + d2f ** 2 + vf
        gm, gv = float(res.pred_mean[i, 0]), float(res.pred_cov[i, 0, 0])  # what the update averages over
        d1g, d2g, vg = _deviation(gg, C, gm, gv, sig)
        S = C * C * pp + r
        Cxz, K = C * pp, C * pp / S
        resid = abs(float(z[i, 0]) - C * pm)
        e_mz = d1g                                                # measurement stage, given the prediction
        e_S = 2 * C * math.sqrt(gv) * d2g + d2g ** 2 + vg
        e_C = math.sqrt(gv) * d2g
        # first order: m = m_p + K (z - c m_p), P = P_p - Cxz^2 / S with dK/dP_p = c R / S^2, dP/dP_p = (R/S)^2
        tol_m = 2 * (r / S * e_mp + (C * r / S ** 2 * e_pp + e_C / S + Cxz * e_S / S ** 2) * resid + K * e_mz)
        tol_P = 2 * ((r / S) ** 2 * e_pp + 2 * Cxz * e_C / S + Cxz ** 2 * e_S / S ** 2)
        mc_m = mc_P = 0.0
        if name == "gp_pf":
            ess = float(res.ess[i])
            mc_m, mc_P = 4 * math.sqrt(kp / ess), 4 * kp * math.sqrt(2 / ess)
        assert abs(float(res.mean[i, 0]) - km) <= tol_m + mc_m, (name, m0, float(res.mean[i, 0]), km, tol_m)
        assert abs(float(res.cov[i, 0, 0]) - kp) <= tol_P + mc_P, (name, m0, float(res.cov[i, 0, 0]), kp, tol_P)
        # not vacuous: the model part of the tolerance is below half the posterior's standard deviation (mean)
        # and below the posterior variance itself (the GPs' latent variance, a real difference, is in it)
        assert tol_m < 0.5 * math.sqrt(kp) and tol_P < kp, (tol_m, math.sqrt(kp), tol_P, kp)


def test_ukf_and_ekf_on_a_linear_model_are_the_kalman_filter():
    """With the true linear model (constant noise) the EKF and the UKF are the Kalman filter exactly."""
    f = AdditiveModel(lambda x: A * x, torch.tensor([[SW ** 2]], dtype=F64))
    g = AdditiveModel(lambda x: C * x, torch.tensor([[SV ** 2]], dtype=F64))
    m = torch.tensor(PRIORS, dtype=F64).unsqueeze(-1)
    P = torch.full((len(PRIORS), 1, 1), P0, dtype=F64)
    z = torch.tensor([[0.4 * i - 1.0] for i in range(len(PRIORS))], dtype=F64)
    for res in (ekf_step(f, g, m, P, z), ukf_step(f, g, m, P, z, noise="expected")):
        for i, m0 in enumerate(PRIORS):
            _, _, km, kp = _kalman(m0, float(z[i, 0]), SW ** 2, SV ** 2)
            assert float(res.mean[i, 0]) == pytest.approx(km, rel=1e-12, abs=1e-13)
            assert float(res.cov[i, 0, 0]) == pytest.approx(kp, rel=1e-12)


def test_gp_pf_reproducible_from_the_seed(linear_gps):
    gf, gg = linear_gps
    m = torch.tensor([[0.0], [1.0]], dtype=F64)
    P = torch.full((2, 1, 1), P0, dtype=F64)
    z = torch.tensor([[0.2], [1.1]], dtype=F64)
    a = pf_step(gf, gg, m, P, z, 300, torch.Generator().manual_seed(7))
    b = pf_step(gf, gg, m, P, z, 300, torch.Generator().manual_seed(7))
    c = pf_step(gf, gg, m, P, z, 300, torch.Generator().manual_seed(8))
    assert torch.equal(a.mean, b.mean) and torch.equal(a.particles, b.particles) and torch.equal(a.cov, b.cov)
    assert not torch.equal(a.mean, c.mean)
    # resampled particles are particles of the predicted set, drawn by the weights
    assert a.particles.shape == (2, 300, 1)


# ------------------------------------------------------------------------------------------ the study
def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return compose("config", overrides=["experiment=gp_bayes_filters", *overrides])


@pytest.mark.parametrize("override,message", [
    ("task.filters=[gp_adf,kf]", "task.filters[1]='kf' is not allowed; choose one of ['ekf', 'ukf', 'pf', 'gp_ekf', "
                                 "'gp_ukf', 'gp_ukf_mm', 'gp_pf', 'gp_adf']"),
    ("task.filters=[gp_adf,gp_adf]", "task.filters=['gp_adf', 'gp_adf'] lists ['gp_adf'] more than once"),
    ("task.train_range=[1.0,-1.0]", "task.train_range=[1.0, -1.0] must be [low, high] with finite low < high"),
    ("task.prior_std=0", "task.prior_std=0.0 must be > 0.0"),
    ("task.num_particles=0", "task.num_particles=0 must be >= 1"),
    ("task.ukf.kappa=-1.0", "task.ukf.kappa=-1.0 must be > -1"),
])
def test_bad_settings_refused_before_work(override, message):
    with pytest.raises(ConfigError) as info:
        validate_config(_compose(override))
    assert message in str(info.value) and "\n" not in str(info.value), str(info.value)


def test_small_run_orders_the_filters_as_the_paper(tmp_path):
    """The full benchmark (200 priors), fewer particles: GP-ADF's NLL_x far below GP-EKF's and the EKF's
    (both overconfident where the function bends), below GP-UKF's; GP-ADF's Mahalanobis distance below
    GP-EKF's and GP-UKF's; moment matching of the GP variance improves the GP-UKF's NLL_x."""
    from dslearn import api

    df = api.run("experiment=gp_bayes_filters", "task.num_particles=200")
    assert set(df["node"]) >= {"ekf", "ukf", "pf", "gp_ekf", "gp_ukf", "gp_ukf_mm", "gp_pf", "gp_adf"}
    mean = df[df["episode"] >= 0].groupby(["node", "metric"])["value"].mean()
    assert (df[(df["metric"] == "nll_x")].groupby("node").size() == 200).all()
    nll = mean.xs("nll_x", level="metric")
    maha = mean.xs("maha_x", level="metric")
    assert nll["gp_adf"] * 100 < nll["gp_ekf"] and nll["gp_adf"] * 100 < nll["ekf"]
    assert nll["gp_adf"] < nll["gp_ukf_mm"] < nll["gp_ukf"]
    assert maha["gp_adf"] < maha["gp_ukf"] < maha["gp_ekf"]
    again = api.run("experiment=gp_bayes_filters", "task.num_particles=200", "task.filters=[gp_pf]")
    a = df[df["node"] == "gp_pf"].reset_index(drop=True)
    b = again[again["node"] == "gp_pf"].reset_index(drop=True)
    keep = a["metric"] != "runtime_s"
    assert a[keep]["value"].tolist() == b[keep.values]["value"].tolist()  # a filter's numbers: its own stream
