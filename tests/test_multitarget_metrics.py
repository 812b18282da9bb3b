"""Multi-target metrics (dslearn.metrics.multitarget) by value: GOSPA and OSPA against hand computations at
sizes where every term matters, their invariances, and against Stone Soup's implementations (a test-only
dependency: those tests skip when it is not installed); identity switches and fragmentations on hand-made
sequences."""

from __future__ import annotations

import datetime
import importlib.util
import itertools
import math

import numpy as np
import pytest
import torch

from dslearn.errors import ConfigError
from dslearn.metrics.multitarget import gospa, identity_metrics, match_tracks, ospa


def t(x):
    return torch.tensor(x, dtype=torch.float64).reshape(-1, 2)


# ---- GOSPA by hand -----------------------------------------------------------------------------


def test_gospa_hand_unequal_sizes_pair_beyond_c_p1():
    # truth: (0,0), (10,0), (0,5); est: (0,1) [d=1 to (0,0)], (13,4) [d=5 to (10,0), beyond c=3], (0,7) [d=2 to (0,5)]
    # alpha=2, c=3, p=1: loc = 1 + 2 = 3; (10,0) missed and (13,4) false: c/2 each; one extra est (50,50) false
    x = t([[0, 0], [10, 0], [0, 5]])
    y = t([[0, 1], [13, 4], [0, 7], [50, 50]])
    g = gospa(x, y, c=3.0, p=1)
    assert g["gospa_loc"].item() == pytest.approx(3.0, abs=1e-12)
    assert g["gospa_missed"].item() == pytest.approx(1.5, abs=1e-12)
    assert g["gospa_false"].item() == pytest.approx(3.0, abs=1e-12)
    assert g["gospa"].item() == pytest.approx(7.5, abs=1e-12)


def test_gospa_hand_p2_and_p3():
    # truth (0,0), (4,0); est (1,1) [d^2 = 2], (4,2.5) [d=2.5 < c=3]; no miss/false; then p = 3
    x, y = t([[0, 0], [4, 0]]), t([[1, 1], [4, 2.5]])
    g = gospa(x, y, c=3.0, p=2)
    assert g["gospa_loc"].item() == pytest.approx(2 + 6.25, abs=1e-12)
    assert g["gospa"].item() == pytest.approx(math.sqrt(8.25), abs=1e-12)
    assert g["gospa_missed"].item() == 0 and g["gospa_false"].item() == 0
    g3 = gospa(x, y, c=3.0, p=3)
    assert g3["gospa"].item() == pytest.approx((2**1.5 + 2.5**3) ** (1 / 3), abs=1e-12)
    # a pair beyond c at p = 2: (4, 3.5) is 3.5 away -> a miss and a false at c^2 / 2 = 4.5 each
    g = gospa(x, t([[1, 1], [4, 3.5]]), c=3.0, p=2)
    assert (g["gospa_loc"].item(), g["gospa_missed"].item(), g["gospa_false"].item()) == pytest.approx((2, 4.5, 4.5))
    assert g["gospa"].item() == pytest.approx(math.sqrt(11.0), abs=1e-12)


def test_gospa_optimal_not_greedy():
    # greedy nearest pairing (x0 -> y0 at 1) forces x1 -> y1 at 3.0; the optimum pairs x0 -> y1, x1 -> y0:
    # p=2: 1 + 9 = 10 vs 2^2 + 2^2 = 8 (1D positions on the x axis: x0=0, x1=2, y0=1... computed below)
    x, y = t([[0, 0], [3, 0]]), t([[1, 0], [-2, 0]])
    # pairings: {x0-y0: 1, x1-y1: 5} -> 1 + 25 = 26; {x0-y1: 2, x1-y0: 2} -> 8; c large
    assert gospa(x, y, c=10.0, p=2)["gospa_loc"].item() == pytest.approx(8.0)


def test_gospa_empty_sets():
    e = torch.zeros(0, 2, dtype=torch.float64)
    x = t([[0, 0], [1, 1]])
    assert gospa(e, e, c=2.0, p=2)["gospa"].item() == 0.0
    g = gospa(x, e, c=2.0, p=2)
    assert (g["gospa_missed"].item(), g["gospa_false"].item(), g["gospa"].item()) == pytest.approx((4.0, 0.0, 2.0))
    g = gospa(e, x, c=2.0, p=1)
    assert (g["gospa_missed"].item(), g["gospa_false"].item(), g["gospa"].item()) == pytest.approx((0.0, 2.0, 2.0))


def test_gospa_masks_and_batch_match_loops():
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(3, 2, 4, 2, generator=gen, dtype=torch.float64) * 3
    y = torch.randn(3, 2, 5, 2, generator=gen, dtype=torch.float64) * 3
    xm = torch.rand(3, 2, 4, generator=gen) > 0.3
    ym = torch.rand(3, 2, 5, generator=gen) > 0.3
    g = gospa(x, y, c=2.5, p=2, truth_mask=xm, est_mask=ym)
    assert g["gospa"].shape == (3, 2)
    for a, b in itertools.product(range(3), range(2)):
        one = gospa(x[a, b][xm[a, b]], y[a, b][ym[a, b]], c=2.5, p=2)
        for k in g:
            assert g[k][a, b].item() == pytest.approx(one[k].item(), abs=1e-12)
        assert g["gospa"][a, b].item() ** 2 == pytest.approx(
            (g["gospa_loc"] + g["gospa_missed"] + g["gospa_false"])[a, b].item(), abs=1e-10)


def test_gospa_ospa_permutation_invariant_and_symmetry():
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(5, 2, generator=gen, dtype=torch.float64) * 2
    y = torch.randn(7, 2, generator=gen, dtype=torch.float64) * 2
    g, o = gospa(x, y, c=1.5, p=2), ospa(x, y, c=1.5, p=2)
    px, py = x[torch.randperm(5, generator=gen)], y[torch.randperm(7, generator=gen)]
    g2, o2 = gospa(px, py, c=1.5, p=2), ospa(px, py, c=1.5, p=2)
    for k in g:
        assert g[k].item() == pytest.approx(g2[k].item(), abs=1e-12)
    for k in o:
        assert o[k].item() == pytest.approx(o2[k].item(), abs=1e-12)
    # swapping the roles of truth and estimate swaps missed and false and leaves the rest
    gs = gospa(y, x, c=1.5, p=2)
    assert gs["gospa"].item() == pytest.approx(g["gospa"].item(), abs=1e-12)
    assert gs["gospa_missed"].item() == pytest.approx(g["gospa_false"].item(), abs=1e-12)
    assert ospa(y, x, c=1.5, p=2)["ospa"].item() == pytest.approx(o["ospa"].item(), abs=1e-12)


def test_gospa_brute_force_small():
    # brute force over all partial assignments of pairs at d < c
    gen = torch.Generator().manual_seed(2)
    for trial in range(20):
        n, m = int(torch.randint(0, 4, (1,), generator=gen)), int(torch.randint(0, 4, (1,), generator=gen))
        x = torch.rand(n, 2, generator=gen, dtype=torch.float64) * 4
        y = torch.rand(m, 2, generator=gen, dtype=torch.float64) * 4
        c, p = 1.7, [1, 2, 3][trial % 3]
        best = math.inf
        for k in range(min(n, m) + 1):
            for rows in itertools.combinations(range(n), k):
                for cols in itertools.permutations(range(m), k):
                    ds = [float((x[i] - y[j]).norm()) for i, j in zip(rows, cols)]
                    if all(d < c for d in ds):
                        best = min(best, sum(d**p for d in ds) + c**p / 2 * (n + m - 2 * k))
        assert gospa(x, y, c=c, p=p)["gospa"].item() ** p == pytest.approx(best, abs=1e-10)


# ---- OSPA by hand ------------------------------------------------------------------------------


def test_ospa_hand():
    # truth (0,0), (10,0); est (0,1) [d=1], (13,4) [d=5 -> cut to c=3], (0,7) [unpaired: n - m = 1]
    x, y = t([[0, 0], [10, 0]]), t([[0, 1], [13, 4], [0, 7]])
    o = ospa(x, y, c=3.0, p=1)
    assert o["ospa_loc"].item() == pytest.approx((1 + 3) / 3, abs=1e-12)
    assert o["ospa_card"].item() == pytest.approx(3 / 3, abs=1e-12)
    assert o["ospa"].item() == pytest.approx(7 / 3, abs=1e-12)
    o = ospa(x, y, c=3.0, p=2)
    assert o["ospa_loc"].item() == pytest.approx(math.sqrt((1 + 9) / 3), abs=1e-12)
    assert o["ospa_card"].item() == pytest.approx(math.sqrt(9 / 3), abs=1e-12)
    assert o["ospa"].item() == pytest.approx(math.sqrt(19 / 3), abs=1e-12)
    e = torch.zeros(0, 2, dtype=torch.float64)
    assert ospa(e, e, c=3.0)["ospa"].item() == 0.0
    assert ospa(x, e, c=3.0)["ospa"].item() == pytest.approx(3.0)
    assert ospa(e, y, c=3.0, p=1)["ospa_card"].item() == pytest.approx(3.0)


def test_bad_input_named():
    x = t([[0, 0]])
    with pytest.raises(ConfigError, match="c="):
        gospa(x, x, c=0.0)
    with pytest.raises(ConfigError, match="p="):
        ospa(x, x, c=1.0, p=0.5)
    with pytest.raises(ConfigError, match="threshold="):
        identity_metrics(x[None], x[None], threshold=-1)
    with pytest.raises(ConfigError, match="truth"):
        gospa(x, torch.zeros(1, 3, dtype=torch.float64), c=1.0)


# ---- identity switches and fragmentations ------------------------------------------------------


def test_identity_switch_and_fragmentation_by_hand():
    # one target on the x axis at x = t, two tracks; threshold 1
    # step: 0     1     2      3      4     5
    # trk0: 0.1   1.1   far    far    far   far    -> matches t0, t1; lost at t2 (fragment)
    # trk1: far   far   far    3.2    4.1   far    -> picked up at t3 by another track (switch), lost at t5 (end)
    far = 100.0
    x = torch.tensor([[[float(s), 0.0]] for s in range(6)], dtype=torch.float64)  # (6, 1, 2)
    y0 = [[0.1, 0], [1.1, 0], [far, 0], [far, 0], [far, 0], [far, 0]]
    y1 = [[far, far], [far, far], [far, far], [3.2, 0], [4.1, 0], [far, far]]
    y = torch.tensor([[a, b] for a, b in zip(y0, y1)], dtype=torch.float64)  # (6, 2, 2)
    m = match_tracks(x, y, 1.0)
    assert m[:, 0].tolist() == [0, 0, -1, 1, 1, -1]
    r = identity_metrics(x, y, 1.0)
    assert r["id_switches"].item() == 1
    assert r["fragmentations"].item() == 1  # t1 -> t2 (lost, picked up later); the loss at t5 is not followed by a match
    assert (r["matches"].item(), r["misses"].item(), r["false_tracks"].item()) == (4, 2, 12 - 4)


def test_clear_mot_keeps_previous_correspondence():
    # two targets close together; track B is nearer to target 0 at step 1, but A still lies within the
    # threshold of target 0, so the step-0 correspondences are kept: no switch
    x = torch.tensor([[[0.0, 0], [2.0, 0]], [[0.0, 0], [2.0, 0]]], dtype=torch.float64)
    y = torch.tensor([[[0.1, 0], [2.1, 0]], [[0.8, 0], [1.3, 0]]], dtype=torch.float64)
    m = match_tracks(x, y, 1.0)
    assert m.tolist() == [[0, 1], [0, 1]]
    assert identity_metrics(x, y, 1.0)["id_switches"].item() == 0
    # beyond the threshold the correspondence breaks and the free pairs are re-assigned: two switches
    y2 = torch.tensor([[[0.1, 0], [2.1, 0]], [[2.2, 0], [0.2, 0]]], dtype=torch.float64)
    assert match_tracks(x, y2, 1.0).tolist() == [[0, 1], [1, 0]]
    assert identity_metrics(x, y2, 1.0)["id_switches"].item() == 2


def test_identity_absent_target_does_not_fragment_and_batches():
    # the target is absent at step 1 (mask): tracked at 0 and 2 -> no fragmentation, no switch
    x = torch.zeros(3, 1, 2, dtype=torch.float64)
    y = torch.tensor([[[0.0, 0.0]], [[50.0, 0.0]], [[0.1, 0.0]]], dtype=torch.float64)
    tm = torch.tensor([[True], [False], [True]])
    r = identity_metrics(x, y, 1.0, truth_mask=tm)
    assert (r["fragmentations"].item(), r["id_switches"].item(), r["misses"].item()) == (0, 0, 0)
    assert r["false_tracks"].item() == 1
    # batch dims first: two copies give the same counts per element
    rb = identity_metrics(x.expand(2, 3, 1, 2), y.expand(2, 3, 1, 2), 1.0, truth_mask=tm.expand(2, 3, 1))
    assert rb["false_tracks"].tolist() == [1, 1]


# ---- against Stone Soup ------------------------------------------------------------------------

#: the comparisons with Stone Soup (a test-only oracle) run where it is installed; the tests above run everywhere
needs_stonesoup = pytest.mark.skipif(importlib.util.find_spec("stonesoup") is None,
                                     reason="Stone Soup (a test-only oracle, pip install stonesoup) is not installed")


def _ss_states(a, when):
    from stonesoup.types.state import State

    return [State(np.asarray(r, dtype=float).reshape(-1, 1), timestamp=when) for r in a]


@needs_stonesoup
@pytest.mark.parametrize("p", [1, 2, 3])
def test_gospa_against_stonesoup(p):
    from stonesoup.metricgenerator.ospametric import GOSPAMetric

    when = datetime.datetime(2020, 1, 1)
    gen = np.random.default_rng(3 + p)
    worst = 0.0
    for trial in range(40):
        n, m = gen.integers(0, 6), gen.integers(0, 6)
        if n + m == 0:
            continue
        x, y = gen.uniform(0, 6, (n, 2)), gen.uniform(0, 6, (m, 2))
        c = 2.0
        ref, _ = GOSPAMetric(c=c, p=p).compute_gospa_metric(_ss_states(y, when), _ss_states(x, when))
        ours = gospa(torch.from_numpy(x).reshape(n, 2), torch.from_numpy(y).reshape(m, 2), c=c, p=p)
        for k_ss, k in (("distance", "gospa"), ("localisation", "gospa_loc"), ("missed", "gospa_missed"),
                        ("false", "gospa_false")):
            worst = max(worst, abs(float(ref.value[k_ss]) - ours[k].item()))
    assert worst < 1e-9


@needs_stonesoup
def test_ospa_against_stonesoup():
    # Stone Soup assigns by the cut distance and then sums its p-th powers; at p = 1 that is the optimum
    from stonesoup.metricgenerator.ospametric import OSPAMetric

    when = datetime.datetime(2020, 1, 1)
    gen = np.random.default_rng(7)
    worst = 0.0
    for trial in range(40):
        n, m = gen.integers(0, 6), gen.integers(0, 6)
        if n + m == 0:
            continue
        x, y = gen.uniform(0, 6, (n, 2)), gen.uniform(0, 6, (m, 2))
        ref = OSPAMetric(c=2.0, p=1).compute_OSPA_distance(_ss_states(y, when), _ss_states(x, when))
        ours = ospa(torch.from_numpy(x).reshape(n, 2), torch.from_numpy(y).reshape(m, 2), c=2.0, p=1)
        worst = max(worst, abs(float(ref.value) - ours["ospa"].item()))
    assert worst < 1e-9


def test_matched_order_charges_the_match_distance_where_the_track_is_absent():
    # one target at the origin over steps 1..2; track 0 0.1 m from it but absent at step 2, track 1 1 m from it:
    # track 0 costs 0.01 + c^2, track 1 costs 1 + 1 (by hand), so the scenario's match distance c decides
    from dslearn.metrics.multitarget import matched_order

    nan = float("nan")
    truth = torch.zeros(1, 3, 1, 2, dtype=torch.float64)
    est = torch.tensor([[[[0.1, 0.0], [1.0, 0.0]], [[0.1, 0.0], [1.0, 0.0]], [[nan, nan], [1.0, 0.0]]]],
                       dtype=torch.float64).unsqueeze(0)  # (N=1, B=1, K+1=3, M=2, 2)
    assert matched_order(est, truth, c=1.0).tolist() == [[[0]]]
    assert matched_order(est, truth, c=2.0).tolist() == [[[1]]]
    assert matched_order(est, truth).tolist() == [[[1]]]  # the default: 2 m


@pytest.mark.parametrize("p", [1.0, 2.0, 3.0])
def test_one_target_one_track_batches_equal_the_general_path(p):
    """Sets of one target and one track (Liu's field) are computed batched; the general path (per set, SciPy's
    assignment: forced here by an all-True mask, or by a second track far away) gives the same numbers (bit for bit
    at the matrix's order p = 2, to rounding elsewhere), near and beyond the cut-off alike."""
    gen = torch.Generator().manual_seed(3)
    x = 2 * torch.randn(6, 5, 1, 2, generator=gen, dtype=torch.float64)
    y = x + 1.5 * torch.randn(6, 5, 1, 2, generator=gen, dtype=torch.float64)
    whole = torch.ones(6, 5, 1, dtype=torch.bool)
    for f in (gospa, ospa):
        fast, ref = f(x, y, 2.0, p), f(x, y, 2.0, p, truth_mask=whole)
        for k in ref:
            if p == 2.0:
                assert torch.equal(fast[k], ref[k]), k
            torch.testing.assert_close(fast[k], ref[k], rtol=1e-15, atol=0)
    g = gospa(x, y, 2.0, p)
    assert bool((g["gospa_missed"] > 0).any()) and bool((g["gospa_loc"] > 0).any())  # both kinds of pair occur
    for b in range(5):  # each column of the 6 x 5 sets as a sequence of 6 steps
        t, e = x[:, b], y[:, b]  # (T, 1, 2)
        fast = match_tracks(t, e, 1.5)
        ref = match_tracks(t, torch.cat([e, torch.full_like(e, 1e6)], 1), 1.5)
        assert torch.equal(fast, ref)
