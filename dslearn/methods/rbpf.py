r"""Braga et al.'s method as a method of the matrix: every node (aircraft) runs a Rao-Blackwellised particle
filter of its own state with the online E-step (Algorithms 1-2), the nodes combine their sufficient
statistics (the method's fusion part, :class:`~dslearn.fusion.stats_consensus.StatisticsConsensus`:
non-cooperative, centralised or ``q`` rounds of consensus) and each runs the M-step on the result — all by
:func:`dslearn.learning.online_em.run_tbn`, on the altimeter readings alone.

What the navigators know besides the readings, as in the paper (Section VI): the terrain map
(``scenario.terrain``), the start (``scenario.initial_states()``, every particle starts there) and, with
``em.init_mode=true``, the altimeter's mode at ``t = 0`` (the scenario's ``t = 0`` entry of the second
measurement channel). The noise parameters are learned online within every episode by the method's learner
(:class:`~dslearn.learning.learners.OnlineEM`, ``learner=online_em``; the stochastic approximation starts afresh
per flight, as in the study): the training episodes teach it nothing.

Estimates: node ``s``'s posterior mean of its own position (the particle mean), gathered as one report of
the four platforms (``nodes = ["onboard"]``: each platform estimated by its own filter; a node has no
estimate of the others), ``t = 0`` the known start; covariance: the weighted covariance of the particles'
positions (zero at ``t = 0``), so the matrix reports the RBPF's position NEES too. The filter's random numbers of test episode ``i`` come from the stream
``(seed, "filter", i)``, the key of the study's Monte Carlo run ``i`` (``filter_streams=common``).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import torch

from dslearn.episodes import Episodes, Estimates, Measurements, Scenario, ScenarioSpec
from dslearn.errors import ConfigError, check_choice, check_integer, check_number
from dslearn.learning.learners import OnlineEM, _block, refuse
from dslearn.learning.online_em import KERNEL_DTYPES, run_tbn
from dslearn.methods.base import require
from dslearn.network import SensorNetwork
from dslearn.sim.terrain import cv_model
from dslearn.streams import Streams

#: the kind of fusion part the method takes (consensus on sufficient statistics)
FUSION_KIND = "statistics"
KERNEL_KEYS = {"jitter_pos": 1.0, "jitter_vel": 0.0, "dtype": None}
#: the reporting entry: every platform's own filter
NODE = "onboard"


def check_particle_settings(method) -> None:
    """Check (and make floats of) the particle filter's settings shared by :class:`RBPFMethod` and
    :class:`~dslearn.methods.rbpf_modes.RBPFModesMethod`: ``filter.num_particles``, ``filter.process_noise`` and
    ``filter.ess_threshold``."""
    check_integer("filter.num_particles", method.num_particles, 1)
    method.process_noise = check_number("filter.process_noise", method.process_noise, 0.0, strict=True)
    method.ess_threshold = check_number("filter.ess_threshold", method.ess_threshold, 0.0, high=1.0)


@dataclasses.dataclass
class RBPFMethod:
    """RBPF + online EM + cooperation on the sufficient statistics (Braga et al.).

    Args:
        fusion: the cooperation (the ``consensus`` part, ``kind = "statistics"``).
        num_particles: ``N_P``.
        process_noise: the filters' ``Q_XX = Q_YY`` [(m/s^2)^2] (Eq. 24).
        ess_threshold: resample when ESS < ``ess_threshold * N_P``.
        regularise: post-regularised resampling factor (0: the paper's plain systematic resampling).
        backward_kernel: ``jitter_pos``, ``jitter_vel`` (variances added to ``G Q G^T`` in Eq. 17),
            ``dtype`` (null: the state's; float32 for the ``N x N`` products).
        fusion_name: the fusion part's label (its ``conf/consensus`` option).
        learner: the online EM (:class:`~dslearn.learning.learners.OnlineEM`: its ``em`` settings and initial
            ``modes``); ``None``: its defaults (``conf/learner/online_em.yaml``). No other learner.
    """

    fusion_kind = FUSION_KIND
    #: the learners it can use (the first: its own, taken when none is given)
    learners = ("online_em",)

    fusion: Any
    num_particles: int = 300
    process_noise: float = 100.0
    ess_threshold: float = 0.5
    regularise: float = 0.0
    backward_kernel: Any = None
    fusion_name: str | None = None
    learner: Any = None

    def __post_init__(self) -> None:
        if getattr(self.fusion, "kind", None) != self.fusion_kind:
            name = self.fusion_name or type(self.fusion).__name__
            raise ConfigError(f"consensus={name} is not a cooperation on sufficient statistics: Braga et al.'s "
                              f"RBPF + online EM (filter=rbpf_em) combines its nodes' EM statistics, "
                              f"consensus=statistics")
        check_particle_settings(self)
        self.regularise = check_number("filter.regularise", self.regularise, 0.0)
        bk = _block(self.backward_kernel, KERNEL_KEYS, "filter.backward_kernel")
        check_number("filter.backward_kernel.jitter_pos", bk["jitter_pos"], 0.0, strict=True)
        check_number("filter.backward_kernel.jitter_vel", bk["jitter_vel"], 0.0)
        check_choice("filter.backward_kernel.dtype", bk["dtype"], tuple(KERNEL_DTYPES))
        self.backward_kernel = bk
        if self.learner is None:
            self.learner = OnlineEM()
        elif not isinstance(self.learner, OnlineEM):
            raise refuse(self.learner, "Braga et al.'s RBPF (filter=rbpf_em) learns the altimeter noise with its "
                                       "online EM", self.learners)
        if self.learner.units != OnlineEM.units:
            raise refuse(self.learner, "Braga et al.'s altimeter noise modes are given in metres (the terrain "
                                       "scenario declares no sensor noise std to scale them by)", self.learners)

    @property
    def em(self) -> dict:
        """The online EM's settings (the learner's ``em``)."""
        return self.learner.em

    @property
    def init(self):
        """The EM's initial noise parameters (the learner's ``modes``)."""
        return self.learner.init

    @property
    def label(self) -> str:
        return f"rbpf_em {self.fusion.name}"

    @staticmethod
    def spec_misfit(spec: ScenarioSpec) -> str | None:
        """What the engine needs of a scenario, declared (:func:`dslearn.methods.base.declared_misfit`)."""
        return require(spec, "Braga et al.'s RBPF + online EM (platforms that measure the terrain altitude under "
                           "them, over a communication graph)", measurement="terrain_altitude", networked=True)

    def fits(self, spec: ScenarioSpec) -> str | None:
        return RBPFMethod.spec_misfit(spec)

    def estimate(self, scenario: Scenario, network: SensorNetwork, train: Episodes, test: Measurements,
                 seed: int) -> Estimates:
        """Every platform's own filter on every test flight (``train`` is not used: the EM is online)."""
        meas, vis = test.meas, test.visible
        s, b, t1, a = vis.shape
        if s != a or s != network.num_nodes:
            raise ConfigError(f"scenario {scenario.spec.name}: RBPF + online EM needs one node per platform; "
                              f"the measurements hold {s} nodes and {a} platforms")
        idx = torch.arange(s, device=meas.device)
        y = meas[idx, :, :, idx, 0].transpose(0, 1)  # (B, S, K+1)
        r0 = meas[idx, :, 0, idx, 1].transpose(0, 1).round().long()  # (B, S)
        dtype, device = meas.dtype, meas.device
        terrain = scenario.terrain
        terrain = type(terrain)(terrain.z.to(device, dtype), terrain.resolution)
        x0 = scenario.initial_states().to(device, dtype).expand(b, s, -1)
        bk = self.backward_kernel
        dyn = cv_model(scenario.spec.dt, self.process_noise, (bk["jitter_pos"], bk["jitter_vel"]), dtype=dtype,
                       device=device, kernel_dtype=KERNEL_DTYPES[bk["dtype"]])
        gen = Streams.from_keys([(int(seed), "filter", i) for i in range(b)], (b, 1), device=device)
        em = self.em
        res = run_tbn(y, terrain, x0, [self.fusion.strategy], self.fusion.weights, self.init, dyn,
                      num_particles=self.num_particles, gen=gen, r0=r0, eta_exponent=em["eta_exponent"],
                      burn_in=em["burn_in"], ess_threshold=self.ess_threshold, sigma_floor=em["sigma_floor"],
                      init_mode=em["init_mode"], regularise=self.regularise)
        est = res.est[:, :, 0, :, :2].permute(1, 0, 2, 3)  # (B, K, S, 2)
        mean = torch.cat([x0[:, None, :, :2], est], 1)[None]  # (1, B, K+1, S, 2)
        cov = res.pos_cov[:, :, 0].permute(1, 0, 2, 3, 4)  # (B, K, S, 2, 2): the particles' spread
        cov = torch.cat([torch.zeros_like(cov[:, :1]), cov], 1)[None]  # t = 0: the known start
        return Estimates(mean, cov, [NODE], torch.ones(1, dtype=torch.bool))
