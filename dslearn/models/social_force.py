r"""Social force model (Helbing & Molnár 1995), simplified as in Yu et al. Eq. (3)–(4)."""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from ..errors import ConfigError, check_positive
from ..types import AGENT_DIM, POS, VEL, StepContext, agents, joint
from .base import MotionModel


def social_force_acceleration(
    pos: Tensor, vel: Tensor, desired: Tensor, tau: Tensor, alpha: Tensor, beta: Tensor
) -> Tensor:
    r"""Eq. (4): :math:`g_j = (v_j^* - v_j)/\tau_j + \sum_{k\ne j} \alpha_j e^{-d_{jk}/\beta_j} (x_j-x_k)/d_{jk}`.

    Args:
        pos, vel: ``(*B, A, 2)``.
        desired: ``(A, 2)`` desired velocities :math:`v^*`.
        tau, alpha, beta: ``(A,)`` per-agent relaxation time, strength, range.
    Returns:
        ``(*B, A, 2)`` accelerations.
    """
    diff = pos.unsqueeze(-2) - pos.unsqueeze(-3)  # (*B, A, A, 2): x_j - x_k
    a = pos.shape[-2]
    off = ~torch.eye(a, dtype=torch.bool, device=pos.device)
    # the self term (k = j) is excluded; a tiny floor keeps the force (zero direction) and its
    # autograd Jacobian finite when two agents coincide (e.g. two vague priors at one point)
    dist = (diff.pow(2).sum(-1) + 1e-18).sqrt()  # (*B, A, A)
    mag = alpha[:, None] * torch.exp(-dist / beta[:, None]) * off
    repulse = (mag.unsqueeze(-1) * diff / dist.clamp_min(1e-9).unsqueeze(-1)).sum(-2)
    return (desired - vel) / tau[:, None] + repulse


class SocialForce(MotionModel):
    r"""Social force motion model, Eq. (3) with Euler steps.

    .. math::
        x_j^{t+1} = x_j^t + v_j^t \Delta t, \quad v_j^{t+1} = v_j^t + g_j(y^t)\,\Delta t,

    process noise :math:`Q = \sigma_\eta^2 I`.

    Args:
        desired_velocities: ``A`` pairs :math:`v_j^*`.
        tau, alpha, beta: scalars shared by all agents or one value per agent.
        noise_std: :math:`\sigma_\eta` (> 0).
    """

    def __init__(
        self,
        desired_velocities: Sequence[Sequence[float]],
        tau: float | Sequence[float] = 0.25,
        alpha: float | Sequence[float] = 6.0,
        beta: float | Sequence[float] = 5.0,
        noise_std: float = 1e-3,
    ):
        super().__init__()
        desired = torch.as_tensor(desired_velocities, dtype=torch.float64)
        if desired.ndim != 2 or desired.shape[-1] != 2:
            raise ConfigError(
                f"scenario.desired_velocities must be a list of [vx, vy] pairs, got shape {tuple(desired.shape)}"
            )
        a = desired.shape[0]
        check_positive("model.noise_std", noise_std)

        def per_agent(name, v):
            t = torch.as_tensor(v, dtype=torch.float64).flatten()
            if t.numel() == 1:
                t = t.expand(a).clone()
            if t.numel() != a:
                raise ConfigError(f"scenario.{name} must be one value or {a} values (one per agent)")
            for k, vk in enumerate(t.tolist()):
                if name != "alpha":
                    check_positive(f"scenario.{name}[{k}]", vk)
            return t

        self.num_agents = a
        self.state_dim = AGENT_DIM * a
        self.register_buffer("desired", desired)
        self.register_buffer("tau", per_agent("tau", tau))
        self.register_buffer("alpha", per_agent("alpha", alpha))
        self.register_buffer("beta", per_agent("beta", beta))
        self.noise_std = float(noise_std)

    def forward(self, x: Tensor, ctx: StepContext) -> Tensor:
        ag = agents(x)
        pos, vel = ag[..., POS], ag[..., VEL]
        p = {k: getattr(self, k).to(x) for k in ("desired", "tau", "alpha", "beta")}
        acc = social_force_acceleration(pos, vel, p["desired"], p["tau"], p["alpha"], p["beta"])
        return joint(torch.cat([pos + vel * ctx.dt, vel + acc * ctx.dt], dim=-1))

    def noise_cov(self, x: Tensor, ctx: StepContext) -> Tensor:
        q = self.noise_std**2 * torch.eye(self.state_dim, dtype=x.dtype, device=x.device)
        return q.expand(*x.shape[:-1], *q.shape)
