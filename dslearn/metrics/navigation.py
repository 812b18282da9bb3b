r"""Navigation metrics of the terrain-based navigation study (Braga et al.): the RBPFs' position and
noise-parameter estimates against the simulated truth, and the study's tidy rows.

:func:`tbn_errors` compares the filters' posterior means with the true flights (squared position error, and
for diagnosis the velocity error and the terrain-height misfit); :func:`tbn_metrics` reduces them, with the
parameter errors against the true jump-Markov noise, to the run-level metrics and time series of the study;
:func:`tbn_rows` writes them as tidy rows (one per run x strategy x metric [x recorded time]).

Shapes: T steps, R Monte Carlo runs, C strategies, S nodes, K noise modes.
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from dslearn.learning.online_em import TBNResult
from dslearn.models.jmnls import NoiseParams
from dslearn.sim.terrain import Scenario

#: the run-level metrics of :func:`tbn_metrics`, in row order (``throughput_kBps`` follows them)
RUN_METRICS = ("pos_rms", "pos_rms_first5s", "mu_rms", "sigma_rms", "pi_rms", "pos_rms_worst_node", "pos_err_max",
               "lost_nodes", "lost_track", "resample_rate", "degenerate_events")


@dataclass
class TBNErrors:
    """Errors of the filters' estimates against the truth, each ``(T, R, C, S)``.

    Attributes:
        pos_se: squared position error ``||p_hat - p||^2`` [m^2].
        vel_se: squared velocity error [(m/s)^2] (with ``detail``; else None).
        h_misfit: terrain height at the estimate minus at the truth [m] (with ``detail``; else None).
    """

    pos_se: Tensor
    vel_se: Tensor | None = None
    h_misfit: Tensor | None = None


def tbn_errors(res: TBNResult, scn: Scenario, detail: bool = False) -> TBNErrors:
    """The errors of ``res.est`` (T, R, C, S, 4) against the true states ``scn.x`` (R, S, T+1, 4); ``detail``:
    also the velocity error and the height misfit (for the lost-track diagnosis)."""
    xt = scn.x[:, None, :, 1:].permute(3, 0, 1, 2, 4)  # (T, R, 1, S, 4)
    d = res.est[..., :2] - xt[..., :2]
    out = TBNErrors((d * d).sum(-1))
    if detail:
        dv = res.est[..., 2:] - xt[..., 2:]
        out.vel_se = (dv * dv).sum(-1)
        out.h_misfit = scn.terrain(res.est) - scn.terrain(xt)
    if not out.pos_se.isfinite().all():
        raise FloatingPointError("non-finite position error in tbn_errors")
    return out


def parameter_sq_errors(res: TBNResult, truth: NoiseParams) -> tuple[Tensor, Tensor, Tensor]:
    """Squared errors of the noise-parameter estimates: mu, sigma (T, R, C, S, K) and the diagonal of the
    transition matrix (T, R, C, S, K)."""
    mu = (res.mu - truth.mu) ** 2
    sigma = (res.sigma - truth.sigma) ** 2
    pi = (res.pi.diagonal(dim1=-2, dim2=-1) - truth.pi.diagonal()) ** 2
    return mu, sigma, pi


def node_steady_rms(pos_se: Tensor, steady_steps: int) -> Tensor:
    """Steady-state position RMS of every node over the last ``steady_steps`` steps: (T, ...) -> (...)."""
    return pos_se[-steady_steps:].mean(0).sqrt()


def tbn_metrics(res: TBNResult, err: TBNErrors, truth: NoiseParams, *, steady_steps: int, first_steps: int,
                lost_track_m: float, rec_idx: Tensor) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
    """The study's metrics of one batch of runs.

    Returns ``(run_level, series)``: ``run_level`` maps each name of :data:`RUN_METRICS` to an (R, C) tensor
    (``pos_rms``, ``mu_rms``, ``sigma_rms``, ``pi_rms``: RMS over the last ``steady_steps`` steps and the
    nodes (and modes); ``pos_rms_first5s`` over the first ``first_steps``; ``pos_rms_worst_node`` the largest
    per-node steady-state RMS; ``pos_err_max`` the largest error of any node at any step; ``lost_nodes`` /
    ``lost_track`` the nodes / 0-1 flag with a steady-state RMS above ``lost_track_m``; ``resample_rate``
    per node and step; ``degenerate_events``); ``series`` maps names to (T_rec, R, C) tensors at the steps
    ``rec_idx``: the squared errors averaged over nodes (and modes) ``pos_se_t``, ``mu_se_t``, ``sigma_se_t``,
    ``pi_se_t``, and the node-averaged estimates ``mu_k``, ``sigma_k``, ``pi_kk`` (k = 1..K)."""
    mu_err, sg_err, pi_err = parameter_sq_errors(res, truth)
    pos_se = err.pos_se
    dtype = pos_se.dtype
    ss = slice(pos_se.shape[0] - steady_steps, pos_se.shape[0])
    node_rms = node_steady_rms(pos_se, steady_steps)  # (R, C, S)
    filter_steps = res.est.shape[0] * res.est.shape[3]  # steps x nodes of every (run, strategy)
    run_level = {
        "pos_rms": pos_se[ss].mean((0, 3)).sqrt(),
        "pos_rms_first5s": pos_se[:first_steps].mean((0, 3)).sqrt(),
        "mu_rms": mu_err[ss].mean((0, 3, 4)).sqrt(),
        "sigma_rms": sg_err[ss].mean((0, 3, 4)).sqrt(),
        "pi_rms": pi_err[ss].mean((0, 3, 4)).sqrt(),
        "pos_rms_worst_node": node_rms.amax(-1),
        "pos_err_max": pos_se.amax((0, 3)).sqrt(),
        "lost_nodes": (node_rms > lost_track_m).sum(-1).to(dtype),
        "lost_track": (node_rms > lost_track_m).any(-1).to(dtype),
        "resample_rate": res.counters["resample_events"].to(dtype) / filter_steps,
        "degenerate_events": res.counters["degenerate_events"].to(dtype),
    }
    series = {
        "pos_se_t": pos_se[rec_idx].mean(-1),
        "mu_se_t": mu_err[rec_idx].mean((-1, -2)),
        "sigma_se_t": sg_err[rec_idx].mean((-1, -2)),
        "pi_se_t": pi_err[rec_idx].mean((-1, -2)),
    }
    for j in range(truth.k):
        series[f"mu_{j + 1}"] = res.mu[rec_idx][..., j].mean(-1)
        series[f"sigma_{j + 1}"] = res.sigma[rec_idx][..., j].mean(-1)
        series[f"pi_{j + 1}{j + 1}"] = res.pi[rec_idx][..., j, j].mean(-1)
    return run_level, series


def tbn_rows(run_level: dict[str, Tensor], series: dict[str, Tensor], throughput: dict[str, float], *,
             episodes: list[int], strategies, consensus: dict[str, str], rec_time: list[float],
             model: str) -> list[dict]:
    """Tidy rows (dicts) of :func:`tbn_metrics`' output for the runs ``episodes`` (axis R) and ``strategies``
    (axis C): per (run, strategy) the run-level metrics and ``throughput_kBps`` (``time_s = -1``), then every
    series at the times ``rec_time``. Columns: ``episode strategy model consensus node time_s metric value``
    (``consensus``: strategy -> its label; ``node`` = ``avg``)."""
    rows = []
    for ci, sname in enumerate(strategies):
        cons = consensus[sname]
        for ri, ep in enumerate(episodes):
            vals = [(name, v[ri, ci].item()) for name, v in run_level.items()]
            vals.append(("throughput_kBps", throughput[sname]))
            for name, val in vals:
                rows.append({"episode": ep, "strategy": sname, "model": model, "consensus": cons, "node": "avg",
                             "time_s": -1.0, "metric": name, "value": float(val)})
            for name, v in series.items():
                rows.extend({"episode": ep, "strategy": sname, "model": model, "consensus": cons, "node": "avg",
                             "time_s": round(ts, 6), "metric": name, "value": float(val)}
                            for ts, val in zip(rec_time, v[:, ri, ci].tolist()))
    return rows
