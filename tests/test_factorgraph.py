"""Tests of the factor-graph identification / EKF-FG study (Jiang et al., ISITA 2022)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from dslearn.errors import ConfigError
from dslearn.factorgraph.centralized import gauss_newton, iterated_ekf_update
from dslearn.factorgraph.crlb import crlb, crlb_from_fisher, fisher_information
from dslearn.factorgraph.identification import compress_measurements, identify
from dslearn.factorgraph.messages import linearize, marginal, rho_from_zeta, zeta_moment, zeta_natural
from dslearn.factorgraph.scenario import SquaredRange
from dslearn.factorgraph.tracking import TrackState, ekf_fg_step

DT = torch.float64
SENSORS = torch.tensor([[-30.0, 50.0], [10.0, 5.0], [60.0, 20.0]], dtype=DT)


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


def _grid_moments(logp: torch.Tensor, grid: torch.Tensor) -> tuple[float, float]:
    w = torch.exp(logp - logp.max())
    w = w / w.sum()
    m = (w * grid).sum()
    return float(m), float((w * (grid - m) ** 2).sum())


# ---------------------------------------------------------------------------- messages
def test_zeta_matches_brute_force_marginalisation():
    """Eqs. 11-12: integrate the factor times the other variables' Gaussians on a grid (M = 2)."""
    lam = torch.tensor([[1.7, -0.6]], dtype=DT)
    y, s, gamma = torch.tensor([2.3], dtype=DT), torch.tensor([0.4], dtype=DT), torch.tensor([0.5], dtype=DT)
    rho_m = torch.tensor([[0.3, -1.2]], dtype=DT)
    rho_v = torch.tensor([[2.0, 0.7]], dtype=DT)
    prec, info = zeta_natural(lam, y, s, gamma, rho_m, rho_v)
    g1 = torch.linspace(-8, 8, 801, dtype=DT)
    g2 = torch.linspace(-9, 7, 801, dtype=DT)
    X1, X2 = torch.meshgrid(g1, g2, indexing="ij")
    # message to x1: int N(y; l1 x1 + l2 x2 + gamma, s) N(x2; rho_2) dx2
    logf = -0.5 * (y - lam[0, 0] * X1 - lam[0, 1] * X2 - gamma) ** 2 / s - 0.5 * (X2 - rho_m[0, 1]) ** 2 / rho_v[0, 1]
    m, v = _grid_moments(torch.logsumexp(logf, dim=1), g1)
    assert m == pytest.approx(float(info[0, 0] / prec[0, 0]), abs=1e-6)
    assert v == pytest.approx(float(1 / prec[0, 0]), rel=1e-4)
    # moment form of the paper gives the same message
    mm, mv = zeta_moment(lam, y, s, gamma, rho_m, rho_v)
    torch.testing.assert_close(mm, info / prec, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(mv, 1 / prec, rtol=1e-12, atol=1e-12)


def test_rho_and_marginal_are_gaussian_products():
    """Eqs. 13-16 against an explicit product of Gaussian densities on a grid."""
    g = _gen(1)
    prec = torch.rand(4, 3, generator=g, dtype=DT) + 0.2
    mean = torch.randn(4, 3, generator=g, dtype=DT)
    rho_m, rho_v, _ = rho_from_zeta(prec, prec * mean)
    mar_m, mar_v, _ = marginal(prec, prec * mean)
    grid = torch.linspace(-10, 10, 20001, dtype=DT)
    for m in range(3):
        logp_all = sum(-0.5 * prec[n, m] * (grid - mean[n, m]) ** 2 for n in range(4))
        mu, var = _grid_moments(logp_all, grid)
        assert mar_m[m].item() == pytest.approx(mu, abs=1e-7) and mar_v[m].item() == pytest.approx(var, rel=1e-5)
        for n in range(4):
            logp = logp_all + 0.5 * prec[n, m] * (grid - mean[n, m]) ** 2
            mu, var = _grid_moments(logp, grid)
            assert rho_m[n, m].item() == pytest.approx(mu, abs=1e-7)
            assert rho_v[n, m].item() == pytest.approx(var, rel=1e-5)


def test_linear_h_fixed_point_equals_exact_gaussian_product():
    """Linear h: the FG is exact (means), so the converged marginal = product of all likelihoods."""
    g = _gen(2)
    N, M = 6, 3
    A = torch.randn(N, M, generator=g, dtype=DT)
    b = torch.randn(N, generator=g, dtype=DT)
    h = lambda x: x @ A.T + b  # noqa: E731
    x_true = torch.tensor([1.0, -2.0, 0.5], dtype=DT)
    y_var = 0.05 + torch.rand(N, generator=g, dtype=DT)
    y = h(x_true) + y_var.sqrt() * torch.randn(N, generator=g, dtype=DT)
    res = identify(h, y, y_var, torch.zeros(M, dtype=DT), torch.zeros(M, dtype=DT), 300, init_var=10.0)
    info_mat = A.T @ (A / y_var[:, None])
    exact = torch.linalg.solve(info_mat, A.T @ ((y - b) / y_var))
    torch.testing.assert_close(res.mean[-1], exact, rtol=0, atol=1e-8)
    # Gaussian BP variances are at most the exact marginal variances here (overconfident)
    assert bool((res.var[-1] <= torch.linalg.inv(info_mat).diagonal() + 1e-12).all())


def test_taylor_coefficients_match_autograd_and_closed_form():
    """Eqs. 8-9 by autograd vs the paper's closed forms Eqs. 24-26 and vs finite differences."""
    h = SquaredRange(SENSORS)
    beta = torch.tensor([[6.3, -1.1], [40.0, -22.0]], dtype=DT)
    lam, gamma = linearize(h, beta)
    A, B = SENSORS[:, 0], SENSORS[:, 1]
    b1, b2 = beta[:, :1], beta[:, 1:]
    torch.testing.assert_close(lam[..., 0], -2 * (A - b1))
    torch.testing.assert_close(lam[..., 1], -2 * (B - b2))
    torch.testing.assert_close(gamma, A**2 - b1**2 + B**2 - b2**2)
    # a general nonlinear h against central finite differences
    f = lambda x: torch.stack([torch.sin(x[..., 0]) * x[..., 1], torch.exp(0.3 * x[..., 1]) + x[..., 0] ** 3], -1)  # noqa: E731
    x0 = torch.tensor([0.4, -0.7], dtype=DT)
    lam, gamma = linearize(f, x0)
    eps = 1e-6
    fd = torch.stack([(f(x0 + eps * e) - f(x0 - eps * e)) / (2 * eps) for e in torch.eye(2, dtype=DT)], -1)
    torch.testing.assert_close(lam, fd, rtol=1e-7, atol=1e-8)
    torch.testing.assert_close(gamma, f(x0) - lam @ x0)


def test_noise_free_convergence_and_batched_sources():
    """Noise-free linearised data: iterations converge to the truth; sources are a batch dim."""
    h = SquaredRange(SENSORS)
    truth = torch.tensor([[[8.0, -3.0], [30.0, -15.0]]], dtype=DT)    # (B=1, I=2, M=2)
    y = h(truth)                                                        # (1, 2, N)
    res = identify(h, y, torch.full_like(y, 1e-6), truth + 0.0, torch.zeros(2, dtype=DT), 60)
    torch.testing.assert_close(res.mean[-1], truth, rtol=0, atol=1e-6)
    # the error shrinks over the iterations (at the expansion point = truth the FG is exact)
    err = (res.mean - truth).norm(dim=-1).amax((-1, -2))
    assert err[-1] < 1e-6 * err[0]
    assert bool((res.iters_to_converge <= 60).all())
    # relinearising from a wrong expansion point also reaches the truth (Gauss-Newton-like)
    res2 = identify(h, y, torch.full_like(y, 1e-6), truth + 1.5, truth + 1.5, 60, relinearize=True)
    torch.testing.assert_close(res2.mean[-1], truth, rtol=0, atol=1e-6)


def test_zero_lambda_sensor_is_skipped_and_reported():
    """A sensor with lambda = 0 for a parameter sends a flat message; no division by zero."""
    A = torch.tensor([[1.0, 0.0], [1.0, 1.0], [0.0, 2.0]], dtype=DT)
    h = lambda x: x @ A.T  # noqa: E731
    x_true = torch.tensor([0.7, -1.3], dtype=DT)
    y = h(x_true)
    res = identify(h, y, torch.full((3,), 1e-4, dtype=DT), torch.zeros(2, dtype=DT), torch.zeros(2, dtype=DT), 100)
    assert int(res.near_zero_lambda) == 2
    assert torch.isfinite(res.mean).all() and torch.isfinite(res.var).all()
    torch.testing.assert_close(res.mean[-1], x_true, rtol=0, atol=1e-8)
    # a parameter no sensor sees keeps the guess, floors are counted
    A0 = torch.tensor([[1.0, 0.0], [2.0, 0.0]], dtype=DT)
    res0 = identify(lambda x: x @ A0.T, torch.tensor([1.0, 2.0], dtype=DT), torch.full((2,), 0.1, dtype=DT),
                    torch.zeros(2, dtype=DT), torch.tensor([0.0, 5.0], dtype=DT), 5)
    assert torch.isfinite(res0.mean).all() and res0.mean[-1, 1].item() == 5.0 and int(res0.floored) > 0
    assert res0.mean[-1, 0].item() == pytest.approx(1.0)


# ---------------------------------------------------------------------------- CRLB
def test_crlb_matches_monte_carlo_fisher_information():
    """Eq. 31: E[score score^T] by Monte Carlo on a small case equals L/sigma^2 J^T J."""
    h = SquaredRange(SENSORS)
    x = torch.tensor([5.0, -2.0], dtype=DT)
    L, sigma = 4, 3.0
    g = _gen(3)
    R = 20000
    y = h(x)[None, :, None] + sigma * torch.randn(R, 3, L, generator=g, dtype=DT)
    xr = x.expand(R, 2).clone().requires_grad_(True)
    loglik = (-0.5 * (y - h(xr)[..., None]) ** 2 / sigma**2).sum((-1, -2))
    score = torch.autograd.grad(loglik.sum(), xr)[0]                  # (R, 2)
    F_mc = score.T @ score / R
    J = torch.autograd.functional.jacobian(h, x)
    F = fisher_information(J, sigma, L)
    torch.testing.assert_close(F_mc, F, rtol=0.05, atol=0.02 * float(F.diagonal().max()))
    bound = crlb(h, x, sigma, L)
    assert bound.item() == pytest.approx(torch.linalg.inv(F).trace().item() / 2, rel=1e-10)
    # Eq. 33 as printed is 1 / (M tr F), a different (smaller) number
    assert crlb_from_fisher(F, "paper_eq33").item() == pytest.approx(1 / (2 * F.trace().item()))
    # the centralised Gauss-Newton ML estimate attains the bound (per-parameter MSE)
    x_hat = gauss_newton(h, y[:4000], x.expand(4000, 2), 5)
    mse = (x_hat - x).square().mean().item()
    assert mse == pytest.approx(bound.item(), rel=0.1)


def test_singular_fisher_gives_infinite_bound():
    J = torch.tensor([[1.0, 2.0], [2.0, 4.0]], dtype=DT)
    assert math.isinf(crlb_from_fisher(fisher_information(J, 1.0, 3)).item())


# ---------------------------------------------------------------------------- tracking / baselines
def test_ekf_fg_step_is_gaussian_product():
    st = TrackState(*(torch.tensor([v], dtype=DT) for v in (1.0, 0.5, 0.2, 0.3)))
    new = ekf_fg_step(st, torch.tensor([1.5], dtype=DT), torch.tensor([0.1], dtype=DT), 0.2, 0.05)
    Pp = 0.5 + 0.3 + 0.2
    P = 1 / (1 / Pp + 1 / 0.1)
    m = P * (1.2 / Pp + 1.5 / 0.1)
    assert new.x_mean.item() == pytest.approx(m) and new.x_var.item() == pytest.approx(P)
    Pv, rv = 0.35, P + 0.5
    assert new.v_var.item() == pytest.approx(1 / (1 / Pv + 1 / rv))
    assert new.v_mean.item() == pytest.approx(new.v_var.item() * (0.2 / Pv + (m - 1.0) / rv))


def test_iekf_with_linear_h_is_kalman_update():
    A = torch.tensor([[1.0, 0.5], [0.0, 2.0], [1.0, -1.0]], dtype=DT)
    h = lambda x: x @ A.T  # noqa: E731
    g = _gen(4)
    mean = torch.randn(4, generator=g, dtype=DT)
    Q = torch.randn(4, 4, generator=g, dtype=DT)
    cov = Q @ Q.T + torch.eye(4, dtype=DT)
    samples = torch.randn(3, 5, generator=g, dtype=DT)
    z, P = iterated_ekf_update(h, samples, 0.7, mean, cov, 3)
    H = torch.cat([A, torch.zeros_like(A)], -1)
    R = 0.49 / 5 * torch.eye(3, dtype=DT)
    K = cov @ H.T @ torch.linalg.inv(H @ cov @ H.T + R)
    torch.testing.assert_close(z, mean + K @ (samples.mean(-1) - H @ mean))
    torch.testing.assert_close(P, (torch.eye(4, dtype=DT) - K @ H) @ cov)


# ---------------------------------------------------------------------------- bad input
def test_bad_sample_counts_and_noise():
    with pytest.raises(ConfigError, match="num_samples"):
        compress_measurements(torch.zeros(3, 1, dtype=DT))
    with pytest.raises(ConfigError, match="sigma_y"):
        compress_measurements(torch.zeros(3, 5, dtype=DT), noise_var=0.0)
    with pytest.raises(ConfigError, match="num_samples"):
        fisher_information(torch.ones(3, 2, dtype=DT), 1.0, 0)
    with pytest.raises(ConfigError, match="sigma_y"):
        fisher_information(torch.ones(3, 2, dtype=DT), -1.0, 5)
    with pytest.raises(ConfigError, match="num_iters"):
        identify(lambda x: x, torch.zeros(2, dtype=DT), torch.ones(2, dtype=DT), torch.zeros(2, dtype=DT),
                 torch.zeros(2, dtype=DT), 0)


# ---------------------------------------------------------------------------- study end-to-end
def _cfg(**over):
    task = OmegaConf.load("conf/task/jiang_fg.yaml")
    task.mc_runs = 3
    task.scenario.num_timings = 6
    task.num_samples = 10
    task.figures.fig2_iterations = [1, 10]
    task.figures.fig5_sigma_y = [1.0, 5.0]
    task.figures.fig3_episodes = 1
    for k, v in over.items():
        OmegaConf.update(task, k, v)
    return OmegaConf.create({"seed": 0, "device": "cpu", "dtype": "float64", "progress": False, "task": task})


def test_study_run_and_report(tmp_path):
    from dslearn.studies import jiang_fg

    df = jiang_fg.run(_cfg())
    for col in ("metric", "value", "episode", "model", "consensus", "node", "iteration", "timing", "sigma_y",
                "figure"):
        assert col in df.columns
    assert set(df["figure"]) == {"fig2", "fig3", "fig4", "fig5", "diag"}
    assert {"crlb", "centralized_gn", "centralized_ekf", "ekf_fg", "fg_identification"} <= set(df["model"])
    rm = df[(df["metric"] == "rmse") & (df["variant"] == "paper")]
    assert np.isfinite(rm["value"]).all() and (rm["value"] >= 0).all()
    # reproducible from the seed
    df2 = jiang_fg.run(_cfg())
    np.testing.assert_array_equal(df["value"].values[:-1], df2["value"].values[:-1])  # last row: runtime
    # the centralised ML estimate sits near the CRLB
    f5 = rm[rm["figure"] == "fig5"].groupby(["sigma_y", "model"])["value"].apply(lambda v: np.sqrt((v**2).mean()))
    assert f5[(5.0, "centralized_gn")] < 3 * f5[(5.0, "crlb")]
    df["task"] = "jiang_fg"
    text = jiang_fg.report(df, None, tmp_path)
    assert "Fig. 2" in text and "Fig. 5" in text
    for name in ("fig2", "fig3", "fig4", "fig5"):
        assert (tmp_path / f"jiang_fg_{name}.png").exists() and (tmp_path / f"jiang_fg_{name}.csv").exists()


@pytest.mark.parametrize("field,value", [("mc_runs", 0), ("num_samples", 1), ("sigma_y", -1.0),
                                         ("max_iter", 0), ("fg.crlb_form", "bogus"), ("scenario.sensors", []),
                                         ("figures.fig5_sigma_y", [0.0]), ("fg.init_guess", [0.0])])
def test_study_rejects_bad_config(field, value):
    from dslearn.studies import jiang_fg

    with pytest.raises(ConfigError, match=field.split(".")[-1]):
        jiang_fg.run(_cfg(**{field: value}))


def test_small_cholesky_matches_torch():
    from dslearn.factorgraph.linalg import cholesky, cholesky_solve

    g = _gen(5)
    for D in (1, 2, 3, 5):
        X = torch.randn(7, D, D + 2, generator=g, dtype=DT)
        A = X @ X.transpose(-1, -2) + 0.1 * torch.eye(D, dtype=DT)
        L = cholesky(A)
        torch.testing.assert_close(L, torch.linalg.cholesky(A))
        b = torch.randn(7, D, 2, generator=g, dtype=DT)
        torch.testing.assert_close(cholesky_solve(b, L), torch.linalg.solve(A, b))
