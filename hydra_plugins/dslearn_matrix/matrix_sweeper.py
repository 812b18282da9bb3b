"""The matrix sweeper (``hydra/sweeper=matrix``): Hydra's basic sweeper (every combination of the sweep's
values, ``hydra.sweeper.params`` and the command line's ``a=x,y``) less the combinations whose method does not
fit the scenario, decided on each combination's composed configuration before any job starts.

The decision is the ``select`` function's (named by its import path; default
:func:`dslearn.schemas.matrix.select_cells`: each cell's method and scenario built on PyTorch's meta device,
and the method's ``fits`` on the scenario's declared spec). It returns the combinations that run and one
record per combination (``method``, ``scenario``, ``units``, ``status``, ``reason``, ``error``, ``job``,
``overrides``). The sweeper writes every record into the sweep folder, ``matrix_cells.csv`` (with the job number
of each combination that runs and its ``status``: ``run``, ``does_not_fit``, ``left_out`` or ``failed``), and
the dropped ones with a reason (n/a, left out) into ``skipped_cells.csv``; ``dslearn-report`` shows them as
"n/a" cells. A combination whose parts raised while they were built (``failed``, with its ``error``) is not run
either: the sweeper says so on stderr and in its log, ``dslearn-run`` exits 1 after the sweep, and
``dslearn-report`` shows it as failed. The launcher (basic, joblib, ...) gets only the jobs that fit, numbered
0, 1, ... in the sweep's order, so every launcher runs the same jobs and a resumed sweep (``resume=true``) numbers
them alike. ``dslearn-run``'s up-front check applies the same function (the sweeper's ``select`` key).
"""


import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Optional, Sequence

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.config_store import ConfigStore

log = logging.getLogger(__name__)

#: the function that decides which combinations run (the sweeper's default)
SELECT = "dslearn.schemas.matrix.select_cells"


@dataclass
class MatrixSweeperConf:
    _target_: str = "hydra_plugins.dslearn_matrix.matrix_sweeper.MatrixSweeper"
    max_batch_size: Optional[int] = None
    params: Optional[Dict[str, str]] = None
    #: import path of ``select(combos, compose) -> (combinations that run, one record per combination)``
    select: str = SELECT


ConfigStore.instance().store(group="hydra/sweeper", name="matrix", node=MatrixSweeperConf, provider="dslearn")


def write_records(sweep_dir: Path, records: list[dict]) -> None:
    """``matrix_cells.csv`` (every combination) and ``skipped_cells.csv`` (the dropped ones) in ``sweep_dir``."""
    import pandas as pd

    from dslearn.io import atomic_write_csv
    from dslearn.studies.matrix import CELL_COLUMNS, CELLS_FILE, SKIPPED_FILE

    sweep_dir.mkdir(parents=True, exist_ok=True)
    table = pd.DataFrame(records, columns=None if records else list(CELL_COLUMNS))
    for c in CELL_COLUMNS:
        if c not in table.columns:
            table[c] = None
    table = table[list(CELL_COLUMNS) + [c for c in table.columns if c not in CELL_COLUMNS]]
    table["job"] = table["job"].astype("Int64")
    atomic_write_csv(table, sweep_dir / CELLS_FILE)
    atomic_write_csv(table[table["reason"].notna()].drop(columns="job"), sweep_dir / SKIPPED_FILE)


def say_failed(failed: list[dict], where: Path) -> None:
    """Say loudly (stderr and the sweep's log) which combinations failed in the up-front check and will not run,
    each with its error; ``where``: the file that records them."""
    import sys

    lines = [f"matrix sweeper: {len(failed)} combination(s) FAILED while their parts were built and will not run "
             f"(an error in a part, not an n/a cell; recorded in {where}):"]
    lines += [f"  FAILED {r.get('method')} on scenario {r.get('scenario')} ({r.get('overrides')}): {r.get('error')}"
              for r in failed]
    log.error("\n".join(lines))
    print("\n".join(lines), file=sys.stderr, flush=True)


class MatrixSweeper(BasicSweeper):
    """Hydra's basic sweeper over the combinations that fit (see the module's text)."""

    def __init__(self, max_batch_size: Optional[int] = None, params: Optional[Dict[str, str]] = None,
                 select: str = SELECT) -> None:
        super().__init__(max_batch_size=max_batch_size, params=params)
        self.select = select
        self._composed: set[tuple[str, ...]] = set()

    def split_arguments(self, overrides, max_batch_size):  # noqa: D102  (BasicSweeper.sweep calls it on self)
        from hydra.utils import get_object

        from dslearn.studies.matrix import SKIPPED_FILE

        assert self.hydra_context is not None and self.config is not None
        combos = BasicSweeper.split_arguments(overrides, None)[0]
        from dslearn.search_path import add_search_path
        from dslearn.studies.matrix import CELLS_FILE

        add_search_path(self.config.hydra.get("searchpath") or [])  # the user's folders: their options count too
        loader = self.hydra_context.config_loader
        select = get_object(self.select)
        from dslearn.schemas.matrix import take_judgement

        judged = take_judgement(select, combos)  # dslearn-run's up-front check judged these combinations already
        if judged is None:
            judged = select(combos, lambda ov: loader.load_sweep_config(self.config, ov))
        else:
            log.debug("matrix sweeper: the cells as the up-front check judged them (no composition again)")
        kept, records = judged
        self._composed = {tuple(c) for c in kept}
        sweep_dir = Path(str(self.config.hydra.sweep.dir))
        write_records(sweep_dir, records)
        failed = [r for r in records if r.get("status") == "failed"]
        log.info("matrix sweeper: %d of %d combinations fit and run; %d dropped, with the reasons in %s", len(kept),
                 len(combos), len(combos) - len(kept) - len(failed), sweep_dir / SKIPPED_FILE)
        if failed:
            from dslearn.schemas import matrix

            say_failed(failed, sweep_dir / CELLS_FILE)
            matrix.FAILED_CELLS.extend(failed)  # dslearn-run exits 1 after the sweep's other jobs
        from dslearn.studies.matrix import plan_text  # the cells, seeds and the estimated time, before any job

        jobs = self.config.hydra.launcher.get("n_jobs", 1)
        log.info(plan_text(records, self.config.task, (os.cpu_count() or 1) if jobs in (None, -1) else int(jobs)))
        if not kept:
            return []
        n = len(kept) if max_batch_size in (None, -1) else int(max_batch_size)
        return [kept[i:i + n] for i in range(0, len(kept), n)]

    def validate_batch_is_legal(self, batch: Sequence[Sequence[str]]) -> None:
        """The jobs were composed when they were judged; compose only any other."""
        rest = [b for b in batch if tuple(b) not in self._composed]
        if rest:
            super().validate_batch_is_legal(rest)
