r"""Rao-Blackwellised particle filter for a JMNLS (Algorithm 1) with the online E-step (Algorithm 2).

Everything is batched: leading dims ``B...`` (e.g. Monte Carlo run × strategy × node) come first,
then particles ``N``, then modes ``K`` and statistics ``D``. The continuous state follows a linear
Gaussian transition ``x_t = F x_{t-1} + G w_t, w_t ~ N(0, Q)`` (Eq. 23-24); the observation is
``y_t = h(x_t) + e_{r_t}`` with a user-supplied (nonlinear) ``h`` (Eq. 25).

Per time step (:func:`rbpf_step`):

1. resample where the effective sample size < ``ess_threshold * N`` (systematic resampling; the
   particles' mode probabilities and E-step quantities ``T`` are resampled with them);
2. mode prediction (Eq. 11), prior proposal ``x_t ~ f(.|x_{t-1})``;
3. gamma (Eq. 12), mode update (Eq. 13) and weight update (Eq. 14) - all in the log domain;
4. online E-step (Eq. 15-18) via :func:`online_estep` and the local statistics of Algorithm 2, line 2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from dslearn.models.jmnls import NoiseParams, obs_loglik, stats_dim
from dslearn.models.linear_gaussian import LinearGaussianDynamics
from dslearn.streams import Streams, rand, randn


def kernel_log_floor(dtype: torch.dtype) -> float:
    """Exponent floor of the backward kernel (see :func:`_kernel_apply`): log(tiny) + 8, i.e. -700.4 for
    float64 (exp = 2.5e-304) and -79.3 for float32 (exp = 3.5e-35): the smallest entries stay normal numbers."""
    return math.log(torch.finfo(dtype).tiny) + 8.0


@dataclass
class RBPFState:
    """Particle system at time t (batched).

    Attributes:
        x: (B..., N, n) continuous-state particles.
        logw: (B..., N) normalised log weights.
        alpha: (B..., N, K) filtered mode probabilities alpha_{t|t}^{(i)} (Eq. 13).
        T: (B..., N, K, D) E-step auxiliary quantities T_t^{(i)}(l) (Eq. 18).
        t: time index of the last processed measurement (0 = initial).
    """

    x: Tensor
    logw: Tensor
    alpha: Tensor
    T: Tensor
    t: int = 0


def init_state(x0: Tensor, num_particles: int, alpha0: Tensor) -> RBPFState:
    """All particles at x0, equal weights, alpha_{0|0} given (Section VI: x^{(i)}_{s,0} = x_{s,0}).

    Args:
        x0: (B..., n) initial states.
        num_particles: N.
        alpha0: (B..., K) initial mode probabilities.
    """
    bshape = x0.shape[:-1]
    k = alpha0.shape[-1]
    x = x0[..., None, :].expand(*bshape, num_particles, x0.shape[-1]).clone()
    logw = torch.full((*bshape, num_particles), -math.log(num_particles), dtype=x0.dtype, device=x0.device)
    alpha = alpha0[..., None, :].expand(*bshape, num_particles, k).clone()
    T = torch.zeros(*bshape, num_particles, k, stats_dim(k), dtype=x0.dtype, device=x0.device)
    return RBPFState(x, logw, alpha, T, 0)


def ess(logw: Tensor) -> Tensor:
    """Effective sample size 1 / sum w_i^2 from normalised log weights. (B..., N) -> (B...)."""
    return torch.exp(-torch.logsumexp(2.0 * logw, -1))


def systematic_indices(logw: Tensor, gen: torch.Generator | Streams | None = None, u0: Tensor | None = None) -> Tensor:
    """Systematic resampling ancestors. logw: (B..., N) normalised -> (B..., N) long.
    ``u0``: (B..., 1) uniforms (drawn from ``gen`` if not given)."""
    n = logw.shape[-1]
    cw = torch.exp(logw).cumsum(-1)
    cw = cw / cw[..., -1:]
    if u0 is None:
        u0 = rand((*logw.shape[:-1], 1), gen, dtype=logw.dtype, device=logw.device)
    u = (u0 + torch.arange(n, dtype=logw.dtype, device=logw.device)) / n
    # right=True: a uniform equal to a cumulative weight takes the next particle, never one of zero weight
    # before it; the clamp covers a uniform that rounds up to the total
    return torch.searchsorted(cw.contiguous(), u.contiguous(), right=True).clamp_max(n - 1)


def regularisation_bandwidth(n: int, d: int) -> float:
    """Optimal Gaussian-kernel bandwidth ``(4 / (N (d + 2)))^(1 / (d + 4))`` of the regularised particle filter
    (Musso, Oudjane & Le Gland 2001), in units of the particle cloud's standard deviation (0.466 for N = 300, d = 4)."""
    return (4.0 / (n * (d + 2.0))) ** (1.0 / (d + 4.0))


def resample(state: RBPFState, ess_threshold: float, gen: torch.Generator | Streams,
             regularise: float = 0.0) -> tuple[RBPFState, Tensor]:
    """Algorithm 1, line 1: resample the batches whose ESS < ess_threshold * N.

    The systematic-resampling uniform (and, with ``regularise > 0``, the kernel noise) is drawn for every batch
    entry at every call, whether or not it resamples, so an entry's random stream never depends on what the
    other entries of the batch do.

    Args:
        regularise: 0 (the paper: plain systematic resampling) or a factor ``c > 0``: post-regularised
            resampling (Musso et al. 2001): every resampled particle is moved by ``N(0, (c h)^2 Sigma)`` with
            ``Sigma`` the weighted covariance of the particles before resampling and ``h`` the optimal
            bandwidth :func:`regularisation_bandwidth`. Restores the diversity that resampling removes.

    Returns:
        The (possibly) resampled state and a (B...) bool mask of the batches that were resampled.
    """
    n = state.logw.shape[-1]
    dtype, device = state.logw.dtype, state.logw.device
    u0 = rand((*state.logw.shape[:-1], 1), gen, dtype=dtype, device=device)
    kern = randn(state.x.shape, gen, dtype=dtype, device=device) if regularise > 0 else None
    mask = ess(state.logw) < ess_threshold * n
    if not bool(mask.any()):
        return state, mask
    idx = systematic_indices(state.logw, u0=u0)
    keep = torch.arange(n, device=idx.device).expand_as(idx)
    idx = torch.where(mask[..., None], idx, keep)
    # gather with explicitly expanded indices (take_along_dim adds a modulo pass for negative indices)
    x = torch.gather(state.x, -2, idx[..., None].expand_as(state.x))
    if kern is not None:
        w = torch.exp(state.logw)
        dx = state.x - torch.einsum("...i,...in->...n", w, state.x)[..., None, :]
        cov = torch.einsum("...i,...in,...im->...nm", w, dx, dx)
        lam, vec = torch.linalg.eigh(0.5 * (cov + cov.transpose(-1, -2)))  # PSD square root, never fails
        root = vec * lam.clamp_min(0.0).sqrt()[..., None, :]
        h = regularise * regularisation_bandwidth(n, state.x.shape[-1])
        x = x + torch.where(mask[..., None, None], h * kern @ root.transpose(-1, -2), torch.zeros_like(x))
    alpha = torch.gather(state.alpha, -2, idx[..., None].expand_as(state.alpha))
    kd = state.T.shape[-2] * state.T.shape[-1]
    T = torch.gather(state.T.flatten(-2), -2, idx[..., None].expand(*idx.shape, kd)).unflatten(-1, state.T.shape[-2:])
    logw = torch.where(mask[..., None], torch.full_like(state.logw, -math.log(n)), state.logw)
    return RBPFState(x, logw, alpha, T, state.t), mask


def transition_stats(bm: Tensor, e: Tensor) -> Tensor:
    r"""Expected increment E[s_t | x_t^{(i)}, r_t = l] given the backward mode probabilities.

    Args:
        bm: (B..., N, K_l, K_k) backward mode probabilities P(r_{t-1}=k | x_t^{(i)}, r_t=l, ...).
        e: (B..., N) residuals y_t - h(x_t^{(i)}).

    Returns:
        (B..., N, K, D): for mode l, ``S1[k, l'] = bm[l, k] 1(l'=l)``, ``S2[l'] = 1(l'=l)``,
        ``S3a[l'] = 1(l'=l) e``, ``S3b[l'] = 1(l'=l) e^2``.
    """
    k = bm.shape[-1]
    eye = torch.eye(k, dtype=bm.dtype, device=bm.device)
    s1 = (bm[..., :, :, None] * eye[:, None, :]).flatten(-2)  # (..., l, k*K + l')
    s2 = eye.expand(*bm.shape[:-2], k, k)
    s3a = eye * e[..., None, None]
    s3b = eye * (e * e)[..., None, None]
    return torch.cat([s1, s2, s3a, s3b], -1)


def _kernel_apply(zi1: Tensor, mj1: Tensor, v: Tensor, buf: Tensor | None = None) -> Tensor:
    """``A @ v`` with ``A[b, i, j] = exp(zi1[b, i] . mj1[b, j] - max_j(...))`` (row-stabilised kernel).

    The exponent is clamped at :func:`kernel_log_floor` (-700.4 in float64): each row's largest entry is
    exp(0) = 1, so an entry below ~1e-304 is far below the float64 resolution of the row sums, and the clamp keeps
    ``exp`` and the product off the slow underflow / subnormal paths (several times faster on CPUs).
    The product runs as ``(v^T A^T)^T``: with M << N columns this layout is about twice as fast in MKL.

    zi1, mj1: (B, N, n+1); v: (B, N, M) -> (B, N, M). buf: optional scratch space of at least B*N*N
    elements for the kernel matrix (reused across steps: saves allocating and zero-filling fresh pages).
    """
    b, n = zi1.shape[0], zi1.shape[1]
    if buf is not None and buf.numel() >= b * n * n:
        a = torch.bmm(zi1, mj1.transpose(1, 2), out=buf[: b * n * n].view(b, n, n))  # (B, N_i, N_j)
    else:
        a = torch.bmm(zi1, mj1.transpose(1, 2))
    a.sub_(a.amax(-1, keepdim=True)).clamp_min_(kernel_log_floor(a.dtype)).exp_()
    return torch.bmm(v.transpose(1, 2), a.transpose(1, 2)).transpose(1, 2)


def online_estep(x_prev: Tensor, logw_prev: Tensor, alpha_prev: Tensor, T_prev: Tensor, x_new: Tensor,
                 e: Tensor, pi: Tensor, eta: float, dyn: LinearGaussianDynamics) -> Tensor:
    r"""Forward-only smoothing of the sufficient statistics, Eq. (16)-(18).

    With :math:`\tilde w^{(i,j)}(\ell,k) = f(x_t^{(i)}|x_{t-1}^{(j)})\pi_{k\ell}\alpha_{t-1}^{(j)}(k)w_{t-1}^{(j)}`
    (Eq. 17) normalised over (j, k) for each (i, l), Eq. (18) is

    .. math:: \hat T_t^{(i)}(\ell) = \sum_{j,k} \bar w^{(i,j)}(\ell,k)[(1-\eta_t)\hat T_{t-1}^{(j)}(k)
              + \eta_t s_t(x^{(j)}_{t-1}, k, x^{(i)}_t, \ell)].

    Because ``s_t`` depends on j only through k (the observation statistics depend on (x_t, r_t), the
    transition statistics on (r_{t-1}, r_t)), the whole O(K^2 N^2) sum is one batched matrix product
    ``A @ V`` with ``A[i, j] = f(x_t^i | x_{t-1}^j) w_{t-1}^j`` (N×N, stabilised per row in the log
    domain) and ``V[j] = [alpha_{t-1}^j(k), alpha_{t-1}^j(k) T_{t-1}^j(k, :)]_k``, followed by a K×K
    contraction with the TPM. No Python loop over particles or modes.

    Args:
        x_prev: (B..., N, n) particles at t-1 (after resampling).
        logw_prev: (B..., N) their normalised log weights.
        alpha_prev: (B..., N, K) alpha_{t-1|t-1}.
        T_prev: (B..., N, K, D) \hat T_{t-1}.
        x_new: (B..., N, n) particles at t.
        e: (B..., N) residuals y_t - h(x_t^{(i)}).
        pi: (B..., K, K) current TPM estimate (theta').
        eta: step size eta_t.
        dyn: dynamics (backward kernel f).

    Returns:
        (B..., N, K, D) \hat T_t.
    """
    k = alpha_prev.shape[-1]
    d = T_prev.shape[-1]
    bshape = x_prev.shape[:-2]
    n = x_prev.shape[-2]
    kdt = dyn.kernel_dtype or x_new.dtype
    ref = x_new.mean(-2, keepdim=True)  # centre before whitening: avoids cancellation in |z|^2 - 2 z.m
    zi = dyn.whiten(x_new - ref).reshape(-1, n, x_new.shape[-1])  # (B, N, n)
    mj = dyn.whiten(x_prev @ dyn.F.T - ref).reshape(-1, n, x_new.shape[-1])
    # log f(x_t^i | x_{t-1}^j) + log w_{t-1}^j up to terms constant in j, then stabilised per row i
    col = -0.5 * (mj * mj).sum(-1) + logw_prev.reshape(-1, n)  # (B, N)
    # one bmm with the column term folded in as an extra coordinate ([z_i, 1] . [m_j, col_j]); cheaper than
    # baddbmm, which first copies the broadcast column term into the (B, N, N) output
    zi1 = torch.cat([zi, torch.ones_like(zi[..., :1])], -1).to(kdt)  # (B, N, n+1)
    mj1 = torch.cat([mj, col[..., None]], -1).to(kdt)  # (B, N, n+1)
    v = torch.cat([alpha_prev[..., None], alpha_prev[..., None] * T_prev], -1)  # (B..., N, K, 1+D)
    v = v.reshape(-1, n, k * (1 + d)).to(kdt)
    nb = v.shape[0]
    chunk = max(1, int(dyn.kernel_chunk)) if dyn.kernel_chunk else nb
    chunk = min(chunk, nb)
    buf = getattr(dyn, "_kernel_buf", None)  # scratch for the (chunk, N, N) kernel, kept between steps
    if buf is None or buf.numel() < chunk * n * n or buf.dtype != kdt or buf.device != v.device:
        buf = torch.empty(chunk * n * n, dtype=kdt, device=v.device)
        dyn._kernel_buf = buf
    if chunk >= nb:
        u = _kernel_apply(zi1, mj1, v, buf)
    else:  # chunks of the batch keep the (chunk, N, N) kernel in cache between its four passes
        u = torch.cat([_kernel_apply(zi1[b:b + chunk], mj1[b:b + chunk], v[b:b + chunk], buf)
                       for b in range(0, nb, chunk)], 0)
    u = u.to(x_new.dtype).reshape(*bshape, n, k, 1 + d)
    fb = u[..., 0]  # (B..., N_i, K_k) = sum_j A_ij alpha_j(k)
    fbt = u[..., 1:]  # (B..., N_i, K_k, D)
    bm = fb[..., None, :] * pi.transpose(-1, -2)[..., None, :, :]  # (B..., N, K_l, K_k): fb(i,k) pi_kl
    z = bm.sum(-1, keepdim=True).clamp_min(torch.finfo(fb.dtype).tiny)  # Z(i, l)
    bm = bm / z
    # (1 - eta) * part + eta * transition_stats(bm, e), written in place on the diagonal blocks (fewer passes)
    out = torch.einsum("...ikd,...kl->...ild", fbt, pi)
    out.mul_((1.0 - eta) / z)
    kk = k * k
    out[..., :kk].unflatten(-1, (k, k)).diagonal(dim1=-3, dim2=-1).add_(bm.transpose(-1, -2), alpha=eta)  # S1
    out[..., kk:kk + k].diagonal(dim1=-2, dim2=-1).add_(eta)  # S2
    out[..., kk + k:kk + 2 * k].diagonal(dim1=-2, dim2=-1).add_(e[..., None], alpha=eta)  # S3a
    out[..., kk + 2 * k:].diagonal(dim1=-2, dim2=-1).add_((e * e)[..., None], alpha=eta)  # S3b
    return out


def local_stats(logw: Tensor, alpha: Tensor, T: Tensor) -> Tensor:
    """Algorithm 2, line 2: S_{s,t} = sum_i w_i sum_l alpha_i(l) T_i(l). -> (B..., D)."""
    return torch.einsum("...i,...il,...ild->...d", torch.exp(logw), alpha, T)


def rbpf_step(state: RBPFState, y: Tensor, h: Callable[[Tensor], Tensor], theta: NoiseParams,
              dyn: LinearGaussianDynamics, gen: torch.Generator | Streams, *, eta: float, ess_threshold: float = 0.5,
              estep: bool = True, regularise: float = 0.0) -> tuple[RBPFState, Tensor | None, dict]:
    """One RBPF step (Algorithm 1) followed by the online E-step (Algorithm 2).

    Args:
        state: particle system at t-1.
        y: (B...) measurements y_t.
        h: maps states (B..., N, n) to predicted observations (B..., N) (e.g. terrain lookup).
        theta: current parameters with batch shape (B...).
        dyn: dynamics.
        gen: torch generator.
        eta: E-step step size eta_t.
        ess_threshold: resample when ESS < ess_threshold * N (0 never, 1 always).
        estep: run Algorithm 2 (set False for a pure filter).
        regularise: post-regularised resampling factor (0 = the paper's plain resampling; see :func:`resample`).

    Returns:
        (new state, local statistics (B..., D) or None, info dict with ``resampled`` (B...) bool,
        ``degenerate`` (B...) bool: every particle's likelihood was zero even in the log domain (e.g. a
        non-finite measurement) and the weights were reset to uniform, and ``loglik`` (B...) the estimate
        of log p(y_t | y_{1:t-1})).
    """
    st, resampled = resample(state, ess_threshold, gen, regularise)
    alpha_pred = torch.einsum("...ik,...kl->...il", st.alpha, theta.pi)  # Eq. (11)
    x_new = dyn.sample(st.x, gen)  # prior proposal (Algorithm 1, line 4)
    e = y[..., None] - h(x_new)  # (B..., N)
    log_gamma = obs_loglik(e, theta.mu, theta.sigma) + torch.log(alpha_pred.clamp_min(1e-300))  # Eq. (12)
    log_lik = torch.logsumexp(log_gamma, -1)  # log sum_k gamma(k); f/q cancel with the prior proposal
    alpha_new = torch.softmax(log_gamma, -1)  # Eq. (13)
    logw = st.logw + log_lik  # Eq. (14)
    lse = torch.logsumexp(logw, -1, keepdim=True)
    loglik = lse[..., 0]  # log p(y_t | y_{1:t-1}) estimate
    degenerate = ~torch.isfinite(lse[..., 0])
    n = logw.shape[-1]
    logw = torch.where(torch.isfinite(lse), logw - lse, torch.full_like(logw, -math.log(n)))
    logw = torch.nan_to_num(logw, nan=-math.inf)
    # a particle whose gamma underflowed entirely keeps its predicted mode probabilities
    alpha_new = torch.where(torch.isfinite(alpha_new).all(-1, keepdim=True), alpha_new, alpha_pred)
    stats = None
    T_new = st.T
    if estep:
        e_safe = torch.where(torch.isfinite(e), e, torch.zeros_like(e))  # degenerate (non-finite) residuals
        T_new = online_estep(st.x, st.logw, st.alpha, st.T, x_new, e_safe, theta.pi, eta, dyn)
        stats = local_stats(logw, alpha_new, T_new)
    new = RBPFState(x_new, logw, alpha_new, T_new, state.t + 1)
    return new, stats, {"resampled": resampled, "degenerate": degenerate, "loglik": loglik}


def posterior_mean(state: RBPFState) -> Tensor:
    """Weighted particle mean. -> (B..., n)."""
    return torch.einsum("...i,...in->...n", torch.exp(state.logw), state.x)
