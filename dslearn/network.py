r"""Sensor network: node positions, sensing nodes, communication graph.

A network has ``S`` nodes. The first ``num_sensors`` are *sensing* nodes (they measure
targets within ``sensing_range``); the rest are communication-only nodes. Every node runs a
local filter and exchanges information with its graph neighbours.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import torch
from torch import Tensor

from dslearn.errors import ConfigError, check_positive


def is_connected(adj: Tensor) -> bool:
    """Whether the undirected graph with adjacency ``adj`` (S, S) is connected (BFS)."""
    adj = torch.as_tensor(adj).to(torch.bool)
    s = adj.shape[0]
    if s == 0:
        return False
    seen = torch.zeros(s, dtype=torch.bool)
    seen[0] = True
    frontier = seen.clone()
    while frontier.any():
        nxt = adj[frontier].any(0) & ~seen
        seen |= nxt
        frontier = nxt
    return bool(seen.all())


def adjacency_from_radius(positions: Tensor, radius: float) -> Tensor:
    """Nodes closer than ``radius`` are linked. positions: (S, 2) -> (S, S) bool."""
    d = torch.cdist(positions, positions)
    adj = d <= radius
    adj.fill_diagonal_(False)
    return adj


def adjacency_from_edges(num_nodes: int, edges: Sequence[Sequence[int]]) -> Tensor:
    """Undirected adjacency from an explicit 0-based edge list."""
    adj = torch.zeros(num_nodes, num_nodes, dtype=torch.bool)
    for k, e in enumerate(edges):
        if len(e) != 2:
            raise ConfigError(f"network.edges[{k}]={list(e)!r} must be a pair [i, j]")
        i, j = int(e[0]), int(e[1])
        if not (0 <= i < num_nodes and 0 <= j < num_nodes) or i == j:
            raise ConfigError(
                f"network.edges[{k}]={[i, j]!r}: node ids must be distinct and in 0..{num_nodes - 1}"
            )
        adj[i, j] = adj[j, i] = True
    return adj


def adjacency_k_nearest(positions: Tensor, k: int) -> Tensor:
    """Each node linked to its ``k`` nearest nodes (symmetrised)."""
    d = torch.cdist(positions, positions)
    d.fill_diagonal_(float("inf"))
    idx = d.topk(min(k, positions.shape[0] - 1), largest=False).indices
    adj = torch.zeros_like(d, dtype=torch.bool)
    adj.scatter_(1, idx, True)
    return adj | adj.T


@dataclass
class SensorNetwork:
    """A sensor network.

    Attributes:
        positions: (S, 2) node positions.
        num_sensors: the first ``num_sensors`` nodes can measure targets.
        adjacency: (S, S) symmetric bool communication graph, connected.
        sensing_range: a sensing node measures a target closer than this.
        meas_std: measurement noise standard deviation (per coordinate).
    """

    positions: Tensor
    num_sensors: int
    adjacency: Tensor
    sensing_range: float = 4.0
    meas_std: float = 0.2
    names: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        s = self.positions.shape[0]
        if self.positions.ndim != 2 or self.positions.shape[-1] != 2:
            raise ConfigError(f"network.positions must have shape (S, 2), got {tuple(self.positions.shape)}")
        if not 1 <= self.num_sensors <= s:
            raise ConfigError(f"network.num_sensors={self.num_sensors} must be in 1..{s}")
        check_positive("network.sensing_range", self.sensing_range)
        check_positive("network.meas_std", self.meas_std)
        if tuple(self.adjacency.shape) != (s, s):
            raise ConfigError("network adjacency must be (S, S) for S nodes")
        if s > 1 and not is_connected(self.adjacency):
            raise ConfigError(
                "network communication graph is disconnected; increase network.comm_radius "
                "or give a connected network.edges list"
            )
        if not self.names:
            self.names = [f"sensor{i + 1}" for i in range(self.num_sensors)] + [
                f"comm{i + 1}" for i in range(s - self.num_sensors)
            ]

    @property
    def num_nodes(self) -> int:
        return self.positions.shape[0]

    @property
    def is_sensor(self) -> Tensor:
        """(S,) bool: which nodes can measure."""
        m = torch.zeros(self.num_nodes, dtype=torch.bool)
        m[: self.num_sensors] = True
        return m

    def neighbors(self, i: int) -> list[int]:
        return torch.nonzero(self.adjacency[i]).flatten().tolist()

    def visible(self, target_pos: Tensor) -> Tensor:
        """Which sensing nodes see which targets.

        Args:
            target_pos: (*B, A, 2) target positions.
        Returns:
            (S, *B, A) bool; communication-only nodes see nothing.
        """
        p = self.positions.to(target_pos)
        d = (target_pos.unsqueeze(0) - p.reshape(p.shape[0], *([1] * (target_pos.ndim - 1)), 2)).norm(dim=-1)
        vis = d <= self.sensing_range
        vis[self.num_sensors :] = False
        return vis
