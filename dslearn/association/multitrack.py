r"""Managed tracks on a sensor network: targets that enter and leave (issue 35).

Where the targets are not known from the start (a scenario with births and deaths, or
``associator.tracks.manage=on``), every node keeps its own set of tracks (a
:class:`~dslearn.association.tracks.TrackManager`: initiation from the detections no track took, M-of-N
confirmation, deletion after ``delete_after`` consecutive missed steps). Per time step:

1. every node predicts its tracks by the motion model (the EKF's linearisation of each track's block,
   :func:`predict_tracks`) and associates its own detections with them (GNN or JPDA,
   :class:`~dslearn.association.gnn.GNN`, :class:`~dslearn.association.jpda.JPDA`): its local posterior per track;
2. **track-to-track association** (:func:`t2ta_pairs`): over every communication link the two nodes' confirmed
   tracks are matched on the exchanged local posteriors, by the optimal assignment (SciPy's
   :func:`~scipy.optimize.linear_sum_assignment`) of the squared Mahalanobis distances
   :math:`d^2 = (\hat x_i - \hat x_j)^T (P_i + P_j)^{-1} (\hat x_i - \hat x_j)`, a pair allowed only inside the
   chi-square gate :math:`d^2 \le \chi^2_4(P_G)` (Bar-Shalom's track-to-track association test with the
   cross-covariance neglected); the matched pairs join into clusters (connected components over the network: one
   target's tracks), at most one track per node (a node's second track in a cluster is left out of it);
3. **consensus per matched track**: the configured fusion (``consensus=``) runs on each cluster's information pairs
   over the whole network, ``(S, 1, 4)``: a member node brings its predicted pair and its novel information (local
   posterior less prediction, information form); a node outside the cluster is a *naive* node (Kamal et al.) with
   the members' mean predicted pair and no novel information; the members take the fused result (the naive nodes do
   not adopt the track). A track matched to no neighbour keeps its local posterior;
4. every node counts hits and misses (a clustered track counts as detected when any member detected it this step),
   confirms, deletes and starts tracks;
5. with ``adopt`` (default) every node takes its neighbours' established tracks (confirmed, detected at this step
   by some node of its cluster, at least ``confirm_n`` steps old: a clutter track confirmed by chance is not spread)
   that match none of its own (gated as in step 2 against all its tracks, tentative ones included; one copy of a
   target offered by several neighbours): a copy of the neighbour's track, confirmed. So a node also holds the targets
   outside its own sensing range (every node of Kamal et al.'s network holds every target), a communication-only
   node included, one hop further per step.

The estimates are every node's confirmed tracks, one slot per track (a slot is given to a track when it is
confirmed, in order), ``NaN`` where a slot holds no confirmed track at a step: the padded sets that
:func:`dslearn.metrics.multitarget.tracking_metrics` reads with their cardinality.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from scipy.stats import chi2
from torch import Tensor

from dslearn.association.base import DTYPE
from dslearn.association.gating import check_probability
from dslearn.association.tracks import INITIATIONS, TrackManager, TrackManagerSettings, check_track_counts
from dslearn.errors import ConfigError, check_choice, check_flag, check_positive
from dslearn.types import AGENT_DIM, safe_cholesky, symmetrize

#: when the tracks are managed (``associator.tracks.manage``): ``auto`` where the scenario declares births and
#: deaths (its spec's ``births``), ``on`` always, ``off`` never (the tracks are the declared targets from the start)
MANAGE = ("auto", "on", "off")


@dataclass(frozen=True)
class TrackSettings:
    """The associator slot's ``tracks`` (``conf/associator/gnn.yaml``, ``jpda.yaml``); every key checked, naming it.

    ``max_speed`` (m/s, the two-point pairing reach per step is ``max_speed * dt``) and ``velocity_std`` (m/s, the
    single-point initiation's velocity standard deviation) default (``None``) to the scenario's declared start
    velocity standard deviation (``start_velocity_std``): ``3 x`` it and it."""

    manage: str = "auto"
    initiation: str = "two_point"
    confirm_m: int = 2
    confirm_n: int = 3
    delete_after: int = 3
    max_speed: float | None = None
    velocity_std: float | None = None
    t2ta_gate_probability: float = 0.99
    adopt: bool = True

    def __post_init__(self):
        check_flag("associator.tracks.adopt", self.adopt)
        check_choice("associator.tracks.manage", self.manage, MANAGE)
        check_choice("associator.tracks.initiation", self.initiation, INITIATIONS)
        check_track_counts("associator.tracks.", self.confirm_m, self.confirm_n, self.delete_after)
        for name in ("max_speed", "velocity_std"):
            if getattr(self, name) is not None:
                check_positive(f"associator.tracks.{name}", getattr(self, name))
        check_probability("associator.tracks.t2ta_gate_probability", self.t2ta_gate_probability, closed=False)

    @classmethod
    def of(cls, tracks: Any) -> "TrackSettings":
        """From the slot's ``tracks`` node (a mapping, or ``None``: the defaults); a key it does not know is refused
        with the keys it knows."""
        if tracks is None:
            return cls()
        if isinstance(tracks, cls):
            return tracks
        if not isinstance(tracks, Mapping):
            raise ConfigError(f"associator.tracks={tracks!r} must be a mapping of {', '.join(KEYS)}")
        unknown = sorted(set(tracks) - set(KEYS))
        if unknown:
            raise ConfigError(f"associator.tracks.{unknown[0]}: not a track-management setting; allowed: "
                              f"{', '.join(KEYS)}")
        return cls(**dict(tracks))

    def manages(self, spec) -> bool:
        """Whether the tracks are managed on a scenario of this spec."""
        return self.manage == "on" or (self.manage == "auto" and bool(getattr(spec, "births", False)))

    def manager_settings(self, dt: float, start_velocity_std: float) -> TrackManagerSettings:
        """The per-node :class:`~dslearn.association.tracks.TrackManagerSettings` for a scenario's time step and its
        declared start velocity standard deviation."""
        vstd = float(start_velocity_std) if self.velocity_std is None else float(self.velocity_std)
        speed = 3 * vstd if self.max_speed is None else float(self.max_speed)
        return TrackManagerSettings(self.initiation, int(self.confirm_m), int(self.confirm_n), int(self.delete_after),
                                    speed, float(dt), vstd)


#: the keys of ``associator.tracks``
KEYS = tuple(TrackSettings.__dataclass_fields__)


def predict_tracks(mean: Tensor, cov: Tensor, model, ctx) -> tuple[Tensor, Tensor]:
    r"""Every track ``mean (T, 4)``, ``cov (T, 4, 4)`` predicted by the motion model, linearised at its mean (the
    EKF's prediction), each track a target block of the model's joint state (``A`` blocks per call, the rest zero):
    :math:`F_{ii} P F_{ii}^T + Q_{ii}` with the track's own blocks: exact for a model of independent targets (LIN,
    the damped constant velocity, the LSTM without social pooling), the only ones the distributed filter manages
    tracks with. A model that offers ``one_agent()`` (the LSTM) predicts the tracks as a batch of one-agent states
    instead (the same blocks, without the joint Jacobian's ``2A`` backward passes)."""
    t = mean.shape[0]
    if t == 0:
        return mean, cov
    one_agent = getattr(model, "one_agent", None)
    if callable(one_agent):  # the model over one agent: every track a row of the batch, its own 4 x 4 Jacobian
        m, f, q = (v.to(DTYPE) for v in one_agent().linearize(mean, ctx))
        return m, symmetrize(f @ cov @ f.transpose(-1, -2) + q)
    a = int(model.state_dim) // AGENT_DIM
    chunks = math.ceil(t / a)
    x = torch.zeros(chunks * a, AGENT_DIM, dtype=DTYPE)
    x[:t] = mean
    m, f, q = model.linearize(x.reshape(chunks, a * AGENT_DIM), ctx)

    def blocks(mat):  # (chunks, 4a, 4a) -> (T, 4, 4): the diagonal blocks
        b = mat.to(DTYPE).unflatten(-2, (a, AGENT_DIM)).unflatten(-1, (a, AGENT_DIM))
        return torch.diagonal(b, dim1=1, dim2=3).movedim(-1, 1).reshape(chunks * a, AGENT_DIM, AGENT_DIM)[:t]

    fb, qb = blocks(f), blocks(q)
    pm = m.to(DTYPE).reshape(chunks * a, AGENT_DIM)[:t]
    return pm, symmetrize(fb @ cov @ fb.transpose(-1, -2) + qb)


def t2ta_pairs(mean_a: Tensor, cov_a: Tensor, mean_b: Tensor, cov_b: Tensor,
               gate_probability: float) -> list[tuple[int, int]]:
    r"""Track-to-track association of two nodes' tracks ``(Ta, 4)``, ``(Tb, 4)``: the optimal assignment of the
    squared Mahalanobis distances :math:`d^2_{ij} = \Delta^T (P_i + P_j)^{-1} \Delta`, pairs only inside the gate
    :math:`d^2 \le \chi^2_4(P_G)`. Returns the matched ``(i, j)`` pairs."""
    if not mean_a.shape[0] or not mean_b.shape[0]:
        return []
    diff = mean_a.unsqueeze(1) - mean_b.unsqueeze(0)  # (Ta, Tb, 4)
    s = cov_a.unsqueeze(1) + cov_b.unsqueeze(0)
    d2 = (diff * torch.linalg.solve(s, diff.unsqueeze(-1)).squeeze(-1)).sum(-1).numpy()
    gate = chi2.ppf(gate_probability, diff.shape[-1])
    inside = d2 <= gate
    if not inside.any():
        return []
    cost = np.where(inside, d2, gate * (d2.shape[0] + d2.shape[1] + 1))
    rows, cols = linear_sum_assignment(cost)
    return [(int(i), int(j)) for i, j in zip(rows, cols) if inside[i, j]]


def clusters(tracks: list[int], links: list[tuple[int, int, list[tuple[int, int]]]]) -> list[dict[int, int]]:
    """The clusters of matched tracks (connected components of the matched pairs over the links): ``tracks[s]`` the
    number of tracks of node ``s``, ``links`` ``(s, r, pairs)``. Returns ``[{node: track}]`` with two members or
    more, at most one track per node (a node's later track in a component is left out: first come, by node and
    track index)."""
    parent: dict[tuple[int, int], tuple[int, int]] = {}

    def find(x):
        while parent.setdefault(x, x) != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for s, r, pairs in links:
        for i, j in pairs:
            parent[find((s, i))] = find((r, j))
    groups: dict[tuple[int, int], dict[int, int]] = {}
    for s, n in enumerate(tracks):
        for i in range(n):
            if (s, i) in parent:
                g = groups.setdefault(find((s, i)), {})
                g.setdefault(s, i)
    return [g for g in groups.values() if len(g) > 1]


def _info(mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
    o = torch.cholesky_inverse(safe_cholesky(symmetrize(cov)))
    return (o @ mean.unsqueeze(-1)).squeeze(-1), o


def fuse_cluster(cluster: dict[int, int], num_nodes: int, pred: list, post: list, fusion) -> dict[int, tuple]:
    """The configured consensus on one cluster's tracks (the module's step 3): ``pred[s]``, ``post[s]`` node ``s``'s
    predicted and local posterior ``(mean (T, 4), cov (T, 4, 4))``. Returns ``{node: (mean (4,), cov (4, 4))}``."""
    q_pred = torch.zeros(num_nodes, 1, AGENT_DIM, dtype=DTYPE)
    o_pred = torch.zeros(num_nodes, 1, AGENT_DIM, AGENT_DIM, dtype=DTYPE)
    dq, do = torch.zeros_like(q_pred), torch.zeros_like(o_pred)
    members = sorted(cluster)
    for s in members:
        i = cluster[s]
        qp, op = _info(pred[s][0][i], pred[s][1][i])
        qu, ou = _info(post[s][0][i], post[s][1][i])
        q_pred[s, 0], o_pred[s, 0], dq[s, 0], do[s, 0] = qp, op, qu - qp, symmetrize(ou - op)
    naive = [s for s in range(num_nodes) if s not in cluster]
    if naive:
        q_pred[naive, 0] = q_pred[members, 0].mean(0)
        o_pred[naive, 0] = o_pred[members, 0].mean(0)
    q, o = fusion(q_pred, o_pred, dq, do)
    out = {}
    for s in members:
        oo = symmetrize(o[s, 0])
        ch = safe_cholesky(oo)
        out[s] = (torch.cholesky_solve(q[s, 0].unsqueeze(-1), ch).squeeze(-1), torch.cholesky_inverse(ch))
    return out


@dataclass
class NetworkTracks:
    """Every node's managed tracks over a batch of episodes (the module's text).

    Args:
        associator: the per-node :class:`~dslearn.association.gnn.GNN` or :class:`~dslearn.association.jpda.JPDA`.
        settings: the per-node track management.
        t2ta_gate_probability: the track-to-track association gate's :math:`P_G`.
    """

    associator: Any
    settings: TrackManagerSettings
    t2ta_gate_probability: float = 0.99
    adopt: bool = True

    def _adopt(self, managers: list[TrackManager], neighbours: list[list[int]]) -> None:
        """Step 5 of the module's text: every node takes its neighbours' confirmed tracks that match none of its own
        (the neighbours' tracks as they were before any node adopted at this step)."""
        n = self.settings.confirm_n
        offer = [m.confirmed & (m.missed_run == 0) & (m.age >= n) for m in managers]
        snap = [(m.mean[o], m.cov[o], m.missed_run[o]) for m, o in zip(managers, offer)]
        for s, mgr in enumerate(managers):
            for r in neighbours[s]:
                mean, cov, missed = snap[r]
                if not mean.shape[0]:
                    continue
                taken = {j for _, j in t2ta_pairs(mgr.mean, mgr.cov, mean, cov, self.t2ta_gate_probability)}
                new = [j for j in range(mean.shape[0]) if j not in taken]
                if new:
                    mgr.adopt(mean[new], cov[new], missed[new])

    def run(self, meas: Tensor, present: Tensor, adjacency: Tensor, model, obs, fusion, ctx) -> tuple[Tensor, Tensor]:
        """``meas (S, B, K+1, M, 2)``, ``present (S, B, K+1, M)``, ``adjacency (S, S)``. Returns every node's
        confirmed tracks' positions ``(S, B, K+1, C, 2)`` and their covariances ``(S, B, K+1, C, 2, 2)``, NaN where a
        slot holds no confirmed track (``C``: the most slots a node used, at least 1)."""
        s_n, b_n, k1 = meas.shape[:3]
        adj = torch.as_tensor(adjacency).bool().cpu()
        edges = [(s, r) for s in range(s_n) for r in range(s + 1, s_n) if bool(adj[s, r])]
        neighbours = [[r for r in range(s_n) if r != s and bool(adj[s, r])] for s in range(s_n)]
        records = []  # (s, b, t, slot, mean (2,), cov (2, 2))
        slots_used = 1
        z_all = meas.detach().to("cpu", DTYPE)
        p_all = present.detach().cpu().bool()
        for b in range(b_n):
            managers = [TrackManager(self.settings) for _ in range(s_n)]
            slot_of: list[dict[int, int]] = [{} for _ in range(s_n)]
            for t in range(k1):
                pred, post, assoc, hit = [None] * s_n, [None] * s_n, [None] * s_n, [None] * s_n
                for s, mgr in enumerate(managers):
                    if t == 0 or not len(mgr):
                        continue
                    pm, pc = predict_tracks(mgr.mean, mgr.cov, model, ctx)
                    a = self.associator.associate(pm, pc, obs, z_all[s, b, t], p_all[s, b, t])
                    pred[s], post[s], assoc[s], hit[s] = (pm, pc), (a.mean, a.cov), a, a.assigned >= 0
                fused = [dict() for _ in range(s_n)]
                if t > 0:
                    links = []
                    for s, r in edges:
                        if assoc[s] is None or assoc[r] is None:
                            continue
                        cs = managers[s].confirmed.nonzero().squeeze(-1)
                        cr = managers[r].confirmed.nonzero().squeeze(-1)
                        pairs = t2ta_pairs(post[s][0][cs], post[s][1][cs], post[r][0][cr], post[r][1][cr],
                                           self.t2ta_gate_probability)
                        links.append((s, r, [(int(cs[i]), int(cr[j])) for i, j in pairs]))
                    counts = [len(m) if assoc[k] is not None else 0 for k, m in enumerate(managers)]
                    for cl in clusters(counts, links):
                        res = fuse_cluster(cl, s_n, pred, post, fusion)
                        detected = any(bool(hit[s][i]) for s, i in cl.items())
                        for s, i in cl.items():
                            fused[s][i] = res[s]
                            hit[s] = hit[s].clone()
                            hit[s][i] = detected
                for s, mgr in enumerate(managers):
                    a = assoc[s]
                    if a is not None and fused[s]:
                        mean, cov = a.mean.clone(), a.cov.clone()
                        for i, (m_i, c_i) in fused[s].items():
                            mean[i], cov[i] = m_i, c_i
                        a = replace(a, mean=mean, cov=cov)
                    mgr.step(a, z_all[s, b, t], obs, p_all[s, b, t], hit=hit[s])
                if self.adopt:
                    self._adopt(managers, neighbours)
                for s, mgr in enumerate(managers):
                    for i in mgr.confirmed.nonzero().squeeze(-1).tolist():
                        tid = int(mgr.ids[i])
                        slot = slot_of[s].setdefault(tid, len(slot_of[s]))
                        slots_used = max(slots_used, slot + 1)
                        records.append((s, b, t, slot, mgr.mean[i, :2], mgr.cov[i, :2, :2]))
        pos = torch.full((s_n, b_n, k1, slots_used, 2), math.nan, dtype=DTYPE)
        cov = torch.full((s_n, b_n, k1, slots_used, 2, 2), math.nan, dtype=DTYPE)
        for s, b, t, slot, m, c in records:
            pos[s, b, t, slot], cov[s, b, t, slot] = m, c
        return pos, cov
