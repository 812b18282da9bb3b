"""Schema of task ``liu_dgpt`` (Liu et al., FUSION 2022): keys, types, ranges and cross-field rules.

The schema is the study's settings, :class:`dslearn.studies.liu_dgpt.LiuDgpt` (with its field rules),
linked from ``conf/task/liu_dgpt.yaml`` (``/schema/task/liu_dgpt@_here_``), so Hydra refuses an
unknown ``task.*`` key or a wrong type at composition. The values themselves live in the task file
(every field is mandatory), with the S1-S3 generators (``task.scenario_params.s1..s3``:
``_target_`` + ``_partial_`` + parameters). A cell of the grid is chosen with the task's own keys:
``task.tracker``, ``task.aggregations``, ``task.gp_input``, ``task.scenarios``, ``task.noises``; of the
root groups the study reads only ``scenario``, and only a Liu scenario option (``scenario=s1|s2|s3``,
:func:`selected_scenario`).

:func:`check` holds what a schema cannot state: the hyperparameter box, duplicates and the tracker
vs. aggregation rules; :func:`unused` names the task keys a tracker does not read. The config logic
the study needs is the slot ``liu_dgpt_generators`` (:func:`generators`, registered with the
composition root): the root ``scenario`` group's selection and the generators' instantiation.
"""

from __future__ import annotations

from omegaconf import DictConfig

from dslearn.compose import build, register_slot
from dslearn.errors import ConfigError
from dslearn.fusion.aggregation import AGGREGATIONS
from dslearn.schemas.base import register_task
from dslearn.sim.manoeuvres import SCENARIOS, generator_target
from dslearn.studies.liu_dgpt import LiuDgpt  # the task's settings are its schema


def selected_scenario(cfg: DictConfig) -> str | None:
    """The Liu scenario chosen with the top-level ``scenario=s1|s2|s3`` group, or None.

    A Liu scenario option carries its generator (``_target_`` one of the S1-S3 generators, as in
    ``task.scenario_params``); any other ``scenario`` node (the root default ``yu_two_agents``,
    the Yu study's scenario) selects nothing, so the task's own ``task.scenarios`` list runs.
    """
    sc = cfg.get("scenario")
    target = sc.get("_target_") if isinstance(sc, DictConfig) else None
    for s in SCENARIOS:
        if target == generator_target(s):
            return s
    return None


def check(cfg: DictConfig) -> None:
    """Cross-field rules of ``liu_dgpt`` (ranges and types are the schema's)."""
    t = cfg.task
    h = t.hyper
    for lo, hi, inits in (("min_noise", "max_noise", ("init_noise",)),
                          ("min_outputscale", "max_outputscale", ("init_outputscale",)),
                          ("min_lengthscale", "max_lengthscale", ("init_lengthscale_t", "init_lengthscale_r"))):
        for f in inits:
            if not h[lo] <= h[f] <= h[hi]:
                raise ConfigError(f"task.hyper.{f}={h[f]!r} must lie in [task.hyper.{lo}, task.hyper.{hi}] "
                                  f"= [{h[lo]!r}, {h[hi]!r}]")
    for key in ("aggregations", "scenarios", "noises"):
        vals = list(t[key])
        if len(set(vals)) != len(vals):
            raise ConfigError(f"task.{key}={vals} has duplicates")
    if t.tracker != "gp" and not list(t.aggregations):
        raise ConfigError(f"task.aggregations must not be empty; choose from {list(AGGREGATIONS)} "
                          f"(task.tracker=gp runs the standard GP alone)")


def unused(cfg: DictConfig) -> dict[str, str]:
    """The task keys the chosen ``task.tracker`` does not read, and the keys of ``task.hyper`` its optimiser does
    not read (:func:`~dslearn.learning.learners.hyper_unused`; an override of them is refused)."""
    from dslearn.learning.learners import hyper_unused

    tr = cfg.task.get("tracker")
    out = {f"task.{k}": f"({why})" for k, why in hyper_unused(cfg.task.get("hyper"), "task.hyper").items()}
    if tr == "gp":
        why = "with task.tracker=gp (the centralised standard GP alone)"
        out.update({"task.aggregations": why, "task.centralised": why})
    elif tr == "dgpt":
        out["task.centralised"] = "with task.tracker=dgpt (the aggregation rules alone)"
    return out


def uses(cfg: DictConfig) -> tuple[str, ...]:
    """Of the root groups, the study reads ``scenario`` when it is a Liu scenario option (s1-s3)."""
    return ("scenario",) if selected_scenario(cfg) is not None else ()


#: what the study uses in place of each root group (all its parts are in ``task``)
INSTEAD = {
    "scenario": "its scenarios are task.scenarios with task.scenario_params; of the root group it takes "
                "only a Liu scenario, scenario=s1|s2|s3",
    "network": "its sensors are task.num_sensors, task.sensing_range and task.area_size",
    "model": "its motion model is the tracker's GP over task.gp_input, with task.hyper",
    "observation": "its sensors measure positions with the noise levels task.noises",
    "consensus": "its fusion is task.aggregations",
    "filter": "its tracker is task.tracker, with task.window and task.hyper",
    "data": "its Monte Carlo runs are task.mc_runs",
}


def generators(cfg: DictConfig, slots=None) -> dict:
    """Slot ``liu_dgpt_generators``: the trajectory generator of each scenario the run covers, in order:
    ``task.scenarios``, or the one a root ``scenario=s1|s2|s3`` selects (:func:`selected_scenario`), each
    instantiated from ``task.scenario_params.<s>`` (``_partial_``: runs, steps, random stream at run time)."""
    t = cfg.task
    sel = selected_scenario(cfg)
    scenarios = [sel] if sel is not None else [str(s) for s in t.scenarios]
    return {s: build(t.scenario_params[s], f"task.scenario_params.{s}") for s in scenarios}


register_task("liu_dgpt", LiuDgpt, check, uses=uses, instead=INSTEAD, unused=unused)
register_slot("liu_dgpt_generators", generators)
