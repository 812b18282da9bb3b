r"""Global nearest neighbour: one optimal assignment of detections to tracks per step (SciPy's
:func:`~scipy.optimize.linear_sum_assignment`), each track taking at most one gated detection or none (a
missed detection), then the Kalman update of each track by its detection.

Two costs (``cost``):

* ``"likelihood"`` (default): the most probable joint association, the JPDA event of largest probability:
  each assigned pair scores :math:`\log(P_D\,\mathcal N(z_j; \hat z_i, S_i) / \lambda)`, each missed track
  :math:`\log(1 - P_D P_G)`, and the assignment maximises the sum;
* ``"mahalanobis"``: the sum of the Mahalanobis distances :math:`\sqrt{\nu^T S^{-1}\nu}` of the assigned
  pairs is minimised, a missed track costing the gate's own distance :math:`\sqrt{\chi^2_{D_z}(P_G)}`
  (``detection_probability`` and ``clutter_density`` are then not used).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from torch import Tensor

from dslearn.association.base import (DTYPE, Association, check_inputs, innovations, kalman_update,
                                      predict_measurement)
from dslearn.association.gating import check_probability, gate, gate_threshold, mahalanobis2
from dslearn.errors import check_choice, check_positive
from dslearn.models.base import ObservationModel


def log_likelihood_ratios(d2: Tensor, s: Tensor, detection_probability: float, clutter_density: float) -> Tensor:
    r""":math:`\log(P_D\,\mathcal N(z_j; \hat z_i, S_i) / \lambda)`, ``(T, M)``, from the squared distances."""
    dz = s.shape[-1]
    log_norm = -0.5 * (dz * math.log(2 * math.pi) + torch.logdet(s))  # (T,)
    return math.log(detection_probability) - math.log(clutter_density) + log_norm.unsqueeze(-1) - 0.5 * d2



def gated_innovations(mean: Tensor, cov: Tensor, observation: ObservationModel, detections: Tensor,
                      present: Tensor | None, gate_probability: float):
    """What every associator starts from: the checked inputs, each track's predicted measurement, the innovations
    ``(T, M, Dz)`` of every detection, their squared Mahalanobis distances and the gate."""
    mean, cov, det, present = check_inputs(mean, cov, detections, present)
    t, m = mean.shape[0], det.shape[0]
    pred = predict_measurement(mean, cov, observation)
    nu = innovations(pred, observation, det)
    d2 = mahalanobis2(nu, pred.S) if m else torch.zeros(t, 0, dtype=DTYPE)
    return mean, cov, det, present, pred, nu, d2, gate(d2, nu.shape[-1], gate_probability, present)

def assignment(pair: np.ndarray, gated: np.ndarray, miss: float) -> np.ndarray:
    """The optimal assignment of ``M`` detections to ``T`` tracks, ``(T,)`` int64 (the detection of each track, -1
    for missed), from the pair costs ``pair (T, M)``, the gate ``gated (T, M)`` (a pair outside it is not allowed)
    and the cost ``miss`` of a missed track (``inf``: a miss is worse than any pair, yet allowed where there are
    too few detections)."""
    t, m = gated.shape
    assigned = np.full(t, -1, dtype=np.int64)
    if t and m and bool(gated.any()):
        # tracks x (detections + one dummy column per track): a dummy is its own track's missed detection
        pair_np = np.where(gated, pair, np.inf)
        dummy = np.full((t, t), np.inf)
        np.fill_diagonal(dummy, miss)
        cost = np.concatenate([pair_np, dummy], axis=1)
        if math.isinf(miss):
            finite = np.abs(pair_np[np.isfinite(pair_np)])
            np.fill_diagonal(cost[:, m:], 1.0 + finite.sum() * 2)
        rows, cols = linear_sum_assignment(cost)
        take = cols < m
        assigned[rows[take]] = cols[take]
    return assigned


class GNN:
    """Global nearest neighbour associator (:class:`~dslearn.association.base.Associator`).

    Args:
        detection_probability: :math:`P_D` in (0, 1].
        clutter_density: :math:`\\lambda` (> 0, false detections per unit measurement volume).
        gate_probability: :math:`P_G` in (0, 1] (1: no gate).
        cost: ``"likelihood"`` or ``"mahalanobis"``.
    """

    def __init__(self, detection_probability: float = 0.9, clutter_density: float = 1e-3,
                 gate_probability: float = 0.99, cost: str = "likelihood"):
        self.detection_probability = check_probability("associator.detection_probability", detection_probability)
        check_positive("associator.clutter_density", clutter_density)
        self.clutter_density = float(clutter_density)
        self.gate_probability = check_probability("associator.gate_probability", gate_probability)
        check_choice("associator.cost", cost, ("likelihood", "mahalanobis"))
        self.cost = cost

    def costs(self, d2: Tensor, s: Tensor) -> tuple[Tensor, float]:
        """The pair costs ``(*, T, M)`` from the squared distances ``d2 (*, T, M)`` and the innovation covariances
        ``s (*, T, Dz, Dz)``, and the cost of a missed track (the module's text)."""
        if self.cost == "likelihood":
            pdpg = self.detection_probability * self.gate_probability
            pair = -log_likelihood_ratios(d2, s, self.detection_probability, self.clutter_density)
            return pair, (-math.log(1 - pdpg) if pdpg < 1 else math.inf)
        return d2.sqrt(), math.sqrt(gate_threshold(self.gate_probability, s.shape[-1]))

    def associate(self, mean: Tensor, cov: Tensor, observation: ObservationModel, detections: Tensor,
                  present: Tensor | None = None) -> Association:
        mean, cov, det, present, pred, nu, d2, gated = gated_innovations(
            mean, cov, observation, detections, present, self.gate_probability)
        t, m, dz = mean.shape[0], det.shape[0], nu.shape[-1]
        pair, miss = self.costs(d2, pred.S)
        assigned = assignment(pair.detach().numpy(), gated.numpy(), miss)
        assigned_t = torch.from_numpy(assigned)
        hit = assigned_t >= 0
        weights = torch.zeros(t, m, dtype=DTYPE)
        weights[hit.nonzero().squeeze(-1), assigned_t[hit]] = 1.0
        nu_sel = torch.zeros(t, dz, dtype=DTYPE)
        nu_sel[hit] = nu[hit.nonzero().squeeze(-1), assigned_t[hit]]
        upd_mean, upd_cov = kalman_update(mean, cov, pred, nu_sel)
        new_mean = torch.where(hit.unsqueeze(-1), upd_mean, mean)
        new_cov = torch.where(hit.unsqueeze(-1).unsqueeze(-1), upd_cov, cov)
        unassigned = present & ~(weights > 0).any(0)
        return Association(weights, (~hit).to(DTYPE), assigned_t, gated, unassigned, new_mean, new_cov)
