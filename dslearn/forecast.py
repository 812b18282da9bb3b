r"""Trajectory forecasting: the constant-velocity baseline and the GP roll-outs of observed positions
(``(M, T_obs, 2)`` pedestrian-windows, metres; the LSTM's batched prediction is
:func:`dslearn.models.lstm.lstm_predict`; the displacement errors against the truth are
:mod:`dslearn.metrics.forecast`).

Used by the ETH/UCY forecasting study (:mod:`dslearn.studies.ethucy_forecast`); everything here
works on position tensors only (no data set, no config file).
"""

from __future__ import annotations

import torch
from torch import Tensor

from dslearn.models.gp import GPMotionModel
from dslearn.models.gp_backends import OnlineGP
from dslearn.models.kernels import se, sq_dist_inner


def constant_velocity(obs: Tensor, pred_len: int) -> Tensor:
    """``(..., T_obs, 2) -> (..., pred_len, 2)``: ``p_last + k (p_last - p_prev)``, k = 1..pred_len."""
    v = obs[..., -1, :] - obs[..., -2, :]
    k = torch.arange(1, pred_len + 1, dtype=obs.dtype, device=obs.device)
    return obs[..., -1:, :] + k[:, None] * v[..., None, :]


def load_gp_data(gp: OnlineGP, x: Tensor, y: Tensor) -> None:
    """Replace the GP's data with ``x (n, Dx) -> y (n, Dy)`` in one factorisation (node 0)."""
    gp.set_data(x.unsqueeze(0), y.unsqueeze(0))


def fit_gp(gp: OnlineGP, x: Tensor, y: Tensor, c, gen: torch.Generator) -> dict:
    """Fit the kernel hyperparameters by marginal likelihood on ``c.fit_points`` random examples
    (``c.fit_iters`` Adam steps at ``c.fit_lr``), then keep ``c.points`` random examples (the same
    permutation) as the GP's data. Returns the fitted hyperparameters."""
    perm = torch.randperm(x.shape[0], generator=gen)
    fit_idx = perm[: int(c.fit_points)]
    if int(c.fit_iters) > 0 and fit_idx.numel() >= 2:
        load_gp_data(gp, x[fit_idx], y[fit_idx])
        gp.fit(int(c.fit_iters), float(c.fit_lr))
    use = perm[: int(c.points)]
    load_gp_data(gp, x[use], y[use])
    return {"lengthscale": float(gp.lengthscale[0]), "outputscale": float(gp.outputscale[0]), "noise_var": float(gp.noise_var[0])}


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
    of a forecasting fold. All stored points must be valid (as :func:`load_gp_data` makes them).
    """
    ls, os_ = gp.lengthscale[0].to(x), gp.outputscale[0].to(x)
    d2 = sq_dist_inner(x, gp.data()[0][0].to(x), ls)
    return gp.prior_mean(x.unsqueeze(0))[0] + se(d2, os_) @ gp.alpha[0].to(x)


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


def gp_forecaster(kind: str, quads: Tensor, dt: float, c, gen: torch.Generator, dtype, device):
    """Build and fit a GP predictor on ground-truth position quadruples ``(K, 4, 2)``.

    ``kind`` = ``gp``: :class:`OnlineGP` on velocities ``[v_t, v_{t-1}] -> v_{t+1}`` (identity
    mean), rolled out by :func:`gp_velocity_rollout`; ``gp_state``: :class:`GPMotionModel` on the
    state ``[p, v]`` (identity mean), rolled out by :func:`gp_state_rollout`. ``c`` holds the
    initial hyperparameters and the budget (``outputscale lengthscale noise_std points fit_points
    fit_iters fit_lr``). Returns ``(predict(obs (M, T, 2), pred_len) -> (M, pred_len, 2), extra)``
    with the fitted hyperparameters and the number of points in ``extra``.
    """
    args = (float(c.outputscale), float(c.lengthscale), float(c.noise_std))
    if kind == "gp":
        x, y = gp_velocity_data(quads, dt)
        gp = OnlineGP(1, 4, 2, *args, "identity", capacity=2, dtype=dtype, device=device)
        hp = fit_gp(gp, x, y, c, gen)

        def predict(obs: Tensor, pred_len: int) -> Tensor:
            return gp_velocity_rollout(gp, obs.to(device, dtype), pred_len, dt).to(obs)
    elif kind == "gp_state":
        x, y = gp_state_data(quads, dt)
        m = GPMotionModel(4, 1, *args, mean="identity", capacity=2, dtype=dtype, device=device)
        hp = fit_gp(m.gp, x, y, c, gen)

        def predict(obs: Tensor, pred_len: int) -> Tensor:
            return gp_state_rollout(m, obs.to(device, dtype), pred_len, dt).to(obs)
    else:
        raise ValueError(f"unknown GP forecaster {kind!r}; choose gp or gp_state")
    extra = {f"gp_{k}": v for k, v in hp.items()}
    extra["gp_points"] = min(int(c.points), x.shape[0])
    return predict, extra
