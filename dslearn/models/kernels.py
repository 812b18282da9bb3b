r"""The squared-exponential kernel, the one copy every GP of the package evaluates.

:math:`k(a, b) = \sigma_f^2 \exp\left(-\tfrac12 \|(a - b) / \ell\|^2\right)`: GPyTorch's
``ScaleKernel(RBFKernel)`` (ARD where :math:`\ell` has one entry per input dimension), written out for the per-step
hot paths, which read its hyperparameters as plain tensors (equality with GPyTorch is tested). Used by the exact and
the sparse online GPs (:mod:`dslearn.models.gp_backends`), Liu's DGPT experts and their hyperparameter search
(:mod:`dslearn.filters.dgpt`), the GP-ADF moments (:mod:`dslearn.filters.gp_moments`), the GP that learns through
the filter (:mod:`dslearn.learning.backprop`) and the forecasts (:mod:`dslearn.forecast`).

The scaled squared distance :math:`\|(a - b)/\ell\|^2` is formed in one of two ways, each where its numbers are
relied on: :func:`sq_dist` through :func:`torch.cdist` (matmul-based for large inputs, no ``(Na, Nb, d)`` tensor),
and :func:`sq_dist_inner` by inner products clamped at 0 (differentiable where ``a = b``, where the distance's
gradient is not). Where the per-dimension terms are needed (derivatives with respect to the length scales, the
ADF's moments), the caller forms them and hands their sum to :func:`se`.
"""

from __future__ import annotations

import torch
from torch import Tensor


def se(sq_dist: Tensor, outputscale: Tensor | float) -> Tensor:
    r""":math:`\sigma_f^2 \exp(-\tfrac12 d^2)` of scaled squared distances ``d^2`` (``outputscale`` broadcast)."""
    return outputscale * torch.exp(-0.5 * sq_dist)


def sq_dist(a: Tensor, b: Tensor, lengthscale: Tensor | float) -> Tensor:
    r""":math:`\|(a - b)/\ell\|^2` for ``a (*B, Na, d)``, ``b (*B, Nb, d)`` -> ``(*B, Na, Nb)`` through
    :func:`torch.cdist` (``lengthscale`` broadcast against the inputs: ``(*B, 1, 1)`` or ``(*B, 1, d)``)."""
    return torch.cdist(a / lengthscale, b / lengthscale).pow(2)


def sq_dist_inner(a: Tensor, b: Tensor, lengthscale: Tensor | float) -> Tensor:
    r""":math:`\|(a - b)/\ell\|^2` as :func:`sq_dist`, by inner products
    :math:`\|a'\|^2 + \|b'\|^2 - 2 a'^\top b'` clamped at 0 (differentiable where ``a = b``)."""
    a, b = a / lengthscale, b / lengthscale
    d2 = (a * a).sum(-1).unsqueeze(-1) + (b * b).sum(-1).unsqueeze(-2) - 2 * a @ b.transpose(-1, -2)
    return d2.clamp_min(0.0)


def se_kernel(a: Tensor, b: Tensor, lengthscale: Tensor | float, outputscale: Tensor | float) -> Tensor:
    """The kernel matrix ``(*B, Na, Nb)`` of ``a (*B, Na, d)`` and ``b (*B, Nb, d)`` (:func:`sq_dist`, :func:`se`)."""
    return se(sq_dist(a, b, lengthscale), outputscale)
