r"""Jiang et al.'s setting (ISITA 2022, Sec. IV, Eqs. 20-22) as a scenario of the matrix: a 2-D source
parameter ``x_k`` (one "target" whose position is the parameter) drifting as a noisy polynomial of the
timing ``k``, measured by ``N`` fixed sensors, each taking ``L`` samples of the squared range
:math:`h_n(x) = (A_n - x_1)^2 + (B_n - x_2)^2` plus i.i.d. :math:`\mathcal N(0, \sigma_y^2)` noise per
timing.

Episodes: the ``K = num_timings`` timings ``k = 1..K`` are the episode's ``K`` states (index ``i`` holds
timing ``k = i + 1``; ``spec.steps = K - 1``), the state is the parameter itself (``state = "param2d"``,
``Dx = 2``). The measurements of sensor ``n`` are ``meas[n, b, i, 0, :]``, its ``L`` raw samples at timing
``i + 1`` (``Dz = L``), all visible. The sensors report to a fusion centre (the factor graph): the
scenario's :class:`~dslearn.network.SensorNetwork` holds the sensors' positions and ``meas_std =
sigma_y``; it has no peer-to-peer graph of its own (``networked = False``; the adjacency is complete: every
sensor reaches the centre).

Random draws: episode ``b`` draws from its own generator first its drive noise ``omega (K, 2)`` and then its
sensor noise ``(K, N, L)``, standard normal in float64, in the order of
:func:`~dslearn.sim.squared_range.run_noise`; a generator seeded with ``run_seed(seed, r)`` therefore gives
Monte Carlo run ``r`` of the ``jiang_fg`` study (same truth, same samples).
"""

from __future__ import annotations

import torch
from torch import Tensor

from dslearn.episodes import Episodes, ScenarioSpec
from dslearn.errors import ConfigError, check_integer, check_positive
from dslearn.network import SensorNetwork
from dslearn.sim.squared_range import SquaredRange, polynomial_trajectory
from dslearn.streams import Streams
from dslearn.types import StepContext

#: the sensors measure at any distance: the network's sensing range is nominal (a finite "unlimited")
UNLIMITED_RANGE = 1.0e9


def _matrix(key: str, value, cols: int | None = None) -> Tensor:
    try:
        t = torch.as_tensor(value, dtype=torch.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"scenario.{key}={value!r} must be a list of lists of numbers") from None
    if t.ndim != 2 or t.shape[0] < 1 or (cols is not None and t.shape[1] != cols):
        want = f"(rows, {cols})" if cols is not None else "a non-empty matrix"
        raise ConfigError(f"scenario.{key} must have shape {want}; got {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise ConfigError(f"scenario.{key}={value!r} must be finite")
    return t


class SquaredRangeScenario:
    """Jiang et al.'s source tracking: one 2-D parameter, ``N`` squared-range sensors.

    Args:
        name: the label in the tables.
        sensors: ``(N, 2)`` sensor positions ``(A_n, B_n)``.
        coefficients: ``(2, 3)`` rows ``(a, b, c)`` of ``x_m,k = a k^2 + b k + c + omega`` (Eq. 20).
        drive_var: :math:`\\sigma_\\omega^2` (Eq. 21).
        num_timings: ``K`` timings ``k = 1..K``.
        num_samples: ``L`` samples per sensor per timing.
        sigma_y: the sensor noise standard deviation (of one squared-range sample).
    """

    #: the scenario places its own sensors (the run's ``network`` part is not used)
    owns_network = True
    num_agents = 1
    state_dim = 2

    def __init__(self, name: str = "jiang", sensors=((-30.0, 50.0), (10.0, 5.0), (60.0, 20.0)),
                 coefficients=((0.05, 0.03, 6.0), (-0.02, 0.07, 0.0)), drive_var: float = 0.5,
                 num_timings: int = 50, num_samples: int = 60, sigma_y: float = 5.0):
        self.sensors = _matrix("sensors", sensors, 2)
        self.coefficients = _matrix("coefficients", coefficients, 3)
        if self.coefficients.shape[0] != 2:
            raise ConfigError(f"scenario.coefficients has {self.coefficients.shape[0]} rows; the matrix compares "
                              "2-D positions, so the source has 2 parameters (2 rows (a, b, c))")
        check_integer("scenario.num_timings", num_timings, 2)
        check_integer("scenario.num_samples", num_samples, 1)
        check_positive("scenario.drive_var", drive_var, strict=False)
        check_positive("scenario.sigma_y", sigma_y)
        self.name = str(name)
        self.drive_var = float(drive_var)
        self.num_timings = num_timings
        self.num_samples = num_samples
        self.sigma_y = float(sigma_y)
        self.h = SquaredRange(self.sensors)
        n = self.sensors.shape[0]
        adj = ~torch.eye(n, dtype=torch.bool)
        self.network = SensorNetwork(self.sensors.clone(), n, adj, UNLIMITED_RANGE, self.sigma_y,
                                     names=[f"sensor{i + 1}" for i in range(n)])
        # the area: the sensors and the noise-free trajectory, 10 % margin
        mean = polynomial_trajectory(self.coefficients, num_timings, 0.0, noise=torch.zeros(num_timings, 2,
                                                                                          dtype=torch.float64))
        pts = torch.cat([self.sensors, mean])
        lo, hi = pts.min(0).values, pts.max(0).values
        pad = 0.1 * (hi - lo).clamp_min(1.0)
        self.area = (float(lo[0] - pad[0]), float(hi[0] + pad[0]), float(lo[1] - pad[1]), float(hi[1] + pad[1]))

    @property
    def spec(self) -> ScenarioSpec:
        """One 2-D parameter measured by squared-range sensors at unit timings; a fusion centre, no graph."""
        return ScenarioSpec(self.name, "squared_range", 1, "param2d", 1.0, self.num_timings - 1, networked=False)

    def ctx(self) -> StepContext:
        return StepContext(dt=1.0)

    def positions(self, states: Tensor) -> Tensor:
        """``(B, K, 2) -> (B, K, 1, 2)``: the parameter is the position."""
        return states.unsqueeze(-2)

    def draw(self, gens) -> tuple[Tensor, Tensor]:
        """Standard-normal drive ``(B, K, 2)`` and sensor noise ``(B, K, N, L)`` (float64, CPU), episode ``b``
        from ``gens[b]`` (drive first, then the sensors, as :func:`~dslearn.sim.squared_range.run_noise`)."""
        k, n, lsm = self.num_timings, self.sensors.shape[0], self.num_samples
        drive, sensor = [], []
        for g in gens:
            drive.append(torch.randn(k, 2, generator=g, dtype=torch.float64))
            sensor.append(torch.randn(k, n, lsm, generator=g, dtype=torch.float64))
        if not drive:
            return torch.zeros(0, k, 2, dtype=torch.float64), torch.zeros(0, k, n, lsm, dtype=torch.float64)
        return torch.stack(drive), torch.stack(sensor)

    def episodes(self, drive: Tensor, noise: Tensor) -> Episodes:
        """The episodes of given standard-normal draws: truth (Eqs. 20-21) and every sensor's ``L`` samples
        (Eq. 22 plus ``sigma_y`` times the noise), as the study computes them."""
        truth = polynomial_trajectory(self.coefficients.to(drive), self.num_timings, self.drive_var, noise=drive)
        samples = self.h(truth).unsqueeze(-1) + self.sigma_y * noise  # (B, K, N, L)
        meas = samples.permute(2, 0, 1, 3).unsqueeze(-2)  # (N, B, K, 1, L)
        visible = torch.ones(meas.shape[:-1], dtype=torch.bool)
        return Episodes(truth, meas.contiguous(), visible)

    def sample(self, num: int, network: SensorNetwork, generator: torch.Generator | Streams) -> Episodes:
        """``num`` episodes; ``generator``: per-episode :class:`~dslearn.streams.Streams` (episode ``i`` depends
        only on its own stream) or one ``torch.Generator`` drawn from episode after episode."""
        if network is not self.network and network.num_sensors != self.sensors.shape[0]:
            raise ConfigError(f"scenario {self.name} is measured by its own {self.sensors.shape[0]} sensors")
        if isinstance(generator, Streams):
            if generator.shape != (num,):
                raise ValueError(f"SquaredRangeScenario.sample: streams over {generator.shape} for {num} episodes")
            gens = generator.gens
        else:
            gens = [generator] * num
        return self.episodes(*self.draw(gens))
