"""Unlabelled detections on a sensor network (issue 35): the clutter scenario's statistics, the associator slot of
the distributed filter (labels bit-identical to today's cells, GNN exactly the labelled update where the
association is unambiguous), the validation of the scenario and of the slot, and a tiny end-to-end cell per preset
with its multi-target metrics."""

from __future__ import annotations

import math

import pandas as pd
import pytest
import torch

from dslearn.association.gnn import GNN
from dslearn.association.network import GNNAssociator, JPDAAssociator, NodeAssociation
from dslearn.episodes import Measurements
from dslearn.errors import ConfigError
from dslearn.filters.distributed import associated_belief, initial_belief, track
from dslearn.fusion.strategies import HybridConsensus
from dslearn.models.constant_velocity import ConstantVelocity
from dslearn.models.observation import LinearPositionObservation
from dslearn.sim.clutter import ClutterScenario, clutter_cap, detections
from dslearn.sim.placement import make_network
from dslearn.sim.scenario import SocialForceScenario, episode_streams

F64 = torch.float64


def _network(sensing_range=4.0):
    return make_network(num_sensors=4, num_comm=6, area=[0.0, 8.0, 0.0, 8.0], seed=0, comm_radius=4.0,
                        sensing_range=sensing_range, meas_std=0.2)


# ------------------------------------------------------------------------------------------------ the detections
def test_detection_and_clutter_statistics():
    """Over many draws: the clutter count per sensing node and step has mean ``clutter_rate`` (Poisson: std
    sqrt(rate / n)), a target in range is detected with frequency ``p_detect`` (binomial std), every clutter
    detection lies in its sensor's disc, communication-only nodes report nothing; 5 standard deviations."""
    net = _network()
    a, s, b, k1 = 3, net.num_nodes, 400, 6
    gen = torch.Generator().manual_seed(1)
    pos = 8 * torch.rand(b, k1, a, 2, generator=gen, dtype=F64)
    vis = net.visible(pos)  # (S, B, K+1, A)
    meas = pos.unsqueeze(0).expand(s, -1, -1, -1, -1) * vis.unsqueeze(-1)
    rate, p_d = 1.7, 0.8
    vals, present = detections(meas, vis, net, p_d, rate, episode_streams(0, "test", 0, b))
    assert vals.shape == (s, b, k1, a + clutter_cap(rate), 2) and present.shape == vals.shape[:-1]
    # a detection of a target is exactly its reading: which slots hold one (the readings are distinct points)
    is_target = (vals.unsqueeze(-2) == meas.unsqueeze(-3)).all(-1).any(-1) & present  # (S, B, K+1, M)
    sensors = net.num_sensors
    n_clutter = (present & ~is_target)[:sensors].sum(-1).to(F64)  # (4, B, K+1)
    n = n_clutter.numel()
    assert abs(n_clutter.mean().item() - rate) < 5 * math.sqrt(rate / n)
    assert abs(n_clutter.var().item() - rate) < 0.15 * rate  # Poisson: variance = mean
    n_vis = int(vis[:sensors].sum())
    freq = is_target[:sensors].sum().item() / n_vis
    assert abs(freq - p_d) < 5 * math.sqrt(p_d * (1 - p_d) / n_vis)
    assert not present[sensors:].any()
    centre = net.positions[:sensors].view(sensors, 1, 1, 1, 2).to(F64)
    d = (vals[:sensors] - centre).norm(dim=-1)
    assert bool((d[present[:sensors] & ~is_target[:sensors]] <= net.sensing_range + 1e-12).all())
    assert bool((vals[~present] == 0).all())


def test_detections_of_an_episode_do_not_depend_on_the_others():
    """One stream per episode: episode 0's detection set is the same drawn alone or with others."""
    sc = ClutterScenario(desired_velocities=[[1.0, -1.0], [-1.0, -1.0]], start_corners=[[1.5, 5.0], [5.0, 5.0]],
                         p_detect=0.7, clutter_rate=2.0)
    net = _network()
    one = sc.sample(1, net, episode_streams(3, "test", 0, 1))
    three = sc.sample(3, net, episode_streams(3, "test", 0, 3))
    assert torch.equal(one.meas[:, 0], three.meas[:, 0]) and torch.equal(one.visible[:, 0], three.visible[:, 0])
    assert not sc.spec.labelled and sc.spec.num_agents == 2


@pytest.mark.parametrize("field,kwargs", [("scenario.clutter_rate", dict(clutter_rate=-0.5)),
                                          ("scenario.p_detect", dict(p_detect=0.0)),
                                          ("scenario.p_detect", dict(p_detect=1.5)),
                                          ("scenario.start_velocity_std", dict(start_velocity_std=0.0))])
def test_scenario_validation_names_the_field(field, kwargs):
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        ClutterScenario(**kwargs)


@pytest.mark.parametrize("cls,kwargs,field", [
    (GNNAssociator, dict(gate_probability=0.0), "associator.gate_probability"),
    (GNNAssociator, dict(detection_probability=1.2), "associator.detection_probability"),
    (GNNAssociator, dict(clutter_density=-1.0), "associator.clutter_density"),
    (GNNAssociator, dict(cost="nearest"), "associator.cost"),
    (JPDAAssociator, dict(detection_probability=1.0), "associator.detection_probability"),
    (JPDAAssociator, dict(marginals="loopy"), "associator.marginals"),
    (JPDAAssociator, dict(info_update="exact"), "associator.info_update"),
])
def test_associator_validation_names_the_field(cls, kwargs, field):
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        cls(**kwargs)


# ------------------------------------------------------------------------------------------------ the filter hook
def _separated(num: int = 3):
    """Two walkers far apart (parallel paths 4 m apart), labelled readings, the filter's parts."""
    sc = SocialForceScenario(desired_velocities=[[1.0, 0.0], [1.0, 0.0]], start_corners=[[0.5, 1.5], [0.5, 5.5]],
                             start_size=0.5)
    net = _network(sensing_range=6.0)
    ep = sc.sample(num, net, episode_streams(0, "test", 0, num)).measurements
    model = ConstantVelocity(2, noise_std=0.1)
    return sc, net, ep, model, LinearPositionObservation(0.2), HybridConsensus.for_network(adjacency=net.adjacency)


def _shuffled(ep: Measurements, seed: int = 0) -> Measurements:
    """The same readings as sets: each node's slots in a random order at every step (no slot tells a target)."""
    g = torch.Generator().manual_seed(seed)
    order = torch.rand(ep.visible.shape, generator=g).argsort(-1)
    meas = ep.meas.gather(-2, order.unsqueeze(-1).expand_as(ep.meas))
    return Measurements(meas, ep.visible.gather(-1, order))


def test_gnn_on_unambiguous_detections_is_exactly_the_labelled_update():
    """Clutter-free, every target in range detected, targets 4 m apart: GNN at every node assigns each detection to
    its own target's track, so the beliefs are those of the labelled update, bit for bit."""
    sc, net, ep, model, obs, fusion = _separated()
    ctx = sc.ctx()
    init = initial_belief(ep, net, ctx.dt, fusion, sc.area)
    want = track(ep, net, model, obs, fusion, ctx, init)
    hook = NodeAssociation(GNN(detection_probability=1.0, clutter_density=1e-6, gate_probability=0.999), 2)
    got = track(_shuffled(ep), net, model, obs, fusion, ctx, init, associate=hook)
    assert torch.equal(got.mean, want.mean) and torch.equal(got.info, want.info)
    # the same with the first belief from the declared start, associated and fused (both paths share it here)
    start = (torch.tensor([[0.75, 1.75, 1.0, 0.0], [0.75, 5.75, 1.0, 0.0]], dtype=F64),
             torch.diag_embed(torch.tensor([0.1, 0.1, 1.0, 1.0], dtype=F64)).expand(2, 4, 4))
    b0 = associated_belief(_shuffled(ep, 1), fusion, start, hook, obs)
    a = track(ep, net, model, obs, fusion, ctx, b0)
    b = track(_shuffled(ep, 2), net, model, obs, fusion, ctx, b0, associate=hook)
    assert torch.equal(a.mean, b.mean) and torch.equal(a.info, b.info)


def test_jpda_on_unambiguous_detections_is_close_to_the_labelled_update():
    """JPDA weighs the one gated detection with beta close to 1 (P_D near 1, sparse clutter): the positions are near
    the labelled ones."""
    sc, net, ep, model, obs, fusion = _separated()
    ctx = sc.ctx()
    init = initial_belief(ep, net, ctx.dt, fusion, sc.area)
    want = track(ep, net, model, obs, fusion, ctx, init)
    from dslearn.association.jpda import JPDA

    hook = NodeAssociation(JPDA(detection_probability=0.999, clutter_density=1e-6, gate_probability=0.999), 2)
    got = track(_shuffled(ep), net, model, obs, fusion, ctx, init, associate=hook)
    pos = torch.tensor([0, 1, 4, 5])  # both targets' positions
    assert (got.mean[..., pos] - want.mean[..., pos]).abs().max() < 0.05  # within 5 cm (readings of sigma 20 cm)
    assert torch.equal(got.info, got.info.transpose(-1, -2)) and bool(torch.isfinite(got.info).all())


# ------------------------------------------------------------------------------------------------ the slot, the matrix
def _rows(make_cfg, *lines):
    from dslearn.compose import build_study

    cfg = make_cfg("task=matrix", "task.train_episodes=1", "task.test_episodes=2", *lines)
    df = build_study(cfg).run()
    return df[df["metric"] != "runtime_s"].reset_index(drop=True)


@pytest.mark.parametrize("method", ["ekf_lin_hybrid", "ekf_gp_hybrid"])
def test_labels_associator_keeps_every_labelled_cell_bit_identical(make_cfg, method):
    """associator=labels set explicitly or left at its default: the same rows, bit for bit, the same label."""
    base = _rows(make_cfg, f"method={method}", "scenario=yu_two_agents")
    explicit = _rows(make_cfg, f"method={method}", "scenario=yu_two_agents", "associator=labels")
    pd.testing.assert_frame_equal(base, explicit, check_exact=True)
    assert "gnn" not in str(base["method"].iloc[0])


@pytest.mark.parametrize("method", ["ekf_lin_hybrid_gnn", "ekf_lin_hybrid_jpda", "ekf_gp_hybrid_gnn", "ekf_gp_hybrid_jpda",
                                    "ekf_lstm_hybrid_gnn", "ekf_lstm_hybrid_jpda"])
def test_every_association_preset_runs_on_unlabelled_detections(make_cfg, method):
    """A tiny cell per preset: finite RMSE of the matched tracks, GOSPA with its parts adding up, OSPA, identity
    switches, for every node and test episode."""
    more = ["task.train_episodes=2", "model.epochs=3"] if "lstm" in method else []  # early stopping holds one out
    df = _rows(make_cfg, f"method={method}", "scenario=yu_crowd_clutter", *more)
    wide = df.pivot_table(index=["node", "episode"], columns="metric", values="value")
    for m in ("rmse", "gospa", "gospa_loc", "gospa_missed", "gospa_false", "ospa", "id_switches", "fragmentations"):
        assert m in wide and bool(wide[m].map(math.isfinite).all()), m
    assert len(wide) == 10 * 2 and (wide["gospa"] >= 0).all() and (wide["ospa"] <= 2.0 + 1e-12).all()
    assert str(df["method"].iloc[0]).endswith(method.rsplit("_", 1)[1])


def test_refusals_name_the_associator(make_cfg, tmp_path):
    """labels on unlabelled detections, an associator on a labelled scenario, an engine without an associator on
    unlabelled detections: refused before any work with the reason; a key the chosen associator does not read is
    refused at composition, naming it."""
    from dslearn.app.precheck import precheck
    from dslearn.schemas.matrix import misfit

    why = misfit(make_cfg("task=matrix", "method=ekf_lin_hybrid", "scenario=yu_crowd_clutter"))
    assert "associator=labels needs every measurement labelled" in why and "associator=gnn" in why
    why = misfit(make_cfg("task=matrix", "method=ekf_lin_hybrid_gnn", "scenario=yu_two_agents"))
    assert "associator=gnn associates unlabelled detections" in why
    why = misfit(make_cfg("task=matrix", "method=dgpt_rbcm", "scenario=yu_crowd_clutter"))
    assert "labelled with its target" in why and "unlabelled detections" in why
    err = precheck(["task=matrix", "method=ekf_lin_hybrid_jpda", "scenario=yu_crowd_clutter", "+associator.cost=likelihood",
                    f"hydra.run.dir={tmp_path / 'run'}"])
    assert err is not None and "associator.cost" in err and "JPDA does not read it" in err
    err = precheck(["task=yu", "associator=gnn", f"hydra.run.dir={tmp_path / 'run'}"])
    assert err is not None and "root group associator" in err
    err = precheck(["task=matrix", "method=ekf_lin_hybrid_gnn", "scenario=yu_crowd_clutter", "scenario.clutter_rate=-1",
                    f"hydra.run.dir={tmp_path / 'run'}"])
    assert err is not None and "scenario.clutter_rate" in err


def test_jpda_pda_information_update_is_the_pda_update_at_one_node():
    """info_update=pda: one node's information update with the pseudo-measurement equals the moment-form PDA update of
    :class:`JPDA` (spread of the innovations included; that one is checked against Stone Soup), for two tracks
    sharing detections (block-diagonal prior); the default (Sandell and Olfati-Saber) is another update (its gain is
    that of R / (1 - beta0))."""
    from dslearn.association.jpda import JPDA
    from dslearn.filters.information import novel_information

    gen = torch.Generator().manual_seed(0)
    means = torch.tensor([[0.0, 0.0, 1.0, 0.5], [0.8, 0.3, -0.5, 0.2]], dtype=F64)
    covs = []
    for _ in range(2):
        a = torch.randn(4, 4, generator=gen, dtype=F64) * 0.4
        covs.append(a @ a.T + 0.1 * torch.eye(4, dtype=F64))
    covs = torch.stack(covs)
    det = torch.tensor([[0.1, -0.1], [0.6, 0.4], [0.3, 0.1], [5.0, 5.0]], dtype=F64)
    obs = LinearPositionObservation(0.3)
    jp = JPDA(detection_probability=0.8, clutter_density=0.05, gate_probability=0.99)
    ref = jp.associate(means, covs, obs, det)
    y = means.reshape(1, 1, 8)
    omega = torch.block_diag(*torch.linalg.inv(covs)).reshape(1, 1, 8, 8)
    present = torch.ones(1, 1, 4, dtype=torch.bool)
    out = {}
    for mode in ("pda", "sandell"):
        hook = NodeAssociation(jp, 2, info_update=mode)
        meas, vis, lin = hook(y, omega, det.reshape(1, 1, 4, 2), present, obs)
        dq, do = novel_information(y, meas, vis, obs, omega_pred=omega, linearized=lin)
        o_new = omega + do
        mean = torch.linalg.solve(o_new, (omega @ y.unsqueeze(-1)).squeeze(-1).unsqueeze(-1) + dq.unsqueeze(-1))
        out[mode] = mean.reshape(2, 4), torch.linalg.inv(o_new[0, 0])
    assert ref.gated[0, :3].all() and ref.gated[1, :3].all()  # a shared cluster
    for i in range(2):
        torch.testing.assert_close(out["pda"][0][i], ref.mean[i], rtol=0, atol=1e-10)
        torch.testing.assert_close(out["pda"][1][4 * i:4 * i + 4, 4 * i:4 * i + 4], ref.cov[i], rtol=0, atol=1e-10)
    assert (out["sandell"][0] - ref.mean).abs().max() > 1e-4 and (out["sandell"][1][:4, :4] - ref.cov[0]).abs().max() > 1e-4


@pytest.mark.parametrize("kind", ["gnn", "jpda"])
def test_one_track_per_node_closed_forms_equal_the_per_node_functions(kind):
    """A node with one track (Liu's field) takes the closed forms, batched over nodes and episodes: the same
    pseudo-measurements as the general path, run here with a second track far away (its own cluster, gating
    nothing), which calls :func:`assignment` / :func:`marginals` per node; nodes with no detection, with detections
    outside the gate and with several gated ones are all in the batch."""
    from dslearn.association.jpda import JPDA

    gen = torch.Generator().manual_seed(4)
    s, b, m = 6, 3, 5
    mean = torch.randn(s, b, 4, generator=gen, dtype=F64)
    a = torch.randn(s, b, 4, 4, generator=gen, dtype=F64) * 0.3
    cov = a @ a.transpose(-1, -2) + 0.05 * torch.eye(4, dtype=F64)
    det = mean[..., None, :2] + 0.6 * torch.randn(s, b, m, 2, generator=gen, dtype=F64)
    det[0, 0] += 50.0  # every detection of this node and episode outside the gate
    present = torch.rand(s, b, m, generator=gen) < 0.7
    present[1] = False  # a node without detections
    obs = LinearPositionObservation(0.3)
    assoc = {"gnn": GNN(0.8, 0.5, 0.99), "jpda": JPDA(0.8, 0.5, 0.99)}[kind]  # clutter dense enough that a miss can win
    one = NodeAssociation(assoc, 1)(mean, torch.linalg.inv(cov), det, present, obs)
    far = torch.cat([mean, torch.full_like(mean, 1e4)], -1)  # track 2 at 10 km: gates nothing
    om = torch.zeros(s, b, 8, 8, dtype=F64)
    om[..., :4, :4], om[..., 4:, 4:] = torch.linalg.inv(cov), torch.eye(4, dtype=F64)
    two = NodeAssociation(assoc, 2)(far, om, det, present, obs)
    torch.testing.assert_close(one[0], two[0][:, :, :1], rtol=0, atol=1e-12)
    assert torch.equal(one[1], two[1][:, :, :1]) and not two[1][:, :, 1].any()
    torch.testing.assert_close(one[2][2], two[2][2][:, :, :1], rtol=1e-12, atol=0)  # R (over 1 - beta0 for JPDA)
    assert 0 < int(one[1].sum()) < s * b and not one[1][0, 0] and not one[1][1].any()
