r"""Braga et al.'s RBPF + online EM + consensus on the EM statistics, taken to sensors that track targets: every
node runs, for every target, a Rao-Blackwellised particle filter over its sensor's jump-Markov noise modes (a mixture
Kalman filter, :mod:`dslearn.filters.mkf`) with a constant-velocity (LIN) state, the online E-step on the particles'
paths, the nodes combine their sufficient statistics (the method's fusion part,
:class:`~dslearn.fusion.stats_consensus.StatisticsConsensus`) and each runs the M-step
(:func:`dslearn.models.jmnls.m_step`, the one of Braga's engine) on the result.

The sensors are the method's observation part (``observation=sensor``: the scenario's own sensor model). Position
sensors (the linear position sensor) are as described below: each node filters every target it sees with its own
readings, the Kalman filter per particle exact. A nonlinear sensor (squared range, range, bearing: Jiang et al.'s
source) reads one scalar per step, which does not fix a 2-D position on its own (a squared range fixes a circle):
the sensors' readings of a target are fused in one filter, a fusion centre's (the scenario's sensors report to one,
``networked = false`` on Jiang's), whose particles are the sensors' joint mode sequences, each sensor with its own
mode chain and its own statistics, and each particle carries the extended Kalman filter of the state (the reading
linearised with the observation model's Jacobian at the particle's prediction, the sensors taken one after the
other: :func:`dslearn.filters.mkf.mkf_step_sensors`). The EM and the consensus on the statistics are the same: the
sensors' statistics (weighted over the centre's particles, summed over the targets) are combined by the fusion part
and every sensor runs the M-step on its combination. The prior's mean sits at the first fix of the readings at
``t = 0`` (:func:`dslearn.filters.distributed.first_fix` with the sensors fused, the linearisation point of the
first update; its covariance stays the diffuse prior, so no reading is counted twice); the modes' initial
spreads are in units of the reading's noise std (the observation model's ``R``: ``sigma_y / sqrt(L)`` for Jiang's
``L`` averaged samples). Estimates: the fusion centre's (``nodes = ["fusion"]``).

The model each node assumes: the target moves as ``x_t = F x_{t-1} + G w_t`` (Braga et al.'s Eq. 23-24,
:func:`dslearn.sim.terrain.cv_model`, ``Q = q I_2``, ``q = filter.process_noise``) and the sensor measures its
position as ``y_t = H x_t + e_t``, ``e_t ~ N(0, sigma_{r_t}^2 I_2)`` with ``r_t`` a two-state Markov chain (each
node-target measurement stream its own chain; the modes' parameters are the node's, learned from all the targets
it sees). The modes are zero-mean: a common bias of a position sensor moves every measurement of the target the
same way and cannot be told from the target's position, so the EM learns the modes' spreads and the transition
matrix only.

The EM starts afresh in every test episode (online, as in Braga et al.): the training episodes teach it nothing.
Its learner is :class:`~dslearn.learning.learners.OnlineEMSensor` (``learner=online_em_sensor``): Braga et al.'s
online EM with its initial modes in units of the sensors' noise standard deviation, so one setting is sized for
Yu's 0.2 m and Liu's 2 m sensors alike, zero-mean modes and no mode known at ``t = 0``.

Estimates: every node's mixture mean and covariance of each target's position; a target a node has not yet
seen stays at the diffuse prior (:func:`dslearn.filters.distributed.prior_means`, ``prior_pos_std``,
``prior_vel_std``), as in the distributed filter with ``consensus=individual``. The random numbers of test
episode ``i`` come from the stream ``(seed, "filter", i)``.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import torch

from dslearn.episodes import Episodes, Estimates, Measurements, Scenario, ScenarioSpec
from dslearn.errors import ConfigError, check_integer, check_number
from dslearn.filters.distributed import diffuse_prior, first_fix, prior_means
from dslearn.filters.mkf import LinearGaussianState, init_state, local_stats, mkf_step, mkf_step_sensors, moments
from dslearn.fusion.strategies import Centralized
from dslearn.learning.learners import OnlineEMSensor, refuse
from dslearn.methods.base import require
from dslearn.methods.rbpf import FUSION_KIND, check_particle_settings
from dslearn.models.base import ObservationModel
from dslearn.models.jmnls import NoiseParams, m_step, stats_dim
from dslearn.models.observation import LinearPositionObservation
from dslearn.network import SensorNetwork
from dslearn.sim.terrain import cv_model
from dslearn.streams import Streams

#: the state layout it tracks per target (``[px, py, vx, vy]``)
AGENT_DIM = 4
#: the readings it explains: positions (a Kalman filter per particle at every node) or one scalar per sensor and
#: step of a nonlinear sensor (an extended Kalman filter per particle at a fusion centre)
MEASUREMENTS = ("position", "squared_range", "range", "bearing")
#: the state layouts whose first two entries it estimates: Yu's walkers, a 2-D parameter (Jiang's source)
STATE_LAYOUTS = ("pv2d", "param2d")
#: the reporting entry of the fusion centre (nonlinear sensors)
CENTRE = "fusion"


def _finished(mean: torch.Tensor, cov: torch.Tensor, params: list) -> tuple:
    """A run's mixture means and covariances and its noise parameters after each step (``params`` stacked);
    FloatingPointError on a non-finite estimate."""
    if not (torch.isfinite(mean).all() and torch.isfinite(cov).all()):
        raise FloatingPointError("non-finite estimate in the RBPF over noise modes (this is a bug)")
    return mean, cov, NoiseParams(torch.stack([p.mu for p in params]), torch.stack([p.sigma for p in params]),
                                  torch.stack([p.pi for p in params]))


@dataclasses.dataclass
class RBPFModesMethod:
    """RBPF over the noise modes (mixture Kalman filter, LIN state) + online EM + consensus on the statistics.

    Args:
        fusion: the cooperation on the statistics (the ``consensus`` part, ``kind = "statistics"``).
        num_particles: particles (mode sequences) per node and target.
        process_noise: ``q`` of the constant-velocity model [(m/s^2)^2].
        ess_threshold: resample when ESS < ``ess_threshold * N``.
        prior_pos_std, prior_vel_std: the diffuse prior of a target not yet seen [m], [m/s].
        ekf_iterations: a nonlinear sensor's linearisations per update of a particle's filter (the iterated extended
            Kalman update, :func:`dslearn.filters.mkf.iekf_mode_updates`; 1: the extended update at the prediction);
            ``None``: 5. The linear position sensor's Kalman update is exact and reads no count: a value given with
            it is refused.
        fusion_name: the fusion part's label.
        learner: the online EM for position sensors (:class:`~dslearn.learning.learners.OnlineEMSensor`); ``None``:
            its defaults (``conf/learner/online_em_sensor.yaml``).
        observation: the sensors' model (the ``observation`` part, ``observation=sensor``: the scenario's own): the
            linear position sensor (every node's own Kalman filters) or a nonlinear sensor of one reading per step
            (the fusion centre's extended Kalman filters); its ``noise_std`` is the modes' unit. ``None``: the linear
            position sensor with the network's noise (``network.meas_std``).
    """

    fusion_kind = FUSION_KIND
    learners = ("online_em_sensor",)

    fusion: Any
    num_particles: int = 64
    process_noise: float = 1.0
    ess_threshold: float = 0.5
    prior_pos_std: float = 1000.0
    prior_vel_std: float = 1000.0
    ekf_iterations: int | None = None
    fusion_name: str | None = None
    learner: Any = None
    observation: Any = None

    def __post_init__(self) -> None:
        obs = self.observation
        if obs is not None and (not isinstance(obs, ObservationModel) or obs.learnable
                                or not (isinstance(obs, LinearPositionObservation) or obs.meas_dim == 1)):
            raise ConfigError(f"observation={type(obs).__name__} is not a sensor model the RBPF over noise modes "
                              f"(filter=rbpf_em_lin) can take: it learns the noise of fixed sensors, the linear "
                              f"position sensor or one reading per step of a nonlinear one (observation=sensor|"
                              f"linear|squared_range|range|bearing)")
        if getattr(self.fusion, "kind", None) != self.fusion_kind:
            name = self.fusion_name or type(self.fusion).__name__
            raise ConfigError(f"consensus={name} is not a cooperation on sufficient statistics: the RBPF over noise "
                              f"modes + online EM (filter=rbpf_em_lin) combines its nodes' EM statistics, "
                              f"consensus=statistics")
        check_particle_settings(self)
        for key in ("prior_pos_std", "prior_vel_std"):
            setattr(self, key, check_number(f"filter.{key}", getattr(self, key), 0.0, strict=True))
        it = self.ekf_iterations
        if it is not None:
            check_integer("filter.ekf_iterations", it, 1, note=" (1: the extended Kalman update)")
        if it is not None and not self.centre:
            raise ConfigError(f"filter.ekf_iterations={it!r}: the linear position sensor's Kalman update is exact and "
                              f"reads no linearisation count; drop the key (it is read with a nonlinear sensor of one "
                              f"reading per step: observation=sensor on squared ranges, ranges or bearings)")
        if self.learner is None:
            self.learner = OnlineEMSensor()
        elif not isinstance(self.learner, OnlineEMSensor):
            raise refuse(self.learner, "the RBPF over noise modes (filter=rbpf_em_lin) learns the position sensors' "
                                       "zero-mean noise modes, in units of their noise std, with the online EM",
                         self.learners)

    @property
    def label(self) -> str:
        return f"rbpf_em_lin {self.fusion.name}"

    @property
    def iterations(self) -> int:
        """The iterated EKF's linearisations per update (``ekf_iterations``, 5 when not given)."""
        return 5 if self.ekf_iterations is None else self.ekf_iterations

    @property
    def centre(self) -> bool:
        """Whether the sensors' readings are fused at a fusion centre (a nonlinear sensor of one reading per step)."""
        return self.observation is not None and not isinstance(self.observation, LinearPositionObservation)

    @staticmethod
    def spec_misfit(spec: ScenarioSpec) -> str | None:
        """What the engine needs of a scenario, declared (:func:`dslearn.methods.base.declared_misfit`): sensors that
        track targets (not platforms navigating themselves: Braga's aircraft are ``method=rbpf_em``'s), readings of
        their positions or a nonlinear sensor's (its observation part declares which it explains), 2-D positions of
        a ``[px, py, ...]`` state or a 2-D parameter."""
        if spec.navigates_itself:
            return (f"the RBPF over noise modes (filter=rbpf_em_lin) tracks targets that sensors measure; on scenario "
                    f"{spec.name} every node navigates itself (its own platform, no target: Braga et al.'s own engine, "
                    f"method=rbpf_em)")
        return require(spec, "the RBPF over noise modes (a Kalman filter per mode sequence, extended for a nonlinear "
                             "sensor: readings of the targets' positions or one scalar reading per sensor and step, "
                             "2-D positions to estimate)", measurement=MEASUREMENTS, state=STATE_LAYOUTS)

    def fits(self, spec: ScenarioSpec) -> str | None:
        why = RBPFModesMethod.spec_misfit(spec)
        if why is None and spec.measurement != "position" and not self.centre:
            why = (f"the RBPF over noise modes with the linear position sensor (observation=linear) cannot read "
                   f"scenario {spec.name}'s {spec.measurement}: observation=sensor (the scenario's own sensor model)")
        return why

    def sensor_std(self, network: SensorNetwork) -> float:
        """The unit of the modes: the std of one reading the model explains (``sqrt(R)``: the linear sensor's
        ``noise_std``, a nonlinear one's ``noise_std / sqrt(samples)``); without an observation part the network's
        ``meas_std``."""
        obs = self.observation
        if obs is None:
            return float(network.meas_std)
        if isinstance(obs, LinearPositionObservation):
            return float(obs.noise_std)
        r = obs.noise_cov(torch.zeros(1, AGENT_DIM, dtype=torch.float64))  # (1, 1, 1): one reading's variance
        return float(r[0, 0, 0]) ** 0.5

    def initial_modes(self, sensor_std: float, dtype, device) -> NoiseParams:
        """The EM's initial noise modes in metres (the learner's, in units of ``sensor_std``)."""
        init = self.learner.init
        return NoiseParams(init.mu.to(device, dtype) * sensor_std, init.sigma.to(device, dtype) * sensor_std,
                           init.pi.to(device, dtype))

    def estimate(self, scenario: Scenario, network: SensorNetwork, train: Episodes, test: Measurements,
                 seed: int) -> Estimates:
        """Every node's filters on every test episode, or the fusion centre's (a nonlinear sensor); ``train`` is not
        used: the EM is online."""
        mean, cov, _ = self.track(test, network, scenario.spec.dt, scenario.area, seed)
        if self.centre:
            return Estimates(mean[..., :2], cov[..., :2, :2], [CENTRE], torch.ones(1, dtype=torch.bool))
        return Estimates(mean[..., :2], cov[..., :2, :2], list(network.names), network.is_sensor.clone())

    def track(self, test: Measurements, network: SensorNetwork, dt: float, area, seed: int):
        """The filters of every node and target on ``test``: mixture means ``(S, B, K+1, A, 4)``, covariances
        ``(S, B, K+1, A, 4, 4)`` and the noise parameters after each step (a :class:`NoiseParams` of
        ``(K+1, B, S, ...)`` tensors); a nonlinear sensor: the fusion centre's, ``S = 1`` (:meth:`track_centre`)."""
        if self.centre:
            return self.track_centre(test, network, dt, area, seed)
        meas, vis = test.meas, test.visible
        s, b, t1, a = vis.shape
        dtype, device = torch.float64, meas.device
        y = meas.to(dtype).permute(1, 2, 0, 3, 4)  # (B, K+1, S, A, 2)
        v = vis.permute(1, 2, 0, 3)  # (B, K+1, S, A)
        dyn = cv_model(dt, self.process_noise, dtype=dtype, device=device)
        h = torch.zeros(2, AGENT_DIM, dtype=dtype, device=device)
        h[0, 0] = h[1, 1] = 1.0
        model = LinearGaussianState(dyn.F, dyn.G @ dyn.Q @ dyn.G.T, h)
        theta = self.initial_modes(self.sensor_std(network), dtype, device)
        k = theta.k
        theta = theta.expand(b, s)
        m0 = prior_means(a, area).to(device, dtype).expand(b, s, a, AGENT_DIM)
        p0 = torch.diag(torch.tensor([self.prior_pos_std ** 2] * 2 + [self.prior_vel_std ** 2] * 2, dtype=dtype,
                                     device=device)).expand(b, s, a, AGENT_DIM, AGENT_DIM)
        alpha0 = torch.full((k,), 1.0 / k, dtype=dtype, device=device)
        state = init_state(m0, p0, alpha0, self.num_particles, stats_dim(k))
        comb = self.fusion.matrix().to(device, dtype)  # (S, S)
        gen = Streams.from_keys([(int(seed), "filter", i) for i in range(b)], (b,), device=device)
        em = self.learner.em
        means, covs, params = [], [], []
        for t in range(t1):
            n = t + 1  # the EM's step count (eta_1 = 1)
            th = NoiseParams(theta.mu[:, :, None], theta.sigma[:, :, None], theta.pi[:, :, None])
            state, _ = mkf_step(state, y[:, t], v[:, t], model, th, gen, eta=float(n) ** (-em["eta_exponent"]),
                                ess_threshold=self.ess_threshold, predict=t > 0, learn_mean=False)
            stats = local_stats(state).sum(2)  # (B, S, D): the node's statistics over its targets
            glob = torch.einsum("sr,brd->bsd", comb, stats)  # the cooperation (identity / Eq. 19 / Algorithm 3)
            if n > em["burn_in"]:
                theta = m_step(glob, theta, sigma_floor=em["sigma_floor"])
            mk, ck = moments(state)
            means.append(mk)
            covs.append(ck)
            params.append(theta)
        mean = torch.stack(means, 1).permute(2, 0, 1, 3, 4)  # (S, B, K+1, A, 4)
        cov = torch.stack(covs, 1).permute(2, 0, 1, 3, 4, 5)
        return _finished(mean, cov, params)

    def track_centre(self, test: Measurements, network: SensorNetwork, dt: float, area, seed: int):
        """The fusion centre's filters of every target on ``test`` from all the sensors' readings (the module
        docstring): mixture means ``(1, B, K+1, A, 4)``, covariances ``(1, B, K+1, A, 4, 4)`` and every sensor's
        noise parameters after each step (``(K+1, B, S, ...)``)."""
        obs = self.observation
        meas, vis = test.meas, test.visible
        s, b, t1, a = vis.shape
        dtype, device = torch.float64, meas.device
        if s != obs.sensors.shape[0]:
            raise ConfigError(f"the observation model has {obs.sensors.shape[0]} sensors; the measurements hold {s} "
                              f"nodes")
        z = obs.reading(meas.to(dtype))  # (S, B, K+1, A, d)
        y = z.permute(1, 2, 3, 0, 4)  # (B, K+1, A, S, d)
        v = vis.permute(1, 2, 3, 0)  # (B, K+1, A, S)
        dyn = cv_model(dt, self.process_noise, dtype=dtype, device=device)
        model = LinearGaussianState(dyn.F, dyn.G @ dyn.Q @ dyn.G.T, torch.zeros(z.shape[-1], AGENT_DIM, dtype=dtype,
                                                                                  device=device))

        def observe(j: int, x):  # sensor j's reading and Jacobian at states x (..., 4): the model takes node-first
            xs = x.unsqueeze(0).expand(s, *x.shape)
            return obs(xs)[j], obs.jacobian(xs)[j]

        theta = self.initial_modes(self.sensor_std(network), dtype, device)
        k = theta.k
        theta = theta.expand(b, s)
        m0, p0 = self.centre_prior(test, network, dt, area, dtype, device)
        alpha0 = torch.full((k,), 1.0 / k, dtype=dtype, device=device)
        state = init_state(m0, p0, alpha0, self.num_particles, stats_dim(k))  # (B, A, N, ...)
        state.alpha = state.alpha[..., None, :].expand(*state.alpha.shape[:-1], s, k).clone()
        state.T = state.T[..., None, :].expand(*state.T.shape[:-1], s, state.T.shape[-1]).clone()
        comb = self.fusion.matrix().to(device, dtype)  # (S, S)
        gen = Streams.from_keys([(int(seed), "filter", i) for i in range(b)], (b,), device=device)
        em = self.learner.em
        means, covs, params = [], [], []
        for t in range(t1):
            n = t + 1
            th = NoiseParams(theta.mu[:, None], theta.sigma[:, None], theta.pi[:, None])  # (B, 1, S, ...)
            state, _ = mkf_step_sensors(state, y[:, t], v[:, t], model, observe, th, gen,
                                        eta=float(n) ** (-em["eta_exponent"]), ess_threshold=self.ess_threshold,
                                        predict=t > 0, learn_mean=False, wrap=obs.residual,
                                        iterations=self.iterations)
            stats = local_stats(state).sum(1)  # (B, S, D): every sensor's statistics over the targets
            glob = torch.einsum("sr,brd->bsd", comb, stats)
            if n > em["burn_in"]:
                theta = m_step(glob, theta, sigma_floor=em["sigma_floor"])
            mk, ck = moments(state)
            means.append(mk)
            covs.append(ck)
            params.append(theta)
        mean = torch.stack(means, 1)[None]  # (1, B, K+1, A, 4)
        cov = torch.stack(covs, 1)[None]
        return _finished(mean, cov, params)

    def centre_prior(self, test: Measurements, network: SensorNetwork, dt: float, area, dtype, device):
        """The fusion centre's prior of every target ``(B, A, 4)``, ``(B, A, 4, 4)``: the diffuse prior
        (``prior_pos_std``, ``prior_vel_std``, zero velocity) with its mean's position at the first fix of the
        sensors' readings at ``t = 0`` (:func:`~dslearn.filters.distributed.first_fix`, the sensors fused), the
        linearisation point of the first update."""
        s, b, _, a = test.visible.shape
        m0, o0 = diffuse_prior(a, area, self.prior_pos_std, self.prior_vel_std, (s, b), dtype, device)
        fix, _ = first_fix(test, dt, Centralized(torch.eye(s, dtype=dtype, device=device)), self.observation, m0, o0)
        mean = prior_means(a, area).to(device, dtype).expand(b, a, AGENT_DIM).clone()
        mean[..., :2] = fix[0].unflatten(-1, (a, AGENT_DIM))[..., :2]
        if not torch.isfinite(mean).all():
            raise FloatingPointError("the first fix of the sensors' readings is not finite")
        cov = torch.diag(torch.tensor([self.prior_pos_std ** 2] * 2 + [self.prior_vel_std ** 2] * 2, dtype=dtype,
                                      device=device)).expand(b, a, AGENT_DIM, AGENT_DIM)
        return mean, cov
