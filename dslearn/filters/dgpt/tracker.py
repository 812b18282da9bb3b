r"""DGPT tracking loop (paper Sec. III) and the centralised standard-GP benchmark (Sec. V-B).

Everything is batched over ``B`` episodes (Monte Carlo runs x scenarios x noise levels), the
aggregation pipelines, the two coordinates and the experts; the only Python loops are over time
steps, optimiser iterations and the (<= 4) aggregation rules.

Per time step ``k`` (``dt`` = 1 step):

1. the sliding window ``[k - W + 1, k]`` of every sensor's *own* measurements is gathered; a
   sensor with no measurement in its window is left out (Sec. III-B). Active sensors are compacted
   to the first ``M_k`` expert slots and windows padded to ``W_max`` slots (masks);
2. if sliding the window further would leave no measurement at all (target outside coverage for
   ``W`` steps or more) the window stops sliding: it stays at ``[k_last, k_last + W - 1]``
   where ``k_last`` is the last step with a detection, so the trackers keep extrapolating with
   growing GP variance (prediction only) instead of failing;
3. the shared hyperparameters are updated on the factorised log marginal likelihood (Eq. 15),
   warm-started from the previous step (Sec. III-C): either solved to a gradient tolerance by
   trust-region Newton (``optimizer="newton"``) or by a fixed number of Adam/SGD steps; the
   centralised GP does the same with Eq. 14 on the union of all windows. Every (episode,
   pipeline, coordinate) is its own problem with its own optimiser state and iteration count
   (:mod:`dslearn.filters.dgpt.hyperopt`), so an episode's result does not depend on the other
   episodes of its batch;
4. the *updated* estimate of step ``k`` (test input ``t = k``) and the *predictive* estimate of
   step ``k + 1`` (test input ``t = k + 1``) are aggregated (Eqs. 9-13), with the Theorem 1 bound.

Inputs: temporal ``x = t``; spatio-temporal ``x = (\hat r_{t-1}, t)`` where ``\hat r`` is the
tracker's own updated position estimate of the previous step (0, the prior mean, before the
first step). With spatio-temporal inputs each aggregation rule therefore runs its own pipeline
(own experts, own hyperparameters); with temporal inputs the experts and hyperparameters do not
depend on the rule and one pipeline serves all rules.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from dslearn.filters.dgpt.hyperopt import (
    ElementwiseAdam,
    Optimiser,
    Posterior,
    SolveInfo,
    bounds,
    init_theta,
    log_marginal_likelihood,
    newton_maximise,
    projected_gradient,
    unpack,
    values,
)
from dslearn.fusion.aggregation import aggregate, aggregate_grbcm, ucb_bound, ucb_bound_grbcm

GP_INPUTS = ("temporal", "spatiotemporal")
OPTIMISERS = tuple(o.value for o in Optimiser)


@dataclass
class HyperConfig:
    """Online hyperparameter learning settings (Sec. III-C).

    ``optimizer="newton"``: per problem, trust-region Newton on Eq. 15 / Eq. 14 until the
    largest gradient component (nats per unit log-parameter) is <= ``tol`` or ``max_iters``.
    ``"adam"`` / ``"sgd"``: ``iters`` steps of size ``lr`` per time step (``iters_first`` at an
    episode's first step with data), per problem. ``gap_check``: after the update, also solve
    each problem to 1e-8 from the learned point (not used by the tracker) and record how far
    below that maximum the learned hyperparameters are (diagnostic; costs a Newton solve).
    Both keep the log-hyperparameters in the box ``[min_*, max_*]`` (noise variance,
    outputscale [m^2], length scales [s or m]; :func:`dslearn.filters.dgpt.hyperopt.bounds`).
    """

    optimizer: str = "adam"
    lr: float = 0.1
    iters: int = 3
    iters_first: int = 10
    tol: float = 1.0e-6
    max_iters: int = 100
    gap_check: bool = False
    init_outputscale: float = 1.0e5
    init_lengthscale_t: float = 10.0
    init_lengthscale_r: float = 300.0
    init_noise: float = 1.0
    min_noise: float = 1.0e-4
    max_noise: float = 1.0e8
    min_outputscale: float = 1.0e-6
    max_outputscale: float = 1.0e8
    min_lengthscale: float = 1.0e-3
    max_lengthscale: float = 1.0e3


@dataclass
class TrackResult:
    """Per-step outputs. Method axis: the aggregation rules in order, then (optionally) the
    centralised GP. Shapes ``(B, A [+1], T, 2)`` unless stated.

    Hyperparameter records (``P`` pipelines, ``C = 2`` coordinates, ``p = d + 2`` values
    (outputscale, lengthscales, noise variance)); suffix ``_e`` = the experts' pipelines,
    ``_c`` = the centralised GP (``None`` where not run):
    ``hyper_*`` ``(B, P|1, C, T, p)`` after the update of step k; ``iters_*`` ``(B, P|1, C, T)``
    optimiser iterations; ``grad_*`` largest |gradient| after the update (Newton, or with
    ``gap_check``; NaN otherwise); ``gap_*`` maximum minus achieved log likelihood [nats] and
    ``noise_mle_*`` the maximiser's noise variance, ``gap_solved_*`` 1 where that reference
    solve met its tolerance within its cap (``gap_check`` only; NaN otherwise);
    ``learning`` ``(B, T)`` bool, the episode had data (hyperparameters were learned) at step k.
    """

    upd_mean: Tensor
    upd_var: Tensor
    pred_mean: Tensor
    pred_var: Tensor
    upd_bound: Tensor
    pred_bound: Tensor
    n_experts: Tensor  # (B, T) experts taking part at the update of step k
    methods: list
    hyper_e: Tensor | None = None
    hyper_c: Tensor | None = None
    iters_e: Tensor | None = None
    iters_c: Tensor | None = None
    grad_e: Tensor | None = None
    grad_c: Tensor | None = None
    gap_e: Tensor | None = None
    gap_c: Tensor | None = None
    noise_mle_e: Tensor | None = None
    noise_mle_c: Tensor | None = None
    gap_solved_e: Tensor | None = None
    gap_solved_c: Tensor | None = None
    learning: Tensor | None = None
    n_jitter: int = 0
    gap_unconverged: int = 0


def _window(avail, meas, k, window, wmax, last_any, return_order=False):
    """Gather and compact the windows of step k. Returns (times (B,W), mask (B,M,W), z (B,M,W,2))
    [and the sensor index of each expert slot (B,M) with ``return_order``]."""
    b, s, _ = avail.shape
    has_data = last_any >= 0
    # the window slides with k but stops once sliding further would drop its last measurement
    end = torch.minimum(torch.full_like(last_any, k), last_any + window - 1).clamp_min(0)
    j = torch.arange(wmax, device=avail.device)
    times = end[:, None] - wmax + 1 + j  # (B, W)
    valid = (times >= end[:, None] - window[:, None] + 1) & (times >= 0) & has_data[:, None]
    tc = times.clamp_min(0)
    av = avail.gather(2, tc[:, None, :].expand(b, s, wmax)) & valid[:, None, :]
    zz = meas.gather(2, tc[:, None, :, None].expand(b, s, wmax, 2))
    active = av.any(-1)
    m = max(1, int(active.sum(-1).max()))
    order = torch.argsort(active.to(torch.int8), dim=1, descending=True, stable=True)[:, :m]
    av_e = av.gather(1, order[..., None].expand(b, m, wmax))
    z_e = zz.gather(1, order[..., None, None].expand(b, m, wmax, 2))
    if return_order:
        return times, av_e, z_e, order
    return times, av_e, z_e


def _inputs(times, est, gp_input, dt):
    """Training inputs (B, P, W, d) for pipelines with estimate history est (B, P, T, 2)."""
    t = (times.to(est.dtype) * dt)[:, None, :, None].expand(est.shape[0], est.shape[1], -1, 1)
    if gp_input == "temporal":
        return t
    prev = (times - 1).clamp_min(0)
    r = est.gather(2, prev[:, None, :, None].expand(-1, est.shape[1], -1, 2))
    r = torch.where((times - 1 >= 0)[:, None, :, None], r, torch.zeros_like(r))
    return torch.cat([r, t], -1)


def _test_input(k, est, gp_input, dt):
    """Test input (B, P, 1, d) for step k using the estimates of step k-1."""
    b, p = est.shape[:2]
    t = torch.full((b, p, 1, 1), k * dt, dtype=est.dtype, device=est.device)
    if gp_input == "temporal":
        return t
    r = est[:, :, k - 1][:, :, None] if k >= 1 else torch.zeros(b, p, 1, 2, dtype=est.dtype,
                                                                  device=est.device)
    return torch.cat([r, t], -1)


def _init_theta(batch_shape, d, hc: HyperConfig, dtype, device):
    ls = [hc.init_lengthscale_t] if d == 1 else [hc.init_lengthscale_r] * 2 + [hc.init_lengthscale_t]
    return init_theta(batch_shape, d, hc.init_outputscale, ls, hc.init_noise, dtype=dtype,
                      device=device)


_M32 = 0xFFFFFFFF


def _mix32(h: Tensor) -> Tensor:
    """A 32-bit integer finaliser (xor-shift-multiply), on int64 tensors holding uint32 values."""
    h = h & _M32
    h = h ^ (h >> 16)
    h = (h * 0x7FEB352D) & _M32
    h = h ^ (h >> 15)
    h = (h * 0x846CA68B) & _M32
    return h ^ (h >> 16)


def keyed_uniform(key: Tensor, *fields: Tensor) -> Tensor:
    """Counter-based uniforms in [0, 1) with 53 random bits: a hash of the episode key (int64)
    and integer fields (broadcast together). The same (key, fields) give the same number in any
    batch, so draws made from it do not depend on the other episodes of a batch."""
    h = _mix32(key & _M32)
    h = _mix32(h ^ ((key >> 32) & _M32))
    for f in fields:
        h = _mix32(h ^ (f & _M32))
    h2 = _mix32(h ^ 0x9E3779B9)
    return ((h >> 5) * 67108864 + (h2 >> 6)).to(torch.float64) / 9007199254740992.0


class _Objective:
    """Eq. 15 / Eq. 14 of the (episode, pipeline, coordinate) problems of one step.

    Data ``(B, P, C, M, W, ...)``; ``self(theta, idx, order)`` with episode indices ``idx``
    evaluates ``theta (len(idx), P, C, p)``; ``self.flat(theta, idx, order)`` with indices into
    the flattened problems ``B * P * C`` evaluates ``theta (len(idx), p)``.
    """

    def __init__(self, x, z, mask, jc):
        self.x, self.z, self.mask, self.jc = x, z, mask, jc
        self._flat = None

    def __call__(self, theta, idx, order):
        return log_marginal_likelihood(theta, self.x[idx], self.z[idx], self.mask[idx], order,
                                       self.jc)

    def flat(self, theta, idx, order):
        if self._flat is None:
            n = self.x.shape[0] * self.x.shape[1] * self.x.shape[2]
            self._flat = tuple(a.reshape(n, *a.shape[3:]) for a in (self.x, self.z, self.mask))
        x, z, m = self._flat
        return log_marginal_likelihood(theta, x[idx], z[idx], m[idx], order, self.jc)


def _solve(fun: _Objective, th, act, tol, max_iters, box):
    """Newton solve of every active problem; returns theta (B, P, C, p) and per-problem info."""
    shp = th.shape
    thf, info = newton_maximise(lambda t_, i_: fun.flat(t_, i_, 2), th.reshape(-1, shp[-1]),
                                act.reshape(-1), tol, max_iters, box=box)
    info = SolveInfo(*(v.reshape(shp[:-1]) for v in (info.f, info.grad, info.iters, info.converged)))
    return thf.reshape(shp), info


def track(meas: Tensor, avail: Tensor, window: Tensor, *, gp_input: str = "temporal",
          aggregations=("poe", "gpoe", "bcm", "rbcm"), centralised: bool = True,
          hyper: HyperConfig | None = None, dt: float = 1.0, delta: float = 0.05,
          normalise_beta: bool = False, progress: bool = False, grbcm_comm_points: int = 10,
          comm_seed: int = 0, episode_keys: Tensor | None = None) -> TrackResult:
    r"""Run DGPT (and the centralised GP) on a batch of episodes.

    Args:
        meas: ``(B, S, T, 2)`` measurements (anything where not detected).
        avail: ``(B, S, T)`` bool, sensor s detected the target at step t.
        window: ``(B,)`` sliding-window length (steps) per episode.
        gp_input: ``"temporal"`` or ``"spatiotemporal"``.
        aggregations: aggregation rules (see :mod:`dslearn.fusion.aggregation`).
        centralised: also run the standard GP on the union of the windows.
        hyper: :class:`HyperConfig`.
        dt: sampling period (time input = step * dt).
        delta: Theorem 1 confidence parameter (bound holds w.p. >= 1 - delta).
        normalise_beta: normalise the Eq. 7 weights to sum 1.
        progress: tqdm bar over time steps.
        grbcm_comm_points: size of grBCM's communication set (see below).
        comm_seed: used only without ``episode_keys``: then episode ``i`` of the batch has key
            ``comm_seed * 1_000_003 + i``.
        episode_keys: ``(B,)`` int64, the key of each episode's grBCM draws (see
            :func:`keyed_uniform`): an episode's draws depend only on its key.

    Episodes are independent: each (episode, pipeline, coordinate) has its own hyperparameters,
    optimiser state and iteration count, and its own random draws, so an episode gives the same
    result (up to round-off) alone or in any batch.

    grBCM (``"grbcm"`` in ``aggregations``): at every step a random subset of
    ``grbcm_comm_points`` measurements of the union of all current windows is the communication
    set :math:`D_c`; it is *sent to every sensor* (extra communication, and no longer "each
    sensor uses only its own data", DGPT's premise). Expert ``+i`` is the GP on
    :math:`D_c \cup D_i` (:math:`D_i` = sensor i's window minus the points drawn into
    :math:`D_c`), the communication expert the GP on :math:`D_c` alone; both use the pipeline's
    shared hyperparameters, learned from the plain local experts (Eq. 15) as for every rule.

    Returns:
        :class:`TrackResult`.
    """
    hc = hyper or HyperConfig()
    if hc.optimizer not in OPTIMISERS:
        raise ValueError(f"optimizer={hc.optimizer!r}; choose from {list(OPTIMISERS)}")
    dtype, dev = meas.dtype, meas.device
    b, s, T, _ = meas.shape
    window = window.to(dev).long()
    wmax = int(window.max())
    aggs = list(aggregations)
    A = len(aggs)
    if A == 0 and not centralised:
        raise ValueError("track: nothing to run (no aggregation rule and centralised=False)")
    use_e = A > 0  # A = 0: the centralised standard GP alone (tracker=gp)
    g_on = "grbcm" in aggs
    if g_on and int(grbcm_comm_points) < 1:
        raise ValueError("grbcm_comm_points must be >= 1")
    if episode_keys is None:
        episode_keys = int(comm_seed) * 1_000_003 + torch.arange(b)
    ekeys = episode_keys.to(device=dev, dtype=torch.long)
    P = 1 if gp_input == "temporal" else max(1, A)
    d = 1 if gp_input == "temporal" else 3
    C = 2
    nm = A + (1 if centralised else 0)
    box = bounds(d, hc.min_noise, (hc.min_outputscale, hc.max_outputscale),
                 (hc.min_lengthscale, hc.max_lengthscale), hc.max_noise, dtype=dtype, device=dev)
    jc = [0]  # Cholesky jitter count

    th_e = _init_theta((b, P, C), d, hc, dtype, dev)
    th_c = _init_theta((b, 1, C), d, hc, dtype, dev)
    optimiser = Optimiser(hc.optimizer)
    newton = optimiser is Optimiser.NEWTON
    if not newton:
        opt_e = ElementwiseAdam(th_e, hc.lr, kind=optimiser, box=box)
        opt_c = ElementwiseAdam(th_c, hc.lr, kind=optimiser, box=box)

    z0 = torch.zeros(b, nm, T, 2, dtype=dtype, device=dev)
    upd_mean, upd_var, pred_mean, pred_var = z0.clone(), z0.clone(), z0.clone(), z0.clone()
    upd_bound, pred_bound = z0.clone(), z0.clone()
    pred_var[:, :, 0] = hc.init_outputscale
    n_exp = torch.zeros(b, T, dtype=torch.long, device=dev)
    est_e = torch.zeros(b, P, T, 2, dtype=dtype, device=dev)  # per-pipeline updated estimates
    est_c = torch.zeros(b, 1, T, 2, dtype=dtype, device=dev)
    p_ = d + 2
    nan = float("nan")
    rec = {}
    for tag, pp in (("e", P), ("c", 1)):
        rec[f"hyper_{tag}"] = torch.zeros(b, pp, C, T, p_, dtype=dtype, device=dev)
        rec[f"iters_{tag}"] = torch.zeros(b, pp, C, T, dtype=torch.long, device=dev)
        for f in ("grad", "gap", "noise_mle", "gap_solved"):
            rec[f"{f}_{tag}"] = torch.full((b, pp, C, T), nan, dtype=dtype, device=dev)
    learning = torch.zeros(b, T, dtype=torch.bool, device=dev)
    gap_unconv = 0

    any_t = avail.any(1)
    last_any = torch.full((b,), -1, dtype=torch.long, device=dev)
    steps = range(T)
    if progress:
        from tqdm import tqdm
        steps = tqdm(steps, desc=f"dgpt[{gp_input}]", leave=False)

    for k in steps:
        had = last_any >= 0
        last_any = torch.where(any_t[:, k], torch.full_like(last_any, k), last_any)
        has_data = last_any >= 0
        learning[:, k] = has_data
        times, m_e, z_e, sens_id = _window(avail, meas, k, window, wmax, last_any, return_order=True)
        M = m_e.shape[1]
        n_exp[:, k] = m_e.any(-1).sum(-1)
        # experts: batch (B, P, C, M, W)
        x_e = _inputs(times, est_e, gp_input, dt)[:, :, None, None].expand(b, P, C, M, wmax, d)
        y_e = z_e.permute(0, 3, 1, 2)[:, None].expand(b, P, C, M, wmax)
        mk_e = m_e[:, None, None].expand(b, P, C, M, wmax)
        if centralised:  # union of windows, compacted: batch (B, 1, C, 1, N)
            mf = m_e.reshape(b, M * wmax)
            n = max(1, int(mf.sum(-1).max()))
            o = torch.argsort(mf.to(torch.int8), dim=1, descending=True, stable=True)[:, :n]
            mk_c = mf.gather(1, o)[:, None, None, None].expand(b, 1, C, 1, n)
            zf = z_e.reshape(b, M * wmax, 2).gather(1, o[..., None].expand(b, n, 2))
            y_c = zf.permute(0, 2, 1)[:, None, :, None]
            xin = _inputs(times, est_c, gp_input, dt)  # (B, 1, W, d)
            xin = xin[:, :, None].expand(b, 1, M, wmax, d).reshape(b, 1, M * wmax, d)
            xin = xin.gather(2, o[:, None, :, None].expand(b, 1, n, d))
            x_c = xin[:, :, None, None].expand(b, 1, C, 1, n, d)

        if g_on:  # grBCM: communication set D_c and augmented experts D_c u D_i
            pg = 0 if P == 1 else aggs.index("grbcm")
            mf = m_e.reshape(b, M * wmax)
            # per-episode keyed draws: uniform per (episode, step, sensor, measurement time)
            u = keyed_uniform(ekeys[:, None, None], torch.full_like(times, k)[:, None, :],
                              sens_id[:, :, None], times[:, None, :].clamp_min(0)).to(dtype)
            u = torch.where(mf, u.reshape(b, M * wmax), torch.full((b, M * wmax), -1.0, dtype=dtype,
                                                                   device=dev))
            ncc = min(int(grbcm_comm_points), M * wmax)
            sc_c, o_c = u.topk(ncc, dim=1)
            cmask = sc_c >= 0  # (B, ncc) drawn measurements (fewer where fewer exist)
            loc = mf.clone()
            loc.scatter_(1, o_c, False)
            loc = loc.reshape(b, M, wmax)
            # only grBCM's own pipeline pg: (B, C, M, W + |D_c|) augmented experts
            xin = _inputs(times, est_e[:, pg:pg + 1], gp_input, dt)[:, 0]  # (B, W, d): per slot
            x_cm = xin.gather(1, (o_c % wmax)[..., None].expand(b, ncc, d))  # (B, ncc, d)
            z_cm = z_e.reshape(b, M * wmax, 2).gather(1, o_c[..., None].expand(b, ncc, 2))
            x_ag = torch.cat([xin[:, None, None].expand(b, C, M, wmax, d),
                              x_cm[:, None, None].expand(b, C, M, ncc, d)], -2)
            y_ag = torch.cat([z_e.permute(0, 3, 1, 2),
                              z_cm.permute(0, 2, 1)[:, :, None].expand(b, C, M, ncc)], -1)
            mk_ag = torch.cat([loc[:, None].expand(b, C, M, wmax),
                               cmask[:, None, None].expand(b, C, M, ncc)], -1)
            x_c1 = x_cm[:, None, None].expand(b, C, 1, ncc, d)
            y_c1 = z_cm.permute(0, 2, 1)[:, :, None]
            mk_c1 = cmask[:, None, None].expand(b, C, 1, ncc)
            emask_g = loc.any(-1)[:, None, :].expand(b, C, M)

        # --- online hyperparameter learning (Eq. 15 / Eq. 14), warm-started, per problem ------
        groups = []
        if use_e:
            groups.append(("e", P, _Objective(x_e, y_e, mk_e, jc)))
        if centralised:
            groups.append(("c", 1, _Objective(x_c, y_c, mk_c, jc)))
        if bool(has_data.any()):
            for tag, pp, fun in groups:
                th = th_e if tag == "e" else th_c
                act = has_data[:, None, None].expand(b, pp, C)
                if newton:
                    th, info = _solve(fun, th, act, hc.tol, hc.max_iters, box)
                    rec[f"iters_{tag}"][..., k] = info.iters
                    rec[f"grad_{tag}"][..., k] = torch.where(act, info.grad, torch.full_like(info.grad, nan))
                else:
                    opt = opt_e if tag == "e" else opt_c
                    n_it = torch.where(has_data & ~had, hc.iters_first, hc.iters) * has_data.long()
                    for it in range(int(n_it.max())):
                        idx = torch.nonzero(n_it > it)[:, 0]
                        _, g = fun(th[idx], idx, 1)
                        th[idx] = opt.step(th[idx], -g, idx)
                    rec[f"iters_{tag}"][..., k] = n_it[:, None, None]
                if hc.gap_check:
                    idx = torch.nonzero(has_data)[:, 0]
                    f0, g0 = fun(th[idx], idx, 1)
                    thm, infm = _solve(fun, th, act, min(hc.tol, 1e-8), max(hc.max_iters, 200), box)
                    gap = torch.full_like(infm.f, nan)
                    gap[idx] = infm.f[idx] - f0
                    rec[f"gap_{tag}"][..., k] = gap
                    rec[f"noise_mle_{tag}"][..., k] = torch.where(act, unpack(thm)[2],
                                                                  torch.full_like(gap, nan))
                    gg = torch.full_like(gap, nan)
                    gg[idx] = projected_gradient(th[idx], g0, box).abs().amax(-1)
                    rec[f"grad_{tag}"][..., k] = gg
                    gap_unconv += int((act & ~infm.converged).sum())
                    rec[f"gap_solved_{tag}"][..., k] = torch.where(act, infm.converged.to(dtype),
                                                                   torch.full_like(gap, nan))
                if tag == "e":
                    th_e = th
                else:
                    th_c = th
        rec["hyper_e"][..., k, :] = values(th_e)
        rec["hyper_c"][..., k, :] = values(th_c)

        # --- updated estimate of step k, then predictive estimate of step k + 1 ------------
        if use_e:
            post_e = Posterior(th_e, x_e, y_e, mk_e, jc)
            prior = unpack(th_e)[0]  # (B, P, C)
            emask = m_e.any(-1)[:, None, None, :].expand(b, P, C, M)
        if g_on:
            post_g = Posterior(th_e[:, pg], x_ag, y_ag, mk_ag, jc)
            post_c1 = Posterior(th_e[:, pg], x_c1, y_c1, mk_c1, jc)
        if centralised:
            post_c = Posterior(th_c, x_c, y_c, mk_c, jc)
            pr_c = unpack(th_c)[0][:, 0]  # (B, C)
            cm = mk_c[:, 0].any(-1)  # (B, C, 1)
        for target_k, store_m, store_v, store_b in ((k, upd_mean, upd_var, upd_bound),
                                                    (k + 1, pred_mean, pred_var, pred_bound)):
            if target_k >= T:
                continue
            if use_e:
                xs = _test_input(target_k, est_e, gp_input, dt)[:, :, None, None].expand(b, P, C, M, 1, d)
                mu, var = post_e(xs)
                mu, var = mu[..., 0], var[..., 0]  # (B, P, C, M)
            if g_on:
                xg = _test_input(target_k, est_e[:, pg:pg + 1], gp_input, dt)[:, 0, None, None]
                mu_g, var_g = post_g(xg.expand(b, C, M, 1, d))
                mu_c1, var_c1 = post_c1(xg.expand(b, C, 1, 1, d))
                mu_g, var_g = mu_g[..., 0], var_g[..., 0]  # (B, C, M)
                mu_c1, var_c1 = mu_c1[:, :, 0, 0], var_c1[:, :, 0, 0]  # (B, C)
            for a, rule in enumerate(aggs):
                p = 0 if P == 1 else a
                if rule == "grbcm":
                    am, av, beta = aggregate_grbcm(mu_g, var_g, emask_g, mu_c1, var_c1, normalise_beta)
                    store_m[:, a, target_k] = am
                    store_v[:, a, target_k] = av
                    # Theorem 1's argument over the augmented experts and the communication expert
                    store_b[:, a, target_k] = ucb_bound_grbcm(var_g, beta, emask_g, var_c1, delta)
                    continue
                am, av, beta = aggregate(mu[:, p], var[:, p], emask[:, p], prior[:, p], rule,
                                         normalise_beta)
                store_m[:, a, target_k] = am
                store_v[:, a, target_k] = av
                store_b[:, a, target_k] = ucb_bound(var[:, p], beta, emask[:, p], prior[:, p], delta)
            if centralised:
                xs = _test_input(target_k, est_c, gp_input, dt)[:, :, None, None].expand(b, 1, C, 1, 1, d)
                mu, var = post_c(xs)
                mu, var = mu[:, 0, :, :, 0], var[:, 0, :, :, 0]  # (B, C, 1)
                store_m[:, A, target_k] = mu[..., 0]
                store_v[:, A, target_k] = var[..., 0]
                store_b[:, A, target_k] = ucb_bound(var, torch.ones_like(var), cm, pr_c, delta)
            if target_k == k:  # feed the estimates back as spatio-temporal inputs
                est_e[:, :, k] = upd_mean[:, :P, k] if P > 1 else upd_mean[:, :1, k]
                if centralised:
                    est_c[:, 0, k] = upd_mean[:, A, k]

    if not use_e:
        for key in [k_ for k_ in rec if k_.endswith("_e")]:
            rec[key] = None
    if not centralised:
        for key in [k_ for k_ in rec if k_.endswith("_c")]:
            rec[key] = None
    methods = aggs + (["standard_gp"] if centralised else [])
    return TrackResult(upd_mean, upd_var, pred_mean, pred_var, upd_bound, pred_bound, n_exp, methods,
                       learning=learning, n_jitter=jc[0], gap_unconverged=gap_unconv, **rec)


def per_method(res: TrackResult, field: str) -> Tensor:
    """(B, methods, C, T) view of a per-pipeline record: rule a -> its pipeline, standard GP -> c."""
    e, c = getattr(res, f"{field}_e"), getattr(res, f"{field}_c")
    cols = []
    for a, m in enumerate(res.methods):
        if m == "standard_gp":
            cols.append(c[:, 0])
        else:
            cols.append(e[:, 0 if e.shape[1] == 1 else a])
    return torch.stack(cols, 1)


def hyper_summary(res: TrackResult, tol: float | None = None) -> dict:
    """Per-episode summaries ``(B, methods)`` of the hyperparameter learning (steps with data, both
    coordinates); ``tol``: the Newton tolerance (unconverged fraction), None for Adam/SGD."""
    if res.learning is None or res.hyper_e is None and res.hyper_c is None:
        return {}
    lw = res.learning[:, None, None, :].to(res.upd_mean.dtype)  # (B, 1, 1, T)
    cnt = (lw.sum(-1) * 2).clamp_min(1)[..., 0]  # (B, 1)

    def mean(x):
        x = torch.nan_to_num(x.to(lw.dtype), nan=0.0)
        return (x * lw).sum((-1, -2)) / cnt

    out = {"hyper_iters": mean(per_method(res, "iters")),
           "hyper_noise_var": mean(per_method(res, "hyper")[..., -1]),
           "hyper_outputscale": mean(per_method(res, "hyper")[..., 0])}
    grad = per_method(res, "grad")
    if bool(torch.isfinite(grad).any()):
        on = lw.expand_as(grad) > 0
        out["hyper_grad_max"] = torch.where(on, grad, torch.zeros_like(grad)).amax((-1, -2))
        if tol is not None:
            out["hyper_unconverged_frac"] = mean((grad > tol).to(lw.dtype))
    gap = per_method(res, "gap")
    if bool(torch.isfinite(gap).any()):
        on = (lw.expand_as(gap) > 0) & torch.isfinite(gap)
        g = torch.where(on, gap, torch.full_like(gap, float("nan"))).flatten(-2)
        out["ml_gap_mean"] = mean(gap)
        out["ml_gap_median"] = torch.nan_to_num(g.nanmedian(-1).values, nan=0.0)
        out["ml_gap_max"] = torch.where(on, gap, torch.zeros_like(gap)).amax((-1, -2))
        out["ml_gap_frac_gt1"] = mean((gap > 1.0).to(lw.dtype))
        out["noise_var_mle"] = mean(per_method(res, "noise_mle"))
        out["ml_gap_unsolved_frac"] = mean(1.0 - per_method(res, "gap_solved"))
    return out
