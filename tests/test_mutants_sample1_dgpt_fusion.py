"""DGPT and fusion against independent references (benchmarks/mutation: survivors of the mutation run): the
DGPT estimates against a plain numpy GP posterior and gPoE (raw Eq. 7 weights by default, time inputs k * dt
in the measurements' float64), the tracker's records (dtypes, reference-solve count), the trust-region
Newton's step acceptance and its working dtype, the Cholesky jitter fallback, the NRMSE of a small-range
coordinate, the tidy node rows' index and the fusion parts' error messages and checks."""

import math

import numpy as np
import pandas as pd
import pytest
import torch

from dslearn.errors import ConfigError
from dslearn.filters.dgpt import HyperConfig, TrackResult, track
from dslearn.filters.dgpt import hyperopt as ho
from dslearn.filters.dgpt.experts import _chol_jitter
from dslearn.fusion.aggregation import AggregationRule
from dslearn.fusion.statistics import check_eq22, combination_matrices, weight_matrix
from dslearn.fusion.stats_consensus import StatisticsConsensus
from dslearn.fusion.weights import validate_weights
from dslearn.metrics.regression import dgpt_metrics
from dslearn.metrics.rows import node_rows

D = torch.float64


# ------------------------------------------------------------------------------------------ DGPT tracker
def _episode(S=2, T=4):
    """One episode, S sensors detecting at every step; smooth, different measurements per sensor."""
    t = torch.arange(T, dtype=D)
    meas = torch.stack([torch.stack([3.0 * torch.sin(0.7 * t + s) + 0.2 * s,
                                     2.0 * torch.cos(0.5 * t - s) - 1.0], -1) for s in range(S)])[None]
    return meas, torch.ones(1, S, T, dtype=torch.bool)


#: fixed hyperparameters (no learning steps): the estimates are plain GP posteriors with these values
_FIXED = dict(optimizer="adam", iters=0, iters_first=0, init_outputscale=4.0, init_lengthscale_t=0.15,
              init_noise=0.01)


def _gp(x, z, xs, os_, ls, noise):
    """numpy GP posterior (Eqs. 5-6) of the latent f at xs, SE kernel, 1-d inputs."""
    def k(a, b):
        return os_ * np.exp(-0.5 * ((a[:, None] - b[None, :]) / ls) ** 2)
    K = k(x, x) + noise * np.eye(len(x))
    ks = k(x, np.array([xs]))[:, 0]
    return ks @ np.linalg.solve(K, z), os_ - ks @ np.linalg.solve(K, ks)


def _experts(meas, k, target, window, dt, os_, ls, noise):
    """Every sensor's GP posterior at time ``target * dt`` from its window of step k: (S, 2) means, vars."""
    m = meas[0].numpy()
    times = np.arange(max(0, k - window + 1), k + 1)
    mu, var = np.zeros((m.shape[0], 2)), np.zeros((m.shape[0], 2))
    for s in range(m.shape[0]):
        for c in range(2):
            mu[s, c], var[s, c] = _gp(times * dt, m[s, times, c], target * dt, os_, ls, noise)
    return mu, var


def test_dgpt_temporal_estimates_are_the_gp_posterior_at_k_dt_in_float64():
    """One sensor, PoE (a single expert is itself): the updated estimate of step k is the GP posterior at
    t = k dt of the window's measurements at times j dt, the predictive one at (k + 1) dt, computed in
    float64 (numpy; dt = 0.1 is not a float32 number: inputs rounded to float32 move the result by ~1e-9)."""
    meas, avail = _episode(S=1, T=4)
    dt, w = 0.1, 3
    res = track(meas, avail, torch.tensor([w]), aggregations=("poe",), centralised=False,
                hyper=HyperConfig(**_FIXED), dt=dt)
    for k in range(4):
        for target, mean, var in ((k, res.upd_mean, res.upd_var), (k + 1, res.pred_mean, res.pred_var)):
            if target >= 4:
                continue
            mu, v = _experts(meas, k, target, w, dt, 4.0, 0.15, 0.01)
            np.testing.assert_allclose(mean[0, 0, target].numpy(), mu[0], rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(var[0, 0, target].numpy(), v[0], rtol=1e-8)  # os - ks K^-1 ks: cancellation


def test_dgpt_gpoe_default_uses_the_raw_eq7_weights():
    """track's default ``normalise_beta=False``: gPoE with beta_i = 0.5 (log sigma_**^2 - log sigma_i^2)
    (Eq. 7 unnormalised), precision sum_i beta_i / sigma_i^2, from numpy expert posteriors (normalised
    weights, summing to 1, would give a variance larger by sum_i beta_i, here ~3.1 x 2 experts)."""
    meas, avail = _episode(S=2, T=4)
    dt, w = 0.1, 3
    res = track(meas, avail, torch.tensor([w]), aggregations=("gpoe",), centralised=False,
                hyper=HyperConfig(**_FIXED), dt=dt)
    for k in range(4):
        mu, v = _experts(meas, k, k, w, dt, 4.0, 0.15, 0.01)
        beta = np.maximum(0.5 * (np.log(4.0) - np.log(v)), 0.0)
        prec = (beta / v).sum(0)
        np.testing.assert_allclose(res.upd_var[0, 0, k].numpy(), 1.0 / prec, rtol=1e-8)
        np.testing.assert_allclose(res.upd_mean[0, 0, k].numpy(), (beta * mu / v).sum(0) / prec, rtol=1e-9,
                                   atol=1e-12)


def _newton_gap_run():
    meas, avail = _episode(S=2, T=3)
    # tol 1e-300: the reference solve (tol min(tol, 1e-8)) can meet it only at an exact zero gradient, so it
    # stalls unconverged (radius at round-off) on most problems
    hc = HyperConfig(optimizer="newton", tol=1e-300, max_iters=3, gap_check=True, init_outputscale=4.0,
                     init_lengthscale_t=1.5, init_noise=0.01)
    return track(meas, avail, torch.tensor([2]), aggregations=("poe",), centralised=True, hyper=hc)


def test_dgpt_records_keep_their_dtypes_and_count_the_unconverged_reference_solves():
    """float64 measurements (torch's default dtype float32): the per-step records are float64 (hyper,
    grad, gap, noise_mle, gap_solved) and the iteration counts integers (int64); ``gap_unconverged`` is the
    number of reference solves that missed their tolerance, i.e. of the 0 entries of ``gap_solved``."""
    assert torch.get_default_dtype() == torch.float32
    res = _newton_gap_run()
    for tag in ("e", "c"):
        for f in ("hyper", "grad", "gap", "noise_mle", "gap_solved"):
            assert getattr(res, f"{f}_{tag}").dtype == D, (f, tag)
        it = getattr(res, f"iters_{tag}")
        assert it.dtype == torch.long
        assert ((it >= 0) & (it <= 3)).all() and (it[..., 1:] > 0).any()
        sol = getattr(res, f"gap_solved_{tag}")
        assert ((sol == 0) | (sol == 1)).all()  # every step has data: no NaN
    n_unsolved = int((res.gap_solved_e == 0).sum() + (res.gap_solved_c == 0).sum())
    assert n_unsolved > 0
    assert res.gap_unconverged == n_unsolved


# ------------------------------------------------------------------------------------------ Newton
def _dip(th, idx):
    """f(x) = -x^2 - 10 exp(-100 x^2): a narrow well at 0 inside a concave bowl, maxima at
    x* = +-sqrt(ln(1000) / 100) (f'(x*) = 0); f, g (n, 1), H (n, 1, 1)."""
    x = th[:, 0]
    e = torch.exp(-100.0 * x ** 2)
    f = -x ** 2 - 10.0 * e
    g = -2.0 * x + 2000.0 * x * e
    h = -2.0 + 2000.0 * e * (1.0 - 200.0 * x ** 2)
    return f, g[:, None], h[:, None, None]


X_STAR = math.sqrt(math.log(1000.0) / 100.0)


def test_newton_rejects_a_step_that_lowers_the_objective():
    """From x = 1 the Newton step of the bowl lands at x = 0, the bottom of the well (f = -10 < f(1) = -1):
    it must be rejected (the trust radius shrinks) and the solve ends at the maximum x* (closed form), not
    at the well's stationary point 0; one iteration leaves x = 1 unchanged."""
    th0 = torch.tensor([[1.0]], dtype=D)
    th1, info1 = ho.newton_maximise(_dip, th0, torch.tensor([True]), 1e-10, 1)
    assert th1[0, 0].item() == 1.0 and info1.f[0].item() == -1.0 - 10.0 * math.exp(-100.0)
    th, info = ho.newton_maximise(_dip, th0, torch.tensor([True]), 1e-10, 100)
    assert bool(info.converged[0])
    assert th[0, 0].item() == pytest.approx(X_STAR, rel=1e-9)
    assert info.f[0].item() == pytest.approx(-X_STAR ** 2 - 0.01, rel=1e-12)


def test_newton_works_in_the_dtype_of_theta_whatever_the_default_dtype():
    """float32 theta with torch's default dtype float64: the solve stays in float32 and finds x* to float32
    accuracy (no float64 tensor of the default dtype mixes in)."""
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:
        th, info = ho.newton_maximise(_dip, torch.tensor([[1.0]], dtype=torch.float32), torch.tensor([True]),
                                      1e-3, 100)
    finally:
        torch.set_default_dtype(old)
    assert th.dtype == torch.float32 and info.f.dtype == torch.float32
    assert th[0, 0].item() == pytest.approx(X_STAR, rel=1e-4)


# ------------------------------------------------------------------------------------------ experts
def test_chol_jitter_adds_jitter_only_to_the_failed_matrices():
    """A batch of a positive definite matrix and a slightly indefinite one (eigenvalue ~ -5e-8: Cholesky
    fails): the first keeps its plain Cholesky factor, the second gets that of sig + 1e-6 * scale * I
    (numpy), with a warning."""
    good = torch.tensor([[4.0, 1.0], [1.0, 3.0]], dtype=D)
    bad = torch.tensor([[1.0, 1.0], [1.0, 1.0 - 1e-7]], dtype=D)
    scale = torch.tensor([5.0, 7.0], dtype=D)
    with pytest.warns(RuntimeWarning, match="Cholesky failed for 1 matrices"):
        chol = _chol_jitter(torch.stack([good, bad]), scale)
    np.testing.assert_allclose(chol[0].numpy(), np.linalg.cholesky(good.numpy()), rtol=1e-14)
    want = np.linalg.cholesky(bad.numpy() + 7e-6 * np.eye(2))
    np.testing.assert_allclose(chol[1].numpy(), want, rtol=1e-9)


# ------------------------------------------------------------------------------------------ metrics
def test_dgpt_nrmse_divides_by_a_range_below_one():
    """NRMSE = RMSE / range of the true coordinate, also when that range is below 1 (x: 0.5, y: 0.25)."""
    truth = torch.tensor([[0.0, 0.0], [0.25, 0.25], [0.5, 0.125]], dtype=D)[None]
    err = torch.tensor([[9.0, 9.0], [0.1, 0.2], [0.3, 0.0]], dtype=D)[None, None]  # step 0 does not count
    avail = torch.ones(1, 1, 3, dtype=torch.bool)
    one = torch.ones(1, 1, 3, 2, dtype=D)
    res = TrackResult(upd_mean=truth[:, None] + err, upd_var=one.clone(), pred_mean=truth[:, None] + one,
                      pred_var=one.clone(), upd_bound=one.clone(), pred_bound=one.clone(),
                      n_experts=torch.tensor([[1, 1, 1]]), methods=["poe"])
    m = {k: float(v[0, 0]) for k, v in dgpt_metrics(res, truth, avail, 0.05).items()}
    rx, ry = math.sqrt((0.1 ** 2 + 0.3 ** 2) / 2), math.sqrt(0.2 ** 2 / 2)
    assert m["rmse_x_updated"] == pytest.approx(rx, rel=1e-14)
    assert m["nrmse_x_updated"] == pytest.approx(rx / 0.5, rel=1e-14)
    assert m["nrmse_y_updated"] == pytest.approx(ry / 0.25, rel=1e-14)
    assert m["nrmse_x_predictive"] == pytest.approx(1.0 / 0.5, rel=1e-14)


def test_node_rows_have_a_fresh_range_index():
    """The tidy frame of several metrics is indexed 0..n-1 (one row per node x episode x metric), so that
    row labels are unique (.loc, joins)."""
    metrics = {"rmse": torch.tensor([[1.0, 2.0], [3.0, 4.0]]), "nees": torch.tensor([[5.0, 6.0], [7.0, 8.0]])}
    df = node_rows(metrics, ["a", "b"], ["sensor", "relay"], study="x")
    pd.testing.assert_index_equal(df.index, pd.RangeIndex(8))
    assert df.loc[5, "metric"] == "nees" and df.loc[5, "value"] == 6.0 and df.loc[5, "node"] == "a"
    assert list(df.columns) == ["study", "node", "node_kind", "episode", "metric", "value"]


# ------------------------------------------------------------------------------------------ fusion
def test_aggregation_rule_refusal_names_the_field():
    with pytest.raises(ConfigError, match=r"^consensus\.rule='moe' is not allowed; choose one of \['poe'"):
        AggregationRule("moe")


def test_statistics_consensus_refuses_an_unknown_weight_rule_naming_it():
    adj = torch.tensor([[0, 1], [1, 0]], dtype=torch.bool)
    with pytest.raises(ConfigError, match=r"consensus\.weights='uniform' is not allowed; choose one of "
                                          r"\['half_max_degree'"):
        StatisticsConsensus(adj, "consensus_3", weights="uniform")


def test_validate_weights_names_weight_on_an_unlinked_pair():
    adj = torch.tensor([[0, 1, 0], [1, 0, 1], [0, 1, 0]], dtype=torch.bool)  # path 0 - 1 - 2
    w = torch.full((3, 3), 1.0 / 3, dtype=D)  # doubly stochastic, but w[0, 2] > 0 without a link
    validate_weights(w, None, doubly=True)
    with pytest.raises(ConfigError, match="^consensus weights put weight on a pair of nodes that are not linked$"):
        validate_weights(w, adj, doubly=True)


def test_check_eq22_refuses_a_non_square_matrix():
    """A 2 x 3 matrix is refused as not square (naming its shape) before any condition is evaluated."""
    a = torch.tensor([[0.5, 0.5, 0.0], [0.5, 0.5, 0.0]], dtype=D)
    with pytest.raises(ConfigError, match=r"must be square \(N_S, N_S\), got shape \(2, 3\)"):
        check_eq22(a)


_DEVICES = ["meta"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.mark.parametrize("device", _DEVICES)
def test_combination_matrices_are_built_on_the_device_of_the_weights(device):
    """Per strategy: I, 11^T / S, A^q (numpy matrix power), on the device of the weights ``a`` (the RBPF
    study passes them on the run's device); ``meta`` stands in for an accelerator on a CPU-only machine."""
    adj = torch.tensor([[0, 1, 0], [1, 0, 1], [0, 1, 0]], dtype=torch.bool)
    a = weight_matrix(adj, "metropolis")
    names = ["noncooperative", "centralised", "consensus_3"]
    want = np.stack([np.eye(3), np.full((3, 3), 1.0 / 3), np.linalg.matrix_power(a.numpy(), 3)])
    np.testing.assert_allclose(combination_matrices(names, a).numpy(), want, rtol=1e-14, atol=1e-15)
    got = combination_matrices(names, a.to(device))
    assert got.device.type == device and got.shape == (3, 3, 3) and got.dtype == D
    if device != "meta":
        np.testing.assert_allclose(got.cpu().numpy(), want, rtol=1e-14, atol=1e-15)
