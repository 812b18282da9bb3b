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
``learning_curves.csv`` in the run directory (``task.curves_file``) and to the result's
``attrs["learning_curves"]``; the report turns them into ``learning_curves.png`` and a convergence table.

The study's settings are :class:`ForecastSettings` (the task's fields; :mod:`dslearn.schemas.ethucy_forecast`
adds the composed data sets and checks them); its slots are filled by the composition root: the data sets of
``task.datasets`` as specs (``ethucy_forecast_datasets``) and where the learning curves go
(``ethucy_forecast_curves_file``: ``task.curves_file``, a relative name inside the run directory, ``null`` =
nowhere). Python use (the same defaults and checks as ``dslearn-run``)::

    from dslearn import api
    df = api.run("experiment=ethucy_forecast", "task.quick=true", "task.scenes=[zara1]")

Results: one row per (held-out scene × predictor × metric), ``value`` = the mean over all
test pedestrian-windows of that scene (the benchmark's number); metrics ``ade``, ``fde``
(metres), ``count`` (pedestrian-windows), ``train_s`` (training seconds); for the LSTMs
``epochs_run``, ``best_epoch``, ``best_val_loss``, ``final_val_loss`` / ``final_train_loss``
(last epoch run), ``batch_size``; ``episode`` = fold index.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import List, Optional

import pandas as pd
import torch

from dslearn.data.datasets import CONVENTIONS, DatasetSpec, leave_one_out, load_dataset
from dslearn.data.ethucy import split_scene, windows
from dslearn.data.window_tensors import cat_windows, per_agent, quads, subsample
from dslearn.errors import ConfigError
from dslearn.forecast import constant_velocity, gp_forecaster
from dslearn.learning.lstm import train_forecast_lstm
from dslearn.metrics.forecast import forecast_row, forecast_scores
from dslearn.settings import ranged
from dslearn.types import DTYPES

log = logging.getLogger(__name__)

PREDICTORS = ("cv", "lstm", "social_lstm", "gp", "gp_state")
LSTM_MODELS = ("lstm", "social_lstm")
CURVE_COLUMNS = ["scene", "fold", "model", "epoch", "train_loss", "val_loss", "lr", "best", "seconds"]


# ------------------------------------------------------------------------------------------ settings
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
    dtype: str = ranged("float32", choices=tuple(DTYPES))


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
class ForecastFolds:
    """Leave-one-scene-out folds: the test scenes, and the pool a fold trains on (minus its test scene)."""

    test: List[str] = field(default_factory=list)
    pool: List[str] = field(default_factory=list)


@dataclass
class ForecastSettings:
    """The study's settings (the fields of ``conf/task/ethucy_forecast.yaml`` but the data sets, which
    the composition root hands over as specs)."""

    _target_: str = "dslearn.studies.ethucy_forecast.EthucyForecastStudy"
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
    folds: ForecastFolds = field(default_factory=ForecastFolds)


def effective_settings(s: ForecastSettings) -> ForecastSettings:
    """The settings with ``quick`` applied (<= 2 epochs, stride >= 10, <= 40 test windows, GP budget 300)."""
    if not s.quick:
        return s
    g = s.gp
    return replace(
        s, lstm=replace(s.lstm, epochs=min(int(s.lstm.epochs), 2)),
        gp=replace(g, points=min(g.points, 300), fit_points=min(g.fit_points, 100), fit_iters=min(g.fit_iters, 5)),
        train_stride=max(s.train_stride, 10), max_test_windows=min(s.max_test_windows or 40, 40),
    )


def fold_train_scenes(s: ForecastSettings, test_scene: str) -> tuple[str, ...]:
    """``train_scenes`` if given, else the fold's: ``folds.pool`` minus the test scene."""
    if s.train_scenes is not None:
        return tuple(str(n) for n in s.train_scenes)
    return leave_one_out(test_scene, s.folds.pool)


def load_windows(s: ForecastSettings, specs: dict[str, DatasetSpec],
                 length: int) -> tuple[dict, dict, dict, dict, dict]:
    """Every scene the folds need (``specs``: the data sets by name): scenes, test windows (test scenes),
    train / validation windows (benchmark time split of each file) and the train parts' position
    quadruples (for the GPs)."""
    needed = set(s.scenes)
    for n in s.scenes:
        needed |= set(fold_train_scenes(s, n))
    scenes = {n: load_dataset(specs[n], s.data_root, str(s.convention)) for n in sorted(needed)}
    test_w, train_w, val_w, quad = {}, {}, {}, {}
    for name, sc in scenes.items():
        if name in s.scenes:
            w, _ = windows(sc, length, int(s.test_stride), int(s.min_peds))
            test_w[name] = subsample(w, s.max_test_windows)
        tr, va = split_scene(sc, "train"), split_scene(sc, "val")
        train_w[name] = windows(tr, length, int(s.train_stride), int(s.min_peds))[0]
        val_w[name] = windows(va, length, int(s.train_stride), int(s.min_peds))[0]
        quad[name] = quads([tr])
    return scenes, test_w, train_w, val_w, quad


# ------------------------------------------------------------------------------------------ the study
@dataclass
class EthucyForecastStudy:
    """Leave-one-scene-out ADE/FDE of every predictor (see the module docstring).

    Slots: ``settings`` (:class:`ForecastSettings`), the run's ``seed``, ``dtype`` (of the GPs; the LSTMs'
    is ``settings.lstm.dtype``) and ``device``, the data sets by name (``ethucy_forecast_datasets``) and the
    learning-curve file (``ethucy_forecast_curves_file``; None = none written)."""

    settings: ForecastSettings
    seed: int
    dtype: torch.dtype
    device: torch.device
    ethucy_forecast_datasets: dict[str, DatasetSpec]
    ethucy_forecast_curves_file: Optional[Path] = None

    def run(self, diagnostics=None, progress: bool = False) -> pd.DataFrame:
        """Train and test every predictor on every fold; the tidy results table (curves in its attrs)."""
        t = effective_settings(self.settings)
        seed, device, gp_dtype = int(self.seed), self.device, self.dtype
        lstm_dtype = DTYPES[str(t.lstm.dtype)]
        obs_len, pred_len = int(t.obs_len), int(t.pred_len)
        t_start = time.perf_counter()
        scenes, test_w, train_w, val_w, quad = load_windows(t, self.ethucy_forecast_datasets, obs_len + pred_len)
        log.info("data loaded in %.1fs", time.perf_counter() - t_start)

        rows = []
        curves: list[pd.DataFrame] = []
        for fold, test_scene in enumerate(t.scenes):
            train_names = fold_train_scenes(t, test_scene)
            dt = scenes[test_scene].dt
            tw = test_w[test_scene]
            if tw.shape[0] == 0:
                raise ConfigError(f"task.scenes: scene {test_scene} has no test window with the given settings")
            truth_agents = per_agent(tw)  # (M, 20, 2)
            obs_agents, fut_agents = truth_agents[:, :obs_len], truth_agents[:, obs_len:]
            trw = subsample(cat_windows([train_w[n] for n in train_names]), t.max_train_windows)
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
                    log.info("%s %s: %d epochs, best validation loss %.5f at epoch %d", test_scene, pred_name,
                             len(hist), hist.attrs["best_val_loss"], hist.attrs["best_epoch"])
                    pred = predict(tw)
                else:  # GPs
                    q = torch.cat([quad[n] for n in train_names], 0)
                    gen = torch.Generator().manual_seed(seed * 1000 + fold)
                    predict, extra = gp_forecaster(pred_name, q, dt, t.gp, gen, gp_dtype, device)
                    pred = predict(obs_agents, pred_len)
                secs = time.perf_counter() - t0
                try:
                    scores = forecast_scores(pred, fut_agents)
                except FloatingPointError as e:
                    raise FloatingPointError(f"{pred_name} on {test_scene}: {e}") from None
                for metric, value in (*scores.items(), ("train_s", secs), *extra.items()):
                    rows.append(forecast_row(pred_name, test_scene, fold, metric, value))
                log.info("%s %s: ADE %.3f FDE %.3f (%.1fs)", test_scene, pred_name, scores["ade"], scores["fde"], secs)
        df = pd.DataFrame(rows)
        lc = pd.concat(curves, ignore_index=True)[CURVE_COLUMNS] if curves else pd.DataFrame(columns=CURVE_COLUMNS)
        df.attrs["learning_curves"] = lc
        path = self.ethucy_forecast_curves_file
        if path is not None and curves:
            from dslearn.io import atomic_write_csv

            atomic_write_csv(lc, path)
            log.info("learning curves: %s", path)
        df.attrs["wall_s"] = time.perf_counter() - t_start
        log.info("ethucy_forecast finished in %.1fs", df.attrs["wall_s"])
        return df
