"""Recorded crowds as unlabelled detections (dslearn/sim/crowd.py): every pedestrian of a window, entering and
leaving as recorded; windows and presence by hand, the detections of present pedestrians only."""

import math
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import torch

from dslearn.data.episodes import extract_crowd_windows
from dslearn.errors import ConfigError
from dslearn.sim.crowd import RecordedCrowdScenario


def _scene():
    """Three pedestrians on straight lines, sampled every 0.5 s: ped 1 over [0, 4] s at (t, 0), ped 2 over
    [1, 2] s at (0, 2t), ped 3 over [3.5, 6] s at (-t, 1); the file spans [0, 6] s."""
    rows = []
    for t in np.arange(0.0, 4.01, 0.5):
        rows.append(("f", 1, t, t, 0.0))
    for t in (1.0, 1.5, 2.0):
        rows.append(("f", 2, t, 0.0, 2 * t))
    for t in np.arange(3.5, 6.01, 0.5):
        rows.append(("f", 3, t, -t, 1.0))
    df = pd.DataFrame(rows, columns=["file", "ped", "t", "x", "y"])
    return SimpleNamespace(name="hand", dt=0.5, df=df)


def test_crowd_windows_by_hand():
    """Windows of 4 steps of 0.5 s every 4 steps: [0, 2], [2, 4], [4, 6] s. A pedestrian is in a window where its
    track covers at least two of the window's 5 times; its velocity is the finite difference of its positions."""
    eps = extract_crowd_windows(_scene(), max_agents=3, steps=4, dt=0.5, stride=4)
    assert len(eps) == 3 and eps.states.shape == (3, 5, 12)
    assert eps.meta.peds.tolist() == ["1,2", "1,3", "3"] and eps.meta.agents.tolist() == [2, 2, 1]
    assert eps.meta.t0.tolist() == [0.0, 2.0, 4.0] and eps.attrs == {"too_crowded": 0}
    s = eps.states.unflatten(-1, (3, 4))  # (B, K+1, A, 4)
    t = torch.arange(5, dtype=torch.float64) * 0.5
    # window 0: ped 1 throughout at (t, 0) moving (1, 0); ped 2 at t = 1, 1.5, 2 at (0, 2t) moving (0, 2)
    torch.testing.assert_close(s[0, :, 0], torch.stack([t, 0 * t, 1 + 0 * t, 0 * t], -1), rtol=0, atol=1e-12)
    present = ~torch.isnan(s[0, :, 1, 0])
    assert present.tolist() == [False, False, True, True, True]
    torch.testing.assert_close(s[0, 2:, 1], torch.tensor([[0.0, 2.0, 0.0, 2.0], [0.0, 3.0, 0.0, 2.0],
                                                          [0.0, 4.0, 0.0, 2.0]], dtype=torch.float64))
    assert bool(torch.isnan(s[0, :, 2]).all())  # the third slot is empty
    # window 1 ([2, 4] s): ped 1 throughout; ped 3 from 3.5 s (two times: 3.5, 4.0) at (-t, 1) moving (-1, 0)
    assert (~torch.isnan(s[1, :, 1, 0])).tolist() == [False, False, False, True, True]
    torch.testing.assert_close(s[1, 3:, 1], torch.tensor([[-3.5, 1.0, -1.0, 0.0], [-4.0, 1.0, -1.0, 0.0]],
                                                         dtype=torch.float64))
    # window 2 ([4, 6] s): ped 1 ends at 4 s (one time only: absent), ped 3 throughout
    assert (~torch.isnan(s[2, :, 0, 0])).all() and bool(torch.isnan(s[2, :, 1:]).all())
    # the cap: a window with more pedestrians than max_agents is dropped and counted
    one = extract_crowd_windows(_scene(), max_agents=1, steps=4, dt=0.5, stride=4)
    assert one.meta.peds.tolist() == ["3"] and one.attrs == {"too_crowded": 2}
    with pytest.raises(ConfigError, match="scenario.episodes.max_agents"):
        extract_crowd_windows(_scene(), max_agents=0, steps=4)


def _corridor(**change):
    """The shipped corridor recording as a crowd scenario (no ETH/UCY files needed)."""
    values = dict(dataset=dict(label="corridor", files=["corridor.txt"], root="pkg://dslearn.data/corridor",
                               frame_step=10, dt=0.4, fps=25.0, units="m", val_first_frame=None),
                  name="corridor_crowd", episodes=dict(max_agents=8, steps=6, stride=3),
                  network=dict(num_sensors=4, k_nearest=2, sensing_range=8.0, meas_std=0.2))
    values.update(change)
    return RecordedCrowdScenario(**values)


def test_a_crowd_reports_only_present_pedestrians():
    """With P_D = 1 and no clutter, each sensor's detections at a step are exactly the present pedestrians in its
    range, at their true positions up to the sensor noise; absent ones have a NaN truth and no detection."""
    from dslearn.sim.scenario import episode_streams

    sc = _corridor(p_detect=1.0, clutter_rate=0.0)
    spec = sc.spec
    assert (spec.labelled, spec.births, spec.num_agents, spec.source) == (False, True, 8, "recorded")
    ep = sc.sample(3, sc.network, episode_streams(0, "test", 0, 3), split="test")
    alive = sc.alive(ep.states)  # (B, K+1, A)
    pos = ep.states.unflatten(-1, (-1, 4))[..., :2]
    assert bool(torch.isnan(pos[~alive]).all()) and bool(torch.isfinite(pos[alive]).all())
    assert int(alive.sum()) > 0 and not bool(alive.all())  # pedestrians enter and leave
    in_range = sc.network.visible(pos.nan_to_num(0.0)) & alive.unsqueeze(0)  # (S, B, K+1, A)
    assert torch.equal(ep.visible.sum(-1), in_range.sum(-1))
    for s in range(sc.network.num_nodes):  # every detection is a present pedestrian's position plus noise (< 6 sigma)
        det = ep.meas[s][ep.visible[s]]  # (n, 2)
        b, k = torch.nonzero(ep.visible[s], as_tuple=True)[:2]
        d = (det.unsqueeze(1) - pos[b, k]).norm(dim=-1).nan_to_num(math.inf).min(-1).values
        assert bool((d < 6 * 0.2 * math.sqrt(2)).all())
    with pytest.raises(ConfigError, match="scenario.p_detect"):
        _corridor(p_detect=0.0)
    with pytest.raises(ConfigError, match=r"scenario.episodes: unknown key\(s\) \['agents'\]"):
        _corridor(episodes=dict(agents=2))


def test_a_crowd_cell_runs_with_managed_tracks():
    """A matrix cell of LIN under GNN on the crowd: the multi-target metrics of managed tracks (GOSPA and its
    parts) come out finite."""
    from dslearn.api import run

    if not _ethucy():
        pytest.skip("the ETH/UCY data are absent")
    res = run("task=matrix", "method=ekf_lin_hybrid_gnn", "scenario=eth_zara1_crowd", "task.train_episodes=1",
              "task.test_episodes=2", "task.seeds=1")
    gospa = res.loc[res.metric == "gospa", "value"]
    assert len(gospa) and bool(np.isfinite(gospa).all()) and bool((gospa > 0).all())


def _ethucy() -> bool:
    from dslearn.data.ethucy import data_available

    return data_available()
