"""Initialisation in information form, bounded interactions, and a layout where one sensor sees
neither target at t = 0 and t = 1 (it must get its initial belief from its neighbours)."""

import math

import pytest
import torch

from dslearn.fusion.strategies import make_fusion
from dslearn.fusion.weights import consensus_weights
from dslearn.models.social_force import SocialForce, soft_distance, social_force_acceleration
from dslearn.sim.placement import make_network
from dslearn.sim.scenario import SocialForceScenario
from dslearn import api
from dslearn.filters.distributed import diffuse_prior, first_observations, initial_belief, prior_means
from dslearn.types import StepContext, agents, batch_jacobian

D = torch.float64

# the late-sensor layout, written out: sensors 1-4, then communication nodes 1-6; sensor 4 sits
# below the agents' start squares, more than the sensing range (4 m) away from both
POSITIONS = [[4.0, 6.0], [2.5, 4.0], [5.5, 4.0], [4.0, 1.25], [1.0, 6.0], [7.0, 6.0],
             [1.5, 2.0], [6.5, 2.0], [4.0, 3.0], [4.0, 7.5]]
# the links of `network=yu_blind` (nodes within 3.2 m), written out
EDGES = [[0, 1], [0, 2], [0, 4], [0, 5], [0, 8], [0, 9], [1, 2], [1, 3], [1, 4], [1, 6], [1, 8], [2, 3],
         [2, 5], [2, 7], [2, 8], [3, 6], [3, 7], [3, 8], [6, 8], [7, 8]]


def _layout():
    pos = "[" + ",".join(f"[{x},{y}]" for x, y in POSITIONS) + "]"
    edges = "[" + ",".join(f"[{i},{j}]" for i, j in EDGES) + "]"
    return [f"network.positions={pos}", f"network.edges={edges}"]


def _study(make_cfg, model, consensus, *extra):
    return api.build_study(make_cfg(f"model={model}", f"consensus={consensus}", *_layout(), *extra))


def _sensor_means(df, metric):
    df = df[(df["metric"] == metric) & (df["node_kind"] == "sensor")]
    return df.groupby("node")["value"].mean()


def test_layout_premise(make_cfg):
    """Sensor 4 sees neither target at both t = 0 and t = 1 (what its own initialisation needs) in
    any test episode, and sees them later."""
    study = _study(make_cfg, "lin", "individual", "data.train_episodes=0", "data.test_episodes=50")
    test, _ = study.sample()
    vis = test.visible[3]  # (B, K+1, A)
    assert not (vis[:, 0] & vis[:, 1]).any()
    assert vis[:, :2].any(1).float().mean() < 0.25  # and mostly not even once
    assert vis.any(1).float().mean() > 0.95


def test_sfm_individual_stays_bounded_at_every_sensor(make_cfg):
    """The measured failure: the late sensor's SFM filter diverged to ~100 m with ~4,000 jitter
    events when both agents' priors sat on one point (8.3 m, 3,815 events on this layout before
    the fix). Now every sensor stays below 1 m; most of the late sensor's error is the diffuse
    prior's before it first sees the agents (from about t = 3-4, of 12 steps)."""
    from dslearn.diagnostics import Diagnostics

    study = _study(make_cfg, "sfm", "individual", "data.train_episodes=0", "data.test_episodes=50")
    with Diagnostics() as diag:  # the run's diagnostics receive every jitter record
        df = study.run(diagnostics=diag)
    err = _sensor_means(df, "track_err")
    assert torch.isfinite(torch.tensor(df["value"].to_numpy())).all()
    assert (err < 1.0).all(), err.to_dict()
    assert diag.jitter.count <= 5  # counted: 0 in the measured runs
    assert diag.counts["train_episodes_seen"] == 0 and diag.timings["evaluate_s"] > 0


@pytest.mark.parametrize("consensus", ["hybrid", "hybrid_nodes"])
def test_zero_mean_gp_consensus_prediction_at_the_late_sensor(make_cfg, consensus):
    """With consensus the late sensor's initial belief comes from its neighbours, so its data set
    holds pairs near the true t = 0 states like the others' (it predicted at ~9x their error)."""
    study = _study(make_cfg, "gp", consensus, "data.train_episodes=30", "data.test_episodes=20")
    pred = _sensor_means(study.run(), "pred_err")
    others = pred.drop("sensor4").mean()
    assert pred["sensor4"] <= 1.5 * others, pred.to_dict()


def test_one_rule_for_every_fusion():
    """Individual fusion gives the paper's initialisation where the node saw the target and the
    diffuse prior elsewhere; centralised fusion sums every sensor's first observations."""
    net = make_network(positions=POSITIONS, edges=EDGES)
    scen = SocialForceScenario()
    ep = scen.sample(3, net, torch.Generator().manual_seed(3))
    w = consensus_weights(net.adjacency, "uniform")
    dt, sig2 = scen.dt, net.meas_std**2
    seen = ep.visible[:, :, 0] & ep.visible[:, :, 1]  # (S, B, A)
    m, o = initial_belief(ep.measurements, net, dt, make_fusion("individual", w), scen.area)
    pm, po = diffuse_prior(2, scen.area, 1000.0, 1000.0, (), D, "cpu")
    z0, z1 = ep.meas[:, :, 0], ep.meas[:, :, 1]
    for i in range(net.num_nodes):
        for b in range(3):
            for j in range(2):
                blk = slice(4 * j, 4 * j + 4)
                if seen[i, b, j]:
                    # the paper's y0 = (z0, (z1 - z0)/dt), Omega0 = diag(1/s2, 1/s2, dt^2/2s2, dt^2/2s2), plus
                    # the diffuse prior's (1e-6-sized) information
                    y0 = torch.cat([z0[i, b, j], (z1[i, b, j] - z0[i, b, j]) / dt])
                    om = torch.tensor([1 / sig2, 1 / sig2, dt**2 / (2 * sig2), dt**2 / (2 * sig2)], dtype=D)
                    assert torch.allclose(o[i, b, blk, blk], torch.diag(om) + po[blk, blk], rtol=1e-12)
                    assert torch.allclose(m[i, b, blk], y0, atol=1e-4)
                else:
                    assert torch.allclose(o[i, b, blk, blk], po[blk, blk])
                    assert torch.allclose(m[i, b, blk], pm[blk])
    # centralised: the prior plus the sum over sensors of their pseudo-measurements
    mc, oc = initial_belief(ep.measurements, net, dt, make_fusion("centralized", w), scen.area)
    dq, do = first_observations(ep.measurements, net, dt)
    o_exp = po + do.sum(0)
    assert torch.allclose(oc, o_exp.expand_as(oc))
    q_exp = (po @ pm) + dq.sum(0)
    assert torch.allclose(mc, torch.linalg.solve(o_exp, q_exp.unsqueeze(-1)).squeeze(-1).expand_as(mc), atol=1e-9)


def test_priors_keep_targets_apart():
    for a in (1, 2, 3, 5):
        p = prior_means(a, (0.0, 8.0, 0.0, 8.0))[:, :2]
        # a single target sits at the circle's first point c + (r, 0), r = 8 / 16; more are centred on c
        centre = torch.tensor([4.5, 4.0] if a == 1 else [4.0, 4.0], dtype=D)
        assert torch.allclose(p.mean(0), centre, atol=1e-12), (a, p)
        if a > 1:
            d = torch.cdist(p, p) + torch.eye(a, dtype=D) * 1e9
            assert d.min() >= 2 * 0.5 * math.sin(math.pi / a) - 1e-12  # on a circle of radius 8/16


def test_soft_distance_is_the_distance_beyond_eps_and_smooth_below():
    eps = 0.2
    u = torch.linspace(0, 1.0, 2001, dtype=D)
    s = soft_distance(u, eps)
    far = u >= eps**2
    assert torch.equal(s[far], u[far].sqrt())
    assert (s[~far] > 0).all() and (s.diff() >= 0).all()
    # value, first and second derivative continuous at u = eps^2
    x = torch.tensor([eps**2 - 1e-7, eps**2 + 1e-7], dtype=D, requires_grad=True)
    y = soft_distance(x, eps)
    (g,) = torch.autograd.grad(y.sum(), x, create_graph=True)
    (h,) = torch.autograd.grad(g.sum(), x)
    y, g, h = y.detach(), g.detach(), h.detach()
    assert abs(float(y[1] - y[0])) < 1e-6 and abs(float(g[1] - g[0])) < 1e-4 and abs(float(h[1] - h[0])) / abs(float(h[1])) < 1e-4


def test_social_force_is_finite_and_bounded_when_agents_coincide():
    sfm = SocialForce([[1.0, -1.0], [-1.0, -1.0]], 0.25, 6.0, 5.0, softening=0.2)
    ctx = StepContext(dt=0.25)
    for gap in (0.0, 1e-9, 1e-3, 0.05):
        x = torch.tensor([[4.0, 4.0, 0.0, 0.0, 4.0 + gap, 4.0, 0.0, 0.0]], dtype=D)
        J = batch_jacobian(lambda z: sfm(z, ctx), x)
        assert torch.isfinite(J).all()
        # |d(acc)/d(pos)| <= alpha * 8 / (3 eps) (the force magnitude over the smallest soft distance), times dt
        assert J[..., 2:4, 0:2].abs().max() <= 0.25 * 6.0 * 8 / (3 * 0.2) * 2
    # autograd Jacobian = finite differences at near-coincidence
    x = torch.tensor([4.0, 4.0, 0.3, -0.2, 4.05, 3.98, -0.1, 0.4], dtype=D)
    J = batch_jacobian(lambda z: sfm(z, ctx), x)
    h = 1e-6
    fd = torch.stack([(sfm(x + h * e, ctx) - sfm(x - h * e, ctx)) / (2 * h) for e in torch.eye(8, dtype=D)], -1)
    assert torch.allclose(J, fd, atol=1e-6)


def test_social_force_equals_the_plain_model_for_agents_apart():
    """Agents further apart than the softening: exactly Eq. (4) (the simulation is unchanged)."""
    pos = torch.tensor([[1.0, 2.0], [3.0, 2.5]], dtype=D)
    vel = torch.tensor([[0.5, 0.0], [-0.5, 0.1]], dtype=D)
    des = torch.tensor([[1.0, -1.0], [-1.0, -1.0]], dtype=D)
    tau, alpha, beta = torch.full((2,), 0.25, dtype=D), torch.full((2,), 6.0, dtype=D), torch.full((2,), 5.0, dtype=D)
    acc = social_force_acceleration(pos, vel, des, tau, alpha, beta, softening=0.2)
    d = (pos[0] - pos[1]).norm()
    f01 = 6.0 * torch.exp(-d / 5.0) * (pos[0] - pos[1]) / d
    assert torch.allclose(acc[0], (des[0] - vel[0]) / 0.25 + f01, atol=1e-14)
    assert torch.allclose(acc[1], (des[1] - vel[1]) / 0.25 - f01, atol=1e-14)


def test_interactions_with_an_unknown_agent_vanish_inside_the_filter():
    """With a diffuse belief about agent 2, the filter's social force neither pushes agent 1 nor
    couples their linearisation; with a sharp belief it is the plain model."""
    sfm = SocialForce([[1.0, -1.0], [-1.0, -1.0]], 0.25, 6.0, 5.0)
    x = torch.tensor([3.0, 4.0, 1.0, -1.0, 4.0, 4.0, -1.0, -1.0], dtype=D)
    sharp = torch.diag(torch.full((8,), 1e-4, dtype=D))
    vague = sharp.clone()
    vague[4:, 4:] = torch.eye(4, dtype=D) * 1e6
    plain = sfm(x, StepContext(dt=0.25))
    assert torch.equal(sfm(x, StepContext(dt=0.25, cov=sharp)), plain)
    J = batch_jacobian(lambda z: sfm(z, StepContext(dt=0.25, cov=vague)), x)
    assert J[2:4, 4:6].abs().max() < 1e-12  # agent 1's velocity no longer depends on agent 2's position
    free = sfm(x, StepContext(dt=0.25, cov=vague))
    assert torch.allclose(agents(free)[0, 2:], torch.tensor([1.0, -1.0], dtype=D), atol=1e-12)  # v* exactly
