r"""Joint probabilistic data association (Bar-Shalom, Fortmann, Scheffe 1983), exact: the tracks are split
into clusters that share gated detections (connected components, :mod:`scipy.sparse.csgraph`), and every
joint event of a cluster (each track takes one of its gated detections, no detection twice, or is missed) is
enumerated. An event's probability is proportional to

.. math:: \prod_{i \text{ assigned } j} \frac{P_D\,\mathcal N(z_j; \hat z_i, S_i)}{\lambda}
          \prod_{i \text{ missed}} (1 - P_D P_G),

and the marginals :math:`\beta_{ij}` (detection ``j`` is track ``i``'s) and :math:`\beta_{i0}` (missed) sum
the normalised events. Each track is then updated by PDA:

.. math:: \hat x^+ = \hat x + K \nu, \quad \nu = \sum_j \beta_{ij} \nu_{ij}, \qquad
          P^+ = \beta_{i0} P + (1 - \beta_{i0})(P - K S K^T)
                + K \Big(\sum_j \beta_{ij} \nu_{ij}\nu_{ij}^T - \nu\nu^T\Big) K^T,

the last term the spread of the innovations.

Where a cluster is too large to enumerate (a dense crowd: 15 tracks sharing detections have more than
:math:`10^5` joint events), the marginals can be approximated by loopy belief propagation on the association's
bipartite graph (Williams and Lau 2014, :func:`lbp_marginals`; exact on clusters whose gate graph is a tree),
chosen by ``marginals``: ``exact`` (every event, an error past ``max_joint_events``), ``lbp`` (every cluster by
belief propagation) or ``auto`` (exact where the cluster's bound :math:`\prod_i (1 + g_i)` on its events, ``g_i``
track ``i``'s gated detections, is at most ``max_joint_events``, belief propagation otherwise, each such cluster
counted in the run's diagnostics as ``jpda_lbp_clusters``).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.special import logsumexp
from torch import Tensor

from dslearn.association.base import Association, kalman_gain
from dslearn.association.gating import check_probability
from dslearn.association.gnn import gated_innovations, log_likelihood_ratios
from dslearn.diagnostics import record_count
from dslearn.errors import ConfigError, check_choice, check_positive
from dslearn.models.base import ObservationModel


def _events(options: list[np.ndarray], limit: int):
    """Every joint event of a cluster: one entry per track, a detection index or -1 (missed), no detection
    twice. Raises :class:`ConfigError` past ``limit`` events."""
    out, cur, used = [], [], set()

    def rec(k):
        if k == len(options):
            out.append(tuple(cur))
            if len(out) > limit:
                raise ConfigError(f"associator.max_joint_events={limit}: a cluster of {len(options)} tracks has more "
                                  "joint events; raise it or narrow the gate (associator.gate_probability)")
            return
        cur.append(-1)
        rec(k + 1)
        cur.pop()
        for j in options[k]:
            if j not in used:
                used.add(j)
                cur.append(int(j))
                rec(k + 1)
                cur.pop()
                used.discard(j)

    rec(0)
    return out


#: how a cluster's marginals are computed (the module's text)
MARGINALS = ("exact", "lbp", "auto")
#: belief propagation stops when no message (each in (0, 1]) moves more than this, or after LBP_MAX_ITER sweeps
LBP_TOLERANCE = 1e-13
LBP_MAX_ITER = 10_000


def lbp_marginals(psi: np.ndarray, tol: float = LBP_TOLERANCE, max_iter: int = LBP_MAX_ITER
                  ) -> tuple[np.ndarray, np.ndarray, bool]:
    r"""Approximate JPDA marginals by loopy belief propagation (Williams and Lau 2014). ``psi (T, M)``: each pair's
    weight over its track's miss weight, :math:`\psi_{ij} = P_D \mathcal N(z_j) / (\lambda (1 - P_D P_G))`, 0
    outside the gate (a detection's clutter weight is 1). The messages from tracks to detections and back,

    .. math:: \mu_{ij} = \frac{\psi_{ij}}{1 + \sum_{j' \ne j} \psi_{ij'} \nu_{j'i}}, \qquad
              \nu_{ji} = \frac{1}{1 + \sum_{i' \ne i} \mu_{i'j}},

    are iterated from :math:`\nu = 1` to their fixed point; then :math:`\beta_{ij} \propto \psi_{ij}\nu_{ji}`,
    :math:`\beta_{i0} \propto 1`. Returns ``beta (T, M)``, ``beta0 (T,)`` and whether it converged."""
    nu = np.ones_like(psi)
    converged = False
    for _ in range(max_iter):
        val = psi * nu
        mu = psi / (1.0 + val.sum(1, keepdims=True) - val)
        new = 1.0 / (1.0 + mu.sum(0, keepdims=True) - mu)
        step = np.abs(new - nu).max(initial=0.0)
        nu = new
        if step <= tol:
            converged = True
            break
    val = psi * nu
    s = 1.0 + val.sum(1)
    return val / s[:, None], 1.0 / s, converged


def _exact(score, miss, tracks, options, limit):
    events = _events(options, limit)
    logw = np.array([sum(miss if j < 0 else score[i, j] for i, j in zip(tracks, e)) for e in events])
    w = np.exp(logw - logsumexp(logw))
    beta = np.zeros((len(tracks), score.shape[1]))
    b0 = np.zeros(len(tracks))
    for e, we in zip(events, w):
        for k, j in enumerate(e):
            if j < 0:
                b0[k] += we
            else:
                beta[k, j] += we
    return beta, b0


def marginals(score: np.ndarray, miss: float, gated: np.ndarray, limit: int = 100_000,
              method: str = "exact") -> tuple[np.ndarray, np.ndarray]:
    r"""The JPDA marginals from log scores: ``score (T, M)`` the pairs' :math:`\log(P_D \mathcal N / \lambda)`,
    ``miss`` :math:`\log(1 - P_D P_G)`, ``gated (T, M)``; ``method`` one of :data:`MARGINALS` (the module's
    text). Returns ``beta (T, M)`` and ``beta0 (T,)``."""
    t, m = gated.shape
    beta, beta0 = np.zeros((t, m)), np.ones(t)
    if t == 0:
        return beta, beta0
    # clusters: the components of the graph of tracks (0..T-1) and detections (T..T+M-1) joined by gates
    r, c = np.nonzero(gated)
    graph = coo_matrix((np.ones(len(r)), (r, c + t)), shape=(t + m, t + m))
    _, label = connected_components(graph, directed=False)
    for lab in np.unique(label[:t]):
        tracks = np.flatnonzero(label[:t] == lab)
        options = [np.flatnonzero(gated[i]) for i in tracks]
        bound = math.prod(1 + len(o) for o in options)
        if method == "exact" or (method == "auto" and bound <= limit):
            b, b0 = _exact(score, miss, tracks, options, limit)
        else:
            g = gated[tracks]
            psi = np.where(g, np.exp(np.where(g, score[tracks], 0.0) - miss), 0.0)
            b, b0, ok = lbp_marginals(psi)
            record_count("jpda_lbp_clusters")
            if not ok:
                record_count("jpda_lbp_unconverged")
        beta[tracks] = b
        beta0[tracks] = b0
    return beta, beta0


class JPDA:
    """Exact JPDA associator (:class:`~dslearn.association.base.Associator`).

    Args:
        detection_probability: :math:`P_D` in (0, 1).
        clutter_density: :math:`\\lambda` (> 0).
        gate_probability: :math:`P_G` in (0, 1].
        max_joint_events: the most joint events a cluster may have (> 0; more stops with an error naming this
            setting under ``marginals="exact"``, and switches the cluster to belief propagation under ``"auto"``).
        marginals: ``exact``, ``lbp`` or ``auto`` (the module's text).
    """

    def __init__(self, detection_probability: float = 0.9, clutter_density: float = 1e-3,
                 gate_probability: float = 0.99, max_joint_events: int = 100_000, marginals: str = "exact"):
        self.detection_probability = check_probability("associator.detection_probability", detection_probability,
                                                        closed=False)
        check_positive("associator.clutter_density", clutter_density)
        self.clutter_density = float(clutter_density)
        self.gate_probability = check_probability("associator.gate_probability", gate_probability)
        check_positive("associator.max_joint_events", max_joint_events)
        self.max_joint_events = int(max_joint_events)
        check_choice("associator.marginals", marginals, MARGINALS)
        self.marginals = marginals

    def associate(self, mean: Tensor, cov: Tensor, observation: ObservationModel, detections: Tensor,
                  present: Tensor | None = None) -> Association:
        mean, cov, det, present, pred, nu, d2, gated = gated_innovations(
            mean, cov, observation, detections, present, self.gate_probability)
        score = log_likelihood_ratios(d2, pred.S, self.detection_probability, self.clutter_density)
        miss = math.log(1 - self.detection_probability * self.gate_probability)
        b, b0 = marginals(score.detach().numpy(), miss, gated.numpy(), self.max_joint_events, self.marginals)
        beta, beta0 = torch.from_numpy(b), torch.from_numpy(b0)
        # PDA update with the combined innovation and the spread of the innovations
        k = kalman_gain(cov, pred)  # (T, n, Dz)
        nu_c = (beta.unsqueeze(-1) * nu).sum(1)  # (T, Dz)
        spread = torch.einsum("tm,tmi,tmj->tij", beta, nu, nu) - nu_c.unsqueeze(-1) * nu_c.unsqueeze(-2)
        kt = k.transpose(-1, -2)
        new_mean = mean + (k @ nu_c.unsqueeze(-1)).squeeze(-1)
        b0v = beta0.view(-1, 1, 1)
        new_cov = b0v * cov + (1 - b0v) * (cov - k @ pred.S @ kt) + k @ spread @ kt
        full = torch.cat([beta0.unsqueeze(-1), beta], dim=1)
        assigned = full.argmax(1) - 1
        unassigned = present & ~gated.any(0)
        return Association(beta, beta0, assigned, gated, unassigned, new_mean, new_cov)
