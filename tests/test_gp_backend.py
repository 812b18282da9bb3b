"""The GP backend protocol (dslearn.models.gp_backends.protocol.GPBackend): every backend (exact with either
factor, window, SGPR, SSGP) satisfies it; its variance gradient and differentiable mean against finite
differences and the closed-form Jacobian; the aggregated GP over every backend against a hand
computation of the four rules for two experts, its Jacobian against finite differences, a single node
against the backend alone; a tiny Yu study and the CLI for every variant; the refused combinations."""

import contextlib
import io
import math
import os

import numpy as np
import pandas as pd
import pytest
import torch

from dslearn.errors import ConfigError
from dslearn.models.gp_backends.exact import OnlineGP
from dslearn.models.gp_backends.sparse import SGPR, SSGP, WindowGP, make_online_gp
from dslearn.models.aggregated import AggregatedGPMotion
from dslearn.models.gp import GPMotionModel
from dslearn.models.gp_backends.protocol import GPBackend
from dslearn.models.observation import GPObservation
from dslearn.types import StepContext

D = torch.float64
CTX = StepContext(dt=0.25)
HYP = dict(outputscale=1.3, lengthscale=1.7, noise_std=0.4)
RULES = ("poe", "gpoe", "bcm", "rbcm")
#: every backend, in a regime where it is not the exact GP: the window slides (8 of 15 points), SGPR
#: has 6 inducing inputs for 15 points, SSGP 40 features
BACKENDS = {
    "exact_inverse": dict(variant="exact", factor="inverse"),
    "exact_cholesky": dict(variant="exact", factor="cholesky"),
    "window": dict(variant="window", window=8),
    "sgpr": dict(variant="sgpr", inducing=6),
    "ssgp": dict(variant="ssgp", features=40),
}
FLAGS = {  # supports_belief, grows_per_append
    "exact_inverse": (True, True), "exact_cholesky": (True, True), "window": (True, False),
    "sgpr": (False, False), "ssgp": (False, False),
}


def _data(s=2, dx=4, n=15, seed=0):
    """``n`` examples per node of a nonlinear map (different data per node; nodes past the first skip
    every fourth point: invalid rows): a list of ``(x (S, Dx), y (S, Dx), valid (S,))``."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for i in range(n):
        x = 1.2 * torch.randn(s, dx, generator=g, dtype=D)
        y = x + 0.4 * torch.sin(1.3 * x) + 0.05 * torch.randn(s, dx, generator=g, dtype=D)
        out.append((x, y, torch.tensor([True] + [i % 4 != 1] * (s - 1))))
    return out


def _model(name, s=2, dx=4, n=15, mean="identity", noise="latent", seed=0, **kw):
    """A GP motion model of ``s`` nodes on backend ``name`` with the examples of :func:`_data`."""
    m = GPMotionModel(dx, s, mean=mean, noise=noise, **HYP, **BACKENDS[name], **kw)
    for x, y, valid in _data(s, dx, n, seed):
        m.add_data(x, y, valid)
    return m


def _queries(s, b=3, dx=4, seed=7):
    return 1.2 * torch.randn(s, b, dx, generator=torch.Generator().manual_seed(seed), dtype=D)


# ------------------------------------------------------------------------------------- protocol
@pytest.mark.parametrize("name", list(BACKENDS))
def test_every_backend_satisfies_the_protocol(name):
    opts = {k: v for k, v in BACKENDS[name].items() if k not in ("variant", "factor")}
    direct = make_online_gp(BACKENDS[name]["variant"], 2, 4, 4, mean="zero", dtype=D, device="cpu", **HYP, **opts)
    model = _model(name, n=0)
    for b in (direct, model.gp):
        assert isinstance(b, GPBackend)
        assert (b.supports_belief, b.grows_per_append) == FLAGS[name]
        assert (b.num_nodes, b.input_dim, b.output_dim) == (2, 4, 4)
        hyp = torch.stack([b.outputscale, b.lengthscale, b.noise_var])
        torch.testing.assert_close(hyp, torch.tensor([[1.69], [1.7], [0.16]], dtype=D).expand(3, 2), rtol=1e-15, atol=0)
    assert type(model.gp) is {"window": WindowGP, "sgpr": SGPR, "ssgp": SSGP}.get(name, OnlineGP)


def test_observation_gp_and_a_stranger():
    assert isinstance(GPObservation(3).gp, GPBackend)

    class PredictOnly:  # what a backend needs is more than a predict method
        num_nodes = input_dim = output_dim = 1

        def predict(self, x, jacobian=True, variance=True):
            return x, None, None

    assert not isinstance(PredictOnly(), GPBackend)


@pytest.mark.parametrize("name", list(BACKENDS))
def test_variance_gradient_equals_finite_differences(name):
    empty = _model(name, n=0).gp
    x = _queries(2)
    # no data: the prior variance, constant (SSGP: sigma_f^2 (cos^2 + sin^2) summed in floating point)
    torch.testing.assert_close(empty.variance_gradient(x), torch.zeros_like(x), rtol=0, atol=1e-15)
    for n in (4, 15):  # SGPR still collecting its 6 inducing inputs / past them; window not full / sliding
        gp = _model(name, n=n).gp
        grad = gp.variance_gradient(x)
        h = 1e-5
        fd = torch.stack([(gp.predict(x + h * e, jacobian=False)[1] - gp.predict(x - h * e, jacobian=False)[1]) / (2 * h)
                          for e in torch.eye(4, dtype=D)], -1)
        torch.testing.assert_close(grad, fd, rtol=1e-6, atol=1e-9)
        assert grad.abs().max() > 0.05  # informative: the variance does change near the data


@pytest.mark.parametrize("name", list(BACKENDS))
def test_differentiable_mean_is_the_posterior_mean_and_its_jacobian(name):
    gp = _model(name).gp
    x = _queries(2).requires_grad_(True)
    mean, _, jac = gp.predict(x.detach())
    with torch.enable_grad():
        dm = gp.differentiable_mean(x)
        rows = [torch.autograd.grad(dm[..., o].sum(), x, retain_graph=True)[0] for o in range(4)]
    torch.testing.assert_close(dm.detach(), mean, rtol=0, atol=1e-12)
    torch.testing.assert_close(torch.stack(rows, -2), jac, rtol=0, atol=1e-11)
    # the learned part is not negligible: the Jacobian is not the prior mean's identity
    assert (jac - torch.eye(4, dtype=D)).abs().max() > 0.05


@pytest.mark.parametrize("name", ["sgpr", "ssgp"])
def test_belief_is_refused_where_not_supported(name):
    gp = _model(name).gp
    with pytest.raises(ConfigError, match=r"model\.inputs=belief.*choose model\.inputs=mean"):
        gp.predict_belief(_queries(2), torch.eye(4, dtype=D).expand(2, 3, 4, 4))
    with pytest.raises(ConfigError, match=rf"model\.inputs=belief.*model\.variant={name}"):
        GPMotionModel(4, 2, inputs="belief", **HYP, **BACKENDS[name])


@pytest.mark.parametrize("name", list(BACKENDS))
def test_reserve_only_where_the_backend_grows(name):
    model = _model(name, n=3)
    before = model.gp.state_tensors()
    model.reserve(300)
    if name == "exact_inverse":  # the inverse factor's buffer is allocated at once
        assert model.gp.X.shape[1] >= 303
    elif name == "exact_cholesky":  # the Cholesky factor grows as it fills (every solve runs over the buffer)
        assert model.gp.X.shape[1] == 256
    elif name == "window":
        assert model.gp.X.shape[1] == 9  # window + 1 rows
    after = model.gp.state_tensors()
    assert after.keys() == before.keys() and all(torch.equal(after[k], before[k]) for k in before)
    # the same appends with and without the reservation: the same posterior
    ref = _model(name, n=20)
    res = _model(name, n=0)
    res.reserve(20)
    for x, y, valid in _data(n=20):
        res.add_data(x, y, valid)
    x = _queries(2)
    for a, b in zip(res.linearize(x, CTX), ref.linearize(x, CTX)):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", list(BACKENDS))
def test_a_refused_model_file_changes_nothing(tmp_path, name):
    """The backend checks the saved state before anything is replaced; the model's own state (here the
    adaptive process noise) is restored when the backend refuses."""
    src = _model(name, n=15, noise="adaptive")
    src.q_noise.fill_(0.7)
    p = tmp_path / "m.pt"
    src.save(p)
    smaller = {"exact_inverse": dict(variant="window", window=5), "exact_cholesky": dict(variant="window", window=5),
               "window": dict(variant="window", window=5), "sgpr": dict(variant="sgpr", inducing=4),
               "ssgp": dict(variant="ssgp", features=8)}[name]
    dst = GPMotionModel(4, 2, mean="identity", noise="adaptive", **{**HYP, "lengthscale": 2.2}, **smaller)
    g = torch.Generator().manual_seed(1)
    for _ in range(3):
        x = torch.randn(2, 4, generator=g, dtype=D)
        dst.add_data(x, x + 0.1)
    x = _queries(2)
    before = [t.clone() for t in (*dst.linearize(x, CTX), dst.q_noise, dst.gp.lengthscale)]
    with pytest.raises(ConfigError, match="more than model.window=5|does not match"):
        dst.load(p)
    after = (*dst.linearize(x, CTX), dst.q_noise, dst.gp.lengthscale)
    assert float(before[-2].max()) == 0.4**2 and abs(float(before[-1].max()) - 2.2) < 1e-12
    for a, b in zip(after, before):
        assert torch.equal(a, b)
    # the same file into a model of its own size: the same predictions as the saved model
    same = GPMotionModel(4, 2, mean="identity", noise="adaptive", **HYP, **BACKENDS[name]).load(p)
    for a, b in zip(same.linearize(x, CTX), src.linearize(x, CTX)):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-10)


# ----------------------------------------------------------------------------- aggregated GP
def _hand_two_experts(r, v, pv, rule, normalise=False):
    """The aggregation of two experts written out (numpy): residuals ``r (2, Dy)``, variances ``v (2,)``."""
    r, v = np.asarray(r, dtype=np.float64), np.asarray(v, dtype=np.float64)
    if rule in ("poe", "bcm"):
        beta = np.ones(2)
    else:
        beta = np.maximum(0.0, 0.5 * (np.log(pv) - np.log(v)))
        if normalise:
            beta = beta / beta.sum()
    prec = beta[0] / v[0] + beta[1] / v[1]
    num = beta[0] / v[0] * r[0] + beta[1] / v[1] * r[1]
    if rule == "bcm":
        prec += (1.0 - 2.0) / pv
    if rule == "rbcm":
        prec += (1.0 - beta.sum()) / pv
    return num / prec, 1.0 / prec


@pytest.mark.parametrize("rule", RULES)
@pytest.mark.parametrize("name", list(BACKENDS))
def test_aggregate_equals_the_rule_on_the_experts_own_predictions(name, rule):
    for noise in ("latent", "predictive"):
        base = _model(name, noise=noise)
        agg = AggregatedGPMotion(base, rule)
        x = _queries(2)
        mu, _, Q = agg.linearize(x, CTX)
        pv = float(base.gp.outputscale.mean())
        for i in range(2):
            for b in range(3):
                xi = x[i, b].expand(2, 1, 4).contiguous()  # node i's state, asked of both experts
                m, v, _ = base.gp.predict(xi, jacobian=False)
                r = (m - xi)[:, 0]  # identity prior mean: the residuals
                am, av = _hand_two_experts(r.numpy(), v[:, 0].numpy(), pv, rule)
                if noise == "predictive":
                    av = av + float(base.gp.noise_var.mean())
                np.testing.assert_allclose(mu[i, b].numpy(), x[i, b].numpy() + am, rtol=1e-10, atol=1e-12)
                np.testing.assert_allclose(Q[i, b].numpy(), av * np.eye(4), rtol=1e-10, atol=1e-13)
        # the experts disagree here, so the rule matters: not simply expert 0
        assert (mu - base.linearize(x, CTX)[0]).abs().max() > 1e-3


@pytest.mark.parametrize("rule", RULES)
@pytest.mark.parametrize("name", list(BACKENDS))
def test_aggregated_jacobian_equals_finite_differences(name, rule):
    base = _model(name, s=3)
    agg = AggregatedGPMotion(base, rule)
    x = _queries(3, b=2)
    mu, J, _ = agg.linearize(x, CTX)
    h = 1e-5
    fd = torch.stack([(agg(x + h * e, CTX) - agg(x - h * e, CTX)) / (2 * h) for e in torch.eye(4, dtype=D)], -1)
    torch.testing.assert_close(J, fd, rtol=1e-6, atol=1e-8)
    torch.testing.assert_close(agg(x, CTX), mu, rtol=0, atol=1e-13)
    if rule in ("gpoe", "rbcm"):  # the weights move with the variances: without its gradient the Jacobian is off
        J_frozen = AggregatedGPMotion(base, rule, jacobian="frozen_weights").linearize(x, CTX)[1]
        assert (J_frozen - fd).abs().max() > 1e-4


@pytest.mark.parametrize("name", list(BACKENDS))
def test_single_node_equals_the_backend_alone(name):
    """One expert: PoE and BCM are the expert itself (BCM's correction (1 - M)/prior is 0). gPoE keeps its
    mean and Jacobian (beta cancels) but divides the variance by beta = log(prior / var) / 2; rBCM
    shrinks towards the prior, precision beta/var + (1 - beta)/prior. With normalised weights (beta = 1)
    all four are the expert itself."""
    base = _model(name, s=1)
    g = torch.Generator().manual_seed(3)
    x = torch.stack([xi for xi, _, _ in _data(1)[:4]], 1) + 0.2 * torch.randn(1, 4, 4, generator=g, dtype=D)
    mu0, J0, Q0 = base.linearize(x, CTX)
    var = Q0[..., 0, 0]
    pv = float(base.gp.outputscale[0])
    assert float(var.max()) < 0.9 * pv  # near the data: beta > 0
    close = dict(rtol=1e-9, atol=1e-11)
    for rule in RULES:
        for normalise in (False, True):
            mu, J, Q = AggregatedGPMotion(base, rule, normalise_beta=normalise).linearize(x, CTX)
            if rule in ("poe", "bcm") or normalise:
                for a, b in zip((mu, J, Q), (mu0, J0, Q0)):
                    torch.testing.assert_close(a, b, **close)
                continue
            beta = 0.5 * torch.log(pv / var)
            if rule == "gpoe":
                torch.testing.assert_close(mu, mu0, **close)
                torch.testing.assert_close(J, J0, rtol=1e-8, atol=1e-10)
                torch.testing.assert_close(Q[..., 0, 0], var / beta, **close)
            else:  # rbcm
                prec = beta / var + (1 - beta) / pv
                torch.testing.assert_close(mu, x + (beta / var / prec).unsqueeze(-1) * (mu0 - x), **close)
                torch.testing.assert_close(Q[..., 0, 0], 1 / prec, **close)
                assert (mu - mu0).abs().max() > 1e-3  # a real shrinkage, not the expert


def test_aggregated_refuses_what_it_would_ignore():
    with pytest.raises(ConfigError, match=r"^model\.inputs=belief is not available for an aggregated GP \(model\."
                                          r"aggregation=rbcm\).*choose model\.inputs=mean"):
        AggregatedGPMotion(GPMotionModel(4, 2, inputs="belief"), "rbcm")
    with pytest.raises(ConfigError, match=r"^model\.jacobian=autograd is not available for an aggregated GP \(model\."
                                          r"aggregation=poe\).*choose model\.jacobian=closed_form"):
        AggregatedGPMotion(GPMotionModel(4, 2, jacobian="autograd"), "poe")


# ------------------------------------------------------------------------- study and command line
def test_tiny_yu_study_for_every_variant():
    from dslearn import api

    res = {}
    for v in ("exact", "window", "sgpr", "ssgp"):
        study = api.yu_study(model="gp_increment_rbcm", consensus="hybrid", train_episodes=2, test_episodes=1,
                                     **{"+model.variant": v})
        assert study.model.base.variant == v
        df = study.run()
        assert len(df) and df["value"].map(math.isfinite).all(), v
        per = df.pivot_table(index=["node", "episode"], columns="metric", values="value")
        # every node predicts with the same aggregate of all nodes' GPs, rolled out from the same true start
        pred = per["pred_err"].to_numpy()
        np.testing.assert_allclose(pred, np.full_like(pred, pred[0]), rtol=1e-12, atol=0)
        res[v] = df.set_index(["node", "episode", "metric", *[c for c in df.columns if c not in
                                                                 ("node", "episode", "metric", "value")]])["value"]
    # 24 points per node: within the window (500) and the inducing budget (128), so the window GP is the exact
    # GP, and SGPR too up to its jitter (1e-8 sigma_f^2 on K_uu; measured 1.7e-7 relative); SSGP's 200
    # features approximate the kernel (not a copy of the exact run)
    pd.testing.assert_series_equal(res["window"], res["exact"], rtol=1e-9, atol=0, check_exact=False)
    pd.testing.assert_series_equal(res["sgpr"], res["exact"], rtol=1e-5, atol=0, check_exact=False)
    assert (res["ssgp"] - res["exact"]).abs().max() > 1e-4


def _cli(argv):
    from dslearn.run import main

    out, err = io.StringIO(), io.StringIO()
    code, old = 0, os.environ.get("CI")
    os.environ["CI"] = "1"
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                main(list(argv))
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else 1
    finally:
        if old is None:
            os.environ.pop("CI", None)
        else:
            os.environ["CI"] = old
    return code, out.getvalue(), err.getvalue()


def test_cli_up_front_check_accepts_every_variant_and_rule(tmp_path):
    from dslearn.app.precheck import precheck

    sweep = ["-m", "model=gp_rbcm,gp_increment_rbcm", "+model.variant=exact,window,sgpr,ssgp",
             "model.aggregation=poe,gpoe,bcm,rbcm", "data.train_episodes=1", "data.test_episodes=1",
             f"hydra.sweep.dir={tmp_path / 'sw'}"]
    assert precheck(sweep) is None
    run = tmp_path / "run"
    code, out, err = _cli(["model=gp_increment_rbcm", "+model.variant=ssgp", "+model.features=50", "data.train_episodes=1",
                           "data.test_episodes=1", "print_table=false", f"hydra.run.dir={run}"])
    assert code == 0, err[-2000:]
    df = pd.read_csv(run / "results.csv")
    assert len(df) and df["value"].map(math.isfinite).all() and set(df["model"]) == {"gp_increment_rbcm"}


@pytest.mark.parametrize("overrides,expected", [
    (["model=gp_rbcm", "+model.inputs=belief"],
     "model.inputs=belief is not available for an aggregated GP (model.aggregation=rbcm): it aggregates the node GPs "
     "at the belief's mean; choose model.inputs=mean"),
    (["model=gp_increment_rbcm", "+model.variant=sgpr", "model.jacobian=autograd", "model.aggregation=gpoe"],
     "model.jacobian=autograd is not available for an aggregated GP (model.aggregation=gpoe): its Jacobian is set by "
     "model.aggregation_jacobian (exact | frozen_weights); choose model.jacobian=closed_form"),
], ids=["belief", "autograd"])
def test_cli_refuses_what_the_aggregated_gp_cannot_use(tmp_path, overrides, expected):
    run = tmp_path / "run"
    code, out, err = _cli([*overrides, "data.train_episodes=1", "data.test_episodes=1", f"hydra.run.dir={run}"])
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and lines == ["dslearn-run: configuration error: " + expected], (code, err[-2000:])
    assert "Traceback" not in err + out and not run.exists()
