"""The validation layer: structured-config schemas of the root keys and groups (:mod:`.core`) and of
every task (one module each, built with :mod:`.base`). Importing this package registers them all
in Hydra's ConfigStore; :func:`validate_config` checks a composed configuration before any work."""

import importlib

from dslearn.schemas.base import (ROOT_GROUPS, TASKS, check_overrides, check_ranges, ranged, register_task, task_uses,
                                  validate_task)
from dslearn.schemas.core import validate_config  # the root and Yu group schemas; the whole check

#: the modules that register a task schema (one per study)
TASK_MODULES = ("yu", "yu_faults", "liu_dgpt", "jiang_fg", "braga_tbn", "ethucy_forecast", "ethucy_tracking", "matrix",
                "gp_bayes_filters")

for _m in TASK_MODULES:
    try:
        importlib.import_module(f"dslearn.schemas.{_m}")
    except ModuleNotFoundError as _e:  # noqa: PERF203  (a schema module not written yet)
        if _e.name != f"dslearn.schemas.{_m}":
            raise

__all__ = ["ROOT_GROUPS", "TASKS", "TASK_MODULES", "check_overrides", "check_ranges", "ranged", "register_task",
           "task_uses", "validate_config", "validate_task"]
