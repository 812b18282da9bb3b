"""The GP-Bayes filter family on the network: the GP-ADF prediction step (``filter=adf``,
:mod:`dslearn.filters.adf`) and the GP-UKF with moment matching (``filter=ukf_mm``,
``filter.predict.expected_variance``).

The ADF's mean and covariance are checked against a Monte Carlo of the GP predictive, against the single-node
exact moments of :func:`dslearn.filters.gp_moments.predictive_moments` (an independent implementation) when every
output shares the kernel, and against the EKF in the small-covariance limit; masked data points, the kept
data-only terms (extended per appended point) and the refusals of models without the moments are checked too.
The UKF option is checked against a hand-computed unscented average, and to be the UKF exactly when off.
"""

from __future__ import annotations

import math

import pandas as pd
import pytest
import torch
from hydra import compose, initialize_config_dir

from dslearn import api
from dslearn.compose import build_motion_model, build_network, build_predict, build_scenario
from dslearn.conf_paths import CONF_DIR
from dslearn.errors import ConfigError
from dslearn.filters import adf
from dslearn.filters.adf import ALLOWED_MODELS, MomentMatchingPredict, adf_misfit, adf_predict, belief_moments
from dslearn.filters.gp_moments import predictive_moments
from dslearn.filters.information import predict as ekf_predict
from dslearn.filters.ukf import UnscentedPredict, ukf_predict
from dslearn.models import ConstantVelocity, GPMotionModel
from dslearn.types import StepContext
from test_task_groups import _cli  # dslearn-run in process: (exit code, stderr lines)

D = torch.float64
CTX = StepContext(dt=0.25)
S, DX, N = 2, 4, 20
OS, LS, NOISE = 0.6, 0.9, 0.2  # sigma_f, l, sigma_eps


def make_gp(mean="identity", noise="latent", points=N, seed=0, mask=True, os=OS, ls=LS, factor="auto"):
    """Two nodes, a 4-dim state, ``points`` random data per node (about a fifth of them masked)."""
    gp = GPMotionModel(DX, S, outputscale=os, lengthscale=ls, noise_std=NOISE, mean=mean, noise=noise, factor=factor)
    g = torch.Generator().manual_seed(seed)
    X = torch.randn(S, points, DX, generator=g, dtype=D)
    Y = X + 0.4 * torch.sin(2.0 * X.roll(1, -1)) + 0.05 * torch.randn(S, points, DX, generator=g, dtype=D)
    valid = torch.rand(S, points, generator=g) > 0.2 if mask else None
    gp.gp.set_data(X, Y, valid)
    if noise == "adaptive":  # learned (position, velocity) variances, distinct per node
        gp.q_noise.copy_(torch.tensor([[0.03, 0.07], [0.02, 0.05]], dtype=D))
    return gp


def beliefs(b=1, seed=1, scale=0.5):
    """``(S, b, Dx)`` means near the data and ``(S, b, Dx, Dx)`` covariances of about ``scale``^2."""
    g = torch.Generator().manual_seed(seed)
    m = 0.5 * torch.randn(S, b, DX, generator=g, dtype=D)
    a = torch.randn(S, b, DX, DX, generator=g, dtype=D)
    P = scale**2 * (a @ a.transpose(-1, -2) / DX + 0.3 * torch.eye(DX, dtype=D))
    return m, P


def run_adf(model, m, P, full=True):
    return adf_predict(m, torch.linalg.inv(P), model, CTX, full=full)


# ------------------------------------------------------------------------------------------ Monte Carlo
@pytest.mark.parametrize("mean,noise", [("identity", "latent"), ("zero", "latent"), ("zero", "predictive"),
                                        ("identity", "adaptive")])
def test_mean_and_covariance_equal_a_monte_carlo_of_the_gp_predictive(mean, noise):
    """y ~ N(m, P), f ~ N(mu(y), sigma^2(y) I + the noise mode's terms): mean, covariance and Cov(f, y) = F P of the
    ADF within 4 standard errors of 1e5 samples per node; the EKF's covariance is far outside them (the test sees
    the difference)."""
    model = make_gp(mean, noise)
    m, P = beliefs()
    y_pred, _, _, P_pred, F, _ = run_adf(model, m, P)
    k = 100_000
    g = torch.Generator().manual_seed(7)
    y = m + (torch.linalg.cholesky(P) @ torch.randn(S, 1, DX, k, generator=g, dtype=D)).transpose(-1, -2)[:, 0]
    mu, var, _ = model.gp.predict(y, jacobian=False)  # (S, k, Dx), (S, k)
    sd = var.unsqueeze(-1)
    if noise == "predictive":
        sd = sd + NOISE**2
    sd = (sd + model.extra_noise(y).unsqueeze(1)).sqrt()
    f = mu + sd * torch.randn(S, k, DX, generator=g, dtype=D)
    df, dy = f - f.mean(1, keepdim=True), y - y.mean(1, keepdim=True)
    se = lambda z: z.std(1) / math.sqrt(k)  # noqa: E731

    assert ((f.mean(1) - y_pred[:, 0]).abs() <= 4 * se(f)).all()
    prod = df.unsqueeze(-1) * df.unsqueeze(-2)  # (S, k, Dx, Dx)
    cov = prod.mean(1) * k / (k - 1)
    assert ((cov - P_pred[:, 0]).abs() <= 4 * se(prod)).all(), (cov - P_pred[:, 0]).abs() / se(prod)
    cross = df.unsqueeze(-1) * dy.unsqueeze(-2)  # Cov(f, y) = F P (Stein)
    assert ((cross.mean(1) * k / (k - 1) - (F @ P)[:, 0]).abs() <= 4 * se(cross)).all()
    # the EKF's covariance at the same belief: outside the Monte Carlo's band
    P_ekf = ekf_predict(m, torch.linalg.inv(P), model, CTX, full=True)[3]
    assert ((cov - P_ekf[:, 0]).abs() / se(prod)).max() > 10


# ------------------------------------------------------------------------------------------ exact references
@pytest.mark.parametrize("mean", ["zero", "identity"])
@pytest.mark.parametrize("noise", ["latent", "predictive"])
def test_equals_the_single_node_exact_moments_with_a_shared_kernel(mean, noise):
    """predictive_moments (SE-ARD, per output; Deisenroth et al.) with every output's lengthscales equal to the
    node's, on the node's valid points: the same mean, covariance and cross-covariance to 1e-10. With the identity
    prior mean f = y + g(y): mean m + E[g], covariance P + Cov(y, g) + Cov(g, y) + Cov(g), Cov(y, f) = P + Cov(y, g)."""
    model = make_gp(mean, noise)
    m, P = beliefs(b=3)
    y_pred, _, _, P_pred, F, _ = run_adf(model, m, P)
    X, _, valid = model.gp.data()
    for s in range(S):
        Xs, al = X[s][valid[s]], model.gp.alpha[s][valid[s]].T  # (n_s, Dx), (E, n_s)
        n = Xs.shape[0]
        sf2, ls, sn2 = (float(h[s]) for h in (model.gp.outputscale, model.gp.lengthscale, model.gp.noise_var))
        # the GP's own values (its noise is rounded through float32, its output scale through a softplus)
        assert abs(sf2 - OS**2) < 1e-12 and abs(ls - LS) < 1e-12 and abs(sn2 - NOISE**2) < 1e-8
        K = sf2 * torch.exp(-0.5 * (Xs.unsqueeze(1) - Xs).pow(2).sum(-1) / ls**2) + sn2 * torch.eye(n, dtype=D)
        pm, pc, cr = predictive_moments(m[s], P[s], Xs, al, torch.full((DX, DX), ls, dtype=D),
                                        torch.full((DX,), sf2, dtype=D), torch.full((DX,), sn2, dtype=D),
                                        torch.linalg.cholesky(K).expand(DX, n, n), include_noise=noise == "predictive")
        if mean == "identity":
            pm, pc, cr = m[s] + pm, P[s] + cr + cr.transpose(-1, -2) + pc, P[s] + cr
        torch.testing.assert_close(y_pred[s], pm, rtol=0, atol=1e-10)
        torch.testing.assert_close(P_pred[s], pc, rtol=0, atol=1e-10)
        torch.testing.assert_close(P[s] @ F[s].transpose(-1, -2), cr, rtol=0, atol=1e-10)


@pytest.mark.parametrize("noise", ["latent", "predictive", "adaptive"])
@pytest.mark.parametrize("mean", ["zero", "identity"])
def test_a_vanishing_covariance_gives_the_ekf(mean, noise):
    """P -> 0: the mean is the GP mean at the belief's mean, F its Jacobian, the predicted covariance the model's
    Q there (latent variance plus the noise mode's terms): the EKF step's numbers."""
    model = make_gp(mean, noise)
    m, _ = beliefs(b=2)
    eps = 1e-9  # the differences are O(eps) (curvature times P): 100 eps allowed
    P = eps * torch.eye(DX, dtype=D).expand(S, 2, DX, DX)
    y_pred, _, _, P_pred, F, Q = run_adf(model, m, P)
    y_e, _, _, P_e, F_e, Q_e = ekf_predict(m, torch.linalg.inv(P), model, CTX, full=True)
    for u, v in ((y_pred, y_e), (F, F_e), (P_pred, P_e), (Q, Q_e)):  # Q: F P F^T is O(eps)
        torch.testing.assert_close(u, v, rtol=0, atol=100 * eps)
    _, _, _, var = belief_moments(model.gp, m, P)
    torch.testing.assert_close(var, model.gp.predict(m, jacobian=False)[1], rtol=0, atol=100 * eps)
    assert (P_e.diagonal(dim1=-2, dim2=-1) > 1e3 * eps).all()  # a latent variance that is not itself O(eps)


def test_no_data_gives_the_prior_mean_and_the_prior_variance():
    """An empty data set: f = m(y) + w, w ~ N(0, sigma_f^2 I): y_pred = A m, P_pred = A P A^T + sigma_f^2 I."""
    model = GPMotionModel(DX, S, outputscale=OS, lengthscale=LS, noise_std=NOISE, mean="identity")
    m, P = beliefs()
    y_pred, _, _, P_pred, F, Q = run_adf(model, m, P)
    torch.testing.assert_close(y_pred, m, rtol=0, atol=1e-12)
    torch.testing.assert_close(P_pred, P + OS**2 * torch.eye(DX, dtype=D), rtol=0, atol=1e-12)
    torch.testing.assert_close(F, torch.eye(DX, dtype=D).expand_as(P), rtol=0, atol=0)
    torch.testing.assert_close(Q, OS**2 * torch.eye(DX, dtype=D).expand_as(P), rtol=0, atol=1e-12)


def test_the_linearised_model_reproduces_the_predicted_covariance():
    """full=True: F = Cov(f, y) P^{-1} and Q = P_pred - F P F^T, positive semi-definite (a Schur complement)."""
    model = make_gp("identity", "latent")
    m, P = beliefs(b=4, scale=1.0)
    _, _, omega_pred, P_pred, F, Q = run_adf(model, m, P)
    torch.testing.assert_close(F @ P @ F.transpose(-1, -2) + Q, P_pred, rtol=0, atol=1e-12)
    assert (torch.linalg.eigvalsh(Q) > 0).all()
    torch.testing.assert_close(omega_pred @ P_pred, torch.eye(DX, dtype=D).expand_as(P), rtol=0, atol=1e-10)


# ------------------------------------------------------------------------------------------ data handling
def test_masked_points_make_no_difference():
    """The valid points alone, or the same points among masked ones (any inputs, any targets): the same moments."""
    g = torch.Generator().manual_seed(3)
    X = torch.randn(S, 12, DX, generator=g, dtype=D)
    Y = X + 0.3 * torch.tanh(X)
    junk = 3.0 * torch.randn(S, 7, DX, generator=g, dtype=D)
    a = GPMotionModel(DX, S, outputscale=OS, lengthscale=LS, noise_std=NOISE, mean="identity")
    a.gp.set_data(X, Y)
    b = GPMotionModel(DX, S, outputscale=OS, lengthscale=LS, noise_std=NOISE, mean="identity")
    order = torch.randperm(19, generator=g)
    Xb, Yb = torch.cat([X, junk], 1)[:, order], torch.cat([Y, -junk], 1)[:, order]
    b.gp.set_data(Xb, Yb, (order < 12).expand(S, -1))
    m, P = beliefs(b=3)
    for u, v in zip(run_adf(a, m, P), run_adf(b, m, P)):
        torch.testing.assert_close(u, v, rtol=0, atol=1e-12)
    # appended one by one, invalid ones among them: the kept terms follow (and agree with the rebuilt ones)
    c = GPMotionModel(DX, S, outputscale=OS, lengthscale=LS, noise_std=NOISE, mean="identity")
    for i in range(19):
        c.add_data(Xb[:, i], Yb[:, i], (order[i] < 12).expand(S))
        run_adf(c, m, P)
    for u, v in zip(run_adf(a, m, P), run_adf(c, m, P)):
        torch.testing.assert_close(u, v, rtol=0, atol=1e-11)


@pytest.mark.parametrize("factor", ["inverse", "cholesky"])
def test_the_kept_terms_extended_per_point_equal_the_rebuilt_ones(factor):
    """gram() keeps (K + s^2 I)^{-1} and the data-only kernel factor between calls and extends them by one row per
    appended point: equal to a rebuild from scratch; a change of hyperparameters rebuilds them."""
    model = make_gp("identity", "latent", points=5, factor=factor)
    m, P = beliefs(b=2)
    g = torch.Generator().manual_seed(5)
    for t in range(30):
        x = torch.randn(S, DX, generator=g, dtype=D)
        model.add_data(x, x + 0.1 * torch.sin(x), torch.tensor([True, t % 4 != 0]))
        kept = run_adf(model, m, P)
    gr = adf._GRAMS[model.gp]
    X, _, valid = model.gp.data()
    n = X.shape[1]
    K = OS**2 * torch.exp(-0.5 * (X.unsqueeze(2) - X.unsqueeze(1)).pow(2).sum(-1) / LS**2)
    K = torch.where(valid.unsqueeze(-1) & valid.unsqueeze(-2), K, torch.zeros_like(K))  # invalid: decoupled unit rows
    K = K + torch.diag_embed(torch.where(valid, model.gp.noise_var.unsqueeze(-1), torch.ones_like(K[..., 0])))
    assert gr.Kinv.shape == (S, n, n)
    torch.testing.assert_close(gr.Kinv, torch.linalg.inv(K), rtol=0, atol=1e-11)
    G = torch.exp(-0.25 * (X.unsqueeze(2) - X.unsqueeze(1)).pow(2).sum(-1) / LS**2)
    G = G * (valid.unsqueeze(-1) & valid.unsqueeze(-2))
    torch.testing.assert_close(gr.G, G, rtol=0, atol=1e-14)
    adf._GRAMS.clear()
    for u, v in zip(kept, run_adf(model, m, P)):
        torch.testing.assert_close(u, v, rtol=0, atol=1e-11)
    # new hyperparameters (a refit): rebuilt, not extended
    model.gp.covar_module.base_kernel.lengthscale = torch.full((S, 1, 1), 1.3, dtype=D)
    model.gp.refactorize()
    after = run_adf(model, m, P)
    adf._GRAMS.clear()
    for u, v in zip(after, run_adf(model, m, P)):
        torch.testing.assert_close(u, v, rtol=0, atol=1e-12)
    assert not torch.allclose(after[0], kept[0])


def test_batches_and_chunks_do_not_change_the_numbers(monkeypatch):
    """Many queries at once, in chunks of one query and one node, or one query at a time: the same numbers."""
    model = make_gp("identity", "latent")
    m, P = beliefs(b=5)
    whole = run_adf(model, m, P)
    monkeypatch.setattr(adf, "CHUNK_ELEMENTS", 1)
    for u, v in zip(whole, run_adf(model, m, P)):
        torch.testing.assert_close(u, v, rtol=0, atol=1e-13)
    for b in range(5):
        one = run_adf(model, m[:, b : b + 1], P[:, b : b + 1])
        for u, v in zip(whole, one):
            torch.testing.assert_close(u[:, b : b + 1], v, rtol=0, atol=1e-13)


# ------------------------------------------------------------------------------------------ refusals
def test_models_without_exact_moments_are_refused():
    msg = ("filter=adf (the GP-ADF prediction step) needs the exact GP motion model: "
           "model=gp|gp_increment|gp_adaptive|gp_cv")
    m, P = beliefs()
    with pytest.raises(ConfigError, match=msg.replace("(", r"\(").replace(")", r"\)").replace("|", r"\|")):
        MomentMatchingPredict()(m, torch.linalg.inv(P), ConstantVelocity(1), CTX)
    window = GPMotionModel(DX, S, variant="window", window=8)
    assert "model=gp_window (model.variant=window) has no exact predictive moments" in adf_misfit(window, "gp_window")
    assert adf_misfit(make_gp()) is None
    with pytest.raises(ConfigError) as e:  # the start-up check of a run
        api.compose("filter=adf", "model=lin")
    assert str(e.value).startswith(msg) and "model=lin has no exact predictive moments" in str(e.value)
    with pytest.raises(ConfigError, match="model=gp_sgpr"):
        api.compose("filter=adf", "model=gp_sgpr")
    with pytest.raises(ConfigError, match="model=lin has no exact"):  # task=yu_faults: every model of its grid
        api.compose("experiment=yu_faults", "filter=adf")
    api.compose("experiment=yu_faults", "filter=adf", "task.models=[gp_increment,gp_cv]")


def test_the_allowed_models_are_exactly_the_exact_gp_options():
    """Every conf/model option built for the Yu scenario: the ADF takes it iff it is listed in ALLOWED_MODELS."""
    cfg = api.compose()
    scenario, network = build_scenario(cfg), build_network(cfg)
    options = sorted(p.stem for p in (CONF_DIR / "model").glob("*.yaml"))
    from dslearn.compose import group_options

    nodes = group_options("model", options)
    fits = {name for name, node in nodes.items()
            if adf_misfit(build_motion_model(node, scenario, network, D, torch.device("meta"))) is None}
    assert fits == set(ALLOWED_MODELS)


def test_a_matrix_cell_with_a_model_without_moments_is_na():
    """The matrix sweeper lists filter=adf with model=lin as n/a with the reason; with the GP it is a job."""
    from dslearn.schemas.matrix import select_cells

    combos = [["task=matrix", "method=ekf_lin_hybrid", "filter=adf", "scenario=yu_two_agents"],
              ["task=matrix", "method=ekf_gp_hybrid", "filter=adf", "scenario=yu_two_agents"]]
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        kept, records = select_cells(combos, lambda ov: compose("config", overrides=list(ov)))
    assert kept == [combos[1]]
    assert records[0]["job"] is None and records[0]["method"] == "adf lin hybrid"
    assert records[0]["reason"].startswith("adf lin hybrid does not fit scenario yu: filter=adf (the GP-ADF")
    assert records[1]["job"] == 0 and records[1]["method"] == "adf gp_increment hybrid" and records[1]["reason"] is None


def test_the_memory_guard_counts_the_kept_terms():
    """filter=adf adds its two (S, cap, cap) float64 buffers per node (cap about 1.5 n, n = train episodes x steps)
    to the run's estimated peak memory; other filters add nothing."""
    from dslearn.schemas.core import estimate_core_memory

    assert "adf" not in estimate_core_memory(api.compose())
    small = estimate_core_memory(api.compose("filter=adf", "data.train_episodes=10", "data.test_episodes=1"))["adf"]
    big = estimate_core_memory(api.compose("filter=adf", "data.train_episodes=100", "data.test_episodes=1"))["adf"]
    n = 100 * 12  # the Yu scenario: 12 steps per episode; 10 nodes
    assert 10 * 2 * (1.5 * n) ** 2 * 8 <= big <= 10 * 2 * (1.5 * n + 64) ** 2 * 8 + 4 * adf.CHUNK_ELEMENTS * 8
    assert 50 < big / small < 100  # quadratic in the data (the temporaries aside)


# ------------------------------------------------------------------------------------------ GP-UKF option
def test_ukf_expected_variance_is_the_hand_computed_unscented_average():
    """Q = sum_k w_k Sigma_f(chi_k) I on a small case (S = 2, Dx = 4, one belief), sigma points and weights by
    hand; the rest of the step is the UKF's."""
    model = make_gp("identity", "latent")
    m, P = beliefs()
    omega = torch.linalg.inv(P)
    for alpha, beta, kappa in ((1.0, 2.0, 0.0), (0.5, 2.0, 1.0)):
        lam = alpha**2 * (DX + kappa) - DX
        w = torch.full((2 * DX + 1,), 0.5 / (DX + lam), dtype=D)
        w[0] = lam / (DX + lam)
        L = torch.linalg.cholesky(torch.linalg.inv(omega))[:, 0]  # (S, Dx, Dx)
        off = math.sqrt(DX + lam) * L.transpose(-1, -2)  # rows: columns of L
        pts = torch.cat([m, m + off, m - off], 1)  # (S, 2Dx+1, Dx)
        var = model.gp.predict(pts, jacobian=False)[1]  # (S, 2Dx+1)
        Q_hand = (var * w).sum(-1).reshape(S, 1, 1, 1) * torch.eye(DX, dtype=D)
        step = UnscentedPredict(alpha, beta, kappa, expected_variance=True)
        y, _, _, P_mm, _, Q = step(m, omega, model, CTX, full=True)
        y0, _, _, P_0, _, Q0 = UnscentedPredict(alpha, beta, kappa)(m, omega, model, CTX, full=True)
        torch.testing.assert_close(Q, Q_hand, rtol=0, atol=1e-13)
        torch.testing.assert_close(y, y0, rtol=0, atol=0)
        torch.testing.assert_close(P_mm - P_0, Q_hand - Q0, rtol=0, atol=1e-13)
        assert not torch.allclose(Q, Q0)  # the option does something here
        assert step.name == "ukf_mm"


def test_ukf_without_expected_variance_is_the_ukf_bit_for_bit():
    """expected_variance=false (filter=ukf's value): the same tensors as the UKF step with its defaults, whose Q is
    the model's at the prior mean, exactly."""
    model = make_gp("identity", "latent")
    m, P = beliefs(b=3)
    omega = torch.linalg.inv(P)
    step = build_predict(api.compose("filter=ukf"))
    assert step == UnscentedPredict() and step.expected_variance is False and step.name == "ukf"
    a = step(m, omega, model, CTX, full=True)
    b = ukf_predict(m, omega, model, CTX, full=True)
    assert all(torch.equal(u, v) for u, v in zip(a, b))
    assert torch.equal(a[5], model.noise_cov(m, CTX))
    mm = build_predict(api.compose("filter=ukf_mm"))
    assert mm == UnscentedPredict(expected_variance=True)


def test_ukf_expected_variance_is_refused_without_a_gp():
    m, P = beliefs()
    key = "filter.predict.expected_variance=true (filter=ukf_mm)"
    with pytest.raises(ConfigError, match=r"filter\.predict\.expected_variance=true \(filter=ukf_mm\)"):
        UnscentedPredict(expected_variance=True)(m, torch.linalg.inv(P), ConstantVelocity(1), CTX)
    with pytest.raises(ConfigError) as e:
        api.compose("filter=ukf_mm", "model=lin")
    assert str(e.value).startswith(key) and "model=lin has no state-dependent process noise" in str(e.value)
    with pytest.raises(ConfigError, match="filter.predict.expected_variance='yes' must be true or false"):
        api.compose("filter=ukf", "filter.predict.expected_variance=yes")
    UnscentedPredict()(m, torch.linalg.inv(P), ConstantVelocity(1), CTX)  # off: any model
    api.compose("filter=ukf_mm", "model=gp_sgpr")  # any GP: a latent variance to average


# ------------------------------------------------------------------------------------------ end to end
def test_dslearn_run_with_filter_adf(tmp_path):
    """One small matrix cell through the command line: the ADF step on the increment GP, learned online."""
    code, lines = _cli(["task=matrix", "method=ekf_gp_hybrid", "filter=adf", "task.train_episodes=1",
                        "task.test_episodes=1", f"hydra.run.dir={tmp_path / 'r'}"])
    assert code == 0, lines
    df = pd.read_csv(tmp_path / "r" / "results.csv")
    assert set(df["method"]) == {"adf gp_increment hybrid"}
    rmse = df[df["metric"] == "rmse"]["value"]
    assert len(rmse) > 0 and rmse.notna().all() and (rmse < 5.0).all() and (rmse > 0).all()
