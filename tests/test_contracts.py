"""Contract tests: every option of every config group composes and its part instantiates, every
experiment composes and passes the validation layer, and every implementation of a role keeps
the role's contract (shapes, symmetry, positive definiteness, finite-difference Jacobians)."""

from __future__ import annotations

import inspect

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import get_object
from omegaconf import OmegaConf

from dslearn.compose import build, build_fusion, build_motion_model, build_network, build_observation, build_scenario
from dslearn.schemas.core import CONF_DIR, validate_config
from dslearn.models.base import MotionModel, ObservationModel

GROUPS = sorted(p.name for p in CONF_DIR.iterdir() if p.is_dir() and not p.name.startswith("_"))


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return compose("config", overrides=list(overrides))


ALL_OPTIONS = [(g, o) for g in GROUPS if g != "experiment" for o in _options(g)]


def test_every_group_has_options():
    assert {"model", "observation", "consensus", "network", "scenario", "filter", "task", "experiment"} <= set(GROUPS)
    assert all(_options(g) for g in GROUPS), [g for g in GROUPS if not _options(g)]


@pytest.mark.parametrize("group,option", ALL_OPTIONS, ids=[f"{g}={o}" for g, o in ALL_OPTIONS])
def test_every_option_composes_and_names_an_importable_part(group, option):
    """Composes with the default study or, for an option of another study's group (a Liu aggregation
    rule, a data set), with at least one experiment that uses the group."""
    from hydra.errors import ConfigCompositionException

    cfg, errors = None, []
    for context in ([], *([f"experiment={e}"] for e in _options("experiment"))):
        for sel in (f"{group}={option}", f"+{group}={option}"):  # a group outside the root defaults: '+'
            try:
                cfg = _compose(*context, sel)
                break
            except ConfigCompositionException as e:
                errors.append(f"{context} {sel}: {str(e).splitlines()[0]}")
        if cfg is not None:
            break
    assert cfg is not None, errors
    node = OmegaConf.select(cfg, group)
    if node is None:  # an option that writes into another package (e.g. '@package task')
        return
    spec = OmegaConf.to_container(node, resolve=False)
    targets = []

    def walk(x, where):
        if isinstance(x, dict):
            if "_target_" in x:
                targets.append((where, x))
            for k, v in x.items():
                walk(v, f"{where}.{k}")

    walk(spec, group)
    for where, t in targets:
        fn = get_object(t["_target_"])  # importable
        params = inspect.signature(fn).parameters
        if not any(p.kind is p.VAR_KEYWORD for p in params.values()):
            keys = {k for k in t if not k.startswith("_") and k != "name" and not isinstance(t[k], dict)}
            assert keys <= set(params), (where, sorted(keys - set(params)))


@pytest.mark.parametrize("experiment", _options("experiment"))
def test_every_experiment_composes_and_validates(experiment):
    cfg = _compose(f"experiment={experiment}")
    validate_config(cfg)  # the whole validation layer, before any work


@pytest.fixture(scope="module")
def yu_world():
    cfg = _compose()
    scenario, network = build_scenario(cfg), build_network(cfg)
    return cfg, scenario, network


# ------------------------------------------------------------------------------- motion models
MODELS = _options("model")


@pytest.mark.parametrize("option", MODELS)
def test_motion_model_contract(option, yu_world):
    cfg, scenario, network = yu_world
    node = _compose(f"model={option}").model
    model = build_motion_model(node, scenario, network, torch.float64, torch.device("cpu"))
    assert isinstance(model, MotionModel)
    s, b, dx = network.num_nodes, 3, scenario.state_dim
    gen = torch.Generator().manual_seed(0)
    x = scenario.sample(b, network, gen).states[:, 0].to(torch.float64)  # (B, Dx) true start states
    if model.learnable:  # learn a few pairs so the GP is not at its prior
        for t in range(3):
            xi = x[t % b].expand(s, dx).contiguous()
            model.add_data(xi, xi + 0.05)
    xs = x.expand(s, b, dx).contiguous()
    ctx = scenario.ctx()
    mean, F, Q = model.linearize(xs, ctx)
    assert mean.shape == (s, b, dx) and F.shape == (s, b, dx, dx) and Q.shape == (s, b, dx, dx)
    assert torch.isfinite(mean).all() and torch.isfinite(F).all()
    torch.testing.assert_close(Q, Q.transpose(-1, -2), rtol=0, atol=1e-12)
    assert torch.linalg.eigvalsh(Q).min() > 0  # process noise positive definite
    # Jacobian against central finite differences of the mean
    eps = 1e-6
    fd = torch.stack([(model(xs + eps * e, ctx) - model(xs - eps * e, ctx)) / (2 * eps)
                      for e in torch.eye(dx, dtype=xs.dtype)], -1)
    torch.testing.assert_close(F, fd, rtol=1e-4, atol=1e-5)


# ------------------------------------------------------------------------- observation models
@pytest.mark.parametrize("option", _options("observation"))
def test_observation_model_contract(option, yu_world):
    cfg, scenario, network = yu_world
    obs = build_observation(_compose(f"observation={option}").observation, network, torch.float64, torch.device("cpu"))
    assert isinstance(obs, ObservationModel)
    s, a = network.num_nodes, scenario.num_agents
    y = torch.randn(s, a, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) + 4.0
    h, C, R = obs.linearize(y)
    assert h.shape == (s, a, obs.meas_dim) and C.shape == (s, a, obs.meas_dim, 4) and R.shape[-2:] == (obs.meas_dim, obs.meas_dim)
    torch.testing.assert_close(R, R.transpose(-1, -2), rtol=0, atol=1e-12)
    assert torch.linalg.eigvalsh(R).min() > 0


# --------------------------------------------------------------------------------------- fusion
@pytest.mark.parametrize("option", _options("consensus"))
def test_fusion_contract(option, yu_world):
    """Every fusion: row-stochastic weights (doubly stochastic for the symmetric rules; the paper's
    uniform 1/(|N_i|+1) rule is not); SPD symmetric fused information; when every node
    holds the same prior and the same novel information, it keeps the prior plus a positive
    multiple of it (consensus of equal beliefs changes nothing but the weighting)."""
    cfg, scenario, network = yu_world
    fusion = build_fusion(_compose(f"consensus={option}").consensus, network)
    w = fusion.weights
    torch.testing.assert_close(w.sum(1), torch.ones_like(w.sum(1)))
    from dslearn.fusion.weights import consensus_weights

    for rule in ("metropolis", "max_degree"):
        wd = consensus_weights(network.adjacency, rule)
        torch.testing.assert_close(wd.sum(0), torch.ones_like(wd.sum(0)))
        torch.testing.assert_close(wd, wd.T)
    assert (w >= 0).all()
    s, dx = network.num_nodes, 4
    o = torch.eye(dx, dtype=torch.float64).expand(s, 1, dx, dx).clone()
    q = torch.ones(s, 1, dx, dtype=torch.float64)
    q2, o2 = fusion(q, o, 0.5 * q, 0.5 * o)
    torch.testing.assert_close(o2, o2.transpose(-1, -2), rtol=0, atol=1e-12)
    assert torch.linalg.eigvalsh(o2).min() > 0
    ratio = o2[..., 0, 0]
    torch.testing.assert_close(q2[..., 0], ratio)  # q / Omega keeps the common mean 1


# ---------------------------------------------------------------------------- filter: predict
@pytest.mark.parametrize("option", _options("filter"))
def test_predict_step_contract(option, yu_world):
    """Every prediction step equals the Kalman prediction for the linear (constant-velocity) model."""
    from dslearn.compose import build_predict
    from dslearn.models.constant_velocity import ConstantVelocity

    cfg, scenario, network = yu_world
    step = build_predict(_compose(f"filter={option}"))
    model = ConstantVelocity(scenario.num_agents, 0.1)
    ctx = scenario.ctx()
    dx = scenario.state_dim
    gen = torch.Generator().manual_seed(3)
    a = torch.randn(2, 3, dx, dx, dtype=torch.float64, generator=gen)
    P = a @ a.transpose(-1, -2) + torch.eye(dx, dtype=torch.float64)
    mean = torch.randn(2, 3, dx, dtype=torch.float64, generator=gen)
    y, q, om = step(mean, torch.linalg.inv(P), model, ctx)
    F = model.jacobian(mean, ctx)
    Pp = F @ P @ F.transpose(-1, -2) + model.noise_cov(mean, ctx)
    torch.testing.assert_close(y, model(mean, ctx))
    torch.testing.assert_close(torch.linalg.inv(om), Pp, rtol=1e-8, atol=1e-8)
    torch.testing.assert_close(q, (om @ y.unsqueeze(-1)).squeeze(-1))


# ------------------------------------------------------------------------------- network parts
@pytest.mark.parametrize("option", _options("network"))
def test_network_contract(option):
    net = build(_compose(f"network={option}").network, "network")
    adj = net.adjacency
    assert torch.equal(adj, adj.T) and not adj.diagonal().any()
    assert net.num_nodes == len(net.names) and int(net.is_sensor.sum()) >= 1
