r"""Particle (Monte Carlo) prediction step (GP-PF) for the information filter.

A drop-in alternative to :func:`dslearn.filters.information.predict`, the unscented step
(:mod:`dslearn.filters.ukf`) and the moment-matching step (:mod:`dslearn.filters.adf`): same arguments,
same return tuple, so :func:`dslearn.filters.distributed.track` runs it at every node (``filter=pf``).
It is the prediction of a Gaussian particle filter (Kotecha & Djuric, *Gaussian particle filtering*,
IEEE TSP 2003) with the sampling of the GP-PF (Ko & Fox, *GP-BayesFilters*, Autonomous Robots 2009):
per node and episode, :math:`N` particles are drawn from the belief :math:`\mathcal N(\hat y, P)`,
:math:`P = \Omega^{-1}`, each is pushed through the motion model's mean and a draw of the model's process
noise at that particle is added,

.. math::
    x_i = \hat y + L z_i,\quad L L^T = P,\qquad
    y_i = f(x_i) + Q(x_i)^{1/2} w_i,\qquad z_i, w_i \sim \mathcal N(0, I),

(for a GP motion model :math:`f` is its posterior mean and :math:`Q(x_i)` its predictive variance at the
particle, the noise mode's terms included: :math:`y_i` is a draw of the GP predictive at :math:`x_i`, as in
the GP-PF; for the linear and social-force models :math:`Q` is their constant process noise), and the cloud
is moment-matched into information form:

.. math::
    \hat y^{t|t-1} = \frac1N \sum_i y_i,\quad
    P^{t|t-1} = \frac1{N-1} \sum_i (y_i - \hat y^{t|t-1})(y_i - \hat y^{t|t-1})^T,\quad
    \Omega^{t|t-1} = (P^{t|t-1})^{-1},\quad q^{t|t-1} = \Omega^{t|t-1} \hat y^{t|t-1}.

This is the GP-PF's *prediction*, moment-matched: the belief handed on is a Gaussian, not a particle
posterior. The update, the fusion and the learning stay the information filter's. That is no loss in the
update itself: with the linear position sensor the weighted-particle update of the Gaussian particle filter
(weights :math:`\mathcal N(z; C y_i, R)`) has, as :math:`N \to \infty`, the moments of the Kalman update of
the matched Gaussian, which the information filter computes exactly; what the step does not keep is any
non-Gaussian shape of the predicted cloud, and the particles are drawn afresh at every step.

With ``full=True`` the step also returns :math:`P^{t|t-1}`, the statistical linearisation from the particles,
:math:`F = \widehat{\mathrm{Cov}}(f(x), x)\, \widehat{\mathrm{Cov}}(x)^{-1}` (the least-squares regression of
the propagated means on the drawn particles: the model's matrix exactly for a linear model), and
:math:`Q = P^{t|t-1} - F P F^T`, symmetrised and, where Monte Carlo error makes it indefinite, floored to
positive semi-definite at eigenvalue 0 (then :math:`F P F^T + Q` exceeds :math:`P^{t|t-1}` by that floor), which
is what the RTS smoother and the EM step of ``noise=adaptive`` need (as :mod:`dslearn.filters.adf`).

Randomness: the step keeps a :class:`torch.Generator` per device, seeded from ``filter.predict.seed``
(``conf/filter/pf.yaml`` sets it to the run's ``seed``, as the scenarios' ``seed: ${seed}`` do, so a sweep over
run seeds draws different particles; the global RNG is neither read nor advanced), advanced at every call.
A fresh step with the same seed gives bit-identical results for the same sequence of calls; the draws are made
on the belief's device and in its dtype (so a CPU and a GPU run draw different particles). All draws of a call
are made before the model is evaluated, and the model is evaluated in chunks of particles
(:data:`CHUNK_ELEMENTS`), so the chunking changes the numbers by rounding only.

GPs without data: while no node's exact GP holds a valid point
(:meth:`~dslearn.models.gp_backends.exact.OnlineGP.void_nodes`; Liu's 200 sensors, whose learning gate admits
nothing), the predictive at every particle is the prior's, an affine
mean (``zero``, ``constant``, ``identity``, ``constant_velocity``) and a constant diagonal noise, so the particles
are i.i.d. Gaussian and the moment-matched cloud has a known law: its mean Gaussian and, independent of it, its
scatter Wishart. The step then draws these two from that law (:func:`_void_moments`: ``O(Dx^2)`` draws per node and
episode instead of ``2 N Dx``); the numbers change in their random realisation only, not in distribution (tested
against the particles, ``tests/test_particle_speed.py``), and ``F`` is the prior mean's Jacobian, which the
particles' regression recovers up to rounding. Wherever some node holds data, every particle is drawn as above.

Batched over nodes, episodes and particles (no Python loop over any of them); differentiable where the model
is (the draws are reparameterised), which the backprop learner uses. Jitter that a near-singular belief or
predicted covariance needs is recorded like the other steps' (:func:`~dslearn.types.safe_cholesky`).
Any motion model fits: a per-node model (the GPs) gets the node dimension first, ``(S, B N, Dx)``, a parametric
one the particle dimension first, ``(N, S, B, Dx)``, with ``ctx.cov`` the belief's covariance (as the unscented
step's sigma points: the social force's softening reads it).
"""

from __future__ import annotations

import dataclasses
import math
import numbers

import torch
from torch import Tensor

from dslearn.errors import ConfigError
from dslearn.filters.ukf import _noise_at, _per_node
from dslearn.filters.ukf import _propagate as _ukf_propagate
from dslearn.models.base import MotionModel
from dslearn.types import StepContext, safe_cholesky, spd_inverse, symmetrize

#: where the step's settings live in the configuration (``conf/filter/pf.yaml``)
KEY = "filter.predict"
#: the most elements of one model evaluation's temporaries (queries x data points, or x Dx^2): the particles
#: are evaluated in chunks below it (float64: 128 MB)
CHUNK_ELEMENTS = 1 << 24


def check_particles(particles) -> int:
    """``particles`` as an int; :class:`~dslearn.errors.ConfigError` naming ``filter.predict.particles`` unless
    it is an integer >= 2 (a sample covariance needs two particles)."""
    if isinstance(particles, bool) or not isinstance(particles, numbers.Integral) or int(particles) < 2:
        raise ConfigError(f"{KEY}.particles={particles!r} must be an integer >= 2 (the number of particles "
                          f"per node and episode)")
    return int(particles)


def check_seed(seed) -> int:
    """``seed`` as an int; ConfigError naming ``filter.predict.seed`` unless it is an integer >= 0."""
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or int(seed) < 0:
        raise ConfigError(f"{KEY}.seed={seed!r} must be an integer >= 0")
    return int(seed)


def _gp_model(model: MotionModel):
    """The :class:`~dslearn.models.gp.GPMotionModel` whose predictive the step evaluates directly (``None``
    for any other model): mean and latent variance in one pass, without the Jacobian ``noise_cov`` computes."""
    from dslearn.models.gp import GPMotionModel

    return model if isinstance(model, GPMotionModel) else None


def _data_points(model: MotionModel) -> int:
    gp = getattr(model, "gp", None)
    n = getattr(gp, "n", 0)
    return int(n) if isinstance(n, (int, numbers.Integral)) else 0


def _sqrt_psd(Q: Tensor) -> Tensor:
    """A square root ``R`` with ``R R^T = Q`` of PSD matrices ``(*B, D, D)``: the Cholesky factor where it exists,
    the symmetric root with eigenvalues floored at 0 where not (a singular noise needs no jitter)."""
    L, info = torch.linalg.cholesky_ex(Q)
    bad = info > 0
    if not bool(bad.any()):
        return L
    lam, V = torch.linalg.eigh(symmetrize(Q))
    R = V * lam.clamp_min(0.0).sqrt().unsqueeze(-2)
    return torch.where(bad[..., None, None], R, L)


def _noise_root(Q: Tensor) -> Tensor:
    """:func:`_sqrt_psd` of the model's noise ``(*B, D, D)``; a noise that is one matrix broadcast over the batch
    (stride 0: the linear and social-force models' constant ``Q``) is factored once."""
    if Q.dim() > 2 and all(st == 0 for st in Q.stride()[:-2]):
        one = Q[(0,) * (Q.dim() - 2)]
        return _sqrt_psd(one).expand(Q.shape)
    return _sqrt_psd(Q)


def _propagate(model: MotionModel, x: Tensor, w: Tensor, P: Tensor, ctx: StepContext) -> tuple[Tensor, Tensor]:
    """Means ``f(x)`` and predictive draws ``f(x) + Q(x)^{1/2} w`` at particles ``x (S, B, n, Dx)``, ``w`` alike."""
    s, b, n, dx = x.shape
    gpm = _gp_model(model)
    if gpm is not None:  # the GP predictive at each particle (Ko & Fox): diagonal, noise mode included
        mean, var, _ = gpm.gp.predict(x.reshape(s, b * n, dx), jacobian=False, variance=True)
        if gpm.noise_mode == "predictive":
            var = var + gpm.gp.noise_var.to(var).unsqueeze(-1)
        d = var.unsqueeze(-1) + gpm.extra_noise(var).to(var).unsqueeze(1)  # (S, B n, Dx)
        f = mean.reshape(x.shape).to(x.dtype)
        return f, f + d.clamp_min(0.0).sqrt().reshape(x.shape).to(x.dtype) * w
    # any other model: f through the unscented step's propagation (the node dimension first for per-node
    # models, the particle dimension first for the rest), its noise at every particle laid out alike
    f = _ukf_propagate(model, x, P, ctx).to(x.dtype)
    if _per_node(model):
        Q = _noise_at(model, x, P, ctx)
    else:
        Q = model.noise_cov(x.movedim(-2, 0), dataclasses.replace(ctx, cov=P)).movedim(0, -3)
    R = _noise_root(Q.to(x.dtype))
    return f, f + (R @ w.unsqueeze(-1)).squeeze(-1)


def _void_prior(model: MotionModel, mean: Tensor, particles: int) -> tuple[Tensor, Tensor, Tensor] | None:
    r"""Where every node's GP holds no valid point (the predictive is the prior at any input) and the prior mean is
    affine (``zero``, ``constant``, ``identity``, ``constant_velocity``): the prior's mean :math:`f(\hat y)` at the
    belief's mean ``(S, B, Dx)``, its Jacobian :math:`A` ``(S, B, Dx, Dx)`` (constant) and the diagonal noise
    :math:`D` ``(S, 1, Dx)`` that :func:`_propagate` adds at every particle (the prior's latent variance, the noise
    mode's terms included). ``None`` for anything else (a node with data, another model or backend, the ``meta``
    device, ``particles <= 2 Dx``): the particles are drawn."""
    from dslearn.models.gp_backends.means import ConstantVelocityMean, IdentityMean, ZeroMean

    gpm = _gp_model(model)
    if gpm is None or mean.device.type == "meta" or particles <= 2 * mean.shape[-1]:
        return None
    gp = gpm.gp
    if not (callable(getattr(gp, "void_nodes", None)) and callable(getattr(gp, "prior_variance", None))):
        return None
    module = getattr(gp, "mean_module", None)
    affine = (module is None and getattr(gp, "mean_type", None) == "constant") or \
        type(module) in (ZeroMean, IdentityMean, ConstantVelocityMean)
    if not affine or (gp.num_nodes, gp.output_dim) != (mean.shape[0], mean.shape[-1]):
        return None
    if not bool(gp.void_nodes().all()):
        return None
    s, b, dx = mean.shape
    f = gp.prior_mean(mean).to(mean.dtype)  # (S, B, Dx): predict's mean where k_* = 0
    A = gp.prior_mean_jacobian(mean).to(mean.dtype).expand(s, b, dx, dx)
    var = gp.prior_variance().unsqueeze(-1)  # (S, 1): as predict's (S, B n) latent variance, one query
    if gpm.noise_mode == "predictive":
        var = var + gpm.gp.noise_var.to(var).unsqueeze(-1)
    d = (var.unsqueeze(-1) + gpm.extra_noise(var).to(var).unsqueeze(1)).clamp_min(0.0).to(mean.dtype)  # (S, 1, Dx)
    return f, A, d


def _void_moments(mean: Tensor, L: Tensor, prior: tuple[Tensor, Tensor, Tensor], N: int,
                  generator: torch.Generator | None) -> tuple[Tensor, Tensor]:
    r"""The moment-matched cloud of :math:`N` particles through an affine model with a constant diagonal noise,
    drawn from its exact law instead of particle by particle. The particles are :math:`y_i = f(\hat y) + R u_i`
    with :math:`R = (A L,\ D^{1/2})` (``Dx x 2Dx``) and :math:`u_i = (z_i, w_i)` i.i.d. :math:`\mathcal N(0, I_{2Dx})`,
    so their mean is :math:`f(\hat y) + R \bar u` and their scatter :math:`(N-1) P^{t|t-1} = R\, W R^T` with
    :math:`\bar u \sim \mathcal N(0, I/N)` and, independent of it, the scatter of the :math:`u_i`,
    :math:`W \sim` Wishart :math:`(I_{2Dx}, N-1)`, drawn as :math:`T T^T` with Bartlett's factor :math:`T` (lower
    triangular, :math:`T_{kk}^2 \sim \chi^2_{N-1-k}`, :math:`T_{kj} \sim \mathcal N(0, 1)` below the diagonal;
    ``N > 2 Dx``). ``2Dx + Dx (2Dx - 1)`` normals and ``2Dx`` gamma draws per node and episode instead of ``2 N Dx``
    normals, and no factorisation. Returns ``(y_pred (S, B, Dx), P_pred (S, B, Dx, Dx))``."""
    f, A, d = prior
    *batch, dx = mean.shape
    k = 2 * dx
    R = torch.cat([A @ L, torch.diag_embed(d.sqrt()).expand(*batch, dx, dx)], -1)  # (S, B, Dx, 2Dx)
    kw = dict(generator=generator, dtype=mean.dtype, device=mean.device)
    u = torch.randn((*batch, k), **kw)
    rows, cols = torch.tril_indices(k, k, -1, device=mean.device)
    below = torch.randn((*batch, rows.numel()), **kw)
    dof = (N - 1) - torch.arange(k, dtype=mean.dtype, device=mean.device)  # chi^2_{N-1-k} = 2 Gamma((N-1-k)/2)
    chi2 = 2.0 * torch._standard_gamma((0.5 * dof).expand(*batch, k).contiguous(), generator=generator)
    T = torch.diag_embed(chi2.sqrt())
    T[..., rows, cols] = below
    y_pred = f + (R @ u.unsqueeze(-1)).squeeze(-1) / math.sqrt(N)
    RT = R @ T
    P_pred = symmetrize(RT @ RT.transpose(-1, -2) / (N - 1))
    return y_pred, P_pred


def _psd_floor(Q: Tensor) -> Tensor:
    """``Q`` with negative eigenvalues set to 0, for the matrices that have any (the rest untouched)."""
    lam, V = torch.linalg.eigh(Q)
    neg = (lam < 0).any(-1)
    if not bool(neg.any()):
        return Q
    floored = symmetrize((V * lam.clamp_min(0.0).unsqueeze(-2)) @ V.transpose(-1, -2))
    return torch.where(neg[..., None, None], floored, Q)


def pf_predict(mean: Tensor, omega: Tensor, model: MotionModel, ctx: StepContext, full: bool = False, *,
               particles: int = 500, generator: torch.Generator | None = None) -> tuple[Tensor, ...]:
    r"""The GP-PF prediction of an information-form belief, moment-matched (module docstring).

    Args:
        mean: ``(S, B, Dx)`` prior means; omega: ``(S, B, Dx, Dx)`` prior information.
        model: any :class:`~dslearn.models.base.MotionModel`.
        particles: ``N`` per node and episode (>= 2).
        generator: the source of the draws, on ``mean``'s device (``None``: the global RNG).
    Returns:
        ``(y_pred (S,B,Dx), q_pred (S,B,Dx), omega_pred (S,B,Dx,Dx))`` and with ``full`` also ``P_pred``, the
        statistical linearisation ``F`` and ``Q = P_pred - F P F^T`` (floored to PSD), all ``(S,B,Dx,Dx)``.
    """
    N = check_particles(particles)
    P = spd_inverse(omega)
    L = safe_cholesky(P)  # jitter (recorded) where the belief is near-singular
    *batch, dx = mean.shape
    prior = _void_prior(model, mean, N) if len(batch) == 2 else None
    if prior is not None:  # every node's GP is its (affine) prior: the cloud's moments drawn directly
        y_pred, P_pred = _void_moments(mean, L, prior, N, generator)
        omega_pred = spd_inverse(P_pred)  # jitter (recorded) where the cloud is degenerate
        q_pred = (omega_pred @ y_pred.unsqueeze(-1)).squeeze(-1)
        if not full:
            return y_pred, q_pred, omega_pred
        F = prior[1].clone()  # the particles' regression of f(x_i) = A x_i + c on x_i: A itself
        Q = _psd_floor(symmetrize(P_pred - F @ P @ F.transpose(-1, -2)))
        return y_pred, q_pred, omega_pred, P_pred, F, Q
    # every draw of the call first (particles, then noise), so that the chunks below cannot change them
    z = torch.randn((*batch, 2, N, dx), generator=generator, dtype=mean.dtype, device=mean.device)
    x = mean.unsqueeze(-2) + z[..., 0, :, :] @ L.transpose(-1, -2)  # (S, B, N, Dx): x_i = m + L z_i
    w = z[..., 1, :, :]
    per_query = max(_data_points(model), dx * dx, 1)
    rows = max(1, math.prod(batch))
    chunk = max(1, min(N, CHUNK_ELEMENTS // (rows * per_query)))
    parts = [_propagate(model, x[..., i:i + chunk, :], w[..., i:i + chunk, :], P, ctx) for i in range(0, N, chunk)]
    f = torch.cat([p[0] for p in parts], -2) if len(parts) > 1 else parts[0][0]
    y = torch.cat([p[1] for p in parts], -2) if len(parts) > 1 else parts[0][1]
    y_pred = y.mean(-2)
    dy = y - y_pred.unsqueeze(-2)
    P_pred = symmetrize(dy.transpose(-1, -2) @ dy / (N - 1))
    omega_pred = spd_inverse(P_pred)  # jitter (recorded) where the cloud is degenerate
    q_pred = (omega_pred @ y_pred.unsqueeze(-1)).squeeze(-1)
    if not full:
        return y_pred, q_pred, omega_pred
    dxp = x - x.mean(-2, keepdim=True)
    df = f - f.mean(-2, keepdim=True)
    C_xx = symmetrize(dxp.transpose(-1, -2) @ dxp)  # (N-1) Cov(x), (N-1) Cov(x, f): the factor cancels
    C_xf = dxp.transpose(-1, -2) @ df
    F = torch.cholesky_solve(C_xf, safe_cholesky(C_xx)).transpose(-1, -2)  # Cov(f, x) Cov(x)^{-1}
    Q = _psd_floor(symmetrize(P_pred - F @ P @ F.transpose(-1, -2)))
    return y_pred, q_pred, omega_pred, P_pred, F, Q


class ParticlePredict:
    """:func:`pf_predict` as a config part (``conf/filter/pf.yaml``: ``predict``), callable like
    :func:`dslearn.filters.information.predict` (``(mean, omega, model, ctx, full=False)``).

    Holds ``particles`` (``filter.predict.particles``, an integer >= 2) and ``seed`` (``filter.predict.seed``,
    an integer >= 0; ConfigError naming the key otherwise) and one :class:`torch.Generator` per device, seeded
    from ``seed`` on the first call on that device and advanced by every call. Any motion model fits (no
    ``model_misfit``). Its :attr:`name` is ``pf`` (a :class:`~dslearn.filters.information.PredictionStep`).
    """

    name = "pf"
    noise_at_mean = False
    differentiates_gp = True

    def __init__(self, particles: int = 500, seed: int = 0):
        self.particles = check_particles(particles)
        self.seed = check_seed(seed)
        self._generators: dict[str, torch.Generator] = {}

    def __repr__(self) -> str:
        return f"ParticlePredict(particles={self.particles}, seed={self.seed})"

    def generator(self, device) -> torch.Generator:
        """The step's generator on ``device`` (created and seeded on first use)."""
        dev = torch.device(device)
        key = str(dev)
        g = self._generators.get(key)
        if g is None:
            g = torch.Generator(device=dev).manual_seed(self.seed)
            self._generators[key] = g
        return g

    def __call__(self, mean: Tensor, omega: Tensor, model: MotionModel, ctx: StepContext, full: bool = False):
        gen = None if mean.device.type == "meta" else self.generator(mean.device)
        return pf_predict(mean, omega, model, ctx, full, particles=self.particles, generator=gen)


__all__ = ["CHUNK_ELEMENTS", "ParticlePredict", "check_particles", "check_seed", "pf_predict"]
