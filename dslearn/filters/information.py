r"""Extended information filter steps (Yu et al. Algorithm 2).

Beliefs are information pairs :math:`(q, \Omega)` with :math:`\Omega = P^{-1}`, :math:`q = \Omega \hat y`.
Shapes: nodes first, ``(S, B, Dx)`` and ``(S, B, Dx, Dx)``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..models.base import MotionModel, ObservationModel
from ..types import AGENT_DIM, StepContext, safe_cholesky, spd_inverse, symmetrize


def to_moment(q: Tensor, omega: Tensor) -> tuple[Tensor, Tensor]:
    """Information pair -> (mean, covariance)."""
    chol = safe_cholesky(omega)
    mean = torch.cholesky_solve(q.unsqueeze(-1), chol).squeeze(-1)
    return mean, symmetrize(torch.cholesky_inverse(chol))


def to_information(mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
    """(mean, covariance) -> information pair."""
    omega = spd_inverse(cov)
    return (omega @ mean.unsqueeze(-1)).squeeze(-1), omega


def predict(
    mean: Tensor, omega: Tensor, model: MotionModel, ctx: StepContext
) -> tuple[Tensor, Tensor, Tensor]:
    r"""Prediction (Algorithm 2 lines 2–6).

    :math:`\hat y^{t|t-1} = f(\hat y^{t-1})`, :math:`A = \partial f/\partial y`,
    :math:`\Omega^{t|t-1} = (A \Omega^{-1} A^T + Q)^{-1}`, :math:`q^{t|t-1} = \Omega^{t|t-1} \hat y^{t|t-1}`.

    Returns:
        ``(y_pred (S,B,Dx), q_pred (S,B,Dx), omega_pred (S,B,Dx,Dx))``.
    """
    y_pred, F, Q = model.linearize(mean, ctx)
    P = spd_inverse(omega)
    P_pred = symmetrize(F @ P @ F.transpose(-1, -2) + Q)
    omega_pred = spd_inverse(P_pred)
    q_pred = (omega_pred @ y_pred.unsqueeze(-1)).squeeze(-1)
    return y_pred, q_pred, omega_pred


def novel_information(
    y_pred: Tensor, meas: Tensor, visible: Tensor, obs: ObservationModel
) -> tuple[Tensor, Tensor]:
    r"""Novel information of each node's measurements (Algorithm 2 lines 7–11).

    For each target ``j`` a node sees: :math:`\bar z = z - h(\hat y_j) + C \hat y_j`,
    :math:`\delta q = \sum_j C_j^T R_j^{-1} \bar z_j`, :math:`\delta\Omega = \sum_j C_j^T R_j^{-1} C_j`,
    with :math:`C_j` the Jacobian placed in target ``j``'s block. A node that sees nothing
    contributes zero.

    Args:
        y_pred: ``(S, B, Dx)``; meas: ``(S, B, A, 2)``; visible: ``(S, B, A)`` bool.
    Returns:
        ``(dq (S, B, Dx), domega (S, B, Dx, Dx))``.
    """
    yj = y_pred.unflatten(-1, (-1, AGENT_DIM))  # (S, B, A, 4)
    h, C, R = obs.linearize(yj)
    Rinv_C = torch.linalg.solve(R, C)  # (S, B, A, 2, 4)
    zbar = meas - h + (C @ yj.unsqueeze(-1)).squeeze(-1)
    m = visible.to(y_pred.dtype)
    dq_blocks = (C.transpose(-1, -2) @ torch.linalg.solve(R, zbar.unsqueeze(-1))).squeeze(-1) * m.unsqueeze(-1)
    dO_blocks = (C.transpose(-1, -2) @ Rinv_C) * m.unsqueeze(-1).unsqueeze(-1)  # (S, B, A, 4, 4)
    dq = dq_blocks.flatten(-2)
    domega = _block_diag(dO_blocks)
    return dq, symmetrize(domega)


def _block_diag(blocks: Tensor) -> Tensor:
    """``(*B, A, d, d) -> (*B, A d, A d)`` block-diagonal."""
    a, d = blocks.shape[-3], blocks.shape[-1]
    out = blocks.new_zeros(*blocks.shape[:-3], a * d, a * d)
    for j in range(a):
        out[..., j * d : (j + 1) * d, j * d : (j + 1) * d] = blocks[..., j, :, :]
    return out
