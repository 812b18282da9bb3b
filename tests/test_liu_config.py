"""Configuration of task ``liu_dgpt``: the schema (keys and types at composition, ranges naming the
field, cross-field rules) and the config groups (every option composes, is checked and is what the
study instantiates / reads)."""

import contextlib
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
from dslearn.studies import liu_dgpt


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return compose("config", overrides=list(overrides))


def _plan(*overrides):
    cfg = _compose("experiment=liu_table1", *overrides)
    validate_task(cfg)
    return liu_dgpt.plan(cfg)


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
    ("tracker=dgpt task.centralised=true", "tracker=dgpt runs the aggregation rule(s) only"),
    ("noise=[1,-2]", "noise[1]=-2 must be a number > 0"),
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


@pytest.mark.parametrize("option", ["dgpt", "gp"])
def test_every_tracker_option(option):
    p = _plan(f"tracker={option}")
    assert p["centralised"] is (option == "gp")
    assert p["aggregations"] == ([] if option == "gp" else ["poe", "gpoe", "bcm", "rbcm", "grbcm"])


@pytest.mark.parametrize("option", ["poe", "gpoe", "bcm", "rbcm", "grbcm"])
def test_every_aggregation_option(option):
    p = _plan(f"aggregation={option}")
    assert p["aggregations"] == [option] and p["centralised"] is True
    assert _plan(f"aggregation={option}", "tracker=dgpt")["centralised"] is False


@pytest.mark.parametrize("option", ["temporal", "spatiotemporal"])
def test_every_gp_input_option(option):
    for base in ("experiment=liu_table1", "experiment=liu_table2"):  # the group beats the experiment's default
        cfg = _compose(base, f"gp_input={option}")
        validate_task(cfg)
        assert liu_dgpt.plan(cfg)["gp_input"] == option


@pytest.mark.parametrize("option", ["s1", "s2", "s3"])
def test_every_scenario_option_instantiates_its_generator(option):
    p = _plan(f"scenario={option}")
    assert p["scenarios"] == [option]
    gen = p["generators"][option]
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
        assert p["generators"]["s1"].keywords["turn_every"] == 7
    assert _plan()["scenarios"] == ["s1", "s2", "s3"]  # the root default (Yu's scenario) selects nothing
    # a scenario option's own node is its generator: a parameter there is not a key (fails at composition)
    code, lines = _cli(["experiment=liu_table1", "scenario=s1", "scenario.turn_every=7", "hydra.run.dir=/nonexistent/x"])
    assert code == 2 and len(lines) == 1 and "scenario.turn_every" in lines[0], lines


def test_noise_value_key_selects_noise_levels():
    assert _plan("noise=2")["noises"] == [2.0]
    assert _plan("noise=[1,4]")["noises"] == [1.0, 4.0]
    assert _plan()["noises"] == [1.0, 2.0, 4.0]
