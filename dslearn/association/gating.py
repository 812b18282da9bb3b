r"""Gating by the predicted measurement covariance: a detection ``z`` lies in track ``i``'s gate when its
squared Mahalanobis distance :math:`\nu^T S^{-1} \nu` (:math:`\nu = z - \hat z`, :math:`S = H P H^T + R`) is at
most the chi-square quantile of the gate probability :math:`P_G` with ``Dz`` degrees of freedom."""

from __future__ import annotations

import math

import torch
from scipy.stats import chi2
from torch import Tensor

from dslearn.errors import ConfigError, _number


def check_probability(field: str, value, *, closed: bool = True) -> float:
    """``value`` as a float in (0, 1] (or (0, 1) when not ``closed``), else :class:`ConfigError` naming ``field``."""
    v = _number(field, value)
    if not (0 < v < 1 or (closed and v == 1)):
        raise ConfigError(f"{field}={value!r} must be in (0, 1{']' if closed else ')'}")
    return v


def gate_threshold(gate_probability: float, dim: int) -> float:
    """The chi-square quantile of ``gate_probability`` with ``dim`` degrees of freedom (inf at 1: no gate)."""
    p = check_probability("gate_probability", gate_probability)
    return math.inf if p == 1 else float(chi2.ppf(p, dim))


def mahalanobis2(nu: Tensor, s: Tensor) -> Tensor:
    r""":math:`\nu^T S^{-1} \nu` for innovations ``nu (T, M, Dz)`` and covariances ``s (T, Dz, Dz)``: ``(T, M)``."""
    sol = torch.linalg.solve(s.unsqueeze(1).expand(*nu.shape, nu.shape[-1]), nu.unsqueeze(-1)).squeeze(-1)
    return (nu * sol).sum(-1)


def gate(d2: Tensor, dim: int, gate_probability: float, present: Tensor | None = None) -> Tensor:
    """The pairs inside the gate, ``(T, M)`` bool, from squared distances ``d2 (T, M)`` of ``dim``-dimensional
    measurements; detections not ``present (M,)`` are in no gate."""
    inside = d2 <= gate_threshold(gate_probability, dim)
    return inside if present is None else inside & present.to(torch.bool).unsqueeze(0)
