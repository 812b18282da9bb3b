r"""Constant-velocity (LIN) motion model."""

from __future__ import annotations

import torch
from torch import Tensor

from dslearn.errors import ConfigError, check_positive
from dslearn.types import AGENT_DIM, StepContext
from dslearn.models.base import MotionModel


class ConstantVelocity(MotionModel):
    r"""Each agent independently: :math:`p^{t+1} = p^t + v^t \Delta t`, :math:`v^{t+1} = v^t`.

    Process noise :math:`Q = \sigma^2 I` (the paper's LIN uses :math:`\sigma = 0.1`).

    Args:
        num_agents: number of agents ``A`` (``Dx = 4A``).
        noise_std: process noise standard deviation :math:`\sigma` (> 0).
    """

    @classmethod
    def for_scenario(cls, noise_std: float = 0.1, *, scenario, device=None) -> "ConstantVelocity":
        """The config factory (``conf/model/lin.yaml``): one agent block per agent of ``scenario``."""
        return cls(scenario.num_agents, noise_std).to(device)

    def __init__(self, num_agents: int, noise_std: float = 0.1):
        super().__init__()
        if num_agents < 1:
            raise ConfigError(f"scenario.num_agents={num_agents} must be >= 1")
        check_positive("model.noise_std", noise_std)
        self.num_agents = int(num_agents)
        self.state_dim = AGENT_DIM * self.num_agents
        self.noise_std = float(noise_std)

    def matrix(self, dt: float, dtype=torch.float64, device=None) -> Tensor:
        """The transition matrix ``F`` (Dx, Dx)."""
        block = torch.eye(AGENT_DIM, dtype=dtype, device=device)
        block[0, 2] = block[1, 3] = dt
        return torch.block_diag(*([block] * self.num_agents))

    def forward(self, x: Tensor, ctx: StepContext) -> Tensor:
        return x @ self.matrix(ctx.dt, x.dtype, x.device).T

    def jacobian(self, x: Tensor, ctx: StepContext) -> Tensor:
        f = self.matrix(ctx.dt, x.dtype, x.device)
        return f.expand(*x.shape[:-1], *f.shape)

    def noise_cov(self, x: Tensor, ctx: StepContext) -> Tensor:
        q = self.noise_std**2 * torch.eye(self.state_dim, dtype=x.dtype, device=x.device)
        return q.expand(*x.shape[:-1], *q.shape)
