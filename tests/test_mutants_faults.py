"""dslearn/fusion/faults.py: the faulty-network wrapper against an independent recomputation of its
semantics (the live graph of step t from the seeded generator and column t of the alive schedule,
Metropolis/uniform weights on it, W^L handed to the base strategy), its defaults, its refusals and
its link counts (benchmarks/mutation: survivors of the mutation run)."""

import copy

import pytest
import torch

from dslearn.errors import ConfigError
from dslearn.fusion.faults import FaultyFusion, draw_live_graph, live_weights
from dslearn.fusion.strategies import make_fusion
from dslearn.fusion.weights import metropolis

D = torch.float64
# a small irregular graph: path 0-1-2-3 and a leaf 4 on node 1 (degrees 1, 3, 2, 1, 1); 4 edges
EDGES = [(0, 1), (1, 2), (2, 3), (1, 4)]
S, B, DX, L = 5, 3, 4, 3


def _adj() -> torch.Tensor:
    a = torch.zeros(S, S, dtype=torch.bool)
    for i, j in EDGES:
        a[i, j] = a[j, i] = True
    return a


def _beliefs(seed=0):
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(S, B, DX, DX, generator=g, dtype=D)
    o = a @ a.transpose(-1, -2) + DX * torch.eye(DX, dtype=D)
    q = torch.randn(S, B, DX, generator=g, dtype=D)
    return q, o, 0.3 * torch.randn(S, B, DX, generator=g, dtype=D), 0.2 * o


def _base(name="hybrid"):
    return make_fusion(name, metropolis(_adj()), L, "one")


def _expected(live: torch.Tensor, name="hybrid", method="metropolis"):
    """What the wrapper must return for the live graphs ``live (B, S, S)``: the base strategy with
    ``W^L`` of the live graph's weights, computed here episode by episode."""
    wl = torch.stack([torch.linalg.matrix_power(live_weights(live[b:b + 1], method)[0], L) for b in range(B)])
    return _base(name)(*_beliefs(), wl=wl)


def _same(a, b, tol=1e-13):
    """Equal up to rounding (the wrapper mixes with a batched W^L, the base with a static one)."""
    return all(torch.allclose(x, y, rtol=tol, atol=tol) for x, y in zip(a, b))


def test_live_weights_default_method_is_metropolis():
    g = torch.Generator().manual_seed(1)
    live = draw_live_graph(_adj(), torch.ones(B, S, dtype=torch.bool), 0.4, g)
    assert torch.equal(live_weights(live), live_weights(live, "metropolis"))
    # closed form on the full graph: w_01 = 1 / (1 + max(1, 3)), w_00 = 1 - 1/4
    w = live_weights(_adj().expand(B, S, S))
    assert float(w[0, 0, 1]) == 0.25 and float(w[0, 0, 0]) == 0.75 and w.dtype == D


def test_draw_live_graph_accepts_a_0_1_adjacency_of_any_dtype():
    alive = torch.ones(B, S, dtype=torch.bool)
    ref = draw_live_graph(_adj(), alive, 0.5, torch.Generator().manual_seed(4))
    for dtype in (torch.float64, torch.int64):
        out = draw_live_graph(_adj().to(dtype), alive, 0.5, torch.Generator().manual_seed(4))
        assert out.dtype == torch.bool and torch.equal(out, ref)


def test_refusals_name_the_key_and_the_choices():
    live = _adj().expand(B, S, S)
    choices = r"is not allowed; choose one of \['metropolis', 'uniform'\]"
    with pytest.raises(ConfigError, match=r"^faults\.weights='mean' " + choices):
        live_weights(live, "mean")
    with pytest.raises(ConfigError, match=r"^faults\.weights='mean' " + choices):
        FaultyFusion(_base(), _adj(), 0.1, "mean")
    for bad in (1.5, -0.1):
        with pytest.raises(ConfigError, match=rf"^faults\.link_fail={bad!r} must be a probability in \[0, 1\]"):
            FaultyFusion(_base(), _adj(), bad)
    ff = FaultyFusion(_base(), _adj(), 0.1)
    with pytest.raises(RuntimeError, match=r"begin\(alive\) must be called"):
        ff(*_beliefs())  # a consensus strategy needs the alive schedule first
    with pytest.raises(ValueError, match="batch size"):
        ff.begin(None)


def test_every_link_down_is_individual_fusion():
    """p_link = 1 is a legal probability: no message arrives, every node keeps its own belief."""
    ff = FaultyFusion(_base("hybrid"), _adj(), 1.0)
    ff.begin(None, batch=B)
    out = ff(*_beliefs())
    ref = make_fusion("individual", metropolis(_adj()), L)(*_beliefs())
    for x, y in zip(out, ref):
        torch.testing.assert_close(x, y, rtol=1e-13, atol=1e-13)
    assert ff.live_links == 0.0 and ff.nominal_links == len(EDGES) * B


def test_defaults_are_no_faults_metropolis_seed_0():
    q, o, dq, do = _beliefs()
    ff = FaultyFusion(_base(), _adj())  # p_link 0, Metropolis weights
    ff.begin(None, batch=B)
    assert _same(ff(q, o, dq, do), _base()(q, o, dq, do))
    # the default seed is 0 and begin() defaults to split "test"
    alive = torch.ones(S, B, 4, dtype=torch.bool)
    a, b = FaultyFusion(_base(), _adj(), 0.5), FaultyFusion(_base(), _adj(), 0.5, "metropolis", 0)
    a.begin(alive)
    b.begin(alive)
    for _ in range(4):
        assert _same(a(q, o, dq, do), b(q, o, dq, do))
    a.begin(alive, episodes=[3, 0, 7])
    b.begin(alive, episodes=[3, 0, 7], split="test")
    for _ in range(4):
        assert _same(a(q, o, dq, do), b(q, o, dq, do))


def test_link_draws_follow_the_seed_and_continue_until_reseeded():
    """Step t's live graph is draw t of a generator seeded ``seed``; a second begin() continues the
    stream (fresh failures), begin(reseed=True) starts it again."""
    q, o, dq, do = _beliefs()
    p, seed, steps = 0.5, 7, 3
    ref_gen = torch.Generator().manual_seed(seed)
    alive = torch.ones(B, S, dtype=torch.bool)
    first = [_expected(draw_live_graph(_adj(), alive, p, ref_gen)) for _ in range(steps)]
    second = [_expected(draw_live_graph(_adj(), alive, p, ref_gen)) for _ in range(steps)]
    assert not all(_same(x, y) for x, y in zip(first, second))
    ff = FaultyFusion(_base(), _adj(), p, seed=seed)
    for reseed, ref in ((False, first), (False, second), (True, first)):
        if reseed:
            ff.begin(None, batch=B, reseed=True)
        else:
            ff.begin(None, batch=B)  # the default: the stream continues
        for r in ref:
            out = ff(q, o, dq, do)
            for x, y in zip(out, r):
                torch.testing.assert_close(x, y, rtol=1e-13, atol=1e-13)


def test_call_t_uses_column_t_of_the_alive_schedule_and_holds_the_last():
    """Call t after begin() (t = 0 is the initial belief's fusion) uses ``alive[:, :, t]``; calls past
    the schedule's end keep its last column; ``begin(None)`` is every node alive at every call."""
    k = 3
    alive = torch.ones(S, B, k + 1, dtype=torch.bool)
    alive[1, :, 1] = False          # t = 1: the hub fails (transiently)
    alive[0, 0, 2] = False          # t = 2: a leaf fails in episode 0
    alive[2:4, 1, 3] = False        # t = 3: two nodes fail in episode 1
    ff = FaultyFusion(_base(), _adj(), 0.0)
    ff.begin(alive)
    for t in list(range(k + 1)) + [k + 1, k + 2]:
        a = alive[:, :, min(t, k)].T  # (B, S)
        live = _adj() & a.unsqueeze(-1) & a.unsqueeze(-2)
        for x, y in zip(ff(*_beliefs()), _expected(live)):
            torch.testing.assert_close(x, y, rtol=1e-13, atol=1e-13)
    ff.begin(None, batch=B)
    for _ in range(3):
        assert _same(ff(*_beliefs()), _base()(*_beliefs()))


def test_link_counts_closed_form():
    """live_links / nominal_links sum the live and nominal undirected links over steps and episodes."""
    alive = torch.ones(S, B, 2, dtype=torch.bool)
    alive[1, 0, 1] = False  # the hub (3 links) fails in episode 0 at t = 1
    ff = FaultyFusion(_base(), _adj(), 0.0)
    ff.begin(alive)
    ff(*_beliefs())
    ff(*_beliefs())
    assert ff.nominal_links == 2 * B * len(EDGES)
    assert ff.live_links == 2 * B * len(EDGES) - 3


@pytest.mark.parametrize("name", ["individual", "centralized"])
def test_no_message_strategies_need_no_schedule_and_draw_nothing(name):
    ff = FaultyFusion(_base(name), _adj(), 0.5, seed=3)
    state = ff.gen.get_state()
    for _ in range(2):
        assert _same(ff(*_beliefs()), _base(name)(*_beliefs()))
    assert torch.equal(ff.gen.get_state(), state) and ff.live_links == 0.0


def test_deep_copy_keeps_the_wrapper_working():
    ff = FaultyFusion(_base(), _adj(), 0.5, seed=2)
    ff.begin(None, batch=B)
    twin = copy.deepcopy(ff)
    assert twin.iterations == L and twin.name == "hybrid"
    assert _same(twin(*_beliefs()), ff(*_beliefs()))
