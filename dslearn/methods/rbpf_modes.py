r"""Braga et al.'s RBPF + online EM + consensus on the EM statistics, taken to position sensors: every node runs,
for every target, a Rao-Blackwellised particle filter over its sensor's jump-Markov noise modes (a mixture Kalman
filter, :mod:`dslearn.filters.mkf`) with a constant-velocity (LIN) state, the online E-step on the particles'
paths, the nodes combine their sufficient statistics (the method's fusion part,
:class:`~dslearn.fusion.stats_consensus.StatisticsConsensus`) and each runs the M-step
(:func:`dslearn.models.jmnls.m_step`, the one of Braga's engine) on the result.

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
from dslearn.errors import ConfigError
from dslearn.filters.distributed import prior_means
from dslearn.filters.mkf import LinearGaussianState, init_state, local_stats, mkf_step, moments
from dslearn.learning.learners import OnlineEMSensor, refuse
from dslearn.methods.base import require
from dslearn.methods.rbpf import FUSION_KIND, _num
from dslearn.models.jmnls import NoiseParams, m_step, stats_dim
from dslearn.network import SensorNetwork
from dslearn.sim.terrain import cv_model
from dslearn.streams import Streams

#: the state layout it tracks per target (``[px, py, vx, vy]``)
AGENT_DIM = 4


@dataclasses.dataclass
class RBPFModesMethod:
    """RBPF over the noise modes (mixture Kalman filter, LIN state) + online EM + consensus on the statistics.

    Args:
        fusion: the cooperation on the statistics (the ``consensus`` part, ``kind = "statistics"``).
        num_particles: particles (mode sequences) per node and target.
        process_noise: ``q`` of the constant-velocity model [(m/s^2)^2].
        ess_threshold: resample when ESS < ``ess_threshold * N``.
        prior_pos_std, prior_vel_std: the diffuse prior of a target not yet seen [m], [m/s].
        fusion_name: the fusion part's label.
        learner: the online EM for position sensors (:class:`~dslearn.learning.learners.OnlineEMSensor`); ``None``:
            its defaults (``conf/learner/online_em_sensor.yaml``).
    """

    fusion_kind = FUSION_KIND
    learners = ("online_em_sensor",)

    fusion: Any
    num_particles: int = 64
    process_noise: float = 1.0
    ess_threshold: float = 0.5
    prior_pos_std: float = 1000.0
    prior_vel_std: float = 1000.0
    fusion_name: str | None = None
    learner: Any = None

    def __post_init__(self) -> None:
        if getattr(self.fusion, "kind", None) != self.fusion_kind:
            name = self.fusion_name or type(self.fusion).__name__
            raise ConfigError(f"consensus={name} is not a cooperation on sufficient statistics: the RBPF over noise "
                              f"modes + online EM (filter=rbpf_em_lin) combines its nodes' EM statistics, "
                              f"consensus=statistics")
        n = self.num_particles
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ConfigError(f"filter.num_particles={n!r} must be an integer >= 1")
        self.process_noise = _num("process_noise", self.process_noise, 0.0, True)
        self.ess_threshold = _num("ess_threshold", self.ess_threshold, 0.0, False, 1.0)
        self.prior_pos_std = _num("prior_pos_std", self.prior_pos_std, 0.0, True)
        self.prior_vel_std = _num("prior_vel_std", self.prior_vel_std, 0.0, True)
        if self.learner is None:
            self.learner = OnlineEMSensor()
        elif not isinstance(self.learner, OnlineEMSensor):
            raise refuse(self.learner, "the RBPF over noise modes (filter=rbpf_em_lin) learns the position sensors' "
                                       "zero-mean noise modes, in units of their noise std, with the online EM",
                         self.learners)

    @property
    def label(self) -> str:
        return f"rbpf_em_lin {self.fusion.name}"

    @staticmethod
    def spec_misfit(spec: ScenarioSpec) -> str | None:
        """What the engine needs of a scenario, declared (:func:`dslearn.methods.base.declared_misfit`): a linear
        observation of a ``[px, py, vx, vy]`` state, which makes the model linear-Gaussian given the modes (the
        Kalman filter per particle is exact only then)."""
        return require(spec, "the RBPF over noise modes (a Kalman filter per mode sequence: sensors that measure "
                             "the targets' positions, a linear observation of a [px, py, vx, vy] state)",
                       measurement="position", state="pv2d")

    def fits(self, spec: ScenarioSpec) -> str | None:
        return RBPFModesMethod.spec_misfit(spec)

    def initial_modes(self, sensor_std: float, dtype, device) -> NoiseParams:
        """The EM's initial noise modes in metres (the learner's, in units of ``sensor_std``)."""
        init = self.learner.init
        return NoiseParams(init.mu.to(device, dtype) * sensor_std, init.sigma.to(device, dtype) * sensor_std,
                           init.pi.to(device, dtype))

    def estimate(self, scenario: Scenario, network: SensorNetwork, train: Episodes, test: Measurements,
                 seed: int) -> Estimates:
        """Every node's filters on every test episode (``train`` is not used: the EM is online)."""
        mean, cov, _ = self.track(test, network, scenario.spec.dt, scenario.area, seed)
        return Estimates(mean[..., :2], cov[..., :2, :2], list(network.names), network.is_sensor.clone())

    def track(self, test: Measurements, network: SensorNetwork, dt: float, area, seed: int):
        """The filters of every node and target on ``test``: mixture means ``(S, B, K+1, A, 4)``, covariances
        ``(S, B, K+1, A, 4, 4)`` and the noise parameters after each step (a :class:`NoiseParams` of
        ``(K+1, B, S, ...)`` tensors)."""
        meas, vis = test.meas, test.visible
        s, b, t1, a = vis.shape
        dtype, device = torch.float64, meas.device
        y = meas.to(dtype).permute(1, 2, 0, 3, 4)  # (B, K+1, S, A, 2)
        v = vis.permute(1, 2, 0, 3)  # (B, K+1, S, A)
        dyn = cv_model(dt, self.process_noise, dtype=dtype, device=device)
        h = torch.zeros(2, AGENT_DIM, dtype=dtype, device=device)
        h[0, 0] = h[1, 1] = 1.0
        model = LinearGaussianState(dyn.F, dyn.G @ dyn.Q @ dyn.G.T, h)
        theta = self.initial_modes(float(network.meas_std), dtype, device)
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
        if not (torch.isfinite(mean).all() and torch.isfinite(cov).all()):
            raise FloatingPointError("non-finite estimate in the RBPF over noise modes (this is a bug)")
        hist = NoiseParams(torch.stack([p.mu for p in params]), torch.stack([p.sigma for p in params]),
                           torch.stack([p.pi for p in params]))
        return mean, cov, hist

