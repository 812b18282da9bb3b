"""The nonlinear sensors as observation models (squared range, range, bearing, terrain altitude) and Yu et al.'s
distributed information filter with them on Jiang's and Braga's scenarios: Jacobians against central finite
differences and autograd, the extended information update against filterpy's EKF, the spec checks, end-to-end
cells."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import torch

from dslearn.episodes import Measurements, ScenarioSpec
from dslearn.errors import ConfigError
from dslearn.filters.distributed import first_fix, diffuse_prior
from dslearn.filters.information import novel_information
from dslearn.fusion.strategies import Centralized, HybridConsensus, Individual
from dslearn.models.observation import (BearingObservation, LinearPositionObservation, RangeObservation,
                                        SquaredRangeObservation, TerrainAltitudeObservation, bilinear,
                                        scenario_sensor)

F64 = torch.float64
BIN = Path(sys.executable).parent


def _terrain(seed=0, h=12, w=17, res=25.0):
    g = torch.Generator().manual_seed(seed)
    z = 500 + 80 * torch.randn(h, w, generator=g, dtype=F64)
    return TerrainAltitudeObservation(z, res, 3.0)


def _sensors(kind, seed=0):
    g = torch.Generator().manual_seed(seed)
    pos = 40 * torch.rand(3, 2, generator=g, dtype=F64) - 20
    return {"squared_range": SquaredRangeObservation(pos, 5.0, 4), "range": RangeObservation(pos, 0.5, 2),
            "bearing": BearingObservation(pos, 0.05), "terrain": _terrain(seed)}[kind]


def _points(kind, seed=1):
    """Random target states ``(S=3, B=5, 4)`` ([px, py, vx, vy]); inside the map for the terrain."""
    g = torch.Generator().manual_seed(seed)
    y = torch.randn(3, 5, 4, generator=g, dtype=F64) * torch.tensor([15.0, 15.0, 2.0, 2.0], dtype=F64)
    if kind == "terrain":  # inside the 16 x 11 cells of 25 m
        y[..., 0] = 10 + 380 * torch.rand(3, 5, generator=g, dtype=F64)
        y[..., 1] = 10 + 230 * torch.rand(3, 5, generator=g, dtype=F64)
    return y


KINDS = ("squared_range", "range", "bearing", "terrain")


@pytest.mark.parametrize("kind", KINDS)
def test_jacobian_matches_central_differences_and_autograd(kind):
    obs, y = _sensors(kind), _points(kind)
    jac = obs.jacobian(y)
    assert jac.shape == (3, 5, 1, 4) and jac.dtype == F64
    # central finite differences, entry by entry of the state block
    eps = 1e-5
    fd = torch.zeros_like(jac)
    for k in range(4):
        e = torch.zeros(4, dtype=F64)
        e[k] = eps
        fd[..., 0, k] = ((obs(y + e) - obs(y - e)) / (2 * eps))[..., 0]
    torch.testing.assert_close(jac, fd, rtol=1e-6, atol=1e-7)
    # autograd of forward (the terrain: of the simulator's own bilinear lookup)
    if kind == "terrain":
        from dslearn.sim.terrain import TerrainMap

        fn = TerrainMap(obs.elevation, obs.resolution)
        f = lambda x: fn(x).unsqueeze(-1)  # noqa: E731
    else:
        f = obs
    x = y.clone().requires_grad_(True)
    grad = torch.autograd.grad(f(x).sum(), x)[0]
    torch.testing.assert_close(jac[..., 0, :], grad, rtol=1e-10, atol=1e-12)
    assert (jac[..., 2:] == 0).all()  # a sensor of the position: nothing of the velocity
    # linearize is (forward, jacobian, noise_cov)
    h, C, R = obs.linearize(y)
    torch.testing.assert_close(h, obs(y), rtol=0, atol=0)
    torch.testing.assert_close(C, jac, rtol=0, atol=0)


def test_values_by_hand():
    s = torch.tensor([[0.0, 0.0], [3.0, 0.0], [0.0, 4.0]], dtype=F64)
    y = torch.tensor([[[3.0, 4.0, 1.0, 1.0]]] * 3, dtype=F64)  # (3, 1, 4): the target at (3, 4)
    assert SquaredRangeObservation(s, 2.0, 8)(y).flatten().tolist() == [25.0, 16.0, 9.0]
    assert RangeObservation(s, 2.0)(y).flatten().tolist() == [5.0, 4.0, 3.0]
    b = BearingObservation(s, 0.1)(y).flatten()
    torch.testing.assert_close(b, torch.tensor([math.atan2(4, 3), math.pi / 2, 0.0], dtype=F64))
    # the squared range's L samples averaged: R = sigma^2 / L
    sq = SquaredRangeObservation(s, 2.0, 8)
    assert sq.noise_cov(y).flatten().tolist() == [0.5] * 3
    raw = torch.arange(24, dtype=F64).reshape(3, 1, 1, 8)
    assert sq.reading(raw).flatten().tolist() == [3.5, 11.5, 19.5]
    # the bearing's innovation is wrapped: 3.1 - (-3.1) is -0.083..., not 6.2
    r = BearingObservation(s, 0.1).residual(torch.tensor([3.1], dtype=F64), torch.tensor([-3.1], dtype=F64))
    assert r.item() == pytest.approx(6.2 - 2 * math.pi, abs=1e-12)
    # the terrain: bilinear between the four corners of a cell, the map's own value on its nodes
    z = torch.tensor([[0.0, 10.0], [20.0, 40.0]], dtype=F64)
    h, g = bilinear(z, 5.0, torch.tensor([[2.5, 2.5], [5.0, 0.0], [1.0, 4.0]], dtype=F64))
    assert h[0].item() == pytest.approx(17.5) and h[1].item() == pytest.approx(10.0, abs=1e-6)
    # at (1, 4): fx = 0.2, fy = 0.8: dh/dx = ((10-0)(0.2) + (40-20)(0.8)) / 5, dh/dy = ((20-0)(0.8) + (40-10)(0.2)) / 5
    assert g[2].tolist() == pytest.approx([(10 * 0.2 + 20 * 0.8) / 5, (20 * 0.8 + 30 * 0.2) / 5])
    # beyond the border: the value clamped (the simulator's), no slope across it
    h, g = bilinear(z, 5.0, torch.tensor([[-3.0, 2.5]], dtype=F64))
    assert h.item() == pytest.approx(10.0) and g[0, 0].item() == 0.0 and g[0, 1].item() == pytest.approx(4.0)


def test_extended_information_update_matches_filterpy_ekf():
    """Three squared-range sensors fused centrally, L = 5 samples each, a correlated non-identity prior: the
    information-form update (samples averaged, R = sigma^2 / L) equals filterpy's EKF with the 15 samples stacked."""
    from filterpy.kalman import ExtendedKalmanFilter

    g = torch.Generator().manual_seed(3)
    sensors = torch.tensor([[-30.0, 50.0], [10.0, 5.0], [60.0, 20.0]], dtype=F64)
    sigma, L = 5.0, 5
    x_true = torch.tensor([7.0, 2.0, 0.3, -0.2], dtype=F64)
    x_bar = torch.tensor([7.8, 1.1, 0.0, 0.5], dtype=F64)  # the prediction, off the truth
    A = torch.randn(4, 4, generator=g, dtype=F64)
    P = A @ A.T + torch.diag(torch.tensor([0.5, 0.8, 0.2, 0.3], dtype=F64))  # correlated, position and velocity
    obs = SquaredRangeObservation(sensors, sigma, L)
    samples = (sensors - x_true[:2]).square().sum(-1).unsqueeze(-1) + sigma * torch.randn(3, L, generator=g,
                                                                                              dtype=F64)
    meas = samples.reshape(3, 1, 1, L)  # (S, B, A, channels)
    omega = torch.linalg.inv(P)
    q_pred = (omega @ x_bar).expand(3, 1, 4)
    o_pred = omega.expand(3, 1, 4, 4)
    dq, do = novel_information(x_bar.expand(3, 1, 4), meas, torch.ones(3, 1, 1, dtype=torch.bool), obs)
    q, o = Centralized(torch.eye(3, dtype=F64))(q_pred, o_pred, dq, do)
    mean = torch.linalg.solve(o[0, 0], q[0, 0])
    cov = torch.linalg.inv(o[0, 0])

    ekf = ExtendedKalmanFilter(dim_x=4, dim_z=3 * L)
    ekf.x = x_bar.numpy().reshape(4, 1).copy()
    ekf.P = P.numpy().copy()
    ekf.R = sigma**2 * torch.eye(3 * L, dtype=F64).numpy()
    rows = lambda x: torch.as_tensor(x, dtype=F64).flatten()  # noqa: E731

    def hx(x):
        return (sensors - rows(x)[:2]).square().sum(-1).repeat_interleave(L).numpy().reshape(-1, 1)

    def hjac(x):
        j = torch.zeros(3, 4, dtype=F64)
        j[:, :2] = 2 * (rows(x)[:2] - sensors)
        return j.repeat_interleave(L, 0).numpy()

    ekf.update(samples.reshape(-1, 1).numpy(), hjac, hx)
    torch.testing.assert_close(mean, torch.as_tensor(ekf.x, dtype=F64).flatten(), rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(cov, torch.as_tensor(ekf.P, dtype=F64), rtol=1e-8, atol=1e-10)
    # every term matters: the update moved the mean and shrank the position's covariance
    assert (mean - x_bar).abs()[:2].min() > 1e-2 and torch.linalg.det(cov) < 1e-3 * torch.linalg.det(P)


@pytest.mark.parametrize("kind", ["squared_range", "bearing"])
def test_unscented_update_matches_filterpy_ukf(kind):
    """One sensor (squared range with L = 5 samples, or a bearing), a correlated prior: the statistical
    linearisation in the information update equals filterpy's UKF update with the same sigma points (alpha = 1,
    beta = 2, kappa = 0; for the squared range the 5 samples stacked); and it differs from the extended update."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    from dslearn.filters.ukf import UnscentedPredict

    g = torch.Generator().manual_seed(5)
    sensor = torch.tensor([[10.0, 5.0]], dtype=F64)
    L = 5 if kind == "squared_range" else 1
    sigma = 5.0 if kind == "squared_range" else 0.05
    obs = SquaredRangeObservation(sensor, sigma, L) if kind == "squared_range" else BearingObservation(sensor, sigma)
    x_bar = torch.tensor([7.8, 1.1, 0.0, 0.5], dtype=F64)
    A = torch.randn(4, 4, generator=g, dtype=F64)
    P = A @ A.T + torch.diag(torch.tensor([0.5, 0.8, 0.2, 0.3], dtype=F64))
    x_true = torch.tensor([7.0, 2.0, 0.3, -0.2], dtype=F64)
    z1 = obs(x_true.reshape(1, 4))[0]
    samples = z1 + sigma * torch.randn(L, generator=g, dtype=F64)
    omega = torch.linalg.inv(P).reshape(1, 1, 4, 4)
    y = x_bar.reshape(1, 1, 4)
    step = UnscentedPredict()
    lin = step.observation_linearization(obs, y, omega, 1)
    meas = samples.reshape(1, 1, 1, L)
    vis = torch.ones(1, 1, 1, dtype=torch.bool)
    dq, do = novel_information(y, meas, vis, obs, linearized=lin)
    q, o = Individual(torch.eye(1, dtype=F64))((omega @ y.unsqueeze(-1)).squeeze(-1), omega, dq, do)
    mean, cov = torch.linalg.solve(o[0, 0], q[0, 0]), torch.linalg.inv(o[0, 0])

    def hx(x):
        return obs(torch.as_tensor(x, dtype=F64).reshape(1, 4))[0].repeat(L).numpy()

    ukf = UnscentedKalmanFilter(dim_x=4, dim_z=L, dt=1.0, hx=hx, fx=lambda x, dt: x,
                                points=MerweScaledSigmaPoints(4, alpha=1.0, beta=2.0, kappa=0.0))
    if kind == "bearing":  # the UKF's own residual, wrapped
        ukf.residual_z = lambda a, b: (a - b + math.pi) % (2 * math.pi) - math.pi
    ukf.x, ukf.P, ukf.Q = x_bar.numpy().copy(), P.numpy().copy(), torch.zeros(4, 4, dtype=F64).numpy()
    ukf.R = sigma**2 * torch.eye(L, dtype=F64).numpy()
    ukf.predict()  # the identity with Q = 0: the sigma points of the prior, the prior unchanged
    ukf.update(samples.numpy())
    torch.testing.assert_close(mean, torch.as_tensor(ukf.x, dtype=F64), rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(cov, torch.as_tensor(ukf.P, dtype=F64), rtol=1e-8, atol=1e-10)
    ext_q, _ = novel_information(y, meas, vis, obs)
    assert (ext_q - dq).abs().max() > 1e-6 * dq.abs().max()  # the statistical linearisation is not the Jacobian's


def test_first_fix_finds_the_source_from_the_diffuse_prior():
    """Jiang's sensors, the source 40 m from where the diffuse prior puts it: the iterated update of the first two
    readings fixes its position and velocity (Gauss-Newton from far off)."""
    sensors = torch.tensor([[-30.0, 50.0], [10.0, 5.0], [60.0, 20.0]], dtype=F64)
    obs = SquaredRangeObservation(sensors, 1e-3, 1)
    p0, p1 = torch.tensor([6.0, 0.1], dtype=F64), torch.tensor([6.5, -0.3], dtype=F64)
    z = torch.stack([(sensors - p).square().sum(-1) for p in (p0, p1)], 1)  # (3, 2)
    meas = Measurements(z.reshape(3, 1, 2, 1, 1), torch.ones(3, 1, 2, 1, dtype=torch.bool))
    m0, o0 = diffuse_prior(1, (-40.0, 70.0, -10.0, 60.0), 1000.0, 1000.0, (3, 1), F64, "cpu")
    mean, info = first_fix(meas, 0.5, Centralized(torch.eye(3, dtype=F64)), obs, m0, o0)
    torch.testing.assert_close(mean[0, 0], torch.tensor([6.0, 0.1, 1.0, -0.8], dtype=F64), rtol=0, atol=1e-6)
    assert info.shape == (3, 1, 4, 4) and bool((torch.linalg.eigvalsh(info) > 0).all())


# ------------------------------------------------------------------------------------------------------------------
# the scenario's declared spec decides


def test_declared_measurement_picks_or_refuses_the_observation_model():
    jiang = ScenarioSpec("jiang", "squared_range", 1, "param2d", 1.0, 49, networked=False)
    braga = ScenarioSpec("braga", "terrain_altitude", 4, "platform", 0.05, 60, kind="self")
    yu = ScenarioSpec("yu", "position", 2, "pv2d", 0.1, 50)
    assert "scenario jiang measures squared_range (observation=sensor" in LinearPositionObservation.spec_misfit(jiang)
    assert LinearPositionObservation.spec_misfit(yu) is None
    assert SquaredRangeObservation.spec_misfit(jiang) is None
    assert "observation=squared_range explains squared_range readings; scenario braga measures terrain_altitude" \
        in SquaredRangeObservation.spec_misfit(braga)
    assert TerrainAltitudeObservation.spec_misfit(braga) is None
    assert "observation=terrain" in TerrainAltitudeObservation.spec_misfit(yu)
    for spec in (jiang, braga, yu):
        assert scenario_sensor.spec_misfit(spec) is None
    assert "no model of sonar readings" in scenario_sensor.spec_misfit(ScenarioSpec("x", "sonar", 1, "pv2d", 1.0, 3))
    # the fusions: consensus needs a graph, and nodes that share targets
    assert "the sensors of scenario jiang have none" in HybridConsensus.spec_misfit(jiang)
    assert "every node navigates itself" in HybridConsensus.spec_misfit(braga)
    assert HybridConsensus.spec_misfit(yu) is None
    for cls in (Individual, Centralized):
        assert cls.spec_misfit(jiang) is None and cls.spec_misfit(braga) is None


def test_scenario_sensor_builds_the_scenarios_own_model():
    from dslearn.sim.jiang import SquaredRangeScenario

    sc = SquaredRangeScenario(num_samples=7, sigma_y=2.0)
    obs = scenario_sensor(None, scenario=sc, network=sc.network)
    assert isinstance(obs, SquaredRangeObservation) and obs.samples == 7 and obs.noise_std == 2.0
    torch.testing.assert_close(obs.sensors, sc.sensors)
    assert scenario_sensor(0.5, scenario=sc, network=sc.network).noise_std == 0.5  # a deliberate mismatch


@pytest.mark.parametrize("build, field", [
    (lambda: SquaredRangeObservation(torch.zeros(3, 2), -1.0), "observation.noise_std"),
    (lambda: SquaredRangeObservation(torch.zeros(3, 2), 1.0, 0), "observation.samples"),
    (lambda: RangeObservation(torch.zeros(3, 3), 1.0), "network.positions"),
    (lambda: BearingObservation(torch.zeros(3, 2), 0.1, 4), "observation=bearing reads one sample"),
    (lambda: TerrainAltitudeObservation(torch.zeros(5), 25.0, 1.0), "the terrain map must be a (H, W) grid"),
    (lambda: TerrainAltitudeObservation(torch.zeros(5, 5), 0.0, 1.0), "scenario.terrain.resolution_m"),
    (lambda: TerrainAltitudeObservation(torch.zeros(5, 5), 25.0, float("nan")), "observation.noise_std"),
])
def test_bad_input_is_refused_naming_the_field(build, field):
    with pytest.raises(ConfigError, match=field.replace("(", r"\(").replace(")", r"\)").replace(".", r"\.")):
        build()


# ------------------------------------------------------------------------------------------------------------------
# end to end: dslearn-run task=matrix


def _run(tmp_path, *overrides):
    env = {**os.environ, "DSLEARN_CACHE_DIR": "off"}
    out = tmp_path / "run"
    cmd = [str(BIN / "dslearn-run"), "task=matrix", *overrides, "task.train_episodes=2", "task.test_episodes=2",
           f"hydra.run.dir={out}"]
    r = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    return r, out


@pytest.mark.parametrize("method, scenario, extra, bound", [
    # Jiang: a filter that ignored the readings and followed the drift's mean would err by the drive noise,
    # sqrt(2 * 0.5) = 1 m over the two coordinates; the fused squared ranges (3 sensors x 60 samples) do better
    ("ekf_lin_centralized", "jiang", [], 1.0),
    ("ukf_lin_centralized", "jiang", [], 1.0),
    # Braga: each aircraft stays nearer its own track than half the formation's spacing (50 m) on a map whose
    # relief varies over 250 m (the smoothing)
    ("ekf_lin_individual", "braga", ["scenario.steps=60"], 50.0),
    ("ukf_lin_individual", "braga", ["scenario.steps=60"], 50.0),
])
def test_lin_presets_run_on_jiang_and_braga(tmp_path, method, scenario, extra, bound):
    r, out = _run(tmp_path, f"method={method}", f"scenario={scenario}", *extra)
    assert r.returncode == 0, r.stderr[-2000:]
    df = pd.read_csv(out / "results.csv")
    rmse = df[df["metric"] == "rmse"]["value"]
    assert len(rmse) > 0 and rmse.map(math.isfinite).all()
    assert rmse.max() < bound, rmse.describe()
    if scenario == "braga":  # every platform by its own node's filter
        assert set(df[df["metric"] == "rmse"]["node"]) == {"onboard"}
    else:
        assert set(df[df["metric"] == "rmse"]["node"]) == {"sensor1", "sensor2", "sensor3"}


@pytest.mark.parametrize("overrides, reason", [
    (["method=ekf_lin_individual", "observation=linear", "scenario=jiang"],
     "observation=linear explains readings of the targets' positions; scenario jiang measures squared_range"),
    (["method=ekf_lin_individual", "scenario=jiang"], "every node fuses only its own readings"),
    (["method=ekf_lin_hybrid", "scenario=jiang"], "the sensors of scenario jiang have none"),
    (["method=ukf_lin_hybrid", "scenario=braga"], "every node navigates itself"),
])
def test_cells_that_cannot_run_are_refused_with_the_reason(tmp_path, overrides, reason):
    r, _ = _run(tmp_path, *overrides)
    assert r.returncode == 2 and reason in r.stderr, r.stderr[-2000:]
