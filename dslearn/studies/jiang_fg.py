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
so its rows do not depend on ``task.mc_runs``.

``rmse`` rows hold one episode's root-mean-square error per parameter (mean over the M
parameters and, where ``timing = -1``, over all timings). The report pools episodes as
``sqrt(mean(rmse^2))`` (the Monte Carlo RMSE); ``summary.csv``'s ``mean`` is the plain mean.
The CRLB rows hold ``sqrt(tr F^{-1} / M)`` at the true state (Eq. 27), the same units.

The configuration is checked by :mod:`dslearn.schemas.jiang_fg` before ``run`` is called; the
engine is :mod:`dslearn.learning.factor_graph.engine`, the figures :mod:`dslearn.reports.jiang_fg`.
"""

from __future__ import annotations

import time
import warnings

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig

from dslearn.learning.factor_graph.engine import TrackerSettings, simulate
from dslearn.schemas.base import to_plain
from dslearn.schemas.jiang_fg import MAIN_VARIANT as MAIN, ablation_values
from dslearn.sim.squared_range import SquaredRange, polynomial_trajectory, run_noise

MODELS = ("fg_identification", "ekf_fg", "centralized_gn", "centralized_ekf")
CONSENSUS = {"fg_identification": "gaussian_bp", "ekf_fg": "gaussian_bp", "centralized_gn": "centralized",
             "centralized_ekf": "centralized", "crlb": "-", "truth": "-"}
NODE = "fusion_center"


def _params(t) -> dict:
    """Plain values of the checked ``cfg.task``: the main grid's settings and each ablation's."""
    p = {k: t[k] for k in ("mc_runs", "num_samples", "max_iter")} | {"sigma_y": float(t.sigma_y)}
    sc, figs = to_plain(t.scenario), to_plain(t.figures)
    p.update(sensors=sc["sensors"], coefficients=sc["coefficients"], drive_var=float(sc["drive_var"]),
             num_timings=sc["num_timings"], fig2_iterations=sorted(set(figs["fig2_iterations"])),
             fig3_episodes=figs["fig3_episodes"], fig5_sigma_y=[float(s) for s in figs["fig5_sigma_y"]])
    p["settings"] = dict(num_samples=t.num_samples, initial_state=sc["initial_state"], baseline_iters=t.baseline_iters,
                         **to_plain(t.fg), **to_plain(t.tracker))
    p["ablations"] = {}
    for name, node in t.ablations.items():
        over = ablation_values(str(name), node)
        its = over.pop("max_iter", p["max_iter"])
        p["ablations"][str(name)] = ({**p["settings"], **over}, its)
    return p


# ----------------------------------------------------------------------------- rows
def _rows(values: np.ndarray, metric: str, **keys) -> pd.DataFrame:
    """Tidy rows from ``values (B,)`` (episode-indexed) or ``(B, K)`` (episode x timing)."""
    values = np.asarray(values, dtype=float)
    B = values.shape[0]
    if values.ndim == 1:
        df = pd.DataFrame({"episode": np.arange(B), "value": values})
    else:
        K = values.shape[1]
        df = pd.DataFrame({"episode": np.repeat(np.arange(B), K), "timing": np.tile(np.arange(1, K + 1), B),
                           "value": values.reshape(-1)})
    df["metric"] = metric
    for k, v in keys.items():
        df[k] = v
    return df


def _rmse(sq: torch.Tensor) -> np.ndarray:
    return sq.sqrt().cpu().numpy()


def run(cfg: DictConfig) -> pd.DataFrame:
    """Run every figure's grid of the study; returns the tidy results table."""
    p = _params(cfg.task)
    device, dtype, seed = torch.device(str(cfg.device)), getattr(torch, str(cfg.dtype)), int(cfg.seed)
    t0 = time.perf_counter()

    B, K, L = p["mc_runs"], p["num_timings"], p["num_samples"]
    sensors = torch.tensor(p["sensors"], dtype=dtype, device=device)
    h = SquaredRange(sensors)
    N, M = sensors.shape
    # every Monte Carlo run r draws from its own stream seeded by (seed, r): its numbers do not
    # depend on mc_runs or on the other runs; all configurations share them (common random numbers)
    drive, noise = run_noise(seed, range(B), K, M, N, L, dtype=dtype, device=device)
    truth = polynomial_trajectory(torch.tensor(p["coefficients"], dtype=dtype, device=device), K, p["drive_var"],
                                  noise=drive)

    # configuration grid: (sigma_y, iterations) -- fig2 varies t, fig5 varies sigma_y
    T, s0 = p["max_iter"], p["sigma_y"]
    grid = sorted({(s0, t) for t in p["fig2_iterations"]} | {(s, T) for s in p["fig5_sigma_y"]} | {(s0, T)})
    index = {g: i for i, g in enumerate(grid)}
    sig = torch.tensor([g[0] for g in grid], dtype=dtype, device=device)
    its = torch.tensor([g[1] for g in grid], device=device)
    out = simulate(h, truth, noise, sig, its, TrackerSettings.from_config(**p["settings"]))

    frames = []
    base = dict(node=NODE, variant=MAIN)
    err = {m: (out.estimates[m] - truth).square().mean(-1) for m in MODELS}  # (C, B, K)
    crlb = out.crlb_truth                                                     # (C, B, K)
    ref = index[(s0, T)]
    # Fig. 2: identification RMSE vs iteration (within the T-iteration run), tracker vs its iteration count
    for t in range(out.fg_iter_sqerr.shape[0]):
        frames.append(_rows(_rmse(out.fg_iter_sqerr[t, ref].mean(-1)), "rmse", figure="fig2",
                            model="fg_identification", consensus="gaussian_bp", iteration=t, timing=-1,
                            sigma_y=s0, **base))
    for t in p["fig2_iterations"]:
        frames.append(_rows(_rmse(err["ekf_fg"][index[(s0, t)]].mean(-1)), "rmse", figure="fig2", model="ekf_fg",
                            consensus="gaussian_bp", iteration=t, timing=-1, sigma_y=s0, **base))
    for m in ("centralized_gn", "centralized_ekf"):
        frames.append(_rows(_rmse(err[m][ref].mean(-1)), "rmse", figure="fig2", model=m, consensus="centralized",
                            iteration=-1, timing=-1, sigma_y=s0, **base))
    frames.append(_rows(_rmse(crlb[ref].mean(-1)), "rmse", figure="fig2", model="crlb", consensus="-",
                        iteration=-1, timing=-1, sigma_y=s0, **base))
    # Fig. 3: trajectories of the first episodes
    E = min(p["fig3_episodes"], B)
    if E:
        names = [f"x{m + 1}" for m in range(truth.shape[-1])]
        series = {"truth": truth[:E]} | {m: out.estimates[m][ref, :E] for m in ("fg_identification", "ekf_fg",
                                                                                "centralized_ekf")}
        for model, val in series.items():
            for m, pname in enumerate(names):
                frames.append(_rows(val[..., m].cpu().numpy(), "estimate", figure="fig3", model=model,
                                    consensus=CONSENSUS[model], iteration=T if model != "truth" else -1,
                                    sigma_y=s0, param=pname, **base))
    # Fig. 4: RMSE per timing; Fig. 5: RMSE vs sigma_y
    for m in MODELS:
        frames.append(_rows(_rmse(err[m][ref]), "rmse", figure="fig4", model=m, consensus=CONSENSUS[m],
                            iteration=T if m in ("fg_identification", "ekf_fg") else -1, sigma_y=s0, **base))
    frames.append(_rows(_rmse(crlb[ref]), "rmse", figure="fig4", model="crlb", consensus="-", iteration=-1,
                        sigma_y=s0, **base))
    for s in p["fig5_sigma_y"]:
        c = index[(s, T)]
        for m in MODELS:
            frames.append(_rows(_rmse(err[m][c].mean(-1)), "rmse", figure="fig5", model=m, consensus=CONSENSUS[m],
                                iteration=T if m in ("fg_identification", "ekf_fg") else -1, timing=-1,
                                sigma_y=s, **base))
        frames.append(_rows(_rmse(crlb[c].mean(-1)), "rmse", figure="fig5", model="crlb", consensus="-",
                            iteration=-1, timing=-1, sigma_y=s, **base))
    # diagnostics per configuration
    for (s, t), c in index.items():
        diag = {"near_zero_lambda": out.near_zero_lambda[c].double(), "precision_floor": out.floored[c].double(),
                "iters_to_converge": out.iters_to_converge[c].double().mean(-1),
                "unconverged_fraction": (out.iters_to_converge[c] > T).double().mean(-1),
                "obs_var_mean": out.obs_var[c].mean(-1),
                "gated_fraction": out.gated[c].double() / (K * M)}
        for metric, v in diag.items():
            frames.append(_rows(v.cpu().numpy(), metric, figure="diag", model="fg_identification",
                                consensus="gaussian_bp", iteration=t, timing=-1, sigma_y=s, **base))
    n_zero = int(out.near_zero_lambda.sum())
    n_floor = int(out.floored.sum())
    if n_zero or n_floor:
        warnings.warn(f"jiang_fg: {n_zero} near-zero Taylor slopes (sensor skipped for that parameter) and "
                      f"{n_floor} precision floors; see metric near_zero_lambda / precision_floor", stacklevel=2)
    # ablations: same data, other FG settings, at (sigma_y, max_iter)
    for name, (over, t_ab) in p["ablations"].items():
        o = simulate(h, truth, noise, sig[ref:ref + 1], torch.tensor([t_ab], device=device), TrackerSettings.from_config(**over))
        ab = dict(node=NODE, variant=name, figure="fig2", consensus="gaussian_bp", timing=-1, sigma_y=s0)
        for t in range(o.fg_iter_sqerr.shape[0]):
            frames.append(_rows(_rmse(o.fg_iter_sqerr[t, 0].mean(-1)), "rmse", model="fg_identification",
                                iteration=t, **ab))
        e = (o.estimates["ekf_fg"][0] - truth).square().mean(-1)
        frames.append(_rows(_rmse(e.mean(-1)), "rmse", model="ekf_fg", iteration=t_ab, **ab))
    frames.append(_rows(np.array([time.perf_counter() - t0]), "runtime_s", figure="diag", model="all",
                        consensus="-", iteration=-1, timing=-1, sigma_y=float("nan"), **base))
    df = pd.concat(frames, ignore_index=True)
    df["param"] = df["param"].fillna("all") if "param" in df else "all"
    df["timing"] = df["timing"].astype(int)
    cols = ["figure", "variant", "model", "consensus", "node", "iteration", "timing", "sigma_y", "param",
            "metric", "episode", "value"]
    return df[cols + [c for c in df.columns if c not in cols]]
