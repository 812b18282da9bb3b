r"""Study ``braga_tbn``: distributed online EM with RBPFs and consensus on sufficient statistics for
cooperative terrain-based navigation with unknown jump-Markov radar-altimeter noise (Braga et al.).

:class:`BragaStudy` simulates ``settings.mc_runs`` Monte Carlo flights of the four-aircraft finger-four
formation (Section VI, Table I) and runs every strategy (non-cooperative, centralised, consensus_q) on the same
measurements. :meth:`BragaStudy.run` returns a tidy DataFrame with

* run-level metrics (``time_s = -1``): ``pos_rms`` (steady-state window), ``pos_rms_first5s``, ``mu_rms``,
  ``sigma_rms``, ``pi_rms`` (steady-state window, over nodes and modes), ``throughput_kBps`` (Table II),
  ``pos_rms_worst_node`` (largest per-node steady-state position RMS), ``pos_err_max`` (largest position error
  of any node at any step), ``lost_nodes`` / ``lost_track`` (nodes / 0-1 flag with a steady-state position RMS
  above ``lost_track_m``), ``resample_rate``, ``degenerate_events``;
* time series (``time_s >= 0``, node-averaged): ``pos_se_t``, ``mu_se_t``, ``sigma_se_t``, ``pi_se_t``
  (squared errors averaged over nodes/modes) and the estimates ``mu_k``, ``sigma_k``, ``pi_kk`` for Fig. 4.

Every Monte Carlo run draws its truth and measurements from its own random stream (seed, run index) and its
filters from (seed, run index) (``filter_streams=common``: common random numbers for all strategies) or
(seed, run index, strategy) (``independent``), so a run's result never depends on ``mc_batch``, ``workers``
or the other runs and strategies (:mod:`dslearn.streams`).

Its settings are :class:`BragaTask` (every part of the study is in it: flights, terrain, network, filters);
the harness (terrain, models, flights, filters) is :mod:`dslearn.learning.online_em`, the errors against the
truth :mod:`dslearn.metrics.navigation`, Table II and Figs 3-6 :mod:`dslearn.reports.braga_tbn`, the
lost-track diagnostics ``python -m dslearn.tools.tbn_trace``.

Python use (the same defaults and checks as ``dslearn-run``)::

    from dslearn import api
    df = api.run("experiment=braga_tbn", "task.mc_runs=4")
"""

from __future__ import annotations

import os
import time
import warnings
from dataclasses import dataclass, field
from typing import Any, List, Optional

import pandas as pd
import torch

from dslearn.fusion.statistics import parse_strategy
from dslearn.learning.online_em import TBNJob, prepare_job, simulate_and_filter
from dslearn.metrics.navigation import tbn_errors, tbn_metrics, tbn_rows
from dslearn.settings import ranged

MODEL = "rbpf_online_em"


# ------------------------------------------------------------------------------------------ settings
@dataclass
class BragaModes:
    """The jump-Markov altimeter noise: true modes and the EM's initial guess (K modes each)."""

    mu_true: List[float] = ranged(factory=lambda: [0.0, 20.0], min_len=1)
    sigma_true: List[float] = ranged(factory=lambda: [1.0, 4.0], gt=0.0, each=True, min_len=1)
    pi_true: List[Any] = ranged(factory=lambda: [[0.85, 0.15], [0.4, 0.6]], min_len=1)
    mu_init: List[float] = ranged(factory=lambda: [-5.0, 25.0], min_len=1)
    sigma_init: List[float] = ranged(factory=lambda: [5.0, 5.0], gt=0.0, each=True, min_len=1)
    pi_init: List[Any] = ranged(factory=lambda: [[0.5, 0.5], [0.5, 0.5]], min_len=1)


@dataclass
class BragaEM:
    eta_exponent: float = ranged(0.7, gt=0.5, le=1.0)  # stochastic-approximation conditions
    burn_in: int = ranged(50, ge=0)
    sigma_floor: float = ranged(1e-3, gt=0.0)
    init_mode: Any = ranged("true", choices=("true", "uniform", True))  # `init_mode=true` on the CLI is a bool


@dataclass
class BragaResampling:
    regularise: float = ranged(0.0, ge=0.0)


@dataclass
class BragaBackwardKernel:
    jitter_pos: float = ranged(1.0, gt=0.0)
    jitter_vel: float = ranged(0.0, ge=0.0)
    dtype: Optional[str] = ranged(None, choices=("float32", "float64"))


@dataclass
class BragaTerrain:
    size_m: float = ranged(25000.0, gt=0.0)
    resolution_m: float = ranged(25.0, gt=0.0)
    smoothing_m: float = ranged(250.0, gt=0.0)
    elevation_std_m: float = ranged(100.0, gt=0.0)
    mean_elevation_m: float = 500.0
    seed_offset: int = 0


@dataclass
class BragaNetwork:
    edges: List[Any] = ranged(factory=lambda: [[0, 1], [0, 2], [2, 3]], min_len=1)
    fusion_centre: int = ranged(0, ge=0, le=3)


@dataclass
class BragaConsensus:
    weights: str = "half_max_degree"  # checked (with the retired value's message) by the task's cross-field check
    matrix: Optional[List[Any]] = None


@dataclass
class BragaTask:
    """The study's settings (``conf/task/braga_tbn.yaml``, Table I); the field rules are checked before any
    work, with the cross-field rules of :mod:`dslearn.schemas.braga_tbn`."""

    _target_: str = "dslearn.studies.braga_tbn.BragaStudy"
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
    modes: BragaModes = field(default_factory=BragaModes)
    em: BragaEM = field(default_factory=BragaEM)
    ess_threshold: float = ranged(0.5, ge=0.0, le=1.0)
    resampling: BragaResampling = field(default_factory=BragaResampling)
    filter_streams: str = ranged("common", choices=("common", "independent"))
    lost_track_m: float = ranged(15.0, gt=0.0)
    backward_kernel: BragaBackwardKernel = field(default_factory=BragaBackwardKernel)
    terrain: BragaTerrain = field(default_factory=BragaTerrain)
    network: BragaNetwork = field(default_factory=BragaNetwork)
    consensus: BragaConsensus = field(default_factory=BragaConsensus)
    strategies: List[str] = ranged(factory=lambda: ["noncooperative", "centralised", "consensus_1", "consensus_5",
                                                    "consensus_10"], min_len=1)
    bytes_per_float: int = ranged(4, gt=0)
    kilobyte: int = ranged(1024, choices=(1000, 1024))
    record_every: int = ranged(10, gt=0)
    zoom_s: float = ranged(5.0, ge=0.0)
    steady_state_s: float = ranged(45.0, gt=0.0)


def consensus_label(strategy: str) -> str:
    """The ``consensus`` column of a strategy's rows: ``none``, ``fusion_centre`` or ``average_q<q>``."""
    kind, q = parse_strategy(strategy)
    return {"noncooperative": "none", "centralised": "fusion_centre"}.get(kind, f"average_q{q}")


def steady_steps(settings: BragaTask) -> int:
    """Steps of the steady-state window (the last ``steady_state_s`` seconds, at least one step)."""
    return max(1, int(round(settings.steady_state_s / settings.dt)))


# ------------------------------------------------------------------------------------------ the study
def _worker_init() -> None:
    torch.set_num_threads(1)


def _run_batch(job: TBNJob, settings: BragaTask, c0: int, nr: int, progress: bool = False) -> list[dict]:
    """Simulate and filter Monte Carlo runs c0..c0+nr-1 (one batch); returns the tidy rows."""
    episodes = list(range(c0, c0 + nr))
    scn, res = simulate_and_filter(job, episodes, progress=progress)
    if res.counters["offmap_particles"]:
        warnings.warn(f"braga_tbn: {res.counters['offmap_particles']} particle positions fell outside the terrain "
                      "map (clamped to its border); enlarge task.terrain.size_m")
    run_level, series = tbn_metrics(res, tbn_errors(res, scn), job.truth, steady_steps=steady_steps(settings),
                                    first_steps=max(1, int(round(5.0 / settings.dt))),
                                    lost_track_m=settings.lost_track_m, rec_idx=job.rec_idx)
    strategies = job.params.strategies
    return tbn_rows(run_level, series, job.throughput, episodes=episodes, strategies=strategies,
                    consensus={s: consensus_label(s) for s in strategies}, rec_time=job.rec_time, model=MODEL)


@dataclass
class BragaStudy:
    """The Monte Carlo study of Braga et al. (Section VI): every strategy on the same flights.

    Slots (filled by the composition root): ``settings`` (:class:`BragaTask`), the run's ``seed``, ``dtype``
    (float64 or float32) and ``device``."""

    settings: BragaTask
    seed: int
    dtype: torch.dtype
    device: torch.device

    def job(self) -> TBNJob:
        """The terrain, models, recording grid and throughput every Monte Carlo batch shares."""
        return prepare_job(self.settings, seed=self.seed, device=self.device, dtype=self.dtype)

    def batches(self) -> list[tuple[int, int]]:
        """``(first run, number of runs)`` of every Monte Carlo batch."""
        s = self.settings
        return [(c0, min(s.mc_batch, s.mc_runs - c0)) for c0 in range(0, s.mc_runs, s.mc_batch)]

    def run(self, diagnostics=None, progress: bool = False) -> pd.DataFrame:
        """Run the study (see the module docstring). Returns the tidy results table."""
        job = self.job()
        s, device = self.settings, torch.device(job.device)
        frames = []
        t_start = time.perf_counter()
        batches = self.batches()
        workers = min(s.workers, len(batches)) if device.type == "cpu" else 1
        if workers <= 1:
            for c0, nr in batches:
                frames.extend(_run_batch(job, s, c0, nr, progress))
        else:  # independent MC batches in worker processes (1 thread each); same seeds -> same results as serial
            import concurrent.futures as cf
            import multiprocessing as mp

            # glibc malloc settings for the workers only: keep freed MB-sized buffers in the heap instead of
            # returning them to the OS every step (fewer page faults; about 7 % faster). Not set if already set.
            env = {"MALLOC_MMAP_THRESHOLD_": str(1 << 30), "MALLOC_TRIM_THRESHOLD_": str(1 << 30)}
            env = {key: val for key, val in env.items() if key not in os.environ}
            os.environ.update(env)
            try:
                with cf.ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"),
                                            initializer=_worker_init) as ex:
                    futs = [ex.submit(_run_batch, job, s, c0, nr, progress) for c0, nr in batches]
                    out = [f.result() for f in futs]  # collected in batch order
            except cf.process.BrokenProcessPool as exc:  # e.g. a __main__ script without the `if __name__` guard
                warnings.warn(f"braga_tbn: worker processes failed ({exc}); running the MC batches serially")
                out = [_run_batch(job, s, c0, nr, progress) for c0, nr in batches]
            finally:
                for key in env:
                    os.environ.pop(key, None)
            for rows in out:
                frames.extend(rows)
        elapsed = time.perf_counter() - t_start
        df = pd.DataFrame(frames)
        df.attrs["elapsed_s"] = elapsed
        df = pd.concat([df, pd.DataFrame([{"episode": -1, "strategy": "all", "model": MODEL, "consensus": "-",
                                           "node": "avg", "time_s": -1.0, "metric": "wall_time_s",
                                           "value": float(elapsed)}])], ignore_index=True)
        return df
