r"""Study ``jiang_fg``: factor-graph identification + EKF-FG tracking (Jiang et al., ISITA 2022).

One run computes all four figures' grids, vectorised over configurations and Monte Carlo runs:

* ``fig2``: RMSE of the FG identification after ``t = 0..T`` iterations (``fg_identification``)
  and of the EKF-FG tracker run with ``t`` iterations per timing (``ekf_fg``); centralised
  baselines and CRLB as reference rows (``iteration = -1``).
* ``fig3``: estimates vs truth over time (first ``figures.fig3_episodes`` episodes), ``metric = estimate``.
* ``fig4``: RMSE per timing index.
* ``fig5``: RMSE averaged over timings vs ``sigma_y``.
* ``diag``: near-zero slopes (skipped sensors), precision floors, iterations to converge,
  the EKF-FG observation variance and the fraction of gated FG outputs.

``variant`` is ``default`` for the main grid (the settings of ``conf/task/jiang_fg.yaml``) or
the name of an ablation (``task.ablations``), run on the same data; ``paper`` is the paper's
EKF-FG (``sigma_e^2`` = CRLB at the prediction). Monte Carlo run ``r`` draws its truth and
noise from its own stream seeded by ``(seed, r)`` (:func:`~dslearn.sim.squared_range.run_noise`),
so its rows do not depend on ``mc_runs``.

``rmse`` rows hold one episode's root-mean-square error per parameter (mean over the M
parameters and, where ``timing = -1``, over all timings). The report pools episodes as
``sqrt(mean(rmse^2))`` (the Monte Carlo RMSE); ``summary.csv``'s ``mean`` is the plain mean.
The CRLB rows hold ``sqrt(tr F^{-1} / M)`` at the true state (Eq. 27), the same units.

The study's settings are :class:`JiangTask` (checked by :mod:`dslearn.schemas.jiang_fg` before it is
built); each ablation's overrides arrive typed (slot ``jiang_fg_ablations``). The engine is
:mod:`dslearn.learning.factor_graph.engine`, the errors :mod:`dslearn.metrics.identification`, the
figures :mod:`dslearn.reports.jiang_fg`. Python use::

    from dslearn import api
    df = api.run("experiment=jiang_fg", "task.mc_runs=3")
"""

import time
import warnings
from dataclasses import asdict, dataclass, field
from typing import Any, Dict, List, Optional

import numpy as np
import pandas as pd
import torch

from dslearn.filters.ekf_fg import OBS_VAR_MODES
from dslearn.learning.factor_graph.crlb import CRLB_FORMS
from dslearn.learning.factor_graph.engine import TrackerSettings, simulate
from dslearn.learning.factor_graph.identification import GRAPHS, SCHEDULES
from dslearn.metrics.identification import crlb_at_truth, identification_rows, rmse, squared_error
from dslearn.settings import ranged
from dslearn.sim.squared_range import SquaredRange, polynomial_trajectory, run_noise

# (no postponed annotations here: the validation layer reads the nested settings' types from the fields)

TASK = "jiang_fg"
#: ``variant`` label of the main grid's rows (an ablation may not take it)
MAIN_VARIANT = "default"
MODELS = ("fg_identification", "ekf_fg", "centralized_gn", "centralized_ekf")
CONSENSUS = {"fg_identification": "gaussian_bp", "ekf_fg": "gaussian_bp", "centralized_gn": "centralized",
             "centralized_ekf": "centralized", "crlb": "-", "truth": "-"}
NODE = "fusion_center"

#: the rules of every FG / tracker setting (shared by the main grid and the ablations)
SETTING_RULES = dict(
    init_guess_mode=dict(choices=("fixed", "prediction")), init_var=dict(gt=0.0), prior_var=dict(gt=0.0),
    measurement_var=dict(choices=("sample", "known")), crlb_form=dict(choices=tuple(CRLB_FORMS)),
    lambda_tol=dict(ge=0.0), converge_tol=dict(gt=0.0), schedule=dict(choices=tuple(SCHEDULES)),
    damping=dict(ge=0.0, lt=1.0), graph=dict(choices=tuple(GRAPHS)), taylor_point=dict(choices=("prediction", "guess")),
    initial_state_var=dict(gt=0.0), initial_gradient_var=dict(gt=0.0), process_var=dict(ge=0.0),
    gradient_var=dict(ge=0.0), obs_var=dict(choices=tuple(OBS_VAR_MODES)), gate=dict(gt=0.0),
    baseline_iters=dict(ge=1), max_iter=dict(ge=1),
)


def _r(name: str, default):
    """A field with the rules of the FG / tracker setting ``name``."""
    return ranged(default, **SETTING_RULES[name])


# ------------------------------------------------------------------------------------------ settings

@dataclass
class JiangScenario:
    """The field of Sec. IV (Eqs. 20-22): sensors ``(A_n, B_n)``, the source's polynomial coefficients
    ``(a, b, c)`` per parameter, the drive noise variance, the timings and the tracker's start."""

    sensors: List[Any] = ranged(factory=lambda: [[-30.0, 50.0], [10.0, 5.0], [60.0, 20.0]], min_len=1)
    coefficients: List[Any] = ranged(factory=lambda: [[0.05, 0.03, 6.0], [-0.02, 0.07, 0.0]], min_len=1)
    drive_var: float = ranged(0.5, ge=0.0)
    num_timings: int = ranged(50, ge=1)
    initial_state: List[float] = ranged(factory=lambda: [2.0, -2.0], min_len=1)


@dataclass
class JiangFG:
    """The factor graph's identification settings."""

    init_guess: List[float] = ranged(factory=lambda: [0.0, 0.0], min_len=1)
    init_guess_mode: str = _r("init_guess_mode", "fixed")
    init_var: float = _r("init_var", 100.0)
    prior_var: Optional[float] = _r("prior_var", None)
    relinearize: bool = False
    taylor_point: str = _r("taylor_point", "prediction")
    schedule: str = _r("schedule", "flooding")
    damping: float = _r("damping", 0.0)
    graph: str = _r("graph", "scalar")
    measurement_var: str = _r("measurement_var", "sample")
    crlb_form: str = _r("crlb_form", "trace_inverse")
    lambda_tol: float = _r("lambda_tol", 1e-8)
    converge_tol: float = _r("converge_tol", 1e-3)


@dataclass
class JiangTracker:
    """The EKF-FG (Eqs. 17-19), shared with the centralised EKF."""

    initial_state_var: float = _r("initial_state_var", 10.0)
    initial_gradient_var: float = _r("initial_gradient_var", 10.0)
    process_var: float = _r("process_var", 1.0)
    gradient_var: float = _r("gradient_var", 0.01)
    obs_var: str = _r("obs_var", "crlb")
    gate: Optional[float] = _r("gate", None)


@dataclass
class JiangFigures:
    fig2_iterations: List[int] = ranged(factory=lambda: list(range(1, 11)), ge=1, each=True, min_len=1)
    fig3_episodes: int = ranged(3, ge=0)
    fig5_sigma_y: List[float] = ranged(factory=lambda: [0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0], gt=0.0, each=True,
                                       min_len=1)


@dataclass
class JiangTask:
    """The settings of task ``jiang_fg`` (``conf/task/jiang_fg.yaml``). ``ablations``: name -> the FG /
    tracker settings (and ``max_iter``) it overrides; the study receives them typed (slot
    ``jiang_fg_ablations``)."""

    _target_: str = "dslearn.studies.jiang_fg.JiangFgStudy"
    name: str = TASK
    mc_runs: int = ranged(100, ge=1)
    scenario: JiangScenario = field(default_factory=JiangScenario)
    num_samples: int = ranged(60, ge=1)
    sigma_y: float = ranged(5.0, gt=0.0)
    max_iter: int = ranged(10, ge=1)
    fg: JiangFG = field(default_factory=JiangFG)
    tracker: JiangTracker = field(default_factory=JiangTracker)
    baseline_iters: int = ranged(3, ge=1)
    figures: JiangFigures = field(default_factory=JiangFigures)
    ablations: Dict[str, Any] = field(default_factory=dict)  # name -> overrides (dslearn.schemas.jiang_fg.Ablation)


# ------------------------------------------------------------------------------------------ the study

@dataclass
class JiangFgStudy:
    """One run of every figure's grid. ``jiang_fg_ablations``: name -> the settings that ablation
    overrides (typed; keys of :class:`~dslearn.learning.factor_graph.engine.TrackerSettings` and
    ``max_iter``), run on the main grid's data at ``(sigma_y, max_iter)``."""

    settings: JiangTask
    jiang_fg_ablations: Dict[str, Dict[str, Any]]
    seed: int
    dtype: torch.dtype
    device: torch.device

    def settings_values(self) -> dict:
        """The main grid's :class:`TrackerSettings` values (plain)."""
        s = self.settings
        return dict(num_samples=s.num_samples, initial_state=list(s.scenario.initial_state),
                    baseline_iters=s.baseline_iters, **asdict(s.fg), **asdict(s.tracker))

    def tracker_settings(self) -> TrackerSettings:
        """The main grid's identification + tracking settings."""
        return TrackerSettings.from_config(**self.settings_values())

    def ablation_runs(self) -> dict[str, tuple[TrackerSettings, int]]:
        """Each ablation's settings (the main grid's, with its overrides) and its FG iterations."""
        base = self.settings_values()
        out = {}
        for name, over in self.jiang_fg_ablations.items():
            over = dict(over)
            its = over.pop("max_iter", self.settings.max_iter)
            out[str(name)] = (TrackerSettings.from_config(**{**base, **over}), its)
        return out

    def run(self, diagnostics=None, progress: bool = False) -> pd.DataFrame:
        """Run every figure's grid of the study; returns the tidy results table."""
        s = self.settings
        device, dtype, seed = self.device, self.dtype, int(self.seed)
        settings, ablations = self.tracker_settings(), self.ablation_runs()
        fig2_iterations = sorted(set(s.figures.fig2_iterations))
        fig5_sigma_y = [float(x) for x in s.figures.fig5_sigma_y]
        t0 = time.perf_counter()

        B, K, L = s.mc_runs, s.scenario.num_timings, s.num_samples
        sensors = torch.tensor(s.scenario.sensors, dtype=dtype, device=device)
        h = SquaredRange(sensors)
        N, M = sensors.shape
        # every Monte Carlo run r draws from its own stream seeded by (seed, r): its numbers do not
        # depend on mc_runs or on the other runs; all configurations share them (common random numbers)
        drive, noise = run_noise(seed, range(B), K, M, N, L, dtype=dtype, device=device)
        truth = polynomial_trajectory(torch.tensor(s.scenario.coefficients, dtype=dtype, device=device), K,
                                      float(s.scenario.drive_var), noise=drive)

        # configuration grid: (sigma_y, iterations) -- fig2 varies t, fig5 varies sigma_y
        T, s0 = s.max_iter, float(s.sigma_y)
        grid = sorted({(s0, t) for t in fig2_iterations} | {(x, T) for x in fig5_sigma_y} | {(s0, T)})
        index = {g: i for i, g in enumerate(grid)}
        sig = torch.tensor([g[0] for g in grid], dtype=dtype, device=device)
        its = torch.tensor([g[1] for g in grid], device=device)
        out = simulate(h, truth, noise, sig, its, settings)

        frames = []
        base = dict(node=NODE, variant=MAIN_VARIANT)
        err = {m: squared_error(out.estimates[m], truth) for m in MODELS}   # (C, B, K)
        crlb = crlb_at_truth(h, truth, sig, L)                                # (C, B, K)
        fg_err = squared_error(out.fg_iter_means, truth)                      # (T+1, C, B, K)
        ref = index[(s0, T)]
        # Fig. 2: identification RMSE vs iteration (within the T-iteration run), tracker vs its iteration count
        for t in range(fg_err.shape[0]):
            frames.append(identification_rows(rmse(fg_err[t, ref]), "rmse", figure="fig2",
                                              model="fg_identification", consensus="gaussian_bp", iteration=t,
                                              timing=-1, sigma_y=s0, **base))
        for t in fig2_iterations:
            frames.append(identification_rows(rmse(err["ekf_fg"][index[(s0, t)]]), "rmse", figure="fig2",
                                              model="ekf_fg", consensus="gaussian_bp", iteration=t, timing=-1,
                                              sigma_y=s0, **base))
        for m in ("centralized_gn", "centralized_ekf"):
            frames.append(identification_rows(rmse(err[m][ref]), "rmse", figure="fig2", model=m,
                                              consensus="centralized", iteration=-1, timing=-1, sigma_y=s0, **base))
        frames.append(identification_rows(rmse(crlb[ref]), "rmse", figure="fig2", model="crlb", consensus="-",
                                          iteration=-1, timing=-1, sigma_y=s0, **base))
        # Fig. 3: trajectories of the first episodes
        E = min(s.figures.fig3_episodes, B)
        if E:
            names = [f"x{m + 1}" for m in range(truth.shape[-1])]
            series = {"truth": truth[:E]} | {m: out.estimates[m][ref, :E] for m in ("fg_identification", "ekf_fg",
                                                                                    "centralized_ekf")}
            for model, val in series.items():
                for m, pname in enumerate(names):
                    frames.append(identification_rows(val[..., m].cpu().numpy(), "estimate", figure="fig3",
                                                      model=model, consensus=CONSENSUS[model],
                                                      iteration=T if model != "truth" else -1, sigma_y=s0,
                                                      param=pname, **base))
        # Fig. 4: RMSE per timing; Fig. 5: RMSE vs sigma_y
        for m in MODELS:
            frames.append(identification_rows(rmse(err[m][ref], over_timings=False), "rmse", figure="fig4", model=m,
                                              consensus=CONSENSUS[m],
                                              iteration=T if m in ("fg_identification", "ekf_fg") else -1,
                                              sigma_y=s0, **base))
        frames.append(identification_rows(rmse(crlb[ref], over_timings=False), "rmse", figure="fig4", model="crlb",
                                          consensus="-", iteration=-1, sigma_y=s0, **base))
        for x in fig5_sigma_y:
            c = index[(x, T)]
            for m in MODELS:
                frames.append(identification_rows(rmse(err[m][c]), "rmse", figure="fig5", model=m,
                                                  consensus=CONSENSUS[m],
                                                  iteration=T if m in ("fg_identification", "ekf_fg") else -1,
                                                  timing=-1, sigma_y=x, **base))
            frames.append(identification_rows(rmse(crlb[c]), "rmse", figure="fig5", model="crlb", consensus="-",
                                              iteration=-1, timing=-1, sigma_y=x, **base))
        # diagnostics per configuration
        for (x, t), c in index.items():
            diag = {"near_zero_lambda": out.near_zero_lambda[c].double(), "precision_floor": out.floored[c].double(),
                    "iters_to_converge": out.iters_to_converge[c].double().mean(-1),
                    "unconverged_fraction": (out.iters_to_converge[c] > T).double().mean(-1),
                    "obs_var_mean": out.obs_var[c].mean(-1),
                    "gated_fraction": out.gated[c].double() / (K * M)}
            for metric, v in diag.items():
                frames.append(identification_rows(v.cpu().numpy(), metric, figure="diag", model="fg_identification",
                                                  consensus="gaussian_bp", iteration=t, timing=-1, sigma_y=x, **base))
        n_zero = int(out.near_zero_lambda.sum())
        n_floor = int(out.floored.sum())
        if n_zero or n_floor:
            warnings.warn(f"jiang_fg: {n_zero} near-zero Taylor slopes (sensor skipped for that parameter) and "
                          f"{n_floor} precision floors; see metric near_zero_lambda / precision_floor", stacklevel=2)
        # ablations: same data, other FG settings, at (sigma_y, max_iter)
        for name, (ab_settings, t_ab) in ablations.items():
            o = simulate(h, truth, noise, sig[ref:ref + 1], torch.tensor([t_ab], device=device), ab_settings)
            ab = dict(node=NODE, variant=name, figure="fig2", consensus="gaussian_bp", timing=-1, sigma_y=s0)
            o_err = squared_error(o.fg_iter_means, truth)
            for t in range(o_err.shape[0]):
                frames.append(identification_rows(rmse(o_err[t, 0]), "rmse", model="fg_identification",
                                                  iteration=t, **ab))
            e = squared_error(o.estimates["ekf_fg"][0], truth)
            frames.append(identification_rows(rmse(e), "rmse", model="ekf_fg", iteration=t_ab, **ab))
        frames.append(identification_rows(np.array([time.perf_counter() - t0]), "runtime_s", figure="diag",
                                          model="all", consensus="-", iteration=-1, timing=-1, sigma_y=float("nan"),
                                          **base))
        df = pd.concat(frames, ignore_index=True)
        df["param"] = df["param"].fillna("all") if "param" in df else "all"
        df["timing"] = df["timing"].astype(int)
        cols = ["figure", "variant", "model", "consensus", "node", "iteration", "timing", "sigma_y", "param",
                "metric", "episode", "value"]
        return df[cols + [c for c in df.columns if c not in cols]]
