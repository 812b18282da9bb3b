r"""Study ``ethucy_tracking``: Yu et al. Section VI (robot study) on real pedestrians (ETH/UCY).

Two protocols (``task.protocol``):

``tables`` (``dslearn-run experiment=real_tables``) — Tables III–IV and Fig. 4 analogue. Per
scene (``task.scenes``): episodes of ``m`` interacting pedestrians (:mod:`dslearn.data.episodes`,
physical time), a time split inside the scene, a LiDAR-like network around the scene
(:mod:`dslearn.sim.real`), then

* tracking error of the distributed EKF (``cfg.consensus``, hybrid by default) with the GP
  (``cfg.model``, learned online through Algorithm 1 on the training episodes), the same GP
  with a constant-velocity prior mean (``gp_cv``, :class:`ConstantVelocityMeanGP`), LIN and SFM;
* prediction error (roll-out from the true state at t = 0, the paper's V-C protocol) of GP,
  LIN, SFM and LSTM;
* predicted trajectories of a few test episodes (rows ``pred_x``/``pred_y``) for the figure.

``data_size`` (``dslearn-run experiment=gp_vs_lstm``) — Fig. 5 analogue: prediction error of the
GP (learned online through the consensus EKF, evaluated after ``n`` training episodes) and of
the LSTM (trained offline on the first ``n`` training episodes fused by consensus on
measurements) for ``n`` in ``task.data_sizes``, ``task.seeds`` seeds, on the real scenes and
on the synthetic Yu scenario (``cfg.scenario`` / ``cfg.network``).

SFM on real data (the true model is unknown): its shared parameters
:math:`(\tau, \alpha, \beta)` are fitted on the training episodes by minimising the mean
position error of its roll-outs from each episode's state at t = 0 (exactly the prediction
protocol), grid search then Adam on :math:`(\log\tau, \alpha \ge 0, \log\beta)`; each agent's
desired velocity :math:`v_j^*` is its mean velocity over the episode's first
``task.sfm.desired_steps`` states (default 1: the velocity in the t = 0 state, the same
information LIN gets). See :func:`fit_social_force`.

The LSTM (Social-LSTM encoder–decoder, :mod:`dslearn.models.lstm`) is trained offline on the
positions the network estimates when it tracks the training episodes with LIN and consensus
on measurements (CM), the nodes' estimates combined by their information (:func:`cm_fused`)
— the paper's VI-C recipe; one window of ``obs_len + pred_len`` states per episode (sliding
if episodes are longer).
"""

from __future__ import annotations

import logging
import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig
from torch import Tensor

from dslearn.fusion.strategies import FUSIONS, Fusion, make_fusion
from dslearn.fusion.weights import consensus_weights
from dslearn.data.episodes import CRITERIA, SPLITS, extract_episodes, split_episodes
from dslearn.errors import ConfigError, as_list, check_choice, check_positive
from dslearn.models import ConstantVelocity, LinearPositionObservation
from dslearn.models.base import MotionModel
from dslearn.learning.gp import OnlineGP
from dslearn.models.social_force import SocialForce
from dslearn.sim.network import SensorNetwork
from dslearn.sim.real import arena_network, scene_extent
from dslearn.sim.scenario import episode_streams, measure
from dslearn.sim.scenario import Episodes
from dslearn.filters.distributed import initial_belief, prediction_error, track, tracking_metrics
from dslearn.types import JITTER, POS, VEL, StepContext, agents, joint, safe_cholesky

log = logging.getLogger(__name__)

TASK = "ethucy_tracking"
PROTOCOLS = ("tables", "data_size")
MODELS = ("gp", "gp_cv", "lin", "sfm", "lstm")
DTYPES = {"float64": torch.float64, "float32": torch.float32}
FIT_ON = ("truth", "fused")


# --------------------------------------------------------------------------------------------
# SFM with per-episode desired velocities, and its fit
# --------------------------------------------------------------------------------------------
def episode_social_force(num_agents: int, tau: float = 1.0, alpha: float = 0.0, beta: float = 1.0,
                         noise_std: float = 0.1) -> SocialForce:
    r"""The social force model of :mod:`dslearn.models.social_force` (the same code, bounded
    interactions included) with shared :math:`(\tau, \alpha, \beta)`; each episode's desired
    velocities are set with :meth:`~dslearn.models.social_force.SocialForce.set_desired`
    ``(B, A, 2)`` before tracking or rolling out a batch of episodes."""
    return SocialForce([[0.0, 0.0]] * int(num_agents), tau, alpha, beta, noise_std)


def desired_velocity(states: Tensor, desired_steps: int = 1) -> Tensor:
    """Each agent's mean velocity over the first ``desired_steps`` states: ``(B, K+1, 4A) -> (B, A, 2)``."""
    return agents(states[:, :desired_steps])[..., VEL].mean(1)


def _rollout_error(model: SocialForce, states: Tensor, ctx: StepContext) -> Tensor:
    """Mean position error of the roll-out from ``states[:, 0]`` (differentiable)."""
    x = states[:, 0]
    errs = []
    for t in range(1, states.shape[1]):
        x = model(x, ctx)
        errs.append((agents(x)[..., POS] - agents(states[:, t])[..., POS]).norm(dim=-1))
    return torch.stack(errs).mean()


def fit_social_force(
    states: Tensor,
    dt: float,
    desired_steps: int = 1,
    tau_grid=(0.25, 0.5, 1.0, 2.0, 4.0, 8.0),
    alpha_grid=(0.0, 0.5, 1.0, 2.0, 4.0, 8.0),
    beta_grid=(0.25, 0.5, 1.0, 2.0, 4.0),
    refine_iters: int = 150,
    refine_lr: float = 0.05,
) -> tuple[dict[str, float], float]:
    r"""Fit shared SFM parameters to trajectories by roll-out error.

    Objective: mean over episodes, steps t = 1..K and agents of
    :math:`\|\hat x_j^t - x_j^t\|` where :math:`\hat x` is the SFM roll-out from the state at
    t = 0 with :math:`v_j^*` = :func:`desired_velocity`. Grid search over
    ``tau_grid x alpha_grid x beta_grid`` (only :math:`\tau \ge \Delta t`: a shorter relaxation
    time makes the Euler step overshoot; largest :math:`\tau` first, so where the error does not
    depend on :math:`\tau` the weakest relaxation is kept), then ``refine_iters`` Adam steps on
    :math:`(\log\tau, \alpha, \log\beta)` from the best grid point (:math:`\alpha` projected to
    :math:`\ge 0`, :math:`\tau \ge \Delta t`); the better of the two is returned.

    Args:
        states: ``(B, K+1, 4A)`` trajectories (truth or fused estimates).
    Returns:
        ``({"tau", "alpha", "beta"}, objective)``.
    """
    states = states.detach().to(torch.float64)
    a = states.shape[-1] // 4
    ctx = StepContext(dt=float(dt))
    model = episode_social_force(a).set_desired(desired_velocity(states, desired_steps))
    best, best_loss = None, math.inf
    taus = sorted((float(v) for v in tau_grid if float(v) >= dt - 1e-12), reverse=True) or [float(dt)]
    with torch.no_grad():
        for tau in taus:  # largest first: where the error does not depend on tau, keep the weakest relaxation
            for alpha in alpha_grid:
                for beta in beta_grid:
                    model.set_parameters(float(tau), float(alpha), float(beta))
                    loss = float(_rollout_error(model, states, ctx))
                    if loss < best_loss:
                        best, best_loss = (float(tau), float(alpha), float(beta)), loss
    log_tau = torch.tensor(math.log(best[0]), dtype=torch.float64, requires_grad=True)
    alpha = torch.tensor(best[1], dtype=torch.float64, requires_grad=True)
    log_beta = torch.tensor(math.log(best[2]), dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([log_tau, alpha, log_beta], lr=refine_lr)
    for _ in range(int(refine_iters)):
        opt.zero_grad()
        model.set_parameters(log_tau.exp(), alpha, log_beta.exp())
        loss = _rollout_error(model, states, ctx)
        if not torch.isfinite(loss):
            break
        loss.backward()
        opt.step()
        with torch.no_grad():
            alpha.clamp_(min=0.0)
            log_tau.clamp_(math.log(dt), math.log(1e3))
            log_beta.clamp_(math.log(1e-2), math.log(1e2))
    with torch.no_grad():
        model.set_parameters(log_tau.exp(), alpha.detach(), log_beta.exp())
        refined = float(_rollout_error(model, states, ctx))
    if math.isfinite(refined) and refined < best_loss:
        best, best_loss = (float(log_tau.detach().exp()), float(alpha.detach()), float(log_beta.detach().exp())), refined
    return {"tau": best[0], "alpha": best[1], "beta": best[2]}, best_loss


# --------------------------------------------------------------------------------------------
# configuration
# --------------------------------------------------------------------------------------------
def _get(node, key, default=None):
    return node.get(key, default) if node is not None and hasattr(node, "get") else default


def _int(field, v, minimum=1):
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < minimum:
        raise ConfigError(f"{field}={v!r} must be an integer >= {minimum}")
    return int(v)


def validate(cfg: DictConfig) -> None:
    """Check ``cfg.task`` (and the groups it uses) before any work; ConfigError names the field."""
    t = cfg.task
    check_choice("dtype", cfg.get("dtype", "float64"), tuple(DTYPES))
    dev = str(cfg.get("device", "cpu"))
    check_choice("device", dev.split(":")[0], ("cpu", "cuda"))
    if dev.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError("device=cuda was asked for but no CUDA device is available; use device=cpu")
    check_choice("task.protocol", t.protocol, PROTOCOLS)
    models = as_list("task.models", t.models, none_as_empty=True)
    if not models:
        raise ConfigError("task.models must name at least one of " + str(list(MODELS)))
    for m in models:
        check_choice("task.models", m, MODELS)
    if t.protocol == "data_size":
        if "lstm" not in models or not {"gp", "gp_cv"} & set(models):
            raise ConfigError("task.models must contain 'lstm' and 'gp' (or 'gp_cv') for task.protocol=data_size")
    from dslearn.data.ethucy import ALL_SCENES

    scenes = as_list("task.scenes", t.scenes, none_as_empty=True)
    for s in scenes:
        check_choice("task.scenes", s, tuple(ALL_SCENES))
    if not scenes and not (t.protocol == "data_size" and t.get("synthetic", False)):
        raise ConfigError("task.scenes must name at least one scene (or set task.synthetic=true for data_size)")
    check_choice("task.convention", t.convention, ("physical", "benchmark"))
    check_positive("task.dt", t.dt)
    _int("task.steps", t.steps, 2)
    _int("task.agents", t.agents, 2)
    check_positive("task.max_dist", t.max_dist)
    _int("task.stride", t.stride, 1)
    check_choice("task.criterion", t.criterion, CRITERIA)
    check_positive("task.min_speed", t.min_speed, strict=False)
    check_choice("task.split", t.split, SPLITS)
    if t.split == "scene":
        raise ConfigError(
            "task.split=scene is not supported by this study: the GP's inputs are absolute positions "
            "in each scene's own frame and the network is placed around one scene; use time or random"
        )
    if not 0.0 < float(t.test_fraction) < 1.0:
        raise ConfigError(f"task.test_fraction={t.test_fraction!r} must be in (0, 1)")
    _int("task.train_episodes", t.train_episodes, 1)
    _int("task.test_episodes", t.test_episodes, 1)
    _int("task.plot_episodes", t.plot_episodes, 0)
    n = t.network
    _int("task.network.num_sensors", n.num_sensors, 1)
    _int("task.network.k_nearest", n.k_nearest, 1)
    check_positive("task.network.sensing_range", n.sensing_range)
    check_positive("task.network.meas_std", n.meas_std)
    check_positive("task.network.margin", n.margin, strict=False)
    check_positive("task.lin.noise_std", t.lin.noise_std)
    s = t.sfm
    check_positive("task.sfm.noise_std", s.noise_std)
    check_choice("task.sfm.fit_on", s.fit_on, FIT_ON)
    _int("task.sfm.desired_steps", s.desired_steps, 1)
    if s.desired_steps > t.steps + 1:
        raise ConfigError(f"task.sfm.desired_steps={s.desired_steps} must be <= task.steps + 1")
    _int("task.sfm.refine_iters", s.refine_iters, 0)
    for k in ("tau", "beta"):
        vals = as_list(f"task.sfm.grid.{k}", s.grid[k], none_as_empty=True)
        if not vals:
            raise ConfigError(f"task.sfm.grid.{k} must not be empty")
        for v in vals:
            check_positive(f"task.sfm.grid.{k}", v)
    for v in as_list("task.sfm.grid.alpha", s.grid.alpha, none_as_empty=True) or [None]:
        check_positive("task.sfm.grid.alpha", v, strict=False)
    lstm = t.lstm
    for k in ("embed", "hidden", "obs_len", "pred_len"):
        _int(f"task.lstm.{k}", lstm[k], 1)
    from dslearn.models.lstm import schedule_from_config

    sched = schedule_from_config(lstm, prefix="task.lstm")
    if "patience" in sched:
        vf = lstm.get("val_fraction", 0.2)
        check_positive("task.lstm.val_fraction", vf)
        if float(vf) >= 1.0:
            raise ConfigError(f"task.lstm.val_fraction={vf!r} must be in (0, 1)")
    check_choice("task.lstm.pooling", lstm.pooling, ("none", "social"))
    if lstm.obs_len + lstm.pred_len > t.steps + 1:
        raise ConfigError(
            f"task.lstm.obs_len + task.lstm.pred_len = {lstm.obs_len + lstm.pred_len} must be <= task.steps + 1 "
            f"= {t.steps + 1} (the LSTM's training windows are cut from the episodes)"
        )
    if t.protocol == "data_size":
        sizes = as_list("task.data_sizes", t.data_sizes, none_as_empty=True)
        if not sizes:
            raise ConfigError("task.data_sizes must list at least one number of training episodes")
        for v in sizes:
            _int("task.data_sizes", v, 1)
        _int("task.seeds", t.seeds, 1)
    if {"gp", "gp_cv"} & set(models):
        check_choice("model.kind", _get(cfg.model, "kind", cfg.model.name), ("gp",))
    check_choice("consensus.name", cfg.consensus.name, FUSIONS)
    if cfg.consensus.name == "centralized":
        raise ConfigError("consensus.name=centralized is a reference, not a distributed filter; use hybrid, cm, ci, ce or individual")
    check_choice("consensus.weights", cfg.consensus.weights, ("uniform", "metropolis", "max_degree"))
    _int("consensus.iterations", cfg.consensus.iterations, 0)
    check_positive("filter.prior_pos_std", cfg.filter.prior_pos_std)
    check_positive("filter.prior_vel_std", cfg.filter.prior_vel_std)


# --------------------------------------------------------------------------------------------
# data
# --------------------------------------------------------------------------------------------
@dataclass
class Data:
    """One data source prepared for the protocol.

    ``train`` holds the training pool in the order online learning sees it; ``test`` the test
    episodes. ``train_fused`` (filled later) are the CM-fused estimates of ``train``.
    """

    label: str  # scene name or "synthetic"
    kind: str  # "real" | "synthetic"
    train: Episodes
    test: Episodes
    network: SensorNetwork
    ctx: StepContext
    area: tuple[float, float, float, float]  # (xmin, xmax, ymin, ymax): where the diffuse prior puts the targets
    num_agents: int
    info: dict


def _episodes_to(ep: Episodes, dtype, device) -> Episodes:
    return Episodes(ep.states.to(device, dtype), ep.meas.to(device, dtype), ep.visible.to(device))


def real_data(cfg: DictConfig, scene_name: str, seed: int, max_train: int, dtype, device) -> Data:
    """Episodes of one ETH/UCY scene, its network and measurements (all seeded by ``seed``)."""
    from dslearn.data.ethucy import load_scene

    t = cfg.task
    scene = load_scene(scene_name, root=t.get("data_root"), convention=t.convention)
    eps = extract_episodes(
        scene, int(t.agents), int(t.steps), float(t.dt), float(t.max_dist), int(t.stride), str(t.criterion), float(t.min_speed)
    )
    train_idx, test_idx = split_episodes(eps, str(t.split), float(t.test_fraction), None, seed)
    n_tr, n_te = min(max_train, len(train_idx)), min(int(t.test_episodes), len(test_idx))
    if n_tr < 1 or n_te < 1:
        raise ConfigError(
            f"task.scenes: scene {scene_name!r} gives {len(train_idx)} training and {len(test_idx)} test episodes "
            f"with these settings; lower task.max_dist/task.min_speed/task.stride or choose another scene"
        )
    if n_tr < max_train or n_te < int(t.test_episodes):
        warnings.warn(
            f"scene {scene_name}: only {len(train_idx)} training / {len(test_idx)} test episodes available "
            f"(asked {max_train} / {int(t.test_episodes)}); using {n_tr} / {n_te}"
        )
    rng = np.random.default_rng(seed + 17)
    test_sel = np.sort(rng.choice(test_idx, size=n_te, replace=False)) if n_te < len(test_idx) else test_idx
    tr, te = eps.select(train_idx[:n_tr]), eps.select(test_sel)
    net = arena_network(
        scene_extent(torch.tensor(scene.df[["x", "y"]].to_numpy())),
        int(t.network.num_sensors),
        int(t.network.k_nearest),
        float(t.network.sensing_range),
        float(t.network.meas_std),
        float(t.network.margin),
    )
    # one measurement-noise stream per episode: an episode's measurements do not depend on how
    # many episodes are drawn
    test = measure(te.states, net, episode_streams(int(seed), "test", 0, len(te.states)))
    train = measure(tr.states, net, episode_streams(int(seed), "train", 0, len(tr.states)))
    ext = tuple(float(v) for v in scene_extent(torch.tensor(scene.df[["x", "y"]].to_numpy())))
    info = {
        "episodes_total": len(eps),
        "train_pool": len(train_idx),
        "test_pool": len(test_idx),
        "scene_dt": scene.dt,
        "test_meta": te.meta,
        "visible_frac": float(test.visible[: net.num_sensors].any(0).float().mean()),
    }
    return Data(
        scene_name, "real", _episodes_to(train, dtype, device), _episodes_to(test, dtype, device), net,
        StepContext(dt=float(t.dt)), ext, int(t.agents), info,
    )


def synthetic_data(cfg: DictConfig, seed: int, max_train: int, dtype, device) -> Data:
    """The Yu synthetic scenario and network (``cfg.scenario``, ``cfg.network``)."""
    from dslearn.studies.yu import build_network, build_scenario

    scenario, net = build_scenario(cfg.scenario), build_network(cfg.network)
    test = scenario.sample(int(cfg.task.test_episodes), net, episode_streams(seed, "test", 0, int(cfg.task.test_episodes)))
    train = scenario.sample(max_train, net, episode_streams(seed, "train", 0, max_train))
    info = {"episodes_total": max_train + int(cfg.task.test_episodes), "scene_dt": scenario.dt, "test_meta": None}
    return Data(
        "synthetic", "synthetic", _episodes_to(train, dtype, device), _episodes_to(test, dtype, device), net,
        scenario.ctx(), tuple(scenario.area), scenario.num_agents, info,
    )


# --------------------------------------------------------------------------------------------
# models and evaluation
# --------------------------------------------------------------------------------------------
def _fusion(cfg: DictConfig, net: SensorNetwork, name: str | None = None) -> Fusion:
    c = cfg.consensus
    w = consensus_weights(net.adjacency, c.weights)
    return make_fusion(name or c.name, w, int(c.iterations), c.omega)


class ConstantVelocityMeanGP(OnlineGP):
    r""":class:`~dslearn.models.gp.OnlineGP` whose prior mean is the constant-velocity step,
    :math:`m(y) = F_{cv} y` (``p + v \Delta t``, ``v``), so the GP learns the deviation of the
    one-step transition from constant velocity. Far from its data it falls back to LIN instead
    of to "stand still" (``mean: identity``) or to the origin (``mean: zero``).
    """

    def __init__(self, *args, dt: float, **kwargs):
        kwargs["mean"] = "identity"  # passes the parent's checks; both mean methods are overridden
        super().__init__(*args, **kwargs)
        a = self.input_dim // 4
        self.F = ConstantVelocity(a).matrix(float(dt), self.dtype_, self.device_)

    def prior_mean(self, x: Tensor) -> Tensor:
        return x @ self.F.to(x).T

    def prior_mean_jacobian(self, x: Tensor) -> Tensor:
        return self.F.to(x).expand(*x.shape[:-1], *self.F.shape)


def _gp(cfg: DictConfig, data: Data, dtype, device, cv_mean: bool = False) -> MotionModel:
    """The GP of ``cfg.model``; with ``cv_mean`` its prior mean is replaced by the CV step."""
    from dslearn.studies.yu import build_motion_model

    stub = SimpleNamespace(num_agents=data.num_agents, state_dim=4 * data.num_agents)
    model = build_motion_model(cfg.model, stub, data.network.num_nodes, dtype, device)
    if cv_mean:
        c, d = cfg.model, 4 * data.num_agents
        model.gp = ConstantVelocityMeanGP(
            data.network.num_nodes, d, d, c.outputscale, c.lengthscale, c.noise_std, dt=data.ctx.dt, dtype=dtype, device=device
        )
    return model


def _gp_name(cfg, cv_mean: bool) -> str:
    return f"{cfg.model.name}_cv" if cv_mean else str(cfg.model.name)


def _init(cfg, data: Data, ep: Episodes, fusion: Fusion):
    return initial_belief(ep, data.network, data.ctx.dt, fusion, data.area, cfg.filter.prior_pos_std, cfg.filter.prior_vel_std)


@torch.no_grad()
def cm_fused(cfg: DictConfig, data: Data, ep: Episodes) -> Tensor:
    r"""Track ``ep`` with LIN and consensus on measurements (CM); the nodes' estimates combined
    by their information, :math:`\hat y = (\sum_i \Omega_i)^{-1} \sum_i \Omega_i \hat y_i`,
    ``(B, K+1, Dx)``.

    The initial belief is fused by CM like every later step, and a node that learns nothing
    about a target holds the diffuse prior (near-zero information): the information weighting
    gives such a node almost no weight, where a plain node average would drag the estimate
    towards the prior's mean. After consensus the nodes agree closely, and the combination is
    close to their average.
    """
    net = data.network
    fusion = _fusion(cfg, net, "cm")
    lin = ConstantVelocity(data.num_agents, float(cfg.task.lin.noise_std))
    obs = LinearPositionObservation(net.meas_std)
    res = track(ep, net, lin, obs, fusion, data.ctx, _init(cfg, data, ep, fusion))
    info = res.info.sum(0)
    q = (res.info @ res.mean.unsqueeze(-1)).sum(0)
    return torch.cholesky_solve(q, safe_cholesky(info)).squeeze(-1)


def train_online(cfg, model, data: Data, fusion: Fusion, upto: int, seen: int) -> int:
    """Algorithm 1 on training episodes ``seen..upto-1`` (one at a time). Returns ``upto``."""
    obs = LinearPositionObservation(data.network.meas_std)
    gate = cfg.filter.get("learn_gate_std")
    fit_every = getattr(model, "fit_every", 0)
    for k in range(seen, upto):
        ep = data.train.select(slice(k, k + 1))
        track(ep, data.network, model, obs, fusion, data.ctx, _init(cfg, data, ep, fusion), learn=True, learn_gate_std=gate)
        if fit_every and (k + 1) % fit_every == 0:
            model.fit()
    return upto


def _rows(metrics: dict[str, Tensor], net: SensorNetwork, **keys) -> pd.DataFrame:
    frames = []
    s = net.num_nodes
    kinds = ["sensor" if bool(net.is_sensor[i]) else "comm" for i in range(s)]
    for name, val in metrics.items():
        v = val.detach().cpu().double()
        b = v.shape[1]
        frames.append(
            pd.DataFrame(
                {
                    "node": [net.names[i] for i in range(s) for _ in range(b)],
                    "node_kind": [kinds[i] for i in range(s) for _ in range(b)],
                    "episode": list(range(b)) * s,
                    "metric": name,
                    "value": v.reshape(-1).numpy(),
                }
            )
        )
    df = pd.concat(frames, ignore_index=True)
    for i, (k, v) in enumerate(keys.items()):
        df.insert(i, k, v)
    return df


@torch.no_grad()
def evaluate_tracking(cfg, model, data: Data, fusion: Fusion, per_node: bool) -> dict[str, Tensor]:
    """Tracking metrics on the test episodes plus the prediction error (Table II/IV protocol)."""
    obs = LinearPositionObservation(data.network.meas_std)
    res = track(data.test, data.network, model, obs, fusion, data.ctx, _init(cfg, data, data.test, fusion))
    m = tracking_metrics(res, data.test.states)
    m["pred_err"] = prediction_error(model, data.test.states, data.network.num_nodes, data.ctx, per_node=per_node)
    return m


def _lstm_cfg(t) -> dict:
    keys = ("embed", "hidden", "obs_len", "pred_len", "pooling", "grid", "neighbourhood")
    return {k: t.lstm[k] for k in keys if k in t.lstm}


def lstm_windows(fused: Tensor, obs_len: int, pred_len: int) -> tuple[Tensor, Tensor]:
    """Sliding windows of fused positions: ``(B, K+1, 4A) -> (N, obs_len + pred_len, A, 2)``, and
    the episode each window was cut from, ``(N,)`` (a validation split holds out whole episodes)."""
    pos = agents(fused)[..., POS]
    w = obs_len + pred_len
    k1 = pos.shape[1]
    starts = range(0, k1 - w + 1)
    groups = torch.arange(pos.shape[0]).repeat(len(starts))
    return torch.cat([pos[:, s : s + w] for s in starts], 0), groups


def train_lstm_model(cfg: DictConfig, data: Data, windows: tuple[Tensor, Tensor], seed: int, dtype, device):
    """A fresh Social-LSTM trained on ``windows`` (from :func:`lstm_windows`) with the schedule of
    ``task.lstm`` (the paper's fixed one, or early stopping on held-out episodes); returns
    ``(model, loss curve)``; with early stopping the curve's ``attrs["restored_epoch"]`` is the
    epoch whose weights were kept."""
    from dslearn.models.lstm import SocialLSTM, holdout_split, schedule_from_config, train_lstm

    t = cfg.task
    kw = _lstm_cfg(t)
    win, groups = windows
    sched = schedule_from_config(t.lstm, prefix="task.lstm")
    val = None
    if "patience" in sched:
        win, val = holdout_split(win, groups, float(t.lstm.get("val_fraction", 0.2)), seed)
        val = val.to(device, dtype)
    torch.manual_seed(seed)
    model = SocialLSTM(data.num_agents, dt=data.ctx.dt, dtype=dtype, device=device, **kw)
    curve = train_lstm(model, win.to(device, dtype), **sched, val_windows=val, seed=int(seed),
                       progress=bool(cfg.get("progress", False)))
    return model, curve


def _pred_rows(model, src: Data, per_node: bool, **keys) -> pd.DataFrame:
    err = prediction_error(model, src.test.states, src.network.num_nodes, src.ctx, per_node=per_node)
    return _rows({"pred_err": err}, src.network, **keys)


def trajectory_rows(model, src: Data, per_node: bool, n: int, **keys) -> pd.DataFrame:
    """Predicted positions of the first ``n`` test episodes (node ``sensor1``): rows ``pred_x``/``pred_y``
    with ``step`` (0..K; step 0 is the given true state) and ``agent`` columns."""
    if n <= 0:
        return pd.DataFrame()
    st = src.test.states  # the whole test batch (per-episode model state, e.g. SFM's v*), first n kept
    x0 = st[:, 0]
    k = st.shape[1] - 1
    with torch.no_grad():
        if per_node:
            roll = model.rollout(x0.unsqueeze(0).expand(src.network.num_nodes, *x0.shape).contiguous(), k, src.ctx)[0]
        else:
            roll = model.rollout(x0, k, src.ctx)
    return position_rows(torch.cat([x0.unsqueeze(1), roll], 1), src, n, **keys)


def position_rows(traj: Tensor, src: Data, n: int, **keys) -> pd.DataFrame:
    """Rows ``pred_x``/``pred_y`` (node ``sensor1``, ``node_kind`` trajectory) of the positions in
    the first ``n`` joint-state trajectories ``traj (B, K+1, Dx)``."""
    if n <= 0:
        return pd.DataFrame()
    pos = agents(traj[:n])[..., POS].detach().cpu().double().numpy()  # (n, K+1, A, 2)
    b, k1, a, _ = pos.shape
    ep, step, ag = np.meshgrid(np.arange(b), np.arange(k1), np.arange(a), indexing="ij")
    frames = []
    for c, name in ((0, "pred_x"), (1, "pred_y")):
        frames.append(
            pd.DataFrame(
                {"node": src.network.names[0], "node_kind": "trajectory", "episode": ep.ravel(), "step": step.ravel(),
                 "agent": ag.ravel(), "metric": name, "value": pos[..., c].ravel()}
            )
        )
    df = pd.concat(frames, ignore_index=True)
    for i, (kk, v) in enumerate(keys.items()):
        df.insert(i, kk, v)
    return df


# --------------------------------------------------------------------------------------------
# protocols
# --------------------------------------------------------------------------------------------
def _fit_sfm(cfg, data: Data, n_train: int, fused: Tensor | None) -> tuple[SocialForce, dict, float]:
    s = cfg.task.sfm
    src = data.train.states[:n_train] if s.fit_on == "truth" else fused[:n_train]
    params, loss = fit_social_force(
        src.cpu(), data.ctx.dt, int(s.desired_steps), tuple(s.grid.tau), tuple(s.grid.alpha), tuple(s.grid.beta),
        int(s.refine_iters), float(s.refine_lr),
    )
    model = episode_social_force(data.num_agents, noise_std=float(s.noise_std), **params)
    model.set_desired(desired_velocity(data.test.states, int(s.desired_steps)))
    return model, params, loss


def protocol_tables(cfg: DictConfig, data: Data, seed: int, dtype, device) -> pd.DataFrame:
    """Tables III–IV and Fig. 4 rows for one data source."""
    t = cfg.task
    models = list(t.models)
    n_train = len(data.train)
    fusion = _fusion(cfg, data.network)
    net = data.network
    base = dict(data=data.kind, scene=data.label, train_episodes=n_train, test_episodes=len(data.test), seed=seed)
    frames, times = [], {}
    n_plot = min(int(t.plot_episodes), len(data.test))

    def add(model_name, cons, df):
        for i, (k, v) in enumerate({"model": model_name, "consensus": cons}.items()):
            df.insert(i, k, v)
        frames.append(df)

    cover = {"visible_frac": data.info.get("visible_frac", float("nan")), "train_pool": data.info.get("train_pool", float("nan"))}
    for k, v in cover.items():  # fraction of (test episode, step, pedestrian) seen by >= 1 sensor; episodes available
        add("-", "-", pd.DataFrame({"node": ["avg"], "node_kind": ["param"], "episode": [0], "metric": [k], "value": [float(v)], **{kk: [vv] for kk, vv in base.items()}}))
    if n_plot:
        add("truth", "-", position_rows(data.test.states, data, n_plot, **base))
    if "lin" in models:
        t0 = time.perf_counter()
        lin = ConstantVelocity(data.num_agents, float(t.lin.noise_std))
        add("lin", fusion.name, _rows(evaluate_tracking(cfg, lin, data, fusion, False), net, **base))
        add("lin", fusion.name, trajectory_rows(lin, data, False, n_plot, **base))
        times["lin"] = time.perf_counter() - t0
    fused = None
    if "lstm" in models or ("sfm" in models and t.sfm.fit_on == "fused"):
        t0 = time.perf_counter()
        fused = cm_fused(cfg, data, data.train)
        times["cm_fuse"] = time.perf_counter() - t0
    if "sfm" in models:
        t0 = time.perf_counter()
        sfm, params, loss = _fit_sfm(cfg, data, n_train, fused)
        log.info("%s: SFM fitted on %s: %s (roll-out error %.3f)", data.label, t.sfm.fit_on, params, loss)
        add("sfm", fusion.name, _rows(evaluate_tracking(cfg, sfm, data, fusion, False), net, **base))
        add("sfm", fusion.name, trajectory_rows(sfm, data, False, n_plot, **base))
        for k, v in {**params, "fit_loss": loss}.items():
            add("sfm", "-", pd.DataFrame({"node": ["avg"], "node_kind": ["param"], "episode": [0], "metric": [f"sfm_{k}"], "value": [v], **{kk: [vv] for kk, vv in base.items()}}))
        times["sfm"] = time.perf_counter() - t0
    for key in ("gp", "gp_cv"):
        if key not in models:
            continue
        t0 = time.perf_counter()
        gp = _gp(cfg, data, dtype, device, key == "gp_cv")
        train_online(cfg, gp, data, fusion, n_train, 0)
        name = _gp_name(cfg, key == "gp_cv")
        add(name, fusion.name, _rows(evaluate_tracking(cfg, gp, data, fusion, True), net, **base))
        add(name, fusion.name, trajectory_rows(gp, data, True, n_plot, **base))
        times[key] = time.perf_counter() - t0
    if "lstm" in models:
        t0 = time.perf_counter()
        win = lstm_windows(fused, int(t.lstm.obs_len), int(t.lstm.pred_len))
        lstm, curve = train_lstm_model(cfg, data, win, seed, dtype, device)
        add("lstm", "cm", _pred_rows(lstm, data, False, **base))
        add("lstm", "cm", trajectory_rows(lstm, data, False, n_plot, **base))
        last = curve.iloc[int(curve.attrs.get("restored_epoch", len(curve))) - 1]
        add("lstm", "cm", pd.DataFrame({"node": ["avg"], "node_kind": ["param"], "episode": [0], "metric": ["lstm_train_loss"], "value": [float(last["train_loss"])], **{kk: [vv] for kk, vv in base.items()}}))
        times["lstm"] = time.perf_counter() - t0
    log.info("%s: component times %s", data.label, {k: round(v, 1) for k, v in times.items()})
    df = pd.concat(frames, ignore_index=True)
    df.attrs["times"] = times
    return df


def protocol_data_size(cfg: DictConfig, data: Data, seed: int, dtype, device) -> pd.DataFrame:
    """Fig. 5 rows: GP (online, consensus EKF) and LSTM (offline, CM-fused) prediction error vs
    number of training episodes, for one data source and seed."""
    t = cfg.task
    sizes = sorted({min(int(v), len(data.train)) for v in t.data_sizes})
    fusion = _fusion(cfg, data.network)
    net = data.network
    frames = []
    base = dict(data=data.kind, scene=data.label, test_episodes=len(data.test), seed=seed)
    keys = [k for k in ("gp", "gp_cv") if k in t.models]
    gps = {k: _gp(cfg, data, dtype, device, k == "gp_cv") for k in keys}
    fused = cm_fused(cfg, data, data.train)
    seen = 0
    for n in sizes:
        for k, gp in gps.items():
            train_online(cfg, gp, data, fusion, n, seen)
            m = evaluate_tracking(cfg, gp, data, fusion, True)
            df = _rows(m, net, train_episodes=n, **base)
            df.insert(0, "model", _gp_name(cfg, k == "gp_cv"))
            df.insert(1, "consensus", fusion.name)
            frames.append(df)
        seen = n
        win = lstm_windows(fused[:n], int(t.lstm.obs_len), int(t.lstm.pred_len))
        lstm, _ = train_lstm_model(cfg, data, win, seed * 7919 + n, dtype, device)
        df = _pred_rows(lstm, data, False, train_episodes=n, **base)
        df.insert(0, "model", "lstm")
        df.insert(1, "consensus", "cm")
        frames.append(df)
        log.info("%s seed %d: n=%d done", data.label, seed, n)
    return pd.concat(frames, ignore_index=True)


def run(cfg: DictConfig) -> pd.DataFrame:
    """Task entry point for ``dslearn-run`` (see the module docstring)."""
    validate(cfg)
    t = cfg.task
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    dtype = DTYPES[cfg.get("dtype", "float64")]
    device = torch.device(str(cfg.get("device", "cpu")))
    seed0 = int(cfg.seed)
    jitter0 = JITTER.count
    frames = []
    t_start = time.perf_counter()
    if t.protocol == "tables":
        for scene in t.scenes:
            torch.manual_seed(seed0)
            data = real_data(cfg, str(scene), seed0, int(t.train_episodes), dtype, device)
            frames.append(protocol_tables(cfg, data, seed0, dtype, device))
    else:
        max_train = max(int(v) for v in t.data_sizes)
        sources = [("real", str(s)) for s in t.scenes] + ([("synthetic", "synthetic")] if t.get("synthetic", False) else [])
        for kind, label in sources:
            for i in range(int(t.seeds)):
                seed = seed0 + i
                torch.manual_seed(seed)
                if kind == "real":
                    data = real_data(cfg, label, seed, max_train, dtype, device)
                else:
                    data = synthetic_data(cfg, seed, max_train, dtype, device)
                frames.append(protocol_data_size(cfg, data, seed, dtype, device))
    df = pd.concat(frames, ignore_index=True)
    df.insert(2, "protocol", str(t.protocol))
    df.insert(3, "agents", int(t.agents))
    for col in ("step", "agent"):
        if col not in df.columns:
            df[col] = np.nan
    df.attrs["jitter_events"] = JITTER.count - jitter0
    log.info("%s/%s finished in %.1fs", TASK, t.protocol, time.perf_counter() - t_start)
    return df


def report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path) -> str:
    """Tables III–IV analogue (Markdown + CSV), Fig. 4 and Fig. 5 analogues (PNG)."""
    from dslearn.plotting.real import real_report

    return real_report(results, summary, out_dir)
