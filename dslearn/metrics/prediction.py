r"""Motion models on held-out episodes against the truth (Yu et al. Tables II and IV, Fig. 4): the
tracking errors of a filter run together with the model's roll-out prediction error, the rows of
stored trajectories (the truth, or a model's roll-out from it) and of scalar values (a fit's
parameters, a data source's statistics).

The studies run the filters and the models; the functions here compare their output with the truth
and write the tidy rows (the layout of :func:`dslearn.metrics.rows.metric_rows`: the constant key
columns first)."""

from __future__ import annotations

import numpy as np
import pandas as pd
from torch import Tensor

from dslearn.filters.distributed import TrackResult
from dslearn.metrics.tracking import prediction_error, tracking_metrics
from dslearn.models.base import MotionModel
from dslearn.types import POS, StepContext, agents


def tracking_and_prediction_errors(result: TrackResult, model: MotionModel, truth: Tensor, num_nodes: int,
                                   ctx: StepContext, per_node: bool) -> dict[str, Tensor]:
    """The tracking metrics of ``result`` (:func:`~dslearn.metrics.tracking.tracking_metrics`) on the
    episodes whose true states are ``truth (B, K+1, Dx)``, plus ``pred_err``: the roll-out of ``model``
    from each episode's true state at t = 0 against the truth (:func:`~dslearn.metrics.tracking.prediction_error`;
    ``per_node``: one model per node). Every value ``(S, B)``."""
    metrics = tracking_metrics(result, truth)
    metrics["pred_err"] = prediction_error(model, truth, num_nodes, ctx, per_node=per_node)
    return metrics


def position_rows(traj: Tensor | None, node: str, n: int, **keys) -> pd.DataFrame:
    """Rows ``pred_x`` / ``pred_y`` (node ``node``, ``node_kind`` trajectory, with ``episode``, ``step``
    (0..K) and ``agent`` columns) of the positions in the first ``n`` joint-state trajectories
    ``traj (B, K+1, Dx)``; the ``keys`` columns first. Empty for ``n <= 0`` (``traj`` may then be None)."""
    if n <= 0:
        return pd.DataFrame()
    pos = agents(traj[:n])[..., POS].detach().cpu().double().numpy()  # (n, K+1, A, 2)
    b, k1, a, _ = pos.shape
    ep, step, ag = np.meshgrid(np.arange(b), np.arange(k1), np.arange(a), indexing="ij")
    frames = []
    for c, name in ((0, "pred_x"), (1, "pred_y")):
        frames.append(
            pd.DataFrame(
                {"node": node, "node_kind": "trajectory", "episode": ep.ravel(), "step": step.ravel(),
                 "agent": ag.ravel(), "metric": name, "value": pos[..., c].ravel()}
            )
        )
    df = pd.concat(frames, ignore_index=True)
    for i, (kk, v) in enumerate(keys.items()):
        df.insert(i, kk, v)
    return df


def scalar_row(metric: str, value: float, **keys) -> pd.DataFrame:
    """One row of a scalar (node ``avg``, ``node_kind`` param, episode 0), the ``keys`` columns last."""
    return pd.DataFrame({"node": ["avg"], "node_kind": ["param"], "episode": [0], "metric": [metric], "value": [value],
                         **{k: [v] for k, v in keys.items()}})
