"""Study ``liu_dgpt``: distributed GP tracking (Liu et al., FUSION 2022), Tables I-II, Figs 5-7.

The protocol only: :class:`LiuDgptStudy` runs the grid (scenarios x noise levels x Monte Carlo runs,
the aggregation rules + the centralised standard GP) for one input type (``gp_input``) and returns a
tidy DataFrame. Its settings are :class:`LiuDgpt` (the task's keys: ``tracker``, ``aggregations``,
``gp_input``, ``noises``, ...; their ranges are the field rules), its trajectory generators arrive
built, one per scenario of the run (slot ``liu_dgpt_generators``). Tracker:
:mod:`dslearn.filters.dgpt`; trajectories and measurements: :mod:`dslearn.sim.manoeuvres`; errors
and rows: :mod:`dslearn.metrics.regression`; tables and figures: :mod:`dslearn.reports.liu_dgpt`.

Python use (the same defaults and checks as ``dslearn-run``)::

    from dslearn import api
    df = api.run("experiment=liu_table1", "task.mc_runs=2", "scenario=s1", "task.noises=[2.0]")
"""

import logging
import math
import struct
import time
from dataclasses import asdict, dataclass
from typing import Callable, Dict, List, Optional

import numpy as np
import pandas as pd
import torch

from dslearn.filters.dgpt import GP_INPUTS, OPTIMISERS, HyperConfig, track
from dslearn.fusion.aggregation import AGGREGATIONS
from dslearn.metrics.regression import dgpt_metrics, dgpt_rows, dgpt_trace_rows
from dslearn.settings import ranged
from dslearn.sim.manoeuvres import SCENARIOS, generator_target, measure, sensor_field

# (no postponed annotations here: the validation layer reads the nested settings' types from the fields)

TASK = "liu_dgpt"
TRACKERS = ("dgpt", "gp")
_POS = dict(gt=0.0)


# ------------------------------------------------------------------------------------------ settings
# Every field is mandatory: the values live in conf/task/liu_dgpt.yaml.

@dataclass(kw_only=True)
class HyperSettings:
    """Online hyperparameter learning (:class:`~dslearn.filters.dgpt.HyperConfig`, with its ranges)."""

    optimizer: str = ranged(choices=OPTIMISERS)
    lr: float = ranged(**_POS)
    iters: int = ranged(ge=0)
    iters_first: int = ranged(ge=0)
    tol: float = ranged(**_POS)
    max_iters: int = ranged(ge=1)
    gap_check: bool
    init_outputscale: float = ranged(**_POS)
    init_lengthscale_t: float = ranged(**_POS)
    init_lengthscale_r: float = ranged(**_POS)
    init_noise: float = ranged(**_POS)
    min_noise: float = ranged(**_POS)
    max_noise: float = ranged(**_POS)
    min_outputscale: float = ranged(**_POS)
    max_outputscale: float = ranged(**_POS)
    min_lengthscale: float = ranged(**_POS)
    max_lengthscale: float = ranged(**_POS)


@dataclass(kw_only=True)
class S1Params:
    """``dslearn.sim.manoeuvres.generate_s1`` (``_partial_``: runs, steps, generator at run time)."""

    _target_: str = ranged(choices=(generator_target("s1"),))
    _partial_: bool = ranged(choices=(True,))
    turn_every: int = ranged(ge=1)
    speeds: List[float] = ranged(each=True, ge=0.0, min_len=1)
    headings_deg: List[float] = ranged(each=True, ge=-360.0, le=360.0, min_len=1)
    accel_std: float = ranged(ge=0.0)


@dataclass(kw_only=True)
class S2Params:
    _target_: str = ranged(choices=(generator_target("s2"),))
    _partial_: bool = ranged(choices=(True,))
    a_max: float = ranged(ge=0.0)
    p_zero: float = ranged(ge=0.0, le=1.0)
    p_max: float = ranged(ge=0.0, le=1.0)
    tau: float = ranged(**_POS)
    v0: float = ranged(ge=0.0)
    v_max: float = ranged(**_POS)


@dataclass(kw_only=True)
class S3Params:
    _target_: str = ranged(choices=(generator_target("s3"),))
    _partial_: bool = ranged(choices=(True,))
    speed: float = ranged(ge=0.0)
    turn_rate_deg: float
    turn_duration: float = ranged(**_POS)
    straight: float = ranged(ge=0.0)
    accel_std: float = ranged(ge=0.0)


@dataclass(kw_only=True)
class ScenarioParams:
    """The S1-S3 trajectory generators (``_target_`` + ``_partial_`` + parameters)."""

    s1: S1Params
    s2: S2Params
    s3: S3Params


@dataclass(kw_only=True)
class WindowLengths:
    """Sliding-window length per scenario [steps]."""

    s1: int = ranged(ge=1)
    s2: int = ranged(ge=1)
    s3: int = ranged(ge=1)


@dataclass(kw_only=True)
class TraceCell:
    """The cell whose first ``episodes`` episodes get per-step rows (Figs 5-6)."""

    scenario: str = ranged(choices=SCENARIOS)
    noise: float = ranged(**_POS)
    episodes: int = ranged(ge=0)


@dataclass(kw_only=True)
class LiuDgpt:
    """The settings of task ``liu_dgpt`` (``conf/task/liu_dgpt.yaml``)."""

    _target_: str = "dslearn.studies.liu_dgpt.LiuDgptStudy"
    name: str = TASK
    gp_input: str = ranged(choices=GP_INPUTS)
    tracker: Optional[str] = ranged(None, choices=TRACKERS)  # None = the rules (+ the standard GP if centralised)
    scenarios: List[str] = ranged(each=True, choices=SCENARIOS, min_len=1)
    noises: List[float] = ranged(each=True, min_len=1, **_POS)
    aggregations: List[str] = ranged(each=True, choices=AGGREGATIONS)
    grbcm_comm_points: int = ranged(ge=1)
    centralised: bool
    normalise_beta: bool
    mc_runs: int = ranged(ge=1)
    batch_runs: int = ranged(ge=1)
    num_sensors: int = ranged(ge=1)
    sensing_range: float = ranged(**_POS)
    area_size: float = ranged(**_POS)
    num_steps: int = ranged(ge=2)
    dt: float = ranged(**_POS)
    window: WindowLengths
    ucb_delta: float = ranged(gt=0.0, lt=1.0)
    torch_threads: Optional[int] = ranged(ge=1)
    hyper: HyperSettings
    scenario_params: ScenarioParams
    trace: TraceCell

    def methods(self) -> tuple[list[str], bool]:
        """The aggregation rules the study runs and whether it runs the centralised standard GP:
        ``tracker`` None = ``aggregations`` (+ the standard GP if ``centralised``), ``dgpt`` =
        ``aggregations`` alone, ``gp`` = the standard GP alone."""
        if self.tracker == "gp":
            return [], True
        return [str(a) for a in self.aggregations], self.tracker is None and bool(self.centralised)


@dataclass
class LiuDgptPlan:
    """What one run computes: the grid's cells, the methods, the sizes and the tracker's settings."""

    gp_input: str
    scenarios: list[str]
    noises: list[float]
    aggregations: list[str]
    centralised: bool
    trace: TraceCell
    window: dict[str, int]
    hyper: HyperConfig
    generators: dict[str, Callable]
    mc_runs: int
    batch_runs: int
    num_sensors: int
    num_steps: int
    sensing_range: float
    area_size: float
    dt: float
    ucb_delta: float
    normalise_beta: bool
    grbcm_comm_points: int
    torch_threads: Optional[int]


# ------------------------------------------------------------------------------------------ the study

@dataclass
class LiuDgptStudy:
    """One run of the DGPT grid. ``liu_dgpt_generators``: the trajectory generator of each scenario the
    run covers, in order (``generate_s*`` with the task's parameters; the run's scenarios are its keys)."""

    settings: LiuDgpt
    liu_dgpt_generators: Dict[str, Callable]
    seed: int
    dtype: torch.dtype
    device: torch.device

    def plan(self) -> LiuDgptPlan:
        """The run's grid. The methods are those of ``tracker`` (:meth:`LiuDgpt.methods`). A
        single-cell run traces (Figs 5-6) its own cell when the trace cell is not in it."""
        t = self.settings
        scenarios = list(self.liu_dgpt_generators)
        noises = [float(n) for n in t.noises]
        aggregations, centralised = t.methods()
        trace = TraceCell(scenario=str(t.trace.scenario), noise=float(t.trace.noise), episodes=int(t.trace.episodes))
        if trace.scenario not in scenarios or not any(math.isclose(trace.noise, n) for n in noises):
            trace.scenario, trace.noise = scenarios[0], noises[0]
        return LiuDgptPlan(
            gp_input=t.gp_input, scenarios=scenarios, noises=noises, aggregations=aggregations,
            centralised=centralised, trace=trace, window={s: int(getattr(t.window, s)) for s in scenarios},
            hyper=HyperConfig(**asdict(t.hyper)), generators=dict(self.liu_dgpt_generators), mc_runs=t.mc_runs,
            batch_runs=t.batch_runs, num_sensors=t.num_sensors, num_steps=t.num_steps, sensing_range=t.sensing_range,
            area_size=t.area_size, dt=t.dt, ucb_delta=t.ucb_delta, normalise_beta=t.normalise_beta,
            grbcm_comm_points=t.grbcm_comm_points, torch_threads=t.torch_threads)

    def run(self, diagnostics=None, progress: bool = False) -> pd.DataFrame:
        """Run the grid; a tidy DataFrame (one row per episode x method x metric, and per step of
        the traced episodes)."""
        p = self.plan()
        old_threads = torch.get_num_threads()
        if p.torch_threads is not None:
            torch.set_num_threads(p.torch_threads)
        try:
            return _run(p, int(self.seed), self.device, self.dtype, bool(progress))
        finally:
            torch.set_num_threads(old_threads)


def _method_keys(methods):
    model = ["standard_gp" if m == "standard_gp" else "dgpt" for m in methods]
    cons = ["-" if m == "standard_gp" else m for m in methods]
    return model, cons


def _stream_key(seed: int, *key: int) -> int:
    """A 63-bit seed for the random stream named by ``key`` (numpy ``SeedSequence``)."""
    ss = np.random.SeedSequence(entropy=int(seed) % 2 ** 64, spawn_key=tuple(int(k) for k in key))
    return int(ss.generate_state(1, np.uint64)[0] >> np.uint64(1))


def _float_key(x: float) -> int:
    return struct.unpack("<Q", struct.pack("<d", float(x)))[0]


def episodes(p: LiuDgptPlan, seed: int):
    """Trajectories, sensors and measurements of the grid, one random stream per episode.

    Stream keys (``seed`` + key): (0, scenario, run) -> trajectory, then sensor field (shared by
    the noise levels of a run: common random numbers); (1, scenario, run, sigma) -> measurement
    noise; (2, scenario, run, sigma) -> the episode key of grBCM's draws. ``scenario`` is the index
    in :data:`SCENARIOS` and ``run`` the MC-run index, so an episode does not depend on which
    other scenarios, noise levels or runs are part of the job, nor on ``mc_runs``.

    Returns:
        truth (E, T, 2), meas (E, S, T, 2), avail (E, S, T), window (E,), episode keys (E,),
        keys [(scenario, sigma, run)] of the E episodes.
    """
    R, T = p.mc_runs, p.num_steps
    truth_l, meas_l, av_l, win_l, ek_l, keys = [], [], [], [], [], []
    for s in p.scenarios:
        si = SCENARIOS.index(s)
        pos, sens = [], []
        for r in range(R):
            g = torch.Generator().manual_seed(_stream_key(seed, 0, si, r))
            pos.append(p.generators[s](1, T, g, dt=p.dt, dtype=torch.float64)[0])
            sens.append(sensor_field(1, p.num_sensors, p.area_size, g))
        for nz in p.noises:
            for r in range(R):
                g = torch.Generator().manual_seed(_stream_key(seed, 1, si, r, _float_key(nz)))
                z, av = measure(pos[r], sens[r], p.sensing_range, torch.full((1,), nz, dtype=torch.float64), g)
                truth_l.append(pos[r])
                meas_l.append(z)
                av_l.append(av)
                ek_l.append(_stream_key(seed, 2, si, r, _float_key(nz)))
                keys.append((s, nz, r))
            win_l.append(torch.full((R,), p.window[s], dtype=torch.long))
    return (torch.cat(truth_l), torch.cat(meas_l), torch.cat(av_l), torch.cat(win_l),
            torch.tensor(ek_l, dtype=torch.long), keys)


def _run(p: LiuDgptPlan, seed: int, device: torch.device, dtype: torch.dtype, progress: bool) -> pd.DataFrame:
    t0 = time.time()
    R = p.mc_runs
    truth, meas, avail, window, ekeys, keys = episodes(p, seed)
    run_idx = torch.tensor([k[2] for k in keys])

    frames = []
    n_jitter = 0
    for c0 in range(0, R, p.batch_runs):
        sel = torch.nonzero((run_idx >= c0) & (run_idx < c0 + p.batch_runs))[:, 0]
        tr = truth[sel].to(device=device, dtype=dtype)
        res = track(meas[sel].to(device=device, dtype=dtype), avail[sel].to(device), window[sel],
                    gp_input=p.gp_input, aggregations=p.aggregations,
                    centralised=p.centralised, hyper=p.hyper, dt=p.dt,
                    delta=p.ucb_delta, normalise_beta=p.normalise_beta, progress=progress,
                    grbcm_comm_points=p.grbcm_comm_points, episode_keys=ekeys[sel])
        n_jitter += res.n_jitter
        av = avail[sel].to(device)
        met = dgpt_metrics(res, tr, av, p.ucb_delta, p.hyper.tol if p.hyper.optimizer == "newton" else None)
        model, cons = _method_keys(res.methods)
        kk = [keys[i] for i in sel.tolist()]
        frames.extend(dgpt_rows(met, kk, model, cons))
        trace = dgpt_trace_rows(p.trace.scenario, p.trace.noise, p.trace.episodes, res, tr, av, kk, model, cons)
        if trace is not None:
            frames.append(trace)
    df = pd.concat(frames, ignore_index=True)
    df["node"] = "fusion"
    df["gp_input"] = p.gp_input
    if "step" not in df:
        df["step"] = -1
    df["step"] = df["step"].fillna(-1).astype(int)
    df["value"] = df["value"].astype(float)
    df["noise"] = df["noise"].astype(float)
    df["episode"] = df["episode"].astype(int)
    df.attrs["wall_time_s"] = time.time() - t0
    df.attrs["cholesky_jitter"] = n_jitter
    if n_jitter:
        logging.getLogger(__name__).warning("liu_dgpt: %d Cholesky factorisations needed jitter", n_jitter)
    cols = ["episode", "scenario", "noise", "gp_input", "model", "consensus", "node", "step",
            "metric", "value"]
    return df[cols]
