"""learner=backprop (dslearn.learning.backprop): gradients through the distributed information filter and its L
consensus rounds, the weights' parametrisation, Q and R learned from measurements alone, and the consensus
filter's gradient approaching the centralised filter's as L grows."""

import pytest
import torch

from dslearn.episodes import Episodes, Measurements
from dslearn.errors import ConfigError
from dslearn.filters.information import novel_information, predict
from dslearn.fusion.strategies import Centralized, HybridConsensus
from dslearn.fusion.weights import metropolis, uniform
from dslearn.learning.backprop import (BackpropLearning, BackpropParameters, LinearMotion, LinearSensor, fit,
                                       graph_mask, innovation_nll, log_cholesky, masked_softmax, run_filter,
                                       weight_logits)
from dslearn.types import StepContext

S, DT = 4, 0.5
F = torch.tensor([[1.0, 0, DT, 0], [0, 1, 0, DT], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=torch.float64)


@pytest.fixture(autouse=True)
def one_thread():  # tiny batched matrices: one thread is ~100x faster than two on a shared machine
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def line(s=S):
    adj = torch.zeros(s, s, dtype=torch.bool)
    for i in range(s - 1):
        adj[i, i + 1] = adj[i + 1, i] = True
    return adj


class Net:
    num_nodes = S


def simulate(q_diag, R, B, K, seed, s=S):
    """A 2-D constant-velocity target seen by every node of the line graph: x' = F x + w, z_i = H x + v_i."""
    g = torch.Generator().manual_seed(seed)
    x = torch.zeros(B, 4, dtype=torch.float64)
    x[:, 2:] = torch.randn(B, 2, generator=g, dtype=torch.float64)
    xs = [x]
    for _ in range(K):
        x = x @ F.T + torch.randn(B, 4, generator=g, dtype=torch.float64) * q_diag.sqrt()
        xs.append(x)
    X = torch.stack(xs, 1)
    z = X[..., :2].unsqueeze(0) + torch.randn(s, B, K + 1, 2, generator=g, dtype=torch.float64) @ torch.linalg.cholesky(R).T
    return Episodes(X, z.unsqueeze(-2), torch.ones(s, B, K + 1, 1, dtype=torch.bool))


def common_prior(ep, fusion):  # every node: the same vague prior (no truth)
    s, b = ep.meas.shape[:2]
    return (torch.zeros(s, b, 4, dtype=torch.float64),
            1e-4 * torch.eye(4, dtype=torch.float64).expand(s, b, 4, 4).clone())


def test_masked_softmax_weights_are_row_stochastic_on_the_graph():
    adj = line(5)
    mask = graph_mask(adj)
    logits = torch.randn(5, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 3
    w = masked_softmax(logits, mask)
    assert torch.allclose(w.sum(-1), torch.ones(5, dtype=torch.float64), atol=1e-15, rtol=0)
    assert (w[~mask] == 0).all() and (w[mask] > 0).all()
    assert w[0, 2] == 0 and w[0, 0] > 0 and w[0, 1] > 0  # node 0 talks to node 1 only
    # the initial logits reproduce the configured rule's weights
    for rule in (uniform, metropolis):
        assert torch.allclose(masked_softmax(weight_logits(rule(adj), mask), mask), rule(adj), atol=1e-15, rtol=0)


def test_log_cholesky_is_positive_definite_and_round_trips():
    raw = torch.tensor([[-3.0, 0.0], [5.0, 2.0]], dtype=torch.float64)  # L = [[e^-3, 0], [5, e^2]]
    R = log_cholesky(raw)
    want = torch.tensor([[torch.e ** -6, 5 * torch.e ** -3], [5 * torch.e ** -3, 25 + torch.e ** 4]], dtype=torch.float64)
    assert torch.allclose(R, want, rtol=1e-14, atol=0)
    assert (torch.linalg.eigvalsh(R) > 0).all()


def test_gradcheck_one_step_and_l_consensus_rounds():
    """float64 gradcheck of (fused q, fused Omega, innovation NLL) w.r.t. Q, R, the weights' logits and omega
    through one prediction, the novel information and L = 3 hybrid consensus rounds (3 nodes, 2 episodes, 2
    targets)."""
    g = torch.Generator().manual_seed(0)
    s, b, a = 3, 2, 2
    adj = line(s)
    mask = graph_mask(adj)
    base = HybridConsensus(uniform(adj), 3, 1.0)
    y = torch.randn(s, b, 4 * a, generator=g, dtype=torch.float64)
    A = torch.randn(s, b, 4 * a, 4 * a, generator=g, dtype=torch.float64)
    o = A @ A.mT + torch.eye(4 * a, dtype=torch.float64)
    meas = torch.randn(s, b, a, 2, generator=g, dtype=torch.float64)
    vis = torch.tensor([True, False, True]).view(s, 1, 1).expand(s, b, a)

    def step(q_log, r_raw, logits, omega_log):
        motion, obs = LinearMotion(a, F, torch.diag_embed(q_log.exp())), LinearSensor(log_cholesky(r_raw))
        fusion = HybridConsensus(uniform(adj), 3, 1.0)
        fusion.wl, fusion.omega = torch.linalg.matrix_power(masked_softmax(logits, mask), 3), omega_log.exp()
        y_pred, q_pred, o_pred, P_pred, *_ = predict(y, o, motion, StepContext(dt=DT), full=True)
        dq, do = novel_information(y_pred, meas, vis, obs)
        q, om = fusion(q_pred, o_pred, dq, do)
        nll, _ = innovation_nll(y_pred, P_pred, meas, vis, obs)
        return q, om, nll

    inputs = (torch.log(torch.tensor([0.1, 0.2, 0.3, 0.4], dtype=torch.float64)),
              torch.tensor([[-1.0, 0.0], [0.3, -0.5]], dtype=torch.float64),
              weight_logits(base.weights, mask) + 0.1 * torch.randn(s, s, generator=g, dtype=torch.float64),
              torch.tensor(0.2, dtype=torch.float64))
    inputs = tuple(x.clone().requires_grad_(True) for x in inputs)
    assert torch.autograd.gradcheck(step, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_q_and_r_learned_from_measurements_alone_within_10_percent():
    """4 nodes on a line, a CV target, F and H known, Q and R learned from the innovations (no truth) by the
    hybrid consensus filter with doubly stochastic weights, omega = S and L = 30 (W^30 within 2e-3 of the
    average: the centralised filter, whose innovation likelihood is consistent).

    Data size from the estimator's spread: at 200 episodes x 30 steps the learned values over 4 seeds spread
    with a standard deviation of about 7 % (position noise and R are the least identified, they trade off
    against each other); 400 x 60 steps (4x the data) brings it to about 3.5 %, so 10 % is ~3 standard errors."""
    q_true = torch.tensor([0.04, 0.04, 0.04, 0.04], dtype=torch.float64)
    R_true = torch.tensor([[0.05, 0.01], [0.01, 0.04]], dtype=torch.float64)
    ep = simulate(q_true, R_true, B=400, K=60, seed=0)
    adj = line()
    fusion = HybridConsensus(metropolis(adj), 30, float(S))
    p = BackpropParameters(1, F, 0.2 * torch.eye(4, dtype=torch.float64), 0.2 * torch.eye(2, dtype=torch.float64),
                           fusion, adj, learn=("q", "r"))
    fit(p, ep.measurements, Net(), StepContext(dt=DT), common_prior, epochs=2, lr=1.0, first_step=3,
        optimizer="lbfgs")
    q_hat, R_hat = p.q_log.detach().exp(), p.R().detach()
    assert ((q_hat / q_true - 1).abs() < 0.10).all(), q_hat
    assert float(torch.linalg.matrix_norm(R_hat - R_true) / torch.linalg.matrix_norm(R_true)) < 0.10, R_hat
    assert ((R_hat.diagonal() / R_true.diagonal() - 1).abs() < 0.10).all(), R_hat


def test_consensus_gradient_approaches_the_centralised_one_as_l_grows():
    q_true = torch.tensor([0.04, 0.04, 0.02, 0.02], dtype=torch.float64)
    R_true = torch.tensor([[0.05, 0.01], [0.01, 0.04]], dtype=torch.float64)
    ep = simulate(q_true, R_true, B=10, K=12, seed=3).measurements
    adj = line()

    def grad(fusion):
        p = BackpropParameters(1, F, 0.1 * torch.eye(4, dtype=torch.float64), 0.1 * torch.eye(2, dtype=torch.float64),
                               fusion, adj, learn=("q", "r"))
        run = run_filter(p, ep, Net(), StepContext(dt=DT), common_prior, first_step=3)
        (run.nll_sum / run.nll_count).backward()
        return torch.cat([p.q_log.grad, p.r_raw.grad.flatten()])

    ref = grad(Centralized(metropolis(adj), 0))
    errs = [float((grad(HybridConsensus(metropolis(adj), L, float(S))) - ref).norm() / ref.norm())
            for L in (1, 2, 4, 8, 16, 32, 64)]
    assert all(b < a for a, b in zip(errs, errs[1:])), errs
    assert errs[0] > 0.05 and errs[-1] < 1e-3, errs  # far at L = 1; lambda_2(W)^64 = 0.805^64 ~ 1e-6


def test_learner_settings_are_checked():
    assert BackpropLearning().learn == ["q", "r", "weights", "omega"]
    with pytest.raises(ConfigError, match="learner.learn"):
        BackpropLearning(learn=["q", "bogus"])
    with pytest.raises(ConfigError, match="learner.loss"):
        BackpropLearning(loss="mse")
    with pytest.raises(ConfigError, match="learner.epochs"):
        BackpropLearning(epochs=-1)
    with pytest.raises(ConfigError, match="consensus=ce|cm|ci|hybrid"):
        BackpropLearning(learn=["weights"]).check_fusion(Centralized(uniform(line()), 0))


def test_supervised_loss_and_measurements_only_rule():
    ep = simulate(torch.full((4,), 0.04, dtype=torch.float64), 0.04 * torch.eye(2, dtype=torch.float64), 6, 8, 1)
    p = BackpropParameters(1, F, 0.1 * torch.eye(4, dtype=torch.float64), 0.1 * torch.eye(2, dtype=torch.float64),
                           HybridConsensus(uniform(line()), 2, 1.0), line(), learn=("q", "r", "weights", "omega"))
    with pytest.raises(ConfigError, match="supervised"):
        fit(p, ep.measurements, Net(), StepContext(dt=DT), common_prior, epochs=1, loss="supervised")
    h = fit(p, ep, Net(), StepContext(dt=DT), common_prior, epochs=5, lr=0.05, loss="supervised", batch=3)
    assert len(h.loss) == 5 and h.loss[-1] < h.loss[0]
    w = p.W().detach()
    assert torch.allclose(w.sum(-1), torch.ones(S, dtype=torch.float64)) and (w[~graph_mask(line())] == 0).all()


def test_composition_refuses_unsupported_models():
    from hydra import compose, initialize_config_dir

    import dslearn.schemas  # noqa: F401  (the task schemas)
    from dslearn.compose import build_cell_parts
    from dslearn.conf_paths import CONF_DIR

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = compose("config", overrides=["task=matrix", "method=ekf_gp_hybrid", "model=gp_sgpr", "learner=backprop",
                                           "learner.learn=[model]", "scenario=yu_two_agents"])
        with pytest.raises(ConfigError, match=r"learner=backprop supports model=lin\|sfm\|gp.*variant=sgpr"):
            build_cell_parts(cfg, check_only=True)
        ok = compose("config", overrides=["task=matrix", "method=ekf_lin_hybrid_backprop", "scenario=yu_two_agents"])
        _, _, method = build_cell_parts(ok, check_only=True)
        assert method.learner.name == "backprop"


def test_train_fusion_individual_learns_alone_then_tracks_with_the_consensus():
    """learner.train_fusion: the loss runs through no consensus (each node on its own measurements) and the
    learned numbers are tracked with the configured fusion, its rule weights and omega untouched."""
    from dslearn.fusion.strategies import Individual

    with pytest.raises(ConfigError, match="learner.train_fusion"):
        BackpropLearning(train_fusion="alone")
    with pytest.raises(ConfigError, match=r"train_fusion=individual.*only q, r, model"):
        BackpropLearning(train_fusion="individual", learn=["q", "omega"])
    hyb = HybridConsensus(metropolis(line()), 3, 2.0)
    assert BackpropLearning().training_fusion(hyb) is hyb
    lr = BackpropLearning(train_fusion="individual", learn=["q", "r"])
    ind = lr.training_fusion(hyb)
    assert isinstance(ind, Individual) and ind.iterations == 3
    assert lr.label == "backprop(individual)" and BackpropLearning().label == "backprop"

    from dslearn import api
    from dslearn.compose import build_study

    def run(*extra):
        cfg = api.compose("task=matrix", "method=ekf_lin_hybrid_backprop", "scenario=yu_two_agents",
                          "task.train_episodes=2", "task.test_episodes=1", "learner.epochs=3", *extra)
        study = build_study(cfg)
        df = study.run()
        return set(df["method"]), study

    labels, ind_run = run("learner.train_fusion=individual", "learner.learn=[q,r]")
    assert labels == {"ekf lin hybrid learner=backprop(individual)"}, labels
    labels_c, con_run = run("learner.learn=[q,r]")
    assert labels_c == {"ekf lin hybrid learner=backprop"}
    # the loss ran through different filters (no consensus vs hybrid): different first losses and numbers
    a, b = ind_run.method.learned, con_run.method.learned
    assert abs(a["loss"][0] - b["loss"][0]) > 1e-3 * abs(b["loss"][0]), (a["loss"], b["loss"])
    assert max(abs(x - y) for x, y in zip(a["q_diag"], b["q_diag"])) > 1e-6


def test_compare_script_writes_its_table(tmp_path):
    """experiments/backprop/compare.py: one row per scenario and variant, the hand-set and the [q,r] variants
    share the motion model (same prediction error), the learned ones track with finite errors."""
    import importlib.util
    from pathlib import Path

    import pandas as pd

    path = Path(__file__).resolve().parents[1] / "experiments" / "backprop" / "compare.py"
    spec = importlib.util.spec_from_file_location("backprop_compare", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    mod.main(["--scenarios", "yu_two_agents", "--train", "2", "--test", "2", "--out", str(tmp_path)])
    df = pd.read_csv(tmp_path / "compare.csv").set_index("variant")
    assert list(df.index) == list(mod.VARIANTS) and (tmp_path / "compare.md").exists()
    assert df.loc["nodes alone, frozen [q,r]", "pred_err"] == df.loc["hand-set", "pred_err"]
    assert df.loc["end to end [q,r]", "pred_err"] == df.loc["hand-set", "pred_err"]
    assert df.loc["end to end [q,r,model]", "pred_err"] != df.loc["hand-set", "pred_err"]
    assert df[["rmse", "nees_pos", "pred_err"]].notna().all().all()
