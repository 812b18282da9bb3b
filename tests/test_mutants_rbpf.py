"""dslearn/filters/rbpf.py: systematic resampling in closed form (the last particle reachable, only
relative weights matter, the uniform drawn from ``gen`` in the weights' dtype, any batch dims) and the
transition statistics without batch dims (benchmarks/mutation: survivors of the mutation run)."""

import math

import pytest
import torch

from dslearn.filters.rbpf import systematic_indices, transition_stats

D = torch.float64


def test_systematic_indices_closed_form():
    """w = (0.1, 0.2, 0.3, 0.4), u = (u0 + i) / 4: ancestor i is the first j with cumsum(w)_j >= u_i."""
    logw = torch.tensor([0.1, 0.2, 0.3, 0.4], dtype=D).log()
    u0 = torch.tensor([[0.5]], dtype=D)
    assert systematic_indices(logw[None], u0=u0).tolist() == [[1, 2, 3, 3]]
    # only relative weights matter: the cumulative weights are divided by their total
    assert systematic_indices(logw[None] + 0.7, u0=u0).tolist() == [[1, 2, 3, 3]]
    assert systematic_indices(logw[None] - 2.0, u0=torch.tensor([[0.05]], dtype=D)).tolist() == [[0, 1, 2, 3]]
    # all the weight on the last particle: every ancestor is the last particle
    last = torch.tensor([[-math.inf, -math.inf, -math.inf, 0.0]], dtype=D)
    for u in (0.25, 0.5, 1 - 2**-53):
        assert systematic_indices(last, u0=torch.tensor([[u]], dtype=D)).tolist() == [[3, 3, 3, 3]]


def test_a_zero_weight_particle_is_never_an_ancestor():
    last = torch.tensor([[-math.inf, -math.inf, -math.inf, 0.0]], dtype=D)
    assert systematic_indices(last, u0=torch.zeros(1, 1, dtype=D)).tolist() == [[3, 3, 3, 3]]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_uniform_is_drawn_from_gen_in_the_weights_dtype(dtype):
    """Without ``u0``: one uniform per batch entry from ``gen`` (in logw's dtype), any batch dims."""
    g = torch.Generator().manual_seed(0)
    logw = torch.log_softmax(torch.randn(2, 3, 7, generator=g, dtype=D), -1).to(dtype)
    got = systematic_indices(logw, torch.Generator().manual_seed(5))
    u0 = torch.rand(2, 3, 1, generator=torch.Generator().manual_seed(5), dtype=dtype)
    want = systematic_indices(logw, u0=u0)
    assert got.shape == (2, 3, 7) and torch.equal(got, want)
    # and u0 is what the ancestors say: counts differ from N w by less than 1 (systematic resampling)
    counts = torch.nn.functional.one_hot(got, 7).sum(-2).to(D)
    assert ((counts - 7 * logw.double().exp()).abs() < 1 + 1e-6).all()


def test_transition_stats_closed_form_without_batch_dims():
    """bm (N, K, K), e (N,): row l = [bm[l, k] 1(l'=l) for k, l'] + [1(l'=l)] + [1(l'=l) e] + [1(l'=l) e^2]."""
    n, k = 3, 2
    g = torch.Generator().manual_seed(1)
    bm, e = torch.rand(n, k, k, generator=g, dtype=D), torch.randn(n, generator=g, dtype=D)
    out = transition_stats(bm, e)
    want = torch.zeros(n, k, k * k + 3 * k, dtype=D)
    for i in range(n):
        for l in range(k):
            for kk in range(k):
                want[i, l, kk * k + l] = bm[i, l, kk]
            want[i, l, k * k + l] = 1.0
            want[i, l, k * k + k + l] = e[i]
            want[i, l, k * k + 2 * k + l] = e[i] ** 2
    assert torch.equal(out, want)
    batched = transition_stats(bm.expand(4, n, k, k), e.expand(4, n))
    assert batched.shape == (4, n, k, k * k + 3 * k) and torch.equal(batched, want.expand(4, -1, -1, -1))
