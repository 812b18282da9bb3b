r"""Study ``ethucy_tracking``: Yu et al. Section VI (robot study) on real pedestrians (ETH/UCY).

Two protocols (``task.protocol``):

``tables`` (``dslearn-run experiment=real_tables``) — Tables III–IV and Fig. 4 analogue. Per
scene (``task.scenes``): episodes of ``m`` interacting pedestrians (:mod:`dslearn.data.episodes`,
physical time; a scene is a data set of ``task.datasets``, ``conf/dataset/<name>.yaml``), a time
split inside the scene, a LiDAR-like network around the scene
(:mod:`dslearn.sim.real`), then

* for every motion model of ``task.models`` (``conf/model`` options, composed as the faults
  study's; ``gp`` = the root ``model`` group): tracking error of the distributed filter
  (``cfg.consensus``, hybrid by default; the root ``filter`` group's prediction step, EKF or
  ``filter=ukf``; the root ``observation`` group's sensor model, ``observation=gp`` learned
  online too) and prediction error (roll-out from the true state at t = 0, the paper's V-C
  protocol);
* predicted trajectories of a few test episodes (rows ``pred_x``/``pred_y``) for the figure.

``data_size`` (``dslearn-run experiment=gp_vs_lstm``) — Fig. 5 analogue: the same rows after
``n`` training episodes for ``n`` in ``task.data_sizes`` (online models learn through the consensus
filter up to ``n``; offline models are fitted on the first ``n``), ``task.seeds`` seeds, on the real
scenes and on the synthetic Yu scenario (``cfg.scenario`` / ``cfg.network``).

A model learns online (``model.learnable``: the GPs, Algorithm 1 on the training episodes) or
offline (``model.learns_offline``: :meth:`~dslearn.models.base.MotionModel.fit_offline` once on
the training episodes' trajectories, before tracking): the SFM of real data (``sfm_fit``: the true
model is unknown; its shared :math:`(\tau, \alpha, \beta)` are fitted to the training
roll-outs, :mod:`dslearn.learning.sfm_fit`) and the LSTM (``lstm``, ``social_lstm``:
:class:`~dslearn.models.lstm.SocialLSTM`). What an offline model learns from is its
``train_on`` key, else ``task.train_on``: ``truth`` (the true tracks) or ``fused`` (default: the
positions the network estimates when it tracks the training episodes with LIN and consensus on
measurements (CM), the nodes' estimates combined by their information, :func:`cm_fused` — the
paper's VI-C recipe). The study never decodes a model's name.
"""

from __future__ import annotations

import copy
import logging
import time

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf
from torch import Tensor

from dslearn.compose import (build_fusion, build_motion_model, build_network, build_observation, build_predict,
                             build_scenario, group_options, resolve_dtype)
from dslearn.data.datasets import load_dataset, task_datasets
from dslearn.episodes import Episodes, Measurements
from dslearn.filters.distributed import initial_belief, track
from dslearn.fusion.strategies import ConsensusOnMeasurements, Fusion
from dslearn.learning.online import OnlineLearner
from dslearn.metrics import metric_rows, prediction_error, tracking_metrics
from dslearn.models import ConstantVelocity, LinearPositionObservation
from dslearn.models.base import MotionModel
from dslearn.network import SensorNetwork
from dslearn.sim.real import Data, real_source
from dslearn.sim.scenario import sample_split
from dslearn.types import POS, agents, safe_cholesky

log = logging.getLogger(__name__)

TASK = "ethucy_tracking"
#: names of ``task.models`` kept from before the entries were ``conf/model`` options: entry ->
#: (the option, the label of its rows); option None = the root ``model`` group, labelled by its name
ALIASES = {"gp": (None, None), "sfm": ("sfm_fit", "sfm")}
GP_TARGET = "dslearn.models.gp.GPMotionModel.for_scenario"
GP_CV_TARGET = "dslearn.learning.gp_cv.gp_cv_for_scenario"
AGGREGATED_TARGET = "dslearn.models.aggregated.aggregated_for_scenario"
#: the model factories that run on real data (sized by :class:`dslearn.sim.real.RealScenario`), and
#: the GPs among them whose ``inputs`` ``task.gp_inputs`` sets
REAL_TARGETS = (GP_TARGET, GP_CV_TARGET, AGGREGATED_TARGET, "dslearn.models.constant_velocity.ConstantVelocity.for_scenario",
                "dslearn.learning.sfm_fit.FittedSocialForce.for_scenario", "dslearn.models.lstm.SocialLSTM.for_scenario")
GP_INPUT_TARGETS = (GP_TARGET, GP_CV_TARGET)
#: the observation group's default noise: the root network's sensors (here: the study's own network)
NETWORK_NOISE = "${network.meas_std}"


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


def model_entries(cfg: DictConfig) -> list[tuple[str, str, dict]]:
    """``(entry, label, spec)`` of every ``task.models`` entry, in order: ``spec`` is the plain config
    of its ``conf/model`` option (composed by :func:`dslearn.compose.group_options`; the legacy
    names of :data:`ALIASES` map to an option or to the root ``model`` group), with the keys of
    ``task.model_keys.<entry>`` replaced and, for the GPs that have it, ``inputs = task.gp_inputs``;
    ``label`` (the rows' ``model``) is the option's ``name`` (an alias's own label where it has one)."""
    t = cfg.task
    names = [str(m) for m in t.models]
    options = sorted({ALIASES.get(n, (n, None))[0] for n in names} - {None})
    composed = _options(options)
    extra = t.get("model_keys") or {}
    out = []
    for n in names:
        option, label = ALIASES.get(n, (n, None))
        spec = OmegaConf.to_container(cfg.model, resolve=True) if option is None else copy.deepcopy(composed[option])
        if n in extra:
            spec.update(OmegaConf.to_container(extra[n], resolve=True) if OmegaConf.is_config(extra[n]) else dict(extra[n]))
        if str(t.get("gp_inputs", "mean")) != "mean" and spec.get("_target_") in GP_INPUT_TARGETS:
            spec["inputs"] = str(t.gp_inputs)
        out.append((n, str(label or spec.get("name", n)), spec))
    return out


_OPTIONS: dict[tuple, dict] = {}


def _options(names: list[str]) -> dict[str, dict]:
    """The plain configs of ``conf/model`` options (:func:`dslearn.compose.group_options`), memoised by
    the config folders and the option: the up-front check of every job of a sweep and the run compose
    the same options, and composing one costs ~0.3 s."""
    from dslearn.conf_paths import CONF_DIRS

    where = tuple(str(d) for d in CONF_DIRS)
    todo = [n for n in names if (where, n) not in _OPTIONS]
    if todo:
        for n, node in group_options("model", todo).items():
            _OPTIONS[(where, n)] = OmegaConf.to_container(node, resolve=True)
    return {n: _OPTIONS[(where, n)] for n in names}


def build_model(spec: dict, data: Data, dtype, device) -> MotionModel:
    """The model of an entry's ``spec`` (:func:`model_entries`), sized by the data source's scenario
    (:attr:`dslearn.sim.real.Data.scenario`) and network."""
    return build_motion_model(spec, data.scenario, data.network, dtype, device)


def observation_model(cfg: DictConfig, data: Data, dtype, device):
    """The root ``observation`` group's sensor model for ``data``'s network; its noise, where the option
    leaves it at the network's (``${network.meas_std}``), is this study's sensors' (``task.network.meas_std``)."""
    raw = OmegaConf.to_container(cfg.observation, resolve=False)
    spec = OmegaConf.to_container(cfg.observation, resolve=True)
    if raw.get("noise_std") == NETWORK_NOISE:
        spec["noise_std"] = float(data.network.meas_std)
    return build_observation(spec, data.network, dtype, device)


def offline_source(model: MotionModel, cfg: DictConfig) -> str:
    """What an offline model learns from: its ``train_on``, else ``task.train_on``."""
    return str(model.train_on or cfg.task.get("train_on", "fused"))


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
    lin = ConstantVelocity(data.num_agents, float(cfg.task.cm_fusion.noise_std))
    obs = LinearPositionObservation(net.meas_std)
    res = track(ep.measurements, net, lin, obs, fusion, data.ctx, _init(cfg, data, ep.measurements, fusion))
    info = res.info.sum(0)
    q = (res.info @ res.mean.unsqueeze(-1)).sum(0)
    return torch.cholesky_solve(q, safe_cholesky(info)).squeeze(-1)


def learner(cfg, model, data: Data, fusion: Fusion, dtype=torch.float64, device="cpu") -> OnlineLearner:
    """Algorithm 1 (:class:`~dslearn.learning.online.OnlineLearner`) for ``model`` on ``data``'s network, with
    the root ``filter`` group's prediction step (EKF, or ``filter=ukf``) and a fresh sensor model of the
    root ``observation`` group (:func:`observation_model`; ``observation=gp`` learns online too)."""
    return OnlineLearner(data.network, model, observation_model(cfg, data, dtype, torch.device(device)), fusion, data.ctx,
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


class OfflineData:
    """The trajectories offline models learn from, made once per data source: the true training
    tracks, or the CM-fused estimates (:func:`cm_fused`, made on first use)."""

    def __init__(self, cfg: DictConfig, data: Data, times: dict | None = None):
        self.cfg, self.data, self.times, self._fused = cfg, data, times if times is not None else {}, None

    def __call__(self, model: MotionModel) -> Tensor:
        src = offline_source(model, self.cfg)
        if src == "truth":
            return self.data.train.states
        if self._fused is None:
            t0 = time.perf_counter()
            self._fused = cm_fused(self.cfg, self.data, self.data.train)
            self.times["cm_fuse"] = time.perf_counter() - t0
        return self._fused


def fit_offline(model: MotionModel, source: OfflineData, n: int, seed: int) -> None:
    """Fit an offline model on the first ``n`` training trajectories of its source (no-op for the others)."""
    if model.learns_offline:
        model.fit_offline(source(model)[:n], source.data.ctx.dt, seed=int(seed))
        log.info("%s: %s fitted offline on %d %s training episodes: %s", source.data.label, type(model).__name__, n,
                 offline_source(model, source.cfg), {k: round(v, 4) for k, v in getattr(model, "fit_info", {}).items()})


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
    """Tables III–IV and Fig. 4 rows for one data source: every model of ``task.models`` tracks the
    test episodes (after its online or offline learning on the ``n`` training episodes) and rolls
    them out from the truth; an offline model's fit adds its ``fit_info`` as parameter rows
    (``<label>_<key>``, e.g. ``sfm_tau``, ``lstm_train_loss``)."""
    n_train = len(data.train)
    fusion = _fusion(cfg, data.network)
    net = data.network
    base = dict(data=data.kind, scene=data.label, train_episodes=n_train, test_episodes=len(data.test), seed=seed)
    frames, times = [], {}
    n_plot = min(int(cfg.task.plot_episodes), len(data.test))
    offline = OfflineData(cfg, data, times)

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
    for _, label, spec in model_entries(cfg):
        t0 = time.perf_counter()
        model = build_model(spec, data, dtype, device)
        fit_offline(model, offline, n_train, seed)
        for k, v in getattr(model, "fit_info", {}).items():
            add(label, "-", param(f"{label}_{k}", float(v)))
        model.begin_episodes(data.test.states)
        alg = learner(cfg, model, data, fusion, dtype, device)
        if alg.learnable:
            train_online(alg, data, n_train)
        add(label, fusion.name, metric_rows(evaluate_tracking(alg, data, model.learnable), net, **base))
        add(label, fusion.name, trajectory_rows(model, data, model.learnable, n_plot, **base))
        times[label] = time.perf_counter() - t0
    log.info("%s: component times %s", data.label, {k: round(v, 1) for k, v in times.items()})
    df = pd.concat(frames, ignore_index=True)
    df.attrs["times"] = times
    return df


def protocol_data_size(cfg: DictConfig, data: Data, seed: int, dtype, device) -> pd.DataFrame:
    """Fig. 5 rows for one data source and seed: every model of ``task.models`` after ``n`` training
    episodes, ``n`` in ``task.data_sizes`` (online models learn on, episode after episode; offline
    models are fitted again on the first ``n``, with seed ``seed * 7919 + n``)."""
    t = cfg.task
    sizes = sorted({min(int(v), len(data.train)) for v in t.data_sizes})
    fusion = _fusion(cfg, data.network)
    net = data.network
    frames = []
    base = dict(data=data.kind, scene=data.label, test_episodes=len(data.test), seed=seed)
    offline = OfflineData(cfg, data)
    runs = []
    for _, label, spec in model_entries(cfg):
        model = build_model(spec, data, dtype, device)
        runs.append((label, model, learner(cfg, model, data, fusion, dtype, device)))
    for n in sizes:
        for label, model, alg in runs:
            fit_offline(model, offline, n, seed * 7919 + n)
            model.begin_episodes(data.test.states)
            if alg.learnable:
                train_online(alg, data, n)
            df = metric_rows(evaluate_tracking(alg, data, model.learnable), net, train_episodes=n, **base)
            df.insert(0, "model", label)
            df.insert(1, "consensus", fusion.name)
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
