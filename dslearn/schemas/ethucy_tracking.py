"""Schema of the ``ethucy_tracking`` task (``conf/task/ethucy_tracking.yaml``): Yu et al. Section VI
on ETH/UCY (``experiment=real_tables`` / ``experiment=gp_vs_lstm``). Keys and types are checked at
composition, ranges by :func:`dslearn.schemas.base.check_ranges`, the rest by :func:`check`."""

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

from omegaconf import DictConfig

from dslearn.errors import ConfigError, check_choice
from dslearn.schemas.base import ranged, register_task
from dslearn.schemas.datasets import DatasetSchema, FoldsSchema, check_scene_names
from dslearn.schemas.ethucy_forecast import check_datasets, check_device

PROTOCOLS = ("tables", "data_size")
#: the default task.models: conf/model options (gp = the root model group; dslearn.studies.ethucy_tracking.ALIASES)
MODELS = ("gp", "gp_cv", "lin", "sfm_fit", "lstm")
CRITERIA = ("mutual", "closest")
SPLITS = ("time", "scene", "random")  # as dslearn.data.episodes; "scene" is refused with the reason in check()
AGGREGATED_TARGET = "dslearn.models.aggregated.aggregated_for_scenario"
GP_TARGET = "dslearn.models.gp.GPMotionModel.for_scenario"
TRAIN_ON = ("fused", "truth")  # what offline models learn from (dslearn.studies.ethucy_tracking.OfflineData)
GP_INPUTS = ("belief", "mean")  # dslearn.models.gp.INPUTS: where the EKF evaluates the GPs
FUSIONS = ("hybrid", "cm", "ci", "ce", "individual")


@dataclass
class RealNetwork:
    """``task.network``: LiDAR-like sensors around the scene (:func:`dslearn.sim.real.arena_network`)."""

    num_sensors: int = ranged(4, ge=1)
    k_nearest: int = ranged(2, ge=1)
    sensing_range: float = ranged(8.0, gt=0.0)
    meas_std: float = ranged(0.2, gt=0.0)
    margin: float = ranged(0.0, ge=0.0)


@dataclass
class CmFusion:
    """``task.cm_fusion``: the filter that makes the fused training tracks (:func:`dslearn.studies.ethucy_tracking.cm_fused`)."""

    noise_std: float = ranged(0.1, gt=0.0)


@dataclass
class EthucyTrackingTask:
    entry: str = "dslearn.studies.ethucy_tracking:run"
    name: str = "ethucy_tracking"
    protocol: str = ranged("tables", choices=PROTOCOLS)
    data_root: Optional[str] = None
    scenes: List[str] = field(default_factory=lambda: ["zara1", "zara2", "univ", "hotel", "eth"])
    convention: str = ranged("physical", choices=("physical", "benchmark"))
    dt: float = ranged(0.4, gt=0.0)
    steps: int = ranged(11, ge=2)
    agents: int = ranged(2, ge=2)
    max_dist: float = ranged(3.0, gt=0.0)
    criterion: str = ranged("mutual", choices=CRITERIA)
    min_speed: float = ranged(0.3, ge=0.0)
    stride: int = ranged(4, ge=1)
    split: str = ranged("time", choices=SPLITS)
    test_fraction: float = ranged(0.2, gt=0.0, lt=1.0)
    train_episodes: int = ranged(128, ge=1)
    test_episodes: int = ranged(25, ge=1)
    plot_episodes: int = ranged(3, ge=0)
    models: List[str] = ranged(factory=lambda: list(MODELS), min_len=1)  # conf/model/<name>.yaml (checked in check())
    model_keys: Dict[str, Dict[str, Any]] = field(default_factory=dict)  # entry -> keys of its option to replace
    train_on: str = ranged("fused", choices=TRAIN_ON)
    gp_inputs: str = ranged("belief", choices=GP_INPUTS)
    network: RealNetwork = field(default_factory=RealNetwork)
    cm_fusion: CmFusion = field(default_factory=CmFusion)
    data_sizes: List[int] = ranged(factory=lambda: [8, 16, 32, 64, 128], ge=1, each=True)
    seeds: int = ranged(3, ge=1)
    synthetic: bool = False
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


def check_models(cfg: DictConfig) -> None:
    """``task.models`` and ``task.model_keys``: every entry a ``conf/model`` option (or a legacy name,
    :data:`dslearn.studies.ethucy_tracking.ALIASES`), each runnable on real data (its ``_target_`` one
    of :data:`~dslearn.studies.ethucy_tracking.REAL_TARGETS`), built once on the ``meta`` device with
    the episodes' shape (every refusal of its factory, naming the entry), the GP's ``task.gp_inputs``
    rules, and the episodes an offline fit holds out."""
    from dslearn.conf_paths import CONF_DIRS
    from dslearn.studies import ethucy_tracking as et

    t = cfg.task
    names = [str(m) for m in t.models]
    files = sorted({p.stem for d in CONF_DIRS if (d / "model").is_dir() for p in (d / "model").glob("*.yaml")})
    for n in names:
        if n not in et.ALIASES and n not in files:
            raise ConfigError(f"task.models contains {n!r}: no conf/model/{n}.yaml; choose from {files} or "
                              f"{sorted(et.ALIASES)} (gp: the root model group; sfm: sfm_fit labelled sfm)")
    if len(set(names)) != len(names):
        raise ConfigError(f"task.models={names} names an entry twice")
    for n in (t.get("model_keys") or {}):
        if str(n) not in names:
            raise ConfigError(f"task.model_keys.{n} changes an entry that task.models={names} does not list")
    entries = et.model_entries(cfg)
    labels = [label for _, label, _ in entries]
    if len(set(labels)) != len(labels):
        raise ConfigError(f"task.models={names} gives two entries the same label {labels} (the rows' model column)")
    sizes = [int(t.train_episodes)] if t.protocol == "tables" else [int(v) for v in t.data_sizes]
    for n, label, spec in entries:
        where = f"task.models entry {n!r}" + (" (the root model group)" if et.ALIASES.get(n, (n,))[0] is None else "")
        target = spec.get("_target_")
        if target not in et.REAL_TARGETS:
            raise ConfigError(f"{where}: model._target_={target!r} (model {label}) does not run on real data (its "
                              f"parameters come from a simulation, or it is not sized by a real scene); choose an "
                              f"option whose _target_ is one of {list(et.REAL_TARGETS)} (sfm_fit for the social force)")
        if target in (GP_TARGET, et.GP_CV_TARGET, AGGREGATED_TARGET):
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

    from dslearn.compose import build_motion_model, resolve_dtype
    from dslearn.sim.real import RealScenario

    t = cfg.task
    scenario = RealScenario(int(t.agents), float(t.dt), int(t.steps), (0.0, 1.0, 0.0, 1.0))
    network = SimpleNamespace(num_nodes=int(t.network.num_sensors))
    try:
        return build_motion_model(spec, scenario, network, resolve_dtype(cfg.get("dtype", "float64")), torch.device("meta"))
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None


def uses(cfg: DictConfig) -> tuple[str, ...]:
    """The root groups the study reads (:mod:`dslearn.studies.ethucy_tracking`): the fusion
    (``consensus``), the filter (``filter``: initial prior, gate, prediction step) and the sensor model
    (``observation``) always; the root model (``model``) when ``task.models`` lists ``gp`` (the root
    model group's entry); the synthetic Yu scenario and network (``scenario``, ``network``) with
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

register_task("ethucy_tracking", EthucyTrackingTask, check, uses=uses, instead=INSTEAD)
