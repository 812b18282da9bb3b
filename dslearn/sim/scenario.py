r"""Ground-truth episodes of interacting agents and the network's measurements (Yu et al. V-A)."""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from dslearn.episodes import ScenarioSpec, Episodes
from dslearn.errors import ConfigError, check_positive
from dslearn.models.social_force import SOFTENING, SocialForce
from dslearn.network import SensorNetwork
from dslearn.streams import Streams, rand, randn
from dslearn.types import AGENT_DIM, StepContext, agents, joint


class SocialForceScenario:
    r"""Agents driven by the social force model, starting uniformly in squares.

    Args:
        desired_velocities: ``A`` pairs :math:`v_j^*` (also the initial velocities).
        start_corners: ``A`` lower-left corners of the start squares.
        start_size: side of the start squares.
        tau, alpha, beta: social force parameters (shared or per agent).
        process_std: :math:`\sigma_\eta`, added to position and velocity each step.
        horizon: ``T`` in seconds; dt: :math:`\Delta t` in seconds; ``K = T/\Delta t`` steps.
        softening: interaction softening radius in metres (bounded forces when agents nearly
            coincide, :func:`~dslearn.models.social_force.soft_distance`).
    """

    def __init__(
        self,
        desired_velocities: Sequence[Sequence[float]] = ((1.0, -1.0), (-1.0, -1.0)),
        start_corners: Sequence[Sequence[float]] = ((1.5, 5.0), (5.0, 5.0)),
        start_size: float = 1.5,
        tau: float | Sequence[float] = 0.25,
        alpha: float | Sequence[float] = 6.0,
        beta: float | Sequence[float] = 5.0,
        process_std: float = 1e-3,
        horizon: float = 3.0,
        dt: float = 0.25,
        area: Sequence[float] = (0.0, 8.0, 0.0, 8.0),
        softening: float = SOFTENING,
    ):
        check_positive("scenario.dt", dt)
        check_positive("scenario.horizon", horizon)
        check_positive("scenario.start_size", start_size, strict=False)
        check_positive("scenario.process_std", process_std, strict=False)
        self.sfm = SocialForce(desired_velocities, tau, alpha, beta, noise_std=max(process_std, 1e-12), softening=softening)
        self.num_agents = self.sfm.num_agents
        corners = torch.as_tensor(start_corners, dtype=torch.float64)
        if corners.shape != (self.num_agents, 2):
            raise ConfigError(
                f"scenario.start_corners must hold {self.num_agents} [x, y] pairs (one per agent), "
                f"got shape {tuple(corners.shape)}"
            )
        steps = horizon / dt
        if abs(steps - round(steps)) > 1e-9:
            raise ConfigError(f"scenario.horizon={horizon} must be a multiple of scenario.dt={dt}")
        self.corners = corners
        self.start_size = float(start_size)
        self.process_std = float(process_std)
        self.dt = float(dt)
        self.steps = int(round(steps))
        self.area = tuple(float(a) for a in area)

    #: the sensors are placed by the run's ``network`` part (this scenario has none of its own)
    network = None

    @property
    def state_dim(self) -> int:
        return AGENT_DIM * self.num_agents

    @property
    def spec(self) -> ScenarioSpec:
        """What the scenario offers (:class:`~dslearn.episodes.ScenarioSpec`): positions of ``A`` agents
        measured by range-limited sensors, states ``[p, v]`` per agent, moved by the social force (``dynamics``,
        its parameters :attr:`sfm`)."""
        return ScenarioSpec("yu", "position", self.num_agents, "pv2d", self.dt, self.steps, dynamics="social_force")

    def positions(self, states: Tensor) -> Tensor:
        """``(B, K+1, 4A) -> (B, K+1, A, 2)``."""
        return agents(states)[..., :2]

    def ctx(self) -> StepContext:
        return StepContext(dt=self.dt)

    def sample(self, num: int, network: SensorNetwork, generator: torch.Generator | Streams) -> Episodes:
        """Simulate ``num`` episodes (vectorised over episodes) and the network's measurements.

        ``generator``: one ``torch.Generator`` for the batch, or :class:`~dslearn.streams.Streams`
        over ``(num,)`` (one stream per episode, e.g. :func:`episode_streams`): then episode ``i``
        depends only on its own stream, not on how many episodes are drawn with it.
        """
        a, k = self.num_agents, self.steps
        per_ep = isinstance(generator, Streams)
        pos0 = self.corners + self.start_size * rand((num, a, 2), generator)
        # an episode's draws, in its stream's order: start positions, process noise, measurement noise
        noise = randn((num, k, self.state_dim), generator) if per_ep else None
        vel0 = self.sfm.desired.expand(num, a, 2)
        x = joint(torch.cat([pos0, vel0], -1))
        traj = [x]
        ctx = self.ctx()
        for t in range(k):
            eta = noise[:, t] if per_ep else torch.randn(x.shape, generator=generator, dtype=x.dtype)
            x = self.sfm(x, ctx) + self.process_std * eta
            traj.append(x)
        return measure(torch.stack(traj, 1), network, generator)


def measure(states: Tensor, network: SensorNetwork, generator: torch.Generator | Streams) -> Episodes:
    """Range-limited noisy position measurements of true joint states ``(B, K+1, 4A)``:
    noise ``(S, B, K+1, A, 2)`` drawn from ``generator`` (or, from per-episode
    :class:`~dslearn.streams.Streams` over ``(B,)``, episode by episode), zeroed where a node does
    not see the agent. Used for simulated and for real (ETH/UCY) trajectories alike."""
    pos = agents(states)[..., :2]  # (B, K+1, A, 2)
    vis = network.visible(pos)  # (S, B, K+1, A)
    if isinstance(generator, Streams):
        noise = network.meas_std * randn((pos.shape[0], network.num_nodes, *pos.shape[1:]), generator, dtype=pos.dtype).transpose(0, 1)
    else:
        noise = network.meas_std * torch.randn((network.num_nodes, *pos.shape), generator=generator, dtype=pos.dtype)
    meas = (pos.unsqueeze(0) + noise.to(pos.device)) * vis.unsqueeze(-1)
    return Episodes(states, meas, vis)


def episode_streams(seed: int, split: str, start: int, num: int) -> Streams:
    """One random stream per episode ``start .. start + num - 1`` of ``split`` (``"train"``,
    ``"test"``, ...): episode ``i`` of a run is the same whatever the data-set size."""
    return Streams.from_keys([(int(seed), str(split), int(i)) for i in range(start, start + num)], (num,))


def sample_split(scenario, network, seed: int, test_episodes: int, train_episodes: int, dtype, device):
    """The (test, train) episodes of a run, on ``device`` in ``dtype``. One random stream per
    episode (:func:`episode_streams`), so episode ``i`` of either set is the same whatever the
    number of training or test episodes. A recorded scenario (``spec.source == "recorded"``) is told the
    pool each set comes from (``split=``)."""
    pools = getattr(getattr(scenario, "spec", None), "source", None) == "recorded"

    def draw(num, split):
        streams = episode_streams(seed, split, 0, num)
        return scenario.sample(num, network, streams, split=split) if pools else scenario.sample(num, network, streams)

    test, train = draw(test_episodes, "test"), draw(train_episodes, "train")
    return test.to(dtype, device), train.to(dtype, device)
