r"""Rauch–Tung–Striebel smoothing of a filtered run, and the EM statistics of its process noise.

Used to learn a motion model's process noise while tracking (``model.noise=adaptive``): after
each training episode every node smooths its own filtered estimates and forms the expected
one-step transition error given the whole episode, the M-step of EM for :math:`Q`
(Shumway & Stoffer 1982; Särkkä, *Bayesian Filtering and Smoothing*, ch. 12), linearised as in
the EKF. Shapes: nodes first, time second, ``(S, K+1, Dx)`` and ``(S, K+1, Dx, Dx)``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from dslearn.types import safe_cholesky, symmetrize


def rts_smoother(m: Tensor, P: Tensor, y_pred: Tensor, P_pred: Tensor, F: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    r"""Extended RTS smoother.

    Args:
        m, P: filtered means ``(S, K+1, Dx)`` and covariances ``(S, K+1, Dx, Dx)``, t = 0..K.
        y_pred, P_pred, F: prediction to step t (mean, covariance, Jacobian of the step from
            t-1), ``(S, K, ...)`` for t = 1..K.

    Returns:
        smoothed ``m_s (S, K+1, Dx)``, ``P_s (S, K+1, Dx, Dx)`` and the gains
        ``G (S, K, Dx, Dx)``, :math:`G_t = P_t F_{t+1}^T (P^{t+1|t})^{-1}` for t = 0..K-1.
    """
    k = y_pred.shape[1]
    ms, Ps, Gs = [m[:, k]], [P[:, k]], []
    for t in range(k - 1, -1, -1):
        chol = safe_cholesky(P_pred[:, t])
        # G = P_t F^T P_pred^{-1}  <=>  G^T = P_pred^{-1} F P_t
        G = torch.cholesky_solve(F[:, t] @ P[:, t], chol).transpose(-1, -2)
        ms.append(m[:, t] + (G @ (ms[-1] - y_pred[:, t]).unsqueeze(-1)).squeeze(-1))
        Ps.append(symmetrize(P[:, t] + G @ (Ps[-1] - P_pred[:, t]) @ G.transpose(-1, -2)))
        Gs.append(G)
    return torch.stack(ms[::-1], 1), torch.stack(Ps[::-1], 1), torch.stack(Gs[::-1], 1)


def transition_error_moments(
    m: Tensor, P: Tensor, y_pred: Tensor, P_pred: Tensor, F: Tensor
) -> Tensor:
    r"""Expected outer product of the one-step transition error given the whole run,
    :math:`M_t = E[(y^t - f(y^{t-1}))(y^t - f(y^{t-1}))^T \mid z^{0:K}]`, t = 1..K.

    Linearised at the filtered estimate, :math:`f(y) \approx \hat y^{t|t-1} + F_t (y - \hat y^{t-1})`:
    with smoothed moments :math:`m^s, P^s` and the lag-one covariance
    :math:`C_t = P^s_t G_{t-1}^T`,

    .. math::
        M_t = e_t e_t^T + P^s_t - F_t C_t^T - C_t F_t^T + F_t P^s_{t-1} F_t^T,\quad
        e_t = m^s_t - \hat y^{t|t-1} - F_t (m^s_{t-1} - \hat y^{t-1}).

    Their average over t is the EM (M-step) estimate of a constant :math:`Q`.

    Returns:
        ``(S, K, Dx, Dx)``.
    """
    ms, Ps, G = rts_smoother(m, P, y_pred, P_pred, F)
    e = ms[:, 1:] - y_pred - (F @ (ms[:, :-1] - m[:, :-1]).unsqueeze(-1)).squeeze(-1)
    C = Ps[:, 1:] @ G.transpose(-1, -2)  # Cov(y^t, y^{t-1} | all)
    FC = F @ C.transpose(-1, -2)
    M = e.unsqueeze(-1) * e.unsqueeze(-2) + Ps[:, 1:] - FC - FC.transpose(-1, -2) + F @ Ps[:, :-1] @ F.transpose(-1, -2)
    return symmetrize(M)
