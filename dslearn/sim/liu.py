r"""Liu et al.'s scenarios S1-S3 (FUSION 2022, Sec. V-A) as scenarios of the matrix: one target whose
trajectory a manoeuvre generator of :mod:`dslearn.sim.manoeuvres` draws, measured by a fixed field of
range-limited position sensors with the paper's noise, the sensors linked by a communication radius.

The field is drawn once per run seed (``seed``; the paper draws one per Monte Carlo run): ``num_sensors``
sensors uniform over the square ``[-area_size/2, area_size/2]^2``
(:func:`~dslearn.sim.manoeuvres.sensor_field`), each measuring the target's position within
``sensing_range`` with i.i.d. ``N(0, meas_std^2)`` noise per axis (:func:`~dslearn.sim.manoeuvres.measure`).
Two sensors closer than ``comm_radius`` talk to each other; a field whose graph is disconnected is
refused (:class:`~dslearn.errors.ConfigError` naming ``scenario.comm_radius``). The trajectories are
centred on the origin, the centre of the area, as in the Liu study.

The state is the project's ``pv2d`` layout (one agent ``[px, py, vx, vy]``), so the distributed filters
fit as well as Liu's tracker.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from dslearn.episodes import Episodes, ScenarioSpec
from dslearn.errors import ConfigError, check_integer, check_positive
from dslearn.network import SensorNetwork, adjacency_from_radius, is_connected
from dslearn.sim.manoeuvres import measure, sensor_field
from dslearn.streams import Streams, stream_seed
from dslearn.types import StepContext, agents

#: the key of the sensor field's random stream (with the run seed)
FIELD_STREAM = "liu_sensor_field"


def components(adj: Tensor) -> int:
    """The number of connected components of the undirected graph ``adj (S, S)``."""
    adj = torch.as_tensor(adj).to(torch.bool)
    s = adj.shape[0]
    seen = torch.zeros(s, dtype=torch.bool)
    n = 0
    for i in range(s):
        if seen[i]:
            continue
        n += 1
        frontier = torch.zeros(s, dtype=torch.bool)
        frontier[i] = True
        seen[i] = True
        while frontier.any():
            nxt = adj[frontier].any(0) & ~seen
            seen |= nxt
            frontier = nxt
    return n


def field_network(positions: Tensor, comm_radius: float, sensing_range: float, meas_std: float,
                  seed: int | None = None) -> SensorNetwork:
    """Every node a sensor at ``positions (S, 2)``, linked within ``comm_radius``.

    Raises:
        ConfigError: the graph is disconnected (naming ``scenario.comm_radius``, the number of components
            and the radius that would connect this field).
    """
    check_positive("scenario.comm_radius", comm_radius)
    adj = adjacency_from_radius(positions, float(comm_radius))
    if positions.shape[0] > 1 and not is_connected(adj):
        # the smallest radius that connects this field: the longest edge of its minimum spanning tree
        need = _connecting_radius(positions)
        of = "" if seed is None else f" drawn with seed={seed}"
        raise ConfigError(
            f"scenario.comm_radius={comm_radius:g} leaves the sensor field{of} disconnected "
            f"({components(adj)} groups of sensors that cannot reach each other); this field needs "
            f"scenario.comm_radius >= {need:.4g} (or more sensors: scenario.num_sensors)")
    return SensorNetwork(positions, positions.shape[0], adj, float(sensing_range), float(meas_std))


def _connecting_radius(positions: Tensor) -> float:
    """The longest edge of the Euclidean minimum spanning tree of ``positions (S, 2)`` (Prim)."""
    d = torch.cdist(positions, positions)
    s = d.shape[0]
    inside = torch.zeros(s, dtype=torch.bool)
    inside[0] = True
    best = d[0].clone()
    longest = 0.0
    for _ in range(s - 1):
        cand = torch.where(inside, torch.full_like(best, float("inf")), best)
        j = int(cand.argmin())
        longest = max(longest, float(cand[j]))
        inside[j] = True
        best = torch.minimum(best, d[j])
    return longest


class ManoeuvreScenario:
    r"""One target manoeuvring as in Liu et al.'s S1, S2 or S3, a fixed sensor field per run seed.

    Args:
        trajectory: the generator, ``trajectory(runs, steps, generator, dt=...)`` -> positions and
            velocities ``(runs, steps, 2)`` (:data:`dslearn.sim.manoeuvres.GENERATORS`, its parameters
            bound: a ``functools.partial``).
        name: the scenario's label in the tables (``s1``, ``s2``, ``s3``).
        steps: ``K`` (an episode has ``K + 1`` states).
        dt: seconds per step.
        num_sensors, sensing_range, area_size: the sensor field (``area_size``: side of the square).
        meas_std: the measurement noise standard deviation per axis (m).
        comm_radius: two sensors closer than this communicate.
        seed: the run seed (the field's random stream is keyed by it).
    """

    #: the scenario places its own sensors (the run's ``network`` part is not used)
    owns_network = True

    def __init__(self, trajectory: Callable, name: str = "s1", steps: int = 60, dt: float = 1.0,
                 num_sensors: int = 200, sensing_range: float = 50.0, area_size: float = 1000.0,
                 meas_std: float = 2.0, comm_radius: float = 200.0, seed: int = 0):
        if not callable(trajectory):
            raise ConfigError(f"scenario.trajectory={trajectory!r} must be a trajectory generator "
                              "(_target_: dslearn.sim.manoeuvres.generate_s1|s2|s3, _partial_: true)")
        check_integer("scenario.steps", steps, 2)
        check_integer("scenario.num_sensors", num_sensors, 1)
        for key, v in (("dt", dt), ("sensing_range", sensing_range), ("area_size", area_size),
                       ("meas_std", meas_std)):
            check_positive(f"scenario.{key}", v)
        check_integer("scenario.seed", seed, 0)
        self.trajectory = trajectory
        self.name = str(name)
        self.steps = steps
        self.dt = float(dt)
        self.area_size = float(area_size)
        self.seed = seed
        half = 0.5 * self.area_size
        self.area = (-half, half, -half, half)
        gen = torch.Generator().manual_seed(stream_seed(seed, FIELD_STREAM))
        pos = sensor_field(1, num_sensors, self.area_size, gen)[0]
        self.network = field_network(pos, float(comm_radius), float(sensing_range), float(meas_std), seed)

    num_agents = 1
    state_dim = 4

    @property
    def spec(self) -> ScenarioSpec:
        """One target measured by range-limited position sensors, state ``[p, v]``."""
        return ScenarioSpec(self.name, "position", 1, "pv2d", self.dt, self.steps)

    def ctx(self) -> StepContext:
        return StepContext(dt=self.dt)

    def positions(self, states: Tensor) -> Tensor:
        """``(B, K+1, 4) -> (B, K+1, 1, 2)``."""
        return agents(states)[..., :2]

    def _draw(self, runs: int, gen: torch.Generator, sensors: Tensor, sensing_range: float, meas_std: float):
        """Trajectories and their measurements from one generator: truth ``(R, K+1, 4)``, ``z (R, S, K+1, 2)``,
        ``avail (R, S, K+1)`` (the trajectory's draws first, then the noise)."""
        pos, vel = self.trajectory(runs, self.steps + 1, gen, dt=self.dt)
        z, avail = measure(pos, sensors.expand(runs, -1, -1), sensing_range,
                           torch.full((runs,), meas_std, dtype=pos.dtype), gen)
        return torch.cat([pos, vel], -1), z, avail

    def sample(self, num: int, network: SensorNetwork, generator: torch.Generator | Streams) -> Episodes:
        """``num`` episodes measured by the sensing nodes of ``network`` (its sensing range and noise).

        ``generator``: one ``torch.Generator`` for the batch, or per-episode :class:`~dslearn.streams.Streams`
        (then episode ``i``, its trajectory and its noise, depends only on its own stream)."""
        s = network.num_sensors
        sensors = network.positions[:s].to(torch.float64)[None]
        r, sig = float(network.sensing_range), float(network.meas_std)
        if isinstance(generator, Streams):
            if generator.shape != (num,):
                raise ValueError(f"ManoeuvreScenario.sample: streams over {generator.shape} for {num} episodes")
            parts = [self._draw(1, g, sensors, r, sig) for g in generator.gens]
            if parts:
                states, z, avail = (torch.cat(p) for p in zip(*parts))
            else:
                states = torch.zeros(0, self.steps + 1, 4, dtype=torch.float64)
                z = torch.zeros(0, s, self.steps + 1, 2, dtype=torch.float64)
                avail = torch.zeros(0, s, self.steps + 1, dtype=torch.bool)
        else:
            states, z, avail = self._draw(num, generator, sensors, r, sig)
        n = network.num_nodes
        meas = torch.zeros(n, num, self.steps + 1, 1, 2, dtype=states.dtype)
        vis = torch.zeros(n, num, self.steps + 1, 1, dtype=torch.bool)
        meas[:s, :, :, 0] = z.transpose(0, 1)
        vis[:s, :, :, 0] = avail.transpose(0, 1)
        return Episodes(states, meas, vis)
