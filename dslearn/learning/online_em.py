r"""Distributed online EM for the TBN scenario: RBPF + online E-step at every node, cooperation on the
sufficient statistics, M-step (Section V), vectorised over Monte Carlo runs × strategies × nodes × particles.

Per time step t (all batches at once):

1. every node runs Algorithm 1 (RBPF) and Algorithm 2 (online E-step) with its current theta -> S_{s,t};
2. the statistics are combined per strategy (identity / Eq. 19 average / Algorithm 3 consensus);
3. after the burn-in, every node runs the M-step (Eq. 8) on its combined statistics.

All strategies of one Monte Carlo run see the same truth and measurements (common random numbers).
:func:`run_tbn` sees only the measurements (and the initial state, known in the paper's Section VI); the
errors against the truth are computed by :mod:`dslearn.metrics.navigation`. The Monte Carlo harness of the
study (:func:`tbn_params`, :func:`prepare_job`, :func:`simulate_and_filter`) builds the terrain, the models
and each batch's flights from the plain values of a checked ``braga_tbn`` task (the study's typed settings,
:class:`dslearn.studies.braga_tbn.BragaTask`, or the same values as nested plain dicts) and returns the
estimates and the simulated truth side by side.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import torch
from torch import Tensor

from dslearn.errors import ConfigError
from dslearn.filters.rbpf import ess, init_state, posterior_mean, rbpf_step
from dslearn.fusion.statistics import (combination_matrices, network_adjacency, parse_strategy,
                                       throughput_bytes_per_step, weight_matrix)
from dslearn.models.jmnls import NoiseParams, m_step, make_params, params_dim, stats_dim
from dslearn.models.linear_gaussian import LinearGaussianDynamics
from dslearn.sim.terrain import Scenario, TerrainMap, cv_model, make_terrain, simulate
from dslearn.streams import Streams


@dataclass
class TBNResult:
    """Per-step traces, batch (R, C) or (R, C, S).

    Attributes:
        est: (T, R, C, S, 4) posterior-mean states (position, velocity) after step t.
        pos_cov: (T, R, C, S, 2, 2) the weighted covariance of the particles' positions about ``est`` after
            step t (the filter's position uncertainty; symmetric by construction).
        mu, sigma: (T, R, C, S, K) parameter estimates after the step-t M-step.
        pi: (T, R, C, S, K, K) TPM estimates.
        diagnostics: with ``diagnostics=True``, per-step (T, R, C, S) traces of the filter (no truth in them):
            ``ess`` (before resampling), ``spread`` (weighted RMS distance of the particle positions from their
            mean [m]), ``p_mode_last`` (posterior probability of the last mode), ``resampled`` (bool). The
            errors against the truth are :func:`dslearn.metrics.navigation.tbn_errors`.
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
    pos_cov: Tensor | None = None


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
    cov_tr = torch.empty(steps, r_, c_, s_, 2, 2, dtype=dtype, device=device)
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
        w = torch.exp(state.logw)
        dp = state.x[..., :2] - est[..., None, :2]
        c = torch.einsum("...i,...ia,...ib->...ab", w, dp, dp)
        cov_tr[t - 1] = 0.5 * (c + c.transpose(-1, -2))  # exactly symmetric
        mu_tr[t - 1] = theta.mu
        sg_tr[t - 1] = theta.sigma
        pi_tr[t - 1] = theta.pi
        if diagnostics:
            diag["spread"][t - 1] = torch.einsum("...i,...i->...", w, (dp * dp).sum(-1)).sqrt()
            diag["resampled"][t - 1] = info["resampled"]
            diag["p_mode_last"][t - 1] = torch.einsum("...i,...i->...", w, state.alpha[..., -1])
    if not (torch.isfinite(est_tr).all() and torch.isfinite(mu_tr).all() and torch.isfinite(sg_tr).all()):
        raise FloatingPointError("non-finite estimate in run_tbn (this is a bug: weights are kept in the log domain)")
    return TBNResult(est_tr, mu_tr, sg_tr, pi_tr, counters, diag, cov_tr)


# ----------------------------------------------------------------------------------------- MC harness
KERNEL_DTYPES = {None: None, "float32": torch.float32, "float64": torch.float64}
STATE_DTYPES = {"float64": torch.float64, "float32": torch.float32}


@dataclass(frozen=True)
class TBNParams:
    """What the harness needs of a checked ``braga_tbn`` task: plain values and the objects built from
    them (the true and initial noise parameters, the finger-four graph and its consensus weights)."""

    strategies: tuple[str, ...]
    num_particles: int
    steps: int
    dt: float
    filter_streams: str
    record_every: int
    zoom_s: float
    bytes_per_float: int
    kilobyte: int
    process_noise: float
    truth_process_noise: float
    formation_spacing: float
    v0: tuple[float, float]
    start: tuple[float, float]
    truth: NoiseParams
    init: NoiseParams
    eta_exponent: float
    burn_in: int
    sigma_floor: float
    init_mode: str
    ess_threshold: float
    regularise: float
    jitter: tuple[float, float]
    kernel_dtype: torch.dtype | None
    terrain: dict
    terrain_seed_offset: int
    adj: Tensor
    fusion_centre: int
    weights: Tensor


def tbn_params(task) -> TBNParams:
    """The :class:`TBNParams` of a checked ``braga_tbn`` task: its typed settings (a dataclass instance with
    the task's fields) or the same values as nested plain dicts, lists and numbers."""
    if dataclasses.is_dataclass(task) and not isinstance(task, type):
        task = dataclasses.asdict(task)
    if not isinstance(task, dict):  # plain dicts only: a lazy mapping of the composition is converted before
        raise TypeError(f"tbn_params takes the task's settings (a dataclass) or plain dicts, not {type(task).__name__}")
    t = task
    m, em, bk, tr = t["modes"], t["em"], t["backward_kernel"], t["terrain"]
    adj = network_adjacency(4, t["network"]["edges"])  # finger four: 4 aircraft
    return TBNParams(
        strategies=tuple(str(s) for s in t["strategies"]), num_particles=int(t["num_particles"]), steps=int(t["steps"]),
        dt=float(t["dt"]), filter_streams=str(t["filter_streams"]), record_every=int(t["record_every"]),
        zoom_s=float(t["zoom_s"]), bytes_per_float=int(t["bytes_per_float"]), kilobyte=int(t["kilobyte"]),
        process_noise=float(t["process_noise"]), truth_process_noise=float(t["truth_process_noise"]),
        formation_spacing=float(t["formation_spacing"]),
        v0=tuple(float(a) for a in t["v0"]), start=tuple(float(a) for a in t["start"]),
        truth=make_params(m["mu_true"], m["sigma_true"], m["pi_true"], prefix="task.modes (true)"),
        init=make_params(m["mu_init"], m["sigma_init"], m["pi_init"], prefix="task.modes (initial)"),
        eta_exponent=float(em["eta_exponent"]), burn_in=int(em["burn_in"]), sigma_floor=float(em["sigma_floor"]),
        init_mode="true" if em["init_mode"] is True else str(em["init_mode"]),  # `init_mode=true` on the CLI: a bool
        ess_threshold=float(t["ess_threshold"]), regularise=float(t["resampling"]["regularise"]),
        jitter=(float(bk["jitter_pos"]), float(bk["jitter_vel"])), kernel_dtype=KERNEL_DTYPES[bk["dtype"]],
        terrain={k: float(tr[k]) for k in ("size_m", "resolution_m", "smoothing_m", "elevation_std_m",
                                           "mean_elevation_m")},
        terrain_seed_offset=int(tr["seed_offset"]), adj=adj, fusion_centre=int(t["network"]["fusion_centre"]),
        weights=weight_matrix(adj, t["consensus"]["weights"], t["consensus"]["matrix"]),
    )


@dataclass
class TBNJob:
    """Everything the Monte Carlo batches of one study share (:func:`prepare_job`); picklable, so worker
    processes get it whole.

    Attributes:
        params: the task's values (:class:`TBNParams`).
        terrain: the map; truth: the true noise parameters (run dtype and device).
        truth_dyn, filt_dyn: the aircraft's and the filters' constant-velocity models.
        seed, device, dtype: the run's.
        rec_idx, rec_time: the recorded steps (indices into the T steps) and their times [s].
        throughput: strategy -> communication throughput [kB/s] (Table II).
    """

    params: TBNParams
    terrain: TerrainMap
    truth: NoiseParams
    truth_dyn: LinearGaussianDynamics
    filt_dyn: LinearGaussianDynamics
    seed: int
    device: torch.device
    dtype: torch.dtype
    rec_idx: Tensor
    rec_time: list[float]
    throughput: dict[str, float]


def prepare_job(task, *, seed: int, device: torch.device | str, dtype: torch.dtype | str) -> TBNJob:
    """Everything the Monte Carlo batches share (terrain, models, recording grid, throughput) from a checked
    task (:func:`tbn_params`: its typed settings or plain values), the run's ``seed``, ``device`` and ``dtype``
    (``float64`` or ``float32``)."""
    p = task if isinstance(task, TBNParams) else tbn_params(task)
    device = torch.device(str(device))
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device=cuda but CUDA is not available")
    if isinstance(dtype, str):
        dtype = STATE_DTYPES[dtype]
    if dtype not in STATE_DTYPES.values():
        raise ConfigError(f"dtype={dtype}: the TBN harness runs in {list(STATE_DTYPES)}")
    seed = int(seed)
    kw = dict(dtype=dtype, device=device)
    tgen = torch.Generator(device=device).manual_seed(seed * 7919 + p.terrain_seed_offset + 17)
    terrain = make_terrain(**p.terrain, gen=tgen, **kw)
    truth = p.truth
    truth = type(truth)(truth.mu.to(**kw), truth.sigma.to(**kw), truth.pi.to(**kw))
    truth_dyn = cv_model(p.dt, max(p.truth_process_noise, 1e-12), p.jitter, **kw)
    filt_dyn = cv_model(p.dt, p.process_noise, p.jitter, kernel_dtype=p.kernel_dtype, **kw)
    steps, dt = p.steps, p.dt
    n_zoom = int(round(p.zoom_s / dt))
    rec = [t for t in range(1, steps + 1) if t <= n_zoom or t % p.record_every == 0]
    thr = {sname: throughput_bytes_per_step(sname, p.adj, stats_dim(truth.k), params_dim(truth.k),
                                            fusion_centre=p.fusion_centre, bytes_per_float=p.bytes_per_float)
                  / dt / p.kilobyte for sname in p.strategies}
    return TBNJob(params=p, terrain=terrain, truth=truth, truth_dyn=truth_dyn, filt_dyn=filt_dyn, seed=seed,
                  device=device, dtype=dtype, rec_idx=torch.tensor([t - 1 for t in rec], device=device),
                  rec_time=[t * dt for t in rec], throughput=thr)


def simulate_and_filter(job: TBNJob, episodes: list[int], diagnostics: bool = False, nodes: list[int] | None = None,
                        progress: bool = False) -> tuple[Scenario, TBNResult]:
    """Truth, measurements and every strategy's filters for the Monte Carlo runs ``episodes``.

    Run ``ep`` draws its truth and measurements from the stream (seed, "truth", ep) and each strategy's filter
    from (seed, "filter", ep) (``task.filter_streams=common``: common random numbers) or
    (seed, "filter", ep, strategy) (``independent``), whatever the batch, worker or strategy list.
    ``nodes``: filter only these aircraft (non-cooperative strategies only; for diagnosis).
    Returns ``(scenario, TBNResult)``: the simulated truth and the filters' estimates, side by side (their
    errors: :func:`dslearn.metrics.navigation.tbn_errors`)."""
    p, terrain, truth = job.params, job.terrain, job.truth
    seed, device, strategies = job.seed, torch.device(job.device), p.strategies
    nr = len(episodes)
    common = p.filter_streams == "common"
    truth_gen = Streams.from_keys([(seed, "truth", ep) for ep in episodes], (nr,), device=device)
    filt_gen = Streams.from_keys([(seed, "filter", ep) if common else (seed, "filter", ep, sname)
                                  for ep in episodes for sname in strategies], (nr, len(strategies)), device=device)
    scn = simulate(terrain, truth, job.truth_dyn, runs=nr, start=torch.tensor(list(p.start)),
                   v0=torch.tensor(list(p.v0)), spacing=p.formation_spacing, steps=p.steps, gen=truth_gen)
    weights = p.weights
    if nodes is not None:
        if any(parse_strategy(sn)[0] != "noncooperative" for sn in strategies):
            raise ConfigError("filtering a subset of the nodes needs task.strategies=[noncooperative] (the other "
                              "strategies need the whole network)")
        idx = torch.tensor(nodes, device=scn.x.device)
        scn = Scenario(scn.x[:, idx], scn.r[:, idx], scn.y[:, idx], scn.terrain)
        weights = torch.eye(len(nodes), dtype=weights.dtype)
    # the filters get the measurements and the initial state / mode (known at t = 0, Section VI)
    res = run_tbn(scn.y, scn.terrain, scn.x[:, :, 0], list(strategies), weights, p.init, job.filt_dyn,
                  r0=scn.r[..., 0], num_particles=p.num_particles, gen=filt_gen, burn_in=p.burn_in,
                  progress=progress, diagnostics=diagnostics, eta_exponent=p.eta_exponent,
                  ess_threshold=p.ess_threshold, sigma_floor=p.sigma_floor, init_mode=p.init_mode,
                  regularise=p.regularise)
    return scn, res
