"""ETH/UCY tracking study: episode extraction, arena network, SFM fit, end-to-end runs, config errors."""

import math
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException

from dslearn.schemas.core import CONF_DIR
from dslearn.data.episodes import _groups, extract_episodes, finite_difference_velocity, split_episodes
from dslearn.data.ethucy import data_available
from dslearn.errors import ConfigError
from dslearn.models.social_force import SocialForce
from dslearn.network import is_connected
from dslearn.learning import sfm_fit
from dslearn.learning.lstm import lstm_windows
from dslearn.models.gp_backends.exact import OnlineGP
from dslearn.models.gp_backends.means import ConstantVelocityMean
from dslearn.schemas import validate_task
from dslearn import api
from dslearn.sim.real import ArenaSettings, Data, EpisodeRecipe, arena_network, perimeter_positions, scene_extent
from dslearn.sim.scenario import measure
from dslearn.studies import ethucy_tracking as et
from dslearn.types import StepContext


# ---------------------------------------------------------------------------------------------
# a hand-made scene
# ---------------------------------------------------------------------------------------------
def _track(ped, steps, p0, v, dt, file="toy.txt"):
    s = np.asarray(steps)
    t = s * dt
    return pd.DataFrame({"file": file, "ped": ped, "step": s, "t": t, "x": p0[0] + v[0] * t, "y": p0[1] + v[1] * t})


def toy_scene(dt=0.4):
    """Peds 1+2: a walking pair 1 m apart (steps 0..30). Ped 3: alone 10 m away (0..30).
    Ped 4: next to the pair but only for steps 0..3. Peds 5+6: a pair 4 m apart (0..30), far from all."""
    parts = [
        _track(1, range(31), (0.0, 0.0), (1.0, 0.5), dt),
        _track(2, range(31), (0.0, 1.0), (1.0, 0.5), dt),
        _track(3, range(31), (0.0, 11.0), (-0.8, 0.0), dt),
        _track(4, range(4), (0.5, 0.5), (1.0, 0.0), dt),
        _track(5, range(31), (30.0, 0.0), (0.0, 1.2), dt),
        _track(6, range(31), (34.0, 0.0), (0.0, 1.2), dt),
    ]
    df = pd.concat(parts, ignore_index=True).sort_values(["step", "ped"]).reset_index(drop=True)
    return SimpleNamespace(name="toy", dt=dt, df=df)


def test_episode_windows_presence_and_interaction():
    sc = toy_scene()
    eps = extract_episodes(sc, num_agents=2, steps=5, max_dist=3.0, stride=5)
    # windows start at t = 0, 2, ..., 10 (steps 0, 5, ..., 25): 6 windows, one group each
    assert len(eps) == 6
    assert (eps.meta["peds"] == "1,2").all()
    np.testing.assert_allclose(eps.meta["t0"], 0.4 * 5 * np.arange(6), atol=1e-12)
    assert eps.states.shape == (6, 6, 8)
    # the 4 m pair joins once max_dist allows it; ped 3 (alone) and ped 4 (leaves) never do
    wide = extract_episodes(sc, num_agents=2, steps=5, max_dist=5.0, stride=5)
    assert set(wide.meta["peds"]) == {"1,2", "5,6"} and len(wide) == 12
    assert not any("3" in p.split(",") or "4" in p.split(",") for p in wide.meta["peds"])
    # ped 4 is present (and nearest to ped 1) in the first window of 2 steps only: then {1, 4}
    short = extract_episodes(sc, num_agents=2, steps=2, max_dist=3.0, stride=3)
    first = short.meta[short.meta["t0"] == 0.0]
    assert set(first["peds"]) == {"1,4"}
    assert (short.meta[short.meta["t0"] > 0.0]["peds"] == "1,2").all()


def test_episode_truth_is_exact_for_linear_motion_and_resampling():
    sc = toy_scene()
    for dt in (0.4, 0.2, 0.6):  # native, finer and non-multiple resampling
        eps = extract_episodes(sc, num_agents=2, steps=6, dt=dt, max_dist=3.0, stride=6)
        eps = eps.select(np.nonzero((eps.meta["peds"] == "1,2").to_numpy())[0])  # (at dt=0.2 ped 4 joins window 0)
        assert len(eps) >= 3
        st = eps.states.unflatten(-1, (2, 4)).numpy()  # (B, K+1, A, 4)
        t = eps.meta["t0"].to_numpy()[:, None] + dt * np.arange(7)[None]
        for a, (p0, v) in enumerate((((0.0, 0.0), (1.0, 0.5)), ((0.0, 1.0), (1.0, 0.5)))):
            np.testing.assert_allclose(st[:, :, a, 0], p0[0] + v[0] * t, atol=1e-12)
            np.testing.assert_allclose(st[:, :, a, 1], p0[1] + v[1] * t, atol=1e-12)
            np.testing.assert_allclose(st[:, :, a, 2], v[0], atol=1e-12)
            np.testing.assert_allclose(st[:, :, a, 3], v[1], atol=1e-12)
    # finite differences: central inside, one-sided at the ends
    p = np.array([0.0, 1.0, 4.0, 9.0])
    np.testing.assert_allclose(finite_difference_velocity(p, 1.0), [1.0, 2.0, 4.0, 5.0])


def test_min_speed_and_three_agent_groups():
    sc = toy_scene()
    assert len(extract_episodes(sc, 2, 5, max_dist=3.0, stride=5, min_speed=1.2)) == 0  # pair walks at 1.118 m/s
    assert len(extract_episodes(sc, 2, 5, max_dist=3.0, stride=5, min_speed=1.1)) == 6
    pos = np.array([[0, 0], [1, 0], [0, 1], [10, 10], [11, 10], [30, 30.0]])
    assert _groups(pos, 3, 2.0, "mutual") == [(0, 1, 2)]
    assert _groups(pos, 2, 2.0, "mutual") == [(0, 1), (3, 4)]  # 0's nearest: 1 and 2 tied, 1 by index
    assert _groups(pos, 2, 2.0, "closest") == [(0, 1), (3, 4)]


def test_time_split_has_no_overlap():
    sc = toy_scene()
    eps = extract_episodes(sc, 2, 3, max_dist=5.0, stride=2)
    tr, te = split_episodes(eps, "time", 0.25, seed=3)
    assert len(tr) and len(te) and not set(tr) & set(te)
    bound = 0.75 * 12.0
    assert (eps.meta["t1"].to_numpy()[tr] <= bound + 1e-9).all()
    assert (eps.meta["t0"].to_numpy()[te] >= bound - 1e-9).all()
    tr2, _ = split_episodes(eps, "time", 0.25, seed=4)
    assert sorted(tr) == sorted(tr2) and list(tr) != list(tr2)  # same set, seeded order


# ---------------------------------------------------------------------------------------------
# arena network over a scene extent
# ---------------------------------------------------------------------------------------------
def test_arena_network_placement_connectivity_and_range():
    ext = scene_extent(torch.tensor([[0.0, 0.0], [10.0, 6.0], [3.0, 2.0]]))
    assert ext == (0.0, 10.0, 0.0, 6.0)
    pos = perimeter_positions(ext, 4)
    torch.testing.assert_close(pos, torch.tensor([[5.0, 0.0], [10.0, 3.0], [5.0, 6.0], [0.0, 3.0]], dtype=torch.float64))
    net = arena_network(ext, 4, k_nearest=2, sensing_range=4.0, meas_std=0.2)
    assert net.num_nodes == 4 and net.num_sensors == 4 and is_connected(net.adjacency)
    assert net.adjacency.sum(1).tolist() == [2, 2, 2, 2]  # a ring: each talks to its 2 nearest
    # one agent at (5, 1): within 4 m of the bottom sensor only; another at (1, 3): left sensor only
    states = torch.tensor([[5.0, 1.0, 0.0, 0.0, 1.0, 3.0, 0.0, 0.0]], dtype=torch.float64).reshape(1, 1, 8).expand(2000, 2, 8)
    ep = measure(states, net, torch.Generator().manual_seed(0))
    vis = ep.visible[:, 0, 0]  # (S, A)
    assert vis.tolist() == [[True, False], [False, False], [False, False], [False, True]]
    assert (ep.meas[~ep.visible] == 0).all()
    err = ep.meas[0, :, :, 0] - torch.tensor([5.0, 1.0], dtype=torch.float64)
    assert abs(float(err.std()) - 0.2) < 0.01 and abs(float(err.mean())) < 0.01
    with pytest.raises(ConfigError, match="k_nearest"):
        arena_network((0, 40, 0, 1), 6, k_nearest=1)  # pairs of neighbours: disconnected
    with pytest.raises(ConfigError, match="sensing_range"):
        arena_network(ext, 4, sensing_range=0.0)


# ---------------------------------------------------------------------------------------------
# SFM
# ---------------------------------------------------------------------------------------------
def _sfm_data(tau, alpha, beta, n=24, k=11, dt=0.4, seed=0):
    g = torch.Generator().manual_seed(seed)
    p1 = torch.rand(n, 2, generator=g, dtype=torch.float64) * 1.5
    p2 = p1 + torch.tensor([3.0, 0.3]) + torch.rand(n, 2, generator=g, dtype=torch.float64) * 0.5
    v1 = torch.tensor([1.0, 0.1]) + 0.2 * torch.rand(n, 2, generator=g, dtype=torch.float64)
    v2 = torch.tensor([-1.0, 0.0]) + 0.2 * torch.rand(n, 2, generator=g, dtype=torch.float64)
    x = torch.cat([p1, v1, p2, v2], -1)
    model = sfm_fit.episode_social_force(2, tau, alpha, beta).set_desired(torch.stack([v1, v2], 1))
    traj = [x]
    for _ in range(k):
        x = model(x, StepContext(dt))
        traj.append(x)
    return torch.stack(traj, 1)


def test_episode_sfm_is_the_core_social_force():
    """The real-data study's SFM is the core model (bounded interactions included); per-episode
    desired velocities broadcast like one shared set, episode by episode."""
    desired = torch.tensor([[[1.0, -1.0], [-1.0, -1.0]], [[0.5, 0.2], [-0.3, 0.9]], [[0.0, 1.0], [1.0, 0.0]]], dtype=torch.float64)
    ours = sfm_fit.episode_social_force(2, 0.25, 6.0, 5.0).set_desired(desired)
    assert isinstance(ours, SocialForce)
    x = torch.randn(3, 8, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    x[1, 4:6] = x[1, 0:2] + 0.05  # two agents nearly on one point: still finite
    out = ours(x, StepContext(0.25))
    assert torch.isfinite(out).all()
    for b in range(3):
        core = SocialForce(desired[b].tolist(), 0.25, 6.0, 5.0)
        torch.testing.assert_close(out[b], core(x[b], StepContext(0.25)), rtol=0, atol=1e-14)


def test_sfm_fit_recovers_known_parameters():
    true = dict(tau=0.7, alpha=2.5, beta=0.8)
    states = _sfm_data(**true)
    # desired velocity = velocity in the t=0 state, as the simulation's initial velocity
    params, loss = sfm_fit.fit_social_force(states, 0.4, 1, refine_iters=300, refine_lr=0.05)
    # what the test is about: the parameters (the final roll-out loss depends on the CPU's
    # floating-point path: 0.009 on one machine where the parameters were within 0.7 %)
    assert math.isfinite(loss)
    for k, v in true.items():
        assert abs(params[k] - v) / v < 0.05, (k, params[k], v)


# ---------------------------------------------------------------------------------------------
# end to end
# ---------------------------------------------------------------------------------------------
def _flat(d: dict, prefix: str = "task.") -> list[str]:
    """``{"network": {"k_nearest": 0}}`` -> ``["task.network.k_nearest=0"]`` (Hydra overrides; the keys of
    ``task.model_keys``, a mapping with no keys of its own, are added: ``+task.model_keys.lstm.epochs=2``)."""
    out = []
    for k, v in d.items():
        plus = "+" if prefix.startswith("task.model_keys.") and not prefix.startswith("+") else ""
        if isinstance(v, dict):
            out += _flat(v, f"{prefix}{k}.")
        elif isinstance(v, (list, tuple)):
            out.append(f"{plus}{prefix}{k}=[" + ",".join(str(x) for x in v) + "]")
        else:
            out.append(f"{plus}{prefix}{k}={'null' if v is None else v}")
    return out


SMALL = {"train_episodes": 4, "test_episodes": 3, "plot_episodes": 2}
#: the keys of the small run's model options (task.model_keys), for the entries a run lists
SMALL_KEYS = {"lstm": {"epochs": 2}, "social_lstm": {"epochs": 2},
              "sfm_fit": {"refine_iters": 3, "tau_grid": [0.5, 2.0], "alpha_grid": [0.0, 1.0], "beta_grid": [1.0]}}
SMALL_KEYS["sfm"] = SMALL_KEYS["sfm_fit"]
DEFAULT_MODELS = ["gp", "gp_cv", "lin", "sfm_fit", "lstm"]  # conf/task/ethucy_tracking.yaml


def compose_cfg(*groups, **task):
    """The composed ``experiment=real_tables`` config (root group overrides in ``groups``), with the small
    run's model keys for the entries of ``task.models`` (``model_keys`` in ``task`` add to them)."""
    models = task.get("models", DEFAULT_MODELS)
    keys = {m: dict(SMALL_KEYS[m]) for m in models if m in SMALL_KEYS}
    for m, k in task.pop("model_keys", {}).items():
        keys[m] = {**keys.get(m, {}), **k}
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return compose("config", overrides=["experiment=real_tables", "progress=false", "study=test", *groups,
                                            *_flat(SMALL), *_flat(task), *_flat({"model_keys": keys})])


def tiny_cfg(*groups, **task):
    """The tiny run's config, composed and checked as ``dslearn-run`` does before any work."""
    cfg = compose_cfg(*groups, **task)
    validate_task(cfg)
    return cfg


@pytest.mark.skipif(not data_available(), reason="ETH/UCY data root missing")
def test_tables_end_to_end_on_a_real_scene(tmp_path):
    cfg = tiny_cfg(scenes=["zara1"])
    df = api.build_study(cfg).run()
    for col in ("model", "consensus", "node", "episode", "metric", "value", "scene", "train_episodes", "data"):
        assert col in df.columns
    sens = df[df["node_kind"] == "sensor"]
    got = set(zip(sens["model"], sens["metric"]))
    for m in ("gp_increment", "gp_increment_cv", "lin", "sfm_fit", "lstm"):  # every model tracks and predicts
        assert {(m, "track_err"), (m, "pred_err")} <= got
    assert sens["value"].notna().all() and (sens["value"] >= 0).all()
    assert (sens["train_episodes"] == 4).all() and len(sens[(sens.model == "lin") & (sens.metric == "pred_err")]) == 4 * 3
    params = df[df.node_kind == "param"].set_index("metric")["value"]
    assert {"sfm_fit_tau", "sfm_fit_alpha", "sfm_fit_beta", "sfm_fit_fit_loss", "lstm_train_loss", "lstm_q_pos_std",
            "lstm_q_vel_std"} <= set(params.index)
    traj = df[df["metric"].isin(["pred_x", "pred_y"])]
    assert set(traj["model"]) == {"truth", "gp_increment", "gp_increment_cv", "lin", "sfm_fit", "lstm"}
    assert set(traj["episode"]) == {0, 1} and set(traj["step"]) == set(range(12))
    # LIN's first predicted step equals the truth at t=1 (v0 is the forward difference)
    piv = traj.pivot_table(index=["model", "episode", "agent", "step"], columns="metric", values="value")
    np.testing.assert_allclose(piv.loc["lin"].xs(1, level="step").to_numpy(), piv.loc["truth"].xs(1, level="step").to_numpy(), atol=1e-9)
    # pred_err by hand from the stored trajectories: mean over steps 1..K and agents of the position error
    lin_err = sens[(sens.model == "lin") & (sens.metric == "pred_err") & (sens.node == "sensor1")].set_index("episode")["value"]
    for ep in (0, 1):
        d = piv.loc["lin"].xs(ep, level="episode") - piv.loc["truth"].xs(ep, level="episode")
        d = d[d.index.get_level_values("step") >= 1]
        assert lin_err[ep] == pytest.approx(float(np.hypot(d["pred_x"], d["pred_y"]).mean()), rel=1e-9)
    from dslearn.report import summarize

    df2 = df.assign(study="test", task="ethucy_tracking")
    from dslearn.reports.ethucy_tracking import report

    text = report(df2, summarize(df2), tmp_path)
    assert "Table III" in text and "ZARA1" in text  # the data set's label (conf/dataset/zara1.yaml) and (tmp_path / "ethucy_table3.md").exists() and (tmp_path / "ethucy_fig4_trajectories.png").exists()


#: ETH test episodes (seed 0, the experiment's 25) where the learned filters left the track when the GP was
#: linearised at the belief's mean (task.gp_inputs=mean): 3 and 18 (12 m and 47 m after 128 training
#: episodes, 4-75x LIN after 32), and 4 and 13, the increment GP's worst relative to LIN after the fix
ETH_WORST = [3, 4, 13, 18]


@pytest.mark.skipif(not data_available(), reason="ETH/UCY data root missing")
def test_learned_filters_stay_on_the_track_of_the_worst_eth_episodes():
    """Each GP of the study (``model=gp_increment``: ``gp`` and ``gp_cv``; ``model=gp``: the zero-mean GP as
    printed) learns online from 32 ETH training episodes and tracks the worst test episodes to the end: no
    learned model may do worse than the motion prior it starts from (the same GP without data) by more than
    20 % on any episode, and each stays within a factor of LIN per episode: 1.5 for the constant-velocity
    prior mean (whose prior is LIN with process noise sigma_f^2), 3 for the identity prior mean (whose
    stand-still prior alone is 2.7x LIN on episode 4)."""
    from dslearn.metrics import tracking_metrics
    from dslearn.models import ConstantVelocity

    runs = {}
    for group in ("gp_increment", "gp"):
        cfg = tiny_cfg(f"model={group}", scenes=["eth"], train_episodes=32, test_episodes=25)
        assert cfg.task.gp_inputs == "belief"  # the study's default
        study = api.build_study(cfg)
        torch.manual_seed(0)
        data = study.real_data("eth", 0, 32)
        fusion = study.fusion(data.network)
        test = data.test.select(ETH_WORST)

        def err(alg):
            res = alg.estimate(test.measurements)
            assert torch.isfinite(res.mean).all()
            return tracking_metrics(res, test.states)["track_err"].mean(0)  # (B,): sensor average

        lin = err(study.learner(ConstantVelocity(2, 0.1), data, fusion))
        gps = {e.label: e.make for e in study.ethucy_tracking_models if e.entry in ("gp", "gp_cv")}
        for label, make in gps.items() if group == "gp_increment" else [(group, gps[group])]:
            prior = err(study.learner(make(data.scenario, data.network), data, fusion))
            alg = study.learner(make(data.scenario, data.network), data, fusion)
            et.train_online(alg, data, 32)
            assert alg.model.gp.n == 32 * 11 and alg.model.inputs == "belief"
            runs[label] = (err(alg), prior, lin)
    for name, (learned, prior, lin) in runs.items():
        assert (learned <= 1.2 * prior).all(), (name, learned, prior)
        if name != "gp":  # the zero-mean GP's prior is the origin: 3-15x LIN on ETH, whatever it learns
            factor = 1.5 if name.endswith("_cv") else 3.0
            assert (learned <= factor * lin).all(), (name, learned / lin)


def test_data_size_end_to_end_on_synthetic(tmp_path):
    cfg = tiny_cfg(protocol="data_size", scenes=[], synthetic=True, data_sizes=[2, 4], seeds=2, plot_episodes=0,
                   models=["gp", "gp_cv", "lstm"])
    df = api.build_study(cfg).run()
    sens = df[(df["node_kind"] == "sensor") & (df["metric"] == "pred_err")]
    assert set(sens["model"]) == {"gp_increment", "gp_increment_cv", "lstm"}
    assert set(sens["train_episodes"]) == {2, 4} and set(sens["seed"]) == {0, 1}
    assert (sens["data"] == "synthetic").all() and sens["value"].notna().all()
    from dslearn.reports.ethucy_tracking import data_size_table, real_report

    tab = data_size_table(df)
    assert set(tab["seeds"]) == {2} and len(tab) == 6
    real_report(df, pd.DataFrame(), tmp_path)
    assert (tmp_path / "ethucy_fig5_gp_vs_lstm.png").exists()


@pytest.mark.parametrize(
    "override,field",
    [
        ({"protocol": "forecast"}, "task.protocol"),
        ({"agents": 1}, "task.agents"),
        ({"split": "scene"}, "task.split"),
        ({"split": "sideways"}, "task.split"),
        ({"network": {"sensing_range": 0}}, "task.network.sensing_range"),
        ({"network": {"k_nearest": 0}}, "task.network.k_nearest"),
        ({"model_keys": {"sfm_fit": {"train_on": "oracle"}}}, "entry 'sfm_fit': model.train_on"),
        ({"model_keys": {"sfm_fit": {"tau_grid": [0.5, -1.0]}}}, r"model.tau_grid\[1\]"),
        ({"model_keys": {"sfm_fit": {"desired_steps": 13}}}, "model.desired_steps"),
        ({"model_keys": {"sfm_fit": {"fit_on": "truth"}}}, r"unknown key\(s\) \['fit_on'\]"),
        ({"model_keys": {"lstm": {"pooling": "max"}}}, "entry 'lstm': model.pooling"),
        ({"model_keys": {"lstm": {"pred_len": 20}}}, "model.pred_len"),
        ({"model_keys": {"lstm": {"schedule": "sometimes"}}}, "model.schedule"),
        ({"models": ["lin"], "model_keys": {"lstm": {"epochs": 3}}}, "task.model_keys.lstm"),
        ({"models": ["mlp"]}, "task.models"),
        ({"models": ["lin", "lin"]}, "task.models"),
        ({"models": ["lstm"], "train_episodes": 1}, "task.train_episodes gives 1"),  # residual Q holds one out
        ({"train_on": "oracle"}, "task.train_on"),
        ({"test_fraction": 1.5}, "task.test_fraction"),
        ({"scenes": ["mars"]}, "task.scenes"),
        ({"criterion": "nearest"}, "task.criterion"),
        ({"protocol": "data_size", "data_sizes": [1, 4]}, "task.data_sizes gives 1"),
        ({"protocol": "data_size", "data_sizes": [0]}, "task.data_sizes"),
        ({"datasets": {"zara1": {"frame_step": 0}}}, "task.datasets.zara1.frame_step"),
        ({"gp_inputs": "sigma_points"}, "task.gp_inputs"),
    ],
)
def test_bad_config_is_a_clear_error(override, field):
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        tiny_cfg(**override)


def test_unknown_keys_and_wrong_types_fail_at_composition():
    for over, key in (({"bogus": 1}, "task.bogus"), ({"network": {"radius": 3}}, "task.network.radius"),
                      ({"steps": "eleven"}, "task.steps"), ({"datasets": {"eth": {"fps": "fast"}}}, "task.datasets.eth.fps")):
        with pytest.raises(ConfigCompositionException, match=key.replace(".", r"\.")):
            compose_cfg(**over)


def test_bad_root_groups_are_clear_errors():
    with pytest.raises(ConfigError, match=r"consensus\.name"):
        tiny_cfg("consensus=centralized")
    with pytest.raises(ConfigError, match=r"two entries the same label \['lin', 'gp_increment_cv', 'lin'"):
        tiny_cfg("model=lin")  # the root model (entry gp) is LIN, and so is the entry lin
    tiny_cfg("model=lin", models=["gp", "sfm"])  # the root model may be any model that runs on real data
    tiny_cfg("model=sfm", models=["lin", "sfm"])  # not listed (no gp entry): the root model is not read
    with pytest.raises(ConfigError, match=r"entry 'gp' \(the root model group\): model\._target_=.*SocialForce.*sfm_fit"):
        tiny_cfg("model=sfm", models=["gp"])  # the true social force: parameters of the simulation
    # the belief average exists for the exact and window GPs only (closed-form Jacobian)
    for group in ("model=gp_sgpr", "model=gp_ssgp", "model.jacobian=autograd"):
        with pytest.raises(ConfigError, match=r"task\.gp_inputs=belief.*task\.gp_inputs=mean"):
            tiny_cfg(group)
        tiny_cfg(group, gp_inputs="mean")
    with pytest.raises(ConfigError, match=r"task\.gp_inputs=belief.*aggregated"):
        tiny_cfg("model=gp_increment_rbcm", models=["gp", "lin"])
    tiny_cfg("model=gp_window")


def test_constant_velocity_mean_gp_falls_back_to_lin():
    from dslearn.models import ConstantVelocity

    gp = OnlineGP(3, 8, 8, 1.0, 2.0, 0.5, mean=ConstantVelocityMean(0.4))
    x = torch.randn(3, 5, 8, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    f = ConstantVelocity(2).matrix(0.4)
    mean, var, jac = gp.predict(x)
    torch.testing.assert_close(mean, x @ f.T)  # no data: exactly the CV step
    torch.testing.assert_close(jac, f.expand(3, 5, 8, 8))
    # one stored transition that deviates from CV: the prediction there moves towards it
    y = x[:, 0] @ f.T + 0.3
    gp.append(x[:, 0], y)
    m2, _, _ = gp.predict(x[:, :1])
    assert ((m2[:, 0] - x[:, 0] @ f.T) > 0.1).all() and ((m2[:, 0] - x[:, 0] @ f.T) < 0.3).all()


def test_cm_fused_ignores_uninformed_nodes():

    ext = (0.0, 10.0, 0.0, 6.0)
    net = arena_network(ext, 4, k_nearest=2, sensing_range=3.0, meas_std=0.2)
    # two agents walking along the bottom, seen by the bottom sensor only at t = 0
    k = 6
    t = 0.4 * torch.arange(k + 1, dtype=torch.float64)
    a1 = torch.stack([4.0 + 0.5 * t, 0.5 + 0 * t, 0.5 + 0 * t, 0 * t], -1)
    a2 = torch.stack([5.0 + 0.5 * t, 1.0 + 0 * t, 0.5 + 0 * t, 0 * t], -1)
    states = torch.cat([a1, a2], -1).unsqueeze(0)
    ep = measure(states, net, torch.Generator().manual_seed(0))
    assert ep.visible[0, 0, 0].all() and not ep.visible[1:, 0, 0].any()
    study = api.build_study(tiny_cfg())
    data = Data("toy", "real", ep, ep, net, StepContext(0.4), ext, 2, {})
    fused = study.cm_fused(data, ep)
    err0 = (fused[0, 0].unflatten(-1, (2, 4))[:, :2] - states[0, 0].unflatten(-1, (2, 4))[:, :2]).norm(dim=-1)
    assert (err0 < 0.7).all()  # a plain node average would sit ~2 m off (3 of 4 nodes at the prior's mean)


def test_lstm_early_stopping_holds_out_whole_episodes():
    """Windows carry their episode; early stopping validates on held-out episodes only."""
    from dslearn.models.lstm import holdout_split

    fused = torch.randn(5, 13, 8, dtype=torch.float64)
    win, groups = lstm_windows(fused, 2, 10)
    assert win.shape == (5 * 2, 12, 2, 2) and groups.tolist() == [0, 1, 2, 3, 4] * 2
    tr, va = holdout_split(win, groups, 0.4, seed=0)
    assert len(tr) + len(va) == len(win) and len(va) == 2 * 2  # 2 of 5 episodes, both windows each
    # every validation window belongs to a held-out episode: none of its windows is in training
    va_set = {tuple(w.flatten().tolist()) for w in va}
    assert not va_set & {tuple(w.flatten().tolist()) for w in tr}
    cfg = tiny_cfg(protocol="data_size", scenes=[], synthetic=True, data_sizes=[4], seeds=1, plot_episodes=0,
                   models=["gp", "gp_cv", "lstm"], model_keys={"lstm": {"schedule": "early_stopping", "epochs": 3, "patience": 1}})
    df = api.build_study(cfg).run()
    assert set(df[df["metric"] == "pred_err"]["model"]) == {"gp_increment", "gp_increment_cv", "lstm"}



# ---------------------------------------------------------------------------------------------
# the models are model options; observation and filter are the root groups'
# ---------------------------------------------------------------------------------------------
def _rows(df, model, metric="track_err"):
    r = df[(df.model == model) & (df.metric == metric) & (df.node_kind == "sensor")]
    return r.sort_values(["node", "episode"])["value"].to_numpy()


@pytest.fixture(scope="module")
def zara1():
    """A tiny zara1 source (4 training, 3 test episodes) and the small run's study."""
    if not data_available():
        pytest.skip("ETH/UCY data root missing")
    study = api.build_study(tiny_cfg(scenes=["zara1"], models=["lin", "sfm", "lstm"]))
    torch.manual_seed(0)
    return study, study.real_data("zara1", 0, 4)


def test_lin_sfm_lstm_rows_equal_the_recipes_built_by_hand(zara1):
    """The entries lin, sfm (= sfm_fit, labelled sfm) and lstm, composed from their options and learned through
    the offline hook, give the rows of the study's recipe built by hand from its parts: LIN with sigma 0.1 and
    the linear sensors; the social force fitted on the true training tracks (fit_episode_social_force); the LSTM
    trained on the CM-fused training tracks (train_lstm_model with the run's seed, the paper's fixed schedule)."""
    from dslearn.learning.lstm import train_lstm_model
    from dslearn.metrics import prediction_error, tracking_metrics
    from dslearn.models import ConstantVelocity, LinearPositionObservation
    from dslearn.learning.online import OnlineLearner

    study, data = zara1
    df = study.protocol_tables(data, 0)
    fusion = study.fusion(data.network)

    def by_hand(model, metric):
        alg = OnlineLearner(data.network, model, LinearPositionObservation(data.network.meas_std), fusion, data.ctx,
                            init=lambda ep: study.initial_belief(data, ep, fusion), learn_gate_std=2.0)
        if metric == "pred_err":
            err = prediction_error(model, data.test.states, data.network.num_nodes, data.ctx, per_node=False)
        else:
            err = tracking_metrics(alg.estimate(data.test.measurements), data.test.states)[metric]
        return err[: data.network.num_sensors].cpu().numpy().ravel()  # (sensor, episode) as the rows are sorted

    lin = ConstantVelocity(2, 0.1)
    c = SimpleNamespace(desired_steps=1, grid=SimpleNamespace(tau=[0.5, 2.0], alpha=[0.0, 1.0], beta=[1.0]),
                        refine_iters=3, refine_lr=0.05, noise_std=0.1)
    sfm, params, loss = sfm_fit.fit_episode_social_force(data.train.states.cpu(), data.test.states, data.ctx.dt, c)
    fused = study.cm_fused(data, data.train)
    kw = {"embed": 64, "hidden": 64, "obs_len": 2, "pred_len": 10, "pooling": "none", "grid": 4, "neighbourhood": 2.0,
          "schedule": "fixed", "epochs": 2, "batch_size": 8, "lr": 1e-3}
    lstm, _ = train_lstm_model(kw, 2, data.ctx.dt, lstm_windows(fused, 2, 10), 0, torch.float64, torch.device("cpu"))
    for label, model in (("lin", lin), ("sfm", sfm)):
        for metric in ("track_err", "nees", "pred_err"):
            np.testing.assert_array_equal(_rows(df, label, metric), by_hand(model, metric), err_msg=f"{label} {metric}")
    np.testing.assert_array_equal(_rows(df, "lstm", "pred_err"), by_hand(lstm, "pred_err"))
    p = df[df.node_kind == "param"].set_index("metric")["value"]
    assert [p[f"sfm_{k}"] for k in ("tau", "alpha", "beta", "fit_loss")] == [*params.values(), loss]
    # the LSTM is a motion model of the filter too: its tracking rows, with the Q it estimated
    te = _rows(df, "lstm")
    assert len(te) == 4 * 3 and np.isfinite(te).all() and p["lstm_q_pos_std"] > 0


def test_observation_gp_is_used(zara1):
    """observation=gp: every learner gets its own GP sensor model (the network's sensor noise), learned online
    from the training episodes, so LIN's tracking rows move; with the linear sensors LIN learns nothing."""
    from dslearn.models.observation import GPObservation, LinearPositionObservation

    study, data = zara1
    lin = api.build_study(tiny_cfg(scenes=["zara1"], models=["lin"]))
    gp = api.build_study(tiny_cfg("observation=gp", scenes=["zara1"], models=["lin"]))
    fusion = study.fusion(data.network)
    obs = gp.learner(None, data, fusion).obs
    assert type(obs) is GPObservation and obs.gp.num_nodes == data.network.num_nodes
    assert type(lin.learner(None, data, fusion).obs) is LinearPositionObservation
    a = lin.protocol_tables(data, 0)
    b = gp.protocol_tables(data, 0)
    ta, tb = _rows(a, "lin"), _rows(b, "lin")
    assert len(ta) == len(tb) == 12 and np.isfinite(tb).all()
    assert np.abs(ta - tb).max() > 1e-3
    np.testing.assert_array_equal(_rows(a, "lin", "pred_err"), _rows(b, "lin", "pred_err"))  # the roll-out: no sensor


def test_filter_ukf_is_used(zara1):
    """filter=ukf: the fitted social force's tracking rows move (sigma points through a nonlinear model); LIN's
    stay equal to machine precision (for a linear model the unscented prediction is the Kalman prediction)."""
    _, data = zara1
    a = api.build_study(tiny_cfg(scenes=["zara1"], models=["lin", "sfm"])).protocol_tables(data, 0)
    b = api.build_study(tiny_cfg("filter=ukf", scenes=["zara1"], models=["lin", "sfm"])).protocol_tables(data, 0)
    np.testing.assert_allclose(_rows(a, "lin"), _rows(b, "lin"), rtol=1e-9, atol=1e-12)
    assert np.abs(_rows(a, "sfm") - _rows(b, "sfm")).max() > 1e-6


# ---------------------------------------------------------------------------------------------
# the study is a component: typed settings and the task's slots (the composition root's config logic)
# ---------------------------------------------------------------------------------------------
def test_study_module_reads_no_configuration():
    """The study takes typed settings and built parts: it neither names the config libraries nor imports the
    composition root or the validation layer (the config logic is the task's slots, dslearn/schemas)."""
    import ast
    import inspect
    import re

    src = inspect.getsource(et)
    assert not re.search("omegaconf|hydra|DictConfig|to_plain", src, re.IGNORECASE)
    mods = {n.module for n in ast.walk(ast.parse(src)) if isinstance(n, ast.ImportFrom)}
    mods |= {a.name for n in ast.walk(ast.parse(src)) if isinstance(n, ast.Import) for a in n.names}
    assert not {m for m in mods if m and m.startswith(("dslearn.compose", "dslearn.schemas"))}, mods


def test_settings_are_typed_and_split_into_recipe_and_arena():
    """The composed task arrives as the study's settings dataclass; each of its values reaches the episode
    recipe and the arena network under its own name (distinct values: a swapped pair fails)."""
    cfg = tiny_cfg(scenes=["zara1"], models=["lin"], max_dist=2.5, min_speed=0.25, stride=3, steps=9, dt=0.5, criterion="closest",
                   split="random", test_fraction=0.3, network={"num_sensors": 5, "k_nearest": 3, "sensing_range": 6.5,
                                                                "meas_std": 0.15, "margin": 0.1})
    study = api.build_study(cfg)
    s = study.settings
    assert isinstance(s, et.EthucyTrackingSettings) and isinstance(s.network, ArenaSettings)
    assert isinstance(s.cm_fusion, et.CmFusionSettings) and s.cm_fusion.noise_std == 0.1
    want = dict(agents=2, steps=9, dt=0.5, max_dist=2.5, stride=3, criterion="closest", min_speed=0.25, split="random",
                test_fraction=0.3, test_episodes=3)
    assert s.episode_recipe() == EpisodeRecipe(**want)
    ext = (0.0, 12.0, 0.0, 7.0)
    net, ref = s.network.network(ext), arena_network(ext, 5, k_nearest=3, sensing_range=6.5, meas_std=0.15, margin=0.1)
    assert torch.equal(net.positions, ref.positions) and torch.equal(net.adjacency, ref.adjacency)
    assert (net.meas_std, net.sensing_range) == (0.15, 6.5)
    assert set(study.ethucy_tracking_datasets) >= {"zara1", "eth"}
    assert study.ethucy_tracking_datasets["zara1"].label == "ZARA1"


def test_observation_noise_follows_the_study_network():
    """The sensor model of a source's network has that network's noise (task.network.meas_std), not the
    root network's that the observation option names, unless the option's noise is set."""
    from dslearn.models import LinearPositionObservation

    ext = (0.0, 10.0, 0.0, 6.0)
    study = api.build_study(tiny_cfg("network.meas_std=0.5", network={"meas_std": 0.35}))
    net = study.settings.network.network(ext)
    obs = study.ethucy_tracking_observation(net)
    assert type(obs) is LinearPositionObservation and obs.noise_std == 0.35
    assert study.ethucy_tracking_observation(arena_network(ext, 4, meas_std=0.27)).noise_std == 0.27
    fixed = api.build_study(tiny_cfg("observation.noise_std=0.45", network={"meas_std": 0.35}))
    assert fixed.ethucy_tracking_observation(net).noise_std == 0.45


def test_model_entries_cm_fusion_and_synthetic_slots():
    """The model entries carry their labels and make a fresh model per call; the CM fusion of the fused
    tracks takes the root consensus group's weights and iterations; the root scenario and network are built
    for the synthetic source only."""
    from dslearn.fusion.strategies import ConsensusOnMeasurements
    from dslearn.fusion.weights import consensus_weights
    from dslearn.models import ConstantVelocity
    from dslearn.sim.real import RealScenario

    study = api.build_study(tiny_cfg("consensus.iterations=2", "consensus.weights=metropolis",
                                     models=["gp", "gp_cv", "lin", "sfm"]))
    entries = study.ethucy_tracking_models
    assert [(e.entry, e.label) for e in entries] == [("gp", "gp_increment"), ("gp_cv", "gp_increment_cv"),
                                                      ("lin", "lin"), ("sfm", "sfm")]
    net = arena_network((0.0, 10.0, 0.0, 6.0), 4)
    scenario = RealScenario(2, 0.4, 11, (0.0, 10.0, 0.0, 6.0))
    a, b = entries[0].make(scenario, net), entries[0].make(scenario, net)
    assert a is not b and a.gp is not b.gp and a.inputs == "belief" and a.state_dim == 8
    lin = entries[2].make(scenario, net)
    assert type(lin) is ConstantVelocity and lin.noise_std == 0.1
    assert entries[1].make(scenario, net, device=torch.device("meta")).gp.mean_type == "constant_velocity"
    cm = study.ethucy_tracking_cm_fusion(net)
    assert type(cm) is ConsensusOnMeasurements and cm.iterations == 2 and cm.weights_rule == "metropolis"
    torch.testing.assert_close(cm.weights, consensus_weights(net.adjacency, "metropolis"))
    assert type(study.fusion(net)).__name__ == "HybridConsensus" and study.fusion(net).iterations == 2
    assert study.ethucy_tracking_synthetic is None  # tables: the root scenario and network are not built
    syn = api.build_study(tiny_cfg(protocol="data_size", scenes=[], synthetic=True, data_sizes=[2], seeds=1,
                                   plot_episodes=0, models=["lin"]))
    world = syn.ethucy_tracking_synthetic
    assert isinstance(world, et.SyntheticWorld) and world.network.num_nodes > 0 and world.scenario.num_agents == 2
    assert syn.sources() == [("synthetic", "synthetic")]


def test_position_and_scalar_rows():
    """The stored trajectories' rows: x and y of each agent at each step of the first n episodes, keys first."""
    from dslearn.metrics.prediction import position_rows, scalar_row

    traj = torch.arange(3 * 4 * 8, dtype=torch.float64).reshape(3, 4, 8)  # (B, K+1, [p, v] x 2 agents)
    df = position_rows(traj, "sensor1", 2, data="real", scene="s")
    assert list(df.columns) == ["data", "scene", "node", "node_kind", "episode", "step", "agent", "metric", "value"]
    assert len(df) == 2 * 4 * 2 * 2 and set(df.episode) == {0, 1} and (df.node == "sensor1").all()
    got = df.set_index(["metric", "episode", "step", "agent"])["value"]
    for e in range(2):
        for k in range(4):
            for a in range(2):
                assert got[("pred_x", e, k, a)] == traj[e, k, 4 * a] and got[("pred_y", e, k, a)] == traj[e, k, 4 * a + 1]
    assert position_rows(None, "sensor1", 0, data="real").empty
    row = scalar_row("sfm_tau", 0.7, data="real", seed=3)
    assert row.to_dict("records") == [{"node": "avg", "node_kind": "param", "episode": 0, "metric": "sfm_tau",
                                       "value": 0.7, "data": "real", "seed": 3}]
