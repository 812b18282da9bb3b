r"""Learning a distributed information filter by backpropagation (``learner=backprop``).

The filter is the project's own: :func:`dslearn.filters.distributed.track` (prediction,
:func:`~dslearn.filters.information.novel_information`, a :mod:`dslearn.fusion.strategies` fusion with its ``L``
rounds as ``W^L``) runs unchanged on parts whose numbers are tensors of a :class:`BackpropParameters` module, so
autograd follows the information filter and the consensus rounds; no step is written twice here. Learned:

- ``q``: the motion model's process noise, one agent block ``diag(exp(q_log))`` (4 values shared by the agents);
- ``r``: the sensors' noise ``R = L L^T`` with ``L`` log-Cholesky (2 x 2, shared by the nodes);
- ``weights``: the consensus weights, a masked softmax over each node's neighbours and itself (row-stochastic on
  the graph's edges by construction, zero off it), initialised at the configured rule's weights;
- ``omega``: the novel-information weight :math:`\omega = \exp(\cdot)` (fusions that use it: hybrid, cm);
- ``model``: the motion model's own parameters (:func:`motion_parameters`, one :class:`MotionParameters` per
  kind of model):

  * ``model=lin`` (constant velocity): its transition matrix ``F`` (one agent block, shared by the agents,
    initialised at the constant velocity matrix);
  * ``model=sfm`` (the social force): each agent's :math:`\tau` and :math:`\beta` (log) and :math:`\alpha`,
    initialised at the configured values (the desired velocities stay as given);
  * the exact GPs (``gp``, ``gp_increment``, ``gp_adaptive``, ``gp_cv``, ``gp_window``; ``inputs=mean``):
    each node's length scale, signal and noise variance (log). The data sets are first gathered online on
    the training episodes (Algorithm 1, as ``learner=online``), then held fixed while the hyperparameters
    learn through the filter; the posterior is refactorised from the data at every pass
    (:class:`DifferentiableGP`), so autograd follows the kernel matrix, its Cholesky factor, the mean, the
    latent variance (the filter's ``Q``) and the closed-form Jacobian;
  * ``model=lstm`` / ``social_lstm``: every weight of the encoder-decoder, after its offline fit (the
    model's own learner, ``fit_offline``): fine-tuned through the filter, its Jacobian differentiated once more
    (``create_graph``).

  Other motion models are refused at composition, with the reason. For a GP, ``q`` is refused: its process
  noise is its own predictive variance, learned through its hyperparameters.

Losses: ``innovation`` (measurements only, Yu et al.'s setting): the negative log-likelihood of every node's
innovations :math:`\nu = z - H\hat y^{t|t-1}`, :math:`\nu \sim \mathcal N(0, H P^{t|t-1} H^T + R)`, summed over the
nodes, targets seen and steps and divided by the number of terms; ``supervised``: the mean squared error of the
nodes' position estimates to the true positions (training episodes with truth).

Memory: ``chunk`` episodes per backward pass (:func:`fit`): a step's gradient accumulated chunk by chunk, each
chunk's loss sum divided by the whole step's term count, is the step's full-batch gradient, in one chunk's graph.
What does not shrink with the episodes is the parameters' own graph, rebuilt per chunk: an exact GP's factorised
posterior holds a few ``(S, n, n)`` matrices of its ``S`` nodes' ``n`` data points.
"""

from __future__ import annotations

import abc
import copy
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar

import torch
from torch import Tensor, nn

from dslearn.episodes import Episodes, Measurements
from dslearn.errors import ConfigError, check_choice
from dslearn.filters.distributed import TrackResult, track
from dslearn.filters.information import PredictionStep, prediction_step
from dslearn.filters.information import predict as ekf_predict
from dslearn.fusion.strategies import Fusion, make_fusion
from dslearn.learning import Learner
from dslearn.models.base import MotionModel, ObservationModel
from dslearn.models.kernels import se, sq_dist_inner
from dslearn.types import AGENT_DIM, POS, StepContext, agents, safe_cholesky

#: what ``learner.learn`` may list
LEARNABLE = ("q", "r", "weights", "omega", "model")
LOSSES = ("innovation", "supervised")
OPTIMIZERS = ("adam", "lbfgs")
#: where ``learner=backprop`` trains: through the configured consensus, or each node alone (then frozen)
TRAIN_FUSIONS = ("consensus", "individual")
#: the motion models (``conf/model`` options) whose parameters this learner can learn
SUPPORTED_MODELS = ("lin", "sfm", "gp", "gp_increment", "gp_adaptive", "gp_cv", "gp_window", "lstm", "social_lstm")
#: the prediction steps it can differentiate with a GP motion model (the GP-ADF and GP-UKF-MM read the
#: GP's own factor, not the differentiable posterior: :attr:`PredictionStep.differentiates_gp`), as named in messages
GP_STEPS = ("ekf", "ukf", "pf")
#: fusions with consensus weights (``weights``: those that run consensus rounds, :attr:`Fusion.mixes`) and with a
#: novel-information weight (``omega``: :attr:`Fusion.uses_omega`), as named in messages
WEIGHTED_FUSIONS = ("ce", "cm", "ci", "hybrid")
OMEGA_FUSIONS = ("cm", "hybrid")

_LOG = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------------ parametrisations
def graph_mask(adjacency: Tensor) -> Tensor:
    """``(S, S)`` bool: the graph's edges and every node itself (where a consensus weight may be non-zero)."""
    a = torch.as_tensor(adjacency).to(torch.bool)
    return a | torch.eye(a.shape[0], dtype=torch.bool, device=a.device)


def masked_softmax(logits: Tensor, mask: Tensor) -> Tensor:
    """Row-wise softmax over the entries of ``mask``: rows sum to 1, exact zeros off ``mask``."""
    return logits.masked_fill(~mask, float("-inf")).softmax(-1)


def weight_logits(weights: Tensor, mask: Tensor) -> Tensor:
    """Logits whose :func:`masked_softmax` is ``weights`` (positive on ``mask``, rows summing to 1)."""
    w = weights.to(torch.float64)
    if bool(((w <= 0) & mask).any()):
        raise ConfigError("learner=backprop: the initial consensus weights must be positive on the graph's edges")
    return torch.where(mask, w.clamp_min(1e-300).log(), torch.zeros_like(w))


def log_cholesky(raw: Tensor) -> Tensor:
    """SPD ``L L^T`` from an unconstrained square ``raw``: ``L`` = strict lower part + ``diag(exp(diag raw))``."""
    low = torch.tril(raw, -1) + torch.diag_embed(raw.diagonal(dim1=-2, dim2=-1).exp())
    return low @ low.transpose(-1, -2)


def log_cholesky_raw(cov: Tensor) -> Tensor:
    """Inverse of :func:`log_cholesky`."""
    low = torch.linalg.cholesky(cov)
    return torch.tril(low, -1) + torch.diag_embed(low.diagonal(dim1=-2, dim2=-1).log())


# -------------------------------------------------------------------------------------------- parts as tensors
class LinearMotion(MotionModel):
    """``x' = blockdiag(F_a, ..., F_a) x``, ``Q = blockdiag(Q_a, ...)``: a linear motion model whose agent block
    ``F_a`` and noise ``Q_a`` (4 x 4) are tensors (autograd follows them)."""

    def __init__(self, num_agents: int, f_block: Tensor, q_block: Tensor):
        super().__init__()
        self.num_agents, self.f_block, self.q_block = int(num_agents), f_block, q_block
        self.state_dim = AGENT_DIM * self.num_agents

    def _big(self, block: Tensor, x: Tensor) -> Tensor:
        eye = torch.eye(self.num_agents, dtype=x.dtype, device=x.device)
        return torch.kron(eye, block.to(x))

    def forward(self, x: Tensor, ctx: StepContext) -> Tensor:
        return x @ self._big(self.f_block, x).transpose(-1, -2)

    def jacobian(self, x: Tensor, ctx: StepContext) -> Tensor:
        f = self._big(self.f_block, x)
        return f.expand(*x.shape[:-1], *f.shape)

    def noise_cov(self, x: Tensor, ctx: StepContext) -> Tensor:
        q = self._big(self.q_block, x)
        return q.expand(*x.shape[:-1], *q.shape)


class LinearSensor(ObservationModel):
    """``z = y[:2] + nu``, ``nu ~ N(0, R)`` with ``R`` (2 x 2) a tensor (autograd follows it)."""

    linear = True

    def __init__(self, r: Tensor):
        super().__init__()
        self.r = r

    def forward(self, y: Tensor) -> Tensor:
        return y[..., :2]

    def jacobian(self, y: Tensor) -> Tensor:
        h = torch.eye(2, AGENT_DIM, dtype=y.dtype, device=y.device)
        return h.expand(*y.shape[:-1], *h.shape)

    def noise_cov(self, y: Tensor) -> Tensor:
        return self.r.to(y).expand(*y.shape[:-1], 2, 2)


class NoiseOverride(MotionModel):
    """``base``'s mean and Jacobian with the process noise ``Q = blockdiag(Q_a, ...)`` of a tensor ``Q_a``
    (4 x 4; ``learn: [q]`` for a model whose own noise is replaced)."""

    def __init__(self, base: MotionModel, q_block: Tensor):
        super().__init__()
        self.base, self.q_block = base, q_block
        self.state_dim, self.num_agents = base.state_dim, base.state_dim // AGENT_DIM

    def forward(self, x: Tensor, ctx: StepContext) -> Tensor:
        return self.base(x, ctx)

    def jacobian(self, x: Tensor, ctx: StepContext) -> Tensor:
        return self.base.jacobian(x, ctx)

    def noise_cov(self, x: Tensor, ctx: StepContext) -> Tensor:
        eye = torch.eye(self.num_agents, dtype=x.dtype, device=x.device)
        q = torch.kron(eye, self.q_block.to(x))
        return q.expand(*x.shape[:-1], *q.shape)

    def linearize(self, x: Tensor, ctx: StepContext) -> tuple[Tensor, Tensor, Tensor]:
        mean, jac, _ = self.base.linearize(x, ctx)
        return mean, jac, self.noise_cov(x, ctx)


class DifferentiableGP(MotionModel):
    r"""The posterior of a :class:`~dslearn.models.gp.GPMotionModel`'s exact GPs on fixed data sets, with the
    hyperparameters as tensors: :math:`K + \sigma_\epsilon^2 I` is factorised once per pass (the module is built
    per pass), so autograd follows the factor into the mean :math:`m(x) + k_*^T\alpha`, the latent variance
    :math:`\sigma_f^2 - \|L^{-1}k_*\|^2`, the closed-form Jacobian and the process noise of the model's noise
    mode (``latent``, ``predictive``: :math:`+\sigma_\epsilon^2`, ``adaptive``: + the model's fixed EM noise).
    Equals the model's own :meth:`~dslearn.models.gp_backends.exact.OnlineGP.predict` at the same numbers
    (tested). Inputs ``(S, *B, Dx)``, the node dimension first."""

    def __init__(self, base, X: Tensor, R: Tensor, mask: Tensor, lengthscale: Tensor, outputscale: Tensor,
                 noise: Tensor):
        super().__init__()
        self.base, self.state_dim = base, base.state_dim
        self.X, self.mask = X, mask
        self.ls, self.os, self.noise = lengthscale, outputscale, noise  # (S,) each
        m = mask.to(X.dtype)
        self.m = m
        n = X.shape[1]
        K = self._kernel(X, X) * (m.unsqueeze(-1) * m.unsqueeze(-2))
        eye = torch.eye(n, dtype=X.dtype, device=X.device)
        K = K + eye * (noise.reshape(-1, 1, 1) * m.unsqueeze(-1) + (1 - m).unsqueeze(-1))
        self.L = safe_cholesky(K)
        self.alpha = torch.cholesky_solve(R * m.unsqueeze(-1), self.L)  # (S, n, Dy)

    def _kernel(self, a: Tensor, b: Tensor) -> Tensor:
        """``(S, Na, d), (S, Nb, d) -> (S, Na, Nb)``: :math:`\\sigma_f^2 \\exp(-\\|a-b\\|^2 / 2l^2)`, by inner
        products (differentiable where ``a = b``, unlike the distance)."""
        return se(sq_dist_inner(a, b, self.ls.reshape(-1, 1, 1)), self.os.reshape(-1, 1, 1))

    def predict(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Mean ``(S, N, Dx)``, latent variance ``(S, N)``, Jacobian ``(S, N, Dx, Dx)`` at ``x (S, N, Dx)``."""
        gp = self.base.gp
        ks = self._kernel(self.X, x) * self.m.unsqueeze(-1)  # (S, n, N)
        ka = ks.transpose(-1, -2) @ self.alpha  # (S, N, Dy)
        mean = gp.prior_mean(x) + ka
        w = torch.linalg.solve_triangular(self.L, ks, upper=False)
        var = (self.os.unsqueeze(-1) - (w * w).sum(-2)).clamp_min(0.0)
        kax = torch.einsum("san,sao,sad->snod", ks, self.alpha, self.X)
        ls2 = (self.ls**2).reshape(-1, 1, 1, 1)
        jac = gp.prior_mean_jacobian(x) - (ka.unsqueeze(-1) * x.unsqueeze(-2) - kax) / ls2
        return mean, var, jac

    @property
    def num_nodes(self) -> int:
        """``S``: a per-node model (the UKF and PF steps put the node dimension first)."""
        return self.base.num_nodes

    def _flat(self, x: Tensor) -> Tensor:
        return self.base._flat(x)

    def linearize(self, x: Tensor, ctx: StepContext) -> tuple[Tensor, Tensor, Tensor]:
        mean, var, jac = self.predict(self._flat(x))
        if self.base.noise_mode == "predictive":
            var = var + self.noise.unsqueeze(-1)
        eye = torch.eye(self.state_dim, dtype=x.dtype, device=x.device)
        q = var.reshape(*x.shape[:-1], 1, 1) * eye
        if self.base.noise_mode == "adaptive":
            extra = self.base.extra_noise(x).reshape(x.shape[0], *([1] * (x.dim() - 2)), self.state_dim)
            q = q + torch.diag_embed(extra.expand(*x.shape))
        return mean.reshape(x.shape), jac.reshape(*x.shape, self.state_dim), q

    def forward(self, x: Tensor, ctx: StepContext) -> Tensor:
        return self.linearize(x, ctx)[0]

    def jacobian(self, x: Tensor, ctx: StepContext) -> Tensor:
        return self.linearize(x, ctx)[1]

    def noise_cov(self, x: Tensor, ctx: StepContext) -> Tensor:
        return self.linearize(x, ctx)[2]


def _graph_input(x: Tensor) -> Tensor:
    """``x`` itself where it is part of a graph (the belief's mean: its path stays), else a leaf that needs grad."""
    return x if x.requires_grad else x.detach().requires_grad_(True)


class DifferentiableJacobian(MotionModel):
    """``base`` with its autograd Jacobian kept in the graph (``create_graph``): the EKF's ``F`` is then
    differentiable in the model's parameters and in the belief it is taken at, not only its mean. Every row
    of ``F`` by reverse mode, or (``position_rows``, the LSTM) the ``2A`` position rows, the velocity rows
    being their finite difference as the model defines them."""

    def __init__(self, base: MotionModel, position_rows: bool = False):
        super().__init__()
        self.base, self.state_dim, self.position_rows = base, base.state_dim, bool(position_rows)

    def forward(self, x: Tensor, ctx: StepContext) -> Tensor:
        return self.base(x, ctx)

    def noise_cov(self, x: Tensor, ctx: StepContext) -> Tensor:
        return self.base.noise_cov(x, ctx)

    def linearize(self, x: Tensor, ctx: StepContext) -> tuple[Tensor, Tensor, Tensor]:
        with torch.enable_grad():
            z = _graph_input(x)
            y = self.base(z, ctx)
            out = agents(y)[..., POS].reshape(*y.shape[:-1], -1) if self.position_rows else y
            rows = [torch.autograd.grad(out[..., i].sum(), z, create_graph=True)[0] for i in range(out.shape[-1])]
        F = torch.stack(rows, -2)
        if self.position_rows:
            a = self.state_dim // AGENT_DIM
            jp = F.unflatten(-2, (a, 2))
            sel = torch.eye(self.state_dim, dtype=x.dtype, device=x.device).view(a, AGENT_DIM, -1)[:, POS]
            F = torch.cat([jp, (jp - sel) / self.base.dt], dim=-2).flatten(-3, -2)
        return y, F, self.noise_cov(x, ctx)

    def jacobian(self, x: Tensor, ctx: StepContext) -> Tensor:
        return self.linearize(x, ctx)[1]


class MotionParameters(nn.Module, abc.ABC):
    """The learnable numbers of one kind of motion model (``learner.learn: [model]``) and the differentiable
    model they give for a pass (:meth:`build`) or, detached, for tracking (:meth:`frozen`).
    ``q_block``: the learned agent block of ``Q`` replacing the model's own noise, or ``None``."""

    kind: ClassVar[str]
    #: whether ``learn: [q]`` applies (False: the model's noise is its own, e.g. a GP's predictive variance)
    takes_q: ClassVar[bool] = True
    #: whether its ``Q`` is always ``q``'s (learned or not; the linear model has no noise of its own)
    always_q: ClassVar[bool] = False

    @classmethod
    def of(cls, model: MotionModel, num_agents: int, dt: float) -> "MotionParameters":
        """The numbers of ``model`` (``A = num_agents`` targets, ``dt`` seconds per step)."""
        return cls(model)

    @classmethod
    def misfit(cls, model: MotionModel, predict: PredictionStep) -> str | None:
        """Why they cannot be learned for ``model`` under the prediction step ``predict`` (``None``: they can)."""
        return None

    @abc.abstractmethod
    def build(self, q_block: Tensor | None) -> MotionModel:
        """The differentiable model of one pass (its numbers in the graph)."""

    @abc.abstractmethod
    def frozen(self, q_block: Tensor | None) -> MotionModel:
        """The learned model, detached, for tracking."""

    @abc.abstractmethod
    def summary(self) -> dict[str, Any]:
        """The learned numbers as plain Python values."""


class LinearParameters(MotionParameters):
    """``model=lin``: the agent block ``F_a`` of the transition matrix (its ``Q`` is always ``q``'s)."""

    kind = "lin"
    always_q = True

    @classmethod
    def of(cls, model: MotionModel, num_agents: int, dt: float) -> "LinearParameters":
        return cls(num_agents, model.matrix(dt)[:AGENT_DIM, :AGENT_DIM])

    def __init__(self, num_agents: int, f_block: Tensor):
        super().__init__()
        self.num_agents = int(num_agents)
        self.f_block = nn.Parameter(f_block.detach().to(torch.float64).clone())

    def build(self, q_block: Tensor | None) -> LinearMotion:
        return LinearMotion(self.num_agents, self.f_block, q_block)

    def frozen(self, q_block: Tensor | None) -> LinearMotion:
        return LinearMotion(self.num_agents, self.f_block.detach().clone(), q_block.detach())

    def summary(self) -> dict[str, Any]:
        return {"f_block": self.f_block.detach().tolist()}


class SocialForceParameters(MotionParameters):
    r"""``model=sfm``: each agent's :math:`\log\tau`, :math:`\alpha`, :math:`\log\beta`
    (:meth:`~dslearn.models.social_force.SocialForce.set_parameters` keeps their graph)."""

    kind = "sfm"

    def __init__(self, model):
        super().__init__()
        self._template = (copy.deepcopy(model),)  # not a submodule: the numbers below are the parameters
        self.tau_log = nn.Parameter(model.tau.detach().to(torch.float64).log().clone())
        self.alpha = nn.Parameter(model.alpha.detach().to(torch.float64).clone())
        self.beta_log = nn.Parameter(model.beta.detach().to(torch.float64).log().clone())

    def numbers(self) -> tuple[Tensor, Tensor, Tensor]:
        return self.tau_log.exp(), self.alpha, self.beta_log.exp()

    def build(self, q_block: Tensor | None) -> MotionModel:
        m = DifferentiableJacobian(copy.deepcopy(self._template[0]).set_parameters(*self.numbers()))
        return m if q_block is None else NoiseOverride(m, q_block)

    def frozen(self, q_block: Tensor | None) -> MotionModel:
        with torch.no_grad():
            m = copy.deepcopy(self._template[0]).set_parameters(*(t.detach().clone() for t in self.numbers()))
        return m if q_block is None else NoiseOverride(m, q_block.detach())

    def summary(self) -> dict[str, Any]:
        tau, alpha, beta = (t.detach().tolist() for t in self.numbers())
        return {"sfm": {"tau": tau, "alpha": alpha, "beta": beta}}


class GPParameters(MotionParameters):
    """An exact GP motion model's hyperparameters per node (log length scale, signal and noise variance) on
    the data sets it holds now (gathered online before; fixed while they learn). :meth:`frozen` writes them
    into the model and refactorises its online GP once; a noise variance below GPyTorch's constraint is
    raised to it (logged)."""

    kind = "gp"
    takes_q = False

    @classmethod
    def misfit(cls, model: MotionModel, predict: PredictionStep) -> str | None:
        """Only under a prediction step that differentiates the GP's posterior."""
        if not predict.differentiates_gp:
            return f"a GP under filter={predict.name} (the GP's steps: {'|'.join(GP_STEPS)})"
        return None

    def __init__(self, model):
        super().__init__()
        self._model = (model,)
        gp = model.gp
        X, R, mask = gp.data()
        self.register_buffer("X", X.detach().to(torch.float64).clone())
        self.register_buffer("R", R.detach().to(torch.float64).clone())
        self.register_buffer("data_mask", mask.detach().clone())
        self.ls_log = nn.Parameter(gp.lengthscale.to(torch.float64).log().clone())
        self.os_log = nn.Parameter(gp.outputscale.to(torch.float64).log().clone())
        self.noise_log = nn.Parameter(gp.noise_var.to(torch.float64).log().clone())

    def numbers(self) -> tuple[Tensor, Tensor, Tensor]:
        return self.ls_log.exp(), self.os_log.exp(), self.noise_log.exp()

    def build(self, q_block: Tensor | None) -> DifferentiableGP:
        return DifferentiableGP(self._model[0], self.X, self.R, self.data_mask, *self.numbers())

    def frozen(self, q_block: Tensor | None):
        model = self._model[0]
        gp = model.gp
        ls, os_, noise = (t.detach() for t in self.numbers())
        floor = float(gp.likelihood.noise_covar.raw_noise_constraint.lower_bound)
        if bool((noise < floor).any()):
            _LOG.warning("learner=backprop: GP noise variance %s raised to GPyTorch's lower bound %g",
                         noise.tolist(), floor)
            noise = noise.clamp_min(floor * (1 + 1e-9))
        kw = dict(dtype=gp.dtype_, device=gp.device_)
        gp.covar_module.base_kernel.lengthscale = ls.reshape(-1, 1, 1).to(**kw)
        gp.covar_module.outputscale = os_.to(**kw)
        gp.likelihood.noise = noise.reshape(-1, 1).to(**kw)
        gp.refactorize()
        return model

    def summary(self) -> dict[str, Any]:
        ls, os_, noise = (t.detach().tolist() for t in self.numbers())
        return {"gp": {"lengthscale": ls, "outputscale": os_, "noise_var": noise}}


class LSTMParameters(MotionParameters):
    """``model=lstm`` / ``social_lstm``: every weight of a copy of the (offline-fitted) encoder-decoder."""

    kind = "lstm"

    def __init__(self, model):
        super().__init__()
        self.lstm = copy.deepcopy(model).to(torch.float64)

    def build(self, q_block: Tensor | None) -> MotionModel:
        m = DifferentiableJacobian(self.lstm, position_rows=True)
        return m if q_block is None else NoiseOverride(m, q_block)

    def frozen(self, q_block: Tensor | None) -> MotionModel:
        m = copy.deepcopy(self.lstm).requires_grad_(False)
        return m if q_block is None else NoiseOverride(m, q_block.detach())

    def summary(self) -> dict[str, Any]:
        return {"lstm_weights": int(sum(p.numel() for p in self.lstm.parameters()))}


#: the numbers a motion model may declare trainable (:attr:`~dslearn.models.base.MotionModel.gradient_parameters`)
MOTION_PARAMETERS = {c.kind: c for c in (LinearParameters, SocialForceParameters, GPParameters, LSTMParameters)}


def declared_parameters(model: MotionModel) -> type[MotionParameters] | None:
    """The :class:`MotionParameters` class of the numbers ``model`` declares trainable (``None``: none)."""
    kind = model.gradient_parameters
    return None if kind is None else MOTION_PARAMETERS[kind]


def motion_misfit(model: MotionModel, predict: PredictionStep | None = None) -> str | None:
    """Why ``learner=backprop`` cannot learn ``model``'s parameters under the prediction step ``predict`` (``None``:
    the EKF's), ``None`` where it can: the numbers the model declares trainable
    (:attr:`~dslearn.models.base.MotionModel.gradient_parameters`), what it says against it
    (:meth:`~dslearn.models.base.MotionModel.gradient_misfit`), what those numbers need of the step."""
    params = declared_parameters(model)
    if params is None:
        return f"{type(model).__name__} has no differentiable parameters here"
    return model.gradient_misfit() or params.misfit(model, prediction_step(predict))


def takes_q(model: MotionModel) -> bool:
    """Whether ``learn: [q]`` applies to ``model`` (:attr:`MotionParameters.takes_q` of the numbers it declares
    trainable: not for a GP)."""
    params = declared_parameters(model)
    return params is None or params.takes_q


def motion_parameters(model: MotionModel, num_agents: int, dt: float) -> MotionParameters:
    """The :class:`MotionParameters` of ``model`` (:func:`motion_misfit` first): the numbers it declares trainable."""
    params = declared_parameters(model)
    if params is None:
        raise ConfigError(motion_misfit(model))
    return params.of(model, num_agents, dt)


class BackpropParameters(nn.Module):
    """The learnable numbers of a distributed filter with position sensors, in float64.

    Args:
        num_agents: targets ``A`` (state ``4A``).
        f_block, q_block: the linear motion model's agent block (used where ``motion`` is ``None``) and the
            initial process noise (4 x 4; its diagonal is learned, its off-diagonal entries are dropped).
        r: the sensors' noise covariance (2 x 2).
        fusion: the configured fusion (its class, ``L`` and rule weights and omega are the initial values).
        adjacency: ``(S, S)`` communication graph.
        learn: which of :data:`LEARNABLE` get gradients (the others stay at their initial values).
        motion: the motion model's numbers (:func:`motion_parameters`); ``None``: ``model=lin`` with ``f_block``.
            For a model other than ``lin``, the learned ``Q`` replaces the model's own noise only where
            ``learn`` lists ``q``; a model without ``q`` (:attr:`MotionParameters.takes_q`) refuses it.
    """

    def __init__(self, num_agents: int, f_block: Tensor | None, q_block: Tensor, r: Tensor, fusion: Fusion,
                 adjacency: Tensor, learn=("q", "r"), motion: MotionParameters | None = None):
        super().__init__()
        dt = torch.float64
        self.num_agents, self.base_fusion = int(num_agents), fusion
        self.register_buffer("mask", graph_mask(adjacency))
        self.motion_params = motion if motion is not None else LinearParameters(num_agents, f_block)
        self.q_log = nn.Parameter(q_block.detach().to(dt).diagonal().log().clone())
        self.r_raw = nn.Parameter(log_cholesky_raw(r.detach().to(dt)))
        self.logits = nn.Parameter(weight_logits(torch.as_tensor(fusion.weights), self.mask))
        self.omega_log = nn.Parameter(torch.tensor(math.log(float(fusion.omega)), dtype=dt))
        self.set_learn(learn)

    def set_learn(self, learn) -> None:
        learn = tuple(learn)
        if "q" in learn and not self.motion_params.takes_q:
            raise ConfigError(f"learner.learn=[q]: the {self.motion_params.kind} motion model's process noise is "
                              f"its own predictive variance (learned through model); drop q")
        self.learn = learn
        names = {"q": "q_log", "r": "r_raw", "weights": "logits", "omega": "omega_log"}
        for k, p in names.items():
            getattr(self, p).requires_grad_(k in learn)
        self.motion_params.requires_grad_("model" in learn)

    @property
    def f_block(self) -> Tensor:
        """The linear model's agent block (``model=lin``)."""
        return self.motion_params.f_block

    def _q_block(self) -> Tensor | None:
        """The agent block of ``Q`` a pass uses: ``q``'s (always for ``lin``, else where ``q`` is learned) or
        ``None`` (the model's own noise)."""
        return self.Q() if self.motion_params.always_q or "q" in self.learn else None

    # the numbers
    def Q(self) -> Tensor:
        return torch.diag_embed(self.q_log.exp())

    def R(self) -> Tensor:
        return log_cholesky(self.r_raw)

    def W(self) -> Tensor:
        return masked_softmax(self.logits, self.mask)

    def omega(self) -> Tensor:
        return self.omega_log.exp()

    # the parts
    def motion(self) -> MotionModel:
        return self.motion_params.build(self._q_block())

    def observation(self) -> LinearSensor:
        return LinearSensor(self.R())

    def fusion(self) -> Fusion:
        """The configured fusion strategy (same class, same ``L``) with ``W^L`` and omega from the parameters."""
        f = copy.copy(self.base_fusion)
        if f.mixes:  # consensus weights
            w = self.W()
            f.weights, f.wl = w, torch.linalg.matrix_power(w, f.iterations)
        if f.uses_omega:
            f.omega = self.omega()
        return f

    def detached(self) -> tuple[MotionModel, LinearSensor, Fusion]:
        """The learned parts with plain tensors (for tracking the test episodes)."""
        with torch.no_grad():
            f = self.fusion()
            for k in ("weights", "wl", "omega"):
                if isinstance(getattr(f, k, None), Tensor):
                    setattr(f, k, getattr(f, k).detach().clone())
            if isinstance(f.omega, Tensor):
                f.omega = float(f.omega)
            q = self._q_block()
            return (self.motion_params.frozen(None if q is None else q.detach()), LinearSensor(self.R().detach()), f)

    def summary(self) -> dict[str, Any]:
        with torch.no_grad():
            return {"q_diag": self.q_log.exp().tolist(), "r": self.R().tolist(), "omega": float(self.omega()),
                    "weights": self.W().tolist(), **self.motion_params.summary()}


# --------------------------------------------------------------------------------------------------- the losses
def agent_blocks(P: Tensor) -> Tensor:
    """``(*B, 4A, 4A) -> (*B, A, 4, 4)``: each target's own covariance block."""
    a = P.shape[-1] // AGENT_DIM
    blocks = P.unflatten(-2, (a, AGENT_DIM)).unflatten(-1, (a, AGENT_DIM))  # (..., A, 4, A, 4)
    return torch.diagonal(blocks, dim1=-4, dim2=-2).movedim(-1, -3)


def innovation_nll(y_pred: Tensor, P_pred: Tensor, meas: Tensor, visible: Tensor,
                   obs: ObservationModel) -> tuple[Tensor, Tensor]:
    r"""Sum and count of the Gaussian negative log-likelihoods of the innovations of one step: node ``i``'s
    measurement of target ``j``, :math:`\nu = z - h(\hat y_j)`, :math:`S = C P_{jj} C^T + R`.
    ``y_pred (S, B, Dx)``, ``P_pred (S, B, Dx, Dx)``, ``meas (S, B, A, Dz)``, ``visible (S, B, A)``."""
    yj = agents(y_pred)
    h, C, R = obs.linearize(yj)
    S_cov = C @ agent_blocks(P_pred) @ C.transpose(-1, -2) + R
    S_cov = 0.5 * (S_cov + S_cov.transpose(-1, -2))
    chol = torch.linalg.cholesky(S_cov)
    white = torch.linalg.solve_triangular(chol, (meas - h).unsqueeze(-1), upper=False).squeeze(-1)
    dz = meas.shape[-1]
    nll = 0.5 * (white.pow(2).sum(-1) + 2 * chol.diagonal(dim1=-2, dim2=-1).log().sum(-1) + dz * math.log(2 * math.pi))
    m = visible.to(nll.dtype)
    return (nll * m).sum(), m.sum()


@dataclass
class Run:
    """One differentiable pass: the filter's result and the loss terms."""

    result: TrackResult
    nll_sum: Tensor
    nll_count: Tensor


def run_filter(params: BackpropParameters, ep: Measurements, network, ctx: StepContext,
               init: Callable[[Measurements, Fusion], tuple[Tensor, Tensor]], first_step: int = 2,
               predict_step=None) -> Run:
    """Track ``ep`` with the parameters' parts through :func:`~dslearn.filters.distributed.track` (autograd on)
    and collect the innovation terms of the steps ``t >= first_step`` (``init(ep, fusion)``: the initial belief)."""
    motion, obs, fusion = params.motion(), params.observation(), params.fusion()
    step_of = predict_step or ekf_predict
    terms = []

    def step(y, o, model, ctx, full=False):  # the filter's prediction step, its prediction recorded
        out = step_of(y, o, model, ctx, full=True)
        t = len(terms) + 1
        terms.append(None if t < first_step else (t, out[0], out[3]))
        return out if full else out[:3]

    res = track(ep, network, motion, obs, fusion, ctx, init(ep, fusion), predict_step=step)
    total = torch.zeros((), dtype=ep.meas.dtype, device=ep.meas.device)
    count = torch.zeros((), dtype=ep.meas.dtype, device=ep.meas.device)
    for item in terms:
        if item is None:
            continue
        t, y_pred, P_pred = item
        s, c = innovation_nll(y_pred, P_pred, ep.meas[:, :, t], ep.visible[:, :, t], obs)
        total, count = total + s, count + c
    return Run(res, total, count)


def supervised_mse(result: TrackResult, states: Tensor, first_step: int = 1) -> Tensor:
    """Mean squared error of every node's position estimates to the true positions (steps ``>= first_step``)."""
    est = agents(result.mean[:, :, first_step:])[..., :2]  # (S, B, K', A, 2)
    truth = agents(states[:, first_step:])[..., :2].unsqueeze(0)
    return (est - truth).pow(2).sum(-1).mean()


def supervised_sse(result: TrackResult, states: Tensor, first_step: int = 1) -> tuple[Tensor, int]:
    """Sum and count of the squared errors :func:`supervised_mse` averages (its terms: nodes, episodes, steps
    ``>= first_step``, targets), for a chunk of a step's episodes."""
    est = agents(result.mean[:, :, first_step:])[..., :2]  # (S, B, K', A, 2)
    truth = agents(states[:, first_step:])[..., :2].unsqueeze(0)
    sq = (est - truth).pow(2).sum(-1)
    return sq.sum(), sq.numel()


def loss_terms(meas: Measurements, idx: Tensor, loss: str, first_step: int = 2) -> float:
    """The number of terms the loss of the episodes ``idx`` is normalised by, known before any pass (it depends on
    no learned number): the innovations of the visible targets at the steps ``t >= first_step`` (``innovation``,
    at least 1 as the loss clamps it), or every node's, episode's, step's (``>= 1``) and target's squared error
    (``supervised``)."""
    vis = meas.visible[:, idx]  # (S, B, K+1, A)
    if loss == "innovation":
        return max(float(vis[:, :, first_step:].sum()), 1.0)
    s, b, k1, a = vis.shape
    return float(s * b * max(k1 - 1, 0) * a)


# ------------------------------------------------------------------------------------------------- training
@dataclass
class FitHistory:
    loss: list[float] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)

    @property
    def seconds_per_epoch(self) -> float:
        return sum(self.seconds) / max(len(self.seconds), 1)


def fit(params: BackpropParameters, train: Episodes | Measurements, network, ctx: StepContext,
        init: Callable[[Measurements, Fusion], tuple[Tensor, Tensor]], *, epochs: int = 50, lr: float = 0.05,
        batch: int | None = None, loss: str = "innovation", seed: int = 0, first_step: int = 2,
        predict_step=None, optimizer: str = "adam", model_lr: float | None = None,
        chunk: int | None = None) -> FitHistory:
    """Adam on the learnable parameters; each epoch visits the training episodes once in a seeded random order,
    ``batch`` episodes per step (``None``: all). ``optimizer=lbfgs``: full-batch L-BFGS (strong Wolfe line
    search), ``epochs`` outer steps of up to 20 iterations each, ``lr`` its initial step.
    ``loss=supervised`` needs :class:`~dslearn.episodes.Episodes`. ``model_lr``: Adam's step size for the motion
    model's own parameters (``None``: ``lr``; an LSTM's weights want a far smaller one than the log-noises).

    ``chunk``: episodes per backward pass (``None``: all of the step's episodes in one pass). A step's episodes
    are then tracked ``chunk`` at a time, each chunk's loss sum divided by the whole step's term count
    (:func:`loss_terms`) and backpropagated at once, so that its graph is freed before the next chunk; the
    gradients accumulate to the step's full-batch gradient (exactly in exact arithmetic: the episodes are
    independent given the parameters, and the loss is a sum over them divided by a count no parameter moves),
    then one optimiser step. Peak memory is one chunk's graph instead of the step's. The parameters' own parts
    (a GP's factorised posterior, ``W^L``) are rebuilt per chunk. Exact for the deterministic prediction steps;
    the particle step draws its particles per pass, so chunks draw other particles than the whole batch would."""
    check_choice("learner.loss", loss, LOSSES)
    check_choice("learner.optimizer", optimizer, OPTIMIZERS)
    if chunk is not None and (isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1):
        raise ConfigError(f"learner.chunk={chunk!r} must be an integer >= 1 or null (all of a step's episodes)")
    if loss == "supervised" and not isinstance(train, Episodes):
        raise ConfigError("learner.loss=supervised needs training episodes with their true states")
    meas = train.measurements if isinstance(train, Episodes) else train
    trainable = [p for p in params.parameters() if p.requires_grad]
    hist = FitHistory()
    if not trainable or epochs == 0:
        return hist
    gen = torch.Generator().manual_seed(int(seed))
    n = len(meas)

    def objective(idx: Tensor) -> Tensor:
        run = run_filter(params, meas.select(idx), network, ctx, init, first_step, predict_step)
        if loss == "innovation":
            return run.nll_sum / run.nll_count.clamp_min(1.0)
        return supervised_mse(run.result, train.states[idx])

    def accumulate(idx: Tensor) -> Tensor:
        """The step's loss on the episodes ``idx``, its gradient accumulated into ``.grad`` (``chunk`` episodes per
        backward pass, each chunk's share scaled by the step's term count: the full-batch gradient)."""
        if chunk is None or chunk >= len(idx):
            value = objective(idx)
            value.backward()
            return value.detach()
        terms = loss_terms(meas, idx, loss, first_step)
        total, counted = torch.zeros((), dtype=meas.meas.dtype, device=meas.meas.device), 0.0
        for part in idx.split(int(chunk)):
            run = run_filter(params, meas.select(part), network, ctx, init, first_step, predict_step)
            if loss == "innovation":
                s, c = run.nll_sum, float(run.nll_count)
            else:
                s, c = supervised_sse(run.result, train.states[part])
            (s / terms).backward()
            total, counted = total + s.detach(), counted + c
            del run, s
        if max(counted, 1.0) != terms:  # the count known up front is the one the passes summed
            raise RuntimeError(f"learner.chunk: the chunks counted {counted} loss terms, the step {terms}")
        return total / terms

    if optimizer == "lbfgs":
        opt = torch.optim.LBFGS(trainable, lr=lr, max_iter=20, line_search_fn="strong_wolfe")
        every = torch.arange(n, device=meas.meas.device)

        def closure():
            opt.zero_grad()
            return accumulate(every)

        for _ in range(epochs):
            t0 = time.perf_counter()
            hist.loss.append(float(opt.step(closure).detach()))
            hist.seconds.append(time.perf_counter() - t0)
        return hist
    own = {id(p) for p in params.motion_params.parameters()}
    groups = [{"params": [p for p in trainable if id(p) not in own]},
              {"params": [p for p in trainable if id(p) in own], "lr": lr if model_lr is None else model_lr}]
    opt = torch.optim.Adam([g for g in groups if g["params"]], lr=lr)
    size = n if batch is None else min(int(batch), n)
    for _ in range(epochs):
        t0, total = time.perf_counter(), 0.0
        order = torch.randperm(n, generator=gen)
        for i in range(0, n, size):
            idx = order[i:i + size].to(meas.meas.device)
            opt.zero_grad()
            value = accumulate(idx)
            opt.step()
            total += float(value) * len(idx)
        hist.loss.append(total / n)
        hist.seconds.append(time.perf_counter() - t0)
    return hist


# ---------------------------------------------------------------------------------------------- the learner
@dataclass
class BackpropLearning(Learner):
    """Learn the distributed filter's numbers by backpropagating through the information filter and the ``L``
    consensus rounds on the training episodes, then track with them (``conf/learner/backprop.yaml``).

    Args:
        epochs: passes over the training episodes.
        lr: Adam's step size (on the log-parametrised numbers).
        batch: episodes per Adam step (``null``: all of them).
        loss: ``innovation`` (measurements only) | ``supervised`` (MSE to the training episodes' true positions).
        learn: which of ``q``, ``r``, ``weights``, ``omega``, ``model`` are learned.
        train_fusion: ``consensus`` (end to end: the loss backpropagates through the configured fusion and its
            ``L`` rounds) | ``individual`` (every node trains on its own measurements with no consensus, the
            numbers shared by the nodes; they are then frozen and tracked with the configured fusion: "train
            each node offline, then run consensus"; learns no consensus numbers, so ``learn`` lists neither
            ``weights`` nor ``omega``).
        model_lr: Adam's step size for the motion model's own parameters (``learn: [model]``); ``null``: ``lr``.
        chunk: episodes per backward pass within a step (``null``: all of the step's ``batch`` episodes at once).
            The same gradient, accumulated chunk by chunk (each chunk's loss scaled by the step's term count),
            then one step: memory for one chunk's graph instead of the step's (:func:`fit`).
    """

    name: ClassVar[str] = "backprop"
    learns_through_update = True
    #: the motion model still gathers its data online first (a GP, Algorithm 1;
    #: :func:`dslearn.schemas.base.online_learning`)
    config_online_parts: ClassVar[tuple] = ("model",)

    epochs: int = 30
    lr: float = 0.05
    batch: Any = None
    loss: str = "innovation"
    learn: Any = field(default_factory=lambda: ["q", "r", "weights", "omega"])
    train_fusion: str = "consensus"
    model_lr: Any = None
    chunk: Any = None

    @property
    def runs_nodes_alone(self) -> bool:
        """``train_fusion=individual`` trains every node's filter alone (:attr:`Learner.runs_nodes_alone`)."""
        return self.train_fusion == "individual"

    def __post_init__(self) -> None:
        if isinstance(self.epochs, bool) or not isinstance(self.epochs, int) or self.epochs < 0:
            raise ConfigError(f"learner.epochs={self.epochs!r} must be an integer >= 0")
        if isinstance(self.lr, bool) or not isinstance(self.lr, (int, float)) or not 0 < self.lr < float("inf"):
            raise ConfigError(f"learner.lr={self.lr!r} must be a finite number > 0")
        if self.model_lr is not None and (isinstance(self.model_lr, bool) or not isinstance(self.model_lr, (int, float))
                                          or not 0 < self.model_lr < float("inf")):
            raise ConfigError(f"learner.model_lr={self.model_lr!r} must be a finite number > 0 or null (= learner.lr)")
        if self.batch is not None and (isinstance(self.batch, bool) or not isinstance(self.batch, int)
                                       or self.batch < 1):
            raise ConfigError(f"learner.batch={self.batch!r} must be an integer >= 1 or null (all episodes)")
        if self.chunk is not None and (isinstance(self.chunk, bool) or not isinstance(self.chunk, int)
                                       or self.chunk < 1):
            raise ConfigError(f"learner.chunk={self.chunk!r} must be an integer >= 1 or null (all of a step's "
                              f"episodes in one backward pass)")
        check_choice("learner.loss", self.loss, LOSSES)
        learn = [self.learn] if isinstance(self.learn, str) else list(self.learn or [])
        bad = [k for k in learn if k not in LEARNABLE]
        if bad or len(set(learn)) != len(learn):
            raise ConfigError(f"learner.learn={learn!r}: each of {list(LEARNABLE)} at most once")
        self.learn = learn
        if self.model_lr is not None and "model" not in learn:
            raise ConfigError(f"learner.model_lr={self.model_lr!r} is the step size of the motion model's parameters, "
                              f"but learner.learn={learn!r} does not list model; remove it or add model")
        check_choice("learner.train_fusion", self.train_fusion, TRAIN_FUSIONS)
        if self.train_fusion == "individual" and {"weights", "omega"} & set(learn):
            raise ConfigError(f"learner.train_fusion=individual learns no consensus numbers: learner.learn={learn!r} "
                              f"may list only q, r, model")

    @property
    def label(self) -> str:
        """The rows' learner label: ``backprop``, or ``backprop(individual)`` where the nodes trained alone."""
        return self.name if self.train_fusion == "consensus" else f"{self.name}({self.train_fusion})"

    def training_fusion(self, fusion: Fusion) -> Fusion:
        """The fusion the loss backpropagates through: the configured one, or none (``train_fusion=individual``)."""
        if self.train_fusion == "consensus":
            return fusion
        return make_fusion("individual", torch.as_tensor(fusion.weights), fusion.iterations)

    def check_fusion(self, fusion: Fusion) -> None:
        """ConfigError where ``learn`` asks for what the fusion does not have."""
        if "weights" in self.learn and not fusion.mixes:
            raise ConfigError(f"learner.learn=[weights] needs consensus weights (consensus="
                              f"{'|'.join(WEIGHTED_FUSIONS)}), not consensus={fusion.name}")
        if "omega" in self.learn and not fusion.uses_omega:
            raise ConfigError(f"learner.learn=[omega] needs a fusion with omega (consensus="
                              f"{'|'.join(OMEGA_FUSIONS)}), not consensus={fusion.name}")
