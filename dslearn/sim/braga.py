r"""Braga et al.'s setting (terrain-based navigation, Section VI / Table I) as a scenario of the matrix: four
aircraft in finger-four formation fly at constant velocity over a terrain map; each measures, with its radar
altimeter, the terrain height under itself plus jump-Markov noise (``y = h(p) + mu_r + sigma_r eps``,
Eq. 25). Each aircraft is a node of the network (the formation's edges) and navigates itself: the
"targets" are the platforms, node ``s`` measures platform ``s`` only.

* ``spec``: measurement ``terrain_altitude``, ``A = 4`` platforms, state ``platform`` (per platform
  ``[p_X, p_Y, v_X, v_Y]``, ``Dx = 16``; the nodes are the platforms, not sensors of targets).
* measurements ``(S, B, K+1, A, 2)``: ``meas[s, b, t, s, 0]`` the altimeter reading ``y_{s,t}`` [m];
  ``meas[s, b, 0, s, 1]`` the altimeter's mode at ``t = 0`` (known at the start, Section VI: the filters
  start from ``alpha_{0|0} = 1(r_0 = l)``), zero elsewhere; only ``(s, s)`` is visible.
* the map (:attr:`terrain`) and the start (:meth:`initial_states`, the same every flight: the leader at
  ``start``, the formation behind it, all at ``v0``) are known to the navigators, as in the paper.

The map is drawn once per run seed, as the study draws it (``seed * 7919 + seed_offset + 17``). Episode ``b``
draws its flight, modes and noise from its own stream with :func:`dslearn.sim.terrain.simulate`: streams
keyed ``(seed, "truth", r)`` give the ``braga_tbn`` study's Monte Carlo run ``r``.
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from dslearn.episodes import Episodes, ScenarioSpec
from dslearn.errors import ConfigError, check_integer, check_keys, check_positive
from dslearn.fusion.statistics import network_adjacency
from dslearn.models.jmnls import make_params
from dslearn.network import SensorNetwork
from dslearn.sim.terrain import TerrainMap, cv_model, finger_four_offsets, make_terrain, simulate
from dslearn.streams import Streams
from dslearn.types import StepContext, agents

#: the finger four
NUM_AIRCRAFT = 4
NAMES = ["leader", "wingman", "element_lead", "element_wingman"]
TERRAIN_KEYS = ("size_m", "resolution_m", "smoothing_m", "elevation_std_m", "mean_elevation_m", "seed_offset")


def terrain_seed(seed: int, seed_offset: int) -> int:
    """The map's generator seed (the study's :func:`~dslearn.learning.online_em.prepare_job`)."""
    return int(seed) * 7919 + int(seed_offset) + 17


@functools.lru_cache(maxsize=4)
def terrain_map(seed: int, size_m: float, resolution_m: float, smoothing_m: float, elevation_std_m: float,
                mean_elevation_m: float, seed_offset: int) -> TerrainMap:
    """The map of a run seed (float64, CPU), as the study draws it; kept for the next scenario of the same
    values (a sweep builds the scenario once per combination; a 25 km map takes seconds). Read-only."""
    gen = torch.Generator().manual_seed(terrain_seed(seed, seed_offset))
    return make_terrain(size_m, resolution_m, smoothing_m, elevation_std_m, mean_elevation_m, gen=gen,
                        dtype=torch.float64)


class TerrainScenario:
    """The finger-four formation over a terrain map with jump-Markov altimeter noise.

    Args:
        name: the label in the tables.
        steps: ``K`` measurements (an episode has ``K + 1`` states); dt: ``T`` [s].
        truth_process_noise: the aircraft's true acceleration noise ``Q = q I`` [(m/s^2)^2] (0: stabilised flight).
        v0, start, formation_spacing: the formation's velocity [m/s], the leader's start [m], the spacing [m].
        mu_true, sigma_true, pi_true: the altimeter's true modes (means, standard deviations [m], transitions).
        terrain: the map (``size_m``, ``resolution_m``, ``smoothing_m``, ``elevation_std_m``,
            ``mean_elevation_m``, ``seed_offset``).
        edges: the communication graph of the four aircraft (node 0 = the leader).
        seed: the run seed (the map is drawn from it).
    """

    owns_network = True
    num_agents = NUM_AIRCRAFT
    state_dim = 4 * NUM_AIRCRAFT

    def __init__(self, name: str = "braga", steps: int = 1800, dt: float = 0.05, truth_process_noise: float = 0.0,
                 v0=(170.0, 170.0), start=(3000.0, 3000.0), formation_spacing: float = 100.0,
                 mu_true=(0.0, 20.0), sigma_true=(1.0, 4.0), pi_true=((0.85, 0.15), (0.4, 0.6)),
                 terrain: dict | None = None, edges=((0, 1), (0, 2), (2, 3)), seed: int = 0):
        check_integer("scenario.steps", steps, 1)
        check_positive("scenario.dt", dt)
        check_positive("scenario.truth_process_noise", truth_process_noise, strict=False)
        check_positive("scenario.formation_spacing", formation_spacing)
        for key, v in (("v0", v0), ("start", start)):
            if not isinstance(v, (list, tuple)) or len(v) != 2:
                raise ConfigError(f"scenario.{key}={v!r} must be a list of 2 numbers [m or m/s]")
        if float(torch.as_tensor(v0, dtype=torch.float64).norm()) == 0.0:
            raise ConfigError("scenario.v0 must be non-zero (it sets the formation's heading)")
        check_integer("scenario.seed", seed, 0)
        terrain = check_keys("scenario.terrain", terrain or {}, TERRAIN_KEYS)
        t = {"size_m": 25000.0, "resolution_m": 25.0, "smoothing_m": 250.0, "elevation_std_m": 100.0,
             "mean_elevation_m": 500.0, "seed_offset": 0, **terrain}
        for key in ("size_m", "resolution_m", "smoothing_m", "elevation_std_m"):
            check_positive(f"scenario.terrain.{key}", t[key])
        self.truth = make_params(list(mu_true), list(sigma_true), [list(r) for r in pi_true],
                                 prefix="scenario (true modes)")
        self.name, self.steps, self.dt, self.seed = str(name), steps, float(dt), seed
        self.v0 = tuple(float(a) for a in v0)
        self.start = tuple(float(a) for a in start)
        self.formation_spacing = float(formation_spacing)
        self.terrain = terrain_map(seed, *(float(t[k]) for k in TERRAIN_KEYS[:5]), int(t["seed_offset"]))
        self.truth_dyn = cv_model(self.dt, max(float(truth_process_noise), 1e-12), dtype=torch.float64)
        xmax, ymax = self.terrain.extent
        self.area = (0.0, float(xmax), 0.0, float(ymax))
        x0 = self.initial_states()
        if bool(self.terrain.outside(x0).any()):
            raise ConfigError(f"scenario.start={list(self.start)}: the formation starts outside the "
                              f"{xmax:g} m x {ymax:g} m map (scenario.terrain.size_m)")
        try:
            adj = network_adjacency(NUM_AIRCRAFT, [list(e) for e in edges])
        except ConfigError as e:
            raise ConfigError(str(e).replace("task.network.edges", "scenario.edges")) from None
        # nominal range and noise: each aircraft senses the ground under itself; sigma = the largest true mode's
        self.network = SensorNetwork(x0[:, :2].clone(), NUM_AIRCRAFT, adj, 0.5 * self.formation_spacing,
                                     float(self.truth.sigma.max()), names=list(NAMES))

    @property
    def spec(self) -> ScenarioSpec:
        """Four platforms navigating by terrain altitude over a communication graph."""
        return ScenarioSpec(self.name, "terrain_altitude", NUM_AIRCRAFT, "platform", self.dt, self.steps, kind="self")

    def ctx(self) -> StepContext:
        return StepContext(dt=self.dt)

    def initial_states(self) -> Tensor:
        """``(S, 4)`` the aircraft's known start ``[p_X, p_Y, v_X, v_Y]`` (float64), as the study's flights start."""
        start = torch.as_tensor(list(self.start)).to(self.terrain.z)
        v0 = torch.as_tensor(list(self.v0)).to(self.terrain.z)
        off = finger_four_offsets(self.formation_spacing, v0)
        return torch.cat([start + off, v0.expand(NUM_AIRCRAFT, 2)], -1)

    def positions(self, states: Tensor) -> Tensor:
        """``(B, K+1, 16) -> (B, K+1, 4, 2)``."""
        return agents(states)[..., :2]

    def flights(self, num: int, generator):
        """The study's :class:`~dslearn.sim.terrain.Scenario` of ``num`` flights (truth ``x (B, S, K+1, 4)``,
        modes ``r``, readings ``y``)."""
        return simulate(self.terrain, self.truth, self.truth_dyn, runs=num, start=torch.tensor(list(self.start)),
                        v0=torch.tensor(list(self.v0)), spacing=self.formation_spacing, steps=self.steps,
                        gen=generator)

    def sample(self, num: int, network: SensorNetwork, generator: torch.Generator | Streams) -> Episodes:
        """``num`` flights; ``generator``: per-episode :class:`~dslearn.streams.Streams` (flight ``i`` depends
        only on its own stream) or one ``torch.Generator``."""
        s, t1 = NUM_AIRCRAFT, self.steps + 1
        if isinstance(generator, Streams) and generator.shape != (num,):
            raise ValueError(f"TerrainScenario.sample: streams over {generator.shape} for {num} episodes")
        meas = torch.zeros(s, num, t1, s, 2, dtype=torch.float64)
        vis = torch.zeros(s, num, t1, s, dtype=torch.bool)
        if num == 0:
            return Episodes(torch.zeros(0, t1, 4 * s, dtype=torch.float64), meas, vis)
        scn = self.flights(num, generator)
        idx = torch.arange(s)
        meas[idx, :, :, idx, 0] = scn.y.transpose(0, 1)
        meas[idx, :, 0, idx, 1] = scn.r[..., 0].transpose(0, 1).to(meas.dtype)
        vis[idx, :, :, idx] = True
        states = scn.x.transpose(1, 2).flatten(-2)  # (B, K+1, S*4)
        return Episodes(states.contiguous(), meas, vis)
