r"""Distributed online EM for the TBN scenario: RBPF + online E-step at every node, cooperation on the
sufficient statistics, M-step (Section V), vectorised over Monte Carlo runs × strategies × nodes × particles.

Per time step t (all batches at once):

1. every node runs Algorithm 1 (RBPF) and Algorithm 2 (online E-step) with its current theta -> S_{s,t};
2. the statistics are combined per strategy (identity / Eq. 19 average / Algorithm 3 consensus);
3. after the burn-in, every node runs the M-step (Eq. 8) on its combined statistics.

All strategies of one Monte Carlo run see the same truth and measurements (common random numbers).
:func:`run_tbn` sees only the measurements (and the initial state, known in the paper's Section VI);
:func:`score_tbn` computes the errors against the truth. The Monte Carlo harness of the study
(:func:`tbn_params`, :func:`prepare_job`, :func:`simulate_and_filter`) builds the terrain, the models
and each batch's flights from the plain values of a checked ``braga_tbn`` task (:mod:`dslearn.schemas.braga_tbn`;
the study converts its configuration, :func:`dslearn.studies.braga_tbn.job_from_config`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from dslearn.errors import ConfigError
from dslearn.filters.rbpf import ess, init_state, posterior_mean, rbpf_step
from dslearn.fusion.statistics import (combination_matrices, network_adjacency, parse_strategy,
                                       throughput_bytes_per_step, weight_matrix)
from dslearn.models.jmnls import NoiseParams, m_step, make_params, params_dim, stats_dim
from dslearn.models.linear_gaussian import LinearGaussianDynamics
from dslearn.sim.terrain import Scenario, cv_model, make_terrain, simulate
from dslearn.streams import Streams


@dataclass
class TBNResult:
    """Per-step traces, batch (R, C) or (R, C, S).

    Attributes:
        est: (T, R, C, S, 4) posterior-mean states (position, velocity) after step t.
        mu, sigma: (T, R, C, S, K) parameter estimates after the step-t M-step.
        pi: (T, R, C, S, K, K) TPM estimates.
        pos_se: (T, R, C, S) squared position error ||p_hat - p||^2 [m^2], filled by :func:`score_tbn`
            (the filter itself never sees the truth).
        diagnostics: with ``diagnostics=True``, per-step (T, R, C, S) traces: ``ess`` (before resampling),
            ``spread`` (weighted RMS distance of the particle positions from their mean [m]), ``p_mode_last``
            (posterior probability of the last mode), ``resampled`` (bool), and from :func:`score_tbn`
            ``vel_se`` (squared velocity error [(m/s)^2]) and ``h_misfit`` (terrain height at the estimate minus
            at the truth [m]).
        counters: event counts: ``resample_events`` and ``degenerate_events`` (R, C) summed over nodes and
            time (a degenerate event = all weights of a node underflowed and were reset to uniform),
            ``sigma_clamped``, ``offmap_particles`` (sampled every 50 steps), ``filter_steps``.
    """

    est: Tensor
    mu: Tensor
    sigma: Tensor
    pi: Tensor
    counters: dict = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)
    pos_se: Tensor | None = None


def run_tbn(y: Tensor, terrain, x0: Tensor, strategies, weights: Tensor, init: NoiseParams,
            dyn: LinearGaussianDynamics, *, num_particles: int, gen, r0: Tensor | None = None,
            eta_exponent: float = 0.7, burn_in: int = 50, ess_threshold: float = 0.5, sigma_floor: float = 1e-3,
            init_mode: str = "true", progress: bool = False, diagnostics: bool = False,
            regularise: float = 0.0) -> TBNResult:
    """Run the distributed online EM on a batch of flights, from the measurements only.

    Args:
        y: (R, S, T+1) altimeter measurements of R runs and S nodes (``y[..., 0]`` unused).
        terrain: the map h (a :class:`~dslearn.sim.terrain.TerrainMap`).
        x0: (R, S, 4) initial states; every particle starts there (Section VI: x^{(i)}_{s,0} = x_{s,0}).
        strategies: C strategy names (see :func:`dslearn.fusion.statistics.parse_strategy`).
        weights: (S, S) consensus weights (checked against Eq. 22 by the caller).
        init: initial parameter guess (unbatched, K modes).
        dyn: filter dynamics (Eq. 23 with the filter's Q).
        num_particles: N_P.
        gen: a ``torch.Generator`` or :class:`~dslearn.streams.Streams` over (R, C) (one stream per
            run and strategy: each run's result is then independent of the batch it is in).
        r0: (R, S) initial modes, needed for ``init_mode="true"`` (alpha_{0|0} = 1(r_0 = l), the paper).
        eta_exponent: eta_t = t^-eta_exponent.
        burn_in: the M-step starts after this many steps (E-step runs from t = 1).
        ess_threshold: resampling threshold as a fraction of N_P.
        sigma_floor: lower bound on estimated sigma.
        init_mode: ``true`` (alpha_{0|0} = 1(r_0 = l), as in the paper) or ``uniform``.
        progress: show a tqdm bar over time.
        regularise: post-regularised resampling factor (0: the paper's plain systematic resampling).
        diagnostics: also record the per-step traces listed in :class:`TBNResult` (for lost-track analysis).
    """
    r_, s_, t1 = y.shape
    nx = x0.shape[-1]
    steps = t1 - 1
    c_ = len(strategies)
    bshape = (r_, c_, s_)
    dtype, device = x0.dtype, x0.device
    comb = combination_matrices(strategies, weights.to(dtype=dtype, device=device))  # (C, S, S)
    theta = NoiseParams(init.mu.to(dtype=dtype, device=device), init.sigma.to(dtype=dtype, device=device),
                        init.pi.to(dtype=dtype, device=device)).expand(*bshape)
    k = init.k
    x0 = x0[:, None].expand(r_, c_, s_, nx)
    if init_mode == "true":
        if r0 is None:
            raise ValueError("run_tbn: init_mode='true' needs the initial modes r0")
        alpha0 = torch.nn.functional.one_hot(r0, k).to(dtype)[:, None].expand(r_, c_, s_, k)
    else:
        alpha0 = torch.full((r_, c_, s_, k), 1.0 / k, dtype=dtype, device=device)
    state = init_state(x0, num_particles, alpha0)
    h = terrain
    est_tr = torch.empty(steps, r_, c_, s_, nx, dtype=dtype, device=device)
    mu_tr = torch.empty(steps, *bshape, k, dtype=dtype, device=device)
    sg_tr = torch.empty_like(mu_tr)
    pi_tr = torch.empty(steps, *bshape, k, k, dtype=dtype, device=device)
    counters = {"resample_events": torch.zeros(r_, c_, dtype=torch.long, device=device),
                "degenerate_events": torch.zeros(r_, c_, dtype=torch.long, device=device),
                "sigma_clamped": 0, "offmap_particles": 0, "filter_steps": steps * r_ * c_ * s_}
    diag = {}
    if diagnostics:
        diag = {name: torch.empty(steps, r_, c_, s_, dtype=dtype, device=device)
                for name in ("ess", "spread", "p_mode_last")}
        diag["resampled"] = torch.empty(steps, r_, c_, s_, dtype=torch.bool, device=device)
    it = range(1, steps + 1)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc="braga_tbn", leave=False)
    for t in it:
        yt = y[:, None, :, t].expand(*bshape)
        eta = float(t) ** (-eta_exponent)
        if diagnostics:
            diag["ess"][t - 1] = ess(state.logw)
        state, stats, info = rbpf_step(state, yt, h, theta, dyn, gen, eta=eta, ess_threshold=ess_threshold,
                                       regularise=regularise)
        counters["resample_events"] += info["resampled"].sum(-1)
        counters["degenerate_events"] += info["degenerate"].sum(-1)
        if t % 50 == 0:
            counters["offmap_particles"] += int(h.outside(state.x).sum())
        glob = torch.einsum("csr,Rcrd->Rcsd", comb, stats)  # cooperation (identity / Eq. 19 / Algorithm 3)
        if t > burn_in:
            theta = m_step(glob, theta, sigma_floor=sigma_floor, counters=counters)
        est = posterior_mean(state)
        est_tr[t - 1] = est
        mu_tr[t - 1] = theta.mu
        sg_tr[t - 1] = theta.sigma
        pi_tr[t - 1] = theta.pi
        if diagnostics:
            w = torch.exp(state.logw)
            dp = state.x[..., :2] - est[..., None, :2]
            diag["spread"][t - 1] = torch.einsum("...i,...i->...", w, (dp * dp).sum(-1)).sqrt()
            diag["resampled"][t - 1] = info["resampled"]
            diag["p_mode_last"][t - 1] = torch.einsum("...i,...i->...", w, state.alpha[..., -1])
    if not (torch.isfinite(est_tr).all() and torch.isfinite(mu_tr).all() and torch.isfinite(sg_tr).all()):
        raise FloatingPointError("non-finite estimate in run_tbn (this is a bug: weights are kept in the log domain)")
    return TBNResult(est_tr, mu_tr, sg_tr, pi_tr, counters, diag)


def score_tbn(res: TBNResult, scn: Scenario) -> TBNResult:
    """The metrics that need the truth: ``res.pos_se`` and, with diagnostics, ``vel_se`` / ``h_misfit``."""
    xt = scn.x[:, None, :, 1:].permute(3, 0, 1, 2, 4)  # (T, R, 1, S, 4)
    d = res.est[..., :2] - xt[..., :2]
    res.pos_se = (d * d).sum(-1)
    if res.diagnostics:
        dv = res.est[..., 2:] - xt[..., 2:]
        res.diagnostics["vel_se"] = (dv * dv).sum(-1)
        res.diagnostics["h_misfit"] = scn.terrain(res.est) - scn.terrain(xt)
    if not torch.isfinite(res.pos_se).all():
        raise FloatingPointError("non-finite position error in score_tbn")
    return res


# ----------------------------------------------------------------------------------------- MC harness
KERNEL_DTYPES = {None: None, "float32": torch.float32, "float64": torch.float64}


def tbn_params(task: dict) -> dict:
    """Plain values and built objects (true / initial parameters, graph, weights) of a checked ``braga_tbn``
    task given as plain values (nested dicts, lists and numbers, resolved: the caller converts its configuration)."""
    if not isinstance(task, dict):
        raise TypeError(f"tbn_params takes the task as a plain dict, not {type(task).__name__}")
    t = task
    p = {k: t[k] for k in ("mc_runs", "mc_batch", "num_particles", "steps", "workers", "strategies",
                           "bytes_per_float", "kilobyte", "filter_streams", "record_every")}
    for k in ("dt", "process_noise", "formation_spacing", "steady_state_s", "truth_process_noise", "lost_track_m",
              "zoom_s"):
        p[k] = float(t[k])
    p["v0"], p["start"] = [float(a) for a in t["v0"]], [float(a) for a in t["start"]]
    m, em, bk, tr = t["modes"], t["em"], t["backward_kernel"], t["terrain"]
    p["truth"] = make_params(m["mu_true"], m["sigma_true"], m["pi_true"], prefix="task.modes (true)")
    p["init"] = make_params(m["mu_init"], m["sigma_init"], m["pi_init"], prefix="task.modes (initial)")
    p["eta_exponent"], p["burn_in"], p["sigma_floor"] = float(em["eta_exponent"]), em["burn_in"], float(em["sigma_floor"])
    p["init_mode"] = "true" if em["init_mode"] is True else em["init_mode"]  # `init_mode=true` on the CLI: a bool
    p["ess_threshold"], p["regularise"] = float(t["ess_threshold"]), float(t["resampling"]["regularise"])
    p["jitter"] = (float(bk["jitter_pos"]), float(bk["jitter_vel"]))
    p["kernel_dtype"] = KERNEL_DTYPES[bk["dtype"]]
    p["terrain"] = {k: float(tr[k]) for k in ("size_m", "resolution_m", "smoothing_m", "elevation_std_m",
                                               "mean_elevation_m")}
    p["terrain_seed_offset"] = int(tr["seed_offset"])
    p["adj"] = network_adjacency(4, t["network"]["edges"])  # finger four: 4 aircraft
    p["fusion_centre"] = t["network"]["fusion_centre"]
    p["weights"] = weight_matrix(p["adj"], t["consensus"]["weights"], t["consensus"]["matrix"])
    return p


def prepare_job(task: dict, *, seed: int, device: str, dtype: str, progress: bool = False) -> dict:
    """Everything the Monte Carlo batches share (terrain, models, recording grid, throughput) from a checked
    task as plain values (:func:`tbn_params`), the run's ``seed``, ``device``, ``dtype`` (``float64`` or
    ``float32``) and whether to show progress."""
    p = tbn_params(task)
    device = torch.device(str(device))
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device=cuda but CUDA is not available")
    dtype = {"float64": torch.float64, "float32": torch.float32}[str(dtype)]
    seed, progress = int(seed), bool(progress)
    kw = dict(dtype=dtype, device=device)
    tgen = torch.Generator(device=device).manual_seed(seed * 7919 + p["terrain_seed_offset"] + 17)
    terrain = make_terrain(**p["terrain"], gen=tgen, **kw)
    truth = p["truth"]
    truth = type(truth)(truth.mu.to(**kw), truth.sigma.to(**kw), truth.pi.to(**kw))
    truth_dyn = cv_model(p["dt"], max(p["truth_process_noise"], 1e-12), p["jitter"], **kw)
    filt_dyn = cv_model(p["dt"], p["process_noise"], p["jitter"], kernel_dtype=p["kernel_dtype"], **kw)
    steps, dt = p["steps"], p["dt"]
    n_zoom = int(round(p["zoom_s"] / dt))
    rec = [t for t in range(1, steps + 1) if t <= n_zoom or t % p["record_every"] == 0]
    thr = {sname: throughput_bytes_per_step(sname, p["adj"], stats_dim(truth.k), params_dim(truth.k),
                                            fusion_centre=p["fusion_centre"], bytes_per_float=p["bytes_per_float"])
                  / dt / p["kilobyte"] for sname in p["strategies"]}
    return dict(p=p, terrain=terrain, truth=truth, truth_dyn=truth_dyn, filt_dyn=filt_dyn, seed=seed,
                device=str(device), dtype=dtype, rec_idx=torch.tensor([t - 1 for t in rec], device=device),
                rec_time=[t * dt for t in rec], thr=thr, progress=progress)


def simulate_and_filter(job: dict, episodes: list[int], diagnostics: bool = False, nodes: list[int] | None = None):
    """Truth, measurements, every strategy's filters and their scores for the Monte Carlo runs ``episodes``.

    Run ``ep`` draws its truth and measurements from the stream (seed, "truth", ep) and each strategy's filter
    from (seed, "filter", ep) (``task.filter_streams=common``: common random numbers) or
    (seed, "filter", ep, strategy) (``independent``), whatever the batch, worker or strategy list.
    ``nodes``: filter only these aircraft (non-cooperative strategies only; for diagnosis).
    Returns ``(scenario, TBNResult)``."""
    p, terrain, truth = job["p"], job["terrain"], job["truth"]
    seed, device, strategies = job["seed"], torch.device(job["device"]), p["strategies"]
    nr = len(episodes)
    common = p["filter_streams"] == "common"
    truth_gen = Streams.from_keys([(seed, "truth", ep) for ep in episodes], (nr,), device=device)
    filt_gen = Streams.from_keys([(seed, "filter", ep) if common else (seed, "filter", ep, sname)
                                  for ep in episodes for sname in strategies], (nr, len(strategies)), device=device)
    scn = simulate(terrain, truth, job["truth_dyn"], runs=nr, start=torch.tensor(p["start"]),
                   v0=torch.tensor(p["v0"]), spacing=p["formation_spacing"], steps=p["steps"], gen=truth_gen)
    weights = p["weights"]
    if nodes is not None:
        if any(parse_strategy(sn)[0] != "noncooperative" for sn in strategies):
            raise ConfigError("filtering a subset of the nodes needs task.strategies=[noncooperative] (the other "
                              "strategies need the whole network)")
        idx = torch.tensor(nodes, device=scn.x.device)
        scn = Scenario(scn.x[:, idx], scn.r[:, idx], scn.y[:, idx], scn.terrain)
        weights = torch.eye(len(nodes), dtype=weights.dtype)
    # the filters get the measurements and the initial state / mode (known at t = 0, Section VI)
    res = run_tbn(scn.y, scn.terrain, scn.x[:, :, 0], strategies, weights, p["init"], job["filt_dyn"],
                  r0=scn.r[..., 0], num_particles=p["num_particles"], gen=filt_gen, burn_in=p["burn_in"],
                  progress=job["progress"], diagnostics=diagnostics, eta_exponent=p["eta_exponent"],
                  ess_threshold=p["ess_threshold"], sigma_floor=p["sigma_floor"], init_mode=p["init_mode"],
                  regularise=p["regularise"])
    return scn, score_tbn(res, scn)
