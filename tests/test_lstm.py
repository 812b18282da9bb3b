"""LSTM encoder-decoder / Social-LSTM: shapes, training, pooling, checkpoints, MotionModel."""

import pytest
import torch

from dslearn.errors import ConfigError
from dslearn.models.base import MotionModel
from dslearn.models.lstm import SocialLSTM, load_checkpoint, save_checkpoint, train_lstm
from dslearn.types import StepContext

F64 = torch.float64


def _lines(n, obs=2, pred=10, seed=0):
    """Straight constant-velocity lines: (n, obs+pred, 1, 2)."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(obs + pred, dtype=F64)
    v = 0.6 * torch.randn(n, 2, generator=g, dtype=F64)
    p0 = 3.0 * torch.randn(n, 2, generator=g, dtype=F64)
    return (p0[:, None] + t[None, :, None] * v[:, None]).unsqueeze(2)


def test_shapes_and_validation():
    for pooling in ("none", "social"):
        m = SocialLSTM(3, obs_len=2, pred_len=10, embed=8, hidden=8, pooling=pooling, seed=0)
        assert isinstance(m, MotionModel) and m.state_dim == 12
        out = m.predict(torch.randn(4, 2, 3, 2, dtype=F64))
        assert out.shape == (4, 10, 3, 2) and out.dtype == F64 and torch.isfinite(out).all()
    m32 = SocialLSTM(2, obs_len=3, pred_len=5, embed=8, hidden=8, dtype=torch.float32)
    out = m32.predict(torch.randn(2, 3, 2, 2, dtype=F64))
    assert out.shape == (2, 5, 2, 2) and out.dtype == F64  # returned in the input's dtype
    # absent agents (NaN) give NaN outputs and do not disturb the others
    h = torch.randn(1, 2, 2, 2, dtype=F64)
    h_nan = h.clone()
    h_nan[0, :, 1] = float("nan")
    out = m.predict(h_nan)
    assert torch.isnan(out[0, :, 1]).all() and torch.isfinite(out[0, :, 0]).all()
    with pytest.raises(ValueError, match="obs_len"):
        m.predict(torch.randn(1, 5, 3, 2, dtype=F64))
    with pytest.raises(ConfigError, match="lstm.pooling"):
        SocialLSTM(1, pooling="attention")
    with pytest.raises(ConfigError, match="lstm.obs_len"):
        SocialLSTM(1, obs_len=1)
    with pytest.raises(ConfigError, match="lstm.neighbourhood"):
        SocialLSTM(1, neighbourhood=0.0)


def test_training_reduces_loss_and_learns_straight_lines():
    w = _lines(256)
    m = SocialLSTM(1, embed=16, hidden=32, seed=0)
    hist = train_lstm(m, w, epochs=25, batch_size=16, lr=5e-3, val_windows=_lines(32, seed=1), seed=0)
    assert list(hist.columns) == ["epoch", "train_loss", "val_loss", "seconds"] and len(hist) == 25
    assert hist.train_loss.iloc[-1] < 0.05 * hist.train_loss.iloc[0]
    assert hist.val_loss.iloc[-1] < 0.05 * hist.val_loss.iloc[0]
    test = _lines(64, seed=2)
    pred = m.predict(test[:, :2])
    err = (pred - test[:, 2:]).norm(dim=-1)  # metres, lines move ~0.85 m per step
    assert err.mean() < 0.35, float(err.mean())
    # far better than predicting that nobody moves
    still = (test[:, 1:2] - test[:, 2:]).norm(dim=-1)
    assert err.mean() < 0.1 * still.mean()


def test_training_is_seeded():
    w = _lines(32)
    a = SocialLSTM(1, embed=8, hidden=8, seed=3)
    b = SocialLSTM(1, embed=8, hidden=8, seed=3)
    ha = train_lstm(a, w, epochs=2, batch_size=8, lr=1e-3, seed=5)
    hb = train_lstm(b, w, epochs=2, batch_size=8, lr=1e-3, seed=5)
    assert ha.train_loss.tolist() == hb.train_loss.tolist()
    with pytest.raises(ConfigError, match="windows"):
        train_lstm(a, w[:, :5], epochs=1, batch_size=8, lr=1e-3)
    with pytest.raises(ConfigError, match="lstm.epochs"):
        train_lstm(a, w, epochs=0, batch_size=8, lr=1e-3)


def test_social_pooling_inside_vs_outside():
    m = SocialLSTM(2, pooling="social", grid=4, neighbourhood=2.0, embed=8, hidden=8, seed=0)
    with torch.no_grad():  # make the pooled term matter
        for p in m.pool_embed.parameters():
            p.normal_(0.0, 1.0)
    ego = torch.tensor([[0.0, 0.0], [0.4, 0.0]], dtype=F64)  # (obs_len, 2)
    alone = m.predict(ego.view(1, 2, 1, 2))[0, :, 0]

    def with_neighbour(offset):
        nb = ego + torch.tensor(offset, dtype=F64)
        return m.predict(torch.stack([ego, nb], dim=1).unsqueeze(0))[0, :, 0]

    far = with_neighbour([5.0, 5.0])  # outside the 2 m square at every step
    near = with_neighbour([0.3, 0.2])  # inside
    assert torch.allclose(far, alone, atol=1e-12, rtol=0)
    assert (near - alone).abs().max() > 1e-3
    # without pooling the neighbour never matters
    m0 = SocialLSTM(2, pooling="none", embed=8, hidden=8, seed=0)
    h = torch.stack([ego, ego + 0.3], dim=1).unsqueeze(0)
    assert torch.allclose(m0.predict(h)[0, :, 0], m0.predict(ego.view(1, 2, 1, 2))[0, :, 0], atol=1e-12, rtol=0)


def test_checkpoint_round_trip_and_mismatch(tmp_path):
    m = SocialLSTM(2, pooling="social", embed=8, hidden=8, seed=0)
    path = tmp_path / "ck" / "lstm.pt"
    hist = train_lstm(m, _lines(16).expand(-1, -1, 2, -1).clone(), epochs=1, batch_size=8, lr=1e-3, checkpoint=path)
    assert path.is_file()
    h = torch.randn(3, 2, 2, 2, dtype=F64)
    # into a fresh model with the same hyperparameters (different init)
    m2 = SocialLSTM(2, pooling="social", embed=8, hidden=8, seed=1).load(path)
    assert torch.equal(m.predict(h), m2.predict(h))
    # built from the saved hyperparameters
    m3 = load_checkpoint(path, num_agents=2)
    assert m3.hparams() == m.hparams() and torch.equal(m.predict(h), m3.predict(h))
    assert m3.checkpoint_history.train_loss.tolist() == hist.train_loss.tolist()
    with pytest.raises(ConfigError, match="pooling"):
        SocialLSTM(2, pooling="none", embed=8, hidden=8).load(path)
    with pytest.raises(ConfigError, match="hidden: checkpoint 8 vs model 16"):
        load_checkpoint(path, SocialLSTM(2, pooling="social", embed=8, hidden=16))
    with pytest.raises(ConfigError, match="dt"):
        SocialLSTM(2, pooling="social", embed=8, hidden=8, dt=2 / 3).load(path)
    torch.save({"weights": torch.zeros(2)}, tmp_path / "other.pt")
    with pytest.raises(ConfigError, match="not a"):
        load_checkpoint(tmp_path / "other.pt")
    save_checkpoint(m, tmp_path / "plain.pt")  # without history
    assert load_checkpoint(tmp_path / "plain.pt", num_agents=1).checkpoint_history.empty


def test_motion_model_interface():
    m = SocialLSTM(2, obs_len=2, pred_len=4, embed=8, hidden=8, pooling="social", dt=0.4, seed=0)
    ctx = StepContext(dt=0.4)
    x = torch.tensor([[0.0, 0.0, 1.0, 0.0, 0.5, 0.2, 0.0, 1.0]], dtype=F64).expand(3, 8).clone()
    x[1] += 0.1
    nxt = m(x, ctx)
    assert nxt.shape == (3, 8)
    # history from the state: [p - v dt, p]
    hist = m.history_from_state(x)
    assert torch.allclose(hist[0, 0, 0], torch.tensor([-0.4, 0.0], dtype=F64))
    pred = m.predict(hist)  # (3, 4, 2, 2)
    roll = m.rollout(x, 9, ctx)  # longer than pred_len: continues autoregressively
    assert roll.shape == (3, 9, 8)
    r = roll.view(3, 9, 2, 4)
    assert torch.allclose(r[:, :4, :, :2], pred, atol=1e-12)
    assert torch.allclose(nxt.view(3, 2, 4), r[:, 0], atol=1e-12)
    # velocities are finite differences of the positions
    p_all = torch.cat([x.view(3, 1, 2, 4)[..., :2], r[..., :2]], dim=1)
    assert torch.allclose(r[..., 2:], (p_all[:, 1:] - p_all[:, :-1]) / 0.4, atol=1e-12)
    # steps 5..8 = a fresh prediction from the last obs_len predicted positions
    again = m.predict(r[:, 2:4, :, :2])
    assert torch.allclose(r[:, 4:8, :, :2], again, atol=1e-12)
    # extra batch dimensions, Jacobian by autograd, noise
    xb = x.view(1, 3, 8).expand(2, 3, 8)
    assert m(xb, ctx).shape == (2, 3, 8) and m.rollout(xb, 2, ctx).shape == (2, 3, 2, 8)
    jac = m.jacobian(x, ctx)
    assert jac.shape == (3, 8, 8) and torch.isfinite(jac).all()
    assert torch.allclose(m.noise_cov(x, ctx)[0], 0.01 * torch.eye(8, dtype=F64), atol=1e-15, rtol=0)
    with pytest.raises(ConfigError, match="dt"):
        m(x, StepContext(dt=0.25))


def test_sparse_pooling_equals_dense_grid_pooling():
    """The pair-wise pooled embedding equals Linear(vec(H_i)) of the dense Alahi tensor."""
    m = SocialLSTM(1, pooling="social", grid=4, neighbourhood=2.0, embed=8, hidden=6, seed=0)
    g = torch.Generator().manual_seed(0)
    pos = 1.5 * torch.rand(3, 7, 2, generator=g, dtype=F64)  # many pairs inside the 2 m square
    h = torch.randn(3, 7, 6, generator=g, dtype=F64)
    mask = torch.ones(3, 7, dtype=torch.bool)
    mask[1, 4:] = False
    dense = m._pool(pos, h, mask)  # (B, A, G^2 H)
    assert dense.abs().sum() > 0
    assert torch.allclose(m._pooled_embedding(pos, h, mask), m.pool_embed(dense), atol=1e-12, rtol=0)
    # hand check of one cell: agent 0 alone with a neighbour 0.3 m to the right, 0.1 m up
    p = torch.tensor([[[0.0, 0.0], [0.3, 0.1]]], dtype=F64)
    hh = torch.randn(1, 2, 6, generator=g, dtype=F64)
    H = m._pool(p, hh, torch.ones(1, 2, dtype=torch.bool)).view(1, 2, 16, 6)
    cell = int((0.3 + 1.0) // 0.5) * 4 + int((0.1 + 1.0) // 0.5)  # = 2 * 4 + 2
    assert torch.equal(H[0, 0, cell], hh[0, 1]) and H[0, 0].abs().sum() == hh[0, 1].abs().sum()
