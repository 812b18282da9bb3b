"""Every task refuses an override of a root group it does not read, and accepts one of a group it reads.

The expected table below is written from the studies (what each ``run`` reads of ``cfg``), not from
the declarations in :mod:`dslearn.schemas`: a declaration that claims a group the study does not read,
or misses one it reads, fails here. The override is found on the command line / in the sweep (the
start-up check, :func:`dslearn.app.precheck.precheck`), never by comparing values: selecting a group's
default option for a task that does not read it is refused too.
"""

from __future__ import annotations

import contextlib
import io
import os

import pytest

from dslearn.app.precheck import precheck
from dslearn.run import main
from dslearn.schemas.base import ROOT_GROUPS, TASKS, task_uses

#: the context that selects each task (its experiment where it has one)
CONTEXT = {
    "yu": ["task=yu"],
    "yu_faults": ["experiment=yu_faults"],
    "liu_dgpt": ["experiment=liu_table1"],
    "jiang_fg": ["experiment=jiang_fg"],
    "braga_tbn": ["experiment=braga_tbn"],
    "ethucy_forecast": ["experiment=ethucy_forecast"],
    "ethucy_tracking": ["experiment=real_tables"],
    # the same tasks where what they read depends on their own keys
    "ethucy_tracking/no_gp": ["experiment=real_tables", "task.models=[lin,sfm]"],
    "ethucy_tracking/synthetic": ["experiment=gp_vs_lstm"],
    "liu_dgpt/s3": ["experiment=liu_table1", "scenario=s3"],
    "matrix": ["task=matrix", "model=lin"],
    "gp_bayes_filters": ["experiment=gp_bayes_filters"],
}

#: what each study reads of the root groups (from dslearn/studies/<task>.py)
READS = {
    "yu": set(ROOT_GROUPS) - {"learner", "associator"},  # its parts are the root groups but a matrix method's learner
    # and associator
    # build_scenario / build_network / build_observation / cfg.filter / cfg.consensus.iterations; the
    # models and fusions of the grid are task.models / task.fusions, the episodes task.*_episodes
    "yu_faults": {"scenario", "network", "observation", "filter", "consensus.iterations"},
    "liu_dgpt": set(),
    # a cell: the scenario, the network part (Yu's scenario places no sensors of its own), the method's engine
    # (filter) and the parts the distributed filter takes, its learner among them; the episodes are task.*_episodes
    "matrix": {"scenario", "network", "filter", "model", "observation", "consensus", "method", "learner", "associator"},
    "jiang_fg": set(),
    "braga_tbn": set(),
    "gp_bayes_filters": set(),
    "ethucy_forecast": set(),
    # the fusion and cm_fused (consensus), the initial prior / gate / prediction step (filter), the sensor
    # model (observation), the root model as the entry gp of task.models
    "ethucy_tracking": {"model", "consensus", "filter", "observation"},
    "ethucy_tracking/no_gp": {"consensus", "filter", "observation"},  # no gp in task.models: cfg.model not read
    "ethucy_tracking/synthetic": {"model", "consensus", "filter", "observation", "scenario", "network"},  # synthetic_data()
    "liu_dgpt/s3": {"scenario"},  # a Liu scenario option narrows task.scenarios (selected_scenario)
}

#: per root group: a group selection (the default option where possible: not a change of value) and a
#: key override, both valid for every task that reads the group
LINES = {
    "scenario": ("scenario=yu_two_agents", "scenario.process_std=0.002"),
    "network": ("network=yu", "network.meas_std=0.3"),
    "model": ("model=gp", "model.noise_std=0.4"),
    "observation": ("observation=linear", "observation.noise_std=0.3"),
    "consensus": ("consensus=ci", "consensus.iterations=3"),
    "filter": ("filter=default", "filter.prior_pos_std=500.0"),
    "data": ("data=small", "data.train_episodes=5"),
    # the learner: an option the matrix's context (model=lin) takes, and the group removed (its default is null)
    "learner": ("learner=none", "~learner"),
    # the associator: its default option, and the group removed (the labels given, as with its default)
    "associator": ("associator=labels", "~associator"),
}


def _reads(case: str, line: str) -> bool:
    key = line.split("=", 1)[0].lstrip("+~")
    return any(key == r or key.startswith(r + ".") for r in READS[case])


def _check(case: str, line: str, tmp_path) -> str | None:
    return precheck([*CONTEXT[case], line, f"hydra.run.dir={tmp_path / 'run'}"])


CASES = [(case, group, line) for case in CONTEXT for group in ROOT_GROUPS for line in LINES[group]]
if {c.split("/")[0] for c in CONTEXT} != set(TASKS):
    raise AssertionError(f"every registered task needs a context here: {sorted(TASKS)}")


@pytest.mark.parametrize("case,group,line", CASES, ids=[f"{c}:{line}" for c, g, line in CASES])
def test_root_group_override_refused_unless_read(case, group, line, tmp_path):
    task = case.split("/")[0]
    if case == "liu_dgpt/s3" and group == "scenario":  # another option replaces the Liu scenario
        line = {"scenario=yu_two_agents": "scenario=s1", "scenario.process_std=0.002": "scenario._partial_=true"}[line]
    err = _check(case, line, tmp_path)
    if _reads(case, line):
        assert err is None, (case, line, err)
        return
    assert err is not None, f"task={task} does not read {line.split('=')[0]} but {line} was accepted"
    assert f"task={task}" in err and f"root group {group}" in err and f"remove {line}" in err, err
    instead = TASKS[task].instead.get(group)
    assert instead and f"({instead})" in err, err  # what the task uses instead
    assert not (tmp_path / "run").exists()


def test_declarations_match_what_the_studies_read(make_cfg):
    """``task_uses`` of each composed context is the table above (the declaration is the study's)."""
    for case, ctx in CONTEXT.items():
        got = set(task_uses(make_cfg(*ctx)))
        assert got == READS[case], (case, sorted(got))
        task = case.split("/")[0]
        # every group it does not read (wholly) says what the task uses instead
        missing = [g for g in ROOT_GROUPS if g not in got and not TASKS[task].instead.get(g)]
        assert not missing, (case, missing)


def test_partly_read_group_names_the_keys_it_reads(tmp_path):
    err = _check("yu_faults", "consensus=ci", tmp_path)
    assert err.startswith("task=yu_faults uses only consensus.iterations of the root group consensus ("), err
    assert "task.fusions" in err and "task.weights" in err
    for line in ("consensus.weights=metropolis", "consensus.omega=one", "+consensus.extra=1", "~consensus"):
        err = _check("yu_faults", line, tmp_path)
        assert err is not None and "uses only consensus.iterations" in err and f"remove {line}" in err, (line, err)


def test_brief_message_and_the_default_option_is_an_override_too(tmp_path):
    msg = "task=liu_dgpt does not use the root group consensus (its fusion is task.aggregations); remove consensus=hybrid"
    assert _check("liu_dgpt", "consensus=hybrid", tmp_path) == msg  # hybrid = the root default: same values
    assert _check("liu_dgpt", "consensus.iterations=4", tmp_path) == msg.replace("consensus=hybrid",
                                                                                  "consensus.iterations=4")


def test_sweep_job_that_does_not_read_a_group_is_refused_before_any_job(tmp_path):
    # job 0 lists gp (reads model), job 1 does not: refused, naming job 1
    err = precheck(["-m", "experiment=real_tables", "task.models=[gp,lin],[lin,sfm]", "model.noise_std=0.4",
                    f"hydra.sweep.dir={tmp_path / 's'}"])
    assert err is not None and "task=ethucy_tracking does not use the root group model" in err, err
    assert "(sweep job 1: " in err and "task.models=[lin,sfm]" in err, err
    # each job's own lines: the Liu scenario s1 is read, the Yu scenario of job 1 is not
    err = precheck(["-m", "experiment=liu_table1", "scenario=s1,yu_two_agents", f"hydra.sweep.dir={tmp_path / 's'}"])
    assert err is not None and err.startswith("task=liu_dgpt does not use the root group scenario (") and \
        "remove scenario=yu_two_agents (sweep job 1: " in err, err
    # a sweep over a group's options for a task that does not read it
    err = precheck(["-m", "experiment=jiang_fg", "consensus=ci,cm", f"hydra.sweep.dir={tmp_path / 's'}"])
    assert err is not None and err.startswith("task=jiang_fg does not use the root group consensus (") and \
        "(sweep job 0: " in err, err
    assert not (tmp_path / "s").exists()


@pytest.mark.parametrize("argv", [
    ["experiment=real_aggregation"],        # selects model (defaults) and sweeps model / model.aggregation
    ["experiment=yu_table1_ukf"],           # selects data and filter in its defaults, sweeps model x consensus
    ["experiment=gp_vs_lstm"],              # the synthetic source: the root scenario and network
    ["experiment=liu_grid"],                # sweeps the root scenario over s1-s3 and the task's own keys
    ["experiment=yu_faults", "consensus.iterations=2", "filter=ukf", "network=yu_blind"],
])
def test_experiments_that_select_groups_for_their_own_task_pass(argv, tmp_path):
    assert precheck([*argv, f"hydra.sweep.dir={tmp_path / 's'}", f"hydra.run.dir={tmp_path / 'r'}"]) is None


def _cli(argv):
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


def test_cli_exits_2_with_one_line(tmp_path):
    code, lines = _cli(["task=liu_dgpt", "consensus=ci", f"hydra.run.dir={tmp_path / 'r'}"])
    assert code == 2 and lines == ["dslearn-run: configuration error: task=liu_dgpt does not use the root group "
                                   "consensus (its fusion is task.aggregations); remove consensus=ci"], lines
    code, lines = _cli(["-m", "experiment=braga_tbn", "model=lin,gp", f"hydra.sweep.dir={tmp_path / 's'}"])
    assert code == 2 and len(lines) == 1 and "task=braga_tbn does not use the root group model (" in lines[0], lines
    assert not (tmp_path / "r").exists() and not (tmp_path / "s").exists()
