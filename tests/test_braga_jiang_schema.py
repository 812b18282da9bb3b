"""The config schemas of the jiang_fg and braga_tbn tasks (keys / types at composition, ranges and
cross-field rules before any work), their options, and the Braga diagnostics tool."""

from __future__ import annotations

import dataclasses
import inspect

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from dslearn.schemas.core import CONF_DIR, validate_config
from dslearn.errors import ConfigError


def _compose(experiment: str, *overrides: str):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return compose("config", overrides=[f"experiment={experiment}", *overrides])


@pytest.mark.parametrize("experiment", ["jiang_fg", "braga_tbn"])
def test_defaults_compose_and_pass(experiment):
    cfg = _compose(experiment)
    validate_config(cfg)  # root keys + the task schema + its cross-field check
    assert OmegaConf.get_type(cfg.task).__name__ in ("JiangTask", "BragaTask")


@pytest.mark.parametrize("experiment,override,fragment", [
    ("jiang_fg", "task.bogus=1", "bogus"),
    ("jiang_fg", "task.fg.bogus=1", "bogus"),
    ("jiang_fg", "task.mc_runs=abc", "mc_runs"),
    ("jiang_fg", "task.fg.relinearize=maybe", "relinearize"),
    ("braga_tbn", "task.bogus=1", "bogus"),
    ("braga_tbn", "task.em.bogus=1", "bogus"),
    ("braga_tbn", "task.num_particles=abc", "num_particles"),
    ("braga_tbn", "task.dt=fast", "dt"),
])
def test_unknown_key_or_wrong_type_fails_at_composition(experiment, override, fragment):
    with pytest.raises(Exception, match=fragment) as info:
        _compose(experiment, override)
    assert not isinstance(info.value, ConfigError)  # Hydra's own error, before any check of ours runs


@pytest.mark.parametrize("override,message", [
    ("task.mc_runs=0", "task.mc_runs=0 must be >= 1"),
    ("task.sigma_y=0", "task.sigma_y=0.0 must be > 0.0"),
    ("task.fg.damping=1.0", "task.fg.damping=1.0 must be >= 0.0 and < 1.0"),
    ("task.fg.graph=tree", "task.fg.graph='tree' is not allowed; choose one of ['scalar', 'joint']"),
    ("task.tracker.obs_var=bogus", "task.tracker.obs_var='bogus' is not allowed"),
    ("task.figures.fig2_iterations=[1,0]", "task.figures.fig2_iterations[1]=0 must be >= 1"),
    ("task.scenario.initial_state=[1.0]", "task.scenario.initial_state=[1.0] must have 2 entries"),
    ("task.scenario.coefficients=[[1,2,3]]", "task.scenario.coefficients=[[1, 2, 3]] needs 2 rows"),
    ("task.scenario.sensors=[[0,0],[1]]", "every sensor needs the same number"),
    ("task.scenario.sensors=[[0,a]]", "task.scenario.sensors[0]=[0, 'a'] must be a list of finite numbers"),
    ("task.num_samples=1", "task.num_samples=1 must be >= 2 with task.fg.measurement_var=sample"),
    ("+task.ablations.x={bogus:1}", "task.ablations.x.bogus: Key 'bogus' not in 'Ablation'"),
    ("+task.ablations.x={damping:abc}", "task.ablations.x.damping"),
    ("+task.ablations.x={max_iter:0}", "task.ablations.x.max_iter=0 must be >= 1"),
    ("+task.ablations.x={init_guess:[1.0]}", "task.ablations.x.init_guess=[1.0] must have 2 entries"),
    ("+task.ablations.default={damping:0.5}", "task.ablations.default: the name 'default' is the main grid's"),
])
def test_jiang_values_name_the_field(override, message):
    cfg = _compose("jiang_fg", override)
    with pytest.raises(ConfigError) as info:
        validate_config(cfg)
    assert message in str(info.value), str(info.value)


def test_jiang_ablation_fields_are_the_tracker_settings():
    from dslearn.learning.factor_graph.engine import TrackerSettings
    from dslearn.schemas.jiang_fg import Ablation

    want = {f.name for f in dataclasses.fields(TrackerSettings)} - {"num_samples", "initial_state"} | {"max_iter"}
    assert {f.name for f in dataclasses.fields(Ablation)} == want


def test_jiang_every_option_composes_and_instantiates():
    """Each choice of the fg / tracker settings composes, passes the checks and builds TrackerSettings; the
    README's '+task.ablations.<name>={...}' override works and its values reach the settings typed."""
    from dslearn import api
    from dslearn.learning.factor_graph.crlb import CRLB_FORMS

    options = [f"task.fg.crlb_form={c}" for c in CRLB_FORMS] + [
        "task.fg.schedule=sequential", "task.fg.graph=joint", "task.fg.taylor_point=guess",
        "task.fg.init_guess_mode=prediction", "task.fg.measurement_var=known", "task.fg.relinearize=true",
        "task.fg.prior_var=4.0", "task.tracker.obs_var=crlb", "task.tracker.gate=10.83"]
    for ov in options:
        cfg = _compose("jiang_fg", ov, "+task.ablations.mine={relinearize:true,damping:0,prior_var:null,max_iter:7}")
        validate_config(cfg)
        study = api.build_study(cfg)  # the settings and the typed ablations, as the composition root fills them
        s = study.tracker_settings()
        key, val = ov.split("=")
        got = getattr(s, key.split(".")[-1])
        assert str(got).lower() == val.lower() or got == float(val), (ov, got)
        runs = study.ablation_runs()
        m, its = runs["mine"]
        assert its == 7 and m.relinearize is True and m.prior_var == float("inf")
        assert isinstance(m.damping, float) and m.damping == 0.0
        assert m.num_samples == s.num_samples and m.obs_var == s.obs_var  # the keys it leaves out: the main grid's
        assert set(runs) == {"mine", *OmegaConf.load(CONF_DIR / "task" / "jiang_fg.yaml").ablations}
        assert runs["converged_fixed_point"][1] == 100 and runs["paper"][1] == cfg.task.max_iter


def test_braga_weight_options_compose_and_build():
    """Every rule of ``task.consensus.weights`` composes, passes the checks and builds the matrix
    written out by hand: on the paper's finger four (edges 0-1, 0-2, 2-3; degrees 2, 1, 2, 1), where
    1/(2 d_max) is Eq. (26) and Metropolis equals 1/(1 + d_max), and on a graph where those two
    differ (edges 0-1, 0-2, 0-3, 1-2; degrees 3, 2, 2, 1: the edge 1-2 joins two nodes below d_max)."""
    from dslearn.learning.online_em import tbn_params

    def built(rule, *over):
        over = [f"task.consensus.weights={rule}", *over]
        cfg = _compose("braga_tbn", *over)
        validate_config(cfg)
        return tbn_params(OmegaConf.to_object(cfg.task)).weights  # the study's typed settings

    def same(w, rows):
        torch.testing.assert_close(w, torch.tensor(rows, dtype=torch.float64), rtol=0, atol=1e-15)

    a, b, c, h = 1 / 3, 2 / 3, 1 / 4, 1 / 2
    eq26 = [[0.5, 0.25, 0.25, 0.0], [0.25, 0.75, 0.0, 0.0], [0.25, 0.0, 0.5, 0.25], [0.0, 0.0, 0.25, 0.75]]
    third = [[a, a, a, 0.0], [a, b, 0.0, 0.0], [a, 0.0, a, a], [0.0, 0.0, a, b]]  # 1/(1 + 2) on every edge
    same(built("half_max_degree"), eq26)  # the paper's Eq. (26)
    same(built("max_degree_core"), third)
    same(built("metropolis"), third)  # 1/(1 + max(d_i, d_j)) = 1/3: every edge touches a degree-2 node
    same(built("matrix", f"task.consensus.matrix={eq26}".replace(" ", "")), eq26)
    kite = "task.network.edges=[[0,1],[0,2],[0,3],[1,2]]"
    same(built("half_max_degree", kite), [[h, 1 / 6, 1 / 6, 1 / 6], [1 / 6, b, 1 / 6, 0.0],
                                          [1 / 6, 1 / 6, b, 0.0], [1 / 6, 0.0, 0.0, 5 / 6]])  # 1/(2 * 3)
    same(built("max_degree_core", kite), [[c, c, c, c], [c, h, c, 0.0], [c, c, h, 0.0], [c, 0.0, 0.0, 3 / 4]])
    same(built("metropolis", kite), [[c, c, c, c], [c, 5 / 12, a, 0.0], [c, a, 5 / 12, 0.0],
                                     [c, 0.0, 0.0, 3 / 4]])  # w_12 = 1/(1 + 2)
    cfg = _compose("braga_tbn", "task.consensus.weights=max_degree")
    with pytest.raises(ConfigError, match="task.consensus.weights='max_degree' is ambiguous"):
        validate_config(cfg)


@pytest.mark.parametrize("override,message", [
    ("task.mc_batch=0", "task.mc_batch=0 must be >= 1"),
    ("task.em.init_mode=bogus", "task.em.init_mode='bogus' is not allowed"),
    ("task.em.burn_in=-1", "task.em.burn_in=-1 must be >= 0"),
    ("task.backward_kernel.dtype=float16", "task.backward_kernel.dtype='float16' is not allowed"),
    ("task.kilobyte=999", "task.kilobyte=999 is not allowed; choose one of [1000, 1024]"),
    ("task.v0=[1.0,2.0,3.0]", "task.v0 has 3 entries; it allows at most 2"),
    ("task.network.fusion_centre=4", "task.network.fusion_centre=4 must be >= 0 and <= 3"),
    ("task.modes.mu_init=[-5.0,25.0,3.0]", "K mismatch"),
    ("task.consensus.weights=matrix", "task.consensus.weights=matrix needs task.consensus.matrix"),
    ("task.strategies=[]", "task.strategies has 0 entries"),
])
def test_braga_values_name_the_field(override, message):
    cfg = _compose("braga_tbn", override)
    with pytest.raises(ConfigError) as info:
        validate_config(cfg)
    assert message in str(info.value), str(info.value)


def test_braga_init_mode_true_from_the_command_line():
    """``task.em.init_mode=true`` arrives as a bool; it is accepted and means the paper's initialisation."""
    from dslearn.learning.online_em import tbn_params

    cfg = _compose("braga_tbn", "task.em.init_mode=true")
    validate_config(cfg)
    assert OmegaConf.to_object(cfg.task).em.init_mode is True
    assert tbn_params(OmegaConf.to_object(cfg.task)).init_mode == "true"
    assert tbn_params(OmegaConf.to_container(cfg.task, resolve=True)).init_mode == "true"
    uniform = _compose("braga_tbn", "task.em.init_mode=uniform").task
    assert tbn_params(OmegaConf.to_object(uniform)).init_mode == "uniform"


def test_braga_settings_and_plain_values_give_the_same_harness_params():
    """The harness reads the study's typed settings (``BragaTask``) and the same values as plain dicts alike,
    with every value of the configuration (not a default) where the task sets one."""
    import dataclasses

    from dslearn.learning.online_em import tbn_params
    from dslearn.studies.braga_tbn import BragaTask

    cfg = _compose("braga_tbn", "task.steps=1230", "task.dt=0.04", "task.network.edges=[[0,1],[1,2],[2,3]]",
                   "task.modes.mu_init=[-1.0,7.0]", "task.backward_kernel.dtype=float32", "task.em.burn_in=9",
                   "task.terrain.seed_offset=5", "task.start=[100.0,200.0]")
    validate_config(cfg)
    settings = OmegaConf.to_object(cfg.task)
    assert type(settings) is BragaTask and settings.modes.mu_init == [-1.0, 7.0]
    typed, plain = tbn_params(settings), tbn_params(OmegaConf.to_container(cfg.task, resolve=True))
    for f in dataclasses.fields(typed):
        a, b = getattr(typed, f.name), getattr(plain, f.name)
        if isinstance(a, torch.Tensor):
            assert torch.equal(a, b), f.name
        elif f.name in ("truth", "init"):
            assert all(torch.equal(getattr(a, k), getattr(b, k)) for k in ("mu", "sigma", "pi")), f.name
        else:
            assert a == b, f.name
    assert (typed.steps, typed.dt, typed.burn_in, typed.terrain_seed_offset, typed.start) == (1230, 0.04, 9, 5,
                                                                                             (100.0, 200.0))
    assert typed.kernel_dtype is torch.float32 and typed.init.mu.tolist() == [-1.0, 7.0]
    assert typed.adj.tolist() == [[0, 1, 0, 0], [1, 0, 1, 0], [0, 1, 0, 1], [0, 0, 1, 0]]
    with pytest.raises(TypeError, match="tbn_params"):
        tbn_params(cfg.task)  # a config node is neither: the composition root converts it


def test_run_tbn_takes_no_truth():
    """The filter loop's inputs are the measurements, the map, the initial state/mode and the models."""
    from dslearn.learning.online_em import run_tbn

    params = list(inspect.signature(run_tbn).parameters)
    assert params[:3] == ["y", "terrain", "x0"] and "scn" not in params and "truth" not in params


def test_tbn_trace_tool_screen_and_episodes(capsys):
    from dslearn.tools.tbn_trace import _episodes, main

    assert _episodes("0-2,5") == [0, 1, 2, 5]
    main(["screen", "0-1", "task.steps=20", "task.num_particles=10", "task.em.burn_in=5",
          "task.steady_state_s=0.5", "task.workers=1", "task.strategies=[noncooperative,consensus_1]",
          "task.terrain.size_m=12000.0", "task.terrain.resolution_m=50.0"])
    out = capsys.readouterr().out.strip().splitlines()
    assert [ln.split(":")[0] for ln in out] == ["noncooperative", "consensus_1"]
    assert all(ln.split(": ")[1].startswith("2 runs, lost track") for ln in out)
