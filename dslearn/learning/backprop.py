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
- ``model``: the motion model's parameters. Supported models now: ``model=lin`` (constant velocity), whose
  parameter is its transition matrix ``F`` (one agent block, shared by the agents, initialised at the constant
  velocity matrix). Other motion models are refused at composition.

Losses: ``innovation`` (measurements only, Yu et al.'s setting): the negative log-likelihood of every node's
innovations :math:`\nu = z - H\hat y^{t|t-1}`, :math:`\nu \sim \mathcal N(0, H P^{t|t-1} H^T + R)`, summed over the
nodes, targets seen and steps and divided by the number of terms; ``supervised``: the mean squared error of the
nodes' position estimates to the true positions (training episodes with truth).
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar

import torch
from torch import Tensor, nn

from dslearn.episodes import Episodes, Measurements
from dslearn.errors import ConfigError, check_choice
from dslearn.filters.distributed import TrackResult, track
from dslearn.filters.information import predict as ekf_predict
from dslearn.fusion.strategies import Fusion, make_fusion
from dslearn.models.base import MotionModel, ObservationModel
from dslearn.types import AGENT_DIM, StepContext, agents

#: what ``learner.learn`` may list
LEARNABLE = ("q", "r", "weights", "omega", "model")
LOSSES = ("innovation", "supervised")
OPTIMIZERS = ("adam", "lbfgs")
#: where ``learner=backprop`` trains: through the configured consensus, or each node alone (then frozen)
TRAIN_FUSIONS = ("consensus", "individual")
#: the motion models (``conf/model`` options) whose parameters this learner can learn
SUPPORTED_MODELS = ("lin",)
#: fusions with consensus weights (``weights``) and with a novel-information weight (``omega``)
WEIGHTED_FUSIONS = ("ce", "cm", "ci", "hybrid")
OMEGA_FUSIONS = ("cm", "hybrid")


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


class BackpropParameters(nn.Module):
    """The learnable numbers of a distributed filter with a linear motion model and position sensors, in float64.

    Args:
        num_agents: targets ``A`` (state ``4A``).
        f_block, q_block: the motion model's agent block and its process noise (4 x 4; ``q_block`` diagonal
            is learned, its off-diagonal entries are dropped).
        r: the sensors' noise covariance (2 x 2).
        fusion: the configured fusion (its class, ``L`` and rule weights and omega are the initial values).
        adjacency: ``(S, S)`` communication graph.
        learn: which of :data:`LEARNABLE` get gradients (the others stay at their initial values).
    """

    def __init__(self, num_agents: int, f_block: Tensor, q_block: Tensor, r: Tensor, fusion: Fusion,
                 adjacency: Tensor, learn=("q", "r")):
        super().__init__()
        dt = torch.float64
        self.num_agents, self.base_fusion = int(num_agents), fusion
        self.register_buffer("mask", graph_mask(adjacency))
        self.f_block = nn.Parameter(f_block.detach().to(dt).clone())
        self.q_log = nn.Parameter(q_block.detach().to(dt).diagonal().log().clone())
        self.r_raw = nn.Parameter(log_cholesky_raw(r.detach().to(dt)))
        self.logits = nn.Parameter(weight_logits(torch.as_tensor(fusion.weights), self.mask))
        self.omega_log = nn.Parameter(torch.tensor(math.log(float(fusion.omega)), dtype=dt))
        self.set_learn(learn)

    def set_learn(self, learn) -> None:
        names = {"model": "f_block", "q": "q_log", "r": "r_raw", "weights": "logits", "omega": "omega_log"}
        for k, p in names.items():
            getattr(self, p).requires_grad_(k in learn)

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
    def motion(self) -> LinearMotion:
        return LinearMotion(self.num_agents, self.f_block, self.Q())

    def observation(self) -> LinearSensor:
        return LinearSensor(self.R())

    def fusion(self) -> Fusion:
        """The configured fusion strategy (same class, same ``L``) with ``W^L`` and omega from the parameters."""
        f = copy.copy(self.base_fusion)
        if f.name in WEIGHTED_FUSIONS:
            w = self.W()
            f.weights, f.wl = w, torch.linalg.matrix_power(w, f.iterations)
        if f.uses_omega:
            f.omega = self.omega()
        return f

    def detached(self) -> tuple[LinearMotion, LinearSensor, Fusion]:
        """The learned parts with plain tensors (for tracking the test episodes)."""
        with torch.no_grad():
            f = self.fusion()
            for k in ("weights", "wl", "omega"):
                if isinstance(getattr(f, k, None), Tensor):
                    setattr(f, k, getattr(f, k).detach().clone())
            if isinstance(f.omega, Tensor):
                f.omega = float(f.omega)
            return (LinearMotion(self.num_agents, self.f_block.detach().clone(), self.Q().detach()),
                    LinearSensor(self.R().detach()), f)

    def summary(self) -> dict[str, Any]:
        with torch.no_grad():
            return {"q_diag": self.q_log.exp().tolist(), "r": self.R().tolist(), "omega": float(self.omega()),
                    "weights": self.W().tolist(), "f_block": self.f_block.tolist()}


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
        predict_step=None, optimizer: str = "adam") -> FitHistory:
    """Adam on the learnable parameters; each epoch visits the training episodes once in a seeded random order,
    ``batch`` episodes per step (``None``: all). ``optimizer=lbfgs``: full-batch L-BFGS (strong Wolfe line
    search), ``epochs`` outer steps of up to 20 iterations each, ``lr`` its initial step.
    ``loss=supervised`` needs :class:`~dslearn.episodes.Episodes`."""
    check_choice("learner.loss", loss, LOSSES)
    check_choice("learner.optimizer", optimizer, OPTIMIZERS)
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

    if optimizer == "lbfgs":
        opt = torch.optim.LBFGS(trainable, lr=lr, max_iter=20, line_search_fn="strong_wolfe")
        every = torch.arange(n, device=meas.meas.device)

        def closure():
            opt.zero_grad()
            value = objective(every)
            value.backward()
            return value

        for _ in range(epochs):
            t0 = time.perf_counter()
            hist.loss.append(float(opt.step(closure).detach()))
            hist.seconds.append(time.perf_counter() - t0)
        return hist
    opt = torch.optim.Adam(trainable, lr=lr)
    size = n if batch is None else min(int(batch), n)
    for _ in range(epochs):
        t0, total = time.perf_counter(), 0.0
        order = torch.randperm(n, generator=gen)
        for i in range(0, n, size):
            idx = order[i:i + size].to(meas.meas.device)
            opt.zero_grad()
            value = objective(idx)
            value.backward()
            opt.step()
            total += float(value.detach()) * len(idx)
        hist.loss.append(total / n)
        hist.seconds.append(time.perf_counter() - t0)
    return hist


# ---------------------------------------------------------------------------------------------- the learner
@dataclass
class BackpropLearning:
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
    """

    name: ClassVar[str] = "backprop"

    epochs: int = 30
    lr: float = 0.05
    batch: Any = None
    loss: str = "innovation"
    learn: Any = field(default_factory=lambda: ["q", "r", "weights", "omega"])
    train_fusion: str = "consensus"

    def __post_init__(self) -> None:
        if isinstance(self.epochs, bool) or not isinstance(self.epochs, int) or self.epochs < 0:
            raise ConfigError(f"learner.epochs={self.epochs!r} must be an integer >= 0")
        if isinstance(self.lr, bool) or not isinstance(self.lr, (int, float)) or not 0 < self.lr < float("inf"):
            raise ConfigError(f"learner.lr={self.lr!r} must be a finite number > 0")
        if self.batch is not None and (isinstance(self.batch, bool) or not isinstance(self.batch, int)
                                       or self.batch < 1):
            raise ConfigError(f"learner.batch={self.batch!r} must be an integer >= 1 or null (all episodes)")
        check_choice("learner.loss", self.loss, LOSSES)
        learn = [self.learn] if isinstance(self.learn, str) else list(self.learn or [])
        bad = [k for k in learn if k not in LEARNABLE]
        if bad or len(set(learn)) != len(learn):
            raise ConfigError(f"learner.learn={learn!r}: each of {list(LEARNABLE)} at most once")
        self.learn = learn
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
        if "weights" in self.learn and fusion.name not in WEIGHTED_FUSIONS:
            raise ConfigError(f"learner.learn=[weights] needs consensus weights (consensus="
                              f"{'|'.join(WEIGHTED_FUSIONS)}), not consensus={fusion.name}")
        if "omega" in self.learn and not fusion.uses_omega:
            raise ConfigError(f"learner.learn=[omega] needs a fusion with omega (consensus="
                              f"{'|'.join(OMEGA_FUSIONS)}), not consensus={fusion.name}")
