"""learner=backprop with the motion model's own parameters (learn: [model]): the social force's tau, alpha, beta,
the exact GP's hyperparameters, the LSTM's weights. The differentiable parts equal the models' own predictions,
their gradients are checked by gradcheck / finite differences through the filter and the consensus rounds, and
the social force's numbers learned from measurements alone come back towards the truth."""

import math

import pytest
import torch

from dslearn.episodes import Episodes
from dslearn.errors import ConfigError
from dslearn.fusion.strategies import HybridConsensus
from dslearn.fusion.weights import metropolis
from dslearn.learning.backprop import (BackpropParameters, DifferentiableGP, DifferentiableJacobian, GPParameters, LSTMParameters,
                                       SocialForceParameters, fit, run_filter)
from dslearn.models.gp import GPMotionModel
from dslearn.models.social_force import SocialForce
from dslearn.types import StepContext

DT = 0.4
CTX = StepContext(dt=DT)
D64 = torch.float64


@pytest.fixture(autouse=True)
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def line(s):
    adj = torch.zeros(s, s, dtype=torch.bool)
    for i in range(s - 1):
        adj[i, i + 1] = adj[i + 1, i] = True
    return adj


class Net:
    def __init__(self, s):
        self.num_nodes = s


def gp_with_data(mean="identity", noise="latent", nodes=2, appends=12, seed=0, **variant):
    torch.manual_seed(seed)
    m = GPMotionModel(4, nodes, outputscale=0.8, lengthscale=1.5, noise_std=0.3, mean=mean, noise=noise, **variant)
    for k in range(appends):
        x = torch.randn(nodes, 4, dtype=D64)
        y = x + 0.1 * torch.randn(nodes, 4, dtype=D64)
        valid = torch.ones(nodes, dtype=torch.bool)
        if k == 3:
            valid[0] = False  # one masked point in node 0's data set
        m.add_data(x, y, valid)
    if noise == "adaptive":
        m.q_noise.copy_(torch.tensor([[0.02, 0.05], [0.03, 0.01]], dtype=D64)[:nodes])
    return m


# ------------------------------------------------------------------------------------------------------ the GP
@pytest.mark.parametrize("mean,noise,variant", [("identity", "latent", {}), ("zero", "predictive", {}),
                                                ("identity", "adaptive", {}),
                                                ("identity", "latent", {"variant": "window", "window": 5})])
def test_differentiable_gp_equals_the_online_gp(mean, noise, variant):
    """Mean, Jacobian and Q of the refactorised posterior equal the online GP's incremental ones (also the sliding
    window's, past its window: 12 appends of 5)."""
    m = gp_with_data(mean, noise, **variant)
    dgp = GPParameters(m).build(None)
    x = torch.randn(2, 3, 4, dtype=D64)
    for a, b in zip(dgp.linearize(x, CTX), m.linearize(x, CTX)):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-11)


def test_gp_hyperparameter_gradients_gradcheck():
    """gradcheck of the GP's mean, Jacobian and latent variance in its log hyperparameters (float64)."""
    m = gp_with_data(nodes=1, appends=6)
    p = GPParameters(m)
    x = torch.randn(1, 2, 4, dtype=D64)

    def f(ls_log, os_log, noise_log):
        d = DifferentiableGP(m, p.X, p.R, p.data_mask, ls_log.exp(), os_log.exp(), noise_log.exp())
        return d.linearize(x, CTX)

    args = tuple(t.detach().clone().requires_grad_(True) for t in (p.ls_log, p.os_log, p.noise_log))
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-7)


def test_frozen_gp_takes_the_learned_hyperparameters():
    """frozen() writes the numbers into the model and refactorises: its own prediction then equals the
    differentiable one at those numbers."""
    m = gp_with_data()
    p = GPParameters(m)
    with torch.no_grad():
        p.ls_log += torch.tensor([0.3, -0.2], dtype=D64)
        p.os_log += 0.4
        p.noise_log -= 0.5
    want = p.build(None).linearize(torch.ones(2, 1, 4, dtype=D64), CTX)
    frozen = p.frozen(None)
    assert frozen is m
    torch.testing.assert_close(m.gp.lengthscale, p.ls_log.exp().detach(), rtol=1e-12, atol=0)
    got = m.linearize(torch.ones(2, 1, 4, dtype=D64), CTX)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b.detach(), rtol=1e-9, atol=1e-11)


# ------------------------------------------------------------------------------------------ the social force
def sfm(tau=0.5, alpha=2.0, beta=1.0, noise=0.02):
    return SocialForce([[1.0, 0.0], [-1.0, 0.2]], tau, alpha, beta, noise_std=noise, softening=0.2)


def simulate_crowd(model, b, k, s, r_std, seed):
    """Two agents walking towards each other under the social force, seen by every node of a line graph."""
    g = torch.Generator().manual_seed(seed)
    x = torch.zeros(b, 8, dtype=D64)
    x[:, 0:2] = torch.tensor([-3.0, 0.0]) + 0.3 * torch.randn(b, 2, generator=g, dtype=D64)
    x[:, 4:6] = torch.tensor([3.0, 0.3]) + 0.3 * torch.randn(b, 2, generator=g, dtype=D64)
    x[:, 2:4] = torch.tensor([1.0, 0.0]) + 0.2 * torch.randn(b, 2, generator=g, dtype=D64)
    x[:, 6:8] = torch.tensor([-1.0, 0.0]) + 0.2 * torch.randn(b, 2, generator=g, dtype=D64)
    xs = [x]
    with torch.no_grad():
        for _ in range(k):
            x = model(x, CTX) + model.noise_std * torch.randn(b, 8, generator=g, dtype=D64)
            xs.append(x)
    X = torch.stack(xs, 1)  # (B, K+1, 8)
    pos = X.reshape(b, k + 1, 2, 4)[..., :2]
    z = pos.unsqueeze(0) + r_std * torch.randn(s, b, k + 1, 2, 2, generator=g, dtype=D64)
    return Episodes(X, z, torch.ones(s, b, k + 1, 2, dtype=torch.bool))


def known_prior(ep, fusion):  # every node starts at the first state, known to 10 cm (no truth after t = 0)
    s, b = ep.meas.shape[:2]
    P = torch.diag(torch.tensor([0.01, 0.01, 0.04, 0.04] * 2, dtype=D64))
    return ep_first[0].expand(s, b, 8).clone(), P.expand(s, b, 8, 8).clone()


ep_first = [None]


def test_sfm_jacobian_is_the_models_own():
    m = sfm()
    x = torch.randn(3, 8, dtype=D64)
    y, F, Q = DifferentiableJacobian(m).linearize(x, CTX)
    torch.testing.assert_close(F, m.jacobian(x, CTX), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(y, m(x, CTX))
    torch.testing.assert_close(Q, m.noise_cov(x, CTX))


def test_sfm_gradcheck_through_the_filter_and_l_consensus_rounds():
    """The innovation loss through 3 steps of the information filter and L = 2 hybrid rounds, in tau, alpha,
    beta (and Q, R): autograd against finite differences (gradcheck, float64)."""
    s = 3
    ep = simulate_crowd(sfm(), 2, 3, s, 0.1, seed=1)
    ep_first[0] = ep.states[:, 0]
    fusion = HybridConsensus(metropolis(line(s)), 2, 1.0)
    motion = SocialForceParameters(sfm(tau=0.7, alpha=1.5, beta=1.2))
    params = BackpropParameters(2, None, 0.02**2 * torch.eye(4, dtype=D64), 0.01 * torch.eye(2, dtype=D64), fusion,
                                line(s), learn=("model", "q", "r"), motion=motion)

    def loss(tau_log, alpha, beta_log, q_log):
        motion.tau_log, motion.alpha, motion.beta_log, params.q_log = tau_log, alpha, beta_log, q_log
        run = run_filter(params, ep.measurements, Net(s), CTX, known_prior, first_step=1)
        return run.nll_sum / run.nll_count

    args = tuple(t.detach().clone().requires_grad_(True)
                 for t in (motion.tau_log, motion.alpha, motion.beta_log, params.q_log))
    for mod, name in ((motion, "tau_log"), (motion, "alpha"), (motion, "beta_log"), (params, "q_log")):
        delattr(mod, name)  # plain attributes: gradcheck's inputs take the parameters' place
    assert torch.autograd.gradcheck(loss, args, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_sfm_numbers_learned_from_measurements_alone_come_back_towards_the_truth():
    """Start the social force at tau x 3, alpha / 2, beta x 2; learn them from the nodes' innovations (no truth
    after t = 0): every number ends closer to the simulation's (in log scale) and the loss falls."""
    s, truth = 3, dict(tau=0.5, alpha=2.0, beta=1.0)
    ep = simulate_crowd(sfm(**truth), 16, 20, s, 0.05, seed=2)
    ep_first[0] = ep.states[:, 0]
    fusion = HybridConsensus(metropolis(line(s)), 2, 1.0)
    motion = SocialForceParameters(sfm(tau=1.5, alpha=1.0, beta=2.0))
    params = BackpropParameters(2, None, 0.02**2 * torch.eye(4, dtype=D64), 0.05**2 * torch.eye(2, dtype=D64),
                                fusion, line(s), learn=("model",), motion=motion)
    before = {k: float(v[0].detach()) for k, v in zip(truth, motion.numbers())}
    hist = fit(params, ep.measurements, Net(s), CTX, known_prior, epochs=150, lr=0.05, first_step=1)
    after = {k: float(v[0].detach()) for k, v in zip(truth, motion.numbers())}
    assert hist.loss[-1] < hist.loss[0]
    for k in truth:
        assert abs(math.log(after[k] / truth[k])) < 0.5 * abs(math.log(before[k] / truth[k])), (k, before, after)


# ----------------------------------------------------------------------------------------------------- the LSTM
def small_lstm():
    from dslearn.models.lstm import SocialLSTM

    torch.manual_seed(0)
    m = SocialLSTM(num_agents=1, dt=DT, embed=4, hidden=5, obs_len=2, pred_len=2).to(D64)
    return m


def test_lstm_jacobian_is_the_models_own_and_its_weight_gradient_matches_finite_differences():
    m = small_lstm()
    x = torch.randn(2, 4, dtype=D64)
    y, F, Q = LSTMParameters(m).build(None).linearize(x, CTX)
    y0, F0, Q0 = m.linearize(x, CTX)
    torch.testing.assert_close(F, F0, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(y, y0, rtol=1e-12, atol=1e-12)
    # the innovation loss through 3 filter steps and 2 hybrid rounds, along one direction of every weight
    s = 2
    g = torch.Generator().manual_seed(3)
    X = torch.cumsum(0.3 * torch.randn(2, 4, 4, generator=g, dtype=D64), 1)
    z = X[..., :2].unsqueeze(0).unsqueeze(-2) + 0.1 * torch.randn(s, 2, 4, 1, 2, generator=g, dtype=D64)
    ep = Episodes(X, z, torch.ones(s, 2, 4, 1, dtype=torch.bool))

    def prior(ep, fusion):
        return (X[:, 0].expand(s, 2, 4).clone(), (0.1 * torch.eye(4, dtype=D64)).expand(s, 2, 4, 4).clone())

    fusion = HybridConsensus(metropolis(line(s)), 2, 1.0)
    motion = LSTMParameters(m)
    params = BackpropParameters(1, None, 0.01 * torch.eye(4, dtype=D64), 0.01 * torch.eye(2, dtype=D64), fusion,
                                line(s), learn=("model",), motion=motion)

    def loss():
        run = run_filter(params, ep.measurements, Net(s), CTX, prior, first_step=1)
        return run.nll_sum / run.nll_count

    value = loss()
    value.backward()
    weights = [p for p in motion.parameters()]
    d = [torch.randn(p.shape, generator=g, dtype=D64) for p in weights]
    analytic = sum(float((p.grad * u).sum()) for p, u in zip(weights, d))
    h = 1e-6
    with torch.no_grad():
        for p, u in zip(weights, d):
            p += h * u
        up = float(loss())
        for p, u in zip(weights, d):
            p -= 2 * h * u
        down = float(loss())
        for p, u in zip(weights, d):
            p += h * u
    numeric = (up - down) / (2 * h)
    assert abs(analytic - numeric) <= 1e-5 * max(1.0, abs(numeric)), (analytic, numeric)
    assert abs(numeric) > 1e-3  # the direction moves the loss: the check is not vacuous


# ------------------------------------------------------------------------------------------------- composition
def _cell(*over):
    from dslearn import api
    from dslearn.compose import build_cell_parts

    cfg = api.compose("task=matrix", "scenario=yu_two_agents", "learner=backprop", *over)
    return build_cell_parts(cfg, check_only=True)[2]


def test_composition_takes_the_supported_models_and_refuses_the_others_with_the_reason():
    assert _cell("method=ekf_sfm_hybrid", "learner.learn=[model,q,r]").learner.name == "backprop"
    assert _cell("method=ekf_gp_hybrid", "learner.learn=[model,r,weights]").learner.name == "backprop"
    assert _cell("method=ekf_lstm_hybrid", "learner.learn=[model,q]").learner.name == "backprop"
    with pytest.raises(ConfigError, match=r"learner.learn=\[q\].*predictive variance"):
        _cell("method=ekf_gp_hybrid", "learner.learn=[model,q]")
    with pytest.raises(ConfigError, match=r"learner=backprop supports model=.*variant=sgpr"):
        _cell("method=ekf_gp_hybrid", "model=gp_sgpr", "learner.learn=[model]")
    with pytest.raises(ConfigError, match=r"filter=adf"):
        _cell("method=ekf_gp_hybrid", "filter=adf", "learner.learn=[model]")
    with pytest.raises(ConfigError, match="learner.model_lr"):
        _cell("method=ekf_lin_hybrid", "learner.model_lr=-1", "learner.learn=[model]")
    with pytest.raises(ConfigError, match=r"learner.model_lr=0.001 .* does not list model"):
        _cell("method=ekf_lin_hybrid", "learner.model_lr=0.001")


def test_gp_hyperparameters_learned_end_to_end_on_yu():
    """model=gp_increment, learner=backprop, learn [model, r]: the data sets are gathered online first, the
    hyperparameters then move, the model tracks the test episodes with them, and the loss falls."""
    from dslearn import api
    from dslearn.compose import build_study

    cfg = api.compose("task=matrix", "method=ekf_gp_hybrid", "model=gp_increment", "learner=backprop",
                      "scenario=yu_two_agents", "task.train_episodes=3", "task.test_episodes=1", "learner.epochs=4",
                      "learner.learn=[model,r]")
    study = build_study(cfg)
    df = study.run()
    learned = study.method.learned
    assert set(df["method"]) == {"ekf gp_increment hybrid learner=backprop"}
    gp = study.method.model.gp
    assert gp.n > 0  # data gathered online before
    ls = torch.tensor(learned["gp"]["lengthscale"], dtype=D64)
    torch.testing.assert_close(gp.lengthscale, ls, rtol=1e-12, atol=0)
    assert float((ls - 2.0).abs().max()) > 1e-3  # moved from the configured 2.0
    assert learned["loss"][-1] < learned["loss"][0]
    assert torch.isfinite(torch.tensor(df["value"].to_numpy())).all()


@pytest.mark.parametrize("step", ["ukf", "pf"])
def test_differentiable_gp_runs_the_ukf_and_particle_steps_as_the_online_gp(step):
    """The differentiable posterior is a per-node model to the UKF's and the PF's propagation (the node dimension
    first): the same prediction as the online GP's (the PF from the same seed: the same draws)."""
    from dslearn.filters.particle import pf_predict
    from dslearn.filters.ukf import ukf_predict

    m = gp_with_data(noise="adaptive")
    dgp = GPParameters(m).build(None)
    g = torch.Generator().manual_seed(5)
    mean = torch.randn(2, 3, 4, generator=g, dtype=D64)
    A = torch.randn(2, 3, 4, 4, generator=g, dtype=D64)
    omega = A @ A.transpose(-1, -2) + 4 * torch.eye(4, dtype=D64)

    def run(model):
        if step == "ukf":
            return ukf_predict(mean, omega, model, CTX, True)
        return pf_predict(mean, omega, model, CTX, True, particles=64, generator=torch.Generator().manual_seed(1))

    for a, b in zip(run(dgp), run(m)):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-10)
