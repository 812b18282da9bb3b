"""Targets that enter and leave (issue 35): the scenario's existence intervals, track management by value
(initiation, M-of-N confirmation, deletion), the track-to-track association and the per-cluster consensus on
hand-computed cases, GOSPA / OSPA / identity metrics with births and deaths against a hand computation, the slot's
``tracks`` settings checked, yu_crowd_clutter unchanged by them, and a tiny end-to-end cell on yu_crowd_births."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import torch

from dslearn.association import GNN, TrackManager, TrackManagerSettings
from dslearn.association.multitrack import (KEYS, TrackSettings, clusters, fuse_cluster, predict_tracks,
                                            t2ta_pairs)
from dslearn.errors import ConfigError
from dslearn.fusion.strategies import Centralized
from dslearn.metrics.multitarget import matched_order, tracking_metrics
from dslearn.models.constant_velocity import ConstantVelocity
from dslearn.models.observation import LinearPositionObservation
from dslearn.sim.clutter import check_births, existence_intervals
from dslearn.types import StepContext

D = torch.float64
NAN = math.nan


# ------------------------------------------------------------------------------------------------ the scenario
def test_existence_intervals_by_hand():
    """K = 10, birth_until 0.4 (births at steps 0..4), death_from 0.6 (deaths at 6..11, 11 = stays): u0 = 0 -> 0,
    u0 = 0.99 -> 4, u0 = 0.5 -> 2; u1 = 0 -> 6, u1 = 0.99 -> 11 (stays), u1 = 0.5 -> 9."""
    u = torch.tensor([[[0.0, 0.0], [0.99, 0.99], [0.5, 0.5]]], dtype=D)
    alive = existence_intervals(u, 10, 0.4, 0.6)[0]  # (K+1, A)
    assert alive.shape == (11, 3)
    assert alive[:, 0].nonzero().squeeze(-1).tolist() == list(range(0, 6))
    assert alive[:, 1].nonzero().squeeze(-1).tolist() == list(range(4, 11))
    assert alive[:, 2].nonzero().squeeze(-1).tolist() == list(range(2, 9))
    with pytest.raises(ConfigError, match="scenario.death_from"):
        check_births(True, 0.5, 0.4)
    with pytest.raises(ConfigError, match="scenario.births"):
        check_births("yes", 0.4, 0.6)


def test_births_scenario_truth_and_detections(make_cfg):
    """yu_crowd_births: the spec declares births; a target's true state is NaN exactly outside its existence
    interval and no node detects it there; every target exists at some step."""
    from dslearn.compose import build
    from dslearn.sim.scenario import episode_streams

    cfg = make_cfg("task=matrix", "method=ekf_lin_hybrid_gnn", "scenario=yu_crowd_births")
    sc = build(cfg.scenario, "scenario")
    net = build(cfg.network, "network")
    assert sc.spec.births and not sc.spec.labelled and sc.steps == 24
    ep = sc.sample(6, net, episode_streams(0, "test", 0, 6))
    pos = sc.positions(ep.states)  # (B, K+1, A, 2)
    alive = ~pos.isnan().any(-1)
    assert bool((pos.isnan().all(-1) | alive).all())  # a target's position is all NaN or none
    assert bool(alive.any(1).all()) and not bool(alive.all())
    # each target's presence is one interval of steps, its first at most 0.4 K, its end at least 0.6 K
    for b in range(6):
        for a in range(4):
            steps = alive[b, :, a].nonzero().squeeze(-1)
            assert steps.tolist() == list(range(int(steps[0]), int(steps[-1]) + 1))
            assert int(steps[0]) <= 0.4 * 24 and int(steps[-1]) + 1 >= 0.6 * 24
    # the detections of a target come from the labelled reading; none where it is absent: every present slot at a
    # step where no target exists is clutter, and the count never exceeds targets alive + clutter cap
    assert ep.meas.shape[:3] == (net.num_nodes, 6, 25)


# ------------------------------------------------------------------------------------------------ track management
def _kf(x, p, z, r):
    h = np.zeros((2, 4))
    h[0, 0] = h[1, 1] = 1
    s = h @ p @ h.T + r
    k = p @ h.T @ np.linalg.inv(s)
    return x + k @ (z - h @ x), p - k @ s @ k.T


def test_track_initiation_confirmation_deletion_by_hand():
    """Single-point initiation (velocity std 0.5), 2-of-3 confirmation, deletion after 2 misses, on a hand-made
    sequence of 5 steps (dt = 1, CV with q = 0.1^2 I): exact counts, ids and states."""
    obs = LinearPositionObservation(0.2)
    r = 0.04 * np.eye(2)
    model, ctx = ConstantVelocity(1, 0.1), StepContext(dt=1.0)
    st = TrackManagerSettings(initiation="single_point", confirm_m=2, confirm_n=3, delete_after=2, dt=1.0,
                              velocity_std=0.5)
    tm, gnn = TrackManager(st), GNN(0.9, 1e-3, 0.99)

    def step(z):
        z = torch.tensor(z, dtype=D).reshape(-1, 2)
        if len(tm):
            pm, pc = predict_tracks(tm.mean, tm.cov, model, ctx)
            tm.step(gnn.associate(pm, pc, obs, z), z, obs)
        else:
            tm.step(None, z, obs)

    step([[0.0, 0.0], [5.0, 5.0]])  # two tentative tracks
    assert tm.ids.tolist() == [0, 1] and tm.confirmed.tolist() == [False, False]
    np.testing.assert_allclose(tm.cov[0].diagonal().numpy(), [0.04, 0.04, 0.25, 0.25], rtol=0, atol=1e-15)
    step([[1.0, 0.0]])  # track 0 detected (2 of 2: confirmed), track 1 missed (1 of 2: may still make 2 of 3)
    f = np.eye(4)
    f[0, 2] = f[1, 3] = 1
    x0, p0 = np.zeros(4), np.diag([0.04, 0.04, 0.25, 0.25])
    x1, p1 = _kf(f @ x0, f @ p0 @ f.T + 0.01 * np.eye(4), np.array([1.0, 0.0]), r)
    assert tm.ids.tolist() == [0, 1] and tm.confirmed.tolist() == [True, False] and tm.hits.tolist() == [2, 1]
    np.testing.assert_allclose(tm.mean[0].numpy(), x1, rtol=0, atol=1e-12)
    np.testing.assert_allclose(tm.cov[0].numpy(), p1, rtol=0, atol=1e-12)
    step([[2.0, 0.0], [9.0, 9.0]])  # track 1 missed again (cannot make 2 of 3: deleted); (9, 9) starts track 2
    assert tm.ids.tolist() == [0, 2] and tm.confirmed.tolist() == [True, False]
    step([])  # track 0 missed once; track 2 missed (1 of 2)
    assert tm.ids.tolist() == [0, 2] and tm.missed_run.tolist() == [1, 1]
    step([])  # track 0 missed twice: deleted (delete_after = 2); track 2 hopeless: deleted
    assert len(tm) == 0


def test_two_point_tracks_wait_for_m_of_n_when_m_exceeds_two():
    """confirm_m = 3 of confirm_n = 4: a two-point track starts tentative with its two detections counted."""
    obs = LinearPositionObservation(0.2)
    tm = TrackManager(TrackManagerSettings(initiation="two_point", confirm_m=3, confirm_n=4, max_speed=2.0, dt=1.0))
    tm.step(None, torch.tensor([[0.0, 0.0]], dtype=D), obs)
    tm.step(None, torch.tensor([[1.0, 0.0]], dtype=D), obs)
    assert tm.confirmed.tolist() == [False] and tm.hits.tolist() == [2] and tm.age.tolist() == [2]
    np.testing.assert_allclose(tm.mean[0].numpy(), [1.0, 0.0, 1.0, 0.0])


# ------------------------------------------------------------------------------------------------ T2TA and fusion
def test_t2ta_hand_case_optimal_not_greedy_and_gated():
    """S = P_i + P_j = I: d^2 = |dx|^2. Node a at x = 0 and 1, node b at 0.6 and 2 (and one at 3.9 beyond the 99 %
    gate chi2_4 = 13.28 from both... 3.9^2 = 15.2 from 0): greedy would take (1, 0.6) = 0.16 then (0, 2) = 4 (sum
    4.16); the optimal assignment is (0, 0.6) + (1, 2) = 1.36."""
    half = 0.5 * torch.eye(4, dtype=D).expand(3, 4, 4)

    def tracks(xs):
        return torch.tensor([[x, 0.0, 0.0, 0.0] for x in xs], dtype=D)

    pairs = t2ta_pairs(tracks([0.0, 1.0]), half[:2], tracks([0.6, 2.0]), half[:2], 0.99)
    assert pairs == [(0, 0), (1, 1)]
    # the gate: 3.9^2 = 15.21 > 13.28 (chi2_4 at 0.99) is no pair; 3.6^2 = 12.96 is
    assert t2ta_pairs(tracks([0.0]), half[:1], tracks([3.9]), half[:1], 0.99) == []
    assert t2ta_pairs(tracks([0.0]), half[:1], tracks([3.6]), half[:1], 0.99) == [(0, 0)]
    # clusters over three nodes in a chain: node 0's track 1 ~ node 1's track 0 ~ node 2's track 2
    cl = clusters([2, 1, 3], [(0, 1, [(1, 0)]), (1, 2, [(0, 2)])])
    assert cl == [{0: 1, 1: 0, 2: 2}]


def test_cluster_consensus_centralized_by_hand():
    """consensus=centralized on a cluster of nodes 0 and 2 of 3: each member's fused information is its own
    predicted information plus both members' novel information (the naive node 1 adds none)."""
    p_pred = [torch.eye(4, dtype=D) * v for v in (1.0, 2.0, 4.0)]
    x_pred = [torch.tensor([0.0, 0.0, 1.0, 0.0], dtype=D), None, torch.tensor([0.2, 0.0, 1.0, 0.0], dtype=D)]
    x_post = [torch.tensor([0.1, 0.0, 1.0, 0.0], dtype=D), None, torch.tensor([0.3, 0.1, 1.0, 0.0], dtype=D)]
    p_post = [torch.eye(4, dtype=D) * 0.5, None, torch.eye(4, dtype=D) * 0.8]
    pred = [(x_pred[s].unsqueeze(0), p_pred[s].unsqueeze(0)) if s != 1 else None for s in range(3)]
    post = [(x_post[s].unsqueeze(0), p_post[s].unsqueeze(0)) if s != 1 else None for s in range(3)]
    out = fuse_cluster({0: 0, 2: 0}, 3, pred, post, Centralized(torch.eye(3, dtype=D)))
    assert sorted(out) == [0, 2]
    dO = [torch.linalg.inv(p_post[s]) - torch.linalg.inv(p_pred[s]) for s in (0, 2)]
    dq = [torch.linalg.inv(p_post[s]) @ x_post[s] - torch.linalg.inv(p_pred[s]) @ x_pred[s] for s in (0, 2)]
    for s in (0, 2):
        o = torch.linalg.inv(p_pred[s]) + dO[0] + dO[1]
        q = torch.linalg.inv(p_pred[s]) @ x_pred[s] + dq[0] + dq[1]
        torch.testing.assert_close(out[s][1], torch.linalg.inv(o), rtol=0, atol=1e-12)
        torch.testing.assert_close(out[s][0], torch.linalg.solve(o, q), rtol=0, atol=1e-12)


# ------------------------------------------------------------------------------------------------ metrics
def test_gospa_ospa_identity_with_births_and_deaths_by_hand():
    """c = 2, p = 2. Step 1: target 0 at (0, 0), target 1 not born; tracks (0.5, 0) and (3, 3) (false).
    Step 2: both targets, (0, 0) and (10, 0); one track (0, 1). GOSPA^2: 0.25 + 2 (one false) = 2.25, then
    1 + 2 (one missed) = 3. OSPA^2 (n = 2, m = 1): (0.25 + 4) / 2, then (1 + 4) / 2."""
    truth = torch.tensor([[[0.0, 0.0], [NAN, NAN]], [[0.0, 0.0], [NAN, NAN]], [[0.0, 0.0], [10.0, 0.0]]], dtype=D)
    est = torch.tensor([[[NAN, NAN], [NAN, NAN]], [[0.5, 0.0], [3.0, 3.0]], [[0.0, 1.0], [NAN, NAN]]], dtype=D)
    m = tracking_metrics(est[None, None], truth[None], c=2.0, p=2.0)
    assert m["gospa"].shape == (1, 1)
    assert m["gospa"].item() == pytest.approx((1.5 + math.sqrt(3.0)) / 2, abs=1e-12)
    assert m["gospa_loc"].item() == pytest.approx((0.25 + 1.0) / 2, abs=1e-12)
    assert m["gospa_missed"].item() == pytest.approx((0 + 2.0) / 2, abs=1e-12)
    assert m["gospa_false"].item() == pytest.approx((2.0 + 0) / 2, abs=1e-12)
    assert m["ospa"].item() == pytest.approx((math.sqrt(4.25 / 2) + math.sqrt(2.5)) / 2, abs=1e-12)
    assert (m["id_switches"].item(), m["fragmentations"].item()) == (0.0, 0.0)
    # the matched order: target 0 to track 0 (0.25 + 1); target 1 (present one step, no track 1 then: c^2)
    assert matched_order(est[None, None], truth[None]).tolist() == [[[0, 1]]]


def test_identity_switch_and_fragmentation_with_absent_tracks():
    """One target over 4 steps: track 0, no track (a gap: a fragmentation), track 1 (a switch), track 1."""
    truth = torch.zeros(5, 1, 2, dtype=D)
    est = torch.full((5, 2, 2), NAN, dtype=D)
    est[1, 0] = est[3, 1] = est[4, 1] = torch.tensor([0.1, 0.0], dtype=D)
    m = tracking_metrics(est[None, None], truth[None], c=2.0, p=2.0)
    assert (m["id_switches"].item(), m["fragmentations"].item()) == (1.0, 1.0)
    assert m["gospa_missed"].item() == pytest.approx(2.0 / 4, abs=1e-12)


# ------------------------------------------------------------------------------------------------ the slot
def test_tracks_settings_checked_naming_the_field():
    assert set(KEYS) == {"manage", "initiation", "confirm_m", "confirm_n", "delete_after", "max_speed",
                         "velocity_std", "t2ta_gate_probability", "adopt"}
    with pytest.raises(ConfigError, match=r"associator.tracks.manage.*auto.*on.*off"):
        TrackSettings.of({"manage": "always"})
    with pytest.raises(ConfigError, match=r"associator.tracks.initiation.*two_point.*single_point"):
        TrackSettings.of({"initiation": "m_of_n"})
    with pytest.raises(ConfigError, match=r"associator.tracks.confirm_m=4 must be <= associator.tracks.confirm_n=3"):
        TrackSettings.of({"confirm_m": 4, "confirm_n": 3})
    with pytest.raises(ConfigError, match=r"associator.tracks.delete_after=0 must be an integer >= 1"):
        TrackSettings.of({"delete_after": 0})
    with pytest.raises(ConfigError, match=r"associator.tracks.t2ta_gate_probability"):
        TrackSettings.of({"t2ta_gate_probability": 1.0})
    with pytest.raises(ConfigError, match=r"associator.tracks.confirm: not a track-management setting; allowed: "):
        TrackSettings.of({"confirm": 2})
    s = TrackSettings.of({"velocity_std": 0.5}).manager_settings(0.25, 1.0)
    assert (s.velocity_std, s.max_speed, s.dt) == (0.5, 1.5, 0.25)


def _rows(make_cfg, *lines):
    from dslearn.compose import build_study

    cfg = make_cfg("task=matrix", "task.train_episodes=1", "task.test_episodes=2", *lines)
    df = build_study(cfg).run()
    return df[df["metric"] != "runtime_s"].reset_index(drop=True)


def test_known_start_unchanged_by_the_tracks_settings(make_cfg):
    """yu_crowd_clutter (no births): tracks.manage=auto (the default) and off give the same rows, bit for bit."""
    base = _rows(make_cfg, "method=ekf_lin_hybrid_gnn", "scenario=yu_crowd_clutter")
    off = _rows(make_cfg, "method=ekf_lin_hybrid_gnn", "scenario=yu_crowd_clutter", "associator.tracks.manage=off",
                "associator.tracks.confirm_m=3", "associator.tracks.confirm_n=5")
    pd.testing.assert_frame_equal(base, off, check_exact=True)


@pytest.mark.parametrize("method", ["ekf_lin_hybrid_gnn", "ekf_lin_hybrid_jpda"])
def test_births_cell_end_to_end(make_cfg, method):
    """A tiny cell on yu_crowd_births: GOSPA's parts add up to its square at every step (so their means do not, in
    general: checked on the parts' bounds), OSPA within c, identity counts whole; the missed part is not zero (targets
    are born and must be confirmed first)."""
    df = _rows(make_cfg, f"method={method}", "scenario=yu_crowd_births")
    wide = df.pivot_table(index=["node", "episode"], columns="metric", values="value", dropna=False)
    for m in ("gospa", "gospa_loc", "gospa_missed", "gospa_false", "ospa", "id_switches", "fragmentations"):
        assert bool(wide[m].map(math.isfinite).all()), m
    # the matched track's errors over the steps where target and track both exist (a sensor holds tracks)
    sensing = wide.loc[[n for n in wide.index.get_level_values(0).unique() if n.startswith("sensor")]]
    for m in ("rmse", "pos_err", "nees_pos"):
        assert bool(sensing[m].map(math.isfinite).all()) and (sensing[m] > 0).all(), m
    assert (sensing["pos_err"] <= sensing["rmse"] + 1e-12).all()  # the mean of |e| is at most its root mean square
    assert len(wide) == 10 * 2 and (wide["ospa"] <= 2.0 + 1e-12).all() and (wide["gospa"] <= 2.0 * 2).all()
    assert (wide["gospa_missed"] > 0).any() and (wide["id_switches"] % 1 == 0).all()
    sensors = wide.loc[[n for n in wide.index.get_level_values(0).unique() if n.startswith("sensor")]]
    assert (sensors["gospa_loc"] > 0).all()  # every sensor confirmed and kept tracks


def test_managed_tracks_refusals(make_cfg, tmp_path):
    """A learning method on births is n/a with the reason; a key the slot does not know is refused naming the
    allowed ones; associator=labels refuses tracks."""
    from dslearn.app.precheck import precheck
    from dslearn.schemas.matrix import misfit

    why = misfit(make_cfg("task=matrix", "method=ekf_gp_hybrid_gnn", "scenario=yu_crowd_births"))
    assert "scenario yu_crowd_births reports unlabelled detections of targets that enter and leave" in why
    assert "learner=none" in why
    err = precheck(["task=matrix", "method=ekf_lin_hybrid_gnn", "scenario=yu_crowd_births",
                    "+associator.tracks.bogus=1",
                    f"hydra.run.dir={tmp_path / 'run'}"])
    assert err is not None and "associator.tracks.bogus" in err and "allowed: manage" in err
    err = precheck(["task=matrix", "method=ekf_lin_hybrid", "scenario=yu_two_agents", "+associator.tracks.confirm_m=2",
                    f"hydra.run.dir={tmp_path / 'run'}"])
    assert err is not None and "associator.tracks" in err


def test_network_tracks_adoption_by_hand():
    """Two linked nodes; node 0 detects one target moving at 1 m/s along x at every step, node 1 detects nothing.
    Two-point initiation (2 of 3): node 0's track is confirmed at step 1 and established (3 steps old) at step 2,
    when node 1 takes an exact copy of it; from then on each node holds exactly one track, node 1's a slot of its
    own; without adoption node 1 holds none."""
    from dslearn.association.multitrack import NetworkTracks
    from dslearn.fusion.strategies import Individual

    k1 = 6
    meas = torch.zeros(2, 1, k1, 1, 2, dtype=D)
    meas[0, 0, :, 0, 0] = torch.arange(k1, dtype=D)
    present = torch.zeros(2, 1, k1, 1, dtype=torch.bool)
    present[0] = True
    obs, model, ctx = LinearPositionObservation(0.2), ConstantVelocity(1, 0.1), StepContext(dt=1.0)
    settings = TrackManagerSettings(initiation="two_point", confirm_m=2, confirm_n=3, delete_after=3, max_speed=2.0,
                                    dt=1.0)
    adj = torch.tensor([[False, True], [True, False]])
    fusion = Individual(torch.eye(2, dtype=D))
    for adopt in (True, False):
        nt = NetworkTracks(GNN(0.9, 1e-3, 0.99), settings, 0.99, adopt)
        pos, cov = nt.run(meas, present, adj, model, obs, fusion, ctx)
        held = (~pos.isnan().any(-1)).sum(-1)[:, 0]  # (S, K+1): confirmed tracks per node and step
        assert held[0].tolist() == [0, 1, 1, 1, 1, 1]
        if adopt:
            assert pos.shape[3] == 1 and held[1].tolist() == [0, 0, 1, 1, 1, 1]
            torch.testing.assert_close(pos[1, 0, 2], pos[0, 0, 2], rtol=0, atol=0)
            torch.testing.assert_close(cov[1, 0, 2], cov[0, 0, 2], rtol=0, atol=0)
            np.testing.assert_allclose(pos[0, 0, 1, 0].numpy(), [1.0, 0.0])  # two-point: the second detection
        else:
            assert held[1].tolist() == [0] * k1


def test_matched_position_metrics_by_hand_and_as_the_labelled_ones_without_absences():
    """Births: target 1 absent at step 1 and its matched track absent at step 2: only the present pairs count.
    Without absences: exactly position_metrics of the matched tracks."""
    from dslearn.episodes import Estimates
    from dslearn.metrics.multitarget import matched_position_metrics
    from dslearn.metrics.positions import position_metrics

    truth = torch.tensor([[[0.0, 0.0], [0.0, 0.0]], [[0.0, 0.0], [NAN, NAN]], [[0.0, 0.0], [10.0, 0.0]],
                          [[0.0, 0.0], [10.0, 0.0]]], dtype=D)[None]  # (1, K+1 = 4, 2, 2)
    est = torch.tensor([[[9.0, 9.0], [9.0, 9.0]], [[0.3, 0.4], [NAN, NAN]], [[0.0, 1.0], [NAN, NAN]],
                        [[0.0, 2.0], [10.0, 0.5]]], dtype=D)[None, None]  # (1, 1, 4, 2, 2)
    cov = torch.eye(2, dtype=D).expand(1, 1, 4, 2, 2, 2) * 0.25
    m = matched_position_metrics(est, cov, truth)
    # pairs: step 1 (0.5), step 2 (1.0), step 3 (2.0, 0.5)
    assert m["rmse"].item() == pytest.approx(math.sqrt((0.25 + 1 + 4 + 0.25) / 4), abs=1e-12)
    assert m["pos_err"].item() == pytest.approx((0.5 + 1 + 2 + 0.5) / 4, abs=1e-12)
    assert m["nees_pos"].item() == pytest.approx((0.25 / 0.25 / 2 + 1 / 0.25 / 2 + (4 + 0.25) / 0.25 / 4) / 3,
                                                 abs=1e-12)
    full = torch.randn(3, 2, 5, 4, 2, dtype=D, generator=torch.Generator().manual_seed(0))
    tr = torch.randn(2, 5, 3, 2, dtype=D, generator=torch.Generator().manual_seed(1))
    cv = torch.eye(2, dtype=D).expand(3, 2, 5, 4, 2, 2) * 0.3
    from dslearn.studies.matrix import matched_estimates

    ref = position_metrics(matched_estimates(Estimates(full, cv, ["a", "b", "c"], torch.ones(3, dtype=torch.bool)),
                                             tr), tr)
    got = matched_position_metrics(full, cv, tr)
    for k in ("rmse", "pos_err", "nees_pos"):
        torch.testing.assert_close(got[k], ref[k], rtol=1e-12, atol=1e-12)
