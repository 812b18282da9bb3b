r"""Cooperation on sufficient statistics (Braga et al., Section V) as the fusion part of a method: how the
nodes' local online-EM statistics are combined before each node's M-step. A part of its own kind
(``kind = "statistics"``), distinct from the information-form fusions of :mod:`dslearn.fusion.strategies`
and the GP aggregation rules of :mod:`dslearn.fusion.aggregation`: a method declares the kind it takes
(Braga et al.'s RBPF + online EM, :class:`dslearn.methods.rbpf.RBPFMethod`).

Strategies (:func:`dslearn.fusion.statistics.parse_strategy`): ``noncooperative`` (each node its own
statistics), ``centralised`` (a fusion centre averages them, Eq. 19) and ``consensus_<q>`` (``q`` rounds of
average consensus, Eq. 20 / Algorithm 3, with the weights of a rule checked against Eq. 22).
"""

from __future__ import annotations

import torch
from torch import Tensor

from dslearn.errors import ConfigError
from dslearn.fusion.statistics import RETIRED_RULES, STAT_WEIGHT_RULES, combination_matrices, parse_strategy, weight_matrix

#: the default weight rule (Braga et al.'s Eq. 26: 1 / (2 d_max))
DEFAULT_WEIGHTS = "half_max_degree"


class StatisticsConsensus:
    """The combination of the local sufficient statistics over a communication graph.

    Args:
        adjacency: ``(S, S)`` bool communication graph (the scenario's network, connected).
        strategy: ``noncooperative`` | ``centralised`` | ``consensus_<q>`` (``q >= 1`` rounds).
        weights: the consensus weight rule of ``consensus_<q>`` (:data:`~dslearn.fusion.statistics.STAT_WEIGHT_RULES`;
            ``matrix``: the explicit ``matrix``); the other strategies use no weights and refuse another rule.
        matrix: the explicit ``(S, S)`` weights of ``weights=matrix`` (checked against Eq. 22 and the graph).
    """

    kind = "statistics"

    def __init__(self, adjacency: Tensor, strategy: str = "consensus_10", weights: str = DEFAULT_WEIGHTS,
                 matrix=None):
        try:
            kind, q = parse_strategy(str(strategy))
        except ConfigError:
            raise ConfigError(f"consensus.strategy={strategy!r} is not allowed; use noncooperative, centralised or "
                              "consensus_<q> with q >= 1 (e.g. consensus_10)") from None
        if weights in RETIRED_RULES:
            raise ConfigError(f"consensus.weights={weights!r} is ambiguous and not accepted: {RETIRED_RULES[weights]}")
        if weights not in STAT_WEIGHT_RULES:
            raise ConfigError(f"consensus.weights={weights!r} is not allowed; choose one of {list(STAT_WEIGHT_RULES)}")
        if kind != "consensus" and (weights != DEFAULT_WEIGHTS or matrix is not None):
            raise ConfigError(f"consensus.strategy={strategy} combines the statistics without consensus weights; "
                              f"consensus.weights / consensus.matrix apply to consensus_<q> only (leave "
                              f"weights={DEFAULT_WEIGHTS}, matrix=null)")
        if matrix is not None and weights != "matrix":
            raise ConfigError(f"consensus.matrix is used with consensus.weights=matrix only (weights={weights})")
        adj = torch.as_tensor(adjacency).to(torch.bool)
        try:
            self.weights = weight_matrix(adj, weights, matrix)  # (S, S) float64, Eq. 22 checked
        except ConfigError as e:
            raise ConfigError(str(e).replace("task.consensus.", "consensus.").replace("task.network.edges",
                                                                                       "the scenario's network")) from None
        self.strategy = str(strategy)
        self.rule = str(weights)
        self.iterations = q

    @property
    def name(self) -> str:
        return self.strategy

    def matrix(self) -> Tensor:
        """The linear map applied to the stacked statistics ``(S, S)`` (identity, ``11^T / S`` or ``A^q``)."""
        return combination_matrices([self.strategy], self.weights)[0]

    def __repr__(self) -> str:
        return f"StatisticsConsensus(strategy={self.strategy!r}, weights={self.rule!r})"
