r"""Terrain-based navigation scenario (Section VI, Table I).

* terrain elevation map: a 2-D Gaussian low-pass filter over uniform noise (seeded), rescaled to a
  chosen elevation standard deviation, looked up with bilinear interpolation (``h`` of Eq. 25);
* constant-velocity aircraft model, Eq. (23)-(24), state ``[p_X, p_Y, v_X, v_Y]``;
* four aircraft in finger-four formation (leader, wingman, element lead, element wingman);
* radar-altimeter noise from a K-state Markov chain (Eq. 25): ``y = h(p) + mu_r + sigma_r * eps``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from dslearn.models.jmnls import NoiseParams, simulate_modes
from dslearn.models.linear_gaussian import LinearGaussianDynamics
from dslearn.streams import Streams, randn


@dataclass
class TerrainMap:
    """Elevation grid with bilinear lookup.

    Attributes:
        z: (H, W) elevations [m]; ``z[i, j]`` is the elevation at ``(X, Y) = (j * res, i * res)``.
        resolution: grid spacing [m].
    """

    z: Tensor
    resolution: float

    @property
    def extent(self) -> tuple[float, float]:
        """(X_max, Y_max) in metres."""
        return ((self.z.shape[1] - 1) * self.resolution, (self.z.shape[0] - 1) * self.resolution)

    def __call__(self, p: Tensor) -> Tensor:
        """Bilinear elevation lookup h(p_X, p_Y). p: (..., >=2) (first two entries are X, Y) -> (...).

        Points outside the map are clamped to its border (counted by :meth:`outside`).
        """
        hgt, wid = self.z.shape
        gx = (p[..., 0] / self.resolution).clamp(0.0, wid - 1 - 1e-9)
        gy = (p[..., 1] / self.resolution).clamp(0.0, hgt - 1 - 1e-9)
        j0 = gx.floor()
        i0 = gy.floor()
        fx = gx - j0
        fy = gy - i0
        j0 = j0.long()
        i0 = i0.long()
        flat = self.z.reshape(-1)
        base = i0 * wid + j0
        z00 = flat[base]
        z01 = flat[base + 1]
        z10 = flat[base + wid]
        z11 = flat[base + wid + 1]
        return (z00 * (1 - fx) * (1 - fy) + z01 * fx * (1 - fy) + z10 * (1 - fx) * fy + z11 * fx * fy)

    def outside(self, p: Tensor) -> Tensor:
        """Bool mask of points outside the map. p: (..., >=2) -> (...)."""
        xm, ym = self.extent
        return (p[..., 0] < 0) | (p[..., 0] > xm) | (p[..., 1] < 0) | (p[..., 1] > ym)


def gaussian_kernel1d(sigma_cells: float, dtype=torch.float64, device="cpu") -> Tensor:
    """Normalised 1-D Gaussian kernel of half-width ceil(3 sigma)."""
    r = max(1, int(math.ceil(3.0 * sigma_cells)))
    x = torch.arange(-r, r + 1, dtype=dtype, device=device)
    k = torch.exp(-0.5 * (x / sigma_cells) ** 2)
    return k / k.sum()


def make_terrain(size_m: float, resolution_m: float, smoothing_m: float, elevation_std_m: float,
                 mean_elevation_m: float, gen: torch.Generator, *, dtype=torch.float64, device="cpu") -> TerrainMap:
    """Terrain by a separable 2-D Gaussian low-pass filter over uniform noise [Gustafsson 2010, ref. 12].

    Args:
        size_m: side of the square map [m].
        resolution_m: grid spacing [m].
        smoothing_m: standard deviation of the Gaussian filter [m].
        elevation_std_m: the filtered field is rescaled to this standard deviation [m].
        mean_elevation_m: and shifted to this mean [m].
        gen: generator (seeded) - the same seed gives the same map.
    """
    n = int(round(size_m / resolution_m)) + 1
    sig = smoothing_m / resolution_m
    ker = gaussian_kernel1d(sig, dtype, device)
    pad = ker.numel() // 2
    noise = torch.rand(n + 2 * pad, n + 2 * pad, generator=gen, dtype=dtype, device=device)
    z = torch.nn.functional.conv2d(noise[None, None], ker.view(1, 1, 1, -1))
    z = torch.nn.functional.conv2d(z, ker.view(1, 1, -1, 1))[0, 0]
    z = (z - z.mean()) / z.std() * elevation_std_m + mean_elevation_m
    return TerrainMap(z.contiguous(), float(resolution_m))


def cv_model(dt: float, q: float, kernel_jitter=(1.0, 0.0), *, dtype=torch.float64, device="cpu",
             kernel_dtype=None) -> LinearGaussianDynamics:
    """Constant-velocity model of Eq. (23)-(24) with ``Q = q I_2``.

    Args:
        dt: sampling period T [s].
        q: Q_XX = Q_YY [(m/s^2)^2].
        kernel_jitter: (position, velocity) variances added for the backward kernel only.
        kernel_dtype: dtype of the N×N backward-kernel products (None: same as ``dtype``).
    """
    kw = dict(dtype=dtype, device=device)
    F = torch.tensor([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]], **kw)
    G = torch.tensor([[dt * dt / 2, 0], [0, dt * dt / 2], [dt, 0], [0, dt]], **kw)
    Q = q * torch.eye(2, **kw)
    jp, jv = float(kernel_jitter[0]), float(kernel_jitter[1])
    jit = torch.tensor([jp, jp, jv, jv], **kw)
    return LinearGaussianDynamics(F, G, Q, jit, kernel_dtype)


def finger_four_offsets(spacing: float, heading: Tensor) -> Tensor:
    """Finger-four formation offsets (node 1 = flight leader) relative to the leader.

    Node 2 (wingman) behind-left of the leader, node 3 (element lead) behind-right, node 4 (element
    wingman) behind-right of node 3. Units of ``spacing`` [m]. heading: (2,) -> (4, 2).
    """
    h = heading / heading.norm()
    left = torch.stack([-h[1], h[0]])
    back = -h
    rel = torch.tensor([[0.0, 0.0], [1.0, 1.0], [1.0, -1.0], [2.0, -2.0]], dtype=h.dtype, device=h.device)
    return spacing * (rel[:, :1] * back + rel[:, 1:] * left)


@dataclass
class Scenario:
    """Simulated ground truth for a batch of Monte Carlo runs.

    Attributes:
        x: (R, S, T+1, 4) true states (t = 0..T).
        r: (R, S, T+1) true modes.
        y: (R, S, T+1) measurements (y[..., 0] unused).
        terrain: the map.
    """

    x: Tensor
    r: Tensor
    y: Tensor
    terrain: TerrainMap


def simulate(terrain: TerrainMap, truth: NoiseParams, dyn: LinearGaussianDynamics, *, runs: int, start: Tensor,
             v0: Tensor, spacing: float, steps: int, gen: torch.Generator | Streams) -> Scenario:
    """Simulate ``runs`` independent flights of the 4-aircraft formation over ``terrain``.

    With ``gen`` a :class:`~dslearn.streams.Streams` over ``(runs,)``, every run's truth, modes and
    measurement noise come from that run's own generator (the same run gives the same flight in any batch).

    Args:
        truth: true noise parameters (unbatched, K modes).
        dyn: truth dynamics (Eq. 23 with the truth's Q).
        start: (2,) leader start position [m]; v0: (2,) initial velocity [m/s].
        spacing: formation spacing [m].
        steps: number of measurements T.
    """
    start = torch.as_tensor(start).to(terrain.z)
    v0 = torch.as_tensor(v0).to(terrain.z)
    dtype, device = start.dtype, start.device
    off = finger_four_offsets(spacing, v0)  # (4, 2)
    s = off.shape[0]
    x0 = torch.cat([start + off, v0.expand(s, 2)], -1)  # (S, 4)
    x = [x0.expand(runs, s, 4).clone()]
    w = randn((runs, steps, s, dyn.Q.shape[0]), gen, dtype=dtype, device=device)  # driving noise, all steps
    gw = (w @ dyn.chol_q.T) @ dyn.G.T  # (R, T, S, 4)
    for t in range(steps):
        x.append(x[-1] @ dyn.F.T + gw[:, t])
    x = torch.stack(x, 2)  # (R, S, T+1, 4)
    r = simulate_modes(truth.pi, (runs, s), steps, gen)
    eps = randn((runs, s, steps + 1), gen, dtype=dtype, device=device)
    y = terrain(x) + truth.mu[r] + truth.sigma[r] * eps
    return Scenario(x, r, y, terrain)


def terrain_gradient(scn: Scenario, step_m: float = 5.0) -> Tensor:
    """|grad h| of the map at the true positions by central differences. -> (R, S, T) (t = 1..T)."""
    p = scn.x[..., 1:, :2]
    ex = torch.tensor([step_m, 0.0], dtype=p.dtype, device=p.device)
    ey = torch.tensor([0.0, step_m], dtype=p.dtype, device=p.device)
    h = scn.terrain
    gx = (h(p + ex) - h(p - ex)) / (2 * step_m)
    gy = (h(p + ey) - h(p - ey)) / (2 * step_m)
    return torch.sqrt(gx * gx + gy * gy)
