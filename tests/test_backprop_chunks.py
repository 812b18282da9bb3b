"""learner=backprop with learner.chunk: a step's episodes tracked and backpropagated a chunk at a time, each
chunk's loss scaled by the whole step's term count, so that the accumulated gradient is the full-batch gradient
(to rounding) and the learned numbers follow the same path; chunk=null is today's single pass; chunk <= 0 is
refused naming learner.chunk."""

import copy

import pytest
import torch

from dslearn.episodes import Episodes
from dslearn.errors import ConfigError
from dslearn.fusion.strategies import HybridConsensus
from dslearn.fusion.weights import metropolis
from dslearn.learning.backprop import BackpropLearning, BackpropParameters, GPParameters, fit, loss_terms
from dslearn.models.gp import GPMotionModel
from dslearn.types import StepContext
from test_backprop import line, one_thread  # noqa: F401  (the line graph; one thread for tiny batched matrices)

S, DT = 3, 0.5
D64 = torch.float64
CTX = StepContext(dt=DT)
F = torch.tensor([[1.0, 0, DT, 0], [0, 1, 0, DT], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=D64)


class Net:
    num_nodes = S


def simulate(B, K, seed):
    """A 2-D constant-velocity target seen by the nodes of a line graph, each missing some steps (so the episodes'
    loss term counts differ)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.zeros(B, 4, dtype=D64)
    x[:, 2:] = torch.randn(B, 2, generator=g, dtype=D64)
    xs = [x]
    for _ in range(K):
        x = x @ F.T + 0.2 * torch.randn(B, 4, generator=g, dtype=D64)
        xs.append(x)
    X = torch.stack(xs, 1)
    z = X[..., :2].unsqueeze(0) + 0.2 * torch.randn(S, B, K + 1, 2, generator=g, dtype=D64)
    visible = torch.rand(S, B, K + 1, 1, generator=g) > 0.25
    return Episodes(X, (z * visible).unsqueeze(-2), visible)


def prior(ep, fusion):  # every node: the first true position, loosely known (no truth after t = 0)
    s, b = ep.meas.shape[:2]
    return torch.zeros(s, b, 4, dtype=D64), 0.5 * torch.eye(4, dtype=D64).expand(s, b, 4, 4).clone()


def lin_params():
    fusion = HybridConsensus(metropolis(line(S)), 2, 1.0)
    return BackpropParameters(1, F, 0.1 * torch.eye(4, dtype=D64), 0.1 * torch.eye(2, dtype=D64), fusion, line(S),
                              learn=("q", "r", "weights", "omega", "model"))


def gp_params():
    torch.manual_seed(0)
    m = GPMotionModel(4, S, outputscale=0.8, lengthscale=1.5, noise_std=0.3, mean="identity", noise="latent")
    for _ in range(10):
        x = torch.randn(S, 4, dtype=D64)
        m.add_data(x, x @ F.T + 0.1 * torch.randn(S, 4, dtype=D64), torch.ones(S, dtype=torch.bool))
    fusion = HybridConsensus(metropolis(line(S)), 2, 1.0)
    return BackpropParameters(1, None, torch.eye(4, dtype=D64), 0.1 * torch.eye(2, dtype=D64), fusion, line(S),
                              learn=("model", "r", "weights", "omega"), motion=GPParameters(m))


def trained(make, data, **kw):
    p = make()
    hist = fit(p, data, Net(), CTX, prior, first_step=2, seed=3, **kw)
    grads = {k: v.grad.detach().clone() for k, v in p.named_parameters() if v.requires_grad}
    values = {k: v.detach().clone() for k, v in p.named_parameters() if v.requires_grad}
    return grads, values, hist


def assert_rel(a: dict, b: dict, rtol: float):
    assert a.keys() == b.keys() and a
    for k in a:
        scale = max(float(b[k].abs().max()), 1e-300)
        assert float((a[k] - b[k]).abs().max()) <= rtol * scale, (k, a[k], b[k])


@pytest.mark.parametrize("make", [lin_params, gp_params], ids=["lin", "gp_increment"])
@pytest.mark.parametrize("loss", ["innovation", "supervised"])
def test_chunked_gradient_equals_the_full_batch_gradient(make, loss):
    """One Adam step over 3 episodes: the gradient of every learned number with chunk=1 and chunk=2 (2 + 1, uneven)
    equals the single pass's to 1e-10 relative; the step's logged loss too."""
    ep = simulate(3, 8, seed=1)
    data = ep if loss == "supervised" else ep.measurements
    g_full, _, h_full = trained(make, data, epochs=1, lr=1e-3, loss=loss)
    assert all(float(g.abs().max()) > 0 for g in g_full.values())  # every learned number moves the loss
    for chunk in (1, 2):
        g, _, h = trained(make, data, epochs=1, lr=1e-3, loss=loss, chunk=chunk)
        assert_rel(g, g_full, 1e-10)
        assert h.loss[0] == pytest.approx(h_full.loss[0], rel=1e-12)


@pytest.mark.parametrize("make", [lin_params, gp_params], ids=["lin", "gp_increment"])
def test_chunked_training_follows_the_same_path(make):
    """A few epochs of Adam with batches of 3 of 5 episodes (3 + 2 per epoch), chunk=2: the learned numbers and the
    loss history agree with chunk=null's to rounding."""
    data = simulate(5, 8, seed=2).measurements
    _, v_full, h_full = trained(make, data, epochs=3, lr=0.05, batch=3)
    _, v, h = trained(make, data, epochs=3, lr=0.05, batch=3, chunk=2)
    assert_rel(v, v_full, 1e-9)
    assert h.loss == pytest.approx(h_full.loss, rel=1e-10)
    assert any(float((v[k] - make().get_parameter(k).detach()).abs().max()) > 1e-3 for k in v)  # they moved


def test_chunked_lbfgs_takes_the_same_steps():
    data = simulate(3, 6, seed=4).measurements
    _, v_full, h_full = trained(lin_params, data, epochs=1, lr=0.5, optimizer="lbfgs")
    _, v, h = trained(lin_params, data, epochs=1, lr=0.5, optimizer="lbfgs", chunk=1)
    assert_rel(v, v_full, 1e-8)
    assert h.loss == pytest.approx(h_full.loss, rel=1e-10)


def test_chunk_null_is_the_single_pass_bit_for_bit():
    """chunk=null, and a chunk at least the step's episodes, run the single pass: the same numbers to the bit."""
    data = simulate(3, 6, seed=5).measurements
    _, v_none, h_none = trained(lin_params, data, epochs=2, lr=0.05)
    _, v_big, h_big = trained(lin_params, data, epochs=2, lr=0.05, chunk=3)
    for k in v_none:
        assert torch.equal(v_none[k], v_big[k]), k
    assert h_none.loss == h_big.loss


def test_loss_terms_counts_what_the_loss_divides_by():
    ep = simulate(4, 5, seed=6)
    idx = torch.tensor([2, 0])
    assert loss_terms(ep.measurements, idx, "innovation", 2) == float(ep.visible[:, idx, 2:].sum())
    assert loss_terms(ep.measurements, idx, "supervised") == float(S * 2 * 5 * 1)
    none = Episodes(ep.states, ep.meas, torch.zeros_like(ep.visible))
    assert loss_terms(none.measurements, idx, "innovation", 2) == 1.0  # the loss clamps its count at 1


@pytest.mark.parametrize("bad", [0, -2, 1.5, True, "2"])
def test_chunk_below_one_or_not_an_integer_is_refused(bad):
    with pytest.raises(ConfigError, match="learner.chunk"):
        BackpropLearning(chunk=bad)
    with pytest.raises(ConfigError, match="learner.chunk"):
        fit(lin_params(), simulate(2, 4, seed=0).measurements, Net(), CTX, prior, epochs=1, chunk=bad)
    assert BackpropLearning(chunk=1).chunk == 1 and BackpropLearning().chunk is None


def test_chunk_is_a_key_of_the_composed_learner():
    from dslearn import api
    from dslearn.compose import build_cell_parts

    cfg = api.compose("task=matrix", "scenario=yu_two_agents", "method=ekf_lin_hybrid_backprop", "learner.chunk=2")
    assert build_cell_parts(cfg, check_only=True)[2].learner.chunk == 2
    with pytest.raises(ConfigError, match="learner.chunk"):
        build_cell_parts(api.compose("task=matrix", "scenario=yu_two_agents", "method=ekf_lin_hybrid_backprop",
                                     "learner.chunk=0"), check_only=True)
