r"""Fitting the social force model to trajectories (real pedestrians, where the true model is unknown).

The model is the ONE :class:`dslearn.models.social_force.SocialForce` (bounded interactions
included) with shared :math:`(\tau, \alpha, \beta)`; each episode's desired velocities
:math:`v_j^*` are the agents' mean velocity over the first ``desired_steps`` states
(:func:`desired_velocity`; default 1: the velocity in the t = 0 state, the information LIN gets).
:func:`fit_social_force` minimises the mean position error of its roll-outs from each episode's
state at t = 0 (the prediction protocol): grid search, then Adam on
:math:`(\log\tau, \alpha \ge 0, \log\beta)`.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from dslearn.models.social_force import SocialForce
from dslearn.types import POS, VEL, StepContext, agents

#: the default grids of the fit's search (:func:`fit_social_force`)
TAU_GRID = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
ALPHA_GRID = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0)
BETA_GRID = (0.25, 0.5, 1.0, 2.0, 4.0)


def episode_social_force(num_agents: int, tau: float = 1.0, alpha: float = 0.0, beta: float = 1.0,
                         noise_std: float = 0.1) -> SocialForce:
    r"""The social force model of :mod:`dslearn.models.social_force` (the same code, bounded
    interactions included) with shared :math:`(\tau, \alpha, \beta)`; each episode's desired
    velocities are set with :meth:`~dslearn.models.social_force.SocialForce.set_desired`
    ``(B, A, 2)`` before tracking or rolling out a batch of episodes."""
    return SocialForce([[0.0, 0.0]] * int(num_agents), tau, alpha, beta, noise_std)


def desired_velocity(states: Tensor, desired_steps: int = 1) -> Tensor:
    """Each agent's mean velocity over the first ``desired_steps`` states: ``(B, K+1, 4A) -> (B, A, 2)``."""
    return agents(states[:, :desired_steps])[..., VEL].mean(1)


def measured_desired_velocity(meas: Tensor, visible: Tensor, dt: float, desired_steps: int = 1) -> Tensor:
    """Each agent's velocity from measurements alone: ``(S, B, K+1, A, 2)``, ``(S, B, K+1, A)`` -> ``(B, A, 2)``.

    At every step the agent's measured position is the mean of the readings of the nodes that see it; the velocity
    is the difference between its first measured step and its ``desired_steps``-th measured step after that, over
    the time between them (``desired_steps = 1`` with the agent seen at t = 0 and t = 1: the velocity of the
    filter's first observations). An agent measured at fewer steps gets 0."""
    w = visible.to(meas.dtype).unsqueeze(-1)
    n = w.sum(0)                                                   # (B, K+1, A, 1) nodes that see the agent
    pos = (meas * w).sum(0) / n.clamp_min(1.0)                     # (B, K+1, A, 2)
    seen = n[..., 0] > 0                                           # (B, K+1, A)
    count = seen.long().cumsum(1)
    first = (seen & (count == 1)).long().argmax(1)                 # (B, A) the first measured step
    later = seen & (count == int(desired_steps) + 1)
    found = later.any(1)
    last = later.long().argmax(1)
    p0 = pos.gather(1, first[:, None, :, None].expand(-1, 1, -1, 2))[:, 0]
    p1 = pos.gather(1, last[:, None, :, None].expand(-1, 1, -1, 2))[:, 0]
    span = ((last - first).clamp_min(1) * float(dt)).to(meas.dtype)[..., None]
    return torch.where(found[..., None], (p1 - p0) / span, torch.zeros_like(p0))


def _rollout_error(model: SocialForce, states: Tensor, ctx: StepContext) -> Tensor:
    """Mean position error of the roll-out from ``states[:, 0]`` (differentiable)."""
    x = states[:, 0]
    errs = []
    for t in range(1, states.shape[1]):
        x = model(x, ctx)
        errs.append((agents(x)[..., POS] - agents(states[:, t])[..., POS]).norm(dim=-1))
    return torch.stack(errs).mean()


def fit_social_force(
    states: Tensor,
    dt: float,
    desired_steps: int = 1,
    tau_grid=TAU_GRID,
    alpha_grid=ALPHA_GRID,
    beta_grid=BETA_GRID,
    refine_iters: int = 150,
    refine_lr: float = 0.05,
) -> tuple[dict[str, float], float]:
    r"""Fit shared SFM parameters to trajectories by roll-out error.

    Objective: mean over episodes, steps t = 1..K and agents of
    :math:`\|\hat x_j^t - x_j^t\|` where :math:`\hat x` is the SFM roll-out from the state at
    t = 0 with :math:`v_j^*` = :func:`desired_velocity`. Grid search over
    ``tau_grid x alpha_grid x beta_grid`` (only :math:`\tau \ge \Delta t`: a shorter relaxation
    time makes the Euler step overshoot; largest :math:`\tau` first, so where the error does not
    depend on :math:`\tau` the weakest relaxation is kept), then ``refine_iters`` Adam steps on
    :math:`(\log\tau, \alpha, \log\beta)` from the best grid point (:math:`\alpha` projected to
    :math:`\ge 0`, :math:`\tau \ge \Delta t`); the better of the two is returned.

    Args:
        states: ``(B, K+1, 4A)`` trajectories (truth or fused estimates).
    Returns:
        ``({"tau", "alpha", "beta"}, objective)``.
    """
    states = states.detach().to(torch.float64)
    a = states.shape[-1] // 4
    ctx = StepContext(dt=float(dt))
    model = episode_social_force(a).set_desired(desired_velocity(states, desired_steps))
    best, best_loss = None, math.inf
    taus = sorted((float(v) for v in tau_grid if float(v) >= dt - 1e-12), reverse=True) or [float(dt)]
    with torch.no_grad():
        for tau in taus:  # largest first: where the error does not depend on tau, keep the weakest relaxation
            for alpha in alpha_grid:
                for beta in beta_grid:
                    model.set_parameters(float(tau), float(alpha), float(beta))
                    loss = float(_rollout_error(model, states, ctx))
                    if loss < best_loss:
                        best, best_loss = (float(tau), float(alpha), float(beta)), loss
    log_tau = torch.tensor(math.log(best[0]), dtype=torch.float64, requires_grad=True)
    alpha = torch.tensor(best[1], dtype=torch.float64, requires_grad=True)
    log_beta = torch.tensor(math.log(best[2]), dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([log_tau, alpha, log_beta], lr=refine_lr)
    for _ in range(int(refine_iters)):
        opt.zero_grad()
        model.set_parameters(log_tau.exp(), alpha, log_beta.exp())
        loss = _rollout_error(model, states, ctx)
        if not torch.isfinite(loss):
            break
        loss.backward()
        opt.step()
        with torch.no_grad():
            alpha.clamp_(min=0.0)
            log_tau.clamp_(math.log(dt), math.log(1e3))
            log_beta.clamp_(math.log(1e-2), math.log(1e2))
    with torch.no_grad():
        model.set_parameters(log_tau.exp(), alpha.detach(), log_beta.exp())
        refined = float(_rollout_error(model, states, ctx))
    if math.isfinite(refined) and refined < best_loss:
        best, best_loss = (float(log_tau.detach().exp()), float(alpha.detach()), float(log_beta.detach().exp())), refined
    return {"tau": best[0], "alpha": best[1], "beta": best[2]}, best_loss


def fit_episode_social_force(train_states: Tensor, test_states: Tensor, dt: float, c) -> tuple[SocialForce, dict, float]:
    """Fit on ``train_states`` (truth or fused estimates) with the settings of ``c`` (``task.sfm``:
    ``desired_steps grid.{tau,alpha,beta} refine_iters refine_lr noise_std``) and return the model
    with the test episodes' desired velocities set, the parameters and the objective."""
    params, loss = fit_social_force(
        train_states, dt, int(c.desired_steps), tuple(c.grid.tau), tuple(c.grid.alpha), tuple(c.grid.beta),
        int(c.refine_iters), float(c.refine_lr),
    )
    model = episode_social_force(test_states.shape[-1] // 4, noise_std=float(c.noise_std), **params)
    model.set_desired(desired_velocity(test_states, int(c.desired_steps)))
    return model, params, loss


class FittedSocialForce(SocialForce):
    r"""The social force model whose shared :math:`(\tau, \alpha, \beta)` are fitted offline
    (``conf/model/sfm_fit.yaml``): :meth:`fit_offline` runs :func:`fit_social_force` on the
    training trajectories (true tracks or the network's estimates, ``train_on``), and
    :meth:`begin_episodes` sets each episode's desired velocities from the episodes about to be
    tracked (:func:`desired_velocity`: the velocity at t = 0 with ``desired_steps = 1``, the state
    every roll-out starts from). Before a fit: :math:`(\tau, \alpha, \beta) = (1, 0, 1)` and
    desired velocities 0."""

    learns_offline = True
    @staticmethod
    def spec_misfit(spec) -> str | None:
        """Fitted to any scenario's tracks, it needs nothing of the simulation (unlike model=sfm); but the matrix's
        protocol reads each agent's desired velocity from that agent's own measurements (:meth:`begin_measured`),
        which unlabelled detections do not tell apart."""
        if getattr(spec, "labelled", True):
            return None
        return (f"model=sfm_fit reads each agent's desired velocity from the agent's own measurements at its first "
                f"steps; scenario {spec.name} reports unlabelled detections, which do not say whose they are")

    def gradient_misfit(self) -> str | None:
        """A gradient learner leaves it alone: its desired velocities are set per episode and it fits offline."""
        return ("the fitted social force sets its desired velocities per episode and fits offline (model=sfm "
                "learns the social force's numbers)")

    @classmethod
    def for_scenario(
        cls,
        noise_std: float = 0.1,
        train_on: str | None = "truth",
        desired_steps: int = 1,
        tau_grid=TAU_GRID,
        alpha_grid=ALPHA_GRID,
        beta_grid=BETA_GRID,
        refine_iters: int = 150,
        refine_lr: float = 0.05,
        *,
        scenario,
        device=None,
    ) -> "FittedSocialForce":
        """The config factory: one agent block per agent of ``scenario``, the fit's settings
        (:func:`fit_social_force`'s arguments). ConfigError naming ``model.<key>`` for a bad value."""
        from dslearn.errors import ConfigError, check_choice, check_integer, check_positive

        if train_on is not None:
            check_choice("model.train_on", train_on, ("truth", "fused"))
        check_integer("model.desired_steps", desired_steps, 1)
        steps = getattr(scenario, "steps", None)
        if steps is not None and desired_steps > int(steps) + 1:
            raise ConfigError(f"model.desired_steps={desired_steps} must be <= the episodes' {int(steps) + 1} states")
        for name, grid, positive in (("tau_grid", tau_grid, True), ("alpha_grid", alpha_grid, False),
                                     ("beta_grid", beta_grid, True)):
            if len(list(grid)) < 1:
                raise ConfigError(f"model.{name} must list at least one value")
            for i, v in enumerate(grid):
                check_positive(f"model.{name}[{i}]", v, strict=positive)
        check_integer("model.refine_iters", refine_iters, 0)
        check_positive("model.refine_lr", refine_lr)
        model = cls([[0.0, 0.0]] * int(scenario.num_agents), 1.0, 0.0, 1.0, noise_std)
        model.train_on = train_on
        model.fit_settings = dict(desired_steps=int(desired_steps), tau_grid=tuple(float(v) for v in tau_grid),
                                  alpha_grid=tuple(float(v) for v in alpha_grid),
                                  beta_grid=tuple(float(v) for v in beta_grid), refine_iters=int(refine_iters),
                                  refine_lr=float(refine_lr))
        model.fit_info = {}
        return model.to(device)

    def fit_offline(self, trajectories: Tensor, dt: float, seed: int = 0) -> "FittedSocialForce":
        """Fit :math:`(\\tau, \\alpha, \\beta)` to ``trajectories (B, K+1, 4A)`` (deterministic: ``seed``
        is not used); ``fit_info`` = the parameters and the roll-out objective (``fit_loss``)."""
        params, loss = fit_social_force(trajectories.detach().cpu(), dt, **self.fit_settings)
        self.set_parameters(params["tau"], params["alpha"], params["beta"])
        self.fit_info = {**params, "fit_loss": loss}
        return self

    # the offline-fit cache (dslearn.learning.fit_cache)
    def fit_cache_settings(self) -> dict:
        """What besides the data and ``dt`` changes :meth:`fit_offline`: the agents, the fit's settings, the noise."""
        return {"num_agents": self.num_agents, **self.fit_settings, "noise_std": self.noise_std,
                "softening": self.softening}

    def fitted_state(self) -> dict:
        return {"fit_info": dict(self.fit_info)}

    def load_fitted_state(self, state: dict) -> "FittedSocialForce":
        info = dict(state["fit_info"])
        self.set_parameters(float(info["tau"]), float(info["alpha"]), float(info["beta"]))
        self.fit_info = info
        return self

    def begin_episodes(self, states: Tensor) -> None:
        self.set_desired(desired_velocity(states, self.fit_settings["desired_steps"]))

    def begin_measured(self, meas: Tensor, visible: Tensor, dt: float) -> None:
        """Desired velocities from the measurements alone (:func:`measured_desired_velocity`): the matrix's protocol."""
        self.set_desired(measured_desired_velocity(meas, visible, dt, self.fit_settings["desired_steps"]))
