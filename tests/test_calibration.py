"""``learner=calibrate`` (dslearn/learning/calibrate.py): a scale of Q and of R fitted by maximum likelihood of the
nodes' innovations, each node alone. The likelihood equals filterpy's Kalman filter's, summed over the same steps;
on a linear-Gaussian problem with known noises the fit recovers them within the statistical error of the sample
(from the observed information); the learner is refused, naming it and the allowed ones, by an engine that
cannot use it; a matrix cell runs with it."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from filterpy.kalman import KalmanFilter

from dslearn import api
from dslearn.episodes import Measurements
from dslearn.errors import ConfigError
from dslearn.filters.ukf import UnscentedPredict
from dslearn.learning import learners as L
from dslearn.learning.calibrate import (CalibrateLearning, ScaledNoise, ScaledSensor, calibrate, counted,
                                        individual_nll)
from dslearn.models.constant_velocity import ConstantVelocity
from dslearn.models.observation import LinearPositionObservation
from dslearn.types import StepContext

DT = 1.0
CTX = StepContext(dt=DT)


def _cv(dt: float = DT) -> np.ndarray:
    f = np.eye(4)
    f[0, 2] = f[1, 3] = dt
    return f


def _simulate(nodes: int, episodes: int, steps: int, agents: int, q_std: float, r_std: float, seed: int,
              see: float = 1.0):
    """Constant-velocity targets with process noise ``N(0, q_std^2 I_4)`` (the structure ConstantVelocity's Q
    has) seen by ``nodes`` sensors with noise ``N(0, r_std^2 I_2)``, each measurement kept with probability
    ``see``. Returns the measurements (float64)."""
    g = np.random.default_rng(seed)
    f = _cv()
    x = np.zeros((episodes, agents, 4))
    x[..., 2:] = g.normal(0.0, 1.0, (episodes, agents, 2))
    states = [x]
    for _ in range(steps):
        x = x @ f.T + q_std * g.normal(size=x.shape)
        states.append(x)
    pos = np.stack(states, 1)[..., :2]  # (B, K+1, A, 2)
    meas = pos[None] + r_std * g.normal(size=(nodes, *pos.shape))
    vis = g.random(meas.shape[:-1]) < see
    meas = np.where(vis[..., None], meas, 0.0)
    return Measurements(torch.tensor(meas), torch.tensor(vis))


def _init(nodes: int, episodes: int, agents: int, mean: torch.Tensor | None = None, var=(1e8, 1e8, 1e8, 1e8)):
    """Every node's initial belief: ``mean`` (zeros) with covariance ``diag(var)`` per target (diffuse default)."""
    dx = 4 * agents
    m = torch.zeros(nodes, episodes, dx, dtype=torch.float64) if mean is None else mean
    info = torch.diag(1.0 / torch.tensor(var, dtype=torch.float64).repeat(agents)).expand(nodes, episodes, dx, dx)
    return m, info.clone()


# ------------------------------------------------------------------------------ the likelihood: filterpy
def _filterpy_nll(ep: Measurements, init, q_var: float, r_var: float, mask: torch.Tensor) -> np.ndarray:
    """The same sum with filterpy: one KalmanFilter per (node, episode, target); predict, update where the node
    measured the target, minus its log-likelihood where ``mask`` counts the innovation. ``(B,)``."""
    s, b, k1, a, _ = ep.meas.shape
    mean, info = init
    out = np.zeros(b)
    for i in range(s):
        for e in range(b):
            cov = torch.linalg.inv(info[i, e]).numpy()
            for j in range(a):
                kf = KalmanFilter(dim_x=4, dim_z=2)
                kf.x = mean[i, e, 4 * j:4 * j + 4].numpy().reshape(4, 1).copy()
                kf.P = cov[4 * j:4 * j + 4, 4 * j:4 * j + 4].copy()
                kf.F, kf.Q = _cv(), q_var * np.eye(4)
                kf.H, kf.R = np.eye(2, 4), r_var * np.eye(2)
                for t in range(1, k1):
                    kf.predict()
                    if bool(ep.visible[i, e, t, j]):
                        kf.update(ep.meas[i, e, t, j].numpy().reshape(2, 1))
                        if bool(mask[i, e, t, j]):
                            out[e] -= float(kf.log_likelihood)
    return out


@pytest.mark.parametrize("step", ["ekf", "ukf"])
def test_the_likelihood_equals_filterpys(step):
    """Two nodes, three episodes, two targets, a third of the measurements missing; Q, R at the configured numbers
    and at scaled ones, the scales one per batch element (as the grid runs them): every episode's innovation NLL
    equals the sum of filterpy's -log-likelihoods over the same (node, target, step) terms. The UKF's step on a
    linear model is exact, so it equals it too."""
    s, b, k, a = 2, 3, 15, 2
    ep = _simulate(s, b, k, a, q_std=0.3, r_std=0.5, seed=1, see=0.7)
    gen = torch.Generator().manual_seed(2)
    init = _init(s, b, a, mean=torch.randn(s, b, 4 * a, generator=gen, dtype=torch.float64),
                 var=(4.0, 4.0, 1.0, 1.0))
    mask = counted(ep.visible, 2)
    assert int(mask.sum()) > 20  # enough terms, some steps missing
    model, obs = ConstantVelocity(a, noise_std=0.3), LinearPositionObservation(0.5)
    predict = UnscentedPredict() if step == "ukf" else None
    ours = individual_nll(model, obs, ep, init, CTX, mask, predict)
    ref = _filterpy_nll(ep, init, 0.09, 0.25, mask)
    np.testing.assert_allclose(ours.numpy(), ref, rtol=1e-9, atol=1e-9)
    # scaled, two scale pairs in one batch (grid-major: the episodes repeated)
    qs = torch.tensor([2.5, 0.1], dtype=torch.float64).repeat_interleave(b)
    rs = torch.tensor([0.3, 4.0], dtype=torch.float64).repeat_interleave(b)
    two = Measurements(ep.meas.repeat(1, 2, 1, 1, 1), ep.visible.repeat(1, 2, 1, 1))
    both = individual_nll(ScaledNoise(model, qs), ScaledSensor(obs, rs), two,
                          (init[0].repeat(1, 2, 1), init[1].repeat(1, 2, 1, 1)), CTX, mask.repeat(1, 2, 1, 1), predict)
    np.testing.assert_allclose(both[:b].numpy(), _filterpy_nll(ep, init, 0.09 * 2.5, 0.25 * 0.3, mask), rtol=1e-9)
    np.testing.assert_allclose(both[b:].numpy(), _filterpy_nll(ep, init, 0.09 * 0.1, 0.25 * 4.0, mask), rtol=1e-9)


def test_counted_innovations_need_the_warmup_steps():
    vis = torch.tensor([True, True, False, True, True, True, True]).view(1, 1, 7, 1)
    assert counted(vis, 2).view(-1).tolist() == [False, False, False, False, False, True, True]
    assert counted(vis, 1).view(-1).tolist() == [False, True, False, False, True, True, True]


# ---------------------------------------------------------------------------------- recovery of Q and R
def _standard_errors(model, obs, ep, init, mask, log_q: float, log_r: float, h: float = 0.05) -> np.ndarray:
    """Standard errors of (log10 s_q, log10 s_r) from the observed information: the inverse Hessian of the
    summed NLL at the estimate, by central differences (step ``h`` decades) on a 3 x 3 stencil."""
    offs = [(dq, dr) for dq in (-h, 0.0, h) for dr in (-h, 0.0, h)]
    b = len(ep)
    qs = torch.tensor([10 ** (log_q + dq) for dq, _ in offs], dtype=torch.float64).repeat_interleave(b)
    rs = torch.tensor([10 ** (log_r + dr) for _, dr in offs], dtype=torch.float64).repeat_interleave(b)
    g = len(offs)
    rep = Measurements(ep.meas.repeat(1, g, 1, 1, 1), ep.visible.repeat(1, g, 1, 1))
    tot = individual_nll(ScaledNoise(model, qs), ScaledSensor(obs, rs), rep,
                         (init[0].repeat(1, g, 1), init[1].repeat(1, g, 1, 1)), CTX, mask.repeat(1, g, 1, 1))
    f = {o: float(v) for o, v in zip(offs, tot.view(g, b).sum(-1))}
    hqq = (f[(h, 0.0)] - 2 * f[(0.0, 0.0)] + f[(-h, 0.0)]) / h**2
    hrr = (f[(0.0, h)] - 2 * f[(0.0, 0.0)] + f[(0.0, -h)]) / h**2
    hqr = (f[(h, h)] - f[(h, -h)] - f[(-h, h)] + f[(-h, -h)]) / (4 * h**2)
    cov = np.linalg.inv(np.array([[hqq, hqr], [hqr, hrr]]))
    return np.sqrt(np.diag(cov))


def test_calibration_recovers_known_noises():
    """100 episodes of 30 steps, one node each (so the terms' likelihood is exact and the episodes independent):
    the model is handed Q = 0.05^2 I and R = 2.5^2 I, the truth is 0.2^2 I and 0.5^2 I (scales 16 and 0.04). The
    fitted log10-scales lie within 4 standard errors (from the observed information of this sample: the inverse
    Hessian of its NLL; about 0.02 and 0.01 decades here) plus the grid's resolution (1/64 decade) of the truth."""
    b, k = 100, 30
    ep = _simulate(1, b, k, 1, q_std=0.2, r_std=0.5, seed=3)
    init = _init(1, b, 1)
    model, obs = ConstantVelocity(1, noise_std=0.05), LinearPositionObservation(2.5)
    cal = calibrate(model, obs, ep, init, CTX, warmup=3)
    est = np.log10([cal.q_scale, cal.r_scale])
    true = np.log10([16.0, 0.04])
    se = _standard_errors(model, obs, ep, init, counted(ep.visible, 3), *est)
    assert np.all(se < 0.05), se  # the sample pins the scales down: the test is sharp
    assert np.all(np.abs(est - true) <= 4 * se + 1 / 64), (est, true, se)
    assert cal.terms == b * (k - 2) and cal.filters == b and cal.nll < cal.nll_hand
    # the fit maximises the likelihood: no neighbour on the last grid's scale does better
    assert cal.history[-1]["nll"] == pytest.approx(cal.nll)


def test_one_scale_alone_and_the_grid_is_relative():
    """``fit: [r]`` with Q at the truth recovers R alone (Q's scale stays 1; R within 0.1 decade, 25 %, from 100
    episodes); a hand-set R 10x larger in std (2 decades in variance: a whole number of the first grid's steps)
    lands on the same fitted R."""
    b, k = 100, 30
    ep = _simulate(1, b, k, 1, q_std=0.2, r_std=0.5, seed=4)
    init = _init(1, b, 1)
    model = ConstantVelocity(1, noise_std=0.2)
    a = calibrate(model, LinearPositionObservation(2.5), ep, init, CTX, fit=("r",), warmup=3)
    c = calibrate(model, LinearPositionObservation(25.0), ep, init, CTX, fit=("r",), warmup=3)
    assert a.q_scale == 1.0 and abs(math.log10(a.r_scale / 0.04)) < 0.1
    assert 2.5**2 * a.r_scale == pytest.approx(25.0**2 * c.r_scale, rel=1e-9)  # the same fitted R


def test_a_scale_the_data_do_not_determine_stays_hand_set():
    """Position process noise 1 m against sensors of 0.05 m: R hardly changes the innovations' spread, so the
    likelihood is nearly flat in it. The maximum itself (tolerance 0) drives R towards 0 (the grid's edge); with the
    tolerance the fit is the point nearest the hand-set numbers among those within 1.92 of the smallest summed NLL:
    R moves less, and its summed NLL is within that margin of the maximum's."""
    b, k = 20, 20
    ep = _simulate(1, b, k, 1, q_std=1.0, r_std=0.05, seed=5)
    init = _init(1, b, 1)
    model, obs = ConstantVelocity(1, noise_std=1.0), LinearPositionObservation(0.05)
    free = calibrate(model, obs, ep, init, CTX, warmup=3, tolerance=0.0)
    kept = calibrate(model, obs, ep, init, CTX, warmup=3)
    assert free.nll == pytest.approx(free.nll_min, abs=1e-12)
    assert abs(math.log10(kept.r_scale)) < abs(math.log10(free.r_scale))
    assert kept.terms == free.terms and (kept.nll - free.nll) * kept.terms <= 1.92  # as likely as the maximum
    assert (kept.nll - kept.nll_min) * kept.terms <= 1.92 + 1e-9


# ------------------------------------------------------------------------------------------- the learner
def test_settings_are_checked():
    assert CalibrateLearning().fit == ["q", "r"] and CalibrateLearning(fit=["r", "q"]).fit == ["q", "r"]
    assert CalibrateLearning(fit="q").label == "calibrate[q]" and CalibrateLearning().label == "calibrate"
    for kw, needle in [({"fit": ["x"]}, "learner.fit=['x']: learner=calibrate fits a non-empty list of ['q', 'r']"),
                       ({"fit": []}, "learner.fit=[]"),
                       ({"fit": ["q", "q"]}, "learner.fit=['q', 'q']"),
                       ({"points": 4}, "learner.points=4 must be odd"),
                       ({"points": 1}, "learner.points=1 must be an integer >= 3"),
                       ({"decades": 0}, "learner.decades=0 must be a number in (0, 30)"),
                       ({"warmup": 0}, "learner.warmup=0 must be an integer >= 1"),
                       ({"tolerance": -1}, "learner.tolerance=-1 must be a number >= 0"),
                       ({"holdout": 1.0}, "learner.holdout=1.0 must be a number >= 0 and < 1")]:
        with pytest.raises(ConfigError) as e:
            CalibrateLearning(**kw)
        assert needle in str(e.value) and "\n" not in str(e.value), str(e.value)


REFUSED = [
    (["method=adf_gp_hybrid"], "learner=calibrate: it scales the process noise that the EKF or UKF prediction "
                               "step takes at the mean (filter=default|ukf), not filter=adf's",
     "allowed: learner=online|none"),
    (["method=ekf_gp_hybrid", "observation=gp"], "learner=calibrate: learner.fit=[r] scales the linear position "
                                                 "sensor's R", "allowed: learner=online|none"),
    (["method=dgpt_rbcm", "scenario=liu_s1"], "learner=calibrate: Liu's DGPT",
     "allowed: learner=online_hyperparameters"),
    (["method=fg_ekf", "scenario=jiang"], "learner=calibrate: Jiang's EKF-FG", "allowed: learner=fg_identification"),
    (["method=rbpf_em", "scenario=braga"], "learner=calibrate: Braga", "allowed: learner=online_em"),
]


@pytest.mark.parametrize("overrides,needle,allowed", REFUSED, ids=[" ".join(o) for o, _, _ in REFUSED])
def test_engines_that_cannot_use_it_refuse_it(overrides, needle, allowed):
    with pytest.raises(L.LearnerRefused) as e:
        api.compose("task=matrix", *overrides, "learner=calibrate")
    msg = str(e.value)
    assert msg.startswith(needle) and allowed in msg and "\n" not in msg, msg


def test_a_matrix_cell_calibrates_then_tracks():
    """A cell of the preset on Liu's S1 (12 m/s targets turning by up to 110 degrees, sensors of 2 m): LIN's
    walkers' Q (0.1^2 I) is far too small there; the fit raises it by more than 10x (about 400x measured,
    experiments/matrix/README.md) and the likelihood improves; the cell's numbers are finite, its row label names
    the learner. With the GP observation model ``fit: [q]`` is accepted (``r`` is refused above)."""
    from dslearn.compose import build_cell_parts, build_study

    cfg = api.compose("task=matrix", "method=ekf_lin_hybrid_calibrated", "scenario=liu_s1", "observation.noise_std=2.0",
                      "task.train_episodes=2", "task.test_episodes=1")
    study = build_study(cfg)
    df = study.run()
    assert set(df["method"]) == {"ekf lin hybrid learner=calibrate"}
    assert np.isfinite(df["value"]).all()
    learned = study.method.learned
    assert learned["terms"] > 0 and learned["nll"] < learned["nll_hand"] and learned["held_out_episodes"] == 0
    assert learned["q_scale"] > 10.0
    _, _, m = build_cell_parts(api.compose("task=matrix", "method=ekf_gp_hybrid", "observation=gp",
                                           "learner=calibrate", "learner.fit=[q]"), check_only=True)
    assert m.learner.fit == ["q"] and m.label.endswith("learner=calibrate[q]")
