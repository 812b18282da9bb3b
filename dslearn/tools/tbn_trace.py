r"""Diagnostics of the ``braga_tbn`` study (not its protocol): filter cost and lost-track analysis.

    python -m dslearn.tools.tbn_trace                       # benchmark: ms per filter step, projected costs
    python -m dslearn.tools.tbn_trace trace 48 'task.strategies=[centralised,consensus_10]'
    python -m dslearn.tools.tbn_trace screen 0-59 --nodes 0 'task.strategies=[noncooperative]'

Overrides are Hydra overrides of ``experiment=braga_tbn`` (composed and checked like ``dslearn-run``).
Runs are numbered as in the study: the same seed gives the same flights and filters
(:func:`dslearn.learning.online_em.simulate_and_filter`).
"""

from __future__ import annotations

import time

import torch
from omegaconf import DictConfig

from dslearn.learning.online_em import TBNJob, simulate_and_filter
from dslearn.metrics.navigation import node_steady_rms, tbn_errors
from dslearn.sim.terrain import terrain_gradient
from dslearn.studies.braga_tbn import BragaStudy, steady_steps


def compose_cfg(overrides: list[str] = ()) -> DictConfig:
    """``experiment=braga_tbn`` with Hydra ``overrides``, checked (root keys and the task schema)."""
    import dslearn.schemas  # noqa: F401  (registers the task schemas)
    from hydra import compose, initialize_config_dir

    from dslearn.schemas.core import CONF_DIR, validate_config
    from dslearn.schemas import validate_task

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = compose("config", overrides=["experiment=braga_tbn", "progress=false", *overrides])
    validate_config(cfg)
    validate_task(cfg)
    return cfg


def study_of(cfg: DictConfig) -> BragaStudy:
    """The study of a checked ``braga_tbn`` configuration, built by the composition root."""
    from dslearn.compose import build_study

    study = build_study(cfg)
    if not isinstance(study, BragaStudy):
        raise TypeError(f"tbn_trace diagnoses the braga_tbn study, not {type(study).__name__}")
    return study


def trace_runs(cfg: DictConfig, episodes, diagnostics: bool = True, nodes: list[int] | None = None):
    """Simulate and filter the given Monte Carlo runs (any subset, any order: each run's result depends only on
    (seed, run index, strategy)) and return ``(scenario, TBNResult, TBNErrors)`` with the per-step diagnostics of
    :func:`dslearn.learning.online_em.run_tbn` (ESS, particle spread, ...) and the errors against the truth
    (:func:`dslearn.metrics.navigation.tbn_errors`: position, with ``diagnostics`` also velocity error and height
    misfit) for lost-track analysis.
    ``nodes``: filter only these aircraft (noncooperative only); the scenario is restricted to them."""
    scn, res = simulate_and_filter(study_of(cfg).job(), list(episodes), diagnostics=diagnostics, nodes=nodes)
    return scn, res, tbn_errors(res, scn, detail=diagnostics)


def _screen_chunk(job: TBNJob, n_ss: int, episodes: list[int], nodes: list[int] | None) -> list[tuple]:
    torch.set_num_threads(1)
    scn, res = simulate_and_filter(job, episodes, nodes=nodes)
    pos_se = tbn_errors(res, scn).pos_se
    node_rms = node_steady_rms(pos_se, n_ss)  # (R, C, S)
    err_max = pos_se.amax(0).sqrt()
    mu = (res.mu[-n_ss:] - job.truth.mu).pow(2).mean((0, -1)).sqrt()  # (R, C, S) per-node mu RMS
    out = []
    for ri, ep in enumerate(episodes):
        for ci, sname in enumerate(job.params.strategies):
            out.append((ep, sname, node_rms[ri, ci].tolist(), err_max[ri, ci].tolist(), mu[ri, ci].tolist()))
    return out


def screen_lost_tracks(cfg: DictConfig, episodes, nodes: list[int] | None = None, chunk: int = 10) -> list[tuple]:
    """Per-node steady-state position RMS, largest position error and mu RMS of many runs, in ``task.workers``
    processes (chunks of ``chunk`` runs). Returns ``(episode, strategy, node_rms, err_max, mu_rms)`` tuples."""
    study = study_of(cfg)
    job, n_ss, workers = study.job(), steady_steps(study.settings), study.settings.workers
    episodes = list(episodes)
    chunks = [episodes[i:i + chunk] for i in range(0, len(episodes), chunk)]
    if workers <= 1 or len(chunks) == 1:
        parts = [_screen_chunk(job, n_ss, c, nodes) for c in chunks]
    else:
        import concurrent.futures as cf
        import multiprocessing as mp

        with cf.ProcessPoolExecutor(min(workers, len(chunks)), mp_context=mp.get_context("spawn")) as ex:
            parts = list(ex.map(_screen_chunk, [job] * len(chunks), [n_ss] * len(chunks), chunks,
                                [nodes] * len(chunks)))
    return [row for part in parts for row in part]


def benchmark(steps: int = 200, mc_batch: int = 1, num_particles: int = 300, device: str = "cpu",
              strategies=None, workers: int | None = None, kernel_dtype: str | None = None) -> dict:
    """Time ``steps`` filter steps of the default scenario (in this process, 1 MC batch) and extrapolate.

    Returns a dict with ``ms_per_step`` (wall) and ``cpu_ms_per_step`` (this process's CPU time; robust on
    a loaded machine) for all strategies × 4 nodes × ``mc_batch`` runs, ``s_per_run_all`` (one MC run of
    all strategies, 1800 steps), ``s_per_run_one_strategy`` and ``min_full_protocol`` (100 runs × all
    strategies with ``workers`` worker processes, default ``min(2, cpu count)``, each on its own core;
    from the CPU time, so it assumes the cores are not shared with other jobs), and prints them.
    The clock starts at the first filter step (terrain generation and the flight simulation are excluded).
    """
    import os

    import dslearn.learning.online_em as _tbn

    workers = workers or max(1, min(2, os.cpu_count() or 1))
    over = [f"task.mc_runs={mc_batch}", f"task.mc_batch={mc_batch}", "task.workers=1", f"task.steps={steps}",
            f"task.num_particles={num_particles}", f"device={device}", "dtype=float64",
            f"task.backward_kernel.dtype={kernel_dtype or 'null'}", f"task.steady_state_s={steps * 0.05 / 2}"]
    if strategies is not None:
        over.append(f"task.strategies=[{','.join(strategies)}]")
    cfg = compose_cfg(over)
    study = study_of(cfg)
    t0 = time.perf_counter()
    job = study.job()
    clock = {}
    orig = _tbn.rbpf_step

    def timed(*a, **kw):
        if "wall" not in clock:
            clock["wall"], clock["cpu"] = time.perf_counter(), time.process_time()
        return orig(*a, **kw)

    _tbn.rbpf_step = timed
    try:
        simulate_and_filter(job, list(range(mc_batch)))
    finally:
        _tbn.rbpf_step = orig
    elapsed = time.perf_counter() - clock["wall"]
    cpu = time.process_time() - clock["cpu"]
    n_strat = len(study.settings.strategies)
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


def _episodes(text: str) -> list[int]:
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out.extend(range(int(a), int(b) + 1) if b else [int(a)])
    return out


def _trace_report(cfg: DictConfig, episodes: list[int], nodes: list[int] | None, show: list[int] | None) -> str:
    """Per-node summary and, for lost nodes (or ``show``), a time table of the diagnostics."""
    s = study_of(cfg).settings
    scn, res, errors = trace_runs(cfg, episodes, nodes=nodes)
    dg, grad = res.diagnostics, terrain_gradient(scn)
    n_ss = steady_steps(s)
    err = errors.pos_se.sqrt()  # (T, R, C, S)
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
        for ci, sname in enumerate(s.strategies):
            ss = err[-n_ss:, ri, ci].pow(2).mean(0).sqrt()
            lines.append(f"run {ep} {sname}: node steady-state RMS [m] {[round(v, 1) for v in ss.tolist()]}, "
                         f"max error {err[:, ri, ci].max():.1f} m")
            for si, node in enumerate(node_ids):
                if not (ss[si] > s.lost_track_m or (show is not None and node in show)):
                    continue
                mu, sg, pi = res.mu[:, ri, ci, si], res.sigma[:, ri, ci, si], res.pi[:, ri, ci, si]
                r_last = (scn.r[ri, si, 1:] == mu.shape[-1] - 1).to(err.dtype)
                lines.append(f"  node {node}: t[s] | error spread vel.err [m, m, m/s] | ESS | |grad h| | "
                             f"h(est)-h(true) [m] | P(last mode) (true) | mu sigma pi_kk")
                for t in times:
                    w = slice(max(0, t - 9), t + 1)
                    par = " ".join(f"{v:6.2f}" for v in (*mu[t].tolist(), *sg[t].tolist(),
                                                         *pi[t].diagonal().tolist()))
                    lines.append(f"  {(t + 1) * s.dt:6.2f} | {err[t, ri, ci, si]:6.1f} {spread[t, ri, ci, si]:5.1f} "
                                 f"{errors.vel_se[t, ri, ci, si].sqrt():5.1f} | {dg['ess'][t, ri, ci, si]:4.0f} | "
                                 f"{grad[ri, si, t]:.2f} | {errors.h_misfit[w, ri, ci, si].mean():6.2f} | "
                                 f"{dg['p_mode_last'][w, ri, ci, si].mean():.2f} ({r_last[w].mean():.2f}) | {par}")
    return "\n".join(lines)


def _screen_report(cfg: DictConfig, episodes: list[int], nodes: list[int] | None) -> str:
    s = study_of(cfg).settings
    rows = screen_lost_tracks(cfg, episodes, nodes=nodes)
    lines = []
    lost_m = s.lost_track_m
    for sname in s.strategies:
        r = [row for row in rows if row[1] == sname]
        worst = torch.tensor([max(row[2]) for row in r], dtype=torch.float64)
        emax = torch.tensor([max(row[3]) for row in r], dtype=torch.float64)
        mu = torch.tensor([sum(v * v for v in row[4]) / len(row[4]) for row in r], dtype=torch.float64).sqrt()
        q = emax.quantile(torch.tensor([0.5, 0.9], dtype=torch.float64)).tolist()
        lines.append(f"{sname}: {len(r)} runs, lost track (worst node > {lost_m:g} m) "
                     f"{int((worst > lost_m).sum())}; worst-node steady-state RMS median {worst.median():.2f} m; "
                     f"max error median {q[0]:.1f} m, 90% {q[1]:.1f} m, max {emax.max():.1f} m; mu RMS "
                     f"{mu.pow(2).mean().sqrt():.3f} m (median {mu.median():.3f} m)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    """``python -m dslearn.tools.tbn_trace [benchmark | trace RUNS | screen RUNS] [--nodes 0,1] [task.x=y ...]``

    * ``benchmark`` (default): time the filter step and extrapolate the cost of the protocol;
    * ``trace 41,64``: re-run these Monte Carlo runs with diagnostics and print per-node summaries, the filter's
      calibration (error / particle spread) and a time table for every lost node (``--show 0`` adds node 0);
    * ``screen 0-99``: lost-track count and error statistics over many runs (``--nodes 0`` filters only node 0,
      ``task.strategies=[noncooperative]`` needed for that).
    Runs are numbered as in the study (same seed -> the same flights and filters)."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m dslearn.tools.tbn_trace", description=main.__doc__.split("\n")[0])
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
    cfg = compose_cfg(overrides)
    nodes = [int(v) for v in a.nodes.split(",")] if a.nodes else None
    if a.command == "trace":
        show = [int(v) for v in a.show.split(",")] if a.show else None
        print(_trace_report(cfg, _episodes(a.runs), nodes, show))
    else:
        print(_screen_report(cfg, _episodes(a.runs), nodes))


if __name__ == "__main__":  # python -m dslearn.tools.tbn_trace [benchmark | trace RUNS | screen RUNS]
    main()
