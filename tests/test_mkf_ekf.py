"""The extended (and iterated extended) Kalman update per particle of the RBPF over noise modes
(dslearn/filters/mkf.py: ekf_mode_updates, iekf_mode_updates, mkf_step_sensors) against filterpy's
ExtendedKalmanFilter on squared ranges, and with a linear observation model against the Kalman update it
extends (bit for bit where the operations are the same)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dslearn.filters.mkf import (LinearGaussianState, MKFState, ekf_mode_updates, iekf_mode_updates, init_state,
                                 mkf_step_sensors, mode_updates)
from dslearn.models.jmnls import LOG_2PI, NoiseParams, stats_dim
from dslearn.models.observation import LinearPositionObservation, SquaredRangeObservation

F64 = torch.float64
SENSORS = np.array([[-30.0, 50.0], [10.0, 5.0], [60.0, 20.0]])
SIGMA = np.array([0.7, 2.5])  # unequal modes (the reading's std under each)
#: a prediction with every term: a non-identity, correlated covariance, a velocity, particles apart
MEANS = np.array([[6.1, 0.4, 0.3, -0.2], [5.2, 1.3, -0.1, 0.4]])
P = np.array([[0.9, 0.3, 0.2, 0.05], [0.3, 1.4, -0.1, 0.1], [0.2, -0.1, 0.6, 0.02], [0.05, 0.1, 0.02, 0.4]])
COVS = np.stack([P, 1.7 * P + np.diag([0.2, 0.0, 0.1, 0.3])])


def _sq_range(j):
    s = SENSORS[j]

    def hx(x):
        return np.array([(x[0] - s[0]) ** 2 + (x[1] - s[1]) ** 2])

    def jac(x):
        return np.array([[2 * (x[0] - s[0]), 2 * (x[1] - s[1]), 0.0, 0.0]])

    return hx, jac


def _observe(j):
    """Sensor j's squared range of the dslearn model (node-first states) at states of any leading shape."""
    obs = SquaredRangeObservation(torch.tensor(SENSORS), 1.0)

    def observe(x):
        xs = x.unsqueeze(0).expand(len(SENSORS), *x.shape)
        return obs(xs)[j], obs.jacobian(xs)[j]

    return observe


def _filterpy_update(m, p, y, j, sigma):
    from filterpy.kalman import ExtendedKalmanFilter

    ekf = ExtendedKalmanFilter(dim_x=4, dim_z=1)
    ekf.x, ekf.P, ekf.R = m.copy(), p.copy(), np.array([[sigma ** 2]])
    hx, jac = _sq_range(j)
    ekf.update(np.array([y]), jac, hx)
    return ekf.x.copy(), ekf.P.copy(), ekf.S.copy(), ekf.y.copy()


def test_the_extended_update_is_filterpys_on_a_squared_range():
    """Two particles (different means and non-identity covariances), two modes of unequal noise, each of the three
    sensors: the updated means and covariances, the predictive log-densities (from filterpy's innovation and its
    covariance S) and the residual's moments (at the updated mean, with tr(H P_l H^T)) equal filterpy's
    ExtendedKalmanFilter.update with the squared range and its Jacobian."""
    mean, cov = torch.tensor(MEANS), torch.tensor(COVS)
    mu, sigma = torch.zeros(2, dtype=F64), torch.tensor(SIGMA)
    truth = np.array([6.0, 0.8])
    for j in range(3):
        y = float(((truth - SENSORS[j]) ** 2).sum()) + 1.3  # off the prediction by several of the modes' stds
        hx_j, jac_j = _sq_range(j)
        observe = _observe(j)
        hx, H = observe(mean)
        ll, m_l, p_l, e1, e2 = ekf_mode_updates(mean, cov, y - hx, H, mu, sigma,
                                                lambda m: y - observe(m)[0])
        for i in range(2):
            for mode in range(2):
                x, p, s, innov = _filterpy_update(MEANS[i], COVS[i], y, j, SIGMA[mode])
                np.testing.assert_allclose(m_l[i, mode].numpy(), x, rtol=1e-12, atol=1e-12)
                np.testing.assert_allclose(p_l[i, mode].numpy(), p, rtol=1e-9, atol=1e-12)
                want = -0.5 * (innov[0] ** 2 / s[0, 0] + math.log(s[0, 0]) + LOG_2PI)
                assert float(ll[i, mode]) == pytest.approx(want, rel=1e-12, abs=1e-12)
                res = y - hx_j(x)[0]
                hh = jac_j(MEANS[i])
                assert float(e1[i, mode]) == pytest.approx(res, rel=1e-9, abs=1e-9)
                assert float(e2[i, mode]) == pytest.approx(res ** 2 + (hh @ p @ hh.T)[0, 0], rel=1e-9)
        # the update moved the means toward the reading: the residual under the update is smaller than the innovation
        assert bool((e1.abs() < (y - hx).abs()).all())


def test_the_iterated_update_is_gauss_newton_on_each_modes_posterior():
    """Iteration i + 1 linearises at mode l's iterate m_i and updates the same prediction (filterpy's EKF given the
    Jacobian and h at m_i, with the innovation y - h(m_i) - H_i (m - m_i)); one iteration is the extended update;
    enough iterations reach the posterior's mode (the gradient of the negative log posterior vanishes there)."""
    mean, cov = torch.tensor(MEANS), torch.tensor(COVS)
    mu, sigma = torch.zeros(2, dtype=F64), torch.tensor(SIGMA)
    y = torch.tensor([2650.0], dtype=F64)
    observe = _observe(0)
    one = iekf_mode_updates(mean, cov, y, observe, mu, sigma, 1)
    hx, H = observe(mean)
    ref = ekf_mode_updates(mean, cov, y - hx, H, mu, sigma, lambda m: y - observe(m)[0])
    for a, b in zip(one, ref):
        assert torch.equal(a, b)
    two = iekf_mode_updates(mean, cov, y, observe, mu, sigma, 2)
    hx_j, jac_j = _sq_range(0)
    for i in range(2):
        for mode in range(2):
            m1 = one[1][i, mode].numpy()
            hh = jac_j(m1)
            innov = 2650.0 - hx_j(m1)[0] - (hh @ (MEANS[i] - m1))[0]
            s = (hh @ COVS[i] @ hh.T)[0, 0] + SIGMA[mode] ** 2
            k = COVS[i] @ hh.T / s
            np.testing.assert_allclose(two[1][i, mode].numpy(), MEANS[i] + k[:, 0] * innov, rtol=1e-12, atol=1e-10)
            assert float(two[0][i, mode]) == pytest.approx(-0.5 * (innov ** 2 / s + math.log(s) + LOG_2PI), rel=1e-12)
    many = iekf_mode_updates(mean, cov, y, observe, mu, sigma, 30)
    for i in range(2):
        for mode in range(2):
            x = many[1][i, mode].numpy()
            hh = jac_j(x)
            grad = np.linalg.solve(COVS[i], x - MEANS[i]) - hh[0] * (2650.0 - hx_j(x)[0]) / SIGMA[mode] ** 2
            assert np.abs(grad).max() < 1e-8 * (1 + np.abs(hh).max() / SIGMA[mode] ** 2)
    # the iterations matter here: the one-step update is not the mode
    assert float((many[1] - one[1]).abs().max()) > 1e-3


def _old_mode_updates(mean, cov, y, model, mu, sigma):
    """The Kalman update as it was before the extended one (dslearn/filters/mkf.py, commit 5324438), verbatim."""
    H = model.H
    d, n = H.shape
    eye_d = torch.eye(d, dtype=mean.dtype, device=mean.device)
    eye_n = torch.eye(n, dtype=mean.dtype, device=mean.device)
    hp = H @ cov
    s0 = hp @ H.T
    r = (sigma * sigma)[..., None, :, None, None] * eye_d
    s = s0[..., None, :, :] + r
    chol = torch.linalg.cholesky(s)
    v = y[..., None, None, :] - (mean @ H.T)[..., None, :] - mu[..., None, :, None]
    sv = torch.cholesky_solve(v[..., None], chol)[..., 0]
    logdet = 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    loglik = -0.5 * ((v * sv).sum(-1) + logdet + d * LOG_2PI)
    gain = torch.cholesky_solve(hp[..., None, :, :].expand(*s.shape[:-2], d, n), chol).transpose(-1, -2)
    m_new = mean[..., None, :] + (gain @ v[..., None])[..., 0]
    a = eye_n - gain @ H
    p_new = a @ cov[..., None, :, :] @ a.transpose(-1, -2) + gain @ r @ gain.transpose(-1, -2)
    p_new = 0.5 * (p_new + p_new.transpose(-1, -2))
    res = y[..., None, None, :] - m_new @ H.T
    e1 = res.sum(-1)
    e2 = (res * res).sum(-1) + torch.diagonal(H @ p_new @ H.T, dim1=-2, dim2=-1).sum(-1)
    return loglik, m_new, p_new, e1, e2


def test_with_a_linear_observation_the_extended_update_is_the_kalman_update():
    """The linear position sensor: its h and constant matrix through ekf_mode_updates give the Kalman update before
    the extension bit for bit (the same operations), so does mode_updates now; its per-particle Jacobian (the
    model's jacobian, batched) and the iterated update give it to rounding."""
    g = torch.Generator().manual_seed(5)
    mean = torch.randn(3, 7, 4, generator=g, dtype=F64)
    a = torch.randn(3, 7, 4, 4, generator=g, dtype=F64)
    cov = a @ a.transpose(-1, -2) + 0.1 * torch.eye(4, dtype=F64)
    y = torch.randn(3, 2, generator=g, dtype=F64)
    mu = torch.zeros(3, 2, dtype=F64)
    sigma = torch.tensor([[0.3, 1.1], [0.5, 0.9], [0.2, 2.0]], dtype=F64)
    obs = LinearPositionObservation(0.3)
    model = LinearGaussianState(torch.eye(4, dtype=F64), torch.eye(4, dtype=F64), obs.matrix())
    old = _old_mode_updates(mean, cov, y, model, mu, sigma)
    H = obs.matrix()
    new = ekf_mode_updates(mean, cov, y[..., None, :] - mean @ H.T, H, mu, sigma,
                           lambda m: y[..., None, None, :] - m @ H.T)
    for o, n in zip(old, new):
        assert torch.equal(o, n)
    for o, n in zip(old, mode_updates(mean, cov, y, model, mu, sigma)):
        assert torch.equal(o, n)
    batched = ekf_mode_updates(mean, cov, y[..., None, :] - obs(mean), obs.jacobian(mean), mu, sigma,
                               lambda m: y[..., None, None, :] - obs(m))
    for o, n in zip(old, batched):
        torch.testing.assert_close(n, o, rtol=1e-12, atol=1e-12)
    iterated = iekf_mode_updates(mean, cov, y, lambda x: (obs(x), obs.jacobian(x)), mu, sigma, 4)
    for o, n in zip(old, iterated):
        torch.testing.assert_close(n, o, rtol=1e-10, atol=1e-10)


def test_the_sensors_in_turn_are_the_joint_update_and_their_own_mode_chains():
    """mkf_step_sensors with a linear h (each sensor one coordinate of the position): one particle's state after the
    sensors in turn is the joint Kalman update with the modes it drew (sequential = batch for independent noises);
    its weight gains log sum_l gamma_j(l) per sensor; each sensor's mode chain and statistics are its own; a sensor
    that does not read at a step moves its mode probabilities by its pi and keeps its statistics."""
    n, k = 6, 2
    dt, q = 1.0, 0.5
    f = torch.tensor([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=F64)
    model = LinearGaussianState(f, q * torch.eye(4, dtype=F64), torch.zeros(1, 4, dtype=F64))
    rows = torch.tensor([[[1.0, 0, 0, 0]], [[0, 1.0, 0, 0]], [[1.0, 1.0, 0, 0]]], dtype=F64)  # three sensors

    def observe(j, x):
        return x @ rows[j].T, rows[j].expand(*x.shape[:-1], 1, 4)

    sig = torch.tensor([[0.4, 2.0], [0.6, 1.5], [0.3, 3.0]], dtype=F64)  # (S, K)
    pi = torch.tensor([[[0.9, 0.1], [0.3, 0.7]], [[0.8, 0.2], [0.5, 0.5]], [[0.95, 0.05], [0.2, 0.8]]], dtype=F64)
    theta = NoiseParams(torch.zeros(3, k, dtype=F64), sig, pi)
    m0 = torch.tensor([1.0, -1.0, 0.5, 0.2], dtype=F64)
    p0 = torch.tensor(P)
    st = init_state(m0, p0, torch.tensor([0.6, 0.4], dtype=F64), n, stats_dim(k))
    st = MKFState(st.mean, st.cov, st.alpha[:, None, :].expand(n, 3, k).clone(), st.logw,
                  st.T[:, None, :].expand(n, 3, stats_dim(k)).clone())
    y = torch.tensor([[1.7], [-0.6], [0.9]], dtype=F64)
    vis = torch.tensor([True, False, True])
    new, info = mkf_step_sensors(st, y, vis, model, observe, theta, torch.Generator().manual_seed(2), eta=0.5,
                                 ess_threshold=0.0, predict=True)
    mp = f @ m0
    pp = f @ p0 @ f.T + q * torch.eye(4, dtype=F64)
    for i in range(n):
        modes = [int(new.alpha[i, j].argmax()) for j in (0, 2)]
        assert all(float(new.alpha[i, j].max()) == 1.0 for j in (0, 2))  # drawn: one-hot
        hj = torch.cat([rows[0], rows[2]])
        r = torch.diag(torch.stack([sig[0, modes[0]], sig[2, modes[1]]]) ** 2)
        s = hj @ pp @ hj.T + r
        kg = pp @ hj.T @ torch.linalg.inv(s)
        want_m = mp + kg @ (torch.cat([y[0], y[2]]) - hj @ mp)
        want_p = (torch.eye(4, dtype=F64) - kg @ hj) @ pp
        torch.testing.assert_close(new.mean[i], want_m, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(new.cov[i], want_p, rtol=1e-10, atol=1e-12)
    # sensor 1 read nothing: its mode probabilities moved by its pi, its statistics stayed
    torch.testing.assert_close(new.alpha[:, 1], (torch.tensor([0.6, 0.4], dtype=F64) @ pi[1]).expand(n, k),
                               rtol=1e-15, atol=0)
    assert torch.equal(new.T[:, 1], st.T[:, 1]) and bool((new.T[:, 0] != 0).any()) and bool((new.T[:, 2] != 0).any())
    # the weights: the normalised product over the reading sensors of sum_l gamma_j(l), the second sensor's from the
    # filter the first one updated (the same for every particle here only where their first modes agree)
    assert torch.isfinite(info["loglik"]) and abs(float(new.logw.exp().sum()) - 1.0) < 1e-12
