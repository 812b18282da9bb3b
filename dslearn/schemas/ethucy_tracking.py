"""Schema of the ``ethucy_tracking`` task (``conf/task/ethucy_tracking.yaml``): Yu et al. Section VI
on ETH/UCY (``experiment=real_tables`` / ``experiment=gp_vs_lstm``). Keys and types are checked at
composition, ranges by :func:`dslearn.schemas.base.check_ranges`, the rest by :func:`check`."""

from dataclasses import dataclass, field
from typing import Dict, List, Optional

from omegaconf import DictConfig

from dslearn.data.datasets import DatasetSchema, FoldsSchema, check_scene_names
from dslearn.errors import ConfigError, check_choice
from dslearn.schemas.base import ranged, register_task
from dslearn.schemas.ethucy_forecast import check_datasets, check_device

PROTOCOLS = ("tables", "data_size")
MODELS = ("gp", "gp_cv", "lin", "sfm", "lstm")
CRITERIA = ("mutual", "closest")
SPLITS = ("time", "scene", "random")  # as dslearn.data.episodes; "scene" is refused with the reason in check()
AGGREGATED_TARGET = "dslearn.models.aggregated.aggregated_for_scenario"
GP_TARGET = "dslearn.models.gp.GPMotionModel.for_scenario"
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
class RealLin:
    noise_std: float = ranged(0.1, gt=0.0)


@dataclass
class SfmGrid:
    tau: List[float] = ranged(factory=lambda: [0.25, 0.5, 1.0, 2.0, 4.0, 8.0], gt=0.0, each=True, min_len=1)
    alpha: List[float] = ranged(factory=lambda: [0.0, 0.5, 1.0, 2.0, 4.0, 8.0], ge=0.0, each=True, min_len=1)
    beta: List[float] = ranged(factory=lambda: [0.25, 0.5, 1.0, 2.0, 4.0], gt=0.0, each=True, min_len=1)


@dataclass
class RealSfm:
    """``task.sfm``: the social-force fit (:func:`dslearn.learning.sfm_fit.fit_social_force`)."""

    noise_std: float = ranged(0.1, gt=0.0)
    fit_on: str = ranged("truth", choices=("truth", "fused"))
    desired_steps: int = ranged(1, ge=1)
    grid: SfmGrid = field(default_factory=SfmGrid)
    refine_iters: int = ranged(150, ge=0)
    refine_lr: float = ranged(0.05, gt=0.0)


@dataclass
class RealLSTM:
    """``task.lstm``: the paper's VI-C network and schedule."""

    embed: int = ranged(64, ge=1)
    hidden: int = ranged(64, ge=1)
    obs_len: int = ranged(2, ge=1)
    pred_len: int = ranged(10, ge=1)
    schedule: str = ranged("fixed", choices=("fixed", "early_stopping"))
    epochs: int = ranged(50, ge=1)
    batch_size: int = ranged(8, ge=1)
    lr: float = ranged(1.0e-3, gt=0.0)
    patience: Optional[int] = ranged(10, ge=1)
    min_delta: float = ranged(0.0, ge=0.0, lt=1.0)
    lr_factor: Optional[float] = ranged(None, gt=0.0, lt=1.0)
    lr_patience: int = ranged(3, ge=1)
    min_lr: float = ranged(0.0, ge=0.0)
    val_fraction: float = ranged(0.2, gt=0.0, lt=1.0)
    pooling: str = ranged("none", choices=("none", "social"))
    grid: int = ranged(4, ge=1)
    neighbourhood: float = ranged(2.0, gt=0.0)


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
    models: List[str] = ranged(factory=lambda: list(MODELS), choices=MODELS, each=True, min_len=1)
    gp_inputs: str = ranged("belief", choices=GP_INPUTS)
    network: RealNetwork = field(default_factory=RealNetwork)
    lin: RealLin = field(default_factory=RealLin)
    sfm: RealSfm = field(default_factory=RealSfm)
    lstm: RealLSTM = field(default_factory=RealLSTM)
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
    models = list(t.models)
    if t.protocol == "data_size":
        if "lstm" not in models or not {"gp", "gp_cv"} & set(models):
            raise ConfigError("task.models must contain 'lstm' and 'gp' (or 'gp_cv') for task.protocol=data_size")
        if not list(t.data_sizes):
            raise ConfigError("task.data_sizes must list at least one number of training episodes")
    check_scene_names("task.scenes", list(t.scenes), t)
    if not list(t.scenes) and not (t.protocol == "data_size" and t.synthetic):
        raise ConfigError("task.scenes must name at least one scene (or set task.synthetic=true for data_size)")
    if t.sfm.desired_steps > t.steps + 1:
        raise ConfigError(f"task.sfm.desired_steps={t.sfm.desired_steps} must be <= task.steps + 1")
    from dslearn.models.lstm import schedule_from_config

    schedule_from_config(t.lstm, prefix="task.lstm")
    if t.lstm.obs_len + t.lstm.pred_len > t.steps + 1:
        raise ConfigError(
            f"task.lstm.obs_len + task.lstm.pred_len = {t.lstm.obs_len + t.lstm.pred_len} must be <= task.steps + 1 "
            f"= {t.steps + 1} (the LSTM's training windows are cut from the episodes)"
        )
    if {"gp", "gp_cv"} & set(models):
        target = cfg.model.get("_target_")
        if target not in (GP_TARGET, AGGREGATED_TARGET):
            raise ConfigError(f"model._target_={target!r} (model={cfg.model.get('name')}) is not allowed with task.models "
                              f"gp / gp_cv; choose a GP model group (model=gp, gp_increment, gp_window, gp_rbcm, ...: "
                              f"_target_ {GP_TARGET} or {AGGREGATED_TARGET})")
        variant = cfg.model.get("variant") or "exact"
        if t.gp_inputs == "belief" and (target == AGGREGATED_TARGET or variant not in ("exact", "window")):
            raise ConfigError(f"task.gp_inputs=belief averages the exact or window GP over the belief; model="
                              f"{cfg.model.get('name')} ({'aggregated' if target == AGGREGATED_TARGET else variant}) "
                              f"has no such average: choose task.gp_inputs=mean or model=gp_increment, gp, gp_window")
        if t.gp_inputs == "belief" and cfg.model.get("jacobian") == "autograd":
            raise ConfigError("task.gp_inputs=belief: the Jacobian averaged over the belief is closed form; choose "
                              "model.jacobian=closed_form or task.gp_inputs=mean")
        if target == AGGREGATED_TARGET:
            from dslearn.models.aggregated import RULES

            if "gp_cv" in models:
                raise ConfigError(f"task.models contains gp_cv (the GP with a constant-velocity prior mean), which has no "
                                  f"aggregated form; with model={cfg.model.get('name')} use task.models without gp_cv")
            check_choice("model.aggregation", cfg.model.get("aggregation"), RULES)
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


register_task("ethucy_tracking", EthucyTrackingTask, check)
