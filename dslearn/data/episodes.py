r"""Tracking episodes from real pedestrian trajectories (ETH/UCY) for the Yu-style studies.

An *episode* is a window of ``K`` steps (``K + 1`` states, :math:`\Delta t` apart) in which ``m``
pedestrians of one scene file are all present and interact: at the window start they form a
*mutual nearest-neighbour group* (each member's ``m - 1`` nearest pedestrians, among those
present for the whole window, are exactly the other members) whose largest pairwise distance
is at most ``max_dist``. The truth is the project's joint state layout, ``(B, K+1, 4m)`` with
``[p_x, p_y, v_x, v_y]`` per agent, velocities by finite differences of the (resampled)
positions (central in the interior, one-sided at the two ends, so exact for linear motion).

Time: a scene's rows are ``scene.dt`` apart; positions at the study's :math:`\Delta t` are
obtained by linear interpolation of each pedestrian's track (exact copies when the two
steps agree). The tracking studies use *physical* time (``load_scene(...,
convention="physical")``: ``biwi_eth.txt`` rows are 10/15 s apart, the others 0.4 s).

A scene is anything with ``name`` (str), ``dt`` (float, seconds per row step) and ``df``
(DataFrame with columns ``file, ped, t, x, y``; ``t`` in seconds, ``ped`` unique across the
scene's files), e.g. :class:`dslearn.data.ethucy.Scene`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from dslearn.errors import ConfigError, check_choice, check_integer, check_positive

CRITERIA = ("mutual", "closest")
SPLITS = ("time", "scene", "random")
_EPS = 1e-6


@dataclass
class EpisodeSet:
    """Ground-truth episodes of ``m`` interacting pedestrians.

    Attributes:
        states: ``(B, K+1, 4m)`` float64 joint states ``[p_x, p_y, v_x, v_y]`` per agent.
        meta: one row per episode: ``scene, file, peds`` (comma-separated ids), ``t0`` and
            ``t1`` (window start/end, s), ``dist0`` (group diameter at the start, m),
            ``file_tmin, file_tmax`` (the file's time range, for time splits).
        dt: seconds between states.
    """

    states: Tensor
    meta: pd.DataFrame
    dt: float
    num_agents: int = 2
    attrs: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return self.states.shape[0]

    @property
    def steps(self) -> int:
        return self.states.shape[1] - 1

    @property
    def positions(self) -> Tensor:
        """``(B, K+1, m, 2)``."""
        return self.states.unflatten(-1, (-1, 4))[..., :2]

    def select(self, idx) -> "EpisodeSet":
        idx = np.asarray(idx, dtype=np.int64)
        return EpisodeSet(
            self.states[torch.as_tensor(idx)], self.meta.iloc[idx].reset_index(drop=True), self.dt, self.num_agents, dict(self.attrs)
        )

    @staticmethod
    def concat(sets: Sequence["EpisodeSet"]) -> "EpisodeSet":
        sets = [s for s in sets if len(s)]
        if not sets:
            raise ValueError("no episodes to concatenate")
        dts = {round(s.dt, 12) for s in sets}
        if len(dts) != 1 or len({s.num_agents for s in sets}) != 1:
            raise ValueError("episode sets differ in dt or number of agents")
        return EpisodeSet(
            torch.cat([s.states for s in sets]),
            pd.concat([s.meta for s in sets], ignore_index=True),
            sets[0].dt,
            sets[0].num_agents,
        )


def finite_difference_velocity(pos: np.ndarray, dt: float) -> np.ndarray:
    """Velocities of positions sampled ``dt`` apart along axis 0 (central inside, one-sided ends).

    Args:
        pos: ``(K+1, ...)`` positions, ``K >= 1``.
    Returns:
        ``(K+1, ...)`` velocities; exact when the motion is linear in time.
    """
    if pos.shape[0] < 2:
        raise ValueError("need at least two positions for a finite difference")
    return np.gradient(pos, dt, axis=0, edge_order=1)


def resample_track(t: np.ndarray, xy: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Linear interpolation of one track ``(t (n,), xy (n, 2))`` at ``times (k,)`` -> ``(k, 2)``.

    ``times`` must lie inside ``[t[0], t[-1]]`` (up to 1e-6 s); exact at the sample times.
    """
    if times.min() < t[0] - _EPS or times.max() > t[-1] + _EPS:
        raise ValueError("resample_track: times outside the track")
    times = np.clip(times, t[0], t[-1])
    return np.stack([np.interp(times, t, xy[:, 0]), np.interp(times, t, xy[:, 1])], -1)


def _groups(pos: np.ndarray, m: int, max_dist: float, criterion: str) -> list[tuple[int, ...]]:
    """Interacting groups among ``n`` pedestrians at positions ``pos (n, 2)``.

    ``mutual``: ``{i} ∪ NN_{m-1}(i)`` such that every member's ``m - 1`` nearest neighbours are
    the other members (for ``m = 2``: mutual nearest neighbours). ``closest``: the candidate
    groups ``{i} ∪ NN_{m-1}(i)`` taken greedily by increasing diameter, disjoint. Both require
    the diameter (largest pairwise distance) ``<= max_dist``. Ties broken by index.
    """
    n = pos.shape[0]
    if n < m:
        return []
    d = np.sqrt(((pos[:, None, :] - pos[None, :, :]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    nn = np.argsort(d, axis=1, kind="stable")[:, : m - 1]  # (n, m-1)
    cands = {}
    for i in range(n):
        g = tuple(sorted([i, *nn[i].tolist()]))
        sub = d[np.ix_(g, g)]
        diam = float(np.where(np.isinf(sub), 0.0, sub).max())
        if diam <= max_dist:
            cands[g] = diam
    if criterion == "mutual":
        out = []
        for g in cands:
            if all(tuple(sorted([j, *nn[j].tolist()])) == g for j in g):
                out.append(g)
        return sorted(out)
    out, used = [], set()
    for g, _ in sorted(cands.items(), key=lambda kv: (kv[1], kv[0])):
        if used.isdisjoint(g):
            out.append(g)
            used.update(g)
    return sorted(out)


def _file_windows(fdf: pd.DataFrame, span: float, stride: int, dt: float):
    """One recording file's tracks ``{ped: (t (n,), xy (n, 2))}`` in time order, its time range ``tmin, tmax`` and the
    number of windows of ``span`` seconds starting every ``stride`` steps of ``dt`` from ``tmin``."""
    tracks = {}
    for ped, g in fdf.groupby("ped", sort=True):
        g = g.sort_values("t")
        tracks[ped] = (g["t"].to_numpy(float), g[["x", "y"]].to_numpy(float))
    tmin, tmax = float(fdf["t"].min()), float(fdf["t"].max())
    n_start = int(math.floor((tmax - span - tmin) / (stride * dt) + _EPS)) + 1
    return tracks, tmin, tmax, n_start


def extract_episodes(
    scene: Any,
    num_agents: int = 2,
    steps: int = 11,
    dt: float | None = None,
    max_dist: float = 3.0,
    stride: int | None = None,
    criterion: str = "mutual",
    min_speed: float = 0.0,
) -> EpisodeSet:
    r"""Windows of ``steps`` steps in which ``num_agents`` pedestrians are present and interact.

    Candidate windows start every ``stride`` study steps from each file's first time (default
    ``stride = steps``: a group's consecutive windows touch but do not overlap). A pedestrian is
    a candidate if its track covers the whole window; groups are chosen among the candidates
    at the window start (see :func:`_groups`); one episode per group and window.

    Args:
        scene: a scene (``name``, ``dt``, ``df`` with ``file, ped, t, x, y``).
        num_agents: ``m`` (>= 2).
        steps: ``K`` (episode has ``K + 1`` states).
        dt: study :math:`\Delta t` in seconds (``None``: the scene's own step).
        max_dist: largest pairwise distance within a group at the window start (m).
        stride: window start spacing in study steps.
        criterion: ``mutual`` or ``closest``.
        min_speed: drop episodes in which some member's mean speed is below this (m/s).
    Returns:
        :class:`EpisodeSet` (may be empty).
    """
    check_integer("task.agents", num_agents, 2)
    check_integer("task.steps", steps, 1)
    check_choice("task.criterion", criterion, CRITERIA)
    check_positive("task.max_dist", max_dist)
    check_positive("task.min_speed", min_speed, strict=False)
    dt = float(scene.dt if dt is None else dt)
    check_positive("task.dt", dt)
    stride = steps if stride is None else stride
    check_integer("task.stride", stride, 1)
    m, span = num_agents, steps * dt
    states, rows = [], []
    df = scene.df
    for file, fdf in df.groupby("file", sort=True):
        tracks, tmin, tmax, n_start = _file_windows(fdf, span, stride, dt)
        ids = np.array(list(tracks))
        first = np.array([tracks[p][0][0] for p in ids])
        last = np.array([tracks[p][0][-1] for p in ids])
        for k in range(max(n_start, 0)):
            t0 = tmin + k * stride * dt
            present = np.nonzero((first <= t0 + _EPS) & (last >= t0 + span - _EPS))[0]
            if present.size < m:
                continue
            times = t0 + dt * np.arange(steps + 1)
            p0 = np.stack([resample_track(*tracks[ids[i]], times[:1])[0] for i in present])
            for g in _groups(p0, m, max_dist, criterion):
                peds = [ids[present[i]] for i in g]
                pos = np.stack([resample_track(*tracks[p], times) for p in peds], 1)  # (K+1, m, 2)
                vel = finite_difference_velocity(pos, dt)
                if min_speed > 0 and (np.linalg.norm(vel, axis=-1).mean(0) < min_speed).any():
                    continue
                states.append(np.concatenate([pos, vel], -1).reshape(steps + 1, 4 * m))
                diam = max(np.linalg.norm(pos[0, a] - pos[0, b]) for a in range(m) for b in range(a + 1, m))
                rows.append(
                    dict(
                        scene=str(scene.name),
                        file=str(file),
                        peds=",".join(str(int(p)) if float(p).is_integer() else str(p) for p in peds),
                        t0=float(t0),
                        t1=float(t0 + span),
                        dist0=float(diam),
                        file_tmin=tmin,
                        file_tmax=tmax,
                    )
                )
    cols = ["scene", "file", "peds", "t0", "t1", "dist0", "file_tmin", "file_tmax"]
    meta = pd.DataFrame(rows, columns=cols)
    st = torch.as_tensor(np.stack(states), dtype=torch.float64) if states else torch.zeros(0, steps + 1, 4 * m, dtype=torch.float64)
    return EpisodeSet(st, meta, dt, m)


def extract_crowd_windows(scene: Any, max_agents: int, steps: int, dt: float | None = None,
                          stride: int | None = None) -> EpisodeSet:
    r"""Windows of ``steps`` steps with **every** pedestrian of the recording in them, each present over the part
    of the window its track covers (pedestrians enter and leave).

    Candidate windows start every ``stride`` study steps from each file's first time (as
    :func:`extract_episodes`). A pedestrian is in a window if its track covers at least two of the window's
    times (a velocity needs two); over the times its track covers it has its interpolated position and its
    finite-difference velocity (:func:`finite_difference_velocity` over that stretch), elsewhere ``NaN`` (absent).
    A window with more than ``max_agents`` pedestrians is dropped (counted in ``attrs["too_crowded"]``), one with
    none too; the pedestrians of a window fill its first slots in the order of their ids, the rest stay absent.

    Returns:
        :class:`EpisodeSet` of ``(B, K+1, 4 max_agents)`` states (``NaN`` where absent); ``meta`` as
        :func:`extract_episodes`' (``dist0`` is ``NaN``) plus ``agents``, the pedestrians in the window.
    """
    check_integer("scenario.episodes.max_agents", max_agents, 1)
    check_integer("scenario.episodes.steps", steps, 1)
    dt = float(scene.dt if dt is None else dt)
    check_positive("scenario.episodes.dt", dt)
    stride = steps if stride is None else stride
    check_integer("scenario.episodes.stride", stride, 1)
    span = steps * dt
    states, rows, crowded = [], [], 0
    for file, fdf in scene.df.groupby("file", sort=True):
        tracks, tmin, tmax, n_start = _file_windows(fdf, span, stride, dt)
        for k in range(max(n_start, 0)):
            t0 = tmin + k * stride * dt
            times = t0 + dt * np.arange(steps + 1)
            inside = []
            for ped, (t, xy) in tracks.items():
                on = (times >= t[0] - _EPS) & (times <= t[-1] + _EPS)
                if on.sum() >= 2:
                    inside.append((ped, on, t, xy))
            if not inside:
                continue
            if len(inside) > max_agents:
                crowded += 1
                continue
            st = np.full((steps + 1, max_agents, 4), np.nan)
            for a, (ped, on, t, xy) in enumerate(inside):
                pos = resample_track(t, xy, times[on])
                st[on, a, :2] = pos
                st[on, a, 2:] = finite_difference_velocity(pos, dt)
            states.append(st.reshape(steps + 1, 4 * max_agents))
            rows.append(dict(scene=str(scene.name), file=str(file),
                             peds=",".join(str(int(p)) if float(p).is_integer() else str(p) for p, *_ in inside),
                             t0=float(t0), t1=float(t0 + span), dist0=math.nan, file_tmin=tmin, file_tmax=tmax,
                             agents=len(inside)))
    cols = ["scene", "file", "peds", "t0", "t1", "dist0", "file_tmin", "file_tmax", "agents"]
    st = (torch.as_tensor(np.stack(states), dtype=torch.float64) if states
          else torch.zeros(0, steps + 1, 4 * max_agents, dtype=torch.float64))
    return EpisodeSet(st, pd.DataFrame(rows, columns=cols), dt, max_agents, {"too_crowded": crowded})


def split_episodes(
    eps: EpisodeSet,
    mode: str = "time",
    test_fraction: float = 0.2,
    test_scenes: Sequence[str] | None = None,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Train/test indices.

    ``time``: per scene file, the last ``test_fraction`` of the file's time range is the test
    period; an episode is *train* if it ends at or before the boundary, *test* if it starts at
    or after it; episodes straddling the boundary are dropped (no moment of any pedestrian is in
    both sets). ``scene``: episodes of ``test_scenes`` are test, the rest train. ``random``: a
    random ``test_fraction`` of the episodes (windows of one group can then sit side by side in
    train and test). Train indices are shuffled with ``seed`` (the order online learning sees
    them), test indices are in time order.
    """
    check_choice("task.split", mode, SPLITS)
    meta = eps.meta
    n = len(meta)
    rng = np.random.default_rng(seed)
    if mode == "scene":
        if not test_scenes:
            raise ConfigError("task.test_scenes must name at least one scene when task.split=scene")
        test_mask = meta["scene"].isin(list(test_scenes)).to_numpy()
        train_mask = ~test_mask
    else:
        if not 0.0 < float(test_fraction) < 1.0:
            raise ConfigError(f"task.test_fraction={test_fraction!r} must be in (0, 1)")
        if mode == "time":
            bound = meta["file_tmin"] + (1.0 - float(test_fraction)) * (meta["file_tmax"] - meta["file_tmin"])
            train_mask = (meta["t1"] <= bound + _EPS).to_numpy()
            test_mask = (meta["t0"] >= bound - _EPS).to_numpy()
        else:
            perm = rng.permutation(n)
            n_test = int(round(float(test_fraction) * n))
            test_mask = np.zeros(n, bool)
            test_mask[perm[:n_test]] = True
            train_mask = ~test_mask
    train = np.nonzero(train_mask)[0]
    test = np.nonzero(test_mask)[0]
    train = train[rng.permutation(len(train))]
    order = np.lexsort((meta["t0"].to_numpy()[test], meta["file"].to_numpy()[test]))
    return train, test[order]
