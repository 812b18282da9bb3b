r"""Metrics of one Gaussian filter step against the truth (Deisenroth et al., ICML 2009, Sec. 5).

Per case (batch entry), for a posterior :math:`\mathcal N(m, P)` of the true state :math:`x` and a
predicted measurement distribution :math:`\mathcal N(\mu_z, S_z)` of the measurement :math:`z`:

* ``nll_x`` :math:`= -\log \mathcal N(x; m, P)`;
* ``maha_x`` :math:`= \sqrt{(x - m)^T P^{-1} (x - m)}` (the Mahalanobis distance, not squared);
* ``rmse_x`` :math:`= \sqrt{\lVert x - m \rVert^2 / D}` (one case: the root of the mean square over the
  state's components);
* ``nll_z`` :math:`= -\log \mathcal N(z; \mu_z, S_z)`.

A posterior covariance that is not positive definite (a particle filter whose weight sits on one
particle) gives ``inf`` for ``nll_x`` and ``maha_x``: reported as it is, never floored.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def _residual(x: Tensor, mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
    """Whitened residual ``L^{-1}(x - mean)`` and ``log|cov|/2``; ``inf`` where ``cov`` is not positive definite."""
    L, info = torch.linalg.cholesky_ex(cov)
    bad = info != 0
    eye = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
    L = torch.where(bad.unsqueeze(-1).unsqueeze(-1), eye, L)
    r = torch.linalg.solve_triangular(L, (x - mean).unsqueeze(-1), upper=False).squeeze(-1)
    r = torch.where(bad.unsqueeze(-1), torch.full_like(r, math.inf), r)
    half_logdet = torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
    return r, half_logdet


def gaussian_nll(x: Tensor, mean: Tensor, cov: Tensor) -> Tensor:
    """``-log N(x; mean, cov)`` ``(*B,)`` for ``x``, ``mean`` ``(*B, D)``, ``cov`` ``(*B, D, D)``."""
    r, half_logdet = _residual(x, mean, cov)
    return 0.5 * (r * r).sum(-1) + half_logdet + 0.5 * x.shape[-1] * math.log(2 * math.pi)


def mahalanobis(x: Tensor, mean: Tensor, cov: Tensor) -> Tensor:
    """``sqrt((x - mean)^T cov^{-1} (x - mean))`` ``(*B,)``."""
    r, _ = _residual(x, mean, cov)
    return (r * r).sum(-1).sqrt()


def rmse(x: Tensor, mean: Tensor) -> Tensor:
    """``sqrt(mean over components of (x - mean)^2)`` ``(*B,)``."""
    return (x - mean).pow(2).mean(-1).sqrt()


def filter_step_metrics(x: Tensor, mean: Tensor, cov: Tensor, z: Tensor, z_mean: Tensor, z_cov: Tensor) -> dict[str, Tensor]:
    """The four metrics of the module docstring, each ``(*B,)``."""
    return {"nll_x": gaussian_nll(x, mean, cov), "maha_x": mahalanobis(x, mean, cov), "rmse_x": rmse(x, mean),
            "nll_z": gaussian_nll(z, z_mean, z_cov)}
