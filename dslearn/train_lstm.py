"""``dslearn-train-lstm``: train one LSTM encoder–decoder / Social-LSTM baseline and save it.

A Hydra app with its own config, ``conf/train_lstm.yaml`` (network and schedule from the
``lstm`` group, ``conf/lstm/default.yaml``)::

    dslearn-train-lstm                                   # paper defaults: obs 2, pred 10, 50 epochs, batch 8
    dslearn-train-lstm lstm.schedule=early_stopping lstm.epochs=200 lstm.patience=10   # stop on val_scenes' loss
    dslearn-train-lstm lstm.pooling=social lstm.epochs=5 train_scenes=[zara1,zara2] val_scenes=[zara3] \\
        train_part=all val_part=all checkpoint=slstm.pt device=cuda

Windows of ``lstm.obs_len + lstm.pred_len`` steps (every pedestrian of a window present
at all of them) come from ``train_scenes`` (data sets of ``datasets``, ``conf/dataset/*.yaml``) (``train_part`` of each file) and
``val_scenes`` (``val_part``). Writes the checkpoint (``torch.save`` of state dict +
hyperparameters; load with :func:`dslearn.models.lstm.load_checkpoint`, safe loading)
and ``history.csv`` (per-epoch train/val loss, learning rate, new-best flag) into the run
directory. ``lstm.schedule=early_stopping`` stops on the validation loss of ``val_scenes``
(``lstm.patience``, cap ``lstm.epochs``) and saves the best-validation weights.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig

from dslearn.compose import DTYPES
from dslearn.schemas.core import CONF_DIR as _CONF_DIR
from dslearn.data.datasets import load_dataset, task_datasets
from dslearn.data.ethucy import split_scene, windows
from dslearn.data.window_tensors import cat_windows, per_agent, subsample
from dslearn.errors import ConfigError, check_choice
from dslearn.io import atomic_write_csv
from dslearn.models.lstm import SCHEDULE_KEYS, SocialLSTM, schedule_from_config, train_lstm

log = logging.getLogger("dslearn.train_lstm")
CONF_DIR = str(_CONF_DIR)
#: keys of the ``lstm`` group (unknown keys are a ConfigError)
LSTM_GROUP_KEYS = ("embed", "hidden", "obs_len", "pred_len", "pooling", "grid", "neighbourhood", "noise_std") + SCHEDULE_KEYS


def _load(cfg: DictConfig, name: str):
    return load_dataset(task_datasets(cfg)[name], cfg.get("data_root"), str(cfg.convention))


def _windows(names, part: str, cfg: DictConfig, length: int) -> torch.Tensor | None:
    parts = []
    for n in names:
        sc = split_scene(_load(cfg, n), part)
        parts.append(windows(sc, length, int(cfg.stride), int(cfg.min_peds))[0])
    parts = [p for p in parts if p.shape[0] > 0]
    return cat_windows(parts) if parts else None


def train(cfg: DictConfig, out_dir: str | Path) -> tuple[SocialLSTM, "object", Path]:
    """Validate ``cfg``, build the data, train, save. Returns (model, history, checkpoint path)."""
    check_choice("device", str(cfg.device).split(":")[0], ("cpu", "cuda"))
    if str(cfg.device).startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError("device=cuda was asked for but no CUDA device is available (torch.cuda.is_available() is False); use device=cpu")
    check_choice("dtype", cfg.dtype, tuple(DTYPES))
    known = tuple(cfg.get("datasets") or {})
    for field in ("train_scenes", "val_scenes"):
        for s in cfg[field]:
            check_choice(field, s, known)
    if not list(cfg.train_scenes):
        raise ConfigError("train_scenes must name at least one scene")
    for field in ("train_part", "val_part"):
        check_choice(field, cfg[field], ("all", "train", "val"))
    check_choice("convention", cfg.convention, ("benchmark", "physical"))
    c = cfg.lstm
    unknown = sorted(set(c.keys()) - set(LSTM_GROUP_KEYS))
    if unknown:
        raise ConfigError(f"lstm has unknown keys {unknown}; allowed: {list(LSTM_GROUP_KEYS)}")
    sched = schedule_from_config(c, prefix="lstm")
    if "patience" in sched and not list(cfg.val_scenes):
        raise ConfigError("lstm.schedule=early_stopping needs validation windows: val_scenes must name at least one scene")
    dts = {task_datasets(cfg)[s].step(str(cfg.convention)) for s in cfg.train_scenes}
    if len(dts) > 1:
        raise ConfigError(f"train_scenes mix time steps {sorted(dts)} under convention={cfg.convention}; use convention=benchmark")
    model = SocialLSTM(
        1, obs_len=int(c.obs_len), pred_len=int(c.pred_len), embed=int(c.embed), hidden=int(c.hidden),
        pooling=str(c.pooling), grid=int(c.grid), neighbourhood=float(c.neighbourhood), dt=dts.pop(),
        dtype=DTYPES[str(cfg.dtype)], device=str(cfg.device), noise_std=float(c.get("noise_std", 0.1)), seed=int(cfg.seed),
    )
    length = model.obs_len + model.pred_len
    tr = _windows(cfg.train_scenes, str(cfg.train_part), cfg, length)
    if tr is None:
        raise ConfigError(f"train_scenes {list(cfg.train_scenes)} give no window of {length} steps")
    if cfg.get("max_windows") is not None:
        tr = subsample(tr, int(cfg.max_windows))
    va = _windows(cfg.val_scenes, str(cfg.val_part), cfg, length) if list(cfg.val_scenes) else None
    if model.pooling == "none":  # independent pedestrians: one sequence each, no padding
        tr = per_agent(tr).unsqueeze(2)
        va = None if va is None else per_agent(va).unsqueeze(2)
    log.info("training %s on %d windows (%s), validating on %s", model.pooling, tr.shape[0], list(cfg.train_scenes),
             "none" if va is None else f"{va.shape[0]} windows")
    ckpt = Path(cfg.checkpoint) if cfg.get("checkpoint") else Path(out_dir) / f"lstm_{model.pooling}.pt"
    if "patience" in sched and va is None:
        raise ConfigError(f"lstm.schedule=early_stopping: val_scenes {list(cfg.val_scenes)} give no validation window")
    hist = train_lstm(model, tr, **sched, val_windows=va, seed=int(cfg.seed), progress=bool(cfg.progress), checkpoint=ckpt)
    if "patience" in sched:
        log.info("early stopping: %d epochs run, best validation loss %.5f at epoch %d (weights restored)",
                 len(hist), hist.attrs["best_val_loss"], hist.attrs["best_epoch"])
    atomic_write_csv(hist, Path(out_dir) / "history.csv")
    return model, hist, ckpt


@hydra.main(version_base=None, config_path=CONF_DIR, config_name="train_lstm")
def _app(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    out_dir = HydraConfig.get().runtime.output_dir
    try:
        _, hist, ckpt = train(cfg, out_dir)
    except ConfigError as e:
        print(f"dslearn-train-lstm: configuration error: {e}", file=sys.stderr)
        raise SystemExit(2)
    print(hist.to_string(index=False))
    print(f"checkpoint: {ckpt}")


def main() -> None:
    _app()


if __name__ == "__main__":
    main()
