r"""Schema of task ``jiang_fg`` (Jiang et al., ISITA 2022: factor-graph identification + EKF-FG).

The schema is the study's settings, :class:`dslearn.studies.jiang_fg.JiangTask`. Keys and types are
checked by Hydra at composition (``conf/task/jiang_fg.yaml`` is linked to it), ranges and choices by the field rules; :func:`check` holds the rules that need
several fields: every sensor / coefficient row / initial vector has M entries (M = the sensors'
coordinate count), finite numbers in the nested lists, ``num_samples >= 2`` with
``fg.measurement_var=sample``, and every ablation's fields (the same rules as ``fg``/``tracker``).

An ablation (``task.ablations.<name>``) overrides any of :class:`Ablation`'s keys; a key it leaves
out keeps the main grid's value. ``prior_var: null`` (no prior node) and ``gate: null`` (no gate)
are overrides, not omissions. ``task.ablations`` stays an open mapping in the composed config, so
``'+task.ablations.mine={relinearize:true}'`` works on the command line (OmegaConf refuses a plain
mapping for a ``Dict[str, Ablation]`` entry); :func:`ablation_values` then checks each entry's keys
and types against :class:`Ablation` (in :func:`check`, before any work), and the slot
``jiang_fg_ablations`` (:func:`ablations`, registered with the composition root) hands the study
each ablation's typed overrides.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional

from omegaconf import MISSING, DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from dslearn.compose import register_slot
from dslearn.errors import ConfigError
from dslearn.schemas.base import check_ranges, ranged, register_task
from dslearn.studies.jiang_fg import MAIN_VARIANT, SETTING_RULES, JiangTask  # noqa: F401  (the settings are the schema)


def _r(name: str, default=MISSING):
    """A field with the rules of the FG / tracker setting ``name`` (shared with the main grid's settings)."""
    return ranged(default, **SETTING_RULES[name])


@dataclass
class Ablation:
    """One variant: any FG / tracker setting (and ``max_iter``); omitted keys stay MISSING (= main grid)."""

    init_guess: Optional[List[float]] = MISSING
    init_guess_mode: Optional[str] = _r("init_guess_mode")
    init_var: Optional[float] = _r("init_var")
    prior_var: Optional[float] = _r("prior_var")
    relinearize: Optional[bool] = MISSING
    taylor_point: Optional[str] = _r("taylor_point")
    schedule: Optional[str] = _r("schedule")
    damping: Optional[float] = _r("damping")
    graph: Optional[str] = _r("graph")
    measurement_var: Optional[str] = _r("measurement_var")
    crlb_form: Optional[str] = _r("crlb_form")
    lambda_tol: Optional[float] = _r("lambda_tol")
    converge_tol: Optional[float] = _r("converge_tol")
    initial_state_var: Optional[float] = _r("initial_state_var")
    initial_gradient_var: Optional[float] = _r("initial_gradient_var")
    process_var: Optional[float] = _r("process_var")
    gradient_var: Optional[float] = _r("gradient_var")
    obs_var: Optional[str] = _r("obs_var")
    gate: Optional[float] = _r("gate")
    baseline_iters: Optional[int] = _r("baseline_iters")
    max_iter: Optional[int] = _r("max_iter")


def _vector(name: str, value, length: int | None) -> None:
    """``value`` a list of finite numbers (of ``length`` entries)."""
    ok = isinstance(value, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                                         for v in value)
    if not ok:
        raise ConfigError(f"{name}={value!r} must be a list of finite numbers")
    if length is not None and len(value) != length:
        raise ConfigError(f"{name}={value!r} must have {length} entries (one per parameter)")


def ablation_values(name: str, node) -> dict:
    """The settings ablation ``name`` overrides, typed by :class:`Ablation` (ConfigError for an unknown key
    or a wrong type; :func:`check` applies the ranges)."""
    if not isinstance(node, (dict, DictConfig)):
        raise ConfigError(f"task.ablations.{name}={node!r} must be a mapping of settings, e.g. {{relinearize: true}}")
    try:
        typed = OmegaConf.merge(OmegaConf.structured(Ablation), node)
    except OmegaConfBaseException as e:
        key = getattr(e, "full_key", None) or "?"
        msg = str(e).splitlines()[0]
        raise ConfigError(f"task.ablations.{name}.{key}: {msg} (allowed keys: {sorted([*SETTING_RULES, 'init_guess', 'relinearize'])})") from None
    return {k: OmegaConf.to_container(typed[k]) if OmegaConf.is_config(typed[k]) else typed[k]
            for k in typed if not OmegaConf.is_missing(typed, k)}


def check(cfg: DictConfig) -> None:
    """The cross-field rules of ``cfg.task`` (after the field rules); raises :class:`ConfigError`."""
    t = cfg.task
    sc = OmegaConf.to_container(t.scenario, resolve=True)
    for i, s in enumerate(sc["sensors"]):
        _vector(f"task.scenario.sensors[{i}]", s, None)
    M = len(sc["sensors"][0])
    if M < 1 or any(len(s) != M for s in sc["sensors"]):
        raise ConfigError(f"task.scenario.sensors={sc['sensors']!r}: every sensor needs the same number (>= 1) of "
                          "coordinates")
    if len(sc["coefficients"]) != M:
        raise ConfigError(f"task.scenario.coefficients={sc['coefficients']!r} needs {M} rows (one per parameter)")
    for m, c in enumerate(sc["coefficients"]):
        _vector(f"task.scenario.coefficients[{m}]", c, 3)
    _vector("task.scenario.initial_state", sc["initial_state"], M)
    _vector("task.fg.init_guess", list(t.fg.init_guess), M)
    if t.fg.measurement_var == "sample" and t.num_samples < 2:
        raise ConfigError(f"task.num_samples={t.num_samples} must be >= 2 with task.fg.measurement_var=sample")
    for name, node in t.ablations.items():
        if str(name) == MAIN_VARIANT:
            raise ConfigError(f"task.ablations.{name}: the name {MAIN_VARIANT!r} is the main grid's; choose another")
        over = ablation_values(str(name), node)
        check_ranges(over, Ablation, f"task.ablations.{name}")
        if "init_guess" in over:
            _vector(f"task.ablations.{name}.init_guess", over["init_guess"], M)
        mv = over.get("measurement_var", t.fg.measurement_var)
        if mv == "sample" and t.num_samples < 2:
            raise ConfigError(f"task.num_samples={t.num_samples} must be >= 2 with "
                              f"task.ablations.{name}.measurement_var=sample")


#: what the study uses in place of each root group (it reads none of them: every part is in ``task``)
INSTEAD = {
    "scenario": "its scenario is task.scenario (the field, Eqs. 20-22)",
    "network": "its sensors are task.scenario.sensors",
    "model": "its parameter model is task.scenario.coefficients with task.tracker's noise",
    "observation": "its sensors' noise is task.sigma_y with task.num_samples samples",
    "consensus": "its fusion is the factor graph of task.fg",
    "filter": "its filter is the EKF-FG of task.tracker",
    "data": "its Monte Carlo runs are task.mc_runs",
}

def ablations(cfg: DictConfig, slots=None) -> dict[str, dict]:
    """Slot ``jiang_fg_ablations``: each ablation's overrides (``task.ablations``, in order), typed by
    :class:`Ablation` (:func:`ablation_values`)."""
    return {str(name): ablation_values(str(name), node) for name, node in cfg.task.ablations.items()}


register_task("jiang_fg", JiangTask, check, uses=(), instead=INSTEAD)
register_slot("jiang_fg_ablations", ablations)
