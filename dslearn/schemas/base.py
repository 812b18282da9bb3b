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
5. **What each part reads of its own config node** (:func:`unread_keys`): the class or factory a node's
   ``_target_`` names declares the keys it reads (``config_reads``) and those it does not read with this
   composed configuration (``config_unused``); an override of a key inside a root group that the chosen
   part does not read is refused too, naming the key and why (:func:`check_part_keys`, from
   :func:`check_overrides`), in the tasks that build that group's option as the part (``parts=`` of
   :func:`register_task`).

Constructors then check only what needs the built objects (shapes, connectivity).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable

from omegaconf import DictConfig, ListConfig, OmegaConf

from dslearn.errors import ConfigError, check_rules
from dslearn.settings import RULES, ranged  # noqa: F401  (the rules this layer applies)


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
            check_rules(name, v, rules)  # its length
            if rules.get("each"):
                for i, x in enumerate(v):
                    check_rules(f"{name}[{i}]", x, rules)
            continue
        if rules.get("each"):
            continue
        check_rules(name, v, rules)


#: the root config groups a task may read besides its own ``task`` node (``conf/config.yaml``'s defaults)
ROOT_GROUPS = ("scenario", "network", "model", "observation", "consensus", "filter", "data", "learner", "associator")
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

#: what a task that does not read the ``associator`` group associates with instead (unless it says so itself): the
#: associator of a matrix cell's method is a part (``conf/associator``) of task=matrix only
ASSOCIATOR_INSTEAD = {"associator": "its measurements come labelled with their targets; associator= selects the "
                                    "associator of a matrix cell's method, task=matrix"}


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """A task's schema, cross-field check and what it reads of the root groups.

    ``uses``: the root groups (:data:`ROOT_GROUPS`, :data:`PRESET_GROUPS`) the task reads, or keys under one it
    reads alone (``"consensus.iterations"``); a function of the composed config where that depends on the task's
    own keys. ``instead``: per root group it does not use, what it uses instead (for the message).
    ``unused``: a function of the composed config giving task keys this configuration does not read
    (``{"task.aggregations": "why"}``). ``parts``: the root groups whose option the task builds as the part it
    names (``_target_``), so that the part's own declaration of the keys it reads applies (:func:`unread_keys`).
    Overriding any key not read is refused by :func:`check_overrides`."""

    name: str
    schema: type
    check: Callable[[DictConfig], None] | None = None
    uses: Any = ()
    instead: dict = dataclasses.field(default_factory=dict)
    unused: Callable[[DictConfig], dict] | None = None
    parts: tuple = ()


#: task name -> its schema and cross-field check (filled by :func:`register_task`)
TASKS: dict[str, TaskSpec] = {}


def register_task(name: str, schema: type, check: Callable[[DictConfig], None] | None = None, *,
                  uses, instead: dict | None = None, unused: Callable[[DictConfig], dict] | None = None,
                  parts=()) -> type:
    """Store ``schema`` as ``schema/task/<name>`` in Hydra's ConfigStore and remember its check and
    the root groups it reads (``uses``, see :class:`TaskSpec`; every task declares them)."""
    from hydra.core.config_store import ConfigStore

    paths = () if callable(uses) else tuple(uses)
    bad = [u for u in paths + tuple(parts) if u.split(".")[0] not in ROOT_GROUPS + PRESET_GROUPS]
    if bad:
        raise TypeError(f"task {name}: uses={bad} names no root group; root groups: {list(ROOT_GROUPS + PRESET_GROUPS)}")
    ConfigStore.instance().store(group="schema/task", name=name, node=schema)
    TASKS[name] = TaskSpec(name, schema, check, uses if callable(uses) else paths,
                           {**PRESET_INSTEAD, **LEARNER_INSTEAD, **ASSOCIATOR_INSTEAD, **(instead or {})}, unused, tuple(parts))
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
    sets counts: an experiment file that selects groups for its own task is not an override here. Then a key
    inside a root group that the chosen part does not read (:func:`check_part_keys`)."""
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
    check_part_keys(cfg, overrides)


# ------------------------------------------------------------------------------------------------
# what each part reads of its own config node

#: keys of a part's config node that name, label or build it rather than set something it reads
PART_KEYS = ("_target_", "_partial_", "name")


def part_class(target) -> Any:
    """The class or factory function a ``_target_`` names (a ``Class.factory`` classmethod: its class); ``None``
    where it cannot be imported (its builder reports that, naming the key)."""
    from hydra.utils import get_object

    try:
        obj = get_object(str(target))
    except Exception:  # noqa: BLE001 - hydra raises ImportError / plain Exception
        return None
    return getattr(obj, "__self__", obj)


def option_target(group: str, name: str) -> str | None:
    """The ``_target_`` of option ``name`` of ``group`` (its YAML file, following the defaults list within the
    group where the file names none); ``None`` where there is no such option."""
    from dslearn.conf_paths import CONF_DIRS

    return _option_target(group, name, tuple(CONF_DIRS))


@functools.lru_cache(maxsize=1024)
def _option_target(group: str, name: str, dirs: tuple) -> str | None:
    CONF_DIRS = dirs
    seen = set()
    while name and name not in seen:
        seen.add(name)
        path = next((d / group / f"{name}.yaml" for d in CONF_DIRS if (d / group / f"{name}.yaml").is_file()), None)
        if path is None:
            return None
        node = OmegaConf.load(path)
        if node.get("_target_"):
            return str(node._target_)
        parents = [str(d) for d in (node.get("defaults") or []) if isinstance(d, str) and d != "_self_"]
        name = parents[0] if parents else None
    return None


def _flag(target, attr: str, default=False):
    cls = part_class(target) if target else None
    return getattr(cls, attr, default) if cls is not None else default


def _label(cfg: DictConfig, group: str) -> str:
    node = cfg.get(group)
    name = node.get("name") if isinstance(node, DictConfig) else None
    return f"{group}={name}" if name else group


def online_learning(cfg: DictConfig, part: str | None = None) -> str | None:
    """``None`` where, with this composed configuration, the motion model (``part="model"``), or any part
    (``part=None``), learns online while tracking; else why not (a phrase naming the parts).

    What learns online: a motion or observation model whose class declares ``config_learns_online`` (the GPs),
    with a learner whose class lets it (``config_online_parts``: the parts it lets learn online; ``learner=online``
    both, ``offline`` the observation model, ``backprop`` the motion model, ``none`` neither). Without a learner
    part (every task but the matrix, or ``learner: null``) the parts learn as they declare. The motion models
    are ``task.models`` where the task has them (``task=yu_faults``, ``ethucy_tracking``), else the root ``model``."""
    uses = {u.split(".")[0] for u in task_uses(cfg)}
    learner = cfg.get("learner") if "learner" in uses else None
    lets, lname = ("model", "observation"), None
    if isinstance(learner, DictConfig) and learner.get("_target_"):
        cls = part_class(learner._target_)
        if cls is None:
            return None
        lets = tuple(getattr(cls, "config_online_parts", lets))
        lname = f"learner={getattr(cls, 'name', learner._target_)}"
    models = None
    names = cfg.task.get("models") if isinstance(cfg.get("task"), DictConfig) else None
    if names is not None:
        targets, models = [], ", ".join(str(m) for m in names)
        for m in names:
            t = option_target("model", str(m))
            if t is None and isinstance(cfg.get("model"), DictConfig):  # an alias of the root model (ethucy_tracking: gp)
                t = cfg.model.get("_target_")
            if t is None:
                return None  # not known here: taken as read
            targets.append(t)
        models = f"task.models=[{models}]"
    else:
        targets = [cfg.model.get("_target_")] if isinstance(cfg.get("model"), DictConfig) else []
        models = _label(cfg, "model")
    model_online = any(_flag(t, "config_learns_online") for t in targets)
    obs = cfg.get("observation") if "observation" in uses else None
    obs_online = isinstance(obs, DictConfig) and _flag(obs.get("_target_"), "config_learns_online")
    if part == "model":
        if "model" in lets and model_online:
            return None
        if lname is not None and "model" not in lets:
            return f"with {lname} the motion model learns nothing online"
        return f"{models} learns nothing online"
    if ("model" in lets and model_online) or ("observation" in lets and obs_online):
        return None
    if lname is not None:
        return f"with {lname} nothing learns online"
    return f"with {models} and {_label(cfg, 'observation')} nothing learns online"


def _who(group: str, prefix: str, node: DictConfig, cls: Any) -> str:
    name = node.get("name") if prefix == group else None
    if isinstance(name, str) and name:
        return f"{group}={name}"
    label = getattr(cls, "config_label", None)
    if label:
        return str(label)
    name = getattr(cls, "name", None)
    if isinstance(name, str) and name and prefix == group:
        return f"{group}={name}"
    return f"{prefix}._target_={node.get('_target_')}"


def _unread(cfg: DictConfig, node: DictConfig, group: str, prefix: str, out: dict) -> None:
    target = node.get("_target_")
    cls = part_class(target) if target else None
    if cls is None:
        return
    who = _who(group, prefix, node, cls)
    keys = [str(k) for k in node.keys() if k not in PART_KEYS]
    reads = getattr(cls, "config_reads", None)
    if reads is not None:
        why = getattr(cls, "config_unread", "it does not read it")
        for k in keys:
            if k not in reads:
                out[f"{prefix}.{k}"] = (who, why)
    hook = hook_of(cls)
    if hook is not None:
        for k, why in (hook(cfg, node) or {}).items():
            w, why = why if isinstance(why, tuple) else (who, why)
            out.setdefault(f"{prefix}.{k}", (w, why))
    for k in keys:
        if f"{prefix}.{k}" in out:
            continue
        try:
            sub = node.get(k)
        except Exception:  # noqa: BLE001 - an interpolation that does not resolve here: its builder says so
            continue
        if isinstance(sub, DictConfig) and sub.get("_target_"):
            _unread(cfg, sub, group, f"{prefix}.{k}", out)


def unread_keys(cfg: DictConfig, group: str) -> dict[str, tuple[str, str]]:
    """The keys of root group ``group``'s node that its part does not read with the composed configuration
    ``cfg``: ``{full key: (the part, why)}``.

    The part is the class or factory its ``_target_`` names (and, for a nested node with a ``_target_`` of its
    own such as ``filter.predict``, that one). It declares what it reads:

    * ``config_reads``: the keys of its node it reads (besides :data:`PART_KEYS`); every other key of the node is
      not read, for the reason ``config_unread`` (a phrase). Without it every key is read (the builder passes
      each to the constructor, which refuses a key it does not take);
    * a conditional rule ``(cfg, node) -> {key: why}`` (or ``{key: (the part, why)}`` to name another part as the
      reason): the keys of its node (dotted below it) that it does not read with this composed configuration, e.g.
      the distributed filter's learning gate where nothing learns online (:func:`online_learning`). A rule that
      reads only the part's own node is its ``config_unused``; one that reads other parts of the configuration is
      kept in this module (:func:`hook_of`), so the parts stay free of the config machinery."""
    node = cfg.get(group)
    out: dict[str, tuple[str, str]] = {}
    if isinstance(node, DictConfig):
        _unread(cfg, node, group, group, out)
    return out


def check_part_keys(cfg: DictConfig, overrides) -> None:
    """Refuse an override (``(key, line)`` pairs, as :func:`check_overrides`) of a key inside a root group that
    the task builds as a part (``parts=`` of :func:`register_task`) where that part does not read it
    (:func:`unread_keys`), and a method preset combined with a part that cannot take a key the preset sets
    (:func:`check_preset_keys`)."""
    spec = TASKS.get(str(cfg.task.name))
    if spec is None:
        return
    check_preset_keys(cfg, overrides)
    if not spec.parts:
        return
    cache: dict[str, dict] = {}
    for key, line in overrides:
        head, _, rest = key.partition(".")
        if not rest or head not in spec.parts:
            continue
        if head not in cache:
            cache[head] = unread_keys(cfg, head)
        for k, (who, why) in cache[head].items():
            if _within(key, k):
                raise ConfigError(f"{k} is not used by {who} ({why}); remove {line}")


def _preset_file(name: str):
    from dslearn.conf_paths import CONF_DIRS

    return _load_preset(name, tuple(CONF_DIRS))


@functools.lru_cache(maxsize=256)
def _load_preset(name: str, dirs: tuple):
    for d in dirs:
        p = d / "method" / f"{name}.yaml"
        if p.is_file():
            return OmegaConf.load(p)
    return None


def preset_choices(name: str) -> tuple[dict[str, str], dict[str, list[str]]]:
    """What method preset ``name`` (``conf/method/<name>.yaml``) selects, ``{group: option}``, and the keys it
    sets inside root groups, ``{group: [key, ...]}``."""
    node = _preset_file(name)
    if node is None:
        return {}, {}
    choices = {}
    for d in node.get("defaults") or []:
        if isinstance(d, DictConfig):
            for k, v in d.items():
                g = str(k).replace("override", "").strip().lstrip("/")
                if g in ROOT_GROUPS:
                    choices[g] = str(v)
    keys = {str(g): [str(k) for k in sub.keys()] for g, sub in node.items()
            if g in ROOT_GROUPS and isinstance(sub, DictConfig)}
    return choices, keys


def _chosen(overrides) -> dict[str, str]:
    """``{group: option}`` of the group choices among ``(key, line)`` overrides."""
    out = {}
    for key, line in overrides:
        if "." not in key and "=" in line and not line.startswith(("~", "+")):
            out[key] = line.split("=", 1)[1]
    return out


def check_preset_keys(cfg: DictConfig, overrides) -> None:
    """A method preset (``method=<preset>``) that sets a key inside a root group (``learner.learn``) combined with
    another option of that group on the command line that takes no such key is refused, naming what the user
    wrote (not a key the user never wrote)."""
    import inspect

    from hydra.utils import get_object

    chosen = _chosen(overrides)
    preset = chosen.get("method")
    if not preset:
        return
    picks, keys = preset_choices(preset)
    for group, ks in keys.items():
        option = chosen.get(group)
        node = cfg.get(group)
        if option is None or option == picks.get(group) or not isinstance(node, DictConfig) or not node.get("_target_"):
            continue
        try:
            params = inspect.signature(get_object(str(node._target_))).parameters
        except Exception:  # noqa: BLE001 - its builder reports it
            continue
        if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
            continue
        bad = [k for k in ks if k not in params]
        if bad:
            sets = ", ".join(f"{group}.{k}" for k in bad)
            others = " ".join(f"{g}={o}" for g, o in picks.items() if g != group)
            raise ConfigError(f"method={preset} sets {sets}; {group}={option} takes no {', '.join(bad)}: remove "
                              f"{group}={option} (the preset's {group}={picks.get(group)}), or choose the parts "
                              f"without the preset: {others} {group}={option}")


def preset_replaced(lines) -> str | None:
    """The parts of a method preset that the command line replaces (``method=ekf_lin_hybrid consensus=ci`` ->
    ``method=ekf_lin_hybrid with consensus=ci in place of its consensus=hybrid``), ``None`` where it replaces none
    (or no preset is chosen)."""
    pairs = []
    for line in lines:
        key = line.split("=", 1)[0]
        if "=" in line and not key.startswith(("~", "+", "hydra")) and "@" not in key:
            pairs.append((key, line))
    chosen = _chosen(pairs)
    preset = chosen.get("method")
    if not preset or preset == "null":
        return None
    picks, _ = preset_choices(preset)
    swapped = [(g, o) for g, o in chosen.items() if g in picks and o != picks[g]]
    if not swapped:
        return None
    return (f"method={preset} with " + ", ".join(f"{g}={o}" for g, o in swapped) + " in place of its "
            + ", ".join(f"{g}={picks[g]}" for g, _ in swapped))


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

# ------------------------------------------------------------------------------------------------
# What a part does not read with the rest of a composed configuration: rules that depend on other parts (the
# learner, the fusion, the task) live here, keyed by the part they speak for, so the parts below this layer
# stay free of the config machinery (tests/test_layers.py); a rule that reads only the part's own node is the
# part's ``config_unused``.

def filter_unused(cfg: DictConfig, node: DictConfig) -> dict:
    """The distributed filter's ``learn_gate_std`` where nothing learns online with ``cfg``
    (:func:`online_learning`): the gate only keeps estimates out of the online data sets."""
    why = online_learning(cfg) if "learn_gate_std" in node else None
    if why is None:
        return {}
    return {"learn_gate_std": f"{why}: the learning gate only keeps estimates out of the data sets learned online"}


def gp_unused(cfg: DictConfig, node: DictConfig) -> dict:
    """The keys of a GP motion model's node (``conf/model/gp*.yaml``) that it does not read with ``cfg``: the
    refit's and the adaptive noise's keys where it learns nothing online (``learner=none``: no data, the GP is its
    prior); ``fit_iters``, ``fit_lr`` with ``fit_every=0`` (fixed hyperparameters); ``noise_fading`` unless
    ``noise=adaptive``."""
    out = {}
    why = online_learning(cfg, "model")
    if why is not None:
        for k in ("fit_every", "fit_iters", "fit_lr", "noise_fading"):
            if k in node:
                out[k] = f"{why}: the GP gathers no data and stays its prior"
    elif node.get("fit_every") == 0:
        for k in ("fit_iters", "fit_lr"):
            if k in node:
                out[k] = "model.fit_every=0: the hyperparameters are never refitted"
    if "noise_fading" in node and node.get("noise") != "adaptive":
        out.setdefault("noise_fading", f"model.noise={node.get('noise')}: only noise=adaptive fades a noise estimate")
    return out


def network_unused(cfg: DictConfig, node: DictConfig) -> dict:
    """The keys of a network node (:func:`~dslearn.sim.placement.make_network`) not read with ``cfg``:
    ``comm_radius`` and ``k_nearest`` where ``edges`` give the links, ``comm_radius`` where ``k_nearest`` does; and
    where the fusion part sends nothing over the links (an individual node, a fusion centre: its class's
    ``uses_links``) the links themselves, ``edges``, and the rules that make them where the positions are given
    (with random positions they still decide which draw is connected)."""
    out: dict[str, Any] = {}
    if node.get("edges") is not None:
        out.update({k: "network.edges gives the links" for k in ("comm_radius", "k_nearest")})
    elif node.get("k_nearest") is not None:
        out["comm_radius"] = "network.k_nearest gives the links"
    spec = TASKS.get(str(cfg.task.name))
    cons = cfg.get("consensus")
    if spec is None or "consensus" not in spec.parts or cons is None or not cons.get("_target_"):
        return out
    cls = part_class(cons._target_)
    if cls is None or getattr(cls, "uses_links", True):
        return out
    who = f"consensus={cons.get('name') or cons._target_}"
    why = f"{getattr(cls, 'config_unread', 'it sends nothing over the links')}; no links between nodes are used"
    keys = ("edges",) if node.get("positions") is None else ("edges", "comm_radius", "k_nearest")
    for k in keys:
        out.setdefault(k, (who, why))
    return out


@functools.lru_cache(maxsize=1)
def hooks() -> dict[Any, Callable[[DictConfig, DictConfig], dict]]:
    """Part (the class or factory a ``_target_`` names, as :func:`part_class` gives it) ->
    its conditional rule. Imported on first use: the parts import PyTorch."""
    from dslearn.methods.distributed import DistributedFilter
    from dslearn.models.aggregated import aggregated_for_scenario
    from dslearn.models.gp import GPMotionModel
    from dslearn.models.gp_cv import gp_cv_for_scenario
    from dslearn.sim.placement import make_network

    return {DistributedFilter: filter_unused, GPMotionModel: gp_unused, gp_cv_for_scenario: gp_unused,
            aggregated_for_scenario: gp_unused, make_network: network_unused}


def hook_of(part: Any) -> Callable[[DictConfig, DictConfig], dict] | None:
    """The conditional rule of ``part`` (its own ``config_unused`` where it declares one, e.g. a learner's
    optimiser settings, else this layer's), ``None`` where it has none."""
    own = getattr(part, "config_unused", None)
    if own is not None:
        return own
    try:
        return hooks().get(part)
    except TypeError:  # an unhashable target
        return None
