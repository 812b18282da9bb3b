r"""Placing a sensor network: node positions (given, or drawn uniformly in an area from a seed) and
its communication graph, built from config values (:func:`make_network`). The network itself and the
graph helpers are :mod:`dslearn.network`."""

from __future__ import annotations

from typing import Sequence

import torch

from dslearn.errors import ConfigError, check_positive
from dslearn.network import (SensorNetwork, adjacency_from_edges, adjacency_from_radius, adjacency_k_nearest,
                             is_connected)


def make_network(
    num_sensors: int = 4,
    num_comm: int = 6,
    area: Sequence[float] = (0.0, 8.0, 0.0, 8.0),
    positions: Sequence[Sequence[float]] | None = None,
    comm_radius: float | None = 4.0,
    edges: Sequence[Sequence[int]] | None = None,
    k_nearest: int | None = None,
    sensing_range: float = 4.0,
    meas_std: float = 0.2,
    seed: int = 0,
    max_tries: int = 1000,
) -> SensorNetwork:
    """Build a network from config values.

    Node positions are ``positions`` if given, else uniform in ``area`` = (xmin, xmax, ymin, ymax)
    drawn from ``seed``. The graph is ``edges`` if given, else ``k_nearest`` neighbours if given,
    else every pair within ``comm_radius``. With random positions and a radius graph, positions
    are redrawn (deterministically from the seed) until the graph is connected; with explicit
    positions or edges a disconnected graph is an error.
    """
    if num_sensors < 1:
        raise ConfigError(f"network.num_sensors={num_sensors} must be >= 1")
    if num_comm < 0:
        raise ConfigError(f"network.num_comm={num_comm} must be >= 0")
    check_positive("network.sensing_range", sensing_range)
    check_positive("network.meas_std", meas_std)
    if comm_radius is not None and edges is None and k_nearest is None:
        check_positive("network.comm_radius", comm_radius)
    s = num_sensors + num_comm
    gen = torch.Generator().manual_seed(int(seed))
    lo = torch.tensor([area[0], area[2]], dtype=torch.float64)
    hi = torch.tensor([area[1], area[3]], dtype=torch.float64)
    for _ in range(max_tries):
        if positions is not None:
            pos = torch.as_tensor(positions, dtype=torch.float64)
            if pos.shape != (s, 2):
                raise ConfigError(
                    f"network.positions has shape {tuple(pos.shape)}; expected ({s}, 2) for "
                    f"num_sensors + num_comm = {s}"
                )
        else:
            pos = lo + (hi - lo) * torch.rand(s, 2, generator=gen, dtype=torch.float64)
        if edges is not None:
            adj = adjacency_from_edges(s, edges)
        elif k_nearest is not None:
            adj = adjacency_k_nearest(pos, int(k_nearest))
        else:
            if comm_radius is None:
                raise ConfigError("network: give one of comm_radius, k_nearest or edges")
            adj = adjacency_from_radius(pos, float(comm_radius))
        if s == 1 or is_connected(adj) or positions is not None or edges is not None:
            break
    return SensorNetwork(pos, num_sensors, adj, float(sensing_range), float(meas_std))


#: how the config layer names it (what it does not read: dslearn.schemas.base.hook_of)
make_network.config_label = "the network part"

