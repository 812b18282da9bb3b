r"""Tracking metrics of the distributed filters: errors of every node's beliefs against the truth."""

from __future__ import annotations

import torch
from torch import Tensor

from dslearn.filters.distributed import TrackResult
from dslearn.models.base import MotionModel
from dslearn.types import StepContext, agents


def tracking_metrics(res: TrackResult, truth: Tensor) -> dict[str, Tensor]:
    r"""Per node and episode: ``track_err`` (the paper's V-C formula, mean position error over
    t = 1..K and targets), ``track_rmse``, and ``nees`` (average NEES over t = 1..K divided by Dx;
    1 for a consistent filter).

    Args:
        res: beliefs ``(S, B, K+1, ...)``; truth: ``(B, K+1, Dx)``.
    Returns:
        dict of ``(S, B)`` tensors.
    """
    err = res.mean[:, :, 1:] - truth[:, 1:].unsqueeze(0)  # (S, B, K, Dx)
    perr = agents(err)[..., :2].norm(dim=-1)  # (S, B, K, A)
    nees = (err.unsqueeze(-2) @ res.info[:, :, 1:] @ err.unsqueeze(-1)).squeeze(-1).squeeze(-1)
    dx = truth.shape[-1]
    return {
        "track_err": perr.mean((-1, -2)),
        "track_rmse": perr.pow(2).mean((-1, -2)).sqrt(),
        "nees": nees.mean(-1) / dx,
    }


def prediction_error(model: MotionModel, truth: Tensor, num_nodes: int, ctx: StepContext, per_node: bool) -> Tensor:
    """Roll the model out from the true state at t = 0 (Table II): mean position error, ``(S, B)``."""
    x0 = truth[:, 0]
    steps = truth.shape[1] - 1
    if per_node:
        roll = model.rollout(x0.unsqueeze(0).expand(num_nodes, *x0.shape).contiguous(), steps, ctx)
    else:
        roll = model.rollout(x0, steps, ctx).unsqueeze(0).expand(num_nodes, -1, -1, -1)
    err = agents(roll - truth[:, 1:].unsqueeze(0))[..., :2].norm(dim=-1)
    return err.mean((-1, -2))
