"""Faults in the network (dslearn/sim/faults.py: the data; dslearn/fusion/faults.py: the links), gating, and
the yu_faults study end to end."""

import math

import pandas as pd
import pytest
import torch

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


def _override(v) -> str:
    """A value in Hydra's override syntax (lists nested, booleans lower case)."""
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(_override(x) for x in v) + "]"
    return str(v).lower() if isinstance(v, bool) else str(v)


def _tiny_study(*overrides, **task):
    """The faults study of ``experiment=yu_faults`` (scenario yu_two_agents, network yu, linear observation,
    filter default: the root defaults) with these ``task`` keys, built by the composition root."""
    from dslearn import api

    task_keys = (f"task.{k}={_override(v)}" for k, v in task.items())
    return api.build_study("experiment=yu_faults", "progress=false", *overrides, *task_keys)


def test_yu_faults_acceptance_point_bounded():
    """30 % link failures + 20 % failed nodes: hybrid stays bounded, nothing is NaN."""
    study = _tiny_study(models=["lin", "gp_increment"], fusions=["hybrid", "individual"], train_episodes=2,
                        test_episodes=4, link_fail=[0.0], node_fail=[0.0], joint=[[0.3, 0.2]], outlier_settings=False)
    df = study.run()
    assert {"model", "consensus", "node", "episode", "metric", "value"} <= set(df.columns)
    te = df[df.metric.isin(["track_err", "track_rmse", "nees"])]
    assert te["value"].notna().all() and (df[df.metric == "nonfinite"]["value"] == 0).all()
    hyb = df[(df.metric == "track_err") & (df.consensus == "hybrid") & (df.link_fail == 0.3) & (df.node == "alive")]
    assert len(hyb) == 2 * 4 and hyb["value"].max() < 1.0
    ind = df[(df.metric == "track_err") & (df.consensus == "individual") & (df.link_fail == 0.3) & (df.node == "alive")]
    assert hyb["value"].mean() < ind["value"].mean()  # consensus still helps on the faulty network
    links = df[(df.metric == "live_link_frac") & (df.consensus == "hybrid") & (df.link_fail == 0.3)]["value"]
    assert 0.4 < links.min() and links.max() < 0.8  # ~0.7 up, fewer with failed nodes
    # deterministic from the seed, and a study keeps no state from one run to the next
    pd.testing.assert_frame_equal(df, study.run())


def test_yu_faults_report(tmp_path):
    from dslearn.report import summarize

    study = _tiny_study(models=["lin"], fusions=["hybrid", "cm"], train_episodes=0, test_episodes=2,
                        link_fail=[0.0, 0.5], node_fail=[0.0, 0.4], joint=[[0.3, 0.2]])
    df = study.run()
    # the outlier settings are wired: gross errors hurt, the chi-square gate rejects some and repairs most
    gate = df[df.metric == "gate_reject_frac"]
    assert (gate[gate.gating == "none"].value == 0).all() and (gate[gate.gating == "chi2"].value > 0.02).all()
    te = df[(df.metric == "track_err") & (df.node == "alive") & (df.link_fail == 0) & (df.node_fail == 0)]
    clean, raw = te[te.outlier_frac == 0].value.mean(), te[(te.outlier_frac > 0) & (te.gating == "none")].value.mean()
    gated = te[(te.outlier_frac > 0) & (te.gating == "chi2")].value.mean()
    assert raw > 2 * clean and gated < 0.5 * raw, (clean, raw, gated)
    from dslearn.reports.yu_faults import report

    text = report(df, summarize(df), tmp_path)
    assert "link-failure" in text and (tmp_path / "yu_faults_link.png").is_file() and (tmp_path / "yu_faults_node.png").is_file()
    assert (tmp_path / "yu_faults_joint.csv").is_file()


def test_fault_settings_grid_in_order_each_once():
    """The grid's settings: the link axis, the node axis, the joint points, then the outlier settings
    (ungated, gated, gated at every joint point); a setting named twice is run once, on its first axis."""
    from dslearn.studies.yu_faults import FaultSetting, FaultTask, fault_settings

    t = FaultTask(link_fail=[0.0, 0.3], node_fail=[0.0, 0.2], joint=[[0.3, 0.2], [0.3, 0.0]], outlier_frac=0.1,
                  gate_prob=0.9)
    assert fault_settings(t) == [
        FaultSetting(0.0, 0.0, axis="link"), FaultSetting(0.3, 0.0, axis="link"), FaultSetting(0.0, 0.2, axis="node"),
        FaultSetting(0.3, 0.2, axis="joint"), FaultSetting(0.0, 0.0, 0.1, None, "outliers"),
        FaultSetting(0.0, 0.0, 0.1, 0.9, "outliers"), FaultSetting(0.3, 0.2, 0.1, 0.9, "joint+outliers"),
        FaultSetting(0.3, 0.0, 0.1, 0.9, "joint+outliers"),
    ]
    t.gate_prob = None  # no gate: the ungated outlier setting only
    assert fault_settings(t)[-1] == FaultSetting(0.0, 0.0, 0.1, None, "outliers") and len(fault_settings(t)) == 5
    t.outlier_settings = False
    assert [st.axis for st in fault_settings(t)] == ["link", "link", "node", "joint"]


def test_alive_summaries_closed_form():
    """Per episode: the alive nodes' mean (a non-finite value adds 0, the count stays), every node's mean,
    the alive nodes' maximum (-inf when none is alive)."""
    from dslearn.metrics.faults import alive_summaries

    nan, inf = float("nan"), float("inf")
    values = torch.tensor([[1.0, 2.0, 5.0], [3.0, inf, 7.0], [10.0, 4.0, 9.0]])  # (S=3, B=3)
    alive = torch.tensor([[True, True, False], [True, True, False], [False, False, False]])
    got = alive_summaries(values, alive)
    assert list(got) == ["alive", "all", "alive_max"]
    torch.testing.assert_close(got["alive"], torch.tensor([2.0, 1.0, 0.0], dtype=torch.float64))  # (2+0)/2
    torch.testing.assert_close(got["all"], torch.tensor([14 / 3, nan, 7.0], dtype=torch.float64), equal_nan=True)
    torch.testing.assert_close(got["alive_max"], torch.tensor([3.0, nan, -inf], dtype=torch.float64), equal_nan=True)


def test_faulty_network_rows_closed_form():
    """One cell's rows from beliefs with known errors: a node off by (3, 4) m at every step has track_err 5,
    NEES (9 + 16) / 4 with unit information; summaries over the nodes alive at the last step; the non-finite,
    live-link and gate fractions; the keys first, in their order."""
    from dslearn.filters.distributed import TrackResult
    from dslearn.metrics.faults import faulty_network_rows

    s, b, k = 3, 2, 4
    truth = torch.zeros(b, k + 1, 4, dtype=torch.float64)
    mean = torch.zeros(s, b, k + 1, 4, dtype=torch.float64)
    mean[0, :, :, :2] = torch.tensor([3.0, 4.0])  # node 0: 5 m off everywhere
    mean[1, :, :, :2] = torch.tensor([0.6, 0.8])  # node 1: 1 m
    mean[2, 1, 2, 0] = float("nan")  # node 2 (dead in episode 1 at the end): one non-finite estimate
    info = torch.eye(4, dtype=torch.float64).expand(s, b, k + 1, 4, 4)
    alive = torch.ones(s, b, k + 1, dtype=torch.bool)
    alive[2, 1, 3:] = False  # node 2 fails at t = 3 in episode 1
    df = faulty_network_rows(TrackResult(mean, info), truth, alive, live_links=6.0, nominal_links=8.0, gate_tested=10,
                             gate_rejected=3, model="lin", consensus="hybrid")
    assert list(df.columns) == ["model", "consensus", "node", "episode", "metric", "value"]
    assert (df.model == "lin").all() and (df.consensus == "hybrid").all()
    v = df.set_index(["metric", "node", "episode"]).value.sort_index()
    assert v["track_err", "alive", 0] == pytest.approx(2.0) and v["track_err", "alive", 1] == pytest.approx(3.0)
    assert v["track_err", "alive_max", 0] == pytest.approx(5.0) and v["track_err", "all", 0] == pytest.approx(2.0)
    assert math.isnan(v["track_err", "all", 1])
    assert v["nees", "alive", 0] == pytest.approx((6.25 + 0.25 + 0.0) / 3)
    assert v["track_rmse", "alive_max", 1] == pytest.approx(5.0)
    assert list(v["nonfinite", "all"]) == [0.0, 1.0]
    assert v["live_link_frac", "all", 0] == 0.75 and v["gate_reject_frac", "all", 0] == 0.3
    assert len(df) == 3 * 3 * b + b + 2
    none = faulty_network_rows(TrackResult(mean, info), truth, alive, live_links=0.0, nominal_links=0.0,
                               gate_tested=0, gate_rejected=0)
    w = none.set_index(["metric", "node", "episode"]).value.sort_index()
    assert math.isnan(w["live_link_frac", "all", 0]) and w["gate_reject_frac", "all", 0] == 0.0


def test_yu_faults_slots_labels_and_fusions():
    """The composition root's slots of the grid: each model option's rows label (its ``name``), and each fusion
    option built with its own type and omega and the root's rounds L."""
    from dslearn.studies.yu_faults import YuFaultsStudy

    study = _tiny_study("consensus.iterations=2", models=["gp_cv", "lin"],
                        fusions=["hybrid", "hybrid_nodes", "individual"])
    assert isinstance(study, YuFaultsStudy)
    assert study.yu_faults_model_labels == {"gp_cv": "gp_increment_cv", "lin": "lin"}
    assert set(study.model_options) == {"gp_cv", "lin"}
    fus = {n: make(study.network) for n, make in study.yu_faults_fusions.make.items()}
    assert study.yu_faults_fusions.rounds == 2 and {f.iterations for f in fus.values()} == {2}
    assert (fus["hybrid"].name, fus["hybrid"].omega) == ("hybrid", 1.0)
    assert (fus["hybrid_nodes"].name, fus["hybrid_nodes"].omega) == ("hybrid", float(study.network.num_nodes))
    assert fus["individual"].name == "individual"
    assert fus["hybrid"] is not study.yu_faults_fusions.make["hybrid"](study.network)  # a fresh one per cell
    # the rows take their labels from the slots: the model's label, the fusion option, the rounds L
    small = _tiny_study("consensus.iterations=2", models=["lin"], fusions=["ci"], train_episodes=0, test_episodes=1,
                        link_fail=[0.1], node_fail=[], joint=[], outlier_settings=False, weights="uniform")
    small.yu_faults_model_labels = {"lin": "lin (label)"}
    df = small.run()
    keys = df.drop(columns=["node", "episode", "metric", "value"]).drop_duplicates().to_dict("records")
    assert keys == [dict(model="lin (label)", consensus="ci", link_fail=0.1, node_fail=0.0, outlier_frac=0.0,
                         gating="none", axis="link", node_fail_mode="permanent", weights="uniform", iterations=2,
                         train_episodes=0)]


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
