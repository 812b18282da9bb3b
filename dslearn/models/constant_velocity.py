r"""Constant-velocity (LIN) motion model."""

from __future__ import annotations

import torch
from torch import Tensor

from dslearn.errors import ConfigError, check_number, check_positive
from dslearn.types import AGENT_DIM, StepContext
from dslearn.models.base import MotionModel


class _LinearAgents(MotionModel):
    """What the constant-velocity models share: ``A`` independent agents, the state-independent transition matrix
    ``F`` of :meth:`matrix` and process noise ``Q`` of :meth:`noise_matrix` (here ``noise_std^2 I``)."""

    independent_targets = True

    def __init__(self, num_agents: int, noise_std: float = 0.1):
        super().__init__()
        if num_agents < 1:
            raise ConfigError(f"scenario.num_agents={num_agents} must be >= 1")
        check_positive("model.noise_std", noise_std)
        self.num_agents = int(num_agents)
        self.state_dim = AGENT_DIM * self.num_agents
        self.noise_std = float(noise_std)

    def noise_matrix(self, dt: float, dtype=torch.float64, device=None) -> Tensor:
        """The process noise ``Q`` (Dx, Dx)."""
        return self.noise_std**2 * torch.eye(self.state_dim, dtype=dtype, device=device)

    def forward(self, x: Tensor, ctx: StepContext) -> Tensor:
        return x @ self.matrix(ctx.dt, x.dtype, x.device).T

    def jacobian(self, x: Tensor, ctx: StepContext) -> Tensor:
        f = self.matrix(ctx.dt, x.dtype, x.device)
        return f.expand(*x.shape[:-1], *f.shape)

    def noise_cov(self, x: Tensor, ctx: StepContext) -> Tensor:
        q = self.noise_matrix(ctx.dt, x.dtype, x.device)
        return q.expand(*x.shape[:-1], *q.shape)


class ConstantVelocity(_LinearAgents):
    r"""Each agent independently: :math:`p^{t+1} = p^t + v^t \Delta t`, :math:`v^{t+1} = v^t`.

    Process noise :math:`Q = \sigma^2 I` (the paper's LIN uses :math:`\sigma = 0.1`).

    Args:
        num_agents: number of agents ``A`` (``Dx = 4A``).
        noise_std: process noise standard deviation :math:`\sigma` (> 0).
    """

    #: a gradient learner trains its transition matrix's agent block (``model=lin``)
    gradient_parameters = "lin"

    @classmethod
    def for_scenario(cls, noise_std: float = 0.1, *, scenario, device=None) -> "ConstantVelocity":
        """The config factory (``conf/model/lin.yaml``): one agent block per agent of ``scenario``."""
        return cls(scenario.num_agents, noise_std).to(device)

    def matrix(self, dt: float, dtype=torch.float64, device=None) -> Tensor:
        """The transition matrix ``F`` (Dx, Dx)."""
        block = torch.eye(AGENT_DIM, dtype=dtype, device=device)
        block[0, 2] = block[1, 3] = dt
        return torch.block_diag(*([block] * self.num_agents))


class DampedConstantVelocity(_LinearAgents):
    r"""Each agent independently: the damped constant-velocity model of the factor-graph identification
    (:mod:`dslearn.learning.factor_graph.motion`), :math:`p^{t+1} = p^t + v^t \Delta t`, :math:`v^{t+1} = a\, v^t`.

    Process noise: :math:`Q = q\, G G^T` per agent, :math:`G = [\Delta t^2/2\, I;\ \Delta t\, I]` (white acceleration
    of intensity ``q``), or, while ``q`` is ``None`` (before an identification), LIN's :math:`\sigma^2 I`. With
    ``a = 1`` and ``q = None`` the model is LIN (:class:`ConstantVelocity`). ``learner=fg_identification`` sets
    ``a`` and ``q`` (:meth:`set_parameters`) from the training episodes' true tracks before any tracking.

    Args:
        num_agents: number of agents ``A`` (``Dx = 4A``).
        a: the share of the velocity kept per step (finite).
        q: the white acceleration's intensity [(m/s^2)^2] (> 0), or ``None``: LIN's noise ``noise_std^2 I``.
        noise_std: LIN's process noise standard deviation (> 0), used while ``q`` is ``None``.
    """

    @classmethod
    def for_scenario(cls, a: float = 1.0, q: float | None = None, noise_std: float = 0.1, *, scenario,
                     device=None) -> "DampedConstantVelocity":
        """The config factory (``conf/model/cv_damped.yaml``): one agent block per agent of ``scenario``."""
        return cls(scenario.num_agents, a, q, noise_std).to(device)

    def __init__(self, num_agents: int, a: float = 1.0, q: float | None = None, noise_std: float = 0.1):
        super().__init__(num_agents, noise_std)
        self.set_parameters(a, q, prefix="model")

    def set_parameters(self, a: float, q: float | None, prefix: str = "model") -> None:
        """Set ``a`` (finite) and ``q`` (> 0, finite, or ``None``: LIN's noise); ConfigError naming ``prefix.a`` /
        ``prefix.q`` otherwise."""
        a = check_number(f"{prefix}.a", a)
        if q is not None:
            check_positive(f"{prefix}.q", q)
        self.a = a
        self.q = None if q is None else float(q)

    def matrix(self, dt: float, dtype=torch.float64, device=None) -> Tensor:
        """The transition matrix ``F`` (Dx, Dx)."""
        block = torch.eye(AGENT_DIM, dtype=dtype, device=device)
        block[0, 2] = block[1, 3] = dt
        block[2, 2] = block[3, 3] = self.a
        return torch.block_diag(*([block] * self.num_agents))

    def noise_matrix(self, dt: float, dtype=torch.float64, device=None) -> Tensor:
        """The process noise ``Q`` (Dx, Dx)."""
        if self.q is None:
            return super().noise_matrix(dt, dtype, device)
        g = torch.tensor([[dt * dt / 2, 0.0], [0.0, dt * dt / 2], [dt, 0.0], [0.0, dt]], dtype=dtype, device=device)
        return torch.block_diag(*([self.q * (g @ g.T)] * self.num_agents))
