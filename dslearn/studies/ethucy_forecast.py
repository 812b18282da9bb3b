r"""ETH/UCY trajectory forecasting: the standard leave-one-scene-out ADE/FDE protocol.

For each test scene (``task.scenes``; default the five benchmark scenes ETH, HOTEL, UNIV, ZARA1,
ZARA2 of ``conf/folds/ethucy.yaml``) the predictors are trained on ``task.train_scenes`` (default:
the fold's, i.e. the pool minus the test scene, so ``zara3`` and ``uni_examples`` always train)
and tested on the held-out one: 8 observed steps (3.2 s) -> 12 predicted steps (4.8 s), benchmark
time convention (every file, ``biwi_eth.txt`` included, at Δt = 0.4 s per row step). Every scene
is a data set of ``task.datasets`` (``conf/dataset/<name>.yaml``; :mod:`dslearn.data.datasets`).

Predictors (``task.predictors``):

* ``cv``: constant velocity, the last observed velocity ``p_8 - p_7`` carried forward.
* ``lstm``: the LSTM encoder–decoder of :mod:`dslearn.models.lstm` (no pooling), trained by
  :func:`dslearn.learning.lstm.train_forecast_lstm`.
* ``social_lstm``: the same with Alahi et al.'s (2016) grid pooling of neighbours'
  hidden states (all pedestrians of a window pool each other).
* ``gp``: the project's online GP (:class:`dslearn.models.OnlineGP`, identity prior
  mean) on single-agent velocities: input ``[v_t, v_{t-1}]`` (m/s), output ``v_{t+1}``;
  with the identity mean it learns the correction to constant velocity and falls back to
  it away from the data. Translation-invariant, so it transfers across scenes.
* ``gp_state``: :class:`dslearn.models.GPMotionModel` exactly as the tracking studies use
  it, on the single-agent state ``[p, v]`` -> next state (identity mean = increment), rolled
  out with ``MotionModel.rollout`` (both GPs: :func:`dslearn.forecast.gp_forecaster`). Its input contains absolute positions, which mean
  nothing in another scene's world frame; it is here to show that.

Both GPs are trained on ground-truth consecutive triples of the training scenes' train
parts, subsampled at random to ``task.gp.points`` (a data budget; exact GP), with kernel
hyperparameters fitted by marginal likelihood (:meth:`OnlineGP.fit`) on a
``task.gp.fit_points`` subset first, and rolled out 12 steps from the state at the last
observed step (velocity = last observed displacement / Δt).

Windows follow the Social GAN loader: 20 consecutive steps of one file, every pedestrian
present at all of them, at least ``task.min_peds`` (2) such pedestrians; test windows
slide by ``task.test_stride`` (1, the benchmark); training windows by
``task.train_stride`` (coarser, for speed; documented in the README). LSTMs train on the
benchmark's train parts (first ~80 % of each training file in time) and are validated on
the validation parts (the rest of each *training* file; the held-out test scene is never
seen): with ``task.lstm.schedule=early_stopping`` (default) training stops after
``task.lstm.patience`` epochs without a new best validation loss (cap ``task.lstm.epochs``)
and the best-validation weights are restored; ``schedule=fixed`` is the paper's plain
schedule (all epochs, last weights). The per-epoch losses of every (fold, LSTM) go to
``learning_curves.csv`` in the run directory (``task.curves_file``); the report turns them
into ``learning_curves.png`` and a convergence table.

Results: one row per (held-out scene × predictor × metric), ``value`` = the mean over all
test pedestrian-windows of that scene (the benchmark's number); metrics ``ade``, ``fde``
(metres), ``count`` (pedestrian-windows), ``train_s`` (training seconds); for the LSTMs
``epochs_run``, ``best_epoch``, ``best_val_loss``, ``final_val_loss`` / ``final_train_loss``
(last epoch run), ``batch_size``; ``episode`` = fold index.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf

from dslearn.data.datasets import leave_one_out, load_dataset, task_datasets
from dslearn.data.ethucy import split_scene, windows
from dslearn.data.window_tensors import cat_windows, per_agent, quads, subsample
from dslearn.errors import ConfigError
from dslearn.types import DTYPES
from dslearn.forecast import ade_fde, constant_velocity, gp_forecaster
from dslearn.learning.lstm import train_forecast_lstm

log = logging.getLogger(__name__)

PREDICTORS = ("cv", "lstm", "social_lstm", "gp", "gp_state")
LSTM_MODELS = ("lstm", "social_lstm")
CURVE_COLUMNS = ["scene", "fold", "model", "epoch", "train_loss", "val_loss", "lr", "best", "seconds"]


def effective_task(t: DictConfig) -> DictConfig:
    """The task config with ``quick`` applied (<= 2 epochs, stride >= 10, <= 40 test windows, GP budget 300)."""
    if not t.get("quick"):
        return t
    q = OmegaConf.to_container(t, resolve=True)
    q["lstm"].update(epochs=min(int(t.lstm.epochs), 2))
    g = t.gp
    q["gp"].update(points=min(g.points, 300), fit_points=min(g.fit_points, 100), fit_iters=min(g.fit_iters, 5))
    q["train_stride"] = max(t.train_stride, 10)
    q["max_test_windows"] = min(t.get("max_test_windows") or 40, 40)
    return OmegaConf.create(q)


def fold_train_scenes(t: DictConfig, test_scene: str) -> tuple[str, ...]:
    """``task.train_scenes`` if given, else the fold's: ``task.folds.pool`` minus the test scene."""
    if t.get("train_scenes") is not None:
        return tuple(str(s) for s in t.train_scenes)
    return leave_one_out(test_scene, t.folds.pool)


def _curves_path(name) -> Path | None:
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
    except Exception:  # not under Hydra (e.g. run(cfg) from Python): the curves stay in df.attrs
        return None


def load_windows(t: DictConfig, length: int) -> tuple[dict, dict, dict, dict, dict]:
    """Every scene the folds need: scenes, test windows (test scenes), train / validation windows
    (benchmark time split of each file) and the train parts' position quadruples (for the GPs)."""
    specs = task_datasets(t)
    needed = set(t.scenes)
    for s in t.scenes:
        needed |= set(fold_train_scenes(t, s))
    scenes = {n: load_dataset(specs[n], t.get("data_root"), str(t.convention)) for n in sorted(needed)}
    test_w, train_w, val_w, quad = {}, {}, {}, {}
    for name, sc in scenes.items():
        if name in t.scenes:
            w, _ = windows(sc, length, int(t.test_stride), int(t.min_peds))
            test_w[name] = subsample(w, t.get("max_test_windows"))
        tr, va = split_scene(sc, "train"), split_scene(sc, "val")
        train_w[name] = windows(tr, length, int(t.train_stride), int(t.min_peds))[0]
        val_w[name] = windows(va, length, int(t.train_stride), int(t.min_peds))[0]
        quad[name] = quads([tr])
    return scenes, test_w, train_w, val_w, quad


def run(cfg: DictConfig) -> pd.DataFrame:
    """Task entry point for ``dslearn-run experiment=ethucy_forecast`` (see module docstring); ``cfg``
    is already checked (:mod:`dslearn.schemas.ethucy_forecast`)."""
    t = effective_task(cfg.task)
    seed = int(cfg.get("seed", 0))
    device = torch.device(str(cfg.get("device", "cpu")))
    gp_dtype = DTYPES[str(cfg.get("dtype", "float64"))]
    lstm_dtype = DTYPES[str(t.lstm.dtype)]
    progress = bool(cfg.get("progress", False))
    obs_len, pred_len = int(t.obs_len), int(t.pred_len)
    t_start = time.perf_counter()
    scenes, test_w, train_w, val_w, quad = load_windows(t, obs_len + pred_len)
    log.info("data loaded in %.1fs", time.perf_counter() - t_start)

    rows = []
    curves: list[pd.DataFrame] = []

    def add(model, scene, fold, metric, value):
        rows.append(dict(model=model, consensus="-", node="avg", scene=scene, metric=metric, value=float(value), episode=fold))

    for fold, test_scene in enumerate(t.scenes):
        train_names = fold_train_scenes(t, test_scene)
        dt = scenes[test_scene].dt
        tw = test_w[test_scene]
        if tw.shape[0] == 0:
            raise ConfigError(f"task.scenes: scene {test_scene} has no test window with the given settings")
        truth_agents = per_agent(tw)  # (M, 20, 2)
        obs_agents, fut_agents = truth_agents[:, :obs_len], truth_agents[:, obs_len:]
        trw = subsample(cat_windows([train_w[n] for n in train_names]), t.get("max_train_windows"))
        vaw = cat_windows([val_w[n] for n in train_names])
        for pi, pred_name in enumerate(t.predictors):
            t0 = time.perf_counter()
            extra = {}
            if pred_name == "cv":
                pred = constant_velocity(obs_agents, pred_len)
            elif pred_name in LSTM_MODELS:
                predict, hist, extra = train_forecast_lstm(
                    pred_name == "social_lstm", trw, vaw, t.lstm, obs_len, pred_len, dt, lstm_dtype, device,
                    seed=seed * 1000 + fold * 10 + pi, train_seed=seed + fold, progress=progress,
                )
                curves.append(hist.assign(scene=test_scene, fold=fold, model=pred_name))
                log.info("%s %s: %d epochs, best validation loss %.5f at epoch %d", test_scene, pred_name, len(hist),
                         hist.attrs["best_val_loss"], hist.attrs["best_epoch"])
                pred = predict(tw)
            else:  # GPs
                q = torch.cat([quad[n] for n in train_names], 0)
                gen = torch.Generator().manual_seed(seed * 1000 + fold)
                predict, extra = gp_forecaster(pred_name, q, dt, t.gp, gen, gp_dtype, device)
                pred = predict(obs_agents, pred_len)
            secs = time.perf_counter() - t0
            ade, fde = ade_fde(pred.to(torch.float64), fut_agents)
            if not (torch.isfinite(ade).all() and torch.isfinite(fde).all()):
                raise RuntimeError(f"{pred_name} on {test_scene}: non-finite predictions")
            add(pred_name, test_scene, fold, "ade", ade.mean())
            add(pred_name, test_scene, fold, "fde", fde.mean())
            add(pred_name, test_scene, fold, "count", ade.numel())
            add(pred_name, test_scene, fold, "train_s", secs)
            for k, v in extra.items():
                add(pred_name, test_scene, fold, k, v)
            log.info("%s %s: ADE %.3f FDE %.3f (%.1fs)", test_scene, pred_name, float(ade.mean()), float(fde.mean()), secs)
    df = pd.DataFrame(rows)
    lc = pd.concat(curves, ignore_index=True)[CURVE_COLUMNS] if curves else pd.DataFrame(columns=CURVE_COLUMNS)
    df.attrs["learning_curves"] = lc
    path = _curves_path(t.get("curves_file"))
    if path is not None and curves:
        from dslearn.io import atomic_write_csv

        atomic_write_csv(lc, path)
        log.info("learning curves: %s", path)
    df.attrs["wall_s"] = time.perf_counter() - t_start
    log.info("ethucy_forecast finished in %.1fs", df.attrs["wall_s"])
    return df
