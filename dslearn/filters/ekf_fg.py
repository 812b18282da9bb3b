r"""EKF-FG tracking of the identified parameters (Jiang et al. 2022, Eqs. 2-5, 17-19).

Each parameter ``m`` is tracked by the state-gradient model of Eq. 4,
:math:`x_k = x_{k-1} + v_{k-1} + w_k`, as independent scalar Gaussian messages (the paper
tracks one parameter at a time, "the rest ... in the same way"):

* prediction (Eq. 17): :math:`m_{k|k-1} = m_{x,k-1} + m_{v,k-1}`,
  :math:`P_{k|k-1} = P_{x,k-1} + P_{v,k-1} + q_x`;
* refinement (Eq. 18): product of the prediction and the identification output
  :math:`\eta_k \sim \mathcal N(m_\eta, \sigma_e^2)` (Eq. 5). The paper takes
  :math:`\sigma_e^2` = CRLB at the prediction (``obs_var="crlb"``). That is the error of a
  *converged* ML estimate; an unconverged FG output can be off by orders of magnitude more.
  :func:`observation_variance` adds the FG's own convergence term (the squared change of its
  mean in the last iteration, ``obs_var="convergence"``) and an innovation gate;
* gradient update (Eq. 19): product of :math:`\mathcal N(m_{v,k-1}, P_{v,k-1} + q_v)` and the
  changing rate :math:`\hat v_k = x_k - x_{k-1}` (unit time), variance :math:`P_{x,k} + P_{x,k-1}`.

``q_x`` and ``q_v`` are not given in the paper (``q_v = 0`` would freeze the gradient once its
variance shrinks); they are configuration choices.
Shapes: ``(*B, M)`` for every tensor.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

OBS_VAR_MODES = ("crlb", "convergence")


@dataclass
class TrackState:
    """Gaussian beliefs of the state and its gradient, each ``(*B, M)``."""

    x_mean: Tensor
    x_var: Tensor
    v_mean: Tensor
    v_var: Tensor


def predict(state: TrackState, process_var: float) -> tuple[Tensor, Tensor]:
    """Eq. 17. Returns ``(x_pred_mean, x_pred_var)``, each ``(*B, M)``."""
    return state.x_mean + state.v_mean, state.x_var + state.v_var + process_var


def refine(x_pred: Tensor, P_pred: Tensor, obs_mean: Tensor, obs_var: Tensor) -> tuple[Tensor, Tensor]:
    """Eq. 18: product of two Gaussians. ``obs_var`` broadcasts to ``(*B, M)``."""
    P_post = 1.0 / (1.0 / P_pred + 1.0 / obs_var)
    return P_post * (x_pred / P_pred + obs_mean / obs_var), P_post


def update_gradient(state: TrackState, x_new: Tensor, P_new: Tensor, gradient_var: float) -> tuple[Tensor, Tensor]:
    """Eq. 19: fuse the old gradient with the observed change ``x_k - x_{k-1}``."""
    Pv = state.v_var + gradient_var
    rate, rate_var = x_new - state.x_mean, P_new + state.x_var
    v_var = 1.0 / (1.0 / Pv + 1.0 / rate_var)
    return v_var * (state.v_mean / Pv + rate / rate_var), v_var


def ekf_fg_step(
    state: TrackState, obs_mean: Tensor, obs_var: Tensor, process_var: float, gradient_var: float,
    x_pred: Tensor | None = None, P_pred: Tensor | None = None,
) -> TrackState:
    """Refinement and gradient update for one timing (the prediction may be passed in)."""
    if (x_pred is None) != (P_pred is None):
        raise ValueError("ekf_fg_step: pass the prediction as both x_pred and P_pred, or neither (then it predicts)")
    if x_pred is None:
        x_pred, P_pred = predict(state, process_var)
    x_new, P_new = refine(x_pred, P_pred, obs_mean, obs_var)
    v_new, Pv_new = update_gradient(state, x_new, P_new, gradient_var)
    return TrackState(x_new, P_new, v_new, Pv_new)


def observation_variance(
    crlb: Tensor, obs_mean: Tensor, prev_mean: Tensor, x_pred: Tensor, P_pred: Tensor,
    mode: str = "crlb", gate: float | None = None,
) -> tuple[Tensor, Tensor]:
    r"""Observation variance :math:`\sigma_e^2` of the FG output (Eq. 5), per parameter.

    Args:
        crlb: ``(*B,)`` per-parameter CRLB at the prediction (the paper's :math:`\sigma_e^2`).
        obs_mean: ``(*B, M)`` FG output after ``t`` iterations.
        prev_mean: ``(*B, M)`` FG output after ``t - 1`` iterations (the guess for ``t = 1``).
        x_pred, P_pred: ``(*B, M)`` the tracker's prediction (Eq. 17).
        mode: ``"crlb"`` (paper) or ``"convergence"``: ``CRLB + (m_t - m_{t-1})^2``. For a
            linearly contracting iteration with rate ``r`` the remaining error is
            ``|m_t - m_{t-1}| |r| / |1 - r|``: 0.4 (``r = -0.7``, period-2 oscillation) to 2.3
            (``r = 0.7``) last steps for the contraction measured here; a converged FG adds nothing.
        gate: normalised-innovation threshold ``g`` (``None`` = off). Where
            ``(m_t - x_pred)^2 / (P_pred + sigma_e^2) > g`` the output is inconsistent with
            the prediction and ``sigma_e^2`` is inflated to ``(m_t - x_pred)^2 / g - P_pred``,
            so that the normalised innovation equals ``g`` (a soft gate: a gated output moves
            the state by ``g P_pred / |m_t - x_pred| <= sqrt(g P_pred)`` instead of onto it).

    Returns:
        ``sigma_e^2 (*B, M)`` and the gated mask ``(*B, M)`` (bool).
    """
    if mode not in OBS_VAR_MODES:
        from dslearn.errors import ConfigError

        raise ConfigError(f"tracker.obs_var={mode!r} must be one of {list(OBS_VAR_MODES)}")
    var = crlb.unsqueeze(-1).expand_as(obs_mean)
    if mode == "convergence":
        var = var + (obs_mean - prev_mean).square()
    gated = torch.zeros_like(obs_mean, dtype=torch.bool)
    if gate is not None:
        need = (obs_mean - x_pred).square() / float(gate) - P_pred
        gated = need > var
        var = torch.where(gated, need, var)
    return var, gated
