"""dslearn/filters, dslearn/fusion and dslearn/metrics: closed forms at small sizes, independent references and
the documented contracts (scratch buffers, defaults, dtypes, error messages) that the mutation run's
survivors showed untested (benchmarks/mutation: survivors of the mutation run)."""

import math
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import torch

from dslearn.episodes import Estimates
from dslearn.errors import ConfigError
from dslearn.filters.distributed import _informed, initial_belief, prior_means, track
from dslearn.filters.gp_bayes import AdditiveModel, pf_step, sigma_points
from dslearn.filters.gp_moments import GPPosterior
from dslearn.filters.information import predict
from dslearn.filters.rbpf import _kernel_apply, init_state, online_estep, rbpf_step
from dslearn.filters.smoother import transition_error_moments
from dslearn.fusion.aggregation import aggregate, aggregate_grbcm, entropy_weights
from dslearn.fusion.stats_consensus import StatisticsConsensus
from dslearn.fusion.strategies import Fusion, make_fusion
from dslearn.fusion.weights import metropolis, validate_weights
from dslearn.metrics.filtering import gaussian_nll, mahalanobis
from dslearn.metrics.regression import dgpt_trace_rows
from dslearn.metrics.trajectories import nees_band, track_record
from dslearn.models import ConstantVelocity, LinearPositionObservation
from dslearn.models.jmnls import make_params, stats_dim
from dslearn.sim.placement import make_network
from dslearn.sim.scenario import SocialForceScenario
from dslearn.sim.terrain import cv_model
from dslearn.types import StepContext

D = torch.float64


# ---------------------------------------------------------------------------------------------- filters


def test_prior_means_circle_uses_the_smaller_side_of_an_off_centre_area():
    """area (2, 10, 0, 10): sides 8 and 10, r = 8/16 = 0.5 around the centre (6, 5), zero velocity."""
    p = prior_means(4, (2.0, 10.0, 0.0, 10.0))
    want = torch.tensor([[6.5, 5.0, 0, 0], [6.0, 5.5, 0, 0], [5.5, 5.0, 0, 0], [6.0, 4.5, 0, 0]], dtype=D)
    torch.testing.assert_close(p, want, rtol=0, atol=1e-12)


def test_learning_gate_admits_a_position_std_exactly_at_the_gate():
    """Information diag(1/4): position variance 4 = gate 2^2 is inside the gate (<=); 1/0.24 > 4 is not."""
    info = torch.diag_embed(torch.tensor([[0.25] * 4, [0.24, 0.24, 0.25, 0.25]], dtype=D)).unsqueeze(1)
    assert _informed(info, 2.0).tolist() == [True, False]
    assert _informed(info, 2.1).tolist() == [True, True]
    assert _informed(info, None).tolist() == [True, True]


class _AdaptiveCV(ConstantVelocity):
    """Constant velocity that asks for the process-noise EM step and records what it is given."""

    adapts_noise = True

    def update_noise(self, moments, q_used, valid):
        self.got = (moments, q_used, valid)


def test_adaptive_noise_em_step_gets_the_smoothed_moments_of_the_filtered_run():
    """With an adaptive model, learning ends with the EM statistics of the whole run: the transition-error
    moments of the filtered means and covariances (the inverse of the filtered information) and the
    predictions from them, recomputed here independently from the returned track."""
    scen = SocialForceScenario(process_std=1e-3)
    net = make_network(seed=1, sensing_range=3.0)
    ep = scen.sample(1, net, torch.Generator().manual_seed(5))
    meas = ep.measurements
    meas = type(meas)(meas.meas[:, :, :6], meas.visible[:, :, :6])  # K = 5 steps
    model, obs = _AdaptiveCV(2, 0.1), LinearPositionObservation(0.2)
    ctx = StepContext(dt=0.25)
    fusion = make_fusion("hybrid", metropolis(net.adjacency), 2, "one")
    init = initial_belief(meas, net, 0.25, fusion, scen.area)
    res = track(meas, net, model, obs, fusion, ctx, init, learn=True)
    moments, q_used, valid = model.got
    m, info = res.mean[:, 0], res.info[:, 0]  # (S, K+1, Dx), (S, K+1, Dx, Dx)
    P = torch.linalg.inv(info)
    preds = [predict(res.mean[:, :, t], res.info[:, :, t], model, ctx, full=True) for t in range(5)]
    yp, Pp, F, Q = (torch.stack([p[i][:, 0] for p in preds], 1) for i in (0, 3, 4, 5))
    want = transition_error_moments(m, P, yp, Pp, F)
    assert moments.shape == (net.num_nodes, 5, 8, 8) and valid.shape == (net.num_nodes,)
    torch.testing.assert_close(moments, want, rtol=1e-7, atol=1e-9)
    torch.testing.assert_close(q_used, Q, rtol=0, atol=0)


def test_sigma_points_of_an_unbatched_gaussian():
    """m = (1, 2), P = diag(4, 9), alpha = 1, beta = 0, kappa = 1: lambda = 1, c = sqrt(3),
    points m, m +- c (2, 0), m +- c (0, 3); weights lambda/3 = 1/3 and 1/6 each."""
    m = torch.tensor([1.0, 2.0], dtype=D)
    X, wm, wc = sigma_points(m, torch.diag(torch.tensor([4.0, 9.0], dtype=D)), 1.0, 0.0, 1.0)
    c = math.sqrt(3.0)
    want = torch.tensor([[1, 2], [1 + 2 * c, 2], [1, 2 + 3 * c], [1 - 2 * c, 2], [1, 2 - 3 * c]], dtype=D)
    torch.testing.assert_close(X, want, rtol=0, atol=1e-12)
    torch.testing.assert_close(wm, torch.tensor([1 / 3] + [1 / 6] * 4, dtype=D), rtol=0, atol=1e-15)
    torch.testing.assert_close(wc, wm, rtol=0, atol=1e-15)


def test_particle_filter_ess_is_n_with_an_uninformative_measurement():
    """An observation model that ignores the state gives every particle the same weight 1/N, so the
    effective sample size 1 / sum w^2 is exactly N (and in general never above N)."""
    f = AdditiveModel(lambda x: x, 0.1 * torch.eye(2, dtype=D))
    g = AdditiveModel(lambda x: 0.0 * x[..., :1], torch.eye(1, dtype=D))
    m, P = torch.zeros(3, 2, dtype=D), torch.eye(2, dtype=D).expand(3, 2, 2)
    res = pf_step(f, g, m, P, torch.ones(3, 1, dtype=D), 50, torch.Generator().manual_seed(0))
    torch.testing.assert_close(res.ess, torch.full((3,), 50.0, dtype=D), rtol=1e-12, atol=0)
    g2 = AdditiveModel(lambda x: x[..., :1], 0.5 * torch.eye(1, dtype=D))
    res2 = pf_step(f, g2, m, P, torch.ones(3, 1, dtype=D), 50, torch.Generator().manual_seed(0))
    assert (res2.ess <= 50.0 + 1e-9).all() and (res2.ess >= 1.0).all()


def _posterior(dtype):
    g = torch.Generator().manual_seed(3)
    X = torch.randn(6, 2, generator=g, dtype=D)
    Y = torch.stack([X[:, 0].sin(), X[:, 1] * X[:, 0]], -1)
    gp = GPPosterior.from_data(X, Y, torch.tensor([[1.0, 0.8], [0.7, 1.2]], dtype=D),
                               torch.tensor([1.0, 0.5], dtype=D), torch.tensor([0.01, 0.02], dtype=D))
    return gp.to(dtype=dtype)


def test_gp_moments_stay_in_the_inputs_dtype_whatever_the_default_dtype():
    """float32 inputs give float32 moments (the module works in the inputs' dtype) even when torch's default
    dtype is float64, and they match the float64 computation to float32 accuracy."""
    m = torch.tensor([0.3, -0.2], dtype=D)
    S = torch.tensor([[0.2, 0.05], [0.05, 0.1]], dtype=D)
    want = _posterior(D).moments(m, S)
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:
        got = _posterior(torch.float32).moments(m.float(), S.float())
    finally:
        torch.set_default_dtype(old)
    for a, b in zip(got, want):
        assert a.dtype == torch.float32
        torch.testing.assert_close(a.double(), b, rtol=1e-4, atol=1e-5)


def test_kernel_apply_without_scratch_buffer_is_the_row_stabilised_product():
    """A[b, i, j] = exp(zi1[b, i].mj1[b, j] - max_j), u = A @ v: direct numpy loop, no buffer given."""
    g = torch.Generator().manual_seed(2)
    zi1, mj1, v = (torch.randn(2, 3, 4, generator=g, dtype=D) for _ in range(3))
    got = _kernel_apply(zi1, mj1, v).numpy()
    z, mm, vv = zi1.numpy(), mj1.numpy(), v.numpy()
    want = np.zeros((2, 3, 4))
    for b in range(2):
        for i in range(3):
            e = np.array([z[b, i] @ mm[b, j] for j in range(3)])
            a = np.exp(e - e.max())
            want[b, i] = a @ vv[b]
    np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-15)


def _estep_inputs(b, n, k=2, seed=4):
    g = torch.Generator().manual_seed(seed)
    d = stats_dim(k)
    dyn = cv_model(0.5, 2.0, (0.7, 0.3))
    x_prev = torch.randn(b, n, 4, generator=g, dtype=D) * 2
    x_new = dyn.sample(x_prev, g) + 0.5 * torch.randn(b, n, 4, generator=g, dtype=D)
    logw = torch.log_softmax(torch.randn(b, n, generator=g, dtype=D), -1)
    alpha = torch.softmax(torch.randn(b, n, k, generator=g, dtype=D), -1)
    T_prev = torch.randn(b, n, k, d, generator=g, dtype=D)
    e = torch.randn(b, n, generator=g, dtype=D)
    pi = torch.tensor([[0.7, 0.3], [0.45, 0.55]], dtype=D).expand(b, k, k)
    return dyn, (x_prev, logw, alpha, T_prev, x_new, e, pi, 0.3)


def test_online_estep_keeps_its_kernel_scratch_buffer_between_steps():
    """The (chunk, N, N) scratch buffer allocated at the first step is the one used at the next step of
    the same size (not reallocated), and the result does not depend on it."""
    dyn, args = _estep_inputs(2, 5)
    dyn.kernel_chunk = None  # one chunk: buffer of exactly B * N * N elements
    first = online_estep(*args, dyn)
    buf = dyn._kernel_buf
    assert buf.numel() == 2 * 5 * 5
    second = online_estep(*args, dyn)
    assert dyn._kernel_buf is buf
    assert torch.equal(first, second)


def test_chunked_online_estep_writes_its_kernels_into_the_kept_buffer():
    """With chunks of one batch entry the kept scratch buffer holds, after the step, the last chunk's
    row-stabilised kernel exp(log f(x_t^i | x_{t-1}^j) + log w^j - max_j) (computed here directly)."""
    b, n = 3, 4
    dyn, args = _estep_inputs(b, n, seed=6)
    dyn.kernel_chunk = 1
    dyn._kernel_buf = torch.full((n * n,), math.nan, dtype=D)
    out = online_estep(*args, dyn)
    x_prev, logw, x_new = args[0], args[1], args[4]
    cov = dyn.kernel_chol @ dyn.kernel_chol.T
    f = torch.distributions.MultivariateNormal(torch.zeros(4, dtype=D), covariance_matrix=cov)
    la = f.log_prob(x_new[-1][:, None, :] - (x_prev[-1] @ dyn.F.T)[None, :, :]) + logw[-1][None, :]
    want = torch.exp(la - la.amax(-1, keepdim=True))
    torch.testing.assert_close(dyn._kernel_buf.view(n, n), want, rtol=1e-10, atol=1e-14)
    dyn2, _ = _estep_inputs(b, n, seed=6)
    dyn2.kernel_chunk = None
    torch.testing.assert_close(out, online_estep(*args, dyn2), rtol=1e-13, atol=1e-14)


def test_rbpf_step_defaults_to_plain_resampling():
    """The default is the paper's plain systematic resampling: the same draws and particles as
    regularise=0 from the same seed (a regularised step draws kernel noise too and differs)."""
    theta = make_params([0.0, 3.0], [1.0, 2.0], [[0.8, 0.2], [0.3, 0.7]]).expand(2)
    dyn = cv_model(0.1, 1.0)
    st = init_state(torch.zeros(2, 4, dtype=D), 6, torch.tensor([[0.6, 0.4]] * 2, dtype=D))
    st.logw = torch.log_softmax(torch.arange(6, dtype=D).expand(2, 6), -1)  # ESS < N: resampled
    y = torch.tensor([0.5, 2.0], dtype=D)

    def h(x):
        return x[..., 0]

    def run(**kw):
        return rbpf_step(st, y, h, theta, dyn, torch.Generator().manual_seed(1), eta=0.5, ess_threshold=1.0, **kw)

    a, b, c = run(), run(regularise=0.0), run(regularise=1.0)
    assert a[2]["resampled"].all()
    assert torch.equal(a[0].x, b[0].x) and torch.equal(a[1], b[1])
    assert not torch.equal(a[0].x, c[0].x)


# ----------------------------------------------------------------------------------------------- fusion


def test_entropy_weights_use_the_variances_dtype_for_a_python_prior_variance():
    """prior_var = 0.1 (a Python float) against float64 variances: beta = 0.5 log(0.1 / 0.05) = 0.5 log 2 to
    float64 accuracy (0.1 not rounded to float32 first); the second expert (0.2 > 0.1) gets 0."""
    var = torch.tensor([0.05, 0.2], dtype=D)
    beta = entropy_weights(var, 0.1, torch.tensor([True, True]))
    assert beta.dtype == D
    torch.testing.assert_close(beta, torch.tensor([0.5 * math.log(2.0), 0.0], dtype=D), rtol=1e-15, atol=0)


def test_aggregate_refuses_grbcm_pointing_to_its_function():
    with pytest.raises(ValueError, match=r"^grbcm needs a communication expert: use aggregate_grbcm\(\)$"):
        aggregate(torch.zeros(2), torch.ones(2), torch.ones(2, dtype=torch.bool), 1.0, "grbcm")


def test_grbcm_normalised_weights_per_batch_entry():
    """Batched (2 entries x 2 experts), normalise_beta: each entry's beta_i = log(c/v_i) / sum_j log(c/v_j)
    sums to 1 on its own, so the communication expert's weight is 0 and the result is the weighted PoE."""
    mean = torch.tensor([[1.0, 2.0], [3.0, -1.0]], dtype=D)
    var = torch.tensor([[0.5, 0.25], [0.1, 0.4]], dtype=D)
    cv = torch.tensor([1.0, 2.0], dtype=D)
    mask = torch.ones(2, 2, dtype=torch.bool)
    m, v, beta = aggregate_grbcm(mean, var, mask, torch.zeros(2, dtype=D), cv, normalise_beta=True)
    raw = torch.log(cv[:, None] / var)
    want_beta = raw / raw.sum(-1, keepdim=True)
    torch.testing.assert_close(beta, want_beta, rtol=1e-14, atol=0)
    prec = (want_beta / var).sum(-1)
    torch.testing.assert_close(v, 1 / prec, rtol=1e-14, atol=0)
    torch.testing.assert_close(m, (want_beta / var * mean).sum(-1) / prec, rtol=1e-14, atol=0)


def test_statistics_consensus_names_the_matrix_in_the_methods_own_keys():
    """A matrix that weights unlinked nodes (path 0-1-2, uniform 1/3) is refused as a ConfigError naming
    consensus.matrix and the scenario's network (not the task.* keys of weight_matrix)."""
    adj = torch.tensor([[0, 1, 0], [1, 0, 1], [0, 1, 0]], dtype=torch.bool)
    with pytest.raises(ConfigError, match=r"^consensus\.matrix puts weight on a pair of nodes that are not linked "
                                          r"in the scenario's network$"):
        StatisticsConsensus(adj, "consensus_2", "matrix", [[1 / 3] * 3] * 3)


def test_fusion_refuses_an_unknown_omega_naming_the_key():
    with pytest.raises(ConfigError, match=r"^consensus\.omega='all' is not allowed; choose one of \['one', 'nodes'\]$"):
        Fusion(torch.eye(3, dtype=D), 2, "all")


def test_validate_weights_column_check_uses_the_given_tolerance():
    """Rows sum to 1, columns to 1.05 / 0.95: accepted as doubly stochastic with atol = 0.1, refused with
    the default atol (1e-10)."""
    w = torch.tensor([[0.55, 0.45], [0.5, 0.5]], dtype=D)
    validate_weights(w, doubly=True, atol=0.1)
    with pytest.raises(ConfigError, match="doubly stochastic"):
        validate_weights(w, doubly=True)


# ---------------------------------------------------------------------------------------------- metrics


def test_mahalanobis_and_nll_in_two_dimensions():
    """x - mean = (1, 2), cov = diag(1, 4): d^2 = 1 + 1 = 2; NLL = d^2/2 + log(2)/1 + log(2 pi)."""
    x = torch.tensor([[1.0, 2.0], [0.0, 0.0]], dtype=D)
    cov = torch.diag(torch.tensor([1.0, 4.0], dtype=D)).expand(2, 2, 2)
    torch.testing.assert_close(mahalanobis(x, torch.zeros(2, 2, dtype=D), cov),
                               torch.tensor([math.sqrt(2.0), 0.0], dtype=D), rtol=1e-15, atol=0)
    nll = gaussian_nll(x, torch.zeros(2, 2, dtype=D), cov)
    torch.testing.assert_close(nll, torch.tensor([1.0, 0.0], dtype=D) + math.log(2.0) + math.log(2 * math.pi),
                               rtol=1e-15, atol=0)


def test_dgpt_trace_rows_index_is_a_fresh_range():
    """Two episodes x one method x 11 series x 3 steps = 66 rows indexed 0..65 in order: row 3 is the
    true y at step 0 of episode 0, row 33 the true x at step 0 of episode 1."""
    b, T = 2, 3
    truth = torch.arange(b * T * 2, dtype=D).reshape(b, T, 2)
    z = torch.ones(b, 1, T, 2, dtype=D)
    res = SimpleNamespace(upd_mean=z, upd_var=z, pred_mean=z, upd_bound=z)
    avail = torch.ones(b, 4, T, dtype=torch.bool)
    keys = [("s", 0.1, 0), ("s", 0.1, 1)]
    df = dgpt_trace_rows("s", 0.1, 2, res, truth, avail, keys, ["gp"], ["poe"])
    assert len(df) == 66
    assert df.index.equals(pd.RangeIndex(66))
    assert (df.loc[3, "metric"], df.loc[3, "step"], df.loc[3, "value"]) == ("trace_true_y", 0, 1.0)
    assert (df.loc[33, "metric"], df.loc[33, "episode"], df.loc[33, "value"]) == ("trace_true_x", 1, 6.0)
    assert (df.loc[30:32, "value"] == 4.0).all()  # detections of episode 0: all 4 sensors


def test_track_record_nees_dof_is_two_per_target():
    """Two targets: nees_dof = 2 A = 4 (an integer) and the band is nees_band(4, B)."""
    truth = torch.zeros(1, 3, 2, 2, dtype=D)
    est = Estimates(torch.zeros(1, 1, 3, 2, 2, dtype=D), torch.eye(2, dtype=D).expand(1, 1, 3, 2, 2, 2),
                    ["n0"], torch.tensor([True]))
    out = track_record(est, truth, 0.5)
    assert out["nees_dof"] == 4 and np.issubdtype(out["nees_dof"].dtype, np.integer)
    np.testing.assert_array_equal(out["nees_band"], np.asarray(nees_band(4, 1)))
