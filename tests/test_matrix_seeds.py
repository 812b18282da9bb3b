"""``task.seeds``: a matrix cell's independent draws (:class:`dslearn.studies.matrix.MatrixCell`, the composition
root's ``draws`` slot), and the refusal of a cell without a method."""

from __future__ import annotations

import pandas as pd
import pytest
import torch

from dslearn import api
from dslearn.errors import ConfigError

CHEAP = ("task=matrix", "method=ekf_lin_hybrid", "task.train_episodes=0", "task.test_episodes=2")


def _values(df):
    cols = ["seed", "method", "scenario", "node", "episode", "metric", "value"]
    return df[df["metric"] != "runtime_s"][cols].reset_index(drop=True)


def test_two_seeds_are_the_runs_of_each_seed_on_yu():
    two = api.run(*CHEAP, "scenario=yu_two_agents", "task.seeds=2")
    assert sorted(two["seed"].unique()) == [0, 1]
    assert (two["metric"] == "runtime_s").sum() == 2  # one run time per draw
    one = api.run(*CHEAP, "scenario=yu_two_agents")  # seeds=1: the seed's single run
    assert set(one["seed"]) == {0}
    first = _values(two[two["seed"] == 0])
    pd.testing.assert_frame_equal(first, _values(one), check_exact=True)
    # the second draw is the run of seed 1, bit for bit (the world and the method rebuilt for it)
    other = api.run(*CHEAP, "scenario=yu_two_agents", "seed=1")
    pd.testing.assert_frame_equal(_values(two[two["seed"] == 1]), _values(other), check_exact=True)
    # and a different draw: other trajectories, other errors
    r0 = first[first["metric"] == "rmse"]["value"].to_numpy()
    r1 = _values(two[two["seed"] == 1]).query("metric == 'rmse'")["value"].to_numpy()
    assert r0.shape == r1.shape and not (r0 == r1).any()


def test_each_draw_redraws_liu_sensor_field_and_tracks():
    from dslearn.compose import build_study

    cfg = api.compose(*CHEAP, "scenario=liu_s1", "task.seeds=2")
    cell = build_study(cfg)
    assert cell.settings.seeds == 2 and cell.seed == 0
    s1, net1, m1 = cell.draws(1)
    s0, net0, m0 = cell.draws(0)  # the draw of seed 0 built anew equals the cell's own
    assert torch.equal(net0.positions, cell.scenario_network.positions)
    assert net1.positions.shape == net0.positions.shape == (200, 2)
    assert not torch.equal(net1.positions, net0.positions)  # a new sensor field
    # Yu's placement is the scenario's fixed layout (network.seed), the same in every draw
    yu = build_study(api.compose(*CHEAP, "scenario=yu_two_agents", "task.seeds=2"))
    assert torch.equal(yu.draws(1)[1].positions, yu.scenario_network.positions)
    # the run: two draws, different tracks (test episode 0's true start differs), numbers per draw
    from dslearn.sim.scenario import sample_split

    t0, _ = sample_split(s0, net0, 0, 1, 0, torch.float64, "cpu")
    t1, _ = sample_split(s1, net1, 1, 1, 0, torch.float64, "cpu")
    assert not torch.equal(t0.states, t1.states)
    df = api.run(*CHEAP[:3], "task.test_episodes=1", "scenario=liu_s1", "task.seeds=2")
    rmse = df[(df["metric"] == "rmse") & (df["node_kind"] == "sensor")].groupby("seed")["value"].mean()
    assert list(rmse.index) == [0, 1] and rmse[0] != rmse[1]


def test_seeds_must_be_at_least_one():
    with pytest.raises(ConfigError, match=r"task\.seeds"):
        api.compose(*CHEAP, "scenario=yu_two_agents", "task.seeds=0")


def test_a_cell_without_a_method_is_refused_up_front():
    from dslearn.app.precheck import precheck

    msg = precheck(["task=matrix", "scenario=liu_s1"])
    assert msg is not None and msg.startswith("task=matrix needs method=<preset>")
    assert "presets: " in msg and "ekf_lin_hybrid" in msg and "dgpt_rbcm" in msg
    assert precheck(["task=matrix", "method=ekf_lin_hybrid", "scenario=liu_s1"]) is None
    assert precheck(["task=matrix", "filter=ukf", "model=lin", "scenario=liu_s1"]) is None  # the parts chosen


def test_the_sweep_plan_counts_cells_seeds_and_estimates_by_hand():
    from omegaconf import OmegaConf

    from dslearn.studies.matrix import JOB_OVERHEAD_S, SECONDS_PER_EPISODE, plan_text

    records = [dict(method="ekf lin hybrid", scenario="s1", job=0), dict(method="dgpt rbcm", scenario="yu", job=1),
               dict(method="ekf lin hybrid", scenario="jiang", job=None),  # n/a: not counted
               dict(method="never measured", scenario="yu", job=2)]
    task = OmegaConf.create({"seeds": 2, "train_episodes": 4, "test_episodes": 6})
    text = plan_text(records, task, workers=2)
    # 2 seeds x (overhead + rate x 10 episodes) for each of the two measured cells, over 2 workers
    sec = 2 * (2 * JOB_OVERHEAD_S + 10 * (SECONDS_PER_EPISODE[("ekf lin hybrid", "s1")]
                                         + SECONDS_PER_EPISODE[("dgpt rbcm", "yu")])) / 2
    assert text.startswith("matrix: 3 cells x 2 seed(s) = 6 draws of 4 training + 6 test episodes; ")
    assert f"estimated {sec / 60:.1f} min of wall time on 2 worker(s) for the 2 measured cells" in text
    assert "plus 1 cells never measured (not estimated)" in text and "one draw of one cell at a time" in text
