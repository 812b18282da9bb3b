"""Training the LSTM / Social-LSTM baselines (:class:`dslearn.models.lstm.SocialLSTM`) for the
real-data studies: on leave-one-scene-out scene windows (forecasting), and on the positions a
sensor network estimated (tracking, the paper's VI-C recipe)."""

from __future__ import annotations

import torch
from torch import Tensor

from dslearn.data.window_tensors import per_agent
from dslearn.models.lstm import (SocialLSTM, episode_windows, holdout_split, lstm_predict, schedule_from_config,
                                 train_lstm)

#: the network keys of a ``task.lstm`` / ``lstm`` block (the rest is the schedule)
NETWORK_KEYS = ("embed", "hidden", "obs_len", "pred_len", "pooling", "grid", "neighbourhood")


def lstm_windows(fused: Tensor, obs_len: int, pred_len: int) -> tuple[Tensor, Tensor]:
    """Sliding windows of fused positions: ``(B, K+1, 4A) -> (N, obs_len + pred_len, A, 2)``, and
    the episode each window was cut from, ``(N,)`` (a validation split holds out whole episodes);
    :func:`dslearn.models.lstm.episode_windows`, the windows of :meth:`SocialLSTM.fit_offline`."""
    return episode_windows(fused, obs_len, pred_len)


def train_lstm_model(c, num_agents: int, dt: float, windows: tuple[Tensor, Tensor], seed: int, dtype, device,
                     progress: bool = False, prefix: str = "task.lstm"):
    """A fresh Social-LSTM trained on ``windows`` (from :func:`lstm_windows`) with the schedule of
    ``c`` (``task.lstm``: the paper's fixed one, or early stopping on held-out episodes); returns
    ``(model, loss curve)``; with early stopping the curve's ``attrs["restored_epoch"]`` is the
    epoch whose weights were kept."""
    kw = {k: c[k] for k in NETWORK_KEYS if k in c}
    win, groups = windows
    sched = schedule_from_config(c, prefix=prefix)
    val = None
    if "patience" in sched:
        win, val = holdout_split(win, groups, float(c.get("val_fraction", 0.2)), seed)
        val = val.to(device, dtype)
    torch.manual_seed(seed)
    model = SocialLSTM(num_agents, dt=dt, dtype=dtype, device=device, **kw)
    curve = train_lstm(model, win.to(device, dtype), **sched, val_windows=val, seed=int(seed), progress=bool(progress))
    return model, curve


def train_forecast_lstm(social: bool, train_w: Tensor, val_w: Tensor, c, obs_len: int, pred_len: int, dt: float,
                        dtype, device, seed: int, train_seed: int, progress: bool = False):
    """One fold's LSTM (``social=False``: each pedestrian alone) or Social-LSTM (``social=True``:
    every pedestrian of a scene window pools the others) on NaN-padded scene windows
    ``(N, T, A, 2)``, validated on ``val_w`` with the schedule of ``c`` (``task.lstm``; the
    Social-LSTM's batch is ``c.social_batch_size`` scene windows when given).

    Returns ``(predict(test windows (N, T, A, 2)) -> (M, pred_len, 2) for the present
    pedestrian-windows, in :func:`dslearn.data.window_tensors.per_agent` order, history, extra)`` where
    ``extra`` holds ``epochs_run best_epoch best_val_loss final_val_loss final_train_loss batch_size``.
    """
    model = SocialLSTM(
        1, obs_len=obs_len, pred_len=pred_len, embed=int(c.embed), hidden=int(c.hidden),
        pooling="social" if social else "none", grid=int(c.grid), neighbourhood=float(c.neighbourhood),
        dt=dt, dtype=dtype, device=device, seed=seed,
    )
    tr = train_w if social else per_agent(train_w).unsqueeze(2)
    va = val_w if social else per_agent(val_w).unsqueeze(2)
    kw = schedule_from_config(c, prefix="task.lstm")
    if social and getattr(c, "social_batch_size", None) is not None:
        kw["batch_size"] = int(c.social_batch_size)
    hist = train_lstm(model, tr, **kw, val_windows=va, seed=train_seed, progress=progress)
    extra = {"epochs_run": len(hist), "best_epoch": hist.attrs["best_epoch"], "best_val_loss": hist.attrs["best_val_loss"],
             "final_val_loss": hist.val_loss.iloc[-1],  # the last epoch run (not the restored one)
             "final_train_loss": hist.train_loss.iloc[-1], "batch_size": kw["batch_size"]}

    def predict(test_w: Tensor) -> Tensor:
        if social:
            pw = lstm_predict(model, test_w[:, :obs_len])
            return pw.permute(0, 2, 1, 3)[torch.isfinite(test_w).all(-1).all(1)]
        return lstm_predict(model, per_agent(test_w)[:, :obs_len].unsqueeze(2), batch=1024)[:, :, 0]

    return predict, hist, extra
