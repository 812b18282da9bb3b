"""Window tensors of trajectory data: NaN-padded scene windows ``(N, T, A, 2)`` (as
:func:`dslearn.data.ethucy.windows` makes them), per-pedestrian windows, subsampling, and runs of
consecutive positions for one-step regression."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor


def per_agent(w: Tensor) -> Tensor:
    """NaN-padded windows ``(N, T, A, 2)`` -> present pedestrian-windows ``(M, T, 2)``."""
    present = torch.isfinite(w).all(-1).all(1)  # (N, A)
    return w.permute(0, 2, 1, 3)[present]


def cat_windows(parts: list[Tensor]) -> Tensor:
    """Concatenate NaN-padded window tensors with different ``A`` (pads with NaN); no window at all
    gives an empty ``(0, T, 0, 2)`` tensor."""
    nonempty = [p for p in parts if p.shape[0] > 0]
    if not nonempty:  # e.g. a data set without a validation part: no window at all
        like = parts[0] if parts else torch.empty(0, 0, 0, 2, dtype=torch.float64)
        return like.new_empty((0, *like.shape[1:2], 0, 2))
    parts = nonempty
    a = max(p.shape[2] for p in parts)
    out = []
    for p in parts:
        if p.shape[2] < a:
            pad = torch.full((*p.shape[:2], a - p.shape[2], 2), float("nan"), dtype=p.dtype)
            p = torch.cat([p, pad], dim=2)
        out.append(p)
    return torch.cat(out, 0)


def subsample(w: Tensor, k: int | None) -> Tensor:
    """At most ``k`` windows, evenly spaced (deterministic)."""
    if k is None or w.shape[0] <= k:
        return w
    idx = torch.linspace(0, w.shape[0] - 1, int(k)).round().long().unique()
    return w[idx]


def quads(scene_parts) -> Tensor:
    """Every run of 4 consecutive positions of every pedestrian: ``(K, 4, 2)`` float64."""
    out = []
    for sc in scene_parts:
        d = sc.df.sort_values(["ped", "step"])
        ped = d["ped"].to_numpy()
        step = d["step"].to_numpy()
        xy = d[["x", "y"]].to_numpy()
        ok = (ped[3:] == ped[:-3]) & (step[3:] - step[:-3] == 3)
        idx = np.nonzero(ok)[0]
        out.append(np.stack([xy[idx], xy[idx + 1], xy[idx + 2], xy[idx + 3]], axis=1))
    return torch.as_tensor(np.concatenate(out, 0))
