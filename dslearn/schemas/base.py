r"""The validation layer's parts: range-checked schema fields, the task registry, the checks.

A study's configuration is checked in three stages, all before any work starts:

1. **Keys and types, at composition.** Every task has a structured-config schema (a dataclass)
   stored in Hydra's ConfigStore as ``schema/task/<name>`` and linked from its config file
   (``conf/task/<name>.yaml`` starts with ``defaults: [/schema/task/<name>@_here_, _self_]``).
   Hydra then refuses an unknown key or a value of the wrong type while it composes.
2. **Ranges and choices, declared on the fields.** ``ranged(default, ge=0)`` /
   ``ranged("a", choices=(...))`` put the rule in the field's metadata; :func:`check_ranges`
   applies every rule of a schema (recursively, also to each element of a list with
   ``each=True``) and raises :class:`~dslearn.errors.ConfigError` naming the field and the
   allowed values.
3. **Cross-field rules**, which a schema cannot state, in the one ``check(cfg)`` function a task
   registers with :func:`register_task`.
4. **What the task reads of the root groups** (``uses=`` of :func:`register_task`, with what it
   uses instead of the others): ``dslearn-run``'s start-up check refuses an override, on the
   command line or in a sweep, of a root group the task does not read (:func:`check_overrides`).

Constructors then check only what needs the built objects (shapes, connectivity).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

from omegaconf import DictConfig, ListConfig, OmegaConf

from dslearn.errors import ConfigError
from dslearn.settings import RULES, ranged  # noqa: F401  (the rules this layer applies)

def _fmt(v) -> str:
    return repr(v) if not isinstance(v, float) or math.isfinite(v) else str(v)


def _check_value(name: str, v, rules: dict) -> None:
    if v is None:
        return
    choices = rules.get("choices")
    if choices is not None and v not in choices:
        raise ConfigError(f"{name}={v!r} is not allowed; choose one of {list(choices)}")
    numeric = isinstance(v, (int, float)) and not isinstance(v, bool)
    if not numeric:
        return
    if isinstance(v, float) and not math.isfinite(v) and any(k in rules for k in ("ge", "gt", "le", "lt")):
        raise ConfigError(f"{name}={v} must be a finite number")
    lo_ge, lo_gt, hi_le, hi_lt = (rules.get(k) for k in ("ge", "gt", "le", "lt"))
    bounds = " and ".join(
        s for s in (
            f">= {_fmt(lo_ge)}" if lo_ge is not None else "", f"> {_fmt(lo_gt)}" if lo_gt is not None else "",
            f"<= {_fmt(hi_le)}" if hi_le is not None else "", f"< {_fmt(hi_lt)}" if hi_lt is not None else "",
        ) if s
    )
    if ((lo_ge is not None and v < lo_ge) or (lo_gt is not None and v <= lo_gt)
            or (hi_le is not None and v > hi_le) or (hi_lt is not None and v >= hi_lt)):
        raise ConfigError(f"{name}={v!r} must be {bounds}")


def check_ranges(node: Any, schema: type, prefix: str) -> None:
    """Apply the rules declared on ``schema``'s fields to ``node`` (a DictConfig / dict); a key the
    schema does not know (added with ``+key=...``, which bypasses Hydra's check) is an error too."""
    known = [f.name for f in dataclasses.fields(schema)]
    if isinstance(node, (DictConfig, dict)):
        unknown = sorted(str(k) for k in node.keys() if k not in known)
        if unknown:
            where = ", ".join(f"{prefix}.{k}" if prefix else k for k in unknown)
            raise ConfigError(f"{where}: unknown key; {prefix or 'the config'} takes {known}")
    for f in dataclasses.fields(schema):
        if isinstance(node, (DictConfig, dict)) and f.name not in node:
            continue
        v = node[f.name]
        name = f"{prefix}.{f.name}" if prefix else f.name
        rules = dict(f.metadata)
        sub = f.type if isinstance(f.type, type) and dataclasses.is_dataclass(f.type) else None
        if sub is None and dataclasses.is_dataclass(f.default_factory if f.default_factory is not dataclasses.MISSING else None):
            sub = f.default_factory
        if sub is not None and v is not None:
            check_ranges(v, sub, name)
            continue
        if isinstance(v, (ListConfig, list, tuple)):
            n = len(v)
            if "min_len" in rules and n < rules["min_len"]:
                raise ConfigError(f"{name} has {n} entries; it needs at least {rules['min_len']}")
            if "max_len" in rules and n > rules["max_len"]:
                raise ConfigError(f"{name} has {n} entries; it allows at most {rules['max_len']}")
            if rules.get("each"):
                for i, x in enumerate(v):
                    _check_value(f"{name}[{i}]", x, rules)
            continue
        if rules.get("each"):
            continue
        _check_value(name, v, rules)


#: the root config groups a task may read besides its own ``task`` node (``conf/config.yaml``'s defaults)
ROOT_GROUPS = ("scenario", "network", "model", "observation", "consensus", "filter", "data", "learner")
#: root groups whose options are presets: each selects options of other root groups (``conf/method/*.yaml``:
#: ``# @package _global_``, ``override /filter: ...``) and sets no key of its own. A task reads a preset group
#: only where it names it in ``uses`` (a task that reads every root group does not read them)
PRESET_GROUPS = ("method",)
#: what a task that does not name a preset group uses instead (unless it says so itself)
PRESET_INSTEAD = {"method": "method presets select the parts of a matrix cell, task=matrix"}
#: what a task that does not read the ``learner`` group learns with instead (unless it says so itself): the
#: learner of a matrix cell's method is a part (``conf/learner``) of task=matrix only
LEARNER_INSTEAD = {"learner": "what it learns is set by its own keys and parts; learner= selects the learner of a "
                              "matrix cell's method, task=matrix"}


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """A task's schema, cross-field check and what it reads of the root groups.

    ``uses``: the root groups (:data:`ROOT_GROUPS`, :data:`PRESET_GROUPS`) the task reads, or keys under one it
    reads alone (``"consensus.iterations"``); a function of the composed config where that depends on the task's
    own keys. ``instead``: per root group it does not use, what it uses instead (for the message).
    ``unused``: a function of the composed config giving task keys this configuration does not read
    (``{"task.aggregations": "why"}``). Overriding any of them is refused by :func:`check_overrides`."""

    name: str
    schema: type
    check: Callable[[DictConfig], None] | None = None
    uses: Any = ()
    instead: dict = dataclasses.field(default_factory=dict)
    unused: Callable[[DictConfig], dict] | None = None


#: task name -> its schema and cross-field check (filled by :func:`register_task`)
TASKS: dict[str, TaskSpec] = {}


def register_task(name: str, schema: type, check: Callable[[DictConfig], None] | None = None, *,
                  uses, instead: dict | None = None, unused: Callable[[DictConfig], dict] | None = None) -> type:
    """Store ``schema`` as ``schema/task/<name>`` in Hydra's ConfigStore and remember its check and
    the root groups it reads (``uses``, see :class:`TaskSpec`; every task declares them)."""
    from hydra.core.config_store import ConfigStore

    paths = () if callable(uses) else tuple(uses)
    bad = [u for u in paths if u.split(".")[0] not in ROOT_GROUPS + PRESET_GROUPS]
    if bad:
        raise TypeError(f"task {name}: uses={bad} names no root group; root groups: {list(ROOT_GROUPS + PRESET_GROUPS)}")
    ConfigStore.instance().store(group="schema/task", name=name, node=schema)
    TASKS[name] = TaskSpec(name, schema, check, uses if callable(uses) else paths,
                           {**PRESET_INSTEAD, **LEARNER_INSTEAD, **(instead or {})}, unused)
    return schema


def task_uses(cfg: DictConfig) -> tuple[str, ...]:
    """The root groups (or keys under one) the task of ``cfg`` reads with this configuration
    (every root group for a task that is not registered)."""
    spec = TASKS.get(str(cfg.task.name))
    if spec is None:
        return ROOT_GROUPS
    return tuple(spec.uses(cfg)) if callable(spec.uses) else tuple(spec.uses)


def _within(key: str, path: str) -> bool:
    return key == path or key.startswith(path + ".")


def check_overrides(cfg: DictConfig, overrides) -> None:
    """Refuse an override of a root group the task of ``cfg`` does not read, or of a task key this
    configuration does not read. ``overrides``: ``(key, line)`` pairs of the command line / sweep
    (``key`` = the group or the dotted key the line sets, e.g. ``consensus`` for ``consensus=ci``,
    ``consensus.iterations`` for ``consensus.iterations=3``). Only what the command line or a sweep
    sets counts: an experiment file that selects groups for its own task is not an override here."""
    spec = TASKS.get(str(cfg.task.name))
    if spec is None:
        return
    used = None
    unused = None
    for key, line in overrides:
        head = key.split(".")[0]
        if head in ROOT_GROUPS or head in PRESET_GROUPS:
            if used is None:
                used = task_uses(cfg)
            if any(_within(key, u) for u in used):
                continue
            inside = [u for u in used if u.split(".")[0] == head]
            why = spec.instead.get(head)
            tail = f" ({why})" if why else ""
            if inside:
                raise ConfigError(f"task={spec.name} uses only {', '.join(inside)} of the root group {head}{tail}; "
                                  f"remove {line}")
            raise ConfigError(f"task={spec.name} does not use the root group {head}{tail}; remove {line}")
        if head == "task" and spec.unused is not None:
            if unused is None:
                unused = spec.unused(cfg) or {}
            for k, why in unused.items():
                if _within(key, k):
                    raise ConfigError(f"{k} is not used by task={spec.name} {why}; remove {line}")


def validate_task(cfg: DictConfig) -> None:
    """Ranges of the task's schema, then its cross-field check (no-op for an unregistered task)."""
    spec = TASKS.get(str(cfg.task.name))
    if spec is None:
        return
    check_ranges(cfg.task, spec.schema, "task")
    if spec.check is not None:
        spec.check(cfg)


def to_plain(node: Any) -> Any:
    """A resolved plain container of ``node`` (DictConfig / ListConfig) or ``node`` itself."""
    if isinstance(node, (DictConfig, ListConfig)):
        return OmegaConf.to_container(node, resolve=True)
    return node
