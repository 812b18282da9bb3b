"""Batched Cholesky factor and solves for tiny SPD matrices (D <= ~8) in plain torch ops.

LAPACK-backed ``torch.linalg.cholesky`` runs one small matrix at a time on CPU; for thousands
of 2x2 / 3x3 systems these unrolled column loops are much faster. Falls back to
:func:`dslearn.types.safe_cholesky` (jitter, recorded) when a pivot is not positive.
"""

from __future__ import annotations

import torch
from torch import Tensor

from dslearn.types import safe_cholesky, symmetrize

_SMALL = 8


def cholesky(A: Tensor) -> Tensor:
    """Lower Cholesky factor of SPD ``A (*B, D, D)``."""
    D = A.shape[-1]
    if D > _SMALL:
        return safe_cholesky(A)
    A = symmetrize(A)
    cols = []
    for j in range(D):
        # L[:, j] = (A[:, j] - sum_{k<j} L[:, k] L[j, k]) / L[j, j]
        c = A[..., :, j].clone()
        for k in range(j):
            c = c - cols[k] * cols[k][..., j : j + 1]
        piv = c[..., j : j + 1]
        if not bool((piv > 0).all()):
            return safe_cholesky(A)
        c = c / piv.sqrt()
        mask = torch.arange(D, device=A.device) >= j
        cols.append(c * mask)
    return torch.stack(cols, -1)


def cholesky_solve(b: Tensor, L: Tensor) -> Tensor:
    """Solve ``L L^T x = b`` for ``b (*B, D, R)``. Returns ``(*B, D, R)``."""
    D = L.shape[-1]
    z = []
    for i in range(D):  # forward: L z = b
        acc = b[..., i, :]
        for k in range(i):
            acc = acc - L[..., i, k : k + 1] * z[k]
        z.append(acc / L[..., i, i : i + 1])
    x = [None] * D
    for i in reversed(range(D)):  # backward: L^T x = z
        acc = z[i]
        for k in range(i + 1, D):
            acc = acc - L[..., k, i : i + 1] * x[k]
        x[i] = acc / L[..., i, i : i + 1]
    return torch.stack(x, -2)
