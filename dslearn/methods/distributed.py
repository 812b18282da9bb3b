r"""Yu et al.'s method as parts: a distributed information filter (EKF or UKF prediction step) with a motion
model, an observation model and a fusion strategy, and a learner (:mod:`dslearn.learning.learners`): the parts
learn online while tracking the training episodes (``learner=online``, Algorithm 1: the GP models), the motion
model offline from their true tracks before it (``learner=offline``: the LSTM; ``learner=fg_identification``: the
damped constant-velocity model's ``(a, q)`` by the factor graph's messages) or nothing is learned (``learner=none``:
LIN, the social force). Without a learner the parts decide (the natural learner)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import pandas as pd
import torch

from dslearn.episodes import Episodes, Estimates, Measurements, Scenario, ScenarioSpec
from dslearn.filters.distributed import associated_belief, initial_belief, track
from dslearn.fusion.strategies import Fusion, make_fusion
from dslearn.learning.learners import (FactorGraphIdentification, NoLearning, OfflineLearning, OnlineLearning,
                                       refuse)
from dslearn.learning.backprop import (SUPPORTED_MODELS, BackpropLearning, BackpropParameters, fit, motion_misfit,
                                       motion_parameters, takes_q)
from dslearn.learning.calibrate import CalibrateLearning, ScaledSensor, calibrate_misfit, scaled_model
from dslearn.learning.fit_cache import fit_offline_cached
from dslearn.learning.online import OnlineLearner
from dslearn.models.observation import LinearPositionObservation
from dslearn.methods.base import require
from dslearn.models.base import MotionModel, ObservationModel
from dslearn.network import SensorNetwork
from dslearn.errors import ConfigError
from dslearn.types import AGENT_DIM, PV_LAYOUTS, safe_cholesky

_LOG = logging.getLogger(__name__)


@dataclass
class DistributedFilter:
    """The distributed filter of Yu et al. Algorithm 1 on a scenario's network.

    Args:
        predict: the prediction step (``filter.predict``: EKF linearisation or the unscented transform).
        model, observation, fusion: the parts (sized for the scenario and its network).
        prior_pos_std, prior_vel_std: the diffuse prior of a node that knows nothing of a target.
        learn_gate_std: the learning gate of Algorithm 1 (``None``: off).
        model_name: the motion model's label (its ``conf/model`` option).
        learner: :class:`~dslearn.learning.learners.OnlineLearning` (the parts that learn online learn while
            tracking the training episodes; needs a motion or observation model that learns online),
            :class:`~dslearn.learning.learners.OfflineLearning` (the motion model fitted to the training episodes'
            true tracks, then frozen; an observation model that learns online still does, as with ``online``;
            needs a model with ``fit_offline``) or :class:`~dslearn.learning.learners.NoLearning`; ``None``: the
            natural learner of the parts (:func:`natural_learner`). A motion model that learns offline has no
            weights until trained: it takes ``offline`` only.
            :class:`~dslearn.learning.learners.FactorGraphIdentification` (``model=cv_damped`` only): the model's
            ``(a, q)`` identified from the training episodes' true tracks before any tracking (its ``fit_motion``).
        associator: the ``associator`` part (:mod:`dslearn.association.network`): ``None`` or ``labels`` = the
            labels the scenario gives (a labelled scenario); ``gnn`` or ``jpda``: every node associates its own
            detections with its predicted tracks, then the update and the consensus run per track (a scenario of
            unlabelled detections only: a labelled one takes ``labels``). The tracks start at the scenario's
            declared start (``start_prior``); the training episodes are tracked (and learned from) the same way.
    """

    #: the learners it can use
    learners = ("online", "offline", "none", "backprop", "calibrate", "fg_identification")
    #: how the config layer names it (:func:`dslearn.schemas.base.unread_keys`)
    config_label = "the distributed filter"

    predict: Any
    model: MotionModel
    observation: ObservationModel
    fusion: Fusion
    prior_pos_std: float = 1000.0
    prior_vel_std: float = 1000.0
    learn_gate_std: float | None = 2.0
    model_name: str = "model"
    learner: Any = None
    associator: Any = None

    @property
    def associates(self) -> bool:
        """Whether it associates unlabelled detections (``associator=gnn|jpda``)."""
        return self.associator is not None and not getattr(self.associator, "needs_labels", True)

    def __post_init__(self) -> None:
        natural = natural_learner(self.model, self.observation)
        if self.learner is None:
            self.learner = natural
            return
        allowed = allowed_learners(self.model, self.observation)
        if isinstance(self.learner, BackpropLearning):
            self._check_backprop()
            return
        if isinstance(self.learner, CalibrateLearning):
            why = calibrate_misfit(self.observation, self.predict, self.learner.fit)
            if why is not None:
                raise refuse(self.learner, why, [a for a in allowed if a != "calibrate"])
            return
        if isinstance(self.learner, FactorGraphIdentification):  # sets a damped constant-velocity model's (a, q)
            why = self.learner.motion_misfit(self.model)
            if why is not None:
                raise refuse(self.learner, why, allowed)
            self.learner.check_motion_settings("the distributed filter (filter=default|ukf)")
            return
        if not isinstance(self.learner, (OnlineLearning, OfflineLearning, NoLearning)):
            raise refuse(self.learner, "the distributed filter (filter=default|ukf) takes "
                         "learner=online|offline|none|backprop|calibrate|fg_identification", allowed)
        if isinstance(self.learner, allowed_learner_types(self.model, self.observation)):
            return
        model = f"model {self.model_name}"
        if self.model.learns_offline:
            why = f"{model} has no weights until trained offline"
        elif isinstance(self.learner, OnlineLearning):
            why = f"{model} learns nothing online, nor does the observation model"
        else:
            why = f"{model} has no offline fit (fit_offline: lstm, social_lstm, sfm_fit)"
        raise refuse(self.learner, why, allowed)

    def _check_backprop(self) -> None:
        """learner=backprop: a motion model whose numbers it can learn (:func:`~dslearn.learning.backprop.motion_misfit`),
        the linear position sensor, a fusion with what ``learner.learn`` asks for; a one-line ConfigError otherwise."""
        why = backprop_misfit(self.model, self.observation, self.predict, self.model_name)
        if why is not None:
            raise ConfigError(why)
        if "q" in self.learner.learn and not takes_q(self.model):
            raise ConfigError(f"learner.learn=[q]: model={self.model_name}'s process noise is its own predictive "
                              f"variance, learned through its hyperparameters (learn: [model]); drop q")
        self.learner.check_fusion(self.fusion)

    def _backprop(self, scenario: Scenario, network: SensorNetwork, train: Episodes, ctx, seed: int, learner):
        """Learn the filter's numbers on the training episodes (:mod:`dslearn.learning.backprop`); the learned parts.
        The motion model first learns as it would alone: an offline model (the LSTM) fits offline, a GP gathers
        its data sets online (Algorithm 1, ``learner``); then its parameters learn through the filter."""
        if self.model.learns_offline:  # one fit per model, training set and seed, shared (the offline-fit cache)
            self._fit_offline(self.model, scenario, train, ctx, seed)
        if self.model.learnable:
            learner.run(train.measurements, [len(train)], lambda k: pd.DataFrame())
        a = self.model.state_dim // AGENT_DIM
        R = self.observation.noise_cov(torch.zeros(1, AGENT_DIM, dtype=torch.float64))[0]
        motion = motion_parameters(self.model, a, ctx.dt)
        if motion.takes_q:
            Q = self.model.noise_cov(torch.zeros(1, self.model.state_dim, dtype=torch.float64), ctx)[0, :AGENT_DIM, :AGENT_DIM]
        else:  # the model's own noise (a GP's variance): q is not learned, this block is never used
            Q = torch.eye(AGENT_DIM, dtype=torch.float64)
        train_fusion = self.learner.training_fusion(self.fusion)
        params = BackpropParameters(a, None, Q, R, train_fusion, network.adjacency, learn=self.learner.learn,
                                    motion=motion)

        def init(ep, fusion):
            return initial_belief(ep, network, ctx.dt, fusion, scenario.area, self.prior_pos_std, self.prior_vel_std)

        lr = self.learner
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            hist = fit(params, train.to(torch.float64, train.meas.device), network, ctx, init, epochs=lr.epochs,
                       lr=lr.lr, batch=lr.batch, loss=lr.loss, seed=seed, predict_step=self.predict,
                       model_lr=lr.model_lr, chunk=lr.chunk)
        self.learned = {**params.summary(), "loss": hist.loss, "seconds_per_epoch": hist.seconds_per_epoch}
        _LOG.info("learner=backprop: %s", {k: v for k, v in self.learned.items() if k != "loss"})
        model, obs, fusion = params.detached()
        self.learned_model = model  # the motion model it tracks with (the learned numbers)
        # train_fusion=individual: the numbers learned by the nodes alone, tracked with the configured fusion
        return model, obs, (fusion if train_fusion is self.fusion else self.fusion)

    def _calibrate(self, scenario: Scenario, network: SensorNetwork, train: Episodes, ctx, seed: int, learner):
        """learner=calibrate: the motion model learns as it does alone (an offline model fits offline, the parts
        that learn online learn on the training episodes, Algorithm 1), and the scales of Q and/or R are fitted to
        the training measurements, each node alone (:mod:`dslearn.learning.calibrate`; parts that learn online
        learn from the first episodes, the scales are fitted on the held-out rest, ``learner.holdout``, which they
        then learn from too); the parts with the scales."""
        if self.model.learns_offline:  # the offline fit every preset of this model shares (the fit cache)
            self._fit_offline(self.model, scenario, train, ctx, seed)
        n = len(train)
        held = min(int(round(self.learner.holdout * n)), n - 1) if learner.learnable and n > 1 else 0
        if learner.learnable:  # from the first episodes; the held-out ones after the fit (the same parts in the end)
            learner.run(train.measurements.select(slice(0, n - held)), [n - held], lambda k: pd.DataFrame())
        meas = train.measurements.select(slice(n - held, n)) if held else train.measurements
        alone = make_fusion("individual", torch.as_tensor(self.fusion.weights), self.fusion.iterations)
        init = initial_belief(meas, network, ctx.dt, alone, scenario.area, self.prior_pos_std, self.prior_vel_std)
        cal = self.learner.run(self.model, self.observation, meas, init, ctx, predict_step=self.predict)
        if held:
            learner.run(train.measurements.select(slice(n - held, n)), [held], lambda k: pd.DataFrame())
        self.learned = {**cal.summary(), "held_out_episodes": held}
        _LOG.info("learner=calibrate: %s", self.learned)
        model = self.model if cal.q_scale == 1.0 else scaled_model(self.model, cal.q_scale)
        obs = self.observation if cal.r_scale == 1.0 else ScaledSensor(self.observation, cal.r_scale)
        return model, obs

    @staticmethod
    def _fit_offline(model: MotionModel, scenario: Scenario, train: Episodes, ctx, seed: int) -> None:
        """The offline fit of ``model`` to the training episodes' true tracks in the filter's layout
        (:func:`filter_tracks`), made once per model, training set and seed and shared (the offline-fit cache)."""
        fit_offline_cached(model, filter_tracks(scenario, train.states, ctx.dt), ctx.dt, seed)

    def _fit_motion(self, model: MotionModel, train: Episodes, ctx, seed: int) -> None:
        """A learner that sets the motion model's parameters from the training episodes' true tracks before any
        tracking (``fit_motion``: ``learner=fg_identification``) does so; the values in :attr:`learned`."""
        fit_motion = getattr(self.learner, "fit_motion", None)
        if fit_motion is None:
            return
        ident = fit_motion(model, train.states, ctx.dt, self.prior_pos_std, self.prior_vel_std, seed)
        self.learned = {"a": model.a, "q": model.q, "var": ident.var.tolist(), "rounds": ident.path.shape[0] - 1,
                        "rows": ident.rows}
        _LOG.info("learner=%s: %s", self.learner.name, self.learned)

    @property
    def label(self) -> str:
        omega = f" ω={self.fusion.omega_label}" if self.fusion.uses_omega and self.fusion.omega_label != "one" else ""
        own = type(self.learner) is type(natural_learner(self.model, self.observation))
        extra = "" if own else f" learner={getattr(self.learner, 'label', self.learner.name)}"
        assoc = f" {self.associator.name}" if self.associates else ""
        return f"{getattr(self.predict, 'name', 'ekf')} {self.model_name} {self.fusion.name}{omega}{extra}{assoc}"

    @staticmethod
    def spec_misfit(spec: ScenarioSpec) -> str | None:
        """What the engine needs of a scenario, declared (:func:`dslearn.methods.base.declared_misfit`): 2-D target
        positions to estimate, read by sensors its observation models explain (the observation part declares which
        kind it explains), targets seen by the network or nodes navigating themselves. What a fusion needs of the
        network (a graph for consensus) the fusion part declares."""
        return require(spec, "the distributed filter (readings of a kind its observation models explain, 2-D "
                             "positions to estimate)", measurement=MEASUREMENT_KINDS, state=STATE_LAYOUTS,
                       kind=("targets", "self"))

    def fits(self, spec: ScenarioSpec) -> str | None:
        reason = DistributedFilter.spec_misfit(spec)
        if reason is None and spec.tracks_targets and getattr(self.fusion, "alone", False) \
                and self.observation.meas_dim < 2:
            reason = (f"with consensus={self.fusion.name} every node fuses only its own readings; one scalar "
                      f"{spec.measurement} reading per step (observation {type(self.observation).__name__}) does "
                      f"not fix a target's 2-D position (a curve of positions fits it): the sensors must fuse "
                      f"(consensus=centralized)")
        if reason is None:
            reason = self._association_misfit(spec)
        # a prediction step that needs a kind of motion model (filter=adf: the exact GP; filter=ukf_mm: a GP)
        misfit = getattr(self.predict, "model_misfit", None) if reason is None else None
        return reason if misfit is None else misfit(self.model, self.model_name)

    def _association_misfit(self, spec: ScenarioSpec) -> str | None:
        """Unlabelled detections need an associator (gnn, jpda), position detections and a learner that tracks
        with it (online, offline, none); an associator needs a scenario of targets."""
        if not getattr(spec, "labelled", True) and not self.associates:
            name = getattr(self.associator, "name", "labels")
            return (f"associator={name} needs every measurement labelled with its target; scenario {spec.name} "
                    f"reports unlabelled detections (choose associator=gnn or associator=jpda)")
        if not self.associates:
            return None
        if getattr(spec, "labelled", True):
            return (f"associator={self.associator.name} associates unlabelled detections; scenario {spec.name} gives "
                    f"every measurement labelled with its target (associator=labels)")
        if not spec.tracks_targets:
            return f"associator={self.associator.name} associates detections of targets; scenario {spec.name} has " \
                   f"nodes navigating themselves"
        if not self.observation.measures_position:
            return (f"associator={self.associator.name} associates position detections; observation "
                    f"{type(self.observation).__name__} does not measure positions")
        if self.learner.learns_through_update:
            return (f"learner={self.learner.name} learns through the labelled update; with "
                    f"associator={self.associator.name} use learner=online|offline|none")
        return self._managed_misfit(spec)

    def _managed_misfit(self, spec: ScenarioSpec) -> str | None:
        """Managed tracks (targets that enter and leave, :mod:`dslearn.association.multitrack`) are tracked with the
        motion model as it is: nothing learns along them (learner=none, or learner=offline: a model fitted to the
        training episodes' true tracks before any tracking), and each track is predicted alone (a model of
        independent targets, :attr:`~dslearn.models.base.MotionModel.independent_targets`)."""
        tracks = getattr(self.associator, "tracks", None)
        if tracks is None or not tracks.manages(spec):
            return None
        why = "of targets that enter and leave" if getattr(spec, "births", False) else "(associator.tracks.manage=on)"
        if not (isinstance(self.learner, NoLearning) or self.learner.fits_offline) or self.model.learnable \
                or self.observation.learnable:
            return (f"scenario {spec.name} reports unlabelled detections {why}: associator={self.associator.name} "
                    f"manages the tracks, and nothing learns along managed tracks; it takes learner=none, or "
                    f"learner=offline with a model fitted to the training tracks (here model={self.model_name}, "
                    f"learner={self.learner.name})")
        if not self.model.independent_targets:
            return (f"scenario {spec.name} reports unlabelled detections {why}: associator={self.associator.name} "
                    f"manages the tracks and predicts each track alone; it takes a motion model of independent "
                    f"targets (model=lin|cv_damped|lstm), not model={self.model_name}")
        return None

    def _init(self, scenario: Scenario, network: SensorNetwork, ctx, fusion: Fusion, obs: ObservationModel):
        """``init(measurements) -> (mean, info)``: :func:`~dslearn.filters.distributed.initial_belief` with the
        observation model and, where the scenario declares its nodes' known start (``initial_states()``, one block
        ``[p, v]`` per platform: Braga's aircraft), that start."""
        start = getattr(scenario, "initial_states", None)
        start = start() if callable(start) and not obs.measures_position else None
        return lambda ep: initial_belief(ep, network, ctx.dt, fusion, scenario.area, self.prior_pos_std,
                                         self.prior_vel_std, obs=obs, start=start)

    def estimate(self, scenario: Scenario, network: SensorNetwork, train: Episodes, test: Measurements,
                 seed: int) -> Estimates:
        ctx, model, fusion, obs = scenario.ctx(), self.model, self.fusion, self.observation
        if self.associates:
            return self._estimate_associating(scenario, network, train, test, seed)

        def online(model, obs, fusion):
            return OnlineLearner(
                network, model, obs, fusion, ctx, init=self._init(scenario, network, ctx, fusion, obs),
                predict_step=self.predict, learn_gate_std=self.learn_gate_std,
            )

        learner = online(model, obs, fusion)
        if isinstance(self.learner, CalibrateLearning):
            model, obs = self._calibrate(scenario, network, train, ctx, seed, learner)
            learner = online(model, obs, fusion)  # tracks with the configured fusion and the scaled noises
        if isinstance(self.learner, BackpropLearning):
            model, obs, fusion = self._backprop(scenario, network, train, ctx, seed, learner)
            learner = online(model, obs, fusion)
        if self.learner.fits_offline:  # supervised: learns from the training episodes' true tracks (once: the fit cache)
            self._fit_offline(model, scenario, train, ctx, seed)
        self._fit_motion(model, train, ctx, seed)
        if self.learner.learns_online and learner.learnable:  # Algorithm 1 (offline: a learning observation model)
            learner.run(train.measurements, [len(train)], lambda k: pd.DataFrame())  # no evaluation at checkpoints
        for m in {id(self.model): self.model, id(model): model}.values():  # a model conditioned per episode (the
            m.begin_measured(test.meas, test.visible, ctx.dt)              # fitted social force's desired velocities)
        res = learner.estimate(test)
        if scenario.spec.navigates_itself:  # each node's estimate of its own platform: one report of every platform
            return own_estimates(res.mean, res.info, scenario.spec.num_agents)
        return beliefs_to_estimates(res.mean, res.info, network, scenario.spec.num_agents)


    def _estimate_associating(self, scenario: Scenario, network: SensorNetwork, train: Episodes, test: Measurements,
                              seed: int) -> Estimates:
        """:meth:`estimate` with every node associating its own detections (:class:`AssociatingLearner`)."""
        ctx, model, fusion, obs = scenario.ctx(), self.model, self.fusion, self.observation
        a = scenario.spec.num_agents
        managed = self.associator.network_tracks(scenario, network)
        if managed is not None:  # targets enter and leave: every node manages its tracks (association.multitrack)
            why = self._managed_misfit(scenario.spec)
            if why is not None:
                raise ConfigError(why)
            if self.learner.fits_offline:  # the model fitted to the training episodes' true tracks, then frozen
                self._fit_offline(model, scenario, train, ctx, seed)
            pos, cov = managed.run(test.meas, test.visible, network.adjacency, model, obs, fusion, ctx)
            return Estimates(pos, cov, list(network.names), network.is_sensor.clone())
        hook = self.associator.make(scenario, network, a)
        start = getattr(scenario, "start_prior", None)
        if not callable(start):
            raise ConfigError(f"associator={self.associator.name}: scenario {scenario.spec.name} declares no start of "
                              f"its targets (start_prior) to start the tracks from")
        prior = start()

        def init(ep):
            return associated_belief(ep, fusion, prior, hook, obs)
        learner = AssociatingLearner(network, model, obs, fusion, ctx, init=init, predict_step=self.predict,
                                     learn_gate_std=self.learn_gate_std, associate=hook)
        if self.learner.fits_offline:
            self._fit_offline(model, scenario, train, ctx, seed)
        self._fit_motion(model, train, ctx, seed)
        if self.learner.learns_online and learner.learnable:
            learner.run(train.measurements, [len(train)], lambda k: pd.DataFrame())
        res = learner.estimate(test)
        return beliefs_to_estimates(res.mean, res.info, network, a)


def filter_tracks(scenario: Scenario, states: torch.Tensor, dt: float) -> torch.Tensor:
    """True tracks ``(B, K+1, Dx)`` in the filter's state layout, ``[p, v]`` per agent, what an offline fit learns
    from: the scenario's states where they already are (``pv2d``, ``platform``), else its positions
    (:meth:`positions`) with velocities by finite differences (:func:`torch.gradient`: central inside, one-sided at
    the ends), as for the recorded pedestrians (Jiang's source is a position alone)."""
    if scenario.spec.state in PV_LAYOUTS:
        return states
    pos = scenario.positions(states)  # (B, K+1, A, 2)
    vel = torch.gradient(pos, spacing=float(dt), dim=1, edge_order=1)[0]
    return torch.cat([pos, vel], -1).flatten(-2)


@dataclass
class AssociatingLearner(OnlineLearner):
    """Algorithm 1's learner (:class:`~dslearn.learning.online.OnlineLearner`) tracking unlabelled detections:
    every node associates its own detections with its tracks (``associate``,
    :class:`~dslearn.association.network.NodeAssociation`) before the update and the fusion."""

    associate: Any = None

    def learn(self, ep: Measurements) -> None:
        track(ep, self.network, self.model, self.obs, self.fusion, self.ctx, self.init(ep), learn=True,
              learn_gate_std=self.learn_gate_std, gate_prob=self.gate_prob, predict_step=self.predict_step,
              associate=self.associate)
        self.seen += 1
        every = int(getattr(self.model, "fit_every", 0) or 0)
        if every and self.seen % every == 0:
            self.model.fit()

    @torch.no_grad()
    def estimate(self, ep: Measurements):
        return track(ep, self.network, self.model, self.obs, self.fusion, self.ctx, self.init(ep), learn=False,
                     gate_prob=self.gate_prob, predict_step=self.predict_step, associate=self.associate)


def natural_learner(model: MotionModel, observation: ObservationModel):
    """The learner the parts call for: offline for a motion model that learns offline (``fit_offline``), else
    online where the motion or the observation model learns online, else none."""
    if model.learns_offline:
        return OfflineLearning()
    if model.learnable or observation.learnable:
        return OnlineLearning()
    return NoLearning()


def allowed_learner_types(model: MotionModel, observation: ObservationModel) -> tuple[type, ...]:
    """The learners (their classes) the distributed filter can use with these parts (the natural one first)."""
    bp = (BackpropLearning,) if backprop_misfit(model, observation) is None else ()
    bp += (CalibrateLearning,) if calibrate_misfit(observation, fit=("q",)) is None else ()
    bp += (FactorGraphIdentification,) if FactorGraphIdentification.motion_misfit(model) is None else ()
    if model.learns_offline:
        return (OfflineLearning, *bp)
    if model.learnable or observation.learnable:
        return (OnlineLearning, NoLearning, *bp)
    return (NoLearning, *bp)


def allowed_learners(model: MotionModel, observation: ObservationModel) -> tuple[str, ...]:
    """The learners the distributed filter can use with these parts, by their config names (the natural one
    first)."""
    return tuple(c.name for c in allowed_learner_types(model, observation))


def backprop_misfit(model: MotionModel, observation: ObservationModel, predict=None, model_name: str | None = None) -> str | None:
    """Why ``learner=backprop`` does not fit these parts (``None`` where it does): a motion model whose numbers it
    can learn (:func:`~dslearn.learning.backprop.motion_misfit`) and the linear position sensor (its ``R``)."""
    name = f"model={model_name}" if model_name else f"model {type(model).__name__}"
    if not isinstance(observation, LinearPositionObservation):
        return (f"learner=backprop learns the linear position sensor's R (observation=linear), not observation "
                f"{type(observation).__name__}")
    why = motion_misfit(model, predict)
    if why is not None:
        return f"learner=backprop supports model={'|'.join(SUPPORTED_MODELS)} with observation=linear, not {name}: {why}"
    return None


def _positions(mean: torch.Tensor, info: torch.Tensor, num_agents: int | None):
    """Every target's position ``(..., A, 2)`` and its covariance ``(..., A, 2, 2)`` (the position block of
    ``info^-1``), for target blocks whose first two entries are the position (``d = Dx / A`` entries each)."""
    cov = torch.cholesky_inverse(safe_cholesky(info))
    a = mean.shape[-1] // AGENT_DIM if num_agents is None else int(num_agents)
    d = mean.shape[-1] // a
    blocks = cov.unflatten(-2, (a, d)).unflatten(-1, (a, d))  # (..., A, d, A, d)
    pos_cov = torch.diagonal(blocks, dim1=-4, dim2=-2).movedim(-1, -3)[..., :2, :2]  # (..., A, 2, 2)
    return mean.unflatten(-1, (a, d))[..., :2], pos_cov


def beliefs_to_estimates(mean: torch.Tensor, info: torch.Tensor, network: SensorNetwork,
                         num_agents: int | None = None) -> Estimates:
    """Information-form beliefs of every node, ``mean (S, B, K+1, Dx)``, ``info (S, B, K+1, Dx, Dx)`` (``A`` target
    blocks, ``[px, py, vx, vy]`` each where ``num_agents`` is not given), as position estimates and their
    covariances (the position blocks of ``info^-1``)."""
    pos, pos_cov = _positions(mean, info, num_agents)
    return Estimates(pos, pos_cov, list(network.names), network.is_sensor.clone())


#: the report of nodes that navigate themselves: every platform estimated by its own node's filter
ONBOARD = "onboard"


def own_estimates(mean: torch.Tensor, info: torch.Tensor, num_agents: int) -> Estimates:
    """Beliefs of nodes that navigate themselves (node ``s`` estimates platform ``s``): node ``s``'s estimate of its
    own platform, gathered as one report of the ``A = S`` platforms (``nodes = ["onboard"]``, as Braga's RBPF
    method reports)."""
    pos, pos_cov = _positions(mean, info, num_agents)  # (S, B, K+1, A, 2)
    s = pos.shape[0]
    if s != num_agents:
        raise ValueError(f"nodes that navigate themselves: {s} nodes for {num_agents} platforms")
    idx = torch.arange(s, device=pos.device)
    own = pos[idx, :, :, idx].movedim(0, -2)[None]  # (1, B, K+1, A, 2)
    own_cov = pos_cov[idx, :, :, idx].movedim(0, -3)[None]  # (1, B, K+1, A, 2, 2)
    return Estimates(own, own_cov, [ONBOARD], torch.ones(1, dtype=torch.bool))


#: the measurement kinds its observation models explain (the observation part declares which one it takes)
MEASUREMENT_KINDS = ("position", "squared_range", "range", "bearing", "terrain_altitude")
#: the state layouts it estimates positions in: Yu's walkers, a 2-D parameter (Jiang's source), platforms (Braga's)
STATE_LAYOUTS = ("pv2d", "param2d", "platform")
