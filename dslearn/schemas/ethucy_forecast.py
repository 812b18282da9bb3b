"""Schema of the ``ethucy_forecast`` task (``conf/task/ethucy_forecast.yaml``): ETH/UCY
leave-one-scene-out forecasting. Keys and types are checked at composition, ranges by
:func:`dslearn.schemas.base.check_ranges`, the rest by :func:`check`."""

from dataclasses import dataclass, field
from typing import Dict, List, Optional

import torch
from omegaconf import DictConfig

from dslearn.data.datasets import check_dataset
from dslearn.errors import ConfigError, check_choice
from dslearn.schemas.base import ranged, register_task
from dslearn.schemas.datasets import DatasetSchema, FoldsSchema, check_scene_names

PREDICTORS = ("cv", "lstm", "social_lstm", "gp", "gp_state")
CONVENTIONS = ("benchmark", "physical")
DTYPES = ("float64", "float32")


@dataclass
class ForecastLSTM:
    """``task.lstm``: network and schedule (see :func:`dslearn.models.lstm.schedule_from_config`)."""

    embed: int = ranged(64, ge=1)
    hidden: int = ranged(64, ge=1)
    schedule: str = ranged("early_stopping", choices=("fixed", "early_stopping"))
    epochs: int = ranged(50, ge=1)
    patience: Optional[int] = ranged(6, ge=1)
    min_delta: float = ranged(0.0, ge=0.0, lt=1.0)
    lr_factor: Optional[float] = ranged(0.5, gt=0.0, lt=1.0)
    lr_patience: int = ranged(2, ge=1)
    min_lr: float = ranged(0.0, ge=0.0)
    batch_size: int = ranged(64, ge=1)
    social_batch_size: Optional[int] = ranged(16, ge=1)
    lr: float = ranged(1.0e-3, gt=0.0)
    grid: int = ranged(4, ge=1)
    neighbourhood: float = ranged(2.0, gt=0.0)
    dtype: str = ranged("float32", choices=DTYPES)


@dataclass
class ForecastGP:
    """``task.gp``: data budget and initial hyperparameters of both GP predictors."""

    points: int = ranged(2000, ge=2)
    fit_points: int = ranged(400, ge=2)
    fit_iters: int = ranged(40, ge=0)
    fit_lr: float = ranged(0.05, gt=0.0)
    outputscale: float = ranged(1.0, gt=0.0)
    lengthscale: float = ranged(1.0, gt=0.0)
    noise_std: float = ranged(0.3, gt=0.0)


@dataclass
class EthucyForecastTask:
    entry: str = "dslearn.studies.ethucy_forecast:run"
    name: str = "ethucy_forecast"
    data_root: Optional[str] = None
    convention: str = ranged("benchmark", choices=CONVENTIONS)
    scenes: List[str] = ranged(factory=lambda: ["eth", "hotel", "univ", "zara1", "zara2"], min_len=1)
    train_scenes: Optional[List[str]] = ranged(None, min_len=1)
    predictors: List[str] = ranged(factory=lambda: list(PREDICTORS), choices=PREDICTORS, each=True, min_len=1)
    obs_len: int = ranged(8, ge=3)
    pred_len: int = ranged(12, ge=1)
    min_peds: int = ranged(2, ge=1)
    test_stride: int = ranged(1, ge=1)
    train_stride: int = ranged(3, ge=1)
    max_test_windows: Optional[int] = ranged(None, ge=1)
    max_train_windows: Optional[int] = ranged(None, ge=1)
    quick: bool = False
    curves_file: Optional[str] = "learning_curves.csv"
    lstm: ForecastLSTM = field(default_factory=ForecastLSTM)
    gp: ForecastGP = field(default_factory=ForecastGP)
    folds: FoldsSchema = field(default_factory=FoldsSchema)
    datasets: Dict[str, DatasetSchema] = field(default_factory=dict)


def check_device(cfg: DictConfig) -> None:
    """``device`` (cpu | cuda[:n], CUDA present) and ``dtype`` (shared by the ETH/UCY tasks)."""
    dev = str(cfg.get("device", "cpu"))
    check_choice("device", dev.split(":")[0], ("cpu", "cuda"))
    if dev.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError("device=cuda was asked for but no CUDA device is available; use device=cpu")
    check_choice("dtype", cfg.get("dtype", "float64"), DTYPES)


def check_datasets(t) -> None:
    """Every composed data set's ranges, and the folds' scenes are data sets."""
    for name, node in (t.get("datasets") or {}).items():
        check_dataset(str(name), node, f"task.datasets.{name}")
    check_scene_names("task.folds.pool", list(t.folds.pool), t)
    check_scene_names("task.folds.test", list(t.folds.test), t)


def check(cfg: DictConfig) -> None:
    t = cfg.task
    check_device(cfg)
    check_datasets(t)
    check_scene_names("task.scenes", list(t.scenes), t)
    if t.get("train_scenes") is not None:
        check_scene_names("task.train_scenes", list(t.train_scenes), t)
    if len(set(t.predictors)) != len(t.predictors):
        raise ConfigError(f"task.predictors={list(t.predictors)} has duplicates")
    cf = t.get("curves_file")
    if cf is not None and not str(cf).strip():
        raise ConfigError(f"task.curves_file={cf!r} must be a file name / path or null (no learning-curve file)")
    from dslearn.models.lstm import schedule_from_config

    schedule_from_config(t.lstm, prefix="task.lstm")


#: what the study uses in place of each root group (it reads none of them: it forecasts from the tracks)
_NO_TRACKING = "it forecasts from the ground-truth tracks of task.scenes"
INSTEAD = {
    "scenario": "its scenes are task.scenes, data sets of task.datasets, with the folds task.folds",
    "network": f"{_NO_TRACKING}: no sensor network",
    "model": "its predictors are task.predictors, with task.gp and task.lstm",
    "observation": f"{_NO_TRACKING}: no observation model",
    "consensus": f"{_NO_TRACKING}: no fusion",
    "filter": f"{_NO_TRACKING}: no filter",
    "data": "its windows are task.obs_len + task.pred_len, at most task.max_train_windows / task.max_test_windows",
}

register_task("ethucy_forecast", EthucyForecastTask, check, uses=(), instead=INSTEAD)
