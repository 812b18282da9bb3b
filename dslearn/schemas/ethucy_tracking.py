"""Schema of the ``ethucy_tracking`` task (``conf/task/ethucy_tracking.yaml``): Yu et al. Section VI
on ETH/UCY (``experiment=real_tables`` / ``experiment=gp_vs_lstm``). Keys and types are checked at
composition, ranges by :func:`dslearn.schemas.base.check_ranges` (the rules on the study's settings,
:class:`dslearn.studies.ethucy_tracking.EthucyTrackingSettings`), the rest by :func:`check`.

The config logic of the study lives here too, as the task's slots of the composition root
(:func:`dslearn.compose.register_slot`): the model entries of ``task.models`` (conf/model options
composed with their aliases, ``task.model_keys`` and ``task.gp_inputs``), the sensor model of a
network (its noise, where the option leaves it at the root network's, is the study's sensors'), the CM
fusion of the fused training tracks, the data sets (:class:`~dslearn.data.datasets.DatasetSpec`) and
the synthetic source (the root scenario and network)."""

import copy
from dataclasses import dataclass, field
from typing import Dict

from omegaconf import DictConfig, OmegaConf

from dslearn.compose import build_motion_model, build_network, build_observation, build_scenario, group_options, register_slot
from dslearn.errors import ConfigError, check_choice
from dslearn.schemas.base import register_task
from dslearn.schemas.datasets import DatasetSchema, FoldsSchema, check_scene_names, spec_from_config
from dslearn.schemas.ethucy_forecast import check_datasets, check_device
from dslearn.studies.ethucy_tracking import (CRITERIA, GP_INPUTS, MODELS, PROTOCOLS, SPLITS, TRAIN_ON,  # noqa: F401
                                             EthucyTrackingSettings, ModelEntry, SyntheticWorld)

TARGET = "dslearn.studies.ethucy_tracking.EthucyTrackingStudy"
AGGREGATED_TARGET = "dslearn.models.aggregated.aggregated_for_scenario"
GP_TARGET = "dslearn.models.gp.GPMotionModel.for_scenario"
GP_CV_TARGET = "dslearn.models.gp_cv.gp_cv_for_scenario"
#: the model factories that run on real data (sized by :class:`dslearn.sim.real.RealScenario`), and
#: the GPs among them whose ``inputs`` ``task.gp_inputs`` sets
REAL_TARGETS = (GP_TARGET, GP_CV_TARGET, AGGREGATED_TARGET, "dslearn.models.constant_velocity.ConstantVelocity.for_scenario",
                "dslearn.learning.sfm_fit.FittedSocialForce.for_scenario", "dslearn.models.lstm.SocialLSTM.for_scenario")
GP_INPUT_TARGETS = (GP_TARGET, GP_CV_TARGET)
#: names of ``task.models`` kept from before the entries were ``conf/model`` options: entry ->
#: (the option, the label of its rows); option None = the root ``model`` group, labelled by its name
ALIASES = {"gp": (None, None), "sfm": ("sfm_fit", "sfm")}
FUSIONS = ("hybrid", "cm", "ci", "ce", "individual")


@dataclass
class _TaskHead:
    _target_: str = TARGET
    name: str = "ethucy_tracking"


@dataclass
class EthucyTrackingTask(EthucyTrackingSettings, _TaskHead):
    """``task``: the study class and name, the study's settings, and the data sets it may use
    (``task.datasets``: handed to the study as specs, :func:`datasets_slot`) with the ETH/UCY folds."""

    folds: FoldsSchema = field(default_factory=FoldsSchema)
    datasets: Dict[str, DatasetSchema] = field(default_factory=dict)


def check(cfg: DictConfig) -> None:
    t = cfg.task
    check_device(cfg)
    check_datasets(t)
    if t.split == "scene":
        raise ConfigError(
            "task.split=scene is not supported by this study: the GP's inputs are absolute positions "
            "in each scene's own frame and the network is placed around one scene; use time or random"
        )
    if t.protocol == "data_size" and not list(t.data_sizes):
        raise ConfigError("task.data_sizes must list at least one number of training episodes")
    check_scene_names("task.scenes", list(t.scenes), t)
    if not list(t.scenes) and not (t.protocol == "data_size" and t.synthetic):
        raise ConfigError("task.scenes must name at least one scene (or set task.synthetic=true for data_size)")
    check_models(cfg)
    c = cfg.consensus
    if c.name == "centralized":
        raise ConfigError("consensus.name=centralized is a reference, not a distributed filter; use hybrid, cm, ci, ce or individual")
    check_choice("consensus.name", c.name, FUSIONS)
    check_choice("consensus.weights", c.weights, ("uniform", "metropolis", "max_degree"))
    if not isinstance(c.iterations, int) or isinstance(c.iterations, bool) or c.iterations < 0:
        raise ConfigError(f"consensus.iterations={c.iterations!r} must be an integer >= 0")
    for k in ("prior_pos_std", "prior_vel_std"):
        v = cfg.filter[k]
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not v > 0:
            raise ConfigError(f"filter.{k}={v!r} must be > 0")


# the model entries ---------------------------------------------------------------------------
def model_entries(cfg: DictConfig) -> list[tuple[str, str, dict]]:
    """``(entry, label, spec)`` of every ``task.models`` entry, in order: ``spec`` is the plain config
    of its ``conf/model`` option (composed by :func:`dslearn.compose.group_options`; the legacy
    names of :data:`ALIASES` map to an option or to the root ``model`` group), with the keys of
    ``task.model_keys.<entry>`` replaced and, for the GPs that have it, ``inputs = task.gp_inputs``;
    ``label`` (the rows' ``model``) is the option's ``name`` (an alias's own label where it has one)."""
    t = cfg.task
    names = [str(m) for m in t.models]
    options = sorted({ALIASES.get(n, (n, None))[0] for n in names} - {None})
    composed = _options(options)
    extra = t.get("model_keys") or {}
    out = []
    for n in names:
        option, label = ALIASES.get(n, (n, None))
        spec = OmegaConf.to_container(cfg.model, resolve=True) if option is None else copy.deepcopy(composed[option])
        if n in extra:
            spec.update(OmegaConf.to_container(extra[n], resolve=True) if OmegaConf.is_config(extra[n]) else dict(extra[n]))
        if str(t.get("gp_inputs", "mean")) != "mean" and spec.get("_target_") in GP_INPUT_TARGETS:
            spec["inputs"] = str(t.gp_inputs)
        out.append((n, str(label or spec.get("name", n)), spec))
    return out


_OPTIONS: dict[tuple, dict] = {}


def _options(names: list[str]) -> dict[str, dict]:
    """The plain configs of ``conf/model`` options (:func:`dslearn.compose.group_options`), memoised by
    the config folders and the option: the up-front check of every job of a sweep and the run compose
    the same options, and composing one costs ~0.3 s."""
    from dslearn.conf_paths import CONF_DIRS

    where = tuple(str(d) for d in CONF_DIRS)
    todo = [n for n in names if (where, n) not in _OPTIONS]
    if todo:
        for n, node in group_options("model", todo).items():
            _OPTIONS[(where, n)] = OmegaConf.to_container(node, resolve=True)
    return {n: _OPTIONS[(where, n)] for n in names}


def check_models(cfg: DictConfig) -> None:
    """``task.models`` and ``task.model_keys``: every entry a ``conf/model`` option (or a legacy name,
    :data:`ALIASES`), each runnable on real data (its ``_target_`` one of :data:`REAL_TARGETS`), built
    once on the ``meta`` device with the episodes' shape (every refusal of its factory, naming the
    entry), the GP's ``task.gp_inputs`` rules, and the episodes an offline fit holds out."""
    from dslearn.conf_paths import CONF_DIRS

    t = cfg.task
    names = [str(m) for m in t.models]
    files = sorted({p.stem for d in CONF_DIRS if (d / "model").is_dir() for p in (d / "model").glob("*.yaml")})
    for n in names:
        if n not in ALIASES and n not in files:
            raise ConfigError(f"task.models contains {n!r}: no conf/model/{n}.yaml; choose from {files} or "
                              f"{sorted(ALIASES)} (gp: the root model group; sfm: sfm_fit labelled sfm)")
    if len(set(names)) != len(names):
        raise ConfigError(f"task.models={names} names an entry twice")
    for n in (t.get("model_keys") or {}):
        if str(n) not in names:
            raise ConfigError(f"task.model_keys.{n} changes an entry that task.models={names} does not list")
    entries = model_entries(cfg)
    labels = [label for _, label, _ in entries]
    if len(set(labels)) != len(labels):
        raise ConfigError(f"task.models={names} gives two entries the same label {labels} (the rows' model column)")
    sizes = [int(t.train_episodes)] if t.protocol == "tables" else [int(v) for v in t.data_sizes]
    for n, label, spec in entries:
        where = f"task.models entry {n!r}" + (" (the root model group)" if ALIASES.get(n, (n,))[0] is None else "")
        target = spec.get("_target_")
        if target not in REAL_TARGETS:
            raise ConfigError(f"{where}: model._target_={target!r} (model {label}) does not run on real data (its "
                              f"parameters come from a simulation, or it is not sized by a real scene); choose an "
                              f"option whose _target_ is one of {list(REAL_TARGETS)} (sfm_fit for the social force)")
        if target in (GP_TARGET, GP_CV_TARGET, AGGREGATED_TARGET):
            _check_gp(t, spec, label)
        model = _meta_model(cfg, spec, where)
        if model.learns_offline:
            c = getattr(model, "offline", {})
            holds_out = c.get("schedule") == "early_stopping" or c.get("process_noise") == "residuals"
            if holds_out and min(sizes) < 2:
                raise ConfigError(f"{where}: model.schedule={c.get('schedule')} / model.process_noise="
                                  f"{c.get('process_noise')} hold whole training episodes out, which needs >= 2; "
                                  f"{'task.train_episodes' if t.protocol == 'tables' else 'task.data_sizes'} gives "
                                  f"{min(sizes)} (or set task.model_keys.{n}.process_noise=fixed)")


def _check_gp(t, spec: dict, label: str) -> None:
    target = spec.get("_target_")
    variant = spec.get("variant") or "exact"
    if t.gp_inputs == "belief" and (target == AGGREGATED_TARGET or variant not in ("exact", "window")):
        raise ConfigError(f"task.gp_inputs=belief averages the exact or window GP over the belief; model "
                          f"{label} ({'aggregated' if target == AGGREGATED_TARGET else variant}) has no such average: "
                          f"choose task.gp_inputs=mean or model=gp_increment, gp, gp_window")
    if t.gp_inputs == "belief" and spec.get("jacobian") == "autograd":
        raise ConfigError(f"task.gp_inputs=belief: the Jacobian averaged over the belief is closed form; model {label} "
                          "has model.jacobian=autograd: choose model.jacobian=closed_form or task.gp_inputs=mean")
    if target == AGGREGATED_TARGET:
        from dslearn.models.aggregated import RULES

        check_choice("model.aggregation", spec.get("aggregation"), RULES)


def _meta_model(cfg: DictConfig, spec: dict, where: str):
    """The entry's model built on the ``meta`` device (shapes only) for episodes of the task's shape."""
    from types import SimpleNamespace

    import torch

    from dslearn.compose import resolve_dtype
    from dslearn.sim.real import RealScenario

    t = cfg.task
    scenario = RealScenario(int(t.agents), float(t.dt), int(t.steps), (0.0, 1.0, 0.0, 1.0))
    network = SimpleNamespace(num_nodes=int(t.network.num_sensors))
    try:
        return build_motion_model(spec, scenario, network, resolve_dtype(cfg.get("dtype", "float64")), torch.device("meta"))
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None


# the task's slots of the composition root ----------------------------------------------------
def models_slot(cfg: DictConfig, slots) -> list[ModelEntry]:
    """``ethucy_tracking_models``: a :class:`~dslearn.studies.ethucy_tracking.ModelEntry` per entry of
    ``task.models`` (:func:`model_entries`); its ``make(scenario, network, device=None)`` builds a fresh
    model of the entry's spec in the run's dtype (and device unless given)."""
    dtype, dev = slots["dtype"], slots["device"]

    def maker(spec: dict):
        def make(scenario, network, device=None):
            return build_motion_model(copy.deepcopy(spec), scenario, network, dtype, dev if device is None else device)

        return make

    return [ModelEntry(n, label, maker(spec)) for n, label, spec in model_entries(cfg)]


def observation_slot(cfg: DictConfig, slots):
    """``ethucy_tracking_observation``: ``make(network)``, a fresh sensor model of the root ``observation``
    group for ``network``; its noise, where the option leaves it null (the sensors' own), is ``network``'s
    sensors' (the study's ``task.network.meas_std``: :func:`dslearn.compose.build_observation`)."""
    spec = OmegaConf.to_container(cfg.observation, resolve=True)
    dtype, dev = slots["dtype"], slots["device"]

    def make(network):
        return build_observation(copy.deepcopy(spec), network, dtype, dev)

    return make


def cm_fusion_slot(cfg: DictConfig, slots):
    """``ethucy_tracking_cm_fusion``: ``make(network)``, consensus on measurements over ``network``'s graph
    with the root ``consensus`` group's weights, iterations and omega (the fused training tracks)."""
    from dslearn.fusion.strategies import ConsensusOnMeasurements

    c = cfg.consensus
    weights, iterations, omega = c.weights, int(c.iterations), c.omega

    def make(network):
        return ConsensusOnMeasurements.for_network(adjacency=network.adjacency, weights=weights, iterations=iterations,
                                                   omega=omega)

    return make


def datasets_slot(cfg: DictConfig, slots) -> dict:
    """``ethucy_tracking_datasets``: every data set of ``task.datasets`` as a
    :class:`~dslearn.data.datasets.DatasetSpec` (:func:`dslearn.schemas.datasets.spec_from_config`)."""
    return {str(k): spec_from_config(str(k), v) for k, v in (cfg.task.get("datasets") or {}).items()}


def synthetic_slot(cfg: DictConfig, slots):
    """``ethucy_tracking_synthetic``: the root scenario and network (the synthetic source) with
    ``task.protocol=data_size task.synthetic=true``, else None (nothing of the root groups is built)."""
    t = cfg.task
    if str(t.protocol) == "data_size" and bool(t.get("synthetic", False)):
        return SyntheticWorld(build_scenario(cfg), build_network(cfg))
    return None


for _name, _builder in (("models", models_slot), ("observation", observation_slot), ("cm_fusion", cm_fusion_slot),
                        ("datasets", datasets_slot), ("synthetic", synthetic_slot)):
    register_slot(f"ethucy_tracking_{_name}", _builder)


# what the task reads of the root groups ----------------------------------------------------------
def uses(cfg: DictConfig) -> tuple[str, ...]:
    """The root groups the study's slots read: the fusion (``consensus``: ``fusion_factory`` and
    :func:`cm_fusion_slot`), the filter (``filter``: initial prior, gate, prediction step) and the sensor
    model (``observation``, :func:`observation_slot`) always; the root model (``model``) when
    ``task.models`` lists ``gp`` (the root model group's entry, :func:`model_entries`); the synthetic Yu
    scenario and network (``scenario``, ``network``, :func:`synthetic_slot`) with
    ``task.protocol=data_size`` and ``task.synthetic=true``."""
    t = cfg.task
    out = ["consensus", "filter", "observation"]
    if "gp" in {str(m) for m in t.models}:
        out.append("model")
    if str(t.protocol) == "data_size" and bool(t.get("synthetic", False)):
        out += ["scenario", "network"]
    return tuple(out)


_SYNTHETIC = "the root scenario and network are the synthetic source of task.protocol=data_size task.synthetic=true"
INSTEAD = {
    "scenario": f"its scenes are task.scenes, data sets of task.datasets; {_SYNTHETIC}",
    "network": f"its network is task.network, placed around each scene; {_SYNTHETIC}",
    "model": "the root model is the entry gp of task.models, run only when it is listed; its other models are "
             "conf/model options listed in task.models (their keys: task.model_keys.<entry>)",
    "data": "its episodes are task.train_episodes and task.test_episodes (task.data_sizes for data_size)",
}

def unused(cfg: DictConfig) -> dict[str, str]:
    """The task keys the chosen ``task.protocol`` does not read (an override of them is refused): the data-size
    curves' sizes, seeds and synthetic source with ``tables``; the tables' training episodes and stored trajectories
    with ``data_size`` (its training episodes are ``task.data_sizes``)."""
    if str(cfg.task.protocol) == "tables":
        why = "with task.protocol=tables (Tables III-IV: task.train_episodes on each scene, seed once)"
        return {"task.data_sizes": why, "task.seeds": why, "task.synthetic": why}
    why = "with task.protocol=data_size (its training episodes are task.data_sizes; no stored trajectories)"
    return {"task.train_episodes": why, "task.plot_episodes": why}


register_task("ethucy_tracking", EthucyTrackingTask, check, uses=uses, instead=INSTEAD, unused=unused,
              parts=("filter", "observation", "model"))  # not consensus: its CM fusion reads every key
