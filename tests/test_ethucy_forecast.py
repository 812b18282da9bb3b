"""ETH/UCY forecasting study: metrics, baselines, GP helpers, tiny end-to-end run and report."""

import math

import pandas as pd
import pytest
import torch
from omegaconf import OmegaConf

from dslearn.data.ethucy import default_root
from dslearn.errors import ConfigError
from dslearn.models.gp import GPMotionModel, OnlineGP
from dslearn.studies import ethucy_forecast as ef
from dslearn.types import StepContext

F64 = torch.float64


def test_ade_fde_hand_computed():
    truth = torch.zeros(3, 2, dtype=F64)
    pred = torch.tensor([[3.0, 4.0], [0.0, 1.0], [0.0, 0.0]], dtype=F64)  # errors 5, 1, 0
    ade, fde = ef.ade_fde(pred, truth)
    assert ade.item() == pytest.approx(2.0) and fde.item() == 0.0
    # a constant 3-4-5 offset: ADE = FDE = 5; batch dims preserved
    t = torch.randn(4, 5, 12, 2, dtype=F64)
    ade, fde = ef.ade_fde(t + torch.tensor([3.0, 4.0], dtype=F64), t)
    assert ade.shape == (4, 5) and torch.allclose(ade, torch.full_like(ade, 5.0)) and torch.allclose(fde, torch.full_like(fde, 5.0))


def test_constant_velocity_exact_on_constant_velocity_tracks():
    g = torch.Generator().manual_seed(0)
    p0, v = torch.randn(50, 2, generator=g, dtype=F64), torch.randn(50, 2, generator=g, dtype=F64)
    tr = p0[:, None] + torch.arange(20, dtype=F64)[None, :, None] * v[:, None]
    pred = ef.constant_velocity(tr[:, :8], 12)
    assert pred.shape == (50, 12, 2)
    ade, fde = ef.ade_fde(pred, tr[:, 8:])
    assert ade.max() < 1e-12 and fde.max() < 1e-12
    # it uses the LAST velocity only: a turn before the last step is ignored
    bent = tr.clone()
    bent[:, :6] += 1.0
    assert torch.allclose(ef.constant_velocity(bent[:, :8], 12), pred)


def _gp_with_data(mean_in=4, out=2, n=300, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, mean_in, generator=g, dtype=F64)
    y = x[:, :out] + 0.3 * torch.sin(x[:, :out])
    gp = OnlineGP(1, mean_in, out, 1.0, 1.0, 0.3, "identity", capacity=2)
    ef._load_gp_data(gp, x, y)
    return gp, g


def test_gp_fast_mean_and_rollouts_match_the_project_gp():
    gp, g = _gp_with_data()
    q = torch.randn(50, 4, generator=g, dtype=F64)
    ref = gp.predict(q.unsqueeze(0), jacobian=False, variance=False)[0][0]
    assert torch.allclose(ef.gp_mean(gp, q), ref, atol=1e-10, rtol=0)
    # bulk loading equals appending the points one by one
    gp2 = OnlineGP(1, 4, 2, 1.0, 1.0, 0.3, "identity")
    for i in range(gp.n):
        gp2.append(gp.X[:, i], (gp.R[:, i] + gp.X[:, i, :2]))
    assert torch.allclose(gp2.predict(q.unsqueeze(0), jacobian=False, variance=False)[0][0], ref, atol=1e-9, rtol=0)
    # state GP: the fast rollout equals MotionModel.rollout of GPMotionModel
    m = GPMotionModel(4, 1, 1.0, 1.0, 0.3, mean="identity", capacity=2)
    xs = torch.randn(200, 4, generator=g, dtype=F64)
    ef._load_gp_data(m.gp, xs, xs + 0.1 * torch.tanh(xs))
    obs = torch.randn(7, 8, 2, generator=g, dtype=F64).cumsum(1)
    fast = ef.gp_state_rollout(m, obs, 5, 0.4)
    x0 = torch.cat([obs[:, -1], (obs[:, -1] - obs[:, -2]) / 0.4], -1).unsqueeze(0)
    slow = m.rollout(x0, 5, StepContext(dt=0.4))[0, :, :, :2]
    assert torch.allclose(fast, slow, atol=1e-10, rtol=0)


def test_gp_velocity_learns_constant_velocity_and_data_helpers():
    # triples from straight lines: the velocity GP must roll out straight lines
    g = torch.Generator().manual_seed(1)
    p0, v = torch.randn(400, 2, generator=g, dtype=F64), torch.randn(400, 2, generator=g, dtype=F64)
    quads = p0[:, None] + torch.arange(4, dtype=F64)[None, :, None] * v[:, None] * 0.4
    x, y = ef.gp_velocity_data(quads, 0.4)
    assert torch.allclose(x[:, :2], v) and torch.allclose(x[:, 2:], v) and torch.allclose(y, v)
    xs, ys = ef.gp_state_data(quads, 0.4)
    assert torch.allclose(xs[:, :2], quads[:, 2]) and torch.allclose(ys[:, 2:], v)
    gp = OnlineGP(1, 4, 2, 1.0, 1.0, 0.3, "identity", capacity=2)
    ef._load_gp_data(gp, x, y)
    tr = p0[:20, None] + torch.arange(20, dtype=F64)[None, :, None] * v[:20, None] * 0.4
    pred = ef.gp_velocity_rollout(gp, tr[:, :8], 12, 0.4)
    ade, _ = ef.ade_fde(pred, tr[:, 8:])
    assert ade.max() < 1e-6


def test_windows_helpers():
    nan = float("nan")
    w = torch.tensor([[[[0.0, 0.0], [nan, nan]], [[1.0, 0.0], [nan, nan]]]], dtype=F64)  # (1, 2, 2, 2)
    w2 = torch.arange(2 * 3 * 2, dtype=F64).view(1, 2, 3, 2)
    cat = ef._cat_windows([w, w2])
    assert cat.shape == (2, 2, 3, 2) and torch.isnan(cat[0, :, 1:]).all()
    agents = ef._per_agent(cat)
    assert agents.shape == (4, 2, 2)
    assert torch.equal(agents[0], w[0, :, 0])
    assert ef._subsample(torch.arange(10), 3).tolist() == [0, 4, 9]
    assert ef._subsample(torch.arange(10), None).numel() == 10


def _tiny_cfg(**task_over):
    t = OmegaConf.load(ef.__file__.replace("dslearn/studies/ethucy_forecast.py", "conf/task/ethucy_forecast.yaml"))
    t.scenes = ["zara1", "hotel"]
    t.lstm.epochs = 1
    t.lstm.embed = 16
    t.lstm.hidden = 16
    t.train_stride = 10
    t.max_train_windows = 120
    t.max_test_windows = 15
    t.gp.points = 200
    t.gp.fit_points = 60
    t.gp.fit_iters = 3
    for k, v in task_over.items():
        OmegaConf.update(t, k, v)
    return OmegaConf.create({"task": t, "seed": 0, "device": "cpu", "dtype": "float64", "progress": False})


def _has_data():
    try:
        default_root()
        return True
    except ConfigError:
        return False


@pytest.mark.skipif(not _has_data(), reason="ETH/UCY data root not found")
def test_tiny_end_to_end_run_and_report(tmp_path):
    df = ef.run(_tiny_cfg())
    assert {"model", "consensus", "node", "scene", "metric", "value", "episode"} <= set(df.columns)
    assert set(df.scene) == {"zara1", "hotel"} and set(df.consensus) == {"-"} and set(df.node) == {"avg"}
    main = df[df.metric.isin(["ade", "fde"])]
    assert set(main.model) == set(ef.PREDICTORS) and len(main) == 2 * 2 * len(ef.PREDICTORS)
    assert (main.value > 0).all() and main.value.map(math.isfinite).all()
    # FDE >= ADE is not a law, but ADE <= max error; check ADE for CV is in a sane range (m)
    cv = main[(main.model == "cv") & (main.metric == "ade")].value
    assert (cv > 0.05).all() and (cv < 3.0).all()
    counts = df[df.metric == "count"].groupby("scene").value.unique()
    assert all(len(v) == 1 for v in counts)  # every predictor scored on the same pedestrian-windows
    text = ef.report(df, None, tmp_path)
    assert "ZARA1" in text and "Social GAN" in text
    assert (tmp_path / "ethucy_forecast.md").is_file() and (tmp_path / "ethucy_forecast.png").is_file()
    tab = pd.read_csv(tmp_path / "ethucy_forecast.csv")
    assert set(tab.columns) == {"scene", "model", "ade", "fde"} and "avg" not in set(tab.scene)  # only 2 scenes


def test_config_errors():
    for over, field in (
        ({"scenes": ["eth", "mars"]}, "task.scenes"),
        ({"predictors": ["cv", "transformer"]}, "task.predictors"),
        ({"obs_len": 2}, "task.obs_len"),
        ({"lstm.epochs": 0}, "task.lstm.epochs"),
        ({"lstm.dtype": "float16"}, "task.lstm.dtype"),
        ({"gp.points": 1}, "task.gp.points"),
        ({"convention": "wall"}, "task.convention"),
    ):
        with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
            ef.run(_tiny_cfg(**over))
    cfg = _tiny_cfg()
    cfg.device = "cuda"
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="cuda"):
            ef.run(cfg)


def test_published_table_is_consistent():
    # each AVG row is the mean of the five scenes (to the 2 decimals printed)
    for model, d in ef.PUBLISHED_SGAN.items():
        for k in (0, 1):
            mean = sum(d[s][k] for s in ("eth", "hotel", "univ", "zara1", "zara2")) / 5
            assert abs(mean - d["avg"][k]) <= 0.006, (model, k)
