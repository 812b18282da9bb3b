"""Study ``liu_dgpt``: distributed GP tracking (Liu et al., FUSION 2022), Tables I-II, Figs 5-7.

The protocol only: ``run(cfg)`` runs the grid (scenarios x noise levels x Monte Carlo runs, the
aggregation rules + the centralised standard GP) for one input type (``task.gp_input``) and
returns a tidy DataFrame. The configuration arrives checked (:mod:`dslearn.schemas.liu_dgpt`);
the methods, inputs and noise levels are the task's keys (``task.tracker``, ``task.aggregations``,
``task.gp_input``, ``task.noises``), the scenario generators are instantiated from
``task.scenario_params`` (``_target_``, ``_partial_``). Tracker: :mod:`dslearn.filters.dgpt`;
trajectories and measurements: :mod:`dslearn.sim.manoeuvres`; tables and figures:
:mod:`dslearn.reports.liu_dgpt`.
"""

from __future__ import annotations

import logging
import math
import struct
import time

import numpy as np
import pandas as pd
import torch

from dslearn.compose import build
from dslearn.filters.dgpt import HyperConfig, hyper_summary, track
from dslearn.schemas.base import to_plain
from dslearn.types import DTYPES
from dslearn.schemas.liu_dgpt import methods, selected_scenario
from dslearn.sim.manoeuvres import SCENARIOS, measure, sensor_field

TASK = "liu_dgpt"


def plan(cfg) -> dict:
    """The run's parameters from a checked config. The root ``scenario=s1|s2|s3`` narrows
    ``task.scenarios`` to that scenario; the methods are those of ``task.tracker``
    (:func:`~dslearn.schemas.liu_dgpt.methods`). A single-cell run traces (Figs 5-6) its own cell
    when ``task.trace``'s is not in it."""
    t = cfg.task
    sel = selected_scenario(cfg)
    scenarios = [sel] if sel is not None else [str(s) for s in t.scenarios]
    noises = [float(n) for n in t.noises]
    aggregations, centralised = methods(t)
    trace = {"scenario": str(t.trace.scenario), "noise": float(t.trace.noise), "episodes": int(t.trace.episodes)}
    if trace["scenario"] not in scenarios or not any(math.isclose(trace["noise"], n) for n in noises):
        trace["scenario"], trace["noise"] = scenarios[0], noises[0]
    p = {k: t[k] for k in ("gp_input", "mc_runs", "batch_runs", "num_sensors", "num_steps", "sensing_range",
                           "area_size", "dt", "ucb_delta", "normalise_beta", "grbcm_comm_points", "torch_threads")}
    p.update(scenarios=scenarios, noises=noises, aggregations=aggregations, centralised=centralised, trace=trace,
             window={s: int(t.window[s]) for s in scenarios}, hyper=HyperConfig(**to_plain(t.hyper)),
             generators={s: build(t.scenario_params[s], f"task.scenario_params.{s}") for s in scenarios})
    return p


def _episode_metrics(res, truth, avail, delta, tol=None):
    """Per-episode, per-method scalar metrics. Returns dict name -> (B, Mth) numpy arrays."""
    b, nm = res.upd_mean.shape[:2]
    T = truth.shape[1]
    det = avail.any(1)  # (B, T)
    first = torch.where(det.any(1), det.float().argmax(1), torch.full((b,), T, device=det.device))
    k = torch.arange(T, device=truth.device)
    ev = (k[None] > first[:, None])  # predictive estimate of k was made with data
    cov = ev & det
    ext = (truth.amax(1) - truth.amin(1)).clamp_min(1e-9)  # (B, 2)
    out = {}
    tr = truth[:, None]
    for kind, mean in (("updated", res.upd_mean), ("predictive", res.pred_mean)):
        se = (mean - tr) ** 2  # (B, M, T, 2)
        for name, msk in (("", ev), ("_covered", cov)):
            w = msk[:, None, :, None].to(se.dtype)
            rmse = ((se * w).sum(2) / w.sum(2).clamp_min(1)).sqrt()  # (B, M, 2)
            for c, ax in enumerate("xy"):
                out[f"rmse_{ax}_{kind}{name}"] = rmse[..., c]
                out[f"nrmse_{ax}_{kind}{name}"] = rmse[..., c] / ext[:, None, c]
    w = ev[:, None, :, None].to(truth.dtype)
    n = w.sum((2, 3)).clamp_min(1) * 2
    err_u = (res.upd_mean - tr).abs()
    err_p = (res.pred_mean - tr).abs()
    out["ucb_coverage"] = ((err_u <= res.upd_bound).to(w.dtype) * w).sum((2, 3)) / n
    out["ucb_coverage_predictive"] = ((err_p <= res.pred_bound).to(w.dtype) * w).sum((2, 3)) / n
    out["ucb_mean_bound"] = (res.upd_bound * w).sum((2, 3)) / n
    out["coverage_3sigma"] = ((err_u <= 3 * res.upd_var.sqrt()).to(w.dtype) * w).sum((2, 3)) / n
    out["coverage_3sigma_predictive"] = ((err_p <= 3 * res.pred_var.sqrt()).to(w.dtype) * w).sum((2, 3)) / n
    evf = ev.to(truth.dtype)
    frac = (det.to(truth.dtype) * evf).sum(1) / evf.sum(1).clamp_min(1)
    out["frac_steps_detected"] = frac[:, None].expand(b, nm)
    out["mean_experts"] = ((res.n_experts.to(truth.dtype) * evf).sum(1) / evf.sum(1).clamp_min(1))[:, None].expand(b, nm)
    out["ucb_nominal"] = torch.full((b, nm), 1.0 - delta, dtype=truth.dtype)
    out.update(hyper_summary(res, tol))
    return {k_: v.detach().cpu().numpy() for k_, v in out.items()}


def _method_keys(methods):
    model = ["standard_gp" if m == "standard_gp" else "dgpt" for m in methods]
    cons = ["-" if m == "standard_gp" else m for m in methods]
    return model, cons


def run(cfg) -> pd.DataFrame:
    """Run the DGPT study grid of ``cfg`` (checked by :func:`dslearn.schemas.validate_task`)."""
    p = plan(cfg)
    dtype = DTYPES[str(cfg.get("dtype", "float64"))]
    old_threads = torch.get_num_threads()
    if p["torch_threads"] is not None:
        torch.set_num_threads(p["torch_threads"])
    try:
        return _run(p, int(cfg.get("seed", 0)), torch.device(str(cfg.get("device", "cpu"))), dtype,
                    bool(cfg.get("progress", False)))
    finally:
        torch.set_num_threads(old_threads)


def _stream_key(seed: int, *key: int) -> int:
    """A 63-bit seed for the random stream named by ``key`` (numpy ``SeedSequence``)."""
    ss = np.random.SeedSequence(entropy=int(seed) % 2 ** 64, spawn_key=tuple(int(k) for k in key))
    return int(ss.generate_state(1, np.uint64)[0] >> np.uint64(1))


def _float_key(x: float) -> int:
    return struct.unpack("<Q", struct.pack("<d", float(x)))[0]


def episodes(p, seed):
    """Trajectories, sensors and measurements of the grid, one random stream per episode.

    Stream keys (``seed`` + key): (0, scenario, run) -> trajectory, then sensor field (shared by
    the noise levels of a run: common random numbers); (1, scenario, run, sigma) -> measurement
    noise; (2, scenario, run, sigma) -> the episode key of grBCM's draws. ``scenario`` is the index
    in :data:`SCENARIOS` and ``run`` the MC-run index, so an episode does not depend on which
    other scenarios, noise levels or runs are part of the job, nor on ``task.mc_runs``.

    Returns:
        truth (E, T, 2), meas (E, S, T, 2), avail (E, S, T), window (E,), episode keys (E,),
        keys [(scenario, sigma, run)] of the E episodes.
    """
    R, T = p["mc_runs"], p["num_steps"]
    truth_l, meas_l, av_l, win_l, ek_l, keys = [], [], [], [], [], []
    for s in p["scenarios"]:
        si = SCENARIOS.index(s)
        pos, sens = [], []
        for r in range(R):
            g = torch.Generator().manual_seed(_stream_key(seed, 0, si, r))
            pos.append(p["generators"][s](1, T, g, dt=p["dt"], dtype=torch.float64)[0])
            sens.append(sensor_field(1, p["num_sensors"], p["area_size"], g))
        for nz in p["noises"]:
            for r in range(R):
                g = torch.Generator().manual_seed(_stream_key(seed, 1, si, r, _float_key(nz)))
                z, av = measure(pos[r], sens[r], p["sensing_range"],
                                torch.full((1,), nz, dtype=torch.float64), g)
                truth_l.append(pos[r])
                meas_l.append(z)
                av_l.append(av)
                ek_l.append(_stream_key(seed, 2, si, r, _float_key(nz)))
                keys.append((s, nz, r))
            win_l.append(torch.full((R,), p["window"][s], dtype=torch.long))
    return (torch.cat(truth_l), torch.cat(meas_l), torch.cat(av_l), torch.cat(win_l),
            torch.tensor(ek_l, dtype=torch.long), keys)


def _run(p, seed, device, dtype, progress):
    t0 = time.time()
    R = p["mc_runs"]
    truth, meas, avail, window, ekeys, keys = episodes(p, seed)
    run_idx = torch.tensor([k[2] for k in keys])

    frames = []
    n_jitter = 0
    for c0 in range(0, R, p["batch_runs"]):
        sel = torch.nonzero((run_idx >= c0) & (run_idx < c0 + p["batch_runs"]))[:, 0]
        tr = truth[sel].to(device=device, dtype=dtype)
        res = track(meas[sel].to(device=device, dtype=dtype), avail[sel].to(device), window[sel],
                    gp_input=p["gp_input"], aggregations=p["aggregations"],
                    centralised=p["centralised"], hyper=p["hyper"], dt=p["dt"],
                    delta=p["ucb_delta"], normalise_beta=p["normalise_beta"], progress=progress,
                    grbcm_comm_points=p["grbcm_comm_points"], episode_keys=ekeys[sel])
        n_jitter += res.n_jitter
        av = avail[sel].to(device)
        met = _episode_metrics(res, tr, av, p["ucb_delta"],
                               p["hyper"].tol if p["hyper"].optimizer == "newton" else None)
        model, cons = _method_keys(res.methods)
        nb, nm = len(sel), len(res.methods)
        kk = [keys[i] for i in sel.tolist()]
        base = pd.DataFrame({
            "scenario": np.repeat([k[0] for k in kk], nm),
            "noise": np.repeat([k[1] for k in kk], nm),
            "episode": np.repeat([k[2] for k in kk], nm),
            "model": np.tile(model, nb),
            "consensus": np.tile(cons, nb),
        })
        for name, arr in met.items():
            f = base.copy()
            f["metric"] = name
            f["value"] = arr.reshape(-1).astype(float)
            frames.append(f)
        trace = _traces(p, res, tr, av, kk, model, cons)
        if trace is not None:
            frames.append(trace)
    df = pd.concat(frames, ignore_index=True)
    df["node"] = "fusion"
    df["gp_input"] = p["gp_input"]
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


def _traces(p, res, truth, avail, kk, model, cons):
    """Per-step rows (step >= 0) for Figs 5-6: first ``trace.episodes`` of one scenario/noise."""
    tr = p["trace"]
    rows = []
    T = truth.shape[1]
    ndet = avail.sum(1)  # (B, T)
    for i, (s, nz, r) in enumerate(kk):
        if s != tr["scenario"] or not math.isclose(nz, tr["noise"]) or r >= tr["episodes"]:
            continue
        for m in range(len(model)):
            series = {
                "trace_true_x": truth[i, :, 0], "trace_true_y": truth[i, :, 1],
                "trace_upd_x": res.upd_mean[i, m, :, 0], "trace_upd_y": res.upd_mean[i, m, :, 1],
                "trace_std_x": res.upd_var[i, m, :, 0].sqrt(), "trace_std_y": res.upd_var[i, m, :, 1].sqrt(),
                "trace_pred_x": res.pred_mean[i, m, :, 0], "trace_pred_y": res.pred_mean[i, m, :, 1],
                "trace_ucb_x": res.upd_bound[i, m, :, 0], "trace_ucb_y": res.upd_bound[i, m, :, 1],
                "trace_detections": ndet[i].to(truth.dtype),
            }
            for name, v in series.items():
                rows.append(pd.DataFrame({
                    "scenario": s, "noise": nz, "episode": r, "model": model[m],
                    "consensus": cons[m], "step": np.arange(T), "metric": name,
                    "value": v.detach().cpu().numpy().astype(float)}))
    if not rows:
        return None
    return pd.concat(rows, ignore_index=True)
