r"""Study ``matrix``: one cell of the comparison matrix, a method (built from parts) on a scenario.

The composition root builds the scenario, the network its sensors form (the scenario's own, or the run's
``network`` part where the scenario leaves the placement open) and the method from the ``filter``,
``model``, ``observation`` and ``consensus`` parts sized for them. The cell draws the training and test
episodes (one random stream per episode), lets the method learn and estimate, and compares the estimated
positions with the true ones (:func:`dslearn.metrics.positions.position_metrics`): ``rmse``, ``pos_err`` and,
where the method has covariances, ``nees_pos``, per reporting node and test episode, plus ``runtime_s``.
A method that does not fit the scenario is refused before any work (:meth:`Method.fits`).

``dslearn-run experiment=matrix`` sweeps every method preset over every scenario it fits;
``dslearn-report`` on the sweep folder writes the matrix (``matrix.md``, ``matrix.csv``, ``matrix.png``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, List

import pandas as pd
import torch

from dslearn.episodes import Scenario
from dslearn.errors import ConfigError
from dslearn.methods.base import Method
from dslearn.metrics.positions import position_metrics
from dslearn.metrics.rows import node_rows
from dslearn.network import SensorNetwork
from dslearn.settings import ranged
from dslearn.sim.scenario import sample_split


#: files a matrix sweep writes into its folder (the matrix sweeper): every combination of the sweep, its
#: job number (empty where it does not fit), row (method label), column (scenario name), units and reason
CELLS_FILE = "matrix_cells.csv"
#: the combinations that do not fit, with the reason (the same columns; the report's "n/a" cells)
SKIPPED_FILE = "skipped_cells.csv"
CELL_COLUMNS = ("job", "method", "scenario", "units", "reason", "overrides")


@dataclass
class LeftOut:
    """Cells a sweep leaves out although they fit: the preset ``method`` (a ``conf/method`` option) on each of
    ``scenarios`` (``conf/scenario`` options), for the reason ``why`` (measured cost beyond the sweep's budget)."""

    method: str = ""
    scenarios: List[str] = field(default_factory=list)
    why: str = ""


@dataclass
class MatrixSettings:
    """``task=matrix``: the episodes of a cell; ``left_out``: the cells a matrix sweep leaves out, with the reason
    (:func:`dslearn.schemas.matrix.select_cells` records them in ``skipped_cells.csv`` like the cells that do not
    fit; a run of one cell, outside a sweep, runs it)."""

    _target_: str = "dslearn.studies.matrix.MatrixCell"
    name: str = "matrix"
    train_episodes: int = ranged(30, ge=0)
    test_episodes: int = ranged(20, ge=1)
    left_out: List[LeftOut] = field(default_factory=list)


@dataclass
class MatrixCell:
    """A method on a scenario: train, estimate, compare with the truth."""

    settings: MatrixSettings
    scenario: Scenario
    scenario_network: SensorNetwork
    method: Method
    seed: int
    dtype: torch.dtype
    device: torch.device

    def run(self, diagnostics=None, progress: bool = False) -> pd.DataFrame:
        spec, method = self.scenario.spec, self.method
        reason = method.fits(spec)
        if reason is not None:
            raise ConfigError(f"{method.label} does not fit scenario {spec.name}: {reason}")
        st = self.settings
        test, train = sample_split(self.scenario, self.scenario_network, self.seed, st.test_episodes,
                                   st.train_episodes, self.dtype, self.device)
        t0 = time.perf_counter()
        est = method.estimate(self.scenario, self.scenario_network, train, test.measurements, self.seed)
        wall = time.perf_counter() - t0
        metrics = position_metrics(est, self.scenario.positions(test.states))
        kinds = ["sensor" if bool(s) else "comm" for s in est.sensing]
        keys = dict(method=method.label, scenario=spec.name, units=spec.units, train_episodes=st.train_episodes,
                    test_episodes=st.test_episodes)
        df = node_rows(metrics, est.nodes, kinds, **keys)
        timing = pd.DataFrame({**{k: [v] for k, v in keys.items()}, "node": ["all"], "node_kind": ["all"],
                               "episode": [-1], "metric": ["runtime_s"], "value": [wall]})
        if diagnostics is not None:
            diagnostics.timings["method_s"] = round(wall, 3)
        return pd.concat([df, timing], ignore_index=True)


def cell_network(scenario: Any, placed: SensorNetwork | None) -> SensorNetwork:
    """The sensors of a cell: the scenario's own network, else the one ``placed`` by the run's network part."""
    own = scenario.network
    if own is not None:
        return own
    if placed is None:
        raise ConfigError(f"scenario {scenario.spec.name} places no sensors of its own: it needs the network part")
    return placed
