r"""Social force model (Helbing & Molnár 1995), simplified as in Yu et al. Eq. (3)–(4)."""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from dslearn.errors import ConfigError, check_positive
from dslearn.types import AGENT_DIM, POS, VEL, StepContext, agents, joint
from dslearn.models.base import MotionModel


#: default softening radius (m) of the interaction distance, :func:`soft_distance`
SOFTENING = 0.2


def soft_distance(d2: Tensor, eps: float | Tensor = SOFTENING) -> Tensor:
    r"""Distance from squared distance, made smooth and bounded below near zero.

    :math:`s(u) = \sqrt u` for :math:`u = d^2 \ge \epsilon^2` (exactly the distance: interactions
    of agents at least ``eps`` apart are untouched), and below it the quadratic in :math:`u`
    that matches value, first and second derivative at :math:`u = \epsilon^2`:
    :math:`s(u) = 3\epsilon/8 + 3u/(4\epsilon) - u^2/(8\epsilon^3)`, increasing, with
    :math:`s(0) = 3\epsilon/8`. As a polynomial in :math:`d^2` it is smooth in the positions,
    also where two agents coincide. ``eps`` may be a tensor broadcasting against ``d2`` (> 0).
    """
    if not torch.is_tensor(eps) and eps <= 0:
        return d2.sqrt()
    e2 = eps * eps
    far = torch.maximum(d2, torch.as_tensor(e2, dtype=d2.dtype, device=d2.device)).sqrt()  # keeps the unused branch's gradient finite
    near = 3 * eps / 8 + 3 * d2 / (4 * eps) - d2 * d2 / (8 * eps**3)
    return torch.where(d2 >= e2, far, near)


def social_force_acceleration(
    pos: Tensor, vel: Tensor, desired: Tensor, tau: Tensor, alpha: Tensor, beta: Tensor,
    softening: float | Tensor = SOFTENING,
) -> Tensor:
    r"""Eq. (4): :math:`g_j = (v_j^* - v_j)/\tau_j + \sum_{k\ne j} \alpha_j e^{-d_{jk}/\beta_j} (x_j-x_k)/d_{jk}`.

    Bounded interactions: :math:`d_{jk}` is the :func:`soft_distance` (equal to the distance
    for agents at least ``softening`` apart), so the force and its Jacobian stay finite and
    smooth when agents coincide or nearly coincide: the repulsion falls to zero at
    coincidence, and every derivative is bounded by :math:`O(\alpha/\epsilon)`.

    Args:
        pos, vel: ``(*B, A, 2)``.
        desired: ``(A, 2)`` desired velocities :math:`v^*` (or ``(*B, A, 2)``, one per episode).
        tau, alpha, beta: ``(A,)`` per-agent relaxation time, strength, range.
        softening: :math:`\epsilon` in metres (0 = the plain distance, singular at coincidence),
            or a tensor ``(*B, A, A)`` of per-pair values.
    Returns:
        ``(*B, A, 2)`` accelerations.
    """
    diff = pos.unsqueeze(-2) - pos.unsqueeze(-3)  # (*B, A, A, 2): x_j - x_k
    a = pos.shape[-2]
    off = ~torch.eye(a, dtype=torch.bool, device=pos.device)
    dist = soft_distance(diff.pow(2).sum(-1), softening)  # (*B, A, A)
    mag = alpha[:, None] * torch.exp(-dist / beta[:, None]) * off
    repulse = (mag.unsqueeze(-1) * diff / dist.unsqueeze(-1)).sum(-2)
    return (desired - vel) / tau[:, None] + repulse


class SocialForce(MotionModel):
    r"""Social force motion model, Eq. (3) with Euler steps.

    .. math::
        x_j^{t+1} = x_j^t + v_j^t \Delta t, \quad v_j^{t+1} = v_j^t + g_j(y^t)\,\Delta t,

    process noise :math:`Q = \sigma_\eta^2 I`. Interactions are bounded
    (:func:`social_force_acceleration` with ``softening``).

    Args:
        desired_velocities: ``A`` pairs :math:`v_j^*`; :meth:`set_desired` replaces them, also by
            one set per episode ``(B, A, 2)`` (real trajectories, where each pedestrian has its own).
        tau, alpha, beta: scalars shared by all agents or one value per agent;
            :meth:`set_parameters` replaces them, also by tensors that carry gradients (fitting).
        noise_std: :math:`\sigma_\eta` (> 0).
        softening: :math:`\epsilon` of :func:`soft_distance` in metres (>= 0).
    """

    #: a gradient learner trains each agent's tau, alpha, beta
    gradient_parameters = "sfm"

    @staticmethod
    def spec_misfit(spec) -> str | None:
        """``model=sfm`` takes the simulation's own parameters: a scenario that simulates the social force."""
        if spec.dynamics == "social_force":
            return None
        return (f"model=sfm is the true social-force model of a simulated crowd: it takes the scenario's social-force "
                f"parameters, which scenario {spec.name} does not have (model=sfm_fit fits them to training tracks)")

    @classmethod
    def for_scenario(cls, noise_std: float = 1e-3, *, scenario, device=None) -> "SocialForce":
        """The config factory (``conf/model/sfm.yaml``): the true model, with the simulation's
        parameters (``scenario.sfm``) and the configured process noise."""
        s = getattr(scenario, "sfm", None)
        if s is None:
            name = getattr(getattr(scenario, "spec", None), "name", type(scenario).__name__)
            raise ConfigError(f"model=sfm is the true social-force model of a simulated crowd: it takes the scenario's "
                              f"social-force parameters, which scenario {name} does not have (model=sfm_fit fits them "
                              f"to training tracks)")
        return cls(s.desired.tolist(), s.tau.tolist(), s.alpha.tolist(), s.beta.tolist(), noise_std, s.softening).to(device)

    def __init__(
        self,
        desired_velocities: Sequence[Sequence[float]],
        tau: float | Sequence[float] = 0.25,
        alpha: float | Sequence[float] = 6.0,
        beta: float | Sequence[float] = 5.0,
        noise_std: float = 1e-3,
        softening: float = SOFTENING,
    ):
        super().__init__()
        desired = torch.as_tensor(desired_velocities, dtype=torch.float64)
        if desired.ndim != 2 or desired.shape[-1] != 2:
            raise ConfigError(
                f"scenario.desired_velocities must be a list of [vx, vy] pairs, got shape {tuple(desired.shape)}"
            )
        a = desired.shape[0]
        check_positive("model.noise_std", noise_std)
        check_positive("scenario.softening", softening, strict=False)

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
        self.softening = float(softening)

    def set_desired(self, desired: Tensor) -> "SocialForce":
        """Desired velocities ``(A, 2)``, or ``(B, A, 2)`` (one set per episode; broadcasts against
        states ``(*S, B, Dx)``)."""
        if desired.shape[-2:] != (self.num_agents, 2):
            raise ValueError(f"desired velocities must end in ({self.num_agents}, 2), got {tuple(desired.shape)}")
        self.desired = desired
        return self

    def set_parameters(self, tau: Tensor | float, alpha: Tensor | float, beta: Tensor | float) -> "SocialForce":
        """Replace :math:`(\tau, \alpha, \beta)` (scalars shared by all agents, or ``(A,)``); tensors
        keep their autograd graph, so a fit can differentiate through :meth:`forward`."""
        for name, v in (("tau", tau), ("alpha", alpha), ("beta", beta)):
            t = torch.as_tensor(v, dtype=torch.float64).reshape(-1)
            setattr(self, name, t.expand(self.num_agents) if t.numel() == 1 else t)
        return self

    def params(self) -> dict[str, float]:
        """The shared parameters as floats (the first agent's, where they differ)."""
        return {k: float(getattr(self, k).reshape(-1)[0]) for k in ("tau", "alpha", "beta")}

    def interaction_softening(self, ctx: StepContext, like: Tensor) -> float | Tensor:
        r"""Per-pair softening :math:`\epsilon_{jk} = \sqrt{\epsilon^2 + \sigma_j^2 + \sigma_k^2}` inside a filter.

        :math:`\sigma_j^2` is the filter's mean position variance of agent ``j`` (``ctx.cov``):
        the interaction with an agent known only vaguely is evaluated at a distance smoothed
        over its uncertainty, an approximation of the expected force under the belief. An agent
        the node knows nothing about (a diffuse prior, :func:`dslearn.filters.distributed.diffuse_prior`)
        then exerts and feels almost no force and the linearisation couples nothing to it;
        for agents known to centimetres it is the plain model (the softening only acts below
        :math:`\epsilon_{jk}`). Without ``ctx.cov`` (simulation, roll-outs) it is ``softening``.
        """
        if ctx.cov is None:
            return self.softening
        var = agents(ctx.cov.diagonal(dim1=-2, dim2=-1).detach())[..., POS].mean(-1).to(like)  # (*B, A)
        return (self.softening**2 + var.unsqueeze(-1) + var.unsqueeze(-2)).sqrt()

    def forward(self, x: Tensor, ctx: StepContext) -> Tensor:
        ag = agents(x)
        pos, vel = ag[..., POS], ag[..., VEL]
        p = {k: getattr(self, k).to(x) for k in ("desired", "tau", "alpha", "beta")}
        eps = self.interaction_softening(ctx, x)
        acc = social_force_acceleration(pos, vel, p["desired"], p["tau"], p["alpha"], p["beta"], eps)
        return joint(torch.cat([pos + vel * ctx.dt, vel + acc * ctx.dt], dim=-1))

    def noise_cov(self, x: Tensor, ctx: StepContext) -> Tensor:
        q = self.noise_std**2 * torch.eye(self.state_dim, dtype=x.dtype, device=x.device)
        return q.expand(*x.shape[:-1], *q.shape)
