r"""Rao-Blackwellised particle filter over the noise modes (a mixture Kalman filter) with the online E-step.

Braga et al.'s jump-Markov measurement noise (:mod:`dslearn.models.jmnls`) on a linear-Gaussian state: the state
follows ``x_t = F x_{t-1} + w_t, w_t ~ N(0, Q)`` and is observed as ``y_t = H x_t + e_t`` with
``e_t ~ N(mu_{r_t} 1, sigma_{r_t}^2 I_d)`` and the mode ``r_t`` a Markov chain (``pi_kl = P(r_t = l | r_{t-1} = k)``).
Given the mode sequence the model is linear-Gaussian, so the particles are mode sequences, each carrying the
Kalman filter of the state given its sequence (Chen & Liu's mixture Kalman filter): where
:mod:`dslearn.filters.rbpf` samples the state and marginalises the current mode, this filter samples the modes
and marginalises the state exactly.

Per step (:func:`mkf_step`), every batch entry at once (leading dims ``B...``, then particles ``N``, modes ``K``):

1. resample where the effective sample size < ``ess_threshold * N`` (the systematic resampling of
   :func:`dslearn.filters.rbpf.systematic_indices`; the Kalman filters, mode probabilities and statistics go
   with their particles);
2. Kalman prediction (the same for every mode);
3. for every mode ``l``: the Kalman update and the predictive density ``N(y_t; H m + mu_l 1, H P H^T + sigma_l^2 I)``
   (:func:`mode_updates`); ``gamma(l) = sum_k alpha(k) pi_kl N_l``, the weight times ``sum_l gamma(l)`` (the
   optimal proposal's incremental weight), the mode drawn from ``gamma / sum gamma`` and the particle keeps that
   mode's Kalman filter;
4. the online E-step on the particle's path (the path-space form of Braga et al.'s Eq. 18, the statistics
   resampled with their particles): ``T_t = (1 - eta_t) T_{t-1} + eta_t s_t`` with ``s_t`` the expectation of the
   statistics of :mod:`dslearn.models.jmnls` over the step's modes given the path and ``y_t`` (Rao-Blackwellised
   over ``r_t``): ``S1_kl = alpha(k) pi_kl N_l / sum gamma``, ``S2_l = d p_l``, ``S3a_l = p_l sum_j E_l[e_j]``,
   ``S3b_l = p_l E_l[|e|^2]`` with ``p_l = gamma(l) / sum gamma`` and the residual's moments under mode ``l``'s
   updated state, ``E_l[e] = y - H m_l``, ``E_l[|e|^2] = |y - H m_l|^2 + tr(H P_l H^T)`` (the filtered, not the
   smoothed, state: the statistic of step ``t`` is not revised later). The ``d`` coordinates of a residual count as
   ``d`` samples of the mode's scalar noise, so the M-step is :func:`dslearn.models.jmnls.m_step` unchanged.

Where a batch entry has no measurement at a step (``visible`` false) it predicts only: the mode probabilities
move by ``pi``, the weights and statistics stay.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from dslearn.filters.rbpf import ess, systematic_indices
from dslearn.models.jmnls import LOG_2PI, NoiseParams
from dslearn.streams import Streams, rand


@dataclass
class LinearGaussianState:
    """The conditionally linear-Gaussian model of the state: ``x_t = F x_{t-1} + w_t``, ``w_t ~ N(0, Q)``,
    observed as ``H x_t`` plus the mode's noise. ``F (n, n)``, ``Q (n, n)``, ``H (d, n)``."""

    F: Tensor
    Q: Tensor
    H: Tensor


@dataclass
class MKFState:
    """The particle system (batched).

    Attributes:
        mean: ``(B..., N, n)`` each particle's Kalman mean; cov: ``(B..., N, n, n)`` its covariance.
        alpha: ``(B..., N, K)`` the probabilities of the particle's current mode (one-hot once drawn).
        logw: ``(B..., N)`` normalised log weights.
        T: ``(B..., N, D)`` the online E-step's statistics of the particle's path.
    """

    mean: Tensor
    cov: Tensor
    alpha: Tensor
    logw: Tensor
    T: Tensor


def init_state(mean0: Tensor, cov0: Tensor, alpha0: Tensor, num_particles: int, stats_dim: int) -> MKFState:
    """Every particle with the prior ``N(mean0, cov0)`` (``(B..., n)``, ``(B..., n, n)``), the mode probabilities
    ``alpha0`` (broadcastable to ``(B..., K)``), equal weights and zero statistics."""
    b = mean0.shape[:-1]
    n = num_particles
    mean = mean0[..., None, :].expand(*b, n, mean0.shape[-1]).clone()
    cov = cov0[..., None, :, :].expand(*b, n, *cov0.shape[-2:]).clone()
    alpha = alpha0.to(mean0).expand(*b, alpha0.shape[-1])[..., None, :].expand(*b, n, alpha0.shape[-1]).clone()
    logw = torch.full((*b, n), -math.log(n), dtype=mean0.dtype, device=mean0.device)
    return MKFState(mean, cov, alpha, logw, torch.zeros(*b, n, stats_dim, dtype=mean0.dtype, device=mean0.device))


def kalman_predict(mean: Tensor, cov: Tensor, model: LinearGaussianState) -> tuple[Tensor, Tensor]:
    """``F m``, ``F P F^T + Q``. mean ``(..., n)``, cov ``(..., n, n)``."""
    cov = model.F @ cov @ model.F.T + model.Q
    return mean @ model.F.T, 0.5 * (cov + cov.transpose(-1, -2))


def mode_updates(mean: Tensor, cov: Tensor, y: Tensor, model: LinearGaussianState, mu: Tensor, sigma: Tensor):
    """The Kalman update of every particle under every mode (:func:`ekf_mode_updates` with the linear
    observation ``H x``: innovation ``y - H m``, the Jacobian ``H`` itself, residual ``y - H m_l``).

    Args:
        mean, cov: ``(B..., N, n)``, ``(B..., N, n, n)`` the prediction.
        y: ``(B..., d)`` the measurement.
        mu, sigma: ``(B..., K)`` the modes' noise means and standard deviations.

    Returns:
        ``loglik (B..., N, K)`` the predictive log-densities ``log N(y; H m + mu_l, H P H^T + sigma_l^2 I)``,
        ``mean (B..., N, K, n)`` and ``cov (B..., N, K, n, n)`` the updated Kalman filters (Joseph form),
        ``e1 (B..., N, K)`` ``sum_j E_l[e_j]`` and ``e2 (B..., N, K)`` ``E_l[|e|^2]`` of the residual
        ``e = y - H x`` under the updated state.
    """
    H = model.H
    return ekf_mode_updates(mean, cov, y[..., None, :] - mean @ H.T, H, mu, sigma,
                            lambda m: y[..., None, None, :] - m @ H.T)


def ekf_mode_updates(mean: Tensor, cov: Tensor, innov: Tensor, H: Tensor, mu: Tensor, sigma: Tensor,
                     residual: Callable[[Tensor], Tensor], per_mode: bool = False):
    r"""The extended Kalman update of every particle under every mode: the observation ``h`` linearised at each
    particle's prediction ``m`` (``h(x) ~ h(m) + H (x - m)``), so the model given the modes is conditionally
    Gaussian and every particle keeps a Gaussian of the state (a marginalised particle filter with linearised
    substructure). With a linear ``h`` (``h(m) = H m``, ``H`` constant) it is the exact Kalman update, the same
    operations in the same order as :func:`mode_updates`.

    Args:
        mean, cov: ``(B..., N, n)``, ``(B..., N, n, n)`` the prediction.
        innov: ``(B..., N, d)`` the innovation ``y - h(m)`` (in the measurement's geometry: an angle wrapped).
        H: the Jacobian of ``h`` at ``m``: ``(d, n)`` (the same for every particle) or ``(B..., N, d, n)``.
        mu, sigma: ``(B..., K)`` the modes' noise means and standard deviations.
        residual: ``m_l (B..., N, K, n) -> y - h(m_l) (B..., N, K, d)``, the residual at the updated means.
        per_mode: ``innov (B..., N, K, d)`` and ``H (B..., N, K, d, n)`` are every mode's own (a linearisation
            at each mode's iterate, :func:`iekf_mode_updates`).

    Returns:
        ``loglik (B..., N, K)`` ``log N(innov; mu_l 1, H P H^T + sigma_l^2 I)``, the updated ``mean (B..., N, K, n)``
        and ``cov (B..., N, K, n, n)`` (Joseph form, symmetrised), ``e1 (B..., N, K)`` ``sum_j E_l[e_j]`` and
        ``e2 (B..., N, K)`` ``E_l[|e|^2] = |y - h(m_l)|^2 + tr(H P_l H^T)`` of the residual ``e = y - h(x)``
        under the updated state (its first-order moments about ``m_l``).
    """
    d, n = H.shape[-2:]
    hk = H if H.ndim == 2 or per_mode else H[..., None, :, :]  # the K (modes) axis of a per-particle Jacobian
    eye_d = torch.eye(d, dtype=mean.dtype, device=mean.device)
    eye_n = torch.eye(n, dtype=mean.dtype, device=mean.device)
    r = (sigma * sigma)[..., None, :, None, None] * eye_d  # (B..., 1, K, d, d)
    if per_mode:
        hp = H @ cov[..., None, :, :]  # (..., N, K, d, n)
        s = hp @ H.transpose(-1, -2) + r  # (..., N, K, d, d)
        v = innov - mu[..., None, :, None]
    else:
        hp = H @ cov  # (..., N, d, n)
        s0 = hp @ H.transpose(-1, -2)  # (..., N, d, d)
        s = s0[..., None, :, :] + r  # (..., N, K, d, d)
        v = innov[..., None, :] - mu[..., None, :, None]  # (..., N, K, d)
        hp = hp[..., None, :, :].expand(*s.shape[:-2], d, n)
    chol = _cholesky(s)
    sv = torch.cholesky_solve(v[..., None], chol)[..., 0]  # S^-1 v
    logdet = 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    loglik = -0.5 * ((v * sv).sum(-1) + logdet + d * LOG_2PI)
    gain = torch.cholesky_solve(hp, chol).transpose(-1, -2)  # P H^T S^-1
    m_new = mean[..., None, :] + (gain @ v[..., None])[..., 0]
    a = eye_n - gain @ hk  # (..., N, K, n, n)
    p_new = a @ cov[..., None, :, :] @ a.transpose(-1, -2) + gain @ r @ gain.transpose(-1, -2)
    p_new = 0.5 * (p_new + p_new.transpose(-1, -2))
    res = residual(m_new)  # E_l[e]
    e1 = res.sum(-1)
    e2 = (res * res).sum(-1) + torch.diagonal(hk @ p_new @ hk.transpose(-1, -2), dim1=-2, dim2=-1).sum(-1)
    return loglik, m_new, p_new, e1, e2


def iekf_mode_updates(mean: Tensor, cov: Tensor, y: Tensor, observe: Callable[[Tensor], tuple[Tensor, Tensor]],
                      mu: Tensor, sigma: Tensor, iterations: int = 1,
                      wrap: Callable[[Tensor, Tensor], Tensor] | None = None):
    r"""The iterated extended Kalman update of every particle under every mode (Gauss-Newton on each mode's
    posterior mode): iteration 1 is :func:`ekf_mode_updates` linearised at the prediction ``m``; each further one
    linearises ``h`` at the mode's last iterate ``m_i`` (``h(x) ~ h(m_i) + H_i (x - m_i)``) and updates the same
    prediction ``(m, P)`` with it, ``m_{i+1} = m + K_i (y - h(m_i) - H_i (m - m_i) - mu_l)``; the predictive density,
    the covariance and the residual's moments are those of the last linearisation. A nonlinear sensor read far more
    precisely than the prediction (Jiang's squared ranges) needs it: one linearisation at the prediction leaves a
    second-order error of the squared step in the updated mean.

    Args:
        mean, cov: ``(B..., N, n)``, ``(B..., N, n, n)`` the prediction.
        y: ``(B..., d)`` the reading.
        observe: ``x (..., n) -> (h(x) (..., d), H(x) (..., d, n))`` at states of any leading shape.
        mu, sigma: ``(B..., K)`` the modes.
        iterations: ``>= 1`` linearisations.
        wrap: ``(z, h) -> z - h`` in the measurement's geometry; ``None``: the difference.

    Returns:
        As :func:`ekf_mode_updates`.
    """
    wrap = wrap if wrap is not None else (lambda z, h: z - h)
    hx, H = observe(mean)

    def residual(m: Tensor) -> Tensor:
        return wrap(y[..., None, None, :], observe(m)[0])

    out = ekf_mode_updates(mean, cov, wrap(y[..., None, :], hx), H, mu, sigma, residual)
    for _ in range(iterations - 1):
        m_i = out[1]  # (B..., N, K, n)
        hx, H = observe(m_i)
        innov = wrap(y[..., None, None, :], hx) + (H @ (m_i - mean[..., None, :])[..., None])[..., 0]
        out = ekf_mode_updates(mean, cov, innov, H, mu, sigma, residual, per_mode=True)
    return out


#: the relative jitter (of the mean diagonal) added to an innovation covariance whose Cholesky factorisation fails
CHOL_JITTER = 1e-10


def _cholesky(s: Tensor) -> Tensor:
    """The Cholesky factor of the innovation covariances ``s (..., d, d)``; where one is not numerically positive
    definite, ``CHOL_JITTER`` times its mean diagonal is added to its diagonal (growing tenfold until it factorises)
    and a warning says how many."""
    chol, info = torch.linalg.cholesky_ex(s)
    bad = info != 0
    if not bool(bad.any()):
        return chol
    count = int(bad.sum())
    eye = torch.eye(s.shape[-1], dtype=s.dtype, device=s.device)
    scale = s.diagonal(dim1=-2, dim2=-1).mean(-1).abs().clamp_min(torch.finfo(s.dtype).tiny)[..., None, None]
    rel = CHOL_JITTER
    while bool(bad.any()) and rel <= 1.0:
        fixed, info = torch.linalg.cholesky_ex(s + rel * scale * eye)
        chol = torch.where(bad[..., None, None], fixed, chol)
        bad = bad & (info != 0)
        rel *= 10.0
    if bool(bad.any()):
        raise FloatingPointError(f"RBPF over noise modes: {int(bad.sum())} innovation covariances are not positive "
                                 f"definite even with jitter of their mean diagonal (non-finite prediction?)")
    warnings.warn(f"RBPF over noise modes: {count} innovation covariances not numerically positive definite; "
                  f"jitter up to {rel / 10.0:g} x their mean diagonal added", RuntimeWarning)
    return chol


def mode_statistics(alpha_prev: Tensor, pi: Tensor, log_gamma: Tensor, e1: Tensor, e2: Tensor, d: int,
                    learn_mean: bool = True) -> Tensor:
    """The expected statistics ``s_t (B..., N, D)`` of one step (layout of :mod:`dslearn.models.jmnls`) given the
    particle's path and ``y_t``: ``alpha_prev (B..., N, K)`` the previous mode's probabilities, ``pi (B..., K, K)``,
    ``log_gamma (B..., N, K)`` ``log sum_k alpha_prev(k) pi_kl N_l``, ``e1``, ``e2`` of :func:`mode_updates`, ``d``
    the measurement's dimension. ``learn_mean=False``: zero-mean modes (``S3a = 0``, so the M-step's ``mu = 0``)."""
    k = alpha_prev.shape[-1]
    lse = torch.logsumexp(log_gamma, -1, keepdim=True)
    p = torch.exp(log_gamma - lse)  # (..., N, K) posterior of r_t
    lik = torch.exp(log_gamma - torch.log(torch.einsum("...ik,...kl->...il", alpha_prev, pi).clamp_min(1e-300)) - lse)
    s1 = alpha_prev[..., :, None] * pi[..., None, :, :] * lik[..., None, :]  # (..., N, K_k, K_l), sums to 1
    s3a = p * e1 if learn_mean else torch.zeros_like(p)
    return torch.cat([s1.flatten(-2), d * p, s3a, p * e2], -1)


def draw_modes(p: Tensor, u: Tensor) -> Tensor:
    """Inverse-CDF draw of one mode per row of ``p (..., K)`` with uniforms ``u (...)`` -> long ``(...)``."""
    c = p.cumsum(-1)
    return (c < u[..., None] * c[..., -1:]).sum(-1).clamp_max(p.shape[-1] - 1)


def resample(state: MKFState, ess_threshold: float, gen: torch.Generator | Streams) -> tuple[MKFState, Tensor]:
    """Systematic resampling of the entries whose ESS < ``ess_threshold * N`` (the uniform drawn for every entry
    at every call). Returns the state and the ``(B...)`` mask of the resampled entries."""
    n = state.logw.shape[-1]
    u0 = rand((*state.logw.shape[:-1], 1), gen, dtype=state.logw.dtype, device=state.logw.device)
    mask = ess(state.logw) < ess_threshold * n
    if not bool(mask.any()):
        return state, mask
    idx = systematic_indices(state.logw, u0=u0)
    idx = torch.where(mask[..., None], idx, torch.arange(n, device=idx.device).expand_as(idx))

    def take(x: Tensor) -> Tensor:
        flat = x.flatten(idx.ndim)
        return torch.gather(flat, -2, idx[..., None].expand(*idx.shape, flat.shape[-1])).view(x.shape)

    logw = torch.where(mask[..., None], torch.full_like(state.logw, -math.log(n)), state.logw)
    return MKFState(take(state.mean), take(state.cov), take(state.alpha), logw, take(state.T)), mask


def mkf_step(state: MKFState, y: Tensor, visible: Tensor, model: LinearGaussianState, theta: NoiseParams,
             gen: torch.Generator | Streams, *, eta: float, ess_threshold: float = 0.5, predict: bool = True,
             learn_mean: bool = True) -> tuple[MKFState, dict]:
    """One step of the mixture Kalman filter with the online E-step (module docstring).

    Args:
        state: the particles at ``t - 1``.
        y: ``(B..., d)`` measurements; visible: ``(B...)`` bool, which entries have one.
        model: the state's linear-Gaussian model.
        theta: the noise modes, batch shape ``(B...)``.
        gen: a generator or per-entry streams over the leading dims (two draws a step: the resampling uniform
            ``(B..., 1)`` and the modes' ``(B..., N)``).
        eta: the E-step's step size ``eta_t``.
        ess_threshold: resample below ``ess_threshold * N`` (0 never).
        predict: ``False``: the first step (the prior is at ``t``).
        learn_mean: ``False``: zero-mean modes (see :func:`mode_statistics`).

    Returns:
        The state at ``t`` and ``{"resampled": (B...) bool, "loglik": (B...)`` the estimate of
        ``log p(y_t | y_{1:t-1})`` (0 where not visible)``}``.
    """
    st, resampled = resample(state, ess_threshold, gen)
    u = rand(st.logw.shape, gen, dtype=st.logw.dtype, device=st.logw.device)
    mean, cov = kalman_predict(st.mean, st.cov, model) if predict else (st.mean, st.cov)
    H = model.H
    new, lse = mode_step(st, mean, cov, visible, theta, u, mode_updates(mean, cov, y, model, theta.mu, theta.sigma),
                         H.shape[0], eta=eta, learn_mean=learn_mean)
    return new, {"resampled": resampled, "loglik": torch.where(visible, lse, torch.zeros_like(lse))}


def mode_step(st: MKFState, mean: Tensor, cov: Tensor, visible: Tensor, theta: NoiseParams, u: Tensor, updates,
              d: int, *, eta: float, learn_mean: bool) -> tuple[MKFState, Tensor]:
    """Step 3-4 of the module docstring on the per-mode updates ``updates`` (:func:`mode_updates` or
    :func:`ekf_mode_updates` of the prediction ``mean``, ``cov``): the mode drawn from the optimal proposal with
    the uniforms ``u (B..., N)``, the weights, the particle's filter of its mode and the E-step; ``d`` the
    measurement's dimension. Entries not ``visible`` keep the prediction, the mode probabilities moved by ``pi``.
    Returns the state and ``(B...)`` the log normaliser of the weights (``log p(y_t | y_{1:t-1})``)."""
    alpha_pred = torch.einsum("...ik,...kl->...il", st.alpha, theta.pi)
    loglik, m_l, p_l, e1, e2 = updates
    log_gamma = loglik + torch.log(alpha_pred.clamp_min(1e-300))
    inc = torch.logsumexp(log_gamma, -1)  # (B..., N)
    p = torch.softmax(log_gamma, -1)
    r = draw_modes(p, u)  # (B..., N)
    pick = r[..., None, None]
    m_new = torch.gather(m_l, -2, pick.expand(*r.shape, 1, m_l.shape[-1]))[..., 0, :]
    p_new = torch.gather(p_l, -3, pick[..., None].expand(*r.shape, 1, *p_l.shape[-2:]))[..., 0, :, :]
    s = mode_statistics(st.alpha, theta.pi, log_gamma, e1, e2, d, learn_mean)
    logw = st.logw + inc
    lse = torch.logsumexp(logw, -1, keepdim=True)
    logw = logw - lse
    vis = visible[..., None]
    new = MKFState(torch.where(vis[..., None], m_new, mean), torch.where(vis[..., None, None], p_new, cov),
                   torch.where(vis[..., None], torch.nn.functional.one_hot(r, p.shape[-1]).to(p), alpha_pred),
                   torch.where(vis, logw, st.logw), torch.where(vis[..., None], (1.0 - eta) * st.T + eta * s, st.T))
    return new, lse[..., 0]


#: ``observe(j, mean (B..., N[, K], n)) -> (h_j (B..., N[, K], d), H_j (B..., N[, K], d, n))``: sensor ``j``'s reading
#: function and its Jacobian at the given states (:func:`mkf_step_sensors`)
Observe = Callable[[int, Tensor], tuple[Tensor, Tensor]]


def mkf_step_sensors(state: MKFState, y: Tensor, visible: Tensor, model: LinearGaussianState, observe: Observe,
                     theta: NoiseParams, gen: torch.Generator | Streams, *, eta: float, ess_threshold: float = 0.5,
                     predict: bool = True, learn_mean: bool = True,
                     wrap: Callable[[Tensor, Tensor], Tensor] | None = None,
                     iterations: int = 1) -> tuple[MKFState, dict]:
    r"""One step of the filter fed by ``S`` sensors at once, each with its own mode chain, the observation
    nonlinear (the extended update, :func:`ekf_mode_updates`): the particles are the sensors' joint mode sequences
    and each carries the extended Kalman filter of the state given them (the state is shared, so the sensors must
    be updated together: one sensor's reading need not fix the state, e.g. a squared range).

    The step resamples and predicts once, then takes the sensors one after the other (``j = 0..S-1``), each by
    :func:`mode_step` from the filters the sensors before it updated (linearised anew at those means): with
    independent noises ``p(y_t | x, r) = prod_j p(y_{t,j} | x, r_j)``, so this is sequential importance sampling
    of the joint modes, sensor ``j``'s mode drawn from its optimal proposal given the path and ``y_{t,1..j}``
    (:func:`mkf_step` for one sensor); with a linear ``h`` the sequential Kalman updates are the joint one.

    Args:
        state: ``alpha (B..., N, S, K)``, ``T (B..., N, S, D)``: every sensor's mode probabilities and statistics.
        y: ``(B..., S, d)`` the readings; visible: ``(B..., S)`` bool.
        model: the state's motion (``F``, ``Q``; its ``H`` is not used).
        observe: sensor ``j``'s reading function and its Jacobian (:data:`Observe`).
        theta: the noise modes, batch shape ``(B..., S)``.
        gen: as :func:`mkf_step`; draws ``(B..., 1)`` for the resampling, then ``(B..., N)`` per sensor.
        wrap: ``(z, h) -> z - h`` in the measurement's geometry (the observation model's ``residual``); ``None``:
            the difference.
        iterations: the linearisations of each sensor's update (:func:`iekf_mode_updates`; 1: the extended update).

    Returns:
        As :func:`mkf_step` (``loglik``: summed over the sensors).
    """
    st, resampled = resample(state, ess_threshold, gen)
    mean, cov = kalman_predict(st.mean, st.cov, model) if predict else (st.mean, st.cov)
    alpha, stats = st.alpha.clone(), st.T.clone()
    logw = st.logw
    total = torch.zeros_like(logw[..., 0])
    for j in range(y.shape[-2]):
        u = rand(st.logw.shape, gen, dtype=st.logw.dtype, device=st.logw.device)
        yj, vj = y[..., j, :], visible[..., j]
        th = NoiseParams(theta.mu[..., j, :], theta.sigma[..., j, :], theta.pi[..., j, :, :])
        ups = iekf_mode_updates(mean, cov, yj, lambda x, j=j: observe(j, x), th.mu, th.sigma, iterations, wrap)
        sub = MKFState(mean, cov, alpha[..., j, :], logw, stats[..., j, :])
        new, lse = mode_step(sub, mean, cov, vj, th, u, ups, yj.shape[-1], eta=eta, learn_mean=learn_mean)
        mean, cov, logw = new.mean, new.cov, new.logw
        alpha[..., j, :], stats[..., j, :] = new.alpha, new.T
        total = total + torch.where(vj, lse, torch.zeros_like(lse))
    return MKFState(mean, cov, alpha, logw, stats), {"resampled": resampled, "loglik": total}


def local_stats(state: MKFState) -> Tensor:
    """The weighted statistics ``sum_i w_i T_i`` ``(B..., D)`` (Braga et al.'s Algorithm 2, line 2); a state of
    several sensors (:func:`mkf_step_sensors`, ``T (B..., N, S, D)``): every sensor's, ``(B..., S, D)``."""
    w = torch.exp(state.logw)
    if state.T.ndim == state.logw.ndim + 2:
        return torch.einsum("...i,...isd->...sd", w, state.T)
    return torch.einsum("...i,...id->...d", w, state.T)


def moments(state: MKFState) -> tuple[Tensor, Tensor]:
    """The mixture's mean ``(B..., n)`` and covariance ``(B..., n, n)`` (the particles' Kalman filters, weighted)."""
    w = torch.exp(state.logw)
    mean = torch.einsum("...i,...in->...n", w, state.mean)
    dm = state.mean - mean[..., None, :]
    cov = torch.einsum("...i,...inm->...nm", w, state.cov + dm[..., :, None] * dm[..., None, :])
    return mean, 0.5 * (cov + cov.transpose(-1, -2))
