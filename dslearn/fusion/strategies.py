r"""Fusion strategies for distributed information filters (Yu et al. Algorithm 3 and its relatives).

Every strategy takes the nodes' prior information :math:`(q^{t|t-1}, \Omega^{t|t-1})` and novel
information :math:`(\delta q, \delta\Omega)`, all ``(S, B, ...)`` (nodes first), and returns
the fused posterior pair. ``L`` rounds of :math:`y_i \leftarrow \sum_j \pi_{ij} y_j` are applied
as one product with :math:`W^L` (identical, and ``L`` times cheaper than looping).
"""

from __future__ import annotations

import numbers

import torch
from torch import Tensor

from dslearn.errors import ConfigError, check_choice
from dslearn.types import symmetrize

FUSIONS = ("individual", "ce", "cm", "ci", "hybrid", "centralized")


def check_consensus(iterations, omega) -> None:
    """The rules of a fusion's ``consensus.iterations`` (``L``, an integer >= 0) and ``consensus.omega`` (``one``,
    ``nodes`` or a finite number > 0), each refused naming its key: the fusion's constructor and the core study's
    schema check (which refuses them before the fusions of a grid are built) apply these."""
    if int(iterations) != iterations or iterations < 0:
        raise ConfigError(f"consensus.iterations={iterations!r} must be an integer >= 0")
    if isinstance(omega, str):
        check_choice("consensus.omega", omega, ("one", "nodes"))
    elif isinstance(omega, bool) or not isinstance(omega, numbers.Real) or not 0 < omega < float("inf"):
        raise ConfigError(f"consensus.omega={omega!r} must be > 0 and finite, 'one' or 'nodes'")


def mix(w: Tensor, y: Tensor) -> Tensor:
    """One (or, with ``W^L``, several) consensus rounds: ``(S, S) x (S, ...) -> (S, ...)``.

    A batched ``w`` of shape ``(B, S, S)`` (one weight matrix per episode, e.g. the live graph
    of a faulty network, :mod:`dslearn.fusion.faults`) mixes ``y (S, B, ...)`` episode by episode.
    """
    if w.ndim == 3:
        return torch.einsum("bij,jb...->ib...", w.to(y), y)
    return torch.einsum("ij,j...->i...", w.to(y), y)


class Fusion:
    r"""Base class. ``iterations`` = L; ``omega`` scales the novel information (hybrid and CM).

    Args:
        weights: ``(S, S)`` consensus weight matrix.
        iterations: number of consensus rounds ``L >= 0``.
        omega: novel-information weight :math:`\omega`: a number, ``"one"`` (the paper, 1) or
            ``"nodes"`` (the number of nodes, as in Battistelli & Chisci 2016).
    """

    name = "base"
    uses_omega = False
    #: the keys of its ``conf/consensus`` node it reads (:func:`dslearn.schemas.base.unread_keys`) and why it reads no
    #: other; ``uses_links``: whether it sends anything over the network's links (else the links are not read)
    config_reads: tuple[str, ...] = ("iterations", "weights", "omega")
    config_unread = "it reads iterations, weights and omega"
    uses_links = True
    #: whether a node fuses only its own readings (no fusion with any other node)
    alone = False
    #: whether it runs consensus rounds: mixes the nodes' information with ``W^L`` (its weights and ``iterations``
    #: act); ``False``: each node alone or a fusion centre (no rounds, no weights)
    mixes = True
    #: whether every node holds one and the same belief (a fusion centre's): the filter then predicts it once
    #: (:func:`dslearn.filters.distributed.track`) and a motion model with per-node state is built for one node
    centre = False

    @classmethod
    def spec_misfit(cls, spec) -> str | None:
        """What the fusion needs of a scenario, declared (:func:`dslearn.methods.base.declared_misfit`): a strategy that
        sends information over the network's links needs a communication graph between the nodes, and nodes that
        share something to agree on (not nodes navigating themselves, ``spec.navigates_itself``)."""
        if not cls.uses_links:
            return None
        if not spec.networked:
            return (f"consensus={cls.name} exchanges information with neighbours over a communication graph; the "
                    f"sensors of scenario {spec.name} have none (they report to a fusion centre: consensus=centralized)")
        if spec.navigates_itself:
            return (f"consensus={cls.name} makes the nodes agree on the targets they all track; on scenario {spec.name} "
                    f"every node navigates itself (no node measures another's platform), so each platform's "
                    f"information has one source and consensus rounds only mix it with the neighbours' predictions "
                    f"(consensus=individual: each node alone; centralized gives each node its own the same)")
        return None

    def __init__(self, weights: Tensor, iterations: int = 4, omega: float | str = "one"):
        check_consensus(iterations, omega)
        self.weights = weights
        self.iterations = int(iterations)
        s = weights.shape[0]
        if isinstance(omega, str):
            self.omega = 1.0 if omega == "one" else float(s)
        else:
            self.omega = float(omega)
        self.omega_label = str(omega)
        self.wl = torch.linalg.matrix_power(weights, self.iterations)

    @property
    def rounds(self) -> int:
        """The consensus rounds it runs: ``iterations`` where it :attr:`mixes`, else 0."""
        return self.iterations if self.mixes else 0

    @classmethod
    def for_network(cls, *, adjacency: Tensor, weights: str = "uniform", iterations: int = 4,
                    omega: float | str = "one") -> "Fusion":
        """The config factory (``conf/consensus/*.yaml``): the weight matrix of rule ``weights``
        (:func:`~dslearn.fusion.weights.consensus_weights`) over the graph ``adjacency``."""
        from dslearn.fusion.weights import consensus_weights

        fusion = cls(consensus_weights(adjacency, weights), iterations, omega)
        fusion.weights_rule = str(weights)
        return fusion

    def __call__(self, q_pred: Tensor, o_pred: Tensor, dq: Tensor, do: Tensor,
                 wl: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Fuse: prior pair ``(S, B, Dx)``, ``(S, B, Dx, Dx)`` and novel pair of the same shapes.
        ``wl``: this step's ``W^L`` (``(S, S)`` or per episode ``(B, S, S)``) instead of the
        nominal one, e.g. on a faulty network (:class:`~dslearn.fusion.faults.FaultyFusion`)."""
        raise NotImplementedError


class Individual(Fusion):
    """No communication: each node fuses only its own measurements."""

    name = "individual"
    config_reads = ()
    config_unread = "each node alone: no consensus rounds"
    uses_links = False
    alone = True
    mixes = False

    def __call__(self, q_pred, o_pred, dq, do, wl=None):
        return q_pred + dq, symmetrize(o_pred + do)


class Centralized(Fusion):
    r"""Reference: every node receives all measurements, :math:`\Omega = \Omega^{t|t-1} + \sum_i \delta\Omega_i`.

    Starting from a common prior, all nodes then hold the centralised information filter.
    """

    name = "centralized"
    config_reads = ()
    config_unread = "a fusion centre: no consensus rounds"
    uses_links = False
    mixes = False
    centre = True

    def __call__(self, q_pred, o_pred, dq, do, wl=None):
        return q_pred + dq.sum(0, keepdim=True), symmetrize(o_pred + do.sum(0, keepdim=True))


class ConsensusOnMeasurements(Fusion):
    r"""CM: :math:`L` rounds on the novel information only, :math:`q = q^{t|t-1} + \omega\,\delta q(L)`."""

    name = "cm"
    uses_omega = True

    def __call__(self, q_pred, o_pred, dq, do, wl=None):
        w = self.wl if wl is None else wl
        return q_pred + self.omega * mix(w, dq), symmetrize(o_pred + self.omega * mix(w, do))


class ConsensusOnInformation(Fusion):
    r"""CI: local posterior first, then :math:`L` rounds on the posterior information pair."""

    name = "ci"
    config_reads = ("iterations", "weights")
    config_unread = "omega weighs the novel information of consensus=hybrid|cm only"

    def __call__(self, q_pred, o_pred, dq, do, wl=None):
        w = self.wl if wl is None else wl
        return mix(w, q_pred + dq), symmetrize(mix(w, o_pred + do))


class HybridConsensus(Fusion):
    r"""Hybrid CMCI (Algorithm 3): :math:`L` rounds on both prior and novel pairs, then
    :math:`q = q^{t|t-1}(L) + \omega\,\delta q(L)`, :math:`\Omega = \Omega^{t|t-1}(L) + \omega\,\delta\Omega(L)`.

    Line 8 of the printed algorithm averages :math:`\delta q` into :math:`\Omega^{t|t-1}`; that is a
    typo, and the prior information matrix itself is averaged here.
    """

    name = "hybrid"
    uses_omega = True

    def __call__(self, q_pred, o_pred, dq, do, wl=None):
        w = self.wl if wl is None else wl
        q = mix(w, q_pred) + self.omega * mix(w, dq)
        o = mix(w, o_pred) + self.omega * mix(w, do)
        return q, symmetrize(o)


class ConsensusOnEstimates(Fusion):
    r"""CE: local posterior, then :math:`L` rounds of averaging the *estimates* :math:`\hat y`
    (the information matrices stay local). Returns the information pair of the averaged estimate.
    """

    name = "ce"
    config_reads = ("iterations", "weights")
    config_unread = "omega weighs the novel information of consensus=hybrid|cm only"

    def __call__(self, q_pred, o_pred, dq, do, wl=None):
        w = self.wl if wl is None else wl
        o = symmetrize(o_pred + do)
        y = torch.linalg.solve(o, (q_pred + dq).unsqueeze(-1)).squeeze(-1)
        y = mix(w, y)
        return (o @ y.unsqueeze(-1)).squeeze(-1), o


_CLASSES = {
    c.name: c
    for c in (Individual, Centralized, ConsensusOnMeasurements, ConsensusOnInformation, HybridConsensus, ConsensusOnEstimates)
}


def make_fusion(name: str, weights: Tensor, iterations: int = 4, omega: float | str = "one") -> Fusion:
    """Fusion strategy by config name (one of :data:`FUSIONS`)."""
    check_choice("consensus.name", name, FUSIONS)
    return _CLASSES[name](weights, iterations, omega)
