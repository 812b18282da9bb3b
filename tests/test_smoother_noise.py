"""RTS smoothing and the EM statistics of the process noise (``model.noise=adaptive``)."""

import torch

from dslearn.filters.smoother import rts_smoother, transition_error_moments
from dslearn.models.gp import GPMotionModel

D = torch.float64


def _linear_gaussian(q: float, r: float, k: int, s: int, seed: int):
    """A 1-D constant-velocity system observed in position, filtered by a Kalman filter with
    the true Q (``(S, ...)`` = ``s`` independent runs)."""
    g = torch.Generator().manual_seed(seed)
    dt = 0.5
    F = torch.tensor([[1.0, dt], [0.0, 1.0]], dtype=D)
    Q = torch.diag(torch.tensor([1e-3, q], dtype=D))
    H = torch.tensor([[1.0, 0.0]], dtype=D)
    x = torch.zeros(s, 2, dtype=D)
    m, P = torch.zeros(s, 2, dtype=D), torch.eye(2, dtype=D).expand(s, 2, 2) * 10.0
    ms, Ps, yp, Pp, xs = [m], [P], [], [], [x]
    for _ in range(k):
        x = x @ F.T + torch.randn(s, 2, generator=g, dtype=D) @ torch.linalg.cholesky(Q).T
        z = x @ H.T + r**0.5 * torch.randn(s, 1, generator=g, dtype=D)
        mp, Pq = m @ F.T, F @ P @ F.T + Q
        S = H @ Pq @ H.T + r
        K = Pq @ H.T / S
        m = mp + (K @ (z - mp @ H.T).unsqueeze(-1)).squeeze(-1)
        P = Pq - K @ H @ Pq
        ms.append(m), Ps.append(P), yp.append(mp), Pp.append(Pq), xs.append(x)
    st = lambda v: torch.stack(v, 1)  # noqa: E731
    return st(ms), st(Ps), st(yp), st(Pp), F.expand(s, k, 2, 2), Q, st(xs)


def test_rts_smoother_equals_the_batch_gaussian_posterior():
    """On a linear-Gaussian system the smoothed means/covariances are the exact posterior of the
    whole trajectory given all measurements (solved here as one joint Gaussian)."""
    g = torch.Generator().manual_seed(0)
    dt, q, r, k = 0.5, 0.04, 0.09, 6
    F = torch.tensor([[1.0, dt], [0.0, 1.0]], dtype=D)
    Q = torch.diag(torch.tensor([1e-2, q], dtype=D))
    P0 = torch.eye(2, dtype=D)
    z = torch.randn(k, generator=g, dtype=D)
    # Kalman filter
    m, P = torch.zeros(2, dtype=D), P0
    ms, Ps, yp, Pp = [m], [P], [], []
    for t in range(k):
        mp, Pq = F @ m, F @ P @ F.T + Q
        K = Pq[:, :1] / (Pq[0, 0] + r)
        m = mp + K[:, 0] * (z[t] - mp[0])
        P = Pq - K @ Pq[:1]
        ms.append(m), Ps.append(P), yp.append(mp), Pp.append(Pq)
    st = lambda v: torch.stack(v).unsqueeze(0)  # noqa: E731
    m_s, P_s, _ = rts_smoother(st(ms), st(Ps), st(yp), st(Pp), F.expand(1, k, 2, 2))
    # joint Gaussian over x_0..x_k: information matrix of the chain + measurements
    n = 2 * (k + 1)
    J = torch.zeros(n, n, dtype=D)
    J[:2, :2] += torch.linalg.inv(P0)
    Qi = torch.linalg.inv(Q)
    h = torch.zeros(n, dtype=D)
    for t in range(k):
        a, b = slice(2 * t, 2 * t + 2), slice(2 * t + 2, 2 * t + 4)
        J[a, a] += F.T @ Qi @ F
        J[b, b] += Qi
        J[a, b] -= F.T @ Qi
        J[b, a] -= Qi @ F
        J[2 * t + 2, 2 * t + 2] += 1 / r
        h[2 * t + 2] += z[t] / r
    cov = torch.linalg.inv(J)
    mean = cov @ h
    for t in range(k + 1):
        assert torch.allclose(m_s[0, t], mean[2 * t : 2 * t + 2], atol=1e-10)
        assert torch.allclose(P_s[0, t], cov[2 * t : 2 * t + 2, 2 * t : 2 * t + 2], atol=1e-10)


def test_em_statistics_estimate_the_true_process_noise():
    """With the true model and a consistent filter, the average expected transition error given
    all data is an unbiased estimate of Q (here its velocity entry, 0.05, within 5 %)."""
    q = 0.05
    m, P, yp, Pp, F, Q, _ = _linear_gaussian(q, 0.04, k=40, s=400, seed=1)
    M = transition_error_moments(m, P, yp, Pp, F)
    est = M[:, 10:].mean((0, 1))  # after the filter's start-up
    assert abs(float(est[1, 1]) - q) / q < 0.05
    assert torch.allclose(M, M.transpose(-1, -2))
    assert (torch.linalg.eigvalsh(M.mean((0, 1))) > 0).all()


def test_adaptive_noise_update_averages_and_respects_validity():
    gp = GPMotionModel(8, num_nodes=3, noise="adaptive", noise_std=0.5, noise_fading=0.5)
    assert torch.allclose(gp.q_noise, torch.full((3, 2), 0.25, dtype=D))  # starts at sigma_eps^2
    k = 4
    latent = 0.01
    Q_used = torch.diag_embed(torch.full((3, k, 8), latent, dtype=D) + gp.extra_noise(torch.zeros(1, dtype=D)).unsqueeze(1))
    target = torch.tensor([0.02, 0.2], dtype=D).repeat_interleave(2).repeat(2)  # pos, vel per agent
    M = torch.diag_embed((target + latent).expand(3, k, 8))
    gp.update_noise(M, Q_used, torch.tensor([True, True, False]))
    # fading average of (initial value, weight 1) and the new sample: b * 1 * 0.25 + sample / (b + 1)
    exp = (0.5 * torch.tensor([0.25, 0.25], dtype=D) + torch.tensor([0.02, 0.2], dtype=D)) / 1.5
    assert torch.allclose(gp.q_noise[:2], exp.expand(2, 2))
    assert torch.allclose(gp.q_noise[2], torch.tensor([0.25, 0.25], dtype=D))  # invalid node unchanged
    # the model adds exactly q on the diagonal, position and velocity entries
    extra = gp.extra_noise(torch.zeros(1, dtype=D))
    assert torch.allclose(extra[0], exp.repeat_interleave(2).repeat(2))
