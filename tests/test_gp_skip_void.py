"""OnlineGP.skip_void: while no node holds a valid point, predictions are the prior and appends write only the
unit row of an invalid point (no passes over the factor), with the numbers of the full passes, bit for bit."""

from __future__ import annotations

import pytest
import torch

from dslearn.models.gp_backends.exact import OnlineGP
from dslearn.models.gp_backends.sparse import WindowGP


def _bits(t: torch.Tensor) -> torch.Tensor:
    """The tensor's bit patterns (-0.0 and 0.0 differ, NaNs compare equal)."""
    return t.contiguous().view(torch.int64) if t.dtype == torch.float64 else t


def _same(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return a.shape == b.shape and torch.equal(_bits(a), _bits(b))


def _run(make, skip: bool, schedule: list[str], queries: int = 1):
    """Predict then append at the predicted point (Algorithm 1), ``schedule`` gives each step's valid nodes:
    ``none``, ``some`` or ``all``; every step's predictions (``queries`` points per node; more after) and the
    buffers at the end."""
    gp = make()
    gp.skip_void = skip
    gen = torch.Generator().manual_seed(5)
    s, d = gp.num_nodes, gp.input_dim
    outs, calls = [], []
    for step, which in enumerate(schedule):
        x = torch.randn(s, d, generator=gen, dtype=torch.float64)
        mean, var, jac = gp.predict(x.unsqueeze(1))
        outs += [mean, var, jac]
        many = torch.randn(s, 3, d, generator=gen, dtype=torch.float64)
        outs += list(gp.predict(many))  # several queries per node (the UKF's sigma points): no paired solve
        gp.predict(x.unsqueeze(1))  # and the point about to be appended again (the paired solve, kept)
        valid = {"none": torch.zeros(s, dtype=torch.bool), "all": torch.ones(s, dtype=torch.bool),
                 "some": torch.arange(s) % 2 == step % 2}[which]
        gp.append(x, torch.sin(x), valid)
        calls.append(gp._void())
    n = gp.n
    buffers = [gp.X[:, :n], gp.Xs[:, :n], gp.Xn[:, :n], gp.R[:, :n], gp.V[:, :n], gp.alpha, gp.L, gp.mask]
    return outs, buffers, calls


MAKERS = {
    "inverse": lambda: OnlineGP(4, 4, 4, capacity=4, mean="identity", factor="inverse"),
    "cholesky": lambda: OnlineGP(4, 4, 4, capacity=4, mean="identity", factor="cholesky"),
    "zero mean": lambda: OnlineGP(3, 2, 2, capacity=64, mean="zero"),
    "window": lambda: WindowGP(3, 4, 4, window=5, mean="identity"),
}


@pytest.mark.parametrize("kind", list(MAKERS))
@pytest.mark.parametrize("schedule", [["none"] * 9, ["none"] * 6 + ["some", "none", "all", "none", "some"],
                                      ["some", "none", "none", "all"]])
def test_skipping_the_void_passes_gives_the_full_passes_numbers_bit_for_bit(kind, schedule):
    fast_out, fast_buf, fast_void = _run(MAKERS[kind], True, schedule)
    full_out, full_buf, _ = _run(MAKERS[kind], False, schedule)
    assert len(fast_out) == len(full_out) == 6 * len(schedule)
    for i, (a, b) in enumerate(zip(fast_out, full_out)):
        assert _same(a, b), f"prediction {i}"
    for i, (a, b) in enumerate(zip(fast_buf, full_buf)):
        assert _same(a, b), f"buffer {i}"
    first_valid = next((i for i, w in enumerate(schedule) if w != "none"), len(schedule))
    assert fast_void == [i < first_valid for i in range(len(schedule))]  # void until the first valid point


def test_the_void_prediction_is_the_prior_and_a_copy():
    gp = OnlineGP(3, 4, 4, capacity=8, mean="identity")
    for _ in range(3):
        x = torch.randn(3, 4, dtype=torch.float64)
        gp.predict(x.unsqueeze(1))
        gp.append(x, x + 1, torch.zeros(3, dtype=torch.bool))
    assert gp.n == 3 and gp._void() and not bool(gp.mask.any())
    x = torch.randn(3, 1, 4, dtype=torch.float64)
    mean, var, jac = gp.predict(x)
    assert torch.equal(mean, x) and mean.data_ptr() != x.data_ptr()  # identity mean, not a view of the input
    assert torch.equal(var, gp.outputscale.unsqueeze(-1)) and torch.equal(jac, torch.eye(4).expand(3, 1, 4, 4).double())
    gp.set_data(torch.randn(3, 2, 4, dtype=torch.float64), torch.randn(3, 2, 4, dtype=torch.float64),
                torch.tensor([[False, False], [True, False], [False, False]]))
    assert not gp._void()  # a data set with a valid point: the full passes
    gp.reset()
    assert gp._void() and gp.n == 0
