r"""Gaussian-process Bayes filters of one node (Deisenroth, Huber, Hanebeck, ICML 2009; Ko & Fox 2009).

The state-space model has additive noise, :math:`x' = f(x) + w`, :math:`z = g(x) + v`. A filter step maps
the prior :math:`\mathcal N(m, P)` and the measurement :math:`z` to the posterior, through the predicted
state :math:`\mathcal N(m_p, P_p)` and the predicted measurement :math:`\mathcal N(\mu_z, S_z)`; all
Gaussian filters end with the same update from the joint Gaussian of :math:`(x, z)`:
:math:`K = C_{xz} S_z^{-1}`, :math:`m^+ = m_p + K (z - \mu_z)`, :math:`P^+ = P_p - K S_z K^T`.

A model (:class:`AdditiveModel` for a known function, :class:`GPModel` for trained GPs) gives the mean
function, the covariance of its additive noise at an input (constant for a known model; the GP's
predictive variance, its own noise included, for a GP) and, for a GP, the exact moments at a Gaussian
input (:mod:`dslearn.filters.gp_moments`). With the true model the filters are the EKF, UKF and
particle filter; with GP models:

* GP-EKF (:func:`ekf_step`): the GP mean linearised at the mean, the GP variance at the mean as noise.
* GP-UKF (:func:`ukf_step`, ``noise="mean"``, Ko & Fox): sigma points through the GP mean, the GP
  variance at the mean as noise; ``noise="expected"`` (GP-UKF with moment matching) uses the
  sigma-point average of the GP variance instead.
* GP-PF (:func:`pf_step`): particles sample the GP predictive :math:`\mathcal N(\mu_f(x), \sigma_f^2(x))`,
  weights are the GP observation model's predictive density of :math:`z`.
* GP-ADF (:func:`adf_step`): the exact predictive moments for the prediction; the same moments of the
  observation GP at the predicted Gaussian (mean, variance, input-output cross-covariance) give the
  joint Gaussian of :math:`(x, z)` for the update.

Everything is batched over leading dims (many priors at once), in the inputs' dtype and device.
The particle filter draws from a ``torch.Generator`` (on the CPU, so a seed gives the same particles on
every device) and resamples systematically.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Optional

import torch
from torch import Tensor

from dslearn.filters.gp_moments import GPPosterior


def jacobian(fn: Callable[[Tensor], Tensor], x: Tensor) -> Tensor:
    """Jacobian ``(*B, E, D)`` of ``fn`` (a map of one input ``(D,)`` to ``(E,)``, applied row-wise) at ``x``
    ``(*B, D)`` (``torch.func``: every batch entry differentiated on its own)."""
    D = x.shape[-1]
    flat = x.reshape(-1, D)
    J = torch.func.vmap(torch.func.jacrev(fn))(flat)
    return J.reshape(*x.shape[:-1], J.shape[-2], D)


@dataclass
class AdditiveModel:
    """A known function ``fn`` ``(*B, D) -> (*B, E)`` with constant additive Gaussian noise ``noise_cov``
    ``(E, E)``."""

    fn: Callable[[Tensor], Tensor]
    noise_cov: Tensor

    def mean(self, x: Tensor) -> Tensor:
        return self.fn(x)

    def noise(self, x: Tensor) -> Tensor:
        """The noise covariance ``(*B, E, E)`` at ``x`` (the same everywhere)."""
        return self.noise_cov.expand(*x.shape[:-1], *self.noise_cov.shape)

    def mean_noise(self, x: Tensor) -> tuple[Tensor, Tensor]:
        return self.mean(x), self.noise(x)


@dataclass
class GPModel:
    """Trained independent GPs as a model: mean = GP mean, noise = GP predictive variance (latent + noise)."""

    gp: GPPosterior

    def mean(self, x: Tensor) -> Tensor:
        return self.gp.mean(x)

    def noise(self, x: Tensor) -> Tensor:
        return torch.diag_embed(self.gp.variance(x, include_noise=True))

    def mean_noise(self, x: Tensor) -> tuple[Tensor, Tensor]:
        mean, var = self.gp.mean_variance(x, include_noise=True)
        return mean, torch.diag_embed(var)

    def moments(self, m: Tensor, S: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        return self.gp.moments(m, S, include_noise=True)


@dataclass
class StepResult:
    """One predict + update step: posterior, predicted state and predicted measurement (all Gaussian);
    ``ess``: the particle filter's effective sample size after the update (``None`` for Gaussian filters);
    ``particles``: its resampled particles ``(*B, N, D)``; ``cross``: the cross-covariance
    ``Cov[x, z]`` ``(*B, D, E)`` of the predicted state and measurement (for the statistical
    linear regression of :func:`slr_information`)."""

    mean: Tensor
    cov: Tensor
    pred_mean: Tensor
    pred_cov: Tensor
    z_mean: Tensor
    z_cov: Tensor
    ess: Optional[Tensor] = None
    particles: Optional[Tensor] = None
    cross: Optional[Tensor] = None


def _sym(P: Tensor) -> Tensor:
    return 0.5 * (P + P.transpose(-1, -2))


def gaussian_update(m_p: Tensor, P_p: Tensor, z_mean: Tensor, z_cov: Tensor, cross: Tensor, z: Tensor):
    """Posterior ``(mean, cov)`` from the joint Gaussian of ``(x, z)``: ``cross = Cov[x, z]`` ``(*B, D, E)``."""
    K = torch.linalg.solve(z_cov, cross.transpose(-1, -2)).transpose(-1, -2)  # C S^{-1} (S symmetric)
    mean = m_p + (K @ (z - z_mean).unsqueeze(-1)).squeeze(-1)
    cov = _sym(P_p - K @ z_cov @ K.transpose(-1, -2))
    return mean, cov


#: :func:`slr_information` floors the eigenvalues of the effective noise at this fraction of the mean variance of
#: the predicted measurement
SLR_FLOOR = 1e-12


def slr_information(m_p: Tensor, P_p: Tensor, z_mean: Tensor, z_cov: Tensor, cross: Tensor, z: Tensor,
                    floor: float = SLR_FLOOR) -> tuple[Tensor, Tensor, Tensor]:
    r"""A filter's measurement moments as novel information, by statistical linear regression.

    From the predicted state :math:`\mathcal N(m_p, P_p)` ``(*B, D)``, ``(*B, D, D)`` and the moments of the
    predicted measurement (``z_mean`` ``(*B, E)``, ``z_cov`` ``(*B, E, E)``, ``cross`` :math:`C = \mathrm{Cov}[x, z]`
    ``(*B, D, E)``): :math:`H = C^T P_p^{-1}`, :math:`R = S_z - H P_p H^T` (the part of the measurement's
    variance the linear fit does not explain), then for a measurement ``z`` ``(*A, *B, E)`` (leading dims
    ``*A``, e.g. the nodes): :math:`\delta\Omega = H^T R^{-1} H` ``(*B, D, D)`` and
    :math:`\delta q = H^T R^{-1} (z - \mu_z + H m_p)` ``(*A, *B, D)``. Added to the information of
    :math:`\mathcal N(m_p, P_p)` this gives exactly the Gaussian update of :func:`gaussian_update` (the
    matrix inversion lemma). :math:`R` is positive semidefinite for any valid joint covariance; where an
    eigenvalue is below ``floor`` times the mean diagonal of ``z_cov`` (rounding, or a joint covariance that is
    not positive definite) it is raised to that value, and ``clamped`` ``(*B,)`` marks those entries."""
    H = torch.linalg.solve(P_p, cross).transpose(-1, -2)              # (P^{-1} C)^T = C^T P^{-1} (P symmetric)
    R = _sym(z_cov - H @ P_p @ H.transpose(-1, -2))
    lo = floor * torch.diagonal(z_cov, dim1=-2, dim2=-1).mean(-1)     # (*B,)
    evals, V = torch.linalg.eigh(R)
    clamped = (evals < lo.unsqueeze(-1)).any(-1)
    if bool(clamped.any()):
        fixed = V @ torch.diag_embed(torch.maximum(evals, lo.unsqueeze(-1))) @ V.transpose(-1, -2)
        R = torch.where(clamped.unsqueeze(-1).unsqueeze(-1), _sym(fixed), R)
    RinvH = torch.linalg.solve(R, H)                                  # (*B, E, D)
    domega = _sym(H.transpose(-1, -2) @ RinvH)
    zbar = z - z_mean + (H @ m_p.unsqueeze(-1)).squeeze(-1)          # (*A, *B, E)
    dq = (RinvH.transpose(-1, -2) @ zbar.unsqueeze(-1)).squeeze(-1)  # R symmetric: H^T R^{-1} = (R^{-1} H)^T
    return dq, domega, clamped


def ekf_step(f, g, m: Tensor, P: Tensor, z: Tensor) -> StepResult:
    """EKF (true model) / GP-EKF (GP models): linearised means, the noise at the linearisation point."""
    F = jacobian(f.mean, m)
    m_p = f.mean(m)
    P_p = _sym(F @ P @ F.transpose(-1, -2) + f.noise(m))
    H = jacobian(g.mean, m_p)
    z_mean = g.mean(m_p)
    z_cov = _sym(H @ P_p @ H.transpose(-1, -2) + g.noise(m_p))
    cross = P_p @ H.transpose(-1, -2)
    mean, cov = gaussian_update(m_p, P_p, z_mean, z_cov, cross, z)
    return StepResult(mean, cov, m_p, P_p, z_mean, z_cov, cross=cross)


def sigma_points(m: Tensor, P: Tensor, alpha: float, beta: float, kappa: float):
    """Scaled symmetric sigma points ``(*B, 2D+1, D)`` and weights ``(2D+1,)`` (mean, covariance) of
    ``N(m, P)``: :math:`\\lambda = \\alpha^2 (D + \\kappa) - D`, points :math:`m \\pm \\sqrt{D + \\lambda} L_{:,i}`."""
    D = m.shape[-1]
    lam = alpha ** 2 * (D + kappa) - D
    L = torch.linalg.cholesky(P)
    c = math.sqrt(D + lam)
    offs = c * L.transpose(-1, -2)                                    # (*B, D, D): rows are columns of L
    X = torch.cat([m.unsqueeze(-2), m.unsqueeze(-2) + offs, m.unsqueeze(-2) - offs], dim=-2)
    wm = torch.full((2 * D + 1,), 0.5 / (D + lam), dtype=m.dtype, device=m.device)
    wm[0] = lam / (D + lam)
    wc = wm.clone()
    wc[0] = wm[0] + 1.0 - alpha ** 2 + beta
    return X, wm, wc


def unscented_transform(model, m: Tensor, P: Tensor, alpha: float, beta: float, kappa: float, noise: str):
    """Mean, covariance (with the model's noise) and input-output cross-covariance of ``model`` at
    ``N(m, P)`` by sigma points; ``noise``: ``mean`` (the noise at ``m``) or ``expected`` (its
    sigma-point average, mean weights)."""
    X, wm, wc = sigma_points(m, P, alpha, beta, kappa)
    Y = model.mean(X)                                                 # (*B, 2D+1, E)
    y = (wm.unsqueeze(-1) * Y).sum(-2)
    dY = Y - y.unsqueeze(-2)
    dX = X - m.unsqueeze(-2)
    cov = (wc.unsqueeze(-1).unsqueeze(-1) * dY.unsqueeze(-1) * dY.unsqueeze(-2)).sum(-3)
    cross = (wc.unsqueeze(-1).unsqueeze(-1) * dX.unsqueeze(-1) * dY.unsqueeze(-2)).sum(-3)
    if noise == "mean":
        R = model.noise(m)
    elif noise == "expected":
        R = (wm.unsqueeze(-1).unsqueeze(-1) * model.noise(X)).sum(-3)
    else:
        raise ValueError(f"noise={noise!r}; choose mean or expected")
    return y, _sym(cov + R), cross


def ukf_step(f, g, m: Tensor, P: Tensor, z: Tensor, alpha: float = 1.0, beta: float = 0.0, kappa: float = 2.0,
             noise: str = "mean") -> StepResult:
    """UKF (true model) / GP-UKF (GP models, ``noise="mean"``) / GP-UKF with moment matching
    (``noise="expected"``): sigma points redrawn from the predicted Gaussian for the update."""
    m_p, P_p, _ = unscented_transform(f, m, P, alpha, beta, kappa, noise)
    z_mean, z_cov, cross = unscented_transform(g, m_p, P_p, alpha, beta, kappa, noise)
    mean, cov = gaussian_update(m_p, P_p, z_mean, z_cov, cross, z)
    return StepResult(mean, cov, m_p, P_p, z_mean, z_cov, cross=cross)


def adf_step(f: GPModel, g: GPModel, m: Tensor, P: Tensor, z: Tensor) -> StepResult:
    """GP-ADF: exact moments of the transition GP at the prior, of the observation GP at the prediction."""
    m_p, P_p, _ = f.moments(m, P)
    z_mean, z_cov, cross = g.moments(m_p, P_p)
    mean, cov = gaussian_update(m_p, P_p, z_mean, z_cov, cross, z)
    return StepResult(mean, cov, m_p, P_p, z_mean, z_cov, cross=cross)


def _randn(shape, generator: torch.Generator, like: Tensor) -> Tensor:
    return torch.randn(shape, generator=generator, dtype=like.dtype, device=generator.device).to(like.device)


def systematic_resample(logw: Tensor, generator: torch.Generator) -> Tensor:
    """Indices ``(*B, N)`` of systematic resampling of normalised log weights ``(*B, N)`` (one uniform per
    batch entry from ``generator``)."""
    N = logw.shape[-1]
    cdf = torch.cumsum(torch.exp(logw), dim=-1)
    cdf = cdf / cdf[..., -1:]
    u0 = torch.rand(logw.shape[:-1], generator=generator, dtype=logw.dtype, device=generator.device).to(logw.device)
    u = (u0.unsqueeze(-1) + torch.arange(N, dtype=logw.dtype, device=logw.device)) / N
    idx = torch.searchsorted(cdf, u.contiguous(), right=True)
    return idx.clamp_(max=N - 1)


def _weighted_moments(x: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
    """Mean ``(*B, D)`` and covariance ``(*B, D, D)`` of particles ``x`` ``(*B, N, D)`` with weights ``(*B, N)``."""
    mean = (w.unsqueeze(-1) * x).sum(-2)
    d = x - mean.unsqueeze(-2)
    cov = (w.unsqueeze(-1).unsqueeze(-1) * d.unsqueeze(-1) * d.unsqueeze(-2)).sum(-3)
    return mean, _sym(cov)


def pf_step(f, g, m: Tensor, P: Tensor, z: Tensor, num_particles: int, generator: torch.Generator) -> StepResult:
    """Particle filter (true model) / GP-PF (GP models): particles from the prior, propagated by sampling
    ``N(f.mean(x), f.noise(x))``, weighted by ``N(z; g.mean(x'), g.noise(x'))``, resampled systematically.
    The Gaussian summaries are the particles' weighted moments (before resampling); the predicted
    measurement is the moment match of ``N(g.mean(x'), g.noise(x'))`` over the predicted particles, ``cross``
    the particles' covariance of ``x'`` and ``g.mean(x')`` (the measurement noise is independent of ``x'``)."""
    N = int(num_particles)
    D = m.shape[-1]
    shape = (*m.shape[:-1], N, D)
    x0 = m.unsqueeze(-2) + (torch.linalg.cholesky(P).unsqueeze(-3) @ _randn(shape, generator, m).unsqueeze(-1)).squeeze(-1)
    f0, Q = f.mean_noise(x0)                                           # (*B, N, D), (*B, N, D, D)
    x1 = f0 + (torch.linalg.cholesky(Q) @ _randn(shape, generator, m).unsqueeze(-1)).squeeze(-1)
    w0 = torch.full(x1.shape[:-1], 1.0 / N, dtype=m.dtype, device=m.device)
    pred_mean, pred_cov = _weighted_moments(x1, w0)
    gz, R = g.mean_noise(x1)                                           # (*B, N, E), (*B, N, E, E)
    z_mean, z_spread = _weighted_moments(gz, w0)
    z_cov = _sym(z_spread + R.mean(-3))
    dx, dz = x1 - pred_mean.unsqueeze(-2), gz - z_mean.unsqueeze(-2)
    cross = (w0.unsqueeze(-1).unsqueeze(-1) * dx.unsqueeze(-1) * dz.unsqueeze(-2)).sum(-3)  # noise: independent of x
    LR = torch.linalg.cholesky(R)
    r = torch.linalg.solve_triangular(LR, (z.unsqueeze(-2) - gz).unsqueeze(-1), upper=False).squeeze(-1)
    loglik = -0.5 * (r * r).sum(-1) - torch.log(torch.diagonal(LR, dim1=-2, dim2=-1)).sum(-1)
    logw = loglik - torch.logsumexp(loglik, dim=-1, keepdim=True)
    w = torch.exp(logw)
    mean, cov = _weighted_moments(x1, w)
    ess = 1.0 / (w * w).sum(-1)
    idx = systematic_resample(logw, generator)
    particles = torch.gather(x1, -2, idx.unsqueeze(-1).expand(*idx.shape, D))
    return StepResult(mean, cov, pred_mean, pred_cov, z_mean, z_cov, ess=ess, particles=particles, cross=cross)
