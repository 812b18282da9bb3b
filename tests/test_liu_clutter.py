"""Liu et al.'s S1 field as unlabelled detections (``scenario=liu_s1_clutter``,
:class:`dslearn.sim.clutter.ClutterManoeuvreScenario`): its truth is Liu's, its detections carry no label, its
declared start is the generator's law, and the association presets run on it."""

from __future__ import annotations

import math

import pytest
import torch

from dslearn.errors import ConfigError
from dslearn.sim.clutter import ClutterManoeuvreScenario, clutter_cap
from dslearn.sim.liu import ManoeuvreScenario
from dslearn.sim.manoeuvres import generate_s1
from dslearn.sim.scenario import episode_streams

F64 = torch.float64


def _pair(**kw):
    liu = ManoeuvreScenario(generate_s1, name="s1", comm_radius=250.0, seed=3)
    unl = ClutterManoeuvreScenario(generate_s1, name="liu_s1_clutter", comm_radius=250.0, seed=3, **kw)
    return liu, unl


def test_the_truth_is_liu_s_and_the_detections_carry_no_label():
    """The same streams give Liu's states bit for bit; each sensor's set holds its reading of the target where it
    detected it (frequency P_D over the steps in range, 5 binomial standard deviations) and clutter in its disc
    (mean count the rate, 5 Poisson standard deviations), in slots of a random order."""
    liu, unl = _pair(p_detect=0.8, clutter_rate=0.5)
    b = 6
    lab = liu.sample(b, liu.network, episode_streams(0, "test", 0, b))
    ep = unl.sample(b, unl.network, episode_streams(0, "test", 0, b))
    assert torch.equal(ep.states, lab.states)
    s, k1 = unl.network.num_nodes, unl.steps + 1
    assert ep.meas.shape == (s, b, k1, 1 + clutter_cap(0.5), 2) and ep.visible.shape == ep.meas.shape[:-1]
    reading = lab.meas[:, :, :, 0]  # (S, B, K+1, 2) Liu's labelled readings
    is_target = (ep.meas == reading.unsqueeze(-2)).all(-1) & ep.visible & lab.visible  # (S, B, K+1, M)
    in_range = int(lab.visible.sum())
    freq = is_target.sum().item() / in_range
    assert abs(freq - 0.8) < 5 * math.sqrt(0.8 * 0.2 / in_range)
    assert bool((is_target.sum(-1) <= 1).all())
    n_clutter = (ep.visible & ~is_target).sum(-1).to(F64)
    assert abs(n_clutter.mean().item() - 0.5) < 5 * math.sqrt(0.5 / n_clutter.numel())
    centre = unl.network.positions.view(s, 1, 1, 1, 2).to(F64)
    d = (ep.meas - centre).norm(dim=-1)
    assert bool((d[ep.visible & ~is_target] <= unl.network.sensing_range + 1e-9).all())
    slot = is_target.float().argmax(-1)[is_target.any(-1)]
    assert len(set(slot.tolist())) > 1  # the target's detection is not always in the same slot
    spec = unl.spec
    assert (spec.name, spec.labelled, spec.num_agents, spec.match_distance) == ("liu_s1_clutter", False, 1, 50.0)
    assert unl.clutter_density(unl.network) == pytest.approx(0.5 / (math.pi * 50.0**2), rel=1e-15)


def test_the_declared_start_is_the_generator_s_first_state_law():
    """``start_prior``: the mean and covariance of the first state over ``start_draws`` trajectories of its own
    stream (recomputed here from the generator), plus the sensors' variance on the position and
    ``start_velocity_std^2`` on the velocity; the episodes' first states lie within it; it draws nothing from the
    episodes' streams (a sample is the same after it)."""
    liu, unl = _pair(start_draws=64, start_velocity_std=0.5)
    mean, cov = unl.start_prior()
    assert mean.shape == (1, 4) and cov.shape == (1, 4, 4)
    from dslearn.sim.clutter import START_STREAM
    from dslearn.streams import stream_seed

    pos, vel = generate_s1(64, unl.steps + 1, torch.Generator().manual_seed(stream_seed(3, START_STREAM)), dt=1.0)
    x0 = torch.cat([pos[:, 0], vel[:, 0]], -1)
    torch.testing.assert_close(mean[0], x0.mean(0), rtol=0, atol=1e-12)
    want = torch.cov(x0.T) + torch.diag(torch.tensor([4.0, 4.0, 0.25, 0.25], dtype=F64))
    torch.testing.assert_close(cov[0], want, rtol=1e-12, atol=1e-12)
    assert torch.equal(cov[0], cov[0].T) and bool((torch.linalg.eigvalsh(cov[0]) > 0).all())
    first = unl.sample(20, unl.network, episode_streams(1, "test", 0, 20)).states[:, 0]  # (20, 4)
    d = first - mean
    m2 = (d.unsqueeze(-2) @ torch.linalg.solve(cov, d.unsqueeze(-1))).squeeze()
    assert bool((m2 < 18.47).all())  # chi^2 with 4 dof at 0.999
    again = unl.sample(20, unl.network, episode_streams(1, "test", 0, 20)).states[:, 0]
    assert torch.equal(first, again)


@pytest.mark.parametrize("field,kwargs", [("scenario.p_detect", dict(p_detect=0.0)),
                                          ("scenario.clutter_rate", dict(clutter_rate=-1.0)),
                                          ("scenario.start_draws", dict(start_draws=1)),
                                          ("scenario.match_distance", dict(match_distance=0.0)),
                                          ("scenario.start_velocity_std", dict(start_velocity_std=-1.0))])
def test_validation_names_the_field(field, kwargs):
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        ClutterManoeuvreScenario(generate_s1, comm_radius=250.0, **kwargs)


def test_an_association_preset_runs_on_the_field(make_cfg):
    """GNN on the 200-sensor field (1 + 1 episodes): every node and episode has finite multi-target metrics, the
    OSPA within its cut-off (the scenario's 50 m), the GOSPA (p = 2, a mean over the steps) at most the root of its
    parts' sum (their means: Jensen), and most nodes' tracks on the target (GOSPA below the cut-off)."""
    from dslearn.compose import build_study

    cfg = make_cfg("task=matrix", "task.train_episodes=1", "task.test_episodes=1", "method=ekf_lin_hybrid_gnn",
                   "scenario=liu_s1_clutter")
    df = build_study(cfg).run()
    wide = df[df.metric != "runtime_s"].pivot_table(index=["node", "episode"], columns="metric", values="value")
    assert len(wide) == 200
    for m in ("gospa", "gospa_loc", "gospa_missed", "gospa_false", "ospa", "id_switches"):
        assert bool(wide[m].map(math.isfinite).all()), m
    assert bool((wide.ospa <= 50.0 + 1e-9).all())
    parts = wide.gospa_loc + wide.gospa_missed + wide.gospa_false  # each a mean of d^2 terms over the steps
    assert bool((wide.gospa <= parts.pow(0.5) + 1e-9).all())
    assert float((wide.gospa < 50.0).mean()) > 0.5
