"""The LSTM / Social-LSTM as a motion model any filter uses (``model=lstm`` / ``model=social_lstm``):
its linearisation, its offline fit (training, process noise from held-out residuals, seeds), the
Social-LSTM's pooling against a plain LSTM with the same weights, and tiny synthetic studies under
the EKF and the UKF."""

import math

import pytest
import torch

from dslearn.compose import build_motion_model, build_network, build_scenario
from dslearn.errors import ConfigError
from dslearn.filters.information import predict
from dslearn.models.lstm import SocialLSTM, episode_windows, holdout_groups, train_lstm
from dslearn.types import StepContext

F64 = torch.float64
DT = 0.25  # the Yu scenario's step


@pytest.fixture(scope="module")
def yu(tmp_path_factory):
    """The default config, its scenario and network, and 6 true training tracks (B, K+1, 8)."""
    from hydra import compose, initialize_config_dir

    import dslearn.schemas  # noqa: F401
    from dslearn.conf_paths import CONF_DIR

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = compose("config", overrides=["model=lstm", "model.epochs=4", "model.embed=16", "model.hidden=16"])
    scenario, network = build_scenario(cfg), build_network(cfg)
    states = scenario.sample(6, network, torch.Generator().manual_seed(5)).states.to(F64)
    return cfg, scenario, network, states


def _model(cfg, scenario, network, **keys):
    node = dict(cfg.model)
    node.update(keys)
    return build_motion_model(node, scenario, network, F64, torch.device("cpu"))


def _fd_jacobian(model, x, ctx, eps=1e-6):
    """Central finite differences of ``forward``: ``(*B, Dx) -> (*B, Dx, Dx)``."""
    cols = [(model(x + eps * e, ctx) - model(x - eps * e, ctx)) / (2 * eps) for e in torch.eye(x.shape[-1], dtype=x.dtype)]
    return torch.stack(cols, -1)


# ------------------------------------------------------------------------------ the option
def test_option_sizes_the_network_from_the_scenario(yu):
    cfg, scenario, network, _ = yu
    m = _model(cfg, scenario, network)
    assert type(m) is SocialLSTM and m.learns_offline and not m.learnable
    assert (m.num_agents, m.state_dim, m.dt) == (2, 8, DT) and (m.embed, m.hidden, m.pooling) == (16, 16, "none")
    assert m.offline["epochs"] == 4 and m.offline["process_noise"] == "residuals" and m.train_on is None
    s = _model(cfg, scenario, network, pooling="social", name="social_lstm")
    assert s.pooling == "social" and hasattr(s, "pool_embed")
    with pytest.raises(ConfigError, match="model.pooling"):
        _model(cfg, scenario, network, pooling="attention")
    with pytest.raises(ConfigError, match="model.process_noise"):
        _model(cfg, scenario, network, process_noise="guess")
    with pytest.raises(ConfigError, match="model.schedule"):
        _model(cfg, scenario, network, schedule="cosine")
    with pytest.raises(ConfigError, match="model.pred_len"):  # 2 + 12 > the scenario's 13 states
        _model(cfg, scenario, network, pred_len=12)


# ------------------------------------------------------------------------- linearisation
def test_ekf_prediction_equals_kalman_with_finite_difference_jacobian(yu):
    """``predict`` (the EKF step) with the LSTM = the Kalman prediction with the Jacobian of
    ``forward`` by central differences, for the plain and the social LSTM."""
    cfg, scenario, network, states = yu
    ctx = scenario.ctx()
    gen = torch.Generator().manual_seed(1)
    mean = states[:3, 4].expand(2, 3, 8) + 0.05 * torch.randn(2, 3, 8, generator=gen, dtype=F64)
    a = torch.randn(2, 3, 8, 8, generator=gen, dtype=F64)
    P = 0.01 * a @ a.transpose(-1, -2) + 0.01 * torch.eye(8, dtype=F64)
    for pooling in ("none", "social"):
        m = _model(cfg, scenario, network, pooling=pooling)
        y, q, om = predict(mean, torch.linalg.inv(P), m, ctx)
        F = _fd_jacobian(m, mean, ctx)
        Pp = F @ P @ F.transpose(-1, -2) + m.noise_cov(mean, ctx)
        torch.testing.assert_close(y, m(mean, ctx), rtol=0, atol=1e-14)
        torch.testing.assert_close(torch.linalg.inv(om), Pp, rtol=1e-7, atol=1e-9)
        torch.testing.assert_close(q, (om @ y.unsqueeze(-1)).squeeze(-1))
        # the Jacobian itself, and its velocity rows (finite differences of the position rows)
        J = m.jacobian(mean, ctx)
        torch.testing.assert_close(J, F, rtol=1e-6, atol=1e-8)
        jp = J.view(2, 3, 2, 4, 8)
        eye = torch.eye(8, dtype=F64).view(2, 4, 8)
        torch.testing.assert_close(jp[..., 2:, :], (jp[..., :2, :] - eye[:, :2]) / DT, rtol=0, atol=1e-12)
        assert J.abs().max() > 0.5  # not a trivial map


def test_repeated_states_are_evaluated_once_with_the_same_mean_and_jacobian(yu):
    """A batch whose rows repeat (the nodes that never saw the target hold one prior) runs the network on its
    distinct rows only; the mean and the Jacobian of every row are those of the batch computed whole, and a
    batch that carries a gradient is never compacted (its gradient reaches every row)."""
    cfg, scenario, network, states = yu
    ctx = scenario.ctx()
    gen = torch.Generator().manual_seed(2)
    distinct = states[:3, 4] + 0.05 * torch.randn(3, 8, generator=gen, dtype=F64)
    idx = torch.tensor([0, 1, 0, 2, 0, 1, 2, 2, 0, 1, 0, 0])
    x = distinct[idx].view(3, 4, 8)
    for pooling in ("none", "social"):
        m = _model(cfg, scenario, network, pooling=pooling)
        calls = []
        m.register_forward_hook(lambda mod, args, out: calls.append(args[0].reshape(-1, 8).shape[0]))
        y, F, _ = m.linearize(x, ctx)
        assert calls == [3]  # the three distinct states, once
        y_whole = torch.stack([m(distinct[i:i + 1], ctx)[0] for i in idx.tolist()]).view(3, 4, 8)
        torch.testing.assert_close(y, y_whole, rtol=1e-12, atol=1e-12)
        F_whole = _fd_jacobian(m, x, ctx)
        torch.testing.assert_close(F, F_whole, rtol=1e-6, atol=1e-8)
        torch.testing.assert_close(F[0, 0], F[0, 2], rtol=0, atol=0)  # rows 0 and 2 are one state
        torch.testing.assert_close(m(x, ctx), y, rtol=0, atol=0)
        # with a gradient on the rows: the whole batch (a compacted one would give the repeats no gradient)
        z = x.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(m(z, ctx)[..., 0].sum(), z)
        torch.testing.assert_close(g[0, 2], g[0, 0])
        assert g.abs().sum(-1).gt(0).all()


def test_distinct_rows_groups_by_value_and_keeps_a_batch_without_repeats():
    from dslearn.types import DISTINCT_SHARE, distinct_rows

    gen = torch.Generator().manual_seed(0)
    base = torch.randn(4, 5, generator=gen, dtype=F64)
    flat = base[torch.tensor([3, 0, 3, 1, 1, 2, 3, 0])]
    rows, inverse = distinct_rows(flat)
    assert rows.shape == (4, 5) and torch.equal(rows[inverse], flat)
    assert distinct_rows(base)[1] is None  # nothing repeats: the batch as it is
    ten = torch.randn(10, 5, generator=gen, dtype=F64)
    assert 10 > DISTINCT_SHARE * 11 and distinct_rows(torch.cat([ten, ten[:1]]))[1] is None  # too few repeats
    nan = flat.clone()
    nan[0, 0] = nan[2, 0] = float("nan")  # equal bits, unequal values: kept whole
    assert distinct_rows(nan)[1] is None
    zero = torch.zeros(6, 5, dtype=F64)
    zero[::2, 0] = -0.0  # a signed zero is another bit pattern: its own group, the same value
    r0, i0 = distinct_rows(zero)
    assert torch.equal(r0[i0], zero)
    assert distinct_rows(flat.clone().requires_grad_(True))[1] is None
    assert distinct_rows(flat.float())[1] is None


# ----------------------------------------------------------------------------- offline fit
def test_training_reduces_the_one_step_error_on_the_training_tracks(yu):
    cfg, scenario, network, states = yu
    m = _model(cfg, scenario, network, epochs=30, process_noise="fixed")
    before = m.one_step_residuals(states)[:, :2].pow(2).sum(-1).mean()
    m.fit_offline(states, DT, seed=0)
    after = m.one_step_residuals(states)[:, :2].pow(2).sum(-1).mean()
    assert after < 0.35 * before, (float(before), float(after))
    assert len(m.training_curve) == 30 and m.fit_info["train_loss"] == m.training_curve.train_loss.iloc[-1]
    # process_noise=fixed: Q = noise_std^2 I
    torch.testing.assert_close(m.noise_cov(states[:2, 0], scenario.ctx())[0], 0.1**2 * torch.eye(8, dtype=F64), rtol=0, atol=0)


def test_process_noise_from_held_out_residuals_and_the_refit_on_every_episode(yu):
    """Q = I_A (x) Sigma, Sigma the second moment of the one-step residuals of the network trained on
    the other episodes, on the held-out ones; the kept weights are the fixed schedule's on every
    episode (those of ``train_lstm`` from the same seed)."""
    cfg, scenario, network, states = yu
    m = _model(cfg, scenario, network)
    m.fit_offline(states, DT, seed=3)
    win, groups = episode_windows(states, 2, 10)
    held = holdout_groups(groups, 0.2, 3)
    ids = torch.unique(groups[held])
    assert ids.numel() == 1  # round(0.2 * 6)
    # the network the residuals came from: trained on the other episodes
    aux = SocialLSTM(2, embed=16, hidden=16, dt=DT, seed=3)
    train_lstm(aux, win[~held], epochs=4, batch_size=8, lr=1e-3, seed=3)
    x = states[ids]
    with torch.no_grad():
        r = (x[:, 1:] - aux(x[:, :-1], StepContext(dt=DT))).reshape(-1, 4)
    sigma = r.T @ r / r.shape[0]
    Q = m.noise_cov(states[:1, 0], scenario.ctx())[0]
    torch.testing.assert_close(Q[:4, :4], sigma, rtol=1e-10, atol=1e-14)
    torch.testing.assert_close(Q[4:, 4:], sigma, rtol=1e-10, atol=1e-14)
    assert Q[:4, 4:].abs().max() == 0
    # the kept weights: the same fresh weights trained on every episode's windows
    full = SocialLSTM(2, embed=16, hidden=16, dt=DT, seed=3)
    train_lstm(full, win, epochs=4, batch_size=8, lr=1e-3, seed=3)
    for (k, v), w in zip(m.state_dict().items(), full.state_dict().values()):
        assert torch.equal(v, w), k
    assert math.isclose(m.fit_info["q_pos_std"], float(sigma.diagonal()[:2].sqrt().mean()), rel_tol=1e-9)


def test_fit_is_seeded(yu):
    cfg, scenario, network, states = yu
    fits = [_model(cfg, scenario, network, epochs=2).fit_offline(states, DT, seed=s) for s in (7, 7, 8)]
    a, b, c = (torch.cat([p.flatten() for p in f.parameters()]) for f in fits)
    assert torch.equal(a, b) and torch.equal(fits[0].process_cov, fits[1].process_cov)
    assert not torch.equal(a, c)
    rng = torch.get_rng_state()
    _model(cfg, scenario, network, epochs=1).fit_offline(states, DT, seed=1)
    assert torch.equal(rng, torch.get_rng_state())  # the run's global RNG is not drawn from


def test_fit_refusals(yu):
    cfg, scenario, network, states = yu
    m = _model(cfg, scenario, network, epochs=1)
    with pytest.raises(ConfigError, match="dt=0.4"):
        m.fit_offline(states, 0.4)
    with pytest.raises(ConfigError, match=">= 2 episodes"):
        m.fit_offline(states[:1], DT)
    with pytest.raises(ConfigError, match="model.pred_len"):
        m.fit_offline(states[:, :8], DT)
    fixed = _model(cfg, scenario, network, epochs=1, process_noise="fixed")
    fixed.fit_offline(states[:1], DT)  # the paper's recipe needs no held-out episode


# ------------------------------------------------------------------------------- pooling
def test_social_pooling_differs_from_the_plain_lstm_only_within_the_neighbourhood(yu):
    """A plain LSTM given the Social-LSTM's weights, with the pooled embedding of an empty grid
    (ReLU(b), the same for every step) folded into its LSTM biases, equals the Social-LSTM where the
    two agents are never within the 2 m square and differs where they are."""
    cfg, scenario, network, _ = yu
    ctx = scenario.ctx()
    soc = _model(cfg, scenario, network, pooling="social")
    with torch.no_grad():
        for p in soc.pool_embed.parameters():
            p.normal_(0.0, 1.0, generator=torch.Generator().manual_seed(2))
    plain = _model(cfg, scenario, network)
    e = soc.embed
    empty = torch.relu(soc.pool_embed[0].bias)
    state = {k: v.clone() for k, v in soc.state_dict().items() if not k.startswith("pool_embed")}
    for cell in ("encoder", "decoder"):
        w = soc.state_dict()[f"{cell}.weight_ih"]
        state[f"{cell}.weight_ih"] = w[:, :e].clone()
        state[f"{cell}.bias_ih"] = soc.state_dict()[f"{cell}.bias_ih"] + w[:, e:] @ empty
    plain.load_state_dict(state)
    far = torch.tensor([[1.0, 1.0, 1.0, 0.0, 6.0, 6.0, -1.0, 0.0]], dtype=F64)
    near = torch.tensor([[1.0, 1.0, 1.0, 0.0, 1.5, 1.3, 0.8, 0.1]], dtype=F64)
    torch.testing.assert_close(soc(far, ctx), plain(far, ctx), rtol=0, atol=1e-12)
    torch.testing.assert_close(soc.jacobian(far, ctx), plain.jacobian(far, ctx), rtol=0, atol=1e-10)
    assert (soc(near, ctx) - plain(near, ctx)).abs().max() > 1e-3
    # the rolled-out predictions too (the decoder pools predicted positions)
    torch.testing.assert_close(soc.rollout(far, 6, ctx), plain.rollout(far, 6, ctx), rtol=0, atol=1e-12)


# ----------------------------------------------------------------------- the synthetic study
@pytest.mark.parametrize("filt", ["default", "ukf"])
def test_tiny_yu_study_with_the_lstm(filt):
    """``model=lstm`` composes, passes the up-front check, is trained offline on 2 training episodes
    (1 held out for Q) and tracks 1 test episode, with finite results labelled by the option."""
    from dslearn import api

    kw = {"model.epochs": 2, "model.embed": 8, "model.hidden": 8, "filter": filt}
    study = api.yu_study(model="lstm", consensus="hybrid", train_episodes=2, test_episodes=1, **kw)
    df = study.run()
    label = "lstm" if filt == "default" else "lstm+ukf"
    assert set(df.model) == {label} and set(df.train_seen) == {2}
    for metric in ("track_err", "pred_err", "nees"):
        v = df[df.metric == metric].value
        assert len(v) == 10 and v.notna().all() and (v > 0).all() and (v < 50).all(), metric
    assert len(study.model.training_curve) == 2 and torch.isfinite(study.model.process_cov).all()


def test_synthetic_studies_refuse_fused_training(make_cfg):
    from dslearn.schemas.core import validate_config

    with pytest.raises(ConfigError, match="model.train_on=fused"):
        validate_config(make_cfg("model=lstm", "model.train_on=fused"))
    validate_config(make_cfg("model=social_lstm", "model.train_on=truth"))


def test_faults_study_fits_the_lstm_once_and_refuses_fused_training(make_cfg, monkeypatch):
    """``task.models=[lstm]`` in the faults study: fitted once (before the grid) on the true training tracks,
    copied into every cell, finite rows labelled lstm; ``train_on=fused`` refused before any episode is drawn."""
    from dslearn import api
    from dslearn.studies import yu_faults

    over = ["experiment=yu_faults", "task.models=[lstm]", "task.fusions=[cm,hybrid]", "task.train_episodes=2",
            "task.test_episodes=1", "task.link_fail=[0.0,0.3]", "task.node_fail=[]", "task.joint=[]",
            "task.outlier_settings=false"]
    fits = []
    real_fit = SocialLSTM.fit_offline
    monkeypatch.setattr(SocialLSTM, "fit_offline", lambda self, *a, **k: fits.append(a[0].shape) or real_fit(self, *a, **k))
    df = api.build_study(make_cfg(*over)).run()
    assert fits == [(2, 13, 8)]  # once, for 2 settings x 2 fusions
    te = df[(df.metric == "track_err") & (df.node == "alive")]
    assert set(te.model) == {"lstm"} and len(te) == 4 and te.value.map(math.isfinite).all()
    real_conf = SocialLSTM.configure_offline
    monkeypatch.setattr(SocialLSTM, "configure_offline", lambda self, prefix="model", **k: real_conf(self, prefix, **{**k, "train_on": "fused"}))
    monkeypatch.setattr(yu_faults, "episode_streams", lambda *a, **k: pytest.fail("drew episodes"))
    with pytest.raises(ConfigError, match="model.train_on=fused"):
        api.build_study(make_cfg(*over)).run()


def test_weights_dtype_float32_inside_a_float64_filter(yu):
    """``model.weights_dtype=float32``: the network's weights and arithmetic in float32, its prediction and
    Jacobian handed back in the filter's float64, equal to the float64 network with the same (rounded) weights
    to float32 precision; the fit trains the float32 weights; a dtype outside float32|float64 is refused."""
    cfg, scenario, network, states = yu
    m32 = _model(cfg, scenario, network, weights_dtype="float32")
    m64 = _model(cfg, scenario, network)
    assert m32.param_dtype == torch.float32 and m64.param_dtype == F64
    m64.load_state_dict({k: v.to(F64) for k, v in m32.state_dict().items()})
    ctx = StepContext(dt=DT)
    x = states[:3, 4]
    y32, y64 = m32(x, ctx), m64(x, ctx)
    assert y32.dtype == F64 and torch.allclose(y32, y64, rtol=1e-5, atol=1e-5) and not torch.equal(y32, y64)
    j32 = m32.jacobian(x, ctx)
    assert j32.dtype == F64 and torch.allclose(j32, _fd_jacobian(m64, x, ctx), rtol=1e-3, atol=1e-3)
    m32.fit_offline(states, DT, seed=3)
    assert m32.param_dtype == torch.float32 and math.isfinite(m32.fit_info["train_loss"])
    with pytest.raises(ConfigError, match="model.weights_dtype"):
        _model(cfg, scenario, network, weights_dtype="float16")
