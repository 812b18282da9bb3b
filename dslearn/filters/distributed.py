r"""Online data-driven distributed EKF (Yu et al. Algorithm 1), vectorised over nodes and episodes."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from dslearn.episodes import Measurements
from dslearn.fusion.strategies import Fusion
from dslearn.filters.information import PredictionStep, novel_information, predict
from dslearn.filters.smoother import transition_error_moments
from dslearn.models.base import MotionModel, ObservationModel
from dslearn.network import SensorNetwork
from dslearn.types import AGENT_DIM, StepContext, agents, safe_cholesky, spd_inverse, symmetrize


def _measurements_only(ep) -> None:
    """The filter sees measurements (:class:`~dslearn.episodes.Measurements`), never the truth."""
    if not isinstance(ep, Measurements):
        raise TypeError(f"the filter takes Measurements (episodes.measurements), not {type(ep).__name__}")


@dataclass(frozen=True)
class FilterSettings:
    """The distributed filter's options besides its prediction step (the ``filter`` group): what a node
    believes about a target before any observation (:func:`diffuse_prior`: position and velocity
    standard deviations) and the learning gate of :func:`track` (``learn_gate_std``, ``None`` = off)."""

    prior_pos_std: float = 1000.0
    prior_vel_std: float = 1000.0
    learn_gate_std: float | None = 2.0


@dataclass
class TrackResult:
    """Filtered beliefs of every node: ``mean (S, B, K+1, Dx)``, ``info (S, B, K+1, Dx, Dx)``."""

    mean: Tensor
    info: Tensor


def prior_means(num_agents: int, area) -> Tensor:
    r"""Where a node places a target it knows nothing about: ``(A, 4)``.

    Target ``j`` sits at :math:`c + r(\cos\theta_j, \sin\theta_j)`, :math:`\theta_j = 2\pi j/A`,
    with ``c`` the centre of ``area = (xmin, xmax, ymin, ymax)`` and ``r`` a sixteenth of its
    smaller side (0.5 m in an 8 m area), at zero velocity: distinct points near the centre, so
    no prior puts two targets on one point (where interaction models are at their stiffest)
    and none is further than needed from a target anywhere in the area. With near-zero
    information (:func:`diffuse_prior`) the mean only matters until a node receives
    information about the target.
    """
    x0, x1, y0, y1 = (float(v) for v in area)
    r = min(x1 - x0, y1 - y0) / 16
    th = 2 * math.pi * torch.arange(num_agents, dtype=torch.float64) / num_agents
    pos = torch.stack([(x0 + x1) / 2 + r * th.cos(), (y0 + y1) / 2 + r * th.sin()], -1)
    return torch.cat([pos, torch.zeros_like(pos)], -1)


def diffuse_prior(
    num_agents: int, area, pos_std: float, vel_std: float, shape: tuple[int, ...], dtype, device
) -> tuple[Tensor, Tensor]:
    """The belief before any observation: :func:`prior_means` with information
    ``diag(pos_std^-2, pos_std^-2, vel_std^-2, vel_std^-2)`` per target (near zero for the
    default 1 km, 1 km/s). Returns ``mean (*shape, Dx)``, ``info (*shape, Dx, Dx)``."""
    mean = prior_means(num_agents, area).to(device, dtype).flatten()
    d = torch.tensor([pos_std**-2, pos_std**-2, vel_std**-2, vel_std**-2], dtype=dtype, device=device).repeat(num_agents)
    info = torch.diag_embed(d)
    return mean.expand(*shape, -1).clone(), info.expand(*shape, -1, -1).clone()


def first_observations(ep: Measurements, network: SensorNetwork, dt: float) -> tuple[Tensor, Tensor]:
    r"""Each node's pseudo-measurement of the initial state from its first two observations
    (Yu et al. V-C), in information form.

    A node that saw target ``j`` at t = 0 and t = 1 contributes :math:`\hat y_j^0 = (z^0, (z^1 - z^0)/\Delta t)`
    with information :math:`\Omega_j = \mathrm{diag}(\sigma_\nu^{-2}, \sigma_\nu^{-2}, \Delta t^2/2\sigma_\nu^2, \Delta t^2/2\sigma_\nu^2)`
    (the paper's :math:`\Omega^0`); any other node contributes zero information about ``j``.

    Returns:
        ``dq (S, B, Dx)``, ``domega (S, B, Dx, Dx)``.
    """
    z0, z1 = ep.meas[:, :, 0], ep.meas[:, :, 1]  # (S, B, A, 2)
    seen = (ep.visible[:, :, 0] & ep.visible[:, :, 1]).to(z0.dtype).unsqueeze(-1)  # (S, B, A, 1)
    sig2 = network.meas_std**2
    y0 = torch.cat([z0, (z1 - z0) / dt], -1)  # (S, B, A, 4)
    w = torch.tensor([1 / sig2, 1 / sig2, dt**2 / (2 * sig2), dt**2 / (2 * sig2)], dtype=z0.dtype, device=z0.device)
    diag = w * seen  # (S, B, A, 4)
    return (diag * y0).flatten(-2), torch.diag_embed(diag.flatten(-2))


#: a start the scenario declares known to its navigators (Braga's aircraft: ``scenario.initial_states()``) is believed
#: to within this standard deviation, in metres for a position and metres per second for a velocity (the
#: information filter needs finite information; the particle filters start every particle there)
KNOWN_START_STD = 1.0
#: Gauss-Newton iterations of the first fix of a nonlinear sensor (:func:`first_fix`)
FIX_ITERATIONS = 20


def known_start(start: Tensor, shape: tuple[int, ...], std: float = KNOWN_START_STD) -> tuple[Tensor, Tensor]:
    """The belief at a known start ``(A, d)`` (every target's block): ``mean (*shape, A d)``, information
    ``std^-2 I`` (``*shape, A d, A d``)."""
    mean = start.flatten()
    info = torch.diag_embed(torch.full_like(mean, std**-2))
    return mean.expand(*shape, -1).clone(), info.expand(*shape, -1, -1).clone()


def _iterated_update(ep: Measurements, t: int, obs: ObservationModel, fusion: Fusion, mean: Tensor, q0: Tensor,
                     o0: Tensor, iterations: int) -> tuple[Tensor, Tensor]:
    r"""The iterated extended information update of the prior ``(q0, o0)`` with the readings at step ``t``
    (Gauss-Newton on the posterior mode): linearised at the current mean, fused, solved, ``iterations`` times."""
    o = o0
    for _ in range(iterations):
        dq, do = novel_information(mean, ep.meas[:, :, t], ep.visible[:, :, t], obs)
        q, o = fusion(q0, o0, dq, do)
        o = symmetrize(o)
        mean = torch.cholesky_solve(q.unsqueeze(-1), safe_cholesky(o)).squeeze(-1)
    return mean, o


def first_fix(ep: Measurements, dt: float, fusion: Fusion, obs: ObservationModel, m0: Tensor, o0: Tensor,
              iterations: int = FIX_ITERATIONS) -> tuple[Tensor, Tensor]:
    r"""The first belief from a nonlinear sensor's first two readings (squared ranges, ranges, ...), the analogue of
    :func:`first_observations`: from the diffuse prior ``(m0, o0)`` the iterated update (:func:`_iterated_update`,
    with the run's fusion) fixes every target's position at ``t = 0`` (:math:`p^0`, covariance :math:`P^0`) and at
    ``t = 1`` (:math:`p^1`, :math:`P^1`); the belief is :math:`(p^0, (p^1 - p^0)/\Delta t)` with the position's
    information :math:`(P^0)^{-1}` and the velocity's :math:`(\Delta t^2) (P^0 + P^1)^{-1}` (the cross-covariance
    left out, as in Yu et al.'s initialisation), for target blocks ``[px, py, vx, vy]``; a block of two entries
    (a position alone) takes :math:`p^0`, :math:`(P^0)^{-1}`. Where the fusion gives a node too little to fix a
    position (one range alone) its fix is as vague as its readings make it."""
    a = ep.meas.shape[-2]
    q0 = (o0 @ m0.unsqueeze(-1)).squeeze(-1)
    p_mean0, o_0 = _iterated_update(ep, 0, obs, fusion, m0, q0, o0, iterations)
    p_mean1, o_1 = _iterated_update(ep, 1, obs, fusion, p_mean0, q0, o0, iterations)
    d = m0.shape[-1] // a
    pos = torch.arange(a, device=m0.device).unsqueeze(-1) * d + torch.arange(2, device=m0.device)  # (A, 2)

    def pos_cov(o):  # (S, B, A, 2, 2): every target's position block of o^-1
        P = torch.cholesky_inverse(safe_cholesky(o))
        return P[..., pos.unsqueeze(-1), pos.unsqueeze(-2)]

    P0, P1 = pos_cov(o_0), pos_cov(o_1)
    x0 = agents_of(p_mean0, a)[..., :2]
    x1 = agents_of(p_mean1, a)[..., :2]
    mean = agents_of(m0, a).clone()
    mean[..., :2] = x0
    blocks = torch.zeros(*mean.shape, d, dtype=m0.dtype, device=m0.device)
    blocks[..., :2, :2] = spd_inverse(P0)
    if d >= 4:
        mean[..., 2:4] = (x1 - x0) / dt
        blocks[..., 2:4, 2:4] = spd_inverse(P0 + P1) * dt**2
        idx = torch.arange(4, d, device=m0.device)  # entries beyond [p, v]: the (diagonal) diffuse prior's
        blocks[..., idx, idx] = o0.diagonal(dim1=-2, dim2=-1).unflatten(-1, (a, d))[..., 4:]
    info = torch.zeros(*mean.shape[:-2], a * d, a * d, dtype=m0.dtype, device=m0.device)
    for j in range(a):
        info[..., j * d:(j + 1) * d, j * d:(j + 1) * d] = blocks[..., j, :, :]
    return mean.flatten(-2), symmetrize(info)


def agents_of(x: Tensor, num_agents: int) -> Tensor:
    """A joint state ``(*B, A d)`` as ``(*B, A, d)`` (a view)."""
    return x.unflatten(-1, (num_agents, -1))


def initial_belief(
    ep: Measurements,
    network: SensorNetwork,
    dt: float,
    fusion: Fusion,
    area,
    prior_pos_std: float = 1000.0,
    prior_vel_std: float = 1000.0,
    obs: ObservationModel | None = None,
    start: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    r"""Initial belief of every node: the diffuse prior fused with the first observations.

    One rule for every fusion strategy: each node starts from :func:`diffuse_prior` (near-zero
    information, distinct means), adds the novel information of its own first two observations
    (:func:`first_observations`) and fuses like at any other step: ``individual`` keeps its
    own (the paper's initialisation where the node saw the target), consensus spreads it to
    the nodes that did not, ``centralized`` sums every sensor's. A node that learns nothing
    about a target keeps the diffuse prior, finite and uninformative (a learning gate,
    ``filter.learn_gate_std``, keeps such estimates out of its data set).

    A sensor that does not measure positions (``obs.measures_position`` false: squared ranges, the terrain
    altitude) gives no first observations of that kind: every node starts at the scenario's known ``start``
    (``(A, d)``, :func:`known_start`) where the scenario declares one (Braga's aircraft), else from the first fix of
    its first two readings fused with the run's fusion (:func:`first_fix`).

    Returns:
        ``mean (S, B, Dx)``, ``info (S, B, Dx, Dx)``.
    """
    _measurements_only(ep)
    s, b = network.num_nodes, len(ep)
    a = ep.meas.shape[-2]
    if obs is not None and not obs.measures_position:
        if start is not None:
            return known_start(start.to(ep.meas.device, ep.meas.dtype), (s, b))
        m0, o0 = diffuse_prior(a, area, prior_pos_std, prior_vel_std, (s, b), ep.meas.dtype, ep.meas.device)
        return first_fix(ep, dt, fusion, obs, m0, o0)
    m0, o0 = diffuse_prior(a, area, prior_pos_std, prior_vel_std, (s, b), ep.meas.dtype, ep.meas.device)
    q0 = (o0 @ m0.unsqueeze(-1)).squeeze(-1)
    dq, do = first_observations(ep, network, dt)
    q, o = fusion(q0, o0, dq, do)
    o = symmetrize(o)
    mean = torch.cholesky_solve(q.unsqueeze(-1), safe_cholesky(o)).squeeze(-1)
    return mean, o


def associated_belief(ep: Measurements, fusion: Fusion, start: tuple[Tensor, Tensor], associate,
                      obs: ObservationModel) -> tuple[Tensor, Tensor]:
    r"""The initial belief of every node from unlabelled detections: the targets' declared start (``start``: mean
    ``(A, d)``, covariance ``(A, d, d)``, the scenario's :meth:`start_prior`) as every node's prior, updated by
    its own detections at ``t = 0`` associated with it (``associate``, as at any step of :func:`track`) and fused.
    Returns ``mean (S, B, Dx)``, ``info (S, B, Dx, Dx)``."""
    _measurements_only(ep)
    s, b = ep.meas.shape[:2]
    mean0, cov0 = (x.to(ep.meas.device, ep.meas.dtype) for x in start)
    a, d = mean0.shape
    info_blocks = spd_inverse(cov0)
    info = torch.zeros(a * d, a * d, dtype=mean0.dtype, device=mean0.device)
    for j in range(a):
        info[j * d:(j + 1) * d, j * d:(j + 1) * d] = info_blocks[j]
    y0 = mean0.flatten().expand(s, b, -1).clone()
    o0 = symmetrize(info).expand(s, b, -1, -1).clone()
    q0 = (o0 @ y0.unsqueeze(-1)).squeeze(-1)
    meas0, vis0, lin = associate(y0, o0, ep.meas[:, :, 0], ep.visible[:, :, 0], obs, None)
    dq, do = novel_information(y0, meas0, vis0, obs, omega_pred=o0, linearized=lin)
    q, o = fusion(q0, o0, dq, do)
    o = symmetrize(o)
    return torch.cholesky_solve(q.unsqueeze(-1), safe_cholesky(o)).squeeze(-1), o


def track(
    ep: Measurements,
    network: SensorNetwork,
    model: MotionModel,
    obs: ObservationModel,
    fusion: Fusion,
    ctx: StepContext,
    init: tuple[Tensor, Tensor],
    learn: bool = False,
    learn_gate_std: float | None = None,
    gate_prob: float | None = None,
    predict_step: PredictionStep | None = None,
    associate=None,
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
        predict_step: the filter's prediction step (``filter.predict``, a
            :class:`~dslearn.filters.information.PredictionStep`: EKF linearisation, the
            default, or :class:`~dslearn.filters.ukf.UnscentedPredict`), called like
            :func:`~dslearn.filters.information.predict`. The unscented one also linearises a nonlinear
            sensor statistically (its ``observation_linearization``: the UKF's update); with a linear or
            learned observation model the update is the extended one.
        associate: unlabelled detections (``ep.meas (S, B, K+1, M, .)``, ``ep.visible`` the present ones): each
            node's detections associated with its predicted tracks, as one pseudo-measurement per track
            (:class:`~dslearn.association.network.NodeAssociation`; its ``num_tracks`` targets), then the same
            update and fusion. ``None``: the measurements are labelled (slot ``j`` is target ``j``).
    """
    _measurements_only(ep)
    if learn and len(ep) != 1:
        raise ValueError("online learning runs one episode at a time")
    y, o = init
    means, infos = [y], [o]
    steps = ep.steps
    adapt = learn and bool(getattr(model, "adapts_noise", False))
    pred_log = []  # (y_pred, P_pred, F, Q) per step, for the process-noise EM step
    informed = torch.ones(network.num_nodes, dtype=torch.bool, device=ep.meas.device)
    # the UKF's measurement step for a nonlinear sensor that learns nothing (the linear sensor: the same update)
    slr = getattr(predict_step, "observation_linearization", None)
    if obs.linear or obs.learnable:
        slr = None
    # a fusion centre (every node holds the centre's belief): the prediction runs once, at node 0, and every node
    # receives it; a motion model with per-node state is then built for one node (its num_nodes: 1)
    s_all = y.shape[0]
    k = 1 if one_belief(fusion, model, s_all) else s_all
    centre = (lambda v: v[:1]) if k < s_all else (lambda v: v)  # the nodes the model predicts for and learns from
    for t in range(1, steps + 1):
        y_pred, q_pred, o_pred, *pq = (predict_step or predict)(centre(y), centre(o), model, ctx, full=adapt)
        if adapt:
            pred_log.append((y_pred[:, 0], *(m[:, 0] for m in pq)))
        if k < s_all:
            y_pred, q_pred, o_pred = (v.expand(s_all, *v.shape[1:]).clone() for v in (y_pred, q_pred, o_pred))
        if associate is None:
            meas_t, vis_t = ep.meas[:, :, t], ep.visible[:, :, t]
            lin = slr(obs, y_pred, o_pred, ep.meas.shape[-2]) if slr is not None else None
        else:
            lin = slr(obs, y_pred, o_pred, associate.num_tracks) if slr is not None else None
            meas_t, vis_t, lin = associate(y_pred, o_pred, ep.meas[:, :, t], ep.visible[:, :, t], obs, lin)
        dq, do = novel_information(y_pred, meas_t, vis_t, obs, gate_prob=gate_prob,
                                   omega_pred=o_pred, linearized=lin)
        q, o = fusion(q_pred, o_pred, dq, do)
        y_new = torch.cholesky_solve(q.unsqueeze(-1), safe_cholesky(o)).squeeze(-1)
        if learn:
            ok_prev, ok_new = _informed(infos[-1], learn_gate_std), _informed(o, learn_gate_std)
            if adapt:
                informed &= ok_prev & ok_new & _informed(o, DIFFUSE_GUARD_STD)
            if model.learnable:
                model.add_data(centre(y)[:, 0], centre(y_new)[:, 0], centre(ok_prev))
            if obs.learnable:
                obs.add_data(agents(y_new[:, 0]), meas_t[:, 0], vis_t[:, 0] & ok_new.unsqueeze(-1))
        y = y_new
        means.append(y)
        infos.append(o)
    if adapt:  # EM step for the process noise: smooth the episode, expected transition errors
        m_f = centre(torch.stack(means, 2))[:, 0]
        P_f = torch.cholesky_inverse(safe_cholesky(centre(torch.stack(infos, 2))[:, 0]))
        yp, Pp, Fj, Qu = (torch.stack(v, 1) for v in zip(*pred_log))
        model.update_noise(transition_error_moments(m_f, P_f, yp, Pp, Fj), Qu, centre(informed))
    return TrackResult(torch.stack(means, 2), torch.stack(infos, 2))


def one_belief(fusion, model, num_nodes: int) -> bool:
    """Whether every node holds one belief that the filter predicts once: a fusion centre (:attr:`Fusion.centre`; not
    a wrapper such as a faulty network's, whose nodes may differ) and a motion model with no per-node state or
    state for one node (its ``num_nodes``)."""
    return (num_nodes > 1 and isinstance(fusion, Fusion) and fusion.centre
            and getattr(model, "num_nodes", 1) == 1)


#: a node whose position std for some target exceeds this (m) still holds (about) the diffuse
#: prior: its estimates carry nothing to learn the process noise from, whatever the learning gate
DIFFUSE_GUARD_STD = 10.0


def _informed(info: Tensor, gate_std: float | None) -> Tensor:
    """``(S, 1, Dx, Dx)`` information -> ``(S,)`` bool: every target's position std <= gate."""
    s = info.shape[0]
    if gate_std is None:
        return torch.ones(s, dtype=torch.bool, device=info.device)
    var = torch.cholesky_inverse(safe_cholesky(info[:, 0])).diagonal(dim1=-2, dim2=-1)
    pos_var = var.unflatten(-1, (-1, AGENT_DIM))[..., :2]
    return (pos_var <= gate_std**2).flatten(-2).all(-1)
