r"""Position errors of any method's estimates (:class:`~dslearn.episodes.Estimates`) against the true
positions: what the matrix compares across methods and scenarios."""

from __future__ import annotations

import torch
from torch import Tensor

from dslearn.episodes import Estimates


def position_metrics(est: Estimates, truth: Tensor) -> dict[str, Tensor]:
    r"""Per reporting node and episode, over the steps :math:`t = 1..K` and the targets:

    * ``rmse``: :math:`\sqrt{\operatorname{mean}_{t,a} \lVert \hat p_{a,t} - p_{a,t} \rVert^2}`;
    * ``pos_err``: the mean position error (Yu et al.'s tracking error);
    * ``nees_pos`` (where the method gives covariances): the mean over ``t`` of
      :math:`\sum_a e_{a,t}^T P_{aa,t}^{-1} e_{a,t} / (2A)`, the position NEES with the targets' blocks
      (1 for a consistent estimator; cross-target covariances are not compared).

    Args:
        est: ``mean (N, B, K+1, A, 2)``, ``cov (N, B, K+1, A, 2, 2)`` or None; truth: ``(B, K+1, A, 2)``.
    Returns:
        ``{name: (N, B)}``.
    """
    err = est.mean[:, :, 1:] - truth[:, 1:].unsqueeze(0).to(est.mean)  # (N, B, K, A, 2)
    sq = err.pow(2).sum(-1)  # (N, B, K, A)
    out = {"rmse": sq.mean((-1, -2)).sqrt(), "pos_err": sq.sqrt().mean((-1, -2))}
    if est.cov is not None:
        e = err.unsqueeze(-1)
        d2 = (e.transpose(-1, -2) @ torch.linalg.solve(est.cov[:, :, 1:], e)).squeeze(-1).squeeze(-1)  # (N, B, K, A)
        out["nees_pos"] = d2.sum(-1).mean(-1) / (2 * truth.shape[-2])
    return out
