r"""Centralised baselines on all raw samples (not in the paper; the issue's reference points).

* :func:`gauss_newton`: snapshot maximum-likelihood estimate of ``x`` from the ``N x L`` raw
  samples of one timing, :math:`\min_x \sum_{n,l} (\hat y_{n,l} - h_n(x))^2`, by Gauss-Newton.
* :func:`iterated_ekf_update`: the measurement update of a centralised iterated EKF on the
  joint state ``z = [x, v]`` (constant-gradient model, Eq. 4) with all raw samples.

With i.i.d. Gaussian noise the per-sensor sample sum is sufficient, so the raw samples enter
through :math:`\sum_l (\hat y_{n,l} - h_n(x)) = L(\bar y_n - h_n(x))`.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from dslearn.types import batch_jacobian, symmetrize
from dslearn.linalg import cholesky, cholesky_solve


def _mm(a: Tensor, b: Tensor) -> Tensor:
    """``a @ b`` for tiny matrices by broadcast-and-sum (batched tiny matmuls are slow on CPU)."""
    return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)


def _t(a: Tensor) -> Tensor:
    return a.transpose(-1, -2)


def gauss_newton(
    h: Callable[[Tensor], Tensor], samples: Tensor, x0: Tensor, num_iters: int = 10
) -> Tensor:
    """Snapshot ML estimate by Gauss-Newton.

    Args:
        h: ``(*B, M) -> (*B, N)``.
        samples: ``(*B, N, L)`` raw samples.
        x0: ``(*B, M)`` starting point.
        num_iters: Gauss-Newton steps.

    Returns:
        ``(*B, M)``.
    """
    ysum, L = samples.sum(-1), samples.shape[-1]
    x = x0
    for _ in range(num_iters):
        J = batch_jacobian(h, x)                                  # (*B, N, M)
        with torch.no_grad():
            r = ysum - L * h(x)                                   # sum_l residuals, (*B, N)
        A = L * _mm(_t(J), J)
        b = _mm(_t(J), r.unsqueeze(-1))
        x = x + cholesky_solve(b, cholesky(A)).squeeze(-1)
    return x.detach()


def cv_predict(mean: Tensor, cov: Tensor, process_var: float, gradient_var: float) -> tuple[Tensor, Tensor]:
    """Constant-gradient prediction for ``z = [x, v]``: ``(*B, 2M)``, ``(*B, 2M, 2M)``.

    ``x_k = x_{k-1} + v_{k-1} + w``, ``v_k = v_{k-1} + w_v`` with ``Q = diag(q_x I, q_v I)``.
    """
    M = mean.shape[-1] // 2
    eye = torch.eye(M, dtype=mean.dtype, device=mean.device)
    F = torch.cat([torch.cat([eye, eye], -1), torch.cat([torch.zeros_like(eye), eye], -1)], -2)
    Q = torch.diag(torch.cat([torch.full((M,), process_var), torch.full((M,), gradient_var)]).to(mean))
    return _mm(mean.unsqueeze(-2), F.T).squeeze(-2), symmetrize(_mm(_mm(F, cov), F.T) + Q)


def iterated_ekf_update(
    h: Callable[[Tensor], Tensor], samples: Tensor, sigma_y: Tensor | float, mean: Tensor, cov: Tensor,
    num_iters: int = 10,
) -> tuple[Tensor, Tensor]:
    """Iterated EKF update (Gauss-Newton on the posterior) with all raw samples.

    Args:
        h: ``(*B, M) -> (*B, N)``; the state is ``z = [x, v] (*B, 2M)``, ``h`` sees ``x``.
        samples: ``(*B, N, L)``.
        sigma_y: per-sample noise std, scalar or ``(*B,)``.
        mean, cov: predicted ``(*B, 2M)``, ``(*B, 2M, 2M)``.
        num_iters: IEKF iterations (1 = plain EKF).

    Returns:
        Posterior ``(mean, cov)``.
    """
    M2 = mean.shape[-1]
    M = M2 // 2
    L = samples.shape[-1]
    ybar = samples.mean(-1)
    N = ybar.shape[-1]
    R = (torch.as_tensor(sigma_y, dtype=mean.dtype, device=mean.device).square() / L)[..., None, None] * torch.eye(
        N, dtype=mean.dtype, device=mean.device
    )
    z = mean
    for _ in range(num_iters):
        Jx = batch_jacobian(h, z[..., :M])                        # (*B, N, M)
        H = torch.cat([Jx, torch.zeros_like(Jx)], -1)              # (*B, N, 2M)
        with torch.no_grad():
            innov = ybar - h(z[..., :M]) - _mm(H, (mean - z).unsqueeze(-1)).squeeze(-1)
        PHt = _mm(cov, _t(H))                                      # (*B, 2M, N)
        S = symmetrize(_mm(H, PHt) + R)
        chol = cholesky(S)
        K = _t(cholesky_solve(_t(PHt), chol))                # P H^T S^{-1}
        z = mean + _mm(K, innov.unsqueeze(-1)).squeeze(-1)
    eye = torch.eye(M2, dtype=mean.dtype, device=mean.device)
    IKH = eye - _mm(K, H)
    cov_post = symmetrize(_mm(_mm(IKH, cov), _t(IKH)) + _mm(_mm(K, R), _t(K)))  # Joseph form
    return z.detach(), cov_post.detach()
