"""The learned motion models on a scenario whose own state is not the filters' (Jiang's source, ``param2d``: a
position alone): the distributed filter tracks ``[p, v]`` per agent there, so the GP and the LSTMs are sized by
the agents (not by the scenario's state), and an offline fit learns from the true positions with velocities by
finite differences."""

import math

import pytest
import torch

from dslearn.methods.distributed import filter_tracks
from dslearn.sim.jiang import SquaredRangeScenario


def test_filter_tracks_by_hand():
    """Positions ``p(t) = (t^2, 3t)`` at ``dt = 0.5``: central differences inside (exact for a quadratic), one-sided
    at the ends; a scenario already in ``[p, v]`` keeps its states."""
    sc = SquaredRangeScenario()
    t = torch.arange(5, dtype=torch.float64) * 0.5
    states = torch.stack([t**2, 3 * t], -1).unsqueeze(0)  # (1, 5, 2): the scenario's own layout
    out = filter_tracks(sc, states, 0.5)
    assert out.shape == (1, 5, 4)
    assert torch.equal(out[0, :, :2], states[0])
    vx = [(0.25 - 0.0) / 0.5, (1.0 - 0.0) / 1.0, (2.25 - 0.25) / 1.0, (4.0 - 1.0) / 1.0, (4.0 - 2.25) / 0.5]
    assert torch.allclose(out[0, :, 2], torch.tensor(vx, dtype=torch.float64), rtol=0, atol=1e-12)
    assert torch.allclose(out[0, :, 3], torch.full((5,), 3.0, dtype=torch.float64), rtol=0, atol=1e-12)

    class PV:
        spec = type("S", (), {"state": "pv2d"})()

    pv = torch.randn(2, 5, 8, dtype=torch.float64)
    assert filter_tracks(PV(), pv, 0.5) is pv


def test_the_gp_and_the_lstm_are_sized_by_the_filters_state_on_jiang():
    from dslearn.models.gp import GPMotionModel
    from dslearn.models.lstm import SocialLSTM

    sc = SquaredRangeScenario()
    assert sc.state_dim == 2 and sc.spec.state == "param2d"
    gp = GPMotionModel.for_scenario(scenario=sc, num_nodes=3, dtype=torch.float64, device="cpu", mean="identity")
    assert gp.state_dim == 4
    x = torch.randn(3, 2, 4, dtype=torch.float64)
    mean, F, Q = gp.linearize(x, sc.ctx())
    assert torch.equal(mean, x)  # no data: the increment GP's prior mean, the identity
    assert F.shape == (3, 2, 4, 4) and Q.shape == (3, 2, 4, 4)
    lstm = SocialLSTM.for_scenario(scenario=sc)
    assert lstm.state_dim == 4 and math.isclose(lstm.dt, 1.0)


@pytest.mark.parametrize("method", ["ekf_gp_centralized", "ekf_lstm_centralized"])
def test_the_learned_models_run_on_jiangs_squared_ranges(method):
    """A matrix cell of the GP and of the LSTM on Jiang's scenario (its own sensor model, a fusion centre) runs and
    tracks the source: every node's position RMSE is finite and within 1 m (the source moves over tens of metres;
    its sensors' squared ranges have sigma 5 m^2)."""
    from dslearn.api import run

    res = run("task=matrix", f"method={method}", "scenario=jiang", "task.train_episodes=2", "task.test_episodes=1",
              "task.seeds=1")
    rmse = res.loc[res.metric == "rmse", "value"]
    assert len(rmse) == 3 and bool(((rmse > 0) & (rmse < 1.0)).all()), rmse
