r"""Batched local GP experts (GPyTorch) over padded sliding windows.

Every expert is an exact zero-mean GP with an SE (RBF) kernel with one length scale per input
dimension (paper Eq. 26), one GP per coordinate. Experts are batched: the batch shape is
``(B, P, C, M)`` = (episodes, pipelines, coordinates, experts). The hyperparameters have batch
shape ``(B, P, C, 1)`` and are broadcast over the expert dimension, i.e. they are *shared by all
experts* of a pipeline (paper Sec. II-C).

Windows hold a varying number of points, so each expert's window is padded to ``W`` slots and a
0/1 mask is carried as the last input column. The masked prior covariance is

.. math::  \tilde K = (m m^\top) \odot K + \operatorname{diag}(1 - m),

so padded slots are decoupled unit-variance dummies with target 0. The likelihood then adds the
noise ``\sigma^2`` to every slot, hence each padded slot contributes exactly
``-\tfrac12 \log(2\pi(1+\sigma^2))`` to the GPyTorch log marginal likelihood; this constant is
added back so :func:`expert_log_marginal_likelihood` is the exact Eq. 14 of the observed points.
Predictions are unaffected by padding (zero cross-covariance with the test points).
"""

from __future__ import annotations

import math
import warnings

import gpytorch
import torch
from linear_operator import to_linear_operator
from torch import Tensor

from dslearn.models.kernels import se_kernel


def _exp_positive(lower: float = 0.0):
    """Constraint ``lower + exp(raw)``: optimisation in log space (scales differ by 1e4)."""
    if lower > 0:
        return gpytorch.constraints.GreaterThan(lower, transform=torch.exp, inv_transform=torch.log)
    return gpytorch.constraints.Positive(transform=torch.exp, inv_transform=torch.log)


class Hypers(torch.nn.Module):
    r"""Shared SE-kernel hyperparameters + Gaussian likelihood for a batch of GPs.

    Args:
        batch_shape: hyperparameter batch shape, e.g. ``(B, P, C, 1)`` (the trailing 1 broadcasts
            over experts).
        dim: input dimension ``d`` (1 temporal, 3 spatio-temporal).
        outputscale: initial amplitude :math:`\sigma_m^2` (Eq. 26).
        lengthscale: initial length scales, length ``d``.
        noise: initial noise variance :math:`\sigma^2` (Eq. 4).
        min_noise: lower bound of the noise variance.
    """

    def __init__(self, batch_shape, dim, outputscale, lengthscale, noise, min_noise=1e-4,
                 dtype=torch.float64, device="cpu"):
        super().__init__()
        batch_shape = torch.Size(batch_shape)
        self.dim = dim
        base = gpytorch.kernels.RBFKernel(ard_num_dims=dim, batch_shape=batch_shape,
                                          lengthscale_constraint=_exp_positive())
        self.kernel = gpytorch.kernels.ScaleKernel(base, batch_shape=batch_shape,
                                                   outputscale_constraint=_exp_positive())
        self.likelihood = gpytorch.likelihoods.GaussianLikelihood(
            batch_shape=batch_shape, noise_constraint=_exp_positive(min_noise))
        self.to(dtype=dtype, device=device)
        ls = torch.as_tensor(lengthscale, dtype=dtype, device=device).reshape(dim)
        self.kernel.base_kernel.lengthscale = ls.expand(*batch_shape, 1, dim).clone()
        self.kernel.outputscale = torch.full(batch_shape, float(outputscale), dtype=dtype, device=device)
        self.likelihood.noise = torch.full((*batch_shape, 1), float(noise), dtype=dtype, device=device)

    @property
    def outputscale(self) -> Tensor:
        """Prior variance :math:`\\sigma_{**}^2` of f, shape = batch_shape."""
        return self.kernel.outputscale

    @property
    def noise(self) -> Tensor:
        """Noise variance, shape = batch_shape."""
        return self.likelihood.noise[..., 0]

    @property
    def lengthscale(self) -> Tensor:
        """Length scales, shape ``(*batch_shape, d)``."""
        return self.kernel.base_kernel.lengthscale[..., 0, :]

    def raw_state(self) -> list[Tensor]:
        return [p.detach().clone() for p in self.parameters()]

    def restore_where(self, old: list[Tensor], keep_new: Tensor) -> None:
        """Undo the last update for batch elements with ``keep_new`` False. keep_new: (B,) bool."""
        with torch.no_grad():
            for p, o in zip(self.parameters(), old):
                k = keep_new.reshape(-1, *([1] * (p.dim() - 1)))
                p.copy_(torch.where(k, p, o))


class MaskedExactGP(gpytorch.models.ExactGP):
    """Zero-mean exact GP over padded windows; the last input column is the 0/1 slot mask.

    Args:
        train_x: ``(*batch, W, d + 1)``; train_y: ``(*batch, W)`` (0 at padded slots).
        hypers: :class:`Hypers` whose batch shape broadcasts against ``batch``.
    """

    def __init__(self, train_x: Tensor, train_y: Tensor, hypers: Hypers):
        super().__init__(train_x, train_y, hypers.likelihood)
        self.hypers = hypers

    def forward(self, x: Tensor) -> gpytorch.distributions.MultivariateNormal:
        mask = x[..., -1]
        k = self.hypers.kernel(x[..., :-1]).to_dense()
        k = k * (mask.unsqueeze(-1) * mask.unsqueeze(-2)) + torch.diag_embed(1.0 - mask)
        k = 0.5 * (k + k.mT)
        return gpytorch.distributions.MultivariateNormal(torch.zeros_like(mask), to_linear_operator(k))


def with_mask(x: Tensor, mask: Tensor) -> Tensor:
    """Append the mask as last input column. x: (..., W, d), mask: (..., W) -> (..., W, d+1)."""
    return torch.cat([x, mask.to(x.dtype).unsqueeze(-1)], dim=-1)


def expert_log_marginal_likelihood(hypers: Hypers, x: Tensor, z: Tensor, mask: Tensor) -> Tensor:
    """Per-expert log marginal likelihood (Eq. 14) of the observed slots, via GPyTorch.

    Args:
        hypers: shared hyperparameters, batch shape broadcastable to ``batch``.
        x: inputs ``(*batch, W, d)``; z: targets ``(*batch, W)``; mask: ``(*batch, W)`` bool.

    Returns:
        ``(*batch,)`` exact :math:`\\log p_i(z^{(i)} | X^{(i)}, \\theta)`; 0 for an empty window.
    """
    m = mask.to(x.dtype)
    xm = with_mask(x, m)
    zm = z * m
    model = MaskedExactGP(xm, zm, hypers)
    model.train()
    mll = gpytorch.mlls.ExactMarginalLogLikelihood(hypers.likelihood, model)
    w = z.shape[-1]
    val = mll(model(xm), zm) * w  # undo GPyTorch's division by the number of slots
    noise = hypers.likelihood.noise  # (*hb, 1) -> broadcast over batch
    n_pad = (1.0 - m).sum(-1)
    return val + 0.5 * n_pad * torch.log(2 * math.pi * (1.0 + noise[..., 0]))


def factorised_log_marginal_likelihood(hypers: Hypers, x: Tensor, z: Tensor, mask: Tensor) -> Tensor:
    """Factorised log marginal likelihood, Eq. 15: sum of local ones over experts (dim -2 of x's batch).

    Args: as :func:`expert_log_marginal_likelihood` with batch ``(..., M)``.

    Returns:
        ``(...,)`` sum over the M experts (experts with empty windows contribute 0).
    """
    return expert_log_marginal_likelihood(hypers, x, z, mask).sum(-1)


def _chol_jitter(sig: Tensor, scale: Tensor) -> Tensor:
    """Batched Cholesky; only the matrices where it fails get jitter ``1e-6 * scale`` (and a
    warning), so one batch element never changes another's result."""
    chol, info = torch.linalg.cholesky_ex(sig)
    bad = info > 0
    if bool(bad.any()):
        warnings.warn(f"DGPT: Cholesky failed for {int(bad.sum())} matrices, adding jitter "
                      "1e-6 * outputscale to those", RuntimeWarning)
        eye = torch.eye(sig.shape[-1], dtype=sig.dtype, device=sig.device)
        jit = torch.where(bad, 1e-6 * scale, torch.zeros_like(scale))
        chol = torch.where(bad[..., None, None], torch.linalg.cholesky(sig + jit[..., None, None] * eye), chol)
    return chol


@torch.no_grad()
def predict_latent(hypers: Hypers, x: Tensor, z: Tensor, mask: Tensor, x_test: Tensor):
    """Posterior of the latent f at test inputs (Eqs. 5-6), batched over experts.

    The covariances come from the GPyTorch kernel; the solve is a batched Cholesky (cheaper than
    building GPyTorch prediction caches for every step). Padded slots are exactly decoupled.

    Args:
        x: ``(*batch, W, d)``, z, mask: ``(*batch, W)``, x_test: ``(*batch, Q, d)``.

    Returns:
        mean, var: ``(*batch, Q)``; var clamped to ``[1e-12, outputscale]``.
    """
    m = mask.to(x.dtype)
    k = hypers.kernel(x).to_dense()
    k = k * (m.unsqueeze(-1) * m.unsqueeze(-2)) + torch.diag_embed(1.0 - m)
    noise = hypers.likelihood.noise.unsqueeze(-1)  # (*hb, 1, 1)
    sig = k + noise * torch.eye(x.shape[-2], dtype=x.dtype, device=x.device)
    sig = 0.5 * (sig + sig.mT)
    chol = _chol_jitter(sig, hypers.outputscale.expand(sig.shape[:-2]))
    ks = hypers.kernel(x, x_test).to_dense() * m.unsqueeze(-1)  # (*batch, W, Q)
    alpha = torch.cholesky_solve((z * m).unsqueeze(-1), chol)  # (*batch, W, 1)
    mean = (ks * alpha).sum(-2)
    v = torch.linalg.solve_triangular(chol, ks, upper=False)
    prior = hypers.outputscale.unsqueeze(-1)
    var = prior - (v ** 2).sum(-2)
    var = torch.minimum(var.clamp_min(1e-12), prior.expand_as(var))
    return mean, var


@torch.no_grad()
def predict_latent_slice(hypers: Hypers, index: int, x: Tensor, z: Tensor, mask: Tensor,
                         x_test: Tensor):
    r""":func:`predict_latent` for ONE pipeline ``index`` of hyperparameters with batch shape
    ``(B, P, C, 1)`` (used by grBCM, whose augmented experts exist in one pipeline only).

    Same SE kernel, written out (:math:`\sigma_m^2\exp(-\tfrac12\|(a-b)/\ell\|^2)`, equal to
    GPyTorch's ``ScaleKernel(RBFKernel)``, tested), Cholesky solve with jitter fallback.

    Args:
        x: ``(B, C, M, W, d)``, z, mask: ``(B, C, M, W)``, x_test: ``(B, C, M, Q, d)``.

    Returns:
        mean, var ``(B, C, M, Q)``.
    """
    ls = hypers.lengthscale[:, index]          # (B, C, 1, d)
    os_ = hypers.outputscale[:, index]         # (B, C, 1)
    noise = hypers.noise[:, index]             # (B, C, 1)
    ls = ls.unsqueeze(-2)                      # (B, C, 1, 1, d)

    def k(a, b):
        return se_kernel(a, b, ls, os_[..., None, None])

    m = mask.to(x.dtype)
    kk = k(x, x) * (m.unsqueeze(-1) * m.unsqueeze(-2)) + torch.diag_embed(1.0 - m)
    eye = torch.eye(x.shape[-2], dtype=x.dtype, device=x.device)
    sig = kk + noise[..., None, None] * eye
    sig = 0.5 * (sig + sig.mT)
    chol = _chol_jitter(sig, os_.expand(sig.shape[:-2]))
    ks = k(x, x_test) * m.unsqueeze(-1)
    alpha = torch.cholesky_solve((z * m).unsqueeze(-1), chol)
    mean = (ks * alpha).sum(-2)
    v = torch.linalg.solve_triangular(chol, ks, upper=False)
    prior = os_.unsqueeze(-1)
    var = torch.minimum((prior - (v ** 2).sum(-2)).clamp_min(1e-12), prior.expand_as(mean))
    return mean, var


def closed_form_gp(x: Tensor, z: Tensor, x_test: Tensor, outputscale, lengthscale, noise):
    """Plain-torch reference GP (Eqs. 5, 6, 14) for one data set — used by the tests.

    Args:
        x: (n, d), z: (n,), x_test: (q, d); lengthscale: (d,).

    Returns:
        mean (q,), latent var (q,), log marginal likelihood (scalar).
    """
    ls = torch.as_tensor(lengthscale, dtype=x.dtype)

    def k(a, b):
        d2 = (((a[:, None, :] - b[None, :, :]) / ls) ** 2).sum(-1)
        return outputscale * torch.exp(-0.5 * d2)

    n = x.shape[0]
    sig = k(x, x) + noise * torch.eye(n, dtype=x.dtype)
    chol = torch.linalg.cholesky(sig)
    alpha = torch.cholesky_solve(z[:, None], chol)[:, 0]
    ks = k(x, x_test)
    mean = ks.T @ alpha
    v = torch.linalg.solve_triangular(chol, ks, upper=False)
    var = outputscale - (v ** 2).sum(0)
    lml = -0.5 * z @ alpha - torch.log(torch.diagonal(chol)).sum() - 0.5 * n * math.log(2 * math.pi)
    return mean, var, lml
