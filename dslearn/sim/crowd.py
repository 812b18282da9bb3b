r"""A recorded scene with every pedestrian in it, seen as unlabelled detections: the ETH/UCY crowds as the crowds
they are, not cut into pairs.

The recording is cut into windows of ``episodes.steps`` steps of ``episodes.dt`` seconds holding every pedestrian
whose track covers at least two of the window's times (:func:`dslearn.data.episodes.extract_crowd_windows`): each
enters and leaves where its track does (``NaN`` true state outside, an absent target for the metrics); a window with
more than ``episodes.max_agents`` pedestrians is dropped (the cap that keeps a cell within the matrix's budget: the
tracks each node manages grow with the crowd). The windows are split into a training and a test pool as
:class:`~dslearn.sim.recorded.RecordedScenario`'s pairs are (``time``: the last ``test_fraction`` of each file's
time range is the test pool).

The LiDAR-like sensors around the scene (:func:`dslearn.sim.real.arena_network`) measure the present pedestrians in
their range (:func:`dslearn.sim.scenario.measure`) and report, per step, a set of detections without labels
(:func:`dslearn.sim.clutter.detections`): each pedestrian detected with probability ``p_detect``, plus a Poisson
number of false detections (``clutter_rate`` per sensor and step) uniform over the sensing disc. The spec declares
the targets' entering and leaving (:class:`~dslearn.sim.clutter.DetectionSpec`, ``births=True``): a method manages
its tracks (``associator.tracks``), starting them from detections with velocity std ``start_velocity_std``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import torch
from torch import Tensor

from dslearn.data.episodes import EpisodeSet, extract_crowd_windows
from dslearn.episodes import Episodes, ScenarioSpec
from dslearn.errors import check_integer, check_positive
from dslearn.network import SensorNetwork
from dslearn.sim.clutter import DetectionSpec, check_detection, clutter_density, detections
from dslearn.sim.recorded import RecordedScenario, _settings, check_window
from dslearn.sim.scenario import measure
from dslearn.streams import Streams


@dataclasses.dataclass(frozen=True)
class CrowdCut:
    """How the recording is cut into crowd windows (``scenario.episodes``)."""

    max_agents: int = 12
    steps: int = 15
    dt: float = 0.4
    stride: int = 8
    split: str = "time"
    test_fraction: float = 0.2


def check_crowd_cut(c: CrowdCut, prefix: str = "scenario.episodes") -> None:
    check_integer(f"{prefix}.max_agents", c.max_agents, 1)
    check_window(c, prefix)


class RecordedCrowdScenario(RecordedScenario):
    r"""Every pedestrian of a recorded scene, measured as unlabelled detections (the module's text).

    Args:
        dataset, name, data_root, convention, network, seed: as :class:`~dslearn.sim.recorded.RecordedScenario`.
        episodes: how the recording is cut into windows (:class:`CrowdCut`'s fields).
        p_detect: :math:`P_D \in (0, 1]`, per sensor, step and pedestrian in range.
        clutter_rate: false detections per sensor and step (>= 0), uniform over its sensing disc.
        start_velocity_std: a new track's velocity standard deviation (m/s; single-point initiation).
        match_distance: m (> 0), beyond which a track is not a pedestrian's (GOSPA's cut-off, ``ScenarioSpec``).
    """

    def __init__(self, dataset: Mapping, name: str = "crowd", data_root: str | None = None,
                 convention: str = "physical", episodes: Mapping | None = None, network: Mapping | None = None,
                 seed: int = 0, p_detect: float = 0.9, clutter_rate: float = 0.5, start_velocity_std: float = 1.0,
                 match_distance: float = 2.0):
        self.p_detect, self.clutter_rate = check_detection(p_detect, clutter_rate)
        check_positive("scenario.match_distance", match_distance)
        self.match_distance = float(match_distance)
        check_positive("scenario.start_velocity_std", start_velocity_std)
        self.start_velocity_std = float(start_velocity_std)
        super().__init__(dataset, name, data_root, convention, episodes, network, seed)

    @staticmethod
    def _cut(episodes: Mapping | None) -> CrowdCut:
        cut = _settings(CrowdCut, episodes, "scenario.episodes")
        check_crowd_cut(cut)
        return cut

    def _extract(self) -> EpisodeSet:
        c = self.cut
        return extract_crowd_windows(self.scene, c.max_agents, c.steps, c.dt, c.stride)

    @property
    def _what(self) -> str:
        return f"at most {self.cut.max_agents} pedestrians"

    _lower = "raise scenario.episodes.max_agents, lower scenario.episodes.stride/steps"

    @property
    def num_agents(self) -> int:
        return int(self.cut.max_agents)

    @property
    def spec(self) -> ScenarioSpec:
        """At most ``max_agents`` recorded pedestrians entering and leaving, unlabelled detections of them."""
        return DetectionSpec(self.name, "position", self.num_agents, "pv2d", self.dt, self.steps, source="recorded",
                             pools=(self.pool_size("train"), self.pool_size("test")), labelled=False,
                             match_distance=self.match_distance, births=True)

    def clutter_density(self, network: SensorNetwork) -> float:
        """The clutter's spatial density per unit area of a sensing disc (:func:`~dslearn.sim.clutter.clutter_density`)."""
        return clutter_density(self.clutter_rate, network)

    def sample(self, num: int, network: SensorNetwork, generator: torch.Generator | Streams,
               split: str | None = None) -> Episodes:
        """The first ``num`` windows of pool ``split``: their true states (``NaN`` where a pedestrian is absent) and
        each sensor's unlabelled detection sets (``meas (S, B, K+1, M, 2)``, ``visible`` the present slots)."""
        states = self.pool_states(split, num)
        alive = self.alive(states)  # (B, K+1, A)
        ep = measure(states.nan_to_num(0.0), network, generator)
        meas, present = detections(ep.meas, ep.visible & alive.unsqueeze(0).to(ep.visible.device), network,
                                   self.p_detect, self.clutter_rate, generator)
        return Episodes(states, meas, present)

    @staticmethod
    def alive(states: Tensor) -> Tensor:
        """``(B, K+1, 4A) -> (B, K+1, A)``: where each pedestrian is present (its true position is a number)."""
        return torch.isfinite(states.unflatten(-1, (-1, 4))[..., 0])
