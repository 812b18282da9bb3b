r"""Moment-matching prediction step (GP-ADF) for the information filter.

A drop-in alternative to :func:`dslearn.filters.information.predict` and the unscented step
(:mod:`dslearn.filters.ukf`): same arguments, same return tuple, so
:func:`dslearn.filters.distributed.track` runs it at every node (``filter=adf``). It is the prediction
of the assumed density filter of Deisenroth, Huber & Hanebeck (*Analytic moment-based Gaussian process
filtering*, ICML 2009) for the network filter's GP motion model
(:class:`~dslearn.models.gp.GPMotionModel` over the exact :class:`~dslearn.models.gp_backends.exact.OnlineGP`):
the predicted belief is the Gaussian with the exact mean and covariance of the GP's prediction at the
belief :math:`y \sim \mathcal N(\hat y, P)`, :math:`P = \Omega^{-1}`.

Per node, the GP is :math:`f(y) = m(y) + g(y) + w`, with the affine prior mean
:math:`m(y) = A y + c` (zero, constant, identity or constant velocity), the posterior mean of the learned
part :math:`g(y) = k(y)^T \alpha`, :math:`k(y)_i = \sigma_f^2 \exp(-\|y - x_i\|^2 / 2 l^2)` over the ``n``
stored inputs (one isotropic SE kernel shared by the :math:`D_x` outputs), and the latent error
:math:`w \sim \mathcal N(0, \Sigma_f(y) I)`, :math:`\Sigma_f(y) = \sigma_f^2 - k^T (K + \sigma_\epsilon^2 I)^{-1} k`.
With :math:`q = \mathbb E[k(y)]` and :math:`J = \mathbb E[\partial f/\partial y]`
(:meth:`~dslearn.models.gp_backends.exact.OnlineGP.predict_belief`, closed form), :math:`J_g = J - A`:

.. math::
    \hat y^{t|t-1} = A \hat y + c + q^T \alpha,

    P^{t|t-1} = A P A^T + A P J_g^T + J_g P A^T
        + \alpha^T \mathbb E[k k^T] \alpha - \mathbb E[g]\,\mathbb E[g]^T
        + \big(\sigma_f^2 - \mathrm{tr}((K + \sigma_\epsilon^2 I)^{-1} \mathbb E[k k^T])\big) I + N,

where :math:`\mathrm{Cov}(y, g) = P J_g^T` is Stein's lemma and :math:`N` is what the model's noise mode
adds to the latent variance (``model.noise``: nothing for ``latent``, :math:`\sigma_\epsilon^2 I` for
``predictive``, the learned :math:`\mathrm{diag}(q)` for ``adaptive``: the same terms as
:meth:`~dslearn.models.gp.GPMotionModel.linearize`). For the shared isotropic kernel one ``n x n`` matrix
per query holds every output pair's expectation (Deisenroth's :math:`Q_{ab}` all equal):

.. math::
    \mathbb E[k_i k_j] = \sigma_f^4\, |I + 2P/l^2|^{-1/2}
        \exp\!\Big(-\frac{\|x_i - x_j\|^2}{4 l^2}
                   - \frac12 (\bar x_{ij} - \hat y)^T (P + \tfrac{l^2}{2} I)^{-1} (\bar x_{ij} - \hat y)\Big),
    \quad \bar x_{ij} = \tfrac12 (x_i + x_j).

The first factor of the exponent depends on the data only; it and :math:`(K + \sigma_\epsilon^2 I)^{-1}`
are kept per GP between calls (:class:`_Gram`) and extended by one row when the GP appended one
point since (an ``O(n^2)`` update through the GP's own factor; anything else, a refit or a new data
set, rebuilds them, ``O(n^3)``). A query then costs ``O(n^2 D_x)``; queries are processed in chunks so that
no temporary exceeds :data:`CHUNK_ELEMENTS` elements. Invalid (masked) data points contribute nothing.
The moments are computed in float64 whatever the run's dtype and returned in it.

With ``full=True`` the step also returns the statistical linearisation
:math:`F = \mathrm{Cov}(f(y), y) P^{-1} = J` (Stein) and :math:`Q = P^{t|t-1} - F P F^T`, the process
noise of the linearised model :math:`y' = \hat y^{t|t-1} + F (y - \hat y) + w`, :math:`w \sim \mathcal N(0, Q)`
(the Schur complement of the joint covariance: positive semi-definite), which is what the RTS smoother
and the EM step of ``noise=adaptive`` need (:func:`dslearn.filters.smoother.transition_error_moments`,
:meth:`~dslearn.models.gp.GPMotionModel.update_noise`).

Only the exact GP motion model has these moments here (:data:`ALLOWED_MODELS`); any other motion model is
refused with a :class:`~dslearn.errors.ConfigError` (:meth:`MomentMatchingPredict.model_misfit`: the start-up
check, the matrix's n/a cells and the first call).
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from dslearn.errors import ConfigError
from dslearn.models.base import MotionModel
from dslearn.types import StepContext, spd_inverse, symmetrize

#: the motion-model options (``conf/model``) whose models the ADF step takes: the exact GP, any prior mean
ALLOWED_MODELS = ("gp", "gp_increment", "gp_adaptive", "gp_cv")
#: the most elements of one ``(nodes, queries, n, n)`` temporary (float64: 128 MB)
CHUNK_ELEMENTS = 1 << 24
F64 = torch.float64


def adf_misfit(model: MotionModel, model_name: str | None = None) -> str | None:
    """Why ``filter=adf`` cannot run with ``model`` (one sentence naming the option and the allowed models),
    ``None`` where it can: the model must be a :class:`~dslearn.models.gp.GPMotionModel` over the exact
    :class:`~dslearn.models.gp_backends.exact.OnlineGP` (``model.variant=exact``)."""
    from dslearn.models.gp import GPMotionModel
    from dslearn.models.gp_backends.exact import OnlineGP

    if isinstance(model, GPMotionModel) and type(model.gp) is OnlineGP:
        return None
    what = f"model={model_name}" if model_name else f"the motion model {type(model).__name__}"
    if isinstance(model, GPMotionModel):
        what += f" (model.variant={model.variant})"
    allowed = "|".join(ALLOWED_MODELS)
    return (f"filter=adf (the GP-ADF prediction step) needs the exact GP motion model: model={allowed} "
            f"with model.variant=exact; {what} has no exact predictive moments (use filter=default or filter=ukf)")


# ------------------------------------------------------------------------------------------ data-only terms
@dataclass
class _Gram:
    """What the moments need of a GP's data set besides its ``alpha``: ``Kinv = (K + s^2 I)^{-1}`` and
    ``G_ij = exp(-|x_i - x_j|^2 / 4 l^2) m_i m_j`` (``m`` the validity mask), both ``(S, n, n)`` float64 views
    of buffers with room to grow, with the inputs, mask and hyperparameters they were built from."""

    X: Tensor
    mask: Tensor
    hypers: tuple[Tensor, Tensor, Tensor]
    K: Tensor  # (S, cap, cap): Kinv in the top-left n x n block
    Gb: Tensor  # (S, cap, cap): G likewise

    @property
    def n(self) -> int:
        return self.X.shape[1]

    @property
    def Kinv(self) -> Tensor:
        return self.K[:, : self.n, : self.n]

    @property
    def G(self) -> Tensor:
        return self.Gb[:, : self.n, : self.n]


_GRAMS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _hypers(gp) -> tuple[Tensor, Tensor, Tensor]:
    return gp._ls.reshape(-1), gp._os, gp._noise


def _same(a: tuple[Tensor, ...], b: tuple[Tensor, ...]) -> bool:
    return all(x.shape == y.shape and torch.equal(x, y) for x, y in zip(a, b))


def _g_matrix(A: Tensor, B: Tensor, ls: Tensor) -> Tensor:
    """``exp(-|a_i - b_j|^2 / 4 l^2)``: ``(S, na, D), (S, nb, D), (S,) -> (S, na, nb)`` (float64)."""
    a, b = A / ls.reshape(-1, 1, 1), B / ls.reshape(-1, 1, 1)
    d2 = (a * a).sum(-1).unsqueeze(-1) + (b * b).sum(-1).unsqueeze(-2) - 2.0 * a @ b.transpose(-1, -2)
    return torch.exp(-0.25 * d2.clamp_min(0.0))


def gram(gp) -> _Gram:
    """The :class:`_Gram` of ``gp``'s current data set: the one kept from the last call if the data and
    hyperparameters are the same, extended by one row if exactly one point was appended since, else rebuilt."""
    X, _, mask = gp.data()
    n = X.shape[1]
    hyp = tuple(h.detach().to(F64).clone() for h in _hypers(gp))
    X64 = X.to(F64)
    old = _GRAMS.get(gp)
    if old is not None and _same(old.hypers, hyp):
        m = old.n
        if m == n and torch.equal(old.X, X64) and torch.equal(old.mask, mask):
            return old
        if m == n - 1 and torch.equal(old.X, X64[:, :m]) and torch.equal(old.mask, mask[:, :m]):
            _extend(gp, old, X64, mask)
            return old
    s = gp.num_nodes
    eye = torch.eye(n, dtype=gp.dtype_, device=X.device).expand(s, n, n)
    K = X64.new_zeros(s, n, n)
    if n:
        K.copy_(symmetrize(gp.solve(eye.contiguous()).to(F64)))
    mm = mask.to(F64)
    G = _g_matrix(X64, X64, hyp[0]) * mm.unsqueeze(-1) * mm.unsqueeze(-2)
    new = _Gram(X64.clone(), mask.clone(), hyp, K, G)
    _GRAMS[gp] = new
    return new


def _extend(gp, g: _Gram, X64: Tensor, mask: Tensor) -> None:
    r"""Add to ``g``, in place, the point appended since. The new last column of :math:`K_n^{-1}` comes from
    the GP's own factor, :math:`c = K_n^{-1} e_n = (-b/d, 1/d)` with :math:`b = K^{-1} k`, :math:`d = \kappa - k^T b`;
    then :math:`K_n^{-1} = \begin{pmatrix} K^{-1} + c_{:n} c_{:n}^T / c_n & c_{:n} \\ c_{:n}^T & c_n \end{pmatrix}`
    (an invalid point is a decoupled unit row: :math:`c = e_n`). ``O(n^2)``; the buffers grow by half."""
    s, m = X64.shape[0], g.n
    n = m + 1
    if n > g.K.shape[-1]:
        cap = max(n, g.K.shape[-1] + max(64, g.K.shape[-1] // 2))
        for name in ("K", "Gb"):
            buf = X64.new_zeros(s, cap, cap)
            buf[:, :m, :m] = getattr(g, name)[:, :m, :m]
            setattr(g, name, buf)
    e = torch.zeros(s, n, 1, dtype=gp.dtype_, device=X64.device)
    e[:, m] = 1.0
    col = gp.solve(e)[..., 0].to(F64)  # (S, n)
    top = col[:, :m]
    g.K[:, :m, :m].addcmul_(top.unsqueeze(-1), (top / col[:, m:]).unsqueeze(-2))
    g.K[:, m, :n] = col
    g.K[:, :n, m] = col
    mm = mask.to(F64)
    row = _g_matrix(X64[:, m:], X64, g.hypers[0])[:, 0] * mm * mm[:, m:]  # (S, n)
    g.Gb[:, m, :n] = row
    g.Gb[:, :n, m] = row
    g.X, g.mask = X64.clone(), mask.clone()


# ------------------------------------------------------------------------------------------ the moments
def _void(gp) -> bool:
    """Whether no node of ``gp`` holds a valid point (where the GP skips its passes for them,
    :attr:`~dslearn.models.gp_backends.exact.OnlineGP.skip_void`)."""
    if gp._void():
        return True
    idx = gp._active()
    return idx is not None and idx.numel() == 0


def belief_moments(gp, x: Tensor, P: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    r"""Exact moments of the GP's prediction at :math:`y \sim \mathcal N(x, P)` (module docstring).

    Args:
        gp: an :class:`~dslearn.models.gp_backends.exact.OnlineGP`.
        x: ``(S, N, Dx)`` belief means (node dimension first); P: ``(S, N, Dx, Dx)`` their covariances.
    Returns:
        ``mean (S, N, Dy)`` :math:`\mathbb E[m(y) + g(y)]`, ``cov (S, N, Dy, Dy)`` :math:`\mathrm{Cov}[m(y) + g(y)]`
        (without the latent variance), ``jac (S, N, Dy, Dx)`` :math:`J = \mathbb E[\partial f/\partial y]`
        (:math:`\mathrm{Cov}(f(y), y) = J P`) and the expected latent variance ``var (S, N)``
        :math:`\mathbb E[\Sigma_f(y)] = \sigma_f^2 - \mathrm{tr}((K + \sigma_\epsilon^2 I)^{-1} \mathbb E[k k^T])`,
        all float64.
    """
    x, P = x.to(F64), P.to(F64)
    s, nq, dx = x.shape
    mean, _, jac = gp.predict_belief(x.to(gp.dtype_), P.to(gp.dtype_), jacobian=True, variance=False)
    mean, jac = mean.to(F64), jac.to(F64)
    A = gp.prior_mean_jacobian(x).to(F64)  # the affine prior mean's matrix (S, N, Dy, Dx)
    Jg = jac - A
    AP = A @ P
    cov = AP @ A.transpose(-1, -2) + AP @ Jg.transpose(-1, -2) + Jg @ AP.transpose(-1, -2)
    os_ = gp._os.to(F64)  # sigma_f^2 per node
    n = gp.n
    if n == 0 or _void(gp):  # no (valid) data: f = m(y) + w, w ~ N(0, sigma_f^2 I)
        # void: every stored point invalid, so E[g] = 0, E[k k^T] = 0 and the trace 0 at every node: the full
        # pass's numbers, without its O(S n^2) terms per query nor the data-only terms' upkeep (gram)
        return mean, symmetrize(cov), jac, os_.unsqueeze(-1).expand(s, nq).clone()
    Eg = mean - gp.prior_mean(x).to(F64)  # E[g(y)] = q^T alpha  (S, N, Dy)
    gr = gram(gp)
    X, alpha = gr.X, gp.alpha.to(F64)  # (S, n, Dx), (S, n, Dy); alpha is 0 at invalid points
    l2 = gr.hypers[0] ** 2  # (S,)
    eye = torch.eye(dx, dtype=F64, device=x.device)
    kk = x.new_empty(s, nq, alpha.shape[-1], alpha.shape[-1])
    tr = x.new_empty(s, nq)
    cs = max(1, min(s, CHUNK_ELEMENTS // (n * n)))
    cq = max(1, min(nq, CHUNK_ELEMENTS // (cs * n * n)))
    root2 = math.sqrt(2.0)
    for s0 in range(0, s, cs):
        sl = slice(s0, s0 + cs)
        Xs, al, G = X[sl].unsqueeze(1), alpha[sl].unsqueeze(1), gr.G[sl].unsqueeze(1)
        Kinv = gr.Kinv[sl].reshape(-1, 1, n * n, 1)  # for tr(Kinv Q) as one product (Kinv symmetric)
        half = (0.5 * l2[sl]).reshape(-1, 1, 1, 1)
        log_s4 = 2.0 * os_[sl].log().reshape(-1, 1)  # log sigma_f^4
        log_2l = (2.0 / l2[sl]).log().reshape(-1, 1)
        for q0 in range(0, nq, cq):
            ql = slice(q0, q0 + cq)
            W = P[sl, ql] + half * eye  # P + l^2/2 I  (cs, cq, Dx, Dx)
            Lw = torch.linalg.cholesky(W)
            diff = (Xs - x[sl, ql].unsqueeze(-2)).transpose(-1, -2)  # (cs, cq, Dx, n): x_i - y_hat
            ut = torch.linalg.solve_triangular(Lw, diff, upper=False).transpose(-1, -2)  # (cs, cq, n, Dx)
            nrm = (ut * ut).sum(-1, keepdim=True)  # (cs, cq, n, 1)
            # log sigma_f^4 |I + 2P/l^2|^{-1/2}, |I + 2P/l^2| = (2/l^2)^Dx |W|
            logc = log_s4 - Lw.diagonal(dim1=-2, dim2=-1).log().sum(-1) - 0.5 * dx * log_2l  # (cs, cq)
            one = torch.ones_like(nrm)
            # one product gives the exponent: a_i . b_j = |u_i + u_j|^2 - 8 log c, where
            # |u_i + u_j|^2 = n_i + n_j + 2 u_i.u_j = 4 (x_bar_ij - y_hat)^T W^{-1} (x_bar_ij - y_hat)
            a = torch.cat([root2 * ut, nrm, one, one], -1)
            b = torch.cat([root2 * ut, one, nrm, (-8.0 * logc)[..., None, None].expand_as(one)], -1)
            Q = (a @ b.transpose(-1, -2)).mul_(-0.125).exp_().mul_(G)  # E[k_i k_j]  (cs, cq, n, n)
            kk[sl, ql] = al.transpose(-1, -2) @ (Q @ al)
            tr[sl, ql] = (Q.reshape(*Q.shape[:2], 1, n * n) @ Kinv)[..., 0, 0]
    cov = cov + kk - Eg.unsqueeze(-1) * Eg.unsqueeze(-2)
    var = (os_.unsqueeze(-1) - tr).clamp_min(0.0)
    return mean, symmetrize(cov), jac, var


def _process_noise(model, var: Tensor) -> Tensor:
    """The diagonal ``(S, N, Dx)`` the model adds for a latent variance ``var (S, N)``: the latent variance on
    every output, plus :math:`\\sigma_\\epsilon^2` (``noise=predictive``) or the learned ``diag(q)``
    (``noise=adaptive``; :meth:`~dslearn.models.gp.GPMotionModel.extra_noise`), as ``linearize`` adds them."""
    if model.noise_mode == "predictive":
        var = var + model.gp.noise_var.to(var).unsqueeze(-1)
    d = var.unsqueeze(-1).expand(*var.shape, model.state_dim)
    return d + model.extra_noise(var).to(var).unsqueeze(1)  # zeros unless adaptive


def adf_predict(mean: Tensor, omega: Tensor, model: MotionModel, ctx: StepContext, full: bool = False):
    r"""The GP-ADF prediction of an information-form belief (module docstring).

    Args:
        mean: ``(S, B, Dx)`` prior means; omega: ``(S, B, Dx, Dx)`` prior information.
        model: the exact GP motion model (:func:`adf_misfit`: :class:`~dslearn.errors.ConfigError` otherwise).
    Returns:
        ``(y_pred (S,B,Dx), q_pred (S,B,Dx), omega_pred (S,B,Dx,Dx))`` and with ``full`` also ``P_pred``, the
        statistical linearisation ``F`` and ``Q = P_pred - F P F^T`` (all ``(S,B,Dx,Dx)``), in ``mean``'s dtype.
    """
    reason = adf_misfit(model)
    if reason is not None:
        raise ConfigError(reason)
    P = spd_inverse(omega)
    s, dx = model.num_nodes, model.state_dim
    if mean.shape[0] != s:
        raise ValueError(f"adf_predict expects the node dimension first: got {tuple(mean.shape)}, S={s}")
    x, Pf = mean.reshape(s, -1, dx), P.reshape(s, -1, dx, dx)
    m, cov, J, var = belief_moments(model.gp, x, Pf)
    P_pred = symmetrize(cov + torch.diag_embed(_process_noise(model, var))).reshape(P.shape).to(mean.dtype)
    y_pred = m.reshape(mean.shape).to(mean.dtype)
    omega_pred = spd_inverse(P_pred)
    q_pred = (omega_pred @ y_pred.unsqueeze(-1)).squeeze(-1)
    if not full:
        return y_pred, q_pred, omega_pred
    F = J.reshape(P.shape).to(mean.dtype)
    Q = symmetrize(P_pred - F @ P @ F.transpose(-1, -2))
    return y_pred, q_pred, omega_pred, P_pred, F, Q


@dataclass(frozen=True)
class MomentMatchingPredict:
    """:func:`adf_predict` as a config part (``conf/filter/adf.yaml``: ``predict``), callable like
    :func:`dslearn.filters.information.predict` (``(mean, omega, model, ctx, full=False)``).

    :meth:`model_misfit` says why a motion model does not fit (the matrix's n/a reason), :meth:`check_model`
    raises it as a :class:`~dslearn.errors.ConfigError` (the start-up check); a call with such a model raises it too.
    A :class:`~dslearn.filters.information.PredictionStep`.
    """

    name: ClassVar[str] = "adf"
    noise_at_mean: ClassVar[bool] = False
    differentiates_gp: ClassVar[bool] = False

    def model_misfit(self, model: MotionModel, model_name: str | None = None) -> str | None:
        return adf_misfit(model, model_name)

    def check_model(self, model: MotionModel, model_name: str | None = None) -> None:
        reason = adf_misfit(model, model_name)
        if reason is not None:
            raise ConfigError(reason)

    def __call__(self, mean: Tensor, omega: Tensor, model: MotionModel, ctx: StepContext, full: bool = False):
        return adf_predict(mean, omega, model, ctx, full=full)


__all__ = ["ALLOWED_MODELS", "MomentMatchingPredict", "adf_misfit", "adf_predict", "belief_moments", "gram"]
