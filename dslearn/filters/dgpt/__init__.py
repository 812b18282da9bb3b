"""Liu et al.'s distributed GP tracker (DGPT) with what it learns on its own: the tracking loop and the
centralised standard-GP benchmark (:mod:`.tracker`), the online hyperparameter learning it runs
(:mod:`.hyperopt`) and the GPyTorch reference of its local experts (:mod:`.experts`)."""

from dslearn.filters.dgpt.tracker import (GP_INPUTS, OPTIMISERS, HyperConfig, TrackResult, hyper_summary,
                                          keyed_uniform, per_method, track)

__all__ = ["GP_INPUTS", "OPTIMISERS", "HyperConfig", "TrackResult", "hyper_summary", "keyed_uniform", "per_method",
           "track"]
