r"""Model identification over the factor graph (Jiang et al. 2022, Sec. III-A, Fig. 1 upper part).

Each sensor compresses its ``L`` samples into a Gaussian message (measurement node D_n: sample
mean and the variance of that mean); the fusion centre linearises ``h`` at the tracker's
predicted state (Eqs. 6-9) and iterates the Gaussian messages of Eqs. 11-16 from an initial
guess. Batch dims are free, so independent sources (``I``) are just another batch dim:
``x (*B, I, M)`` with ``h: (*B, I, M) -> (*B, I, N)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from ..errors import ConfigError
from .messages import linearize, marginal, rho_from_zeta, zeta_natural


def compress_measurements(samples: Tensor, noise_var: float | Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Measurement function node D_n: ``L`` raw samples -> (mean, variance of the mean).

    Args:
        samples: ``(*B, N, L)`` raw samples of each sensor at one timing.
        noise_var: per-sample noise variance :math:`\\sigma_y^2` if known (scalar or ``(*B,)``);
            ``None`` uses the unbiased sample variance (needs ``L >= 2``).

    Returns:
        ``y_mean (*B, N)`` and ``y_var (*B, N)`` = variance / L.
    """
    L = samples.shape[-1]
    if L < 1:
        raise ConfigError(f"num_samples={L} must be >= 1")
    if noise_var is None:
        if L < 2:
            raise ConfigError("num_samples must be >= 2 to estimate the variance (measurement_var=sample)")
        var = samples.var(dim=-1, correction=1)
    else:
        noise_var = torch.as_tensor(noise_var, dtype=samples.dtype, device=samples.device)
        if not bool((noise_var > 0).all()):
            raise ConfigError(f"noise variance sigma_y^2={noise_var.tolist()!r} must be > 0")
        if noise_var.dim() > 0:
            noise_var = noise_var.unsqueeze(-1)
        var = torch.broadcast_to(noise_var, samples.shape[:-1])
    # a degenerate sample variance (all samples equal) would make the sensor infinitely sure
    var = var.clamp_min(torch.finfo(samples.dtype).tiny)
    return samples.mean(-1), var / L


@dataclass
class IdentificationResult:
    """Output of :func:`identify`.

    Attributes:
        mean: ``(T+1, *B, M)`` marginal means after 0..T iterations (0 = the initial guess).
        var: ``(T+1, *B, M)`` marginal variances (0 = ``init_var``).
        near_zero_lambda: ``(*B,)`` number of (sensor, parameter) slopes with
            ``|lambda| <= lambda_tol * max_n |lambda|`` (those sensors are skipped for that parameter).
        floored: ``(*B,)`` number of precision floors hit (parameters no sensor informs).
        iters_to_converge: ``(*B,)`` first iteration whose mean moved by less than ``tol``
            (max abs change); ``T+1`` if never.
    """

    mean: Tensor
    var: Tensor
    near_zero_lambda: Tensor
    floored: Tensor
    iters_to_converge: Tensor


def identify(
    h: Callable[[Tensor], Tensor],
    y_mean: Tensor,
    y_var: Tensor,
    beta: Tensor,
    init_mean: Tensor,
    num_iters: int,
    init_var: float = 100.0,
    prior_var: float = float("inf"),
    relinearize: bool = False,
    lambda_tol: float = 1e-8,
    tol: float = 1e-6,
    min_precision: float = 1e-12,
) -> IdentificationResult:
    """Iterate the Gaussian messages of Eqs. 11-16.

    Args:
        h: measurement function ``(*B, M) -> (*B, N)`` (any torch function; slopes by autograd).
        y_mean, y_var: ``(*B, N)`` sensor messages (from :func:`compress_measurements`).
        beta: ``(*B, M)`` Taylor expansion point (the tracker's predicted state, Sec. III-A).
        init_mean: ``(*B, M)`` or ``(M,)`` initial guess: the first upward messages rho.
        num_iters: number of message-passing iterations ``T >= 1``.
        init_var: variance of the initial upward messages.
        prior_var: variance of an optional prior on ``x`` centred at the initial guess; ``inf``
            (default) is the paper's graph (no prior node).
        relinearize: re-expand ``h`` at the current marginal mean after every iteration (an
            option the paper does not use; the paper keeps ``beta`` fixed).
        lambda_tol: relative threshold reported as a near-zero slope.
        tol: convergence threshold on the mean change, for ``iters_to_converge``.
        min_precision: precision floor for parameters no sensor informs.

    Returns:
        :class:`IdentificationResult`.
    """
    if int(num_iters) < 1:
        raise ConfigError(f"num_iters={num_iters!r} must be >= 1")
    if not init_var > 0:
        raise ConfigError(f"init_var={init_var!r} must be > 0")
    if not prior_var > 0:
        raise ConfigError(f"prior_var={prior_var!r} must be > 0")
    assert y_mean.shape == y_var.shape and beta.shape[:-1] == y_mean.shape[:-1], (y_mean.shape, beta.shape)
    M, N = beta.shape[-1], y_mean.shape[-1]
    init_mean = torch.broadcast_to(init_mean.to(beta), beta.shape)
    prior_prec = 0.0 if prior_var == float("inf") else 1.0 / prior_var
    prior_info = prior_prec * init_mean if prior_prec else 0.0

    lam, gamma = linearize(h, beta)
    assert lam.shape == (*beta.shape[:-1], N, M), lam.shape
    scale = lam.abs().amax(dim=-2, keepdim=True).clamp_min(torch.finfo(lam.dtype).tiny)
    near_zero = (lam.abs() <= lambda_tol * scale).sum((-1, -2))

    rho_mean = init_mean.unsqueeze(-2).expand(*beta.shape[:-1], N, M).clone()
    rho_var = torch.full_like(rho_mean, float(init_var))
    means = [init_mean]
    vars_ = [torch.full_like(init_mean, float(init_var))]
    floored = torch.zeros(beta.shape[:-1], dtype=torch.long, device=beta.device)
    converged_at = torch.full(beta.shape[:-1], int(num_iters) + 1, dtype=torch.long, device=beta.device)
    for t in range(1, int(num_iters) + 1):
        zp, zi = zeta_natural(lam, y_mean, y_var, gamma, rho_mean, rho_var)          # Eqs. 11-12
        rho_mean, rho_var, f_r = rho_from_zeta(zp, zi, prior_prec, prior_info, min_precision)  # Eqs. 13-14
        mean, var, f_m = marginal(zp, zi, prior_prec, prior_info, min_precision)         # Eqs. 15-16
        mean = torch.where(f_m, init_mean, mean)  # nothing informs x_m: keep the guess
        floored = floored + f_r.sum((-1, -2)) + f_m.sum(-1)
        moved = (mean - means[-1]).abs().amax(-1)
        newly = (moved < tol) & (converged_at > t)
        converged_at = torch.where(newly, torch.full_like(converged_at, t), converged_at)
        means.append(mean)
        vars_.append(var)
        if relinearize and t < num_iters:
            lam, gamma = linearize(h, mean)
            scale = lam.abs().amax(dim=-2, keepdim=True).clamp_min(torch.finfo(lam.dtype).tiny)
            near_zero = near_zero + (lam.abs() <= lambda_tol * scale).sum((-1, -2))
    return IdentificationResult(torch.stack(means), torch.stack(vars_), near_zero, floored, converged_at)
