r"""Fusion on an unreliable network: link failures, failed nodes' links, time-varying topologies.

:class:`FaultyFusion` wraps any :class:`~dslearn.fusion.strategies.Fusion`. At every filter step it
draws the *live graph* of every episode from a seeded ``torch.Generator``: each link of the nominal
graph is up with probability ``1 - p_link`` (independently per step and episode: a time-varying
topology), and links of failed nodes are down. Consensus then uses only the messages that arrive:
the weights are recomputed on the live graph (Metropolis :math:`w_{ij} = 1/(1+\max(d_i, d_j))` by
default, or the paper's uniform :math:`1/(|N_i|+1)`), one ``(B, S, S)`` matrix per episode and step,
and ``L`` rounds are ``W^L`` (batched ``matrix_power``). A node without live links keeps its own
belief (:math:`w_{ii} = 1`). Individual and centralised fusion do not exchange messages and ignore
the graph (centralised stays the all-measurements reference).

The faults of the data (which nodes fail when, their lost measurements, gross outliers) are drawn
on the episodes by :mod:`dslearn.sim.faults`; the robust update is chi-square gating on the
innovation (``novel_information(..., gate_prob=p)``, passed through ``track(..., gate_prob=p)``).

Everything is vectorised over episodes and nodes and reproducible from the seeds. Every draw
takes a ``torch.Generator`` or per-episode :class:`~dslearn.streams.Streams` over ``(B,)``; with
streams, an episode's faults depend only on its own key, never on which episodes share its batch.
"""

from __future__ import annotations

import torch
from torch import Tensor

from dslearn.errors import ConfigError, check_choice
from dslearn.fusion.strategies import Fusion
from dslearn.streams import Streams, rand

LIVE_WEIGHTS = ("metropolis", "uniform")


def live_weights(live: Tensor, method: str = "metropolis") -> Tensor:
    """Consensus weights on live graphs.

    Args:
        live: ``(B, S, S)`` bool symmetric adjacency of the links that work (diagonal ignored).
        method: ``metropolis`` (doubly stochastic) or ``uniform`` (row-stochastic, the paper's).
    Returns:
        ``(B, S, S)`` float64 weights; an isolated node gets ``w_ii = 1``.
    """
    check_choice("faults.weights", method, LIVE_WEIGHTS)
    s = live.shape[-1]
    eye = torch.eye(s, dtype=torch.bool, device=live.device)
    a = (live & ~eye).to(torch.float64)
    deg = a.sum(-1)  # (B, S)
    if method == "metropolis":
        w = a / (1.0 + torch.maximum(deg.unsqueeze(-1), deg.unsqueeze(-2)))
        return w + torch.diag_embed(1.0 - w.sum(-1))
    m = a + torch.eye(s, dtype=torch.float64, device=live.device)
    return m / m.sum(-1, keepdim=True)


def draw_live_graph(adj: Tensor, alive: Tensor, p_link: float, gen: torch.Generator | Streams) -> Tensor:
    """One step's live graphs: ``adj (S, S)``, ``alive (B, S)`` -> ``(B, S, S)`` bool.

    Each undirected link is up with probability ``1 - p_link`` (one draw per link, episode and
    step), and only between nodes that are both alive.
    """
    b, s = alive.shape
    up = adj.to(torch.bool).unsqueeze(0).expand(b, s, s)
    if p_link > 0:
        u = rand((b, s, s), gen)
        u = torch.triu(u, 1)
        u = u + u.transpose(-1, -2)  # symmetric: one draw per undirected link
        up = up & (u >= p_link)
    return up & alive.unsqueeze(-1) & alive.unsqueeze(-2)


class FaultyFusion:
    """A fusion strategy on an unreliable network (see the module docstring).

    Call :meth:`begin` with the node-alive schedule before each :func:`dslearn.filters.distributed.track`
    call; every call of the object is one filter step ``t = 1, 2, ...``.

    Args:
        base: the fusion strategy (its ``iterations``, ``omega`` and type are kept).
        adjacency: ``(S, S)`` nominal communication graph.
        p_link: per-step link failure probability in ``[0, 1]``.
        weights: live-graph weights, ``metropolis`` or ``uniform``.
        seed: seed of the link-failure draws: with :meth:`begin`'s ``episodes``, episode ``e`` of
            ``split`` draws from its own stream keyed ``(seed, split, e)`` (reset at every
            :meth:`begin`); otherwise one generator for the batch (reset by ``reseed=True``).
    """

    def __init__(self, base: Fusion, adjacency: Tensor, p_link: float = 0.0, weights: str = "metropolis", seed: int = 0):
        if not 0.0 <= float(p_link) <= 1.0:
            raise ConfigError(f"faults.link_fail={p_link!r} must be a probability in [0, 1]")
        check_choice("faults.weights", weights, LIVE_WEIGHTS)
        self.base = base
        self.adj = torch.as_tensor(adjacency).to(torch.bool)
        self.p_link = float(p_link)
        self.method = weights
        self.seed = int(seed)
        self.gen = torch.Generator().manual_seed(self.seed)
        self.alive: Tensor | None = None
        self.t = 0
        self.live_links = 0.0  # running count of live links (diagnostics)
        self.nominal_links = 0.0

    # the wrapped strategy's labels
    @property
    def name(self) -> str:
        return self.base.name

    def __getattr__(self, item):  # iterations, omega, omega_label, uses_omega, weights ...
        if item == "base":
            raise AttributeError(item)
        return getattr(self.base, item)

    def begin(self, alive: Tensor | None, batch: int | None = None, reseed: bool = False,
              episodes: list[int] | None = None, split: str = "test") -> None:
        """Start a track() call: ``alive (S, B, K+1)`` bool (None = every node always alive).

        ``episodes``: the indices of the batch's episodes in ``split``: each draws its link
        failures from its own stream (the same whatever batch it is tracked in)."""
        if episodes is not None:
            self.gen = Streams.from_keys([(self.seed, split, int(e)) for e in episodes], (len(episodes),))
        elif reseed:
            self.gen = torch.Generator().manual_seed(self.seed)
        if alive is None:
            if batch is None:
                raise ValueError("begin(None) needs the batch size")
            alive = torch.ones(self.adj.shape[0], batch, 1, dtype=torch.bool)
        self.alive = alive
        self.t = 0

    def __call__(self, q_pred: Tensor, o_pred: Tensor, dq: Tensor, do: Tensor) -> tuple[Tensor, Tensor]:
        # the first call after begin() is the initial belief's fusion (t = 0), then t = 1, 2, ...
        tt = self.t
        self.t += 1
        if not self.base.mixes:  # no consensus rounds: no links to fail
            return self.base(q_pred, o_pred, dq, do)
        if self.alive is None:
            raise RuntimeError("FaultyFusion.begin(alive) must be called before tracking")
        tt = min(tt, self.alive.shape[-1] - 1)
        alive_t = self.alive[:, :, tt].T.to(self.adj.device)  # (B, S)
        live = draw_live_graph(self.adj, alive_t, self.p_link, self.gen)
        self.live_links += float(live.sum()) / 2
        self.nominal_links += float(self.adj.sum()) / 2 * live.shape[0]
        w = live_weights(live, self.method)
        wl = torch.linalg.matrix_power(w, self.base.iterations)
        return self.base(q_pred, o_pred, dq, do, wl=wl.to(q_pred))
