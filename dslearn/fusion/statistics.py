r"""Cooperation on sufficient statistics (Section V): non-cooperative, centralised, average consensus.

* non-cooperative: each node runs the M-step on its own statistics;
* centralised: a fusion centre averages the local statistics (Eq. 19), runs the M-step and sends the
  parameters back;
* consensus: q_max rounds of ``zeta_s <- a_ss zeta_s + sum_{r in Gamma(s)} a_sr zeta_r`` (Eq. 20,
  Algorithm 3), each node then runs the M-step on its own ``zeta_s``.

All three are linear maps of the stacked local statistics, so for a batch of strategies they are applied
as one ``(C, S, S)`` tensor (:func:`combination_matrices`); :func:`average_consensus` is the literal
Algorithm 3 loop and is what builds the consensus maps.

Throughput (Table II) is counted from what each strategy transmits (:func:`throughput_bytes_per_step`).
"""

from __future__ import annotations

import re

import torch
from torch import Tensor

from dslearn.errors import ConfigError
from dslearn.fusion.weights import half_max_degree, max_degree, metropolis
from dslearn.network import adjacency_from_edges, is_connected

#: ``task.consensus.weights`` of the Braga study -> rule (``matrix``: the explicit ``task.consensus.matrix``).
#: ``half_max_degree`` is the paper's Eq. (26), 1/(2 d_max); ``max_degree_core`` is 1/(1 + d_max)
#: (:func:`dslearn.fusion.weights.max_degree`).
STAT_WEIGHT_RULES = {"half_max_degree": half_max_degree, "max_degree_core": max_degree, "metropolis": metropolis,
                     "matrix": None}
#: the retired value: it meant 1/(2 d_max) here but means 1/(1 + d_max) in dslearn.fusion.weights
RETIRED_RULES = {"max_degree": "it meant 1/(2 d_max) here (the paper's Eq. 26) but 1/(1 + d_max) in "
                               "dslearn.fusion.weights; use half_max_degree (Eq. 26, the old meaning) or "
                               "max_degree_core (1/(1 + d_max))"}


def check_eq22(a: Tensor, adj: Tensor | None = None, atol: float = 1e-9) -> None:
    r"""Check the average-consensus convergence conditions of Eq. (22).

    (22a) :math:`1^T A = 1^T`, (22b) :math:`A 1 = 1`, (22c) :math:`\rho(A - 11^T/N_S) < 1`;
    plus sparsity (``a_sr = 0`` when r is not a neighbour of s) when ``adj`` is given.

    Raises:
        ConfigError: naming the violated condition.
    """
    a = torch.as_tensor(a, dtype=torch.float64)
    if a.ndim != 2 or a.shape[0] != a.shape[1]:
        raise ConfigError(f"task.consensus.matrix must be square (N_S, N_S), got shape {tuple(a.shape)}")
    n = a.shape[0]
    one = torch.ones(n, dtype=a.dtype)
    if not torch.isfinite(a).all():
        raise ConfigError("task.consensus.matrix must be finite")
    if not torch.allclose(one @ a, one, atol=atol):
        raise ConfigError(f"consensus weight matrix violates Eq. (22a) 1^T A = 1^T: column sums {(one @ a).tolist()}")
    if not torch.allclose(a @ one, one, atol=atol):
        raise ConfigError(f"consensus weight matrix violates Eq. (22b) A 1 = 1: row sums {(a @ one).tolist()}")
    rho = torch.linalg.eigvals(a - torch.ones(n, n, dtype=a.dtype) / n).abs().max().item()
    if not rho < 1.0 - 1e-12:
        raise ConfigError(f"consensus weight matrix violates Eq. (22c) rho(A - 11^T/N_S) < 1: rho = {rho:.6g}")
    if adj is not None:
        allowed = torch.as_tensor(adj).to(torch.bool) | torch.eye(n, dtype=torch.bool)
        if (a.abs() > atol)[~allowed].any():
            raise ConfigError("task.consensus.matrix puts weight on a pair of nodes that are not linked in task.network.edges")


def weight_matrix(adj: Tensor, rule: str = "half_max_degree", matrix=None) -> Tensor:
    """Consensus weight matrix by rule (:data:`STAT_WEIGHT_RULES`), checked against Eq. (22).

    Args:
        adj: (S, S) bool adjacency.
        rule: ``half_max_degree`` (paper, Eq. 26: 1/(2 d_max)), ``max_degree_core`` (1/(1+d_max)),
            ``metropolis`` or ``matrix`` (use ``matrix`` as given).
        matrix: explicit (S, S) weights for ``rule == "matrix"``.
    """
    if rule in RETIRED_RULES:
        raise ConfigError(f"task.consensus.weights={rule!r} is ambiguous and no longer accepted: {RETIRED_RULES[rule]}")
    if rule not in STAT_WEIGHT_RULES:
        raise ConfigError(f"task.consensus.weights={rule!r} is not allowed; choose one of {list(STAT_WEIGHT_RULES)}")
    if rule == "matrix":
        if matrix is None:
            raise ConfigError("task.consensus.weights=matrix needs task.consensus.matrix (an N_S×N_S list)")
        a = torch.as_tensor(matrix, dtype=torch.float64)
    else:
        a = STAT_WEIGHT_RULES[rule](adj)
    check_eq22(a, adj)
    return a


def average_consensus(zeta: Tensor, a: Tensor, q_max: int) -> Tensor:
    """Algorithm 3 for all nodes at once: q_max rounds of zeta <- A zeta (Eq. 20).

    Args:
        zeta: (..., S, D) initial states zeta^{(0)}_s = S_{s,t}.
        a: (S, S) weights.
        q_max: number of iterations.
    """
    for _ in range(int(q_max)):
        zeta = torch.einsum("sr,...rd->...sd", a.to(zeta), zeta)
    return zeta


def parse_strategy(name: str) -> tuple[str, int]:
    """'noncooperative' | 'centralised' | 'consensus_<q>' -> (kind, q)."""
    if name in ("noncooperative", "centralised"):
        return name, 0
    m = re.fullmatch(r"consensus_(\d+)", str(name))
    if m and int(m.group(1)) >= 1:
        return "consensus", int(m.group(1))
    raise ConfigError(f"task.strategies entry {name!r} is not allowed; use noncooperative, centralised or "
                      "consensus_<q> with q >= 1 (e.g. consensus_10)")


def combination_matrices(strategies, a: Tensor) -> Tensor:
    """Linear map applied to the stacked node statistics per strategy. -> (C, S, S).

    noncooperative: I; centralised: 11^T/S (Eq. 19, every node gets the fusion centre's average);
    consensus_q: A^q built by running :func:`average_consensus` on the identity.
    """
    s = a.shape[0]
    eye = torch.eye(s, dtype=a.dtype, device=a.device)
    mats = []
    for name in strategies:
        kind, q = parse_strategy(name)
        if kind == "noncooperative":
            mats.append(eye)
        elif kind == "centralised":
            mats.append(torch.full((s, s), 1.0 / s, dtype=a.dtype, device=a.device))
        else:
            mats.append(average_consensus(eye, a, q))  # A^q I
    return torch.stack(mats)


def hop_distances(adj: Tensor, source: int) -> Tensor:
    """Breadth-first hop counts from ``source``. adj: (S, S) bool -> (S,) long."""
    adj = torch.as_tensor(adj).to(torch.bool)
    s = adj.shape[0]
    dist = torch.full((s,), -1, dtype=torch.long)
    dist[source] = 0
    frontier = torch.zeros(s, dtype=torch.bool)
    frontier[source] = True
    h = 0
    while frontier.any():
        h += 1
        nxt = adj[frontier].any(0) & (dist < 0)
        dist[nxt] = h
        frontier = nxt
    return dist


def throughput_bytes_per_step(name: str, adj: Tensor, n_stats: int, n_params: int, *, fusion_centre: int = 0,
                              bytes_per_float: int = 4) -> int:
    """Bytes the whole network transmits per estimation step for one strategy (Table II).

    * noncooperative: nothing.
    * centralised: every other node's statistics travel to the fusion centre along a shortest path
      (one transmission per hop: ``sum_s hops(s, fc) * n_stats`` floats), and the fusion centre's
      parameters are flooded back along a spanning tree (``(S-1) * n_params`` floats).
    * consensus_q: in each of the q rounds every node sends its statistics to each neighbour
      (``q * sum_s deg(s) * n_stats`` floats).
    """
    adj = torch.as_tensor(adj).to(torch.bool)
    kind, q = parse_strategy(name)
    s = adj.shape[0]
    if kind == "noncooperative":
        floats = 0
    elif kind == "centralised":
        hops = hop_distances(adj, fusion_centre)
        floats = int(hops.sum()) * n_stats + (s - 1) * n_params
    else:
        a = adj.clone()
        a.fill_diagonal_(False)
        floats = q * int(a.sum()) * n_stats
    return floats * bytes_per_float


def network_adjacency(num_nodes: int, edges) -> Tensor:
    """Adjacency from an edge list, required connected (else ConfigError)."""
    adj = adjacency_from_edges(num_nodes, edges)
    if not is_connected(adj):
        raise ConfigError(f"task.network.edges={edges!r} do not connect all {num_nodes} nodes")
    return adj
