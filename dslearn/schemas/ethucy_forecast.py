"""Schema of the ``ethucy_forecast`` task (``conf/task/ethucy_forecast.yaml``): ETH/UCY
leave-one-scene-out forecasting. Keys and types are checked at composition, ranges by
:func:`dslearn.schemas.base.check_ranges`, the rest by :func:`check`.

The study's slots of its own (:func:`dslearn.compose.register_slot`): ``ethucy_forecast_datasets``, the
composed data sets of ``task.datasets`` as :class:`dslearn.data.datasets.DatasetSpec` (by name), and
``ethucy_forecast_curves_file``, where the learning curves go (:func:`curves_path`)."""

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict

import torch
from omegaconf import DictConfig

from dslearn.compose import register_slot
from dslearn.data.datasets import check_dataset
from dslearn.errors import ConfigError, check_choice
from dslearn.schemas.base import register_task
from dslearn.schemas.datasets import DatasetSchema, check_scene_names, spec_from_config
from dslearn.studies.ethucy_forecast import ForecastSettings

DTYPES = ("float64", "float32")


@dataclass
class EthucyForecastTask(ForecastSettings):
    """The task's schema: the study's settings (:class:`dslearn.studies.ethucy_forecast.ForecastSettings`)
    and the data sets the task composes (``conf/dataset/<name>.yaml``, typed by :class:`DatasetSchema`)."""

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

def task_specs(task) -> dict:
    """The data sets of ``task.datasets`` (a config node) as specs, by name."""
    return {str(k): spec_from_config(str(k), v) for k, v in (task.get("datasets") or {}).items()}


def curves_path(name) -> Path | None:
    """Where ``learning_curves.csv`` goes: an absolute ``task.curves_file`` as is, a relative
    one inside the Hydra run directory (not written outside Hydra), ``null`` = nowhere."""
    if name is None:
        return None
    p = Path(str(name))
    if p.is_absolute():
        return p
    try:
        from hydra.core.hydra_config import HydraConfig

        return Path(HydraConfig.get().runtime.output_dir) / p
    except Exception:  # not under Hydra (e.g. the Python API): the curves stay in the result's attrs
        return None


def unused(cfg: DictConfig) -> dict[str, str]:
    """The task keys that ``task.predictors`` do not read: the LSTMs' settings and learning curves without an
    LSTM among them, the GPs' without a GP (an override of them is refused)."""
    preds = [str(p) for p in cfg.task.predictors]
    out = {}
    if not any(p in ("lstm", "social_lstm") for p in preds):
        why = f"with task.predictors={preds} (no lstm or social_lstm)"
        out.update({"task.lstm": why, "task.curves_file": why})
    if not any(p in ("gp", "gp_state") for p in preds):
        out["task.gp"] = f"with task.predictors={preds} (no gp or gp_state)"
    return out


register_task("ethucy_forecast", EthucyForecastTask, check, uses=(), instead=INSTEAD, unused=unused)
register_slot("ethucy_forecast_datasets", lambda cfg, slots: task_specs(cfg.task))
register_slot("ethucy_forecast_curves_file", lambda cfg, slots: curves_path(cfg.task.get("curves_file")))
