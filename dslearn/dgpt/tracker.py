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
3. the shared hyperparameters are updated by a few optimiser steps on the factorised log
   marginal likelihood (Eq. 15), warm-started from the previous step (Sec. III-C); the
   centralised GP maximises Eq. 14 on the union of all windows;
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

from .aggregation import aggregate, aggregate_grbcm, ucb_bound
from .experts import Hypers, expert_log_marginal_likelihood, predict_latent, predict_latent_slice

GP_INPUTS = ("temporal", "spatiotemporal")
OPTIMISERS = ("adam", "sgd")


@dataclass
class HyperConfig:
    """Online hyperparameter learning settings (Sec. III-C)."""

    optimizer: str = "adam"
    lr: float = 0.1
    iters: int = 3
    iters_first: int = 10
    init_outputscale: float = 1.0e5
    init_lengthscale_t: float = 10.0
    init_lengthscale_r: float = 300.0
    init_noise: float = 1.0
    min_noise: float = 1.0e-4


@dataclass
class TrackResult:
    """Per-step outputs. Method axis: the aggregation rules in order, then (optionally) the
    centralised GP. Shapes ``(B, A [+1], T, 2)`` unless stated."""

    upd_mean: Tensor
    upd_var: Tensor
    pred_mean: Tensor
    pred_var: Tensor
    upd_bound: Tensor
    pred_bound: Tensor
    n_experts: Tensor  # (B, T) experts taking part at the update of step k
    methods: list


def _window(avail, meas, k, window, wmax, last_any):
    """Gather and compact the windows of step k. Returns (times (B,W), mask (B,M,W), z (B,M,W,2))."""
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


def _make_hypers(batch_shape, d, hc: HyperConfig, dtype, device):
    ls = [hc.init_lengthscale_t] if d == 1 else [hc.init_lengthscale_r] * 2 + [hc.init_lengthscale_t]
    return Hypers(batch_shape, d, hc.init_outputscale, ls, hc.init_noise, hc.min_noise,
                  dtype=dtype, device=device)


def track(meas: Tensor, avail: Tensor, window: Tensor, *, gp_input: str = "temporal",
          aggregations=("poe", "gpoe", "bcm", "rbcm"), centralised: bool = True,
          hyper: HyperConfig | None = None, dt: float = 1.0, delta: float = 0.05,
          normalise_beta: bool = False, progress: bool = False, grbcm_comm_points: int = 10,
          comm_seed: int = 0) -> TrackResult:
    r"""Run DGPT (and the centralised GP) on a batch of episodes.

    Args:
        meas: ``(B, S, T, 2)`` measurements (anything where not detected).
        avail: ``(B, S, T)`` bool, sensor s detected the target at step t.
        window: ``(B,)`` sliding-window length (steps) per episode.
        gp_input: ``"temporal"`` or ``"spatiotemporal"``.
        aggregations: aggregation rules (see :mod:`dslearn.dgpt.aggregation`).
        centralised: also run the standard GP on the union of the windows.
        hyper: :class:`HyperConfig`.
        dt: sampling period (time input = step * dt).
        delta: Theorem 1 confidence parameter (bound holds w.p. >= 1 - delta).
        normalise_beta: normalise the Eq. 7 weights to sum 1.
        progress: tqdm bar over time steps.
        grbcm_comm_points: size of grBCM's communication set (see below).
        comm_seed: seed of the communication-set draws.

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
    gen_c = torch.Generator().manual_seed(int(comm_seed))
    P = 1 if gp_input == "temporal" else max(1, A)
    d = 1 if gp_input == "temporal" else 3
    C = 2
    nm = A + (1 if centralised else 0)

    hyp_e = _make_hypers((b, P, C, 1), d, hc, dtype, dev)
    hyp_c = _make_hypers((b, 1, C, 1), d, hc, dtype, dev) if centralised else None
    params = (list(hyp_e.parameters()) if use_e else []) + (list(hyp_c.parameters()) if centralised else [])
    opt_cls = {"adam": torch.optim.Adam, "sgd": torch.optim.SGD}[hc.optimizer]
    opt = opt_cls(params, lr=hc.lr)

    z0 = torch.zeros(b, nm, T, 2, dtype=dtype, device=dev)
    upd_mean, upd_var, pred_mean, pred_var = z0.clone(), z0.clone(), z0.clone(), z0.clone()
    upd_bound, pred_bound = z0.clone(), z0.clone()
    pred_var[:, :, 0] = hc.init_outputscale
    n_exp = torch.zeros(b, T, dtype=torch.long, device=dev)
    est_e = torch.zeros(b, P, T, 2, dtype=dtype, device=dev)  # per-pipeline updated estimates
    est_c = torch.zeros(b, 1, T, 2, dtype=dtype, device=dev)

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
        times, m_e, z_e = _window(avail, meas, k, window, wmax, last_any)
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
            u = torch.rand(b, M * wmax, generator=gen_c, dtype=dtype).to(dev)
            u = torch.where(mf, u, torch.full_like(u, -1.0))
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

        # --- online hyperparameter learning (Eq. 15 / Eq. 14), warm-started ---------------
        if bool(has_data.any()):
            n_it = hc.iters_first if bool((has_data & ~had).any()) else hc.iters
            for _ in range(n_it):
                opt.zero_grad()
                loss = -expert_log_marginal_likelihood(hyp_e, x_e, y_e, mk_e).sum() if use_e else 0.0
                if centralised:
                    loss = loss - expert_log_marginal_likelihood(hyp_c, x_c, y_c, mk_c).sum()
                loss.backward()
                old_e = hyp_e.raw_state()
                old_c = hyp_c.raw_state() if centralised else None
                opt.step()
                hyp_e.restore_where(old_e, has_data)
                if centralised:
                    hyp_c.restore_where(old_c, has_data)

        # --- updated estimate of step k, then predictive estimate of step k + 1 ------------
        for target_k, store_m, store_v, store_b in ((k, upd_mean, upd_var, upd_bound),
                                                    (k + 1, pred_mean, pred_var, pred_bound)):
            if target_k >= T:
                continue
            if use_e:
                xs = _test_input(target_k, est_e, gp_input, dt)[:, :, None, None].expand(b, P, C, M, 1, d)
                mu, var = predict_latent(hyp_e, x_e, y_e, mk_e, xs)
                mu, var = mu[..., 0], var[..., 0]  # (B, P, C, M)
                prior = hyp_e.outputscale.detach()[..., 0]  # (B, P, C)
                emask = m_e.any(-1)[:, None, None, :].expand(b, P, C, M)
            if g_on:
                xg = _test_input(target_k, est_e[:, pg:pg + 1], gp_input, dt)[:, 0, None, None]
                mu_g, var_g = predict_latent_slice(hyp_e, pg, x_ag, y_ag, mk_ag, xg.expand(b, C, M, 1, d))
                mu_c1, var_c1 = predict_latent_slice(hyp_e, pg, x_c1, y_c1, mk_c1, xg.expand(b, C, 1, 1, d))
                mu_g, var_g = mu_g[..., 0], var_g[..., 0]  # (B, C, M)
                mu_c1, var_c1 = mu_c1[:, :, 0, 0], var_c1[:, :, 0, 0]  # (B, C)
            for a, rule in enumerate(aggs):
                p = 0 if P == 1 else a
                if rule == "grbcm":
                    am, av, beta = aggregate_grbcm(mu_g, var_g, emask_g, mu_c1, var_c1, normalise_beta)
                    store_m[:, a, target_k] = am
                    store_v[:, a, target_k] = av
                    # Eq. 24 applied by analogy to the augmented experts' weights (no theorem for grBCM)
                    store_b[:, a, target_k] = ucb_bound(var_g, beta, emask_g, prior[:, p], delta)
                    continue
                am, av, beta = aggregate(mu[:, p], var[:, p], emask[:, p], prior[:, p], rule,
                                         normalise_beta)
                store_m[:, a, target_k] = am
                store_v[:, a, target_k] = av
                store_b[:, a, target_k] = ucb_bound(var[:, p], beta, emask[:, p], prior[:, p], delta)
            if centralised:
                xs = _test_input(target_k, est_c, gp_input, dt)[:, :, None, None].expand(b, 1, C, 1, 1, d)
                mu, var = predict_latent(hyp_c, x_c, y_c, mk_c, xs)
                mu, var = mu[:, 0, :, :, 0], var[:, 0, :, :, 0]  # (B, C, 1)
                cm = mk_c[:, 0, :, :, :].any(-1)  # (B, C, 1)
                pr = hyp_c.outputscale.detach()[:, 0, :, 0]
                store_m[:, A, target_k] = mu[..., 0]
                store_v[:, A, target_k] = var[..., 0]
                store_b[:, A, target_k] = ucb_bound(var, torch.ones_like(var), cm, pr, delta)
            if target_k == k:  # feed the estimates back as spatio-temporal inputs
                est_e[:, :, k] = upd_mean[:, :P, k] if P > 1 else upd_mean[:, :1, k]
                if centralised:
                    est_c[:, 0, k] = upd_mean[:, A, k]

    methods = aggs + (["standard_gp"] if centralised else [])
    return TrackResult(upd_mean, upd_var, pred_mean, pred_var, upd_bound, pred_bound, n_exp, methods)
