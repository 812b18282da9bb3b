"""Tests for the DGPT study (Liu et al. 2022): aggregation closed forms, GP/MLL equalities,
windows, scenarios, end-to-end run and config errors. float64, fixed seeds."""

import math

import gpytorch
import pandas as pd
import pytest
import torch
from omegaconf import OmegaConf

from dslearn.dgpt.aggregation import aggregate, aggregate_grbcm, entropy_weights, ucb_bound
from dslearn.dgpt.experts import (Hypers, closed_form_gp, expert_log_marginal_likelihood,
                                  factorised_log_marginal_likelihood, predict_latent,
                                  predict_latent_slice)
from dslearn.dgpt.scenarios import (generate_s1, generate_s2, generate_s3, s3_turn_rates,
                                    singer_sigma)
from dslearn.dgpt.tracker import HyperConfig, _window, track
from dslearn.errors import ConfigError
from dslearn.studies import liu_dgpt

D = torch.float64
TOL = dict(rtol=1e-10, atol=1e-10)


def t(*v):
    return torch.tensor(v[0] if len(v) == 1 else v, dtype=D)


# ------------------------------------------------------------------ aggregation closed forms
def test_poe_identical_experts():
    mu, var = t(3.0, 3.0, 3.0, 3.0), t(2.0, 2.0, 2.0, 2.0)
    m, v, b = aggregate(mu, var, torch.ones(4, dtype=torch.bool), t(10.0), "poe")
    torch.testing.assert_close(m, t(3.0), **TOL)
    torch.testing.assert_close(v, t(0.5), **TOL)  # sigma^2 / M
    torch.testing.assert_close(b, torch.ones(4, dtype=D))


def test_gpoe_two_experts_hand_computed():
    mu, var, pv = t(1.0, 4.0), t(0.5, 2.0), 8.0
    b1, b2 = 0.5 * (math.log(8) - math.log(0.5)), 0.5 * (math.log(8) - math.log(2.0))  # Eq. 7
    prec = b1 / 0.5 + b2 / 2.0  # Eq. 10
    mean = (b1 / 0.5 * 1.0 + b2 / 2.0 * 4.0) / prec  # Eq. 9
    m, v, b = aggregate(mu, var, torch.ones(2, dtype=torch.bool), t(pv), "gpoe")
    torch.testing.assert_close(b, t(b1, b2), **TOL)
    torch.testing.assert_close(v, t(1 / prec), **TOL)
    torch.testing.assert_close(m, t(mean), **TOL)
    # normalised weights
    m2, v2, bn = aggregate(mu, var, torch.ones(2, dtype=torch.bool), t(pv), "gpoe", normalise_beta=True)
    torch.testing.assert_close(bn, t(b1, b2) / (b1 + b2), **TOL)
    torch.testing.assert_close(m2, t(mean), **TOL)  # mean invariant to a common weight scale


def test_bcm_prior_correction():
    mu, var, pv = t(1.0, 4.0), t(0.5, 2.0), 8.0
    prec = 1 / 0.5 + 1 / 2.0 + (1 - 2) / pv  # BCM: (1 - M) sigma_**^-2
    mean = (1 / 0.5 * 1.0 + 1 / 2.0 * 4.0) / prec
    m, v, _ = aggregate(mu, var, torch.ones(2, dtype=torch.bool), t(pv), "bcm")
    torch.testing.assert_close(v, t(1 / prec), **TOL)
    torch.testing.assert_close(m, t(mean), **TOL)


def test_rbcm_beta_weights_and_correction():
    mu, var, pv = t(1.0, 4.0), t(0.5, 2.0), 8.0
    b1, b2 = 0.5 * math.log(8 / 0.5), 0.5 * math.log(8 / 2.0)
    prec = b1 / 0.5 + b2 / 2.0 + (1 - b1 - b2) / pv  # Eq. 13
    mean = (b1 / 0.5 * 1.0 + b2 / 2.0 * 4.0) / prec  # Eq. 12
    m, v, b = aggregate(mu, var, torch.ones(2, dtype=torch.bool), t(pv), "rbcm")
    torch.testing.assert_close(b, t(b1, b2), **TOL)
    torch.testing.assert_close(v, t(1 / prec), **TOL)
    torch.testing.assert_close(m, t(mean), **TOL)


@pytest.mark.parametrize("rule,norm", [("poe", False), ("bcm", False), ("gpoe", True), ("rbcm", True)])
def test_single_expert_is_that_expert(rule, norm):
    m, v, _ = aggregate(t(2.5), t(0.7), torch.ones(1, dtype=torch.bool), t(5.0), rule, norm)
    torch.testing.assert_close(m, t(2.5), **TOL)
    torch.testing.assert_close(v, t(0.7), **TOL)


@pytest.mark.parametrize("rule", ["poe", "gpoe", "bcm", "rbcm"])
def test_masked_expert_excluded_and_empty_gives_prior(rule):
    mu, var = t(1.0, 4.0, -100.0), t(0.5, 2.0, 0.01)
    mask = torch.tensor([True, True, False])
    m, v, _ = aggregate(mu, var, mask, t(8.0), rule)
    m2, v2, _ = aggregate(mu[:2], var[:2], mask[:2], t(8.0), rule)
    torch.testing.assert_close(m, m2, **TOL)
    torch.testing.assert_close(v, v2, **TOL)
    me, ve, _ = aggregate(mu, var, torch.zeros(3, dtype=torch.bool), t(8.0), rule)
    assert me.item() == 0.0 and ve.item() == pytest.approx(8.0)


@pytest.mark.parametrize("rule", ["poe", "gpoe", "bcm", "rbcm"])
def test_random_batches_positive_variances(rule):
    g = torch.Generator().manual_seed(1)
    pv = 1.0 + 9.0 * torch.rand(50, generator=g, dtype=D)
    var = pv[:, None] * torch.rand(50, 7, generator=g, dtype=D).clamp_min(1e-3)
    mu = torch.randn(50, 7, generator=g, dtype=D)
    mask = torch.rand(50, 7, generator=g) < 0.6
    m, v, b = aggregate(mu, var, mask, pv, rule)
    assert torch.isfinite(m).all() and (v > 0).all()
    assert (b >= 0).all()
    if rule in ("bcm", "rbcm"):
        assert (v <= pv + 1e-12).all()  # prior correction never exceeds the prior


def test_grbcm_two_experts_hand_computed():
    mu, var, mc, vc = t(1.0, 4.0), t(0.5, 2.0), t(2.5), t(3.0)
    b1, b2 = 0.5 * math.log(3.0 / 0.5), 0.5 * math.log(3.0 / 2.0)  # entropy gain over the comm. expert
    prec = b1 / 0.5 + b2 / 2.0 + (1 - b1 - b2) / 3.0
    mean = (b1 / 0.5 * 1.0 + b2 / 2.0 * 4.0 + (1 - b1 - b2) / 3.0 * 2.5) / prec
    m, v, b = aggregate_grbcm(mu, var, torch.ones(2, dtype=torch.bool), mc, vc)
    torch.testing.assert_close(b, t(b1, b2), **TOL)
    torch.testing.assert_close(v, t(1 / prec), **TOL)
    torch.testing.assert_close(m, t(mean), **TOL)
    # no expert -> the communication expert; a masked expert is ignored
    m0, v0, _ = aggregate_grbcm(mu, var, torch.zeros(2, dtype=torch.bool), mc, vc)
    torch.testing.assert_close((m0, v0), (mc, vc), **TOL)
    m1, v1, _ = aggregate_grbcm(t(1.0, -50.0), var, torch.tensor([True, False]), mc, vc)
    m2, v2, _ = aggregate_grbcm(t(1.0), t(0.5), torch.tensor([True]), mc, vc)
    torch.testing.assert_close((m1, v1), (m2, v2), **TOL)


def test_predict_latent_slice_equals_gpytorch_path():
    g = torch.Generator().manual_seed(7)
    hyp = Hypers((2, 3, 2, 1), 3, 30.0, [2.0, 3.0, 1.5], 0.4)
    with torch.no_grad():
        for p_ in hyp.parameters():
            p_.add_(0.3 * torch.randn(p_.shape, generator=g, dtype=D))
    x = 2 * torch.randn(2, 3, 2, 4, 6, 3, generator=g, dtype=D)
    z = 5 * torch.randn(2, 3, 2, 4, 6, generator=g, dtype=D)
    mask = torch.rand(2, 3, 2, 4, 6, generator=g) < 0.7
    xs = torch.randn(2, 3, 2, 4, 2, 3, generator=g, dtype=D)
    mu, var = predict_latent(hyp, x, z, mask, xs)
    for p_ in range(3):
        ms, vs = predict_latent_slice(hyp, p_, x[:, p_], z[:, p_], mask[:, p_], xs[:, p_])
        torch.testing.assert_close(ms, mu[:, p_], rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(vs, var[:, p_], rtol=1e-9, atol=1e-9)


def test_grbcm_with_empty_communication_set_is_rbcm():
    g = torch.Generator().manual_seed(4)
    pv = 1.0 + 9.0 * torch.rand(20, generator=g, dtype=D)
    var = pv[:, None] * torch.rand(20, 5, generator=g, dtype=D).clamp_min(1e-3)
    mu = torch.randn(20, 5, generator=g, dtype=D)
    mask = torch.rand(20, 5, generator=g) < 0.7
    # empty D_c: the communication expert is the prior (mean 0, variance sigma_**^2)
    mg, vg, bg = aggregate_grbcm(mu, var, mask, torch.zeros(20, dtype=D), pv)
    mr, vr, br = aggregate(mu, var, mask, pv, "rbcm")
    torch.testing.assert_close((mg, vg, bg), (mr, vr, br), **TOL)
    with pytest.raises(ValueError, match="communication"):
        aggregate(mu, var, mask, pv, "grbcm")


def test_entropy_weights_zero_at_prior():
    b = entropy_weights(t(8.0, 2.0), t(8.0), torch.ones(2, dtype=torch.bool))
    torch.testing.assert_close(b, t(0.0, 0.5 * math.log(4.0)), **TOL)


def test_ucb_bound_closed_form():
    var, beta, delta = t(0.5, 2.0), t(0.3, 0.7), 0.1
    gamma = 2 * math.log(2 / delta)  # sum_i exp(-gamma/2) = delta
    expect = (0.3 * math.sqrt(gamma) / math.sqrt(0.5) + 0.7 * math.sqrt(gamma) / math.sqrt(2.0)) / (
        0.3 / 0.5 + 0.7 / 2.0)
    got = ucb_bound(var, beta, torch.ones(2, dtype=torch.bool), t(8.0), delta)
    torch.testing.assert_close(got, t(expect), **TOL)
    assert 2 * math.exp(-gamma / 2) == pytest.approx(delta)


# ------------------------------------------------------------------ GPs and likelihoods
def _data(seed=0, shape=(2, 3, 5), w=6, d=2):
    g = torch.Generator().manual_seed(seed)
    x = 3 * torch.randn(*shape, w, d, generator=g, dtype=D)
    z = 5 * torch.randn(*shape, w, generator=g, dtype=D)
    mask = torch.rand(*shape, w, generator=g) < 0.6
    mask[0, 0, 0] = False  # one empty window
    mask[..., 0] |= torch.arange(shape[-1]) > 0  # others non-empty
    return x, z, mask


def test_factorised_likelihood_equals_sum_of_local_gpytorch_mlls():
    x, z, mask = _data()
    hyp = Hypers((2, 3, 1), 2, 30.0, [2.0, 3.0], 0.4)
    fact = factorised_log_marginal_likelihood(hyp, x, z, mask)  # (2, 3)
    for i in range(2):
        for j in range(3):
            total = 0.0
            for m in range(5):
                mk = mask[i, j, m]
                if not mk.any():
                    continue
                xi, zi = x[i, j, m][mk], z[i, j, m][mk]
                lik = gpytorch.likelihoods.GaussianLikelihood().double()
                lik.noise = 0.4

                class GP(gpytorch.models.ExactGP):
                    def __init__(self):
                        super().__init__(xi, zi, lik)
                        self.mean = gpytorch.means.ZeroMean()
                        self.cov = gpytorch.kernels.ScaleKernel(gpytorch.kernels.RBFKernel(ard_num_dims=2))

                    def forward(self, xx):
                        return gpytorch.distributions.MultivariateNormal(self.mean(xx), self.cov(xx))

                gp = GP().double()
                gp.cov.outputscale = 30.0
                gp.cov.base_kernel.lengthscale = t(2.0, 3.0)
                gp.train()
                mll = gpytorch.mlls.ExactMarginalLogLikelihood(lik, gp)
                total += (mll(gp(xi), zi) * len(zi)).item()
            # (GPyTorch stores the default noise bound in float32: noise is 0.4 + 6e-9)
            assert fact[i, j].item() == pytest.approx(total, rel=1e-7, abs=1e-7)
    per = expert_log_marginal_likelihood(hyp, x, z, mask)
    assert per[0, 0, 0].abs().item() < 1e-9  # empty window contributes 0


def test_expert_mll_matches_closed_form_and_has_gradients():
    x, z, mask = _data(seed=3)
    hyp = Hypers((2, 3, 1), 2, 30.0, [2.0, 3.0], 0.4)
    per = expert_log_marginal_likelihood(hyp, x, z, mask)
    for (i, j, m) in [(0, 1, 2), (1, 2, 4), (1, 0, 1)]:
        mk = mask[i, j, m]
        _, _, lml = closed_form_gp(x[i, j, m][mk], z[i, j, m][mk], x[i, j, m][:1], 30.0, [2.0, 3.0], 0.4)
        assert per[i, j, m].item() == pytest.approx(lml.item(), rel=1e-10, abs=1e-9)
    per.sum().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in hyp.parameters())


def test_centralised_gp_equals_plain_torch_closed_form():
    g = torch.Generator().manual_seed(7)
    n, q = 25, 4
    x = torch.cat([torch.arange(n, dtype=D)[:, None] * 0.5, 50 * torch.randn(n, 2, generator=g, dtype=D)], -1)
    z = 100 * torch.sin(x[:, 0] / 3) + torch.randn(n, generator=g, dtype=D)
    mask = torch.ones(n + 5, dtype=torch.bool)
    mask[n:] = False  # padding slots
    xp = torch.cat([x, torch.zeros(5, 3, dtype=D)])
    zp = torch.cat([z, 99 * torch.ones(5, dtype=D)])  # garbage at padded slots must be ignored
    xt = x[:q] + 0.25
    hyp = Hypers((1,), 3, 1e4, [40.0, 40.0, 3.0], 1.3)
    mean, var = predict_latent(hyp, xp[None], zp[None], mask[None], xt[None])
    m0, v0, _ = closed_form_gp(x, z, xt, 1e4, [40.0, 40.0, 3.0], 1.3)
    torch.testing.assert_close(mean[0], m0, rtol=1e-9, atol=1e-8)
    torch.testing.assert_close(var[0], v0, rtol=1e-8, atol=1e-8)
    assert (var > 0).all()


# ------------------------------------------------------------------ windows and tracking
def test_window_excludes_sensors_and_freezes_when_empty():
    b, s, T = 1, 3, 12
    avail = torch.zeros(b, s, T, dtype=torch.bool)
    avail[0, 0, 2] = True  # sensor 0 only early
    avail[0, 1, 5] = True
    avail[0, 1, 6] = True
    meas = torch.randn(b, s, T, 2, dtype=D)
    window = torch.tensor([3])
    last = torch.tensor([6])
    times, m_e, z_e = _window(avail, meas, 7, window, 3, last)  # window [5, 7]
    assert times.tolist() == [[5, 6, 7]]
    assert m_e.shape[1] == 1 and m_e[0, 0].tolist() == [True, True, False]  # only sensor 1
    torch.testing.assert_close(z_e[0, 0, :2], meas[0, 1, 5:7])
    # k = 8: window [6, 8] keeps only step 6
    times, m_e, _ = _window(avail, meas, 8, window, 3, last)
    assert times.tolist() == [[6, 7, 8]] and m_e[0, 0].tolist() == [True, False, False]
    # k = 11: nothing in [9, 11] -> the window stopped sliding at [6, 8] (still holds step 6)
    times, m_e, _ = _window(avail, meas, 11, window, 3, last)
    assert times.tolist() == [[6, 7, 8]] and m_e[0, 0].tolist() == [True, False, False]


def test_no_detection_anywhere_prior_and_growing_variance():
    T = 12
    avail = torch.zeros(2, 4, T, dtype=torch.bool)
    avail[1, :2, :3] = True  # episode 1: detections only in steps 0..2
    meas = torch.zeros(2, 4, T, 2, dtype=D)
    meas[1, :, :3] = torch.arange(3, dtype=D)[None, :, None] * 10
    hc = HyperConfig(iters=1, iters_first=2)
    res = track(meas, avail, torch.tensor([3, 3]), hyper=hc)
    for arr in (res.upd_mean, res.upd_var, res.pred_mean, res.pred_var, res.upd_bound):
        assert torch.isfinite(arr).all()
    assert (res.upd_mean[0] == 0).all()  # never detected: prior mean
    torch.testing.assert_close(res.upd_var[0], torch.full_like(res.upd_var[0], hc.init_outputscale))
    v = res.upd_var[1, :, 3:, 0]  # after the data stops: variance grows
    assert (v[:, 1:] >= v[:, :-1] - 1e-9).all() and (v[:, -1] > 2 * v[:, 0]).all()


# ------------------------------------------------------------------ scenarios
def test_s1_constant_velocity_between_turning_points():
    g = torch.Generator().manual_seed(0)
    pos, vel = generate_s1(3, 60, g, accel_std=0.0, turn_every=20, speeds=(10.0, 5.0, 8.0),
                           headings_deg=(0.0, 90.0, 180.0))
    sp = vel.norm(dim=-1)
    torch.testing.assert_close(sp[:, :20], torch.full_like(sp[:, :20], 10.0))
    torch.testing.assert_close(sp[:, 20:40], torch.full_like(sp[:, 20:40], 5.0))
    step = pos[:, 1:] - pos[:, :-1]
    torch.testing.assert_close(step[:, 25], t(0.0, 5.0).expand(3, 2), rtol=0, atol=1e-9)


def test_s2_singer_invariants():
    assert singer_sigma(50.0, 0.4) == pytest.approx(math.sqrt(2500 / 3 * 0.6))
    g = torch.Generator().manual_seed(0)
    pos, vel = generate_s2(20, 80, g, v_max=15.0)
    assert (vel.norm(dim=-1) <= 15.0 + 1e-9).all()
    acc = (vel[:, 1:] - vel[:, :-1])
    assert (acc.abs() <= 50.0 + 1e-9).all()
    assert acc.abs().max() > 5.0  # it does manoeuvre


def test_s3_turn_rates():
    rates = s3_turn_rates(100)
    assert max(rates) == pytest.approx(math.radians(30)) and min(rates) == pytest.approx(-math.radians(30))
    g = torch.Generator().manual_seed(0)
    pos, vel = generate_s3(4, 100, g, accel_std=0.0)
    h = torch.atan2(vel[..., 1], vel[..., 0])
    dh = torch.remainder(h[:, 1:] - h[:, :-1] + math.pi, 2 * math.pi) - math.pi
    r = torch.tensor(rates[1:], dtype=D)
    torch.testing.assert_close(dh, r.expand_as(dh), rtol=0, atol=1e-9)
    torch.testing.assert_close(vel.norm(dim=-1), torch.full_like(dh[:, :1], 10.0).expand(4, 100))
    # a full 9 s turn is 270 deg
    assert sum(1 for x in rates if x > 0) >= 9


# ------------------------------------------------------------------ study end to end + config
def _cfg(**task):
    base = OmegaConf.load("conf/task/liu_dgpt.yaml")
    base.mc_runs = 2
    base.batch_runs = 1  # two chunks: the second has no trace rows
    base.num_steps = 14
    base.num_sensors = 60
    base.area_size = 400.0
    base.scenarios = ["s1", "s3"]
    base.noises = [1.0, 4.0]
    base.hyper.iters = 1
    base.hyper.iters_first = 2
    base.trace = {"scenario": "s1", "noise": 4.0, "episodes": 1}
    for k, v in task.items():
        OmegaConf.update(base, k, v)
    return OmegaConf.create({"seed": 3, "device": "cpu", "dtype": "float64", "progress": False,
                             "task": base})


@pytest.mark.parametrize("gp_input", ["temporal", "spatiotemporal"])
def test_tiny_end_to_end(gp_input, tmp_path):
    df = liu_dgpt.run(_cfg(gp_input=gp_input))
    for col in ("episode", "model", "consensus", "node", "scenario", "noise", "metric", "value"):
        assert col in df.columns
    assert df["value"].dtype == float
    sc = df[df["step"] < 0]
    # 2 scenarios x 2 noises x 2 runs x 6 methods
    for met in liu_dgpt.METRICS + ("ucb_coverage",):
        sub = sc[sc["metric"] == met]
        assert len(sub) == 2 * 2 * 2 * 6
        assert sub["value"].notna().all() and (sub["value"] >= 0).all()
    cov = sc[sc["metric"] == "ucb_coverage"]["value"]
    assert ((cov >= 0) & (cov <= 1)).all()
    assert set(sc["consensus"]) == {"-", "poe", "gpoe", "bcm", "rbcm", "grbcm"}
    if gp_input == "temporal":  # reproducible from the seed
        df2 = liu_dgpt.run(_cfg(gp_input=gp_input))
        pd.testing.assert_frame_equal(df.reset_index(drop=True), df2.reset_index(drop=True))
    df["task"] = "liu_dgpt"
    md = liu_dgpt.report(df, df, tmp_path)
    assert "DGPT-rBCM" in md and "DGPT-grBCM" in md and any(p.suffix == ".png" for p in tmp_path.iterdir())


@pytest.mark.parametrize("field,value", [
    ("gp_input", "spatial"), ("aggregations", ["poe", "moe"]), ("aggregations", []),
    ("window.s1", 0), ("noises", [1.0, -2.0]), ("ucb_delta", 1.5), ("mc_runs", 0),
    ("hyper.optimizer", "newton"), ("scenarios", ["s4"]),
])
def test_bad_input_raises_config_error(field, value):
    with pytest.raises(ConfigError, match=field.split(".")[0]):
        liu_dgpt.run(_cfg(**{field: value}))


# ------------------------------------------------------------------ Hydra spelling (issue 4, part 7)
def _compose(*overrides):
    import pathlib

    from hydra import compose, initialize_config_dir

    conf = str(pathlib.Path(__file__).resolve().parents[1] / "conf")
    with initialize_config_dir(config_dir=conf, version_base=None):
        return compose("config", overrides=list(overrides))


@pytest.mark.parametrize("base", ["experiment=liu_table1", "experiment=liu_table2", "task=liu_dgpt"])
def test_hydra_cell_spelling_selects_one_cell(base):
    cfg = _compose(base, "tracker=dgpt", "aggregation=rbcm", "gp_input=spatiotemporal", "scenario=s3",
                   "noise=2")
    p = liu_dgpt.validate(cfg)
    assert p["gp_input"] == "spatiotemporal" and p["aggregations"] == ["rbcm"]
    assert p["scenarios"] == ["s3"] and p["noises"] == [2.0] and p["centralised"] is False
    assert p["trace"]["scenario"] == "s3" and p["trace"]["noise"] == 2.0  # the cell traces itself
    p = liu_dgpt.validate(_compose(base, "tracker=gp", "gp_input=temporal", "scenario=s1", "noise=4.0"))
    assert p["aggregations"] == [] and p["centralised"] is True and p["gp_input"] == "temporal"
    assert p["scenarios"] == ["s1"] and p["noises"] == [4.0]
    p = liu_dgpt.validate(_compose(base, "aggregation=grbcm"))  # no tracker: + standard GP
    assert p["aggregations"] == ["grbcm"] and p["centralised"] is True


def test_hydra_defaults_run_the_full_grid():
    p = liu_dgpt.validate(_compose("experiment=liu_table1"))  # scenario = the Yu default
    assert p["scenarios"] == ["s1", "s2", "s3"] and p["noises"] == [1.0, 2.0, 4.0]
    assert p["aggregations"] == ["poe", "gpoe", "bcm", "rbcm", "grbcm"] and p["centralised"]
    assert p["gp_input"] == "temporal"
    assert liu_dgpt.validate(_compose("experiment=liu_table2"))["gp_input"] == "spatiotemporal"
    cfg = _compose("experiment=liu_grid")
    assert cfg.study == "liu_grid" and cfg.task.mc_runs == 100


def test_hydra_unknown_values_give_clear_errors():
    from hydra.errors import MissingConfigException

    for ov, opt in (("aggregation=moe", "rbcm"), ("tracker=kf", "dgpt"), ("gp_input=spatial", "temporal"),
                    ("scenario=s4", "s3")):
        with pytest.raises(MissingConfigException, match=opt):  # Hydra lists the options
            _compose("experiment=liu_table1", ov)
    with pytest.raises(ConfigError, match="noise"):
        liu_dgpt.validate(_compose("experiment=liu_table1", "noise=-1"))
    with pytest.raises(ConfigError, match="noise"):
        liu_dgpt.validate(_compose("experiment=liu_table1", "noise=abc"))
    with pytest.raises(ConfigError, match="tracker=gp"):
        liu_dgpt.validate(_compose("experiment=liu_table1", "tracker=gp", "aggregation=rbcm"))


def test_tracker_gp_alone_end_to_end():
    cfg = _cfg(scenarios=["s2"], noises=[2.0])
    cfg.tracker = {"name": "gp"}
    df = liu_dgpt.run(cfg)
    assert set(df["model"]) == {"standard_gp"} and set(df["scenario"]) == {"s2"}
    cfg2 = _cfg(scenarios=["s2"], noises=[2.0])  # the same episodes inside the full run
    full = liu_dgpt.run(cfg2)
    a = df[(df["metric"] == "nrmse_x_updated")]["value"].to_numpy()
    b = full[(full["metric"] == "nrmse_x_updated") & (full["model"] == "standard_gp")]["value"].to_numpy()
    torch.testing.assert_close(torch.tensor(a), torch.tensor(b), rtol=1e-9, atol=1e-12)
