r"""The paper's simulation scenario (Jiang et al. 2022, Sec. IV, Eqs. 20-22).

Sensors at known positions :math:`(A_n, B_n)` measure the squared distance to the source,
:math:`h_n(x) = (A_n - x_1)^2 + (B_n - x_2)^2` (Eq. 22). The source follows
:math:`x_{m,k} = a_m k^2 + b_m k + c_m + \omega_{m,k}`, :math:`\omega\sim\mathcal N(0,\sigma_\omega^2)`
i.i.d. over ``k`` (Eqs. 20-21).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


class SquaredRange(nn.Module):
    """``h_n(x) = ||s_n - x||^2`` (Eq. 22) for sensors ``s (N, M)``: ``(*B, M) -> (*B, N)``."""

    def __init__(self, sensors: Tensor) -> None:
        super().__init__()
        self.register_buffer("sensors", torch.as_tensor(sensors))

    def forward(self, x: Tensor) -> Tensor:
        return (self.sensors.to(x) - x.unsqueeze(-2)).square().sum(-1)


def polynomial_trajectory(
    coeffs: Tensor, num_timings: int, drive_var: float, batch: tuple[int, ...], generator: torch.Generator
) -> Tensor:
    """Eqs. 20-21: true parameters at ``k = 1..K``.

    Args:
        coeffs: ``(M, 3)`` rows ``(a, b, c)`` of ``a k^2 + b k + c``.
        num_timings: ``K``.
        drive_var: :math:`\\sigma_\\omega^2` (i.i.d. over k, not a random walk).
        batch: Monte Carlo batch shape ``B``.
        generator: torch generator (same device as ``coeffs``).

    Returns:
        ``(*B, K, M)``.
    """
    k = torch.arange(1, num_timings + 1, dtype=coeffs.dtype, device=coeffs.device)
    mean = coeffs[:, 0] * k[:, None] ** 2 + coeffs[:, 1] * k[:, None] + coeffs[:, 2]   # (K, M)
    noise = torch.randn(*batch, *mean.shape, generator=generator, dtype=coeffs.dtype, device=coeffs.device)
    return mean + drive_var**0.5 * noise
