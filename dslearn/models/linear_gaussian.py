r"""Linear Gaussian dynamics ``x_t = F x_{t-1} + G w_t, w_t ~ N(0, Q)`` (Braga et al. Eq. 23-24): the
continuous state's transition of the jump Markov nonlinear system that the Rao-Blackwellised particle
filter (:mod:`dslearn.filters.rbpf`) runs and the terrain simulation (:mod:`dslearn.sim.terrain`) draws."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from dslearn.streams import Streams, randn


@dataclass
class LinearGaussianDynamics:
    """x_t = F x_{t-1} + G w_t, w_t ~ N(0, Q) (Eq. 23-24).

    Attributes:
        F: (n, n) transition matrix.
        G: (n, m) noise gain.
        Q: (m, m) driving-noise covariance.
        kernel_jitter: (n,) variances added to ``G Q G^T`` for the backward kernel of Eq. (17) only;
            the Eq. (23) noise has rank m < n so ``f(x_t | x_{t-1})`` has no Lebesgue density
            without it (documented choice; the proposal and the truth use the exact rank-m noise).
        kernel_dtype: dtype of the N×N backward-kernel products (None: the state dtype). float32 (opt-in)
            cut a full TBN run's time by about 27 %, but its rounding makes the particle paths diverge from
            float64 (see the study README); everything else stays in the state dtype.
        kernel_chunk: the O(N^2) step runs over chunks of this many flattened batch entries (None: all at
            once). Small chunks keep the (chunk, N, N) kernel matrix in cache; the result is the same.
    """

    F: Tensor
    G: Tensor
    Q: Tensor
    kernel_jitter: Tensor
    kernel_dtype: torch.dtype | None = None
    kernel_chunk: int | None = 4

    def __post_init__(self):
        self.chol_q = torch.linalg.cholesky(self.Q)
        cov = self.G @ self.Q @ self.G.T
        cov = 0.5 * (cov + cov.T) + torch.diag(self.kernel_jitter)
        self.kernel_chol = torch.linalg.cholesky(cov)

    def sample(self, x: Tensor, gen: torch.Generator | Streams) -> Tensor:
        """Draw x_t ~ f(.|x_{t-1}). x: (..., n) -> (..., n). ``gen``: one generator or per-entry streams."""
        w = randn((*x.shape[:-1], self.Q.shape[0]), gen, dtype=x.dtype, device=x.device)
        return x @ self.F.T + (w @ self.chol_q.T) @ self.G.T

    def whiten(self, x: Tensor) -> Tensor:
        """L^{-1} x for the backward-kernel Cholesky factor L (solve, no inverse). x: (..., n)."""
        flat = x.reshape(-1, x.shape[-1]).T
        return torch.linalg.solve_triangular(self.kernel_chol, flat, upper=False).T.reshape(x.shape)
