r"""Study ``ethucy_tracking``: Yu et al. Section VI (robot study) on real pedestrians (ETH/UCY).

Two protocols (``settings.protocol``, the task's ``protocol`` key):

``tables`` (``dslearn-run experiment=real_tables``) — Tables III–IV and Fig. 4 analogue. Per
scene (``settings.scenes``): episodes of ``m`` interacting pedestrians (:mod:`dslearn.data.episodes`,
physical time; a scene is one of the run's data sets, ``conf/dataset/<name>.yaml``), a time split
inside the scene, a LiDAR-like network around the scene (:mod:`dslearn.sim.real`), then

* for every motion model of the task's ``models`` (each entry a :class:`ModelEntry`, made by the
  composition root from a ``conf/model`` option; ``gp`` = the root ``model`` group): tracking error
  of the distributed filter (the run's fusion, hybrid by default; the run's prediction step, EKF or
  ``filter=ukf``; the run's sensor model, ``observation=gp`` learned online too) and prediction
  error (roll-out from the true state at t = 0, the paper's V-C protocol);
* predicted trajectories of a few test episodes (rows ``pred_x``/``pred_y``) for the figure.

``data_size`` (``dslearn-run experiment=gp_vs_lstm``) — Fig. 5 analogue: the same rows after
``n`` training episodes for ``n`` in ``settings.data_sizes`` (online models learn through the
consensus filter up to ``n``; offline models are fitted on the first ``n``), ``settings.seeds``
seeds, on the real scenes and on the synthetic Yu scenario (the run's root scenario and network,
:class:`SyntheticWorld`).

A model learns online (``model.learnable``: the GPs, Algorithm 1 on the training episodes) or
offline (``model.learns_offline``: :meth:`~dslearn.models.base.MotionModel.fit_offline` once on
the training episodes' trajectories, before tracking): the SFM of real data (``sfm_fit``: the true
model is unknown; its shared :math:`(\tau, \alpha, \beta)` are fitted to the training
roll-outs, :mod:`dslearn.learning.sfm_fit`) and the LSTM (``lstm``, ``social_lstm``:
:class:`~dslearn.models.lstm.SocialLSTM`). What an offline model learns from is its
``train_on`` key, else ``settings.train_on``: ``truth`` (the true tracks) or ``fused`` (default: the
positions the network estimates when it tracks the training episodes with LIN and consensus on
measurements (CM), the nodes' estimates combined by their information, :meth:`EthucyTrackingStudy.cm_fused`
— the paper's VI-C recipe). The study never decodes a model's name.

Python use (the same defaults and checks as ``dslearn-run``, :mod:`dslearn.api`)::

    from dslearn import api
    study = api.build_study("experiment=real_tables", "task.scenes=[zara1]", "task.train_episodes=8")
    df = study.run()
"""

import logging
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from dslearn.data.datasets import DatasetSpec, load_dataset
from dslearn.diagnostics import Diagnostics
from dslearn.episodes import Episodes, Measurements
from dslearn.filters.distributed import FilterSettings, initial_belief, track
from dslearn.fusion.strategies import Fusion
from dslearn.learning.online import OnlineLearner
from dslearn.metrics.prediction import position_rows, scalar_row, tracking_and_prediction_errors
from dslearn.metrics.rows import metric_rows
from dslearn.models import ConstantVelocity, LinearPositionObservation
from dslearn.models.base import MotionModel, ObservationModel
from dslearn.network import SensorNetwork
from dslearn.settings import ranged
from dslearn.sim.real import ArenaSettings, Data, EpisodeRecipe, real_source
from dslearn.sim.scenario import sample_split
from dslearn.types import safe_cholesky

log = logging.getLogger(__name__)

TASK = "ethucy_tracking"
PROTOCOLS = ("tables", "data_size")
#: the default entries of ``models``: conf/model options (gp = the root model group)
MODELS = ("gp", "gp_cv", "lin", "sfm_fit", "lstm")
CRITERIA = ("mutual", "closest")
SPLITS = ("time", "scene", "random")  # as dslearn.data.episodes; "scene" is refused with the reason by the task's check
TRAIN_ON = ("fused", "truth")  # what offline models learn from (OfflineData)
GP_INPUTS = ("belief", "mean")  # dslearn.models.gp.INPUTS: where the EKF evaluates the GPs


# settings ----------------------------------------------------------------------------------
@dataclass
class CmFusionSettings:
    """``cm_fusion``: the filter that makes the fused training tracks (:meth:`EthucyTrackingStudy.cm_fused`)."""

    noise_std: float = ranged(0.1, gt=0.0)


@dataclass
class EthucyTrackingSettings:
    """The study's own settings (the task's keys; the data sets it may use arrive as
    :class:`~dslearn.data.datasets.DatasetSpec` values, the models as :class:`ModelEntry` makers)."""

    protocol: str = ranged("tables", choices=PROTOCOLS)
    data_root: Optional[str] = None
    scenes: List[str] = field(default_factory=lambda: ["zara1", "zara2", "univ", "hotel", "eth"])
    convention: str = ranged("physical", choices=("physical", "benchmark"))
    dt: float = ranged(0.4, gt=0.0)
    steps: int = ranged(11, ge=2)
    agents: int = ranged(2, ge=2)
    max_dist: float = ranged(3.0, gt=0.0)
    criterion: str = ranged("mutual", choices=CRITERIA)
    min_speed: float = ranged(0.3, ge=0.0)
    stride: int = ranged(4, ge=1)
    split: str = ranged("time", choices=SPLITS)
    test_fraction: float = ranged(0.2, gt=0.0, lt=1.0)
    train_episodes: int = ranged(128, ge=1)
    test_episodes: int = ranged(25, ge=1)
    plot_episodes: int = ranged(3, ge=0)
    models: List[str] = ranged(factory=lambda: list(MODELS), min_len=1)  # conf/model/<name>.yaml (checked by the task)
    model_keys: Dict[str, Dict[str, Any]] = field(default_factory=dict)  # entry -> keys of its option to replace
    train_on: str = ranged("fused", choices=TRAIN_ON)
    gp_inputs: str = ranged("belief", choices=GP_INPUTS)
    network: ArenaSettings = field(default_factory=ArenaSettings)
    cm_fusion: CmFusionSettings = field(default_factory=CmFusionSettings)
    data_sizes: List[int] = ranged(factory=lambda: [8, 16, 32, 64, 128], ge=1, each=True)
    seeds: int = ranged(3, ge=1)
    synthetic: bool = False

    def episode_recipe(self) -> EpisodeRecipe:
        """How a scene is cut into episodes and split (:func:`dslearn.sim.real.real_source`)."""
        return EpisodeRecipe(int(self.agents), int(self.steps), float(self.dt), float(self.max_dist), int(self.stride),
                             str(self.criterion), float(self.min_speed), str(self.split), float(self.test_fraction),
                             int(self.test_episodes))


@dataclass(frozen=True)
class ModelEntry:
    """One entry of the task's ``models``: its name, the label of its rows (the ``model`` column) and
    ``make(scenario, network, device=None)``, a fresh model sized by a data source's scenario
    (:attr:`dslearn.sim.real.Data.scenario`) and network, in the run's dtype (and device unless given)."""

    entry: str
    label: str
    make: Callable[..., MotionModel]


@dataclass(frozen=True)
class SyntheticWorld:
    """The synthetic Yu source of the ``data_size`` protocol: the run's scenario and sensor network."""

    scenario: Any
    network: SensorNetwork


# the study ---------------------------------------------------------------------------------
@dataclass
class EthucyTrackingStudy:
    """One run of the real-data study (one protocol over the sources of its settings).

    Its slots are filled by the composition root: the typed settings, the run's seed, dtype and device,
    the filter's settings and prediction step, the fusion of a network (``fusion_factory``), and the
    task's own slots: the model entries (``ethucy_tracking_models``), a sensor model for a network
    (``ethucy_tracking_observation``: its noise, unless set, is that network's sensors'), the CM fusion
    of the fused training tracks (``ethucy_tracking_cm_fusion``), the data sets (``ethucy_tracking_datasets``)
    and, for the synthetic source only, the root scenario and network (``ethucy_tracking_synthetic``)."""

    settings: EthucyTrackingSettings
    seed: int
    dtype: torch.dtype
    device: torch.device
    filter: FilterSettings
    predict: Any
    fusion_factory: Callable[[SensorNetwork], Fusion]
    ethucy_tracking_models: List[ModelEntry]
    ethucy_tracking_observation: Callable[[SensorNetwork], ObservationModel]
    ethucy_tracking_cm_fusion: Callable[[SensorNetwork], Fusion]
    ethucy_tracking_datasets: Dict[str, DatasetSpec]
    ethucy_tracking_synthetic: Optional[SyntheticWorld] = None

    # data ----------------------------------------------------------------------------------
    def real_data(self, scene_name: str, seed: int, max_train: int) -> Data:
        """Episodes of one scene (a data set of the run), its network and measurements (all seeded by
        ``seed``; :func:`dslearn.sim.real.real_source`)."""
        s = self.settings
        scene = load_dataset(self.ethucy_tracking_datasets[scene_name], s.data_root, str(s.convention))
        return real_source(scene, s.episode_recipe(), s.network, seed, max_train, self.dtype, self.device)

    def synthetic_data(self, seed: int, max_train: int) -> Data:
        """The Yu synthetic scenario and network (:class:`SyntheticWorld`)."""
        world = self.ethucy_tracking_synthetic
        if world is None:
            raise ValueError("the synthetic source needs the run's scenario and network (ethucy_tracking_synthetic)")
        scenario, net = world.scenario, world.network
        n_test = int(self.settings.test_episodes)
        test, train = sample_split(scenario, net, seed, n_test, max_train, self.dtype, self.device)
        info = {"episodes_total": max_train + n_test, "scene_dt": scenario.dt, "test_meta": None}
        return Data("synthetic", "synthetic", train, test, net, scenario.ctx(), tuple(scenario.area), scenario.num_agents,
                    info)

    # parts ---------------------------------------------------------------------------------
    def fusion(self, network: SensorNetwork) -> Fusion:
        """The run's fusion over ``network``'s graph."""
        return self.fusion_factory(network)

    def initial_belief(self, data: Data, ep: Measurements, fusion: Fusion):
        f = self.filter
        return initial_belief(ep, data.network, data.ctx.dt, fusion, data.area, f.prior_pos_std, f.prior_vel_std)

    def learner(self, model: MotionModel, data: Data, fusion: Fusion) -> OnlineLearner:
        """Algorithm 1 (:class:`~dslearn.learning.online.OnlineLearner`) for ``model`` on ``data``'s network, with
        the run's prediction step (EKF, or ``filter=ukf``) and a fresh sensor model for that network
        (``observation=gp`` learns online too)."""
        return OnlineLearner(data.network, model, self.ethucy_tracking_observation(data.network), fusion, data.ctx,
                             init=lambda ep: self.initial_belief(data, ep, fusion), predict_step=self.predict,
                             learn_gate_std=self.filter.learn_gate_std)

    def offline_source(self, model: MotionModel) -> str:
        """What an offline model learns from: its ``train_on``, else the settings' ``train_on``."""
        return str(model.train_on or self.settings.train_on)

    @torch.no_grad()
    def cm_fused(self, data: Data, ep: Episodes) -> Tensor:
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
        fusion = self.ethucy_tracking_cm_fusion(net)
        lin = ConstantVelocity(data.num_agents, float(self.settings.cm_fusion.noise_std))
        obs = LinearPositionObservation(net.meas_std)
        res = track(ep.measurements, net, lin, obs, fusion, data.ctx, self.initial_belief(data, ep.measurements, fusion))
        info = res.info.sum(0)
        q = (res.info @ res.mean.unsqueeze(-1)).sum(0)
        return torch.cholesky_solve(q, safe_cholesky(info)).squeeze(-1)

    def evaluate(self, alg: OnlineLearner, data: Data, per_node: bool) -> dict[str, Tensor]:
        """The filter's estimates of the test episodes and the model's roll-outs, against the truth
        (Table II/IV protocol, :func:`dslearn.metrics.prediction.tracking_and_prediction_errors`)."""
        res = alg.estimate(data.test.measurements)
        return tracking_and_prediction_errors(res, alg.model, data.test.states, data.network.num_nodes, data.ctx,
                                              per_node)

    # protocols -----------------------------------------------------------------------------
    def protocol_tables(self, data: Data, seed: int) -> pd.DataFrame:
        """Tables III–IV and Fig. 4 rows for one data source: every model entry tracks the
        test episodes (after its online or offline learning on the ``n`` training episodes) and rolls
        them out from the truth; an offline model's fit adds its ``fit_info`` as parameter rows
        (``<label>_<key>``, e.g. ``sfm_tau``, ``lstm_train_loss``)."""
        n_train = len(data.train)
        fusion = self.fusion(data.network)
        net = data.network
        base = dict(data=data.kind, scene=data.label, train_episodes=n_train, test_episodes=len(data.test), seed=seed)
        frames, times = [], {}
        n_plot = min(int(self.settings.plot_episodes), len(data.test))
        offline = OfflineData(data, self.cm_fused, self.offline_source, times)

        def add(model_name, cons, df):
            for i, (k, v) in enumerate({"model": model_name, "consensus": cons}.items()):
                df.insert(i, k, v)
            frames.append(df)

        cover = {"visible_frac": data.info.get("visible_frac", float("nan")), "train_pool": data.info.get("train_pool", float("nan"))}
        for k, v in cover.items():  # fraction of (test episode, step, pedestrian) seen by >= 1 sensor; episodes available
            add("-", "-", scalar_row(k, float(v), **base))
        if n_plot:
            add("truth", "-", position_rows(data.test.states, net.names[0], n_plot, **base))
        for entry in self.ethucy_tracking_models:
            label = entry.label
            t0 = time.perf_counter()
            model = entry.make(data.scenario, data.network)
            fit_offline(model, offline, n_train, seed)
            for k, v in getattr(model, "fit_info", {}).items():
                add(label, "-", scalar_row(f"{label}_{k}", float(v), **base))
            model.begin_episodes(data.test.states)
            alg = self.learner(model, data, fusion)
            if alg.learnable:
                train_online(alg, data, n_train)
            add(label, fusion.name, metric_rows(self.evaluate(alg, data, model.learnable), net, **base))
            roll = rollout_from_truth(model, data, model.learnable) if n_plot > 0 else None  # the figure's trajectories
            add(label, fusion.name, position_rows(roll, net.names[0], n_plot, **base))
            times[label] = time.perf_counter() - t0
        log.info("%s: component times %s", data.label, {k: round(v, 1) for k, v in times.items()})
        df = pd.concat(frames, ignore_index=True)
        df.attrs["times"] = times
        return df

    def protocol_data_size(self, data: Data, seed: int) -> pd.DataFrame:
        """Fig. 5 rows for one data source and seed: every model entry after ``n`` training
        episodes, ``n`` in ``settings.data_sizes`` (online models learn on, episode after episode; offline
        models are fitted again on the first ``n``, with seed ``seed * 7919 + n``)."""
        sizes = sorted({min(int(v), len(data.train)) for v in self.settings.data_sizes})
        fusion = self.fusion(data.network)
        net = data.network
        frames = []
        base = dict(data=data.kind, scene=data.label, test_episodes=len(data.test), seed=seed)
        offline = OfflineData(data, self.cm_fused, self.offline_source)
        runs = []
        for entry in self.ethucy_tracking_models:
            model = entry.make(data.scenario, data.network)
            runs.append((entry.label, model, self.learner(model, data, fusion)))
        for n in sizes:
            for label, model, alg in runs:
                fit_offline(model, offline, n, seed * 7919 + n)
                model.begin_episodes(data.test.states)
                if alg.learnable:
                    train_online(alg, data, n)
                df = metric_rows(self.evaluate(alg, data, model.learnable), net, train_episodes=n, **base)
                df.insert(0, "model", label)
                df.insert(1, "consensus", fusion.name)
                frames.append(df)
            log.info("%s seed %d: n=%d done", data.label, seed, n)
        return pd.concat(frames, ignore_index=True)

    def sources(self) -> list[tuple[str, str]]:
        """The data sources of the run, ``(kind, label)``: the scenes, then the synthetic scenario
        (``data_size`` with ``synthetic``)."""
        s = self.settings
        extra = [("synthetic", "synthetic")] if s.protocol == "data_size" and s.synthetic else []
        return [("real", str(sc)) for sc in s.scenes] + extra

    def run(self, diagnostics: Diagnostics | None = None, progress: bool = False) -> pd.DataFrame:
        """Every source of the protocol (see the module docstring); a tidy DataFrame (one row per
        source x model x node x episode x metric, plus the parameter and trajectory rows). The
        component times of each source reach ``diagnostics`` (``<source>/<model>_s``)."""
        s = self.settings
        seed0 = int(self.seed)
        frames = []
        t_start = time.perf_counter()
        if s.protocol == "tables":
            for scene in s.scenes:
                torch.manual_seed(seed0)
                data = self.real_data(str(scene), seed0, int(s.train_episodes))
                df = self.protocol_tables(data, seed0)
                if diagnostics is not None:
                    for k, v in df.attrs.get("times", {}).items():
                        diagnostics.timings[f"{data.label}/{k}_s"] = round(v, 3)
                frames.append(df)
        else:
            max_train = max(int(v) for v in s.data_sizes)
            for kind, label in self.sources():
                for i in range(int(s.seeds)):
                    seed = seed0 + i
                    torch.manual_seed(seed)
                    data = self.real_data(label, seed, max_train) if kind == "real" else self.synthetic_data(seed, max_train)
                    frames.append(self.protocol_data_size(data, seed))
        df = pd.concat(frames, ignore_index=True)
        df.insert(2, "protocol", str(s.protocol))
        df.insert(3, "agents", int(s.agents))
        for col in ("step", "agent"):
            if col not in df.columns:
                df[col] = np.nan
        log.info("%s/%s finished in %.1fs", TASK, s.protocol, time.perf_counter() - t_start)
        return df


# learning ----------------------------------------------------------------------------------
def train_online(alg: OnlineLearner, data: Data, upto: int) -> None:
    """Algorithm 1 on the training episodes the learner has not seen, up to ``upto`` (one at a time)."""
    for k in range(alg.seen, upto):
        alg.learn(data.train.measurements.select(slice(k, k + 1)))


class OfflineData:
    """The trajectories offline models learn from, made once per data source: the true training
    tracks, or the fused estimates (``fuse(data, episodes)``, e.g. :meth:`EthucyTrackingStudy.cm_fused`,
    made on first use). ``source(model)`` names what a model learns from (``truth`` or ``fused``)."""

    def __init__(self, data: Data, fuse: Callable[[Data, Episodes], Tensor], source: Callable[[MotionModel], str],
                 times: dict | None = None):
        self.data, self.fuse, self.source = data, fuse, source
        self.times, self._fused = times if times is not None else {}, None

    def __call__(self, model: MotionModel) -> Tensor:
        if self.source(model) == "truth":
            return self.data.train.states
        if self._fused is None:
            t0 = time.perf_counter()
            self._fused = self.fuse(self.data, self.data.train)
            self.times["cm_fuse"] = time.perf_counter() - t0
        return self._fused


def fit_offline(model: MotionModel, source: OfflineData, n: int, seed: int) -> None:
    """Fit an offline model on the first ``n`` training trajectories of its source (no-op for the others)."""
    if model.learns_offline:
        model.fit_offline(source(model)[:n], source.data.ctx.dt, seed=int(seed))
        log.info("%s: %s fitted offline on %d %s training episodes: %s", source.data.label, type(model).__name__, n,
                 source.source(model), {k: round(v, 4) for k, v in getattr(model, "fit_info", {}).items()})


@torch.no_grad()
def rollout_from_truth(model: MotionModel, src: Data, per_node: bool) -> Tensor:
    """The model's roll-out of every test episode from its true state at t = 0, with that state first:
    ``(B, K+1, Dx)`` (``per_node``: node ``sensor1``'s model)."""
    st = src.test.states  # the whole test batch (per-episode model state, e.g. SFM's v*)
    x0 = st[:, 0]
    k = st.shape[1] - 1
    if per_node:
        roll = model.rollout(x0.unsqueeze(0).expand(src.network.num_nodes, *x0.shape).contiguous(), k, src.ctx)[0]
    else:
        roll = model.rollout(x0, k, src.ctx)
    return torch.cat([x0.unsqueeze(1), roll], 1)
