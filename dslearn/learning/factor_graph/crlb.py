r"""Cramer-Rao bound of the snapshot identification (Jiang et al. 2022, Appendix, Eqs. 27-33).

With ``L`` i.i.d. samples per sensor, :math:`\hat y_{n,l} = h_n(x) + u`, :math:`u\sim\mathcal N(0,\sigma_y^2)`,
the Fisher information is (Eq. 31)

.. math::  F(x) = \frac{L}{\sigma_y^2} J^T J,\qquad J = \partial h / \partial x \;(N\times M)\;\text{(Eq. 32)},

and the per-parameter bound is :math:`\mathrm{CRLB} = \mathrm{tr}[F^{-1}]/M` (Eq. 27).

Eq. 33 of the paper writes :math:`\{\mathrm{tr}[F]\}^{-1}/M` instead, which is *not* Eq. 27
(it is smaller by about a factor M^2 / condition); ``form="paper_eq33"`` reproduces it.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from dslearn.errors import ConfigError, check_choice
from dslearn.types import batch_jacobian, symmetrize
from dslearn.linalg import cholesky, cholesky_solve

CRLB_FORMS = ("trace_inverse", "paper_eq33")


def fisher_information(jac: Tensor, sigma_y: Tensor | float, num_samples: int) -> Tensor:
    """Eq. 31: ``F = L / sigma_y^2 * J^T J``.

    Args:
        jac: ``(*B, N, M)`` Jacobian of ``h`` (Eq. 32).
        sigma_y: per-sample noise std, scalar or ``(*B,)``.
        num_samples: ``L``, samples per sensor.

    Returns:
        ``(*B, M, M)``.
    """
    if int(num_samples) < 1:
        raise ConfigError(f"num_samples={num_samples!r} must be >= 1")
    sigma_y = torch.as_tensor(sigma_y, dtype=jac.dtype, device=jac.device)
    if not bool((sigma_y > 0).all()):
        raise ConfigError(f"sigma_y={sigma_y.tolist()!r} must be > 0")
    scale = (num_samples / sigma_y.square())[..., None, None]
    return symmetrize(scale * (jac.transpose(-1, -2) @ jac))


def crlb_from_fisher(fim: Tensor, form: str = "trace_inverse") -> Tensor:
    """Per-parameter variance bound from the FIM ``(*B, M, M) -> (*B,)`` (Eq. 27 or Eq. 33).

    A singular FIM (an unobservable parameter) gives ``inf``.
    """
    check_choice("task.crlb_form", form, CRLB_FORMS)
    M = fim.shape[-1]
    if form == "paper_eq33":
        return 1.0 / (M * fim.diagonal(dim1=-2, dim2=-1).sum(-1))
    # a small ridge keeps the factorisation finite; singular cases are flagged below
    d0 = fim.diagonal(dim1=-2, dim2=-1)
    eye = torch.eye(M, dtype=fim.dtype, device=fim.device)
    ridge = (torch.finfo(fim.dtype).eps * d0.abs().amax(-1).clamp_min(torch.finfo(fim.dtype).tiny))[..., None, None]
    chol = cholesky(fim + ridge * eye)
    inv = cholesky_solve(eye.expand_as(fim), chol)
    out = inv.diagonal(dim1=-2, dim2=-1).sum(-1) / M
    d = chol.diagonal(dim1=-2, dim2=-1).abs()
    # numerically singular: pivots span more than ~1/sqrt(1e3 eps)
    singular = (d.amin(-1) / d.amax(-1).clamp_min(torch.finfo(d.dtype).tiny)).square() < 1e3 * torch.finfo(d.dtype).eps
    return torch.where(singular, torch.full_like(out, float("inf")), out)


def crlb(
    h: Callable[[Tensor], Tensor], x: Tensor, sigma_y: Tensor | float, num_samples: int, form: str = "trace_inverse"
) -> Tensor:
    """Per-parameter CRLB (variance) at ``x (*B, M)`` for measurement function ``h``. Returns ``(*B,)``."""
    return crlb_from_fisher(fisher_information(batch_jacobian(h, x), sigma_y, num_samples), form)
