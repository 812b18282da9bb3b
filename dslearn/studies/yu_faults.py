r"""Yu et al. scenario on an unreliable network (the paper's future work).

Tracking error vs per-step link-failure probability and vs the fraction of failed nodes, for
every fusion strategy and for a parametric (LIN) and a learned (increment GP) motion model,
plus gross measurement outliers with and without chi-square gating. Faults act in training and
in test: the GP is learned online through the faulty network.

The study is a component (:class:`YuFaultsStudy`): the composition root fills its slots with the
run's built parts and its typed settings (:class:`FaultTask`); the grid's motion models are makers of
``task.models``' options, its fusions makers of ``task.fusions``' options (:class:`FaultGridFusions`).
The faults of the data come from :mod:`dslearn.sim.faults`, those of the links from
:mod:`dslearn.fusion.faults`, the rows from :mod:`dslearn.metrics.faults`. All cells of one fault
setting share the same episodes, node-failure schedule, outliers and link-failure draws (common
random numbers), so differences between fusions and models are not sampling noise.

``dslearn-run experiment=yu_faults`` (parameters: ``conf/task/yu_faults.yaml``); in Python::

    from dslearn import api
    df = api.build_study("experiment=yu_faults", "task.test_episodes=5").run()
"""

from __future__ import annotations

import copy
import logging
import time
from dataclasses import dataclass
from typing import Any, Callable, List, Optional

import pandas as pd
import torch

from dslearn.diagnostics import Diagnostics
from dslearn.episodes import Episodes
from dslearn.filters.distributed import FilterSettings, initial_belief
from dslearn.fusion.faults import FaultyFusion
from dslearn.fusion.strategies import Fusion
from dslearn.learning.online import OnlineLearner
from dslearn.metrics.faults import faulty_network_rows
from dslearn.models.base import MotionModel, ObservationModel
from dslearn.network import SensorNetwork
from dslearn.settings import ranged
from dslearn.sim.faults import add_outliers, apply_node_failures, node_failure_schedule
from dslearn.sim.scenario import episode_streams
from dslearn.streams import Streams
from dslearn.studies.yu import check_offline, offline_trajectories
from dslearn.types import StepContext

log = logging.getLogger(__name__)

#: the fusion options the grid can run (``conf/consensus/<name>.yaml``)
FUSION_OPTIONS = ("individual", "ce", "cm", "ci", "hybrid", "hybrid_nodes", "centralized")


@dataclass
class FaultTask:
    """The study's settings (``conf/task/yu_faults.yaml``; the rules are checked before any run)."""

    _target_: str = "dslearn.studies.yu_faults.YuFaultsStudy"
    name: str = "yu_faults"
    models: List[str] = ranged(factory=lambda: ["lin", "gp_increment"], min_len=1)  # conf/model/<name>.yaml
    fusions: List[str] = ranged(factory=lambda: ["individual", "ce", "cm", "ci", "hybrid", "centralized"],
                                min_len=1, each=True, choices=FUSION_OPTIONS)
    train_episodes: int = ranged(15, ge=0)
    test_episodes: int = ranged(20, ge=1)
    link_fail: List[float] = ranged(factory=lambda: [0.0, 0.1, 0.3, 0.5], each=True, ge=0.0, le=1.0)
    node_fail: List[float] = ranged(factory=lambda: [0.0, 0.1, 0.2, 0.4], each=True, ge=0.0, le=1.0)
    joint: List[Any] = ranged(factory=lambda: [[0.3, 0.2]])  # [link_fail, node_fail] pairs
    node_fail_mode: str = ranged("permanent", choices=("permanent", "transient"))
    node_fail_duration: int = ranged(4, ge=1)
    weights: str = ranged("metropolis", choices=("metropolis", "uniform"))
    outlier_frac: float = ranged(0.1, ge=0.0, le=1.0)
    outlier_std: float = ranged(3.0, gt=0.0)
    gate_prob: Optional[float] = ranged(0.99, gt=0.0, lt=1.0)
    outlier_settings: bool = True
    divergence_bound: float = ranged(2.0, gt=0.0)


@dataclass(frozen=True)
class FaultSetting:
    """One fault setting of the grid: per-step link-failure probability, fraction of failed nodes,
    fraction of gross outliers, the chi-square gate's probability (None: no gate) and the grid axis
    it belongs to (``link``, ``node``, ``joint``, ``outliers``, ``joint+outliers``)."""

    link_fail: float
    node_fail: float
    outlier_frac: float = 0.0
    gate_prob: Optional[float] = None
    axis: str = ""


@dataclass(frozen=True)
class FaultGridFusions:
    """The grid's fusion strategies: ``make[name](network)`` builds a fresh fusion of option ``name``
    (its own type and omega; ``hybrid_nodes``: omega = S) with the grid's ``rounds`` L. Its weight rule is
    not used: :class:`~dslearn.fusion.faults.FaultyFusion` recomputes the weights on every step's live
    graph (``FaultTask.weights``)."""

    rounds: int
    make: dict[str, Callable[[SensorNetwork], Fusion]]


def fault_settings(t: FaultTask) -> list[FaultSetting]:
    """The fault settings of the grid, in order, each once: link axis, node axis, joint points, outliers."""
    out: list[FaultSetting] = []
    seen: set[tuple] = set()

    def add(p: float, f: float, outl: float = 0.0, gate: Optional[float] = None, axis: str = "") -> None:
        key = (p, f, outl, gate)
        if key not in seen:
            seen.add(key)
            out.append(FaultSetting(p, f, outl, gate, axis))

    for p in t.link_fail:
        add(float(p), 0.0, axis="link")
    for f in t.node_fail:
        add(0.0, float(f), axis="node")
    for p, f in t.joint:
        add(float(p), float(f), axis="joint")
    if t.outlier_settings and t.outlier_frac > 0:
        add(0.0, 0.0, float(t.outlier_frac), None, axis="outliers")
        if t.gate_prob is not None:
            add(0.0, 0.0, float(t.outlier_frac), float(t.gate_prob), axis="outliers")
            for p, f in t.joint:
                add(float(p), float(f), float(t.outlier_frac), float(t.gate_prob), axis="joint+outliers")
    return out


#: a maker of one motion-model option: ``make(scenario, network, device=None)`` -> a fresh model
ModelMaker = Callable[..., MotionModel]


@dataclass
class YuFaultsStudy:
    """The faults grid: every fault setting x motion model x fusion, learned online and tested on the
    faulty network (see the module docstring). Its slots are filled by the composition root; every
    value is a plain typed value or a built object."""

    settings: FaultTask
    scenario: Any
    network: SensorNetwork
    model_options: dict[str, ModelMaker]  # task.models: {option: make(scenario, network, device=None)}
    yu_faults_model_labels: dict[str, str]  # task.models: {option: its rows' label}
    observation_factory: Callable[[SensorNetwork], ObservationModel]
    yu_faults_fusions: FaultGridFusions
    predict: Any  # the filter's prediction step (stateless)
    filter: FilterSettings
    seed: int
    dtype: torch.dtype
    device: torch.device

    def run(self, diagnostics: Diagnostics | None = None, progress: bool = False) -> pd.DataFrame:
        """Every cell of the grid; a tidy DataFrame (one row per cell x node summary x episode x metric).
        ``diagnostics`` gets the time of the offline fits and the number of cells run; every cell's gating
        counts reach the open :class:`~dslearn.diagnostics.Diagnostics` contexts (the run's)."""
        t = self.settings
        seed = int(self.seed)
        diag = diagnostics or Diagnostics()
        ctx = self.scenario.ctx()
        grid = fault_settings(t)
        cells = len(grid) * len(t.models) * len(t.fusions)
        frames, k, t0 = [], 0, time.perf_counter()
        with diag.timed("fit_offline"):
            offline = fit_offline_models(self.model_options, self.scenario, self.network, ctx, t.train_episodes, seed,
                                         self.dtype, self.device)
        from tqdm.auto import tqdm

        bar = tqdm(total=cells, desc="yu_faults cells", disable=not progress)
        for si, st in enumerate(grid):
            faulty = self.faulty_episodes(si, st)
            for mname in t.models:
                for fname in t.fusions:
                    k += 1
                    df = self.cell(st, si, ctx, mname, fname, faulty, offline[mname])
                    frames.append(df)
                    diag.count("cells")
                    bar.update(1)
                    te = df[(df.metric == "track_err") & (df.node == "alive")]["value"].mean()
                    log.info(
                        "cell %d/%d: link_fail=%.2f node_fail=%.2f outliers=%.2f gate=%s %s/%s: track_err(alive)=%.3f "
                        "(%.0fs)", k, cells, st.link_fail, st.node_fail, st.outlier_frac, st.gate_prob, mname, fname,
                        te, time.perf_counter() - t0,
                    )
        bar.close()
        out = pd.concat(frames, ignore_index=True)
        bad = out[out.metric == "nonfinite"]["value"].sum()
        if bad:
            log.warning("%d non-finite estimates in the grid", int(bad))
        return out

    def faulty_episodes(self, si: int, st: FaultSetting) -> dict[str, tuple[Episodes, torch.Tensor]]:
        """The test and training episodes of setting ``si`` with its data faults, and their node-alive
        schedules ``(S, B, K+1)``: ``{"test": (episodes, alive), "train": (...)}``.

        Common random numbers: the same data and faults for every model x fusion of a setting; one stream
        per episode, so an episode's data and faults do not depend on the batch size."""
        t, scenario, network, seed = self.settings, self.scenario, self.network, int(self.seed)
        s = network.num_nodes
        test = scenario.sample(t.test_episodes, network, episode_streams(seed, "test", 0, t.test_episodes))
        train = scenario.sample(t.train_episodes, network, episode_streams(seed, "train", 0, t.train_episodes))
        steps = test.states.shape[1] - 1
        faulty = {}
        for split, ep in (("test", test), ("train", train)):
            if len(ep) == 0:
                faulty[split] = (ep, torch.ones(s, 0, steps + 1, dtype=torch.bool))
                continue
            gs = Streams.from_keys([(seed, "faults", si, split, e) for e in range(len(ep))], (len(ep),))
            alive = node_failure_schedule(s, len(ep), steps, st.node_fail, gs, t.node_fail_mode, t.node_fail_duration)
            ep = apply_node_failures(ep, alive)
            if st.outlier_frac > 0:
                ep, _ = add_outliers(ep, st.outlier_frac, t.outlier_std, gs)
            faulty[split] = (ep.to(self.dtype, self.device), alive)
        return faulty

    def cell(self, st: FaultSetting, si: int, ctx: StepContext, mname: str, fname: str,
             faulty: dict[str, tuple[Episodes, torch.Tensor]], fitted: MotionModel | None = None) -> pd.DataFrame:
        """One cell: motion model ``mname`` x fusion ``fname`` on setting ``si``; its rows."""
        t, scenario, network, f = self.settings, self.scenario, self.network, self.filter
        seed = int(self.seed)
        # an offline model is the one fitted before the grid (a copy per cell); the others are built fresh
        model = copy.deepcopy(fitted) if fitted is not None else self.model_options[mname](scenario, network)
        obs = self.observation_factory(network)
        fusion = FaultyFusion(self.yu_faults_fusions.make[fname](network), network.adjacency, st.link_fail, t.weights,
                              seed=seed * 1_000_003 + 31 * si + 7)
        train, alive_tr = faulty["train"]
        test, alive_te = faulty["test"]
        model.begin_episodes(test.states)
        learner = OnlineLearner(
            network, model, obs, fusion, ctx,
            init=lambda ep: initial_belief(ep, network, ctx.dt, fusion, scenario.area, f.prior_pos_std,
                                           f.prior_vel_std),
            predict_step=self.predict, learn_gate_std=f.learn_gate_std, gate_prob=st.gate_prob,
        )

        def evaluate(_seen: int):
            fusion.begin(alive_te, episodes=list(range(alive_te.shape[1])), split="test")
            return learner.estimate(test.measurements)

        def before(i: int) -> None:
            fusion.begin(alive_tr[:, i : i + 1], episodes=[i], split="train")

        with Diagnostics() as cell:  # this cell's gating counts (the run's diagnostics get them too)
            if model.learnable:
                learner.run(train.measurements, [len(train)], lambda k: pd.DataFrame(), before=before)
            res = evaluate(len(train))
        return faulty_network_rows(
            res, test.states, alive_te, live_links=fusion.live_links, nominal_links=fusion.nominal_links,
            gate_tested=cell.gate_tested, gate_rejected=cell.gate_rejected,
            model=self.yu_faults_model_labels[mname], consensus=fname, link_fail=st.link_fail,
            node_fail=st.node_fail, outlier_frac=st.outlier_frac,
            gating="chi2" if st.gate_prob is not None else "none", axis=st.axis, node_fail_mode=t.node_fail_mode,
            weights=t.weights, iterations=int(self.yu_faults_fusions.rounds), train_episodes=int(t.train_episodes),
        )


def fit_offline_models(makers: dict[str, ModelMaker], scenario, network: SensorNetwork, ctx: StepContext,
                       train_episodes: int, seed: int, dtype: torch.dtype, device: torch.device) -> dict:
    """The offline models of the grid (``model.learns_offline``: the LSTM), each fitted once, before any cell,
    on the true tracks of the training episodes, which every fault setting shares (faults act on the
    measurements and the links only; :func:`dslearn.studies.yu.offline_trajectories`); ``{name: model or
    None}`` (None: a model built per cell). What a model cannot learn from is refused before any work."""
    out, probes = {}, {}
    for name, make in makers.items():
        with torch.random.fork_rng(devices=[]):  # a probe: shapes only (meta device), no draw of the run's
            probes[name] = make(scenario, network, device=torch.device("meta"))
        if probes[name].learns_offline:
            check_offline(probes[name])
        out[name] = None
    if any(p.learns_offline for p in probes.values()):
        train = scenario.sample(train_episodes, network, episode_streams(seed, "train", 0, train_episodes))
        for name, probe in probes.items():
            if probe.learns_offline:
                model = makers[name](scenario, network)
                out[name] = model.fit_offline(offline_trajectories(model, train).to(device, dtype), ctx.dt, seed=seed)
    return out
