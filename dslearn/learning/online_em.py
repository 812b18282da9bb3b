r"""Distributed online EM for the TBN scenario: RBPF + online E-step at every node, cooperation on the
sufficient statistics, M-step (Section V), vectorised over Monte Carlo runs × strategies × nodes × particles.

Per time step t (all batches at once):

1. every node runs Algorithm 1 (RBPF) and Algorithm 2 (online E-step) with its current theta -> S_{s,t};
2. the statistics are combined per strategy (identity / Eq. 19 average / Algorithm 3 consensus);
3. after the burn-in, every node runs the M-step (Eq. 8) on its combined statistics.

All strategies of one Monte Carlo run see the same truth and measurements (common random numbers).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from dslearn.fusion.statistics import combination_matrices
from dslearn.filters.rbpf import LinearGaussianDynamics, ess, init_state, posterior_mean, rbpf_step
from dslearn.models.jmnls import NoiseParams, m_step
from dslearn.sim.terrain import Scenario


@dataclass
class TBNResult:
    """Per-step traces, batch (R, C) or (R, C, S).

    Attributes:
        pos_se: (T, R, C, S) squared position error ||p_hat - p||^2 [m^2].
        mu, sigma: (T, R, C, S, K) parameter estimates after the step-t M-step.
        pi: (T, R, C, S, K, K) TPM estimates.
        diagnostics: with ``diagnostics=True``, per-step (T, R, C, S) traces: ``ess`` (before resampling),
            ``spread`` (weighted RMS distance of the particle positions from their mean [m]), ``vel_se``
            (squared velocity error [(m/s)^2]), ``h_misfit`` (terrain height at the estimate minus at the truth
            [m]), ``p_mode_last`` (posterior probability of the last mode) and ``resampled`` (bool).
        counters: event counts: ``resample_events`` and ``degenerate_events`` (R, C) summed over nodes and
            time (a degenerate event = all weights of a node underflowed and were reset to uniform),
            ``sigma_clamped``, ``offmap_particles`` (sampled every 50 steps), ``filter_steps``.
    """

    pos_se: Tensor
    mu: Tensor
    sigma: Tensor
    pi: Tensor
    counters: dict = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)


def run_tbn(scn: Scenario, strategies, weights: Tensor, init: NoiseParams, dyn: LinearGaussianDynamics, *,
            num_particles: int, gen, eta_exponent: float = 0.7, burn_in: int = 50,
            ess_threshold: float = 0.5, sigma_floor: float = 1e-3, init_mode: str = "true", progress: bool = False,
            diagnostics: bool = False, regularise: float = 0.0) -> TBNResult:
    """Run the distributed online EM on a batch of simulated flights.

    Args:
        scn: truth for R runs and S nodes.
        strategies: C strategy names (see :func:`dslearn.fusion.statistics.parse_strategy`).
        weights: (S, S) consensus weights (checked against Eq. 22 by the caller).
        init: initial parameter guess (unbatched, K modes).
        dyn: filter dynamics (Eq. 23 with the filter's Q).
        num_particles: N_P.
        gen: a ``torch.Generator`` or :class:`~dslearn.streams.Streams` over (R, C) (one stream per
            run and strategy: each run's result is then independent of the batch it is in).
        eta_exponent: eta_t = t^-eta_exponent.
        burn_in: the M-step starts after this many steps (E-step runs from t = 1).
        ess_threshold: resampling threshold as a fraction of N_P.
        sigma_floor: lower bound on estimated sigma.
        init_mode: ``true`` (alpha_{0|0} = 1(r_0 = l), as in the paper) or ``uniform``.
        progress: show a tqdm bar over time.
        regularise: post-regularised resampling factor (0: the paper's plain systematic resampling).
        diagnostics: also record the per-step traces listed in :class:`TBNResult` (for lost-track analysis).
    """
    r_, s_, t1, nx = scn.x.shape
    steps = t1 - 1
    c_ = len(strategies)
    bshape = (r_, c_, s_)
    dtype, device = scn.x.dtype, scn.x.device
    comb = combination_matrices(strategies, weights.to(dtype=dtype, device=device))  # (C, S, S)
    theta = NoiseParams(init.mu.to(dtype=dtype, device=device), init.sigma.to(dtype=dtype, device=device),
                        init.pi.to(dtype=dtype, device=device)).expand(*bshape)
    k = init.k
    x0 = scn.x[:, None, :, 0].expand(r_, c_, s_, nx)
    if init_mode == "true":
        alpha0 = torch.nn.functional.one_hot(scn.r[..., 0], k).to(dtype)[:, None].expand(r_, c_, s_, k)
    else:
        alpha0 = torch.full((r_, c_, s_, k), 1.0 / k, dtype=dtype, device=device)
    state = init_state(x0, num_particles, alpha0)
    h = scn.terrain
    pos_se = torch.empty(steps, r_, c_, s_, dtype=dtype, device=device)
    mu_tr = torch.empty(steps, *bshape, k, dtype=dtype, device=device)
    sg_tr = torch.empty_like(mu_tr)
    pi_tr = torch.empty(steps, *bshape, k, k, dtype=dtype, device=device)
    counters = {"resample_events": torch.zeros(r_, c_, dtype=torch.long, device=device),
                "degenerate_events": torch.zeros(r_, c_, dtype=torch.long, device=device),
                "sigma_clamped": 0, "offmap_particles": 0, "filter_steps": steps * r_ * c_ * s_}
    diag = {}
    if diagnostics:
        diag = {name: torch.empty(steps, r_, c_, s_, dtype=dtype, device=device)
                for name in ("ess", "spread", "vel_se", "h_misfit", "p_mode_last")}
        diag["resampled"] = torch.empty(steps, r_, c_, s_, dtype=torch.bool, device=device)
    it = range(1, steps + 1)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc="braga_tbn", leave=False)
    for t in it:
        y = scn.y[:, None, :, t].expand(*bshape)
        eta = float(t) ** (-eta_exponent)
        if diagnostics:
            diag["ess"][t - 1] = ess(state.logw)
        state, stats, info = rbpf_step(state, y, h, theta, dyn, gen, eta=eta, ess_threshold=ess_threshold,
                                       regularise=regularise)
        counters["resample_events"] += info["resampled"].sum(-1)
        counters["degenerate_events"] += info["degenerate"].sum(-1)
        if t % 50 == 0:
            counters["offmap_particles"] += int(h.outside(state.x).sum())
        glob = torch.einsum("csr,Rcrd->Rcsd", comb, stats)  # cooperation (identity / Eq. 19 / Algorithm 3)
        if t > burn_in:
            theta = m_step(glob, theta, sigma_floor=sigma_floor, counters=counters)
        est = posterior_mean(state)
        d = est[..., :2] - scn.x[:, None, :, t, :2]
        pos_se[t - 1] = (d * d).sum(-1)
        mu_tr[t - 1] = theta.mu
        sg_tr[t - 1] = theta.sigma
        pi_tr[t - 1] = theta.pi
        if diagnostics:
            w = torch.exp(state.logw)
            dp = state.x[..., :2] - est[..., None, :2]
            diag["spread"][t - 1] = torch.einsum("...i,...i->...", w, (dp * dp).sum(-1)).sqrt()
            dv = est[..., 2:] - scn.x[:, None, :, t, 2:]
            diag["vel_se"][t - 1] = (dv * dv).sum(-1)
            diag["resampled"][t - 1] = info["resampled"]
            diag["h_misfit"][t - 1] = h(est) - h(scn.x[:, None, :, t])
            diag["p_mode_last"][t - 1] = torch.einsum("...i,...i->...", w, state.alpha[..., -1])
    if not (torch.isfinite(pos_se).all() and torch.isfinite(mu_tr).all() and torch.isfinite(sg_tr).all()):
        raise FloatingPointError("non-finite estimate in run_tbn (this is a bug: weights are kept in the log domain)")
    return TBNResult(pos_se, mu_tr, sg_tr, pi_tr, counters, diag)
