"""``learner=calibrate``'s likelihood runs each batch element up to its last counted innovation only
(:func:`dslearn.learning.calibrate.individual_nll` drops the elements done with): the sums equal those of the whole
run, element by element, with one noise scale per element (the grid's), for the EKF's and the UKF's steps, a
motion model without and with per-node state (the GP); the fit is the same."""

from __future__ import annotations

import pytest
import torch

from dslearn.episodes import Measurements
from dslearn.filters.ukf import UnscentedPredict
from dslearn.learning import calibrate as C
from dslearn.models.constant_velocity import ConstantVelocity
from dslearn.models.gp import GPMotionModel
from dslearn.models.observation import LinearPositionObservation
from dslearn.types import StepContext

CTX = StepContext(dt=1.0)


def _episodes(s: int, b: int, k: int, a: int, seed: int) -> tuple[Measurements, tuple[torch.Tensor, torch.Tensor]]:
    """Random walks seen by ``s`` sensors, each episode's sensors seeing the targets up to a different step (so the
    last counted innovation differs between batch elements); diffuse-ish initial beliefs."""
    g = torch.Generator().manual_seed(seed)
    pos = torch.cumsum(0.5 * torch.randn(b, k + 1, a, 2, generator=g, dtype=torch.float64), 1)
    meas = pos.unsqueeze(0) + 0.3 * torch.randn(s, b, k + 1, a, 2, generator=g, dtype=torch.float64)
    vis = torch.rand(s, b, k + 1, a, generator=g) < 0.8
    stop = torch.randint(3, k + 1, (s, b), generator=g)  # sensor i stops seeing episode e's targets at stop[i, e]
    vis &= torch.arange(k + 1).view(1, 1, -1, 1) < stop.view(s, b, 1, 1)
    meas = torch.where(vis.unsqueeze(-1), meas, torch.zeros_like(meas))
    dx = 4 * a
    mean = torch.randn(s, b, dx, generator=g, dtype=torch.float64)
    info = torch.diag(torch.tensor([0.25, 0.25, 1.0, 1.0], dtype=torch.float64).repeat(a)).expand(s, b, dx, dx).clone()
    return Measurements(meas, vis), (mean, info)


def _both(model, obs, ep, init, mask, predict, monkeypatch):
    dropped = C.individual_nll(model, obs, ep, init, CTX, mask, predict)
    monkeypatch.setattr(C, "DROP_SHARE", float("inf"))  # never drop: the whole run
    whole = C.individual_nll(model, obs, ep, init, CTX, mask, predict)
    monkeypatch.undo()
    return dropped, whole


@pytest.mark.parametrize("step", ["ekf", "ukf"])
def test_dropping_the_elements_done_with_gives_the_whole_runs_sums(step, monkeypatch):
    s, b, k, a = 2, 6, 20, 2
    ep, init = _episodes(s, b, k, a, seed=3)
    mask = C.counted(ep.visible, 2)
    last = torch.where(mask.any(-1).any(0), torch.arange(k + 1), -1).amax(-1)
    assert len(set(last.tolist())) > 3 and int(last.min()) < k // 2  # elements finish at different steps
    g = 3  # three scale pairs, grid-major as the grid runs them
    qs = torch.tensor([0.2, 1.0, 7.0], dtype=torch.float64).repeat_interleave(b)
    rs = torch.tensor([3.0, 1.0, 0.4], dtype=torch.float64).repeat_interleave(b)
    rep = Measurements(ep.meas.repeat(1, g, 1, 1, 1), ep.visible.repeat(1, g, 1, 1))
    start = (init[0].repeat(1, g, 1), init[1].repeat(1, g, 1, 1))
    predict = UnscentedPredict() if step == "ukf" else None
    model = C.ScaledNoise(ConstantVelocity(a, noise_std=0.3), qs)
    obs = C.ScaledSensor(LinearPositionObservation(0.5), rs)
    dropped, whole = _both(model, obs, rep, start, mask.repeat(1, g, 1, 1), predict, monkeypatch)
    assert torch.isfinite(whole).all() and bool((whole != 0).all())
    torch.testing.assert_close(dropped, whole, rtol=1e-12, atol=0.0)
    # each grid point's sums are its own: the first scale pair alone gives the same
    alone = C.individual_nll(C.ScaledNoise(ConstantVelocity(a, noise_std=0.3), qs[:b]),
                             C.ScaledSensor(LinearPositionObservation(0.5), rs[:b]), ep, init, CTX, mask, predict)
    torch.testing.assert_close(alone, whole[:b], rtol=1e-12, atol=0.0)


def test_a_per_node_model_keeps_its_nodes(monkeypatch):
    """A GP motion model (per-node state: the nodes stay, the episodes are dropped), with data at one node."""
    s, b, k, a = 3, 5, 16, 1
    ep, init = _episodes(s, b, k, a, seed=5)
    gp = GPMotionModel(4 * a, num_nodes=s, mean="identity", capacity=8)
    gen = torch.Generator().manual_seed(1)
    for _ in range(6):
        x = torch.randn(s, 4 * a, generator=gen, dtype=torch.float64)
        gp.add_data(x, x + 0.1, torch.tensor([True, False, False]))
    mask = C.counted(ep.visible, 2)
    qs = torch.tensor([0.5, 2.0], dtype=torch.float64).repeat_interleave(b)
    rs = torch.tensor([1.5, 0.7], dtype=torch.float64).repeat_interleave(b)
    rep = Measurements(ep.meas.repeat(1, 2, 1, 1, 1), ep.visible.repeat(1, 2, 1, 1))
    start = (init[0].repeat(1, 2, 1), init[1].repeat(1, 2, 1, 1))
    model = C.scaled_model(gp, qs)
    obs = C.ScaledSensor(LinearPositionObservation(0.5), rs)
    dropped, whole = _both(model, obs, rep, start, mask.repeat(1, 2, 1, 1), None, monkeypatch)
    assert torch.isfinite(whole).all()
    torch.testing.assert_close(dropped, whole, rtol=1e-12, atol=0.0)


def test_the_fit_is_the_same(monkeypatch):
    s, b, k, a = 3, 4, 18, 1
    ep, init = _episodes(s, b, k, a, seed=8)
    model, obs = ConstantVelocity(a, noise_std=0.3), LinearPositionObservation(0.5)
    fast = C.calibrate(model, obs, ep, init, CTX, points=5, decades=2.0, zooms=2)
    monkeypatch.setattr(C, "DROP_SHARE", float("inf"))
    whole = C.calibrate(model, obs, ep, init, CTX, points=5, decades=2.0, zooms=2)
    assert (fast.q_scale, fast.r_scale, fast.passes) == (whole.q_scale, whole.r_scale, whole.passes)
    assert fast.nll == pytest.approx(whole.nll, rel=1e-12) and fast.nll_hand == pytest.approx(whole.nll_hand, rel=1e-12)


@pytest.mark.parametrize("inputs", ["mean", "belief"])
def test_a_per_node_model_on_the_nodes_with_an_innovation_only(inputs, monkeypatch):
    """The nodes without a counted innovation are not run (:class:`~dslearn.learning.calibrate.NodeSubset`): the
    sums equal those of every node's filter, and the fit is the one every node gives."""
    s, b, k, a = 4, 3, 14, 1
    ep, init = _episodes(s, b, k, a, seed=9)
    ep.visible[2:] = False  # nodes 2 and 3 never see a target
    ep.meas[2:] = 0.0
    gp = GPMotionModel(4 * a, num_nodes=s, mean="identity", capacity=8, inputs=inputs)
    gen = torch.Generator().manual_seed(4)
    for _ in range(6):
        x = torch.randn(s, 4 * a, generator=gen, dtype=torch.float64)
        gp.add_data(x, x + 0.1, torch.tensor([True, False, True, False]))
    mask = C.counted(ep.visible, 2)
    obs = C.ScaledSensor(LinearPositionObservation(0.5), torch.tensor([1.5, 0.7], dtype=torch.float64).repeat_interleave(b))
    qs = torch.tensor([0.5, 2.0], dtype=torch.float64).repeat_interleave(b)
    rep = Measurements(ep.meas.repeat(1, 2, 1, 1, 1), ep.visible.repeat(1, 2, 1, 1))
    start = (init[0].repeat(1, 2, 1), init[1].repeat(1, 2, 1, 1))
    m2 = mask.repeat(1, 2, 1, 1)
    for predict in (None, UnscentedPredict()):
        whole = C.individual_nll(C.scaled_model(gp, qs), obs, rep, start, CTX, m2, predict)
        nodes = torch.tensor([0, 1])
        sub = Measurements(rep.meas[nodes], rep.visible[nodes])
        part = C.individual_nll(C.scaled_model(C.NodeSubset(gp, nodes), qs), obs, sub,
                                (start[0][nodes], start[1][nodes]), CTX, m2[nodes], predict)
        assert torch.isfinite(whole).all() and bool((whole != 0).all())
        torch.testing.assert_close(part, whole, rtol=1e-12, atol=0.0)
    fit = C.calibrate(gp, LinearPositionObservation(0.5), ep, init, CTX, points=5, decades=2.0, zooms=1)
    assert fit.filters == 2 * b  # two nodes' filters per grid point

    def no_subset(ep_, init_, mask_, keep):  # every node run, as before the subset
        b_ = mask_.flatten(2).any(-1).any(0).nonzero().squeeze(-1)
        return ep_.select(b_), (init_[0][:, b_], init_[1][:, b_]), mask_[:, b_], None

    monkeypatch.setattr(C, "_pack", no_subset)
    every = C.calibrate(gp, LinearPositionObservation(0.5), ep, init, CTX, points=5, decades=2.0, zooms=1)
    assert (fit.q_scale, fit.r_scale) == (every.q_scale, every.r_scale) and every.filters == s * b
    assert fit.nll == pytest.approx(every.nll, rel=1e-12)
