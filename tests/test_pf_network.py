"""The particle prediction step on the network (``filter=pf``, :mod:`dslearn.filters.particle`): the GP-PF's
prediction, moment-matched into the information filter.

Checked against independent references within Monte Carlo bounds computed from the number of particles: the
Kalman prediction ``F m, F P F^T + Q`` on the linear-Gaussian model, the exact GP-ADF moments
(:func:`dslearn.filters.adf.adf_predict`) on a GP motion model with data; its reproducibility from the seed, its
batching, its full outputs, the refusal of bad settings, and an end-to-end run against the EKF on the linear model.
"""

from __future__ import annotations

import math

import pandas as pd
import pytest
import torch

from dslearn import api
from dslearn.compose import build_predict
from dslearn.errors import ConfigError
from dslearn.filters import particle
from dslearn.filters.adf import adf_predict
from dslearn.filters.particle import ParticlePredict, pf_predict
from dslearn.models import ConstantVelocity
from dslearn.types import StepContext
from test_adf_network import beliefs, make_gp  # two nodes, a 4-dim state, a GP with 20 random points per node

D = torch.float64
CTX = StepContext(dt=0.25)


def linear_world(s=2, b=3, agents=2, seed=3):
    """The constant-velocity model with unit process noise (Q = I: far above the Monte Carlo bounds below) and
    ``(S, B)`` random beliefs."""
    model = ConstantVelocity(agents, 1.0)
    dx = 4 * agents
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(s, b, dx, dx, dtype=D, generator=g)
    P = a @ a.transpose(-1, -2) / dx + 0.5 * torch.eye(dx, dtype=D)
    mean = torch.randn(s, b, dx, dtype=D, generator=g)
    return model, mean, P


def kalman(model, mean, P):
    F = model.jacobian(mean, CTX)
    return model(mean, CTX), F @ P @ F.transpose(-1, -2) + model.noise_cov(mean, CTX), F


def within_mc(y, P_pred, y_ref, P_ref, n, k_mean=4.5, k_cov=5.0):
    """Mean within ``k_mean`` standard errors of a sample mean (sd_i / sqrt(N)); covariance within
    ``k_cov`` sqrt(2/N) sd_i sd_j (a Gaussian sample covariance's standard error is at most that)."""
    sd = P_ref.diagonal(dim1=-2, dim2=-1).sqrt()
    z_mean = ((y - y_ref).abs() / (sd / math.sqrt(n))).max()
    z_cov = ((P_pred - P_ref).abs() / (math.sqrt(2.0 / n) * sd.unsqueeze(-1) * sd.unsqueeze(-2))).max()
    return float(z_mean), float(z_cov), bool(z_mean <= k_mean and z_cov <= k_cov)


# ------------------------------------------------------------------------------------------ linear-Gaussian
def test_linear_gaussian_equals_the_kalman_prediction_within_monte_carlo_error():
    """y = A x + w: the particle mean and covariance are the Kalman prediction within the bounds of N = 1e5; the
    statistical linearisation is A itself (the regression of A x_i on x_i is exact); leaving out the noise draw
    (P_pred short by Q = I) is far outside the bounds (the test sees it)."""
    model, mean, P = linear_world()
    n = 100_000
    y, q, om, P_pred, F, Q = pf_predict(mean, torch.linalg.inv(P), model, CTX, full=True, particles=n,
                                        generator=torch.Generator().manual_seed(11))
    y_ref, P_ref, A = kalman(model, mean, P)
    zm, zc, ok = within_mc(y, P_pred, y_ref, P_ref, n)
    assert ok, (zm, zc)
    torch.testing.assert_close(torch.linalg.inv(om), P_pred, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(q, (om @ y.unsqueeze(-1)).squeeze(-1))
    torch.testing.assert_close(F, A, rtol=0, atol=1e-10)
    # the process noise recovered as P_pred - A P A^T: I within the covariance bound
    sd = P_ref.diagonal(dim1=-2, dim2=-1).sqrt()
    assert ((Q - torch.eye(mean.shape[-1], dtype=D)).abs() <= 5 * math.sqrt(2.0 / n) * sd.unsqueeze(-1) * sd.unsqueeze(-2)).all()
    # without the process noise the cloud's covariance is A P A^T: outside the bound
    assert not within_mc(y, P_pred, y_ref, A @ P @ A.transpose(-1, -2), n)[2]


# ------------------------------------------------------------------------------------------ GP motion model
@pytest.mark.parametrize("mean,noise", [("identity", "latent"), ("zero", "predictive"), ("identity", "adaptive")])
def test_gp_moments_equal_the_exact_adf_moments_within_monte_carlo_error(mean, noise):
    """A GP motion model with data (two nodes, 20 points each): particles sample the GP predictive at each draw
    from the belief, so the moment-matched cloud is the exact predictive moments of the GP-ADF within the bounds
    of N = 2e5, and the particles' linearisation F is the ADF's E[df/dy] within the regression's standard error
    (residual sd_i sqrt((P^-1)_jj / N)). The EKF's covariance at the same beliefs is outside the bounds."""
    from dslearn.filters.information import predict as ekf_predict

    model = make_gp(mean, noise)
    m, P = beliefs(b=3)
    n = 200_000
    y, _, _, P_pred, F, _ = ParticlePredict(n, seed=5)(m, torch.linalg.inv(P), model, CTX, full=True)
    ya, _, _, Pa, Fa, Qa = adf_predict(m, torch.linalg.inv(P), model, CTX, full=True)
    zm, zc, ok = within_mc(y, P_pred, ya, Pa, n)
    assert ok, (zm, zc)
    se_F = (Qa.diagonal(dim1=-2, dim2=-1).unsqueeze(-1) * torch.linalg.inv(P).diagonal(dim1=-2, dim2=-1).unsqueeze(-2) / n).sqrt()
    assert ((F - Fa).abs() <= 5 * se_F).all(), ((F - Fa).abs() / se_F).max()
    P_ekf = ekf_predict(m, torch.linalg.inv(P), model, CTX, full=True)[3]
    assert not within_mc(y, P_pred, ya, P_ekf, n)[2]


def test_the_gp_predictive_is_the_models_mean_and_noise_cov_at_each_particle(monkeypatch):
    """The GP fast path (mean and latent variance in one pass) is ``model(x)`` plus a draw with ``model.noise_cov(x)``
    at each particle: the generic path on the same draws gives the same numbers."""
    model = make_gp("identity", "adaptive")
    m, P = beliefs(b=2)
    fast = ParticlePredict(300, seed=2)(m, torch.linalg.inv(P), model, CTX, full=True)
    monkeypatch.setattr(particle, "_gp_model", lambda model: None)
    slow = ParticlePredict(300, seed=2)(m, torch.linalg.inv(P), model, CTX, full=True)
    for a, b in zip(fast, slow):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


# ------------------------------------------------------------------------------------------ reproducibility etc.
def test_reproducible_from_the_seed_and_advanced_per_call():
    """Fresh steps with one seed: bit-identical; another seed: different; a second call of one step: new draws
    (its generator is advanced), and the same as a fresh step's second call. The global RNG is not touched."""
    model, mean, P = linear_world()
    om = torch.linalg.inv(P)
    torch.manual_seed(123)
    before = torch.random.get_rng_state()
    a, b, c = ParticlePredict(200, seed=4), ParticlePredict(200, seed=4), ParticlePredict(200, seed=5)
    ra, rb, rc = (s(mean, om, model, CTX, full=True) for s in (a, b, c))
    assert all(torch.equal(x, y) for x, y in zip(ra, rb))
    assert not torch.equal(ra[0], rc[0]) and not torch.equal(ra[3], rc[3])
    ra2, rb2 = a(mean, om, model, CTX), b(mean, om, model, CTX)
    assert not torch.equal(ra2[0], ra[0]) and all(torch.equal(x, y) for x, y in zip(ra2, rb2))
    assert torch.equal(torch.random.get_rng_state(), before)


def test_the_run_seed_seeds_the_step():
    """``conf/filter/pf.yaml``: ``filter.predict.seed`` is the run's ``seed`` unless set."""
    assert build_predict(api.compose("filter=pf")).seed == 0
    assert build_predict(api.compose("filter=pf", "seed=7")).seed == 7
    step = build_predict(api.compose("filter=pf", "seed=7", "filter.predict.seed=3", "filter.predict.particles=64"))
    assert (step.seed, step.particles) == (3, 64)


def test_batched_shapes_dtype_and_chunks(monkeypatch):
    """(S, B) beliefs give (S, B) outputs, each (node, episode) its own cloud: every one's mean is its own exact
    ADF mean within 4.5 standard errors of 400 particles (a mix-up of nodes or episodes is ~20 of them off);
    float32 in, float32 out; evaluating the particles in chunks changes the numbers by rounding only (the draws are
    made before the chunks)."""
    model = make_gp("identity", "latent")
    m, P = beliefs(b=5)
    om = torch.linalg.inv(P)
    out = ParticlePredict(400, seed=1)(m, om, model, CTX, full=True)
    assert [tuple(t.shape) for t in out] == [(2, 5, 4), (2, 5, 4)] + [(2, 5, 4, 4)] * 4
    assert all(t.dtype == D and torch.isfinite(t).all() for t in out)
    ya, _, _, Pa = adf_predict(m, om, model, CTX, full=True)[:4]
    sd = Pa.diagonal(dim1=-2, dim2=-1).sqrt()
    assert ((out[0] - ya).abs() <= 4.5 * sd / math.sqrt(400)).all()
    assert ((out[0] - ya.flip(1)).abs() > 4.5 * sd / math.sqrt(400)).any()  # the check sees a mix-up
    monkeypatch.setattr(particle, "CHUNK_ELEMENTS", 1000)  # 1000 // (10 rows x 20 points): chunks of 5 particles
    chunked = ParticlePredict(400, seed=1)(m, om, model, CTX, full=True)
    for a, b in zip(out, chunked):
        torch.testing.assert_close(a, b, rtol=1e-11, atol=1e-12)
    lin, mean, P = linear_world()
    out32 = ParticlePredict(50, seed=1)(mean.float(), torch.linalg.inv(P).float(), lin, CTX, full=True)
    assert all(t.dtype == torch.float32 for t in out32)


def test_full_outputs_are_consistent():
    """F P F^T + Q = P_pred where Q needs no floor (the GP: its latent variance well above the Monte Carlo error);
    with a tiny process noise (1e-3 std) Monte Carlo error makes P_pred - F P F^T indefinite and Q is floored to
    PSD (eigenvalues >= 0), never below."""
    model = make_gp("identity", "latent")
    m, P = beliefs(b=3)
    y, q, om, P_pred, F, Q = ParticlePredict(5000, seed=3)(m, torch.linalg.inv(P), model, CTX, full=True)
    assert torch.linalg.eigvalsh(Q).min() > 0
    torch.testing.assert_close(F @ P @ F.transpose(-1, -2) + Q, P_pred, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(Q, Q.transpose(-1, -2), rtol=0, atol=0)
    tiny = ConstantVelocity(2, 1e-3)
    _, mean, P = linear_world()
    *_, P_pred, F, Q = ParticlePredict(500, seed=3)(mean, torch.linalg.inv(P), tiny, CTX, full=True)
    raw = P_pred - F @ P @ F.transpose(-1, -2)
    assert torch.linalg.eigvalsh(0.5 * (raw + raw.mT)).min() < -1e-4  # the raw difference is indefinite
    assert torch.linalg.eigvalsh(Q).min() > -1e-12


@pytest.mark.parametrize("key,value", [("particles", 0), ("particles", 1), ("particles", -5), ("particles", 2.5),
                                       ("particles", "many"), ("particles", True), ("seed", -1), ("seed", 1.5),
                                       ("seed", "x")])
def test_bad_settings_are_refused_naming_the_key(key, value):
    with pytest.raises(ConfigError, match=f"filter.predict.{key}="):
        ParticlePredict(**{key: value})
    with pytest.raises(ConfigError, match=f"filter.predict.{key}"):
        api.compose("filter=pf", f"filter.predict.{key}={value}")


# ------------------------------------------------------------------------------------------ end to end
def _sensor_average(df: pd.DataFrame, metric: str) -> float:
    d = df[(df["metric"] == metric) & (df["node_kind"] == "sensor")]
    return float(d["value"].mean())


def test_end_to_end_on_the_linear_model_tracks_like_the_ekf():
    """``model=lin consensus=hybrid``, one training and four test episodes: with 5000 particles the PF's prediction
    is the Kalman prediction up to Monte Carlo error, so its tracking RMSE and NEES are the EKF's within a few
    per cent (measured: 0.5 % and 1 %); the EKF run differs from itself by nothing."""
    base = ("model=lin", "consensus=hybrid", "data.train_episodes=1", "data.test_episodes=4")
    ekf = api.run(*base, "filter=default")
    pf = api.run(*base, "filter=pf", "filter.predict.particles=5000")
    assert set(pf["model"]) == {"lin+pf"}
    r_ekf, r_pf = _sensor_average(ekf, "track_rmse"), _sensor_average(pf, "track_rmse")
    n_ekf, n_pf = _sensor_average(ekf, "nees"), _sensor_average(pf, "nees")
    assert 0.0 < r_ekf < 1.0 and math.isfinite(r_pf)
    assert abs(r_pf - r_ekf) <= 0.03 * r_ekf, (r_pf, r_ekf)
    assert abs(n_pf - n_ekf) <= 0.05 * n_ekf, (n_pf, n_ekf)


def test_the_memory_guard_counts_the_particle_clouds():
    """filter=pf adds 5 clouds (S, B_test, N, 4m) of float64 and its chunked model evaluation to the estimated
    peak; linear in the particles; other filters add nothing; a run whose clouds exceed the limit is refused
    before it starts, naming the part."""
    from dslearn.filters.particle import CHUNK_ELEMENTS
    from dslearn.schemas.core import estimate_core_memory

    assert "particles" not in estimate_core_memory(api.compose())
    est = estimate_core_memory(api.compose("filter=pf", "filter.predict.particles=1000", "data.test_episodes=3"))
    s, d = 10, 8  # the Yu scenario: 10 nodes, 2 agents
    cloud = s * 3 * 1000 * d
    assert est["particles"] == 5 * cloud * 8 + 4 * min(CHUNK_ELEMENTS, cloud * est_n(api)) * 8
    many = ("filter=pf", "filter.predict.particles=1000000", "data.test_episodes=50")
    big = estimate_core_memory(api.compose(*many, "+max_memory_gb=1000"))["particles"]
    assert big == 5 * (s * 50 * 1_000_000 * d) * 8 + 4 * CHUNK_ELEMENTS * 8  # 160 GB of clouds
    with pytest.raises(ConfigError, match="largest part: particles"):
        api.compose(*many, "+max_memory_gb=20")


def est_n(api):
    """Training data points of the default Yu run (train episodes x steps)."""
    cfg = api.compose()
    return int(cfg.data.train_episodes) * int(round(float(cfg.scenario.horizon) / float(cfg.scenario.dt)))
