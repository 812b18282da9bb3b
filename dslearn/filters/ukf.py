r"""Unscented prediction step (GP-UKF) for the information filter.

A drop-in alternative to :func:`dslearn.filters.information.predict`: same arguments, same
return tuple, so :func:`dslearn.filters.distributed.track` can run it at every node. Instead of
linearising the motion model at the prior mean (EKF), the prior :math:`\mathcal N(\hat y, P)`,
:math:`P = \Omega^{-1}`, is represented by :math:`2D_x + 1` sigma points (scaled unscented
transform, Julier 2002; Wan & van der Merwe 2000), pushed through the model and re-summarised:

.. math::
    \lambda = \alpha^2 (D_x + \kappa) - D_x,\quad
    \chi_0 = \hat y,\quad \chi_{\pm i} = \hat y \pm \sqrt{D_x + \lambda}\, L_{:,i},\quad L L^T = P,

    w^m_0 = \frac{\lambda}{D_x + \lambda},\quad w^c_0 = w^m_0 + 1 - \alpha^2 + \beta,\quad
    w^m_{\pm i} = w^c_{\pm i} = \frac{1}{2 (D_x + \lambda)},

    \hat y^{t|t-1} = \sum_k w^m_k f(\chi_k),\quad
    P^{t|t-1} = \sum_k w^c_k (f(\chi_k) - \hat y^{t|t-1})(f(\chi_k) - \hat y^{t|t-1})^T + Q(\hat y).

The process noise :math:`Q` is the model's :meth:`~dslearn.models.base.MotionModel.noise_cov` at
the prior mean, not an average over the sigma points: for a GP motion model this is its latent
variance at the mean, the process noise of the GP-UKF (Ko & Fox 2009), and it is the same
:math:`Q` the EKF step uses, so the two steps differ only in how the mean is propagated.
With ``expected_variance=True`` (``filter=ukf_mm``: the GP-UKF with moment matching) it is the
unscented average instead, :math:`Q = \sum_k w^m_k Q(\chi_k)`: for a GP motion model the average of its
latent variance :math:`\Sigma_f(\chi_k)` over the sigma points (plus the state-independent terms of its
noise mode), the unscented estimate of :math:`\mathbb E[\Sigma_f(y)]` that the GP-ADF computes exactly
(:mod:`dslearn.filters.adf`). Only GP motion models have a state-dependent :math:`Q`; with any other model
the option changes nothing and is refused (:func:`expected_variance_misfit`).

With ``full=True`` the step also returns the statistical linearisation
:math:`F = P_{xy}^T P^{-1}`, :math:`P_{xy} = \sum_k w^c_k (\chi_k - \hat y)(f(\chi_k) - \hat y^{t|t-1})^T`
(the regression matrix of the propagated on the prior sigma points; the model's matrix for a
linear model), which is what the RTS smoother behind the process-noise EM step needs
(:func:`dslearn.filters.smoother.transition_error_moments`: :math:`F P = P_{xy}^T` is the
unscented RTS cross-covariance).

Shapes follow :mod:`dslearn.filters.information`: nodes first, ``(S, B, Dx)``, ``(S, B, Dx, Dx)``.
Nothing here disables autograd: the step is differentiable wherever the model is.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
import torch
from torch import Tensor

from dslearn.errors import ConfigError, check_finite, check_positive
from dslearn.models.base import MotionModel
from dslearn.types import StepContext, safe_cholesky, spd_inverse, symmetrize


#: where the unscented parameters live in the configuration (``conf/filter/ukf.yaml``)
KEY = "filter.predict"


def check_unscented(alpha: float, beta: float, kappa: float, state_dim: int | None = None) -> None:
    r"""Raise :class:`~dslearn.errors.ConfigError` unless :math:`\alpha > 0`, :math:`\beta \ge 0`,
    :math:`\kappa` finite and, when ``state_dim`` is given, :math:`D_x + \lambda = \alpha^2 (D_x + \kappa) > 0`
    (i.e. :math:`\kappa > -D_x`). The messages name the keys ``filter.predict.alpha|beta|kappa``."""
    check_positive(f"{KEY}.alpha", alpha)
    check_positive(f"{KEY}.beta", beta, strict=False)
    check_finite(f"{KEY}.kappa", kappa)
    if state_dim is not None and not float(state_dim) + float(kappa) > 0:
        raise ConfigError(
            f"{KEY}.kappa={kappa!r} with state dimension Dx={state_dim} gives Dx + lambda = "
            f"alpha^2 (Dx + kappa) = {float(alpha) ** 2 * (state_dim + float(kappa)):g}; it must be > 0: "
            f"use {KEY}.kappa > {-state_dim}"
        )


def unscented_weights(
    state_dim: int, alpha: float, beta: float, kappa: float, dtype=torch.float64, device=None
) -> tuple[Tensor, Tensor, float]:
    """Mean and covariance weights ``(2 Dx + 1,)`` (centre point first) and the scale
    :math:`D_x + \\lambda` of the sigma-point offsets."""
    check_unscented(alpha, beta, kappa, state_dim)
    n = int(state_dim)
    c = float(alpha) ** 2 * (n + float(kappa))  # Dx + lambda
    lam = c - n
    wm = torch.full((2 * n + 1,), 0.5 / c, dtype=dtype, device=device)
    wm[0] = lam / c
    wc = wm.clone()
    wc[0] = wc[0] + 1.0 - float(alpha) ** 2 + float(beta)
    return wm, wc, c


def _sigma_points(mean: Tensor, cov: Tensor, alpha: float, beta: float, kappa: float):
    """:func:`sigma_points` plus the Cholesky factor used (for the statistical linearisation)."""
    n = mean.shape[-1]
    wm, wc, c = unscented_weights(n, alpha, beta, kappa, mean.dtype, mean.device)
    L = safe_cholesky(cov)  # jitter (counted in dslearn.types.JITTER) where cov is near-singular
    off = math.sqrt(c) * L.transpose(-1, -2)  # row i = sqrt(Dx + lambda) L[:, i]
    m = mean.unsqueeze(-2)
    return torch.cat([m, m + off, m - off], dim=-2), wm, wc, L


def sigma_points(mean: Tensor, cov: Tensor, alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0):
    r"""Scaled unscented sigma points of :math:`\mathcal N(\text{mean}, \text{cov})`.

    Args:
        mean: ``(*B, Dx)`` (for a network ``(S, B, Dx)``); cov: ``(*B, Dx, Dx)``.
        alpha, beta, kappa: spread, prior-knowledge and secondary scaling parameters
            (:math:`\alpha > 0`, :math:`\beta \ge 0`, :math:`\kappa > -D_x`).
    Returns:
        ``points (*B, 2Dx+1, Dx)`` (centre, then :math:`+` and :math:`-` offsets along the columns
        of the Cholesky factor), mean weights ``(2Dx+1,)``, covariance weights ``(2Dx+1,)``.
        The points reproduce ``mean`` and ``cov`` exactly:
        :math:`\sum_k w^m_k \chi_k = \text{mean}`, :math:`\sum_k w^c_k (\chi_k - \text{mean})(\cdot)^T = \text{cov}`
        (plus the jitter :func:`~dslearn.types.safe_cholesky` added to a near-singular ``cov``).
    """
    pts, wm, wc, _ = _sigma_points(mean, cov, alpha, beta, kappa)
    return pts, wm, wc


def _per_node(model: MotionModel) -> bool:
    """Whether the model keeps per-node state and so needs the node dimension first (the GP
    models: learnable, with ``num_nodes``); the rest broadcast over any leading dimensions."""
    return bool(getattr(model, "learnable", False)) or hasattr(type(model), "num_nodes")


def _propagate(model: MotionModel, pts: Tensor, cov: Tensor, ctx: StepContext) -> Tensor:
    r"""``f`` at every sigma point: ``pts (*B, K, Dx) -> (*B, K, Dx)``, ``cov (*B, Dx, Dx)`` the prior.

    Per-node models (GP) get ``(S, prod(B[1:]) K, Dx)``: the node dimension stays first, every
    sigma point of node ``i`` is a query of node ``i``'s model; ``ctx.cov`` is repeated per sigma
    point to match. Parametric models get the sigma dimension first, ``(K, *B, Dx)``, so that
    what broadcasts against the belief's batch ``(*B, ...)`` still does: ``ctx.cov (*B, Dx, Dx)``
    (the social force's uncertainty softening reads its diagonal, ``(*B, A)``) and per-episode
    parameters such as the social force's desired velocities ``(B, A, 2)``.
    """
    k, dx = pts.shape[-2], pts.shape[-1]
    batch = pts.shape[:-2]
    if _per_node(model):
        s = batch[0]
        x = pts.reshape(s, -1, dx)
        c = cov.unsqueeze(-3).expand(*batch, k, dx, dx).reshape(s, -1, dx, dx)
        out = model(x, dataclasses.replace(ctx, cov=c))
        return out.reshape(*batch, k, out.shape[-1])
    out = model(pts.movedim(-2, 0), dataclasses.replace(ctx, cov=cov))
    return out.movedim(0, -2)


def _noise_at(model: MotionModel, pts: Tensor, cov: Tensor, ctx: StepContext) -> Tensor:
    """The process noise of a per-node (GP) model at every sigma point: ``pts (*B, K, Dx) -> (*B, K, Dx, Dx)``,
    the points laid out as in :func:`_propagate` (node dimension first, ``ctx.cov`` repeated per point)."""
    k, dx = pts.shape[-2], pts.shape[-1]
    batch = pts.shape[:-2]
    x = pts.reshape(batch[0], -1, dx)
    c = cov.unsqueeze(-3).expand(*batch, k, dx, dx).reshape(batch[0], -1, dx, dx)
    return model.noise_cov(x, dataclasses.replace(ctx, cov=c)).reshape(*batch, k, dx, dx)


#: the key of the moment-matching option (``conf/filter/ukf_mm.yaml``)
EXPECTED_VARIANCE_KEY = f"{KEY}.expected_variance"


def expected_variance_misfit(model: MotionModel, model_name: str | None = None) -> str | None:
    """Why ``filter.predict.expected_variance=true`` does not fit ``model`` (``None`` where it does): only a GP
    motion model (:class:`~dslearn.models.gp.GPMotionModel`, any variant, or the aggregated
    :class:`~dslearn.models.aggregated.AggregatedGPMotion`) has a state-dependent latent variance to average."""
    from dslearn.models.aggregated import AggregatedGPMotion
    from dslearn.models.gp import GPMotionModel

    if isinstance(model, (GPMotionModel, AggregatedGPMotion)):
        return None
    what = f"model={model_name}" if model_name else f"the motion model {type(model).__name__}"
    return (f"{EXPECTED_VARIANCE_KEY}=true (filter=ukf_mm) averages a GP motion model's latent variance over the "
            f"sigma points; {what} has no state-dependent process noise, so it would change nothing (use "
            f"{EXPECTED_VARIANCE_KEY}=false, filter=ukf, or a GP model: model=gp|gp_increment|gp_adaptive|gp_cv|"
            f"gp_window|gp_sgpr|gp_ssgp|gp_rbcm|gp_increment_rbcm)")


def ukf_predict(
    mean: Tensor,
    omega: Tensor,
    model: MotionModel,
    ctx: StepContext,
    full: bool = False,
    alpha: float = 1.0,
    beta: float = 2.0,
    kappa: float = 0.0,
    expected_variance: bool = False,
) -> tuple[Tensor, ...]:
    r"""Unscented prediction of an information-form belief (see the module docstring).

    Args:
        mean: ``(S, B, Dx)`` prior means; omega: ``(S, B, Dx, Dx)`` prior information.
        model: any :class:`~dslearn.models.base.MotionModel` (called as ``model(x, ctx)`` at the
            sigma points with ``ctx.cov`` the prior covariance, and ``model.noise_cov`` at the mean).
        alpha, beta, kappa: unscented parameters (defaults 1, 2, 0: :math:`\lambda = 0`, the
            centre point carries no mean weight and the points sit at :math:`\pm\sqrt{D_x}` standard
            deviations).
        expected_variance: ``Q`` the mean-weighted average of ``model.noise_cov`` over the sigma points
            instead of its value at the prior mean (a GP model only: ConfigError otherwise).
    Returns:
        ``(y_pred (S,B,Dx), q_pred (S,B,Dx), omega_pred (S,B,Dx,Dx))`` and with ``full`` also
        ``P_pred``, the statistical linearisation ``F`` and the process noise ``Q`` (all
        ``(S,B,Dx,Dx)``), as :func:`dslearn.filters.information.predict`.
    """
    check_unscented(alpha, beta, kappa, mean.shape[-1])
    if expected_variance:
        reason = expected_variance_misfit(model)
        if reason is not None:
            raise ConfigError(reason)
    P = spd_inverse(omega)
    pts, wm, wc, L = _sigma_points(mean, P, alpha, beta, kappa)
    gam = _propagate(model, pts, P, ctx)  # (S, B, K, Dx)
    y_pred = torch.einsum("k,...kd->...d", wm, gam)
    dy = gam - y_pred.unsqueeze(-2)
    if expected_variance:  # the unscented average of Q over the sigma points (moment matching)
        Q = torch.einsum("k,...kij->...ij", wm.to(mean.dtype), _noise_at(model, pts, P, ctx).to(mean.dtype))
    else:
        # Q at the prior mean, called last: a GP keeps the solve of this single query for the
        # data-set update that follows in track() (OnlineGP.append reuses it)
        Q = model.noise_cov(mean, dataclasses.replace(ctx, cov=P)).to(mean.dtype)
    P_pred = symmetrize(dy.transpose(-1, -2) @ (wc.unsqueeze(-1) * dy) + Q)
    omega_pred = spd_inverse(P_pred)
    q_pred = (omega_pred @ y_pred.unsqueeze(-1)).squeeze(-1)
    if not full:
        return y_pred, q_pred, omega_pred
    dx = pts - mean.unsqueeze(-2)
    P_xy = dx.transpose(-1, -2) @ (wc.unsqueeze(-1) * dy)  # (S, B, Dx, Dx); the centre has dx = 0
    F = torch.cholesky_solve(P_xy, L).transpose(-1, -2)  # P_xy^T P^{-1}, P = L L^T as sampled
    return y_pred, q_pred, omega_pred, P_pred, F, Q


def unscented_observation(obs, y_pred: Tensor, omega_pred: Tensor, num_agents: int, alpha: float = 1.0,
                          beta: float = 2.0, kappa: float = 0.0) -> tuple[Tensor, Tensor, Tensor]:
    r"""The unscented measurement step in information form: the observation model's statistical linearisation at
    every target's predicted marginal :math:`\mathcal N(\hat y_j, P_{jj})`, :math:`P = (\Omega^{t|t-1})^{-1}`.

    Sigma points :math:`\chi_k` of each target's block (:func:`sigma_points`, ``2d + 1`` points), through the
    sensor, :math:`Z_k = h(\chi_k)`; :math:`\bar z = \sum_k w^m_k Z_k`,
    :math:`P_{xz} = \sum_k w^c_k (\chi_k - \hat y_j)(Z_k - \bar z)^T`, :math:`P_{zz} = \sum_k w^c_k (Z_k - \bar z)(\cdot)^T`;
    the regression :math:`H = P_{xz}^T P_{jj}^{-1}` and its residual added to the sensor's noise,
    :math:`R' = R(\hat y_j) + P_{zz} - H P_{jj} H^T`. With ``(h, C, R) = (\bar z, H, R')`` the extended information
    update (:func:`~dslearn.filters.information.novel_information`) is the UKF's update of one sensor exactly
    (:math:`S = P_{zz} + R`, :math:`K = P_{xz} S^{-1}`); every node linearises its own sensor (the residuals of two
    sensors are taken as uncorrelated). Differences of readings are the model's ``residual`` (an angle wraps).

    Returns:
        ``h (S, B, A, Dz)``, ``C (S, B, A, Dz, d)``, ``R (S, B, A, Dz, Dz)``.
    """
    a = int(num_agents)
    d = y_pred.shape[-1] // a
    P = spd_inverse(omega_pred)
    yj = y_pred.unflatten(-1, (a, d))  # (S, B, A, d)
    blocks = P.unflatten(-2, (a, d)).unflatten(-1, (a, d))  # (S, B, A, d, A, d)
    Pjj = symmetrize(torch.diagonal(blocks, dim1=-4, dim2=-2).movedim(-1, -3))  # (S, B, A, d, d)
    pts, wm, wc, L = _sigma_points(yj, Pjj, alpha, beta, kappa)  # (S, B, A, K, d)
    zk = obs(pts)  # (S, B, A, K, Dz)
    centre = zk[..., :1, :]
    dzk = obs.residual(zk, centre)  # about the centre point's reading (an angle: no wrap inside the spread)
    mean_dz = torch.einsum("k,...kz->...z", wm, dzk)
    zbar = centre.squeeze(-2) + mean_dz
    dz = dzk - mean_dz.unsqueeze(-2)
    dx = pts - yj.unsqueeze(-2)
    P_xz = dx.transpose(-1, -2) @ (wc.unsqueeze(-1) * dz)  # (S, B, A, d, Dz)
    P_zz = dz.transpose(-1, -2) @ (wc.unsqueeze(-1) * dz)  # (S, B, A, Dz, Dz)
    H = torch.cholesky_solve(P_xz, L).transpose(-1, -2)  # P_xz^T Pjj^-1
    R = symmetrize(obs.noise_cov(yj) + P_zz - H @ P_xz)  # H Pjj H^T = H P_xz
    return zbar, H, R


@dataclass(frozen=True)
class UnscentedPredict:
    """:func:`ukf_predict` with fixed parameters, callable like
    :func:`dslearn.filters.information.predict` (``(mean, omega, model, ctx, full=False)``).

    Raises :class:`~dslearn.errors.ConfigError` on construction for ``alpha <= 0``, ``beta < 0``,
    a non-finite ``kappa`` (fields ``filter.predict.alpha`` / ``.beta`` / ``.kappa``) or an
    ``expected_variance`` that is not a boolean, and in :meth:`check_state_dim` or on the first call
    whose state dimension ``Dx`` has ``Dx + kappa <= 0``, before any model call. With
    ``expected_variance`` a motion model without a state-dependent process noise is refused
    (:meth:`model_misfit` / :meth:`check_model`: the start-up check, the matrix's n/a reason, the first call).
    Its :attr:`name` is ``ukf``, or ``ukf_mm`` with ``expected_variance`` (a
    :class:`~dslearn.filters.information.PredictionStep`).
    """

    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0
    expected_variance: bool = False

    def __post_init__(self) -> None:
        check_unscented(self.alpha, self.beta, self.kappa)
        if not isinstance(self.expected_variance, bool):
            raise ConfigError(f"{EXPECTED_VARIANCE_KEY}={self.expected_variance!r} must be true or false")

    @property
    def name(self) -> str:
        return "ukf_mm" if self.expected_variance else "ukf"

    @property
    def noise_at_mean(self) -> bool:
        """The UKF's process noise is the model's at the mean; with ``expected_variance`` its expectation."""
        return not self.expected_variance

    @property
    def differentiates_gp(self) -> bool:
        """With ``expected_variance`` it reads the GP's own predictive variance, not the differentiable posterior."""
        return not self.expected_variance

    def check_state_dim(self, state_dim: int) -> None:
        """ConfigError unless the parameters suit a state of ``state_dim`` (the start-up check's hook)."""
        check_unscented(self.alpha, self.beta, self.kappa, int(state_dim))

    def model_misfit(self, model: MotionModel, model_name: str | None = None) -> str | None:
        """Why this step does not fit ``model`` (``None`` where it does): only ``expected_variance`` asks anything."""
        return expected_variance_misfit(model, model_name) if self.expected_variance else None

    def check_model(self, model: MotionModel, model_name: str | None = None) -> None:
        reason = self.model_misfit(model, model_name)
        if reason is not None:
            raise ConfigError(reason)

    def observation_linearization(self, obs, y_pred: Tensor, omega_pred: Tensor, num_agents: int):
        """The unscented measurement step with these parameters (:func:`unscented_observation`): what the filter's
        update takes for a nonlinear sensor (``obs.linear`` false) that learns nothing online."""
        return unscented_observation(obs, y_pred, omega_pred, num_agents, self.alpha, self.beta, self.kappa)

    def __call__(self, mean: Tensor, omega: Tensor, model: MotionModel, ctx: StepContext, full: bool = False):
        return ukf_predict(mean, omega, model, ctx, full, self.alpha, self.beta, self.kappa,
                           expected_variance=self.expected_variance)
