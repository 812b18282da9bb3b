"""Structured-config schemas of every task (see :mod:`dslearn.schemas.base`). Importing this
package registers them all in Hydra's ConfigStore."""

import importlib

from dslearn.schemas.base import TASKS, check_ranges, ranged, register_task, validate_task

#: the modules that register a task schema (one per study)
TASK_MODULES = ("yu", "yu_faults", "liu_dgpt", "jiang_fg", "braga_tbn", "ethucy_forecast", "ethucy_tracking")

for _m in TASK_MODULES:
    try:
        importlib.import_module(f"dslearn.schemas.{_m}")
    except ModuleNotFoundError as _e:  # noqa: PERF203  (a schema module not written yet)
        if _e.name != f"dslearn.schemas.{_m}":
            raise

__all__ = ["TASKS", "TASK_MODULES", "check_ranges", "ranged", "register_task", "validate_task"]
