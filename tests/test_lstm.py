"""LSTM encoder-decoder / Social-LSTM: shapes, training, pooling, checkpoints, MotionModel."""

import pytest
import torch

from dslearn.data.ethucy import data_available
from dslearn.errors import ConfigError, DataFormatError
from dslearn.models.base import MotionModel
from dslearn.models.lstm import (
    SocialLSTM,
    evaluate_loss,
    holdout_split,
    load_checkpoint,
    save_checkpoint,
    schedule_from_config,
    train_lstm,
)
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
    assert list(hist.columns) == ["epoch", "train_loss", "val_loss", "seconds", "lr", "best"] and len(hist) == 25
    assert (hist.lr == 5e-3).all() and hist.attrs["restored_epoch"] == 25 and not hist.attrs["stopped_early"]
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
    with pytest.raises(DataFormatError, match=r"other\.pt: not a dslearn\.lstm/1 checkpoint \(format None\)"):
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


def _accelerating(n, obs=2, pred=10, seed=0, gain=2.0):
    """Windows whose future moves ``gain`` times faster than the observed motion: (n, obs+pred, 1, 2).

    Training on gain 2 and validating on gain 1 (constant velocity): from its near-zero initial
    output the network's predicted speed grows past the validation optimum (the observed speed)
    towards twice it, so the validation loss falls, then rises.
    """
    g = torch.Generator().manual_seed(seed)
    v = 0.5 * torch.randn(n, 2, generator=g, dtype=F64)
    p0 = torch.randn(n, 2, generator=g, dtype=F64)
    t_obs = torch.arange(obs, dtype=F64)
    t_fut = (obs - 1) + gain * torch.arange(1, pred + 1, dtype=F64)
    t = torch.cat([t_obs, t_fut])
    return (p0[:, None] + t[None, :, None] * v[:, None]).unsqueeze(2)


def test_early_stopping_stops_and_restores_the_best_weights():
    tr, va = _accelerating(128, gain=2.0), _accelerating(64, seed=1, gain=1.0)
    kw = dict(embed=8, hidden=16, seed=0)
    m = SocialLSTM(1, **kw)
    hist = train_lstm(m, tr, epochs=60, batch_size=16, lr=3e-3, val_windows=va, seed=0, patience=4)
    best = hist.attrs["best_epoch"]
    vals = hist.val_loss.to_numpy()
    # the validation loss fell, then rose: stopped long before the cap, patience epochs after the best
    assert hist.attrs["stopped_early"] and len(hist) == best + 4 < 60
    assert 1 < best and vals[best - 1] == vals.min() and vals[-1] > vals[best - 1] and vals[0] > vals[best - 1]
    assert hist.best.tolist() == [bool(vals[i] < vals[:i].min()) if i else True for i in range(len(vals))]
    assert hist.attrs["restored_epoch"] == best and hist.attrs["best_val_loss"] == vals[best - 1]
    # the model holds the best epoch's weights: its validation loss is that epoch's, exactly,
    assert evaluate_loss(m, va) == vals[best - 1]
    # and they are bit-identical to a fixed schedule of `best` epochs with the same seeds
    ref = SocialLSTM(1, **kw)
    href = train_lstm(ref, tr, epochs=best, batch_size=16, lr=3e-3, val_windows=va, seed=0)
    assert all(torch.equal(a, b) for a, b in zip(m.state_dict().values(), ref.state_dict().values()))
    assert href.val_loss.tolist() == hist.val_loss.iloc[:best].tolist()
    assert href.train_loss.tolist() == hist.train_loss.iloc[:best].tolist()
    # restore_best=False keeps the last weights
    m2 = SocialLSTM(1, **kw)
    h2 = train_lstm(m2, tr, epochs=60, batch_size=16, lr=3e-3, val_windows=va, seed=0, patience=4, restore_best=False)
    assert h2.attrs["restored_epoch"] == len(h2) and evaluate_loss(m2, va) == h2.val_loss.iloc[-1]


def test_lr_on_plateau_and_min_delta():
    tr, va = _accelerating(64, gain=2.0), _accelerating(32, seed=1, gain=1.0)
    m = SocialLSTM(1, embed=8, hidden=8, seed=0)
    hist = train_lstm(m, tr, epochs=30, batch_size=16, lr=4e-3, val_windows=va, seed=0, patience=8,
                      lr_factor=0.5, lr_patience=2, min_lr=1e-3)
    lrs = hist.lr.to_numpy()
    assert lrs[0] == 4e-3 and lrs.min() == 1e-3 and (lrs[1:] <= lrs[:-1]).all()  # cut, never below min_lr
    # a cut follows exactly lr_patience epochs without a new best (counted since the best or the last cut)
    since = 0
    for i in range(len(hist) - 1):
        since = 0 if hist.best.iloc[i] else since + 1
        cut = since >= 2 and lrs[i] > 1e-3
        assert lrs[i + 1] == (max(lrs[i] * 0.5, 1e-3) if cut else lrs[i])
        if cut:
            since = 0
    # min_delta: a new best must improve by that fraction
    m = SocialLSTM(1, embed=8, hidden=8, seed=0)
    h = train_lstm(m, tr, epochs=12, batch_size=16, lr=4e-3, val_windows=va, seed=0, patience=50, min_delta=0.2)
    best = h.val_loss.iloc[0]
    for v, flag in zip(h.val_loss.iloc[1:], h.best.iloc[1:]):
        assert flag == (v < 0.8 * best)
        best = v if flag else best


def test_schedule_config_errors():
    ok = {"epochs": 5, "batch_size": 8, "lr": 1e-3}
    assert schedule_from_config(ok) == ok  # schedule defaults to fixed
    es = schedule_from_config({**ok, "schedule": "early_stopping", "patience": 3, "lr_factor": 0.5})
    assert es == {**ok, "patience": 3, "min_delta": 0.0, "lr_factor": 0.5, "lr_patience": 2, "min_lr": 0.0}
    for bad, field in (
        ({"schedule": "cosine"}, "task.lstm.schedule"),
        ({"schedule": "early_stopping", "patience": 0}, "task.lstm.patience"),
        ({"schedule": "early_stopping", "patience": None}, "task.lstm.patience"),
        ({"patience": -2}, "task.lstm.patience"),  # checked under the fixed schedule too
        ({"min_delta": -0.1}, "task.lstm.min_delta"),
        ({"min_delta": 1.0}, "task.lstm.min_delta"),
        ({"lr_factor": 1.5}, "task.lstm.lr_factor"),
        ({"lr_factor": -0.5}, "task.lstm.lr_factor"),
        ({"lr_patience": 0}, "task.lstm.lr_patience"),
        ({"min_lr": -1.0}, "task.lstm.min_lr"),
        ({"epochs": -1}, "task.lstm.epochs"),
        ({"batch_size": 0}, "task.lstm.batch_size"),
        ({"lr": -1e-3}, "task.lstm.lr"),
    ):
        with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
            schedule_from_config({**ok, **bad}, prefix="task.lstm")
    m = SocialLSTM(1, embed=8, hidden=8)
    with pytest.raises(ConfigError, match="validation windows"):
        train_lstm(m, _lines(8), epochs=2, batch_size=4, lr=1e-3, patience=2)
    with pytest.raises(ConfigError, match="validation windows"):
        train_lstm(m, _lines(8), epochs=2, batch_size=4, lr=1e-3, lr_factor=0.5)


@pytest.mark.skipif(not data_available(), reason="ETH/UCY data root not found")
def test_train_lstm_app_early_stopping(tmp_path):
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from dslearn import train_lstm as app

    with initialize_config_dir(config_dir=app.CONF_DIR, version_base=None):
        cfg = compose("train_lstm")
    assert "zara1" in cfg.datasets and list(cfg.datasets.univ.files) == ["students001.txt", "students003.txt"]
    over = {"train_scenes": ["zara1"], "val_scenes": ["zara1"], "stride": 5, "max_windows": 40, "progress": False,
            "lstm": {"embed": 8, "hidden": 8, "schedule": "early_stopping", "epochs": 4, "patience": 1}}
    cfg = OmegaConf.merge(cfg, over)
    model, hist, ckpt = app.train(cfg, tmp_path)
    assert ckpt.is_file() and (tmp_path / "history.csv").is_file()
    assert 1 <= len(hist) <= 4 and hist.attrs["restored_epoch"] == hist.attrs["best_epoch"] == int(hist.val_loss.idxmin()) + 1
    assert load_checkpoint(ckpt).checkpoint_history.val_loss.tolist() == hist.val_loss.tolist()
    for bad, msg in (({"val_scenes": []}, "val_scenes"), ({"lstm": {"schedule": "sgdr"}}, "lstm.schedule"),
                     ({"train_scenes": ["atlantis"]}, "train_scenes"),
                     ({"lstm": {"patience": -1}}, "lstm.patience")):
        with pytest.raises(ConfigError, match=msg):
            app.train(OmegaConf.merge(cfg, bad), tmp_path)
    c2 = OmegaConf.create(OmegaConf.to_container(cfg))
    c2.lstm.warmup = 3
    with pytest.raises(ConfigError, match="unknown keys"):
        app.train(c2, tmp_path)


def test_holdout_split_by_group():
    w = torch.arange(30, dtype=F64).view(30, 1, 1, 1).expand(30, 12, 1, 2).clone()
    groups = torch.arange(30) % 10  # 10 episodes, 3 windows each (interleaved, as sliding windows are)
    tr, va = holdout_split(w, groups, 0.2, seed=0)
    assert tr.shape[0] == 24 and va.shape[0] == 6  # 2 whole episodes held out
    g_tr, g_va = set((tr[:, 0, 0, 0].long() % 10).tolist()), set((va[:, 0, 0, 0].long() % 10).tolist())
    assert len(g_va) == 2 and not g_tr & g_va and g_tr | g_va == set(range(10))
    tr2, va2 = holdout_split(w, groups, 0.2, seed=0)
    assert torch.equal(va, va2) and torch.equal(tr, tr2)  # seeded
    held = {tuple(sorted(set((holdout_split(w, groups, 0.2, seed=s)[1][:, 0, 0, 0].long() % 10).tolist()))) for s in range(10)}
    assert len(held) > 1  # the seed chooses which episodes are held out
    assert holdout_split(w, groups, 0.01, seed=0)[1].shape[0] == 3  # at least one group
    assert holdout_split(w, groups, 0.99, seed=0)[0].shape[0] == 3  # at least one group left to train
    with pytest.raises(ConfigError, match="val_fraction"):
        holdout_split(w, groups, 1.0, seed=0)
    with pytest.raises(ConfigError, match="groups"):
        holdout_split(w, torch.zeros(30), 0.2, seed=0)
