r"""Gaussian messages of the identification factor graph (Jiang et al., ISITA 2022, Sec. III-A).

Sensor ``n`` gives the linearised observation (Eqs. 6-7)

.. math::  y_n \approx \sum_m \lambda_{n,m} x_m + \gamma_n + u_n, \qquad u_n \sim \mathcal N(0, s_n),

with :math:`\lambda_{n,m} = \partial h_n / \partial x_m` and
:math:`\gamma_n = h_n(\beta) - \sum_m \lambda_{n,m}\beta_m` at the expansion point
:math:`\beta` (Eqs. 8-9). The downward message :math:`\zeta_{n\to m}` (Eqs. 11-12) and the
upward message :math:`\rho_{m\to n}` (Eqs. 13-14) are Gaussian-BP messages on this graph.

The paper writes Eqs. 11-12 in moment form, dividing by :math:`\lambda_{n,m}`. Here they are
computed in natural (information) form,

.. math::  \tau_{n\to m} = \frac{\lambda_{n,m}^2}{V_{n,m}},\qquad
           \kappa_{n\to m} = \frac{\lambda_{n,m} r_{n,m}}{V_{n,m}},

with :math:`r_{n,m} = y_n - \gamma_n - \sum_{m'\ne m}\lambda_{n,m'} m_{\rho_{m'\to n}}` and
:math:`V_{n,m} = s_n + \sum_{m'\ne m}\lambda_{n,m'}^2 \sigma^2_{\rho_{m'\to n}}`. This is the same
message (mean :math:`\kappa/\tau = r/\lambda`, variance :math:`1/\tau = V/\lambda^2`) but never
divides by :math:`\lambda`: a sensor with :math:`\lambda_{n,m}=0` sends a flat message to
:math:`x_m` (precision 0), i.e. it is skipped for that parameter.

Shapes: ``B`` any batch dims, ``N`` sensors, ``M`` parameters.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from dslearn.types import batch_jacobian


class LinearMeasurement:
    """A measurement function linear in the parameters, ``h(x) = slopes x + offset``: its Taylor coefficients
    (Eqs. 8-9) are its own, at any point (:func:`linearize` reads them instead of differentiating ``N`` outputs).

    Args:
        slopes: ``(N, M)``; offset: ``(N,)`` (``None``: zero).
    """

    def __init__(self, slopes: Tensor, offset: Tensor | None = None):
        self.slopes = slopes.detach()
        self.offset = torch.zeros_like(self.slopes[:, 0]) if offset is None else offset.detach()

    def __call__(self, x: Tensor) -> Tensor:
        return x @ self.slopes.T + self.offset


def linearize(h: Callable[[Tensor], Tensor], beta: Tensor) -> tuple[Tensor, Tensor]:
    """First-order Taylor coefficients of ``h`` at ``beta`` by autograd (Eqs. 6-9); a
    :class:`LinearMeasurement` gives its own.

    Args:
        h: row-wise measurement function ``(*B, M) -> (*B, N)``.
        beta: expansion point ``(*B, M)``.

    Returns:
        ``lam (*B, N, M)`` (Eq. 8) and ``gamma (*B, N)`` (Eq. 9).
    """
    if isinstance(h, LinearMeasurement):
        n, m = h.slopes.shape
        return (h.slopes.to(beta).expand(*beta.shape[:-1], n, m),
                h.offset.to(beta).expand(*beta.shape[:-1], n))
    lam = batch_jacobian(h, beta)
    with torch.no_grad():
        h0 = h(beta.detach())
    gamma = h0 - (lam @ beta.detach().unsqueeze(-1)).squeeze(-1)
    return lam.detach(), gamma.detach()


def zeta_natural(
    lam: Tensor, y_mean: Tensor, y_var: Tensor, gamma: Tensor, rho_mean: Tensor, rho_var: Tensor
) -> tuple[Tensor, Tensor]:
    """Downward messages :math:`\\zeta_{n\\to m}` (Eqs. 11-12) in natural form.

    Args:
        lam: ``(*B, N, M)`` Taylor slopes.
        y_mean, y_var: ``(*B, N)`` measurement-node message (sensor mean and its variance).
        gamma: ``(*B, N)`` Taylor offsets.
        rho_mean, rho_var: ``(*B, N, M)`` upward messages :math:`\\rho_{m\\to n}` (indexed [n, m]).

    Returns:
        ``(precision, information)``, each ``(*B, N, M)``: :math:`1/\\sigma^2_\\zeta` and
        :math:`m_\\zeta/\\sigma^2_\\zeta`.
    """
    pred = lam * rho_mean                       # lambda_{n,m'} m_rho_{m'->n}
    spread = lam.square() * rho_var             # lambda_{n,m'}^2 var_rho_{m'->n}
    # leave-one-out sums over m' != m (explicit, no "total minus self" cancellation)
    M = lam.shape[-1]
    off = 1.0 - torch.eye(M, dtype=lam.dtype, device=lam.device)
    # (broadcast-and-sum rather than tiny batched matmuls: much faster on CPU)
    resid = (y_mean - gamma).unsqueeze(-1) - (pred.unsqueeze(-1) * off).sum(-2)   # r_{n,m}
    V = y_var.unsqueeze(-1) + (spread.unsqueeze(-1) * off).sum(-2)                 # V_{n,m}
    return lam.square() / V, lam * resid / V


def zeta_moment(
    lam: Tensor, y_mean: Tensor, y_var: Tensor, gamma: Tensor, rho_mean: Tensor, rho_var: Tensor
) -> tuple[Tensor, Tensor]:
    """The paper's literal moment form of Eqs. 11-12 (divides by lambda; for reference/tests).

    Shapes as :func:`zeta_natural`; returns ``(mean, var)`` ``(*B, N, M)``.
    """
    M = lam.shape[-1]
    off = 1.0 - torch.eye(M, dtype=lam.dtype, device=lam.device)
    mean = y_mean.unsqueeze(-1) / lam - ((lam * rho_mean) @ off) / lam - gamma.unsqueeze(-1) / lam
    var = y_var.unsqueeze(-1) / lam.square() + ((lam.square() * rho_var) @ off) / lam.square()
    return mean, var


def rho_from_zeta(
    zeta_prec: Tensor, zeta_info: Tensor, prior_prec: Tensor | float = 0.0, prior_info: Tensor | float = 0.0,
    min_precision: float = 1e-12,
) -> tuple[Tensor, Tensor, Tensor]:
    """Upward messages :math:`\\rho_{m\\to n}` (Eqs. 13-14): product of the other sensors' zetas.

    Args:
        zeta_prec, zeta_info: ``(*B, N, M)`` natural parameters of :math:`\\zeta_{n\\to m}`.
        prior_prec, prior_info: optional prior on each :math:`x_m` (``(*B, M)`` or scalar;
            0 = the paper's flat prior).
        min_precision: floor applied where no other sensor informs :math:`x_m`.

    Returns:
        ``rho_mean (*B, N, M)``, ``rho_var (*B, N, M)`` and ``floored (*B, N, M)`` (bool).
    """
    N = zeta_prec.shape[-2]
    loo = 1.0 - torch.eye(N, dtype=zeta_prec.dtype, device=zeta_prec.device)  # n' != n
    prec = (loo[..., None] * zeta_prec.unsqueeze(-3)).sum(-2) + (prior_prec.unsqueeze(-2) if isinstance(prior_prec, Tensor) else prior_prec)
    info = (loo[..., None] * zeta_info.unsqueeze(-3)).sum(-2) + (prior_info.unsqueeze(-2) if isinstance(prior_info, Tensor) else prior_info)
    floored = prec < min_precision
    prec = torch.where(floored, torch.full_like(prec, min_precision), prec)
    return info / prec, 1.0 / prec, floored


def marginal(
    zeta_prec: Tensor, zeta_info: Tensor, prior_prec: Tensor | float = 0.0, prior_info: Tensor | float = 0.0,
    min_precision: float = 1e-12,
) -> tuple[Tensor, Tensor, Tensor]:
    """Estimation-node marginals (Eqs. 15-16): product of all sensors' zetas.

    Returns ``mean (*B, M)``, ``var (*B, M)``, ``floored (*B, M)`` (bool).
    """
    prec = zeta_prec.sum(-2) + prior_prec
    info = zeta_info.sum(-2) + prior_info
    floored = prec < min_precision
    prec = torch.where(floored, torch.full_like(prec, min_precision), prec)
    return info / prec, 1.0 / prec, floored
