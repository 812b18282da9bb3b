r"""Unlabelled detections: Yu's crowd of walkers (:class:`ClutterScenario`) and Liu et al.'s manoeuvring target
over a 200-sensor field (:class:`ClutterManoeuvreScenario`) seen by range-limited sensors that report, per step, a
set of detections without target labels, some targets missed and clutter among them.

Each sensor detects each target inside its sensing range with probability :math:`P_D` (``p_detect``), the
detection its noisy position (as in :func:`~dslearn.sim.scenario.measure`), and adds a Poisson number of false
detections (rate ``clutter_rate`` per sensor and step) uniform over its sensing disc.

With ``births`` (off by default: every target exists throughout) each target exists over an interval of steps
drawn per episode (:func:`existence_intervals`): it enters at a step drawn uniformly in ``0 .. birth_until * K``
and leaves at one drawn uniformly in ``death_from * K .. K + 1`` (``K + 1``: it stays to the end). Outside its
interval a target is not detected and is not in the truth: its true state is ``NaN`` (what
:meth:`ClutterScenario.positions` reports and :func:`dslearn.metrics.multitarget.tracking_metrics` reads as an absent
target). The walkers are simulated throughout (an absent walker still moves, unseen, in the social force of the
others: a simulation shortcut). The spec declares it (``births=True``, :class:`DetectionSpec`), and a tracker
then manages its tracks (``associator.tracks``). The detections of a sensor
and step are one padded set in a random order (``meas (S, B, K+1, M, 2)``, ``visible`` the present slots,
``M = A + n_max`` with ``n_max`` the Poisson quantile of :data:`CLUTTER_TAIL`): nothing in a slot tells whose
detection it is. The spec says so (``labelled=False``): a method needs an associator (``associator=``).
"""

from __future__ import annotations

import math
import torch
from scipy.stats import poisson
from torch import Tensor

from dataclasses import dataclass

from dslearn.episodes import Episodes, ScenarioSpec
from dslearn.errors import ConfigError, _number, check_flag, check_integer, check_positive
from dslearn.network import SensorNetwork
from dslearn.sim.liu import ManoeuvreScenario
from dslearn.sim.scenario import SocialForceScenario
from dslearn.streams import Streams, rand, stream_seed

#: the clutter count of a sensor and step is drawn from the Poisson law truncated where its upper tail is below this
#: (the padded set's clutter slots; the truncation changes the mean count by less than ``1e-12``)
CLUTTER_TAIL = 1e-12


def clutter_density(clutter_rate: float, network: SensorNetwork) -> float:
    """The clutter's spatial density per unit area of a sensing disc: ``clutter_rate / (pi r^2)``."""
    return clutter_rate / (math.pi * network.sensing_range**2)


def check_detection(p_detect, clutter_rate) -> tuple[float, float]:
    """``p_detect`` in (0, 1] and ``clutter_rate`` >= 0 (finite), else :class:`ConfigError` naming the field."""
    p = _number("scenario.p_detect", p_detect)
    if not 0 < p <= 1:
        raise ConfigError(f"scenario.p_detect={p_detect!r} must be in (0, 1] (the probability that a sensor detects "
                          f"a target inside its range)")
    check_positive("scenario.clutter_rate", clutter_rate, strict=False)
    return p, float(clutter_rate)


def clutter_cap(rate: float, tail: float = CLUTTER_TAIL) -> int:
    """The largest clutter count drawn: the smallest ``n`` with :math:`P(N > n) <` ``tail`` (0 for rate 0)."""
    return 0 if rate == 0 else int(poisson.isf(tail, rate)) + 1


def poisson_counts(u: Tensor, rate: float, cap: int) -> Tensor:
    """Poisson(``rate``) counts from uniforms ``u`` by the inverse CDF, at most ``cap`` (int64, ``u``'s shape)."""
    if cap == 0:
        return torch.zeros(u.shape, dtype=torch.int64, device=u.device)
    k = torch.arange(cap + 1, dtype=torch.float64)
    cdf = torch.from_numpy(poisson.cdf(k.numpy(), rate)).to(u.device, torch.float64)
    return torch.searchsorted(cdf, u.to(torch.float64).contiguous(), right=True).clamp(max=cap)


def detections(pos_meas: Tensor, visible: Tensor, network: SensorNetwork, p_detect: float, clutter_rate: float,
               generator) -> tuple[Tensor, Tensor]:
    """Unlabelled detection sets from labelled noisy readings ``pos_meas (S, B, K+1, A, 2)`` of the targets a node
    sees (``visible (S, B, K+1, A)``): each kept with probability ``p_detect``, clutter added over each sensing
    node's disc, every set shuffled. Returns ``meas (S, B, K+1, M, 2)`` (zeros in absent slots) and ``present
    (S, B, K+1, M)``. Draws, per episode (``generator``: a Generator or per-episode Streams over ``(B,)``): the
    detection draws, the clutter counts, the clutter positions, the shuffle keys."""
    s, b, k1, a = visible.shape
    cap = clutter_cap(clutter_rate)
    m = a + cap
    dtype, dev = pos_meas.dtype, pos_meas.device

    def draw(*shape):  # (B, *shape) from the episode's stream -> (S, B, ...) where shape starts with S
        return rand((b, *shape), generator, dtype=torch.float64).to(dev).transpose(0, 1)

    hit = visible & (draw(s, k1, a) < p_detect)
    count = poisson_counts(draw(s, k1), clutter_rate, cap)  # (S, B, K+1)
    count[network.num_sensors:] = 0  # communication-only nodes sense nothing
    u = draw(s, k1, max(cap, 1), 2)[..., :cap, :]
    r = network.sensing_range * u[..., 0].sqrt()
    th = 2 * math.pi * u[..., 1]
    centre = network.positions.to(dev, torch.float64).view(s, 1, 1, 1, 2)
    clutter = centre + torch.stack([r * th.cos(), r * th.sin()], -1)  # (S, B, K+1, cap, 2)
    clutter_on = torch.arange(cap, device=dev) < count.unsqueeze(-1)
    vals = torch.cat([pos_meas.to(torch.float64) * hit.unsqueeze(-1), clutter * clutter_on.unsqueeze(-1)], -2)
    present = torch.cat([hit, clutter_on], -1)
    order = draw(s, k1, m).argsort(-1)  # a random order of the slots: no slot index tells a target
    vals = vals.gather(-2, order.unsqueeze(-1).expand(*order.shape, 2))
    present = present.gather(-1, order)
    return vals.to(dtype), present


@dataclass(frozen=True)
class DetectionSpec(ScenarioSpec):
    """A :class:`~dslearn.episodes.ScenarioSpec` of unlabelled detections that also declares whether targets enter
    and leave (``births``: each target exists over an interval of steps; a tracker must start and end tracks)."""

    births: bool = False


def check_births(births, birth_until, death_from) -> tuple[bool, float, float]:
    """``births`` a bool, ``birth_until`` in [0, 1), ``death_from`` in (``birth_until``, 1]; else
    :class:`ConfigError` naming the field."""
    check_flag("scenario.births", births)
    lo, hi = _number("scenario.birth_until", birth_until), _number("scenario.death_from", death_from)
    if not 0 <= lo < 1:
        raise ConfigError(f"scenario.birth_until={birth_until!r} must be in [0, 1) (a share of the horizon)")
    if not lo < hi <= 1:
        raise ConfigError(f"scenario.death_from={death_from!r} must be in (scenario.birth_until={lo}, 1] (a share of "
                          f"the horizon)")
    return births, lo, hi


def existence_intervals(u: Tensor, steps: int, birth_until: float, death_from: float) -> Tensor:
    """``alive (B, K+1, A)`` bool from uniforms ``u (B, A, 2)``: target ``a`` enters at step
    ``floor(u0 * (floor(birth_until K) + 1))`` and leaves at ``ceil(death_from K) + floor(u1 * (K + 2 -
    ceil(death_from K)))`` (``K + 1``: it stays), present at the steps in between (its first included)."""
    first_max = int(math.floor(birth_until * steps))
    last_min = min(int(math.ceil(death_from * steps)), steps + 1)
    birth = (u[..., 0] * (first_max + 1)).floor().clamp(max=first_max).long()  # (B, A)
    death = last_min + (u[..., 1] * (steps + 2 - last_min)).floor().clamp(max=steps + 1 - last_min).long()
    death = torch.maximum(death, birth + 1)
    k = torch.arange(steps + 1, device=u.device).view(1, -1, 1)
    return (k >= birth.unsqueeze(1)) & (k < death.unsqueeze(1))


class ClutterScenario(SocialForceScenario):
    r"""Yu's crowd (:class:`~dslearn.sim.scenario.SocialForceScenario`) seen as unlabelled detections
    (:func:`detections`): ``p_detect`` :math:`P_D \in (0, 1]`, ``clutter_rate`` (>= 0, false detections per sensor
    and step, uniform over its sensing disc). The sensors are the run's ``network`` part (as in Yu's scenario).

    Where the targets start is a declared fact of the world (:meth:`start_prior`): each in its start square (the
    uniform law's mean and variance), moving at its desired velocity (standard deviation ``start_velocity_std``);
    a method that associates starts its tracks there (no label is read).
    """

    def __init__(self, *args, p_detect: float = 0.9, clutter_rate: float = 1.0, start_velocity_std: float = 1.0,
                 name: str = "yu_crowd_clutter", births: bool = False, birth_until: float = 0.4,
                 death_from: float = 0.6, match_distance: float = 2.0, **kwargs):
        super().__init__(*args, **kwargs)
        self.p_detect, self.clutter_rate = check_detection(p_detect, clutter_rate)
        check_positive("scenario.match_distance", match_distance)
        self.match_distance = float(match_distance)
        self.births, self.birth_until, self.death_from = check_births(births, birth_until, death_from)
        check_positive("scenario.start_velocity_std", start_velocity_std)
        self.start_velocity_std = float(start_velocity_std)
        self.name = str(name)

    @property
    def spec(self) -> ScenarioSpec:
        """As Yu's scenario's, named ``name``, with unlabelled detections (``labelled=False``); with ``births`` a
        :class:`DetectionSpec` that declares them."""
        if self.births:
            return DetectionSpec(self.name, "position", self.num_agents, "pv2d", self.dt, self.steps,
                                 dynamics="social_force", labelled=False, match_distance=self.match_distance,
                                 births=True)
        return ScenarioSpec(self.name, "position", self.num_agents, "pv2d", self.dt, self.steps,
                            dynamics="social_force", labelled=False, match_distance=self.match_distance)

    def start_prior(self) -> tuple[Tensor, Tensor]:
        """Where the targets start, as declared: ``mean (A, 4)`` (start squares' centres, desired velocities) and
        ``cov (A, 4, 4)`` (a uniform square's variance ``size^2 / 12`` per axis, ``start_velocity_std^2``)."""
        pos = self.corners + self.start_size / 2
        mean = torch.cat([pos, self.sfm.desired.detach().to(torch.float64).clone()], -1)
        var = torch.tensor([max(self.start_size**2 / 12, 1e-6)] * 2 + [self.start_velocity_std**2] * 2,
                           dtype=torch.float64)
        return mean, torch.diag_embed(var.expand(self.num_agents, 4)).clone()

    def clutter_density(self, network: SensorNetwork) -> float:
        """The clutter's spatial density per unit area of a sensing disc (:func:`clutter_density`)."""
        return clutter_density(self.clutter_rate, network)

    def sample(self, num: int, network: SensorNetwork, generator: torch.Generator | Streams) -> Episodes:
        ep = super().sample(num, network, generator)
        if not self.births:
            meas, present = detections(ep.meas, ep.visible, network, self.p_detect, self.clutter_rate, generator)
            return Episodes(ep.states, meas, present)
        alive = self.existence(num, generator).to(ep.visible.device)  # (B, K+1, A)
        meas, present = detections(ep.meas, ep.visible & alive.unsqueeze(0), network, self.p_detect,
                                   self.clutter_rate, generator)
        gone = (~alive).repeat_interleave(4, dim=-1)  # (B, K+1, 4A)
        states = ep.states.masked_fill(gone.to(ep.states.device), math.nan)
        return Episodes(states, meas, present)

    def existence(self, num: int, generator) -> Tensor:
        """Each target's existence over the steps, ``alive (B, K+1, A)`` (:func:`existence_intervals`), drawn after
        the walk and its readings (from each episode's stream, after the detections' draws)."""
        u = rand((num, self.num_agents, 2), generator, dtype=torch.float64)
        return existence_intervals(u, self.steps, self.birth_until, self.death_from)



#: the key of the random stream from which :meth:`ClutterManoeuvreScenario.start_prior` draws (with the run seed)
START_STREAM = "liu_declared_start"


class ClutterManoeuvreScenario(ManoeuvreScenario):
    r"""Liu et al.'s field (:class:`~dslearn.sim.liu.ManoeuvreScenario`: one manoeuvring target, the field's own
    sensors) seen as unlabelled detections (:func:`detections`): ``p_detect`` :math:`P_D \in (0, 1]`,
    ``clutter_rate`` (>= 0, false detections per sensor and step, uniform over its sensing disc).

    Where the target starts is a fact of the world a tracker may know (:meth:`start_prior`): the law of the
    generator's first state, estimated from ``start_draws`` trajectories of a stream of its own (not the episodes'),
    widened by the sensors' noise on the position and ``start_velocity_std`` on the velocity. ``match_distance``
    (m) is the GOSPA/OSPA cut-off and the identity match distance (default: one sensing range).
    """

    def __init__(self, trajectory, name: str = "liu_s1_clutter", steps: int = 60, dt: float = 1.0,
                 num_sensors: int = 200, sensing_range: float = 50.0, area_size: float = 1000.0, meas_std: float = 2.0,
                 comm_radius: float = 200.0, seed: int = 0, p_detect: float = 0.9, clutter_rate: float = 1.0,
                 start_velocity_std: float = 1.0, start_draws: int = 256, match_distance: float = 50.0):
        super().__init__(trajectory, name=name, steps=steps, dt=dt, num_sensors=num_sensors,
                         sensing_range=sensing_range, area_size=area_size, meas_std=meas_std, comm_radius=comm_radius,
                         seed=seed)
        self.p_detect, self.clutter_rate = check_detection(p_detect, clutter_rate)
        check_positive("scenario.start_velocity_std", start_velocity_std)
        check_integer("scenario.start_draws", start_draws, 2)
        check_positive("scenario.match_distance", match_distance)
        self.start_velocity_std, self.start_draws = float(start_velocity_std), int(start_draws)
        self.match_distance = float(match_distance)

    @property
    def spec(self) -> ScenarioSpec:
        """As Liu's scenario's, with unlabelled detections (``labelled=False``)."""
        return ScenarioSpec(self.name, "position", 1, "pv2d", self.dt, self.steps, labelled=False,
                            match_distance=self.match_distance)

    def start_prior(self) -> tuple[Tensor, Tensor]:
        """``mean (1, 4)`` and ``cov (1, 4, 4)`` of the target's first state ``[p, v]`` (the class text)."""
        gen = torch.Generator().manual_seed(stream_seed(self.seed, START_STREAM))
        pos, vel = self.trajectory(self.start_draws, self.steps + 1, gen, dt=self.dt)  # centred as the episodes
        x0 = torch.cat([pos[:, 0], vel[:, 0]], -1).to(torch.float64)  # (R, 4)
        sig = float(self.network.meas_std)
        widen = torch.tensor([sig**2, sig**2, self.start_velocity_std**2, self.start_velocity_std**2],
                             dtype=torch.float64)
        cov = torch.cov(x0.T) + torch.diag(widen)
        return x0.mean(0, keepdim=True), (0.5 * (cov + cov.T)).unsqueeze(0)

    def clutter_density(self, network: SensorNetwork) -> float:
        """The clutter's spatial density per unit area of a sensing disc (:func:`clutter_density`)."""
        return clutter_density(self.clutter_rate, network)

    def sample(self, num: int, network: SensorNetwork, generator: torch.Generator | Streams) -> Episodes:
        """Liu's episodes (:meth:`ManoeuvreScenario.sample`: the trajectory, then the readings), then the
        detection draws of :func:`detections` from the same generator or streams."""
        ep = super().sample(num, network, generator)
        meas, present = detections(ep.meas, ep.visible, network, self.p_detect, self.clutter_rate, generator)
        return Episodes(ep.states, meas, present)
