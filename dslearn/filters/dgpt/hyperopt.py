r"""Hyperparameter learning for the batched DGPT experts: one independent problem per
(episode, pipeline, coordinate).

The shared SE-kernel hyperparameters of a pipeline and coordinate are a vector
``theta`` of length ``d + 2`` (last axis),

.. math:: \theta = (\log\sigma_m^2,\ \log\ell_1, \dots, \log\ell_d,\ \log\sigma^2),

kept inside a box :math:`[\theta_{lo}, \theta_{hi}]` (:func:`bounds`; the noise variance's lower
bound is ``min_noise``). The box matters where the likelihood has no finite maximiser (e.g. it
keeps increasing as a length scale grows, when the data cannot distinguish a constant from a
slowly varying function): there the solvers stop at the bound instead of drifting along a flat
ridge. Leading axes of ``theta`` are *problems*: nothing in this module couples two problems,
so a problem's result does not depend on which other problems share its batch (batch dims
first, elementwise control flow via masks).

* :func:`log_marginal_likelihood` — the factorised log marginal likelihood (Eq. 15, summed over
  the expert axis) of padded windows in closed form (batched Cholesky), with its exact gradient
  and Hessian with respect to ``theta`` (analytic, no autograd; tested against GPyTorch's
  ``ExactMarginalLogLikelihood`` and against autograd).
* :class:`ElementwiseAdam` — Adam (PyTorch's update rule) with per-problem moment estimates and
  per-problem step counters, updating only the problems selected at each call.
* :func:`newton_maximise` — projected trust-region Newton (eigenvalue-modified, saddle-free
  Hessian) per problem, iterated until the largest projected gradient component is below
  ``tol``, or ``max_iters``.
* :class:`Posterior` — the GP posterior (Eqs. 5-6) of padded windows for given ``theta``.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from enum import Enum
from typing import Callable

import torch
from torch import Tensor

from dslearn.models.kernels import se

LOG_2PI = math.log(2.0 * math.pi)


def n_params(d: int) -> int:
    """Length of ``theta`` for input dimension ``d``."""
    return d + 2


def bounds(d: int, min_noise: float, outputscale=(1e-6, 1e8), lengthscale=(1e-3, 1e3),
           max_noise: float = 1e8, dtype=torch.float64, device="cpu"):
    """Box ``(lo, hi)`` for ``theta`` (each ``(d + 2,)``), natural units: outputscale [m^2],
    length scales [s or m], noise variance in ``[min_noise, max_noise]`` [m^2]."""
    lo = [math.log(outputscale[0])] + [math.log(lengthscale[0])] * d + [math.log(min_noise)]
    hi = [math.log(outputscale[1])] + [math.log(lengthscale[1])] * d + [math.log(max_noise)]
    return (torch.tensor(lo, dtype=dtype, device=device), torch.tensor(hi, dtype=dtype, device=device))


def init_theta(batch_shape, d: int, outputscale: float, lengthscales, noise: float,
               dtype=torch.float64, device="cpu") -> Tensor:
    """Initial ``theta`` of shape ``(*batch_shape, d + 2)``."""
    ls = torch.as_tensor(lengthscales, dtype=dtype, device=device).reshape(d)
    vec = torch.cat([torch.tensor([math.log(outputscale)], dtype=dtype, device=device), ls.log(),
                     torch.tensor([math.log(noise)], dtype=dtype, device=device)])
    return vec.expand(*batch_shape, d + 2).clone()


def unpack(theta: Tensor):
    """``theta`` -> (outputscale ``(...)``, lengthscales ``(..., d)``, noise variance ``(...)``)."""
    return theta[..., 0].exp(), theta[..., 1:-1].exp(), theta[..., -1].exp()


def values(theta: Tensor) -> Tensor:
    """``theta`` -> natural values ``(..., d + 2)``: (outputscale, lengthscales, noise variance)."""
    return theta.exp()


def to_hypers(theta: Tensor):
    """A GPyTorch :class:`~dslearn.filters.dgpt.experts.Hypers` holding ``theta`` (batch shape
    ``theta.shape[:-1] + (1,)``, noise constraint ``Positive`` with ``exp``); used by the tests
    to check against GPyTorch."""
    from dslearn.filters.dgpt.experts import Hypers

    d = theta.shape[-1] - 2
    hyp = Hypers(tuple(theta.shape[:-1]) + (1,), d, 1.0, [1.0] * d, 1.0, 0.0,
                 dtype=theta.dtype, device=theta.device)
    with torch.no_grad():
        hyp.kernel.raw_outputscale.copy_(theta[..., 0, None])
        hyp.kernel.base_kernel.raw_lengthscale.copy_(theta[..., None, None, 1:-1])
        hyp.likelihood.noise_covar.raw_noise.copy_(theta[..., None, -1:])
    return hyp


def _cholesky(k: Tensor, scale: Tensor, counter: list | None):
    """Batched Cholesky; where (and only where) it fails, add jitter ``1e-8 * scale`` (then
    ``1e-6``) to that matrix. ``scale``: broadcastable to ``k.shape[:-2]``."""
    chol, info = torch.linalg.cholesky_ex(k)
    eye = torch.eye(k.shape[-1], dtype=k.dtype, device=k.device)
    for rel in (1e-8, 1e-6, 1e-4):
        bad = info > 0
        if not bool(bad.any()):
            break
        n_bad = int(bad.sum())
        if counter is not None:
            counter[0] += n_bad
        warnings.warn(f"DGPT: Cholesky failed for {n_bad} matrices, adding jitter {rel:g} x outputscale "
                      "to those", RuntimeWarning)
        jit = torch.where(bad, rel * scale.expand(bad.shape), torch.zeros_like(bad, dtype=k.dtype))
        chol2, info2 = torch.linalg.cholesky_ex(k + jit[..., None, None] * eye)
        chol = torch.where(bad[..., None, None], chol2, chol)
        info = torch.where(bad, info2, torch.zeros_like(info))
    return chol


def _kernel_parts(theta: Tensor, x: Tensor, mask: Tensor):
    """Masked covariance of padded windows and the pieces its derivatives need.

    theta: ``(*pb, p)``; x: ``(*pb, M, W, d)``; mask: ``(*pb, M, W)``.
    """
    os_, ls, nz = unpack(theta)
    os_ = os_[..., None, None, None]                       # (*pb, 1, 1, 1)
    ls = ls[..., None, None, None, :]                     # (*pb, 1, 1, 1, d)
    m = mask.to(x.dtype)
    dk = ((x[..., :, None, :] - x[..., None, :, :]) / ls) ** 2   # (*pb, M, W, W, d): D_k / l_k^2
    kf = se(dk.sum(-1), os_) * (m[..., :, None] * m[..., None, :])
    diag = m * nz[..., None, None] + (1.0 - m)            # padded slots: decoupled unit variance
    k = kf + torch.diag_embed(diag)
    return k, kf, dk, m, os_[..., 0, 0, 0], nz


def log_marginal_likelihood(theta: Tensor, x: Tensor, z: Tensor, mask: Tensor, order: int = 0,
                            jitter_counter: list | None = None):
    r"""Factorised log marginal likelihood (Eq. 15) of padded windows and its derivatives.

    Args:
        theta: ``(*pb, d + 2)`` per-problem hyperparameters (shared by the problem's experts).
        x: ``(*pb, M, W, d)`` inputs; z: ``(*pb, M, W)`` targets; mask: ``(*pb, M, W)`` bool.
        order: 0 -> value; 1 -> (value, gradient); 2 -> (value, gradient, Hessian).

    Returns:
        ``f (*pb)`` = :math:`\sum_i \log p(z^{(i)}|X^{(i)}, \theta)` over the observed slots
        (an empty window contributes 0), ``g (*pb, p)``, ``H (*pb, p, p)`` w.r.t. ``theta``.

    With :math:`K` the noisy covariance, :math:`\alpha = K^{-1}z`, :math:`K_i = \partial K/\partial\theta_i`:
    :math:`g_i = \tfrac12\alpha^\top K_i\alpha - \tfrac12\operatorname{tr}(K^{-1}K_i)`,
    :math:`H_{ij} = -\alpha^\top K_i K^{-1} K_j\alpha + \tfrac12\operatorname{tr}(K^{-1}K_iK^{-1}K_j)
    + \tfrac12\operatorname{tr}((\alpha\alpha^\top - K^{-1})K_{ij})`.
    """
    k, kf, dk, m, os_, nz = _kernel_parts(theta, x, mask)
    chol = _cholesky(k, os_[..., None], jitter_counter)
    zm = z * m
    alpha = torch.cholesky_solve(zm[..., None], chol)[..., 0]
    f = (-0.5 * (zm * alpha).sum(-1) - torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
         - 0.5 * LOG_2PI * m.sum(-1)).sum(-1)
    if order == 0:
        return f
    d = x.shape[-1]
    kinv = torch.cholesky_inverse(chol)
    dnoise = torch.diag_embed(m * nz[..., None, None])
    dks = torch.stack([kf] + [kf * dk[..., j] for j in range(d)] + [dnoise], -3)  # (*pb,M,p,W,W)
    wmat = alpha[..., :, None] * alpha[..., None, :] - kinv                        # (*pb,M,W,W)
    s = (wmat[..., None, :, :] * dks).sum((-1, -2))                                # (*pb,M,p)
    g = 0.5 * s.sum(-2)
    if order == 1:
        return f, g
    p = d + 2
    a = kinv[..., None, :, :] @ dks                                   # K^-1 K_i
    b = (dks @ alpha[..., None, :, None])[..., 0]                     # K_i alpha
    kb = (a @ alpha[..., None, :, None])[..., 0]                      # K^-1 K_i alpha
    h = -torch.einsum("...iw,...jw->...ij", b, kb) + 0.5 * torch.einsum("...iab,...jba->...ij", a, a)
    # 0.5 tr(W K_ij) with the second derivatives of the SE kernel in log parameters
    t2 = torch.einsum("...ab,...abk,...abl->...kl", wmat * kf, dk, dk)  # (*pb,M,d,d)
    h2 = torch.zeros(*s.shape[:-1], p, p, dtype=x.dtype, device=x.device)
    h2[..., 0, 0] = s[..., 0]
    h2[..., 0, 1:1 + d] = s[..., 1:1 + d]
    h2[..., 1:1 + d, 0] = s[..., 1:1 + d]
    h2[..., 1:1 + d, 1:1 + d] = t2 - 2.0 * torch.diag_embed(s[..., 1:1 + d])
    h2[..., -1, -1] = s[..., -1]
    hess = (h + 0.5 * h2).sum(-3)
    return f, g, 0.5 * (hess + hess.mT)


class Posterior:
    """GP posterior of the latent f given padded windows (Eqs. 5-6), for given ``theta``.

    Args: as :func:`log_marginal_likelihood`. Call with test inputs ``(*pb, M, Q, d)`` ->
    mean, variance ``(*pb, M, Q)`` (variance clamped to ``[1e-12, outputscale]``).
    """

    def __init__(self, theta: Tensor, x: Tensor, z: Tensor, mask: Tensor,
                 jitter_counter: list | None = None):
        k, _, _, m, os_, _ = _kernel_parts(theta, x, mask)
        self.chol = _cholesky(k, os_[..., None], jitter_counter)
        self.alpha = torch.cholesky_solve((z * m)[..., None], self.chol)
        self.x, self.m = x, m
        self.os = os_[..., None, None]                                   # (*pb, 1, 1)
        self.ls = unpack(theta)[1][..., None, None, None, :]  # (*pb, 1, 1, 1, d)

    def __call__(self, xs: Tensor):
        d2 = (((self.x[..., :, None, :] - xs[..., None, :, :]) / self.ls) ** 2).sum(-1)
        ks = se(d2, self.os[..., None]) * self.m[..., None]   # (*pb, M, W, Q)
        mean = (ks * self.alpha).sum(-2)
        v = torch.linalg.solve_triangular(self.chol, ks, upper=False)
        prior = self.os.expand_as(mean)
        var = torch.minimum((prior - (v ** 2).sum(-2)).clamp_min(1e-12), prior)
        return mean, var


class Optimiser(Enum):
    """How the hyperparameters are maximised (``hyper.optimizer``): Newton's method (:func:`newton_maximise`),
    Adam's steps or plain gradient steps (:class:`ElementwiseAdam`)."""

    NEWTON = "newton"
    ADAM = "adam"
    SGD = "sgd"


class ElementwiseAdam:
    """Adam on a batch of independent problems (PyTorch's update rule, ``amsgrad=False``).

    Moments and the step counter are kept per problem (``theta.shape[:-1]``); :meth:`step`
    updates only the problems of the selected leading indices, so a problem's trajectory is
    that of ``torch.optim.Adam`` run on that problem alone. ``box = (lo, hi)``: the updated
    parameters are clipped to it (projected Adam; no clipping without it). ``kind``: an
    :class:`Optimiser` or its value; :attr:`Optimiser.SGD` takes plain gradient steps instead.
    """

    def __init__(self, theta: Tensor, lr: float, betas=(0.9, 0.999), eps: float = 1e-8,
                 kind: str | Optimiser = Optimiser.ADAM, box=None):
        self.lr, self.b1, self.b2, self.eps, self.kind = lr, betas[0], betas[1], eps, Optimiser(kind)
        self.box = box
        self.m = torch.zeros_like(theta)
        self.v = torch.zeros_like(theta)
        self.t = torch.zeros(theta.shape[:-1], dtype=torch.long, device=theta.device)

    def step(self, theta: Tensor, grad: Tensor, idx: Tensor) -> Tensor:
        """One descent step on the problems ``theta[idx]`` with loss gradient ``grad``
        (shape of ``theta[idx]``); returns the updated ``theta[idx]``."""
        if self.kind is Optimiser.SGD:
            return self._clip(theta - self.lr * grad)
        t = self.t[idx] + 1
        m = self.b1 * self.m[idx] + (1.0 - self.b1) * grad
        v = self.b2 * self.v[idx] + (1.0 - self.b2) * grad * grad
        self.t[idx], self.m[idx], self.v[idx] = t, m, v
        tt = t.to(theta.dtype)[..., None]
        bc1 = 1.0 - self.b1 ** tt
        bc2 = 1.0 - self.b2 ** tt
        denom = v.sqrt() / bc2.sqrt() + self.eps
        return self._clip(theta - (self.lr / bc1) * m / denom)

    def _clip(self, theta):
        if self.box is None:
            return theta
        return torch.maximum(torch.minimum(theta, self.box[1]), self.box[0])


@dataclass
class SolveInfo:
    """Per-problem outcome of :func:`newton_maximise` (shape ``theta.shape[:-1]``)."""

    f: Tensor          # objective at the returned theta
    grad: Tensor       # largest |projected gradient component| there
    iters: Tensor      # Newton iterations (objective evaluations after the first)
    converged: Tensor  # the stopping test was met (not the iteration cap, not a stall)


def projected_gradient(theta: Tensor, g: Tensor, box) -> Tensor:
    """Gradient with the components that push against an active bound set to 0."""
    if box is None:
        return g
    lo, hi = box
    fixed = ((theta <= lo) & (g < 0)) | ((theta >= hi) & (g > 0))
    return torch.where(fixed, torch.zeros_like(g), g)


def newton_maximise(evaluate: Callable, theta: Tensor, active: Tensor, tol: float, max_iters: int,
                    box=None, radius: float = 1.0, max_radius: float = 5.0,
                    min_radius: float = 1e-12):
    r"""Maximise independent smooth objectives by projected trust-region Newton, per problem.

    Args:
        evaluate: ``evaluate(theta_sub, idx) -> (f, g, H)`` for the problems ``idx`` (a 1-D index
            into the leading axis; ``theta_sub = theta[idx]``), shapes ``(n,)``, ``(n, p)``,
            ``(n, p, p)``.
        theta: ``(N, p)`` start (warm start), inside ``box``.
        active: ``(N,)`` bool, problems to optimise (the others are returned unchanged).
        tol: gradient tolerance: largest |projected gradient component|.
        max_iters: cap on the iterations (evaluations) of a problem.
        box: ``(lo, hi)`` each ``(p,)``, or None.

    A problem stops when its projected gradient is ``<= tol``, when its trust radius falls
    below ``min_radius`` (stalled at round-off), or after ``max_iters`` iterations.

    Step: with the variables at an active bound held fixed, :math:`\delta = Q|\Lambda|^{-1}c`,
    :math:`c = Q^\top g`, with :math:`-H = Q\Lambda Q^\top` on the free variables (Newton's step
    where :math:`-H \succ 0`, an ascent direction everywhere; along eigen-directions where the
    objective curves upwards the step goes to the trust radius, :math:`r\,c_i/\max(|c_i|, tol)`)
    and the components of ``c`` below ``1e-3 tol`` set to 0 (on a flat ridge, where gradient and
    curvature are both near round-off, their step would be noise), shortened to the trust
    radius, then projected onto the box;
    accepted when the objective increases by at least 1e-4 of the quadratic model's prediction
    (or, once that prediction is below 1e-11 (1 + |f|), does not decrease by more than that);
    the radius shrinks after poor or rejected steps and grows after good ones that hit it. Only
    unfinished problems are evaluated.

    Returns:
        ``(theta, SolveInfo)``.
    """
    th = theta.clone()
    n_all, p = th.shape
    dt, dev = th.dtype, th.device
    f = torch.zeros(n_all, dtype=dt, device=dev)
    g = torch.zeros_like(th)
    H = torch.zeros(n_all, p, p, dtype=dt, device=dev)
    iters = torch.zeros(n_all, dtype=torch.long, device=dev)
    conv = torch.zeros(n_all, dtype=torch.bool, device=dev)
    idx = torch.nonzero(active)[:, 0]
    if idx.numel():
        f[idx], g[idx], H[idx] = evaluate(th[idx], idx)
    done = ~active
    rad = torch.full((n_all,), float(radius), dtype=dt, device=dev)
    eye = torch.eye(p, dtype=dt, device=dev)
    for it in range(int(max_iters) + 1):
        idx = torch.nonzero(~done)[:, 0]
        if idx.numel() == 0:
            break
        thi, fi, gi, Hi, ri = th[idx], f[idx], g[idx], H[idx], rad[idx]
        pg = projected_gradient(thi, gi, box)
        if box is not None:  # variables at a bound with the gradient pushing outwards are fixed
            free = ~(((thi <= box[0]) & (gi < 0)) | ((thi >= box[1]) & (gi > 0)))
        else:
            free = torch.ones_like(gi, dtype=torch.bool)
        ff = free[..., :, None] & free[..., None, :]
        a = torch.where(ff, -Hi, eye.expand_as(Hi))
        lam, q = torch.linalg.eigh(0.5 * (a + a.mT))
        la = lam.abs()
        la = torch.maximum(la, 1e-12 * la.amax(-1, keepdim=True).clamp_min(1.0))
        c = (q.mT @ pg[..., None])[..., 0]
        # directions whose gradient is already far below tol are left alone: on a flat ridge
        # (gradient and curvature both near round-off) their Newton step would be noise
        c = torch.where(c.abs() > 1e-3 * tol, c, torch.zeros_like(c))
        # Newton where -H is positive; along directions of positive curvature of f (no maximum
        # along them) go to the trust radius instead of |lambda|^-1 c
        dirn = torch.where(lam > 0, c / la, ri[..., None] * c / c.abs().clamp_min(tol))
        full = (q @ dirn[..., None])[..., 0]
        stop = pg.abs().amax(-1) <= tol
        conv[idx] = stop
        stop = stop | (ri < min_radius)
        if it == int(max_iters):
            done[idx] = True
            break
        done[idx] = stop
        go = ~stop
        if not bool(go.any()):
            continue
        idx, thi, fi, gi, Hi, ri, pg, full = (v[go] for v in (idx, thi, fi, gi, Hi, ri, pg, full))
        nrm = full.norm(dim=-1)
        sc = (ri / nrm.clamp_min(1e-300)).clamp(max=1.0)
        tgt = thi + full * sc[..., None]
        if box is not None:
            tgt = torch.maximum(torch.minimum(tgt, box[1]), box[0])
        step = tgt - thi
        pred = (gi * step).sum(-1) - 0.5 * (step * (-Hi @ step[..., None])[..., 0]).sum(-1)
        f2, g2, H2 = evaluate(tgt, idx)
        ok = torch.isfinite(f2) & torch.isfinite(g2).all(-1) & torch.isfinite(H2).all(-1).all(-1)
        noise_lvl = 1e-11 * (1.0 + fi.abs())
        gain = torch.where(ok, f2 - fi, torch.full_like(fi, -math.inf))
        tiny = pred <= noise_lvl
        acc = ok & torch.where(tiny, gain >= -noise_lvl, gain >= 1e-4 * pred)
        rho = torch.where(tiny, torch.ones_like(gain), gain / pred.clamp_min(1e-300))
        slen = step.norm(dim=-1)
        r_new = torch.where(~acc | (rho < 0.25), 0.25 * slen, ri)
        r_new = torch.where(acc & (rho > 0.75) & (sc < 1.0), (2.0 * ri).clamp(max=max_radius), r_new)
        th[idx] = torch.where(acc[..., None], tgt, thi)
        f[idx] = torch.where(acc, f2, fi)
        g[idx] = torch.where(acc[..., None], g2, gi)
        H[idx] = torch.where(acc[..., None, None], H2, Hi)
        rad[idx] = r_new
        iters[idx] += 1
    gmax = projected_gradient(th, g, box).abs().amax(-1)
    return th, SolveInfo(f=f, grad=gmax, iters=iters, converged=active & conv)
