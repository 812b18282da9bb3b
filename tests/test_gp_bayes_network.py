"""The ``gp_bayes_filters`` benchmark on a network (``task.nodes > 1``).

Oracles: the Gaussian update of :func:`gaussian_update` (the regression's information must give it exactly), the
centralised EKF with S independent linearised measurements in closed form (numpy), the average-consensus limit
of many rounds (numpy), the golden table of the single-node study, and sums by hand for the report."""

from __future__ import annotations

import gzip
import io
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from hydra import compose, initialize_config_dir

from dslearn.errors import ConfigError
from dslearn.filters.gp_bayes import GPModel, SLR_FLOOR, gaussian_update, slr_information
from dslearn.filters.gp_moments import GPPosterior
from dslearn.filters.information import to_information, to_moment
from dslearn.metrics.filtering import gaussian_nll, mahalanobis
from dslearn.schemas.core import CONF_DIR, validate_config
from dslearn.studies.gp_bayes_filters import (Benchmark, GPBayesFiltersStudy, GPBayesTask, graph_adjacency,
                                              measurement, network_fusion, transition)

F64 = torch.float64
CPU = torch.device("cpu")
SW, P0 = 0.2, 0.5 ** 2
GOLDEN = Path(__file__).resolve().parents[1] / "benchmarks" / "golden" / "gp_bayes_small.csv.gz"
GAUSSIAN = ("ekf", "ukf", "gp_ekf", "gp_ukf", "gp_ukf_mm", "gp_adf")


def _study(**kw) -> GPBayesFiltersStudy:
    return GPBayesFiltersStudy(GPBayesTask(**kw), seed=0, dtype=F64, device=CPU)


def _gp(fn, noise_std: float, ls: float, sv: float, seed: int) -> GPModel:
    """A GP with fixed hyperparameters (those the study trains, about) on 100 noisy points of ``fn``: no training."""
    g = torch.Generator().manual_seed(seed)
    X = 20.0 * torch.rand(100, 1, generator=g, dtype=F64) - 10.0
    Y = fn(X) + noise_std * torch.randn(100, 1, generator=g, dtype=F64)
    return GPModel(GPPosterior.from_data(X, Y, torch.tensor([[ls]], dtype=F64), torch.tensor([sv], dtype=F64),
                                         torch.tensor([max(noise_std ** 2, 1e-8)], dtype=F64)))


def _bench(S: int, B: int = 60, sv: float = 0.01, seed: int = 0, p0: float = P0,
           sw: float = SW) -> tuple[Benchmark, torch.Tensor, torch.Tensor]:
    """The benchmark's truth and S measurements per case (own generator), GPs without training; the prior
    (variance ``p0``; process noise std ``sw``)."""
    g = torch.Generator().manual_seed(seed)
    mu0 = torch.linspace(-10.0, 10.0, B, dtype=F64).unsqueeze(-1)
    x0 = mu0 + math.sqrt(p0) * torch.randn(B, 1, generator=g, dtype=F64)
    x1 = transition(x0) + sw * torch.randn(B, 1, generator=g, dtype=F64)
    z = measurement(x1) + sv * torch.randn(B, 1, generator=g, dtype=F64)
    zs = measurement(x1) + sv * torch.randn(S, B, 1, generator=g, dtype=F64)
    bench = Benchmark(mu0, x0, x1, z, _gp(transition, sw, 0.86, 6.7, 1), _gp(measurement, sv, 0.93, 7.6, 2), zs)
    return bench, mu0, torch.full((B, 1, 1), p0, dtype=F64)


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return compose("config", overrides=["experiment=gp_bayes_filters", *overrides])


# ------------------------------------------------------------------------------------------ the regression
def test_slr_information_gives_the_gaussian_update():
    """Prior information + H^T R^-1 H, H^T R^-1 (z - mu_z + H m) = the joint-Gaussian update (D = 2, E = 2,
    random valid joint covariances): the matrix inversion lemma, to rounding."""
    g = torch.Generator().manual_seed(0)
    B, D, E = 5, 2, 2
    A = torch.randn(B, D + E, D + E, generator=g, dtype=F64)
    J = A @ A.mT + 0.1 * torch.eye(D + E, dtype=F64)                  # joint covariance of (x, z)
    P, C, Sz = J[:, :D, :D], J[:, :D, D:], J[:, D:, D:]
    m, mz = torch.randn(B, D, generator=g, dtype=F64), torch.randn(B, E, generator=g, dtype=F64)
    z = torch.randn(3, B, E, generator=g, dtype=F64)                  # 3 nodes' measurements
    dq, do, clamped = slr_information(m, P, mz, Sz, C, z)
    assert dq.shape == (3, B, D) and do.shape == (B, D, D) and not clamped.any()
    q0, o0 = to_information(m, P)
    mean, cov = to_moment(q0 + dq, o0 + do)
    for i in range(3):
        km, kc = gaussian_update(m, P, mz, Sz, C, z[i])
        torch.testing.assert_close(mean[i], km, rtol=1e-9, atol=1e-10)
        torch.testing.assert_close(cov, kc, rtol=1e-9, atol=1e-10)              # the same at every node


def test_slr_floors_and_marks_a_negative_effective_noise():
    """A cross-covariance too large for a valid joint Gaussian (C^2 > P S_z) gives R < 0: it is floored at
    SLR_FLOOR * S_z and marked; a valid case of the same batch is left as it is."""
    P = torch.tensor([[[2.0]], [[2.0]]], dtype=F64)
    Sz = torch.tensor([[[3.0]], [[3.0]]], dtype=F64)
    C = torch.tensor([[[3.0]], [[1.0]]], dtype=F64)                  # 9 > 6: invalid; 1 < 6: valid
    m, mz, z = torch.zeros(2, 1, dtype=F64), torch.zeros(2, 1, dtype=F64), torch.ones(2, 1, dtype=F64)
    dq, do, clamped = slr_information(m, P, mz, Sz, C, z)
    assert clamped.tolist() == [True, False]
    H = C / P                                                         # C^T P^-1
    assert float(do[0, 0, 0]) == pytest.approx(float(H[0] ** 2 / (SLR_FLOOR * 3.0)), rel=1e-12)
    assert float(do[1, 0, 0]) == pytest.approx(float(H[1] ** 2 / (3.0 - H[1] ** 2 * 2.0)), rel=1e-12)


# ------------------------------------------------------------------------------------------ the fusion
def _ekf_centralised_numpy(bench: Benchmark, sv: float):
    """The EKF on the true model with all S measurements stacked (scalar closed form): posterior mean and
    variance per case."""
    mu0 = bench.prior_mean.numpy()[:, 0]
    zs = bench.z_nodes.numpy()[..., 0]                                # (S, B)
    fp = 0.5 + 25.0 * (1.0 - mu0 ** 2) / (1.0 + mu0 ** 2) ** 2
    mp = 0.5 * mu0 + 25.0 * mu0 / (1.0 + mu0 ** 2)
    Pp = fp ** 2 * P0 + SW ** 2
    H = 10.0 * np.cos(2.0 * mp)
    info = 1.0 / Pp + zs.shape[0] * H ** 2 / sv ** 2
    q = mp / Pp + H / sv ** 2 * (zs - 5.0 * np.sin(2.0 * mp) + H * mp).sum(0)
    return q / info, 1.0 / info


@pytest.mark.parametrize("consensus,rounds,omega", [("centralized", 4, "one"), ("hybrid", 300, "nodes"),
                                                    ("cm", 300, "nodes")])
def test_centralised_ekf_equals_the_stacked_update(consensus, rounds, omega):
    """centralized (and hybrid / CM with omega = S and many rounds on the ring) = the EKF with the S measurements
    stacked, computed in numpy. Tolerance: R = S_z - H P H^T loses about eps * S_z / sigma_v^2 relatively to
    rounding (S_z = H^2 P_p + sigma_v^2 up to 100 * 163 = 1.6e4, sigma_v^2 = 1e-4: 4e-8); the posterior's
    relative error is at most that."""
    S = 10
    bench, m, P = _bench(S)
    st = _study(nodes=S, consensus=consensus, rounds=rounds, omega=omega)
    res = st.network_step("ekf", bench, m, P, network_fusion(st.settings))
    mean, var = _ekf_centralised_numpy(bench, 0.01)
    assert not res.clamped.any()
    for i in range(S):
        np.testing.assert_allclose(res.mean[i, :, 0].numpy(), mean, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(res.cov[i, :, 0, 0].numpy(), var, rtol=1e-7)
    # and the metrics the study reports are those of this posterior
    x1 = bench.x1.numpy()[:, 0]
    nll = 0.5 * (x1 - mean) ** 2 / var + 0.5 * np.log(2 * np.pi * var)
    np.testing.assert_allclose(gaussian_nll(bench.x1, res.mean, res.cov)[3].numpy(), nll, rtol=1e-6)


@pytest.mark.parametrize("name", GAUSSIAN + ("pf", "gp_pf"))
def test_individual_node_is_the_filters_own_update(name):
    """Without communication a node's posterior is its filter's own update with its own measurement (for the
    particle filters: the Gaussian update from their predicted particles' moments). Tolerance: the rounding of
    R = S_z - H P H^T, as in the test above."""
    S = 3
    bench, m, P = _bench(S, B=40)
    st = _study(nodes=S, consensus="individual")
    res = st.network_step(name, bench, m, P, network_fusion(st.settings))
    own = res.step
    for i in range(S):
        km, kc = gaussian_update(own.pred_mean, own.pred_cov, own.z_mean, own.z_cov, own.cross, bench.z_nodes[i])
        torch.testing.assert_close(res.mean[i], km, rtol=1e-7, atol=1e-8)
        torch.testing.assert_close(res.cov[i], kc, rtol=1e-7, atol=1e-12)
        if name in GAUSSIAN:  # the filter's step run with this node's measurement
            b = Benchmark(bench.prior_mean, bench.x0, bench.x1, bench.z_nodes[i], bench.gp_f, bench.gp_g)
            alone = st.step(name, b, m, P)
            torch.testing.assert_close(res.mean[i], alone.mean, rtol=1e-7, atol=1e-8)
            torch.testing.assert_close(res.cov[i], alone.cov, rtol=1e-7, atol=1e-12)


@pytest.mark.parametrize("consensus", ["hybrid", "ci"])
def test_many_rounds_reach_the_average(consensus):
    """300 rounds on a ring of 10 (uniform weights, doubly stochastic on a regular graph; second eigenvalue
    (1 + 2 cos(2 pi / 10)) / 3 = 0.87, 0.87^300 ~ 1e-18): every node holds the same posterior, the prior plus the
    nodes' average novel information (hybrid with omega = 1; CI), for the GP-ADF. With 4 rounds they still differ."""
    S = 10
    bench, m, P = _bench(S)
    st = _study(nodes=S, consensus=consensus, rounds=300)
    res = st.network_step("gp_adf", bench, m, P, network_fusion(st.settings))
    own = res.step
    dq, do, _ = slr_information(own.pred_mean, own.pred_cov, own.z_mean, own.z_cov, own.cross, bench.z_nodes)
    q0, o0 = to_information(own.pred_mean, own.pred_cov)
    mean, cov = to_moment(q0 + dq.mean(0), o0 + do)                   # numpy-free but independent: no fusion code
    torch.testing.assert_close(res.mean, mean.expand_as(res.mean), rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(res.cov, cov.expand_as(res.cov), rtol=1e-9, atol=1e-14)
    assert float((res.mean - res.mean[0]).abs().max()) < 1e-9
    few = _study(nodes=S, consensus=consensus, rounds=4)
    r4 = few.network_step("gp_adf", bench, m, P, network_fusion(few.settings))
    assert float((r4.mean - r4.mean[0]).abs().max()) > 1e-6


def test_centralized_double_counts_the_common_linearisation_error():
    """What the network does. Every node's effective noise R = S_z - C^2 / P holds the linearisation error of g
    over the predicted Gaussian (and, with GPs, the observation GP's latent variance), the same at every node;
    centralized counts it S times as if independent.
    (a) The benchmark (sigma_v = 0.01: that error is most of R), GP-ADF: centralized is overconfident, its mean
    NLL_x and Mahalanobis distance far above a single node's (individual).
    (b) The EKF on the true model with a narrow prior (sigma_0 = 0.05, sigma_w = 0.01, sigma_v = 0.5): in the cases
    whose prediction is narrow (P_p < 1e-3: the linearisation error of g over it, about 10 P_p, is far below
    sigma_v^2) centralized is calibrated: its mean Mahalanobis distance is sqrt(2/pi) = 0.80 (that of a
    calibrated Gaussian) within 3 standard errors (0.6/sqrt(n)); in the cases whose prediction is wide it is
    above 1.5."""
    S = 10
    out = {}
    bench, m, P = _bench(S, B=100)
    for c in ("individual", "centralized"):
        st = _study(nodes=S, consensus=c)
        res = st.network_step("gp_adf", bench, m, P, network_fusion(st.settings))
        out[c] = (float(gaussian_nll(bench.x1, res.mean, res.cov).mean()),
                  float(mahalanobis(bench.x1, res.mean, res.cov).mean()))
    assert out["centralized"][0] > out["individual"][0] + 1.0, out
    assert out["centralized"][1] > 2.0 * out["individual"][1], out
    bench, m, P = _bench(S, B=100, sv=0.5, p0=0.05 ** 2, sw=0.01)
    st = _study(nodes=S, consensus="centralized", measurement_std=0.5, prior_std=0.05, process_std=0.01)
    res = st.network_step("ekf", bench, m, P, network_fusion(st.settings))
    maha = mahalanobis(bench.x1, res.mean, res.cov)[0]                # every node holds the same posterior
    narrow = res.step.pred_cov[:, 0, 0] < 1e-3
    n = int(narrow.sum())
    assert n >= 30
    assert abs(float(maha[narrow].mean()) - math.sqrt(2 / math.pi)) < 3 * 0.6 / math.sqrt(n)
    assert float(maha[~narrow].mean()) > 1.5


def test_graphs():
    ring, path, full = (graph_adjacency(g, 5) for g in ("ring", "path", "complete"))
    assert ring.sum(1).tolist() == [2] * 5 and bool(ring[0, 4]) and not bool(path[0, 4])
    assert path.sum(1).tolist() == [1, 2, 2, 2, 1] and full.sum(1).tolist() == [4] * 5
    assert all(bool((a == a.T).all()) and not a.diagonal().any() for a in (ring, path, full))
    assert graph_adjacency("ring", 2).sum().item() == 2


# ------------------------------------------------------------------------------------------ the study
def test_one_node_is_the_single_node_study():
    """nodes = 1 with every network key at its default (written out): the golden table of the single-node study
    (same rows and columns, values within the golden check's tolerance), no network column."""
    from dslearn import api

    df = api.run("experiment=gp_bayes_filters", "task.num_cases=40", "task.num_particles=200", "task.nodes=1",
                 "task.graph=ring", "task.consensus=hybrid", "task.rounds=4", "task.weights=uniform", "task.omega=one")
    assert list(df.columns) == ["node", "model", "consensus", "episode", "metric", "value"]
    gold = pd.read_csv(io.StringIO(gzip.decompress(GOLDEN.read_bytes()).decode()))
    keys = ["node", "model", "consensus", "episode", "metric"]
    new = df[df["metric"] != "runtime_s"]
    m = gold.merge(new, on=keys, how="outer", suffixes=("_gold", "_new"), indicator=True)
    assert (m["_merge"] == "both").all() and len(m) == len(gold)
    # the golden check's tolerance for this run across CPUs (benchmarks/golden.py CROSS_CPU: the GPs' fitted
    # hyperparameters and the particles amplify a CPU's rounding to ~1e-7 relative)
    np.testing.assert_allclose(m["value_new"], m["value_gold"], rtol=1e-6, atol=1e-9)


def test_network_run_rows_and_report(tmp_path):
    """A network run: one row per sensor and case of each metric, the single-node draws unchanged (the network's
    measurements come from their own stream); the report averages each case over the sensors, then over cases."""
    from dslearn import api
    from dslearn.reports.gp_bayes_filters import network_table, report
    from dslearn.studies.gp_bayes_filters import make_benchmark

    s1, s3 = GPBayesTask(num_cases=5), GPBayesTask(num_cases=5, nodes=3)
    s1.gp.iterations = s3.gp.iterations = 5
    b1, b3 = make_benchmark(s1, 0, F64, CPU), make_benchmark(s3, 0, F64, CPU)
    assert b1.z_nodes is None and torch.equal(b1.z, b3.z) and torch.equal(b1.x1, b3.x1)
    assert b3.z_nodes.shape == (3, 5, 1) and not torch.equal(b3.z_nodes[0], b3.z)

    df = api.run("experiment=gp_bayes_filters", "task.num_cases=6", "task.filters=[ekf,gp_adf]", "task.nodes=3",
                 "task.consensus=cm", "task.rounds=2", "task.graph=path", "task.gp.iterations=5")
    assert list(df.columns) == ["node", "sensor", "model", "consensus", "graph", "rounds", "weights", "omega",
                                "episode", "metric", "value"]
    nll = df[df["metric"] == "nll_x"]
    assert len(nll) == 2 * 3 * 6 and set(nll["sensor"]) == {0, 1, 2}
    assert set(df[df["metric"].isin(["runtime_s", "slr_clamped"])]["sensor"]) == {-1}
    assert set(nll["consensus"]) == {"cm"} and set(nll["graph"]) == {"path"} and set(nll["rounds"]) == {2}
    tab = network_table(df).set_index("filter")
    for f in ("ekf", "gp_adf"):
        per_case = nll[nll["node"] == f].groupby("episode")["value"].mean()
        assert tab.loc[f, "nll_x_mean"] == pytest.approx(per_case.mean(), rel=1e-12)
        assert tab.loc[f, "nll_x_se"] == pytest.approx(per_case.std(ddof=1) / math.sqrt(6), rel=1e-12)
        assert tab.loc[f, "nodes"] == 3 and tab.loc[f, "cases"] == 6 and tab.loc[f, "slr_clamped"] == 0
    text = report(df, pd.DataFrame(), tmp_path)
    assert "on a network" in text and "| GP-ADF | 3 | cm | path | 2 | uniform | one |" in text
    assert (tmp_path / "gp_bayes_filters_network.csv").is_file()


# ------------------------------------------------------------------------------------------ bad settings
@pytest.mark.parametrize("overrides,message", [
    (["task.nodes=0"], "task.nodes=0 must be >= 1"),
    (["task.consensus=ci"], "task.consensus='ci' is a network setting but task.nodes=1"),
    (["task.rounds=8"], "task.rounds=8 is a network setting but task.nodes=1"),
    (["task.graph=path"], "task.graph='path' is a network setting but task.nodes=1"),
    (["task.weights=metropolis"], "task.weights='metropolis' is a network setting but task.nodes=1"),
    (["task.omega=nodes"], "task.omega='nodes' is a network setting but task.nodes=1"),
    (["task.nodes=4", "task.graph=star"], "task.graph='star' is not allowed; choose one of ['ring', 'complete', 'path']"),
    (["task.nodes=4", "task.consensus=avg"], "task.consensus='avg' is not allowed; choose one of ['individual', 'ce'"),
    (["task.nodes=4", "task.rounds=0"], "task.rounds=0 must be >= 1"),
    (["task.nodes=4", "task.weights=equal"], "task.weights='equal' is not allowed; choose one of ['uniform'"),
    (["task.nodes=4", "task.omega=two"], "task.omega='two' is not allowed; choose one of ['one', 'nodes']"),
    (["task.nodes=4", "task.omega=-1.0"], "task.omega=-1.0 must be > 0 and finite, 'one' or 'nodes'"),
    (["task.nodes=4", "task.consensus=centralized", "task.rounds=8"],
     "task.rounds=8: task.consensus=centralized does not use it (only ce|cm|ci|hybrid do)"),
    (["task.nodes=4", "task.consensus=individual", "task.weights=metropolis"],
     "task.weights='metropolis': task.consensus=individual does not use it"),
    (["task.nodes=4", "task.consensus=ci", "task.omega=nodes"], "task.omega='nodes': task.consensus=ci does not use it"),
])
def test_bad_network_settings_refused_before_work(overrides, message):
    with pytest.raises(ConfigError) as info:
        validate_config(_compose(*overrides))
    assert message in str(info.value) and "\n" not in str(info.value), str(info.value)


def test_the_study_itself_refuses_a_network_setting_on_one_node():
    """Built in Python without the config check: refused at the start of run, before the GPs are trained."""
    with pytest.raises(ConfigError, match=r"task.consensus='centralized' is a network setting but task.nodes=1"):
        _study(consensus="centralized").run()
