r"""The composition root: every swappable part of a study is a config node that Hydra instantiates.

A part's config file names its implementation with ``_target_`` (a class, or a ``for_*``
factory classmethod that sizes the part from the run). ``_partial_: true`` marks a part whose
sizes are known only at run time (the number of nodes, the scenario's state, dtype, device,
the communication graph): :func:`build` instantiates it and then calls it with those of the run's
objects its signature names, and only those. ``name`` is the part's label (written into the
result tables): it is passed on only to a target that takes it.

Studies call :func:`build` (or :func:`build_parts` for the usual set) and never decode names.
"""

from __future__ import annotations

import functools
import inspect
from dataclasses import dataclass
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from dslearn.errors import ConfigError, check_choice
from dslearn.types import DTYPES

#: config keys that label a part rather than configure it
LABELS = ("name",)


def resolve_device(device: str) -> torch.device:
    """``cpu`` or ``cuda[:i]``; ConfigError when CUDA is asked for and absent."""
    check_choice("device", str(device).split(":")[0], ("cpu", "cuda"))
    if str(device).startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError("device=cuda was asked for but no CUDA device is available; use device=cpu")
    return torch.device(device)


def resolve_dtype(dtype: str) -> torch.dtype:
    check_choice("dtype", str(dtype), tuple(DTYPES))
    return DTYPES[str(dtype)]


def _target_params(target) -> dict[str, inspect.Parameter]:
    try:
        return dict(inspect.signature(target).parameters)
    except (TypeError, ValueError):
        return {}


def import_object(value: Any, name: str) -> Any:
    """The object an import path names (a part's ``_target_``, a sweeper's ``select``); a
    :class:`ConfigError` naming ``name=value`` where it cannot be imported."""
    from hydra.utils import get_object

    try:
        return get_object(str(value))
    except Exception as e:  # noqa: BLE001  (hydra raises ImportError / plain Exception)
        raise ConfigError(f"{name}={value!r} cannot be imported: {str(e).splitlines()[0]}") from None


def build(node: Any, prefix: str, **runtime: Any) -> Any:
    """Instantiate the config ``node`` (found at ``prefix``, e.g. ``model``); a ``_partial_`` node is
    then called with the ``runtime`` objects its target names (with none given, the partial is
    returned for the caller to complete). Unknown keys, or a part whose
    target cannot be found, raise :class:`ConfigError` naming ``prefix``."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    if node is None:
        raise ConfigError(f"{prefix} is missing (null)")
    spec = OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else dict(node)
    target = spec.get("_target_")
    if not target:
        raise ConfigError(f"{prefix} has no _target_ (the class or factory that builds it)")
    fn = import_object(target, f"{prefix}._target_")
    params = _target_params(fn)
    takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    named = {k for k, p in params.items() if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)}
    for k in LABELS:
        if k in spec and k not in named:
            spec.pop(k)
    unknown = sorted(k for k in spec if not k.startswith("_") and k not in named and not takes_any)
    if unknown:
        allowed = sorted(k for k in named if k not in runtime and k != "self")
        raise ConfigError(f"{prefix}: unknown key(s) {unknown} for {target}; allowed: {allowed}")
    try:
        obj = instantiate(spec, _convert_="all")
    except InstantiationException as e:
        cause = e.__cause__
        if isinstance(cause, (ConfigError, ValueError)) and not isinstance(cause, TypeError):
            raise cause
        raise ConfigError(f"{prefix}: {str(e).splitlines()[0]}") from None
    if isinstance(obj, functools.partial) and runtime:  # without run-time objects: the partial itself
        obj = obj(**{k: v for k, v in runtime.items() if k in named})
    return obj


@dataclass
class Parts:
    """The parts of a learn-while-tracking study, built from the config groups."""

    scenario: Any
    network: Any
    model: Any
    observation: Any
    fusion: Any
    predict: Any
    dtype: torch.dtype
    device: torch.device


def build_scenario(cfg: DictConfig):
    return build(cfg.scenario, "scenario")


def build_network(cfg: DictConfig):
    return build(cfg.network, "network")


def build_motion_model(node: Any, scenario, network, dtype, device, fusion=None):
    """The motion model of ``node`` for ``scenario``, its per-node state (the GPs') for every node of ``network``, or
    for one where ``fusion`` is a fusion centre's (:attr:`~dslearn.fusion.strategies.Fusion.centre`: every node holds
    the centre's one belief, predicted once)."""
    nodes = 1 if fusion is not None and fusion.centre else network.num_nodes
    return build(node, "model", scenario=scenario, num_nodes=nodes, dtype=dtype, device=device)


def build_observation(node: Any, network, dtype, device, scenario=None):
    """The observation model of ``node`` for the sensors of ``network``: its ``noise_std``, where the option leaves
    it null (the ``conf/observation`` default) or does not give it, is those sensors' own noise
    (``network.meas_std``: the scenario's sensors where it brings its own); a number is kept (a deliberate
    mismatch between the model and the sensors). A model sized by the world (the nodes' positions, the map: the
    nonlinear sensors' ``for_scenario``) is handed ``network`` and, where given, ``scenario``."""
    runtime = dict(num_nodes=network.num_nodes, dtype=dtype, device=device, network=network)
    if scenario is not None:
        runtime["scenario"] = scenario
    return build(sensor_noise(node, network), "observation", **runtime)


def sensor_noise(node: Any, network) -> Any:
    """``node`` (an observation option) as a plain dict, its null or missing ``noise_std`` set to ``network.meas_std``
    where its target takes a ``noise_std``."""
    if node is None:
        return node
    spec = OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else dict(node)
    if spec.get("noise_std") is not None:
        return spec
    from hydra.utils import get_object

    try:
        takes = "noise_std" in _target_params(get_object(str(spec.get("_target_"))))
    except Exception:  # noqa: BLE001 - a target that cannot be imported: build() names it
        return spec
    if takes:
        spec["noise_std"] = float(network.meas_std)
    return spec


def build_fusion(node: Any, network, prefix: str = "consensus"):
    return build(node, prefix, adjacency=network.adjacency)


def build_predict(cfg: DictConfig):
    """The filter's prediction step (``filter.predict``: EKF linearisation or unscented)."""
    return build(cfg.filter.get("predict"), "filter.predict")


def build_parts(cfg: DictConfig, model_node: Any = None) -> Parts:
    """Scenario, network (first: connectivity is checked before anything else is built), motion
    and observation models, fusion and the filter's prediction step of ``cfg`` (the run's slots, :data:`SLOTS`)."""
    s = _Slots(cfg)
    dtype, device, scenario, network = s["dtype"], s["device"], s["scenario"], s["network"]
    model = s["model"] if model_node is None else build_motion_model(model_node, scenario, network, dtype, device)
    return Parts(scenario, network, model, s["observation"], s["fusion"], s["predict"], dtype, device)


def group_options(group: str, names, overrides: tuple[str, ...] = ()) -> dict[str, DictConfig]:
    """The config nodes of several options of one group (``{name: cfg.<group>}``), composed by Hydra
    with their defaults lists, as ``<group>=<name>`` would, from the package's config folder and the user's
    ``hydra.searchpath`` folders (:func:`dslearn.search_path.search_overrides`). ``overrides`` apply to each (e.g.
    ``consensus.iterations=4``)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from dslearn.conf_paths import CONF_DIR
    from dslearn.search_path import search_overrides  # (the task schemas the configs name are
    # registered by the caller: the app, dslearn.api or a test imports dslearn.schemas)

    def _all() -> dict[str, DictConfig]:  # with the user's hydra.searchpath folders (their options too)
        return {n: compose("config", overrides=[*search_overrides(), f"{group}={n}", *overrides])[group]
                for n in names}

    if GlobalHydra.instance().is_initialized():
        return _all()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return _all()


# ------------------------------------------------------------------------------------------------
# studies: components whose typed slots the composition root fills

def _filter_settings(cfg: DictConfig):
    from dslearn.filters.distributed import FilterSettings

    f = cfg.filter
    return FilterSettings(float(f.prior_pos_std), float(f.prior_vel_std),
                          None if f.get("learn_gate_std") is None else float(f.learn_gate_std))


def _data_settings(cfg: DictConfig):
    from dslearn.learning.online import DataSettings

    d = OmegaConf.to_container(cfg.data, resolve=True)
    return DataSettings(**{k: d[k] for k in ("train_episodes", "test_episodes", "eval_at", "min_train_episodes")})


class _Slots:
    """The objects of one run (:data:`SLOTS`), each built once on first use (the network before the models that
    need its size; the scenario before the parts sized by it). A ``device`` given replaces the run's: ``meta``
    builds every part with its shapes only (no memory, no numbers), for the up-front checks."""

    def __init__(self, cfg: DictConfig, device: torch.device | None = None):
        self.cfg, self._built = cfg, ({} if device is None else {"device": torch.device(device)})

    def __getitem__(self, name: str) -> Any:
        if name not in self._built:
            self._built[name] = SLOTS[name](self.cfg, self)
        return self._built[name]


#: slot name -> how the composition root fills it from the composed configuration. A study names the
#: slots it needs as the parameters of its constructor (a dataclass's fields); :func:`build_study`
#: fills exactly those, so a study never reads the configuration.
SLOTS: dict[str, Any] = {
    "settings": lambda cfg, s: OmegaConf.to_object(cfg.task),  # the task's typed settings (its schema dataclass)
    "seed": lambda cfg, s: int(cfg.seed),
    "dtype": lambda cfg, s: resolve_dtype(cfg.dtype),
    "device": lambda cfg, s: resolve_device(cfg.device),
    "scenario": lambda cfg, s: build_scenario(cfg),
    "network": lambda cfg, s: build_network(cfg),
    "model": lambda cfg, s: build_motion_model(cfg.model, s["scenario"], s["network"], s["dtype"], s["device"]),
    "model_spec": lambda cfg, s: OmegaConf.to_container(cfg.model, resolve=True),  # plain: labels, progress costs
    "observation": lambda cfg, s: build_observation(cfg.observation, s["network"], s["dtype"], s["device"]),
    "fusion": lambda cfg, s: build_fusion(cfg.consensus, s["network"]),
    "predict": lambda cfg, s: build_predict(cfg),
    "filter": lambda cfg, s: _filter_settings(cfg),
    "data": lambda cfg, s: _data_settings(cfg),
}


def register_slot(name: str, builder) -> None:
    """Add a slot a study may name: ``builder(cfg, slots) -> object`` (``slots[name]`` gives the run's
    other built objects). A task's own slots are registered by its schema module."""
    if name in SLOTS and SLOTS[name] is not builder:
        raise ValueError(f"slot {name!r} is registered already")
    SLOTS[name] = builder


def _model_options(cfg: DictConfig, s: "_Slots") -> dict[str, Any]:
    """``{name: make(scenario, network, device=None)}`` for every ``conf/model`` option of ``task.models``:
    a fresh model of that option per call, with the run's dtype (and device, unless given: ``meta`` for a
    probe of shapes)."""
    nodes = group_options("model", [str(m) for m in cfg.task.models])
    dtype, dev = s["dtype"], s["device"]

    def maker(node):
        return lambda scenario, network, device=None: build_motion_model(node, scenario, network, dtype,
                                                                         dev if device is None else device)

    return {name: maker(node) for name, node in nodes.items()}


def _observation_factory(cfg: DictConfig, s: "_Slots"):
    """``make(network)``: a fresh observation model of the ``observation`` group for ``network``."""
    node, dtype, dev = cfg.observation, s["dtype"], s["device"]
    return lambda network: build_observation(node, network, dtype, dev)


def _fusion_factory(cfg: DictConfig, s: "_Slots"):
    """``make(network)``: the ``consensus`` group's fusion over ``network``'s graph."""
    node = cfg.consensus
    return lambda network: build_fusion(node, network)


def _engine_params(cfg: DictConfig):
    """The parameters of the method ``cfg.filter`` makes (its ``_target_``: the engine)."""
    target = cfg.filter.get("_target_")
    if not target:
        raise ConfigError("filter has no _target_ (the method its engine makes)")
    return inspect.signature(import_object(target, "filter._target_")).parameters


def method_takes(cfg: DictConfig) -> tuple[str, ...]:
    """The parts the method of ``cfg.filter`` takes (its engine's parameters among ``model``,
    ``observation``, ``fusion``, ``learner``, ``associator``), named by their root groups (``fusion`` is the ``consensus`` group)."""
    params = _engine_params(cfg)
    group = {"model": "model", "observation": "observation", "fusion": "consensus", "learner": "learner",
             "associator": "associator"}
    return tuple(g for p, g in group.items() if p in params)


def _scenario_network(cfg: DictConfig, s: "_Slots"):
    """The sensors of a matrix cell: the scenario's own network, else the ``network`` part's placement."""
    scenario = s["scenario"]
    return scenario.network if scenario.network is not None else s["network"]


def _method(cfg: DictConfig, s: "_Slots"):
    """The method of a matrix cell: the ``filter`` part's engine with the parts it takes, each sized for the
    cell's scenario and sensors, and the ``learner`` part (``None`` where ``learner: null``: the engine's own)."""
    scenario, net, dtype, dev = s["scenario"], s["scenario_network"], s["dtype"], s["device"]
    params = _engine_params(cfg)
    once = functools.lru_cache(maxsize=None)  # each built once, where taken
    fusion = once(lambda: build_fusion(cfg.consensus, net))
    learner = once(lambda: None if cfg.get("learner") is None else build(cfg.learner, "learner"))
    # a fusion centre's one belief: one model state, unless the learner runs every node's filter alone
    centre = "fusion" in params and not getattr(learner() if "learner" in params else None, "runs_nodes_alone", False)
    makers = {
        "model": lambda: build_motion_model(cfg.model, scenario, net, dtype, dev, fusion() if centre else None),
        "model_name": lambda: str(cfg.model.name),
        "observation": lambda: build_observation(cfg.observation, net, dtype, dev, scenario),
        "fusion": fusion,
        "fusion_name": lambda: str(cfg.consensus.name),
        "learner": learner,
        "associator": lambda: None if cfg.get("associator") is None else build(cfg.associator, "associator"),
        "network": lambda: net,
        "scenario": lambda: scenario,
        "dtype": lambda: dtype,
        "device": lambda: dev,
    }
    made = build(cfg.filter, "filter", **{k: make() for k, make in makers.items() if k in params})
    return made() if isinstance(made, functools.partial) else made  # an engine that takes no run-time part


def build_cell_parts(cfg: DictConfig, check_only: bool = False):
    """The scenario, its sensors and the method of a matrix cell (``task=matrix``); a method that does not
    fit the scenario is refused with the reason (with ``check_only``: on PyTorch's meta device, so no
    memory is used and no random draw of the run is consumed)."""
    slots = _Slots(cfg, torch.device("meta") if check_only else None)
    with torch.random.fork_rng(devices=[]):
        method = slots["method"]
    reason = method.fits(slots["scenario"].spec)
    if reason is not None:
        raise ConfigError(f"{method.label} does not fit scenario {slots['scenario'].spec.name}: {reason}")
    return slots["scenario"], slots["scenario_network"], method


def _draws(cfg: DictConfig, s: "_Slots"):
    """``draw(seed) -> (scenario, its sensors, method)``: a matrix cell's objects as a run with ``seed`` builds them
    (the configuration with ``seed`` replaced, so whatever interpolates ``${seed}`` follows it, e.g. Liu's sensor
    field; the global torch generator seeded first, as :func:`build_study` does, so a method's initial values
    follow it too). Each call builds anew: one draw at a time."""
    import copy

    dev = s["device"]

    def draw(seed: int):
        c = copy.deepcopy(cfg)
        OmegaConf.set_readonly(c, False)
        with open_dict(c):
            c.seed = int(seed)
        torch.manual_seed(int(seed))
        slots = _Slots(c, dev)  # (the dtype: ``c``'s, the same)
        return slots["scenario"], slots["scenario_network"], slots["method"]

    return draw


SLOTS.update({
    "model_options": _model_options,
    "observation_factory": _observation_factory,
    "fusion_factory": _fusion_factory,
    "scenario_network": _scenario_network,
    "method": _method,
    "draws": _draws,
})


def study_slots(cfg: DictConfig) -> tuple[type, list[str]]:
    """The study class of ``cfg.task`` (its ``_target_``, a class registered with the task's schema) and the
    slots it names (its constructor's parameters); ConfigError for a slot :data:`SLOTS` does not fill."""
    target = str(cfg.task._target_)
    cls = import_object(target, "task._target_")
    params = [n for n in inspect.signature(cls).parameters if n != "self"]
    unknown = [n for n in params if n not in SLOTS]
    if unknown:
        raise ConfigError(f"{target} asks for slot(s) {unknown} that the composition root does not fill; "
                          f"slots: {sorted(SLOTS)}")
    return cls, params


def build_study(cfg: DictConfig) -> Any:
    """The study of ``cfg.task``, its slots (:func:`study_slots`) filled with the run's built parts and typed
    settings (:data:`SLOTS`)."""
    cls, params = study_slots(cfg)
    torch.manual_seed(int(cfg.seed))  # parts with random initial values (features, weights) follow the run's seed
    slots = _Slots(cfg)
    return cls(**{n: slots[n] for n in params})
