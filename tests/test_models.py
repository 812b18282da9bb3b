import math

import gpytorch
import pytest
import torch

from dslearn.errors import ConfigError
from dslearn.models import ConstantVelocity, GPMotionModel, SocialForce
from dslearn.models.gp_backends.exact import OnlineGP
from dslearn.models.social_force import social_force_acceleration
from dslearn.types import StepContext, batch_jacobian

CTX = StepContext(dt=0.25)
D = torch.float64


def test_social_force_two_agents_by_hand():
    pos = torch.tensor([[0.0, 0.0], [3.0, 4.0]], dtype=D)  # distance 5
    vel = torch.tensor([[1.0, 0.0], [0.0, 0.0]], dtype=D)
    desired = torch.tensor([[1.0, -1.0], [-1.0, -1.0]], dtype=D)
    tau, alpha, beta = (torch.full((2,), v, dtype=D) for v in (0.25, 6.0, 5.0))
    g = social_force_acceleration(pos, vel, desired, tau, alpha, beta)
    push = 6.0 * math.exp(-1.0)  # alpha e^{-d/beta}, d = beta = 5
    exp0 = torch.tensor([(1 - 1) / 0.25 + push * (-3 / 5), (-1 - 0) / 0.25 + push * (-4 / 5)], dtype=D)
    exp1 = torch.tensor([(-1 - 0) / 0.25 + push * (3 / 5), (-1 - 0) / 0.25 + push * (4 / 5)], dtype=D)
    assert torch.allclose(g[0], exp0, atol=1e-12)
    assert torch.allclose(g[1], exp1, atol=1e-12)


def test_social_force_step_and_jacobian():
    sfm = SocialForce([[1, -1], [-1, -1]])
    x = torch.tensor([[2.0, 6.0, 1.0, -1.0, 6.0, 6.0, -1.0, -1.0]], dtype=D)
    nxt = sfm(x, CTX)
    assert torch.allclose(nxt[0, :2], x[0, :2] + 0.25 * x[0, 2:4])
    jac = sfm.jacobian(x, CTX)
    eps = 1e-6
    fd = torch.stack([(sfm(x + eps * e, CTX) - sfm(x - eps * e, CTX))[0] / (2 * eps) for e in torch.eye(8, dtype=D)], -1)
    assert torch.allclose(jac[0], fd, atol=1e-7)
    # coincident agents: finite force and Jacobian
    y = torch.tensor([[4.0, 4.0, 0, 0, 4.0, 4.0, 0, 0]], dtype=D)
    assert torch.isfinite(sfm(y, CTX)).all() and torch.isfinite(sfm.jacobian(y, CTX)).all()


def test_constant_velocity_matrix():
    lin = ConstantVelocity(2, 0.1)
    x = torch.randn(3, 8, dtype=D)
    # by hand: positions move by v dt, velocities stay
    ag = x.unflatten(-1, (2, 4))
    expected = torch.cat([ag[..., :2] + 0.25 * ag[..., 2:], ag[..., 2:]], -1).flatten(-2)
    assert torch.allclose(lin(x, CTX), expected, atol=1e-15)
    assert torch.allclose(x @ lin.matrix(0.25).T, expected, atol=1e-15)
    assert torch.allclose(lin.jacobian(x, CTX), batch_jacobian(lambda z: lin(z, CTX), x))
    assert torch.allclose(lin.noise_cov(x, CTX)[0], 0.01 * torch.eye(8, dtype=D))
    with pytest.raises(ConfigError, match="model.noise_std"):
        ConstantVelocity(2, -1.0)


def _plain_gp(X, Y, xq, sf2, ls, noise):
    def k(a, b):
        return sf2 * torch.exp(-0.5 * torch.cdist(a, b).pow(2) / ls**2)

    K = k(X, X) + noise * torch.eye(len(X), dtype=D)
    ks = k(X, xq)
    mean = ks.T @ torch.linalg.solve(K, Y)
    var = sf2 - (ks * torch.linalg.solve(K, ks)).sum(0)
    return mean, var


def _filled(mean="zero", n=60, s=3, d=4, invalid_every=0):
    gp = OnlineGP(s, d, d, outputscale=1.3, lengthscale=1.7, noise_std=0.4, mean=mean, capacity=16)
    X = torch.randn(n, s, d, dtype=D)
    for i in range(n):
        valid = torch.ones(s, dtype=torch.bool)
        if invalid_every and i % invalid_every == 0:
            valid[1] = False
        gp.append(X[i], torch.sin(X[i]) + X[i], valid)
    return gp


@pytest.mark.parametrize("mean", ["zero", "identity"])
def test_online_gp_equals_closed_form(mean):
    gp = _filled(mean, invalid_every=5)  # also grows the buffer several times
    xq = torch.randn(3, 5, 4, dtype=D)
    m, v, _ = gp.predict(xq)
    for s in range(3):
        keep = gp.mask[s, : gp.n]
        X = gp.X[s, : gp.n][keep]
        Y = torch.sin(X) + X - (X if mean == "identity" else 0)
        em, ev = _plain_gp(X, Y, xq[s], 1.3**2, 1.7, 0.16)
        if mean == "identity":
            em = em + xq[s]
        assert torch.allclose(m[s], em, atol=1e-9)
        assert torch.allclose(v[s], ev, atol=1e-9)
    assert int(gp.mask[1, : gp.n].sum()) == 48


def test_online_gp_matches_gpytorch_exact_gp():
    gp = _filled("zero", n=40, s=1, d=2)
    X, Y = gp.X[0, :40], gp.R[0, :40, 0]

    class Exact(gpytorch.models.ExactGP):
        def __init__(self):
            lik = gpytorch.likelihoods.GaussianLikelihood()
            super().__init__(X, Y, lik)
            self.mean_module = gpytorch.means.ZeroMean()
            self.covar_module = gpytorch.kernels.ScaleKernel(gpytorch.kernels.RBFKernel())

        def forward(self, x):
            return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))

    ref = Exact().double()
    ref.covar_module.outputscale = 1.3**2
    ref.covar_module.base_kernel.lengthscale = 1.7
    ref.likelihood.noise = 0.16
    ref.eval()
    xq = torch.randn(7, 2, dtype=D)
    with torch.no_grad(), gpytorch.settings.fast_computations(False, False, False):
        post = ref(xq)
    m, v, _ = gp.predict(xq.unsqueeze(0))
    assert torch.allclose(m[0, :, 0], post.mean, atol=1e-9)
    assert torch.allclose(v[0], post.variance, atol=1e-9)


def test_incremental_alpha_and_factor_equal_refit():
    gp = _filled("zero", n=80)
    alpha_inc = gp.alpha.clone()
    L_inc = gp.L[:, : gp.n, : gp.n].clone()
    gp.refactorize()
    assert torch.allclose(gp.L[:, : gp.n, : gp.n], L_inc, atol=1e-10)
    assert torch.allclose(gp.alpha, alpha_inc, atol=1e-9)


@pytest.mark.parametrize("mean", ["zero", "identity"])
def test_gp_jacobian_finite_differences_and_autograd(mean):
    model = GPMotionModel(4, num_nodes=2, mean=mean, lengthscale=1.5)
    X = torch.randn(30, 2, 4, dtype=D)
    for i in range(30):
        model.add_data(X[i], torch.tanh(X[i]))
    x = torch.randn(2, 3, 4, dtype=D)
    _, jac, q = model.linearize(x, CTX)
    eps = 1e-6
    fd = torch.stack([(model(x + eps * e, CTX) - model(x - eps * e, CTX)) / (2 * eps) for e in torch.eye(4, dtype=D)], -1)
    assert torch.allclose(jac, fd, atol=1e-7)
    assert torch.allclose(jac, model._autograd_jacobian(x), atol=1e-10)
    # Q = Sigma_f(x) I (noise=latent): the exact GP's latent variance at each query, from scratch with the
    # stored hyperparameters (1, 1.5, 0.5^2), below the prior variance sf^2 = 1
    for s in range(2):
        sf2, ls, s2 = (float(t.flatten()[s]) for t in (model.gp.outputscale, model.gp.lengthscale, model.gp.noise_var))
        _, var = _plain_gp(X[:, s], torch.tanh(X[:, s]), x[s], sf2, ls, s2)
        assert 0 < float(var.min()) and float(var.max()) < sf2
        torch.testing.assert_close(q[s], var[:, None, None] * torch.eye(4, dtype=D), rtol=0, atol=1e-10)


def test_gp_save_load_roundtrip(tmp_path):
    model = GPMotionModel(4, num_nodes=2, mean="identity")
    for _ in range(10):
        x = torch.randn(2, 4, dtype=D)
        model.add_data(x, x + 0.1)
    model.save(tmp_path / "gp.pt")
    other = GPMotionModel(4, num_nodes=2, mean="identity").load(tmp_path / "gp.pt")
    x = torch.randn(2, 5, 4, dtype=D)
    assert torch.allclose(model(x, CTX), other(x, CTX), atol=1e-12)


def test_gp_fit_increases_marginal_likelihood():
    gp = OnlineGP(1, 1, 1, outputscale=1.0, lengthscale=1.0, noise_std=0.5)
    x = torch.linspace(-3, 3, 40, dtype=D).reshape(40, 1, 1)
    for i in range(40):
        gp.append(x[i], torch.sin(2 * x[i]) + 0.05 * torch.randn(1, 1, dtype=D))
    losses = gp.fit(iters=60, lr=0.1)
    assert losses[-1] < losses[0] - 0.1
    m, _, _ = gp.predict(torch.tensor([[[0.5]]], dtype=D))
    assert abs(float(m) - math.sin(1.0)) < 0.15


def test_gp_bad_hyperparameters():
    with pytest.raises(ConfigError, match="model.noise_std"):
        OnlineGP(1, 2, 2, noise_std=0.0)
    with pytest.raises(ConfigError, match="model.mean"):
        OnlineGP(1, 2, 2, mean="linear")


@pytest.mark.parametrize("mean", ["zero", "identity", "constant"])
def test_gp_fit_keeps_the_data(mean):
    """Fitting changes hyperparameters only: the stored outputs are the same afterwards."""
    gp = _filled(mean, n=30)
    targets = gp.R[:, : gp.n] + gp.prior_mean(gp.X[:, : gp.n])
    gp.fit(iters=3, lr=0.05)
    after = gp.R[:, : gp.n] + gp.prior_mean(gp.X[:, : gp.n])
    assert torch.allclose(after * gp.mask[:, : gp.n, None], targets * gp.mask[:, : gp.n, None], atol=1e-12)


def test_gp_save_load_grown_buffer_and_mismatch(tmp_path):
    from dslearn.errors import DataFormatError

    torch.manual_seed(0)
    model = GPMotionModel(4, num_nodes=2, mean="identity", lengthscale=1.5, capacity=4)
    for _ in range(9):  # grows past the initial buffer
        x = torch.randn(2, 4, dtype=D)
        model.add_data(x, x + 0.1 * torch.randn(2, 4, dtype=D))
    p = tmp_path / "gp.pt"
    model.save(p)
    other = GPMotionModel(4, num_nodes=2, mean="identity", lengthscale=1.5)
    other.load(p)
    xq = torch.randn(2, 3, 4, dtype=D)
    for a, b in zip(model.linearize(xq, CTX), other.linearize(xq, CTX)):  # mean, Jacobian, Q
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    with pytest.raises(ConfigError, match="2 nodes|3 nodes|does not match"):
        GPMotionModel(4, num_nodes=3, mean="identity").load(p)
    with pytest.raises(ConfigError, match="class"):
        ConstantVelocity(1, 0.1).load(p)
    torch.save({"X": 1}, tmp_path / "bad.pt")
    with pytest.raises(DataFormatError):
        other.load(tmp_path / "bad.pt")
