r"""Forecasting metrics: predicted positions against the true future (``(..., T, 2)`` metres), and the
tidy rows of the ETH/UCY forecasting study (one per held-out scene x predictor x metric)."""

from __future__ import annotations

import torch
from torch import Tensor


def ade_fde(pred: Tensor, truth: Tensor) -> tuple[Tensor, Tensor]:
    """Average and final displacement errors ``(..., T, 2), (..., T, 2) -> (...), (...)``.

    ADE :math:`= \\frac1T \\sum_t \\|\\hat p_t - p_t\\|_2`, FDE :math:`= \\|\\hat p_T - p_T\\|_2` (metres).
    """
    err = (pred - truth).norm(dim=-1)
    return err.mean(-1), err[..., -1]


def forecast_scores(pred: Tensor, truth: Tensor) -> dict[str, float]:
    """The benchmark's numbers of one predictor on one scene's pedestrian-windows ``(M, T, 2)``: ``ade`` and
    ``fde`` (means over the M windows, in float64) and ``count`` (M). ``FloatingPointError`` for a
    non-finite prediction."""
    ade, fde = ade_fde(pred.to(torch.float64), truth)
    if not (torch.isfinite(ade).all() and torch.isfinite(fde).all()):
        raise FloatingPointError("non-finite predictions")
    return {"ade": float(ade.mean()), "fde": float(fde.mean()), "count": ade.numel()}


def forecast_row(model: str, scene: str, fold: int, metric: str, value) -> dict:
    """One tidy row of the forecasting study: ``model consensus node scene metric value episode``
    (``consensus`` = ``-``, ``node`` = ``avg``: no network; ``episode`` = the fold)."""
    return dict(model=model, consensus="-", node="avg", scene=scene, metric=metric, value=float(value), episode=fold)
