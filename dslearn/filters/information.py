r"""Extended information filter steps (Yu et al. Algorithm 2).

Beliefs are information pairs :math:`(q, \Omega)` with :math:`\Omega = P^{-1}`, :math:`q = \Omega \hat y`.
Shapes: nodes first, ``(S, B, Dx)`` and ``(S, B, Dx, Dx)``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Protocol

import torch
from torch import Tensor

from dslearn.diagnostics import record_gate
from dslearn.models.base import MotionModel, ObservationModel
from dslearn.types import StepContext, safe_cholesky, spd_inverse, symmetrize


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
    mean: Tensor, omega: Tensor, model: MotionModel, ctx: StepContext, full: bool = False
) -> tuple[Tensor, ...]:
    r"""Prediction (Algorithm 2 lines 2–6).

    :math:`\hat y^{t|t-1} = f(\hat y^{t-1})`, :math:`A = \partial f/\partial y`,
    :math:`\Omega^{t|t-1} = (A \Omega^{-1} A^T + Q)^{-1}`, :math:`q^{t|t-1} = \Omega^{t|t-1} \hat y^{t|t-1}`.

    Returns:
        ``(y_pred (S,B,Dx), q_pred (S,B,Dx), omega_pred (S,B,Dx,Dx))``, and with ``full`` also
        ``P_pred``, the Jacobian ``F`` and the process noise ``Q`` used (all ``(S,B,Dx,Dx)``).
    """
    P = spd_inverse(omega)
    y_pred, F, Q = model.linearize(mean, dataclasses.replace(ctx, cov=P))
    P_pred = symmetrize(F @ P @ F.transpose(-1, -2) + Q)
    omega_pred = spd_inverse(P_pred)
    q_pred = (omega_pred @ y_pred.unsqueeze(-1)).squeeze(-1)
    if full:
        return y_pred, q_pred, omega_pred, P_pred, F, Q
    return y_pred, q_pred, omega_pred


class PredictionStep(Protocol):
    """The filter's prediction step (``filter.predict``), as the filters and the learners take it: called like
    :func:`predict`, ``(mean, omega, model, ctx, full=False) -> (y_pred, q_pred, omega_pred[, P_pred, F, Q])``.
    The steps: :class:`ExtendedPredict` (``ekf``), :class:`~dslearn.filters.ukf.UnscentedPredict` (``ukf``,
    ``ukf_mm``), :class:`~dslearn.filters.particle.ParticlePredict` (``pf``),
    :class:`~dslearn.filters.adf.MomentMatchingPredict` (``adf``).

    A step may further declare ``model_misfit(model, model_name)`` (why it does not fit a motion model; with
    ``check_model`` and ``check_state_dim``, the start-up checks) and ``observation_linearization(obs, y_pred,
    omega_pred, num_agents)`` (its own update for a nonlinear sensor: the UKF's)."""

    #: its label (``filter=...`` in messages and rows)
    name: str
    #: its process noise is the motion model's ``Q`` at the mean (a scale of it scales the step's; the EKF's and
    #: the UKF's, not a moment-matching or sampling step's)
    noise_at_mean: bool
    #: autograd follows an exact GP motion model's differentiable posterior through it (``learner=backprop``; not
    #: a step that reads the GP's own factor: the GP-ADF, the GP-UKF-MM)
    differentiates_gp: bool

    def __call__(self, mean: Tensor, omega: Tensor, model: MotionModel, ctx: StepContext,
                 full: bool = False) -> tuple[Tensor, ...]: ...


def prediction_step(step: PredictionStep | None) -> PredictionStep:
    """``step``, or the EKF's (:class:`ExtendedPredict`) where none is given."""
    return ExtendedPredict() if step is None else step


@dataclasses.dataclass(frozen=True)
class ExtendedPredict:
    """The EKF prediction step as a config part (``conf/filter/default.yaml``: ``predict``):
    :func:`predict`, the model linearised at the mean (a :class:`PredictionStep`)."""

    name = "ekf"
    noise_at_mean = True
    differentiates_gp = True

    def __call__(self, mean: Tensor, omega: Tensor, model: MotionModel, ctx: StepContext, full: bool = False):
        return predict(mean, omega, model, ctx, full=full)




def chi2_quantile(prob: float, dof: int) -> float:
    """Quantile of the chi-square distribution (closed form for 2 degrees of freedom)."""
    if not 0.0 < prob < 1.0:
        raise ValueError(f"gate probability {prob!r} must be in (0, 1)")
    if dof == 2:
        return -2.0 * math.log1p(-prob)
    from scipy.stats import chi2  # only for measurement dimensions other than 2

    return float(chi2.ppf(prob, dof))


def novel_information(
    y_pred: Tensor,
    meas: Tensor,
    visible: Tensor,
    obs: ObservationModel,
    gate_prob: float | None = None,
    omega_pred: Tensor | None = None,
    linearized: tuple[Tensor, Tensor, Tensor] | None = None,
) -> tuple[Tensor, Tensor]:
    r"""Novel information of each node's measurements (Algorithm 2 lines 7–11).

    For each target ``j`` a node sees: :math:`\bar z = z - h(\hat y_j) + C \hat y_j` (the extended information
    filter's update with the observation model's Jacobian ``C``: linear or not, e.g. a squared range),
    :math:`\delta q = \sum_j C_j^T R_j^{-1} \bar z_j`, :math:`\delta\Omega = \sum_j C_j^T R_j^{-1} C_j`,
    with :math:`C_j` the Jacobian placed in target ``j``'s block. A node that sees nothing
    contributes zero.

    Robust update (optional): with ``gate_prob`` (e.g. 0.99) a measurement is used only if its
    innovation :math:`\nu = z - h(\hat y_j)` passes the chi-square gate
    :math:`\nu^T S^{-1} \nu \le \chi^2_{D_z}(p)`, :math:`S = C_j P_{jj} C_j^T + R_j` with
    :math:`P = (\Omega^{t|t-1})^{-1}` from ``omega_pred`` (``R`` alone if ``omega_pred`` is None).
    Tested and rejected measurements are recorded in the open :class:`~dslearn.diagnostics.Diagnostics`.

    Args:
        y_pred: ``(S, B, Dx)``; meas: ``(S, B, A, C)`` the raw channels (``obs.reading`` makes them the
            ``Dz`` the model explains: the position, or ``L`` squared-range samples averaged); visible: ``(S, B, A)``.
        gate_prob: chi-square gate probability, ``None`` = no gating (the paper).
        omega_pred: ``(S, B, Dx, Dx)`` prior information (for the innovation covariance).
        linearized: ``(h, C, R)`` per target in place of ``obs.linearize`` at the prediction (the UKF's statistical
            linearisation, :func:`~dslearn.filters.ukf.unscented_observation`).
    Returns:
        ``(dq (S, B, Dx), domega (S, B, Dx, Dx))``.
    """
    yj = y_pred.unflatten(-1, (meas.shape[-2], -1))  # (S, B, A, d): d = 4 for [px, py, vx, vy]
    z = obs.reading(meas)  # (S, B, A, Dz): the raw channels the model explains (samples averaged)
    h, C, R = obs.linearize(yj) if linearized is None else linearized
    nu = obs.residual(z, h)  # z - h (an angle wrapped)
    if gate_prob is not None:
        visible = _gate(nu, C, R, omega_pred, visible, gate_prob)
    Rinv_C = torch.linalg.solve(R, C)  # (S, B, A, Dz, d)
    zbar = nu + (C @ yj.unsqueeze(-1)).squeeze(-1)
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


def _gate(nu: Tensor, C: Tensor, R: Tensor, omega_pred: Tensor | None, visible: Tensor, prob: float) -> Tensor:
    """Chi-square innovation gate: ``visible & (nu^T S^-1 nu <= chi2(prob))``, shapes ``(S, B, A)``."""
    S_cov = R
    if omega_pred is not None:
        s, b, dx = omega_pred.shape[:3]
        d = C.shape[-1]
        a = dx // d
        P = torch.cholesky_inverse(safe_cholesky(omega_pred)).view(s, b, a, d, a, d)
        Pjj = torch.diagonal(P, dim1=2, dim2=4).permute(0, 1, 4, 2, 3)  # (S, B, A, d, d)
        S_cov = symmetrize(C @ Pjj @ C.transpose(-1, -2) + R)
    d2 = (nu.unsqueeze(-2) @ torch.linalg.solve(S_cov, nu.unsqueeze(-1))).squeeze(-1).squeeze(-1)
    ok = d2 <= chi2_quantile(prob, nu.shape[-1])
    record_gate(int(visible.sum()), int((visible & ~ok).sum()))
    return visible & ok
