r"""Association on a sensor network: every node associates its own detections with its own predicted tracks, then
the network fuses per track as it does with labelled measurements (the ``associator=`` slot of the distributed
filter, :func:`dslearn.filters.distributed.track`'s ``associate``).

Each node ``s`` holds ``A`` tracks (the target blocks of its joint belief). At a step its predicted tracks are the
blocks of its predicted belief (mean, and the diagonal blocks of :math:`(\Omega^{t|t-1})^{-1}`), their predicted
measurement the filter's own linearisation (``obs.linearize``: :math:`\hat z, C, R`), so the gate
:math:`S = C P C^T + R` is the chosen motion model's prediction. The node's associator (GNN or JPDA, :mod:`.gnn`,
:mod:`.jpda`) turns its detection set into one pseudo-measurement per track, and the information update and the
consensus then run per track, unchanged:

* GNN: the detection assigned to the track (none: the track is not updated by this node);
* JPDA: the information form of the PDA update (Sandell and Olfati-Saber 2008, the JPDA Kalman consensus filter):
  the track's information grows by :math:`(1 - \beta_0) C^T R^{-1} C` and its information vector by
  :math:`C^T R^{-1}((1 - \beta_0)\hat z' + \bar\nu)`, :math:`\bar\nu = \sum_j \beta_j \nu_j`, i.e. the
  measurement :math:`\hat z + \bar\nu / (1 - \beta_0)` with covariance :math:`R / (1 - \beta_0)`. This is an
  approximation of the PDA update (``info_update="sandell"``, the default): its gain is that of the noise
  :math:`R / (1 - \beta_0)`, not of :math:`R`, so even the mean differs from PDA's unless :math:`\beta_0 = 0`, and
  the spread of the innovations (the PDA covariance's last term) is left out. With ``info_update="pda"`` the pseudo-measurement is the one whose
  information update is the PDA update itself, spread included: with the gate's :math:`S` and
  :math:`S_e = (1 - \beta_0) S - \tilde\Sigma`, :math:`\tilde\Sigma = \sum_j \beta_j \nu_j\nu_j^T - \bar\nu\bar\nu^T`,
  the measurement :math:`\hat z + S S_e^{-1} \bar\nu` with covariance :math:`R' = S S_e^{-1} S - C P C^T`
  (then :math:`P - P C^T (C P C^T + R')^{-1} C P = P - K S_e K^T`, the PDA covariance, and the mean moves by
  :math:`K \bar\nu`). :math:`R'` may be indefinite (the spread can make the posterior wider than the prior in
  some direction: information is then taken away). A track whose :math:`S_e` is not positive definite (a spread
  as large as the gate) takes the default's pseudo-measurement, counted as ``jpda_pda_fallbacks`` in the run's
  diagnostics. One node with one track: exactly the PDA update of :class:`~dslearn.association.jpda.JPDA`.

The tracks are the ``A`` targets' from the start (the scenario's declared start region,
:func:`dslearn.filters.distributed.associated_belief`): node ``s``'s track ``j`` and node ``r``'s track ``j`` are
fused as one target, as both started from target ``j``'s start region. Where targets enter and leave (a scenario
that declares births, or ``tracks.manage=on`` in the slot) the tracks are managed instead: every node starts,
confirms and deletes its own tracks and matches them to its neighbours' before the consensus
(:mod:`.multitrack`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import math

import torch
from torch import Tensor

from dslearn.association.base import DTYPE
from dslearn.association.gating import check_probability, gate
from dslearn.association.gnn import GNN, assignment, log_likelihood_ratios
from dslearn.association.jpda import JPDA, MARGINALS, marginals
from dslearn.association.multitrack import NetworkTracks, TrackSettings
from dslearn.diagnostics import record_count
from dslearn.errors import ConfigError, check_choice, check_positive
from dslearn.types import safe_cholesky, symmetrize

#: a JPDA track whose probability of having been detected is at most this is not updated by the node
MIN_DETECTED = 1e-12
#: the clutter density an associator assumes where the scenario declares none (a clutter-free scenario), per m^2
MIN_CLUTTER_DENSITY = 1e-6
#: how a node's JPDA becomes its information update (the module's text)
INFO_UPDATES = ("sandell", "pda")


class NodeAssociation:
    """``associate(y_pred, o_pred, det, present, obs, linearized) -> (meas (S, B, A, Dz), visible (S, B, A),
    linearized)``: every node's detections ``det (S, B, M, Dz)`` (``present (S, B, M)``) associated with its ``A``
    predicted tracks (``y_pred (S, B, A d)``, ``o_pred (S, B, A d, A d)``) by ``associator`` (a :class:`GNN` or a
    :class:`JPDA`), as labelled pseudo-measurements of the tracks (the module's text). The gate and the scores are
    computed for every node and episode at once; the assignment (GNN) or the joint events (JPDA) per node and
    episode, by the associator's own functions (:func:`~dslearn.association.gnn.assignment`,
    :func:`~dslearn.association.jpda.marginals`)."""

    def __init__(self, associator, num_tracks: int, info_update: str = "sandell"):
        if not isinstance(associator, (GNN, JPDA)):
            raise ConfigError(f"the network's associator must be GNN or JPDA, not {type(associator).__name__}")
        check_choice("associator.info_update", info_update, INFO_UPDATES)
        self.associator = associator
        self.num_tracks = int(num_tracks)
        self.combines = isinstance(associator, JPDA)
        self.info_update = info_update

    def __call__(self, y_pred: Tensor, o_pred: Tensor, det: Tensor, present: Tensor, obs, linearized=None):
        a = self.num_tracks
        yj = y_pred.unflatten(-1, (a, -1))  # (S, B, A, d)
        d = yj.shape[-1]
        h, C, R = obs.linearize(yj) if linearized is None else linearized
        z = obs.reading(det)  # (S, B, M, Dz)
        s, b, m = z.shape[:3]
        meas = torch.zeros(s, b, a, z.shape[-1], dtype=z.dtype, device=z.device)
        vis = torch.zeros(s, b, a, dtype=torch.bool, device=z.device)
        busy = present.any(-1)  # (S, B): nodes with detections this step
        if not bool(busy.any()):
            return meas, vis, (h, C, R)
        P = torch.cholesky_inverse(safe_cholesky(o_pred))  # (S, B, Dx, Dx)
        blocks = P.unflatten(-2, (a, d)).unflatten(-1, (a, d))  # (S, B, A, d, A, d)
        Pjj = torch.diagonal(blocks, dim1=-4, dim2=-2).movedim(-1, -3)  # (S, B, A, d, d)
        S = symmetrize(C @ Pjj @ C.transpose(-1, -2) + R).to(DTYPE)  # (S, B, A, Dz, Dz): the gate's covariance
        zz = z.unsqueeze(2).expand(s, b, a, m, z.shape[-1])
        nu = obs.residual(zz, h.unsqueeze(3).expand_as(zz)).to(DTYPE)  # (S, B, A, M, Dz)
        d2 = (nu * torch.linalg.solve(S.unsqueeze(3), nu.unsqueeze(-1)).squeeze(-1)).sum(-1)  # (S, B, A, M)
        assoc = self.associator
        gated = gate(d2, nu.shape[-1], assoc.gate_probability, None) & present.unsqueeze(2)
        gated = gated.cpu()
        if self.combines:  # the pairs' log scores (JPDA) or costs (GNN), on the CPU where the per-node functions run
            score = log_likelihood_ratios(d2, S, assoc.detection_probability, assoc.clutter_density).cpu()
            miss = math.log(1 - assoc.detection_probability * assoc.gate_probability)
        else:
            score, miss = assoc.costs(d2, S)
            score = score.cpu()
        if a == 1 and not (self.combines and assoc.marginals == "lbp"):
            # one track per node: its events are "missed" or one gated detection, so the assignment and the
            # marginals have closed forms, batched over the nodes and episodes (equal to the per-node functions')
            if self.combines:
                logw = torch.cat([torch.full((s, b, a, 1), miss, dtype=DTYPE), torch.where(gated, score, -math.inf)], -1)
                w = torch.exp(logw - torch.logsumexp(logw, -1, keepdim=True))
                beta, beta0 = w[..., 1:], w[..., 0]
            else:
                cost = torch.where(gated, score, math.inf)
                best = cost.argmin(-1, keepdim=True)
                low = cost.gather(-1, best)
                assigned = torch.where(torch.isfinite(low) & (low < miss), best, -1).squeeze(-1)  # miss inf: any
        else:
            beta, beta0 = torch.zeros(s, b, a, m, dtype=DTYPE), torch.ones(s, b, a, dtype=DTYPE)
            assigned = torch.full((s, b, a), -1, dtype=torch.int64)
            score_np, gated_np = score.numpy(), gated.numpy()
            for i, k in busy.nonzero().tolist():
                if self.combines:
                    bt, b0 = marginals(score_np[i, k], miss, gated_np[i, k], assoc.max_joint_events, assoc.marginals)
                    beta[i, k], beta0[i, k] = torch.from_numpy(bt), torch.from_numpy(b0)
                else:
                    assigned[i, k] = torch.from_numpy(assignment(score_np[i, k], gated_np[i, k], miss))
        if not self.combines:  # GNN: the assigned detection, as given
            assigned = assigned.to(z.device)
            vis = assigned >= 0
            meas = torch.where(vis.unsqueeze(-1), z.gather(2, assigned.clamp(min=0).unsqueeze(-1).expand(
                s, b, a, z.shape[-1])), meas)
            return meas, vis, (h, C, R)
        beta, beta0 = beta.to(z.device), beta0.to(z.device)
        w = 1 - beta0  # (S, B, A): the probability that the track was detected
        vis = w > MIN_DETECTED
        nu_c = (beta.unsqueeze(-1) * nu).sum(-2)  # (S, B, A, Dz): the combined innovation
        wv = torch.where(vis, w, torch.ones_like(w))
        meas = torch.where(vis.unsqueeze(-1), (h.to(DTYPE) + nu_c / wv.unsqueeze(-1)).to(z.dtype), meas)
        r_eff = R / wv.to(R.dtype).unsqueeze(-1).unsqueeze(-1)
        if self.info_update == "pda":
            meas, r_eff = self._pda(meas, r_eff, vis, w, beta, nu, nu_c, S, h, R)
        return meas, vis, (h, C, r_eff)

    @staticmethod
    def _pda(meas, r_eff, vis, w, beta, nu, nu_c, S, h, R):
        """The pseudo-measurement and covariance whose information update is the PDA update (the module's text),
        where the track's ``S_e`` is positive definite; the default's elsewhere."""
        spread = torch.einsum("sbam,sbami,sbamj->sbaij", beta, nu, nu) - nu_c.unsqueeze(-1) * nu_c.unsqueeze(-2)
        s_e = symmetrize(w.unsqueeze(-1).unsqueeze(-1) * S - spread)
        chol, info = torch.linalg.cholesky_ex(s_e)
        ok = vis & (info == 0)
        if bool((vis & ~ok).any()):
            record_count("jpda_pda_fallbacks", int((vis & ~ok).sum()))
        eye = torch.eye(S.shape[-1], dtype=S.dtype, device=S.device)
        chol = torch.where(ok.unsqueeze(-1).unsqueeze(-1), chol, eye)
        z_pda = h.to(DTYPE) + (S @ torch.cholesky_solve(nu_c.unsqueeze(-1), chol)).squeeze(-1)
        r_pda = symmetrize(S @ torch.cholesky_solve(S, chol) - (S - R.to(DTYPE)))  # S S_e^-1 S - C P C^T
        meas = torch.where(ok.unsqueeze(-1), z_pda.to(meas.dtype), meas)
        r_eff = torch.where(ok.unsqueeze(-1).unsqueeze(-1), r_pda.to(r_eff.dtype), r_eff)
        return meas, r_eff


# ------------------------------------------------------------------------------------------------
# the associator slot (conf/associator): what a run chooses, made into an associator for a scenario's world


def _detection_facts(scenario, network) -> tuple[float, float]:
    """The scenario's declared detection probability and clutter density (1 and none for a labelled scenario)."""
    p = float(getattr(scenario, "p_detect", 1.0))
    density = getattr(scenario, "clutter_density", None)
    lam = float(density(network)) if callable(density) else 0.0
    return p, max(lam, MIN_CLUTTER_DENSITY)


@dataclass(frozen=True)
class LabelsAssociator:
    """``associator=labels``: the labels the scenario gives (every measurement its target's: today's behaviour,
    the reference). It needs a labelled scenario."""

    name = "labels"
    config_reads = ()
    config_unread = "the labels given need no setting"
    needs_labels = True

    def make(self, scenario, network, num_tracks: int):
        """No association: the labelled update (``None``)."""
        return None


def _check_common(gate_probability, detection_probability, clutter_density) -> None:
    check_probability("associator.gate_probability", gate_probability)
    if detection_probability is not None:
        check_probability("associator.detection_probability", detection_probability)
    if clutter_density is not None:
        check_positive("associator.clutter_density", clutter_density)


@dataclass(frozen=True)
class GNNAssociator:
    """``associator=gnn``: global nearest neighbour (:class:`~dslearn.association.gnn.GNN`) at every node.
    ``detection_probability`` and ``clutter_density``: ``None`` = the scenario's declared ``p_detect`` and its
    clutter rate over a sensing disc (at least :data:`MIN_CLUTTER_DENSITY`)."""

    gate_probability: float = 0.99
    detection_probability: float | None = None
    clutter_density: float | None = None
    cost: str = "likelihood"
    tracks: Any = None

    name = "gnn"
    config_reads = ("gate_probability", "detection_probability", "clutter_density", "cost", "tracks")
    config_unread = "global nearest neighbour does not read it"
    needs_labels = False

    def __post_init__(self):
        _check_common(self.gate_probability, self.detection_probability, self.clutter_density)
        check_choice("associator.cost", self.cost, ("likelihood", "mahalanobis"))
        object.__setattr__(self, "tracks", TrackSettings.of(self.tracks))

    def node_associator(self, scenario, network) -> GNN:
        """The associator every node runs, with the scenario's declared facts where the slot leaves them open."""
        p, lam = _detection_facts(scenario, network)
        p = p if self.detection_probability is None else self.detection_probability
        lam = lam if self.clutter_density is None else self.clutter_density
        return GNN(p, lam, self.gate_probability, self.cost)

    def make(self, scenario, network, num_tracks: int) -> NodeAssociation:
        return NodeAssociation(self.node_associator(scenario, network), num_tracks)

    def network_tracks(self, scenario, network) -> NetworkTracks | None:
        """Managed tracks (:mod:`.multitrack`) where the slot's ``tracks`` manage them on this scenario, else
        ``None`` (the declared targets' tracks from the start)."""
        return _network_tracks(self, scenario, network)


@dataclass(frozen=True)
class JPDAAssociator:
    """``associator=jpda``: exact JPDA (:class:`~dslearn.association.jpda.JPDA`) at every node, in information
    form (the module's text). ``detection_probability`` (< 1 for JPDA; ``None`` = the scenario's ``p_detect``,
    capped at 0.999) and ``clutter_density`` as for :class:`GNNAssociator`."""

    gate_probability: float = 0.99
    detection_probability: float | None = None
    clutter_density: float | None = None
    max_joint_events: int = 100_000
    marginals: str = "exact"
    info_update: str = "sandell"
    tracks: Any = None

    name = "jpda"
    config_reads = ("gate_probability", "detection_probability", "clutter_density", "max_joint_events", "marginals",
                    "info_update", "tracks")
    config_unread = "JPDA does not read it"
    needs_labels = False
    #: JPDA needs P_D < 1 (a missed detection must be possible): a scenario's P_D = 1 is taken as this
    MAX_DETECTION_PROBABILITY = 0.999

    def __post_init__(self):
        _check_common(self.gate_probability, self.detection_probability, self.clutter_density)
        if self.detection_probability is not None:
            check_probability("associator.detection_probability", self.detection_probability, closed=False)
        check_positive("associator.max_joint_events", self.max_joint_events)
        check_choice("associator.marginals", self.marginals, MARGINALS)
        check_choice("associator.info_update", self.info_update, INFO_UPDATES)
        object.__setattr__(self, "tracks", TrackSettings.of(self.tracks))

    def node_associator(self, scenario, network) -> JPDA:
        """The associator every node runs, with the scenario's declared facts where the slot leaves them open."""
        p, lam = _detection_facts(scenario, network)
        p = min(p, self.MAX_DETECTION_PROBABILITY) if self.detection_probability is None else self.detection_probability
        lam = lam if self.clutter_density is None else self.clutter_density
        return JPDA(p, lam, self.gate_probability, int(self.max_joint_events), self.marginals)

    def make(self, scenario, network, num_tracks: int) -> NodeAssociation:
        return NodeAssociation(self.node_associator(scenario, network), num_tracks, self.info_update)

    def network_tracks(self, scenario, network) -> NetworkTracks | None:
        """As :meth:`GNNAssociator.network_tracks`."""
        return _network_tracks(self, scenario, network)


def _network_tracks(slot, scenario, network) -> NetworkTracks | None:
    settings: TrackSettings = slot.tracks
    if not settings.manages(scenario.spec):
        return None
    ctx = scenario.ctx()
    vstd = getattr(scenario, "start_velocity_std", None)
    if vstd is None and (settings.velocity_std is None or settings.max_speed is None):
        raise ConfigError(f"associator.tracks: scenario {scenario.spec.name} declares no start_velocity_std; set "
                          f"associator.tracks.velocity_std and associator.tracks.max_speed")
    manager = settings.manager_settings(ctx.dt, 1.0 if vstd is None else vstd)
    return NetworkTracks(slot.node_associator(scenario, network), manager,
                         settings.t2ta_gate_probability, settings.adopt)
