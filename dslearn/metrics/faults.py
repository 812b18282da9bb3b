r"""Tracking on an unreliable network: the distributed filters' errors against the truth, summarised over
the nodes that are still alive, and the network's own health (live links, gated measurements).

A failed node keeps its last belief and stops measuring, so its error says nothing about the
network's tracking: the headline summary is over the nodes alive at the end of the episode
(:func:`alive_summaries`). :func:`faulty_network_rows` writes one grid cell's tidy rows."""

from __future__ import annotations

import pandas as pd
import torch
from torch import Tensor

from dslearn.filters.distributed import TrackResult
from dslearn.metrics.tracking import tracking_metrics

def alive_summaries(values: Tensor, alive: Tensor) -> dict[str, Tensor]:
    """Per-episode summaries of a per-node metric ``values (S, B)`` given ``alive (S, B)`` (bool: the
    node is alive at the end of the episode); a non-finite value counts as missing (NaN).

    Returns ``(B,)`` float64 tensors: ``alive``, the sum of the alive nodes' finite values over the number
    of alive nodes (a missing value adds 0; 0 when none is alive), ``all``, the mean over every node (NaN
    if any is missing), and ``alive_max``, the maximum over the alive nodes (NaN if one of them is missing,
    ``-inf`` when none is alive)."""
    v = values.detach().cpu().double()
    vz = torch.where(torch.isfinite(v), v, torch.full_like(v, float("nan")))
    a = alive.cpu().double()
    alive_mean = (vz * a).nansum(0) / a.sum(0).clamp_min(1)
    alive_max = torch.where(a > 0, vz, torch.full_like(vz, float("-inf"))).max(0).values
    return {"alive": alive_mean, "all": vz.mean(0), "alive_max": alive_max}


def faulty_network_rows(res: TrackResult, truth: Tensor, alive: Tensor, *, live_links: float, nominal_links: float,
                        gate_tested: int, gate_rejected: int, **keys) -> pd.DataFrame:
    """One cell's tidy rows: columns ``*keys, node, episode, metric, value`` (keys first, in their order).

    Args:
        res: the nodes' beliefs ``(S, B, K+1, ...)``; truth: ``(B, K+1, Dx)``.
        alive: the node-alive schedule ``(S, B, K+1)`` (bool).
        live_links, nominal_links: links that worked / links of the nominal graph, summed over the steps
            and episodes the fusion ran.
        gate_tested, gate_rejected: measurements the chi-square gate tested / rejected.

    Rows: for each of :func:`~dslearn.metrics.tracking.tracking_metrics` (``track_err``, ``track_rmse``,
    ``nees``), per episode, the node summaries ``alive``, ``all``, ``alive_max`` (:func:`alive_summaries`,
    alive = at the last step); ``nonfinite`` (node ``all``): per episode, the nodes whose estimate is not
    finite somewhere; ``live_link_frac`` (episode 0): live / nominal links (NaN without links);
    ``gate_reject_frac`` (episode 0): rejected / tested (0 when nothing was tested).
    """
    m = tracking_metrics(res, truth)  # (S, B) each
    finite = torch.isfinite(res.mean).all(-1).all(-1)  # (S, B)
    alive_end = alive[:, :, -1].to(finite.device)  # (S, B)
    b = truth.shape[0]
    frames = []
    for name, v in m.items():
        for node, val in alive_summaries(v, alive_end).items():
            frames.append(pd.DataFrame({"node": node, "episode": range(b), "metric": name, "value": val.numpy()}))
    frames.append(pd.DataFrame({"node": "all", "episode": range(b), "metric": "nonfinite",
                                "value": (~finite).sum(0).double().cpu().numpy()}))
    links = live_links / nominal_links if nominal_links else float("nan")
    frames.append(pd.DataFrame({"node": "all", "episode": [0], "metric": "live_link_frac", "value": [links]}))
    frames.append(pd.DataFrame({"node": "all", "episode": [0], "metric": "gate_reject_frac",
                                "value": [gate_rejected / gate_tested if gate_tested else 0.0]}))
    df = pd.concat(frames, ignore_index=True)
    for i, (key, v) in enumerate(keys.items()):
        df.insert(i, key, v)
    return df
