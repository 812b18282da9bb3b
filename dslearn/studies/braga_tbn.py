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
``task.workers`` or the other runs and strategies (:mod:`dslearn.streams`). ``trace_runs(cfg, episodes)``
re-runs any subset of runs with per-step diagnostics for lost-track analysis.

``report(...)`` writes Table II (``braga_tbn_table2.md/.csv``) and Figs 3-6 as PNGs.
"""

from __future__ import annotations

import math
import os
import time
import warnings
from pathlib import Path

import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf

from dslearn.config_schema import CONF_DIR
from dslearn.errors import ConfigError, check_choice, check_positive
from dslearn.fusion.statistics import (
    network_adjacency,
    parse_strategy,
    throughput_bytes_per_step,
    weight_matrix,
)
from dslearn.models.jmnls import make_params, params_dim, stats_dim
from dslearn.streams import Streams
from dslearn.learning.online_em import run_tbn
from dslearn.sim.terrain import Scenario, cv_model, make_terrain, simulate

PAPER_THROUGHPUT = {"noncooperative": 0.0, "centralised": 4.5, "consensus_1": 4.7, "consensus_5": 23.5,
                    "consensus_10": 46.9}


def _get(cfg, path, default=None):
    v = OmegaConf.select(cfg, path, default=default)
    return OmegaConf.to_container(v, resolve=True) if OmegaConf.is_config(v) else v


def _validate(cfg: DictConfig) -> dict:
    """Validate ``cfg.task`` and return plain values. Raises ConfigError before any work starts."""
    t = cfg.task
    p = {}
    for key in ("mc_runs", "mc_batch", "num_particles", "steps"):
        v = _get(cfg, f"task.{key}")
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise ConfigError(f"task.{key}={v!r} must be a positive integer")
        p[key] = v
    w = _get(cfg, "task.workers", 1)
    if not isinstance(w, int) or isinstance(w, bool) or w < 1:
        raise ConfigError(f"task.workers={w!r} must be a positive integer (worker processes for the MC batches)")
    p["workers"] = w
    for key in ("dt", "process_noise", "formation_spacing", "steady_state_s"):
        check_positive(f"task.{key}", _get(cfg, f"task.{key}"))
        p[key] = float(_get(cfg, f"task.{key}"))
    check_positive("task.truth_process_noise", _get(cfg, "task.truth_process_noise"), strict=False)
    p["truth_process_noise"] = float(_get(cfg, "task.truth_process_noise"))
    for key in ("v0", "start"):
        v = _get(cfg, f"task.{key}")
        if not (isinstance(v, list) and len(v) == 2):
            raise ConfigError(f"task.{key}={v!r} must be a list [X, Y]")
        p[key] = [float(a) for a in v]
    m = _get(cfg, "task.modes")
    for key in ("mu_true", "sigma_true", "pi_true", "mu_init", "sigma_init", "pi_init"):
        if m is None or key not in m:
            raise ConfigError(f"task.modes.{key} is required")
    p["truth"] = make_params(m["mu_true"], m["sigma_true"], m["pi_true"], prefix="task.modes (true: mu_true/sigma_true/pi_true)")
    p["init"] = make_params(m["mu_init"], m["sigma_init"], m["pi_init"], prefix="task.modes (initial: mu_init/sigma_init/pi_init)")
    if p["truth"].k != p["init"].k:
        raise ConfigError(f"task.modes: K mismatch between the true parameters (K={p['truth'].k}) and the initial "
                          f"guess (K={p['init'].k})")
    em = _get(cfg, "task.em", {}) or {}
    check_positive("task.em.eta_exponent", em.get("eta_exponent", 0.7))
    ex = float(em.get("eta_exponent", 0.7))
    if not 0.5 < ex <= 1.0:
        raise ConfigError(f"task.em.eta_exponent={ex} must lie in (0.5, 1] (stochastic-approximation conditions)")
    p["eta_exponent"] = ex
    bi = em.get("burn_in", 50)
    if not isinstance(bi, int) or bi < 0:
        raise ConfigError(f"task.em.burn_in={bi!r} must be a non-negative integer")
    p["burn_in"] = bi
    check_positive("task.em.sigma_floor", em.get("sigma_floor", 1e-3))
    p["sigma_floor"] = float(em.get("sigma_floor", 1e-3))
    init_mode = em.get("init_mode", "true")
    init_mode = "true" if init_mode is True else init_mode  # `init_mode=true` on the command line is a bool
    check_choice("task.em.init_mode", init_mode, ["true", "uniform"])
    p["init_mode"] = init_mode
    ess = float(_get(cfg, "task.ess_threshold", 0.5))
    if not 0.0 <= ess <= 1.0:
        raise ConfigError(f"task.ess_threshold={ess} must lie in [0, 1] (fraction of N_P)")
    p["ess_threshold"] = ess
    bk = _get(cfg, "task.backward_kernel", {}) or {}
    check_positive("task.backward_kernel.jitter_pos", bk.get("jitter_pos", 1.0))
    check_positive("task.backward_kernel.jitter_vel", bk.get("jitter_vel", 0.0), strict=False)
    p["jitter"] = (float(bk.get("jitter_pos", 1.0)), float(bk.get("jitter_vel", 0.0)))
    check_choice("task.backward_kernel.dtype", bk.get("dtype", None), [None, "float32", "float64"])
    p["kernel_dtype"] = {None: None, "float32": torch.float32, "float64": torch.float64}[bk.get("dtype", None)]
    tr = _get(cfg, "task.terrain", {}) or {}
    for key, dflt in (("size_m", 25000.0), ("resolution_m", 25.0), ("smoothing_m", 250.0), ("elevation_std_m", 100.0)):
        check_positive(f"task.terrain.{key}", tr.get(key, dflt))
    p["terrain"] = dict(size_m=float(tr.get("size_m", 25000.0)), resolution_m=float(tr.get("resolution_m", 25.0)),
                        smoothing_m=float(tr.get("smoothing_m", 250.0)),
                        elevation_std_m=float(tr.get("elevation_std_m", 100.0)),
                        mean_elevation_m=float(tr.get("mean_elevation_m", 500.0)))
    p["terrain_seed_offset"] = int(tr.get("seed_offset", 0))
    if p["terrain"]["resolution_m"] * 4 > p["terrain"]["size_m"]:
        raise ConfigError("task.terrain.resolution_m must be much smaller than task.terrain.size_m")
    net = _get(cfg, "task.network", {}) or {}
    edges = net.get("edges", [[0, 1], [0, 2], [2, 3]])
    p["adj"] = network_adjacency(4, edges)  # finger four: 4 aircraft
    fc = net.get("fusion_centre", 0)
    if not isinstance(fc, int) or not 0 <= fc < 4:
        raise ConfigError(f"task.network.fusion_centre={fc!r} must be a node index in 0..3")
    p["fusion_centre"] = fc
    cons = _get(cfg, "task.consensus", {}) or {}
    p["weights"] = weight_matrix(p["adj"], cons.get("weights", "max_degree"), cons.get("matrix", None))
    strategies = _get(cfg, "task.strategies")
    if not isinstance(strategies, list) or not strategies:
        raise ConfigError("task.strategies must be a non-empty list, e.g. [noncooperative, centralised, consensus_10]")
    for sname in strategies:
        parse_strategy(sname)
    if len(set(strategies)) != len(strategies):
        raise ConfigError(f"task.strategies={strategies} has duplicates")
    p["strategies"] = strategies
    p["bytes_per_float"] = int(_get(cfg, "task.bytes_per_float", 4))
    check_positive("task.bytes_per_float", p["bytes_per_float"])
    p["kilobyte"] = int(_get(cfg, "task.kilobyte", 1024))
    check_choice("task.kilobyte", p["kilobyte"], [1000, 1024])
    p["regularise"] = float(_get(cfg, "task.resampling.regularise", 0.0))
    check_positive("task.resampling.regularise", p["regularise"], strict=False)
    p["filter_streams"] = _get(cfg, "task.filter_streams", "common")
    check_choice("task.filter_streams", p["filter_streams"], ["common", "independent"])
    p["lost_track_m"] = float(_get(cfg, "task.lost_track_m", 15.0))
    check_positive("task.lost_track_m", p["lost_track_m"])
    p["record_every"] = int(_get(cfg, "task.record_every", 10))
    check_positive("task.record_every", p["record_every"])
    p["zoom_s"] = float(_get(cfg, "task.zoom_s", 5.0))
    check_positive("task.zoom_s", p["zoom_s"], strict=False)
    if p["steady_state_s"] > p["steps"] * p["dt"]:
        raise ConfigError(f"task.steady_state_s={p['steady_state_s']} exceeds the flight duration "
                          f"{p['steps'] * p['dt']} s")
    check_choice("device", _get(cfg, "device", "cpu"), ["cpu", "cuda"])
    check_choice("dtype", _get(cfg, "dtype", "float64"), ["float64", "float32"])
    return p


def _worker_init() -> None:
    torch.set_num_threads(1)


def _simulate_and_filter(job: dict, episodes: list[int], diagnostics: bool = False, nodes: list[int] | None = None):
    """Truth, measurements and all strategies' filters for the Monte Carlo runs ``episodes`` (one batch).
    ``nodes``: filter only these aircraft (non-cooperative strategies only; for diagnosis)."""
    p, terrain, truth, truth_dyn, filt_dyn = job["p"], job["terrain"], job["truth"], job["truth_dyn"], job["filt_dyn"]
    seed, device, strategies = job["seed"], torch.device(job["device"]), p["strategies"]
    nr = len(episodes)
    # independent Monte Carlo runs: run `ep` draws its truth and measurements from the stream (seed, "truth", ep)
    # and each strategy's filter from (seed, "filter", ep) (task.filter_streams=common: every strategy its own
    # generator with that same seed, i.e. common random numbers) or (seed, "filter", ep, strategy) (independent),
    # whatever the batch, worker or strategy list
    common = p["filter_streams"] == "common"
    truth_gen = Streams.from_keys([(seed, "truth", ep) for ep in episodes], (nr,), device=device)
    filt_gen = Streams.from_keys([(seed, "filter", ep) if common else (seed, "filter", ep, sname)
                                  for ep in episodes for sname in strategies], (nr, len(strategies)), device=device)
    scn = simulate(terrain, truth, truth_dyn, runs=nr, start=torch.tensor(p["start"]), v0=torch.tensor(p["v0"]),
                   spacing=p["formation_spacing"], steps=p["steps"], gen=truth_gen)
    weights = p["weights"]
    if nodes is not None:
        if any(parse_strategy(sn)[0] != "noncooperative" for sn in strategies):
            raise ConfigError("filtering a subset of the nodes needs task.strategies=[noncooperative] (the other "
                              "strategies need the whole network)")
        idx = torch.tensor(nodes, device=scn.x.device)
        scn = Scenario(scn.x[:, idx], scn.r[:, idx], scn.y[:, idx], scn.terrain)
        weights = torch.eye(len(nodes), dtype=weights.dtype)
    res = run_tbn(scn, strategies, weights, p["init"], filt_dyn, num_particles=p["num_particles"], gen=filt_gen,
                  burn_in=p["burn_in"], progress=job["progress"], diagnostics=diagnostics, **_filter_kwargs(p))
    return scn, res


def _filter_kwargs(p: dict) -> dict:
    """The filter / EM options of :func:`dslearn.learning.online_em.run_tbn` from the validated config."""
    return dict(eta_exponent=p["eta_exponent"], ess_threshold=p["ess_threshold"], sigma_floor=p["sigma_floor"],
                init_mode=p["init_mode"], regularise=p["regularise"])


def _run_batch(job: dict, c0: int, nr: int) -> list[dict]:
    """Simulate and filter Monte Carlo runs c0..c0+nr-1 (one batch); returns the tidy rows."""
    p, truth = job["p"], job["truth"]
    dtype, rec_idx, rec_time, thr = job["dtype"], job["rec_idx"], job["rec_time"], job["thr"]
    strategies, k, steps, dt = p["strategies"], truth.k, p["steps"], p["dt"]
    n_ss = max(1, int(round(p["steady_state_s"] / dt)))
    frames = []
    scn, res = _simulate_and_filter(job, list(range(c0, c0 + nr)))
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


def _setup(cfg: DictConfig) -> dict:
    """Validate the config and build everything the MC batches share (terrain, models, recording grid)."""
    p = _validate(cfg)
    device = torch.device(_get(cfg, "device", "cpu"))
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device=cuda but CUDA is not available")
    dtype = {"float64": torch.float64, "float32": torch.float32}[_get(cfg, "dtype", "float64")]
    seed = int(_get(cfg, "seed", 0))
    progress = bool(_get(cfg, "progress", False))
    kw = dict(dtype=dtype, device=device)

    tgen = torch.Generator(device=device).manual_seed(seed * 7919 + p["terrain_seed_offset"] + 17)
    terrain = make_terrain(**p["terrain"], gen=tgen, **kw)
    truth = p["truth"]
    truth = type(truth)(truth.mu.to(**kw), truth.sigma.to(**kw), truth.pi.to(**kw))
    truth_dyn = cv_model(p["dt"], max(p["truth_process_noise"], 1e-12), p["jitter"], **kw)
    filt_dyn = cv_model(p["dt"], p["process_noise"], p["jitter"], kernel_dtype=p["kernel_dtype"], **kw)
    k = truth.k
    steps, dt = p["steps"], p["dt"]
    n_zoom = int(round(p["zoom_s"] / dt))
    rec = [t for t in range(1, steps + 1) if t <= n_zoom or t % p["record_every"] == 0]
    rec_idx = torch.tensor([t - 1 for t in rec], device=device)
    rec_time = [t * dt for t in rec]
    thr = {}
    for sname in p["strategies"]:
        b = throughput_bytes_per_step(sname, p["adj"], stats_dim(k), params_dim(k), fusion_centre=p["fusion_centre"],
                                      bytes_per_float=p["bytes_per_float"])
        thr[sname] = b / dt / p["kilobyte"]
    return dict(p=p, terrain=terrain, truth=truth, truth_dyn=truth_dyn, filt_dyn=filt_dyn, seed=seed,
                device=str(device), dtype=dtype, rec_idx=rec_idx, rec_time=rec_time, thr=thr, progress=progress)


def trace_runs(cfg: DictConfig, episodes, diagnostics: bool = True, nodes: list[int] | None = None):
    """Simulate and filter the given Monte Carlo runs (any subset, any order: each run's result depends only on
    (seed, run index, strategy)) and return ``(scenario, TBNResult)`` with the per-step diagnostics of
    :func:`dslearn.learning.online_em.run_tbn` (ESS, particle spread, velocity error, ...) for lost-track analysis.
    ``nodes``: filter only these aircraft (noncooperative only); the scenario is restricted to them."""
    job = _setup(cfg)
    return _simulate_and_filter(job, list(episodes), diagnostics=diagnostics, nodes=nodes)


def terrain_gradient(scn: Scenario, step_m: float = 5.0) -> torch.Tensor:
    """|grad h| of the map at the true positions by central differences. -> (R, S, T) (t = 1..T)."""
    p = scn.x[..., 1:, :2]
    ex = torch.tensor([step_m, 0.0], dtype=p.dtype, device=p.device)
    ey = torch.tensor([0.0, step_m], dtype=p.dtype, device=p.device)
    h = scn.terrain
    gx = (h(p + ex) - h(p - ex)) / (2 * step_m)
    gy = (h(p + ey) - h(p - ey)) / (2 * step_m)
    return torch.sqrt(gx * gx + gy * gy)


def _screen_chunk(cfg_yaml: str, episodes: list[int], nodes: list[int] | None) -> list[tuple]:
    torch.set_num_threads(1)
    cfg = OmegaConf.create(cfg_yaml)
    job = _setup(cfg)
    p, truth = job["p"], job["truth"]
    scn, res = _simulate_and_filter(job, episodes, nodes=nodes)
    n_ss = max(1, int(round(p["steady_state_s"] / p["dt"])))
    node_rms = res.pos_se[-n_ss:].mean(0).sqrt()  # (R, C, S)
    err_max = res.pos_se.amax(0).sqrt()
    mu = (res.mu[-n_ss:] - truth.mu).pow(2).mean((0, -1)).sqrt()  # (R, C, S) per-node mu RMS
    out = []
    for ri, ep in enumerate(episodes):
        for ci, sname in enumerate(p["strategies"]):
            out.append((ep, sname, node_rms[ri, ci].tolist(), err_max[ri, ci].tolist(), mu[ri, ci].tolist()))
    return out


def screen_lost_tracks(cfg: DictConfig, episodes, nodes: list[int] | None = None, chunk: int = 10) -> list[tuple]:
    """Per-node steady-state position RMS, largest position error and mu RMS of many runs, in ``task.workers``
    processes (chunks of ``chunk`` runs). Returns ``(episode, strategy, node_rms, err_max, mu_rms)`` tuples."""
    p = _validate(cfg)
    episodes = list(episodes)
    chunks = [episodes[i:i + chunk] for i in range(0, len(episodes), chunk)]
    text = OmegaConf.to_yaml(cfg, resolve=True)
    if p["workers"] <= 1 or len(chunks) == 1:
        parts = [_screen_chunk(text, c, nodes) for c in chunks]
    else:
        import concurrent.futures as cf
        import multiprocessing as mp

        with cf.ProcessPoolExecutor(min(p["workers"], len(chunks)), mp_context=mp.get_context("spawn")) as ex:
            parts = list(ex.map(_screen_chunk, [text] * len(chunks), chunks, [nodes] * len(chunks)))
    return [row for part in parts for row in part]


def run(cfg: DictConfig) -> pd.DataFrame:
    """Run the study (see module docstring). Returns the tidy results table."""
    job = _setup(cfg)
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


# ----------------------------------------------------------------------------------------------- report

def _rms_over_runs(results: pd.DataFrame, metric: str) -> pd.Series:
    d = results[(results.metric == metric) & (results.time_s == -1.0)]
    return d.groupby("strategy", sort=False)["value"].apply(lambda v: math.sqrt((v ** 2).mean()))


def report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path) -> str:
    """Table II-shaped table (RMS errors + throughput per strategy) and Figs 3-6 from the results table."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    res = results[results.get("task", "braga_tbn") == "braga_tbn"] if "task" in results else results
    res = res[res.strategy != "all"]
    order = [s for s in ["noncooperative", "centralised"] if s in set(res.strategy)]
    order += sorted({s for s in res.strategy if str(s).startswith("consensus_")}, key=lambda s: int(s.split("_")[1]))
    n_runs = res[res.metric == "pos_rms"].groupby("strategy")["episode"].nunique()
    tab = pd.DataFrame(index=order)
    for m in ("pos_rms", "pos_rms_first5s", "mu_rms", "sigma_rms", "pi_rms"):
        tab[m] = _rms_over_runs(res, m)
    thr = res[(res.metric == "throughput_kBps")].groupby("strategy")["value"].mean()
    tab["throughput_kBps"] = thr
    tab["paper_throughput_kBps"] = [PAPER_THROUGHPUT.get(s, float("nan")) for s in order]
    deg = res[res.metric == "degenerate_events"].groupby("strategy")["value"].sum()
    tab["degenerate_events"] = deg
    tab["mc_runs"] = n_runs
    run_level = res[res.time_s == -1.0]
    med = {m: run_level[run_level.metric == m].groupby("strategy")["value"].median()
           for m in ("pos_rms", "mu_rms", "sigma_rms", "pi_rms")}
    for m, v in med.items():
        tab[f"{m}_median"] = v
    has_lost = "lost_track" in set(run_level.metric)  # results of older code have no lost-track metrics
    if has_lost:
        lost = run_level[run_level.metric == "lost_track"].groupby("strategy")["value"].sum()
        tab["lost_track_runs"] = lost
        kept = run_level[run_level.metric == "lost_track"].set_index(["strategy", "episode"])["value"] == 0
        mu = run_level[run_level.metric == "mu_rms"].set_index(["strategy", "episode"])["value"]
        mu_kept = mu[kept.reindex(mu.index).fillna(False).astype(bool)]
        tab["mu_rms_tracking_runs"] = mu_kept.groupby("strategy").apply(lambda v: math.sqrt((v ** 2).mean()))
    tab.index.name = "strategy"
    tab = tab.reset_index()
    tab.to_csv(out_dir / "braga_tbn_table2.csv", index=False)
    md = ["## braga_tbn — Table II (throughput) and RMS errors per strategy", "",
          "RMS over Monte Carlo runs (sqrt of the mean of the per-run mean squares); position and parameter errors "
          "over the steady-state window; throughput = what the network transmits (4-byte floats, 1 kB = "
          "1024 B as in the paper).", "",
          "| strategy | pos RMS [m] | pos RMS first 5 s [m] | mu RMS [m] | sigma RMS [m] | pi RMS | "
          "throughput [kB/s] | paper [kB/s] | degenerate | runs |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for _, r in tab.iterrows():
        md.append(f"| {r.strategy} | {r.pos_rms:.2f} | {r.pos_rms_first5s:.2f} | {r.mu_rms:.3f} | {r.sigma_rms:.3f} | "
                  f"{r.pi_rms:.4f} | {r.throughput_kBps:.2f} | {r.paper_throughput_kBps:.1f} | "
                  f"{int(r.degenerate_events)} | {int(r.mc_runs)} |")
    md += ["", "Per-run medians and lost tracks (a run has lost track when some node's steady-state position RMS "
           "exceeds `task.lost_track_m`):", "",
           "| strategy | median pos RMS [m] | median mu RMS [m] | median sigma RMS [m] | median pi RMS | "
           "lost-track runs | mu RMS without them [m] |", "|---|---|---|---|---|---|---|"]
    for _, r in tab.iterrows():
        lost_s = f"{int(r.lost_track_runs)}" if has_lost else "-"
        kept_s = f"{r.mu_rms_tracking_runs:.3f}" if has_lost and not math.isnan(r.mu_rms_tracking_runs) else "-"
        md.append(f"| {r.strategy} | {r.pos_rms_median:.2f} | {r.mu_rms_median:.3f} | {r.sigma_rms_median:.3f} | "
                  f"{r.pi_rms_median:.4f} | {lost_s} | {kept_s} |")
    if {"centralised", "consensus_10"} <= set(tab.strategy):
        mu_rms = tab.set_index("strategy")["mu_rms"]
        md += ["", f"Acceptance ratio consensus_10 / centralised mu RMS: "
               f"{mu_rms['consensus_10'] / mu_rms['centralised']:.2f}"]
    text = "\n".join(md) + "\n"
    (out_dir / "braga_tbn_table2.md").write_text(text)

    ts = res[res.time_s >= 0]
    if ts.empty:
        return text

    def rms_t(metric):
        d = ts[ts.metric == metric].groupby(["strategy", "time_s"])["value"].mean()
        return d.apply(math.sqrt)

    # Fig. 3: position RMS vs time (+ zoom)
    pos = rms_t("pos_se_t")
    fig, axs = plt.subplots(2, 1, figsize=(7, 7))
    for s in order:
        d = pos.loc[s]
        axs[0].plot(d.index, d.values, label=s)
        z = d[d.index <= 5.0]
        axs[1].plot(z.index, z.values, label=s)
    axs[0].set(xlabel="time [s]", ylabel="position RMS error [m]", title="Fig. 3 — position RMS error")
    axs[1].set(xlabel="time [s]", ylabel="position RMS error [m]", title="zoom on the first 5 s")
    axs[1].axvline(2.5, color="k", ls=":", lw=0.8)
    axs[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out_dir / "braga_tbn_fig3_position_rms.png", dpi=120)
    plt.close(fig)

    # Fig. 4: parameter estimates, mean and min/max bounds over runs
    k = len([m for m in set(ts.metric) if m.startswith("mu_") and m[3:].isdigit()])
    truth = {}
    fig, axs = plt.subplots(3, len(order), figsize=(3.2 * len(order), 7.5), sharey="row", squeeze=False)
    for ci, s in enumerate(order):
        for ri, base in enumerate(("mu", "sigma", "pi")):
            ax = axs[ri, ci]
            for j in range(1, k + 1):
                name = f"{base}_{j}" if base != "pi" else f"pi_{j}{j}"
                d = ts[(ts.metric == name) & (ts.strategy == s)].groupby("time_s")["value"]
                m, lo, hi = d.mean(), d.min(), d.max()
                ax.plot(m.index, m.values, lw=1)
                ax.fill_between(m.index, lo.values, hi.values, alpha=0.25)
            if ri == 0:
                ax.set_title(s, fontsize=9)
            if ci == 0:
                ax.set_ylabel({"mu": "mu [m]", "sigma": "sigma [m]", "pi": "pi_kk"}[base])
            if ri == 2:
                ax.set_xlabel("time [s]")
    fig.suptitle("Fig. 4 — parameter estimates (node average; lines: mean over runs, shaded: min/max)")
    fig.tight_layout()
    fig.savefig(out_dir / "braga_tbn_fig4_parameters.png", dpi=110)
    plt.close(fig)

    for fname, metric, ylabel, title in (
            ("braga_tbn_fig5_mu_rms.png", "mu_se_t", "noise mean RMS error [m]", "Fig. 5 — noise mean RMS error"),
            ("braga_tbn_fig6_sigma_rms.png", "sigma_se_t", "noise std RMS error [m]", "Fig. 6 — noise std RMS error")):
        d = rms_t(metric)
        fig, ax = plt.subplots(figsize=(7, 4))
        for s in order:
            ax.semilogy(d.loc[s].index, d.loc[s].values, label=s)
        ax.set(xlabel="time [s]", ylabel=ylabel, title=title)
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out_dir / fname, dpi=120)
        plt.close(fig)
    text += "\nFigures: braga_tbn_fig3_position_rms.png, braga_tbn_fig4_parameters.png, braga_tbn_fig5_mu_rms.png, " \
            "braga_tbn_fig6_sigma_rms.png\n"
    return text


# ----------------------------------------------------------------------------------------------- benchmark

def benchmark(steps: int = 200, mc_batch: int = 1, num_particles: int = 300, device: str = "cpu",
              strategies=None, workers: int | None = None, kernel_dtype: str | None = None) -> dict:
    """Time ``steps`` filter steps of the default scenario (in this process, 1 MC batch) and extrapolate.

    Returns a dict with ``ms_per_step`` (wall) and ``cpu_ms_per_step`` (this process's CPU time; robust on
    a loaded machine) for all strategies × 4 nodes × ``mc_batch`` runs, ``s_per_run_all`` (one MC run of
    all strategies, 1800 steps), ``s_per_run_one_strategy`` and ``min_full_protocol`` (100 runs × all
    strategies with ``workers`` worker processes, default ``min(2, cpu count)``, each on its own core;
    from the CPU time, so it assumes the cores are not shared with other jobs), and prints them.
    """
    import os

    workers = workers or max(1, min(2, os.cpu_count() or 1))
    task = OmegaConf.load(CONF_DIR / "task" / "braga_tbn.yaml")
    over = {"mc_runs": mc_batch, "mc_batch": mc_batch, "workers": 1, "steps": steps, "num_particles": num_particles,
            "steady_state_s": steps * float(task.dt) / 2, "backward_kernel": {"dtype": kernel_dtype}}
    if strategies is not None:
        over["strategies"] = list(strategies)
    cfg = OmegaConf.create({"seed": 0, "device": device, "dtype": "float64", "progress": False,
                            "task": OmegaConf.merge(task, over)})
    p = _validate(cfg)
    t0 = time.perf_counter()
    # time the filter only (terrain generation, ~1 s once per study, is excluded)
    import dslearn.learning.online_em as _tbn

    clock = {}
    orig = _tbn.rbpf_step

    def timed(*a, **kw):
        if "wall" not in clock:
            clock["wall"], clock["cpu"] = time.perf_counter(), time.process_time()
        return orig(*a, **kw)

    _tbn.rbpf_step = timed
    try:
        run(cfg)
    finally:
        _tbn.rbpf_step = orig
    elapsed = time.perf_counter() - clock["wall"]
    cpu = time.process_time() - clock["cpu"]
    n_strat = len(p["strategies"])
    ms, cpu_ms = 1000 * elapsed / steps, 1000 * cpu / steps
    s_run = cpu_ms * 1800 / 1000 / mc_batch
    out = {"ms_per_step": ms, "cpu_ms_per_step": cpu_ms, "s_per_run_all": s_run,
           "s_per_run_one_strategy": s_run / n_strat, "min_full_protocol": s_run * 100 / workers / 60,
           "workers": workers, "total_s": time.perf_counter() - t0, "threads": torch.get_num_threads()}
    print(f"braga_tbn benchmark ({torch.get_num_threads()} thread(s), {mc_batch} run(s) x {n_strat} strategies x 4 "
          f"nodes x {num_particles} particles, kernel dtype {kernel_dtype or 'float64'}): {ms:.1f} ms/step wall, "
          f"{cpu_ms:.1f} ms/step CPU -> {s_run:.1f} s CPU per MC run (all strategies, 1800 steps), "
          f"{s_run / n_strat:.1f} s per run and strategy; 100-run protocol with {workers} worker process(es): "
          f"{out['min_full_protocol']:.1f} min (projected from CPU time)")
    return out


def _cli_cfg(overrides: list[str]) -> DictConfig:
    task = OmegaConf.load(CONF_DIR / "task" / "braga_tbn.yaml")
    cfg = OmegaConf.create({"seed": 0, "device": "cpu", "dtype": "float64", "progress": False, "task": task})
    return OmegaConf.merge(cfg, OmegaConf.from_dotlist(list(overrides)))


def _episodes(text: str) -> list[int]:
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out.extend(range(int(a), int(b) + 1) if b else [int(a)])
    return out


def _trace_report(cfg: DictConfig, episodes: list[int], nodes: list[int] | None, show: list[int] | None) -> str:
    """Per-node summary and, for lost nodes (or ``show``), a time table of the diagnostics."""
    p = _validate(cfg)
    scn, res = trace_runs(cfg, episodes, nodes=nodes)
    dg, grad = res.diagnostics, terrain_gradient(scn)
    n_ss = max(1, int(round(p["steady_state_s"] / p["dt"])))
    err = res.pos_se.sqrt()  # (T, R, C, S)
    spread = dg["spread"]
    g = grad.permute(2, 0, 1)[:, :, None, :].expand_as(err)  # (T, R, C, S)
    flat = g < 0.2
    lines = [f"error/spread RMS ratio: all {(err.pow(2).mean() / spread.pow(2).mean()).sqrt():.2f}, "
             f"|grad h| < 0.2: {(err[flat].pow(2).mean() / spread[flat].pow(2).mean()).sqrt():.2f}; "
             f"steps with error > 3 x spread: {(err > 3 * spread).double().mean():.3f}"]
    node_ids = nodes if nodes is not None else list(range(err.shape[-1]))
    steps = err.shape[0]
    times = list(range(9, min(steps, 400), 20)) + list(range(499, steps, 250))
    for ri, ep in enumerate(episodes):
        for ci, sname in enumerate(p["strategies"]):
            ss = err[-n_ss:, ri, ci].pow(2).mean(0).sqrt()
            lines.append(f"run {ep} {sname}: node steady-state RMS [m] {[round(v, 1) for v in ss.tolist()]}, "
                         f"max error {err[:, ri, ci].max():.1f} m")
            for si, node in enumerate(node_ids):
                if not (ss[si] > p["lost_track_m"] or (show is not None and node in show)):
                    continue
                mu, sg, pi = res.mu[:, ri, ci, si], res.sigma[:, ri, ci, si], res.pi[:, ri, ci, si]
                r_last = (scn.r[ri, si, 1:] == mu.shape[-1] - 1).to(err.dtype)
                lines.append(f"  node {node}: t[s] | error spread vel.err [m, m, m/s] | ESS | |grad h| | "
                             f"h(est)-h(true) [m] | P(last mode) (true) | mu sigma pi_kk")
                for t in times:
                    w = slice(max(0, t - 9), t + 1)
                    par = " ".join(f"{v:6.2f}" for v in (*mu[t].tolist(), *sg[t].tolist(),
                                                         *pi[t].diagonal().tolist()))
                    lines.append(f"  {(t + 1) * p['dt']:6.2f} | {err[t, ri, ci, si]:6.1f} {spread[t, ri, ci, si]:5.1f} "
                                 f"{dg['vel_se'][t, ri, ci, si].sqrt():5.1f} | {dg['ess'][t, ri, ci, si]:4.0f} | "
                                 f"{grad[ri, si, t]:.2f} | {dg['h_misfit'][w, ri, ci, si].mean():6.2f} | "
                                 f"{dg['p_mode_last'][w, ri, ci, si].mean():.2f} ({r_last[w].mean():.2f}) | {par}")
    return "\n".join(lines)


def _screen_report(cfg: DictConfig, episodes: list[int], nodes: list[int] | None) -> str:
    p = _validate(cfg)
    rows = screen_lost_tracks(cfg, episodes, nodes=nodes)
    lines = []
    for sname in p["strategies"]:
        r = [row for row in rows if row[1] == sname]
        worst = torch.tensor([max(row[2]) for row in r], dtype=torch.float64)
        emax = torch.tensor([max(row[3]) for row in r], dtype=torch.float64)
        mu = torch.tensor([sum(v * v for v in row[4]) / len(row[4]) for row in r], dtype=torch.float64).sqrt()
        q = emax.quantile(torch.tensor([0.5, 0.9], dtype=torch.float64)).tolist()
        lines.append(f"{sname}: {len(r)} runs, lost track (worst node > {p['lost_track_m']:g} m) "
                     f"{int((worst > p['lost_track_m']).sum())}; worst-node steady-state RMS median {worst.median():.2f} m; "
                     f"max error median {q[0]:.1f} m, 90% {q[1]:.1f} m, max {emax.max():.1f} m; mu RMS "
                     f"{mu.pow(2).mean().sqrt():.3f} m (median {mu.median():.3f} m)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    """``python -m dslearn.studies.braga_tbn [benchmark | trace RUNS | screen RUNS] [--nodes 0,1] [task.x=y ...]``

    * ``benchmark`` (default): time the filter step and extrapolate the cost of the protocol;
    * ``trace 41,64``: re-run these Monte Carlo runs with diagnostics and print per-node summaries, the filter's
      calibration (error / particle spread) and a time table for every lost node (``--show 0`` adds node 0);
    * ``screen 0-99``: lost-track count and error statistics over many runs (``--nodes 0`` filters only node 0,
      ``task.strategies=[noncooperative]`` needed for that).
    Runs are numbered as in the study (same seed -> the same flights and filters)."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m dslearn.studies.braga_tbn", description=main.__doc__.split("\n")[0])
    ap.add_argument("command", nargs="?", default="benchmark", choices=["benchmark", "trace", "screen"])
    ap.add_argument("runs", nargs="?", default="0", help="run indices, e.g. 41,64 or 0-99")
    ap.add_argument("--nodes", default=None, help="filter only these nodes (noncooperative), e.g. 0")
    ap.add_argument("--show", default=None, help="trace: also print the time table of these nodes")
    ap.add_argument("overrides", nargs="*", help="task.x=y config overrides")
    a, rest = ap.parse_known_args(argv)
    overrides = list(a.overrides) + [r for r in rest if "=" in r]
    torch.set_num_threads(1)
    if a.command == "benchmark":
        benchmark()
        return
    cfg = _cli_cfg(overrides)
    nodes = [int(v) for v in a.nodes.split(",")] if a.nodes else None
    if a.command == "trace":
        show = [int(v) for v in a.show.split(",")] if a.show else None
        print(_trace_report(cfg, _episodes(a.runs), nodes, show))
    else:
        print(_screen_report(cfg, _episodes(a.runs), nodes))


if __name__ == "__main__":  # python -m dslearn.studies.braga_tbn [benchmark | trace RUNS | screen RUNS]
    main()
