r"""Schema of task ``gp_bayes_filters`` (Deisenroth, Huber, Hanebeck, ICML 2009: GP-ADF and the GP-Bayes
filters on the scalar benchmark).

The schema is the study's settings, :class:`dslearn.studies.gp_bayes_filters.GPBayesTask`. Keys and types
are checked by Hydra at composition (``conf/task/gp_bayes_filters.yaml`` is linked to it), ranges and
choices by the field rules; :func:`check` holds the rules that need several fields: each range
``[low, high]`` with ``low < high``, no filter listed twice, a positive unscented scaling
``alpha^2 (1 + kappa)`` (scalar state), and the network settings' rules
(:func:`~dslearn.studies.gp_bayes_filters.check_network`: a valid ``omega``; with ``nodes: 1`` no network
setting changed).
"""

from __future__ import annotations

import math

from omegaconf import DictConfig

from dslearn.errors import ConfigError
from dslearn.schemas.base import register_task
from dslearn.studies.gp_bayes_filters import GPBayesTask, check_network


def check(cfg: DictConfig) -> None:
    """The cross-field rules of ``cfg.task`` (after the field rules); raises :class:`ConfigError`."""
    t = cfg.task
    for key in ("train_range", "prior_mean_range"):
        lo, hi = (float(v) for v in t[key])
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ConfigError(f"task.{key}={[lo, hi]} must be [low, high] with finite low < high")
    names = [str(f) for f in t.filters]
    dup = sorted({f for f in names if names.count(f) > 1})
    if dup:
        raise ConfigError(f"task.filters={names} lists {dup} more than once")
    if float(t.ukf.alpha) ** 2 * (1.0 + float(t.ukf.kappa)) <= 0.0:
        raise ConfigError(f"task.ukf.kappa={t.ukf.kappa} must be > -1 (alpha^2 (1 + kappa) > 0 for the scalar state)")
    check_network(t)


#: what the study uses in place of each root group (it reads none of them: every part is in ``task``)
INSTEAD = {
    "scenario": "its model is the scalar benchmark with task.prior_std, task.process_std, task.measurement_std",
    "network": "its network is task.nodes sensors on task.graph",
    "model": "its transition model is the benchmark's or a GP trained on task.train_points",
    "observation": "its measurement model is the benchmark's or a GP trained on task.train_points",
    "consensus": "its fusion is task.consensus, with task.rounds, task.weights and task.omega",
    "filter": "its filters are task.filters",
    "data": "its cases are task.num_cases prior means",
    "learner": "its GPs are trained by task.gp (GPyTorch, exact marginal likelihood)",
}

register_task("gp_bayes_filters", GPBayesTask, check, uses=(), instead=INSTEAD)
