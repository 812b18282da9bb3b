"""Distributed GP tracking (DGPT), Liu et al., FUSION 2022.

Modules:
    aggregation: PoE / gPoE / BCM / rBCM (Eqs. 7-13), grBCM (Liu et al. 2018) and the Theorem 1 bound (Eq. 24).
    experts: GPyTorch reference experts over padded sliding windows, factorised MLL (Eq. 15), predictions.
    hyperopt: per-problem factorised MLL with exact gradient/Hessian, elementwise Adam, trust-region Newton.
    scenarios: trajectories S1-S3, sensor field, measurements.
    tracker: the online DGPT loop and the centralised standard-GP benchmark.
"""

from .aggregation import AGGREGATIONS, aggregate, aggregate_grbcm, entropy_weights, ucb_bound, ucb_bound_grbcm
from .experts import Hypers, expert_log_marginal_likelihood, factorised_log_marginal_likelihood
from .scenarios import SCENARIOS
from .tracker import GP_INPUTS, OPTIMISERS, HyperConfig, track

__all__ = [
    "AGGREGATIONS", "GP_INPUTS", "OPTIMISERS", "SCENARIOS", "HyperConfig", "Hypers", "aggregate",
    "aggregate_grbcm", "entropy_weights", "expert_log_marginal_likelihood",
    "factorised_log_marginal_likelihood", "track", "ucb_bound", "ucb_bound_grbcm",
]
