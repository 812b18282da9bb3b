"""Configuration of task ``liu_dgpt``: the schema (keys and types at composition, ranges naming the
field, cross-field rules), the task's own keys that pick a cell (``task.tracker``, ``task.aggregations``,
``task.gp_input``, ``task.noises``: once root groups, now keys of the task) and the root ``scenario``
options s1-s3 (every option composes, is checked and is what the study instantiates / reads)."""

import contextlib
import dataclasses
import functools
import io
import os

import pytest
import torch
from hydra import compose, initialize_config_dir

from dslearn.schemas.core import CONF_DIR
from dslearn.errors import ConfigError
from dslearn.schemas import validate_task
from dslearn.sim import manoeuvres
from dslearn import api
from dslearn.studies import liu_dgpt


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return compose("config", overrides=list(overrides))


def _plan(*overrides):
    cfg = _compose("experiment=liu_table1", *overrides)
    validate_task(cfg)
    return api.build_study(cfg).plan()


def _cli(argv):
    from dslearn.run import main

    out, err = io.StringIO(), io.StringIO()
    old = os.environ.get("CI")
    os.environ["CI"] = "1"
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                main(list(argv))
                code = 0
            except SystemExit as e:
                code = e.code
    finally:
        os.environ.pop("CI", None) if old is None else os.environ.__setitem__("CI", old)
    return code, [ln for ln in err.getvalue().splitlines() if ln.strip()]


@pytest.mark.parametrize("override,fragment", [
    ("task.bogus=1", "task.bogus: no such key"),
    ("task.hyper.maxiter=5", "task.hyper.maxiter: no such key"),
    ("task.mc_runs=abc", "task.mc_runs=abc"),
    ("task.hyper.gap_check=maybe", "task.hyper.gap_check=maybe"),
    ("task.scenario_params.s1.bogus=1", "task.scenario_params.s1.bogus: no such key"),
    ("task.mc_runs=-1", "task.mc_runs=-1 must be >= 1"),
    ("task.scenario_params.s2.p_zero=1.5", "task.scenario_params.s2.p_zero=1.5 must be >= 0.0 and <= 1.0"),
    ("task.scenario_params.s1._target_=os.system", "task.scenario_params.s1._target_='os.system' is not allowed"),
    ("task.noises=[1,-2]", "task.noises[1]=-2.0 must be > 0.0"),
    ("task.tracker=both", "task.tracker='both' is not allowed; choose one of ['dgpt', 'gp']"),
    ("task.aggregations=[moe]", "task.aggregations[0]='moe' is not allowed"),
    ("task.gp_input=spatial", "task.gp_input='spatial' is not allowed; choose one of ['temporal', 'spatiotemporal']"),
    ("task.tracker=gp task.aggregations=[]", "task.aggregations is not used by task=liu_dgpt with task.tracker=gp"),
    ("task.tracker=gp task.centralised=true", "task.centralised is not used by task=liu_dgpt with task.tracker=gp"),
    ("task.tracker=dgpt task.centralised=false", "task.centralised is not used by task=liu_dgpt with task.tracker=dgpt"),
    ("task.aggregations=[] task.centralised=true", "task.aggregations must not be empty"),
    # the former root groups / key: a one-line pointer to the task key
    ("tracker=dgpt", "tracker=dgpt: tracker is no longer a root group or key; it is a key of task=liu_dgpt: "
                     "write task.tracker=dgpt"),
    ("aggregation=rbcm", "write task.aggregations=[rbcm]"),
    ("gp_input=spatiotemporal", "write task.gp_input=spatiotemporal"),
    ("noise=2", "write task.noises=[2]"),
    ("-m noise=1,4", "write task.noises=[1],[4]"),
    ("consensus=ci", "task=liu_dgpt does not use the root group consensus (its fusion is task.aggregations)"),
])
def test_cli_refuses_with_one_line_naming_the_field(tmp_path, override, fragment):
    code, lines = _cli(["experiment=liu_table1", *override.split(), f"hydra.run.dir={tmp_path / 'r'}"])
    assert code == 2 and len(lines) == 1, lines
    assert lines[0].startswith("dslearn-run: ") and fragment in lines[0], lines[0]
    assert not (tmp_path / "r").exists()


def test_ranges_name_the_field_in_validate_task():
    for ov, frag in (("task.ucb_delta=1.0", "task.ucb_delta=1.0 must be > 0.0 and < 1.0"),
                     ("task.window.s3=0", "task.window.s3=0 must be >= 1"),
                     ("task.noises=[]", "task.noises has 0 entries; it needs at least 1"),
                     ("task.aggregations=[poe,poe]", "task.aggregations=['poe', 'poe'] has duplicates"),
                     ("task.trace.scenario=s9", "task.trace.scenario='s9' is not allowed")):
        with pytest.raises(ConfigError) as e:
            validate_task(_compose("experiment=liu_table1", ov))
        assert frag in str(e.value), (ov, str(e.value))


ALL_RULES = ["poe", "gpoe", "bcm", "rbcm", "grbcm"]


@pytest.mark.parametrize("option", ["dgpt", "gp"])
def test_every_tracker_option(option):
    p = _plan(f"task.tracker={option}")
    assert p.centralised is (option == "gp")
    assert p.aggregations == ([] if option == "gp" else ALL_RULES)
    # without a tracker: the rules and, with task.centralised, the standard GP
    assert (_plan().aggregations, _plan().centralised) == (ALL_RULES, True)
    assert (_plan("task.centralised=false").aggregations, _plan("task.centralised=false").centralised) == \
        (ALL_RULES, False)


@pytest.mark.parametrize("option", ["poe", "gpoe", "bcm", "rbcm", "grbcm"])
def test_every_aggregation_option(option):
    p = _plan(f"task.aggregations=[{option}]")
    assert p.aggregations == [option] and p.centralised is True
    assert _plan(f"task.aggregations=[{option}]", "task.tracker=dgpt").centralised is False


@pytest.mark.parametrize("option", ["temporal", "spatiotemporal"])
def test_every_gp_input_option(option):
    for base in ("experiment=liu_table1", "experiment=liu_table2"):  # the command line beats the experiment's default
        cfg = _compose(base, f"task.gp_input={option}")
        validate_task(cfg)
        assert api.build_study(cfg).plan().gp_input == option


@pytest.mark.parametrize("option", ["s1", "s2", "s3"])
def test_every_scenario_option_instantiates_its_generator(option):
    p = _plan(f"scenario={option}")
    assert p.scenarios == [option]
    gen = p.generators[option]
    assert isinstance(gen, functools.partial) and gen.func is manoeuvres.GENERATORS[option]
    # the instantiated partial is the generator with the task's parameters: same trajectory
    cfg = _compose("experiment=liu_table1")
    params = {k: v for k, v in cfg.task.scenario_params[option].items() if not k.startswith("_")}
    a = gen(2, 30, torch.Generator().manual_seed(5), dt=1.0, dtype=torch.float64)
    b = manoeuvres.GENERATORS[option](2, 30, torch.Generator().manual_seed(5), dt=1.0, dtype=torch.float64,
                                      **{k: list(v) if hasattr(v, "__len__") else v for k, v in params.items()})
    for x, y in zip(a, b):
        assert x.shape == (2, 30, 2) and torch.equal(x, y)


def test_scenario_parameters_apply_with_and_without_selection():
    for sel in ([], ["scenario=s1"]):
        p = _plan(*sel, "task.scenario_params.s1.turn_every=7")
        assert p.generators["s1"].keywords["turn_every"] == 7
    assert _plan().scenarios == ["s1", "s2", "s3"]  # the root default (Yu's scenario) selects nothing
    # a scenario option's own node is its generator: a parameter there is not a key (fails at composition)
    code, lines = _cli(["experiment=liu_table1", "scenario=s1", "scenario.turn_every=7", "hydra.run.dir=/nonexistent/x"])
    assert code == 2 and len(lines) == 1 and "scenario.turn_every" in lines[0], lines


def test_noise_levels_are_the_task_key():
    assert _plan("task.noises=[2]").noises == [2.0]
    assert _plan("task.noises=[1,4]").noises == [1.0, 4.0]
    assert _plan().noises == [1.0, 2.0, 4.0]


# ------------------------------------------------------------------ the moved keys: same plan as before
def _scenario_plan(cfg, name):
    """The plan's entries of one scenario, from the task node (as the study documents them)."""
    t = cfg.task
    params = {k: v for k, v in t.scenario_params[name].items() if not k.startswith("_")}
    return int(t.window[name]), manoeuvres.GENERATORS[name], params


#: the plans the former spelling (root groups tracker / aggregation / gp_input, top-level noise) gave,
#: as recorded before the move: (former command line, its new spelling, the plan's cell entries)
FORMER = [
    ("experiment=liu_table1", "experiment=liu_table1",
     dict(gp_input="temporal", scenarios=["s1", "s2", "s3"], noises=[1.0, 2.0, 4.0], aggregations=ALL_RULES,
          centralised=True, mc_runs=30, trace={"scenario": "s1", "noise": 4.0, "episodes": 1})),
    ("experiment=liu_table2", "experiment=liu_table2",
     dict(gp_input="spatiotemporal", scenarios=["s1", "s2", "s3"], noises=[1.0, 2.0, 4.0], aggregations=ALL_RULES,
          centralised=True, mc_runs=20, trace={"scenario": "s1", "noise": 4.0, "episodes": 1})),
    ("experiment=liu_table2 tracker=dgpt aggregation=rbcm gp_input=spatiotemporal scenario=s3 noise=2",
     "experiment=liu_table2 task.tracker=dgpt task.aggregations=[rbcm] task.gp_input=spatiotemporal scenario=s3 "
     "task.noises=[2]",
     dict(gp_input="spatiotemporal", scenarios=["s3"], noises=[2.0], aggregations=["rbcm"], centralised=False,
          mc_runs=20, trace={"scenario": "s3", "noise": 2.0, "episodes": 1})),
    ("task=liu_dgpt tracker=gp scenario=s1 noise=4", "task=liu_dgpt task.tracker=gp scenario=s1 task.noises=[4]",
     dict(gp_input="temporal", scenarios=["s1"], noises=[4.0], aggregations=[], centralised=True, mc_runs=30,
          trace={"scenario": "s1", "noise": 4.0, "episodes": 1})),
    ("experiment=liu_table1 aggregation=grbcm", "experiment=liu_table1 task.aggregations=[grbcm]",
     dict(gp_input="temporal", scenarios=["s1", "s2", "s3"], noises=[1.0, 2.0, 4.0], aggregations=["grbcm"],
          centralised=True, mc_runs=30, trace={"scenario": "s1", "noise": 4.0, "episodes": 1})),
]
#: the rest of the plan: the task file's values (unchanged by the move)
FIXED = dict(batch_runs=50, num_sensors=200, num_steps=100, sensing_range=50.0, area_size=1000.0, dt=1.0,
             ucb_delta=0.05, normalise_beta=False, grbcm_comm_points=10, torch_threads=1)


def _assert_plan(cfg, cell):
    validate_task(cfg)
    plan = api.build_study(cfg).plan()
    p = {f.name: getattr(plan, f.name) for f in dataclasses.fields(plan)} | {"trace": dataclasses.asdict(plan.trace)}
    assert {k: p[k] for k in cell} == cell
    assert {k: p[k] for k in FIXED} == FIXED
    assert p["hyper"] == liu_dgpt.HyperConfig(**{k: v for k, v in cfg.task.hyper.items()})
    assert p["hyper"].optimizer == "adam" and p["hyper"].iters == 3 and p["hyper"].init_outputscale == 1.0e5
    assert set(p["window"]) == set(p["generators"]) == set(cell["scenarios"])
    for s in cell["scenarios"]:
        window, fn, params = _scenario_plan(cfg, s)
        gen = p["generators"][s]
        assert p["window"][s] == window == {"s1": 10, "s2": 5, "s3": 5}[s]
        assert gen.func is fn and {k: (list(v) if isinstance(v, (list, tuple)) else v)
                                    for k, v in gen.keywords.items()} == \
            {k: (list(v) if hasattr(v, "__len__") and not isinstance(v, str) else v) for k, v in params.items()}
    assert set(p) == set(cell) | set(FIXED) | {"hyper", "window", "generators"}


@pytest.mark.parametrize("former,new,cell", FORMER, ids=[f[0] for f in FORMER])
def test_moved_keys_give_the_former_plan(former, new, cell):
    _assert_plan(_compose(*new.split()), cell)


def test_liu_grid_jobs_give_the_former_plans(tmp_path):
    """``experiment=liu_grid``: 18 jobs (gp_input x scenario x noise, now ``task.gp_input`` x ``scenario``
    x ``task.noises``), each the former job's plan: one cell, every rule + the standard GP, 100 runs; a
    cell traces itself unless it holds the task's trace cell (s1, sigma 4)."""
    from hydra import compose, initialize_config_dir

    from dslearn.app.composer import sweep_combinations
    from dslearn.app.precheck import precheck

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        combos, multirun, _ = sweep_combinations(["experiment=liu_grid"])
        assert multirun and len(combos) == 18
        seen = set()
        for combo in combos:
            cfg = compose("config", overrides=["experiment=liu_grid", *combo])
            gp_input, scenario, noise = str(cfg.task.gp_input), str(cfg.scenario._target_)[-2:], list(cfg.task.noises)
            assert len(noise) == 1
            seen.add((gp_input, scenario, noise[0]))
            _assert_plan(cfg, dict(gp_input=gp_input, scenarios=[scenario], noises=noise, aggregations=ALL_RULES,
                                   centralised=True, mc_runs=100,
                                   trace={"scenario": scenario, "noise": noise[0], "episodes": 1}))
    assert seen == {(g, s, n) for g in ("temporal", "spatiotemporal") for s in ("s1", "s2", "s3") for n in (1.0, 2.0, 4.0)}
    assert precheck(["experiment=liu_grid", f"hydra.sweep.dir={tmp_path / 's'}"]) is None


def test_former_groups_are_gone():
    for group in ("tracker", "aggregation", "gp_input", "liu_keys"):
        assert not (CONF_DIR / group).exists(), group
    assert "noise" not in _compose("experiment=liu_table1")  # no top-level key left
