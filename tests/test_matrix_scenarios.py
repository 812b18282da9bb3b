"""The matrix's scenarios: Liu et al.'s S1-S3 (``dslearn.sim.liu``) and the recorded data sets
(``dslearn.sim.recorded``: the shipped corridor, ETH/UCY ZARA1 where the data exist), and Liu's DGPT as a
matrix method against the Liu study's own tracker."""

from __future__ import annotations

import functools
import importlib.util
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.sparse.csgraph import minimum_spanning_tree

from dslearn import api
from dslearn.compose import build_cell_parts, build_scenario
from dslearn.data.ethucy import data_available
from dslearn.episodes import ScenarioSpec
from dslearn.errors import ConfigError
from dslearn.network import is_connected
from dslearn.sim import manoeuvres
from dslearn.sim.liu import FIELD_STREAM, ManoeuvreScenario
from dslearn.sim.recorded import RecordedScenario
from dslearn.sim.scenario import episode_streams, sample_split
from dslearn.streams import stream_seed

ROOT = Path(__file__).resolve().parents[1]
F64, CPU = torch.float64, torch.device("cpu")
LIU = ("liu_s1", "liu_s2", "liu_s3")


@functools.lru_cache(maxsize=None)
def _cfg(*overrides):
    return api.compose("task=matrix", *overrides)


def _liu(option: str, **keys) -> ManoeuvreScenario:
    """The option's scenario with some of its keys replaced (built directly, as the composition root does)."""
    c = _cfg("method=dgpt_gpoe", f"scenario={option}").scenario
    t = c.trajectory
    gen = functools.partial(getattr(manoeuvres, t._target_.rsplit(".", 1)[1]),
                            **{k: (list(v) if not isinstance(v, (int, float)) else v) for k, v in t.items()
                               if not k.startswith("_")})
    base = {k: c[k] for k in ("name", "steps", "dt", "num_sensors", "sensing_range", "area_size", "meas_std",
                              "comm_radius", "seed")}
    return ManoeuvreScenario(gen, **{**base, **keys})


# ---------------------------------------------------------------------------------------------- Liu S1-S3
@pytest.mark.parametrize("option", LIU)
def test_liu_spec_and_the_study_generator(option):
    """The declared spec, the field's sizes, and the trajectory generator of the Liu study's own scenario."""
    sc = build_scenario(_cfg("method=dgpt_gpoe", f"scenario={option}"))
    assert sc.spec == ScenarioSpec(option[4:], "position", 1, "pv2d", 1.0, 60, "m", True, "simulated")
    assert sc.owns_network and sc.area == (-500.0, 500.0, -500.0, 500.0)
    net = sc.network
    assert (net.num_nodes, net.num_sensors, net.sensing_range, net.meas_std) == (200, 200, 50.0, 2.0)
    assert is_connected(net.adjacency)
    liu = api.compose("experiment=liu_table1").task.scenario_params[option[4:]]
    assert dict(_cfg("method=dgpt_gpoe", f"scenario={option}").scenario.trajectory) == dict(liu)


def test_liu_field_is_drawn_per_seed():
    """The field is the seed's (uniform over the square), the same for S1-S3 and a redraw, new for a new seed."""
    a, b = _liu("liu_s1", seed=3), _liu("liu_s1", seed=3)
    assert torch.equal(a.network.positions, b.network.positions)
    assert torch.equal(a.network.positions, _liu("liu_s3", seed=3).network.positions)  # the field is not the path's
    assert not torch.equal(a.network.positions, _liu("liu_s1", seed=4).network.positions)
    g = torch.Generator().manual_seed(stream_seed(3, FIELD_STREAM))
    want = (torch.rand(1, 200, 2, generator=g, dtype=F64) - 0.5) * 1000.0
    assert torch.equal(a.network.positions, want[0])
    d = torch.cdist(want[0], want[0])
    assert torch.equal(a.network.adjacency, (d < 250.0) & ~torch.eye(200, dtype=torch.bool))


def test_liu_disconnecting_radius_is_refused_naming_the_radius_it_needs():
    """The refusal threshold is the longest edge of the field's minimum spanning tree (an independent MST)."""
    pos = _liu("liu_s1", seed=5).network.positions
    need = float(minimum_spanning_tree(torch.cdist(pos, pos).numpy()).max())
    with pytest.raises(ConfigError, match=r"scenario\.comm_radius") as e:
        _liu("liu_s1", seed=5, comm_radius=need * (1 - 1e-6))
    assert f"scenario.comm_radius >= {need:.4g}" in str(e.value) and "seed=5" in str(e.value)
    assert is_connected(_liu("liu_s1", seed=5, comm_radius=need * (1 + 1e-6)).network.adjacency)


@pytest.mark.parametrize("option,meas_std", [("liu_s1", 2.0), ("liu_s2", 5.0)])
def test_liu_measurements(option, meas_std):
    """Sensors within range (and only they) measure; the noise is zero-mean with std ``meas_std`` per axis
    (sample std within 3 standard errors, sigma / sqrt(2n))."""
    sc = _liu(option, meas_std=meas_std)
    net = sc.network
    ep = sc.sample(20, net, episode_streams(1, "test", 0, 20))
    pos = ep.states[..., :2]  # (B, T, 2)
    d = torch.linalg.vector_norm(net.positions[:, None, None] - pos[None], dim=-1)  # (S, B, T)
    assert torch.equal(ep.visible[..., 0], d <= 50.0)
    assert not ep.meas[~ep.visible].any()
    res = (ep.meas[..., 0, :] - pos[None])[ep.visible[..., 0]]  # (n, 2)
    n = res.shape[0]
    assert n > 1500
    se = meas_std / math.sqrt(2 * n)
    assert torch.all((res.std(0) - meas_std).abs() < 3 * se), (res.std(0), se)
    assert torch.all(res.mean(0).abs() < 3 * meas_std / math.sqrt(n))


@pytest.mark.parametrize("option", LIU)
def test_liu_truth_is_the_generator_on_the_episode_stream(option):
    """Episode i's states are the generator's positions and velocities drawn first from the episode's stream,
    the same whatever the number of episodes."""
    sc = _liu(option)
    eps = sc.sample(3, sc.network, episode_streams(7, "train", 0, 3))
    for i in range(3):
        g = torch.Generator().manual_seed(stream_seed(7, "train", i))
        p, v = sc.trajectory(1, 61, g, dt=1.0)
        assert torch.equal(eps.states[i], torch.cat([p[0], v[0]], -1))
    one = sc.sample(1, sc.network, episode_streams(7, "train", 0, 1))
    assert torch.equal(one.states[0], eps.states[0]) and torch.equal(one.meas[:, 0], eps.meas[:, 0])
    # the path stays in the area (centred on the origin)
    assert bool((eps.states[..., :2].abs() < 500.0).all())


# ------------------------------------------------------------------------------------------------- DGPT
def test_dgpt_cell_equals_the_liu_study_tracker_bit_for_bit():
    """DGPT (gPoE) in a matrix cell on liu_s1 = the Liu study's tracker (its plan: every rule, the centralised
    GP, its hyperparameters and S1 window) on the same episodes and measurements, bit for bit."""
    from dslearn.filters.dgpt import track

    cfg = _cfg("method=dgpt_gpoe", "scenario=liu_s1", "task.train_episodes=0", "task.test_episodes=2")
    scenario, net, method = build_cell_parts(cfg)
    test, train = sample_split(scenario, net, 0, 2, 0, F64, CPU)
    est = method.estimate(scenario, net, train, test.measurements, 0)
    study = api.build_study("experiment=liu_table1")
    p = study.plan()
    assert p.hyper == method.hyper and p.window["s1"] == method.window and p.gp_input == method.gp_input
    meas = test.meas[:, :, :, 0].transpose(0, 1)  # (B, S, T, 2), the study's layout (zeros where not detected)
    avail = test.visible[:, :, :, 0].transpose(0, 1)
    res = track(meas, avail, torch.full((2,), p.window["s1"]), gp_input=p.gp_input, aggregations=p.aggregations,
                centralised=p.centralised, hyper=p.hyper, dt=p.dt, delta=p.ucb_delta,
                normalise_beta=p.normalise_beta, grbcm_comm_points=p.grbcm_comm_points)
    assert "bcm" in res.methods and "standard_gp" in res.methods  # the study's several methods in one batch
    j = res.methods.index("gpoe")
    assert est.nodes == ["fusion"] and est.mean.shape == (1, 2, 61, 1, 2)
    assert torch.equal(est.mean[0, :, :, 0], res.upd_mean[:, j])
    assert torch.equal(torch.diagonal(est.cov[0, :, :, 0], dim1=-2, dim2=-1), res.upd_var[:, j])
    assert not torch.equal(res.upd_mean[:, j], res.upd_mean[:, res.methods.index("poe")])


def test_dgpt_refuses_an_information_form_fusion_up_front():
    """At composition (the run's up-front validation), naming the option and the allowed rules; and the method
    itself refuses a fusion that is not an aggregation rule."""
    from dslearn.compose import build_fusion
    from dslearn.methods.dgpt import DGPTMethod

    with pytest.raises(ConfigError, match=r"consensus=hybrid .*GP aggregation rule.*consensus=bcm\|gpoe\|poe\|rbcm"):
        api.compose("task=matrix", "method=dgpt_gpoe", "consensus=hybrid", "scenario=liu_s1")
    cfg = _cfg("method=ekf_lin_hybrid", "scenario=liu_s1")
    hybrid = build_fusion(cfg.consensus, build_scenario(cfg).network)
    assert type(hybrid).__name__ == "HybridConsensus" and cfg.consensus.name == "hybrid"
    with pytest.raises(ConfigError, match=r"consensus=hybrid is not a GP aggregation rule.*poe\|gpoe\|bcm\|rbcm"):
        DGPTMethod(hybrid, fusion_name="hybrid")


# ------------------------------------------------------------------------------------------- recorded data
CORRIDOR = ROOT / "dslearn" / "data" / "corridor" / "corridor.txt"


@functools.lru_cache(maxsize=None)
def _corridor(seed: int = 0) -> RecordedScenario:
    return build_scenario(_cfg("method=ekf_lin_hybrid", "scenario=corridor", f"seed={seed}"))


def _file_tracks(path: Path) -> dict[int, dict[int, np.ndarray]]:
    """ped -> frame -> (x, y), read with numpy (independent of the package's reader)."""
    a = np.loadtxt(path)
    out: dict[int, dict[int, np.ndarray]] = {}
    for f, p, x, y in a:
        out.setdefault(int(p), {})[int(f)] = np.array([x, y])
    return out


def test_corridor_file_is_the_generator_script_output():
    spec = importlib.util.spec_from_file_location("make_corridor", ROOT / "benchmarks" / "make_corridor.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert CORRIDOR.read_text() == mod.text(0)
    assert 300 <= CORRIDOR.read_text().count("\n") <= 1000


@pytest.mark.parametrize("split", ["train", "test"])
def test_corridor_episodes_are_the_file_positions(split):
    """Every episode's truth: the two pedestrians' rows of the file (0.4 s apart, the file's step), velocities
    by central differences (one-sided at the ends); the measurements: noise of std 0.2 within range."""
    sc = _corridor()
    n = sc.pool_size(split)
    assert (n, sc.pool_size("test" if split == "train" else "train")) == {"train": (71, 28), "test": (28, 71)}[split]
    ep = sc.sample(n, sc.network, episode_streams(0, split, 0, n), split=split)
    meta = sc.meta(split, n)
    tracks = _file_tracks(CORRIDOR)
    first = min(min(fr) for fr in tracks.values())
    for b in range(n):
        frames = first + 10 * (round(meta.t0[b] / 0.4) + np.arange(12))
        for a, ped in enumerate(int(p) for p in meta.peds[b].split(",")):
            want = np.stack([tracks[ped][int(f)] for f in frames])  # (12, 2)
            got = ep.states[b, :, 4 * a:4 * a + 4].numpy()
            # the file's rows up to round-off (the window's times and the rows' times are computed apart)
            np.testing.assert_allclose(got[:, :2], want, rtol=0, atol=1e-12)
            vel = np.concatenate([want[1:2] - want[:1], (want[2:] - want[:-2]) / 2, want[-1:] - want[-2:-1]]) / 0.4
            np.testing.assert_allclose(got[:, 2:], vel, rtol=0, atol=1e-10)
    pos = ep.states.unflatten(-1, (2, 4))[..., :2]  # (B, T, A, 2)
    d = torch.linalg.vector_norm(sc.network.positions[:, None, None, None] - pos[None], dim=-1)
    assert torch.equal(ep.visible, d < 8.0)
    res = (ep.meas - pos[None])[ep.visible]
    se = 0.2 / math.sqrt(2 * res.shape[0])
    assert res.shape[0] > 1000 and torch.all((res.std(0) - 0.2).abs() < 3 * se)


def test_corridor_pools_network_and_order():
    sc = _corridor()
    tr, te = sc.meta("train", 71), sc.meta("test", 28)
    assert tr.t1.max() <= te.t0.min() + 1e-9  # the time split: no moment in both pools
    xy = np.loadtxt(CORRIDOR)[:, 2:]
    (x0, y0), (x1, y1) = xy.min(0), xy.max(0)
    assert sc.area == (x0, x1, y0, y1)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2  # Yu's arena: one LiDAR at the middle of each side, bottom first
    np.testing.assert_allclose(sc.network.positions.numpy(), [[cx, y0], [x1, cy], [cx, y1], [x0, cy]], atol=1e-12)
    adj, d = sc.network.adjacency, torch.cdist(sc.network.positions, sc.network.positions)
    d.fill_diagonal_(math.inf)
    third = d.sort(1).values[:, 2:3]
    assert torch.equal(adj, adj.T) and bool(adj[d < third].all()) and is_connected(adj)  # each talks to its 2 nearest
    # test episode i is the same whatever the number asked; another seed orders the pools differently
    assert te.iloc[:5].equals(sc.meta("test", 5))
    other = _corridor(1)
    assert not other.meta("test", 28).equals(te) and sorted(other.meta("test", 28).t0) == sorted(te.t0)
    with pytest.raises(ConfigError, match=r"29 test episodes asked for, its test pool holds 28.*task\.test_episodes"):
        sc.sample(29, sc.network, episode_streams(0, "test", 0, 29), split="test")
    with pytest.raises(ValueError, match="split"):
        sc.sample(2, sc.network, episode_streams(0, "test", 0, 2))


def test_too_many_recorded_episodes_are_refused_at_composition(monkeypatch):
    """The pools' sizes are in the scenario's spec once it is built (at composition): a count above them is
    refused by the up-front check, one line naming the key, the count and the pool, without drawing an episode;
    the pools' own sizes pass (no off-by-one)."""
    from dslearn.app.precheck import precheck

    assert _corridor().spec.pools == (71, 28)
    for s in ("yu_two_agents", "liu_s1"):  # a simulator: any number
        assert build_scenario(_cfg("method=ekf_lin_hybrid", f"scenario={s}")).spec.pools is None

    def no_draw(*a, **k):
        raise AssertionError("an episode was drawn during the up-front check")

    monkeypatch.setattr(RecordedScenario, "chosen", no_draw)
    cell = ["task=matrix", "method=ekf_lin_hybrid", "scenario=corridor"]
    assert precheck([*cell, "task.train_episodes=500"]) == (
        "task.train_episodes=500: scenario corridor's training pool holds 71 episodes (ask for at most 71) "
        "or change scenario.episodes (how the recording is cut and split)")
    msg = precheck([*cell, "task.train_episodes=1", "task.test_episodes=29"])
    assert msg.startswith("task.test_episodes=29: scenario corridor's test pool holds 28 episodes") and "\n" not in msg
    assert precheck([*cell, "task.train_episodes=71", "task.test_episodes=28"]) is None
    # the matrix sweeper's own choice of cells refuses it too (a bad count, never an n/a cell), even for a method
    # that does not fit the scenario
    from hydra import compose, initialize_config_dir

    from dslearn.schemas.matrix import select_cells

    combos = [[f"method={m}", f"scenario={s}", "task.train_episodes=100"] for m in ("ekf_lin_hybrid", "fg_ekf")
              for s in ("yu_two_agents", "corridor")]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
        def comp(ov):
            return compose("config", overrides=["task=matrix", *ov])

        assert len(select_cells(combos[:1], comp)[0]) == 1  # yu: a simulator, 100 training episodes are fine
        for bad in (combos, combos[3:]):
            with pytest.raises(ConfigError, match=r"^task\.train_episodes=100: scenario corridor's training pool "
                                                  r"holds 71 episodes"):
                select_cells(bad, comp)


def test_dslearn_run_refuses_too_many_recorded_episodes_before_any_run(tmp_path):
    """The command: one cell exits 2 with the line and writes no run folder; a sweep with one such cell exits 2
    before any job starts (no sweep folder)."""
    import os
    import subprocess
    import sys

    run = [str(Path(sys.executable).parent / "dslearn-run")]
    env = {**os.environ, "CI": "1"}
    r = subprocess.run([*run, "task=matrix", "method=ekf_lin_hybrid", "scenario=corridor", "task.train_episodes=500",
                        f"hydra.run.dir={tmp_path / 'one'}"], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 2, r.stderr[-2000:]
    assert r.stderr.strip() == ("dslearn-run: configuration error: task.train_episodes=500: scenario corridor's "
                                "training pool holds 71 episodes (ask for at most 71) or change scenario.episodes "
                                "(how the recording is cut and split)"), r.stderr[-2000:]
    r = subprocess.run([*run, "-m", "experiment=matrix", "method=ekf_lin_hybrid,ekf_sfm_hybrid",
                        "scenario=yu_two_agents,corridor", "task.train_episodes=2", "task.test_episodes=30",
                        "hydra/launcher=basic", f"hydra.sweep.dir={tmp_path / 'sweep'}"], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, r.stderr[-2000:]
    assert r.stderr.strip().splitlines()[-1] == (
        "dslearn-run: configuration error: task.test_episodes=30: scenario corridor's test pool holds 28 episodes "
        "(ask for at most 28) or change scenario.episodes (how the recording is cut and split)")
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no run folder, no sweep folder, no outputs/


def _values(**change):
    c = _cfg("method=ekf_lin_hybrid", "scenario=corridor").scenario
    from omegaconf import OmegaConf

    v = OmegaConf.to_container(c, resolve=True)
    v.pop("_target_")
    for k, x in change.items():
        node, _, key = k.rpartition(".")
        (v[node] if node else v)[key] = x
    return v


def test_recorded_refusals(tmp_path):
    bad = tmp_path / "corridor.txt"
    lines = CORRIDOR.read_text().splitlines(keepends=True)
    lines[16] = "170.0\t3.0\tabc\t1.0\n"
    bad.write_text("".join(lines))
    with pytest.raises(ConfigError, match=rf"{bad}:17: non-numeric field"):
        RecordedScenario(**_values(**{"dataset.root": str(tmp_path)}))
    with pytest.raises(ConfigError, match=r"scenario\.dataset\.root='.*missing' does not exist"):
        RecordedScenario(**_values(**{"dataset.root": str(tmp_path / "missing")}))
    with pytest.raises(ConfigError, match=r"scenario\.data_root='.*missing' does not exist"):
        RecordedScenario(**_values(**{"dataset.root": None, "data_root": str(tmp_path / "missing")}))
    with pytest.raises(ConfigError, match=r"scenario\.episodes: unknown key\(s\) \['agent'\]"):
        RecordedScenario(**_values(**{"episodes.agent": 2}))
    with pytest.raises(ConfigError, match=r"scenario\.episodes\.split='scene'"):
        RecordedScenario(**_values(**{"episodes.split": "scene"}))
    with pytest.raises(ConfigError, match=r"scenario\.network\.k_nearest"):
        RecordedScenario(**_values(**{"network.k_nearest": 0}))
    with pytest.raises(ConfigError, match=r"none in the test pool"):
        RecordedScenario(**_values(**{"episodes.max_dist": 0.1}))
    shutil.copy(CORRIDOR, tmp_path / "mine.txt")  # a user's copy, named by root + files
    sc = RecordedScenario(**_values(**{"dataset.root": str(tmp_path), "dataset.files": ["mine.txt"]}))
    assert torch.equal(sc.episodes.states, _corridor().episodes.states)


@pytest.mark.parametrize("method", ["ekf_lin_hybrid", "dgpt_gpoe"])
def test_corridor_cell_runs(method):
    """A cell on the corridor: rows per node and test episode; the filters beat the raw sensor error
    (sigma sqrt(2) = 0.28 m)."""
    df = api.run("task=matrix", f"method={method}", "scenario=corridor", "task.train_episodes=2",
                 "task.test_episodes=4")
    r = df[df.metric == "rmse"]
    assert set(r.scenario) == {"corridor"} and len(r) == 4 * len(set(r.node))
    assert r.value.max() < 0.2


def test_zara1_without_its_data_is_refused_at_composition(monkeypatch, tmp_path):
    """Where the data folder is missing, composing the scenario (the run's up-front validation) fails naming it."""
    missing = tmp_path / "eth_ucy"
    monkeypatch.setenv("DSLEARN_ETHUCY_ROOT", str(missing))
    with pytest.raises(ConfigError, match=rf"DSLEARN_ETHUCY_ROOT={missing} .*does not exist; set scenario\.data_root="):
        api.compose("task=matrix", "method=ekf_lin_hybrid", "scenario=eth_zara1")
    with pytest.raises(ConfigError, match=rf"scenario\.data_root='{missing}' does not exist.*crowds_zara01\.txt"):
        api.compose("task=matrix", "method=ekf_lin_hybrid", "scenario=eth_zara1", f"scenario.data_root={missing}")


@pytest.mark.skipif(not data_available(), reason="the ETH/UCY data are absent")
def test_zara1_is_the_tracking_study_source():
    """eth_zara1's training episodes (truth, sensors and measurements) are the real-data tracking study's, bit for
    bit; its test pool is that study's test episodes."""
    from dslearn.schemas.datasets import load_scene
    from dslearn.sim.real import ArenaSettings, EpisodeRecipe, real_source

    sc = build_scenario(_cfg("method=ekf_lin_hybrid", "scenario=eth_zara1"))
    assert sc.spec == ScenarioSpec("eth_zara1", "position", 2, "pv2d", 0.4, 11, "m", True, "recorded", (233, 37))
    ntr, nte = sc.pool_size("train"), sc.pool_size("test")
    recipe = EpisodeRecipe(2, 11, 0.4, 3.0, 4, "mutual", 0.3, "time", 0.2, nte)
    data = real_source(load_scene("zara1", convention="physical"), recipe, ArenaSettings(), 0, ntr, F64, CPU)
    test, train = sample_split(sc, sc.network, 0, nte, ntr, F64, CPU)
    assert torch.equal(sc.network.positions, data.network.positions)
    assert torch.equal(sc.network.adjacency, data.network.adjacency)
    for a, b in ((train.states, data.train.states), (train.meas, data.train.meas), (train.visible, data.train.visible)):
        assert torch.equal(a, b)
    order = np.argsort(sc.pools["test"])
    assert torch.equal(test.states[torch.as_tensor(order)], data.test.states)
