r"""Online data-driven distributed EKF (Yu et al. Algorithm 1), vectorised over nodes and episodes."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .consensus.fusion import Fusion
from .filters.information import novel_information, predict
from .models.base import MotionModel, ObservationModel
from .sim.network import SensorNetwork
from .sim.scenario import Episodes
from .types import AGENT_DIM, StepContext, agents, safe_cholesky


@dataclass
class TrackResult:
    """Filtered beliefs of every node: ``mean (S, B, K+1, Dx)``, ``info (S, B, K+1, Dx, Dx)``."""

    mean: Tensor
    info: Tensor


def initial_belief(
    ep: Episodes,
    network: SensorNetwork,
    dt: float,
    centre: Tensor,
    prior_pos_std: float,
    prior_vel_std: float,
    pooled: bool = False,
) -> tuple[Tensor, Tensor]:
    r"""Initial state and information matrix from the first two observations (Yu et al. V-C).

    A node that saw target ``j`` at t = 0 and t = 1 uses :math:`(z^0, (z^1 - z^0)/\Delta t)` with
    information :math:`\mathrm{diag}(\sigma_\nu^{-2}, \sigma_\nu^{-2}, \Delta t^2/2\sigma_\nu^2, \Delta t^2/2\sigma_\nu^2)`;
    otherwise a weak prior (area centre, zero velocity, the given standard deviations).
    With ``pooled`` (the centralised reference) all sensors' first observations are averaged
    and every node gets that same belief.

    Returns:
        ``mean (S, B, Dx)``, ``info (S, B, Dx, Dx)``.
    """
    z0, z1 = ep.meas[:, :, 0], ep.meas[:, :, 1]  # (S, B, A, 2)
    seen = ep.visible[:, :, 0] & ep.visible[:, :, 1]  # (S, B, A)
    sig2 = network.meas_std**2
    dtype = z0.dtype
    if pooled:
        cnt = seen.sum(0, keepdim=True).to(dtype)  # (1, B, A)
        z0 = (z0 * seen.unsqueeze(-1)).sum(0, keepdim=True) / cnt.clamp_min(1).unsqueeze(-1)
        z1 = (z1 * seen.unsqueeze(-1)).sum(0, keepdim=True) / cnt.clamp_min(1).unsqueeze(-1)
        seen_w = cnt
        seen = cnt > 0
    else:
        seen_w = seen.to(dtype)
    pos = torch.where(seen.unsqueeze(-1), z0, centre.to(dtype))
    vel = torch.where(seen.unsqueeze(-1), (z1 - z0) / dt, torch.zeros_like(z0))
    mean = torch.cat([pos, vel], -1)  # (S', B, A, 4)
    dev = z0.device
    inf_seen = torch.tensor([1 / sig2, 1 / sig2, dt**2 / (2 * sig2), dt**2 / (2 * sig2)], dtype=dtype, device=dev)
    inf_weak = torch.tensor(
        [prior_pos_std**-2, prior_pos_std**-2, prior_vel_std**-2, prior_vel_std**-2], dtype=dtype, device=dev
    )
    diag = torch.where(seen.unsqueeze(-1), inf_seen * seen_w.clamp_min(1).unsqueeze(-1), inf_weak)
    mean = mean.flatten(-2)
    info = torch.diag_embed(diag.flatten(-2))
    s = network.num_nodes
    return mean.expand(s, *mean.shape[1:]).clone(), info.expand(s, *info.shape[1:]).clone()


def track(
    ep: Episodes,
    network: SensorNetwork,
    model: MotionModel,
    obs: ObservationModel,
    fusion: Fusion,
    ctx: StepContext,
    init: tuple[Tensor, Tensor],
    learn: bool = False,
    learn_gate_std: float | None = None,
    gate_prob: float | None = None,
) -> TrackResult:
    r"""Run the distributed EKF over a batch of episodes (Algorithm 1).

    Each step: local prediction (Algorithm 2 lines 2–6) at every node, novel information from
    the node's own measurements (lines 7–11), fusion (Algorithm 3 or another strategy), and —
    when ``learn`` — data-set updates: :math:`D_f \mathrel{+}= (\hat y^{t-1}, \hat y^t)`,
    :math:`D_h \mathrel{+}= (\hat y_j^t, z_{ij}^t)` for the targets node ``i`` saw.

    Args:
        ep: episodes, ``B`` of them (``B`` must be 1 when ``learn``: episodes are sequential).
        init: ``(mean (S, B, Dx), info (S, B, Dx, Dx))``.
        learn_gate_std: a node appends a pair only if its estimate at t-1 (and, for D_h, at t)
            has position standard deviation <= this for every target; ``None`` appends always
            (the paper as written). Without the gate, a node that never saw a target appends
            (vague prior -> fused estimate) pairs that corrupt its GP wherever the vague prior sits.
    """
    if learn and len(ep) != 1:
        raise ValueError("online learning runs one episode at a time")
    y, o = init
    means, infos = [y], [o]
    steps = ep.states.shape[1] - 1
    for t in range(1, steps + 1):
        y_pred, q_pred, o_pred = predict(y, o, model, ctx)
        dq, do = novel_information(y_pred, ep.meas[:, :, t], ep.visible[:, :, t], obs, gate_prob=gate_prob, omega_pred=o_pred)
        q, o = fusion(q_pred, o_pred, dq, do)
        y_new = torch.cholesky_solve(q.unsqueeze(-1), safe_cholesky(o)).squeeze(-1)
        if learn:
            ok_prev, ok_new = _informed(infos[-1], learn_gate_std), _informed(o, learn_gate_std)
            if model.learnable:
                model.add_data(y[:, 0], y_new[:, 0], ok_prev)
            if obs.learnable:
                obs.add_data(agents(y_new[:, 0]), ep.meas[:, 0, t], ep.visible[:, 0, t] & ok_new.unsqueeze(-1))
        y = y_new
        means.append(y)
        infos.append(o)
    return TrackResult(torch.stack(means, 2), torch.stack(infos, 2))


def _informed(info: Tensor, gate_std: float | None) -> Tensor:
    """``(S, 1, Dx, Dx)`` information -> ``(S,)`` bool: every target's position std <= gate."""
    s = info.shape[0]
    if gate_std is None:
        return torch.ones(s, dtype=torch.bool, device=info.device)
    var = torch.cholesky_inverse(safe_cholesky(info[:, 0])).diagonal(dim1=-2, dim2=-1)
    pos_var = var.unflatten(-1, (-1, AGENT_DIM))[..., :2]
    return (pos_var <= gate_std**2).flatten(-2).all(-1)


def tracking_metrics(res: TrackResult, truth: Tensor) -> dict[str, Tensor]:
    r"""Per node and episode: ``track_err`` (the paper's V-C formula, mean position error over
    t = 1..K and targets), ``track_rmse``, and ``nees`` (average NEES over t = 1..K divided by Dx;
    1 for a consistent filter).

    Args:
        res: beliefs ``(S, B, K+1, ...)``; truth: ``(B, K+1, Dx)``.
    Returns:
        dict of ``(S, B)`` tensors.
    """
    err = res.mean[:, :, 1:] - truth[:, 1:].unsqueeze(0)  # (S, B, K, Dx)
    perr = agents(err)[..., :2].norm(dim=-1)  # (S, B, K, A)
    nees = (err.unsqueeze(-2) @ res.info[:, :, 1:] @ err.unsqueeze(-1)).squeeze(-1).squeeze(-1)
    dx = truth.shape[-1]
    return {
        "track_err": perr.mean((-1, -2)),
        "track_rmse": perr.pow(2).mean((-1, -2)).sqrt(),
        "nees": nees.mean(-1) / dx,
    }


def prediction_error(model: MotionModel, truth: Tensor, num_nodes: int, ctx: StepContext, per_node: bool) -> Tensor:
    """Roll the model out from the true state at t = 0 (Table II): mean position error, ``(S, B)``."""
    x0 = truth[:, 0]
    steps = truth.shape[1] - 1
    if per_node:
        roll = model.rollout(x0.unsqueeze(0).expand(num_nodes, *x0.shape).contiguous(), steps, ctx)
    else:
        roll = model.rollout(x0, steps, ctx).unsqueeze(0).expand(num_nodes, -1, -1, -1)
    err = agents(roll - truth[:, 1:].unsqueeze(0))[..., :2].norm(dim=-1)
    return err.mean((-1, -2))
