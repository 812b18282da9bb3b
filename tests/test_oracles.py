"""Filter steps against independent oracles.

* filterpy (``KalmanFilter``, ``ExtendedKalmanFilter``, ``UnscentedKalmanFilter`` with
  ``MerweScaledSigmaPoints``) on the same mean, covariance and model as the information-form
  steps of :mod:`dslearn.filters.information` and :mod:`dslearn.filters.ukf`; the information
  pairs are converted to moments with numpy. Motion models for filterpy are written here in
  numpy (social force, GP posterior mean), with Jacobians by hand or by Richardson-extrapolated
  central differences, never by the project's ``linearize``.
* The chi-square gate against a hand Mahalanobis distance and ``scipy.stats.chi2.ppf``, in a
  case where the prior covariance decides.
* :class:`~dslearn.models.observation.GPObservation` against a hand GP posterior on five points,
  its Jacobian against central differences of its own mean.
"""

import numpy as np
import pytest
import torch
from filterpy.kalman import ExtendedKalmanFilter, KalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter
from scipy.stats import chi2

from dslearn.filters.information import chi2_quantile, novel_information, predict
from dslearn.filters.ukf import UnscentedPredict, sigma_points, unscented_weights
from dslearn.fusion.strategies import make_fusion
from dslearn.models import ConstantVelocity, GPMotionModel, GPObservation, LinearPositionObservation, SocialForce
from dslearn.types import StepContext

D = torch.float64
DT = 0.25
CTX = StepContext(dt=DT)
RTOL = 1e-10


# ------------------------------------------------------------------ helpers (numpy, independent)
def assert_rel(actual, expected, rtol=RTOL):
    """Norm-wise relative agreement: ``max |a - e| <= rtol * max |e|``."""
    a, e = np.asarray(actual, dtype=np.float64), np.asarray(expected, dtype=np.float64)
    assert a.shape == e.shape, (a.shape, e.shape)
    err, scale = float(np.abs(a - e).max()), float(np.abs(e).max())
    assert err <= rtol * scale, f"max abs error {err:.3e} > {rtol:g} x {scale:.3e}"


def moments(y: torch.Tensor, omega: torch.Tensor):
    """Information-form belief of one node/episode -> (mean, covariance) in numpy."""
    return y.detach().numpy().copy(), np.linalg.inv(omega.detach().numpy())


def posterior(q: torch.Tensor, omega: torch.Tensor):
    """Information pair -> (mean, covariance) in numpy."""
    o = omega.detach().numpy()
    return np.linalg.solve(o, q.detach().numpy()), np.linalg.inv(o)


def spd_np(n, rng, scale=1.0, floor=0.2):
    a = rng.normal(size=(n, n))
    return scale * (a @ a.T / n + floor * np.eye(n))


def fd_jacobian(f, x, h=1e-3):
    """Central differences with one Richardson step (error O(h^4)): ``f: (n,) -> (m,)`` -> ``(m, n)``."""
    x = np.asarray(x, dtype=np.float64)

    def central(hh):
        cols = []
        for i in range(x.size):
            e = np.zeros_like(x)
            e[i] = hh
            cols.append((f(x + e) - f(x - e)) / (2 * hh))
        return np.stack(cols, -1)

    return (4 * central(h / 2) - central(h)) / 3


def cv_matrix(num_agents, dt):
    """Constant-velocity transition, written out by hand."""
    block = np.array([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=np.float64)
    return np.kron(np.eye(num_agents), block)


# social force (Yu et al. Eq. (3)-(4)) in numpy, for agents further apart than the softening
SF = dict(
    desired=np.array([[1.0, 0.2], [-0.6, 0.8], [0.3, -1.1]]),
    tau=np.array([0.5, 0.8, 0.6]),
    alpha=np.array([6.0, 4.0, 5.0]),
    beta=np.array([5.0, 3.0, 4.0]),
)


def sf_model(noise_std=0.05):
    return SocialForce(SF["desired"].tolist(), SF["tau"].tolist(), SF["alpha"].tolist(), SF["beta"].tolist(), noise_std)


def sf_f(x, dt=DT):
    a = x.reshape(-1, 4)
    pos, vel = a[:, :2], a[:, 2:]
    acc = (SF["desired"] - vel) / SF["tau"][:, None]
    for j in range(len(a)):
        for k in range(len(a)):
            if j != k:
                u = pos[j] - pos[k]
                d = np.sqrt(u @ u)
                acc[j] += SF["alpha"][j] * np.exp(-d / SF["beta"][j]) * u / d
    return np.concatenate([pos + vel * dt, vel + acc * dt], 1).reshape(-1)


def sf_jac(x, dt=DT):
    r"""Hand Jacobian: :math:`\partial_u [\phi(d) u/d] = (\phi/d) I - \phi (1/(\beta d) + 1/d^2)\, u u^T/d`,
    :math:`\phi = \alpha e^{-d/\beta}`."""
    a = x.reshape(-1, 4)
    n = len(a)
    F = np.eye(4 * n)
    for j in range(n):
        F[4 * j : 4 * j + 2, 4 * j + 2 : 4 * j + 4] = dt * np.eye(2)
        F[4 * j + 2 : 4 * j + 4, 4 * j + 2 : 4 * j + 4] = (1 - dt / SF["tau"][j]) * np.eye(2)
        for k in range(n):
            if j == k:
                continue
            u = a[j, :2] - a[k, :2]
            d = np.sqrt(u @ u)
            phi = SF["alpha"][j] * np.exp(-d / SF["beta"][j])
            J = phi / d * np.eye(2) - phi * (1 / (SF["beta"][j] * d) + 1 / d**2) * np.outer(u, u) / d
            F[4 * j + 2 : 4 * j + 4, 4 * j : 4 * j + 2] += dt * J
            F[4 * j + 2 : 4 * j + 4, 4 * k : 4 * k + 2] -= dt * J
    return F


def sf_prior(rng, nodes):
    """Means of three agents about 3 m apart, moving; covariances with cross-agent terms."""
    base = np.array([0.0, 0.0, 0.9, 0.3, 3.1, 0.5, -0.4, 0.7, 1.2, 2.9, 0.2, -0.9])
    means = [base + 0.1 * rng.normal(size=12) for _ in range(nodes)]
    covs = [spd_np(12, rng, scale=0.05) for _ in range(nodes)]
    return means, covs


def min_softening_margin(points, cov, softening=0.2):
    """Smallest ``d_jk - eps_jk`` over sigma points and pairs (> 0: the plain distance applies)."""
    var = np.diag(cov).reshape(-1, 4)[:, :2].mean(-1)
    eps = np.sqrt(softening**2 + var[:, None] + var[None, :])
    p = points.reshape(len(points), -1, 4)[..., :2]
    d = np.sqrt(((p[:, :, None] - p[:, None, :]) ** 2).sum(-1))
    off = ~np.eye(p.shape[1], dtype=bool)
    return float((d - eps)[:, off].min())


# GP posterior by hand: k(a, b) = sf2 exp(-|a - b|^2 / 2 l^2), noise sn2
def rbf(a, b, sf2, ls):
    d2 = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
    return sf2 * np.exp(-0.5 * d2 / ls**2)


def effective_hyperparameters(gp, hyp):
    """The hyperparameters the GP holds, ``sf2, ls, sn2`` for :func:`gp_posterior`.

    They are the configured ones only to float32 precision (GPyTorch's raw parameters are
    created in float32 before the module moves to float64, see
    :func:`test_gp_hyperparameters_are_stored_in_float64`), so the hand posterior takes the
    stored values; their closeness to the configured ones is checked here at float32 rounding.
    """
    sf2, ls, sn2 = (getattr(gp, k).numpy() for k in ("outputscale", "lengthscale", "noise_var"))
    for got, want in ((sf2, hyp["outputscale"] ** 2), (ls, hyp["lengthscale"]), (sn2, hyp["noise_std"] ** 2)):
        assert np.all(got == got[0]) and abs(got[0] / want - 1) < 4 * np.finfo(np.float32).eps
    return dict(sf2=float(sf2[0]), ls=float(ls[0]), sn2=float(sn2[0]))


def gp_posterior(X, Y, xq, sf2, ls, sn2, prior):
    """Mean ``(N, Dy)`` and latent variance ``(N,)``: ``k** - k*^T (K + sn2 I)^{-1} k*``."""
    K = rbf(X, X, sf2, ls) + sn2 * np.eye(len(X))
    ks = rbf(X, xq, sf2, ls)  # (n, N)
    mean = prior(xq) + ks.T @ np.linalg.solve(K, Y - prior(X))
    var = sf2 - np.einsum("nq,nq->q", ks, np.linalg.solve(K, ks))
    return mean, var


# ------------------------------------------------------------------ 1. Kalman filter, linear model
@pytest.mark.parametrize("fusion", ["individual", "centralized"])
def test_cv_predict_and_information_update_match_filterpy(fusion):
    """Constant velocity + linear position measurements: the EKF prediction and the novel
    information with the individual / centralised update are the Kalman filter (filterpy)."""
    rng = np.random.default_rng(1)
    s, b, a, sig_q, sig_r = 2, 2, 2, 0.1, 0.3
    dx = 4 * a
    model, obs = ConstantVelocity(a, sig_q), LinearPositionObservation(sig_r)
    means = rng.normal(size=(s, b, dx))
    covs = np.stack([[spd_np(dx, rng, scale=0.5) for _ in range(b)] for _ in range(s)])
    mean_t = torch.tensor(means, dtype=D)
    omega_t = torch.tensor(np.linalg.inv(covs), dtype=D)
    meas = torch.tensor(rng.normal(size=(s, b, a, 2)), dtype=D)
    visible = torch.tensor([[[True, True], [False, True]], [[False, True], [True, False]]])

    y_pred, q_pred, o_pred = predict(mean_t, omega_t, model, CTX)
    dq, do = novel_information(y_pred, meas, visible, obs)
    q, o = make_fusion(fusion, torch.eye(s, dtype=D))(q_pred, o_pred, dq, do)

    F, Hrow = cv_matrix(a, DT), np.eye(2, 4)
    for i in range(s):
        for e in range(b):
            senders = range(s) if fusion == "centralized" else [i]
            rows = [(n, j) for n in senders for j in range(a) if visible[n, e, j]]
            kf = KalmanFilter(dim_x=dx, dim_z=2 * len(rows))
            kf.x, kf.P = means[i, e].reshape(-1, 1).copy(), covs[i, e].copy()
            kf.F, kf.Q = F, sig_q**2 * np.eye(dx)
            kf.predict()
            ym, Pm = moments(y_pred[i, e], o_pred[i, e])
            assert_rel(ym, kf.x.ravel())
            assert_rel(Pm, kf.P)
            assert_rel((o_pred[i, e] @ y_pred[i, e]).numpy(), q_pred[i, e].numpy())
            H = np.zeros((2 * len(rows), dx))
            for r, (_, j) in enumerate(rows):
                H[2 * r : 2 * r + 2, 4 * j : 4 * j + 4] = Hrow
            z = np.concatenate([meas[n, e, j].numpy() for n, j in rows]).reshape(-1, 1)
            kf.H, kf.R = H, sig_r**2 * np.eye(2 * len(rows))
            kf.update(z)
            xm, Px = posterior(q[i, e], o[i, e])
            assert_rel(xm, kf.x.ravel())
            assert_rel(Px, kf.P)


# ------------------------------------------------------------------ 2. EKF prediction, nonlinear models
class _EKF(ExtendedKalmanFilter):
    """filterpy's EKF with a nonlinear mean propagation ``fx`` (its default is ``F x``)."""

    def __init__(self, dim_x, fx):
        super().__init__(dim_x=dim_x, dim_z=1)
        self.fx = fx

    def predict_x(self, u=0):
        self.x = self.fx(self.x.ravel()).reshape(-1, 1)


def test_social_force_hand_jacobian_is_the_derivative():
    """The hand Jacobian used as filterpy's ``F`` is the derivative of the numpy model."""
    rng = np.random.default_rng(2)
    (x,), _ = sf_prior(rng, 1)
    J = sf_jac(x)
    assert_rel(J, fd_jacobian(sf_f, x), rtol=1e-9)
    assert np.abs(J - J.T).max() > 1e-2  # not symmetric: F P F^T and F^T P F differ


def test_ekf_predict_social_force_matches_filterpy():
    """Social force (three interacting agents): prediction mean f(y) and covariance F P F^T + Q
    against filterpy's EKF with the hand Jacobian; per node, each with its own belief."""
    rng = np.random.default_rng(3)
    s, sig_q = 2, 0.05
    means, covs = sf_prior(rng, s)
    mean_t = torch.tensor(np.stack(means)[:, None], dtype=D)  # (S, 1, Dx)
    omega_t = torch.tensor(np.linalg.inv(np.stack(covs))[:, None], dtype=D)
    for i in range(s):  # agents at least the softening apart: the model is the plain Eq. (4)
        assert min_softening_margin(means[i][None], covs[i]) > 0.5

    y_pred, _, o_pred = predict(mean_t, omega_t, sf_model(sig_q), CTX)
    for i in range(s):
        ekf = _EKF(12, sf_f)
        ekf.x, ekf.P = means[i].reshape(-1, 1).copy(), covs[i].copy()
        ekf.F, ekf.Q = sf_jac(means[i]), sig_q**2 * np.eye(12)
        ekf.predict()
        ym, Pm = moments(y_pred[i, 0], o_pred[i, 0])
        assert_rel(ym, ekf.x.ravel())
        assert_rel(Pm, ekf.P)


def gp_motion(noise="predictive", nodes=2, n=6, seed=4):
    """A GP motion model (one agent, identity mean) on ``n`` points per node, and the hand data."""
    hyp = dict(outputscale=0.8, lengthscale=1.5, noise_std=0.3)
    model = GPMotionModel(4, nodes, mean="identity", noise=noise, **hyp)
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(nodes, n, 4))
    Y = X + 0.3 * np.tanh(np.roll(X, 1, -1)) + 0.05 * rng.normal(size=X.shape)
    for t in range(n):
        model.add_data(torch.tensor(X[:, t], dtype=D), torch.tensor(Y[:, t], dtype=D))
    return model, X, Y, effective_hyperparameters(model.gp, hyp)


def test_ekf_predict_gp_motion_matches_filterpy():
    """GP motion model (per node): mean = hand GP posterior mean, F by central differences of it,
    Q = (latent variance + sigma^2) I at the prior mean (``noise=predictive``)."""
    model, X, Y, hp = gp_motion()
    rng = np.random.default_rng(5)
    s = X.shape[0]
    means = [0.5 * rng.normal(size=4) for _ in range(s)]
    covs = [spd_np(4, rng, scale=0.3) for _ in range(s)]
    mean_t = torch.tensor(np.stack(means)[:, None], dtype=D)
    omega_t = torch.tensor(np.linalg.inv(np.stack(covs))[:, None], dtype=D)
    y_pred, _, o_pred = predict(mean_t, omega_t, model, CTX)
    for i in range(s):
        fx = lambda x, i=i: gp_posterior(X[i], Y[i], x[None], **hp, prior=lambda z: z)[0][0]  # noqa: E731
        var = gp_posterior(X[i], Y[i], means[i][None], **hp, prior=lambda z: z)[1][0]
        ekf = _EKF(4, fx)
        ekf.x, ekf.P = means[i].reshape(-1, 1).copy(), covs[i].copy()
        ekf.F, ekf.Q = fd_jacobian(fx, means[i]), (var + hp["sn2"]) * np.eye(4)
        ekf.predict()
        ym, Pm = moments(y_pred[i, 0], o_pred[i, 0])
        assert_rel(ym, ekf.x.ravel())
        assert_rel(Pm, ekf.P)


# ------------------------------------------------------------------ 3. UKF prediction
UKF_PARAMS = [(0.5, 1.0, 1.0), (1.0, 2.0, 0.0), (0.8, 0.0, -3.0)]


@pytest.mark.parametrize("alpha,beta,kappa", UKF_PARAMS)
def test_weights_and_sigma_points_are_merwe(alpha, beta, kappa):
    """``unscented_weights`` / ``sigma_points`` are filterpy's Merwe scaled points, same order
    (centre, then + and - along the rows of the upper Cholesky factor of (Dx + lambda) P)."""
    rng = np.random.default_rng(6)
    n = 8
    m, P = rng.normal(size=n), spd_np(n, rng)
    pts = MerweScaledSigmaPoints(n, alpha=alpha, beta=beta, kappa=kappa)
    wm, wc, c = unscented_weights(n, alpha, beta, kappa)
    assert_rel(wm.numpy(), pts.Wm, rtol=1e-13)
    assert_rel(wc.numpy(), pts.Wc, rtol=1e-13)
    lam = alpha**2 * (n + kappa) - n  # filterpy's lambda_
    assert c == pytest.approx(n + lam, rel=1e-14)
    chi, _, _ = sigma_points(torch.tensor(m, dtype=D), torch.tensor(P, dtype=D), alpha, beta, kappa)
    assert_rel(chi.numpy(), pts.sigma_points(m, P), rtol=1e-12)


def _ukf_check(step, model, means, covs, fxs, Qs, points):
    """Run ``step`` on the stacked beliefs and filterpy's UKF per node; compare moments."""
    n = means[0].size
    mean_t = torch.tensor(np.stack(means)[:, None], dtype=D)
    omega_t = torch.tensor(np.linalg.inv(np.stack(covs))[:, None], dtype=D)
    y_pred, q_pred, o_pred = step(mean_t, omega_t, model, CTX)
    for i, (fx, Q) in enumerate(zip(fxs, Qs)):
        ukf = UnscentedKalmanFilter(dim_x=n, dim_z=1, dt=DT, hx=None, fx=lambda x, dt, f=fx: f(x), points=points(n))
        ukf.x, ukf.P, ukf.Q = means[i].copy(), covs[i].copy(), Q
        ukf.predict()
        ym, Pm = moments(y_pred[i, 0], o_pred[i, 0])
        assert_rel(ym, ukf.x)
        assert_rel(Pm, ukf.P)
        assert_rel((o_pred[i, 0] @ y_pred[i, 0]).numpy(), q_pred[i, 0].numpy())


@pytest.mark.parametrize("alpha,beta,kappa", UKF_PARAMS)
def test_ukf_predict_social_force_matches_filterpy(alpha, beta, kappa):
    """UnscentedPredict(alpha, beta, kappa) on the social force = filterpy's UKF with
    MerweScaledSigmaPoints(n, alpha, beta, kappa) and the numpy model."""
    rng = np.random.default_rng(7)
    means, covs = sf_prior(rng, 2)
    pts = lambda n: MerweScaledSigmaPoints(n, alpha=alpha, beta=beta, kappa=kappa)  # noqa: E731
    for m, P in zip(means, covs):  # every sigma point on the plain-distance branch of the model
        assert min_softening_margin(pts(12).sigma_points(m, P), P) > 0.2
    sig_q = 0.05
    _ukf_check(UnscentedPredict(alpha, beta, kappa), sf_model(sig_q), means, covs, [sf_f] * 2,
               [sig_q**2 * np.eye(12)] * 2, pts)
    # the model is nonlinear at this spread: the unscented mean is not the EKF's f(y)
    m0, o0 = torch.tensor(means[0][None, None]), torch.tensor(np.linalg.inv(covs[0])[None, None])
    y_ekf = predict(m0, o0, sf_model(sig_q), CTX)[0]
    y_ukf = UnscentedPredict(alpha, beta, kappa)(m0, o0, sf_model(sig_q), CTX)[0]
    assert float((y_ekf - y_ukf).abs().max()) > 1e-4


def test_ukf_predict_constant_velocity_matches_filterpy():
    """Linear model: the unscented step (non-default parameters) is filterpy's UKF, and the KF."""
    rng = np.random.default_rng(8)
    a, sig_q = 2, 0.1
    means = [rng.normal(size=8) for _ in range(2)]
    covs = [spd_np(8, rng) for _ in range(2)]
    F = cv_matrix(a, DT)
    pts = lambda n: MerweScaledSigmaPoints(n, alpha=0.5, beta=1.0, kappa=1.0)  # noqa: E731
    _ukf_check(UnscentedPredict(0.5, 1.0, 1.0), ConstantVelocity(a, sig_q), means, covs, [lambda x: F @ x] * 2,
               [sig_q**2 * np.eye(8)] * 2, pts)


def test_ukf_predict_gp_motion_matches_filterpy():
    """GP motion model, two nodes with their own data: each node's sigma points go through its
    own GP; Q is the documented process noise at the prior mean (latent + sigma^2, predictive)."""
    model, X, Y, hp = gp_motion()
    rng = np.random.default_rng(9)
    means = [0.5 * rng.normal(size=4) for _ in range(2)]
    covs = [spd_np(4, rng, scale=0.3) for _ in range(2)]
    fxs, Qs = [], []
    for i in range(2):
        fxs.append(lambda x, i=i: gp_posterior(X[i], Y[i], x[None], **hp, prior=lambda z: z)[0][0])
        var = gp_posterior(X[i], Y[i], means[i][None], **hp, prior=lambda z: z)[1][0]
        Qs.append((var + hp["sn2"]) * np.eye(4))
    pts = lambda n: MerweScaledSigmaPoints(n, alpha=0.5, beta=1.0, kappa=1.0)  # noqa: E731
    _ukf_check(UnscentedPredict(0.5, 1.0, 1.0), model, means, covs, fxs, Qs, pts)


# ------------------------------------------------------------------ GP observation model
def gp_observation(noise="predictive", mean="identity"):
    """Two nodes, five points each (node 1's third point appended as invalid), and the hand data."""
    hyp = dict(outputscale=1.5, lengthscale=1.2, noise_std=0.3)
    obs = GPObservation(2, mean=mean, noise=noise, **hyp)
    rng = np.random.default_rng(10)
    X = rng.normal(size=(2, 5, 4))
    Z = X[..., :2] + 0.4 * np.sin(X[..., 2:]) + 0.05 * rng.normal(size=(2, 5, 2))
    valid = np.ones((2, 5), dtype=bool)
    valid[1, 2] = False
    obs.add_data(torch.tensor(X, dtype=D), torch.tensor(Z, dtype=D), torch.tensor(valid))
    hand = effective_hyperparameters(obs.gp, hyp)
    hand["prior"] = (lambda z: z[..., :2]) if mean == "identity" else (lambda z: np.zeros((len(z), 2)))
    data = [(X[i][valid[i]], Z[i][valid[i]]) for i in range(2)]
    return obs, data, hand


@pytest.mark.parametrize("noise", ["predictive", "latent"])
@pytest.mark.parametrize("mean", ["identity", "zero"])
def test_gp_observation_mean_and_noise_match_hand_posterior(noise, mean):
    """h = m(y) + k*^T (K + sn^2 I)^{-1} (Z - m(X)); R = (k** - k*^T (K + sn^2 I)^{-1} k*) I
    (``latent``, the GP covariance Sigma_h) plus sn^2 I (``predictive``)."""
    obs, data, hp = gp_observation(noise, mean)
    rng = np.random.default_rng(11)
    y = rng.normal(size=(2, 1, 3, 4))
    h, C, R = obs.linearize(torch.tensor(y, dtype=D))
    assert h.shape == (2, 1, 3, 2) and C.shape == (2, 1, 3, 2, 4) and R.shape == (2, 1, 3, 2, 2)
    for i, (X, Z) in enumerate(data):
        mu, var = gp_posterior(X, Z, y[i, 0], **hp)
        assert_rel(h[i, 0].numpy(), mu)
        r = var + (hp["sn2"] if noise == "predictive" else 0.0)
        assert_rel(R[i, 0].numpy(), r[:, None, None] * np.eye(2))
    # far from the data the latent variance returns to the prior's sf^2
    far = torch.full((2, 1, 1, 4), 40.0, dtype=D)
    r_far = obs.noise_cov(far)[..., 0, 0]
    assert torch.allclose(r_far, torch.full_like(r_far, hp["sf2"] + (hp["sn2"] if noise == "predictive" else 0.0)),
                          rtol=1e-12)


def test_gp_hyperparameters_are_stored_in_float64():
    """A float64 GP holds the configured sigma_f^2, l and sigma^2 to float64 precision (set from
    float32 tensors before the module's cast, they would carry float32 rounding, ~1e-7 relative)."""
    gp = GPObservation(1, outputscale=1.5, lengthscale=1.2, noise_std=0.3).gp
    assert float(gp.outputscale[0]) == pytest.approx(2.25, rel=1e-14)
    assert float(gp.lengthscale[0]) == pytest.approx(1.2, rel=1e-14)
    assert float(gp.noise_var[0]) == pytest.approx(0.09, rel=1e-14)


@pytest.mark.parametrize("mean", ["identity", "zero"])
def test_gp_observation_jacobian_is_central_difference_of_mean(mean):
    """C[i, j] = dh_i/dy_j by central differences (Richardson) of the model's own mean h."""
    obs, _, _ = gp_observation("predictive", mean)
    rng = np.random.default_rng(12)
    y = torch.tensor(rng.normal(size=(2, 1, 3, 4)), dtype=D)
    C = obs.jacobian(y)

    def central(hh):
        cols = []
        for k in range(4):
            e = torch.zeros(4, dtype=D)
            e[k] = hh
            cols.append((obs(y + e) - obs(y - e)) / (2 * hh))  # each target's h depends on its own state only
        return torch.stack(cols, -1)

    h = 1e-3
    fd = (4 * central(h / 2) - central(h)) / 3
    assert_rel(C.numpy(), fd.numpy(), rtol=1e-9)


def test_ekf_update_gp_observation_matches_filterpy():
    """Novel information of a learned (nonlinear) observation model + the information update
    against filterpy's EKF update with the hand GP mean as ``Hx``, its central-difference
    Jacobian and the hand R at the prior mean."""
    obs, data, hp = gp_observation("predictive", "identity")
    rng = np.random.default_rng(13)
    s, a = 2, 3
    means = [0.7 * rng.normal(size=4 * a) for _ in range(s)]
    covs = [spd_np(4 * a, rng, scale=0.3) for _ in range(s)]
    meas = torch.tensor(rng.normal(size=(s, 1, a, 2)), dtype=D)
    visible = torch.tensor([[[True, False, True]], [[True, True, True]]])
    y_t = torch.tensor(np.stack(means)[:, None], dtype=D)
    o_t = torch.tensor(np.linalg.inv(np.stack(covs))[:, None], dtype=D)
    q_t = (o_t @ y_t.unsqueeze(-1)).squeeze(-1)
    dq, do = novel_information(y_t, meas, visible, obs)
    q, o = make_fusion("individual", torch.eye(s, dtype=D))(q_t, o_t, dq, do)
    for i, (X, Z) in enumerate(data):
        seen = [j for j in range(a) if visible[i, 0, j]]

        def hx(x):
            ag = np.asarray(x).reshape(-1, 4)
            return gp_posterior(X, Z, ag[seen], **hp)[0].reshape(-1, 1)

        Hj = lambda x: fd_jacobian(lambda z: hx(z).ravel(), np.asarray(x).ravel())  # noqa: E731
        var = gp_posterior(X, Z, means[i].reshape(-1, 4)[seen], **hp)[1]
        R = np.kron(np.diag(var + hp["sn2"]), np.eye(2))
        ekf = ExtendedKalmanFilter(dim_x=4 * a, dim_z=2 * len(seen))
        ekf.x, ekf.P = means[i].reshape(-1, 1).copy(), covs[i].copy()
        ekf.update(meas[i, 0, seen].numpy().reshape(-1, 1), Hj, hx, R=R)
        xm, Px = posterior(q[i, 0], o[i, 0])
        assert_rel(xm, ekf.x.ravel())
        assert_rel(Px, ekf.P)


# ------------------------------------------------------------------ chi-square gate
@pytest.mark.parametrize("prob,dof", [(0.99, 2), (0.9, 2), (0.5, 2), (0.999, 2), (0.95, 3), (0.99, 4)])
def test_chi2_quantile_matches_scipy(prob, dof):
    assert chi2_quantile(prob, dof) == pytest.approx(float(chi2.ppf(prob, dof)), rel=1e-12)


def _gate_case(kind):
    """A prior over three agents and innovations whose gate decisions the prior covariance sets.

    Agent 0: along the widest direction of S = C P00 C^T + R, Mahalanobis distance 0.6 of the
    threshold under S, but beyond it under R alone. Agent 1: the same Euclidean norm along its
    narrowest direction of S: beyond the threshold. Agent 2: a small innovation (kept either way).
    """
    a, prob = 3, 0.99
    gamma = float(chi2.ppf(prob, 2))
    rng = np.random.default_rng(14)
    k = 1.0 if kind == "linear" else 4.0  # the learned R (sigma^2 + latent, about 0.2) exceeds 0.2^2
    pos = [k * np.array([[0.40, 0.12], [0.12, 0.08]]), k * np.array([[0.30, -0.05], [-0.05, 0.01]]), 0.05 * np.eye(2)]
    P = np.zeros((4 * a, 4 * a))
    for j in range(a):
        P[4 * j : 4 * j + 2, 4 * j : 4 * j + 2] = pos[j]
        P[4 * j + 2 : 4 * j + 4, 4 * j + 2 : 4 * j + 4] = 0.2 * np.eye(2)
    c = 0.02 * rng.normal(size=(4 * a, 4 * a))
    P = P + c @ c.T  # cross-agent and position-velocity terms
    y = np.concatenate([[0.3, -0.2, 0.5, 0.1], [2.0, 1.0, -0.3, 0.4], [-1.0, 0.5, 0.0, 0.2]])
    if kind == "linear":
        obs = LinearPositionObservation(0.2)
        h = y.reshape(-1, 4)[:, :2]
        Cs = [np.eye(2, 4)] * a
        Rs = [0.04 * np.eye(2)] * a
    else:  # targets near node 0's data, where the GP is confident; C by central differences
        obs, data, hp = gp_observation("predictive", "identity")
        X, Z = data[0]
        y = (X[:3] + 0.1 * rng.normal(size=(3, 4))).reshape(-1)
        h, var = gp_posterior(X, Z, y.reshape(-1, 4), **hp)
        Cs = [fd_jacobian(lambda z: gp_posterior(X, Z, z[None], **hp)[0][0], y[4 * j : 4 * j + 4]) for j in range(a)]
        Rs = [(v + hp["sn2"]) * np.eye(2) for v in var]
    S = [Cs[j] @ P[4 * j : 4 * j + 4, 4 * j : 4 * j + 4] @ Cs[j].T + Rs[j] for j in range(a)]
    nus = []
    w0, v0 = np.linalg.eigh(S[0])
    nus.append(v0[:, -1] * np.sqrt(0.6 * gamma * w0[-1]))
    w1, v1 = np.linalg.eigh(S[1])
    nus.append(v1[:, 0] * np.linalg.norm(nus[0]))
    nus.append(np.array([0.05, -0.03]))
    d2_S = [float(nu @ np.linalg.solve(S[j], nu)) for j, nu in enumerate(nus)]
    d2_R = [float(nu @ np.linalg.solve(Rs[j], nu)) for j, nu in enumerate(nus)]
    meas = h + np.stack(nus)
    return obs, P, y, meas, gamma, prob, d2_S, d2_R


@pytest.mark.parametrize("kind", ["linear", "gp"])
def test_chi2_gate_uses_prior_covariance(kind):
    """Decisions = hand Mahalanobis distance under S = C P_jj C^T + R against chi2.ppf; with the
    prior given, agent 0 is kept although R alone would reject it; without it, it is dropped."""
    obs, P, y, meas, gamma, prob, d2_S, d2_R = _gate_case(kind)
    keep_S = [d <= gamma for d in d2_S]
    keep_R = [d <= gamma for d in d2_R]
    assert keep_S == [True, False, True] and keep_R == [False, False, True]  # the case discriminates
    assert d2_S[1] > 1.5 * gamma and d2_R[0] > 1.5 * gamma  # margins far above rounding

    y_t = torch.tensor(y, dtype=D).reshape(1, 1, -1)
    if kind == "gp":  # the model holds two nodes: the gated node is node 0, node 1 sees nothing
        y_t = y_t.expand(2, 1, -1).clone()
    s = y_t.shape[0]
    meas_t = torch.tensor(meas, dtype=D).expand(s, 1, 3, 2).clone()
    visible = torch.zeros(s, 1, 3, dtype=torch.bool)
    visible[0] = True
    omega = torch.tensor(np.linalg.inv(P), dtype=D).expand(s, 1, 12, 12).clone()

    def kept(gate_omega):
        _, do = novel_information(y_t, meas_t, visible, obs, gate_prob=prob, omega_pred=gate_omega)
        blocks = torch.stack([do[0, 0, 4 * j : 4 * j + 4, 4 * j : 4 * j + 4] for j in range(3)])
        return [bool(bk.abs().max() > 0) for bk in blocks]

    assert kept(omega) == keep_S
    assert kept(None) == keep_R
    # a kept measurement contributes exactly what the ungated update does
    _, do_all = novel_information(y_t, meas_t, visible, obs)
    _, do_gated = novel_information(y_t, meas_t, visible, obs, gate_prob=prob, omega_pred=omega)
    torch.testing.assert_close(do_gated[0, 0, :4, :4], do_all[0, 0, :4, :4], rtol=0, atol=0)
