"""dslearn/filters/smoother.py: the transition-error moments of a linear-Gaussian run against the joint
Gaussian posterior of the whole trajectory, computed by one batch solve (benchmarks/mutation: survivors
of the mutation run)."""

import torch

from dslearn.filters.smoother import transition_error_moments

D = torch.float64


def test_transition_error_moments_equal_the_joint_posterior_moments():
    """y_t = F y_{t-1} + w (F not symmetric, so the lag-one covariance is not), z_t = H y_t + v.
    M_t = E[d d^T | z_{0:K}], d = y_t - F y_{t-1}, from the mean and covariance of the stacked
    trajectory's posterior (information matrix of the whole chain, solved at once)."""
    k, dx = 6, 2
    F = torch.tensor([[1.0, 0.5], [0.0, 0.9]], dtype=D)
    Q = torch.tensor([[0.05, 0.01], [0.01, 0.2]], dtype=D)
    H = torch.tensor([[1.0, 0.0]], dtype=D)
    R = torch.tensor([[0.3]], dtype=D)
    m0, P0 = torch.tensor([0.5, -1.0], dtype=D), torch.diag(torch.tensor([1.0, 2.0], dtype=D))
    z = torch.randn(k + 1, 1, generator=torch.Generator().manual_seed(2), dtype=D) + torch.arange(k + 1.0)[:, None]

    # Kalman filter
    def update(m, P, zt):
        S = H @ P @ H.T + R
        K = P @ H.T @ torch.linalg.inv(S)
        return m + K @ (zt - H @ m), (torch.eye(dx, dtype=D) - K @ H) @ P

    m, P = [None] * (k + 1), [None] * (k + 1)
    yp, Pp = [], []
    m[0], P[0] = update(m0, P0, z[0])
    for t in range(1, k + 1):
        yp.append(F @ m[t - 1])
        Pp.append(F @ P[t - 1] @ F.T + Q)
        m[t], P[t] = update(yp[-1], Pp[-1], z[t])
    M = transition_error_moments(torch.stack(m)[None], torch.stack(P)[None], torch.stack(yp)[None],
                                 torch.stack(Pp)[None], F.expand(1, k, dx, dx))
    assert M.shape == (1, k, dx, dx)

    # the joint posterior of (y_0, ..., y_K)
    n = (k + 1) * dx
    J, h = torch.zeros(n, n, dtype=D), torch.zeros(n, dtype=D)
    blk = lambda t: slice(t * dx, (t + 1) * dx)  # noqa: E731
    Qi, Ri = torch.linalg.inv(Q), torch.linalg.inv(R)
    J[blk(0), blk(0)] += torch.linalg.inv(P0)
    h[blk(0)] += torch.linalg.inv(P0) @ m0
    for t in range(1, k + 1):
        J[blk(t), blk(t)] += Qi
        J[blk(t - 1), blk(t - 1)] += F.T @ Qi @ F
        J[blk(t), blk(t - 1)] -= Qi @ F
        J[blk(t - 1), blk(t)] -= F.T @ Qi
    for t in range(k + 1):
        J[blk(t), blk(t)] += H.T @ Ri @ H
        h[blk(t)] += (H.T @ Ri @ z[t])
    cov = torch.linalg.inv(J)
    mu = cov @ h
    for t in range(1, k + 1):
        A = torch.zeros(dx, n, dtype=D)  # d = A y
        A[:, blk(t)] = torch.eye(dx, dtype=D)
        A[:, blk(t - 1)] = -F
        mean = A @ mu
        want = torch.outer(mean, mean) + A @ cov @ A.T
        torch.testing.assert_close(M[0, t - 1], want, rtol=1e-9, atol=1e-10)
