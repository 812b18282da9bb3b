r"""Metrics of the factor-graph identification and EKF-FG tracking (Jiang et al., ISITA 2022): the
estimates' squared errors against the true parameters, the Cramer-Rao bound at the true state
(Eq. 27) that they are compared with, root-mean-square reductions, and the tidy rows of the study
(one per episode, or per episode x timing).

Shapes: ``C`` configurations, ``B`` Monte Carlo runs (episodes), ``K`` timings, ``M`` parameters.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from dslearn.learning.factor_graph.crlb import crlb
from dslearn.metrics.rows import rows


def squared_error(estimate: Tensor, truth: Tensor) -> Tensor:
    """Squared error per parameter (mean over the ``M`` parameters) of ``estimate (..., B, K, M)``
    against ``truth (B, K, M)``: ``(..., B, K)``."""
    return (estimate - truth).square().mean(-1)


def crlb_at_truth(h: Callable[[Tensor], Tensor], truth: Tensor, sigma_y: Tensor, num_samples: int) -> Tensor:
    """The per-parameter CRLB (a variance, Eq. 27: ``tr F^{-1} / M``) at the true state of every timing,
    for each configuration's sensor noise ``sigma_y (C,)`` and ``num_samples`` samples per sensor:
    ``(C, B, K)``."""
    B, K, M = truth.shape
    C = sigma_y.shape[0]
    sig_cb = sigma_y.to(truth.dtype)[:, None].expand(C, B)
    return torch.stack([crlb(h, truth[:, k].expand(C, B, M), sig_cb, num_samples, "trace_inverse")
                        for k in range(K)], -1)


def rmse(sq: Tensor, over_timings: bool = True) -> np.ndarray:
    """Root-mean-square of squared errors (or variances) ``(..., K)``: over the timings (``(...)``, one per
    episode) or per timing (``over_timings=False``: the root of each)."""
    return (sq.mean(-1) if over_timings else sq).sqrt().cpu().numpy()


def identification_rows(values, metric: str, **keys) -> pd.DataFrame:
    """Tidy rows of one metric's ``values``: ``(B,)`` one per episode, or ``(B, K)`` one per episode x
    timing (``timing`` = 1..K, the paper's ``k``); columns ``episode``, [``timing``], ``metric``,
    ``value`` and the constant ``keys``."""
    values = np.asarray(values, dtype=float)
    if values.ndim == 1:
        return rows(values, ("episode",), metric, **keys)
    df = rows(values, ("episode", "timing"), metric, **keys)
    df["timing"] += 1
    return df
