r"""The exact GP's step through the inverse Cholesky factor, in one pass over memory.

With :math:`K + \sigma^2 I = L L^T` and :math:`M = L^{-1}` (lower triangular), a prediction at
one point and the append that follows there need :math:`w = M k` (the variance
:math:`k_{**} - w^T w` and the new row of :math:`L`) and :math:`b = M^T w = (K + \sigma^2 I)^{-1} k`
(the update of :math:`\alpha` and the new row of :math:`M`, :math:`[-b^T, 1] / d`). Both are
products with the same rows of :math:`M`, so one sweep over the rows computes them: row
:math:`i` gives :math:`w_i = M_{i,:} k` and at once adds :math:`w_i M_{i,:}^T` to :math:`b`. The
two triangular solves through :math:`L` that this replaces cannot share a pass (the second
runs backwards and needs all of the first), so the inverse factor halves what every learning
step streams from memory, and appending a point writes one row (no solve).

:func:`pair` runs that sweep: on the CPU through a compiled kernel (numba, sixteen rows at a time
so that each row is read from memory once and reused from cache, and sixteen rows
stream at once; a node whose ``k`` is zero, one that has learnt nothing valid yet, is skipped),
elsewhere, or without numba, through two batched products (:func:`pair_torch`, the reference
the kernel is tested against).
"""

from __future__ import annotations

import torch
from torch import Tensor

try:  # the compiled CPU kernel; without numba the torch products are used
    import numba
except ImportError:  # pragma: no cover - numba is a dependency; kept for platforms without wheels
    numba = None

HAVE_KERNEL = numba is not None

if HAVE_KERNEL:
    # reassociation lets the compiler vectorise the dot products (the summation order depends on the
    # CPU's vector width, as in any BLAS); no other fast-math assumption (NaN and infinity kept)
    @numba.njit(fastmath={"reassoc", "contract"}, nogil=True, cache=True)
    def _pair_kernel(M, k, n, w, b, need_b):  # pragma: no cover - compiled; tested through pair()
        S = M.shape[0]
        for s in range(S):
            Ms = M[s]
            ks = k[s]
            ws = w[s]
            bs = b[s]
            for j in range(n):
                bs[j] = 0.0
            nonzero = False
            for j in range(n):
                if ks[j] != 0.0:
                    nonzero = True
                    break
            if not nonzero:  # k = 0 (a node whose points are all invalid): w = b = 0, no pass
                for j in range(n):
                    ws[j] = 0.0
                continue
            i = 0
            while i + 16 <= n:
                r0 = Ms[i]
                r1 = Ms[i + 1]
                r2 = Ms[i + 2]
                r3 = Ms[i + 3]
                r4 = Ms[i + 4]
                r5 = Ms[i + 5]
                r6 = Ms[i + 6]
                r7 = Ms[i + 7]
                r8 = Ms[i + 8]
                r9 = Ms[i + 9]
                r10 = Ms[i + 10]
                r11 = Ms[i + 11]
                r12 = Ms[i + 12]
                r13 = Ms[i + 13]
                r14 = Ms[i + 14]
                r15 = Ms[i + 15]
                a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = a8 = a9 = a10 = a11 = a12 = a13 = a14 = a15 = 0.0
                for j in range(i):  # the 16 rows' products over the columns before the block
                    kj = ks[j]
                    a0 += r0[j] * kj
                    a1 += r1[j] * kj
                    a2 += r2[j] * kj
                    a3 += r3[j] * kj
                    a4 += r4[j] * kj
                    a5 += r5[j] * kj
                    a6 += r6[j] * kj
                    a7 += r7[j] * kj
                    a8 += r8[j] * kj
                    a9 += r9[j] * kj
                    a10 += r10[j] * kj
                    a11 += r11[j] * kj
                    a12 += r12[j] * kj
                    a13 += r13[j] * kj
                    a14 += r14[j] * kj
                    a15 += r15[j] * kj
                ws[i] = a0
                ws[i + 1] = a1
                ws[i + 2] = a2
                ws[i + 3] = a3
                ws[i + 4] = a4
                ws[i + 5] = a5
                ws[i + 6] = a6
                ws[i + 7] = a7
                ws[i + 8] = a8
                ws[i + 9] = a9
                ws[i + 10] = a10
                ws[i + 11] = a11
                ws[i + 12] = a12
                ws[i + 13] = a13
                ws[i + 14] = a14
                ws[i + 15] = a15
                for q in range(16):  # the 16 x 16 triangle on the diagonal
                    row = Ms[i + q]
                    a = 0.0
                    for j in range(i, i + q + 1):
                        a += row[j] * ks[j]
                    ws[i + q] += a
                if need_b:
                    a0 = ws[i]
                    a1 = ws[i + 1]
                    a2 = ws[i + 2]
                    a3 = ws[i + 3]
                    a4 = ws[i + 4]
                    a5 = ws[i + 5]
                    a6 = ws[i + 6]
                    a7 = ws[i + 7]
                    a8 = ws[i + 8]
                    a9 = ws[i + 9]
                    a10 = ws[i + 10]
                    a11 = ws[i + 11]
                    a12 = ws[i + 12]
                    a13 = ws[i + 13]
                    a14 = ws[i + 14]
                    a15 = ws[i + 15]
                    for j in range(i):  # b += M[rows]^T w[rows] while the rows are in cache
                        bs[j] += (a0 * r0[j] + a1 * r1[j] + a2 * r2[j] + a3 * r3[j]
                                  + a4 * r4[j] + a5 * r5[j] + a6 * r6[j] + a7 * r7[j]
                                  + a8 * r8[j] + a9 * r9[j] + a10 * r10[j] + a11 * r11[j]
                                  + a12 * r12[j] + a13 * r13[j] + a14 * r14[j] + a15 * r15[j])
                    for q in range(16):
                        row = Ms[i + q]
                        a = ws[i + q]
                        for j in range(i, i + q + 1):
                            bs[j] += a * row[j]
                i += 16
            while i < n:  # the last rows, one at a time
                row = Ms[i]
                a = 0.0
                for j in range(i + 1):
                    a += row[j] * ks[j]
                ws[i] = a
                if need_b:
                    for j in range(i + 1):
                        bs[j] += a * row[j]
                i += 1


def pair_torch(M: Tensor, k: Tensor, n: int, need_b: bool = True) -> tuple[Tensor, Tensor | None]:
    """:func:`pair` through two batched products over the top-left ``n x n`` block (any device)."""
    Mn = M[:, :n, :n]
    w = (Mn @ k[:, :n].unsqueeze(-1).to(M.dtype)).squeeze(-1)
    b = (Mn.transpose(-1, -2) @ w.unsqueeze(-1)).squeeze(-1) if need_b else None
    return w.to(k.dtype), (None if b is None else b.to(k.dtype))


def pair(M: Tensor, k: Tensor, n: int, need_b: bool = True) -> tuple[Tensor, Tensor | None]:
    r"""``w = M k`` and (``need_b``) ``b = M^T w`` for ``M (S, cap, cap)`` lower triangular in its
    top-left ``n x n`` block and ``k (S, n)``; returns ``(S, n)`` tensors in ``k``'s dtype.

    Only the lower triangle of the first ``n`` rows is read: what lies above the diagonal or past
    row ``n`` is never touched. On the CPU with numba, one pass over those rows
    (:data:`HAVE_KERNEL`); otherwise :func:`pair_torch`.
    """
    floats = (torch.float32, torch.float64)
    if not HAVE_KERNEL or M.device.type != "cpu" or M.stride(-1) != 1 or M.dtype not in floats or k.dtype not in floats:
        return pair_torch(M, k, n, need_b)
    kc = k[:, :n].contiguous()
    w = torch.empty_like(kc)
    b = torch.empty_like(kc)
    _pair_kernel(M.detach().numpy(), kc.numpy(), int(n), w.numpy(), b.numpy(), bool(need_b))
    return w, (b if need_b else None)
