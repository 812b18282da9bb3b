r"""Braga et al.'s method as a method of the matrix: every node (aircraft) runs a Rao-Blackwellised particle
filter of its own state with the online E-step (Algorithms 1-2), the nodes combine their sufficient
statistics (the method's fusion part, :class:`~dslearn.fusion.stats_consensus.StatisticsConsensus`:
non-cooperative, centralised or ``q`` rounds of consensus) and each runs the M-step on the result — all by
:func:`dslearn.learning.online_em.run_tbn`, on the altimeter readings alone.

What the navigators know besides the readings, as in the paper (Section VI): the terrain map
(``scenario.terrain``), the start (``scenario.initial_states()``, every particle starts there) and, with
``em.init_mode=true``, the altimeter's mode at ``t = 0`` (the scenario's ``t = 0`` entry of the second
measurement channel). The noise parameters are learned online within every episode (the stochastic
approximation starts afresh per flight, as in the study): the training episodes teach it nothing.

Estimates: node ``s``'s posterior mean of its own position (the particle mean), gathered as one report of
the four platforms (``nodes = ["onboard"]``: each platform estimated by its own filter; a node has no
estimate of the others), ``t = 0`` the known start. No covariance (``cov = None``: the study's engine keeps
the particle mean only). The filter's random numbers of test episode ``i`` come from the stream
``(seed, "filter", i)``, the key of the study's Monte Carlo run ``i`` (``filter_streams=common``).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import torch

from dslearn.episodes import Episodes, Estimates, Measurements, Scenario, ScenarioSpec
from dslearn.errors import ConfigError, check_choice
from dslearn.learning.online_em import KERNEL_DTYPES, run_tbn
from dslearn.methods.base import require
from dslearn.models.jmnls import make_params
from dslearn.network import SensorNetwork
from dslearn.sim.terrain import cv_model
from dslearn.streams import Streams

#: the kind of fusion part the method takes (consensus on sufficient statistics)
FUSION_KIND = "statistics"
EM_KEYS = {"eta_exponent": 0.7, "burn_in": 50, "sigma_floor": 1e-3, "init_mode": "true"}
MODE_KEYS = {"mu_init": [-5.0, 25.0], "sigma_init": [5.0, 5.0], "pi_init": [[0.5, 0.5], [0.5, 0.5]]}
KERNEL_KEYS = {"jitter_pos": 1.0, "jitter_vel": 0.0, "dtype": None}
#: the reporting entry: every platform's own filter
NODE = "onboard"


def _block(value, defaults: dict, prefix: str) -> dict:
    if value is None:
        return dict(defaults)
    if not isinstance(value, dict):
        raise ConfigError(f"{prefix}={value!r} must be a mapping with keys {list(defaults)}")
    unknown = sorted(str(k) for k in value if k not in defaults)
    if unknown:
        raise ConfigError(f"{prefix}: unknown key(s) {unknown}; allowed: {list(defaults)}")
    return {**defaults, **value}


def _num(key: str, v, low: float, strict: bool, high: float | None = None) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or v != v or v == float("inf"):
        raise ConfigError(f"filter.{key}={v!r} must be a finite number")
    if (v <= low if strict else v < low) or (high is not None and v > high):
        rule = f"{'>' if strict else '>='} {low:g}" + ("" if high is None else f" and <= {high:g}")
        raise ConfigError(f"filter.{key}={v!r} must be {rule}")
    return float(v)


@dataclasses.dataclass
class RBPFMethod:
    """RBPF + online EM + cooperation on the sufficient statistics (Braga et al.).

    Args:
        fusion: the cooperation (the ``consensus`` part, ``kind = "statistics"``).
        num_particles: ``N_P``.
        process_noise: the filters' ``Q_XX = Q_YY`` [(m/s^2)^2] (Eq. 24).
        ess_threshold: resample when ESS < ``ess_threshold * N_P``.
        regularise: post-regularised resampling factor (0: the paper's plain systematic resampling).
        em: ``eta_exponent`` (``eta_t = t^-a``, in (0.5, 1]), ``burn_in`` (steps before the first M-step),
            ``sigma_floor``, ``init_mode`` (``true``: start from the known mode at ``t = 0``; ``uniform``).
        modes: the initial guess of the noise parameters ``mu_init``, ``sigma_init``, ``pi_init``.
        backward_kernel: ``jitter_pos``, ``jitter_vel`` (variances added to ``G Q G^T`` in Eq. 17),
            ``dtype`` (null: the state's; float32 for the ``N x N`` products).
        fusion_name: the fusion part's label (its ``conf/consensus`` option).
    """

    fusion_kind = FUSION_KIND

    fusion: Any
    num_particles: int = 300
    process_noise: float = 100.0
    ess_threshold: float = 0.5
    regularise: float = 0.0
    em: Any = None
    modes: Any = None
    backward_kernel: Any = None
    fusion_name: str | None = None

    def __post_init__(self) -> None:
        if getattr(self.fusion, "kind", None) != self.fusion_kind:
            name = self.fusion_name or type(self.fusion).__name__
            raise ConfigError(f"consensus={name} is not a cooperation on sufficient statistics: Braga et al.'s "
                              f"RBPF + online EM (filter=rbpf_em) combines its nodes' EM statistics, "
                              f"consensus=statistics")
        n = self.num_particles
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ConfigError(f"filter.num_particles={n!r} must be an integer >= 1")
        self.process_noise = _num("process_noise", self.process_noise, 0.0, True)
        self.ess_threshold = _num("ess_threshold", self.ess_threshold, 0.0, False, 1.0)
        self.regularise = _num("regularise", self.regularise, 0.0, False)
        em = _block(self.em, EM_KEYS, "filter.em")
        if em["init_mode"] is True:  # `init_mode=true` on the command line is a bool
            em["init_mode"] = "true"
        check_choice("filter.em.init_mode", em["init_mode"], ("true", "uniform"))
        em["eta_exponent"] = _num("em.eta_exponent", em["eta_exponent"], 0.5, True, 1.0)
        b = em["burn_in"]
        if isinstance(b, bool) or not isinstance(b, int) or b < 0:
            raise ConfigError(f"filter.em.burn_in={b!r} must be an integer >= 0")
        em["sigma_floor"] = _num("em.sigma_floor", em["sigma_floor"], 0.0, True)
        self.em = em
        modes = _block(self.modes, MODE_KEYS, "filter.modes")
        self.init = make_params(modes["mu_init"], modes["sigma_init"], modes["pi_init"], prefix="filter.modes")
        self.modes = modes
        bk = _block(self.backward_kernel, KERNEL_KEYS, "filter.backward_kernel")
        _num("backward_kernel.jitter_pos", bk["jitter_pos"], 0.0, True)
        _num("backward_kernel.jitter_vel", bk["jitter_vel"], 0.0, False)
        check_choice("filter.backward_kernel.dtype", bk["dtype"], tuple(KERNEL_DTYPES))
        self.backward_kernel = bk

    @property
    def label(self) -> str:
        return f"rbpf_em {self.fusion.name}"

    def fits(self, spec: ScenarioSpec) -> str | None:
        return require(spec, "Braga et al.'s RBPF + online EM (platforms that measure the terrain altitude under "
                             "them, over a communication graph)", measurement="terrain_altitude", networked=True)

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
        return Estimates(mean, None, [NODE], torch.ones(1, dtype=torch.bool))
