r"""The one writer of tidy metric rows: every result table of the project is built here, from metric
values that the functions of this package computed against the truth."""

from __future__ import annotations

import numpy as np
import pandas as pd
from torch import Tensor

from dslearn.network import SensorNetwork


def metric_rows(metrics: dict[str, Tensor], network: SensorNetwork, **keys) -> pd.DataFrame:
    """Tidy rows of per-node, per-episode metrics ``{name: (S, B)}`` of ``network``'s nodes: columns
    ``*keys, node, node_kind, episode, metric, value`` (keys first, in their order, as constants)."""
    kinds = ["sensor" if network.is_sensor[i] else "comm" for i in range(network.num_nodes)]
    return node_rows(metrics, list(network.names), kinds, **keys)


def node_rows(metrics: dict[str, Tensor], names: list[str], kinds: list[str], **keys) -> pd.DataFrame:
    """Tidy rows of per-node, per-episode metrics ``{name: (N, B)}`` of nodes ``names`` of kinds ``kinds``:
    columns ``*keys, node, node_kind, episode, metric, value`` (keys first, in their order, as constants)."""
    frames = []
    s = len(names)
    for name, val in metrics.items():
        v = val.detach().cpu().double()
        b = v.shape[1]
        frames.append(pd.DataFrame({
            "node": [names[i] for i in range(s) for _ in range(b)],
            "node_kind": [kinds[i] for i in range(s) for _ in range(b)],
            "episode": list(range(b)) * s,
            "metric": name,
            "value": v.reshape(-1).numpy(),
        }))
    df = pd.concat(frames, ignore_index=True)
    for i, (k, v) in enumerate(keys.items()):
        df.insert(i, k, v)
    return df


def rows(values, dims: tuple[str, ...], metric: str, **keys) -> pd.DataFrame:
    """Tidy rows of one metric's values, an array (or tensor) whose axes are named by ``dims``
    (e.g. ``("episode", "timing")``): one row per element, a column per axis (its index), ``metric``,
    ``value``, then the constant ``keys`` columns."""
    v = values.detach().cpu().double().numpy() if isinstance(values, Tensor) else np.asarray(values, dtype=float)
    if v.ndim != len(dims):
        raise ValueError(f"rows: {v.ndim}-d values for the axes {dims}")
    grids = np.meshgrid(*(np.arange(n) for n in v.shape), indexing="ij")
    df = pd.DataFrame({d: g.ravel() for d, g in zip(dims, grids)})
    df["metric"] = metric
    df["value"] = v.ravel()
    for k, val in keys.items():
        df[k] = val
    return df
