"""Data association (dslearn.association) by value: gating, GNN, JPDA and the PDA update against hand
computations at a 1-track 2-detection size and against Stone Soup (a test-only oracle: those tests skip when
it is not installed) on identical single-node inputs; the labels given; track management."""

from __future__ import annotations

import datetime
import importlib.util
import math

import numpy as np
import pytest
import torch
from scipy.stats import chi2

from dslearn.association import (GNN, JPDA, Associator, LabelsGiven, TrackManager, TrackManagerSettings,
                                 gate_threshold, kalman_update, predict_measurement)
from dslearn.association.jpda import marginals
from dslearn.errors import ConfigError
from dslearn.models.base import ObservationModel
from dslearn.models.observation import LinearPositionObservation

D = torch.float64


class LinearModel(ObservationModel):
    """z = H x + v, v ~ N(0, R), any H and R (a test's sensor)."""

    linear = True

    def __init__(self, h, r):
        super().__init__()
        self.h, self.r = torch.as_tensor(h, dtype=D), torch.as_tensor(r, dtype=D)
        self.meas_dim = self.h.shape[0]

    def forward(self, y):
        return y @ self.h.T

    def jacobian(self, y):
        return self.h.expand(*y.shape[:-1], *self.h.shape)

    def noise_cov(self, y):
        return self.r.expand(*y.shape[:-1], *self.r.shape)


H2 = [[1.0, 0, 0, 0], [0, 0, 1.0, 0]]  # state [px, vx, py, vy] (Stone Soup's CV layout)
R2 = [[0.5, 0.1], [0.1, 0.3]]


def one_track():
    mean = torch.tensor([[1.0, 0.5, 2.0, -0.3]], dtype=D)
    a = torch.tensor([[1.0, 0.2, 0.1, 0.0], [0.0, 0.5, 0.0, 0.1], [0.3, 0.0, 0.8, 0.2], [0.0, 0.1, 0.0, 0.4]], dtype=D)
    cov = (a @ a.T + 0.1 * torch.eye(4, dtype=D)).unsqueeze(0)
    det = torch.tensor([[1.4, 1.7], [0.2, 2.9]], dtype=D)
    return mean, cov, det


# ---- by hand: one track, two detections --------------------------------------------------------


def test_hand_one_track_two_detections():
    mean, cov, det = one_track()
    obs = LinearModel(H2, R2)
    pd, lam, pg = 0.8, 0.05, 0.999
    h, r, p, x = np.array(H2), np.array(R2), cov[0].numpy(), mean[0].numpy()
    s = h @ p @ h.T + r
    si = np.linalg.inv(s)
    k = p @ h.T @ si
    nus = [z - h @ x for z in det.numpy()]
    lik = [pd * math.exp(-0.5 * v @ si @ v) / (2 * math.pi * math.sqrt(np.linalg.det(s))) / lam for v in nus]
    miss = 1 - pd * pg
    tot = miss + sum(lik)
    beta0, beta = miss / tot, np.array(lik) / tot
    # the updated Gaussian as the mixture of the three posteriors (missed, detection 1, detection 2), moment matched
    comps = [(x, p)] + [(x + k @ v, p - k @ s @ k.T) for v in nus]
    w = np.array([beta0, *beta])
    m_ref = sum(wi * c[0] for wi, c in zip(w, comps))
    p_ref = sum(wi * (c[1] + np.outer(c[0] - m_ref, c[0] - m_ref)) for wi, c in zip(w, comps))
    # both detections are inside a 0.999 gate
    d2 = [v @ si @ v for v in nus]
    assert max(d2) < chi2.ppf(pg, 2)

    a = JPDA(pd, lam, pg).associate(mean, cov, obs, det)
    assert a.missed[0].item() == pytest.approx(beta0, abs=1e-12)
    np.testing.assert_allclose(a.weights[0].numpy(), beta, atol=1e-12)
    np.testing.assert_allclose(a.mean[0].numpy(), m_ref, atol=1e-12)
    np.testing.assert_allclose(a.cov[0].numpy(), p_ref, atol=1e-12)
    assert a.mean.dtype == D and a.cov.dtype == D

    # GNN (likelihood): the detection of largest likelihood ratio unless a miss scores more
    g = GNN(pd, lam, pg).associate(mean, cov, obs, det)
    best = int(np.argmax(lik)) if max(lik) > miss else -1
    assert g.assigned.tolist() == [best]
    np.testing.assert_allclose(g.mean[0].numpy(), comps[1 + best][0], atol=1e-12)
    np.testing.assert_allclose(g.cov[0].numpy(), comps[1 + best][1], atol=1e-12)
    assert g.unassigned.tolist() == [best != 0, best != 1]
    # GNN (Mahalanobis): the nearer detection
    gm = GNN(pd, lam, pg, cost="mahalanobis").associate(mean, cov, obs, det)
    assert gm.assigned.tolist() == [int(np.argmin(d2))]

    # a clutter density so high that a miss is the best hypothesis: GNN leaves the track as predicted
    g = GNN(pd, 1e6, pg).associate(mean, cov, obs, det)
    assert g.assigned.tolist() == [-1] and torch.equal(g.mean, mean) and torch.equal(g.cov, cov)
    assert g.unassigned.tolist() == [True, True]


def test_gate_excludes_far_detection():
    mean, cov, det = one_track()
    obs = LinearModel(H2, R2)
    far = torch.cat([det, torch.tensor([[40.0, -30.0]], dtype=D)])
    a = JPDA(0.8, 0.05, 0.99).associate(mean, cov, obs, far)
    assert a.gated.tolist() == [[True, True, False]]
    assert a.weights[0, 2].item() == 0.0 and a.unassigned.tolist() == [False, False, True]
    b = JPDA(0.8, 0.05, 0.99).associate(mean, cov, obs, det)
    np.testing.assert_allclose(a.mean.numpy(), b.mean.numpy(), atol=1e-13)
    # an absent detection (mask) is in no gate
    c = JPDA(0.8, 0.05, 0.99).associate(mean, cov, obs, det, present=torch.tensor([True, False]))
    assert c.gated.tolist() == [[True, False]]
    assert gate_threshold(0.99, 2) == pytest.approx(-2 * math.log(0.01))  # chi-square, 2 dof: -2 ln(1 - P_G)
    assert gate_threshold(1.0, 2) == math.inf


def test_jpda_brute_force_two_tracks_and_independent_clusters():
    # two tracks sharing detections: marginals against a brute-force sum over all joint events
    gen = np.random.default_rng(0)
    score = gen.normal(size=(2, 3))
    gated = np.array([[True, True, False], [True, True, True]])
    miss = math.log(0.2)
    beta, beta0 = marginals(score, miss, gated)
    events = [(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1, 2) if a < 0 or a != b]
    w = np.array([math.exp((miss if a < 0 else score[0, a]) + (miss if b < 0 else score[1, b])) for a, b in events])
    w /= w.sum()
    ref = np.zeros((2, 3))
    ref0 = np.zeros(2)
    for (a, b), we in zip(events, w):
        for i, j in ((0, a), (1, b)):
            if j < 0:
                ref0[i] += we
            else:
                ref[i, j] += we
    np.testing.assert_allclose(beta, ref, atol=1e-14)
    np.testing.assert_allclose(beta0, ref0, atol=1e-14)
    # a second, far cluster leaves the first one's result unchanged
    mean, cov, det = one_track()
    obs = LinearModel(H2, R2)
    mean2 = torch.cat([mean, mean + torch.tensor([100.0, 0, 100.0, 0], dtype=D)])
    cov2 = torch.cat([cov, cov])
    det2 = torch.cat([det, det + 100.0])
    one = JPDA(0.8, 0.05, 0.99).associate(mean, cov, obs, det)
    two = JPDA(0.8, 0.05, 0.99).associate(mean2, cov2, obs, det2)
    np.testing.assert_allclose(two.weights[0, :2].numpy(), one.weights[0].numpy(), atol=1e-14)
    np.testing.assert_allclose(two.weights[1, 2:].numpy(), one.weights[0].numpy(), atol=1e-14)
    np.testing.assert_allclose(two.mean[0].numpy(), one.mean[0].numpy(), atol=1e-13)


def test_permuting_detections_permutes_weights():
    mean, cov, det = one_track()
    obs = LinearModel(H2, R2)
    a = JPDA(0.8, 0.05, 0.99).associate(mean, cov, obs, det)
    b = JPDA(0.8, 0.05, 0.99).associate(mean, cov, obs, det.flip(0))
    np.testing.assert_allclose(b.weights.flip(1).numpy(), a.weights.numpy(), atol=1e-14)
    np.testing.assert_allclose(b.cov.numpy(), a.cov.numpy(), atol=1e-13)


def test_labels_given_passes_measurements_through():
    obs = LinearPositionObservation(0.2)
    mean = torch.tensor([[0.0, 0.0, 1.0, 0.0], [5.0, 5.0, 0.0, 1.0]], dtype=D)
    cov = torch.eye(4, dtype=D).expand(2, 4, 4).clone()
    z = torch.tensor([[0.1, -0.1], [5.2, 4.9]], dtype=D)
    lg = LabelsGiven()
    out, mask = lg.measurements(z)
    assert out is z and mask is None
    a = lg.associate(mean, cov, obs, z, present=torch.tensor([True, False]))
    assert a.weights.tolist() == [[1.0, 0.0], [0.0, 0.0]] and a.assigned.tolist() == [0, -1]
    pred = predict_measurement(mean, cov, obs)
    m, p = kalman_update(mean, cov, pred, z - mean[:, :2])
    assert torch.equal(a.mean[0], m[0]) and torch.equal(a.cov[0], p[0])
    assert torch.equal(a.mean[1], mean[1]) and torch.equal(a.cov[1], cov[1])
    for assoc in (lg, GNN(), JPDA()):
        assert isinstance(assoc, Associator)


def test_bad_settings_named():
    with pytest.raises(ConfigError, match="associator.detection_probability"):
        JPDA(detection_probability=1.0)
    with pytest.raises(ConfigError, match="associator.clutter_density"):
        GNN(clutter_density=0)
    with pytest.raises(ConfigError, match="associator.gate_probability"):
        GNN(gate_probability=1.5)
    with pytest.raises(ConfigError, match="associator.cost"):
        GNN(cost="euclid")
    with pytest.raises(ConfigError, match="tracks.initiation"):
        TrackManagerSettings(initiation="one_point")
    with pytest.raises(ConfigError, match="tracks.confirm_m"):
        TrackManagerSettings(initiation="single_point", confirm_m=4, confirm_n=3)
    with pytest.raises(ConfigError, match="tracks.delete_after"):
        TrackManagerSettings(delete_after=0)
    mean, cov, det = one_track()
    with pytest.raises(ConfigError, match="present"):
        JPDA().associate(mean, cov, LinearModel(H2, R2), det, present=torch.tensor([True]))


# ---- track management --------------------------------------------------------------------------


def test_two_point_initiation_and_deletion():
    obs = LinearPositionObservation(0.2)
    r = 0.04
    tm = TrackManager(TrackManagerSettings(initiation="two_point", delete_after=2, max_speed=2.0, dt=0.5))
    tm.step(None, torch.tensor([[0.0, 0.0], [10.0, 10.0]], dtype=D), obs)
    assert len(tm) == 0
    # (0.5, 0.5) is 0.71 from (0, 0), within 2 m/s * 0.5 s; (13, 10) is 3 m from (10, 10): beyond
    tm.step(None, torch.tensor([[0.5, 0.5], [13.0, 10.0]], dtype=D), obs)
    assert len(tm) == 1 and tm.confirmed.tolist() == [True] and tm.ids.tolist() == [0]
    np.testing.assert_allclose(tm.mean[0].numpy(), [0.5, 0.5, 1.0, 1.0])
    ref = np.zeros((4, 4))
    ref[:2, :2] = r * np.eye(2)
    ref[:2, 2:] = ref[2:, :2] = r / 0.5 * np.eye(2)
    ref[2:, 2:] = 2 * r / 0.25 * np.eye(2)
    np.testing.assert_allclose(tm.cov[0].numpy(), ref, atol=1e-15)
    # two missed steps delete it (delete_after = 2); JPDA with nothing in the gate (the far detections, 50 m
    # apart, start no track either)
    jp = JPDA(0.9, 1e-3, 0.99)
    for k in range(2):
        assert len(tm) == 1
        far = torch.tensor([[100.0 + 50 * k, 100.0]], dtype=D)
        a = jp.associate(tm.mean, tm.cov, obs, far)
        assert a.assigned.tolist() == [-1] and a.unassigned.tolist() == [True]
        tm.step(a, far, obs)
    assert len(tm) == 0


def test_m_of_n_confirmation():
    obs = LinearPositionObservation(0.2)
    tm = TrackManager(TrackManagerSettings(initiation="single_point", confirm_m=2, confirm_n=3, max_speed=2.0))
    tm.step(None, torch.tensor([[0.0, 0.0]], dtype=D), obs)
    assert len(tm) == 1 and tm.confirmed.tolist() == [False]
    np.testing.assert_allclose(tm.cov[0].diagonal().numpy(), [0.04, 0.04, 1.0, 1.0])
    gnn = GNN(0.9, 1e-3, 0.99)
    a = gnn.associate(tm.mean, tm.cov, obs, torch.tensor([[0.3, 0.1]], dtype=D))
    tm.step(a, torch.tensor([[0.3, 0.1]], dtype=D), obs)
    assert tm.confirmed.tolist() == [True] and tm.hits.tolist() == [2]
    # a tentative track missed twice in its first 3 steps cannot reach 2 of 3: deleted at once
    tm2 = TrackManager(TrackManagerSettings(initiation="single_point", confirm_m=2, confirm_n=3))
    tm2.step(None, torch.tensor([[0.0, 0.0]], dtype=D), obs)
    none = torch.zeros(0, 2, dtype=D)
    a = gnn.associate(tm2.mean, tm2.cov, obs, none)
    tm2.step(a, none, obs)
    assert len(tm2) == 1  # 1 of 2, can still make 2 of 3
    a = gnn.associate(tm2.mean, tm2.cov, obs, none)
    tm2.step(a, none, obs)
    assert len(tm2) == 0


# ---- against Stone Soup ------------------------------------------------------------------------

#: the comparisons with Stone Soup (a test-only oracle) run where it is installed; the tests above run everywhere
needs_stonesoup = pytest.mark.skipif(importlib.util.find_spec("stonesoup") is None,
                                     reason="Stone Soup (a test-only oracle, pip install stonesoup) is not installed")

T0 = datetime.datetime(2020, 1, 1)


def _scene(seed=0):
    """Three tracks with non-identity covariances, two of them close (they share detections), and detections
    near them plus clutter; Stone Soup's objects and the same numbers as tensors."""
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.types.detection import Detection
    from stonesoup.types.state import GaussianState
    from stonesoup.types.track import Track

    gen = np.random.default_rng(seed)
    means = np.array([[0.0, 1.0, 0.0, 0.5], [1.5, -0.5, 0.8, 0.2], [10.0, 0.0, -5.0, 1.0]])
    covs = []
    for _ in range(3):
        a = gen.normal(size=(4, 4)) * 0.5
        covs.append(a @ a.T + 0.2 * np.eye(4))
    covs = np.array(covs)
    meas_model = LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=np.array(R2))
    zs = np.array([[0.3, 0.2], [1.2, 0.9], [0.9, 0.4], [10.4, -5.5], [4.0, 4.0], [-3.0, 2.5]])
    tracks = [Track([GaussianState(m.reshape(-1, 1), c, timestamp=T0)]) for m, c in zip(means, covs)]
    dets = [Detection(z.reshape(-1, 1), timestamp=T0, measurement_model=meas_model) for z in zs]
    return tracks, dets, torch.from_numpy(means), torch.from_numpy(covs), torch.from_numpy(zs)


def _ss_parts(pd, lam, pg):
    from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel, ConstantVelocity
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.updater.kalman import KalmanUpdater
    from stonesoup.hypothesiser.probability import PDAHypothesiser

    trans = CombinedLinearGaussianTransitionModel([ConstantVelocity(0.1), ConstantVelocity(0.1)])
    predictor = KalmanPredictor(trans)
    updater = KalmanUpdater(measurement_model=None)
    hyp = PDAHypothesiser(predictor=predictor, updater=updater, clutter_spatial_density=lam, prob_detect=pd,
                          prob_gate=pg)
    return predictor, updater, hyp


@needs_stonesoup
@pytest.mark.parametrize("pd,lam,pg", [(0.8, 0.05, 0.99), (0.6, 0.3, 0.95), (0.95, 0.01, 0.999)])
def test_jpda_against_stonesoup(pd, lam, pg):
    from stonesoup.dataassociator.probability import JPDA as SSJPDA
    from stonesoup.updater.probability import PDAUpdater

    tracks, dets, means, covs, zs = _scene()
    _, _, hyp = _ss_parts(pd, lam, pg)
    ss = SSJPDA(hypothesiser=hyp).associate(tracks, set(dets), T0)
    # the predictions Stone Soup associates with (zero time step: the tracks' own states)
    pm = torch.from_numpy(np.array([np.asarray(ss[t][0].prediction.state_vector, float).ravel() for t in tracks]))
    pc = torch.from_numpy(np.array([np.asarray(ss[t][0].prediction.covar, float) for t in tracks]))
    np.testing.assert_allclose(pm.numpy(), means.numpy(), atol=1e-12)
    ours = JPDA(pd, lam, pg).associate(pm, pc, LinearModel(H2, R2), zs)
    worst = {"beta": 0.0, "mean": 0.0, "cov": 0.0}
    for i, t in enumerate(tracks):
        ref_w = np.zeros(len(dets))
        for h in ss[t]:
            if h:
                ref_w[dets.index(h.measurement)] = float(h.probability)
            else:
                worst["beta"] = max(worst["beta"], abs(float(h.probability) - ours.missed[i].item()))
        worst["beta"] = max(worst["beta"], np.abs(ref_w - ours.weights[i].numpy()).max())
        for gm in (True, False):
            upd = PDAUpdater(measurement_model=dets[0].measurement_model, gm_method=gm).update(ss[t])
            worst["mean"] = max(worst["mean"], np.abs(np.asarray(upd.state_vector, float).ravel() - ours.mean[i].numpy()).max())
            worst["cov"] = max(worst["cov"], np.abs(np.asarray(upd.covar, float) - ours.cov[i].numpy()).max())
    # the two near tracks share detections (a cluster), the far one has its own
    assert ours.gated[:2, :3].any(0).all() and ours.gated[2].tolist() == [False, False, False, True, False, False]
    print("JPDA vs Stone Soup max abs differences", worst)
    assert max(worst.values()) < 1e-9


@needs_stonesoup
@pytest.mark.parametrize("pd,lam,pg", [(0.8, 0.05, 0.99), (0.6, 0.3, 0.95)])
def test_gnn_likelihood_is_stonesoup_jpda_best_joint_event(pd, lam, pg):
    # GNN's likelihood cost picks the joint event of largest probability: Stone Soup's JPDA enumerates them
    from stonesoup.dataassociator.probability import JPDA as SSJPDA
    from stonesoup.updater.kalman import KalmanUpdater

    tracks, dets, means, covs, zs = _scene()
    _, _, hyp = _ss_parts(pd, lam, pg)
    ssj = SSJPDA(hypothesiser=hyp)
    multi = ssj.generate_hypotheses(tracks, set(dets), T0)
    joint = ssj.enumerate_JPDA_hypotheses(tracks, multi)
    best = max(joint, key=lambda j: float(j.probability))
    ref = [dets.index(best.hypotheses[t].measurement) if best.hypotheses[t] else -1 for t in tracks]
    ours = GNN(pd, lam, pg).associate(means, covs, LinearModel(H2, R2), zs)
    assert ours.assigned.tolist() == ref
    up = KalmanUpdater(measurement_model=None)
    worst = 0.0
    for i, t in enumerate(tracks):
        h = best.hypotheses[t]
        st = up.update(h) if h else h.prediction
        worst = max(worst, np.abs(np.asarray(st.state_vector, float).ravel() - ours.mean[i].numpy()).max(),
                    np.abs(np.asarray(st.covar, float) - ours.cov[i].numpy()).max())
    print("GNN (likelihood) vs Stone Soup max abs difference", worst)
    assert worst < 1e-9


@needs_stonesoup
@pytest.mark.parametrize("pg", [0.95, 0.99])
def test_gnn_mahalanobis_against_stonesoup(pg):
    from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
    from stonesoup.hypothesiser.distance import DistanceHypothesiser
    from stonesoup.measures import Mahalanobis
    from stonesoup.updater.kalman import KalmanUpdater

    tracks, dets, means, covs, zs = _scene()
    predictor, updater, _ = _ss_parts(0.9, 0.01, pg)
    hyp = DistanceHypothesiser(predictor, updater, measure=Mahalanobis(), missed_distance=math.sqrt(chi2.ppf(pg, 2)))
    ss = GNNWith2DAssignment(hyp).associate(tracks, set(dets), T0)
    ref = [dets.index(ss[t].measurement) if ss[t] else -1 for t in tracks]
    ours = GNN(0.9, 0.01, pg, cost="mahalanobis").associate(means, covs, LinearModel(H2, R2), zs)
    assert ours.assigned.tolist() == ref
    assert sum(r >= 0 for r in ref) >= 2
    up = KalmanUpdater(measurement_model=None)
    worst = 0.0
    for i, t in enumerate(tracks):
        st = up.update(ss[t]) if ss[t] else ss[t].prediction
        worst = max(worst, np.abs(np.asarray(st.state_vector, float).ravel() - ours.mean[i].numpy()).max(),
                    np.abs(np.asarray(st.covar, float) - ours.cov[i].numpy()).max())
    print("GNN (Mahalanobis) vs Stone Soup max abs difference", worst)
    assert worst < 1e-9


# ---- JPDA's marginals by belief propagation (Williams and Lau 2014) ---------------------------------


def _brute_force(score, miss, gated):
    """Every joint event of one cluster summed by hand (a reference independent of the library's enumeration)."""
    import itertools
    t, m = gated.shape
    choices = [[-1] + [j for j in range(m) if gated[i, j]] for i in range(t)]
    beta, beta0, total = np.zeros((t, m)), np.zeros(t), 0.0
    for e in itertools.product(*choices):
        used = [j for j in e if j >= 0]
        if len(used) != len(set(used)):
            continue
        w = math.exp(sum(miss if j < 0 else score[i, j] for i, j in enumerate(e)))
        total += w
        for i, j in enumerate(e):
            if j < 0:
                beta0[i] += w
            else:
                beta[i, j] += w
    return beta / total, beta0 / total


def test_lbp_is_exact_where_the_gate_graph_is_a_tree():
    # a chain track0 - det0 - track1 - det1 - track2 (and a lone detection of track 2): no loop, so belief
    # propagation gives the exact marginals
    gen = np.random.default_rng(3)
    score = gen.normal(size=(3, 3))
    gated = np.array([[True, False, False], [True, True, False], [False, True, True]])
    miss = math.log(0.3)
    ref, ref0 = _brute_force(score, miss, gated)
    beta, beta0 = marginals(score, miss, gated, method="lbp")
    np.testing.assert_allclose(beta, ref, atol=1e-12)
    np.testing.assert_allclose(beta0, ref0, atol=1e-12)
    assert not np.allclose(beta, marginals(score + 1.0, miss, gated, method="lbp")[0])  # the scores matter


def test_lbp_close_to_exact_on_a_loopy_cluster_and_auto_switches_by_the_bound():
    # four tracks all gating four detections (loops everywhere): an approximation, close to the exact marginals
    gen = np.random.default_rng(5)
    score = gen.normal(size=(4, 4))
    gated = np.ones((4, 4), bool)
    miss = math.log(0.25)
    ref, ref0 = _brute_force(score, miss, gated)
    lb, lb0 = marginals(score, miss, gated, method="lbp")
    assert np.abs(lb - ref).max() < 0.05 and np.abs(lb0 - ref0).max() < 0.05
    assert np.abs(lb - ref).max() > 1e-6  # not the exact answer: a real approximation
    np.testing.assert_allclose(lb.sum(1) + lb0, 1.0, atol=1e-12)
    ex, ex0 = marginals(score, miss, gated, method="exact")
    np.testing.assert_allclose(ex, ref, atol=1e-13)
    # auto: the bound 5^4 = 625 events against the limit decides
    au, _ = marginals(score, miss, gated, limit=625, method="auto")
    np.testing.assert_array_equal(au, ex)
    from dslearn.diagnostics import Diagnostics
    with Diagnostics() as d:
        au, _ = marginals(score, miss, gated, limit=624, method="auto")
    np.testing.assert_array_equal(au, lb)
    assert d.counts == {"jpda_lbp_clusters": 1}
    # exact counts the events themselves: 209 (sum over k of C(4, k)^2 k!)
    np.testing.assert_array_equal(marginals(score, miss, gated, limit=209, method="exact")[0], ex)
    with pytest.raises(ConfigError, match="associator.max_joint_events=208"):
        marginals(score, miss, gated, limit=208, method="exact")
    with pytest.raises(ConfigError, match="associator.marginals"):
        JPDA(marginals="loopy")


@needs_stonesoup
@pytest.mark.parametrize("pd,lam,pg", [(0.8, 0.05, 0.99), (0.6, 0.3, 0.95)])
def test_lbp_against_stonesoup(pd, lam, pg):
    from stonesoup.dataassociator.probability import JPDAwithLBP

    tracks, dets, means, covs, zs = _scene()
    _, _, hyp = _ss_parts(pd, lam, pg)
    # Stone Soup's associator fixes its tolerance at 1e-3; its own two steps are called with a tight one
    hyps = {t: hyp.hypothesise(t, set(dets), T0) for t in tracks}
    weights = JPDAwithLBP._calc_likelihood_matrix(tracks, dets, hyps)
    ref = JPDAwithLBP._loopy_belief_propagation(weights, 1, 1e-12)
    ours = JPDA(pd, lam, pg, marginals="lbp").associate(means, covs, LinearModel(H2, R2), zs)
    worst = max(np.abs(ref[:, 0] - ours.missed.numpy()).max(), np.abs(ref[:, 1:] - ours.weights.numpy()).max())
    assert (ref[:, 1:] > 0).tolist() == ours.gated.tolist()  # the same gate
    print("JPDA-LBP vs Stone Soup max abs difference", worst)
    assert worst < 1e-9
