"""A fusion centre holds one belief: the distributed filter predicts it once (at node 0) and every node receives it,
and a motion model with per-node state (the GP) is built for one node. The results are those of every node
predicting its own copy (the S-node GP learning the same data at every node), checked against that run."""

from __future__ import annotations

import torch

from dslearn.filters.distributed import initial_belief, one_belief, track
from dslearn.fusion.faults import FaultyFusion
from dslearn.fusion.strategies import make_fusion
from dslearn.fusion.weights import metropolis
from dslearn.models import ConstantVelocity, LinearPositionObservation
from dslearn.models.gp import GPMotionModel
from dslearn.sim.placement import make_network
from dslearn.sim.scenario import SocialForceScenario
from dslearn.types import StepContext

D = torch.float64
CTX = StepContext(dt=0.25)


class Counting(torch.nn.Module):
    """A motion model that records the node count of every query (a wrapper of ``base``)."""

    def __init__(self, base):
        super().__init__()
        self.base, self.seen = base, []
        self.state_dim, self.learnable = base.state_dim, base.learnable

    def __getattr__(self, name):
        try:
            return super().__getattr__(name)
        except AttributeError:
            return getattr(self.base, name)

    def linearize(self, x, ctx):
        self.seen.append(x.shape[0])
        return self.base.linearize(x, ctx)


def _world():
    scen = SocialForceScenario()
    net = make_network(seed=1, sensing_range=3.0)
    train = scen.sample(2, net, torch.Generator().manual_seed(3))
    test = scen.sample(2, net, torch.Generator().manual_seed(4))
    return scen, net, train, test


def _gp(nodes):
    return GPMotionModel(8, nodes, outputscale=0.5, lengthscale=2.0, noise_std=0.1, mean="identity", dtype=D)


def _run(model, fusion, scen, net, train, test):
    obs = LinearPositionObservation(net.meas_std)
    for k in range(len(train)):  # Algorithm 1: learn while tracking, one training episode at a time
        ep = train.measurements.select([k])
        track(ep, net, model, obs, fusion, CTX, initial_belief(ep, net, CTX.dt, fusion, scen.area), learn=True,
              learn_gate_std=2.0)
    ep = test.measurements
    return track(ep, net, model, obs, fusion, CTX, initial_belief(ep, net, CTX.dt, fusion, scen.area))


def test_centre_predicts_once_and_equals_every_node_predicting():
    scen, net, train, test = _world()
    central = make_fusion("centralized", metropolis(net.adjacency), 0)
    s = net.num_nodes
    one, every = Counting(_gp(1)), _gp(s)
    res1 = _run(one, central, scen, net, train, test)
    res_s = _run(every, central, scen, net, train, test)
    assert set(one.seen) == {1}  # the prediction ran for one node only
    assert one.base.gp.n == every.gp.n > 0  # the centre's GP learned the pairs every node's copy learned
    torch.testing.assert_close(res1.mean, res_s.mean, rtol=0, atol=1e-10)
    torch.testing.assert_close(res1.info, res_s.info, rtol=1e-10, atol=1e-8)
    assert torch.equal(res1.mean, res1.mean[:1].expand_as(res1.mean))  # every node holds the centre's belief


def test_one_belief_only_at_a_centre_with_one_model_state():
    net = make_network(seed=1, sensing_range=3.0)
    w, s = metropolis(net.adjacency), net.num_nodes
    central, hybrid = make_fusion("centralized", w, 0), make_fusion("hybrid", w, 2)
    assert one_belief(central, ConstantVelocity(2, 0.1), s)  # no per-node state
    assert one_belief(central, _gp(1), s)
    assert not one_belief(central, _gp(s), s)  # a GP per node: each predicts its own
    assert not one_belief(hybrid, ConstantVelocity(2, 0.1), s)  # consensus: the nodes' beliefs differ
    assert not one_belief(central, ConstantVelocity(2, 0.1), 1)
    # a faulty network's nodes may differ even under a centre
    assert not one_belief(FaultyFusion(central, net.adjacency, p_link=0.5), ConstantVelocity(2, 0.1), s)


def test_a_matrix_cell_builds_the_centre_one_gp():
    from dslearn import api
    from dslearn.compose import build_cell_parts

    def nodes(*overrides):
        cfg = api.compose("task=matrix", "scenario=yu_two_agents", *overrides)
        net, method = build_cell_parts(cfg, check_only=True)[1:]
        return method.model.num_nodes, net.num_nodes

    assert nodes("method=ekf_gp_centralized")[0] == 1
    got, s = nodes("method=ekf_gp_hybrid")
    assert got == s > 1
    # calibration runs every node's filter alone: one GP per node even under the centre
    assert nodes("method=ekf_gp_hybrid_calibrated", "consensus=centralized")[0] == s
