"""Faults in the network (dslearn/sim/faults.py: the data; dslearn/fusion/faults.py: the links), gating, and
the yu_faults study end to end."""

import math

import pandas as pd
import pytest
import torch
from omegaconf import OmegaConf

from dslearn.fusion.strategies import make_fusion, mix
from dslearn.fusion.weights import metropolis, uniform
from dslearn.fusion.faults import FaultyFusion, draw_live_graph, live_weights
from dslearn.diagnostics import Diagnostics
from dslearn.filters.information import chi2_quantile, novel_information
from dslearn.models import LinearPositionObservation
from dslearn.episodes import Episodes
from dslearn.sim.faults import add_outliers, apply_node_failures, node_failure_schedule
from dslearn.sim.placement import make_network


@pytest.fixture
def net():
    return make_network(num_sensors=4, num_comm=6, seed=0)


def test_live_weights_match_static_and_are_stochastic(net):
    adj = net.adjacency
    b = 5
    full = adj.unsqueeze(0).expand(b, -1, -1)
    torch.testing.assert_close(live_weights(full, "metropolis")[2], metropolis(adj), rtol=0, atol=1e-15)
    torch.testing.assert_close(live_weights(full, "uniform")[4], uniform(adj), rtol=0, atol=1e-15)
    gen = torch.Generator().manual_seed(1)
    alive = torch.rand(b, adj.shape[0], generator=gen) > 0.3
    live = draw_live_graph(adj, alive, 0.4, gen)
    assert torch.equal(live, live.transpose(-1, -2))
    assert not (live & ~adj).any()  # only nominal links
    assert not live[~alive].any()  # a failed node has no live link
    w = live_weights(live, "metropolis")
    ones = torch.ones(b, adj.shape[0], dtype=torch.float64)
    torch.testing.assert_close(w.sum(-1), ones)
    torch.testing.assert_close(w.sum(-2), ones)  # doubly stochastic on every live graph
    assert (w >= 0).all()
    iso = live.sum(-1) == 0
    assert torch.allclose(w.diagonal(dim1=-2, dim2=-1)[iso], torch.ones(int(iso.sum()), dtype=torch.float64))


def test_link_failure_rate(net):
    gen = torch.Generator().manual_seed(0)
    alive = torch.ones(2000, net.num_nodes, dtype=torch.bool)
    live = draw_live_graph(net.adjacency, alive, 0.3, gen)
    frac = live.sum().item() / (net.adjacency.sum().item() * 2000)
    assert abs(frac - 0.7) < 0.01
    assert torch.equal(draw_live_graph(net.adjacency, alive[:3], 0.0, gen), net.adjacency.expand(3, -1, -1))
    assert not draw_live_graph(net.adjacency, alive[:3], 1.0, gen).any()


def test_batched_mix_equals_loop():
    gen = torch.Generator().manual_seed(3)
    w = torch.rand(4, 6, 6, generator=gen, dtype=torch.float64)
    y = torch.randn(6, 4, 8, 8, generator=gen, dtype=torch.float64)
    ref = torch.stack([mix(w[b], y[:, b]) for b in range(4)], 1)
    torch.testing.assert_close(mix(w, y), ref, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("name", ["hybrid", "cm", "ci", "ce", "individual", "centralized"])
def test_faultless_faulty_fusion_equals_base(net, name):
    """p = 0, every node alive: the wrapper reproduces the static fusion (Metropolis weights)."""
    s, b, dx = net.num_nodes, 3, 8
    gen = torch.Generator().manual_seed(5)
    a = torch.randn(s, b, dx, dx, generator=gen, dtype=torch.float64)
    o = a @ a.transpose(-1, -2) + dx * torch.eye(dx, dtype=torch.float64)
    q = torch.randn(s, b, dx, generator=gen, dtype=torch.float64)
    dq, do = 0.1 * q, 0.1 * o
    base = make_fusion(name, metropolis(net.adjacency), 3, "one")
    ff = FaultyFusion(make_fusion(name, uniform(net.adjacency), 3, "one"), net.adjacency, 0.0, "metropolis")
    ff.begin(None, batch=b)
    for x, y in zip(base(q, o, dq, do), ff(q, o, dq, do)):
        torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-12)
    assert ff.name == name and ff.iterations == 3


def test_node_failure_schedule_and_masking():
    gen = torch.Generator().manual_seed(0)
    s, b, k = 10, 50, 12
    alive = node_failure_schedule(s, b, k, 0.2, gen, "permanent")
    assert alive.shape == (s, b, k + 1) and alive[:, :, 0].all()
    assert ((~alive).any(-1).sum(0) == 2).all()  # round(0.2 * 10) nodes fail in every episode
    down = (~alive).to(torch.int8)
    assert (down[..., 1:] >= down[..., :-1]).all()  # permanent: once down, down for good
    tr = node_failure_schedule(s, b, k, 0.4, gen, "transient", duration=3)
    assert ((~tr).sum(-1) <= 3).all() and ((~tr).any(-1).sum(0) == 4).all()
    ep = Episodes(torch.zeros(b, k + 1, 8), torch.ones(s, b, k + 1, 2, 2), torch.ones(s, b, k + 1, 2, dtype=torch.bool))
    ep2 = apply_node_failures(ep, alive)
    assert torch.equal(ep2.visible, alive.unsqueeze(-1).expand_as(ep.visible))
    assert (ep2.meas[~ep2.visible] == 0).all()
    assert torch.equal(node_failure_schedule(s, b, k, 0.0, gen), torch.ones(s, b, k + 1, dtype=torch.bool))


def test_outliers_and_chi2_gate():
    assert math.isclose(chi2_quantile(0.99, 2), 9.210340371976184, rel_tol=1e-12)
    gen = torch.Generator().manual_seed(0)
    s, b, k, a = 4, 200, 5, 2
    ep = Episodes(torch.zeros(b, k + 1, 8), torch.zeros(s, b, k + 1, a, 2, dtype=torch.float64),
                  torch.ones(s, b, k + 1, a, dtype=torch.bool))
    ep2, hit = add_outliers(ep, 0.1, 3.0, gen)
    assert abs(hit.float().mean().item() - 0.1) < 0.01
    assert torch.equal(ep2.meas[~hit], ep.meas[~hit])
    # gating: prior at the truth, a gross error is rejected, a good measurement kept
    obs = LinearPositionObservation(0.2)
    y = torch.zeros(1, 1, 8, dtype=torch.float64)
    omega = torch.eye(8, dtype=torch.float64).expand(1, 1, 8, 8) * 100.0
    meas = torch.tensor([[[[0.1, -0.1], [5.0, 5.0]]]], dtype=torch.float64)
    vis = torch.ones(1, 1, 2, dtype=torch.bool)
    dq0, do0 = novel_information(y, meas, vis, obs)
    with Diagnostics() as outer, Diagnostics() as d:  # the open contexts receive the gate's counts
        dq1, do1 = novel_information(y, meas, vis, obs, gate_prob=0.99, omega_pred=omega)
    assert d.gate_rejected == 1 and d.gate_tested == 2
    assert (outer.gate_rejected, outer.gate_tested) == (1, 2)
    torch.testing.assert_close(do1[..., :4, :4], do0[..., :4, :4])  # target 1 kept
    assert (do1[..., 4:, 4:] == 0).all()  # target 2's gross error dropped
    dq2, do2 = novel_information(y, meas, vis, obs, gate_prob=None, omega_pred=omega)
    assert torch.equal(dq2, dq0) and torch.equal(do2, do0)  # no gate = the paper's update


def _tiny_cfg(**task):
    from pathlib import Path

    conf = Path(__file__).resolve().parents[1] / "conf"
    base = OmegaConf.load(conf / "config.yaml")
    for g, name in (("scenario", "yu_two_agents"), ("network", "yu"), ("observation", "linear"), ("consensus", "hybrid"),
                    ("filter", "default"), ("task", "yu_faults")):
        base[g] = OmegaConf.load(conf / g / f"{name}.yaml")
    base.pop("defaults")
    base.pop("hydra")
    base.study = "yu_faults"
    base.progress = False
    base.task = OmegaConf.merge(base.task, task)
    return base


def test_yu_faults_acceptance_point_bounded():
    """30 % link failures + 20 % failed nodes: hybrid stays bounded, nothing is NaN."""
    from dslearn.studies import yu_faults

    cfg = _tiny_cfg(models=["lin", "gp_increment"], fusions=["hybrid", "individual"], train_episodes=2, test_episodes=4,
                    link_fail=[0.0], node_fail=[0.0], joint=[[0.3, 0.2]], outlier_settings=False)
    df = yu_faults.run(cfg)
    assert {"model", "consensus", "node", "episode", "metric", "value"} <= set(df.columns)
    te = df[df.metric.isin(["track_err", "track_rmse", "nees"])]
    assert te["value"].notna().all() and (df[df.metric == "nonfinite"]["value"] == 0).all()
    hyb = df[(df.metric == "track_err") & (df.consensus == "hybrid") & (df.link_fail == 0.3) & (df.node == "alive")]
    assert len(hyb) == 2 * 4 and hyb["value"].max() < 1.0
    ind = df[(df.metric == "track_err") & (df.consensus == "individual") & (df.link_fail == 0.3) & (df.node == "alive")]
    assert hyb["value"].mean() < ind["value"].mean()  # consensus still helps on the faulty network
    links = df[(df.metric == "live_link_frac") & (df.consensus == "hybrid") & (df.link_fail == 0.3)]["value"]
    assert 0.4 < links.min() and links.max() < 0.8  # ~0.7 up, fewer with failed nodes
    # deterministic from the seed
    df2 = yu_faults.run(cfg)
    pd.testing.assert_frame_equal(df, df2)


def test_yu_faults_report(tmp_path):
    from dslearn.report import summarize
    from dslearn.studies import yu_faults

    cfg = _tiny_cfg(models=["lin"], fusions=["hybrid", "cm"], train_episodes=0, test_episodes=2,
                    link_fail=[0.0, 0.5], node_fail=[0.0, 0.4], joint=[[0.3, 0.2]])
    df = yu_faults.run(cfg)
    from dslearn.reports.yu_faults import report

    text = report(df, summarize(df), tmp_path)
    assert "link-failure" in text and (tmp_path / "yu_faults_link.png").is_file() and (tmp_path / "yu_faults_node.png").is_file()
    assert (tmp_path / "yu_faults_joint.csv").is_file()


def test_an_episode_s_faults_do_not_depend_on_its_batch():
    """Per-episode streams: episode 1's node failures, outliers and live graphs are the same alone
    and inside a batch of three (to the bit)."""
    from dslearn.fusion.faults import draw_live_graph
    from dslearn.sim.faults import add_outliers, node_failure_schedule
    from dslearn.sim.placement import make_network
    from dslearn.sim.scenario import SocialForceScenario, episode_streams
    from dslearn.streams import Streams

    net = make_network()
    scen = SocialForceScenario()
    batch = scen.sample(3, net, episode_streams(7, "test", 0, 3))
    alone = scen.sample(1, net, episode_streams(7, "test", 1, 1))
    assert torch.equal(batch.states[1:2], alone.states) and torch.equal(batch.meas[:, 1:2], alone.meas)
    s, k = net.num_nodes, scen.steps
    gb = Streams.from_keys([(7, "faults", 0, "test", e) for e in range(3)], (3,))
    ga = Streams.from_keys([(7, "faults", 0, "test", 1)], (1,))
    ab = node_failure_schedule(s, 3, k, 0.3, gb)
    aa = node_failure_schedule(s, 1, k, 0.3, ga)
    assert torch.equal(ab[:, 1:2], aa)
    ob, hb = add_outliers(batch, 0.2, 3.0, gb)
    oa, ha = add_outliers(alone, 0.2, 3.0, ga)
    assert torch.equal(hb[:, 1:2], ha) and torch.equal(ob.meas[:, 1:2], oa.meas)
    live_b = draw_live_graph(net.adjacency, ab[:, :, 2].T, 0.4, gb)
    live_a = draw_live_graph(net.adjacency, aa[:, :, 2].T, 0.4, ga)
    assert torch.equal(live_b[1:2], live_a)
