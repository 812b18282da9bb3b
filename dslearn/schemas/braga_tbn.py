r"""Schema of task ``braga_tbn`` (Braga et al.: distributed online EM, RBPFs, consensus on statistics).

Keys and types are checked by Hydra at composition (``conf/task/braga_tbn.yaml`` is linked to
:class:`BragaTask`), ranges and choices by the field rules, and :func:`check` holds the rules that
need several fields or built objects: the noise parameters (K modes, pi rows sum to 1, the true and
initial K agree), a connected finger-four graph, the consensus weights (Eq. 22), the strategy
names, the terrain resolution and the steady-state window against the flight duration.

``task.consensus.weights``: ``half_max_degree`` (the paper's Eq. 26, 1/(2 d_max)), ``max_degree_core``
(1/(1 + d_max), :func:`dslearn.fusion.weights.max_degree`), ``metropolis`` or ``matrix``. The former
value ``max_degree`` (which meant 1/(2 d_max) here but 1/(1 + d_max) in :mod:`dslearn.fusion.weights`)
is refused with a message naming both replacements.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, List, Optional

from omegaconf import DictConfig, OmegaConf

from dslearn.errors import ConfigError
from dslearn.fusion.statistics import network_adjacency, parse_strategy, weight_matrix
from dslearn.models.jmnls import make_params
from dslearn.schemas.base import ranged, register_task


@dataclass
class Modes:
    mu_true: List[float] = ranged(factory=lambda: [0.0, 20.0], min_len=1)
    sigma_true: List[float] = ranged(factory=lambda: [1.0, 4.0], gt=0.0, each=True, min_len=1)
    pi_true: List[Any] = ranged(factory=lambda: [[0.85, 0.15], [0.4, 0.6]], min_len=1)
    mu_init: List[float] = ranged(factory=lambda: [-5.0, 25.0], min_len=1)
    sigma_init: List[float] = ranged(factory=lambda: [5.0, 5.0], gt=0.0, each=True, min_len=1)
    pi_init: List[Any] = ranged(factory=lambda: [[0.5, 0.5], [0.5, 0.5]], min_len=1)


@dataclass
class EM:
    eta_exponent: float = ranged(0.7, gt=0.5, le=1.0)  # stochastic-approximation conditions
    burn_in: int = ranged(50, ge=0)
    sigma_floor: float = ranged(1e-3, gt=0.0)
    init_mode: Any = ranged("true", choices=("true", "uniform", True))  # `init_mode=true` on the CLI is a bool


@dataclass
class Resampling:
    regularise: float = ranged(0.0, ge=0.0)


@dataclass
class BackwardKernel:
    jitter_pos: float = ranged(1.0, gt=0.0)
    jitter_vel: float = ranged(0.0, ge=0.0)
    dtype: Optional[str] = ranged(None, choices=("float32", "float64"))


@dataclass
class Terrain:
    size_m: float = ranged(25000.0, gt=0.0)
    resolution_m: float = ranged(25.0, gt=0.0)
    smoothing_m: float = ranged(250.0, gt=0.0)
    elevation_std_m: float = ranged(100.0, gt=0.0)
    mean_elevation_m: float = 500.0
    seed_offset: int = 0


@dataclass
class Network:
    edges: List[Any] = ranged(factory=lambda: [[0, 1], [0, 2], [2, 3]], min_len=1)
    fusion_centre: int = ranged(0, ge=0, le=3)


@dataclass
class Consensus:
    weights: str = "half_max_degree"  # checked (with the retired value's message) in check()
    matrix: Optional[List[Any]] = None


@dataclass
class BragaTask:
    entry: str = "dslearn.studies.braga_tbn:run"
    name: str = "braga_tbn"
    mc_runs: int = ranged(2, ge=1)
    mc_batch: int = ranged(2, ge=1)
    workers: int = ranged(2, ge=1)
    num_particles: int = ranged(300, ge=1)
    steps: int = ranged(1800, ge=1)
    dt: float = ranged(0.05, gt=0.0)
    process_noise: float = ranged(100.0, gt=0.0)
    truth_process_noise: float = ranged(0.0, ge=0.0)
    v0: List[float] = ranged(factory=lambda: [170.0, 170.0], min_len=2, max_len=2)
    start: List[float] = ranged(factory=lambda: [3000.0, 3000.0], min_len=2, max_len=2)
    formation_spacing: float = ranged(100.0, gt=0.0)
    modes: Modes = field(default_factory=Modes)
    em: EM = field(default_factory=EM)
    ess_threshold: float = ranged(0.5, ge=0.0, le=1.0)
    resampling: Resampling = field(default_factory=Resampling)
    filter_streams: str = ranged("common", choices=("common", "independent"))
    lost_track_m: float = ranged(15.0, gt=0.0)
    backward_kernel: BackwardKernel = field(default_factory=BackwardKernel)
    terrain: Terrain = field(default_factory=Terrain)
    network: Network = field(default_factory=Network)
    consensus: Consensus = field(default_factory=Consensus)
    strategies: List[str] = ranged(factory=lambda: ["noncooperative", "centralised", "consensus_1", "consensus_5",
                                                    "consensus_10"], min_len=1)
    bytes_per_float: int = ranged(4, gt=0)
    kilobyte: int = ranged(1024, choices=(1000, 1024))
    record_every: int = ranged(10, gt=0)
    zoom_s: float = ranged(5.0, ge=0.0)
    steady_state_s: float = ranged(45.0, gt=0.0)


def check(cfg: DictConfig) -> None:
    """The cross-field rules of ``cfg.task`` (after the field rules); raises :class:`ConfigError`."""
    t = OmegaConf.to_container(cfg.task, resolve=True)
    m = t["modes"]
    truth = make_params(m["mu_true"], m["sigma_true"], m["pi_true"],
                        prefix="task.modes (true: mu_true/sigma_true/pi_true)")
    init = make_params(m["mu_init"], m["sigma_init"], m["pi_init"],
                       prefix="task.modes (initial: mu_init/sigma_init/pi_init)")
    if truth.k != init.k:
        raise ConfigError(f"task.modes: K mismatch between the true parameters (K={truth.k}) and the initial "
                          f"guess (K={init.k})")
    tr = t["terrain"]
    if tr["resolution_m"] * 4 > tr["size_m"]:
        raise ConfigError(f"task.terrain.resolution_m={tr['resolution_m']} must be much smaller than "
                          f"task.terrain.size_m={tr['size_m']} (at most a quarter)")
    adj = network_adjacency(4, t["network"]["edges"])  # finger four: 4 aircraft
    weight_matrix(adj, t["consensus"]["weights"], t["consensus"]["matrix"])
    for sname in t["strategies"]:
        parse_strategy(sname)
    if len(set(t["strategies"])) != len(t["strategies"]):
        raise ConfigError(f"task.strategies={t['strategies']} has duplicates")
    if t["steady_state_s"] > t["steps"] * t["dt"]:
        raise ConfigError(f"task.steady_state_s={t['steady_state_s']} exceeds the flight duration "
                          f"task.steps * task.dt = {t['steps'] * t['dt']} s")


#: what the study uses in place of each root group (it reads none of them: every part is in ``task``)
INSTEAD = {
    "scenario": "its flights are task.steps, task.dt, task.start and task.formation_spacing over task.terrain",
    "network": "its network is task.network",
    "model": "its motion model is task.process_noise with the terrain modes task.modes",
    "observation": "its measurement model is the terrain map task.terrain with task.modes",
    "consensus": "its fusion is task.consensus with task.strategies",
    "filter": "its filter is the RBPF of task.num_particles, task.resampling and task.em",
    "data": "its Monte Carlo runs are task.mc_runs",
}

register_task("braga_tbn", BragaTask, check, uses=(), instead=INSTEAD)
