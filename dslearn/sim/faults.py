r"""Faults of the data, drawn on episodes: which nodes fail when (:func:`node_failure_schedule`: a
stretch of ``duration`` steps, or for good), a failed node's lost measurements
(:func:`apply_node_failures`: ``visible`` masked) and gross measurement errors
(:func:`add_outliers`). The fusion side of a faulty network (live graphs, consensus on them) is
:mod:`dslearn.fusion.faults`.

Everything is vectorised over episodes and nodes and reproducible from the seeds. Every draw takes a
``torch.Generator`` or per-episode :class:`~dslearn.streams.Streams` over ``(B,)``; with streams, an
episode's faults depend only on its own key, never on which episodes share its batch.
"""

from __future__ import annotations

import torch
from torch import Tensor

from dslearn.episodes import Episodes
from dslearn.errors import ConfigError, check_choice
from dslearn.streams import Streams, rand, randn

NODE_FAIL_MODES = ("permanent", "transient")


def node_failure_schedule(
    num_nodes: int,
    batch: int,
    steps: int,
    frac: float,
    gen: torch.Generator | Streams,
    mode: str = "permanent",
    duration: int = 4,
) -> Tensor:
    """Which node is alive when: ``(S, B, K+1)`` bool.

    In each episode ``round(frac * S)`` distinct nodes (chosen at random) fail at a step drawn
    uniformly in ``1..K``: for good (``permanent``) or for ``duration`` steps (``transient``).
    Every node is alive at ``t = 0``.
    """
    if not 0.0 <= float(frac) <= 1.0:
        raise ConfigError(f"faults.node_fail={frac!r} must be a fraction in [0, 1]")
    check_choice("faults.node_fail_mode", mode, NODE_FAIL_MODES)
    if int(duration) < 1:
        raise ConfigError(f"faults.node_fail_duration={duration!r} must be >= 1 step")
    n_fail = int(round(frac * num_nodes))
    alive = torch.ones(num_nodes, batch, steps + 1, dtype=torch.bool)
    if n_fail == 0 or steps < 1:
        return alive
    order = rand((batch, num_nodes), gen).argsort(-1)  # random permutation per episode
    failed = torch.zeros(batch, num_nodes, dtype=torch.bool)
    failed.scatter_(1, order[:, :n_fail], True)
    start = 1 + (rand((batch, num_nodes), gen) * steps).long().clamp_max(steps - 1)  # uniform in 1..K
    t = torch.arange(steps + 1).view(1, 1, -1)
    down = t >= start.unsqueeze(-1)
    if mode == "transient":
        down = down & (t < (start + int(duration)).unsqueeze(-1))
    down = down & failed.unsqueeze(-1)  # (B, S, K+1)
    return ~down.permute(1, 0, 2)


def apply_node_failures(ep: Episodes, alive: Tensor) -> Episodes:
    """A failed node measures nothing: ``visible &= alive`` (``alive (S, B, K+1)``)."""
    vis = ep.visible & alive.to(ep.visible.device).unsqueeze(-1)
    return Episodes(ep.states, torch.where(vis.unsqueeze(-1), ep.meas, torch.zeros_like(ep.meas)), vis)


def add_outliers(ep: Episodes, frac: float, std: float, gen: torch.Generator | Streams) -> tuple[Episodes, Tensor]:
    """Replace a fraction ``frac`` of the measurements by gross errors ``z + N(0, std^2 I)``.

    Returns the new episodes and the ``(S, B, K+1, A)`` bool mask of corrupted measurements.
    """
    if not 0.0 <= float(frac) <= 1.0:
        raise ConfigError(f"faults.outlier_frac={frac!r} must be a fraction in [0, 1]")
    if frac > 0 and not float(std) > 0:
        raise ConfigError(f"faults.outlier_std={std!r} must be > 0")
    s, b = ep.visible.shape[:2]
    rest = tuple(ep.visible.shape[2:])
    # drawn episode-first (one stream per episode), then nodes first like the episodes
    hit = (rand((b, s, *rest), gen) < frac).transpose(0, 1).to(ep.visible.device) & ep.visible
    noise = randn((b, s, *rest, 2), gen).transpose(0, 1).to(ep.meas) * float(std)
    meas = ep.meas + noise * hit.unsqueeze(-1)
    return Episodes(ep.states, meas, ep.visible), hit
