"""Fast paths vs the straightforward reference (dslearn.reference) on the same seeds: the GP pieces here;
the whole study for every model and fusion in tests/test_reference.py."""

import numpy as np
import pytest
import torch

from dslearn.models import GPMotionModel
from dslearn.models.gp_backends.exact import OnlineGP
from dslearn.types import StepContext

D = torch.float64
CTX = StepContext(dt=0.25)


def _opts(model, consensus, train, test, **kw):
    from dslearn import api

    return api.yu_study(model=model, consensus=consensus, train_episodes=train, test_episodes=test, **kw)


@pytest.mark.parametrize("factor,cap", [("cholesky", 392), ("inverse", 396)])
def test_append_equals_refit_through_buffer_growth(factor, cap):
    g = torch.Generator().manual_seed(0)
    gp = OnlineGP(3, 4, 4, outputscale=1.1, lengthscale=1.4, noise_std=0.3, capacity=8, factor=factor)
    X = 1.5 * torch.randn(300, 3, 4, generator=g, dtype=D)
    for i in range(300):  # cholesky grows by 128 rows (8 -> 136 -> 264 -> 392), inverse by half (... 264 -> 396)
        gp.predict(X[i].unsqueeze(1))  # the solve reused by append
        gp.append(X[i], torch.sin(X[i]), torch.tensor([True, i % 3 != 0, True]))
    assert gp.L.shape[-1] == cap
    alpha, L = gp.alpha.clone(), gp.L[:, : gp.n, : gp.n].clone()
    xq = torch.randn(3, 4, 4, generator=g, dtype=D)
    m1, v1, j1 = gp.predict(xq)
    gp.refactorize()
    assert torch.allclose(gp.L[:, : gp.n, : gp.n], L, atol=1e-10)
    assert torch.allclose(gp.alpha, alpha, atol=1e-9)
    m2, v2, j2 = gp.predict(xq)
    assert torch.allclose(m1, m2, atol=1e-9) and torch.allclose(v1, v2, atol=1e-9) and torch.allclose(j1, j2, atol=1e-9)


def test_reference_gp_equals_online_gp_and_autograd_jacobian():
    from dslearn.reference import ReferenceGP

    g = torch.Generator().manual_seed(1)
    model = GPMotionModel(8, num_nodes=1, mean="identity")
    ref = ReferenceGP(8, 1.0, 2.0, 0.5, "identity", "latent", D)
    X = torch.randn(40, 1, 8, generator=g, dtype=D)
    for i in range(40):
        model.add_data(X[i], X[i] + 0.1 * torch.tanh(X[i]))
        ref.add(X[i, 0], X[i, 0] + 0.1 * torch.tanh(X[i, 0]))
    x = torch.randn(8, generator=g, dtype=D)
    m, F, Q = model.linearize(x.reshape(1, 1, 8), CTX)
    mr, Fr, Qr = ref.linearize(x)
    assert torch.allclose(m[0, 0], mr, atol=1e-9)
    assert torch.allclose(F[0, 0], Fr, atol=1e-9)
    assert torch.allclose(Q[0, 0], Qr, atol=1e-9)


def test_float32_close_to_float64():
    """float32 is selectable; its accuracy cost on the tiny study is small (stated tolerance)."""
    a = _opts("gp_increment", "hybrid", 2, 2).run()
    b = _opts("gp_increment", "hybrid", 2, 2, dtype="float32").run()
    for metric, tol in (("track_err", 1e-3), ("pred_err", 1e-3)):
        x = a[a.metric == metric]["value"].to_numpy()
        y = b[b.metric == metric]["value"].to_numpy()
        assert np.abs(x - y).max() < tol, (metric, np.abs(x - y).max())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_equals_cpu():
    a = _opts("gp_increment", "hybrid", 2, 2).run()
    b = _opts("gp_increment", "hybrid", 2, 2, device="cuda").run()
    np.testing.assert_allclose(a["value"].to_numpy(), b["value"].to_numpy(), rtol=1e-7, atol=1e-8)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_gp_step_has_no_host_sync():
    gp = OnlineGP(4, 8, 8, device="cuda")
    x = torch.randn(4, 8, device="cuda", dtype=D)
    gp.append(x, x)
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(3):
            x = torch.randn(4, 8, device="cuda", dtype=D)
            gp.predict(x.unsqueeze(1))
            gp.append(x, torch.sin(x))
    finally:
        torch.cuda.set_sync_debug_mode("default")


def _grown(factor_dtype=None, n=200, s=3, d=4, seed=2):
    g = torch.Generator().manual_seed(seed)
    gp = OnlineGP(s, d, d, outputscale=1.2, lengthscale=1.6, noise_std=0.4, mean="identity", capacity=8,
                  factor_dtype=factor_dtype)
    X = 1.5 * torch.randn(n, s, d, generator=g, dtype=D)
    for i in range(n):
        gp.predict(X[i].unsqueeze(1))
        gp.append(X[i], X[i] + 0.3 * torch.sin(X[i]), torch.tensor([True, i % 4 != 0, True]))
    return gp, g


def test_cached_kernel_equals_gpytorch_kernel_at_invalid_points_too():
    gp, g = _grown(n=50)
    xq = torch.randn(3, 6, 4, generator=g, dtype=D)
    X, _, valid = gp.data()
    ref = gp.covar_module(X, xq).to_dense().detach() * valid.unsqueeze(-1)
    assert torch.allclose(gp._cross(xq), ref, atol=1e-12)
    assert torch.allclose(gp.kernel(X, xq) * valid.unsqueeze(-1), ref, atol=1e-12)


def test_paired_solves_of_predict_equal_a_plain_append():
    """Predict-then-append at one point (the paired solves) gives the append without a prediction;
    predicting twice without appending turns the eager backward solve off, and results stay equal."""
    g = torch.Generator().manual_seed(3)
    a = OnlineGP(2, 4, 4, mean="identity", capacity=8)
    b = OnlineGP(2, 4, 4, mean="identity", capacity=8)
    X = torch.randn(60, 2, 4, generator=g, dtype=D)
    for i in range(60):
        a.predict(X[i].unsqueeze(1))
        if i == 30:  # a second prediction before appending
            a.predict(X[i].unsqueeze(1) + 0.1)
            assert not a._streaming
        a.append(X[i], torch.cos(X[i]))
        b.append(X[i], torch.cos(X[i]))
    assert a._streaming  # turned back on by the next append that used a prediction's solve
    xq = torch.randn(2, 5, 4, generator=g, dtype=D)
    for u, v in zip(a.predict(xq), b.predict(xq)):
        assert torch.allclose(u, v, atol=1e-11)
    assert torch.allclose(a.alpha, b.alpha, atol=1e-10)


def test_float32_factor_close_to_float64_factor():
    """model.factor_dtype=float32: the factor in single precision, the rest in float64 (stated tolerance:
    1e-4 relative on mean, variance and Jacobian at n = 200)."""
    ref, g = _grown()
    f32, _ = _grown(torch.float32)
    assert f32.L.dtype == torch.float32 and f32.alpha.dtype == D and f32.X.dtype == D
    xq = torch.randn(3, 7, 4, generator=g, dtype=D)
    for u, v in zip(ref.predict(xq), f32.predict(xq)):
        assert v.dtype == D
        assert ((u - v).abs().max() / u.abs().max()).item() < 1e-4


def test_float32_factor_study_and_bad_values():
    from dslearn.errors import ConfigError

    a = _opts("gp_increment", "hybrid", 2, 2).run()
    b = _opts("gp_increment", "hybrid", 2, 2, **{"model.factor_dtype": "float32"}).run()
    for metric in ("track_err", "pred_err"):
        x, y = (d[d.metric == metric]["value"].to_numpy() for d in (a, b))
        assert np.abs(x - y).max() < 1e-4 * np.abs(x).max(), metric
    with pytest.raises(ConfigError, match="model.factor_dtype"):
        _opts("gp", "hybrid", 1, 1, **{"model.factor_dtype": "float16"})
    with pytest.raises(ConfigError, match="model.factor_dtype"):
        GPMotionModel(8, num_nodes=2, variant="window", window=20, factor_dtype="float32")
