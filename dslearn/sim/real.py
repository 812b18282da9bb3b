r"""A simulated LiDAR-like sensor network over real trajectories (Yu et al. Section VI-A analogue).

The paper's arena has four LiDARs around a 3.5 m x 2 m area, each talking to its two nearest
LiDARs, with location measurements of noise :math:`\sigma_\nu = 0.2` m. Over a real scene we
place ``S`` sensors around the scene's extent (the bounding box of every position in the
scene): on the ellipse through the midpoints of the box's sides, enlarged by ``margin``
(relative), at angles :math:`-\pi/2 + 2\pi i / S` (so ``S = 4`` puts one sensor at the middle
of each side, bottom first, counter-clockwise). The graph links each sensor to its
``k_nearest`` nearest sensors (symmetrised), through :func:`dslearn.sim.placement.make_network`.
A sensor measures a pedestrian only within ``sensing_range``: ``z = p + ν``, ``ν ~ N(0, σ_ν² I)``.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from dslearn.data.episodes import extract_episodes, split_episodes
from dslearn.episodes import Episodes
from dslearn.errors import ConfigError, check_integer, check_positive
from dslearn.network import SensorNetwork
from dslearn.settings import ranged
from dslearn.sim.placement import make_network
from dslearn.sim.scenario import episode_streams, measure
from dslearn.types import StepContext


def scene_extent(xy: Tensor) -> tuple[float, float, float, float]:
    """Bounding box ``(xmin, xmax, ymin, ymax)`` of positions ``(..., 2)``."""
    flat = torch.as_tensor(xy, dtype=torch.float64).reshape(-1, 2)
    lo, hi = flat.min(0).values, flat.max(0).values
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


def perimeter_positions(extent: Sequence[float], num_sensors: int = 4, margin: float = 0.0,
                        key: str = "task.network") -> Tensor:
    r"""``(S, 2)`` sensor positions around ``extent = (xmin, xmax, ymin, ymax)``.

    Sensor ``i`` sits at ``centre + (1 + margin) (w/2 cos θ_i, h/2 sin θ_i)`` with
    :math:`\theta_i = -\pi/2 + 2\pi i / S`. ``key``: the config key of these settings (named in errors).
    """
    xmin, xmax, ymin, ymax = (float(v) for v in extent)
    if not (xmax > xmin and ymax > ymin):
        raise ConfigError(f"scene extent {tuple(extent)} must have positive width and height")
    if num_sensors < 1:
        raise ConfigError(f"{key}.num_sensors={num_sensors} must be >= 1")
    check_positive(f"{key}.margin", margin, strict=False)
    cx, cy = (xmin + xmax) / 2, (ymin + ymax) / 2
    hw, hh = (1 + margin) * (xmax - xmin) / 2, (1 + margin) * (ymax - ymin) / 2
    th = -math.pi / 2 + 2 * math.pi * torch.arange(num_sensors, dtype=torch.float64) / num_sensors
    pos = torch.stack([cx + hw * torch.cos(th), cy + hh * torch.sin(th)], -1)
    return torch.where(pos.abs() < 1e-12, torch.zeros_like(pos), pos)


def arena_network(
    extent: Sequence[float],
    num_sensors: int = 4,
    k_nearest: int = 2,
    sensing_range: float = 8.0,
    meas_std: float = 0.2,
    margin: float = 0.0,
    key: str = "task.network",
) -> SensorNetwork:
    """The LiDAR network of the paper's robot arena, placed around a scene's extent.

    Args:
        extent: ``(xmin, xmax, ymin, ymax)`` of the scene (m).
        num_sensors: ``S`` sensing nodes (no communication-only nodes, as in the arena).
        k_nearest: each sensor talks to its ``k`` nearest sensors (symmetrised).
        sensing_range: a sensor measures a pedestrian closer than this (m).
        meas_std: :math:`\\sigma_\\nu` (m).
        margin: relative enlargement of the placement ellipse.
        key: the config key of these settings, named in errors (the real-data study's ``task.network``).
    Raises:
        ConfigError: bad values, or a disconnected graph (naming the field to change).
    """
    check_integer(f"{key}.k_nearest", k_nearest, 1)
    pos = perimeter_positions(extent, num_sensors, margin, key)
    try:
        return make_network(
            num_sensors=num_sensors,
            num_comm=0,
            positions=pos.tolist(),
            k_nearest=k_nearest,
            comm_radius=None,
            sensing_range=sensing_range,
            meas_std=meas_std,
        )
    except ConfigError as e:
        msg = str(e).replace("network.", f"{key}.")
        raise ConfigError(msg + f"; raise {key}.k_nearest" if "disconnected" in msg else msg) from None


@dataclass
class ArenaSettings:
    """The LiDAR-like network placed around a real scene (:func:`arena_network`'s settings; the
    real-data tracking study's ``task.network``)."""

    num_sensors: int = ranged(4, ge=1)
    k_nearest: int = ranged(2, ge=1)
    sensing_range: float = ranged(8.0, gt=0.0)
    meas_std: float = ranged(0.2, gt=0.0)
    margin: float = ranged(0.0, ge=0.0)

    def network(self, extent: Sequence[float]) -> SensorNetwork:
        """The network of these settings around ``extent`` (:func:`arena_network`)."""
        return arena_network(extent, int(self.num_sensors), int(self.k_nearest), float(self.sensing_range),
                             float(self.meas_std), float(self.margin))


@dataclass(frozen=True)
class EpisodeRecipe:
    """How a real scene is cut into episodes and split (:func:`real_source`): ``agents`` interacting
    pedestrians per episode over ``steps`` steps of ``dt`` seconds
    (:func:`dslearn.data.episodes.extract_episodes` with ``max_dist stride criterion min_speed``), split
    by ``split`` / ``test_fraction`` (:func:`dslearn.data.episodes.split_episodes`), at most
    ``test_episodes`` test episodes."""

    agents: int
    steps: int
    dt: float
    max_dist: float
    stride: int
    criterion: str
    min_speed: float
    split: str
    test_fraction: float
    test_episodes: int


@dataclass(frozen=True)
class RealScenario:
    """What a model option's factory (``_partial_``, :mod:`dslearn.compose`) needs of a data source
    that is not simulated: the agents per episode (``num_agents``, the state ``[p, v]`` per agent),
    the step ``dt``, the steps per episode ``steps`` (``K``: ``K + 1`` states) and the ``area``
    ``(xmin, xmax, ymin, ymax)`` the targets move in."""

    num_agents: int
    dt: float
    steps: int
    area: tuple[float, float, float, float]

    @property
    def state_dim(self) -> int:
        return 4 * self.num_agents

    def ctx(self) -> StepContext:
        return StepContext(dt=self.dt)


@dataclass
class Data:
    """One data source prepared for the protocol.

    ``train`` holds the training pool in the order online learning sees it; ``test`` the test
    episodes. :attr:`scenario` is what a model option is sized by.
    """

    label: str  # scene name or "synthetic"
    kind: str  # "real" | "synthetic"
    train: Episodes
    test: Episodes
    network: SensorNetwork
    ctx: StepContext
    area: tuple[float, float, float, float]  # (xmin, xmax, ymin, ymax): where the diffuse prior puts the targets
    num_agents: int
    info: dict

    @property
    def scenario(self) -> RealScenario:
        """The source as a scenario for the model options (:class:`RealScenario`)."""
        return RealScenario(int(self.num_agents), float(self.ctx.dt), int(self.test.states.shape[1]) - 1,
                            tuple(float(v) for v in self.area))


def episodes_to(ep: Episodes, dtype, device) -> Episodes:
    return Episodes(ep.states.to(device, dtype), ep.meas.to(device, dtype), ep.visible.to(device))


def real_source(scene, recipe: EpisodeRecipe, arena: ArenaSettings, seed: int, max_train: int, dtype,
                device) -> Data:
    """Episodes of ``recipe.agents`` interacting pedestrians of ``scene`` (a
    :class:`dslearn.data.ethucy.Scene`; :func:`dslearn.data.episodes.extract_episodes` with the
    recipe's ``steps dt max_dist stride criterion min_speed``), split by ``recipe.split`` (at most
    ``max_train`` training and ``recipe.test_episodes`` test episodes, seeded), the network of
    ``arena`` around the scene's extent and every episode's measurements (one noise stream
    per episode)."""
    r = recipe
    scene_name = scene.name
    eps = extract_episodes(
        scene, int(r.agents), int(r.steps), float(r.dt), float(r.max_dist), int(r.stride), str(r.criterion), float(r.min_speed)
    )
    train_idx, test_idx = split_episodes(eps, str(r.split), float(r.test_fraction), None, seed)
    n_tr, n_te = min(max_train, len(train_idx)), min(int(r.test_episodes), len(test_idx))
    if n_tr < 1 or n_te < 1:
        raise ConfigError(
            f"task.scenes: scene {scene_name!r} gives {len(train_idx)} training and {len(test_idx)} test episodes "
            f"with these settings; lower task.max_dist/task.min_speed/task.stride or choose another scene"
        )
    if n_tr < max_train or n_te < int(r.test_episodes):
        warnings.warn(
            f"scene {scene_name}: only {len(train_idx)} training / {len(test_idx)} test episodes available "
            f"(asked {max_train} / {int(r.test_episodes)}); using {n_tr} / {n_te}"
        )
    rng = np.random.default_rng(seed + 17)
    test_sel = np.sort(rng.choice(test_idx, size=n_te, replace=False)) if n_te < len(test_idx) else test_idx
    tr, te = eps.select(train_idx[:n_tr]), eps.select(test_sel)
    net = arena.network(scene_extent(torch.tensor(scene.df[["x", "y"]].to_numpy())))
    # one measurement-noise stream per episode: an episode's measurements do not depend on how
    # many episodes are drawn
    test = measure(te.states, net, episode_streams(int(seed), "test", 0, len(te.states)))
    train = measure(tr.states, net, episode_streams(int(seed), "train", 0, len(tr.states)))
    ext = tuple(float(v) for v in scene_extent(torch.tensor(scene.df[["x", "y"]].to_numpy())))
    info = {
        "episodes_total": len(eps),
        "train_pool": len(train_idx),
        "test_pool": len(test_idx),
        "scene_dt": scene.dt,
        "test_meta": te.meta,
        "visible_frac": float(test.visible[: net.num_sensors].any(0).float().mean()),
    }
    return Data(
        scene_name, "real", episodes_to(train, dtype, device), episodes_to(test, dtype, device), net,
        StepContext(dt=float(r.dt)), ext, int(r.agents), info,
    )
