r"""Study ``matrix``: one cell of the comparison matrix, a method (built from parts) on a scenario.

The composition root builds the scenario, the network its sensors form (the scenario's own, or the run's
``network`` part where the scenario leaves the placement open) and the method from the ``filter``,
``model``, ``observation`` and ``consensus`` parts sized for them. The cell draws the training and test
episodes (one random stream per episode), lets the method learn and estimate, and compares the estimated
positions with the true ones (:func:`dslearn.metrics.positions.position_metrics`): ``rmse``, ``pos_err`` and,
where the method has covariances, ``nees_pos``, per reporting node and test episode, plus ``runtime_s``. On a
scenario of unlabelled detections (``spec.labelled`` false) these compare the track matched to each target
(:func:`matched_estimates`), and the multi-target metrics are written too
(:func:`dslearn.metrics.multitarget.tracking_metrics`: ``gospa`` and its parts, ``ospa``, ``id_switches``,
``fragmentations``).
A method that does not fit the scenario is refused before any work (:meth:`Method.fits`).

``task.seeds`` (default 1): the cell runs that many independent draws, with the seeds ``seed``, ``seed + 1``,
..., each a new draw of the world and of the method: the scenario, its sensors and the method are rebuilt
through the composition root with the run's seed replaced (the ``draws`` slot), so a draw redraws what the
seed decides, Liu's sensor field (``scenario.seed: ${seed}``), the trajectories, a recorded scenario's pool
order, the method's own randomness (initial weights); Yu's sensor placement is not redrawn (``network.seed`` is
fixed across run seeds: the layout is part of the scenario, as in Yu et al.'s Fig. 1). One draw at a time: the
peak memory is that of one draw. Every row carries its draw's ``seed``; with ``seeds: 1`` the rows are those of
the run's seed alone, bit for bit.

``dslearn-run experiment=matrix`` sweeps every method preset over every scenario it fits;
``dslearn-report`` on the sweep folder writes the matrix (``matrix.md``, ``matrix.csv``, ``matrix.png``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any, Callable, List, Optional

import pandas as pd
import torch

from dslearn.episodes import Scenario
from dslearn.errors import ConfigError
from dslearn.methods.base import Method
from dslearn.metrics.multitarget import MATRIX_CUTOFF, matched_order, matched_position_metrics, tracking_metrics
from dslearn.metrics.positions import position_metrics
from dslearn.metrics.rows import node_rows
from dslearn.network import SensorNetwork
from dslearn.settings import ranged
from dslearn.sim.scenario import sample_split

log = logging.getLogger(__name__)

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
    """``task=matrix``: the episodes of a cell and its number of independent draws (``seeds``: the run's seed and
    the ``seeds - 1`` following ones); ``left_out``: the cells a matrix sweep leaves out, with the reason
    (:func:`dslearn.schemas.matrix.select_cells` records them in ``skipped_cells.csv`` like the cells that do not
    fit; a run of one cell, outside a sweep, runs it)."""

    _target_: str = "dslearn.studies.matrix.MatrixCell"
    name: str = "matrix"
    train_episodes: int = ranged(30, ge=0)
    test_episodes: int = ranged(20, ge=1)
    seeds: int = ranged(1, ge=1)
    left_out: List[LeftOut] = field(default_factory=list)


#: ``draw(seed) -> (scenario, its sensors, method)``: one draw of a cell, built for a run with that seed
Draw = Callable[[int], "tuple[Scenario, SensorNetwork, Method]"]


@dataclass
class MatrixCell:
    """A method on a scenario: train, estimate, compare with the truth; ``settings.seeds`` times, one draw per
    seed. ``scenario``, ``scenario_network`` and ``method`` are the draw of ``seed``; ``draws`` builds the others
    (the composition root's ``draws`` slot; needed only where ``seeds > 1``)."""

    settings: MatrixSettings
    scenario: Scenario
    scenario_network: SensorNetwork
    method: Method
    seed: int
    dtype: torch.dtype
    device: torch.device
    draws: Optional[Draw] = None

    def _draw(self, k: int):
        """The ``k``-th draw: the cell's own objects for ``k = 0``, else a new build for seed ``seed + k``."""
        if k == 0:
            return self.scenario, self.scenario_network, self.method
        return self.draws(self.seed + k)

    def run(self, diagnostics=None, progress: bool = False) -> pd.DataFrame:
        st = self.settings
        seeds = int(st.seeds)
        if seeds > 1 and self.draws is None:
            raise ConfigError(f"task.seeds={seeds}: this cell was built without the draws of the other seeds (the "
                              f"composition root's 'draws' slot); use task.seeds=1 or dslearn.api.build_study")
        rate = SECONDS_PER_EPISODE.get((str(self.method.label), str(self.scenario.spec.name)))
        guess = (f"; estimated {seeds * rate * (st.train_episodes + st.test_episodes):.0f} s of learning and "
                 f"estimation" if rate is not None else "")
        log.info("%s on %s: %d draw(s) (seeds %d..%d), %d training + %d test episodes each, one draw at a time%s",
                 self.method.label, self.scenario.spec.name, seeds, self.seed, self.seed + seeds - 1,
                 st.train_episodes, st.test_episodes, guess)
        frames, total = [], 0.0
        for k in range(seeds):
            scenario, network, method = self._draw(k)
            if k == 0 and seeds > 1:  # later draws replace it: let the first one's memory go with it
                self.scenario = self.scenario_network = self.method = None
            df, wall = self._run_one(scenario, network, method, self.seed + k)
            del scenario, network, method
            frames.append(df)
            total += wall
            if seeds > 1:
                log.info("draw %d of %d (seed %d) done in %.1f s", k + 1, seeds, self.seed + k, wall)
        if diagnostics is not None:
            diagnostics.timings["method_s"] = round(total, 3)
        return frames[0] if len(frames) == 1 else pd.concat(frames, ignore_index=True)

    def _run_one(self, scenario: Scenario, network: SensorNetwork, method: Method, seed: int):
        """The rows of one draw (every row with its ``seed``) and the method's wall time."""
        spec = scenario.spec
        reason = method.fits(spec)
        if reason is not None:
            raise ConfigError(f"{method.label} does not fit scenario {spec.name}: {reason}")
        st = self.settings
        test, train = sample_split(scenario, network, seed, st.test_episodes, st.train_episodes, self.dtype,
                                   self.device)
        t0 = time.perf_counter()
        est = method.estimate(scenario, network, train, test.measurements, seed)
        wall = time.perf_counter() - t0
        truth = scenario.positions(test.states)
        if getattr(spec, "labelled", True):
            metrics = position_metrics(est, truth)
        elif bool(torch.isfinite(truth).all()):  # unlabelled detections: the track matched to each target, and
            metrics = position_metrics(matched_estimates(est, truth, spec.match_distance), truth)  # multi-target
            metrics.update(tracking_metrics(est.mean, truth, spec.match_distance))
        else:  # targets that enter and leave (a NaN position: absent): over the steps where target and track exist
            metrics = matched_position_metrics(est.mean, est.cov, truth, spec.match_distance)
            metrics.update(tracking_metrics(est.mean, truth, spec.match_distance))
        kinds = ["sensor" if bool(s) else "comm" for s in est.sensing]
        keys = dict(seed=int(seed), method=method.label, scenario=spec.name, units=spec.units,
                    train_episodes=st.train_episodes, test_episodes=st.test_episodes)
        df = node_rows(metrics, est.nodes, kinds, **keys)
        timing = pd.DataFrame({**{k: [v] for k, v in keys.items()}, "node": ["all"], "node_kind": ["all"],
                               "episode": [-1], "metric": ["runtime_s"], "value": [wall]})
        return pd.concat([df, timing], ignore_index=True), wall


def matched_estimates(est, truth, c: float = MATRIX_CUTOFF):
    """The estimates with every node's tracks reordered so that slot ``a`` holds the track matched to target ``a``
    over the episode (:func:`~dslearn.metrics.multitarget.matched_order`): what ``rmse``, ``pos_err`` and
    ``nees_pos`` compare on a scenario of unlabelled detections."""
    from dslearn.episodes import Estimates

    idx = matched_order(est.mean, truth, c)  # (N, B, A)
    steps = est.mean.shape[2]
    gi = idx[:, :, None, :, None].expand(-1, -1, steps, -1, 2)
    mean = est.mean.gather(-2, gi)
    cov = None if est.cov is None else est.cov.gather(-3, gi.unsqueeze(-1).expand(*gi.shape, 2))
    return Estimates(mean, cov, est.nodes, est.sensing)


#: measured seconds per episode (training + test) of one draw's learning and estimation (the cell's ``runtime_s``
#: over its 4 + 4 episodes), by (method label, scenario name): experiment=matrix_small, seed 0, on an idle 2-core
#: machine. The start-up's estimate of a matrix sweep (:func:`plan_text`); cells not here are not estimated.
SECONDS_PER_EPISODE = {
    ("ekf lin hybrid", "yu"): 0.002, ("ekf lin hybrid", "s1"): 0.046, ("ekf lin hybrid", "s2"): 0.07,
    ("ekf lin hybrid", "s3"): 0.055, ("ekf lin hybrid", "corridor"): 0.002,
    ("ukf lin hybrid", "yu"): 0.004, ("ukf lin hybrid", "s1"): 0.04, ("ukf lin hybrid", "s2"): 0.038,
    ("ukf lin hybrid", "s3"): 0.041, ("ukf lin hybrid", "corridor"): 0.002,
    ("ekf sfm hybrid", "yu"): 0.008, ("ukf sfm hybrid", "yu"): 0.005,
    ("ekf gp_increment hybrid", "yu"): 0.267, ("ekf gp_increment hybrid", "s1"): 0.735,
    ("ekf gp_increment hybrid", "s2"): 0.475, ("ekf gp_increment hybrid", "s3"): 0.548,
    ("ekf gp_increment hybrid", "corridor"): 0.014,
    ("dgpt rbcm", "yu"): 0.009, ("dgpt rbcm", "s1"): 0.032, ("dgpt rbcm", "s2"): 0.038, ("dgpt rbcm", "s3"): 0.053,
    ("dgpt rbcm", "corridor"): 0.007, ("fg_ekf t=10", "jiang"): 0.033, ("rbpf_em consensus_10", "braga"): 4.161,
}
#: a job's own cost beside the method's (start, composition, drawing the episodes, writing), per draw [s], measured
#: the same way (the sweep's wall time less the cells' run times)
JOB_OVERHEAD_S = 2.5


def plan_text(records, settings: Any, workers: int) -> str:
    """The start-up line of a matrix sweep: its cells (``records`` with a ``job`` run), the seeds and episodes of
    each, the number of draws and the estimated wall time on ``workers`` parallel workers (from
    :data:`SECONDS_PER_EPISODE` where the cell was measured, else not estimated) and the memory rule (one draw
    of one cell per worker at a time)."""
    runs = [r for r in records if r.get("job") is not None and not (isinstance(r.get("job"), float)
                                                                    and r["job"] != r["job"])]
    seeds, train, test = int(settings.get("seeds", 1)), int(settings.train_episodes), int(settings.test_episodes)
    known, unknown = 0.0, 0
    for r in runs:
        rate = SECONDS_PER_EPISODE.get((str(r.get("method")), str(r.get("scenario"))))
        if rate is None:
            unknown += 1
        else:
            known += seeds * (JOB_OVERHEAD_S + rate * (train + test))
    workers = max(1, int(workers))
    est = (f"estimated {known / workers / 60:.1f} min of wall time on {workers} worker(s) for the "
           f"{len(runs) - unknown} measured cells" + (f", plus {unknown} cells never measured (not estimated)"
                                                      if unknown else "")) if runs else "nothing to run"
    return (f"matrix: {len(runs)} cells x {seeds} seed(s) = {len(runs) * seeds} draws of {train} training + {test} "
            f"test episodes; {est}; memory: each worker holds one draw of one cell at a time (a draw's peak, "
            f"not the seeds')")


#: the override keys that choose a cell's method: the preset, or its parts
METHOD_KEYS = ("method", "filter", "model", "observation", "consensus", "learner")


def check_method_chosen(cfg: Any, keys) -> None:
    """A cell needs a method: refuse a ``task=matrix`` command line that names neither a preset (``method=``) nor
    any part of one (``filter=``, ``model=``, ...; ``keys``: the override keys of the command line or the sweep,
    an experiment counts as choosing), with the presets to pick from. Without it the root config's default parts
    would run silently (the EKF with the online GP: minutes and gigabytes on Liu's 200 sensors)."""
    if str(cfg.task.get("name")) != "matrix":
        return
    heads = {str(k).lstrip("+~").split(".")[0].split("@")[0] for k in keys}
    if heads & {*METHOD_KEYS, "experiment"}:
        return
    from dslearn.conf_paths import CONF_DIRS

    presets = sorted({p.stem for d in CONF_DIRS for p in (d / "method").glob("*.yaml")})
    raise ConfigError(f"task=matrix needs method=<preset> (or the parts: filter=, model=, observation=, consensus=, "
                      f"learner=); presets: {', '.join(presets)}")


def cell_network(scenario: Any, placed: SensorNetwork | None) -> SensorNetwork:
    """The sensors of a cell: the scenario's own network, else the one ``placed`` by the run's network part."""
    own = scenario.network
    if own is not None:
        return own
    if placed is None:
        raise ConfigError(f"scenario {scenario.spec.name} places no sensors of its own: it needs the network part")
    return placed
