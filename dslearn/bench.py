"""``dslearn-bench``: benchmarks that print figures (not timed tests).

Every workload item runs in its own fresh (spawned) process, so its peak resident memory
(``ru_maxrss``) is its own; where a reference is given, the reference
(:mod:`dslearn.reference` or a from-scratch refit) runs *in that same process* and the table
reports the ratio ``reference / fast``.

Workloads (``dslearn-bench [--quick] [WORKLOAD ...]``; none = all):

  speed      the speed targets: one GP consensus configuration (gp / hybrid, 200 + 50 episodes,
             one thread) as configured (the inverse factor in float64), then with the Cholesky
             factor (the previous algorithm) and with the inverse factor in float32, in one
             process, against the previous release's figure (:data:`PREVIOUS_RELEASE`); then
             ``dslearn-run experiment=yu_table1`` end to end with the default launcher.

  reference  Yu protocol, fast path vs the straightforward reference (per-node loops, GPyTorch
             ExactGP refit from scratch at every step, autograd Jacobians) on the SAME reduced
             protocol (``--ref-train`` + ``--ref-test`` episodes), both timed in one process;
             models x fusions of ``--ref-models`` / ``--ref-fusions`` (default: every model and
             every strategy the reference implements); checks the numbers agree: the command
             exits with status 1, naming the item and row, when any metric value differs by more
             than ``dslearn.reference.REFERENCE_TOL`` (relative, absolute below 1) or an item fails.
  protocol   the full Table I + II protocol (200 train + 50 test episodes, 10 nodes) for every
             model x fusion, fast path only, spread over ``--workers`` processes (1 thread each).
  gp         one online GP step (predict with Jacobian and variance + append) per node at data-set
             sizes n, for the exact GP and the window / SGPR / SSGP variants, against a refit from
             scratch (kernel matrix + Cholesky) at every step; log-log plot with fitted slopes.
  fantasy    GPyTorch ExactGP with defaults (first predict = its caches) and ``get_fantasy_model``
             at n = 2,400 (full suite only).
  network    a network of S = 10 / 50 / 200 / 1,000 nodes tracking 2 agents for 100 steps with
             online GP learning (hybrid consensus); reference (per-node loops) on the first steps.
  filters    the cost per step of each prediction step of the distributed filter (filter=default, ukf,
             ukf_mm, adf; pf with 100 / 500 / 2,000 particles) with the GP learned online, S = 10 / 50 / 200
             nodes (hybrid consensus), and of one training epoch of learner=backprop (LIN; the social force's
             and the GP's own parameters too) against the EKF's forward pass on the same episodes.
  dtype      float32 vs float64 on the same seeds (time and accuracy of the Yu study).
  studies    wall time of the other studies' default runs (``dslearn-run ...`` subprocesses).
  matrix     the cost of matrix cells (``task=matrix``), each in its own process, and of their parts: the
             scenario draw, the offline fit (or its load from the offline-fit cache), online learning on the
             training episodes, estimation on the test episodes, and the cell's peak resident memory.
             Settings as ``key=value`` after the workload: ``methods=[a,b]`` (conf/method presets),
             ``scenarios=[c,d]`` (conf/scenario), ``train=10 test=10`` (episodes per cell, as
             ``experiment=matrix``), ``seed=0``, ``cache=fresh|off|user`` (the offline-fit cache: ``fresh``,
             the default, one new folder shared by the workload's cells, as a sweep's workers share theirs;
             ``off``; ``user``: ``$DSLEARN_CACHE_DIR`` as it is). Cells run one after another, methods
             in the order given (so the first preset fitting a model pays the fit).

Outputs in ``--out`` (default: a new folder ``bench-results/<date>_<time>`` in the current
directory, so the committed ``benchmarks/`` tables are only rewritten when asked for with
``--out benchmarks``): ``bench.csv``, ``bench.md`` (with machine info), ``gp_step_cost.png``.
``--quick`` runs a reduced set in a few minutes (without ``studies``, ``fantasy`` and ``matrix`` unless named).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import re
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd
import torch

from dslearn.io import atomic_write_csv, atomic_write_text

ALL = ("speed", "reference", "protocol", "gp", "fantasy", "network", "filters", "dtype", "studies", "matrix")

#: the previous release's figures on the project's 2-core machine (AMD EPYC, torch 2.13 CPU), the
#: denominators of the ``speed`` workload's ratios: one GP consensus configuration (gp / hybrid
#: omega = 1, 200 + 50 episodes, one thread; ``YuStudy.run`` only, measured at commit 27f97cd on
#: the idle machine) and the Table I grid (``dslearn-run experiment=yu_table1``; that release's
#: fastest way, ``hydra/launcher=joblib hydra.launcher.n_jobs=2``, as its README gives it)
PREVIOUS_RELEASE = {"config_s": 53.2, "grid_s": 293.0, "release": "27f97cd"}


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _cuda_peak_mb(device) -> float | None:
    if str(device).startswith("cuda"):
        return torch.cuda.max_memory_allocated() / 2**20
    return None


def machine_info() -> dict:
    cpu = platform.processor() or platform.machine()
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        load = " ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        load = "?"
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "loadavg_1_5_15": load,
    }


def _compose(overrides):
    from hydra import compose, initialize_config_dir

    import dslearn.schemas  # noqa: F401  (registers the task schemas the configs name)
    from dslearn.app.common import CONF_DIR

    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        return compose("config", overrides=list(overrides))


# ------------------------------------------------------------------------------------------
# workload items (each runs in a child process; returns a list of row dicts)
def item_reference(model: str, fusion: str, train: int, test: int, device: str = "cpu") -> list[dict]:
    """One model x fusion through the fast path and the reference, in this process: both timed, and
    their rows compared (:func:`dslearn.reference.compare_results`: ``max_diff`` against
    :data:`dslearn.reference.REFERENCE_TOL`, ``worst`` names the row)."""
    from dslearn.reference import REFERENCE_TOL, ReferenceYu, compare_results
    from dslearn import api

    ov = [f"model={model}", f"consensus={fusion}", f"data.train_episodes={train}", f"data.test_episodes={test}", f"device={device}"]
    cfg = _compose(ov)
    t0 = time.perf_counter()
    fast = api.build_study(cfg).run()
    t_fast = time.perf_counter() - t0
    cfg = _compose([o for o in ov if not o.startswith("device")])
    t0 = time.perf_counter()
    ref = ReferenceYu.from_config(cfg).run()
    t_ref = time.perf_counter() - t0
    cmp = compare_results(fast, ref)
    diff = float(abs(fast["value"].to_numpy() - ref["value"].to_numpy()).max()) if len(fast) == len(ref) else float("nan")
    learn = model.startswith("gp")
    node_steps = 10 * 12 * ((train if learn else 0) + test)
    return [dict(workload="reference", item=f"yu {model}/{fusion} {train}+{test} ep", nodes=10, wall_s=t_fast,
                 ms_per_node_step=1e3 * t_fast / node_steps, reference_s=t_ref, ratio=t_ref / t_fast,
                 reference_note="same reduced protocol, same process" + (
                     "" if cmp["max_diff"] <= REFERENCE_TOL else f"; DIFFERS beyond {REFERENCE_TOL:g}: {cmp['worst']}"),
                 max_abs_diff=diff, max_diff=cmp["max_diff"], worst=cmp["worst"], peak_mb=_peak_mb())]


def reference_failures(rows: list[dict]) -> list[str]:
    """The ``reference`` items whose fast and reference results differ beyond
    :data:`dslearn.reference.REFERENCE_TOL` (or that failed to run), one line each."""
    from dslearn.reference import REFERENCE_TOL

    out = []
    for r in rows:
        if r.get("workload") != "reference":
            continue
        d = r.get("max_diff")
        if d is None or not d <= REFERENCE_TOL:
            out.append(f"{r['item']}: max_diff {d} > {REFERENCE_TOL:g}" + (f" ({r['worst']})" if r.get("worst") else ""))
    return out


def item_protocol(model: str, fusion: str, train: int, test: int, device: str = "cpu", dtype: str = "float64",
                  workload: str = "protocol") -> list[dict]:
    from dslearn import api

    cfg = _compose([f"model={model}", f"consensus={fusion}", f"data.train_episodes={train}",
                    f"data.test_episodes={test}", f"device={device}", f"dtype={dtype}"])
    t0 = time.perf_counter()
    df = api.build_study(cfg).run()
    wall = time.perf_counter() - t0
    learn = model.startswith("gp")
    node_steps = 10 * 12 * ((train if learn else 0) + test)
    sens = df[df["node_kind"] == "sensor"]
    return [dict(workload=workload, item=f"yu {model}/{fusion} {train}+{test} ep {dtype}",
                 nodes=10, wall_s=wall, ms_per_node_step=1e3 * wall / node_steps,
                 track_err=float(sens[sens.metric == "track_err"]["value"].mean()),
                 pred_err=float(sens[sens.metric == "pred_err"]["value"].mean()),
                 peak_mb=_peak_mb(), cuda_peak_mb=_cuda_peak_mb(device))]


def item_speed_config(train: int, test: int, model: str = "gp", fusion: str = "hybrid") -> list[dict]:
    """One GP consensus configuration, single-threaded, in this same process: as configured (the
    inverse factor in float64, ``model.factor=auto``), with the Cholesky factor (the previous
    algorithm: two triangular solves per step), and with the inverse factor in float32. Wall time
    of each run, the default's ratio to the previous release's figure, each variant's ratio to the
    default, and the largest change of any result value against the default."""
    from dslearn import api

    rows, runs = [], {}
    full = (train, test) == (200, 50)
    for form, fd in (("auto", "float64"), ("cholesky", "float64"), ("auto", "float32")):
        cfg = _compose([f"model={model}", f"consensus={fusion}", f"data.train_episodes={train}",
                        f"data.test_episodes={test}", f"model.factor_dtype={fd}", f"model.factor={form}"])
        study = api.build_study(cfg)
        t0 = time.perf_counter()
        df = study.run()
        wall = time.perf_counter() - t0
        sens = df[df["node_kind"] == "sensor"]
        row = dict(workload="speed", item=f"one configuration {model}/{fusion} {train}+{test} ep, factor {form} {fd}",
                   nodes=10, wall_s=wall, track_err=float(sens[sens.metric == "track_err"]["value"].mean()),
                   pred_err=float(sens[sens.metric == "pred_err"]["value"].mean()), peak_mb=_peak_mb())
        if not runs:  # the default: against the previous release
            prev = PREVIOUS_RELEASE["config_s"] if full else None
            row.update(reference_s=prev, ratio=None if prev is None else prev / wall,
                       reference_note=f"previous release {PREVIOUS_RELEASE['release']}: {prev} s" if prev else "")
        else:  # a variant: against the default in this process
            w0, d0 = runs[("auto", "float64")]
            diff = df["value"].to_numpy() - d0["value"].to_numpy()
            rel = float(abs(diff).max() / max(abs(d0["value"].to_numpy()).max(), 1e-300))
            row.update(reference_s=w0, ratio=w0 / wall, max_abs_diff=float(abs(diff).max()),
                       reference_note=f"the default in this process: {w0:.1f} s; largest relative change {rel:.1e}")
        runs[(form, fd)] = (wall, df)
        rows.append(row)
    return rows


def _timed_cli(args: list[str], dir_key: str) -> tuple[int, float, float]:
    """``python -m dslearn.run *args`` in a temporary output folder (``dir_key``: ``hydra.run.dir`` or
    ``hydra.sweep.dir``), timed by a wrapper process: exit code, wall seconds and the largest
    descendant's peak RSS in MB (``-1, nan, nan`` if the wrapper's report cannot be read)."""
    with tempfile.TemporaryDirectory() as tmp:
        code = ("import resource, subprocess, sys, time; t = time.perf_counter(); "
                "r = subprocess.run(sys.argv[1:], capture_output=True, text=True); w = time.perf_counter() - t; "
                "print('RC', r.returncode, 'WALL', w, 'RSS', resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss); "
                "print(r.stderr[-2000:] if r.returncode else '')")
        out = subprocess.run([sys.executable, "-c", code, sys.executable, "-m", "dslearn.run", *args,
                              f"{dir_key}={tmp}/out", "print_table=false"], capture_output=True, text=True)
    toks = out.stdout.split()
    try:
        return int(toks[1]), float(toks[3]), float(toks[5]) / 1024
    except (IndexError, ValueError):
        return -1, float("nan"), float("nan")


def item_grid(experiment: str = "yu_table1") -> list[dict]:
    """``dslearn-run experiment=<grid>`` as a user runs it (the default launcher), in a subprocess:
    end-to-end wall time and the largest worker's peak memory, against the previous release."""
    rc, wall, rss = _timed_cli([f"experiment={experiment}"], "hydra.sweep.dir")
    prev = PREVIOUS_RELEASE["grid_s"] if experiment == "yu_table1" else None
    return [dict(workload="speed", item=f"dslearn-run experiment={experiment} (default launcher)" + ("" if rc == 0 else f" (FAILED rc={rc})"),
                 wall_s=wall, reference_s=prev, ratio=None if prev is None else prev / wall, peak_mb=rss,
                 reference_note=f"previous release {PREVIOUS_RELEASE['release']}, joblib on 2 cores: {prev} s" if prev else "")]


def _make_gp(variant: str, nodes: int, n: int, dim: int, extra: int, gen, dtype=torch.float64):
    """A GP of ``variant`` holding ``n`` random points per node (bulk-loaded)."""
    from dslearn.models.gp_backends.exact import OnlineGP
    from dslearn.models.gp_backends.sparse import SGPR, SSGP, WindowGP

    X = 2 * torch.randn(nodes, n, dim, generator=gen, dtype=dtype)
    Y = torch.sin(X)
    hyp = dict(outputscale=1.0, lengthscale=2.0, noise_std=0.5, dtype=dtype)
    if variant in ("exact", "window"):
        if variant == "exact":
            gp = OnlineGP(nodes, dim, dim, capacity=n + extra + 1, **hyp)
            keep = n
        else:
            gp = WindowGP(nodes, dim, dim, window=1000, **hyp)
            keep = min(n, 1000)
        gp.set_data(X[:, n - keep :], Y[:, n - keep :], residual=True, capacity=n + extra + 1 if variant == "exact" else gp.X.shape[1])
        if variant == "window":
            gp.seen = n
        return gp
    gp = SGPR(nodes, dim, dim, inducing=128, **hyp) if variant == "sgpr" else SSGP(nodes, dim, dim, features=200, **hyp)
    gp.extend(X, Y)
    return gp


def item_gp(variant: str, n: int, nodes: int = 1, dim: int = 8, steps: int = 20, ref_steps: int = 2) -> list[dict]:
    gen = torch.Generator().manual_seed(0)
    t0 = time.perf_counter()
    gp = _make_gp(variant, nodes, n, dim, steps, gen)
    build = time.perf_counter() - t0
    xs = 2 * torch.randn(steps + 1, nodes, dim, generator=gen, dtype=torch.float64)
    gp.predict(xs[0].unsqueeze(1))
    gp.append(xs[0], torch.sin(xs[0]))  # warm-up
    t0 = time.perf_counter()
    for i in range(1, steps + 1):
        gp.predict(xs[i].unsqueeze(1))
        gp.append(xs[i], torch.sin(xs[i]))
    step = (time.perf_counter() - t0) / steps
    row = dict(workload="gp", item=f"gp {variant} n={n} S={nodes}", variant=variant, n=n, nodes=nodes, wall_s=step * steps,
               ms_per_step=1e3 * step, ms_per_node_step=1e3 * step / nodes, build_s=build, peak_mb=_peak_mb())
    if variant == "exact" and ref_steps > 0:
        # reference: kernel matrix + Cholesky from scratch at every step (what a refit does)
        Xr, Yr = (t.clone() for t in gp.data()[:2])
        eye = torch.eye(Xr.shape[1], dtype=torch.float64)
        t0 = time.perf_counter()
        for i in range(ref_steps):
            K = gp.kernel(Xr, Xr) + gp.noise_var.reshape(-1, 1, 1) * eye
            L = torch.linalg.cholesky(K)
            a = torch.cholesky_solve(Yr, L)
            ks = gp.kernel(Xr, xs[i].unsqueeze(1))
            _ = ks.transpose(-1, -2) @ a, torch.linalg.solve_triangular(L, ks, upper=False)
        ref = (time.perf_counter() - t0) / ref_steps
        row.update(reference_ms_per_step=1e3 * ref, ratio=ref / step, reference_note=f"kernel matrix + Cholesky from scratch per step ({ref_steps} steps timed)")
        row["peak_mb"] = _peak_mb()
    return [row]


def item_fantasy(n: int = 2400, dim: int = 8, steps: int = 2) -> list[dict]:
    """GPyTorch defaults at n points (one node, ``dim`` outputs as a batch): refit vs fantasy."""
    import gpytorch

    from dslearn.reference import _ExactGP

    gen = torch.Generator().manual_seed(0)
    X = 2 * torch.randn(n, dim, generator=gen, dtype=torch.float64)
    Y = torch.sin(X).T.contiguous()
    lik = gpytorch.likelihoods.GaussianLikelihood(batch_shape=torch.Size([dim]))
    m = _ExactGP(X.unsqueeze(0).expand(dim, -1, -1), Y, lik, dim).double()
    lik.noise = torch.full((dim, 1), 0.25)
    m.covar_module.base_kernel.lengthscale = torch.full((dim, 1, 1), 2.0)
    m.eval(), lik.eval()
    xs = 2 * torch.randn(steps + 1, dim, generator=gen, dtype=torch.float64)
    rows = []
    t0 = time.perf_counter()
    with torch.no_grad():
        m(xs[0].reshape(1, 1, -1).expand(dim, 1, -1)).variance  # builds the caches (defaults: CG above 800)
    first = time.perf_counter() - t0
    rows.append(dict(workload="fantasy", item=f"gpytorch ExactGP defaults: first predict (caches) n={n}", n=n, nodes=1,
                     wall_s=first, ms_per_step=1e3 * first, peak_mb=_peak_mb()))
    t0 = time.perf_counter()
    fm = m
    with torch.no_grad():
        for i in range(steps):
            x = xs[i + 1].reshape(1, 1, -1).expand(dim, 1, -1)
            fm = fm.get_fantasy_model(x, torch.sin(xs[i + 1]).reshape(dim, 1))
            fm(x).variance
    t = (time.perf_counter() - t0) / steps
    rows.append(dict(workload="fantasy", item=f"gpytorch get_fantasy_model + predict n={n}", n=n, nodes=1, wall_s=t * steps,
                     ms_per_step=1e3 * t, ms_per_node_step=1e3 * t, peak_mb=_peak_mb()))
    return rows


def _network_cfg(nodes: int, steps: int, model: str = "gp_increment", extra: tuple = ()):
    sensors = 4 if nodes == 10 else max(1, round(0.4 * nodes))
    gp = ["+model.capacity=128"] if model.startswith("gp") else []
    return _compose([f"model={model}", "consensus=hybrid", f"network.num_sensors={sensors}", f"network.num_comm={nodes - sensors}",
                     f"scenario.horizon={steps * 0.25}", "data.train_episodes=1", "data.test_episodes=1", *gp, *extra])


def _network_world(cfg, device: str, episodes: int = 1):
    """The study of ``cfg`` on ``device``, its step context, ``episodes`` drawn episodes (seed 2, float64) and
    ``init(measurements, fusion)``, the filter's initial belief."""
    from dslearn import api
    from dslearn.filters.distributed import initial_belief

    cfg.device = device
    study = api.build_study(cfg)
    scenario, network = study.scenario, study.network
    ctx = scenario.ctx()
    ep = scenario.sample(episodes, network, torch.Generator().manual_seed(2)).to(torch.float64, device)

    def init(m, f):
        return initial_belief(m, network, ctx.dt, f, scenario.area, cfg.filter.prior_pos_std, cfg.filter.prior_vel_std)

    return study, ctx, ep, init


def _timed(fn, device: str):
    """``(fn(), seconds)``, CUDA work included (synchronised)."""
    t0 = time.perf_counter()
    out = fn()
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    return out, time.perf_counter() - t0


def item_network(nodes: int, steps: int = 100, ref_steps: int = 0, device: str = "cpu") -> list[dict]:
    from dslearn import api
    from dslearn.filters.distributed import track

    cfg = _network_cfg(nodes, steps)
    study, ctx, ep, init_of = _network_world(cfg, device)
    scenario, network, model, obs, fusion = study.scenario, study.network, study.model, study.observation, study.fusion
    init = init_of(ep.measurements, fusion)
    res, wall = _timed(lambda: track(ep.measurements, network, model, obs, fusion, ctx, init, learn=True), device)
    assert bool(torch.isfinite(res.mean).all())
    row = dict(workload="network", item=f"network S={nodes}, {steps} steps, GP learning, hybrid", nodes=nodes, wall_s=wall,
               ms_per_step=1e3 * wall / steps, ms_per_node_step=1e3 * wall / (steps * nodes),
               peak_mb=_peak_mb(), cuda_peak_mb=_cuda_peak_mb(device))
    if ref_steps:
        from dslearn.reference import ReferenceFusion, ReferenceGP, ReferenceYu
        from dslearn.episodes import Episodes

        mc = cfg.model
        ref_nodes = [ReferenceGP(scenario.state_dim, mc.outputscale, mc.lengthscale, mc.noise_std, mc.mean, mc.noise, torch.float64)
                     for _ in range(nodes)]
        part = Episodes(ep.states[:, : ref_steps + 1].cpu(), ep.meas[:, :, : ref_steps + 1].cpu(), ep.visible[:, :, : ref_steps + 1].cpu())
        ref = ReferenceYu(cfg)
        t0 = time.perf_counter()
        ref._track_one(part.measurements, 0, ref_nodes, ReferenceFusion.from_config(cfg.consensus, network.adjacency),
                       float(obs.noise_std) ** 2, init[0][:, 0].cpu(), init[1][:, 0].cpu(), learn=True, gate=None)
        t_ref = time.perf_counter() - t0
        part_fast = Episodes(ep.states[:, : ref_steps + 1], ep.meas[:, :, : ref_steps + 1], ep.visible[:, :, : ref_steps + 1])
        fresh = api.build_study(cfg)
        network2, model2, obs2, fusion2 = fresh.network, fresh.model, fresh.observation, fresh.fusion
        t0 = time.perf_counter()
        track(part_fast.measurements, network2, model2, obs2, fusion2, ctx, init, learn=True)
        t_fast = time.perf_counter() - t0
        row.update(reference_s=t_ref, ratio=t_ref / t_fast,
                   reference_note=f"both timed on the first {ref_steps} steps only (ratio of those)")
    return [row]


def item_filters(filter: str, nodes: int, steps: int = 50, model: str = "gp_increment", device: str = "cpu",
                 particles: int | None = None) -> list[dict]:
    """One prediction step (``filter=<filter>``) inside the distributed filter: S nodes tracking 2 agents for
    ``steps`` steps, hybrid consensus, the GP learned online (``model=gp_increment``; ``lin``: no learning);
    ``particles``: the GP-PF's particles per node and target belief (``filter=pf``)."""
    from dslearn.compose import build_predict
    from dslearn.filters.distributed import track

    extra = (f"filter={filter}",) + ((f"filter.predict.particles={int(particles)}",) if particles is not None else ())
    cfg = _network_cfg(nodes, steps, model, extra)
    study, ctx, ep, init_of = _network_world(cfg, device)
    network, mdl, obs, fusion = study.network, study.model, study.observation, study.fusion
    init, learn, step = init_of(ep.measurements, fusion), model.startswith("gp"), build_predict(cfg)
    res, wall = _timed(lambda: track(ep.measurements, network, mdl, obs, fusion, ctx, init, learn=learn,
                                     predict_step=step), device)
    assert bool(torch.isfinite(res.mean).all())
    what = "GP learned online" if learn else f"model={model}"
    n = f" particles={int(particles)}" if particles is not None else ""
    return [dict(workload="filters", item=f"filter={filter}{n} S={nodes}, {steps} steps, {what}, hybrid", nodes=nodes,
                 wall_s=wall, ms_per_step=1e3 * wall / steps, ms_per_node_step=1e3 * wall / (steps * nodes),
                 peak_mb=_peak_mb(), cuda_peak_mb=_cuda_peak_mb(device))]


def item_backprop(nodes: int, episodes: int = 8, steps: int = 40, epochs: int = 3, device: str = "cpu",
                  model: str = "lin") -> list[dict]:
    """One training epoch of ``learner=backprop`` (forward through the filter and the L consensus rounds, backward,
    Adam step) on ``episodes`` episodes of ``steps`` steps, against one forward pass of the same EKF on the same
    episodes without gradients (the reference column: its time, and epoch / forward). ``model=lin``: Q, R, weights
    and omega learned; ``sfm`` / ``gp_increment``: the model's own parameters too (the GP on the data it gathered
    online on the same episodes first, Q not learned)."""
    from dslearn.filters.distributed import track
    from dslearn.learning.backprop import BackpropParameters, fit, motion_parameters
    from dslearn.types import AGENT_DIM

    cfg = _network_cfg(nodes, steps, model)
    study, ctx, ep, init = _network_world(cfg, device, episodes)
    network, mdl, obs, fusion = study.network, study.model, study.observation, study.fusion
    if mdl.learnable:  # the GP: its data sets first, online on the same episodes, one at a time (Algorithm 1)
        for i in range(len(ep)):
            one = ep.measurements.select(slice(i, i + 1))
            track(one, network, mdl, obs, fusion, ctx, init(one, fusion), learn=True)
    motion = motion_parameters(mdl, mdl.state_dim // AGENT_DIM, ctx.dt)
    zeros = torch.zeros(1, mdl.state_dim, dtype=torch.float64, device=device)
    q_block = (mdl.noise_cov(zeros, ctx)[0, :AGENT_DIM, :AGENT_DIM] if motion.takes_q
               else torch.eye(AGENT_DIM, dtype=torch.float64, device=device))
    learn = ["q", "r", "weights", "omega"] if model == "lin" else [*(["q"] if motion.takes_q else []), "model", "r",
                                                                    "weights", "omega"]
    params = BackpropParameters(mdl.state_dim // AGENT_DIM, None, q_block,
                                obs.noise_cov(torch.zeros(1, AGENT_DIM, dtype=torch.float64, device=device))[0],
                                fusion, network.adjacency, learn=learn, motion=motion)
    hist = fit(params, ep, network, ctx, init, epochs=epochs, lr=0.05)
    t_epoch = sum(hist.seconds[1:]) / max(len(hist.seconds) - 1, 1)  # the first epoch warms up
    with torch.no_grad():
        _, t_fwd = _timed(lambda: track(ep.measurements, network, mdl, obs, fusion, ctx, init(ep.measurements, fusion)),
                          device)
    what = "" if model == "lin" else f" model={model} ({'+'.join(learn)})"
    return [dict(workload="filters", item=f"learner=backprop{what} S={nodes}, {episodes} episodes x {steps} steps: one "
                                          f"epoch, hybrid",
                 nodes=nodes, wall_s=t_epoch, ms_per_step=1e3 * t_epoch / steps,
                 ms_per_node_step=1e3 * t_epoch / (steps * nodes), peak_mb=_peak_mb(), cuda_peak_mb=_cuda_peak_mb(device),
                 reference_s=t_fwd, ratio=t_epoch / t_fwd,
                 reference_note="reference: the EKF's forward pass on the same episodes, no gradients (ratio epoch / forward)")]


#: the ``matrix`` workload's settings (``dslearn-bench matrix key=value ...``) and their defaults: a representative
#: few cells (the LSTM, the online GP and LIN with hybrid consensus on Liu's 200-sensor field and Yu's 10 nodes),
#: with the episodes of ``experiment=matrix``
MATRIX_DEFAULTS = {"methods": ["ekf_lstm_hybrid", "ekf_gp_hybrid", "ekf_lin_hybrid"],
                   "scenarios": ["liu_s1", "yu_two_agents"], "train": 10, "test": 10, "seed": 0, "cache": "fresh"}
MATRIX_CACHE = ("fresh", "off", "user")
#: the parts of a cell the ``matrix`` workload times (seconds columns of its rows)
MATRIX_PARTS = ("draw_s", "offline_fit_s", "online_learn_s", "estimate_s")


def _options(dirname: str) -> list[str]:
    from dslearn.conf_paths import CONF_DIR

    return sorted(p.stem for p in (Path(CONF_DIR) / dirname).glob("*.yaml"))


def matrix_settings(tokens: list[str]) -> dict:
    """The ``matrix`` workload's settings from ``key=value`` tokens (:data:`MATRIX_DEFAULTS` for the others);
    lists as ``[a,b]`` or ``a,b``. ConfigError naming ``matrix.<key>`` and the allowed values."""
    from dslearn.errors import ConfigError

    out = {k: (list(v) if isinstance(v, list) else v) for k, v in MATRIX_DEFAULTS.items()}
    for tok in tokens:
        key, _, val = tok.partition("=")
        key = key.strip()
        if key not in MATRIX_DEFAULTS:
            raise ConfigError(f"matrix.{key}: unknown setting; allowed: {', '.join(MATRIX_DEFAULTS)}")
        if key in ("methods", "scenarios"):
            names = [v.strip() for v in val.strip().strip("[]").split(",") if v.strip()]
            allowed = _options("method" if key == "methods" else "scenario")
            bad = [n for n in names if n not in allowed]
            if not names or bad:
                raise ConfigError(f"matrix.{key}={val!r}: {'unknown ' + ', '.join(bad) if bad else 'empty'}; "
                                  f"allowed: {', '.join(allowed)}")
            out[key] = names
        elif key == "cache":
            if val not in MATRIX_CACHE:
                raise ConfigError(f"matrix.cache={val!r}: allowed: {', '.join(MATRIX_CACHE)}")
            out[key] = val
        else:
            lo = 1 if key == "test" else 0
            try:
                n = int(val)
            except ValueError:
                n = None
            if n is None or n < lo:
                raise ConfigError(f"matrix.{key}={val!r} must be an integer >= {lo}")
            out[key] = n
    return out


def item_matrix(method: str, scenario: str, train: int = 10, test: int = 10, seed: int = 0,
                cache_dir: str | None = None, overrides: tuple = ()) -> list[dict]:
    """One matrix cell (``task=matrix method=<method> scenario=<scenario>``) as ``dslearn-run`` runs it, in this
    process, with the wall time of its parts: ``build_s`` (composition: the scenario, its network, the method's
    parts), ``draw_s`` (the training and test episodes), ``offline_fit_s`` (the motion model's offline fit, or its
    load from the offline-fit cache: ``fit_cache`` says which), ``online_learn_s`` (Algorithm 1 on the training
    episodes), ``estimate_s`` (tracking the test episodes), ``cell_s`` (the cell's ``runtime_s``: learning and
    estimation; for an engine other than the distributed filter only that total), ``peak_mb`` (the process's peak
    resident memory, ``base_mb`` of it before the cell). ``cache_dir``: ``$DSLEARN_CACHE_DIR`` for the cell;
    ``overrides``: more of the cell's settings (``model.epochs=2``)."""
    import dslearn.studies.matrix as cell_mod
    from dslearn import api
    from dslearn.diagnostics import Diagnostics
    from dslearn.learning.online import OnlineLearner
    from dslearn.methods.distributed import DistributedFilter

    env = os.environ.get("DSLEARN_CACHE_DIR")
    if cache_dir is not None:
        os.environ["DSLEARN_CACHE_DIR"] = cache_dir
    base = _peak_mb()
    parts = dict.fromkeys(MATRIX_PARTS, 0.0)

    def timed(fn, key):
        def wrapper(*args, **kwargs):
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                parts[key] += time.perf_counter() - t
        return wrapper

    saved = (cell_mod.sample_split, OnlineLearner.run, OnlineLearner.estimate)
    cell_mod.sample_split = timed(saved[0], "draw_s")
    OnlineLearner.run, OnlineLearner.estimate = timed(saved[1], "online_learn_s"), timed(saved[2], "estimate_s")
    try:
        t0 = time.perf_counter()
        cfg = _compose(["task=matrix", f"method={method}", f"scenario={scenario}", f"task.train_episodes={int(train)}",
                        f"task.test_episodes={int(test)}", f"seed={int(seed)}", *overrides])
        study = api.build_study(cfg)
        build = time.perf_counter() - t0
        model = getattr(study.method, "model", None)
        if getattr(model, "learns_offline", False):  # the fit itself (the cache's load, if any, is in diag)
            model.fit_offline = timed(model.fit_offline, "offline_fit_s")
        with Diagnostics() as diag:
            df = study.run(diagnostics=diag)
    finally:
        cell_mod.sample_split, OnlineLearner.run, OnlineLearner.estimate = saved
        if env is None:
            os.environ.pop("DSLEARN_CACHE_DIR", None)
        else:
            os.environ["DSLEARN_CACHE_DIR"] = env
    cell = float(df.loc[df.metric == "runtime_s", "value"].iloc[0])
    counts, fitted = diag.counts, parts["offline_fit_s"] > 0
    parts["offline_fit_s"] = float(diag.timings.get("offline_fit_s", parts["offline_fit_s"]))
    fit = ("loaded" if counts.get("offline_fit_cache_hits") else "fitted, stored" if counts.get("offline_fit_cache_stored")
           else "fitted" if fitted else "")
    rmse = df[(df.metric == "rmse") & (df.node_kind == "sensor")]["value"]
    split = isinstance(study.method, DistributedFilter)  # the distributed filter: its parts are timed
    return [dict(workload="matrix", item=f"{method} on {scenario}, {train}+{test} ep, seed {seed}", method=method,
                 scenario=scenario, train=int(train), test=int(test), seed=int(seed), build_s=build,
                 **{k: (v if split or k == "draw_s" else float("nan")) for k, v in parts.items()},
                 cell_s=cell, wall_s=build + parts["draw_s"] + cell, fit_cache=fit,
                 rmse=float(rmse.mean()) if len(rmse) else float("nan"), base_mb=base, peak_mb=_peak_mb())]


def item_study(args: list[str], label: str) -> list[dict]:
    rc, wall, rss = _timed_cli(args, "hydra.run.dir")
    return [dict(workload="studies", item=f"dslearn-run {' '.join(args)}" + ("" if rc == 0 else f" (FAILED rc={rc})"), wall_s=wall,
                 peak_mb=rss, reference_note=label)]


def _child(fn_name, kwargs, threads, q):
    torch.set_num_threads(threads)
    try:
        q.put(("ok", globals()[fn_name](**kwargs)))
    except Exception as e:  # noqa: BLE001 - a failed item is reported in the table, not fatal
        q.put(("err", f"{type(e).__name__}: {e}"))


def run_item(fn_name: str, threads: int = 1, **kwargs) -> list[dict]:
    """Run one item in a fresh spawned process (own peak memory); returns its rows."""
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=_child, args=(fn_name, kwargs, threads, q))
    p.start()
    status, payload = q.get()
    p.join()
    if status != "ok":
        print(f"  {fn_name}({kwargs}) failed: {payload}", flush=True)
        return [dict(workload=fn_name.replace("item_", ""), item=f"{kwargs} FAILED: {payload}")]
    for r in payload:
        print("  " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in r.items() if v is not None), flush=True)
    return payload


def run_parallel(jobs: list[tuple[str, dict]], workers: int, threads: int = 1) -> tuple[list[dict], float]:
    """Run items in ``workers`` concurrent fresh processes; returns rows and total wall time."""
    from concurrent.futures import ProcessPoolExecutor

    t0 = time.perf_counter()
    rows = []
    with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"),
                             initializer=torch.set_num_threads, initargs=(threads,)) as ex:
        futs = [ex.submit(_call, name, kw) for name, kw in jobs]
        for f in futs:
            rows += f.result()
    return rows, time.perf_counter() - t0


def _call(name, kw):
    out = globals()[name](**kw)
    for r in out:
        print(f"  {r['item']}: {r['wall_s']:.1f}s", flush=True)
    return out


# ------------------------------------------------------------------------------------------
def plot_gp(df: pd.DataFrame, path: Path) -> dict:
    """log-log plot of ms per node step vs n; returns the fitted slopes per variant."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    slopes = {}
    fig, ax = plt.subplots(figsize=(6, 4.2))
    g = df[(df.workload == "gp") & (df.nodes == 1)]
    for variant, sub in g.groupby("variant"):
        sub = sub.sort_values("n")
        x, y = np.log10(sub.n.to_numpy(float)), np.log10(sub.ms_per_node_step.to_numpy(float))
        fit = sub.n >= 1000
        slope = float(np.polyfit(x[fit], y[fit], 1)[0]) if fit.sum() >= 2 else float("nan")
        slopes[variant] = slope
        ax.loglog(sub.n, sub.ms_per_node_step, "o-", label=f"{variant} (slope {slope:.2f})")
    ref = g[g.variant == "exact"].dropna(subset=["ratio"]) if "ratio" in g else g.iloc[:0]
    if len(ref):
        rms = ref.ms_per_node_step * ref.ratio
        fit = ref.n >= 1000
        rs = float(np.polyfit(np.log10(ref.n[fit]), np.log10(rms[fit]), 1)[0]) if fit.sum() >= 2 else float("nan")
        slopes["refit from scratch"] = rs
        ax.loglog(ref.n, rms, "s--", color="grey", label=f"refit from scratch (slope {rs:.2f})")
    ax.set_xlabel("data-set size n (points per node)")
    ax.set_ylabel("ms per GP step per node (predict + append)")
    ax.set_title("Online GP step cost (1 node, 1 thread; slopes fitted on n >= 1000)", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return slopes


def plan(workloads, quick: bool, a) -> list:
    """The list of (item function, kwargs) or parallel groups to run."""
    steps = []
    models, fusions = a.models.split(","), a.fusions.split(",")
    if "speed" in workloads:  # the figures of the speed targets: one configuration, then the Table I grid
        tr, te = (50, 50) if quick else (200, 50)
        steps.append(("item_speed_config", dict(train=tr, test=te)))
        if not quick:
            steps.append(("item_grid", dict(experiment="yu_table1")))
    if "reference" in workloads:
        tr, te = (2, 2) if quick else (a.ref_train, a.ref_test)
        for m in a.ref_models.split(","):
            for f in a.ref_fusions.split(","):
                steps.append(("item_reference", dict(model=m, fusion=f, train=tr, test=te, device=a.device)))
    if "gp" in workloads:
        exact = (300, 600, 1200, 2400) if quick else (300, 600, 1200, 2400, 5000, 10000)
        sparse = (600, 2400, 10000) if quick else (600, 2400, 10000, 50000)
        for n in exact:
            steps.append(("item_gp", dict(variant="exact", n=n, ref_steps=(2 if n <= 5000 else 1))))
        for v in ("window", "sgpr", "ssgp"):
            for n in sparse:
                steps.append(("item_gp", dict(variant=v, n=n)))
        if not quick:
            steps.append(("item_gp", dict(variant="exact", n=2400, nodes=10, ref_steps=1)))
    if "fantasy" in workloads and not quick:
        steps.append(("item_fantasy", dict(n=2400)))
    if "network" in workloads:
        for s in ((10, 50, 200) if quick else (10, 50, 200, 1000)):
            steps.append(("item_network", dict(nodes=s, ref_steps=(10 if s <= 50 else 0), device=a.device)))
    if "filters" in workloads:  # the cost of each prediction step, and of a backprop epoch against the EKF
        for s in ((10, 50) if quick else (10, 50, 200)):
            for f in ("default", "ukf", "ukf_mm", "adf"):
                steps.append(("item_filters", dict(filter=f, nodes=s, steps=(20 if quick else 100), device=a.device)))
            for n in ((100, 500) if quick else (100, 500, 2000)):  # the GP-PF: nodes x particles
                steps.append(("item_filters", dict(filter="pf", nodes=s, steps=(20 if quick else 100), device=a.device,
                                                   particles=n)))
            steps.append(("item_backprop", dict(nodes=s, episodes=(4 if quick else 8), device=a.device)))
            for m in ("sfm", "gp_increment"):  # the motion model's own parameters as well
                steps.append(("item_backprop", dict(nodes=s, episodes=(4 if quick else 8), device=a.device, model=m)))
    if "dtype" in workloads:
        tr, te = (20, 20) if quick else (200, 50)
        steps.append(("parallel", [("item_protocol", dict(model="gp_increment", fusion="hybrid", train=tr, test=te, dtype=d, device=a.device,
                                                        workload="dtype"))
                                   for d in ("float64", "float32")]))
    if "protocol" in workloads:
        tr, te = (a.train, a.test) if not quick else (50, 50)
        steps.append(("parallel", [("item_protocol", dict(model=m, fusion=f, train=tr, test=te, device=a.device))
                                   for m in sorted(models, key=lambda m: not m.startswith("gp")) for f in fusions]))
    if "matrix" in workloads:  # cells one after another, methods in the order given (the first fit pays)
        m = getattr(a, "matrix", None) or matrix_settings([])
        cache = {"off": "off", "user": None}.get(m["cache"], getattr(a, "matrix_cache_dir", None))
        for sc in m["scenarios"]:
            for meth in m["methods"]:
                steps.append(("item_matrix", dict(method=meth, scenario=sc, train=m["train"], test=m["test"],
                                                  seed=m["seed"], cache_dir=cache)))
    if "studies" in workloads:
        for args, label in ((["experiment=jiang_fg"], "default run"), (["experiment=braga_tbn"], "default run"),
                            (["task=liu_dgpt"], "default run")):
            steps.append(("item_study", dict(args=args, label=label)))
    return steps


def eta_measure(model: str = "gp_increment", episodes: int = 150) -> list[str]:
    """Measure the CPU time of each online-learning episode of the Yu study and compare the
    ETA a plain bar and the cost-weighted bar would show with the true remaining time
    (``dslearn-bench eta``; one thread)."""
    import numpy as np
    import torch

    from dslearn.filters.distributed import initial_belief, track as track_episode
    from dslearn.progress import episode_costs
    from dslearn import api

    torch.set_num_threads(1)
    c = api.compose("task=yu", f"model={model}", "consensus=hybrid", f"data.train_episodes={episodes}", "data.test_episodes=2")
    study = api.build_study(c)
    scenario, network, m, obs, fusion = study.scenario, study.network, study.model, study.observation, study.fusion
    _, train = study.sample()
    ctx = scenario.ctx()
    ts = []
    for k in range(episodes):
        ep = train.select(slice(k, k + 1)).measurements
        init = initial_belief(ep, network, ctx.dt, fusion, scenario.area, c.filter.prior_pos_std, c.filter.prior_vel_std)
        t = time.process_time()
        track_episode(ep, network, m, obs, fusion, ctx, init, learn=True)
        ts.append(time.process_time() - t)
    ts = np.array(ts)
    costs = np.array(episode_costs(episodes, scenario.steps, c.model))
    out = [f"{model}: {episodes} episodes, CPU {ts.sum():.1f} s, first 5 {ts[:5].mean():.3f} s/episode, "
           f"last 5 {ts[-5:].mean():.3f} s/episode"]
    for frac in (0.1, 0.2, 0.5):
        j = max(1, int(frac * episodes))
        el, true = ts[:j].sum(), ts[j:].sum()
        plain = el / j * (episodes - j)
        weighted = el * costs[j:].sum() / costs[:j].sum()
        out.append(f"after {j}: true remaining {true:.1f} s, plain ETA {plain:.1f} s ({true / plain:.2f}x optimistic), "
                   f"weighted ETA {weighted:.1f} s (true/weighted {true / weighted:.2f})")
    return out


def plain_text(rst: str) -> str:
    """The module docstring as plain text for ``--help``: reStructuredText roles (``:mod:`x```,
    ``:data:`~x```) become their target's name, literals (````x````) their text."""
    text = re.sub(r":[a-z]+:`(~?)([^`]+)`", lambda m: m.group(2).rsplit(".", 1)[-1] if m.group(1) else m.group(2), rst)
    return text.replace("``", "")


EPILOG = """examples:
  dslearn-bench --quick                      the reduced suite (a few minutes): figures into bench-results/<date_time>/
  dslearn-bench speed                        the speed targets only
  dslearn-bench reference --ref-models lin,gp --ref-fusions hybrid
  dslearn-bench matrix methods=[ekf_lstm_hybrid,ukf_lstm_hybrid] scenarios=[liu_s1] train=10 test=10
  dslearn-bench --merge bench-results/a bench-results/b --out bench-results/all

exit codes: 0 done, 1 a reference disagrees or an item failed, 2 bad arguments."""


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="dslearn-bench", description=plain_text(__doc__), epilog=EPILOG,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("workloads", nargs="*", help=f"any of {', '.join(ALL)} (default: all); the matrix workload's "
                                                f"settings as key=value: {', '.join(MATRIX_DEFAULTS)}")
    p.add_argument("--quick", action="store_true", help="reduced sizes: a few minutes")
    p.add_argument("--models", default="lin,sfm,gp_increment",
                   help="protocol / dtype workloads: motion models, comma-separated (default: %(default)s)")
    p.add_argument("--fusions", default="individual,hybrid",
                   help="protocol / dtype workloads: consensus options, comma-separated (default: %(default)s)")
    p.add_argument("--train", type=int, default=200, help="training episodes of the full protocol (default: %(default)s)")
    p.add_argument("--test", type=int, default=50, help="test episodes of the full protocol (default: %(default)s)")
    p.add_argument("--ref-train", type=int, default=5, help="reference workload: training episodes (reduced protocol)")
    p.add_argument("--ref-test", type=int, default=5, help="reference workload: test episodes (reduced protocol)")
    p.add_argument("--ref-models", default="lin,sfm,gp,gp_increment,gp_window",
                   help="reference workload: models (every one the reference implements)")
    p.add_argument("--ref-fusions", default="individual,ce,cm,ci,hybrid,hybrid_nodes,centralized",
                   help="reference workload: consensus options (every strategy; hybrid_nodes: omega = nodes)")
    p.add_argument("--workers", type=int, default=2, help="concurrent processes for the protocol / dtype items")
    p.add_argument("--threads", type=int, default=1, help="torch threads per process")
    p.add_argument("--device", default="cpu", help="cpu | cuda (default: %(default)s)")
    p.add_argument("--out", default=None, help="output folder (default: a new bench-results/<date>_<time>)")
    p.add_argument("--merge", nargs="+", metavar="DIR", help="only merge the bench.csv of earlier runs into --out")
    a = p.parse_args(argv)
    if a.out is None:
        a.out = str(Path("bench-results") / time.strftime("%Y-%m-%d_%H-%M-%S"))
    print(f"dslearn-bench: writing to {a.out}", flush=True)
    if a.merge:
        return merge(a.merge, a.out)
    from dslearn.errors import ConfigError

    settings = [w for w in a.workloads if "=" in w]
    workloads = [w for w in a.workloads if "=" not in w]
    workloads = workloads or [w for w in ALL if not (a.quick and w in ("studies", "fantasy", "matrix"))]
    bad = [w for w in workloads if w not in ALL]
    if bad:
        p.error(f"unknown workload(s) {bad}; choose from {', '.join(ALL)}")
    if settings and "matrix" not in workloads:
        p.error(f"{' '.join(settings)}: key=value settings belong to the matrix workload (dslearn-bench matrix ...)")
    try:
        a.matrix = matrix_settings(settings)
    except ConfigError as e:
        p.error(str(e))
    fresh = None
    if "matrix" in workloads and a.matrix["cache"] == "fresh":  # one new offline-fit cache for the workload's cells
        fresh = tempfile.TemporaryDirectory(prefix="dslearn-bench-fit-cache-")
        a.matrix_cache_dir = fresh.name
    torch.set_num_threads(a.threads)
    info = machine_info()
    print("machine: " + ", ".join(f"{k}={v}" for k, v in info.items()), flush=True)
    rows = []
    t_all = time.perf_counter()
    for name, kw in plan(workloads, a.quick, a):
        if name == "parallel":
            r, wall = run_parallel(kw, a.workers, a.threads)
            rows += r
            label = "dtype" if any(j[1].get("dtype") == "float32" for j in kw) else "protocol"
            rows.append(dict(workload=label, item=f"{label}: all {len(kw)} runs end to end, {a.workers} processes x {a.threads} thread",
                             wall_s=wall, nodes=10, peak_mb=max((x.get("peak_mb") or 0) for x in r),
                             reference_note=f"sum of the runs' own wall times: {sum(x['wall_s'] for x in r):.1f}s"))
            print(f"  {rows[-1]['item']}: {wall:.1f}s", flush=True)
        else:
            rows += run_item(name, a.threads, **kw)
    total = time.perf_counter() - t_all
    if fresh is not None:
        fresh.cleanup()
    info["loadavg_after"] = " ".join(f"{v:.2f}" for v in os.getloadavg())
    info["suite"] = "quick" if a.quick else "full"
    info["total_s"] = round(total, 1)
    df = pd.DataFrame(rows)
    for k, v in info.items():
        df[k] = v
    write_outputs(df, Path(a.out))
    bad = reference_failures(rows)
    if bad:
        print("\ndslearn-bench: the fast path and the reference differ (dslearn.reference.REFERENCE_TOL) in:\n  "
              + "\n  ".join(bad), file=sys.stderr, flush=True)
        raise SystemExit(1)


def write_outputs(df: pd.DataFrame, out: Path) -> str:
    """``bench.csv``, ``bench.md`` (machine lines, table, slopes, protocol ratio) and the GP plot."""
    from dslearn.reports.tables import markdown

    out.mkdir(parents=True, exist_ok=True)
    extra = []
    if (df.workload == "gp").any():
        slopes = plot_gp(df, out / "gp_step_cost.png")
        extra.append("GP step cost slopes (log-log, n >= 1000): " + ", ".join(f"{k} {v:.2f}" for k, v in slopes.items()))
    # the protocol acceptance figure: fast vs reference on the same reduced protocol
    ref = df[df.workload == "reference"]
    if len(ref) and "reference_s" in ref:
        extra.append(f"reduced protocol ({len(ref)} runs): fast {ref.wall_s.sum():.1f}s, reference {ref.reference_s.sum():.1f}s, "
                     f"ratio {ref.reference_s.sum() / ref.wall_s.sum():.1f}x (same process, same protocol)")
    cols = [c for c in ("workload", "item", "n", "nodes", "wall_s", "build_s", *MATRIX_PARTS, "cell_s", "fit_cache",
                        "rmse", "base_mb", "ms_per_step", "ms_per_node_step", "reference_s",
                        "reference_ms_per_step", "ratio",
                        "max_abs_diff", "max_diff", "track_err", "pred_err", "peak_mb", "cuda_peak_mb", "reference_note") if c in df]
    show = df[cols].copy()
    for c in show.columns:
        if show[c].dtype.kind == "f":
            show[c] = show[c].map(lambda v: "" if pd.isna(v) else (f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"))
    show = show.fillna("")
    mcols = [c for c in ("cpu", "cores", "torch", "threads", "python", "loadavg_1_5_15", "loadavg_after", "suite", "total_s") if c in df]
    machines = df[mcols].drop_duplicates()
    head = "\n".join("Machine: " + ", ".join(f"{k}={v}" for k, v in r.items()) for r in machines.to_dict("records"))
    md = "\n\n".join([head, markdown(show), *extra])
    atomic_write_csv(df, out / "bench.csv")
    atomic_write_text(out / "bench.md", md + "\n")
    print(md)
    print(f"\nwrote {out / 'bench.csv'}, {out / 'bench.md'}")
    return md


def merge(dirs: list[str], out: str) -> None:
    """Concatenate the ``bench.csv`` of several runs (e.g. workloads run separately) into one table."""
    df = pd.concat([pd.read_csv(Path(d) / "bench.csv") for d in dirs], ignore_index=True)
    write_outputs(df, Path(out))

if __name__ == "__main__":
    main()
