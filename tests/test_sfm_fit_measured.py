"""The fitted social force under a measurements-only protocol (the matrix): its desired velocities come from the
test episodes' measurements (the nodes' mean reading at the agent's first measured steps), never left at 0."""

import pytest
import torch

from dslearn.learning.sfm_fit import FittedSocialForce, measured_desired_velocity


def _readings():
    """Two nodes, one episode, 4 steps, two agents; dt = 0.5."""
    s, b, t, a = 2, 1, 4, 2
    meas = torch.zeros(s, b, t, a, 2, dtype=torch.float64)
    vis = torch.zeros(s, b, t, a, dtype=torch.bool)
    # agent 0: node 0 sees it at steps 0..3 at (0,0),(1,2),(2,4),(3,6); node 1 at step 1 only, 0.2 m off in x
    for k in range(4):
        meas[0, 0, k, 0] = torch.tensor([1.0 * k, 2.0 * k])
        vis[0, 0, k, 0] = True
    meas[1, 0, 1, 0] = torch.tensor([1.2, 2.0])
    vis[1, 0, 1, 0] = True
    # agent 1: first seen at step 1 (node 1: (5, 5)), then at step 3 (node 0: (4, 5)); never at steps 0, 2
    meas[1, 0, 1, 1] = torch.tensor([5.0, 5.0])
    vis[1, 0, 1, 1] = True
    meas[0, 0, 3, 1] = torch.tensor([4.0, 5.0])
    vis[0, 0, 3, 1] = True
    return meas, vis


def test_measured_desired_velocity_by_hand():
    meas, vis = _readings()
    v = measured_desired_velocity(meas, vis, 0.5, 1)
    # agent 0: step 0 at (0, 0), step 1 the mean of (1, 2) and (1.2, 2) = (1.1, 2): (1.1, 2) / 0.5
    assert torch.allclose(v[0, 0], torch.tensor([2.2, 4.0], dtype=torch.float64), atol=1e-12)
    # agent 1: measured at steps 1 and 3: ((4, 5) - (5, 5)) / (2 * 0.5)
    assert torch.allclose(v[0, 1], torch.tensor([-1.0, 0.0], dtype=torch.float64), atol=1e-12)
    v2 = measured_desired_velocity(meas, vis, 0.5, 2)
    assert torch.allclose(v2[0, 0], torch.tensor([2.0, 4.0], dtype=torch.float64), atol=1e-12)  # (2, 4) / 1.0
    assert torch.equal(v2[0, 1], torch.zeros(2, dtype=torch.float64))  # measured at two steps only: no velocity


def test_the_fitted_social_force_takes_its_desired_velocities_from_the_measurements():
    meas, vis = _readings()
    from types import SimpleNamespace

    model = FittedSocialForce.for_scenario(scenario=SimpleNamespace(num_agents=2, steps=3))
    model.begin_measured(meas, vis, 0.5)
    assert torch.allclose(model.desired.reshape(-1, 2, 2)[0],
                          measured_desired_velocity(meas, vis, 0.5, 1)[0].to(model.desired.dtype))


@pytest.mark.parametrize("scenario", ["corridor"])
def test_the_matrix_sets_the_fitted_social_forces_desired_velocities(monkeypatch, scenario):
    """The matrix's distributed method hands the test episodes' measurements to the model before it tracks."""
    from dslearn.api import run

    seen = []
    orig = FittedSocialForce.begin_measured

    def spy(self, meas, visible, dt):
        seen.append((tuple(meas.shape), float(dt)))
        return orig(self, meas, visible, dt)

    monkeypatch.setattr(FittedSocialForce, "begin_measured", spy)
    run("task=matrix", "method=ekf_sfm_fit_hybrid", f"scenario={scenario}", "task.train_episodes=2",
        "task.test_episodes=2", "task.seeds=1", "model.refine_iters=0")
    assert seen and all(shape[1] == 2 for shape, _ in seen)
