r"""The factor-graph identification (Jiang et al. 2022, Sec. III-A) of a motion model from position measurements,
and the Kalman filter that tracks with the identified model: the position-sensor form of the FG family.

The model, per target (state :math:`x = [p_x, p_y, v_x, v_y]`, step ``dt``):

.. math::  x_{k+1} = F(a)\, x_k + w_k, \qquad F(a) = \begin{bmatrix} I & dt\, I \\ 0 & a I \end{bmatrix},
           \qquad w_k \sim \mathcal N(0, q\, G G^T), \quad G = \begin{bmatrix} dt^2/2\, I \\ dt\, I \end{bmatrix},

a constant-velocity model whose velocity keeps the share ``a`` per step (``a = 1``: constant velocity,
``a < 1``: damped), its transition linear in ``a``, driven by white acceleration of intensity ``q``. The parameters
identified are :math:`\theta = (a, \ln q)`. Every node that sees target ``i`` at step ``k`` measures its position
with noise :math:`\mathcal N(0, \sigma^2 I)` (the scenario's sensors); the ``n`` measurements of one target at one
step enter as their mean with covariance :math:`\sigma^2/n\, I` (the same information: the nodes' noise is equal
and isotropic). A node that does not see the target adds nothing; a step no node sees is a prediction alone.

Identification (prediction-error form): a Kalman filter runs through every training track with :math:`\theta`,
from the diffuse prior at the target's prior point, and takes the two coordinates of each fused measurement one
after the other (scalar updates), so its innovations are independent Gaussians
:math:`y_n - h_n(\theta) \sim \mathcal N(0, s_n)`: :math:`y_n` the measured coordinate, :math:`h_n(\theta)` the
filter's prediction of it, :math:`s_n` the innovation variance. A round expands every :math:`h_n` at the current
estimate :math:`\beta` (Eqs. 6-9; the slopes by the filter's recursions differentiated alongside it). Each
training track (a target of a training episode) is then a measurement node ``D_g`` of the factor graph (Fig. 1,
upper part): as the paper's sensor compresses its samples into one Gaussian message, the track compresses its
linearised innovations into theirs (:func:`track_messages`), and the fusion centre iterates the Gaussian messages
of Eqs. 11-16 (:func:`~dslearn.learning.factor_graph.identification.identify`, the messages of Jiang's
identification) from :math:`\beta`. Their output is the next estimate, halved towards :math:`\beta` until the
criterion :math:`\sum_n (y_n - h_n(\theta))^2 / s_n(\beta)` does not grow. Rounds stop when the estimate moves by
less than ``converge_tol`` or after ``rounds``. On a model linear in :math:`\theta` one round's converged messages
give the batch Gaussian (weighted least-squares) posterior of :math:`\theta`.

Shapes: ``G`` tracks (training episode x target), ``T = K + 1`` steps.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from dslearn.learning.factor_graph.identification import identify
from dslearn.learning.factor_graph.messages import LinearMeasurement
from dslearn.types import symmetrize

#: the parameters identified, in order
PARAMETERS = ("a", "log_q")


def transition(theta: Tensor, dt: float) -> Tensor:
    """``F(a)`` ``(4, 4)`` of ``theta = (a, ln q)`` (linear in ``a``)."""
    z = torch.zeros((), dtype=theta.dtype, device=theta.device)
    one, d, a = z + 1.0, z + float(dt), theta[0]
    return torch.stack([torch.stack([one, z, d, z]), torch.stack([z, one, z, d]),
                        torch.stack([z, z, a, z]), torch.stack([z, z, z, a])])


def process_cov(theta: Tensor, dt: float) -> Tensor:
    """``Q = q G G^T`` ``(4, 4)``, ``q = exp(theta[1])`` (white acceleration)."""
    g = torch.tensor([[dt * dt / 2, 0.0], [0.0, dt * dt / 2], [dt, 0.0], [0.0, dt]], dtype=theta.dtype,
                     device=theta.device)
    return theta[1].exp() * (g @ g.T)


def fuse(meas: Tensor, visible: Tensor) -> tuple[Tensor, Tensor]:
    """The nodes' measurements of each target at each step as their mean and count.

    Args:
        meas: ``(S, B, T, A, 2)``; visible: ``(S, B, T, A)`` bool.

    Returns:
        ``z (B*A, T, 2)`` (zero where no node sees the target) and ``n (B*A, T)`` the number of nodes that see it.
    """
    v = visible.to(meas.dtype)
    n = v.sum(0)                                                  # (B, T, A)
    z = (meas * v[..., None]).sum(0) / n.clamp_min(1.0)[..., None]
    b, t, a = n.shape
    return z.permute(0, 2, 1, 3).reshape(b * a, t, 2), n.permute(0, 2, 1).reshape(b * a, t)


def truth_tracks(states: Tensor, num_agents: int, noise_std: float = 0.0,
                 generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
    """The true positions of every agent of ``states (B, T, 4A)`` as one measurement per step: ``z (B*A, T, 2)`` and
    ``n (B*A, T)`` (1; 0 where the truth is not finite), the layout of :func:`fuse`; ``noise_std > 0`` adds
    ``N(0, noise_std^2)`` per coordinate drawn from ``generator`` (CPU, float64), the measurements' declared noise."""
    b, t, _ = states.shape
    pos = states.unflatten(-1, (int(num_agents), -1))[..., :2].permute(0, 2, 1, 3).reshape(b * int(num_agents), t, 2)
    ok = torch.isfinite(pos).all(-1)
    if noise_std > 0.0:
        pos = pos + float(noise_std) * torch.randn(pos.shape, generator=generator, dtype=torch.float64).to(pos)
    return torch.where(ok[..., None], pos, torch.zeros_like(pos)), ok.to(pos.dtype)


@dataclass
class KalmanPass:
    """One pass of the Kalman filter over ``G`` tracks.

    Attributes:
        pred: ``(G, T, 2)`` each coordinate's prediction before its scalar update (``h_n``).
        var: ``(G, T, 2)`` its innovation variance (``s_n``).
        mean: ``(G, T, 4)`` filtered means; cov: ``(G, T, 4, 4)`` their covariances.
        slopes: ``(G, T, 2, 2)`` the derivatives of ``pred`` with respect to ``theta`` (``None`` unless asked).
    """

    pred: Tensor
    var: Tensor
    mean: Tensor
    cov: Tensor
    slopes: Tensor | None = None


def _sym(p: Tensor) -> Tensor:
    """Symmetric part over the two state dimensions ``(G, 4, 4, ...)``."""
    return 0.5 * (p + p.transpose(1, 2))


def kalman(theta: Tensor, z: Tensor, n: Tensor, dt: float, sigma: float, m0: Tensor, p0: Tensor,
           slopes: bool = False) -> KalmanPass:
    """The Kalman filter of the model ``theta`` over the fused measurements ``z (G, T, 2)``, counts ``n (G, T)``
    (a step with ``n = 0`` is a prediction alone), from ``m0 (G, 4)``, ``p0 (G, 4, 4)`` at ``t = 0``; sensor noise
    ``sigma`` per node and coordinate. ``slopes``: also the exact derivatives of the predictions with respect to
    ``theta`` (the filter's recursions differentiated alongside, forward mode: Eq. 8's slopes)."""
    F, Q = transition(theta, dt), process_cov(theta, dt)
    r = float(sigma) ** 2 / n.clamp_min(1.0)                     # (G, T) the fused measurement's variance
    seen = n > 0
    x, P = m0, p0
    g, m = m0.shape[0], theta.shape[0]
    if slopes:  # tangents: d/dtheta of x (G, 4, M) and P (G, 4, 4, M); dF/da = diag(0, 0, 1, 1), dQ/d(ln q) = Q
        dF = theta.new_zeros(4, 4, m)
        dF[2, 2, 0] = dF[3, 3, 0] = 1.0
        dQ = torch.stack([torch.zeros_like(Q), Q], -1)
        dx, dP = m0.new_zeros(g, 4, m), p0.new_zeros(g, 4, 4, m)
    preds, variances, means, covs, ders = [], [], [], [], []
    for t in range(z.shape[1]):
        if t > 0:
            if slopes:
                dx = torch.einsum("ij,gjm->gim", F, dx) + torch.einsum("ijm,gj->gim", dF, x)
                fpd = torch.einsum("ijm,gjk,lk->gilm", dF, P, F)
                dP = torch.einsum("ij,gjkm,lk->gilm", F, dP, F) + fpd + fpd.transpose(1, 2) + dQ
            x = x @ F.T
            P = symmetrize(F @ P @ F.T + Q)
        pt, st, dt_ = [], [], []
        for c in range(2):
            s = P[:, c, c] + r[:, t]
            gain = P[:, :, c] / s[:, None]                       # (G, 4)
            hx = x[:, c]
            innov = z[:, t, c] - hx
            upd = seen[:, t]
            pt.append(hx)
            st.append(s)
            if slopes:
                dt_.append(dx[:, c])
                ds = dP[:, c, c]                                  # (G, M)
                dgain = dP[:, :, c] / s[:, None, None] - P[:, :, c, None] * (ds / s[:, None].square())[:, None]
                dx_new = dx + dgain * innov[:, None, None] - gain[:, :, None] * dx[:, c][:, None, :]
                dgg = dgain[:, :, None] * gain[:, None, :, None]
                dP_new = dP - (dgg + dgg.transpose(1, 2)) * s[:, None, None, None] \
                    - (gain[:, :, None] * gain[:, None, :])[..., None] * ds[:, None, None]
                dx = torch.where(upd[:, None, None], dx_new, dx)
                dP = torch.where(upd[:, None, None, None], dP_new, dP)
            x = torch.where(upd[:, None], x + gain * innov[:, None], x)
            P = torch.where(upd[:, None, None], P - gain[:, :, None] * gain[:, None, :] * s[:, None, None], P)
        P = symmetrize(P)
        if slopes:
            dP = _sym(dP)
            ders.append(torch.stack(dt_, 1))
        preds.append(torch.stack(pt, -1))
        variances.append(torch.stack(st, -1))
        means.append(x)
        covs.append(P)
    return KalmanPass(torch.stack(preds, 1), torch.stack(variances, 1), torch.stack(means, 1), torch.stack(covs, 1),
                      torch.stack(ders, 1) if slopes else None)


@dataclass
class MotionIdentification:
    """What :func:`identify_motion` found.

    Attributes:
        theta: ``(2,)`` the identified ``(a, ln q)``; var: ``(2,)`` the factor graph's marginal variances of the
            last round (at its expansion point).
        path: ``(R+1, 2)`` the estimate after rounds ``0..R`` (0 = the initial guess).
        criterion: ``(R+1,)`` :math:`\\sum_n (y_n - h_n)^2 / s_n` at each estimate of ``path`` (its own ``s``).
        rows: the innovations used (measurement nodes of the factor graph).
    """

    theta: Tensor
    var: Tensor
    path: Tensor
    criterion: Tensor
    rows: int


def track_messages(lam: Tensor, y: Tensor, s: Tensor, track: Tensor, num_tracks: int) -> tuple[Tensor, Tensor]:
    r"""Each track's measurement node: the Gaussian message on :math:`\theta` of its linearised innovations
    :math:`y_n = \lambda_n^T \theta + u_n`, :math:`u_n \sim \mathcal N(0, s_n)` (information
    :math:`\Lambda_g = \sum_n \lambda_n \lambda_n^T / s_n`, :math:`\eta_g = \sum_n \lambda_n y_n / s_n`), as ``M``
    scalar observations of unit variance along the eigenvectors of :math:`\Lambda_g`: slopes
    :math:`\sqrt{d_j} v_j` and values :math:`v_j^T \eta_g / \sqrt{d_j}` (a direction the track does not inform:
    slope 0, a flat message). Their information sums to the track's, exactly.

    Args:
        lam: ``(N, M)`` slopes; y: ``(N,)`` values (the offsets moved into them); s: ``(N,)`` variances;
        track: ``(N,)`` each row's track in ``0..num_tracks-1``.

    Returns:
        slopes ``(num_tracks * M, M)`` and values ``(num_tracks * M,)``.
    """
    m = lam.shape[-1]
    w = lam / s[:, None]
    info = lam.new_zeros(num_tracks, m, m).index_add_(0, track, w[:, :, None] * lam[:, None, :])
    vec = lam.new_zeros(num_tracks, m).index_add_(0, track, w * y[:, None])
    d, v = torch.linalg.eigh(symmetrize(info))                  # (G, M), (G, M, M): columns v_j
    keep = d > d.amax(-1, keepdim=True).clamp_min(0.0) * 1e-12 + torch.finfo(d.dtype).tiny
    root = d.clamp_min(0.0).sqrt()
    slopes = torch.where(keep[..., None], (v * root[:, None, :]).transpose(-1, -2), torch.zeros_like(v))
    proj = (v * vec[:, :, None]).sum(-2)                        # v_j^T eta, (G, M)
    values = torch.where(keep, proj / torch.where(keep, root, torch.ones_like(root)), torch.zeros_like(proj))
    return slopes.reshape(-1, m), values.reshape(-1)


def identify_motion(z: Tensor, n: Tensor, dt: float, sigma: float, m0: Tensor, p0: Tensor, init_guess, *,
                    iterations: int, rounds: int, init_var: float, prior_var: float, schedule: str, damping: float,
                    graph: str, lambda_tol: float, converge_tol: float, max_halvings: int = 30) -> MotionIdentification:
    """Identify ``theta = (a, ln q)`` from the training tracks' fused measurements by the factor graph's messages
    (the module's docstring).

    Args:
        z, n: ``(G, T, 2)``, ``(G, T)`` from :func:`fuse`; m0, p0: the filter's start per track.
        dt: the scenario's step; sigma: its sensors' noise std (per node and coordinate).
        init_guess: the first expansion point ``(a, ln q)``.
        iterations: message-passing iterations per round; rounds: the most rounds (re-expansions).
        init_var, prior_var, schedule, damping, graph, lambda_tol: the messages' settings
            (:func:`~dslearn.learning.factor_graph.identification.identify`); ``prior_var`` centres a prior node on
            each round's expansion point (``inf``: none).
        converge_tol: the rounds stop once the estimate moves by less (max abs change).
        max_halvings: the most halvings of a step that would let the criterion grow (then the rounds stop); a step
            halved below ``converge_tol`` stops them too (the estimate stays where it is).
    """
    dtype, device = z.dtype, z.device
    seen = (n > 0)[..., None].expand(*n.shape, 2).reshape(-1)
    idx = seen.nonzero().squeeze(-1)
    y = z.reshape(-1)[idx]
    track, num_tracks = torch.div(idx, 2 * z.shape[1], rounding_mode="floor"), z.shape[0]
    beta = torch.as_tensor([float(v) for v in init_guess], dtype=dtype, device=device)
    if idx.numel() == 0:
        return MotionIdentification(beta, torch.full_like(beta, float("inf")), beta[None], beta.new_zeros(1), 0)

    def rows(th, slopes=False):
        kp = kalman(th, z, n, dt, sigma, m0, p0, slopes=slopes)
        lam = kp.slopes.reshape(-1, th.shape[0])[idx] if slopes else None
        return kp.pred.reshape(-1)[idx], kp.var.reshape(-1)[idx], lam

    path, crit, var = [beta], [], torch.full_like(beta, float(init_var))
    for _ in range(int(rounds)):
        h0, s, lam = rows(beta, slopes=True)                      # lam (N, 2): the slopes of Eq. 8 at beta
        j0 = float(((y - h0).square() / s).sum())
        crit.append(j0)
        slopes, values = track_messages(lam, y - h0 + lam @ beta, s, track, num_tracks)
        ident = identify(LinearMeasurement(slopes), values, torch.ones_like(values), beta, beta, int(iterations),
                         init_var=init_var,
                         prior_var=prior_var, relinearize=False, lambda_tol=lambda_tol, tol=converge_tol,
                         schedule=schedule, damping=damping, graph=graph)
        step, var = ident.mean[-1] - beta, ident.var[-1]
        if not bool(torch.isfinite(step).all()):
            break
        new = None
        for _h in range(int(max_halvings) + 1):
            if float(step.abs().max()) < converge_tol:  # a step shorter than the tolerance: converged where it is
                break
            hc = rows(beta + step)[0]
            if float(((y - hc).square() / s).sum()) <= j0:
                new = beta + step
                break
            step = step / 2
        if new is None:
            break
        moved = float((new - beta).abs().max())
        beta = new
        path.append(beta)
        if moved < converge_tol:
            break
    if len(crit) < len(path):
        h0, s, _ = rows(beta)
        crit.append(float(((y - h0).square() / s).sum()))
    return MotionIdentification(beta, var, torch.stack(path), torch.as_tensor(crit, dtype=dtype), int(idx.numel()))
