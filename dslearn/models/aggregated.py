r"""GP motion model whose prediction aggregates every node's GP (issue 4, part 8).

The core study (Yu et al.) gives every node ``i`` its own online GP motion model
:math:`\mathcal{GP}_i` trained on its own (ŷ^{t-1} → ŷ^t) pairs (:class:`GPMotionModel`). Here node
``i``'s *prediction step* uses, instead of its own GP alone, the aggregation of **all** nodes'
GP predictive distributions evaluated at node ``i``'s state estimate, with one of the rules of
Liu et al. (FUSION 2022, Sec. II-B; :mod:`dslearn.fusion.aggregation`): PoE, gPoE, BCM or rBCM.
Communication: one round per step in which every node broadcasts its GP (or answers the other
nodes' queries with its predictive mean/variance); the measurement update stays local (or is
followed by any fusion strategy of the core).

For a query state :math:`x` and expert ``g`` (node ``g``'s GP), with prior mean :math:`m(x)`
(zero, or the identity for ``gp_increment``) the residual :math:`r_g = \mu_g(x) - m(x)` and
variance :math:`\sigma_g^2(x)` (latent, shared by all outputs) are aggregated per output
dimension, then :math:`m(x)` is added back, so the prior-correction terms of BCM/rBCM pull towards
the prior mean, as for a zero-mean GP. The prior variance :math:`\sigma_{**}^2` is the mean of the
nodes' outputscales (they are equal unless hyperparameters are refitted per node).

Jacobian of the aggregated mean (exact, needed by the EKF): the aggregated mean depends on every
expert's residual *and* variance (through the weights :math:`\beta_g` and the normaliser), so

.. math:: \frac{\partial \mu_A}{\partial x} = \frac{\partial m}{\partial x}
    + \sum_g \frac{\partial \mu_A}{\partial r_g}\frac{\partial r_g}{\partial x}
    + \sum_g \frac{\partial \mu_A}{\partial \sigma_g^2}\frac{\partial \sigma_g^2}{\partial x},

with :math:`\partial r_g/\partial x` the GP mean Jacobian and
:math:`\partial\sigma_g^2/\partial x` the gradient of its latent variance, both from the node
GPs' backend (:class:`~dslearn.models.gp_backends.protocol.GPBackend`: ``predict`` and ``variance_gradient``,
closed form for every variant: exact and window GP
:math:`2\sum_a c_a k(x, x_a)(x - x_a)/l^2` with :math:`c = (K + \sigma_\epsilon^2 I)^{-1} k_*`, SGPR
the same over the inducing inputs with :math:`c = (K_{uu}^{-1} - \Sigma^{-1}) k_u`, SSGP
:math:`2(\partial\phi/\partial x)^T A^{-1}\phi`), and the partials of the aggregation rule obtained by
autograd on :func:`dslearn.fusion.aggregation.aggregate` (a small elementwise graph).
``jacobian=frozen_weights`` drops the variance term (treats the weights as locally constant;
cheaper, approximate). Every backend works: ``model.variant=exact|window|sgpr|ssgp``.

The prediction is evaluated at each node's state (the belief's mean): ``model.inputs=belief`` is
refused, as is ``model.jacobian=autograd`` (the Jacobian is the one above, chosen by
``model.aggregation_jacobian``).

grBCM is not offered here: it needs a communication expert (a data subset shared by all
experts), which this setting does not have.
"""

from __future__ import annotations

import torch
from torch import Tensor

from dslearn.fusion.aggregation import aggregate
from dslearn.errors import ConfigError, check_choice
from dslearn.types import AGENT_DIM, StepContext
from dslearn.models.base import MotionModel
from dslearn.models.gp import GPMotionModel

RULES = ("poe", "gpoe", "bcm", "rbcm")
JACOBIANS = ("exact", "frozen_weights")


class AggregatedGPMotion(MotionModel):
    r"""Wraps a :class:`GPMotionModel` with ``S`` node GPs; node ``i`` predicts with the
    aggregation of all ``S`` GPs at its own state.

    Args:
        base: the per-node GP motion model (its data, hyperparameters, ``noise`` mode).
        method: aggregation rule, one of :data:`RULES`.
        normalise_beta: gPoE/rBCM with :math:`\beta_g / \sum_h \beta_h` instead of the raw Eq. 7.
        jacobian: ``exact`` (default) or ``frozen_weights`` (see the module docstring).

    Inputs have the node dimension first, ``(S, *B, Dx)``.
    """

    learnable = True

    def __init__(self, base: GPMotionModel, method: str = "rbcm", normalise_beta: bool = False,
                 jacobian: str = "exact"):
        super().__init__()
        if not isinstance(base, GPMotionModel):
            raise ConfigError("AggregatedGPMotion wraps a GPMotionModel (a model=gp* option)")
        check_aggregation(method, jacobian)
        if base.inputs != "mean":
            raise ConfigError(f"model.inputs={base.inputs} is not available for an aggregated GP (model.aggregation="
                              f"{method}): it aggregates the node GPs at the belief's mean; choose model.inputs=mean")
        if base.jacobian_mode != "closed_form":
            raise ConfigError(f"model.jacobian={base.jacobian_mode} is not available for an aggregated GP (model.aggregation="
                              f"{method}): its Jacobian is set by model.aggregation_jacobian (exact | frozen_weights); "
                              f"choose model.jacobian=closed_form")
        self.base = base
        self.method, self.normalise_beta, self.jacobian_mode = method, bool(normalise_beta), jacobian
        self.state_dim = base.state_dim

    # delegation ------------------------------------------------------------------------
    @property
    def num_nodes(self) -> int:
        return self.base.num_nodes

    @property
    def fit_every(self) -> int:
        return self.base.fit_every

    def add_data(self, inputs: Tensor, outputs: Tensor, valid: Tensor | None = None) -> None:
        self.base.add_data(inputs, outputs, valid)

    def reserve(self, appends: int) -> None:
        self.base.reserve(appends)

    def fit(self) -> "AggregatedGPMotion":
        self.base.fit()
        return self

    def save(self, path) -> None:
        self.base.save(path)

    def load(self, path) -> "AggregatedGPMotion":
        self.base.load(path)
        return self

    # prediction ------------------------------------------------------------------------
    def _aggregate(self, x: Tensor, jacobian: bool):
        """Mean (*x.shape), Jacobian (*x.shape, Dx) or None, variance (*x.shape[:-1], Dy)."""
        gp = self.base.gp
        s, dx = self.num_nodes, self.state_dim
        if x.shape[0] != s:
            raise ValueError(f"AggregatedGPMotion expects the node dimension first: got {tuple(x.shape)}, S={s}")
        ref = gp.outputscale
        xf = x.reshape(s, -1, dx).to(dtype=ref.dtype, device=ref.device)  # (S, N, Dx)
        nq = xf.shape[1]
        xq = xf.reshape(1, s * nq, dx).expand(s, s * nq, dx).contiguous()  # every state, every GP
        mean, var, jac = gp.predict(xq, jacobian=jacobian)  # (S, Q, Dy), (S, Q), (S, Q, Dy, Dx)
        pm = gp.prior_mean(xq)  # (S, Q, Dy)
        r = (mean - pm).permute(1, 2, 0)  # (Q, Dy, S) experts last
        dy = r.shape[1]
        v = var.transpose(0, 1).unsqueeze(1).expand(-1, dy, -1)  # (Q, Dy, S)
        mask = torch.ones_like(r, dtype=torch.bool)
        pv = gp.outputscale.mean().to(r)
        if not jacobian:
            am, av, _ = aggregate(r, v, mask, pv, self.method, self.normalise_beta)
            J = None
        else:
            r_ = r.detach().clone().requires_grad_(True)
            v_ = v.detach().clone().requires_grad_(True)
            with torch.enable_grad():
                am, av, _ = aggregate(r_, v_, mask, pv, self.method, self.normalise_beta)
                gr, gv = torch.autograd.grad(am.sum(), [r_, v_])
            am, av = am.detach(), av.detach()
            jr = jac - gp.prior_mean_jacobian(xq)  # (S, Q, Dy, Dx)
            J = torch.einsum("qos,sqod->qod", gr, jr)
            if self.jacobian_mode == "exact":
                J = J + torch.einsum("qos,sqd->qod", gv, gp.variance_gradient(xq))
            J = J + gp.prior_mean_jacobian(xq).mean(0)
            J = J.reshape(s, nq, dy, dx)
        # keep each node's own states: query q = i * N + n belongs to node i
        mean_out = (pm.mean(0) + am).reshape(s, nq, dy)
        var_out = av.reshape(s, nq, dy)
        return mean_out, J, var_out

    def linearize(self, x: Tensor, ctx: StepContext) -> tuple[Tensor, Tensor, Tensor]:
        """Aggregated mean, its Jacobian and :math:`Q = \\mathrm{diag}(\\sigma_A^2)` (+ noise if
        ``noise=predictive``) at each node's states ``x (S, *B, Dx)``."""
        mean, J, var = self._aggregate(x, jacobian=True)
        if self.base.noise_mode == "predictive":
            var = var + self.base.gp.noise_var.mean()
        q = torch.diag_embed(var)
        return (mean.reshape(x.shape).to(x.dtype), J.reshape(*x.shape, self.state_dim).to(x.dtype),
                q.reshape(*x.shape, self.state_dim).to(x.dtype))

    def forward(self, x: Tensor, ctx: StepContext) -> Tensor:
        mean, _, _ = self._aggregate(x, jacobian=False)
        return mean.reshape(x.shape).to(x.dtype)

    def noise_cov(self, x: Tensor, ctx: StepContext) -> Tensor:
        return self.linearize(x, ctx)[2]

    def jacobian(self, x: Tensor, ctx: StepContext) -> Tensor:
        return self.linearize(x, ctx)[1]


# ------------------------------------------------------------------------ config + runner
def check_aggregation(method: str, jacobian: str = "exact") -> None:
    """ConfigError naming ``model.aggregation`` / ``model.aggregation_jacobian`` and the allowed values."""
    if method == "grbcm":
        raise ConfigError(
            f"model.aggregation='grbcm' is not available for the aggregated GP motion model: grBCM needs a "
            f"communication expert (a data subset shared by every node), which this setting does not have; "
            f"choose one of {list(RULES)}"
        )
    check_choice("model.aggregation", method, RULES)
    check_choice("model.aggregation_jacobian", jacobian, JACOBIANS)


def aggregated_for_scenario(*, scenario, num_nodes: int, dtype, device, aggregation: str = "rbcm",
                            normalise_beta: bool = False, aggregation_jacobian: str = "exact",
                            **gp_keys) -> AggregatedGPMotion:
    """The config factory (``conf/model/gp*_rbcm.yaml``): the GP keys build every node's
    :class:`~dslearn.models.gp.GPMotionModel`; ``aggregation`` fuses their predictions."""
    check_aggregation(str(aggregation), str(aggregation_jacobian))  # before the node GPs are built
    if str(gp_keys.get("noise", "latent")) == "adaptive":
        raise ConfigError("model.noise='adaptive' is not available for an aggregated GP (model.aggregation="
                          f"{aggregation}); choose model.noise=latent or model.noise=predictive")
    base = GPMotionModel(AGENT_DIM * scenario.num_agents, num_nodes, dtype=dtype, device=device, **gp_keys)
    return AggregatedGPMotion(base, str(aggregation), bool(normalise_beta), str(aggregation_jacobian))


#: a GP that learns online (the keys it does not read: dslearn.schemas.base.hook_of)
aggregated_for_scenario.config_learns_online = True

