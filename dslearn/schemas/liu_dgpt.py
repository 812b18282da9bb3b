"""Schema of task ``liu_dgpt`` (Liu et al., FUSION 2022): keys, types, ranges and cross-field rules.

Linked from ``conf/task/liu_dgpt.yaml`` (``/schema/task/liu_dgpt@_here_``), so Hydra refuses an
unknown ``task.*`` key or a wrong type at composition. The values themselves live in the task file
(every field here is mandatory, ``???``), with the S1-S3 generators (``task.scenario_params.s1..s3``:
``_target_`` + ``_partial_`` + parameters). A cell of the grid is chosen with the task's own keys:
``task.tracker``, ``task.aggregations``, ``task.gp_input``, ``task.scenarios``, ``task.noises``; of the
root groups the study reads only ``scenario``, and only a Liu scenario option (``scenario=s1|s2|s3``,
:func:`selected_scenario`).

:func:`check` holds what a schema cannot state: the hyperparameter box, duplicates and the tracker
vs. aggregation rules; :func:`unused` names the task keys a tracker does not read.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional

from omegaconf import MISSING, DictConfig

from dslearn.errors import ConfigError
from dslearn.filters.dgpt import GP_INPUTS, OPTIMISERS
from dslearn.fusion.aggregation import AGGREGATIONS
from dslearn.schemas.base import ranged, register_task
from dslearn.sim.manoeuvres import SCENARIOS, generator_target

TRACKERS = ("dgpt", "gp")
_POS = dict(gt=0.0)


@dataclass
class Hyper:
    optimizer: str = ranged(MISSING, choices=OPTIMISERS)
    lr: float = ranged(MISSING, **_POS)
    iters: int = ranged(MISSING, ge=0)
    iters_first: int = ranged(MISSING, ge=0)
    tol: float = ranged(MISSING, **_POS)
    max_iters: int = ranged(MISSING, ge=1)
    gap_check: bool = MISSING
    init_outputscale: float = ranged(MISSING, **_POS)
    init_lengthscale_t: float = ranged(MISSING, **_POS)
    init_lengthscale_r: float = ranged(MISSING, **_POS)
    init_noise: float = ranged(MISSING, **_POS)
    min_noise: float = ranged(MISSING, **_POS)
    max_noise: float = ranged(MISSING, **_POS)
    min_outputscale: float = ranged(MISSING, **_POS)
    max_outputscale: float = ranged(MISSING, **_POS)
    min_lengthscale: float = ranged(MISSING, **_POS)
    max_lengthscale: float = ranged(MISSING, **_POS)


@dataclass
class S1:
    """``dslearn.sim.manoeuvres.generate_s1`` (``_partial_``: runs, steps, generator at run time)."""
    _target_: str = ranged(MISSING, choices=(generator_target("s1"),))
    _partial_: bool = ranged(MISSING, choices=(True,))
    turn_every: int = ranged(MISSING, ge=1)
    speeds: List[float] = ranged(MISSING, each=True, ge=0.0, min_len=1)
    headings_deg: List[float] = ranged(MISSING, each=True, ge=-360.0, le=360.0, min_len=1)
    accel_std: float = ranged(MISSING, ge=0.0)


@dataclass
class S2:
    _target_: str = ranged(MISSING, choices=(generator_target("s2"),))
    _partial_: bool = ranged(MISSING, choices=(True,))
    a_max: float = ranged(MISSING, ge=0.0)
    p_zero: float = ranged(MISSING, ge=0.0, le=1.0)
    p_max: float = ranged(MISSING, ge=0.0, le=1.0)
    tau: float = ranged(MISSING, **_POS)
    v0: float = ranged(MISSING, ge=0.0)
    v_max: float = ranged(MISSING, **_POS)


@dataclass
class S3:
    _target_: str = ranged(MISSING, choices=(generator_target("s3"),))
    _partial_: bool = ranged(MISSING, choices=(True,))
    speed: float = ranged(MISSING, ge=0.0)
    turn_rate_deg: float = MISSING
    turn_duration: float = ranged(MISSING, **_POS)
    straight: float = ranged(MISSING, ge=0.0)
    accel_std: float = ranged(MISSING, ge=0.0)


@dataclass
class ScenarioParams:
    s1: S1 = field(default_factory=S1)
    s2: S2 = field(default_factory=S2)
    s3: S3 = field(default_factory=S3)


@dataclass
class Window:
    s1: int = ranged(MISSING, ge=1)
    s2: int = ranged(MISSING, ge=1)
    s3: int = ranged(MISSING, ge=1)


@dataclass
class Trace:
    scenario: str = ranged(MISSING, choices=SCENARIOS)
    noise: float = ranged(MISSING, **_POS)
    episodes: int = ranged(MISSING, ge=0)


@dataclass
class LiuDgpt:
    entry: str = MISSING
    name: str = MISSING
    gp_input: str = ranged(MISSING, choices=GP_INPUTS)
    tracker: Optional[str] = ranged(None, choices=TRACKERS)  # null = the rules (+ the standard GP if centralised)
    scenarios: List[str] = ranged(MISSING, each=True, choices=SCENARIOS, min_len=1)
    noises: List[float] = ranged(MISSING, each=True, min_len=1, **_POS)
    aggregations: List[str] = ranged(MISSING, each=True, choices=AGGREGATIONS)
    grbcm_comm_points: int = ranged(MISSING, ge=1)
    centralised: bool = MISSING
    normalise_beta: bool = MISSING
    mc_runs: int = ranged(MISSING, ge=1)
    batch_runs: int = ranged(MISSING, ge=1)
    num_sensors: int = ranged(MISSING, ge=1)
    sensing_range: float = ranged(MISSING, **_POS)
    area_size: float = ranged(MISSING, **_POS)
    num_steps: int = ranged(MISSING, ge=2)
    dt: float = ranged(MISSING, **_POS)
    window: Window = field(default_factory=Window)
    ucb_delta: float = ranged(MISSING, gt=0.0, lt=1.0)
    torch_threads: Optional[int] = ranged(MISSING, ge=1)
    hyper: Hyper = field(default_factory=Hyper)
    scenario_params: ScenarioParams = field(default_factory=ScenarioParams)
    trace: Trace = field(default_factory=Trace)


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


def methods(t) -> tuple[list[str], bool]:
    """The aggregation rules the study runs and whether it runs the centralised standard GP:
    ``task.tracker`` null = ``task.aggregations`` (+ the standard GP if ``task.centralised``),
    ``dgpt`` = ``task.aggregations`` alone, ``gp`` = the standard GP alone."""
    if t.tracker == "gp":
        return [], True
    return [str(a) for a in t.aggregations], t.tracker is None and bool(t.centralised)


def unused(cfg: DictConfig) -> dict[str, str]:
    """The task keys the chosen ``task.tracker`` does not read (an override of them is refused)."""
    tr = cfg.task.get("tracker")
    if tr == "gp":
        why = "with task.tracker=gp (the centralised standard GP alone)"
        return {"task.aggregations": why, "task.centralised": why}
    if tr == "dgpt":
        return {"task.centralised": "with task.tracker=dgpt (the aggregation rules alone)"}
    return {}


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

register_task("liu_dgpt", LiuDgpt, check, uses=uses, instead=INSTEAD, unused=unused)
