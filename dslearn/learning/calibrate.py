r"""Calibrating a distributed filter's noise to a scenario (``learner=calibrate``): maximum likelihood of the
training innovations over a scale of the process noise and a scale of the sensors' noise.

Every hand-set number of a method was set for its own paper's world (LIN's :math:`Q = 0.01 I` for walkers, the
GPs' noise floors for Yu's scenario); this learner fits

.. math::
    Q' = s_q\,Q(\hat y), \qquad R' = s_r\,R

to the scenario's training measurements, whatever the motion model (LIN, the social force, the LSTMs: their
``Q``; a GP: its predictive variance, the ``Q`` it reports to the filter) and the configured prediction step
(``filter=default|ukf``). ``learner.fit`` says which of ``q``, ``r`` are fitted (the other scale stays 1).

The likelihood. Each node runs the filter alone (no consensus: the individual information filter, the
configured prediction step, the method's own parts with the scales) on every training episode; the objective is
the mean Gaussian negative log-likelihood of its innovations

.. math::
    \nu = z_{ij}^t - h(\hat y_j^{t|t-1}), \quad \nu \sim \mathcal N(0,\ C P_{jj}^{t|t-1} C^T + s_r R),

over the nodes ``i``, targets ``j`` and steps ``t`` where node ``i`` measured ``j`` at ``t`` and at each of the
``learner.warmup`` steps before (a node that has not seen the target for a while holds the diffuse prior, whose
innovations carry nothing about the scales). Nodes run alone, so every (node, episode) pair is an independent
filter: for a motion model without per-node state the pairs that have a counted innovation are packed into one
batch and the rest are not run at all (on Liu's field most of the 200 sensors never see the target).

The estimator. A grid search on :math:`(\log_{10} s_q, \log_{10} s_r)`, all grid points of a stage in one
batched pass (the grid is a batch dimension of the filter): ``learner.points`` values per fitted scale over
:math:`\pm` ``learner.decades`` around the hand-set numbers (a best point on the grid's edge moves the grid
there, up to ``learner.shifts`` times), then ``learner.zooms`` finer grids of the same size around the best, each
spanning two steps of the grid before. With the defaults (9 points, 4 decades, 3 zooms) the scales are resolved
to 1/64 of a decade (4 %) over 8 decades, in 4 passes of 81 filters per (node, episode) pair with both scales.
Derivative-free, so the same code serves every motion model and prediction step (the LSTM's linearisation,
the UKF's sigma points) and cannot be trapped by a bad gradient; the grid's point at the hand-set numbers gives
the likelihood before calibration (``nll_hand``). Each stage keeps, of the points whose summed NLL is within
``learner.tolerance`` (1.92: the 95 % likelihood-ratio interval of one parameter) of the smallest found, the one
nearest the hand-set numbers: a scale the data do not determine stays where it was set instead of drifting to the
grid's edge (LIN's ``Q = sigma^2 I`` has position noise, so with a large ``s_q`` the likelihood can be flat in
``s_r`` all the way down to ``R = 0``, an information filter with infinite trust in its sensors).

What the families do with it (``dslearn.methods.distributed.DistributedFilter``): the motion model first learns
as it does alone (the LSTM's offline fit, the GP's online learning on the training episodes, Algorithm 1), then
the scales are fitted on the training episodes, then the test episodes are tracked with the configured fusion
and the scaled noises. A GP learns online from the first training episodes, the scales are fitted on the held-out
rest (``learner.holdout``), then it learns those too (so it is the hand-set method's GP): fitted on the episodes it
learned from, its small variance there would ask for too small an ``s_q``. The LSTM's innovations are in-sample
(its weights are fitted to the training tracks; its own Q already comes from held-out residuals).
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar

import torch
from torch import Tensor

from dslearn.episodes import Measurements
from dslearn.errors import ConfigError
from dslearn.filters.information import novel_information
from dslearn.filters.information import predict as ekf_predict
from dslearn.filters.information import prediction_step
from dslearn.fusion.strategies import make_fusion
from dslearn.learning import Learner
from dslearn.models.base import MotionModel, ObservationModel
from dslearn.types import AGENT_DIM, StepContext, agents, safe_cholesky

_LOG = logging.getLogger(__name__)

#: what ``learner.fit`` may list: a scale of the process noise Q, a scale of the sensors' R
PARTS = ("q", "r")
#: the prediction steps it runs are those whose Q is the model's at the mean (the EKF's and the UKF's:
#: :attr:`~dslearn.filters.information.PredictionStep.noise_at_mean`)


# -------------------------------------------------------------------------------------------- scaled parts
def _per_batch(scale: Tensor, like: Tensor) -> Tensor:
    """``scale`` (a number, or one per batch element: ``(N,)``) shaped to multiply ``like (S, N, ..., d, d)``."""
    scale = scale.to(like)
    if scale.dim() == 0:
        return scale
    return scale.view(1, -1, *([1] * (like.dim() - 2)))


class ScaledNoise(MotionModel):
    r"""``base``'s mean and Jacobian with its process noise times ``scale``: :math:`Q' = s\,Q(y)`. ``scale`` is a
    number or one per batch element (``(N,)``, the filter's batch dimension, the second: nodes first)."""

    def __init__(self, base: MotionModel, scale: Tensor | float):
        super().__init__()
        self.base = base
        self.scale = torch.as_tensor(scale, dtype=torch.float64)
        self.state_dim = base.state_dim

    def forward(self, x: Tensor, ctx: StepContext) -> Tensor:
        return self.base(x, ctx)

    def jacobian(self, x: Tensor, ctx: StepContext) -> Tensor:
        return self.base.jacobian(x, ctx)

    def noise_cov(self, x: Tensor, ctx: StepContext) -> Tensor:
        q = self.base.noise_cov(x, ctx)
        return q * _per_batch(self.scale, q)

    def linearize(self, x: Tensor, ctx: StepContext) -> tuple[Tensor, Tensor, Tensor]:
        mean, jac, q = self.base.linearize(x, ctx)
        return mean, jac, q * _per_batch(self.scale, q)


class PerNodeScaledNoise(ScaledNoise):
    """:class:`ScaledNoise` of a model with per-node state (the GPs): the prediction steps keep the node
    dimension first for it (``num_nodes``, as the base model)."""

    @property
    def num_nodes(self) -> int:
        return self.base.num_nodes

    def _flat(self, x: Tensor) -> Tensor:
        return self.base._flat(x)


class ScaledSensor(ObservationModel):
    """``base``'s measurement function with its noise times ``scale``: :math:`R' = s\\,R` (``scale`` a number or
    one per batch element, the second dimension of ``y (S, N, A, 4)``)."""

    def __init__(self, base: ObservationModel, scale: Tensor | float):
        super().__init__()
        self.base = base
        self.scale = torch.as_tensor(scale, dtype=torch.float64)
        # what the filter reads of a sensor, as the base declares it
        self.meas_dim, self.linear, self.measures_position = base.meas_dim, base.linear, base.measures_position

    def reading(self, meas: Tensor) -> Tensor:
        return self.base.reading(meas)

    def residual(self, z: Tensor, h: Tensor) -> Tensor:
        return self.base.residual(z, h)

    def forward(self, y: Tensor) -> Tensor:
        return self.base(y)

    def jacobian(self, y: Tensor) -> Tensor:
        return self.base.jacobian(y)

    def noise_cov(self, y: Tensor) -> Tensor:
        r = self.base.noise_cov(y)
        return r * _per_batch(self.scale, r)

    def linearize(self, y: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        h, c, r = self.base.linearize(y)
        return h, c, r * _per_batch(self.scale, r)


class NodeSubset(MotionModel):
    """A per-node model (the GPs) answering for its nodes ``nodes`` only, as a model of ``len(nodes)`` nodes: the
    queries ``(len(nodes), *B, Dx)`` are laid into a batch of all its nodes (zeros at the others, unit covariances in
    ``ctx.cov``), the base model is asked, and the rows of ``nodes`` kept. A per-node model's answer at a node
    depends on that node's queries and state only, so these rows are what the base gives them; the filter that
    uses it runs on ``nodes`` only (:func:`calibrate`: the nodes with a counted innovation)."""

    def __init__(self, base: MotionModel, nodes: Tensor):
        super().__init__()
        self.base = base
        self.nodes = nodes
        self.state_dim = base.state_dim

    @property
    def num_nodes(self) -> int:
        return int(self.nodes.numel())

    def _flat(self, x: Tensor) -> Tensor:
        return x.reshape(self.num_nodes, -1, self.state_dim)

    def _full(self, x: Tensor, ctx: StepContext) -> tuple[Tensor, StepContext]:
        idx = self.nodes.to(x.device)
        full = x.new_zeros(self.base.num_nodes, *x.shape[1:])
        full[idx] = x
        cov = ctx.cov
        if cov is not None:
            eye = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
            pad = eye.expand(self.base.num_nodes, *cov.shape[1:]).clone()
            pad[idx] = cov
            cov = pad
        return full, dataclasses.replace(ctx, cov=cov)

    def forward(self, x: Tensor, ctx: StepContext) -> Tensor:
        return self.base(*self._full(x, ctx))[self.nodes.to(x.device)]

    def jacobian(self, x: Tensor, ctx: StepContext) -> Tensor:
        return self.base.jacobian(*self._full(x, ctx))[self.nodes.to(x.device)]

    def noise_cov(self, x: Tensor, ctx: StepContext) -> Tensor:
        return self.base.noise_cov(*self._full(x, ctx))[self.nodes.to(x.device)]

    def linearize(self, x: Tensor, ctx: StepContext) -> tuple[Tensor, Tensor, Tensor]:
        idx = self.nodes.to(x.device)
        return tuple(t[idx] for t in self.base.linearize(*self._full(x, ctx)))


def per_node(model: MotionModel) -> bool:
    """Whether ``model`` keeps per-node state (the node dimension must stay first and whole): the GPs."""
    return bool(getattr(model, "learnable", False)) or hasattr(type(model), "num_nodes")


def scaled_model(model: MotionModel, scale) -> ScaledNoise:
    """``model`` with its process noise times ``scale`` (:class:`PerNodeScaledNoise` for a per-node model)."""
    return (PerNodeScaledNoise if per_node(model) else ScaledNoise)(model, scale)


# ------------------------------------------------------------------------------------------ the likelihood
def counted(visible: Tensor, warmup: int) -> Tensor:
    """``(S, B, K+1, A)`` bool: the innovations the likelihood counts, node ``i`` measuring target ``j`` at ``t``
    and at each of the ``warmup`` steps before (never at ``t < max(warmup, 1)``)."""
    out = visible.clone()
    out[:, :, : max(int(warmup), 1)] = False
    for lag in range(1, int(warmup) + 1):
        out[:, :, lag:] &= visible[:, :, :-lag]
    return out


def innovation_nll(y_pred: Tensor, P_pred: Tensor, meas: Tensor, mask: Tensor, obs: ObservationModel) -> Tensor:
    r"""The Gaussian negative log-likelihood of every node's innovations of one step, summed over the nodes and
    targets in ``mask``: ``(N,)``, one per batch element. :math:`\nu = z - h(\hat y_j)`,
    :math:`S = C P_{jj} C^T + R`; ``y_pred (S, N, Dx)``, ``P_pred (S, N, Dx, Dx)``, ``meas (S, N, A, Dz)``,
    ``mask (S, N, A)``. An innovation covariance that is not positive definite gives ``inf``."""
    yj = agents(y_pred)
    h, C, R = obs.linearize(yj)
    a = y_pred.shape[-1] // AGENT_DIM
    blocks = P_pred.unflatten(-2, (a, AGENT_DIM)).unflatten(-1, (a, AGENT_DIM))
    Pjj = torch.diagonal(blocks, dim1=-4, dim2=-2).movedim(-1, -3)  # (S, N, A, 4, 4)
    S_cov = C @ Pjj @ C.transpose(-1, -2) + R
    S_cov = 0.5 * (S_cov + S_cov.transpose(-1, -2))
    chol, info = torch.linalg.cholesky_ex(S_cov)
    bad = info != 0
    chol = torch.where(bad[..., None, None], torch.eye(S_cov.shape[-1], dtype=S_cov.dtype, device=S_cov.device), chol)
    white = torch.linalg.solve_triangular(chol, (meas - h).unsqueeze(-1), upper=False).squeeze(-1)
    dz = meas.shape[-1]
    nll = 0.5 * (white.pow(2).sum(-1) + 2 * chol.diagonal(dim1=-2, dim2=-1).log().sum(-1) + dz * math.log(2 * math.pi))
    nll = torch.where(bad, torch.full_like(nll, float("inf")), nll)
    return torch.where(mask, nll, torch.zeros_like(nll)).sum(-1).sum(0)


def _batch_subset(part, rows: Tensor):
    """``part`` (a motion or observation model) for the batch elements ``rows`` of the one it was made for: a
    scaled part with one scale per batch element keeps those of ``rows``; any other part is returned as it is."""
    if isinstance(part, (ScaledNoise, ScaledSensor)) and part.scale.dim() > 0:
        return type(part)(part.base, part.scale[rows.to(part.scale.device)])
    return part


#: :func:`individual_nll` drops the batch elements that count no innovation any more once they are this share
#: of those it runs (each drop copies the beliefs and measurements of the rest)
DROP_SHARE = 0.2


def individual_nll(model: MotionModel, obs: ObservationModel, ep: Measurements, init: tuple[Tensor, Tensor],
                   ctx: StepContext, mask: Tensor, predict_step=None) -> Tensor:
    """Each node's filter alone (the individual information filter: prediction, its own novel information) on
    ``ep``'s episodes from ``init = (mean (S, N, Dx), info (S, N, Dx, Dx))``; the innovation NLL summed over the
    steps, nodes and targets of ``mask (S, N, K+1, A)``: ``(N,)``.

    A batch element is run up to its last counted innovation only: past it, nothing it computes enters its sum,
    so the elements that have none left are dropped from the batch (every element's filter is independent of the
    others; ``model`` and ``obs`` may hold one noise scale per element, :class:`ScaledNoise`, :class:`ScaledSensor`,
    which are dropped with it)."""
    step_of = predict_step or ekf_predict
    alone = make_fusion("individual", torch.eye(1), 1)
    y, o = init
    n = y.shape[1]
    total = torch.zeros(n, dtype=y.dtype, device=y.device)
    steps = torch.arange(mask.shape[2], device=mask.device)
    last = torch.where(mask.any(-1).any(0), steps, torch.full_like(steps, -1)).amax(-1)  # (N,) last counted step
    rows = None  # the original batch elements still run (None: all of them)
    meas, visible, m, mod, sensor = ep.meas, ep.visible, mask, model, obs
    for t in range(1, ep.steps + 1):
        live = (last if rows is None else last[rows]) >= t
        size = live.shape[0]
        alive = int(live.sum())
        if alive == 0:
            break
        if size - alive >= DROP_SHARE * size:  # drop the elements done with (their sums are final)
            keep = live.nonzero().squeeze(-1)
            rows = keep if rows is None else rows[keep]
            y, o = y[:, keep], o[:, keep]
            meas, visible, m = meas[:, keep], visible[:, keep], m[:, keep]
            mod, sensor = _batch_subset(model, rows), _batch_subset(obs, rows)
        y_pred, q_pred, o_pred, P_pred, *_ = step_of(y, o, mod, ctx, full=True)
        if bool(m[:, :, t].any()):
            nll = innovation_nll(y_pred, P_pred, meas[:, :, t], m[:, :, t], sensor)
            if rows is None:
                total = total + nll
            else:
                total[rows] = total[rows] + nll
        dq, do = novel_information(y_pred, meas[:, :, t], visible[:, :, t], sensor)
        q, o = alone(q_pred, o_pred, dq, do)
        y = torch.cholesky_solve(q.unsqueeze(-1), safe_cholesky(o)).squeeze(-1)
    return total


# ------------------------------------------------------------------------------------------------ the fit
@dataclass
class Calibration:
    """The fitted scales and what the fit saw: ``q_scale``, ``r_scale`` (1 where not fitted), the mean NLL per
    counted innovation at the fit (``nll``), the smallest on the grids (``nll_min``) and at the hand-set numbers
    (``nll_hand``), the number of counted
    innovations (``terms``), of filters run per grid point (``filters``: (node, episode) pairs), of passes and
    the wall time."""

    q_scale: float = 1.0
    r_scale: float = 1.0
    nll: float = float("nan")
    nll_min: float = float("nan")
    nll_hand: float = float("nan")
    terms: int = 0
    filters: int = 0
    passes: int = 0
    seconds: float = 0.0
    history: list = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        return {"q_scale": self.q_scale, "r_scale": self.r_scale, "nll": self.nll, "nll_min": self.nll_min,
                "nll_hand": self.nll_hand,
                "terms": self.terms, "filters": self.filters, "passes": self.passes,
                "seconds": round(self.seconds, 3)}


def _pack(ep: Measurements, init: tuple[Tensor, Tensor], mask: Tensor, keep_nodes: bool):
    """Only the (node, episode) pairs with a counted innovation: as a batch ``(1, P, ...)`` of independent
    filters, or (``keep_nodes``: a per-node model) the episodes with one at some node, for the nodes with one in
    some episode (their indices are returned last: ``None`` where that is every node)."""
    active = mask.flatten(2).any(-1)  # (S, B)
    if keep_nodes:
        b = active.any(0).nonzero().squeeze(-1)
        nodes = active.any(1).nonzero().squeeze(-1)
        ep, init, mask = ep.select(b), (init[0][:, b], init[1][:, b]), mask[:, b]
        if nodes.numel() == active.shape[0]:
            return ep, init, mask, None
        sub = Measurements(ep.meas[nodes], ep.visible[nodes])
        return sub, (init[0][nodes], init[1][nodes]), mask[nodes], nodes
    s, b = active.nonzero(as_tuple=True)
    packed = Measurements(ep.meas[s, b].unsqueeze(0), ep.visible[s, b].unsqueeze(0))
    return packed, (init[0][s, b].unsqueeze(0), init[1][s, b].unsqueeze(0)), mask[s, b].unsqueeze(0), None


def _repeat(x: Tensor, g: int) -> Tensor:
    """``x (S, N, ...)`` repeated ``g`` times along the batch dimension, grid-major: ``(S, g N, ...)``."""
    return x.repeat(1, g, *([1] * (x.dim() - 2)))


def calibrate(model: MotionModel, obs: ObservationModel, ep: Measurements, init: tuple[Tensor, Tensor],
              ctx: StepContext, *, fit=PARTS, predict_step=None, points: int = 9, decades: float = 4.0,
              zooms: int = 3, shifts: int = 4, warmup: int = 2, tolerance: float = 1.92,
              max_batch: int = 20000) -> Calibration:
    """Fit ``log10`` of the scales of ``fit`` (``q``: the process noise, ``r``: the sensors' noise) by the grid
    search of the module docstring; ``init``: every node's initial belief on ``ep`` (``(S, B, Dx)``,
    ``(S, B, Dx, Dx)``, the individual filter's); ``max_batch``: filters per pass at most (grid points x
    packed pairs; a stage larger than this is run in chunks); ``tolerance``: grid points whose summed NLL is within
    this of the smallest found are as good, and the fit is the one nearest the hand-set numbers (1.92: the 95 %
    likelihood-ratio interval of one parameter; 0: the maximum likelihood itself)."""
    t0 = time.perf_counter()
    fit = tuple(fit)
    mask = counted(ep.visible, warmup)
    out = Calibration(terms=int(mask.sum()))
    if out.terms == 0 or not fit:
        _LOG.warning("learner=calibrate: no innovation to fit (terms=%d, fit=%s): the hand-set numbers stay",
                     out.terms, list(fit))
        out.seconds = time.perf_counter() - t0
        return out
    keep = per_node(model)
    packed, start, mask, nodes = _pack(ep, init, mask, keep)
    if nodes is not None:  # a per-node model, asked for the nodes with a counted innovation only
        model = NodeSubset(model, nodes)
    n = packed.meas.shape[1]
    out.filters = int(mask.shape[0] * n) if keep else n
    k = len(fit)
    centre = [0.0] * k
    half, moved, stage = float(decades), 0, 0
    best_val = float("inf")
    while True:
        axis = [c + torch.linspace(-half, half, points, dtype=torch.float64) for c in centre]
        grid = torch.tensor(list(itertools.product(*[a.tolist() for a in axis])), dtype=torch.float64)  # (G, k)
        values = torch.empty(grid.shape[0], dtype=torch.float64)
        chunk = max(1, int(max_batch) // max(n, 1))
        for i in range(0, grid.shape[0], chunk):
            g = grid[i:i + chunk]
            scales = {p: torch.ones(g.shape[0], dtype=torch.float64) for p in PARTS}
            for j, p in enumerate(fit):
                scales[p] = 10.0 ** g[:, j]
            qs, rs = (scales[p].repeat_interleave(n).to(packed.meas.device) for p in PARTS)
            reps = g.shape[0]
            e = Measurements(_repeat(packed.meas, reps), _repeat(packed.visible, reps))
            with torch.no_grad():
                tot = individual_nll(scaled_model(model, qs), ScaledSensor(obs, rs), e,
                                     (_repeat(start[0], reps), _repeat(start[1], reps)), ctx, _repeat(mask, reps),
                                     predict_step)
            values[i:i + reps] = tot.view(reps, n).sum(-1).cpu() / out.terms
            out.passes += 1
        values = torch.where(torch.isfinite(values), values, torch.full_like(values, float("inf")))
        if stage == 0 and moved == 0:
            hand = (grid.abs().sum(-1) < 1e-12).nonzero()
            if len(hand):
                out.nll_hand = float(values[hand[0, 0]])
        best_val = min(best_val, float(values.min()))
        # the points as likely as the best (within the likelihood-ratio tolerance): the one nearest the hand-set
        # numbers (a direction the data do not determine keeps its hand-set value instead of drifting)
        near = values <= best_val + float(tolerance) / out.terms
        if not bool(near.any()):
            near = values == values.min()
        dist = torch.where(near, grid.pow(2).sum(-1), torch.full_like(values, float("inf")))
        pick = int(dist.argmin())
        point = grid[pick].tolist()
        out.history.append({"centre": list(centre), "half": half, "pick": point, "nll": float(values[pick]),
                            "nll_min": float(values.min())})
        idx = [axis[j].sub(grid[pick, j]).abs().argmin().item() for j in range(k)]
        on_edge = any(i in (0, points - 1) for i in idx)
        centre = list(point)
        if on_edge and moved < shifts and stage == 0:
            moved += 1
            continue
        if stage >= zooms:
            break
        stage += 1
        half = 2 * half / (points - 1)
    out.nll, out.nll_min = float(values[pick]), best_val
    for j, p in enumerate(fit):
        setattr(out, f"{p}_scale", float(10.0 ** point[j]))
    out.seconds = time.perf_counter() - t0
    return out


# ---------------------------------------------------------------------------------------------- the learner
@dataclass
class CalibrateLearning(Learner):
    """Fit a scale of the process noise and/or of the sensors' noise to the scenario's training measurements
    (maximum likelihood of the nodes' innovations, each node alone), then track with the configured fusion
    (``conf/learner/calibrate.yaml``; the estimator: :func:`calibrate`).

    Args:
        fit: which of ``q`` (a scale of the motion model's process noise, a GP's predictive variance included)
            and ``r`` (a scale of the sensors' noise R) are fitted.
        points: grid values per fitted scale and stage (odd, >= 3: the centre is on the grid).
        decades: the first grid spans the hand-set numbers x 10^[-decades, decades].
        zooms: finer grids after the first (each spans two steps of the one before).
        shifts: how often the first grid may move to a best point on its edge.
        warmup: an innovation counts where the node also measured the target at the ``warmup`` steps before.
        tolerance: grid points whose summed NLL is within this of the smallest are as good; the fit is the one
            nearest the hand-set numbers (1.92: the 95 % likelihood-ratio interval of one parameter; 0: the
            maximum likelihood itself).
        holdout: for parts that learn online from the training episodes (the GPs): the share of them held out.
            The parts learn from the others, the scales are fitted on the held-out ones, then the parts learn
            those too (the same parts as the hand-set method's); 0: fitted on every episode after learning.
        max_batch: filters run at once (grid points x (node, episode) pairs); more are run in chunks.
    """

    name: ClassVar[str] = "calibrate"
    learns_through_update = True
    runs_nodes_alone = True  # the scales' likelihood: each node's filter alone (individual_nll)

    fit: Any = field(default_factory=lambda: list(PARTS))
    points: int = 9
    decades: float = 4.0
    zooms: int = 3
    shifts: int = 4
    warmup: int = 2
    tolerance: float = 1.92
    holdout: float = 0.5
    max_batch: int = 20000

    def __post_init__(self) -> None:
        fit = [self.fit] if isinstance(self.fit, str) else list(self.fit or [])
        if not fit or any(p not in PARTS for p in fit) or len(set(fit)) != len(fit):
            raise ConfigError(f"learner.fit={fit!r}: learner=calibrate fits a non-empty list of {list(PARTS)}, each "
                              f"at most once (q: a scale of the process noise, r: a scale of the sensors' noise)")
        self.fit = [p for p in PARTS if p in fit]
        for key, low in (("points", 3), ("zooms", 0), ("shifts", 0), ("warmup", 1), ("max_batch", 1)):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ConfigError(f"learner.{key}={v!r} must be an integer >= {low}")
        if self.points % 2 == 0:
            raise ConfigError(f"learner.points={self.points!r} must be odd (the hand-set numbers are the grid's "
                              f"centre)")
        d = self.decades
        if isinstance(d, bool) or not isinstance(d, (int, float)) or not 0 < d < 30:
            raise ConfigError(f"learner.decades={d!r} must be a number in (0, 30)")
        self.decades = float(d)
        for key, high in (("tolerance", float("inf")), ("holdout", 1.0)):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v < high:
                below = "" if high == float("inf") else " and < 1"
                raise ConfigError(f"learner.{key}={v!r} must be a number >= 0{below}")
            setattr(self, key, float(v))

    @property
    def label(self) -> str:
        """The rows' learner label: ``calibrate`` (q and r), else ``calibrate[q]`` / ``calibrate[r]``."""
        return self.name if len(self.fit) == len(PARTS) else f"{self.name}[{','.join(self.fit)}]"

    def run(self, model: MotionModel, obs: ObservationModel, ep: Measurements, init: tuple[Tensor, Tensor],
            ctx: StepContext, predict_step=None) -> Calibration:
        return calibrate(model, obs, ep, init, ctx, fit=self.fit, predict_step=predict_step, points=self.points,
                         decades=self.decades, zooms=self.zooms, shifts=self.shifts, warmup=self.warmup,
                         tolerance=self.tolerance, max_batch=self.max_batch)


def calibrate_misfit(observation: ObservationModel, predict=None, fit=PARTS) -> str | None:
    """Why ``learner=calibrate`` does not fit these parts (``None`` where it does): the filter's own EKF or UKF
    prediction step (whose Q is the model's at the mean) and, to fit ``r``, the linear position sensor."""
    from dslearn.models.observation import LinearPositionObservation

    step = prediction_step(predict)
    if not step.noise_at_mean:
        return (f"it scales the process noise that the EKF or UKF prediction step takes at the mean (filter=default|"
                f"ukf), not filter={step.name}'s")
    if "r" in fit and not isinstance(observation, LinearPositionObservation):
        return (f"learner.fit=[r] scales the linear position sensor's R (observation=linear), not observation "
                f"{type(observation).__name__}; fit only q (learner.fit=[q])")
    return None
