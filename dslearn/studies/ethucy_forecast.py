r"""ETH/UCY trajectory forecasting: the standard leave-one-scene-out ADE/FDE protocol.

For each of the five benchmark scenes (ETH, HOTEL, UNIV, ZARA1, ZARA2) the predictors are
trained on the other scenes (including ``crowds_zara03`` and ``uni_examples``) and tested
on the held-out one: 8 observed steps (3.2 s) -> 12 predicted steps (4.8 s), benchmark
time convention (every file, ``biwi_eth.txt`` included, at Δt = 0.4 s per row step).

Predictors (``task.predictors``):

* ``cv``: constant velocity, the last observed velocity ``p_8 - p_7`` carried forward.
* ``lstm``: the LSTM encoder–decoder of :mod:`dslearn.models.lstm` (no pooling).
* ``social_lstm``: the same with Alahi et al.'s (2016) grid pooling of neighbours'
  hidden states (all pedestrians of a window pool each other).
* ``gp``: the project's online GP (:class:`dslearn.models.OnlineGP`, identity prior
  mean) on single-agent velocities: input ``[v_t, v_{t-1}]`` (m/s), output ``v_{t+1}``;
  with the identity mean it learns the correction to constant velocity and falls back to
  it away from the data. Translation-invariant, so it transfers across scenes.
* ``gp_state``: :class:`dslearn.models.GPMotionModel` exactly as the tracking studies use
  it, on the single-agent state ``[p, v]`` -> next state (identity mean = increment), rolled
  out with ``MotionModel.rollout``. Its input contains absolute positions, which mean
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

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf
from torch import Tensor

from dslearn.data.ethucy import SCENES, fold_scenes, load_scene, split_scene, windows
from dslearn.errors import ConfigError, check_choice, check_positive
from dslearn.models.gp import GPMotionModel
from dslearn.learning.gp import OnlineGP
from dslearn.models.lstm import SCHEDULE_KEYS, SocialLSTM, schedule_from_config, train_lstm

log = logging.getLogger(__name__)

PREDICTORS = ("cv", "lstm", "social_lstm", "gp", "gp_state")
LABELS = {"cv": "CV", "lstm": "LSTM", "social_lstm": "S-LSTM", "gp": "GP (vel.)", "gp_state": "GP (state)"}
SCENE_LABELS = {"eth": "ETH", "hotel": "HOTEL", "univ": "UNIV", "zara1": "ZARA1", "zara2": "ZARA2"}
DTYPES = {"float64": torch.float64, "float32": torch.float32}
LSTM_MODELS = ("lstm", "social_lstm")
#: every key ``task.lstm`` may hold (unknown keys are a ConfigError)
LSTM_KEYS = ("embed", "hidden", "grid", "neighbourhood", "dtype", "social_batch_size") + SCHEDULE_KEYS
#: the previous default schedule's epoch count (6 epochs, batch 64): the report compares the
#: validation loss there with the best one reached by early stopping
OLD_EPOCHS = 6
CURVE_COLUMNS = ["scene", "fold", "model", "epoch", "train_loss", "val_loss", "lr", "best", "seconds"]

#: Published 8 -> 12 ADE / FDE in metres: Gupta et al., "Social GAN", CVPR 2018, Table 1
#: (t_pred = 12 rows; "Linear" there is a least-squares linear regressor, not constant velocity).
#: See experiments/ethucy_forecast/README.md for how each figure was checked.
PUBLISHED_SGAN = {
    "Linear": {"eth": (1.33, 2.94), "hotel": (0.39, 0.72), "univ": (0.82, 1.59), "zara1": (0.62, 1.21), "zara2": (0.77, 1.48), "avg": (0.79, 1.59)},
    "LSTM": {"eth": (1.09, 2.41), "hotel": (0.86, 1.91), "univ": (0.61, 1.31), "zara1": (0.41, 0.88), "zara2": (0.52, 1.11), "avg": (0.70, 1.52)},
    "S-LSTM": {"eth": (1.09, 2.35), "hotel": (0.79, 1.76), "univ": (0.67, 1.40), "zara1": (0.47, 1.00), "zara2": (0.56, 1.17), "avg": (0.72, 1.54)},
}


# metrics and the constant-velocity baseline ---------------------------------------------
def ade_fde(pred: Tensor, truth: Tensor) -> tuple[Tensor, Tensor]:
    """Average and final displacement errors ``(..., T, 2), (..., T, 2) -> (...), (...)``.

    ADE :math:`= \\frac1T \\sum_t \\|\\hat p_t - p_t\\|_2`, FDE :math:`= \\|\\hat p_T - p_T\\|_2` (metres).
    """
    err = (pred - truth).norm(dim=-1)
    return err.mean(-1), err[..., -1]


def constant_velocity(obs: Tensor, pred_len: int) -> Tensor:
    """``(..., T_obs, 2) -> (..., pred_len, 2)``: ``p_last + k (p_last - p_prev)``, k = 1..pred_len."""
    v = obs[..., -1, :] - obs[..., -2, :]
    k = torch.arange(1, pred_len + 1, dtype=obs.dtype, device=obs.device)
    return obs[..., -1:, :] + k[:, None] * v[..., None, :]


# data -------------------------------------------------------------------------------------
def _per_agent(w: Tensor) -> Tensor:
    """NaN-padded windows ``(N, T, A, 2)`` -> present pedestrian-windows ``(M, T, 2)``."""
    present = torch.isfinite(w).all(-1).all(1)  # (N, A)
    return w.permute(0, 2, 1, 3)[present]


def _cat_windows(parts: list[Tensor]) -> Tensor:
    """Concatenate NaN-padded window tensors with different ``A`` (pads with NaN)."""
    parts = [p for p in parts if p.shape[0] > 0]
    a = max(p.shape[2] for p in parts)
    out = []
    for p in parts:
        if p.shape[2] < a:
            pad = torch.full((*p.shape[:2], a - p.shape[2], 2), float("nan"), dtype=p.dtype)
            p = torch.cat([p, pad], dim=2)
        out.append(p)
    return torch.cat(out, 0)


def _subsample(w: Tensor, k: int | None) -> Tensor:
    """At most ``k`` windows, evenly spaced (deterministic)."""
    if k is None or w.shape[0] <= k:
        return w
    idx = torch.linspace(0, w.shape[0] - 1, int(k)).round().long().unique()
    return w[idx]


# GP predictors ----------------------------------------------------------------------------
def _load_gp_data(gp: OnlineGP, x: Tensor, y: Tensor) -> None:
    """Replace the GP's data with ``x (n, Dx) -> y (n, Dy)`` in one factorisation (node 0)."""
    n = x.shape[0]
    gp.reset()
    gp._alloc(n)
    xs = x.to(gp.X).unsqueeze(0)
    gp.X[:, :n] = xs
    gp.R[:, :n] = y.to(gp.X).unsqueeze(0) - gp.prior_mean(xs)
    gp.mask[:, :n] = True
    gp.n = n
    gp.refactorize()


def _fit_gp(gp: OnlineGP, x: Tensor, y: Tensor, c, gen: torch.Generator) -> dict:
    perm = torch.randperm(x.shape[0], generator=gen)
    fit_idx = perm[: int(c.fit_points)]
    if int(c.fit_iters) > 0 and fit_idx.numel() >= 2:
        _load_gp_data(gp, x[fit_idx], y[fit_idx])
        gp.fit(int(c.fit_iters), float(c.fit_lr))
    use = perm[: int(c.points)]
    _load_gp_data(gp, x[use], y[use])
    return {"lengthscale": float(gp.lengthscale[0]), "outputscale": float(gp.outputscale[0]), "noise_var": float(gp.noise_var[0])}


def _quads(scene_parts) -> Tensor:
    """Every run of 4 consecutive positions of every pedestrian: ``(K, 4, 2)`` float64."""
    out = []
    for sc in scene_parts:
        d = sc.df.sort_values(["ped", "step"])
        ped = d["ped"].to_numpy()
        step = d["step"].to_numpy()
        xy = d[["x", "y"]].to_numpy()
        ok = (ped[3:] == ped[:-3]) & (step[3:] - step[:-3] == 3)
        idx = np.nonzero(ok)[0]
        out.append(np.stack([xy[idx], xy[idx + 1], xy[idx + 2], xy[idx + 3]], axis=1))
    return torch.as_tensor(np.concatenate(out, 0))


def gp_velocity_data(quads: Tensor, dt: float) -> tuple[Tensor, Tensor]:
    """``(K, 4, 2)`` positions -> inputs ``[v_2, v_1]`` (K, 4) and targets ``v_3`` (K, 2), m/s
    (``v_k = (p_k - p_{k-1}) / dt``, indices within the quadruple)."""
    v = (quads[:, 1:] - quads[:, :-1]) / dt  # v_1, v_2, v_3
    return torch.cat([v[:, 1], v[:, 0]], -1), v[:, 2]


def gp_state_data(quads: Tensor, dt: float) -> tuple[Tensor, Tensor]:
    """``(K, 4, 2)`` -> states ``[p_2, v_2]`` and next states ``[p_3, v_3]`` (K, 4)."""
    v = (quads[:, 1:] - quads[:, :-1]) / dt
    return torch.cat([quads[:, 2], v[:, 1]], -1), torch.cat([quads[:, 3], v[:, 2]], -1)


@torch.no_grad()
def gp_mean(gp: OnlineGP, x: Tensor) -> Tensor:
    """Posterior mean of node 0 of ``gp`` at ``x (N, Dx) -> (N, Dy)``.

    Same value as ``gp.predict(x[None])[0]`` (tested), computed with one matmul for the
    squared distances, which is several times faster for the ~10^4 queries x 2000 points
    of a forecasting fold. All stored points must be valid (as :func:`_load_gp_data` makes them).
    """
    n = gp.n
    ls, os_ = gp.lengthscale[0].to(x), gp.outputscale[0].to(x)
    a, b = x / ls, gp.X[0, :n].to(x) / ls
    d2 = ((a * a).sum(-1, keepdim=True) + (b * b).sum(-1) - 2.0 * a @ b.T).clamp_min(0.0)
    return gp.prior_mean(x.unsqueeze(0))[0] + (os_ * torch.exp(-0.5 * d2)) @ gp.alpha[0].to(x)


@torch.no_grad()
def gp_velocity_rollout(gp: OnlineGP, obs: Tensor, pred_len: int, dt: float) -> Tensor:
    """``(M, T_obs, 2)`` observed positions -> ``(M, pred_len, 2)``: iterate the GP mean of the
    next velocity from ``[v_t, v_{t-1}]`` and integrate ``p += v dt``."""
    p = obs[:, -1]
    v_t, v_p = (obs[:, -1] - obs[:, -2]) / dt, (obs[:, -2] - obs[:, -3]) / dt
    seq = []
    for _ in range(pred_len):
        v_p, v_t = v_t, gp_mean(gp, torch.cat([v_t, v_p], -1))
        p = p + v_t * dt
        seq.append(p)
    return torch.stack(seq, 1)


@torch.no_grad()
def gp_state_rollout(model: GPMotionModel, obs: Tensor, pred_len: int, dt: float) -> Tensor:
    """``(M, T_obs, 2)`` -> ``(M, pred_len, 2)``: the mean rollout of ``model`` from
    ``[p_T, v_T]`` (equal to ``model.rollout``, tested; uses :func:`gp_mean` for speed)."""
    x = torch.cat([obs[:, -1], (obs[:, -1] - obs[:, -2]) / dt], -1)
    seq = []
    for _ in range(pred_len):
        x = gp_mean(model.gp, x)
        seq.append(x[:, :2])
    return torch.stack(seq, 1)


@torch.no_grad()
def lstm_predict(model: SocialLSTM, obs: Tensor, batch: int = 64) -> Tensor:
    """``(N, T_obs, A, 2)`` windows -> ``(N, pred_len, A, 2)`` in batches (trimmed padding)."""
    outs = []
    for i in range(0, obs.shape[0], batch):
        o = obs[i : i + batch]
        present = torch.isfinite(o).all(-1).all(1).any(0)
        k = int(present.nonzero().max()) + 1 if bool(present.any()) else 1  # windows are packed
        pred = model.predict(o[:, :, :k])
        full = torch.full((o.shape[0], pred.shape[1], o.shape[2], 2), float("nan"), dtype=o.dtype)
        full[:, :, :k] = pred
        outs.append(full)
    return torch.cat(outs, 0)


# configuration ------------------------------------------------------------------------------
def _int(field: str, v, lo: int = 1) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < lo:
        raise ConfigError(f"{field}={v!r} must be an integer >= {lo}")
    return v


def validate(cfg: DictConfig) -> DictConfig:
    """Check ``cfg.task`` (and device/dtype); returns the effective task config (``quick`` applied)."""
    t = cfg.task
    check_choice("device", str(cfg.get("device", "cpu")).split(":")[0], ("cpu", "cuda"))
    if str(cfg.get("device", "cpu")).startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError("device=cuda was asked for but no CUDA device is available; use device=cpu")
    scenes = list(t.scenes)
    if not scenes:
        raise ConfigError("task.scenes must list at least one of " + str(list(SCENES)))
    for s in scenes:
        check_choice("task.scenes", s, tuple(SCENES))
    if len(set(scenes)) != len(scenes):
        raise ConfigError(f"task.scenes={scenes} has duplicates")
    preds = list(t.predictors)
    if not preds:
        raise ConfigError(f"task.predictors must list at least one of {list(PREDICTORS)}")
    for p in preds:
        check_choice("task.predictors", p, PREDICTORS)
    check_choice("task.convention", t.convention, ("benchmark", "physical"))
    _int("task.obs_len", t.obs_len, 3)
    _int("task.pred_len", t.pred_len)
    _int("task.min_peds", t.min_peds)
    _int("task.test_stride", t.test_stride)
    _int("task.train_stride", t.train_stride)
    if t.get("max_test_windows") is not None:
        _int("task.max_test_windows", t.max_test_windows)
    if t.get("max_train_windows") is not None:
        _int("task.max_train_windows", t.max_train_windows)
    c = t.lstm
    unknown = sorted(set(c.keys()) - set(LSTM_KEYS))
    if unknown:
        raise ConfigError(f"task.lstm has unknown keys {unknown}; allowed: {list(LSTM_KEYS)}")
    for f in ("embed", "hidden", "grid"):
        _int(f"task.lstm.{f}", c[f])
    schedule_from_config(c, prefix="task.lstm")
    if c.get("social_batch_size") is not None:
        _int("task.lstm.social_batch_size", c.social_batch_size)
    check_positive("task.lstm.neighbourhood", c.neighbourhood)
    check_choice("task.lstm.dtype", c.dtype, tuple(DTYPES))
    cf = t.get("curves_file")
    if cf is not None and (not isinstance(cf, str) or not cf.strip()):
        raise ConfigError(f"task.curves_file={cf!r} must be a file name / path or null (no learning-curve file)")
    g = t.gp
    _int("task.gp.points", g.points, 2)
    _int("task.gp.fit_points", g.fit_points, 2)
    _int("task.gp.fit_iters", g.fit_iters, 0)
    for f in ("outputscale", "lengthscale", "noise_std", "fit_lr"):
        check_positive(f"task.gp.{f}", g[f])
    check_choice("dtype", cfg.get("dtype", "float64"), tuple(DTYPES))
    if t.get("quick"):
        q = OmegaConf.to_container(t, resolve=True)
        q["lstm"].update(epochs=min(int(c.epochs), 2))
        q["gp"].update(points=min(g.points, 300), fit_points=min(g.fit_points, 100), fit_iters=min(g.fit_iters, 5))
        q["train_stride"] = max(t.train_stride, 10)
        q["max_test_windows"] = min(t.get("max_test_windows") or 40, 40)
        return OmegaConf.create(q)
    return t


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


# the study ----------------------------------------------------------------------------------
def run(cfg: DictConfig) -> pd.DataFrame:
    """Task entry point for ``dslearn-run experiment=ethucy_forecast`` (see module docstring)."""
    t = validate(cfg)
    seed = int(cfg.get("seed", 0))
    device = torch.device(str(cfg.get("device", "cpu")))
    gp_dtype = DTYPES[str(cfg.get("dtype", "float64"))]
    lstm_dtype = DTYPES[str(t.lstm.dtype)]
    progress = bool(cfg.get("progress", False))
    obs_len, pred_len = int(t.obs_len), int(t.pred_len)
    length = obs_len + pred_len
    root = t.get("data_root")
    t_start = time.perf_counter()

    needed = set(t.scenes)
    for s in t.scenes:
        needed |= set(fold_scenes(s)[1])
    scenes = {name: load_scene(name, root=root, convention=str(t.convention)) for name in sorted(needed)}
    test_w, train_w, val_w, quads = {}, {}, {}, {}
    for name, sc in scenes.items():
        if name in t.scenes:
            w, _ = windows(sc, length, int(t.test_stride), int(t.min_peds))
            test_w[name] = _subsample(w, t.get("max_test_windows"))
        tr, va = split_scene(sc, "train"), split_scene(sc, "val")
        train_w[name] = windows(tr, length, int(t.train_stride), int(t.min_peds))[0]
        val_w[name] = windows(va, length, int(t.train_stride), int(t.min_peds))[0]
        quads[name] = _quads([tr])
    log.info("data loaded in %.1fs", time.perf_counter() - t_start)

    rows = []
    curves: list[pd.DataFrame] = []
    sched = schedule_from_config(t.lstm, prefix="task.lstm")

    def add(model, scene, fold, metric, value):
        rows.append(dict(model=model, consensus="-", node="avg", scene=scene, metric=metric, value=float(value), episode=fold))

    for fold, test_scene in enumerate(t.scenes):
        train_names = fold_scenes(test_scene)[1]
        dt = scenes[test_scene].dt
        tw = test_w[test_scene]
        if tw.shape[0] == 0:
            raise ConfigError(f"task.scenes: scene {test_scene} has no test window with the given settings")
        truth_agents = _per_agent(tw)  # (M, 20, 2)
        obs_agents, fut_agents = truth_agents[:, :obs_len], truth_agents[:, obs_len:]
        trw = _subsample(_cat_windows([train_w[n] for n in train_names]), t.get("max_train_windows"))
        vaw = _cat_windows([val_w[n] for n in train_names])
        for pi, pred_name in enumerate(t.predictors):
            t0 = time.perf_counter()
            extra = {}
            if pred_name == "cv":
                pred = constant_velocity(obs_agents, pred_len)
            elif pred_name in ("lstm", "social_lstm"):
                social = pred_name == "social_lstm"
                c = t.lstm
                model = SocialLSTM(
                    1, obs_len=obs_len, pred_len=pred_len, embed=int(c.embed), hidden=int(c.hidden),
                    pooling="social" if social else "none", grid=int(c.grid), neighbourhood=float(c.neighbourhood),
                    dt=dt, dtype=lstm_dtype, device=device, seed=seed * 1000 + fold * 10 + pi,
                )
                tr_data = trw if social else _per_agent(trw).unsqueeze(2)
                va_data = vaw if social else _per_agent(vaw).unsqueeze(2)
                kw = dict(sched)
                if social and c.get("social_batch_size") is not None:
                    kw["batch_size"] = int(c.social_batch_size)
                hist = train_lstm(model, tr_data, **kw, val_windows=va_data, seed=seed + fold, progress=progress)
                curves.append(hist.assign(scene=test_scene, fold=fold, model=pred_name))
                extra["epochs_run"] = len(hist)
                extra["best_epoch"] = hist.attrs["best_epoch"]
                extra["best_val_loss"] = hist.attrs["best_val_loss"]
                extra["final_val_loss"] = hist.val_loss.iloc[-1]  # the last epoch run (not the restored one)
                extra["final_train_loss"] = hist.train_loss.iloc[-1]
                extra["batch_size"] = kw["batch_size"]
                log.info("%s %s: %d epochs, best validation loss %.5f at epoch %d", test_scene, pred_name, len(hist),
                         hist.attrs["best_val_loss"], hist.attrs["best_epoch"])
                if social:
                    pw = lstm_predict(model, tw[:, :obs_len])
                    pred = pw.permute(0, 2, 1, 3)[torch.isfinite(tw).all(-1).all(1)]
                else:
                    pred = lstm_predict(model, obs_agents.unsqueeze(2), batch=1024)[:, :, 0]
            else:  # GPs
                g = t.gp
                q = torch.cat([quads[n] for n in train_names], 0)
                gen = torch.Generator().manual_seed(seed * 1000 + fold)
                if pred_name == "gp":
                    x, y = gp_velocity_data(q, dt)
                    gp = OnlineGP(1, 4, 2, float(g.outputscale), float(g.lengthscale), float(g.noise_std), "identity",
                                  capacity=2, dtype=gp_dtype, device=device)
                    hp = _fit_gp(gp, x, y, g, gen)
                    pred = gp_velocity_rollout(gp, obs_agents.to(device, gp_dtype), pred_len, dt).to(obs_agents)
                else:
                    x, y = gp_state_data(q, dt)
                    m = GPMotionModel(4, 1, float(g.outputscale), float(g.lengthscale), float(g.noise_std), mean="identity",
                                      capacity=2, dtype=gp_dtype, device=device)
                    hp = _fit_gp(m.gp, x, y, g, gen)
                    pred = gp_state_rollout(m, obs_agents.to(device, gp_dtype), pred_len, dt).to(obs_agents)
                extra.update({f"gp_{k}": v for k, v in hp.items()})
                extra["gp_points"] = min(int(g.points), x.shape[0])
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


# report ---------------------------------------------------------------------------------------
def forecast_table(results: pd.DataFrame) -> pd.DataFrame:
    """Tidy table ``scene, model, ade, fde`` (mean over seeds) with an ``AVG`` row per model
    (the mean over the five scenes, as the benchmark papers report it)."""
    r = results[results.metric.isin(["ade", "fde"])]
    tab = r.groupby(["scene", "model", "metric"], sort=False)["value"].mean().unstack("metric").reset_index()
    order = [s for s in SCENE_LABELS if s in set(tab.scene)]
    tab["scene"] = pd.Categorical(tab.scene, order, ordered=True)
    tab = tab.sort_values(["scene", "model"]).reset_index(drop=True)
    if set(order) == set(SCENE_LABELS):
        avg = tab.groupby("model", sort=False)[["ade", "fde"]].mean().reset_index()
        avg["scene"] = "avg"
        tab["scene"] = tab.scene.astype(str)
        tab = pd.concat([tab, avg[["scene", "model", "ade", "fde"]]], ignore_index=True)
    tab["scene"] = tab.scene.astype(str)
    return tab[["scene", "model", "ade", "fde"]]


def _wide(tab: pd.DataFrame) -> pd.DataFrame:
    models = [m for m in PREDICTORS if m in set(tab.model)]
    out = tab.assign(cell=tab.ade.map("{:.2f}".format) + " / " + tab.fde.map("{:.2f}".format))
    w = out.pivot_table(index="scene", columns="model", values="cell", aggfunc="first", sort=False)[models]
    w.columns = [LABELS[m] for m in models]
    w.index = [SCENE_LABELS.get(s, s.upper()) for s in w.index]
    return w.reset_index(names="scene")


def published_table() -> pd.DataFrame:
    rows = []
    for scene in list(SCENE_LABELS) + ["avg"]:
        row = {"scene": SCENE_LABELS.get(scene, "AVG")}
        for model, d in PUBLISHED_SGAN.items():
            row[model] = f"{d[scene][0]:.2f} / {d[scene][1]:.2f}"
        rows.append(row)
    return pd.DataFrame(rows)


def load_curves(out_dir: Path) -> pd.DataFrame | None:
    """``learning_curves.csv`` of a run directory, or of every run below a sweep directory
    (column ``run`` = its folder relative to ``out_dir``); ``None`` if there is none."""
    out_dir = Path(out_dir)
    files = [out_dir / "learning_curves.csv"] if (out_dir / "learning_curves.csv").is_file() else sorted(out_dir.rglob("learning_curves.csv"))
    if not files:
        return None
    frames = [pd.read_csv(f).assign(run=str(f.parent.relative_to(out_dir)) if f.parent != out_dir else ".") for f in files]
    return pd.concat(frames, ignore_index=True)


def convergence_table(curves: pd.DataFrame, ref_epoch: int = OLD_EPOCHS) -> pd.DataFrame:
    """Per (run, scene, model): epochs run, best epoch, validation loss at ``ref_epoch`` (the old
    fixed schedule's last epoch), best validation loss, and how far above the best the former is."""
    rows = []
    for (run, fold, scene, model), g in curves.groupby(["run", "fold", "scene", "model"], sort=True):
        g = g.sort_values("epoch")
        i_best = int(g.val_loss.to_numpy().argmin())
        ref = g.loc[g.epoch == ref_epoch, "val_loss"]
        best = float(g.val_loss.iloc[i_best])
        v_ref = float(ref.iloc[0]) if len(ref) else float("nan")
        rows.append(dict(run=run, fold=int(fold), scene=scene, model=model, epochs_run=int(g.epoch.max()),
                         best_epoch=int(g.epoch.iloc[i_best]), val_ref=v_ref, val_best=best,
                         excess_pct=100.0 * (v_ref - best) / best, final_lr=float(g.lr.iloc[-1])))
    return pd.DataFrame(rows)


def report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path) -> str:
    """Five-scene ADE/FDE table (``ethucy_forecast.md`` / ``.csv``), the published
    Social GAN figures beside it, and a bar chart (``ethucy_forecast.png``); with the run's
    ``learning_curves.csv`` also the convergence table (``ethucy_forecast_convergence.csv``)
    and the learning curves (``learning_curves.png``)."""
    from dslearn.io import atomic_write_csv, atomic_write_text
    from dslearn.report import markdown

    out_dir = Path(out_dir)
    tab = forecast_table(results)
    atomic_write_csv(tab, out_dir / "ethucy_forecast.csv")
    wide = _wide(tab)
    secs = results[results.metric == "train_s"].groupby("model")["value"].sum()
    lines = [
        "## ETH/UCY leave-one-scene-out forecasting, 8 -> 12 steps (ADE / FDE, m)",
        "",
        markdown(wide),
        "",
        "Training + prediction seconds over all folds: "
        + ", ".join(f"{LABELS.get(m, m)} {secs[m]:.0f}" for m in PREDICTORS if m in secs.index),
        "",
        "### Published (Gupta et al., Social GAN, CVPR 2018, Table 1, t_pred = 12)",
        "",
        markdown(published_table()),
        "",
        "'Linear' there is a least-squares linear regressor over the 8 observed points, not the "
        "constant-velocity model above. See experiments/ethucy_forecast/README.md.",
    ]
    curves = load_curves(out_dir)
    if curves is not None and not curves.empty:
        conv = convergence_table(curves)
        atomic_write_csv(conv, out_dir / "ethucy_forecast_convergence.csv")
        def fmt(f):
            return lambda v: f.format(v) if np.isfinite(v) else "-"

        show = conv.assign(
            scene=conv.scene.map(lambda v: SCENE_LABELS.get(v, v)), model=conv.model.map(lambda v: LABELS.get(v, v)),
            val_ref=conv.val_ref.map(fmt("{:.4f}")), val_best=conv.val_best.map(fmt("{:.4f}")),
            excess_pct=conv.excess_pct.map(fmt("{:+.1f} %")), final_lr=conv.final_lr.map(fmt("{:.2g}")),
        ).rename(columns={"epochs_run": "epochs run", "best_epoch": "best epoch", "val_ref": f"val loss @ epoch {OLD_EPOCHS}",
                          "val_best": "best val loss", "excess_pct": f"epoch {OLD_EPOCHS} above best", "final_lr": "last lr"})
        if show.run.nunique() == 1:
            show = show.drop(columns="run")
        lines += ["", "### LSTM training (validation = the training files' benchmark val parts)", "",
                  markdown(show.drop(columns="fold")), "",
                  f"Epoch {OLD_EPOCHS} of this run = where the previous fixed schedule (6 epochs, batch 64) "
                  "stopped; the first epochs of an early-stopping run equal a fixed run with the same batch "
                  "size and seed while the learning rate is unchanged (not for a different batch size)."]
        try:
            _plot_curves(curves, out_dir / "learning_curves.png")
        except Exception as e:  # figures never break the tables
            log.warning("learning-curve figure failed: %s", e)
    text = "\n".join(lines)
    atomic_write_text(out_dir / "ethucy_forecast.md", text + "\n")
    try:
        _plot(tab, out_dir / "ethucy_forecast.png")
    except Exception as e:  # figures never break the tables
        log.warning("ethucy_forecast figure failed: %s", e)
    return text


def _plot_curves(curves: pd.DataFrame, path: Path) -> None:
    """Train (dashed) and validation (solid) loss per epoch, one panel per fold, both LSTMs;
    a dot marks the best validation epoch (the weights kept), a grey line the old epoch 6."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = curves[curves.run == curves.run.iloc[0]]
    folds = c.drop_duplicates("fold").sort_values("fold")
    fig, axes = plt.subplots(1, len(folds), figsize=(3.3 * len(folds), 3.2), squeeze=False, sharey=False)
    for ax, (_, f) in zip(axes[0], folds.iterrows()):
        for j, m in enumerate(LSTM_MODELS):
            g = c[(c.fold == f.fold) & (c.model == m)].sort_values("epoch")
            if g.empty:
                continue
            col = f"C{j}"
            ax.plot(g.epoch, g.val_loss, "-", color=col, label=f"{LABELS[m]} val")
            ax.plot(g.epoch, g.train_loss, "--", color=col, alpha=0.7, label=f"{LABELS[m]} train")
            b = g.loc[g.val_loss.idxmin()]
            ax.plot([b.epoch], [b.val_loss], "o", color=col)
        later = c[(c.fold == f.fold) & (c.epoch >= 2)][["train_loss", "val_loss"]].to_numpy()
        if later.size and np.isfinite(later).any():  # the first epoch's loss would squash the rest
            lo, hi = np.nanmin(later), np.nanmax(later)
            ax.set_ylim(0.95 * lo, 1.05 * hi)
        ax.axvline(OLD_EPOCHS, color="0.6", lw=0.8)
        ax.set_title(f"test {SCENE_LABELS.get(f.scene, f.scene)}")
        ax.set_xlabel("epoch")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("loss (MSE per coordinate, m$^2$)")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot(tab: pd.DataFrame, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    models = [m for m in PREDICTORS if m in set(tab.model)]
    scenes = list(dict.fromkeys(tab.scene))
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.6))
    width = 0.8 / max(1, len(models))
    for ax, metric in zip(axes, ("ade", "fde")):
        for i, m in enumerate(models):
            sub = tab[tab.model == m].set_index("scene").reindex(scenes)
            ax.bar(np.arange(len(scenes)) + i * width, sub[metric].to_numpy(), width, label=LABELS[m])
        ax.set_xticks(np.arange(len(scenes)) + 0.4 - width / 2)
        ax.set_xticklabels([SCENE_LABELS.get(s, s.upper()) for s in scenes])
        ax.set_ylabel(f"{metric.upper()} [m]")
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("ETH/UCY leave-one-scene-out, 8 -> 12 steps")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
