r"""A motion model of your own: a damped constant-velocity model with its exact Jacobian.

Each target (agent) has the state ``[px, py, vx, vy]``; the joint state of ``A`` agents is their
concatenation (``Dx = 4A``). One step of ``dt`` seconds:

    p' = p + dt v
    v' = v + dt * k * (s * v / n(v) - v),      n(v) = sqrt(|v|^2 + eps^2)

The speed relaxes towards a preferred speed ``s`` at the rate ``k`` (1/s), the heading is kept.
With ``s = 0`` it is a linearly damped constant velocity, with ``k = 0`` exactly the built-in
constant velocity (``model=lin``). ``eps`` keeps ``v / n(v)`` smooth at rest.

A model implements :class:`dslearn.models.base.MotionModel`: ``forward`` (the predicted mean) and
``noise_cov`` (the process noise ``Q``); ``jacobian`` defaults to autograd, here it is written out
(the EKF's prediction step uses it). Every method takes batched states ``(*B, Dx)``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from dslearn.errors import ConfigError
from dslearn.models.base import MotionModel
from dslearn.types import StepContext, agents, joint


class DampedConstantVelocity(MotionModel):
    """Damped constant velocity, each agent independently (see the module docstring).

    Args:
        num_agents: number of agents ``A``.
        noise_std: process noise standard deviation (``Q = noise_std^2 I``).
        damping: the rate ``k`` (1/s) at which the speed relaxes to ``speed``; ``k * dt`` must be <= 1.
        speed: the preferred speed ``s`` (m/s).
        eps: smoothing of the speed at rest (m/s).
    """

    @classmethod
    def for_scenario(cls, noise_std: float = 0.1, damping: float = 0.5, speed: float = 1.4, *, scenario,
                     device=None) -> "DampedConstantVelocity":
        """What the YAML's ``_target_`` names: the composition root calls it with the YAML's keys and the
        run's ``scenario`` (and ``device``) because its signature names them (``_partial_: true``)."""
        return cls(scenario.num_agents, noise_std, damping, speed).to(device)

    def __init__(self, num_agents: int, noise_std: float = 0.1, damping: float = 0.5, speed: float = 1.4,
                 eps: float = 1e-3):
        super().__init__()
        # refuse a value the model cannot use, naming the config key (nothing silently ignored)
        if num_agents < 1:
            raise ConfigError(f"scenario.num_agents={num_agents} must be >= 1")
        if not noise_std > 0:
            raise ConfigError(f"model.noise_std={noise_std} must be > 0")
        if not damping >= 0:
            raise ConfigError(f"model.damping={damping} must be >= 0")
        if not speed >= 0:
            raise ConfigError(f"model.speed={speed} must be >= 0")
        self.num_agents, self.state_dim = int(num_agents), 4 * int(num_agents)
        self.noise_std, self.damping, self.speed, self.eps = float(noise_std), float(damping), float(speed), float(eps)

    def _rate(self, dt: float) -> float:
        a = self.damping * dt
        if a > 1.0:
            raise ConfigError(f"model.damping={self.damping} times the time step {dt} s is {a} > 1 (the velocity "
                              "would overshoot); lower model.damping")
        return a

    def forward(self, x: Tensor, ctx: StepContext) -> Tensor:
        a, dt = self._rate(ctx.dt), ctx.dt
        s = agents(x)                                       # (*B, A, 4)
        p, v = s[..., :2], s[..., 2:]
        n = (v.pow(2).sum(-1, keepdim=True) + self.eps**2).sqrt()
        v_next = (1.0 - a) * v + a * self.speed * v / n
        return joint(torch.cat([p + dt * v, v_next], dim=-1))

    def jacobian(self, x: Tensor, ctx: StepContext) -> Tensor:
        a, dt = self._rate(ctx.dt), ctx.dt
        v = agents(x)[..., 2:]                              # (*B, A, 2)
        n = (v.pow(2).sum(-1) + self.eps**2).sqrt()[..., None, None]
        eye2 = torch.eye(2, dtype=x.dtype, device=x.device)
        # d(v / n)/dv = I / n - v v^T / n^3
        dvv = (1.0 - a) * eye2 + a * self.speed * (eye2 / n - v[..., :, None] * v[..., None, :] / n**3)
        f = torch.zeros(*x.shape, x.shape[-1], dtype=x.dtype, device=x.device)  # (*B, Dx, Dx)
        for i in range(self.num_agents):                    # block diagonal: agents move independently
            o = 4 * i
            f[..., o:o + 2, o:o + 2] = eye2
            f[..., o:o + 2, o + 2:o + 4] = dt * eye2
            f[..., o + 2:o + 4, o + 2:o + 4] = dvv[..., i, :, :]
        return f

    def noise_cov(self, x: Tensor, ctx: StepContext) -> Tensor:
        q = self.noise_std**2 * torch.eye(self.state_dim, dtype=x.dtype, device=x.device)
        return q.expand(*x.shape[:-1], *q.shape)
