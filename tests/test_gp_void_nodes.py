"""OnlineGP.skip_void per node: where some nodes hold a valid point and others none, the passes run on the
active nodes only and the void nodes get the prior; the numbers equal the full passes' (skip_void=False) on mixed
batches of void and non-void nodes, through the predictions, the appends and the buffers: bit for bit, except
the latent variance at several queries per node through the inverse factor (a batched product over the active
nodes' factors: the BLAS's batched kernel for small matrices sums in an order that depends on the batch size,
so there the numbers agree to 1e-12 relative, to float32's 1e-5 with the factor in float32)."""

from __future__ import annotations

import pytest
import torch

from dslearn.models.gp_backends.exact import OnlineGP
from dslearn.models.gp_backends.sparse import WindowGP


def _bits(t: torch.Tensor) -> torch.Tensor:
    """The tensor's bit patterns for float64 (NaNs compare equal); float32 compared as values with NaN."""
    if t.dtype == torch.float64:
        return t.contiguous().view(torch.int64)
    if t.dtype == torch.float32:
        return t.contiguous().view(torch.int32)
    return t


def _same(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return a.shape == b.shape and a.dtype == b.dtype and torch.equal(_bits(a), _bits(b))


def _check(a, b, many: bool, what: str, rtol: float = 1e-12) -> None:
    """Bit for bit; a latent variance at several queries per node to ``rtol`` (module docstring)."""
    if many and a is not None and b is not None:
        torch.testing.assert_close(a, b, rtol=rtol, atol=0.0, msg=what)
    else:
        assert _same(a, b), what


VOID = (1, 4)  # nodes that never hold a valid point


def _run(make, skip: bool, steps: int, queries=(1, 3, 9)):
    """Algorithm 1's pattern (predict at a point, then append there) on a GP whose nodes ``VOID`` never get a valid
    point and the others about two in three; each step also predicts at several points per node (the UKF's
    sigma points; 9 > Dx takes the Jacobian's third branch) with and without the variance and Jacobian."""
    gp = make()
    gp.skip_void = skip
    gen = torch.Generator().manual_seed(11)
    s, d = gp.num_nodes, gp.input_dim
    outs = []  # (prediction, whether it is a latent variance at several queries per node)
    for step in range(steps):
        x = torch.randn(s, d, generator=gen, dtype=torch.float64)
        for nq in queries:
            many = torch.randn(s, nq, d, generator=gen, dtype=torch.float64)
            mean, var, jac = gp.predict(many)
            outs += [(mean, False), (var, nq > 1), (jac, False)]
            outs += [(t, False) for t in gp.predict(many, jacobian=False, variance=False)]
            if gp.supports_belief:  # averaged over a Gaussian belief (model.inputs=belief, the GP-ADF's mean)
                A = torch.randn(s, nq, d, d, generator=gen, dtype=torch.float64)
                cov = 0.3 * A @ A.transpose(-1, -2) + 0.1 * torch.eye(d, dtype=torch.float64)
                mean, var, jac = gp.predict_belief(many, cov)
                outs += [(mean, False), (var, nq > 1), (jac, False)]
                outs += [(t, False) for t in gp.predict_belief(many, cov, jacobian=False, variance=False)]
        outs += [(t, False) for t in gp.predict(x.unsqueeze(1))]  # the point about to be appended (its solves kept for the append)
        valid = torch.rand(s, generator=gen) < 0.67
        valid[list(VOID)] = False
        gp.append(x, torch.sin(x) + 0.1 * x, valid)
    n = gp.n
    buffers = [gp.X[:, :n], gp.Xs[:, :n], gp.Xn[:, :n], gp.R[:, :n], gp.V[:, :n], gp.alpha, gp.L, gp.mask]
    return outs, buffers, gp


MAKERS = {
    "inverse": lambda: OnlineGP(6, 4, 4, capacity=8, mean="identity", factor="inverse"),
    "inverse float32": lambda: OnlineGP(6, 4, 4, capacity=8, mean="identity", factor="inverse",
                                        factor_dtype=torch.float32),
    "cholesky": lambda: OnlineGP(6, 4, 4, capacity=8, mean="identity", factor="cholesky"),
    "zero mean": lambda: OnlineGP(5, 2, 2, capacity=64, mean="zero"),
    "window": lambda: WindowGP(6, 4, 4, window=7, mean="identity"),
}


@pytest.mark.parametrize("kind", list(MAKERS))
def test_per_node_void_passes_give_the_full_passes_numbers_bit_for_bit(kind):
    fast_out, fast_buf, gp = _run(MAKERS[kind], True, 12)
    full_out, full_buf, _ = _run(MAKERS[kind], False, 12)
    assert len(fast_out) == len(full_out)
    rtol = 1e-12 if gp.factor_dtype_ == torch.float64 else 1e-5
    for i, ((a, many), (b, _)) in enumerate(zip(fast_out, full_out)):
        _check(a, b, many, f"prediction {i}", rtol)
    for i, (a, b) in enumerate(zip(fast_buf, full_buf)):
        assert _same(a, b), f"buffer {i}"
    act = gp._active()  # the nodes that run the passes: all but the void ones
    assert act is not None and act.tolist() == [i for i in range(gp.num_nodes) if i not in VOID]
    assert not gp._void()


def test_past_one_block_of_the_inverse_factor():
    """More than 256 points: the inverse factor's products run over several blocks of rows, on the active rows."""
    make = lambda: OnlineGP(5, 4, 4, capacity=8, mean="identity", factor="inverse")  # noqa: E731
    fast_out, fast_buf, gp = _run(make, True, 270, queries=(5,))
    full_out, full_buf, _ = _run(make, False, 270, queries=(5,))
    assert gp.n == 270
    for i, ((a, many), (b, _)) in enumerate(zip(fast_out, full_out)):
        _check(a, b, many, f"prediction {i}")
    assert all(_same(a, b) for a, b in zip(fast_buf, full_buf))


def test_a_void_node_gets_the_prior_and_the_others_their_posterior():
    gp = OnlineGP(3, 4, 4, capacity=8, mean="identity", factor="inverse")
    gen = torch.Generator().manual_seed(3)
    for _ in range(5):
        x = torch.randn(3, 4, generator=gen, dtype=torch.float64)
        gp.append(x, x + 1.0, torch.tensor([True, False, True]))
    q = torch.randn(3, 2, 4, generator=gen, dtype=torch.float64)
    mean, var, jac = gp.predict(q)
    assert gp._active().tolist() == [0, 2]
    assert torch.equal(mean[1], q[1]) and torch.equal(var[1], gp.outputscale[1].expand(2))
    assert torch.equal(jac[1], torch.eye(4, dtype=torch.float64).expand(2, 4, 4))
    # the active nodes: the posterior against a GP holding only their data
    ref = OnlineGP(2, 4, 4, capacity=8, mean="identity", factor="cholesky")
    X, R, m = gp.data()
    ref.set_data(X[[0, 2]], R[[0, 2]], m[[0, 2]], residual=True)
    rm, rv, rj = ref.predict(q[[0, 2]])
    torch.testing.assert_close(mean[[0, 2]], rm, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(var[[0, 2]], rv, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(jac[[0, 2]], rj, rtol=1e-10, atol=1e-12)
    assert not torch.allclose(mean[0], q[0])  # it has learned something


@pytest.mark.parametrize("noise", ["latent", "predictive"])
def test_the_gp_adf_through_a_void_gp_gives_the_full_moments_bit_for_bit(noise):
    """The GP-ADF's exact moments through a GP whose points are all invalid (Liu's field under hybrid fusion):
    the prior's moments without the O(S n^2) terms, equal to the full computation's."""
    from dslearn.filters.adf import adf_predict
    from dslearn.models.gp import GPMotionModel
    from dslearn.types import StepContext

    outs = {}
    for skip in (True, False):
        model = GPMotionModel(8, num_nodes=3, mean="identity", noise=noise, capacity=4)
        model.gp.skip_void = skip
        g = torch.Generator().manual_seed(7)
        res = []
        for step in range(6):
            x = torch.randn(3, 2, 8, generator=g, dtype=torch.float64)
            A = torch.randn(3, 2, 8, 8, generator=g, dtype=torch.float64)
            omega = torch.linalg.inv(0.2 * A @ A.transpose(-1, -2) + 0.05 * torch.eye(8, dtype=torch.float64))
            res += list(adf_predict(x, omega, model, StepContext(dt=1.0), full=True))
            model.add_data(x[:, 0], x[:, 0] + 0.1, torch.zeros(3, dtype=torch.bool))
        outs[skip] = res
        assert model.gp.n == 6 and not bool(model.gp.mask.any())
    for i, (a, b) in enumerate(zip(outs[True], outs[False])):
        assert a.shape == b.shape and torch.equal(a, b), f"output {i}"
