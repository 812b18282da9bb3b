"""Tests for dslearn.filters.rbpf and the braga_tbn study (RBPF + online EM + consensus on sufficient statistics)."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from dslearn.errors import ConfigError
from dslearn.fusion.statistics import (
    average_consensus,
    check_eq22,
    combination_matrices,
    throughput_bytes_per_step,
    weight_matrix,
)
from dslearn.fusion.weights import consensus_weights, half_max_degree, max_degree
from dslearn.sim.terrain import cv_model
from dslearn.filters.rbpf import init_state, online_estep, posterior_mean, rbpf_step
from dslearn.models.jmnls import m_step, make_params
from dslearn.fusion.statistics import network_adjacency
from dslearn.models.jmnls import obs_loglik, simulate_modes, stats_dim

@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """float64 throughout; these tests run thousands of tiny tensor ops: one intra-op thread avoids OpenMP spin-wait overhead
    (several times faster on a busy 2-core machine). Restored afterwards."""
    n, dt = torch.get_num_threads(), torch.get_default_dtype()
    torch.set_num_threads(1)
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_num_threads(n)
    torch.set_default_dtype(dt)


FINGER_FOUR = [[0, 1], [0, 2], [2, 3]]
EQ26 = torch.tensor([[0.5, 0.25, 0.25, 0.0], [0.25, 0.75, 0.0, 0.0], [0.25, 0.0, 0.5, 0.25], [0.0, 0.0, 0.25, 0.75]], dtype=torch.float64)


def _flat(x):
    """h(x) = 0: the measurement carries only the jump-Markov noise (known-state / pure HMM case)."""
    return torch.zeros(x.shape[:-1], dtype=x.dtype)


def _hmm_brute_force(y, a0, theta):
    """Enumerate all mode paths r_0..r_T: filtered alpha_T, log p(y_1:T), smoothed mean of (1/T) sum s_t."""
    k = a0.numel()
    T = y.numel()
    logp, paths = [], []
    for r in itertools.product(range(k), repeat=T + 1):
        lp = math.log(a0[r[0]])
        for t in range(1, T + 1):
            lp += math.log(theta.pi[r[t - 1], r[t]]) + obs_loglik(y[t - 1:t], theta.mu, theta.sigma)[0, r[t]].item()
        logp.append(lp)
        paths.append(r)
    logp = torch.tensor(logp)
    lz = torch.logsumexp(logp, 0)
    w = torch.exp(logp - lz)
    alpha = torch.zeros(k)
    s = torch.zeros(stats_dim(k))
    for wi, r in zip(w, paths):
        alpha[r[-1]] += wi
        v = torch.zeros(stats_dim(k))
        for t in range(1, T + 1):
            v[r[t - 1] * k + r[t]] += 1
            v[k * k + r[t]] += 1
            v[k * k + k + r[t]] += y[t - 1]
            v[k * k + 2 * k + r[t]] += y[t - 1] ** 2
        s += wi * v / T
    return alpha, lz, s


def _hmm_setup():
    theta = make_params([0.0, 3.0], [1.0, 2.0], [[0.8, 0.2], [0.3, 0.7]])
    y = torch.tensor([0.3, 2.8, 3.5, -0.4, 1.2, 4.1])
    a0 = torch.tensor([0.6, 0.4])
    dyn = cv_model(0.1, 1.0)
    return theta, y, a0, dyn


def test_hmm_filter_and_estep_match_brute_force():
    """Conditional HMM filter (Eq. 11-13) and the online E-step with eta_t = 1/t (Eq. 18) vs enumeration."""
    theta, y, a0, dyn = _hmm_setup()
    g = torch.Generator().manual_seed(0)
    st = init_state(torch.zeros(1, 4), 3, a0[None])
    th = theta.expand(1)
    total = 0.0
    for t in range(1, y.numel() + 1):
        st, stats, info = rbpf_step(st, y[t - 1:t], _flat, th, dyn, g, eta=1.0 / t, ess_threshold=0.5)
        total += info["loglik"].item()
    alpha_bf, lz_bf, s_bf = _hmm_brute_force(y, a0, theta)
    torch.testing.assert_close(st.alpha[0], alpha_bf.expand(3, 2), atol=1e-12, rtol=0)
    assert abs(total - lz_bf.item()) < 1e-10
    torch.testing.assert_close(stats[0], s_bf, atol=1e-10, rtol=0)


def test_online_estep_equals_explicit_double_sum():
    """Batched Eq. (16)-(18) equals a literal loop over (i, l, j, k) with f from the full Gaussian density."""
    g = torch.Generator().manual_seed(1)
    n, k = 4, 2
    d = stats_dim(k)
    dyn = cv_model(0.5, 2.0, (0.7, 0.3))
    x_prev = torch.randn(n, 4, generator=g) * 2
    x_new = dyn.sample(x_prev, g) + 0.5 * torch.randn(n, 4, generator=g)
    w = torch.rand(n, generator=g)
    logw = torch.log(w / w.sum())
    alpha = torch.softmax(torch.randn(n, k, generator=g), -1)
    T_prev = torch.randn(n, k, d, generator=g)
    e = torch.randn(n, generator=g)
    pi = torch.tensor([[0.7, 0.3], [0.45, 0.55]])
    eta = 0.37
    got = online_estep(x_prev, logw, alpha, T_prev, x_new, e, pi, eta, dyn)
    cov = dyn.kernel_chol @ dyn.kernel_chol.T
    f = torch.distributions.MultivariateNormal(torch.zeros(4), covariance_matrix=cov)
    want = torch.zeros(n, k, d)
    for i in range(n):
        for l in range(k):
            wt = torch.zeros(n, k)
            for j in range(n):
                for kk in range(k):
                    wt[j, kk] = f.log_prob(x_new[i] - dyn.F @ x_prev[j]).exp() * pi[kk, l] * alpha[j, kk] * logw[j].exp()
            wt = wt / wt.sum()
            for j in range(n):
                for kk in range(k):
                    s = torch.zeros(d)
                    s[kk * k + l] = 1
                    s[k * k + l] = 1
                    s[k * k + k + l] = e[i]
                    s[k * k + 2 * k + l] = e[i] ** 2
                    want[i, l] += wt[j, kk] * ((1 - eta) * T_prev[j, kk] + eta * s)
    torch.testing.assert_close(got, want, atol=1e-10, rtol=1e-9)


def test_online_estep_chunked_and_floored_equals_reference():
    """The chunked, exponent-floored kernel product equals the plain unchunked formula (baddbmm, no floor),
    also when most kernel entries underflow (particles far apart)."""
    g = torch.Generator().manual_seed(5)
    b, n, k = 5, 40, 2
    d = stats_dim(k)
    dyn = cv_model(0.05, 100.0, (1.0, 0.0))
    x_prev = torch.randn(b, n, 4, generator=g) * torch.tensor([30.0, 30.0, 8.0, 8.0])  # far apart: exp(<-700)
    x_new = dyn.sample(x_prev, g)
    logw = torch.log_softmax(3 * torch.randn(b, n, generator=g), -1)
    alpha = torch.softmax(torch.randn(b, n, k, generator=g), -1)
    T_prev = torch.randn(b, n, k, d, generator=g)
    e = torch.randn(b, n, generator=g)
    pi = torch.tensor([[0.7, 0.3], [0.45, 0.55]]).expand(b, k, k)
    eta = 0.2
    # reference: the unchunked formula without the exponent floor
    ref = x_new.mean(-2, keepdim=True)
    zi, mj = dyn.whiten(x_new - ref), dyn.whiten(x_prev @ dyn.F.T - ref)
    col = (-0.5 * (mj * mj).sum(-1) + logw)[:, None, :]
    a = torch.baddbmm(col, zi, mj.transpose(1, 2))
    assert (a - a.amax(-1, keepdim=True) < -745).float().mean() > 0.5  # the underflow regime is exercised
    a = torch.exp(a - a.amax(-1, keepdim=True))
    v = torch.cat([alpha[..., None], alpha[..., None] * T_prev], -1).reshape(b, n, -1)
    u = torch.bmm(a, v).reshape(b, n, k, 1 + d)
    fb, fbt = u[..., 0], u[..., 1:]
    bm = fb[..., None, :] * pi.transpose(-1, -2)[..., None, :, :]
    z = bm.sum(-1, keepdim=True)
    want_part = torch.einsum("bikd,bkl->bild", fbt, pi) / z
    got = {}
    for chunk in (None, 1, 2, 3, 8):
        dyn.kernel_chunk = chunk
        got[chunk] = online_estep(x_prev, logw, alpha, T_prev, x_new, e, pi, eta, dyn)
    for chunk, out in got.items():
        assert torch.equal(out, got[None]) or torch.allclose(out, got[None], rtol=1e-13, atol=0), chunk
    from dslearn.filters.rbpf import transition_stats

    want = (1 - eta) * want_part + eta * transition_stats(bm / z, e)
    torch.testing.assert_close(got[None], want, rtol=1e-12, atol=1e-12)


def test_online_em_recovers_noise_parameters():
    """Known state (h = 0): online EM (eta_t = t^-0.7, burn-in 50) recovers mu, sigma and the TPM."""
    truth = make_params([0.0, 20.0], [1.0, 4.0], [0.85, 0.6])
    g = torch.Generator().manual_seed(3)
    b, T = 8, 2000
    r = simulate_modes(truth.pi, (b,), T, g)
    y = truth.mu[r] + truth.sigma[r] * torch.randn(b, T + 1, generator=g)
    dyn = cv_model(0.05, 1.0)
    theta = make_params([-5.0, 25.0], [5.0, 5.0], [0.5, 0.5]).expand(b)
    st = init_state(torch.zeros(b, 4), 2, torch.nn.functional.one_hot(r[:, 0], 2).double())
    for t in range(1, T + 1):
        st, stats, _ = rbpf_step(st, y[:, t], _flat, theta, dyn, g, eta=t ** -0.7)
        if t > 50:
            theta = m_step(stats, theta)
    # eta_t = t^-0.7 keeps an effective window of ~t^0.7 = 200 samples: ~150 in mode 1, ~55 in mode 2, so the
    # per-chain standard errors are ~(0.08, 0.55) for mu and ~(0.06, 0.4) for sigma; tolerances ~3 SE on the
    # mean over the 8 independent chains, ~4 SE per chain.
    torch.testing.assert_close(theta.mu.mean(0), truth.mu, atol=0.6, rtol=0)
    torch.testing.assert_close(theta.sigma.mean(0), truth.sigma, atol=0.45, rtol=0)
    torch.testing.assert_close(theta.pi.diagonal(dim1=-2, dim2=-1).mean(0), truth.pi.diagonal(), atol=0.04, rtol=0)
    assert ((theta.mu - truth.mu).abs() < torch.tensor([0.35, 2.2])).all()
    assert ((theta.sigma - truth.sigma).abs() < torch.tensor([0.3, 1.6])).all()


def _kalman(y, x0, dyn, hvec, r):
    m, P = x0.clone(), torch.zeros(4, 4)
    qd = dyn.G @ dyn.Q @ dyn.G.T
    out = []
    for t in range(y.shape[-1]):
        m = dyn.F @ m
        P = dyn.F @ P @ dyn.F.T + qd
        s = hvec @ P @ hvec + r
        kg = P @ hvec / s
        m = m + kg * (y[t] - hvec @ m)
        P = P - torch.outer(kg, hvec @ P)
        P = 0.5 * (P + P.T)
        out.append(m)
    return torch.stack(out)


def test_rbpf_approaches_kalman_filter_single_mode():
    """Linear-Gaussian, one mode: the particle mean converges to the Kalman mean as N grows."""
    g = torch.Generator().manual_seed(5)
    dyn = cv_model(0.2, 4.0)
    hvec = torch.tensor([1.0, 0.5, 0.0, 0.0])
    theta = make_params([0.0], [1.0], [[1.0]])
    x0 = torch.tensor([0.0, 0.0, 3.0, -1.0])
    # b = 64 independent chains: over 20 generator seeds (this code) the RMS deviation from the Kalman mean was
    # 0.0585 +- 0.0096 (max 0.087) with N = 3000 and the ratio err(3000)/err(30) 0.114 +- 0.018 (max 0.159), close to
    # the Monte Carlo rate sqrt(30/3000) = 0.1. The bounds below are >= 4 standard deviations above those means.
    steps, b = 15, 64
    xs = [x0.expand(b, 4)]
    for _ in range(steps):
        xs.append(dyn.sample(xs[-1], g))
    xs = torch.stack(xs[1:], 1)  # (b, T, 4)
    y = xs @ hvec + torch.randn(b, steps, generator=g)
    kf = torch.stack([_kalman(y[i], x0, dyn, hvec, 1.0) for i in range(b)])  # (b, T, 4)
    errs = {}
    for n in (30, 3000):
        st = init_state(x0.expand(b, 4), n, torch.ones(b, 1))
        th = theta.expand(b)
        est = []
        for t in range(steps):
            st, _, _ = rbpf_step(st, y[:, t], lambda x: x @ hvec, th, dyn, g, eta=1.0, estep=False)
            est.append(posterior_mean(st))
        errs[n] = (torch.stack(est, 1) - kf)[..., :2].pow(2).mean().sqrt().item()
    assert errs[3000] < 0.2 * errs[30], errs
    assert errs[3000] < 0.1, errs


def test_consensus_converges_to_centralised_average():
    adj = network_adjacency(4, FINGER_FOUR)
    a = weight_matrix(adj, "half_max_degree")
    g = torch.Generator().manual_seed(2)
    zeta = torch.randn(3, 4, 10, generator=g)  # (batch, nodes, statistics)
    avg = zeta.mean(-2, keepdim=True).expand_as(zeta)
    torch.testing.assert_close(average_consensus(zeta, a, 400), avg, atol=1e-12, rtol=0)
    errs = [(average_consensus(zeta, a, q) - avg).abs().max().item() for q in (1, 5, 10)]
    assert errs[0] > errs[1] > errs[2] > 0
    m = combination_matrices(["noncooperative", "centralised", "consensus_1", "consensus_10"], a)
    torch.testing.assert_close(m[0], torch.eye(4))
    torch.testing.assert_close(m[1], torch.full((4, 4), 0.25))
    torch.testing.assert_close(m[2], a)
    torch.testing.assert_close(m[3], torch.linalg.matrix_power(a, 10))
    # the average is preserved by every round (column-stochastic A, Eq. 22a)
    torch.testing.assert_close(average_consensus(zeta, a, 3).mean(-2), zeta.mean(-2))


def test_weight_matrices_against_eq22():
    adj = network_adjacency(4, FINGER_FOUR)
    torch.testing.assert_close(half_max_degree(adj), EQ26, rtol=0, atol=1e-15)  # Eq. (26) reproduced
    assert torch.equal(weight_matrix(adj, "half_max_degree"), half_max_degree(adj))
    assert torch.equal(consensus_weights(adj, "half_max_degree"), half_max_degree(adj))  # registered by name
    # max_degree_core is 1/(1 + d_max) = dslearn.fusion.weights.max_degree: on the finger four (d_max = 2) 1/3
    assert torch.equal(weight_matrix(adj, "max_degree_core"), max_degree(adj))
    torch.testing.assert_close(max_degree(adj)[0, 1], torch.tensor(1 / 3, dtype=torch.float64), rtol=0, atol=1e-15)
    torch.testing.assert_close(half_max_degree(adj)[0, 1], torch.tensor(0.25, dtype=torch.float64), rtol=0, atol=1e-15)
    for rule in ("half_max_degree", "max_degree_core", "metropolis"):
        check_eq22(weight_matrix(adj, rule), adj)
    # the former, ambiguous value is refused with a message naming both replacements
    with pytest.raises(ConfigError, match="task.consensus.weights='max_degree' is ambiguous.*half_max_degree.*max_degree_core"):
        weight_matrix(adj, "max_degree")
    check_eq22(weight_matrix(adj, "matrix", EQ26.tolist()), adj)
    deg = adj.sum(-1).double()
    row_only = (adj.double() + torch.eye(4)) / (deg + 1)[:, None]  # row-stochastic, not column-stochastic
    with pytest.raises(ConfigError, match="22a"):
        check_eq22(row_only)
    with pytest.raises(ConfigError, match="22b"):
        check_eq22(row_only.T)
    with pytest.raises(ConfigError, match="22c"):
        check_eq22(torch.eye(4))  # doubly stochastic but never mixes
    bad = EQ26.clone()
    bad[1, 3] = bad[3, 1] = 0.05
    bad[1, 1] -= 0.05
    bad[3, 3] -= 0.05
    with pytest.raises(ConfigError, match="not linked"):
        check_eq22(bad, adj)
    with pytest.raises(ConfigError, match="weights"):
        weight_matrix(adj, "uniform-ish")


def test_throughput_hand_counted():
    adj = network_adjacency(4, FINGER_FOUR)
    # centralised: stats uplink 1+1+2 hops x 10 floats, params downlink 3 links x 6 floats; 4 B per float
    assert throughput_bytes_per_step("centralised", adj, 10, 6) == (4 * 10 + 3 * 6) * 4 == 232
    # consensus: 6 directed links x 10 floats per round
    assert throughput_bytes_per_step("consensus_1", adj, 10, 6) == 240
    assert throughput_bytes_per_step("consensus_5", adj, 10, 6) == 1200
    assert throughput_bytes_per_step("noncooperative", adj, 10, 6) == 0
    # paper Table II in kB/s (1 kB = 1024 B, 20 Hz): 4.5, 4.7, 23.5, 46.9
    kbps = [throughput_bytes_per_step(s, adj, 10, 6) * 20 / 1024 for s in ("centralised", "consensus_1",
                                                                             "consensus_5", "consensus_10")]
    assert [round(v, 1) for v in kbps] == [4.5, 4.7, 23.4, 46.9]
    path = network_adjacency(3, [[0, 1], [1, 2]])  # fusion centre at an end: hops 1 + 2
    assert throughput_bytes_per_step("centralised", path, 10, 6, fusion_centre=0) == (3 * 10 + 2 * 6) * 4
    with pytest.raises(ConfigError, match="consensus_<q>"):
        throughput_bytes_per_step("consensus_0", adj, 10, 6)


def test_bad_parameters_raise():
    with pytest.raises(ConfigError, match="sum to 1"):
        make_params([0, 1], [1, 1], [[0.9, 0.2], [0.5, 0.5]])
    with pytest.raises(ConfigError, match="sigma must be > 0"):
        make_params([0, 1], [1, -2], [0.8, 0.6])
    with pytest.raises(ConfigError, match="K mismatch"):
        make_params([0, 1, 2], [1, 1], [0.8, 0.6])
    with pytest.raises(ConfigError, match="K mismatch"):
        make_params([0, 1], [1, 1], [[1.0]])


def test_weight_degeneracy_log_domain_no_nan():
    """A wild measurement underflows every linear-domain weight; log-domain weights stay valid, no NaN."""
    theta, _, a0, dyn = _hmm_setup()
    g = torch.Generator().manual_seed(0)
    st = init_state(torch.zeros(2, 4), 5, a0.expand(2, 2))
    th = theta.expand(2)
    x_rand = torch.randn(2, 5, 4, generator=g) * 3
    st.x = x_rand
    y = torch.tensor([1e6, float("nan")])
    st2, stats, info = rbpf_step(st, y, lambda x: x[..., 0], th, dyn, g, eta=0.5)
    lin = torch.exp(obs_loglik(y[:1, None] - x_rand[:1, :, 0], th.mu[:1], th.sigma[:1])).sum(-1)
    assert (lin == 0).all()  # a linear-domain filter would divide 0/0 here
    for t in (st2.logw, st2.alpha, st2.T, stats, posterior_mean(st2)):
        assert not torch.isnan(t).any()
    torch.testing.assert_close(st2.logw.exp().sum(-1), torch.ones(2))
    assert info["degenerate"].tolist() == [False, True]
    new = m_step(stats, th)
    assert torch.isfinite(new.mu).all() and torch.isfinite(new.sigma).all() and torch.isfinite(new.pi).all()


def _tiny_cfg(**over):
    """``experiment=braga_tbn`` with small sizes, composed by Hydra and checked (schema + cross-field rules)."""
    small = {"task.mc_runs": 2, "task.mc_batch": 2, "task.steps": 50, "task.num_particles": 30,
             "task.em.burn_in": 20, "task.steady_state_s": 1.0, "task.terrain.size_m": 12000.0,
             "task.terrain.resolution_m": 50.0, "task.record_every": 20, "task.zoom_s": 0.5}
    small.update(over)
    return _compose(["seed=3", *(f"{k}={v}" for k, v in small.items())])


def _compose(overrides, check=True):
    from hydra import compose, initialize_config_dir

    from dslearn.schemas.core import CONF_DIR, validate_config

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = compose("config", overrides=["experiment=braga_tbn", "progress=false", *overrides])
    if check:
        validate_config(cfg)  # root keys and the task schema (dslearn.schemas.braga_tbn)
    return cfg


def _run(cfg):
    """The study of a checked configuration, built by the composition root, run (as ``dslearn-run`` does)."""
    from dslearn.api import build_study

    return build_study(cfg).run()


def test_end_to_end_tiny_run(tmp_path):
    df = _run(_tiny_cfg())
    for col in ("episode", "metric", "value", "model", "consensus", "node", "strategy", "time_s"):
        assert col in df.columns
    strategies = ["noncooperative", "centralised", "consensus_1", "consensus_5", "consensus_10"]
    run_level = df[(df.time_s == -1) & (df.strategy != "all")]
    assert set(run_level.strategy) == set(strategies)
    for m in ("pos_rms", "mu_rms", "sigma_rms", "pi_rms", "throughput_kBps"):
        v = run_level[run_level.metric == m]
        assert len(v) == 2 * len(strategies) and v.value.notna().all() and (v.value >= 0).all()
    thr = run_level[run_level.metric == "throughput_kBps"].groupby("strategy").value.first()
    assert thr["noncooperative"] == 0 and abs(thr["consensus_10"] - 2400 * 20 / 1024) < 1e-9
    assert abs(thr["centralised"] - 232 * 20 / 1024) < 1e-9
    # tracks: over 40 independent runs x 5 strategies of this configuration (seed 3) the steady-state pos_rms was
    # 2.55 +- 0.75 m (median 2.42, max 6.10). The median of the 10 values here has a standard error of ~0.3 m, so
    # the bound 4 m is > 5 standard errors above 2.42; the max bound 10 m is > 9 sd above the mean
    pos = run_level[run_level.metric == "pos_rms"].value
    assert pos.median() < 4.0 and pos.max() < 10.0, pos.describe()
    assert run_level[run_level.metric == "lost_track"].value.sum() == 0
    series = df[df.time_s >= 0]
    assert {"pos_se_t", "mu_1", "sigma_2", "pi_11"} <= set(series.metric)
    # burn-in: parameters untouched before step 20 (t = 1 s)
    early = series[(series.metric == "mu_1") & (series.time_s < 1.0)]
    assert (early.value == -5.0).all()
    from dslearn.reports.braga_tbn import report

    text = report(df, None, tmp_path)
    assert "centralised" in text and (tmp_path / "braga_tbn_table2.csv").exists()
    assert (tmp_path / "braga_tbn_fig4_parameters.png").exists()


def test_worker_processes_match_serial():
    """task.workers runs MC batches in separate processes; the results are identical to the serial run."""
    over = {"task.mc_runs": 2, "task.mc_batch": 1, "task.steps": 12, "task.num_particles": 10,
            "task.em.burn_in": 5, "task.strategies": "[noncooperative,consensus_1]", "task.steady_state_s": 0.3}
    a = _run(_tiny_cfg(**over, **{"task.workers": 1}))
    b = _run(_tiny_cfg(**over, **{"task.workers": 2}))
    keep = a.metric != "wall_time_s"
    assert a[keep].drop(columns="value").reset_index(drop=True).equals(b[keep].drop(columns="value").reset_index(drop=True))
    assert a[keep].value.tolist() == b[keep].value.tolist()
    assert sorted(set(a[keep].episode)) == [0, 1]


def _by_key(df):
    d = df[df.metric != "wall_time_s"]
    return d.set_index(["episode", "strategy", "metric", "time_s"]).value.sort_index()


def test_runs_independent_of_batch_and_strategy_list():
    """A Monte Carlo run's result depends only on (seed, run index, strategy): run 1 alone (mc_batch=1), inside a
    batch of 3, and with a different strategy list give the same outputs to 1e-9 (per-run random streams)."""
    over = {"task.mc_runs": 3, "task.steps": 40, "task.num_particles": 24, "task.em.burn_in": 10,
            "task.steady_state_s": 0.5, "task.workers": 1, "task.strategies": "[noncooperative,centralised,consensus_5]"}
    batch3 = _by_key(_run(_tiny_cfg(**over, **{"task.mc_batch": 3})))
    alone = _by_key(_run(_tiny_cfg(**over, **{"task.mc_batch": 1})))
    other = _by_key(_run(_tiny_cfg(**{**over, "task.mc_batch": 2, "task.strategies": "[consensus_5]"})))
    assert batch3.index.equals(alone.index) and len(batch3) > 500
    assert set(batch3.index.get_level_values("metric")) >= {"pos_rms", "mu_rms", "pos_se_t", "mu_1", "lost_track"}
    assert (batch3 - alone).abs().max() < 1e-9
    sub = batch3.loc[other.index]
    assert (sub - other).abs().max() < 1e-9
    # and the runs are not copies of each other
    e = batch3.xs("pos_rms", level="metric")
    assert e.xs(0, level="episode").sub(e.xs(1, level="episode")).abs().min() > 1e-6


def test_trace_runs_match_study_and_diagnostics():
    """trace_runs on a subset of runs (in another order) reproduces the study's per-run results and records
    consistent diagnostics (ESS in [1, N], position spread >= 0, h_misfit = h(estimate) - h(truth))."""
    from dslearn.tools.tbn_trace import trace_runs

    over = {"task.mc_runs": 3, "task.mc_batch": 3, "task.steps": 30, "task.num_particles": 20, "task.em.burn_in": 10,
            "task.steady_state_s": 0.5, "task.workers": 1, "task.strategies": "[noncooperative,consensus_1]"}
    cfg = _tiny_cfg(**over)
    study = _by_key(_run(cfg))
    scn, res, err = trace_runs(cfg, [2, 0])
    n_ss = 10  # 0.5 s at 50 ms
    for ri, ep in enumerate([2, 0]):
        for ci, sname in enumerate(["noncooperative", "consensus_1"]):
            want = study[(ep, sname, "pos_rms", -1.0)]
            assert abs(err.pos_se[-n_ss:, ri, ci].mean().sqrt().item() - want) < 1e-9
    dg = res.diagnostics
    assert set(dg) == {"ess", "spread", "p_mode_last", "resampled"}  # the filter's own traces: no truth in them
    assert all(v.shape == err.pos_se.shape for v in (*dg.values(), err.vel_se, err.h_misfit))
    xt = scn.x[:, None, :, 1:].permute(3, 0, 1, 2, 4)  # (T, R, 1, S, 4): the truth, against the estimates
    torch.testing.assert_close(err.h_misfit, scn.terrain(res.est) - scn.terrain(xt), rtol=0, atol=0)
    torch.testing.assert_close(err.vel_se, (res.est[..., 2:] - xt[..., 2:]).pow(2).sum(-1), rtol=0, atol=0)
    assert (dg["ess"] >= 1 - 1e-9).all() and (dg["ess"] <= 20 + 1e-9).all() and (dg["spread"] >= 0).all()
    assert ((dg["p_mode_last"] >= 0) & (dg["p_mode_last"] <= 1 + 1e-12)).all()
    assert dg["resampled"].any() and res.counters["resample_events"].sum() == dg["resampled"].sum()
    # node subsets (diagnosis) are for the non-cooperative strategy only
    with pytest.raises(ConfigError, match="noncooperative"):
        trace_runs(cfg, [0], nodes=[0])


def test_terrain_gradient_planar_closed_form():
    """On a planar map z = 500 + 0.3 X - 0.4 Y the bilinear lookup is exact, so |grad h| = 0.5 everywhere."""
    from dslearn.sim.terrain import Scenario, TerrainMap
    from dslearn.sim.terrain import terrain_gradient

    res = 25.0
    yy, xx = torch.meshgrid(torch.arange(81.0) * res, torch.arange(81.0) * res, indexing="ij")
    h = TerrainMap(500.0 + 0.3 * xx - 0.4 * yy, res)
    x = torch.zeros(2, 3, 6, 4)
    x[..., :2] = 300.0 + 1500.0 * torch.rand(2, 3, 6, 2, generator=torch.Generator().manual_seed(0))
    g = terrain_gradient(Scenario(x, torch.zeros(2, 3, 6, dtype=torch.long), torch.zeros(2, 3, 6), h))
    assert g.shape == (2, 3, 5)
    torch.testing.assert_close(g, torch.full_like(g, 0.5), atol=1e-9, rtol=0)


def test_regularised_resampling_kernel_covariance():
    """Post-regularised resampling: resampled entries get noise N(0, h^2 Sigma) (Sigma = weighted covariance before
    resampling, h = optimal bandwidth); entries above the ESS threshold are untouched; regularise=0 = plain."""
    from dslearn.filters.rbpf import RBPFState, regularisation_bandwidth, resample

    g = torch.Generator().manual_seed(11)
    n = 40000
    cov = torch.tensor([[4.0, 1.0, 0.5, 0.0], [1.0, 2.0, 0.0, 0.3], [0.5, 0.0, 1.0, 0.2], [0.0, 0.3, 0.2, 0.5]])
    x = torch.randn(2, n, 4, generator=g) @ torch.linalg.cholesky(cov).T
    logw = torch.stack([torch.log_softmax(2.0 * torch.randn(n, generator=g), -1), torch.full((n,), -math.log(n))])
    st = RBPFState(x, logw, torch.ones(2, n, 1), torch.zeros(2, n, 1, 1))
    plain, mask0 = resample(st, 0.5, torch.Generator().manual_seed(4))
    reg, mask = resample(st, 0.5, torch.Generator().manual_seed(4), regularise=1.0)
    assert mask.tolist() == mask0.tolist() == [True, False]
    torch.testing.assert_close(reg.x[1], x[1], rtol=0, atol=0)  # not resampled: untouched
    d = reg.x[0] - plain.x[0]  # same ancestors (same uniform), plus the kernel noise
    w = logw[0].exp()
    m = (w[:, None] * x[0]).sum(0)
    sigma = ((w[:, None] * (x[0] - m)).T @ (x[0] - m))
    h = regularisation_bandwidth(n, 4)
    assert abs(regularisation_bandwidth(300, 4) - 0.4660) < 1e-4  # (4 / 1800)^(1/8)
    emp = d.T @ d / n
    torch.testing.assert_close(emp, h * h * sigma, atol=0.03 * h * h * sigma.diagonal().max(), rtol=0)


def test_run_reproducible_and_bad_config():
    cfg = _tiny_cfg(**{"task.mc_runs": 1, "task.mc_batch": 1, "task.steps": 15, "task.num_particles": 10,
                       "task.em.burn_in": 5, "task.strategies": "[centralised]",
                       "task.steady_state_s": 0.5})
    a, b = _run(cfg), _run(cfg)
    keep = a.metric != "wall_time_s"
    assert a[keep].value.tolist() == b[keep].value.tolist()
    for over, msg in (({"task.modes.pi_true": "[[0.9,0.2],[0.4,0.6]]"}, "sum to 1"),
                      ({"task.modes.sigma_init": "[5.0,-1.0]"}, r"task.modes.sigma_init\[1\]=-1.0 must be > 0"),
                      ({"task.modes.mu_init": "[-5.0,25.0,3.0]"}, "K mismatch"),
                      ({"task.strategies": "[consensus_x]"}, "consensus_<q>"),
                      ({"task.consensus.weights": "matrix", "task.consensus.matrix": "[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]"}, "22c"),
                      ({"task.num_particles": 0}, "num_particles"),
                      ({"task.ess_threshold": 1.5}, "ess_threshold"),
                      ({"task.workers": 0}, "workers"),
                      ({"task.filter_streams": "shared"}, "filter_streams"),
                      ({"task.resampling.regularise": -1.0}, "regularise"),
                      ({"task.lost_track_m": 0.0}, "lost_track_m"),
                      ({"task.consensus.weights": "max_degree"}, "ambiguous"),
                      ({"task.steady_state_s": 100.0}, "steady_state_s"),
                      ({"task.terrain.resolution_m": 5000.0}, "resolution_m"),
                      ({"task.network.edges": "[[0,1],[2,3]]"}, "do not connect"),
                      ({"task.em.eta_exponent": 0.5}, "eta_exponent"),
                      ({"task.strategies": "[centralised,centralised]"}, "duplicates")):
        with pytest.raises(ConfigError, match=msg):
            _tiny_cfg(**over)


# ------------------------------------------------------------------------------------------------------
# dslearn.metrics.navigation: the errors against the truth, by hand


def _nav_case():
    """T = 4 steps, R = 1 run, C = 2 strategies, S = 2 nodes, K = 2 modes, with errors chosen by hand: the truth
    sits at (1000, 1000) with zero velocity on the planar map z = 500 + 0.3 X - 0.4 Y."""
    from dslearn.learning.online_em import TBNResult
    from dslearn.sim.terrain import Scenario, TerrainMap

    t_, s_ = 4, 2
    yy, xx = torch.meshgrid(torch.arange(81.0) * 25.0, torch.arange(81.0) * 25.0, indexing="ij")
    terrain = TerrainMap((500.0 + 0.3 * xx - 0.4 * yy).double(), 25.0)
    x = torch.zeros(1, s_, t_ + 1, 4, dtype=torch.float64)
    x[..., :2] = 1000.0
    scn = Scenario(x, torch.zeros(1, s_, t_ + 1, dtype=torch.long), torch.zeros(1, s_, t_ + 1), terrain)
    est = torch.zeros(t_, 1, 2, s_, 4, dtype=torch.float64)
    est[..., :2] = 1000.0
    est[:, 0, 0, 0, :2] += torch.tensor([3.0, 4.0], dtype=torch.float64)  # strategy 0, node 0: 5 m at every step
    est[:, 0, 0, 1, 1] += torch.arange(1.0, 5.0, dtype=torch.float64)  # strategy 0, node 1: 1, 2, 3, 4 m
    est[0, 0, 1, 1, 1] += 10.0  # strategy 1, node 1: 10 m at the first step only
    est[:, 0, 0, 0, 2:] = torch.tensor([1.0, 2.0], dtype=torch.float64)  # a velocity error of sqrt(5) m/s
    truth = make_params([0.0, 20.0], [1.0, 4.0], [[0.85, 0.15], [0.4, 0.6]])
    mu = truth.mu.expand(t_, 1, 2, s_, 2).clone()
    sigma = truth.sigma.expand(t_, 1, 2, s_, 2).clone()
    pi = truth.pi.expand(t_, 1, 2, s_, 2, 2).clone()
    mu[:, :, 0] += torch.tensor([1.0, -1.0], dtype=torch.float64)  # strategy 0: mu off by 1 in both modes
    sigma[:, :, 0, :, 0] = 2.0  # strategy 0: sigma_1 off by 1
    pi[:, :, 0, :, 0] = torch.tensor([0.75, 0.25], dtype=torch.float64)  # strategy 0: pi_11 off by 0.1
    mu[:2, :, 1] += 7.0  # strategy 1: wrong only before the steady-state window
    counters = {"resample_events": torch.tensor([[3, 0]]), "degenerate_events": torch.tensor([[1, 2]])}
    return TBNResult(est, mu, sigma, pi, counters), scn, truth


def test_navigation_errors_and_metrics_by_hand():
    from dslearn.metrics.navigation import RUN_METRICS, tbn_errors, tbn_metrics

    res, scn, truth = _nav_case()
    err = tbn_errors(res, scn, detail=True)
    want_se = torch.tensor([[25.0, 1.0], [25.0, 4.0], [25.0, 9.0], [25.0, 16.0]], dtype=torch.float64)
    torch.testing.assert_close(err.pos_se[:, 0, 0], want_se, rtol=0, atol=1e-12)
    torch.testing.assert_close(err.pos_se[:, 0, 1, 1], torch.tensor([100.0, 0, 0, 0], dtype=torch.float64),
                               rtol=0, atol=1e-12)
    torch.testing.assert_close(err.vel_se[:, 0, 0, 0], torch.full((4,), 5.0, dtype=torch.float64), rtol=0, atol=0)
    # planar map: the height misfit is the slope times the position error, 0.3 * 3 - 0.4 * 4 = -0.7 m
    torch.testing.assert_close(err.h_misfit[:, 0, 0, 0], torch.full((4,), -0.7, dtype=torch.float64), rtol=0,
                               atol=1e-9)
    assert tbn_errors(res, scn).vel_se is None
    run, series = tbn_metrics(res, err, truth, steady_steps=2, first_steps=1, lost_track_m=4.0,
                              rec_idx=torch.tensor([0, 3]))
    assert tuple(run) == RUN_METRICS and all(v.shape == (1, 2) for v in run.values())
    want = {  # (strategy 0, strategy 1)
        "pos_rms": (math.sqrt((25 + 25 + 9 + 16) / 4), 0.0),  # the last 2 steps, both nodes
        "pos_rms_first5s": (math.sqrt((25 + 1) / 2), math.sqrt(100 / 2)),  # the first step
        "mu_rms": (1.0, 0.0), "sigma_rms": (math.sqrt(0.5), 0.0), "pi_rms": (math.sqrt(0.01 / 2), 0.0),
        "pos_rms_worst_node": (5.0, 0.0),  # node RMS: 5 and sqrt(12.5)
        "pos_err_max": (5.0, 10.0),
        "lost_nodes": (1.0, 0.0), "lost_track": (1.0, 0.0),  # 5 > 4 m, sqrt(12.5) = 3.54 < 4 m
        "resample_rate": (3 / 8, 0.0),  # per node and step: 4 steps x 2 nodes
        "degenerate_events": (1.0, 2.0),
    }
    for name, (a, b) in want.items():
        got = run[name][0].tolist()
        assert got == pytest.approx([a, b], rel=1e-12, abs=1e-12), name
    assert set(series) == {"pos_se_t", "mu_se_t", "sigma_se_t", "pi_se_t", "mu_1", "mu_2", "sigma_1", "sigma_2",
                           "pi_11", "pi_22"}
    def close(got, rows):
        torch.testing.assert_close(got, torch.tensor(rows, dtype=torch.float64), rtol=0, atol=1e-12)

    close(series["pos_se_t"][:, 0], [[13.0, 50.0], [20.5, 0.0]])  # (recorded step, strategy), node-averaged
    close(series["mu_se_t"][:, 0], [[1.0, 49.0], [1.0, 0.0]])
    assert series["sigma_se_t"][:, 0, 0].tolist() == pytest.approx([0.5, 0.5], abs=1e-12)
    assert series["pi_se_t"][:, 0, 0].tolist() == pytest.approx([0.005, 0.005], abs=1e-12)
    close(series["mu_1"][:, 0], [[1.0, 7.0], [1.0, 0.0]])  # the estimates
    assert series["mu_2"][:, 0, 0].tolist() == pytest.approx([19.0, 19.0], abs=1e-12)
    assert series["sigma_1"][:, 0, 0].tolist() == [2.0, 2.0] and series["pi_11"][:, 0, 0].tolist() == [0.75, 0.75]
    res.est[1, 0, 0, 0, 0] = float("nan")
    with pytest.raises(FloatingPointError):
        tbn_errors(res, scn)


def test_navigation_rows_layout():
    from dslearn.metrics.navigation import RUN_METRICS, tbn_errors, tbn_metrics, tbn_rows
    from dslearn.studies.braga_tbn import consensus_label

    res, scn, truth = _nav_case()
    run, series = tbn_metrics(res, tbn_errors(res, scn), truth, steady_steps=2, first_steps=1, lost_track_m=4.0,
                              rec_idx=torch.tensor([0, 3]))
    strategies = ("noncooperative", "consensus_5")
    assert [consensus_label(s) for s in ("noncooperative", "centralised", "consensus_5")] == \
        ["none", "fusion_centre", "average_q5"]
    rows = tbn_rows(run, series, {"noncooperative": 0.0, "consensus_5": 23.4375}, episodes=[7], strategies=strategies,
                    consensus={s: consensus_label(s) for s in strategies}, rec_time=[0.05, 0.2000000001], model="m")
    per = len(RUN_METRICS) + 1 + len(series) * 2
    assert len(rows) == 2 * per
    assert list(rows[0]) == ["episode", "strategy", "model", "consensus", "node", "time_s", "metric", "value"]
    first = rows[per:]  # the second strategy: run-level rows, throughput, then the series
    assert [r["metric"] for r in first[:len(RUN_METRICS) + 1]] == [*RUN_METRICS, "throughput_kBps"]
    assert all((r["episode"], r["strategy"], r["consensus"], r["node"], r["model"]) ==
               (7, "consensus_5", "average_q5", "avg", "m") for r in first)
    thr = first[len(RUN_METRICS)]
    assert (thr["time_s"], thr["value"]) == (-1.0, 23.4375)
    pos = [r for r in first if r["metric"] == "pos_se_t"]
    assert [(r["time_s"], r["value"]) for r in pos] == [(0.05, 50.0), (0.2, 0.0)]  # times rounded to 1e-6
    assert next(r for r in rows if r["metric"] == "pos_err_max")["value"] == 5.0


def test_the_study_reads_no_configuration():
    """The study module names no config machinery and imports neither the composition root nor the schemas."""
    import ast
    import re
    from pathlib import Path

    import dslearn.studies.braga_tbn as study

    text = Path(study.__file__).read_text(encoding="utf-8")
    assert not re.search(r"omegaconf|hydra|DictConfig|\bcfg\.|to_plain", text, re.IGNORECASE)
    mods = [n.module for n in ast.walk(ast.parse(text)) if isinstance(n, ast.ImportFrom)]
    mods += [a.name for n in ast.walk(ast.parse(text)) if isinstance(n, ast.Import) for a in n.names]
    assert not [m for m in mods if m and m.split(".")[:2] in (["dslearn", "compose"], ["dslearn", "schemas"])]
