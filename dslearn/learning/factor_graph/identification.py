r"""Model identification over the factor graph (Jiang et al. 2022, Sec. III-A, Fig. 1 upper part).

Each sensor compresses its ``L`` samples into a Gaussian message (measurement node D_n: sample
mean and the variance of that mean); the fusion centre linearises ``h`` at the tracker's
predicted state (Eqs. 6-9) and iterates the Gaussian messages of Eqs. 11-16 from an initial
guess. Batch dims are free, so independent sources (``I``) are just another batch dim:
``x (*B, I, M)`` with ``h: (*B, I, M) -> (*B, I, N)``.

Options beyond the paper (its choices are the defaults): a sequential (Gauss-Seidel over the
parameters) schedule, damping of the zeta messages, re-linearisation at the current estimate,
and ``graph="joint"``: one vector-valued variable node instead of one per parameter, which
removes the loops and makes a re-linearised iteration one Gauss-Newton step.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from dslearn.errors import ConfigError, check_choice, check_positive
from dslearn.linalg import cholesky, cholesky_solve
from dslearn.learning.factor_graph.messages import linearize, marginal, rho_from_zeta, zeta_natural


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


SCHEDULES = ("flooding", "sequential")
GRAPHS = ("scalar", "joint")


def _damp(zp_new: Tensor, zi_new: Tensor, zp_old: Tensor | None, zi_old: Tensor | None, d: float):
    """``(1-d) new + d old`` on the zeta natural parameters; the first messages are undamped."""
    if zp_old is None or not d:
        return zp_new, zi_new
    return (1.0 - d) * zp_new + d * zp_old, (1.0 - d) * zi_new + d * zi_old


def _expand(h, x: Tensor, lambda_tol: float) -> tuple[Tensor, Tensor, Tensor]:
    """The Taylor expansion of ``h`` at ``x`` (:func:`linearize`: the slopes ``lam (*B, N, M)`` and the offsets) and
    its number of near-zero slopes (``|lam| <= lambda_tol`` times the largest slope of its parameter)."""
    lam, gamma = linearize(h, x)
    scale = lam.abs().amax(dim=-2, keepdim=True).clamp_min(torch.finfo(lam.dtype).tiny)
    return lam, gamma, (lam.abs() <= lambda_tol * scale).sum((-1, -2))


def _converged(t: int, mean: Tensor, previous: Tensor, converged_at: Tensor, tol: float) -> Tensor:
    """``converged_at`` set to ``t`` where iteration ``t`` first moved the estimate by less than ``tol`` (max norm)."""
    newly = ((mean - previous).abs().amax(-1) < tol) & (converged_at > t)
    return torch.where(newly, torch.full_like(converged_at, t), converged_at)


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
    schedule: str = "flooding",
    damping: float = 0.0,
    graph: str = "scalar",
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
        schedule: ``"flooding"`` (paper: all zetas, then all rhos, per iteration) or
            ``"sequential"`` (one parameter at a time, ``m = 1..M``: the zetas to ``x_m``, then
            its rhos, so ``x_{m+1}``'s zetas already use the new ``rho_m``; a Gauss-Seidel
            sweep). One iteration = one sweep over all parameters either way.
        damping: ``d in [0, 1)``: the new zeta messages (natural parameters) are mixed as
            ``(1-d) new + d old`` from the second iteration on (0 = the paper's update).
        graph: ``"scalar"`` (paper, Fig. 1: one variable node per parameter ``x_m``, scalar
            messages, Eqs. 11-16; loopy for ``M >= 2``, ``N >= 2``) or ``"joint"``: one
            ``M``-dimensional variable node ``x``. Each sensor then sends the rank-one Gaussian
            message of its linearised observation, information ``lambda_n lambda_n^T / s_n``
            and ``lambda_n (y_n - gamma_n) / s_n``; the graph is a tree, so one iteration gives
            the exact weighted least-squares solution of the current linearisation, and with
            ``relinearize=True`` one iteration is one Gauss-Newton step. ``schedule``,
            ``damping`` and ``init_var`` have no role there (no loops, no upward messages).

    Returns:
        :class:`IdentificationResult`.
    """
    if int(num_iters) < 1:
        raise ConfigError(f"num_iters={num_iters!r} must be >= 1")
    check_positive("init_var", init_var, finite=False)
    check_positive("prior_var", prior_var, finite=False)
    check_choice("schedule", schedule, SCHEDULES)
    if not 0.0 <= float(damping) < 1.0:
        raise ConfigError(f"damping={damping!r} must be in [0, 1)")
    check_choice("graph", graph, GRAPHS)
    assert y_mean.shape == y_var.shape and beta.shape[:-1] == y_mean.shape[:-1], (y_mean.shape, beta.shape)
    M, N = beta.shape[-1], y_mean.shape[-1]
    init_mean = torch.broadcast_to(init_mean.to(beta), beta.shape)
    prior_prec = 0.0 if prior_var == float("inf") else 1.0 / prior_var
    prior_info = prior_prec * init_mean if prior_prec else 0.0

    lam, gamma, near_zero = _expand(h, beta, lambda_tol)
    assert lam.shape == (*beta.shape[:-1], N, M), lam.shape

    if graph == "joint":
        return _identify_joint(h, y_mean, y_var, lam, gamma, near_zero, init_mean, int(num_iters), init_var,
                               prior_prec, relinearize, lambda_tol, tol, min_precision)
    rho_mean = init_mean.unsqueeze(-2).expand(*beta.shape[:-1], N, M).clone()
    rho_var = torch.full_like(rho_mean, float(init_var))
    means = [init_mean]
    vars_ = [torch.full_like(init_mean, float(init_var))]
    floored = torch.zeros(beta.shape[:-1], dtype=torch.long, device=beta.device)
    converged_at = torch.full(beta.shape[:-1], int(num_iters) + 1, dtype=torch.long, device=beta.device)
    zp = zi = None
    eye_m = torch.eye(M, dtype=torch.bool, device=beta.device)
    for t in range(1, int(num_iters) + 1):
        if schedule == "flooding":
            zp_new, zi_new = zeta_natural(lam, y_mean, y_var, gamma, rho_mean, rho_var)   # Eqs. 11-12
            zp, zi = _damp(zp_new, zi_new, zp, zi, damping)
            rho_mean, rho_var, f_r = rho_from_zeta(zp, zi, prior_prec, prior_info, min_precision)  # Eqs. 13-14
        else:  # sequential: parameter m's zetas and rhos, then m + 1 with the new rho_m
            f_r = torch.zeros_like(rho_mean, dtype=torch.bool)
            for m in range(M):
                sel = eye_m[m]                                                           # (M,) one-hot
                zp_new, zi_new = zeta_natural(lam, y_mean, y_var, gamma, rho_mean, rho_var)
                if zp is None:
                    zp, zi = zp_new, zi_new                   # columns m' > m are replaced below
                zp_d, zi_d = _damp(zp_new, zi_new, zp, zi, damping if t > 1 else 0.0)
                zp, zi = torch.where(sel, zp_d, zp), torch.where(sel, zi_d, zi)
                rm, rv, fr = rho_from_zeta(zp, zi, prior_prec, prior_info, min_precision)
                rho_mean, rho_var = torch.where(sel, rm, rho_mean), torch.where(sel, rv, rho_var)
                f_r = f_r | (fr & sel)
        mean, var, f_m = marginal(zp, zi, prior_prec, prior_info, min_precision)         # Eqs. 15-16
        mean = torch.where(f_m, init_mean, mean)  # nothing informs x_m: keep the guess
        floored = floored + f_r.sum((-1, -2)) + f_m.sum(-1)
        converged_at = _converged(t, mean, means[-1], converged_at, tol)
        means.append(mean)
        vars_.append(var)
        if relinearize and t < num_iters:
            lam, gamma, more = _expand(h, mean, lambda_tol)
            near_zero = near_zero + more
    return IdentificationResult(torch.stack(means), torch.stack(vars_), near_zero, floored, converged_at)


def _identify_joint(
    h, y_mean: Tensor, y_var: Tensor, lam: Tensor, gamma: Tensor, near_zero: Tensor, init_mean: Tensor,
    num_iters: int, init_var: float, prior_prec: float, relinearize: bool, lambda_tol: float, tol: float,
    min_precision: float,
) -> IdentificationResult:
    """``graph="joint"`` of :func:`identify`: one vector variable node, rank-one sensor messages."""
    M = init_mean.shape[-1]
    eye = torch.eye(M, dtype=init_mean.dtype, device=init_mean.device)
    means = [init_mean]
    vars_ = [torch.full_like(init_mean, float(init_var))]
    floored = torch.zeros(init_mean.shape[:-1], dtype=torch.long, device=init_mean.device)
    converged_at = torch.full(init_mean.shape[:-1], num_iters + 1, dtype=torch.long, device=init_mean.device)
    w = 1.0 / y_var                                                         # (*B, N)
    for t in range(1, num_iters + 1):
        # sensor n -> x: N(lambda_n^T x + gamma_n; y_n, s_n) as information (Lambda_n, eta_n); product at x
        lw = lam * w.unsqueeze(-1)                                          # (*B, N, M)
        info_mat = (lw.unsqueeze(-1) * lam.unsqueeze(-2)).sum(-3) + prior_prec * eye      # (*B, M, M)
        info_vec = (lw * (y_mean - gamma).unsqueeze(-1)).sum(-2) + prior_prec * init_mean  # (*B, M)
        # a parameter no sensor informs: precision floor at the guess (counted)
        f_m = info_mat.diagonal(dim1=-2, dim2=-1) < min_precision
        fl = torch.where(f_m, torch.full_like(init_mean, min_precision), torch.zeros_like(init_mean))
        info_mat = info_mat + torch.diag_embed(fl)
        info_vec = info_vec + fl * init_mean
        chol = cholesky(info_mat)
        mean = cholesky_solve(info_vec.unsqueeze(-1), chol).squeeze(-1)
        var = cholesky_solve(eye.expand_as(info_mat), chol).diagonal(dim1=-2, dim2=-1)
        floored = floored + f_m.sum(-1)
        converged_at = _converged(t, mean, means[-1], converged_at, tol)
        means.append(mean)
        vars_.append(var)
        if relinearize and t < num_iters:
            lam, gamma, more = _expand(h, mean, lambda_tol)
            near_zero = near_zero + more
    return IdentificationResult(torch.stack(means), torch.stack(vars_), near_zero, floored, converged_at)
