r"""Observation models: a sensor measures each target in range separately.

Besides the linear position sensor (Yu et al.) and the learned GP, the nonlinear sensors of the other papers'
scenarios, each with its analytic Jacobian (:meth:`~dslearn.models.base.ObservationModel.jacobian`) and its noise:
the squared range to the node's own fixed position (Jiang et al.: ``L`` samples per step, averaged), the range, the
bearing, and the terrain altitude under a platform read from a map by bilinear interpolation (Braga et al.). The
world facts they need (the nodes' positions, the samples per step, the map, the sensors' noise) come from the
scenario and its network (``for_scenario``); :func:`scenario_sensor` (``observation=sensor``) picks the model
of the measurement kind the scenario declares.

The per-node sensors take states with the node dimension first, ``(S, *B, d)``: node ``i`` measures from its own
position. A target's state is a block ``(d,)`` whose first two entries are its position (``[px, py, ...]``).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from dslearn.errors import ConfigError, check_choice, check_integer, check_positive
from dslearn.types import AGENT_DIM
from dslearn.models.base import ObservationModel
from dslearn.models.gp_backends import GPBackend, OnlineGP


def _misfit(spec, measurement: str, option: str, readings: str = "") -> str | None:
    """Why ``observation=<option>``, a model of ``measurement`` readings, cannot explain scenario ``spec``'s (``None``
    where it measures ``measurement``)."""
    if spec.measurement == measurement:
        return None
    return (f"observation={option} explains {readings or measurement + ' readings'}; scenario {spec.name} measures "
            f"{spec.measurement} (observation=sensor picks the scenario's own sensor model)")


class LinearPositionObservation(ObservationModel):
    r"""Eq. (5): :math:`z_{ij} = x_j + \nu`, :math:`\nu \sim \mathcal N(0, \sigma_\nu^2 I_2)`.

    Args:
        noise_std: :math:`\sigma_\nu` (> 0).
    """

    linear = True

    @staticmethod
    def spec_misfit(spec) -> str | None:
        """It explains position readings only (declared: :func:`dslearn.methods.base.declared_misfit`)."""
        return _misfit(spec, "position", "linear", "readings of the targets' positions")

    def __init__(self, noise_std: float = 0.2):
        super().__init__()
        check_positive("observation.noise_std", noise_std)
        self.noise_std = float(noise_std)

    def matrix(self, dtype=torch.float64, device=None) -> Tensor:
        return torch.eye(2, AGENT_DIM, dtype=dtype, device=device)

    def forward(self, y: Tensor) -> Tensor:
        return y[..., :2]

    def jacobian(self, y: Tensor) -> Tensor:
        h = self.matrix(y.dtype, y.device)
        return h.expand(*y.shape[:-1], *h.shape)

    def noise_cov(self, y: Tensor) -> Tensor:
        r = self.noise_std**2 * torch.eye(2, dtype=y.dtype, device=y.device)
        return r.expand(*y.shape[:-1], 2, 2)


class GPObservation(ObservationModel):
    r"""Learned observation model :math:`h` (data set :math:`D_{h,i}` of Algorithm 1).

    One GP per node maps a target state (4) to its measurement (2), learned from the node's
    own (ŷ_j^t, z_ij^t) pairs. ``R`` is the GP covariance :math:`\Sigma_h` (``latent``, as
    printed) or with :math:`\sigma_\epsilon^2` added (``predictive``, default: with latent
    variance alone the filter would treat learned measurements as nearly noise-free once the
    data set is large).

    Inputs have the node dimension first: ``(S, *B, 4)``.
    """

    learnable = True
    config_learns_online = True  #: it learns online (:func:`dslearn.schemas.base.online_learning`)

    def __init__(
        self,
        num_nodes: int,
        outputscale: float = 1.0,
        lengthscale: float = 2.0,
        noise_std: float = 0.2,
        mean: str = "identity",
        noise: str = "predictive",
        dtype: torch.dtype = torch.float64,
        device: str | torch.device = "cpu",
    ):
        super().__init__()
        check_choice("observation.noise", noise, ("latent", "predictive"))
        self.noise_mode = noise
        # used through the GPBackend protocol: num_nodes, predict, noise_var, append
        self.gp: GPBackend = OnlineGP(num_nodes, AGENT_DIM, 2, outputscale, lengthscale, noise_std, mean, dtype=dtype, device=device)

    def linearize(self, y: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        s = self.gp.num_nodes
        flat = y.reshape(s, -1, AGENT_DIM)
        mean, var, jac = self.gp.predict(flat)
        if self.noise_mode == "predictive":
            var = var + self.gp.noise_var.unsqueeze(-1)
        r = var.reshape(*y.shape[:-1], 1, 1) * torch.eye(2, dtype=y.dtype, device=y.device)
        return mean.reshape(*y.shape[:-1], 2), jac.reshape(*y.shape[:-1], 2, AGENT_DIM), r

    def forward(self, y: Tensor) -> Tensor:
        return self.linearize(y)[0]

    def jacobian(self, y: Tensor) -> Tensor:
        return self.linearize(y)[1]

    def noise_cov(self, y: Tensor) -> Tensor:
        return self.linearize(y)[2]

    def add_data(self, inputs: Tensor, outputs: Tensor, valid: Tensor) -> None:
        for a in range(inputs.shape[1]):
            self.gp.append(inputs[:, a], outputs[:, a], valid[:, a])


# ------------------------------------------------------------------------------------------------
# nonlinear sensors


def _positions(key: str, value) -> Tensor:
    """``(S, 2)`` finite float64 node positions, or a ConfigError naming ``key``."""
    t = torch.as_tensor(value, dtype=torch.float64)
    if t.ndim != 2 or t.shape[-1] != 2 or t.shape[0] < 1:
        raise ConfigError(f"{key} must have shape (S, 2); got {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise ConfigError(f"{key} must be finite")
    return t


def _samples(value) -> int:
    return check_integer("observation.samples", value, 1, note=" (the scenario's samples per step)")


def _need_scenario(scenario, option: str) -> None:
    if scenario is None:
        raise ConfigError(f"observation={option} is sized by the scenario (its sensors, samples, map): a method of "
                          f"task=matrix takes it; this task builds its observation model without the scenario")


def _place(jac_pos: Tensor, d: int) -> Tensor:
    """``(*B, Dz, 2)`` derivatives with respect to the position -> ``(*B, Dz, d)`` (zero for the other entries)."""
    if d < 2:
        raise ConfigError(f"a target's state block has {d} entries; a sensor of its position needs >= 2")
    return torch.nn.functional.pad(jac_pos, (0, d - 2))


class _NodeSensor(ObservationModel):
    """A scalar sensor at every node's fixed position ``(S, 2)``, reading ``samples`` i.i.d. samples per step with
    noise ``noise_std`` each; :meth:`reading` averages them, so ``R = noise_std^2 / samples`` (exactly the
    information of the samples stacked: ``L`` identical rows ``H`` with ``R = noise_std^2`` each give
    ``L H^T H / noise_std^2`` and ``H^T sum_l z_l / noise_std^2``)."""

    meas_dim = 1
    measures_position = False
    #: the scenario's measurement kind this model explains (:attr:`~dslearn.episodes.ScenarioSpec.measurement`)
    measurement = ""
    option = ""

    @classmethod
    def spec_misfit(cls, spec) -> str | None:
        return _misfit(spec, cls.measurement, cls.option)

    def __init__(self, sensors, noise_std: float, samples: int = 1):
        super().__init__()
        check_positive("observation.noise_std", noise_std)
        self.noise_std = float(noise_std)
        self.samples = _samples(samples)
        self.register_buffer("sensors", _positions("the sensors' positions (network.positions)", sensors))

    @classmethod
    def for_scenario(cls, noise_std: float | None = None, *, scenario=None, network, device=None):
        """The config factory: the nodes of the cell's ``network`` are the sensors; the samples per step are the
        scenario's (``num_samples``, one where it declares none)."""
        _need_scenario(scenario, cls.option)
        if noise_std is None:
            noise_std = float(network.meas_std)
        samples = getattr(scenario, "num_samples", 1)
        return cls(network.positions, noise_std, samples).to(device)

    def reading(self, meas: Tensor) -> Tensor:
        if meas.shape[-1] < self.samples:
            raise ValueError(f"{type(self).__name__}: {meas.shape[-1]} measurement channels, {self.samples} samples "
                             f"expected (scenario's num_samples)")
        return meas[..., : self.samples].mean(-1, keepdim=True)

    def _offset(self, y: Tensor) -> Tensor:
        """``p - s_i``: ``(S, *B, 2)`` for states ``(S, *B, d)`` (node ``i`` first)."""
        s = self.sensors.to(y)
        if y.shape[0] != s.shape[0]:
            raise ValueError(f"{type(self).__name__}: states of {y.shape[0]} nodes, {s.shape[0]} sensors")
        return y[..., :2] - s.view(s.shape[0], *([1] * (y.ndim - 2)), 2)

    def noise_cov(self, y: Tensor) -> Tensor:
        r = torch.full((1, 1), self.noise_std**2 / self.samples, dtype=y.dtype, device=y.device)
        return r.expand(*y.shape[:-1], 1, 1)


class SquaredRangeObservation(_NodeSensor):
    r"""Squared range from node ``i`` (Jiang et al. Eq. 22): :math:`h_i(y) = \|p - s_i\|^2`,
    :math:`\partial h_i/\partial p = 2 (p - s_i)^T`."""

    measurement = "squared_range"
    option = "squared_range"

    def forward(self, y: Tensor) -> Tensor:
        return self._offset(y).square().sum(-1, keepdim=True)

    def jacobian(self, y: Tensor) -> Tensor:
        return _place(2.0 * self._offset(y).unsqueeze(-2), y.shape[-1])


class RangeObservation(_NodeSensor):
    r"""Range from node ``i``: :math:`h_i(y) = \|p - s_i\|`, :math:`\partial h_i/\partial p = (p - s_i)^T / h_i`
    (undefined at the sensor itself)."""

    measurement = "range"
    option = "range"

    def forward(self, y: Tensor) -> Tensor:
        return self._offset(y).norm(dim=-1, keepdim=True)

    def jacobian(self, y: Tensor) -> Tensor:
        d = self._offset(y)
        return _place((d / d.norm(dim=-1, keepdim=True)).unsqueeze(-2), y.shape[-1])


class BearingObservation(_NodeSensor):
    r"""Bearing from node ``i`` [rad]: :math:`h_i(y) = \operatorname{atan2}(p_y - s_{i,y}, p_x - s_{i,x})`,
    :math:`\partial h_i/\partial p = (-\Delta_y, \Delta_x) / \|\Delta\|^2`; the innovation is wrapped to
    :math:`(-\pi, \pi]` (:meth:`residual`). One sample per step (an average of angles is not their mean)."""

    measurement = "bearing"
    option = "bearing"

    def __init__(self, sensors, noise_std: float, samples: int = 1):
        if samples != 1:
            raise ConfigError(f"observation=bearing reads one sample per step; the scenario gives {samples}")
        super().__init__(sensors, noise_std, samples)

    def forward(self, y: Tensor) -> Tensor:
        d = self._offset(y)
        return torch.atan2(d[..., 1], d[..., 0]).unsqueeze(-1)

    def jacobian(self, y: Tensor) -> Tensor:
        d = self._offset(y)
        g = torch.stack([-d[..., 1], d[..., 0]], -1) / d.square().sum(-1, keepdim=True)
        return _place(g.unsqueeze(-2), y.shape[-1])

    def residual(self, z: Tensor, h: Tensor) -> Tensor:
        return torch.remainder(z - h + math.pi, 2 * math.pi) - math.pi


def bilinear(z: Tensor, resolution: float, p: Tensor) -> tuple[Tensor, Tensor]:
    r"""Value and gradient of the bilinear interpolation of the grid ``z (H, W)`` (``z[i, j]`` at
    ``(X, Y) = (j, i) * resolution``) at points ``p (..., >=2)``: ``(h (...), grad (..., 2))``. The value is the
    simulator's (:class:`dslearn.sim.terrain.TerrainMap`: points outside the map clamped to its border); the
    gradient is that of the cell's bilinear patch, zero along an axis where the point lies beyond the border."""
    hgt, wid = z.shape
    ux, uy = p[..., 0] / resolution, p[..., 1] / resolution
    gx = ux.clamp(0.0, wid - 1 - 1e-9)
    gy = uy.clamp(0.0, hgt - 1 - 1e-9)
    j0, i0 = gx.floor(), gy.floor()
    fx, fy = gx - j0, gy - i0
    j0, i0 = j0.long(), i0.long()
    flat = z.reshape(-1)
    base = i0 * wid + j0
    z00, z01, z10, z11 = flat[base], flat[base + 1], flat[base + wid], flat[base + wid + 1]
    h = z00 * (1 - fx) * (1 - fy) + z01 * fx * (1 - fy) + z10 * (1 - fx) * fy + z11 * fx * fy
    dx = ((z01 - z00) * (1 - fy) + (z11 - z10) * fy) / resolution
    dy = ((z10 - z00) * (1 - fx) + (z11 - z01) * fx) / resolution
    dx = torch.where((ux < 0) | (ux > wid - 1), torch.zeros_like(dx), dx)
    dy = torch.where((uy < 0) | (uy > hgt - 1), torch.zeros_like(dy), dy)
    return h, torch.stack([dx, dy], -1)


class TerrainAltitudeObservation(ObservationModel):
    r"""The terrain altitude under a platform (Braga et al. Eq. 25 without the altimeter's modes):
    :math:`h(y) = \mathrm{map}(p)`, the map's bilinear interpolation, its gradient the Jacobian
    (:func:`bilinear`); ``R = noise_std^2``. Reads the first measurement channel (the altimeter; Braga's second
    channel holds the mode at ``t = 0``, which this Gaussian model does not use).

    Args:
        elevation: ``(H, W)`` grid [m]; resolution: its spacing [m]; noise_std: the altimeter's standard deviation.
    """

    meas_dim = 1
    measures_position = False

    @staticmethod
    def spec_misfit(spec) -> str | None:
        return _misfit(spec, "terrain_altitude", "terrain")

    def __init__(self, elevation, resolution: float, noise_std: float):
        super().__init__()
        check_positive("observation.noise_std", noise_std)
        check_positive("the map's resolution (scenario.terrain.resolution_m)", resolution)
        z = torch.as_tensor(elevation, dtype=torch.float64)
        if z.ndim != 2 or min(z.shape) < 2:
            raise ConfigError(f"the terrain map must be a (H, W) grid with H, W >= 2; got {tuple(z.shape)}")
        self.noise_std = float(noise_std)
        self.resolution = float(resolution)
        self.register_buffer("elevation", z)

    @classmethod
    def for_scenario(cls, noise_std: float | None = None, *, scenario=None, network, device=None):
        """The config factory: the scenario's map (``scenario.terrain``) and its altimeter's noise."""
        _need_scenario(scenario, "terrain")
        terrain = getattr(scenario, "terrain", None)
        if terrain is None:
            raise ConfigError(f"observation=terrain needs the scenario's terrain map; scenario "
                              f"{scenario.spec.name} has none")
        if noise_std is None:
            noise_std = float(network.meas_std)
        return cls(terrain.z, terrain.resolution, noise_std).to(device)

    def reading(self, meas: Tensor) -> Tensor:
        return meas[..., :1]

    def linearize(self, y: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        h, g = bilinear(self.elevation.to(y), self.resolution, y)
        return h.unsqueeze(-1), _place(g.unsqueeze(-2), y.shape[-1]), self.noise_cov(y)

    def forward(self, y: Tensor) -> Tensor:
        return bilinear(self.elevation.to(y), self.resolution, y)[0].unsqueeze(-1)

    def jacobian(self, y: Tensor) -> Tensor:
        return _place(bilinear(self.elevation.to(y), self.resolution, y)[1].unsqueeze(-2), y.shape[-1])

    def noise_cov(self, y: Tensor) -> Tensor:
        r = torch.full((1, 1), self.noise_std**2, dtype=y.dtype, device=y.device)
        return r.expand(*y.shape[:-1], 1, 1)


#: the observation model of each measurement kind a scenario declares (``observation=sensor``)
SENSOR_MODELS = {"squared_range": SquaredRangeObservation, "range": RangeObservation,
                 "bearing": BearingObservation, "terrain_altitude": TerrainAltitudeObservation}


def _sensor_misfit(spec) -> str | None:
    if spec.measurement == "position" or spec.measurement in SENSOR_MODELS:
        return None
    return (f"observation=sensor has no model of {spec.measurement} readings (scenario {spec.name}); it knows "
            f"position, {', '.join(SENSOR_MODELS)}")


def scenario_sensor(noise_std: float | None = None, *, scenario=None, network, device=None) -> ObservationModel:
    """``observation=sensor``: the model of the measurement kind the scenario declares
    (:attr:`~dslearn.episodes.ScenarioSpec.measurement`: the linear position sensor for ``position``, else
    :data:`SENSOR_MODELS`), with the world facts from the scenario and its network; ``noise_std`` null: the
    sensors' own noise."""
    _need_scenario(scenario, "sensor")
    spec = scenario.spec
    why = _sensor_misfit(spec)
    if why is not None:
        raise ConfigError(why)
    if noise_std is None:
        noise_std = float(network.meas_std)
    if spec.measurement == "position":
        return LinearPositionObservation(noise_std).to(device)
    return SENSOR_MODELS[spec.measurement].for_scenario(noise_std, scenario=scenario, network=network, device=device)


scenario_sensor.spec_misfit = _sensor_misfit
