"""Rao-Blackwellised particle filters with distributed online EM for jump-Markov nonlinear systems
(Braga, Özkan, Fritsche, Gustafsson, Bruno: cooperative terrain-based navigation using consensus).

Modules:
    jmnls: the jump-Markov system (Eq. 1), parameter validation, sufficient statistics, M-step (Eq. 8).
    filter: RBPF (Algorithm 1, Eq. 11-14) and the online E-step (Algorithm 2, Eq. 15-18).
    cooperation: non-cooperative / centralised (Eq. 19) / consensus (Algorithm 3, Eq. 20-22, 26), throughput.
    terrain: terrain map, bilinear lookup, constant-velocity model (Eq. 23-24), finger-four formation.
    tbn: the vectorised distributed online-EM loop for the TBN study.
    (random streams per Monte Carlo run and strategy: :mod:`dslearn.streams`, so results do not depend on batching.)
"""

from .cooperation import (average_consensus, check_eq22, combination_matrices, max_degree_paper,
                          throughput_bytes_per_step, weight_matrix)
from .filter import (LinearGaussianDynamics, RBPFState, init_state, local_stats, online_estep, posterior_mean,
                     rbpf_step)
from .jmnls import NoiseParams, m_step, make_params, params_dim, stats_dim, validate_params
from .terrain import TerrainMap, cv_model, make_terrain, simulate
from ..streams import Streams, stream_seed
from .tbn import run_tbn

__all__ = [
    "average_consensus", "check_eq22", "combination_matrices", "max_degree_paper", "throughput_bytes_per_step",
    "weight_matrix", "LinearGaussianDynamics", "RBPFState", "init_state", "local_stats", "online_estep",
    "posterior_mean", "rbpf_step", "NoiseParams", "m_step", "make_params", "params_dim", "stats_dim",
    "validate_params", "TerrainMap", "cv_model", "make_terrain", "simulate", "run_tbn", "Streams", "stream_seed",
]
