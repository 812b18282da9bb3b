r"""Metrics of the distributed GP tracker (Liu et al., FUSION 2022): the per-episode errors of every
method's position estimates against the true track (RMSE, NRMSE, coverage of the UCB and 3-sigma
bands), the tracker's own per-episode summaries (detections, experts, hyperparameter learning), and
their tidy rows (one per episode x method x metric; per step for the traced episodes)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from dslearn.filters.dgpt import TrackResult, hyper_summary


def dgpt_metrics(res: TrackResult, truth: Tensor, avail: Tensor, delta: float,
                 tol: float | None = None) -> dict[str, np.ndarray]:
    """Per-episode, per-method scalar metrics of a :class:`~dslearn.filters.dgpt.TrackResult`.

    Errors count at the steps whose predictive estimate was made with data (after the episode's
    first detection); ``*_covered`` only at those of them with a detection. NRMSE divides by the
    range of the true coordinate over the episode. ``delta``: the UCB's confidence parameter
    (``ucb_nominal = 1 - delta``); ``tol``: the Newton tolerance (None for Adam/SGD).

    Args:
        res: the tracker's estimates ``(B, M, T, 2)``; truth: ``(B, T, 2)``; avail: ``(B, S, T)``
            which sensors detected the target at each step.

    Returns:
        name -> ``(B, M)`` numpy arrays.
    """
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


def dgpt_rows(metrics: dict[str, np.ndarray], keys: list[tuple], model: list[str],
              consensus: list[str]) -> list[pd.DataFrame]:
    """Tidy rows of :func:`dgpt_metrics` ``{name: (B, M)}``: one frame per metric, a row per episode
    (``keys[b] = (scenario, noise, run)``) x method (labels ``model[m]``, ``consensus[m]``)."""
    nb, nm = len(keys), len(model)
    base = pd.DataFrame({
        "scenario": np.repeat([k[0] for k in keys], nm),
        "noise": np.repeat([k[1] for k in keys], nm),
        "episode": np.repeat([k[2] for k in keys], nm),
        "model": np.tile(model, nb),
        "consensus": np.tile(consensus, nb),
    })
    frames = []
    for name, arr in metrics.items():
        f = base.copy()
        f["metric"] = name
        f["value"] = arr.reshape(-1).astype(float)
        frames.append(f)
    return frames


def dgpt_trace_rows(scenario: str, noise: float, episodes: int, res: TrackResult, truth: Tensor, avail: Tensor,
                    keys: list[tuple], model: list[str], consensus: list[str]) -> pd.DataFrame | None:
    """Per-step rows (``step >= 0``) for Figs 5-6: the true track next to every method's estimates,
    standard deviations and UCB, and the number of detecting sensors, of the first ``episodes``
    episodes of the cell (``scenario``, ``noise``); None when the batch holds none of them."""
    rows = []
    T = truth.shape[1]
    ndet = avail.sum(1)  # (B, T)
    for i, (s, nz, r) in enumerate(keys):
        if s != scenario or not math.isclose(nz, noise) or r >= episodes:
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
                    "consensus": consensus[m], "step": np.arange(T), "metric": name,
                    "value": v.detach().cpu().numpy().astype(float)}))
    if not rows:
        return None
    return pd.concat(rows, ignore_index=True)
