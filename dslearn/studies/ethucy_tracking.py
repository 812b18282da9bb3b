r"""Study ``ethucy_tracking``: Yu et al. Section VI (robot study) on real pedestrians (ETH/UCY).

Two protocols (``task.protocol``):

``tables`` (``dslearn-run experiment=real_tables``) — Tables III–IV and Fig. 4 analogue. Per
scene (``task.scenes``): episodes of ``m`` interacting pedestrians (:mod:`dslearn.data.episodes`,
physical time; a scene is a data set of ``task.datasets``, ``conf/dataset/<name>.yaml``), a time
split inside the scene, a LiDAR-like network around the scene
(:mod:`dslearn.sim.real`), then

* tracking error of the distributed EKF (``cfg.consensus``, hybrid by default) with the GP
  (``cfg.model``, learned online through Algorithm 1 on the training episodes), the same GP
  with a constant-velocity prior mean (``gp_cv``, :class:`~dslearn.learning.means.ConstantVelocityMean`), LIN and SFM;
* prediction error (roll-out from the true state at t = 0, the paper's V-C protocol) of GP,
  LIN, SFM and LSTM;
* predicted trajectories of a few test episodes (rows ``pred_x``/``pred_y``) for the figure.

``data_size`` (``dslearn-run experiment=gp_vs_lstm``) — Fig. 5 analogue: prediction error of the
GP (learned online through the consensus EKF, evaluated after ``n`` training episodes) and of
the LSTM (trained offline on the first ``n`` training episodes fused by consensus on
measurements) for ``n`` in ``task.data_sizes``, ``task.seeds`` seeds, on the real scenes and
on the synthetic Yu scenario (``cfg.scenario`` / ``cfg.network``).

SFM on real data (the true model is unknown): its shared :math:`(\tau, \alpha, \beta)` are
fitted to the training episodes' roll-outs (:mod:`dslearn.learning.sfm_fit`).

The LSTM (Social-LSTM encoder–decoder, :mod:`dslearn.learning.lstm`) is trained offline on the
positions the network estimates when it tracks the training episodes with LIN and consensus
on measurements (CM), the nodes' estimates combined by their information (:func:`cm_fused`)
— the paper's VI-C recipe; one window of ``obs_len + pred_len`` states per episode (sliding
if episodes are longer).
"""

from __future__ import annotations

import copy
import logging
import time
from types import SimpleNamespace

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf, open_dict
from torch import Tensor

from dslearn.compose import build_fusion, build_motion_model, build_network, build_predict, build_scenario, resolve_dtype
from dslearn.data.datasets import load_dataset, task_datasets
from dslearn.filters.distributed import initial_belief, track
from dslearn.fusion.strategies import ConsensusOnMeasurements, Fusion
from dslearn.learning.lstm import lstm_windows, train_lstm_model
from dslearn.learning.online import OnlineLearner
from dslearn.learning.sfm_fit import fit_episode_social_force
from dslearn.metrics import metric_rows, prediction_error, tracking_metrics
from dslearn.models import ConstantVelocity, LinearPositionObservation
from dslearn.models.base import MotionModel
from dslearn.sim.network import SensorNetwork
from dslearn.sim.real import Data, real_source
from dslearn.sim.scenario import Episodes, Measurements, sample_split
from dslearn.types import POS, agents, safe_cholesky

log = logging.getLogger(__name__)

TASK = "ethucy_tracking"



# data --------------------------------------------------------------------------------------
def real_data(cfg: DictConfig, scene_name: str, seed: int, max_train: int, dtype, device) -> Data:
    """Episodes of one scene (a data set of ``task.datasets``), its network and measurements (all
    seeded by ``seed``; :func:`dslearn.sim.real.real_source`)."""
    t = cfg.task
    scene = load_dataset(task_datasets(t)[scene_name], t.get("data_root"), str(t.convention))
    return real_source(scene, t, seed, max_train, dtype, device)


def synthetic_data(cfg: DictConfig, seed: int, max_train: int, dtype, device) -> Data:
    """The Yu synthetic scenario and network (``cfg.scenario``, ``cfg.network``)."""
    scenario, net = build_scenario(cfg), build_network(cfg)
    test, train = sample_split(scenario, net, seed, int(cfg.task.test_episodes), max_train, dtype, device)
    info = {"episodes_total": max_train + int(cfg.task.test_episodes), "scene_dt": scenario.dt, "test_meta": None}
    return Data("synthetic", "synthetic", train, test, net, scenario.ctx(), tuple(scenario.area), scenario.num_agents, info)


# models and evaluation ---------------------------------------------------------------------
def _fusion(cfg: DictConfig, net: SensorNetwork) -> Fusion:
    return build_fusion(cfg.consensus, net)


def _gp(cfg: DictConfig, data: Data, dtype, device, cv_mean: bool = False) -> MotionModel:
    """The GP of ``cfg.model``; with ``cv_mean`` its prior mean is replaced by the CV step."""
    stub = SimpleNamespace(num_agents=data.num_agents, state_dim=4 * data.num_agents)
    node = cfg.model
    if cv_mean:  # the same GP with the constant-velocity step as its prior mean (a mean module)
        node = OmegaConf.merge(node, {"mean": {"_target_": "dslearn.learning.means.ConstantVelocityMean", "dt": float(data.ctx.dt)}})
    if cfg.task.get("gp_inputs", "mean") != "mean":  # where the EKF evaluates the GP (GPMotionModel's `inputs`)
        node = copy.deepcopy(node)
        with open_dict(node):
            node.inputs = str(cfg.task.gp_inputs)
    model = build_motion_model(node, stub, data.network, dtype, device)
    return model


def _gp_name(cfg, cv_mean: bool) -> str:
    return f"{cfg.model.name}_cv" if cv_mean else str(cfg.model.name)


def _init(cfg, data: Data, ep: Measurements, fusion: Fusion):
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
    net, c = data.network, cfg.consensus
    fusion = ConsensusOnMeasurements.for_network(adjacency=net.adjacency, weights=c.weights,
                                                 iterations=int(c.iterations), omega=c.omega)
    lin = ConstantVelocity(data.num_agents, float(cfg.task.lin.noise_std))
    obs = LinearPositionObservation(net.meas_std)
    res = track(ep.measurements, net, lin, obs, fusion, data.ctx, _init(cfg, data, ep.measurements, fusion))
    info = res.info.sum(0)
    q = (res.info @ res.mean.unsqueeze(-1)).sum(0)
    return torch.cholesky_solve(q, safe_cholesky(info)).squeeze(-1)


def learner(cfg, model, data: Data, fusion: Fusion) -> OnlineLearner:
    """Algorithm 1 (:class:`~dslearn.learning.online.OnlineLearner`) for ``model`` on ``data``'s network, with
    the root ``filter`` group's prediction step (EKF, or ``filter=ukf``)."""
    return OnlineLearner(data.network, model, LinearPositionObservation(data.network.meas_std), fusion, data.ctx,
                         init=lambda ep: _init(cfg, data, ep, fusion), predict_step=build_predict(cfg),
                         learn_gate_std=cfg.filter.get("learn_gate_std"))


def train_online(alg: OnlineLearner, data: Data, upto: int) -> None:
    """Algorithm 1 on the training episodes the learner has not seen, up to ``upto`` (one at a time)."""
    for k in range(alg.seen, upto):
        alg.learn(data.train.measurements.select(slice(k, k + 1)))


def evaluate_tracking(alg: OnlineLearner, data: Data, per_node: bool) -> dict[str, Tensor]:
    """Tracking metrics on the test episodes plus the prediction error (Table II/IV protocol)."""
    m = tracking_metrics(alg.estimate(data.test.measurements), data.test.states)
    m["pred_err"] = prediction_error(alg.model, data.test.states, data.network.num_nodes, data.ctx, per_node=per_node)
    return m


def _train_lstm(cfg: DictConfig, data: Data, win, seed: int, dtype, device):
    return train_lstm_model(cfg.task.lstm, data.num_agents, data.ctx.dt, win, seed, dtype, device, cfg.get("progress", False))


def _pred_rows(model, src: Data, per_node: bool, **keys) -> pd.DataFrame:
    err = prediction_error(model, src.test.states, src.network.num_nodes, src.ctx, per_node=per_node)
    return metric_rows({"pred_err": err}, src.network, **keys)


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


# protocols ---------------------------------------------------------------------------------
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

    def param(metric, value):  # one scalar row (node avg, node_kind param)
        return pd.DataFrame({"node": ["avg"], "node_kind": ["param"], "episode": [0], "metric": [metric], "value": [value],
                             **{kk: [vv] for kk, vv in base.items()}})

    def add(model_name, cons, df):
        for i, (k, v) in enumerate({"model": model_name, "consensus": cons}.items()):
            df.insert(i, k, v)
        frames.append(df)

    cover = {"visible_frac": data.info.get("visible_frac", float("nan")), "train_pool": data.info.get("train_pool", float("nan"))}
    for k, v in cover.items():  # fraction of (test episode, step, pedestrian) seen by >= 1 sensor; episodes available
        add("-", "-", param(k, float(v)))
    if n_plot:
        add("truth", "-", position_rows(data.test.states, data, n_plot, **base))
    if "lin" in models:
        t0 = time.perf_counter()
        lin = ConstantVelocity(data.num_agents, float(t.lin.noise_std))
        add("lin", fusion.name, metric_rows(evaluate_tracking(learner(cfg, lin, data, fusion), data, False), net, **base))
        add("lin", fusion.name, trajectory_rows(lin, data, False, n_plot, **base))
        times["lin"] = time.perf_counter() - t0
    fused = None
    if "lstm" in models or ("sfm" in models and t.sfm.fit_on == "fused"):
        t0 = time.perf_counter()
        fused = cm_fused(cfg, data, data.train)
        times["cm_fuse"] = time.perf_counter() - t0
    if "sfm" in models:
        t0 = time.perf_counter()
        src = data.train.states[:n_train] if t.sfm.fit_on == "truth" else fused[:n_train]
        sfm, params, loss = fit_episode_social_force(src.cpu(), data.test.states, data.ctx.dt, t.sfm)
        log.info("%s: SFM fitted on %s: %s (roll-out error %.3f)", data.label, t.sfm.fit_on, params, loss)
        add("sfm", fusion.name, metric_rows(evaluate_tracking(learner(cfg, sfm, data, fusion), data, False), net, **base))
        add("sfm", fusion.name, trajectory_rows(sfm, data, False, n_plot, **base))
        for k, v in {**params, "fit_loss": loss}.items():
            add("sfm", "-", param(f"sfm_{k}", v))
        times["sfm"] = time.perf_counter() - t0
    for key in ("gp", "gp_cv"):
        if key not in models:
            continue
        t0 = time.perf_counter()
        gp = _gp(cfg, data, dtype, device, key == "gp_cv")
        alg = learner(cfg, gp, data, fusion)
        train_online(alg, data, n_train)
        name = _gp_name(cfg, key == "gp_cv")
        add(name, fusion.name, metric_rows(evaluate_tracking(alg, data, True), net, **base))
        add(name, fusion.name, trajectory_rows(gp, data, True, n_plot, **base))
        times[key] = time.perf_counter() - t0
    if "lstm" in models:
        t0 = time.perf_counter()
        win = lstm_windows(fused, int(t.lstm.obs_len), int(t.lstm.pred_len))
        lstm, curve = _train_lstm(cfg, data, win, seed, dtype, device)
        add("lstm", "cm", _pred_rows(lstm, data, False, **base))
        add("lstm", "cm", trajectory_rows(lstm, data, False, n_plot, **base))
        last = curve.iloc[int(curve.attrs.get("restored_epoch", len(curve))) - 1]
        add("lstm", "cm", param("lstm_train_loss", float(last["train_loss"])))
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
    gps = {k: learner(cfg, _gp(cfg, data, dtype, device, k == "gp_cv"), data, fusion) for k in keys}
    fused = cm_fused(cfg, data, data.train)
    for n in sizes:
        for k, alg in gps.items():
            train_online(alg, data, n)
            m = evaluate_tracking(alg, data, True)
            df = metric_rows(m, net, train_episodes=n, **base)
            df.insert(0, "model", _gp_name(cfg, k == "gp_cv"))
            df.insert(1, "consensus", fusion.name)
            frames.append(df)
        win = lstm_windows(fused[:n], int(t.lstm.obs_len), int(t.lstm.pred_len))
        lstm, _ = _train_lstm(cfg, data, win, seed * 7919 + n, dtype, device)
        df = _pred_rows(lstm, data, False, train_episodes=n, **base)
        df.insert(0, "model", "lstm")
        df.insert(1, "consensus", "cm")
        frames.append(df)
        log.info("%s seed %d: n=%d done", data.label, seed, n)
    return pd.concat(frames, ignore_index=True)


def run(cfg: DictConfig) -> pd.DataFrame:
    """Task entry point for ``dslearn-run`` (see the module docstring); ``cfg`` is already checked
    (:mod:`dslearn.schemas.ethucy_tracking`)."""
    t = cfg.task
    dtype = resolve_dtype(cfg.get("dtype", "float64"))
    device = torch.device(str(cfg.get("device", "cpu")))
    seed0 = int(cfg.seed)
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
    log.info("%s/%s finished in %.1fs", TASK, t.protocol, time.perf_counter() - t_start)
    return df
