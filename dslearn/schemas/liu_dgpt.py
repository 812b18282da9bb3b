"""Schema of task ``liu_dgpt`` (Liu et al., FUSION 2022): keys, types, ranges and cross-field rules.

Linked from ``conf/task/liu_dgpt.yaml`` (``/schema/task/liu_dgpt@_here_``), so Hydra refuses an
unknown ``task.*`` key or a wrong type at composition. The values themselves live in the YAML
files (every field here is mandatory, ``???``): the task file (with the S1-S3 generators,
``task.scenario_params.s1..s3``: ``_target_`` + ``_partial_`` + parameters), and the group options
``conf/tracker/``, ``conf/aggregation/``, ``conf/gp_input/`` (``# @package task``: they write
``task.tracker`` / ``task.aggregations`` / ``task.centralised`` / ``task.gp_input``).

:func:`check` holds what a schema cannot state: the hyperparameter box, duplicates, the tracker
vs. aggregation rules and the top-level ``noise`` value (``conf/liu_keys/default.yaml``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import List, Optional

from omegaconf import MISSING, DictConfig, ListConfig

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
    tracker: Optional[str] = ranged(None, choices=TRACKERS)  # null = the rules + the standard GP
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


def _plain_noise(v):
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        return [v]
    if isinstance(v, (ListConfig, list, tuple)):
        return list(v)
    raise ConfigError(f"noise={v!r} must be a number > 0 (e.g. noise=2) or a list of them")


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
    aggs = list(t.aggregations)
    if t.tracker == "gp":
        if aggs:
            raise ConfigError(f"tracker=gp (the centralised standard GP) takes no aggregation; got "
                              f"task.aggregations={aggs}: use tracker=dgpt aggregation={aggs[0]}")
        if not t.centralised:
            raise ConfigError("tracker=gp runs the centralised standard GP: task.centralised must be true")
    elif not aggs:
        raise ConfigError(f"task.aggregations must not be empty; choose from {list(AGGREGATIONS)} "
                          f"(tracker=gp runs the standard GP alone)")
    if t.tracker == "dgpt" and t.centralised:
        raise ConfigError("tracker=dgpt runs the aggregation rule(s) only: task.centralised must be false "
                          "(unset tracker to run both)")
    nz = cfg.get("noise")
    if nz is not None:
        vals = _plain_noise(nz)
        if not vals:
            raise ConfigError("noise must not be empty")
        for i, n in enumerate(vals):
            name = "noise" if len(vals) == 1 else f"noise[{i}]"
            if isinstance(n, bool) or not isinstance(n, (int, float)) or not math.isfinite(n) or n <= 0:
                raise ConfigError(f"{name}={n!r} must be a number > 0")


register_task("liu_dgpt", LiuDgpt, check)
