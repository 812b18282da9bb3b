r"""The paper's simulation scenario (Jiang et al. 2022, Sec. IV, Eqs. 20-22).

Sensors at known positions :math:`(A_n, B_n)` measure the squared distance to the source,
:math:`h_n(x) = (A_n - x_1)^2 + (B_n - x_2)^2` (Eq. 22). The source follows
:math:`x_{m,k} = a_m k^2 + b_m k + c_m + \omega_{m,k}`, :math:`\omega\sim\mathcal N(0,\sigma_\omega^2)`
i.i.d. over ``k`` (Eqs. 20-21).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from dslearn.errors import ConfigError


class SquaredRange(nn.Module):
    """``h_n(x) = ||s_n - x||^2`` (Eq. 22) for sensors ``s (N, M)``: ``(*B, M) -> (*B, N)``."""

    def __init__(self, sensors: Tensor) -> None:
        super().__init__()
        self.register_buffer("sensors", torch.as_tensor(sensors))

    def forward(self, x: Tensor) -> Tensor:
        return (self.sensors.to(x) - x.unsqueeze(-2)).square().sum(-1)


def run_seed(seed: int, run: int) -> int:
    """A 64-bit seed for Monte Carlo run ``run`` of base seed ``seed`` (both ``>= 0``).

    Derived with :class:`numpy.random.SeedSequence` from the pair ``(seed, run)``, so every run has its
    own, well-separated stream, and ``(seed, run)`` pairs never collide the way ``seed * C + run`` can.
    """
    if int(seed) < 0 or int(run) < 0:
        raise ConfigError(f"seed={seed!r} and run index {run!r} must be >= 0")
    return int(np.random.SeedSequence([int(seed), int(run)]).generate_state(1, dtype=np.uint64)[0])


def run_noise(
    seed: int, runs, num_timings: int, num_params: int, num_sensors: int, num_samples: int,
    dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu",
) -> tuple[Tensor, Tensor]:
    """Standard-normal draws of the Monte Carlo runs ``runs``, each from its own stream.

    Run ``r`` draws, from a CPU generator seeded with :func:`run_seed` ``(seed, r)``, first its
    drive noise ``omega (K, M)`` and then its sensor noise ``(K, N, L)``, in float64. A run's
    numbers therefore depend only on ``(seed, r)``: not on how many runs there are, which runs
    share its batch, the device or the dtype of the computation (they are cast afterwards).

    Returns:
        ``drive (R, K, M)`` and ``sensor (R, K, N, L)`` on ``device`` in ``dtype``.
    """
    drive, sensor = [], []
    for r in runs:
        g = torch.Generator().manual_seed(run_seed(seed, r))
        drive.append(torch.randn(num_timings, num_params, generator=g, dtype=torch.float64))
        sensor.append(torch.randn(num_timings, num_sensors, num_samples, generator=g, dtype=torch.float64))
    if not drive:
        raise ConfigError("run_noise: at least one Monte Carlo run is needed")
    return torch.stack(drive).to(device=device, dtype=dtype), torch.stack(sensor).to(device=device, dtype=dtype)


def polynomial_trajectory(
    coeffs: Tensor, num_timings: int, drive_var: float, batch: tuple[int, ...] = (),
    generator: torch.Generator | None = None, noise: Tensor | None = None,
) -> Tensor:
    """Eqs. 20-21: true parameters at ``k = 1..K``.

    Args:
        coeffs: ``(M, 3)`` rows ``(a, b, c)`` of ``a k^2 + b k + c``.
        num_timings: ``K``.
        drive_var: :math:`\\sigma_\\omega^2` (i.i.d. over k, not a random walk).
        batch: Monte Carlo batch shape ``B`` (with ``generator``).
        generator: torch generator (same device as ``coeffs``) to draw the drive noise from.
        noise: ``(*B, K, M)`` standard-normal drive noise instead of ``batch`` / ``generator``
            (e.g. from :func:`run_noise`).

    Returns:
        ``(*B, K, M)``.
    """
    k = torch.arange(1, num_timings + 1, dtype=coeffs.dtype, device=coeffs.device)
    mean = coeffs[:, 0] * k[:, None] ** 2 + coeffs[:, 1] * k[:, None] + coeffs[:, 2]   # (K, M)
    if noise is None:
        noise = torch.randn(*batch, *mean.shape, generator=generator, dtype=coeffs.dtype, device=coeffs.device)
    assert noise.shape[-2:] == mean.shape, (noise.shape, mean.shape)
    return mean + drive_var**0.5 * noise
