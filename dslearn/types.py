r"""Shared types and state layout.

Joint state of ``A`` agents: ``y = [y_1, ..., y_A]`` with ``y_j = (p_x, p_y, v_x, v_y)``,
so ``Dx = 4 A``. Shapes are batch first, event last: state ``(*B, Dx)``, covariance
``(*B, Dx, Dx)``; beliefs across a network put nodes first, ``(S, *B, Dx)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import torch
from torch import Tensor

from dslearn.diagnostics import SESSION, JitterLog, record_jitter  # noqa: F401  (JitterLog: re-exported)

#: the dtype names configs use (root ``dtype``, ``model.factor_dtype``, task dtypes) -> torch dtypes
DTYPES = {"float64": torch.float64, "float32": torch.float32}

AGENT_DIM = 4
#: the scenario state layouts (:attr:`dslearn.episodes.ScenarioSpec.state`) that are the filters' own, ``[p, v]`` per
#: agent or platform (``param2d``, Jiang's source, is a position alone)
PV_LAYOUTS = ("pv2d", "platform")
POS = slice(0, 2)
VEL = slice(2, 4)


def agents(x: Tensor) -> Tensor:
    """Split a joint state ``(*B, 4A)`` into ``(*B, A, 4)`` (a view)."""
    return x.unflatten(-1, (-1, AGENT_DIM))


def joint(x: Tensor) -> Tensor:
    """Inverse of :func:`agents`: ``(*B, A, 4) -> (*B, 4A)``."""
    return x.flatten(-2)


def positions(x: Tensor) -> Tensor:
    """Positions of every agent, ``(*B, 4A) -> (*B, A, 2)``."""
    return agents(x)[..., POS]


@dataclass
class StepContext:
    """What a model may need besides the state.

    Attributes:
        dt: time step in seconds.
        cov: the filter's covariance of the state being predicted, ``(*B, Dx, Dx)``, set by the
            filter's prediction step (``None`` elsewhere: simulation, roll-outs). Models whose
            prediction depends on how well the state is known use it (the social force softens
            interactions with poorly known agents); the others ignore it.
    """

    dt: float = 0.25
    cov: Optional[Tensor] = None


def symmetrize(m: Tensor) -> Tensor:
    """``(M + M^T) / 2`` over the last two dims."""
    return 0.5 * (m + m.transpose(-1, -2))


def batch_jacobian(f: Callable[[Tensor], Tensor], x: Tensor, create_graph: bool = False) -> Tensor:
    """Jacobian of a row-wise ``f: (*B, Din) -> (*B, Dout)``. Returns ``(*B, Dout, Din)``."""
    with torch.enable_grad():
        x = x.detach().requires_grad_(True)
        y = f(x)
        rows = [
            torch.autograd.grad(y[..., i].sum(), x, retain_graph=True, create_graph=create_graph)[0]
            for i in range(y.shape[-1])
        ]
    return torch.stack(rows, dim=-2)


#: :func:`distinct_rows` compacts a batch only where at most this share of its rows are distinct (below it the
#: batch is kept as it is, so a batch without repeats computes exactly as before)
DISTINCT_SHARE = 0.9
#: the multiplier of :func:`distinct_rows`' hash (odd; column ``j``'s word is multiplied by it times ``2j + 1``)
_ROW_HASH = 0x9E3779B97F4A7C15 - (1 << 64)


def distinct_rows(flat: Tensor) -> tuple[Tensor, Optional[Tensor]]:
    """``(N, D) -> (rows (U, D), inverse (N,))`` with ``rows[inverse] == flat`` bit for bit, where at most
    :data:`DISTINCT_SHARE` of the ``N`` rows are distinct; else ``(flat, None)``. A model that is one function of the
    row (no per-row state) then evaluates each distinct row once: the nodes of a sensor network that never saw a
    target hold the same prior, and so do every grid point's filters up to their first measurement. Rows are
    grouped by a hash of their 64-bit words and the grouping is then checked value for value (a collision, a NaN or
    a signed zero keeps the batch whole). Not for a row that carries a gradient (a gather would send every
    duplicate's gradient to its representative)."""
    n = flat.shape[0]
    if n < 2 or flat.requires_grad or flat.dtype != torch.float64:
        return flat, None
    words = flat.contiguous().view(torch.int64)
    mult = torch.arange(1, 2 * flat.shape[-1], 2, dtype=torch.int64, device=flat.device) * _ROW_HASH  # odd, wrapping
    key = (words * mult).sum(-1)  # wraps modulo 2^64: a hash of the row's bits
    uniq, inverse = torch.unique(key, return_inverse=True)
    if uniq.numel() > DISTINCT_SHARE * n:
        return flat, None
    rep = torch.empty(uniq.numel(), dtype=torch.long, device=flat.device)
    rep.scatter_(0, inverse, torch.arange(n, device=flat.device))  # one member of each group
    rows = flat[rep]
    if not bool((rows[inverse] == flat).all()):
        return flat, None
    return rows, inverse


#: the jitter records of the session outside any run (``dslearn.diagnostics.SESSION``); a run's
#: own records are in its :class:`~dslearn.diagnostics.Diagnostics`
JITTER = SESSION.jitter


def safe_cholesky(m: Tensor, max_tries: int = 6, log: Optional[JitterLog] = None) -> Tensor:
    """Cholesky factor of SPD ``m`` (*B, D, D); adds growing diagonal jitter where it fails.

    Jitter is per matrix and only for the matrices whose factorisation failed: it starts at
    1e-10 times that matrix's mean absolute diagonal and grows tenfold until the factor exists.
    Matrices of the batch that factor cleanly are left untouched (so one near-singular node
    or episode never perturbs the others). Each jittered matrix is recorded in ``log`` if given,
    else in the open :class:`~dslearn.diagnostics.Diagnostics` (:func:`dslearn.diagnostics.record_jitter`).
    """
    m = symmetrize(m)
    chol, info = torch.linalg.cholesky_ex(m)
    bad = info > 0
    if not bool(bad.any()):
        return chol
    record = log.record if log is not None else record_jitter
    scale = m.diagonal(dim1=-2, dim2=-1).abs().mean(-1).clamp_min(1e-12)
    jitter = torch.where(bad, 1e-10 * scale, torch.zeros_like(scale))
    eye = torch.eye(m.shape[-1], dtype=m.dtype, device=m.device)
    needed = bad.clone()
    for _ in range(max_tries + 6):
        chol, info = torch.linalg.cholesky_ex(m + jitter[..., None, None] * eye)
        still = info > 0
        if not bool(still.any()):
            for j in jitter[needed].tolist():
                record(j)
            return chol
        jitter = torch.where(still, 10.0 * jitter, jitter)
    raise torch.linalg.LinAlgError(
        f"{int(still.sum())} matrix(es) not positive definite even with jitter {float(jitter.max()):g}"
    )


def spd_inverse(m: Tensor, log: Optional[JitterLog] = None) -> Tensor:
    """Inverse of an SPD matrix through its Cholesky factor, symmetrised."""
    return symmetrize(torch.cholesky_inverse(safe_cholesky(m, log=log)))
