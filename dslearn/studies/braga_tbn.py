r"""Study ``braga_tbn``: distributed online EM with RBPFs and consensus on sufficient statistics for
cooperative terrain-based navigation with unknown jump-Markov radar-altimeter noise (Braga et al.).

``run(cfg)`` simulates ``task.mc_runs`` Monte Carlo flights of the four-aircraft finger-four formation
(Section VI, Table I) and runs every strategy (non-cooperative, centralised, consensus_q) on the same
measurements. It returns a tidy DataFrame with

* run-level metrics (``time_s = -1``): ``pos_rms`` (steady-state window), ``pos_rms_first5s``, ``mu_rms``,
  ``sigma_rms``, ``pi_rms`` (steady-state window, over nodes and modes), ``throughput_kBps`` (Table II),
  ``pos_rms_worst_node`` (largest per-node steady-state position RMS), ``pos_err_max`` (largest position error
  of any node at any step), ``lost_nodes`` / ``lost_track`` (nodes / 0-1 flag with a steady-state position RMS
  above ``task.lost_track_m``), ``resample_rate``, ``degenerate_events``;
* time series (``time_s >= 0``, node-averaged): ``pos_se_t``, ``mu_se_t``, ``sigma_se_t``, ``pi_se_t``
  (squared errors averaged over nodes/modes) and the estimates ``mu_k``, ``sigma_k``, ``pi_kk`` for Fig. 4.

Every Monte Carlo run draws its truth and measurements from its own random stream (seed, run index) and its
filters from (seed, run index) (``task.filter_streams=common``: common random numbers for all strategies) or
(seed, run index, strategy) (``independent``), so a run's result never depends on ``task.mc_batch``,
``task.workers`` or the other runs and strategies (:mod:`dslearn.streams`).

The configuration is checked by :mod:`dslearn.schemas.braga_tbn` before ``run`` is called; the harness
(terrain, models, flights, filters) is :mod:`dslearn.learning.online_em`, Table II and Figs 3-6 are
:mod:`dslearn.reports.braga_tbn`, the lost-track diagnostics ``python -m dslearn.tools.tbn_trace``.
"""

from __future__ import annotations

import os
import time
import warnings

import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf

from dslearn.fusion.statistics import parse_strategy
from dslearn.learning.online_em import prepare_job, simulate_and_filter


def job_from_config(cfg: DictConfig) -> dict:
    """The Monte Carlo job (:func:`dslearn.learning.online_em.prepare_job`) of a checked configuration: its
    ``task`` as plain values with the root ``seed``, ``device``, ``dtype`` and ``progress``."""
    return prepare_job(OmegaConf.to_container(cfg.task, resolve=True), seed=int(cfg.seed), device=str(cfg.device),
                       dtype=str(cfg.dtype), progress=bool(cfg.get("progress") or False))


def _worker_init() -> None:
    torch.set_num_threads(1)


def _run_batch(job: dict, c0: int, nr: int) -> list[dict]:
    """Simulate and filter Monte Carlo runs c0..c0+nr-1 (one batch); returns the tidy rows."""
    p, truth = job["p"], job["truth"]
    dtype, rec_idx, rec_time, thr = job["dtype"], job["rec_idx"], job["rec_time"], job["thr"]
    strategies, k, steps, dt = p["strategies"], truth.k, p["steps"], p["dt"]
    n_ss = max(1, int(round(p["steady_state_s"] / dt)))
    frames = []
    scn, res = simulate_and_filter(job, list(range(c0, c0 + nr)))
    if res.counters["offmap_particles"]:
        warnings.warn(f"braga_tbn: {res.counters['offmap_particles']} particle positions fell outside the terrain "
                      "map (clamped to its border); enlarge task.terrain.size_m")
    mu_err = (res.mu - truth.mu) ** 2  # (T, R, C, S, K)
    sg_err = (res.sigma - truth.sigma) ** 2
    pi_err = (res.pi.diagonal(dim1=-2, dim2=-1) - truth.pi.diagonal()) ** 2
    ss = slice(steps - n_ss, steps)
    node_rms = res.pos_se[ss].mean(0).sqrt()  # (R, C, S) steady-state position RMS of every node
    scal = {
        "pos_rms": res.pos_se[ss].mean((0, 3)).sqrt(),
        "pos_rms_first5s": res.pos_se[: max(1, int(round(5.0 / dt)))].mean((0, 3)).sqrt(),
        "mu_rms": mu_err[ss].mean((0, 3, 4)).sqrt(),
        "sigma_rms": sg_err[ss].mean((0, 3, 4)).sqrt(),
        "pi_rms": pi_err[ss].mean((0, 3, 4)).sqrt(),
        "pos_rms_worst_node": node_rms.amax(-1),
        "pos_err_max": res.pos_se.amax((0, 3)).sqrt(),
        "lost_nodes": (node_rms > p["lost_track_m"]).sum(-1).to(dtype),
        "lost_track": (node_rms > p["lost_track_m"]).any(-1).to(dtype),
        "resample_rate": res.counters["resample_events"].to(dtype) / (steps * 4),
        "degenerate_events": res.counters["degenerate_events"].to(dtype),
    }  # each (R, C)
    series = {
        "pos_se_t": res.pos_se[rec_idx].mean(-1),
        "mu_se_t": mu_err[rec_idx].mean((-1, -2)),
        "sigma_se_t": sg_err[rec_idx].mean((-1, -2)),
        "pi_se_t": pi_err[rec_idx].mean((-1, -2)),
    }  # each (T_rec, R, C)
    for j in range(k):
        series[f"mu_{j + 1}"] = res.mu[rec_idx][..., j].mean(-1)
        series[f"sigma_{j + 1}"] = res.sigma[rec_idx][..., j].mean(-1)
        series[f"pi_{j + 1}{j + 1}"] = res.pi[rec_idx][..., j, j].mean(-1)
    for ci, sname in enumerate(strategies):
        kind, q = parse_strategy(sname)
        cons_name = {"noncooperative": "none", "centralised": "fusion_centre"}.get(kind, f"average_q{q}")
        for ri in range(nr):
            ep = c0 + ri
            rows = [(name, v[ri, ci].item()) for name, v in scal.items()]
            rows.append(("throughput_kBps", thr[sname]))
            for name, val in rows:
                frames.append({"episode": ep, "strategy": sname, "model": "rbpf_online_em", "consensus": cons_name,
                               "node": "avg", "time_s": -1.0, "metric": name, "value": float(val)})
            for name, v in series.items():
                vals = v[:, ri, ci].tolist()
                frames.extend({"episode": ep, "strategy": sname, "model": "rbpf_online_em",
                               "consensus": cons_name, "node": "avg", "time_s": round(ts, 6), "metric": name,
                               "value": float(val)} for ts, val in zip(rec_time, vals))
    return frames


def run(cfg: DictConfig) -> pd.DataFrame:
    """Run the study (see module docstring). Returns the tidy results table."""
    job = job_from_config(cfg)
    p, device = job["p"], torch.device(job["device"])
    frames = []
    t_start = time.perf_counter()
    batches = [(c0, min(p["mc_batch"], p["mc_runs"] - c0)) for c0 in range(0, p["mc_runs"], p["mc_batch"])]
    workers = min(p["workers"], len(batches)) if device.type == "cpu" else 1
    if workers <= 1:
        for c0, nr in batches:
            frames.extend(_run_batch(job, c0, nr))
    else:  # independent MC batches in worker processes (1 thread each); same seeds -> same results as serial
        import concurrent.futures as cf
        import multiprocessing as mp

        # glibc malloc settings for the workers only: keep freed MB-sized buffers in the heap instead of
        # returning them to the OS every step (fewer page faults; about 7 % faster). Not set if already set.
        env = {"MALLOC_MMAP_THRESHOLD_": str(1 << 30), "MALLOC_TRIM_THRESHOLD_": str(1 << 30)}
        env = {key: val for key, val in env.items() if key not in os.environ}
        os.environ.update(env)
        try:
            with cf.ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_worker_init) as ex:
                futs = [ex.submit(_run_batch, job, c0, nr) for c0, nr in batches]
                out = [f.result() for f in futs]  # collected in batch order
        except cf.process.BrokenProcessPool as exc:  # e.g. a __main__ script without the `if __name__` guard
            warnings.warn(f"braga_tbn: worker processes failed ({exc}); running the MC batches serially")
            out = [_run_batch(job, c0, nr) for c0, nr in batches]
        finally:
            for key in env:
                os.environ.pop(key, None)
        for rows in out:
            frames.extend(rows)
    elapsed = time.perf_counter() - t_start
    df = pd.DataFrame(frames)
    df.attrs["elapsed_s"] = elapsed
    df = pd.concat([df, pd.DataFrame([{"episode": -1, "strategy": "all", "model": "rbpf_online_em", "consensus": "-",
                                       "node": "avg", "time_s": -1.0, "metric": "wall_time_s",
                                       "value": float(elapsed)}])], ignore_index=True)
    return df
