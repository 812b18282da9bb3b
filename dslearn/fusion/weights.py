r"""Consensus weight matrices over an undirected communication graph.

All functions take a symmetric boolean/0-1 adjacency matrix ``adj`` of shape ``(S, S)``
(no self loops needed; the diagonal is ignored) and return a weight matrix ``W`` of shape
``(S, S)`` with ``W[i, j] > 0`` only for ``j`` in ``N_i ∪ {i}``. One consensus round is
``y <- einsum("ij,j...->i...", W, y)``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from dslearn.errors import ConfigError, check_choice


def _clean(adj: Tensor) -> Tensor:
    adj = torch.as_tensor(adj)
    if adj.ndim != 2 or adj.shape[0] != adj.shape[1]:
        raise ConfigError(f"adjacency must be square (S, S), got shape {tuple(adj.shape)}")
    a = adj.to(torch.bool).clone()
    a.fill_diagonal_(False)
    if not torch.equal(a, a.T):
        raise ConfigError("adjacency must be symmetric (undirected graph)")
    return a


def uniform(adj: Tensor, dtype=torch.float64) -> Tensor:
    r"""The paper's weights :math:`\pi_{ij} = 1/(|N_i|+1)` for :math:`j \in N_i \cup \{i\}`.

    Row-stochastic, but doubly stochastic only on regular graphs.
    """
    a = _clean(adj)
    m = a.to(dtype) + torch.eye(a.shape[0], dtype=dtype)
    return m / m.sum(-1, keepdim=True)


def metropolis(adj: Tensor, dtype=torch.float64) -> Tensor:
    r"""Metropolis–Hastings weights :math:`w_{ij} = 1/(1+\max(d_i, d_j))`, :math:`w_{ii} = 1-\sum_j w_{ij}`.

    Symmetric and doubly stochastic on any undirected graph.
    """
    a = _clean(adj)
    deg = a.sum(-1).to(dtype)
    w = a.to(dtype) / (1.0 + torch.maximum(deg[:, None], deg[None, :]))
    w = w + torch.diag(1.0 - w.sum(-1))
    return w


def max_degree(adj: Tensor, dtype=torch.float64) -> Tensor:
    r"""Maximum-degree weights :math:`w_{ij} = 1/(1+d_{max})`, :math:`w_{ii} = 1-d_i/(1+d_{max})`.

    Symmetric and doubly stochastic.
    """
    a = _clean(adj)
    deg = a.sum(-1).to(dtype)
    w = a.to(dtype) / (1.0 + deg.max())
    w = w + torch.diag(1.0 - w.sum(-1))
    return w


def half_max_degree(adj: Tensor, dtype=torch.float64) -> Tensor:
    r"""Half-maximum-degree weights :math:`w_{ij} = 1/(2 d_{max})`, :math:`w_{ii} = 1-d_i/(2 d_{max})`.

    The rule of Braga et al.'s Eq. (26) (on their finger-four graph, d_max = 2, it gives that
    matrix exactly). Symmetric and doubly stochastic; more self-weight than :func:`max_degree`
    (``1/(1+d_max)``), so average consensus converges more slowly but never oscillates
    (every eigenvalue is >= 0). Needs at least one edge.
    """
    a = _clean(adj)
    deg = a.sum(-1).to(dtype)
    if not float(deg.max()) > 0:
        raise ConfigError("half_max_degree weights need a graph with at least one edge")
    w = a.to(dtype) / (2.0 * deg.max())
    w = w + torch.diag(1.0 - w.sum(-1))
    return w


#: name -> weight rule (the table :func:`consensus_weights` selects from)
WEIGHT_RULES = {"uniform": uniform, "metropolis": metropolis, "max_degree": max_degree,
                "half_max_degree": half_max_degree}
#: the names of the weight rules (``consensus.weights``)
WEIGHT_METHODS = tuple(WEIGHT_RULES)


def consensus_weights(adj: Tensor, method: str = "uniform", dtype=torch.float64) -> Tensor:
    """Weight matrix by name: ``uniform`` (paper), ``metropolis``, ``max_degree`` (``1/(1+d_max)``)
    or ``half_max_degree`` (``1/(2 d_max)``, Braga et al. Eq. 26)."""
    check_choice("consensus.weights", method, WEIGHT_METHODS)
    w = WEIGHT_RULES[method](adj, dtype)
    validate_weights(w, adj, doubly=method != "uniform")
    return w


def validate_weights(w: Tensor, adj: Tensor | None = None, *, doubly: bool = False, atol: float = 1e-10) -> None:
    """Check that ``w`` is non-negative, row-stochastic (and column-stochastic if ``doubly``).

    Also checks that ``w`` only puts weight on graph edges when ``adj`` is given.
    Raises :class:`ConfigError` naming the violated property.
    """
    if (w < -atol).any():
        raise ConfigError("consensus weights must be non-negative")
    if not torch.allclose(w.sum(-1), torch.ones_like(w[0]), atol=atol):
        raise ConfigError("consensus weights must be row-stochastic (each row sums to 1)")
    if doubly and not torch.allclose(w.sum(0), torch.ones_like(w[0]), atol=atol):
        raise ConfigError("consensus weights must be doubly stochastic (columns sum to 1) for this method")
    if adj is not None:
        a = _clean(adj) | torch.eye(w.shape[0], dtype=torch.bool)
        if (w.abs() > atol)[~a].any():
            raise ConfigError("consensus weights put weight on a pair of nodes that are not linked")
