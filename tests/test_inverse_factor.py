"""The exact GP through its inverse Cholesky factor (model.factor=inverse, the CPU default) against
the Cholesky factor and closed forms."""

import copy

import numpy as np
import pytest
import torch

from dslearn.errors import ConfigError
from dslearn.models.gp_backends import inverse_factor
from dslearn.models.gp_backends.exact import OnlineGP
from dslearn.models import GPMotionModel

D = torch.float64


def _lower(s, cap, n, dtype=D, seed=0):
    """A lower-triangular buffer whose entries above the diagonal and past row ``n`` are NaN: a
    kernel that reads them returns NaN."""
    g = torch.Generator().manual_seed(seed)
    M = torch.full((s, cap, cap), float("nan"), dtype=dtype)
    M[:, :n, :n] = torch.tril(torch.randn(s, n, n, generator=g, dtype=D)).to(dtype)
    M[:, :n, :n] += torch.triu(torch.full((n, n), float("nan"), dtype=dtype), 1)
    return M, torch.randn(s, n, generator=g, dtype=D)


@pytest.mark.parametrize("n", [1, 2, 7, 8, 9, 16, 17, 63, 257])
def test_pair_equals_dense_products_and_reads_only_the_lower_triangle(n):
    M, k = _lower(3, n + 5, n)
    Mn = torch.tril(torch.nan_to_num(M[:, :n, :n], nan=0.0))
    w_ref = (Mn @ k.unsqueeze(-1)).squeeze(-1)
    b_ref = (Mn.transpose(-1, -2) @ w_ref.unsqueeze(-1)).squeeze(-1)
    w, b = inverse_factor.pair(M, k, n)
    assert w.shape == b.shape == (3, n) and w.dtype == b.dtype == D
    assert torch.isfinite(w).all() and torch.isfinite(b).all()
    scale = (Mn.abs() @ k.abs().unsqueeze(-1)).squeeze(-1).max()
    assert (w - w_ref).abs().max() <= 1e-13 * scale
    assert (b - b_ref).abs().max() <= 1e-12 * scale * Mn.abs().sum(-2).max()
    w_only, none = inverse_factor.pair(M, k, n, need_b=False)
    assert none is None and torch.equal(w_only, w)


def test_pair_of_a_zero_right_hand_side_is_zero_without_reading_the_factor():
    M, k = _lower(3, 20, 17)
    k[1] = 0.0  # node 1 has learnt nothing valid: its row of k is zero
    M[1] = float("nan")  # ... and its factor is not read
    w, b = inverse_factor.pair(M, k, 17)
    assert torch.equal(w[1], torch.zeros(17, dtype=D)) and torch.equal(b[1], torch.zeros(17, dtype=D))
    ref = inverse_factor.pair(torch.nan_to_num(M, nan=0.0), k, 17)
    assert torch.equal(w[[0, 2]], ref[0][[0, 2]]) and torch.equal(b[[0, 2]], ref[1][[0, 2]])


def test_pair_with_a_float32_factor_accumulates_in_the_right_hand_sides_dtype():
    M, k = _lower(2, 40, 33, dtype=torch.float32)
    w, b = inverse_factor.pair(M, k, 33)
    Mn = torch.tril(torch.nan_to_num(M[:, :33, :33], nan=0.0)).to(D)
    w_ref = (Mn @ k.unsqueeze(-1)).squeeze(-1)
    assert w.dtype == D and torch.allclose(w, w_ref, rtol=0, atol=1e-12 * float(w_ref.abs().max()) * 33)
    assert torch.allclose(b, (Mn.transpose(-1, -2) @ w_ref.unsqueeze(-1)).squeeze(-1), rtol=1e-10, atol=1e-10)


def test_torch_path_equals_the_kernel(monkeypatch):
    M, k = _lower(2, 30, 21)
    M = torch.nan_to_num(M, nan=0.0)
    a = inverse_factor.pair(M, k, 21)
    monkeypatch.setattr(inverse_factor, "HAVE_KERNEL", False)
    b = inverse_factor.pair(M, k, 21)
    for u, v in zip(a, b):
        assert torch.allclose(u, v, rtol=1e-13, atol=1e-13)


def _stream(factor, n=300, s=3, d=4, seed=0, predict=True, capacity=8):
    g = torch.Generator().manual_seed(seed)
    gp = OnlineGP(s, d, d, outputscale=1.1, lengthscale=1.4, noise_std=0.3, mean="identity", capacity=capacity,
                  factor=factor)
    X = 1.5 * torch.randn(n, s, d, generator=g, dtype=D)
    for i in range(n):
        if predict and i % 7 != 3:  # most appends reuse a prediction's pass; some do their own
            gp.predict(X[i].unsqueeze(1))
        gp.append(X[i], X[i] + 0.3 * torch.sin(X[i]), torch.tensor([True, i % 3 != 0, True]))
    return gp, g


def test_auto_is_inverse_on_the_cpu_and_the_window_gp_keeps_its_cholesky_factor():
    assert OnlineGP(2, 4, 4).inverse is inverse_factor.HAVE_KERNEL
    assert OnlineGP(2, 4, 4, factor="cholesky").inverse is False
    m = GPMotionModel(8, num_nodes=2, variant="window", window=20)
    assert m.gp.inverse is False


def test_inverse_factor_equals_cholesky_factor_through_growth_and_invalid_points():
    inv, g = _stream("inverse")
    chol, _ = _stream("cholesky")
    assert inv.inverse and not chol.inverse and inv.n == chol.n == 300
    n = inv.n
    M, L = inv.L[:, :n, :n], chol.L[:, :n, :n]
    assert torch.equal(M, torch.tril(M))
    assert (M @ L - torch.eye(n, dtype=D)).abs().max() < 1e-11  # M = L^{-1}
    xq = torch.randn(3, 9, 4, generator=g, dtype=D)
    for u, v in zip(inv.predict(xq), chol.predict(xq)):
        assert torch.allclose(u, v, rtol=0, atol=1e-11)
    assert torch.allclose(inv.alpha, chol.alpha, atol=1e-10)
    rhs = torch.randn(3, n, 2, generator=g, dtype=D)
    assert torch.allclose(inv.solve(rhs), chol.solve(rhs), atol=1e-9)


def test_incremental_inverse_factor_equals_a_refactorisation():
    gp, g = _stream("inverse", n=200)
    M, alpha = gp.L[:, : gp.n, : gp.n].clone(), gp.alpha.clone()
    xq = torch.randn(3, 5, 4, generator=g, dtype=D)
    before = gp.predict(xq)
    gp.refactorize()
    assert torch.allclose(gp.L[:, : gp.n, : gp.n], M, atol=1e-10)
    assert torch.allclose(gp.alpha, alpha, atol=1e-9)
    for u, v in zip(before, gp.predict(xq)):
        assert torch.allclose(u, v, atol=1e-10)


def test_appends_without_predictions_equal_predict_then_append():
    a, g = _stream("inverse", n=120)
    b, _ = _stream("inverse", n=120, predict=False)
    xq = torch.randn(3, 4, 4, generator=g, dtype=D)
    for u, v in zip(a.predict(xq), b.predict(xq)):
        assert torch.allclose(u, v, atol=1e-12)


def test_reserve_allocates_once_and_changes_no_result():
    a, _ = _stream("inverse", n=150, capacity=8)
    g = torch.Generator().manual_seed(0)
    b = OnlineGP(3, 4, 4, outputscale=1.1, lengthscale=1.4, noise_std=0.3, mean="identity", capacity=8, factor="inverse")
    b.reserve(150)
    cap = b.L.shape[-1]
    assert cap == 150
    X = 1.5 * torch.randn(150, 3, 4, generator=g, dtype=D)
    for i in range(150):
        if i % 7 != 3:
            b.predict(X[i].unsqueeze(1))
        b.append(X[i], X[i] + 0.3 * torch.sin(X[i]), torch.tensor([True, i % 3 != 0, True]))
    assert b.L.shape[-1] == cap  # no regrowth
    xq = torch.randn(3, 4, 4, dtype=D)
    for u, v in zip(a.predict(xq), b.predict(xq)):
        assert torch.allclose(u, v, atol=1e-12)
    chol = OnlineGP(3, 4, 4, capacity=8, factor="cholesky")
    chol.reserve(1000)  # the Cholesky solves run over the whole buffer: no slack taken
    assert chol.L.shape[-1] == 8


def test_study_results_do_not_depend_on_the_factor_form():
    from dslearn import api

    runs = [api.yu_study(model="gp_increment", consensus="hybrid", train_episodes=3, test_episodes=2,
                                 **{"model.factor": f}).run() for f in ("inverse", "cholesky")]
    a, b = (r["value"].to_numpy() for r in runs)
    np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-10)


def test_bad_factor_values_are_refused_before_any_work():
    from dslearn import api

    with pytest.raises(ConfigError, match="model.factor"):
        api.yu_study(model="gp", consensus="hybrid", **{"model.factor": "lu"})
    with pytest.raises(ConfigError, match="model.factor"):
        GPMotionModel(8, num_nodes=2, variant="window", window=20, factor="inverse")
    with pytest.raises(ConfigError, match="model.factor"):
        OnlineGP(2, 4, 4, factor="qr")


def _exact_posterior(X, Y, valid, xq, sf2, ls, s2):
    """The textbook exact GP of one node, from scratch: identity prior mean, RBF kernel
    ``k(a, b) = sf2 exp(-|a - b|^2 / 2 ls^2)`` on the valid points only; mean
    ``x + k^T (K + s2 I)^{-1} (Y - X)`` and latent variance ``sf2 - k^T (K + s2 I)^{-1} k`` at ``xq (N, d)``."""
    X, Y = X[valid], Y[valid]

    def k(a, b):
        return sf2 * torch.exp(-torch.cdist(a, b).square() / (2 * ls**2))

    G = k(X, X) + s2 * torch.eye(len(X), dtype=D)
    ks = k(X, xq)
    return xq + ks.T @ torch.linalg.solve(G, Y - X), sf2 - (ks * torch.linalg.solve(G, ks)).sum(0)


def test_a_copied_gp_keeps_streaming():
    """A deep copy is an independent GP: the original and the copy, fed different points after the
    copy, each predict what the exact GP of its own data set predicts (computed from scratch with
    the hyperparameters the original held before the copy)."""
    n, s, d = 40, 3, 4
    gp, g = _stream("inverse", n=n)
    hyp = [(float(gp.outputscale[i]), float(gp.lengthscale.flatten()[i]), float(gp.noise_var.flatten()[i]))
           for i in range(s)]  # 1.1^2, 1.4, 0.3^2 as stored
    twin = copy.deepcopy(gp)
    X = 1.5 * torch.randn(n, s, d, generator=torch.Generator().manual_seed(0), dtype=D)  # _stream's inputs
    valid = torch.stack([torch.tensor([True, i % 3 != 0, True]) for i in range(n)])  # (n, S)
    xa, xb = torch.randn(2, s, d, generator=g, dtype=D)
    for m, x in ((gp, xa), (twin, xb)):
        m.predict(x.unsqueeze(1))
        m.append(x, x + 0.3 * torch.sin(x))
    xq = torch.randn(s, 5, d, generator=g, dtype=D)
    for m, x in ((gp, xa), (twin, xb)):
        assert m.n == n + 1
        mean, var, _ = m.predict(xq)
        for i in range(s):
            Xi = torch.cat([X[:, i], x[i : i + 1]])
            vi = torch.cat([valid[:, i], torch.tensor([True])])
            ref_mean, ref_var = _exact_posterior(Xi, Xi + 0.3 * torch.sin(Xi), vi, xq[i], *hyp[i])
            torch.testing.assert_close(mean[i], ref_mean, rtol=0, atol=1e-11)
            torch.testing.assert_close(var[i], ref_var, rtol=0, atol=1e-11)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_inverse_factor_on_cuda_equals_the_cpu_kernel():
    """model.factor=inverse on CUDA (torch products, no compiled kernel) against the CPU kernel."""
    g = torch.Generator().manual_seed(5)
    X = 1.5 * torch.randn(80, 3, 4, generator=g, dtype=D)
    gps = [OnlineGP(3, 4, 4, mean="identity", capacity=8, factor="inverse", device=dev) for dev in ("cpu", "cuda")]
    for i in range(80):
        for gp in gps:
            gp.predict(X[i].unsqueeze(1).to(gp.device_))
            gp.append(X[i].to(gp.device_), torch.sin(X[i]).to(gp.device_))
    xq = torch.randn(3, 5, 4, generator=g, dtype=D)
    for u, v in zip(gps[0].predict(xq), gps[1].predict(xq.cuda())):
        assert torch.allclose(u, v.cpu(), atol=1e-11)
