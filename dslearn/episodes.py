r"""Episodes and what the network sees of them: batches of true joint states and every node's
measurements (the floor that simulation, filters, fusion and learning share)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from torch import Tensor

from dslearn.network import SensorNetwork
from dslearn.types import StepContext


@dataclass
class Measurements:
    """What the filters and the fusion see of a batch of episodes: the measurements, not the truth.

    Attributes:
        meas: ``(S, B, K+1, A, 2)`` measurements of every node (zeros where not visible).
        visible: ``(S, B, K+1, A)`` bool, which node measured which target.
    """

    meas: Tensor
    visible: Tensor

    def __len__(self) -> int:
        return self.meas.shape[1]

    @property
    def steps(self) -> int:
        """``K``: the number of steps after t = 0."""
        return self.meas.shape[2] - 1

    def select(self, idx) -> "Measurements":
        return Measurements(self.meas[:, idx], self.visible[:, idx])


@dataclass
class Episodes:
    """A batch of episodes.

    Attributes:
        states: ``(B, K+1, Dx)`` true joint states at t = 0..K.
        meas: ``(S, B, K+1, A, 2)`` measurements of every node (zeros where not visible).
        visible: ``(S, B, K+1, A)`` bool, which node measured which target.
    """

    states: Tensor
    meas: Tensor
    visible: Tensor

    def __len__(self) -> int:
        return self.states.shape[0]

    def select(self, idx) -> "Episodes":
        return Episodes(self.states[idx], self.meas[:, idx], self.visible[:, idx])

    @property
    def measurements(self) -> Measurements:
        """The part of the episodes a filter may see (the truth stays with the metrics)."""
        return Measurements(self.meas, self.visible)

    def to(self, dtype, device) -> "Episodes":
        return Episodes(self.states.to(device, dtype), self.meas.to(device, dtype), self.visible.to(device))


# ------------------------------------------------------------------------------------------------
# the matrix: what a scenario declares, what every method returns

#: kinds of measurement a scenario yields (what a method's observation side must handle)
MEASUREMENTS = ("position", "squared_range", "terrain_altitude")
#: kinds of scenario: targets seen by a network of sensors; nodes navigating themselves (one platform per node)
TARGETS, SELF = "targets", "self"
KINDS = (TARGETS, SELF)


@dataclass(frozen=True)
class ScenarioSpec:
    """What a scenario offers a method, declared (no tensors): the matrix decides by it whether a
    method fits (:meth:`dslearn.methods.base.Method.fits`).

    Attributes:
        name: label in the tables (``yu``, ``s1``, ``jiang``, ``zara1``, ...).
        measurement: one of :data:`MEASUREMENTS`: range-limited noisy positions of the targets, squared
            ranges to fixed sensors (repeated samples per step), terrain altitude under each platform.
        num_agents: ``A``, the targets (platforms) whose positions are estimated.
        state: the layout of the true states, ``pv2d`` (per agent ``[px, py, vx, vy]``, ``Dx = 4A``) or
            the scenario's own (``param2d``: a 2-D parameter per agent; ``platform``: a navigation state).
        dt: seconds per step; steps: ``K`` (an episode has ``K + 1`` states).
        units: of the positions (the RMSE's unit).
        networked: the scenario has a communication graph between its nodes.
        source: ``simulated`` or ``recorded`` (a data set).
        pools: ``(training, test)`` episodes a recorded scenario holds (a run may ask for at most these; the
            up-front check of ``task=matrix`` refuses more), ``None`` for a simulator (any number).
        dynamics: the motion model the scenario simulates its targets with, where a method may take it as
            known: ``social_force`` (Helbing's social force, its parameters the scenario's ``sfm``); ``None``
            for a recording or a simulator that offers none (``model=sfm`` needs ``social_force``).
        kind: one of :data:`KINDS`: ``targets`` (targets seen by the network's sensors) or ``self`` (every node
            navigates itself: node ``s`` measures only its own platform ``s``, Braga's aircraft).
        labelled: every measurement comes labelled with its target (``meas (S, B, K+1, A, ...)``, slot ``j`` target
            ``j``); ``False``: each sensor reports a set of unlabelled detections per step (padded: ``meas (S, B, K+1,
            M, ...)``, ``visible`` the present slots), missed detections and clutter among them, and a method needs
            an associator (``associator=``) to tell which detection is which target's.
        match_distance: the distance (in ``units``) beyond which a track is not a target's, where the tracks are
            unlabelled: the cut-off ``c`` of GOSPA and OSPA, the identity metrics' match distance and a missed
            target's cost in the matched-track order (:mod:`dslearn.metrics.multitarget`); a fact of the world's
            scale (2 m for pedestrians).
    """

    name: str
    measurement: str
    num_agents: int
    state: str
    dt: float
    steps: int
    units: str = "m"
    networked: bool = True
    source: str = "simulated"
    pools: tuple[int, int] | None = None
    dynamics: str | None = None
    kind: str = TARGETS
    labelled: bool = True
    match_distance: float = 2.0

    @property
    def tracks_targets(self) -> bool:
        """The network's sensors see targets (``kind = "targets"``)."""
        return self.kind == TARGETS

    @property
    def navigates_itself(self) -> bool:
        """Every node navigates itself (``kind = "self"``): node ``s`` measures only its own platform ``s``."""
        return self.kind == SELF


@dataclass
class Estimates:
    """What a method returns for a batch of test episodes, reduced to what every method estimates: the
    targets' positions (and, where the method has one, their covariance), comparable across methods.

    Attributes:
        mean: ``(N, B, K+1, A, 2)`` position estimates of ``N`` reporting nodes (every node of a
            distributed filter; one for a method with a fusion centre).
        cov: ``(N, B, K+1, A, 2, 2)`` their covariances, or ``None`` (no NEES then).
        nodes: the ``N`` reporting nodes' names.
        sensing: ``(N,)`` bool, the node senses (tables average over sensing nodes, Yu et al.'s "sensor
            average"; a fusion centre counts as sensing).
    """

    mean: Tensor
    cov: Tensor | None
    nodes: list[str]
    sensing: Tensor


@runtime_checkable
class Scenario(Protocol):
    """A simulator or a data set, as the matrix uses it: it declares what it offers (``spec``), draws
    episodes (the truth kept apart from the measurements) and tells where the targets are in a true
    state. ``network`` is its own sensor network, or ``None`` where the run's ``network`` part places the
    sensors (Yu et al.'s scenario)."""

    spec: ScenarioSpec
    network: SensorNetwork | None
    area: tuple

    def ctx(self) -> StepContext: ...

    def sample(self, num: int, network: SensorNetwork, generator) -> Episodes:
        """``num`` episodes measured by ``network``; ``generator``: a ``torch.Generator`` or per-episode
        :class:`~dslearn.streams.Streams` (episode ``i`` then depends only on its own stream)."""

    def positions(self, states: Tensor) -> Tensor:
        """The targets' positions in true states: ``(B, K+1, Dx) -> (B, K+1, A, 2)``."""
