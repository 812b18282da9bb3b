r"""The associator interface and what every associator shares: the predicted measurement of each track
(:math:`\hat z = h(\hat x)`, :math:`H = \partial h / \partial x`, :math:`S = H P H^T + R`), the Kalman update
of a track by one detection, and the result of an association.

Shapes: ``T`` tracks with states ``mean (T, n)``, ``cov (T, n, n)``; ``M`` detections ``(M, Dz)`` with an
optional presence mask ``(M,)`` (a padded set). Everything is computed in float64.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import torch
from torch import Tensor

from dslearn.errors import ConfigError
from dslearn.models.base import ObservationModel

DTYPE = torch.float64


@dataclass(frozen=True)
class MeasurementPrediction:
    """Each track's predicted measurement: ``z (T, Dz)``, ``H (T, Dz, n)``, ``R (T, Dz, Dz)``,
    ``S = H P H^T + R (T, Dz, Dz)``."""

    z: Tensor
    H: Tensor
    R: Tensor
    S: Tensor


@dataclass(frozen=True)
class Association:
    r"""The association of ``M`` detections to ``T`` tracks and the tracks it updated.

    Attributes:
        weights: ``(T, M)``: the probability that detection ``j`` is track ``i``'s (0/1 for an assignment);
        missed: ``(T,)``: the probability that track ``i`` was not detected (each row of ``weights`` and its
            ``missed`` add up to 1);
        assigned: ``(T,)`` int64: the detection of each track's most probable hypothesis, -1 for missed;
        gated: ``(T, M)`` bool: the pairs inside the gate;
        unassigned: ``(M,)`` bool: present detections that no track took (GNN: assigned to none; JPDA: in no
            track's gate): what track initiation starts from;
        mean, cov: ``(T, n)``, ``(T, n, n)``: the updated tracks.
    """

    weights: Tensor
    missed: Tensor
    assigned: Tensor
    gated: Tensor
    unassigned: Tensor
    mean: Tensor
    cov: Tensor


@runtime_checkable
class Associator(Protocol):
    """Associates a set of detections to predicted tracks and updates them."""

    def associate(self, mean: Tensor, cov: Tensor, observation: ObservationModel, detections: Tensor,
                  present: Tensor | None = None) -> Association:
        """``mean (T, n)``, ``cov (T, n, n)``: the predicted tracks; ``detections (M, Dz)``; ``present (M,)``."""
        ...


def check_inputs(mean: Tensor, cov: Tensor, detections: Tensor, present: Tensor | None):
    """The inputs in float64 with their shapes checked, and the presence mask (default: all present)."""
    mean, cov, det = (torch.as_tensor(a).to(DTYPE) for a in (mean, cov, detections))
    if mean.dim() != 2 or cov.shape != (*mean.shape, mean.shape[-1]):
        raise ConfigError(f"mean {tuple(mean.shape)} and cov {tuple(cov.shape)} must be (T, n) and (T, n, n)")
    if det.dim() != 2:
        raise ConfigError(f"detections {tuple(det.shape)} must be (M, Dz)")
    if present is None:
        present = torch.ones(det.shape[0], dtype=torch.bool)
    present = torch.as_tensor(present, dtype=torch.bool)
    if present.shape != det.shape[:1]:
        raise ConfigError(f"present {tuple(present.shape)} must be ({det.shape[0]},), one flag per detection")
    return mean, cov, det, present


def predict_measurement(mean: Tensor, cov: Tensor, observation: ObservationModel) -> MeasurementPrediction:
    r""":math:`\hat z = h(\hat x)`, :math:`H`, :math:`R` and :math:`S = H P H^T + R` of every track (float64)."""
    mean, cov = mean.to(DTYPE), cov.to(DTYPE)
    z = observation(mean).to(DTYPE)
    h = observation.jacobian(mean).to(DTYPE)
    r = observation.noise_cov(mean).to(DTYPE)
    s = h @ cov @ h.transpose(-1, -2) + r
    return MeasurementPrediction(z, h, r, s)


def innovations(pred: MeasurementPrediction, observation: ObservationModel, detections: Tensor) -> Tensor:
    """``nu[i, j] = z_j - zhat_i`` in the measurement's own geometry, ``(T, M, Dz)``."""
    t, m = pred.z.shape[0], detections.shape[0]
    zz = detections.to(DTYPE).unsqueeze(0).expand(t, m, -1)
    zh = pred.z.unsqueeze(1).expand(t, m, -1)
    return observation.residual(zz, zh).to(DTYPE)


def kalman_gain(cov: Tensor, pred: MeasurementPrediction) -> Tensor:
    r""":math:`K = P H^T S^{-1}`, ``(T, n, Dz)``."""
    pht = cov @ pred.H.transpose(-1, -2)
    return torch.linalg.solve(pred.S, pht.transpose(-1, -2)).transpose(-1, -2)


def kalman_update(mean: Tensor, cov: Tensor, pred: MeasurementPrediction, nu: Tensor) -> tuple[Tensor, Tensor]:
    r"""The (extended) Kalman update by one innovation per track ``nu (T, Dz)``:
    :math:`x + K\nu`, :math:`P - K S K^T`."""
    k = kalman_gain(cov, pred)
    return mean + (k @ nu.unsqueeze(-1)).squeeze(-1), cov - k @ pred.S @ k.transpose(-1, -2)
