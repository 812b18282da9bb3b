"""The offline-fit cache (dslearn.learning.fit_cache): one fit per model, training set and seed, shared by the
presets that fit the same model; a fit loaded from it gives bit-identical results to a fresh one."""

from __future__ import annotations

import logging

import pandas as pd
import pytest
import torch

from dslearn.compose import build_study
from dslearn.diagnostics import Diagnostics
from dslearn.learning import fit_cache
from dslearn.learning.sfm_fit import FittedSocialForce
from dslearn.models.lstm import SocialLSTM

#: a small LSTM fit (the network and schedule of the presets, shrunk)
SMALL = ["model.epochs=2", "model.embed=8", "model.hidden=8", "model.pred_len=3"]


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """A cache folder of this test only (never the user's ~/.cache/dslearn)."""
    monkeypatch.setenv("DSLEARN_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache" / fit_cache.KIND


def _cell(make_cfg, method, *extra):
    cfg = make_cfg("task=matrix", f"method={method}", "scenario=yu_two_agents", "task.train_episodes=3",
                   "task.test_episodes=2", *SMALL, *extra)
    study = build_study(cfg)
    with Diagnostics() as diag:
        df = study.run(diagnostics=diag)
    return df[df.metric != "runtime_s"].reset_index(drop=True), study.method.model, diag


def test_a_fit_loaded_from_the_cache_gives_bit_identical_estimates(make_cfg, cache, caplog):
    with caplog.at_level(logging.INFO, logger="dslearn.learning.fit_cache"):
        first, m1, d1 = _cell(make_cfg, "ekf_lstm_hybrid")
        second, m2, d2 = _cell(make_cfg, "ekf_lstm_hybrid")
    assert m1.fit_cache["source"] == "fit" and m2.fit_cache["source"] == "cache"
    assert m1.fit_cache["key"] == m2.fit_cache["key"] and len(m1.fit_cache["key"]) == 64
    assert list(cache.glob("*.pt")) == [cache / f"{m1.fit_cache['key']}.pt"]
    assert d1.counts == {"offline_fit_cache_misses": 1, "offline_fit_cache_stored": 1}
    assert d2.counts == {"offline_fit_cache_hits": 1} and d2.timings["offline_fit_s"] >= 0
    assert f"offline fit: loaded from cache {m1.fit_cache['key']}" in caplog.text
    pd.testing.assert_frame_equal(first, second, check_exact=True)  # every rmse, pos_err, nees value, bit for bit
    for (k, a), (_, b) in zip(m1.state_dict().items(), m2.state_dict().items()):
        assert torch.equal(a, b), k
    assert torch.equal(m1.process_cov, m2.process_cov) and bool(torch.isfinite(m1.process_cov).all())
    assert m1.fit_info == m2.fit_info and not m2.training
    pd.testing.assert_frame_equal(m1.training_curve, m2.training_curve, check_exact=True)
    assert repr(m1.training_curve.attrs) == repr(m2.training_curve.attrs)  # best_val_loss: NaN (fixed schedule)


def test_the_ekf_and_the_ukf_share_one_fit_and_the_estimates_equal_a_fit_without_cache(make_cfg, cache, monkeypatch):
    _, m_ekf, _ = _cell(make_cfg, "ekf_lstm_hybrid")
    ukf, m_ukf, d = _cell(make_cfg, "ukf_lstm_individual")
    assert m_ukf.fit_cache == {"key": m_ekf.fit_cache["key"], "source": "cache"}
    assert d.counts == {"offline_fit_cache_hits": 1}
    monkeypatch.setenv("DSLEARN_CACHE_DIR", "off")
    fresh, m_off, d_off = _cell(make_cfg, "ukf_lstm_individual")
    assert m_off.fit_cache["source"] == "off" and "offline_fit_cache_misses" not in d_off.counts
    pd.testing.assert_frame_equal(ukf, fresh, check_exact=True)


def _model(**kw):
    return SocialLSTM(2, obs_len=2, pred_len=3, embed=8, hidden=8, dt=0.4, seed=0).configure_offline(epochs=2, **kw)


def test_the_key_changes_with_the_training_set_the_seed_dt_and_the_settings():
    states = torch.randn(3, 8, 8, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    key = fit_cache.fit_key(_model(), states, 0.4, 0)
    assert fit_cache.fit_key(_model(), states.clone(), 0.4, 0) == key  # by content, not by object
    other = states.clone()
    other[1, 2, 3] += 1e-12
    changed = {
        "training set": fit_cache.fit_key(_model(), other, 0.4, 0),
        "fewer episodes": fit_cache.fit_key(_model(), states[:2], 0.4, 0),
        "float32 states": fit_cache.fit_key(_model(), states.float(), 0.4, 0),
        "seed": fit_cache.fit_key(_model(), states, 0.4, 1),
        "dt": fit_cache.fit_key(_model(), states, 0.2, 0),
        "epochs": fit_cache.fit_key(_model().configure_offline(epochs=3), states, 0.4, 0),
        "process noise": fit_cache.fit_key(_model(process_noise="fixed"), states, 0.4, 0),
        "dtype": fit_cache.fit_key(_model().to(torch.float32), states, 0.4, 0),
        "pooling": fit_cache.fit_key(SocialLSTM(2, pred_len=3, embed=8, hidden=8, pooling="social", seed=0)
                                     .configure_offline(epochs=2), states, 0.4, 0),
    }
    assert len({key, *changed.values()}) == len(changed) + 1, changed


def test_a_corrupt_or_foreign_entry_is_fitted_again_and_overwritten(cache):
    states = torch.randn(3, 8, 8, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    ref = fit_cache.fit_offline_cached(_model(), states, 0.4, 0)
    path = cache / f"{ref.fit_cache['key']}.pt"
    good = path.read_bytes()
    for bad in (good[: len(good) // 2], b"", b"not a torch file"):
        path.write_bytes(bad)
        again = fit_cache.fit_offline_cached(_model(), states, 0.4, 0)
        assert again.fit_cache["source"] == "fit"
        loaded = fit_cache.fit_offline_cached(_model(), states, 0.4, 0)  # overwritten: it loads again
        assert loaded.fit_cache["source"] == "cache"
        for (k, a), (_, b), (_, c) in zip(ref.state_dict().items(), again.state_dict().items(),
                                          loaded.state_dict().items()):
            assert torch.equal(a, b) and torch.equal(a, c), k
    # an entry stored under another key (renamed) is not this key's: refitted
    other = fit_cache.fit_offline_cached(_model(), states, 0.4, 1)
    (cache / f"{other.fit_cache['key']}.pt").replace(path)
    assert fit_cache.fit_offline_cached(_model(), states, 0.4, 0).fit_cache["source"] == "fit"
    assert fit_cache.fit_offline_cached(_model(), states, 0.4, 0).fit_cache["source"] == "cache"
    assert not [p for p in cache.iterdir() if p.name.endswith(".tmp")]  # the atomic writes left no temporary file


def test_the_fitted_social_force_round_trips(cache):
    class Scen:
        num_agents, steps = 2, 6

    gen = torch.Generator().manual_seed(3)
    states = torch.cumsum(0.1 * torch.randn(2, 7, 8, dtype=torch.float64, generator=gen), dim=1)

    def fresh():
        return FittedSocialForce.for_scenario(scenario=Scen(), tau_grid=(0.5, 1.0), alpha_grid=(0.0, 1.0),
                                              beta_grid=(1.0,), refine_iters=3)

    a = fit_cache.fit_offline_cached(fresh(), states, 0.4, 0)
    b = fit_cache.fit_offline_cached(fresh(), states, 0.4, 0)
    assert (a.fit_cache["source"], b.fit_cache["source"]) == ("fit", "cache")
    assert a.fit_info == b.fit_info and set(a.fit_info) == {"tau", "alpha", "beta", "fit_loss"}
    for name in ("tau", "alpha", "beta"):
        assert torch.equal(getattr(a, name), getattr(b, name))
    c = fit_cache.fit_offline_cached(fresh(), states[:1], 0.4, 0)
    assert c.fit_cache["source"] == "fit" and c.fit_cache["key"] != a.fit_cache["key"]


def test_the_key_covers_the_code_that_fits(monkeypatch):
    """An edited fit (the model's module or a base's) is a new key: the source files are part of it."""
    from pathlib import Path

    names = {f.name for f in fit_cache.code_files(_model())}
    assert {"lstm.py", "base.py"} <= names
    sfm = {f.name for f in fit_cache.code_files(FittedSocialForce([[0.0, 0.0]], 1.0, 0.0, 1.0, 0.1))}
    assert {"sfm_fit.py", "social_force.py", "base.py"} <= sfm
    states = torch.randn(3, 8, 8, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    key = fit_cache.fit_key(_model(), states, 0.4, 0)
    real = Path.read_bytes
    monkeypatch.setattr(Path, "read_bytes", lambda self: real(self) + (b"# edited" if self.name == "lstm.py" else b""))
    assert fit_cache.fit_key(_model(), states, 0.4, 0) != key


def test_a_cache_folder_that_cannot_be_written_only_costs_the_cache(tmp_path, monkeypatch, caplog):
    blocker = tmp_path / "a file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("DSLEARN_CACHE_DIR", str(blocker / "cache"))  # its parent is a file: nothing can be written
    states = torch.randn(3, 8, 8, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    with caplog.at_level(logging.WARNING, logger="dslearn.learning.fit_cache"):
        m = fit_cache.fit_offline_cached(_model(), states, 0.4, 0)
    assert m.fit_cache["source"] == "fit" and m.fit_info["train_loss"] > 0
    assert "cannot lock cache entry" in caplog.text and "cannot write cache entry" in caplog.text


def test_the_calibrating_learner_shares_the_fit(make_cfg, cache):
    """learner=calibrate fits the offline model as the plain preset does (then scales Q and R): the same fit."""
    _, plain, _ = _cell(make_cfg, "ekf_lstm_hybrid")
    _, calibrated, d = _cell(make_cfg, "ekf_lstm_hybrid", "learner=calibrate")
    assert calibrated.fit_cache == {"key": plain.fit_cache["key"], "source": "cache"}
    assert d.counts == {"offline_fit_cache_hits": 1}
