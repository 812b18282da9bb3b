r"""A straightforward reference implementation of the Yu et al. protocol, for benchmarks and tests.

Same mathematics as :mod:`dslearn.filters.distributed` / :mod:`dslearn.studies.yu`, written the way one
would write it first, and kept deliberately that way: the baseline the fast path is timed and
tested against (``tests/test_reference.py``, ``dslearn-bench reference``).

* Python loops over episodes (``B = 1`` at a time), sensor nodes, targets, consensus rounds
  and neighbours; every belief is a single ``(Dx,)`` vector and ``(Dx, Dx)`` matrix.
* Its own consensus weights (:func:`reference_weights`, each rule's formula per edge), its own
  fusion for every strategy (:class:`ReferenceFusion`: ``L`` explicit rounds over the neighbours,
  never a matrix power), its own initial belief (:func:`reference_initial_belief`, one node and
  one episode at a time), its own metrics and metric rows (:func:`reference_tracking_metrics`,
  :func:`reference_prediction_error`, :func:`reference_rows`) and its own Algorithm 1 loop.
* The GP motion model of each node is a GPyTorch ``ExactGP`` with GPyTorch defaults
  (``ZeroMean``, ``ScaleKernel(RBFKernel)``, ``GaussianLikelihood``; one batch entry per output,
  sharing the hyperparameter values), rebuilt from its data set whenever the data set changed,
  i.e. refactorised from scratch at every online-learning step; the Jacobian of the posterior
  mean by autograd (``torch.autograd.functional.jacobian``). ``model.variant=window`` keeps the
  last ``window`` appended slots (an append the learning gate refused takes a slot, unused).
* LIN / SFM use the same model classes, called one node and one state at a time with that
  node's covariance in the step context (the social force softens interactions by it), with
  the Jacobian by autograd.

Shared with the fast path (they are the data, not the method): the scenario, the network's
geometry (positions, adjacency, noise), the sampled episodes and measurements, the model
classes of LIN / SFM, and the SPD helpers of :mod:`dslearn.types` (Cholesky with per-matrix
jitter). The two paths then produce the same numbers up to floating-point rounding:
:func:`compare_results` measures the difference, :data:`REFERENCE_TOL` bounds it.
"""

from __future__ import annotations

import dataclasses
import math

import gpytorch
import numpy as np
import pandas as pd
import torch
from torch import Tensor

from dslearn.compose import build_motion_model, build_network, build_observation, build_scenario, resolve_device, resolve_dtype
from dslearn.errors import ConfigError, check_choice
from dslearn.models import GPMotionModel
from dslearn.models.constant_velocity import ConstantVelocity
from dslearn.models.observation import LinearPositionObservation
from dslearn.models.social_force import SocialForce
from dslearn.sim.scenario import sample_split
from dslearn.types import AGENT_DIM, StepContext, safe_cholesky, spd_inverse

#: fast path vs reference: the largest difference allowed in any metric value, measured as
#: ``|fast - ref| / max(1, |fast|, |ref|)`` (:func:`compare_results`; absolute below 1, relative
#: above: the NEES of a node holding the diffuse prior reaches 1e5). Both paths are float64 and
#: differ in summation order only, amplified by the information matrices' conditioning (a 1 km
#: prior block beside a 0.2 m measured one: ~1e7). Measured: at most 7.9e-9 over every model x
#: fusion of ``dslearn-bench reference`` (5 + 5 episodes, 10 nodes; CE with the increment GP),
#: 1.3e-10 over ``tests/test_reference.py``. Not meaningful without the learning gate
#: (``filter.learn_gate_std=null``) under individual fusion: a node then learns from its diffuse
#: prior and rounding grows ~1e4-fold per step (the fast path differs from itself by O(1)
#: between its inverse and Cholesky factors there).
REFERENCE_TOL = 1e-7

FUSION_NAMES = ("individual", "ce", "cm", "ci", "hybrid", "centralized")
WEIGHT_RULES = ("uniform", "metropolis", "max_degree", "half_max_degree")
#: the columns that label a metric row (everything but ``value``)
ROW_KEYS = ("model", "consensus", "omega", "iterations", "weights", "train_episodes", "test_episodes", "train_seen",
            "node", "node_kind", "episode", "metric")


# ------------------------------------------------------------------------------------------
# consensus weights and fusion
def _neighbours(adjacency) -> list[list[int]]:
    """``N_i``: the nodes linked to ``i`` (the diagonal ignored)."""
    a = torch.as_tensor(adjacency).tolist()
    return [[j for j in range(len(a)) if j != i and bool(a[i][j])] for i in range(len(a))]


def reference_weights(adjacency, rule: str) -> list[list[float]]:
    r"""The consensus weight matrix of ``rule``, written per edge with loops (``d_i = |N_i|``):

    * ``uniform``: :math:`\pi_{ij} = 1/(d_i + 1)` for :math:`j \in N_i \cup \{i\}`;
    * ``metropolis``: :math:`w_{ij} = 1/(1 + \max(d_i, d_j))` for :math:`j \in N_i`;
    * ``max_degree``: :math:`w_{ij} = 1/(1 + d_{max})` for :math:`j \in N_i`;
    * ``half_max_degree``: :math:`w_{ij} = 1/(2 d_{max})` for :math:`j \in N_i`;

    and for the last three :math:`w_{ii} = 1 - \sum_{j \in N_i} w_{ij}`. Returns ``S`` rows of ``S`` floats.
    """
    check_choice("consensus.weights", rule, WEIGHT_RULES)
    nb = _neighbours(adjacency)
    s = len(nb)
    deg = [len(n) for n in nb]
    dmax = max(deg)
    if rule == "half_max_degree" and dmax == 0:
        raise ConfigError("consensus.weights=half_max_degree needs a graph with at least one edge")
    w = [[0.0] * s for _ in range(s)]
    for i in range(s):
        if rule == "uniform":
            for j in nb[i] + [i]:
                w[i][j] = 1.0 / (deg[i] + 1)
            continue
        for j in nb[i]:
            if rule == "metropolis":
                w[i][j] = 1.0 / (1 + max(deg[i], deg[j]))
            elif rule == "max_degree":
                w[i][j] = 1.0 / (1 + dmax)
            else:
                w[i][j] = 1.0 / (2 * dmax)
        w[i][i] = 1.0 - sum(w[i][j] for j in nb[i])
    return w


class ReferenceFusion:
    r"""Every fusion strategy, one node at a time, ``L`` consensus rounds as loops:
    one round is :math:`x_i \leftarrow \sum_{j \in N_i \cup \{i\}} w_{ij} x_j` for every node.

    With :math:`(q^-, \Omega^-)` the prior and :math:`(\delta q, \delta\Omega)` the novel pair of node ``i``
    and :math:`x(L)` a quantity after ``L`` rounds:

    * ``individual``: :math:`(q^- + \delta q, \Omega^- + \delta\Omega)`;
    * ``centralized``: :math:`(q^- + \sum_k \delta q_k, \Omega^- + \sum_k \delta\Omega_k)`;
    * ``cm``: :math:`(q^- + \omega\,\delta q(L), \Omega^- + \omega\,\delta\Omega(L))`;
    * ``ci``: :math:`((q^- + \delta q)(L), (\Omega^- + \delta\Omega)(L))`;
    * ``hybrid``: :math:`(q^-(L) + \omega\,\delta q(L), \Omega^-(L) + \omega\,\delta\Omega(L))`;
    * ``ce``: the local posterior :math:`\Omega = \Omega^- + \delta\Omega`, its estimate
      :math:`\hat y = \Omega^{-1}(q^- + \delta q)` averaged over ``L`` rounds, returned as :math:`(\Omega\,\hat y(L), \Omega)`.

    ``omega``: ``"one"`` (1), ``"nodes"`` (``S``) or a number > 0.
    """

    def __init__(self, name: str, adjacency, weights: str = "uniform", iterations: int = 4, omega="one"):
        check_choice("consensus.name", name, FUSION_NAMES)
        if isinstance(iterations, bool) or int(iterations) != iterations or int(iterations) < 0:
            raise ConfigError(f"consensus.iterations={iterations!r} must be an integer >= 0")
        self.name, self.iterations, self.weights_rule = name, int(iterations), str(weights)
        self.neighbours = _neighbours(adjacency)
        s = len(self.neighbours)
        self.W = reference_weights(adjacency, weights)
        if isinstance(omega, str):
            check_choice("consensus.omega", omega, ("one", "nodes"))
            self.omega = 1.0 if omega == "one" else float(s)
        else:
            if isinstance(omega, bool) or not 0 < float(omega) < math.inf:
                raise ConfigError(f"consensus.omega={omega!r} must be > 0, 'one' or 'nodes'")
            self.omega = float(omega)
        self.omega_label = str(omega)

    @classmethod
    def from_config(cls, node, adjacency) -> "ReferenceFusion":
        """From the ``consensus`` config node (``name``, ``weights``, ``iterations``, ``omega``)."""
        return cls(str(node.name), adjacency, str(node.get("weights", "uniform")), node.get("iterations", 4),
                   node.get("omega", "one"))

    @property
    def uses_omega(self) -> bool:
        return self.name in ("cm", "hybrid")

    def rounds(self, xs: list[Tensor]) -> list[Tensor]:
        """``L`` rounds of averaging over each node's neighbourhood."""
        for _ in range(self.iterations):
            new = []
            for i in range(len(xs)):
                acc = self.W[i][i] * xs[i]
                for j in self.neighbours[i]:
                    acc = acc + self.W[i][j] * xs[j]
                new.append(acc)
            xs = new
        return xs

    def __call__(self, q_pred, o_pred, dq, do) -> tuple[list[Tensor], list[Tensor]]:
        s, w = len(q_pred), self.omega
        sym = lambda m: 0.5 * (m + m.T)  # noqa: E731
        if self.name == "individual":
            return [q_pred[i] + dq[i] for i in range(s)], [sym(o_pred[i] + do[i]) for i in range(s)]
        if self.name == "centralized":
            sq, so = dq[0], do[0]
            for k in range(1, s):
                sq, so = sq + dq[k], so + do[k]
            return [q_pred[i] + sq for i in range(s)], [sym(o_pred[i] + so) for i in range(s)]
        if self.name == "ci":
            q = self.rounds([q_pred[i] + dq[i] for i in range(s)])
            o = self.rounds([o_pred[i] + do[i] for i in range(s)])
            return q, [sym(m) for m in o]
        if self.name == "ce":
            o = [sym(o_pred[i] + do[i]) for i in range(s)]
            y = self.rounds([torch.linalg.solve(o[i], q_pred[i] + dq[i]) for i in range(s)])
            return [o[i] @ y[i] for i in range(s)], o
        dqL, doL = self.rounds(dq), self.rounds(do)
        if self.name == "cm":
            return [q_pred[i] + w * dqL[i] for i in range(s)], [sym(o_pred[i] + w * doL[i]) for i in range(s)]
        qL, oL = self.rounds(q_pred), self.rounds(o_pred)  # hybrid
        return [qL[i] + w * dqL[i] for i in range(s)], [sym(oL[i] + w * doL[i]) for i in range(s)]


# ------------------------------------------------------------------------------------------
# initial belief
def reference_initial_belief(meas: Tensor, visible: Tensor, b: int, meas_std: float, dt: float, area,
                             fusion: ReferenceFusion, pos_std: float = 1000.0, vel_std: float = 1000.0
                             ) -> tuple[list[Tensor], list[Tensor]]:
    r"""Every node's belief at t = 0 in episode ``b``: the diffuse prior fused with the first two observations.

    Prior of target ``j`` of ``A``: position :math:`c + r(\cos 2\pi j/A, \sin 2\pi j/A)` (``c`` the centre of
    ``area = (xmin, xmax, ymin, ymax)``, ``r`` a sixteenth of its smaller side), velocity 0,
    information :math:`\mathrm{diag}(\sigma_p^{-2}, \sigma_p^{-2}, \sigma_v^{-2}, \sigma_v^{-2})`.
    A node that measured ``j`` at t = 0 and t = 1 (``z^0``, ``z^1``) adds the pseudo-measurement
    :math:`(z^0, (z^1 - z^0)/\Delta t)` with information
    :math:`\mathrm{diag}(\sigma^{-2}, \sigma^{-2}, \Delta t^2/2\sigma^2, \Delta t^2/2\sigma^2)` as its novel
    information, fused like at any step (``fusion``).

    Args:
        meas: ``(S, B, K+1, A, 2)``; visible: ``(S, B, K+1, A)``.
    Returns:
        ``S`` means ``(Dx,)`` and ``S`` information matrices ``(Dx, Dx)``.
    """
    s, a = meas.shape[0], meas.shape[-2]
    dx, dtype = AGENT_DIM * a, meas.dtype
    x0, x1, y0, y1 = (float(v) for v in area)
    r = min(x1 - x0, y1 - y0) / 16
    sig2 = meas_std**2
    q_prior, o_prior, dq, do = [], [], [], []
    for i in range(s):
        m = torch.zeros(dx, dtype=dtype)
        o = torch.zeros(dx, dx, dtype=dtype)
        q_new = torch.zeros(dx, dtype=dtype)
        o_new = torch.zeros(dx, dx, dtype=dtype)
        for j in range(a):
            k = AGENT_DIM * j
            th = 2 * math.pi * j / a
            m[k], m[k + 1] = (x0 + x1) / 2 + r * math.cos(th), (y0 + y1) / 2 + r * math.sin(th)
            for d, std in enumerate((pos_std, pos_std, vel_std, vel_std)):
                o[k + d, k + d] = 1.0 / std**2
            if bool(visible[i, b, 0, j]) and bool(visible[i, b, 1, j]):
                z0, z1 = meas[i, b, 0, j], meas[i, b, 1, j]
                pseudo = (z0[0], z0[1], (z1[0] - z0[0]) / dt, (z1[1] - z0[1]) / dt)
                info = (1 / sig2, 1 / sig2, dt**2 / (2 * sig2), dt**2 / (2 * sig2))
                for d in range(AGENT_DIM):
                    q_new[k + d] = info[d] * pseudo[d]
                    o_new[k + d, k + d] = info[d]
        q_prior.append(o @ m)
        o_prior.append(o)
        dq.append(q_new)
        do.append(o_new)
    q, om = fusion(q_prior, o_prior, dq, do)
    return [torch.cholesky_solve(q[i].unsqueeze(-1), safe_cholesky(om[i])).squeeze(-1) for i in range(s)], om


# ------------------------------------------------------------------------------------------
# motion models, one node and one state at a time
class _ExactGP(gpytorch.models.ExactGP):
    def __init__(self, x, y, lik, dy):
        super().__init__(x, y, lik)
        bs = torch.Size([dy])
        self.mean_module = gpytorch.means.ZeroMean(batch_shape=bs)
        self.covar_module = gpytorch.kernels.ScaleKernel(gpytorch.kernels.RBFKernel(batch_shape=bs), batch_shape=bs)

    def forward(self, x):
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))


class ReferenceGP:
    """One node's GP motion model: a list of appended slots and a GPyTorch ExactGP rebuilt on change.

    ``window``: keep only the last ``window`` slots (``model.variant=window``); every append takes
    a slot, an invalid one (``valid`` False, or a non-finite pair) holds no point.
    """

    def __init__(self, dim: int, outputscale: float, lengthscale: float, noise_std: float, mean: str, noise: str, dtype,
                 window: int | None = None):
        self.dim, self.sf, self.ls, self.sn, self.mean_type, self.noise_mode = dim, outputscale, lengthscale, noise_std, mean, noise
        self.dtype, self.window = dtype, window
        self.slots: list[tuple[Tensor, Tensor] | None] = []
        self.model = None

    def prior(self, x: Tensor) -> Tensor:
        return x.clone() if self.mean_type == "identity" else torch.zeros_like(x)

    @property
    def points(self) -> list[tuple[Tensor, Tensor]]:
        return [p for p in self.slots if p is not None]

    def add(self, x: Tensor, y: Tensor, valid: bool = True) -> None:
        ok = valid and bool(torch.isfinite(x).all()) and bool(torch.isfinite(y).all())
        self.slots.append((x.detach().clone(), (y - self.prior(x)).detach().clone()) if ok else None)
        if self.window is not None and len(self.slots) > self.window:
            self.slots.pop(0)
        self.model = None  # refactorise from scratch at the next use

    def _build(self):
        pts = self.points
        X = torch.stack([p[0] for p in pts])  # (n, d)
        Y = torch.stack([p[1] for p in pts])  # (n, Dy)
        lik = gpytorch.likelihoods.GaussianLikelihood(batch_shape=torch.Size([self.dim]))
        m = _ExactGP(X.unsqueeze(0).expand(self.dim, -1, -1), Y.T.contiguous(), lik, self.dim).to(self.dtype)
        m.covar_module.outputscale = torch.full((self.dim,), self.sf**2, dtype=self.dtype)
        m.covar_module.base_kernel.lengthscale = torch.full((self.dim, 1, 1), self.ls, dtype=self.dtype)
        lik.noise = torch.full((self.dim, 1), self.sn**2, dtype=self.dtype)
        m.eval()
        lik.eval()
        self.model = m

    def mean(self, x: Tensor) -> Tensor:
        if not self.points:
            return self.prior(x)
        if self.model is None:
            self._build()
        out = self.model(x.reshape(1, 1, -1).expand(self.dim, 1, -1))
        return self.prior(x) + out.mean[:, 0]

    def linearize(self, x: Tensor, cov: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """``(Dx,) -> mean (Dx,), F (Dx, Dx), Q (Dx, Dx)`` (``cov`` unused: the GP ignores it)."""
        mean = self.mean(x)
        if self.points:
            var = self.model(x.reshape(1, 1, -1).expand(self.dim, 1, -1)).variance[0, 0].detach()
        else:
            var = torch.tensor(self.sf**2, dtype=x.dtype)
        F = torch.autograd.functional.jacobian(self.mean, x)
        if self.noise_mode == "predictive":
            var = var + self.sn**2
        return mean.detach(), F.detach(), var * torch.eye(self.dim, dtype=x.dtype)


class _ParametricRef:
    """LIN / SFM model called one state at a time (with that node's covariance ``cov`` in the
    step context, as the filter's prediction step gives it), Jacobian by autograd."""

    def __init__(self, model, ctx: StepContext):
        self.model, self.ctx = model, ctx

    def linearize(self, x: Tensor, cov: Tensor | None = None):
        ctx = dataclasses.replace(self.ctx, cov=None if cov is None else cov.unsqueeze(0))
        f = lambda z: self.model(z.unsqueeze(0), ctx)[0]  # noqa: E731
        return f(x).detach(), torch.autograd.functional.jacobian(f, x).detach(), self.model.noise_cov(x.unsqueeze(0), ctx)[0]

    def mean(self, x: Tensor) -> Tensor:
        return self.model(x.unsqueeze(0), self.ctx)[0]

    def add(self, x, y, valid: bool = True) -> None:
        pass


# ------------------------------------------------------------------------------------------
# metrics
def reference_tracking_metrics(means: Tensor, infos: Tensor, truth: Tensor) -> dict[str, list[list[float]]]:
    r"""Per node ``i`` and episode ``b``, with :math:`e^t = \hat y^t_i - y^t` and :math:`p^t_j` the
    position part of target ``j``'s block of :math:`e^t`, over t = 1..K and the ``A`` targets:
    ``track_err`` :math:`= \frac{1}{KA}\sum_{t,j} \lVert p^t_j \rVert`,
    ``track_rmse`` :math:`= (\frac{1}{KA}\sum_{t,j} \lVert p^t_j\rVert^2)^{1/2}`,
    ``nees`` :math:`= \frac{1}{K D_x}\sum_t e^{tT}\Omega^t_i e^t`.

    Args:
        means: ``(S, B, K+1, Dx)``.
        infos: ``(S, B, K+1, Dx, Dx)``.
        truth: ``(B, K+1, Dx)``.
    Returns:
        ``{name: S lists of B floats}``.
    """
    s, nb, k1, dx = means.shape
    a = dx // AGENT_DIM
    out = {"track_err": [], "track_rmse": [], "nees": []}
    for i in range(s):
        rows = {name: [] for name in out}
        for b in range(nb):
            err_sum, sq_sum, nees_sum = 0.0, 0.0, 0.0
            for t in range(1, k1):
                e = means[i, b, t] - truth[b, t]
                for j in range(a):
                    d = math.hypot(float(e[AGENT_DIM * j]), float(e[AGENT_DIM * j + 1]))
                    err_sum += d
                    sq_sum += d * d
                nees_sum += float(e @ infos[i, b, t] @ e)
            n = (k1 - 1) * a
            rows["track_err"].append(err_sum / n)
            rows["track_rmse"].append(math.sqrt(sq_sum / n))
            rows["nees"].append(nees_sum / (k1 - 1) / dx)
        for name in out:
            out[name].append(rows[name])
    return out


@torch.no_grad()
def reference_prediction_error(nodes, truth: Tensor, per_node: bool) -> list[list[float]]:
    """Roll each node's model out from the true state at t = 0 (Table II): mean position error over
    t = 1..K and targets, ``S`` lists of ``B`` floats (one roll-out copied to every node when
    the model is shared)."""
    nb, k1, dx = truth.shape
    a = dx // AGENT_DIM
    out = []
    for i in range(len(nodes) if per_node else 1):
        row = []
        for b in range(nb):
            x, err = truth[b, 0], 0.0
            for t in range(1, k1):
                x = nodes[i].mean(x).detach()
                for j in range(a):
                    err += math.hypot(float(x[AGENT_DIM * j] - truth[b, t, AGENT_DIM * j]),
                                      float(x[AGENT_DIM * j + 1] - truth[b, t, AGENT_DIM * j + 1]))
            row.append(err / ((k1 - 1) * a))
        out.append(row)
    return out if per_node else [list(out[0]) for _ in nodes]


def reference_rows(metrics: dict[str, list[list[float]]], names: list[str], is_sensor: list[bool], **keys) -> pd.DataFrame:
    """One row per metric x node x episode (in that order): ``*keys, node, node_kind, episode, metric, value``."""
    rows = []
    for metric, per_node in metrics.items():
        for i, vals in enumerate(per_node):
            for b, v in enumerate(vals):
                rows.append({**keys, "node": names[i], "node_kind": "sensor" if is_sensor[i] else "comm",
                             "episode": b, "metric": metric, "value": float(v)})
    return pd.DataFrame(rows)


# ------------------------------------------------------------------------------------------
class ReferenceYu:
    """The Yu study through the naive implementation: same config, data and seeds as
    :class:`dslearn.studies.yu.YuStudy`; its own weights, fusion, initial belief, filter,
    learning loop, metrics and rows."""

    def __init__(self, cfg):
        self.cfg = cfg

    @classmethod
    def from_config(cls, cfg) -> "ReferenceYu":
        return cls(cfg)

    def _check(self, model, obs) -> None:
        c = self.cfg
        if not isinstance(obs, LinearPositionObservation) or obs.learnable:
            raise ConfigError(f"observation.name={c.observation.name!r}: the reference implementation supports 'linear' only")
        step = c.filter.get("predict")
        if step is not None and step.get("_target_") != "dslearn.filters.information.ExtendedPredict":
            raise ConfigError(f"filter.predict._target_={step.get('_target_')!r}: the reference implementation supports the EKF "
                              "prediction step only (dslearn.filters.information.ExtendedPredict)")
        if isinstance(model, GPMotionModel):
            mc = c.model
            if mc.get("noise", "latent") not in ("latent", "predictive"):
                raise ConfigError(f"model.noise={mc.noise!r}: the reference implementation supports latent and predictive only")
            if mc.get("mean", "zero") not in ("zero", "identity"):
                raise ConfigError(f"model.mean={mc.mean!r}: the reference implementation supports zero and identity only")
            if mc.get("fit_every", 0) or mc.get("variant", "exact") not in ("exact", "window") or mc.get("factor_dtype"):
                raise ConfigError("model: the reference implementation supports the exact and window GPs with fixed "
                                  "hyperparameters in the run's dtype only (variant=exact|window, fit_every=0, factor_dtype=null)")
        elif not isinstance(model, (ConstantVelocity, SocialForce)):
            raise ConfigError(f"model.name={c.model.name!r}: the reference implementation supports lin, sfm and the exact / window GPs")

    def run(self, progress: bool = False) -> pd.DataFrame:
        c = self.cfg
        torch.manual_seed(int(c.seed))
        dtype, device = resolve_dtype(c.dtype), resolve_device(c.device)
        if device.type != "cpu" or dtype != torch.float64:
            raise ConfigError("device, dtype: the reference implementation runs on cpu in float64 only")
        scenario, network = build_scenario(c), build_network(c)
        model = build_motion_model(c.model, scenario, network, dtype, device)
        obs = build_observation(c.observation, network, dtype, device)
        self._check(model, obs)
        fusion = ReferenceFusion.from_config(c.consensus, network.adjacency)
        ctx = scenario.ctx()
        test, train = sample_split(scenario, network, int(c.seed), c.data.test_episodes, c.data.train_episodes, dtype, device)
        S = network.num_nodes
        learnable = isinstance(model, GPMotionModel)
        if learnable:
            mc = c.model
            window = int(mc.window) if mc.get("variant", "exact") == "window" else None
            nodes = [ReferenceGP(scenario.state_dim, mc.outputscale, mc.lengthscale, mc.noise_std, mc.get("mean", "zero"),
                                 mc.get("noise", "latent"), dtype, window) for _ in range(S)]
        else:
            nodes = [_ParametricRef(model, ctx)] * S
        self.ref_nodes, self.ref_fusion = nodes, fusion
        gate = c.filter.get("learn_gate_std")
        sig2 = float(obs.noise_std) ** 2
        names, sensor = list(network.names), [i < network.num_sensors for i in range(S)]
        keys = dict(model=str(c.model.name), consensus=fusion.name, omega=fusion.omega_label if fusion.uses_omega else "-",
                    iterations=fusion.iterations if fusion.name not in ("individual", "centralized") else 0,
                    weights=str(c.consensus.weights), train_episodes=int(c.data.train_episodes),
                    test_episodes=int(c.data.test_episodes))

        def init(meas: Tensor, visible: Tensor, b: int):
            return reference_initial_belief(meas, visible, b, float(network.meas_std), ctx.dt, scenario.area, fusion,
                                            c.filter.prior_pos_std, c.filter.prior_vel_std)

        def evaluate(k: int) -> pd.DataFrame:  # one test episode at a time
            means, infos = [], []
            for b in range(len(test)):
                y0, o0 = init(test.meas, test.visible, b)
                mb, ob = self._track_one(test.measurements, b, nodes, fusion, sig2, y0, o0, learn=False, gate=None)
                means.append(mb)
                infos.append(ob)
            metrics = reference_tracking_metrics(torch.stack(means, 1), torch.stack(infos, 1), test.states)
            metrics["pred_err"] = reference_prediction_error(nodes, test.states, learnable)
            return reference_rows(metrics, names, sensor, **keys, train_seen=int(k))

        ev = c.data.get("eval_at")
        checkpoints = sorted({int(v) for v in ev}) if (ev is not None and learnable) else [int(c.data.train_episodes)]
        frames, seen = [], 0
        for k in checkpoints:  # Algorithm 1: learn from training episodes in order, evaluate at each checkpoint
            while learnable and seen < k:
                y0, o0 = init(train.meas, train.visible, seen)
                self._track_one(train.measurements, seen, nodes, fusion, sig2, y0, o0, learn=True, gate=gate)
                seen += 1
            frames.append(evaluate(k))
        return pd.concat(frames, ignore_index=True)

    # ------------------------------------------------------------------------------------
    def _track_one(self, ep, b, nodes, fusion, sig2, y0, o0, learn, gate):
        """One episode ``b``; ``y0``, ``o0``: ``S`` initial means ``(Dx,)`` and information matrices.
        Returns ``(S, K+1, Dx)``, ``(S, K+1, Dx, Dx)``."""
        S, K = len(nodes), ep.steps
        dx = y0[0].shape[-1]
        dtype = y0[0].dtype
        A = dx // AGENT_DIM
        y = [y0[i].clone() for i in range(S)]
        om = [o0[i].clone() for i in range(S)]
        hist_y, hist_o = [torch.stack(y)], [torch.stack(om)]
        C = torch.zeros(2, AGENT_DIM, dtype=dtype)
        C[0, 0] = C[1, 1] = 1.0
        Rinv = torch.eye(2, dtype=dtype) / sig2
        for t in range(1, K + 1):
            q_pred, o_pred, dq, do = [], [], [], []
            for i in range(S):
                P = spd_inverse(om[i])  # inverse through Cholesky, jitter as in the fast path
                mean, F, Q = nodes[i].linearize(y[i], P)
                Pp = F @ P @ F.T + Q
                Pp = 0.5 * (Pp + Pp.T)
                Op = spd_inverse(Pp)
                o_pred.append(Op)
                q_pred.append(Op @ mean)
                dqi = torch.zeros(dx, dtype=dtype)
                doi = torch.zeros(dx, dx, dtype=dtype)
                for j in range(A):
                    if bool(ep.visible[i, b, t, j]):
                        sl = slice(j * AGENT_DIM, (j + 1) * AGENT_DIM)
                        dqi[sl] += C.T @ Rinv @ ep.meas[i, b, t, j]
                        doi[sl, sl] += C.T @ Rinv @ C
                dq.append(dqi)
                do.append(doi)
            q_new, o_new = fusion(q_pred, o_pred, dq, do)
            y_new = [torch.cholesky_solve(q_new[i].unsqueeze(-1), safe_cholesky(o_new[i])).squeeze(-1) for i in range(S)]
            if learn:
                for i in range(S):  # D_f += (y^{t-1}, y^t) where the belief at t-1 passes the gate
                    nodes[i].add(y[i], y_new[i], gate is None or self._informed(hist_o[-1][i], gate))
            y, om = y_new, o_new
            hist_y.append(torch.stack(y))
            hist_o.append(torch.stack(om))
        return torch.stack(hist_y, 1), torch.stack(hist_o, 1)

    @staticmethod
    def _informed(o: Tensor, gate: float) -> bool:
        """Every target's position standard deviation (from ``o^{-1}``) is at most ``gate``."""
        var = spd_inverse(o).diagonal()
        for j in range(o.shape[-1] // AGENT_DIM):
            if var[j * AGENT_DIM] > gate**2 or var[j * AGENT_DIM + 1] > gate**2:
                return False
        return True


def run_reference(cfg) -> pd.DataFrame:
    """The reference implementation of :func:`dslearn.studies.yu.run` (same rows' values)."""
    return ReferenceYu.from_config(cfg).run()


def compare_results(fast: pd.DataFrame, ref: pd.DataFrame) -> dict:
    r"""Fast-path rows vs reference rows of one run.

    The rows must match one to one on :data:`ROW_KEYS` (the labels both write) and in order; the
    values are compared by :math:`|a - b| / \max(1, |a|, |b|)` (two NaNs agree, one NaN differs
    infinitely). Returns ``max_diff`` (the largest such difference; ``inf`` when the labels
    differ) and ``worst`` (which row, with both values, or which label differs).
    """
    if len(fast) != len(ref):
        return dict(max_diff=math.inf, worst=f"row counts differ: fast {len(fast)}, reference {len(ref)}")
    for col in ROW_KEYS:
        if col not in fast or col not in ref:
            return dict(max_diff=math.inf, worst=f"column {col!r} missing from {'fast' if col not in fast else 'reference'}")
        a, b = fast[col].astype(str).to_numpy(), ref[col].astype(str).to_numpy()
        if (a != b).any():
            k = int(np.argmax(a != b))
            return dict(max_diff=math.inf, worst=f"row {k}: {col} differs (fast {a[k]!r}, reference {b[k]!r})")
    a, b = fast["value"].to_numpy(float), ref["value"].to_numpy(float)
    with np.errstate(invalid="ignore"):
        d = np.abs(a - b) / np.maximum(1.0, np.maximum(np.abs(a), np.abs(b)))
    both_nan = np.isnan(a) & np.isnan(b)
    d = np.where(both_nan, 0.0, np.where(np.isnan(d), np.inf, d))
    if not len(d):
        return dict(max_diff=0.0, worst="")
    k = int(np.argmax(d))
    r = fast.iloc[k]
    return dict(max_diff=float(d[k]),
                worst=f"{r['metric']} node {r['node']} episode {r['episode']} train_seen {r['train_seen']}: "
                      f"fast {a[k]:.10g}, reference {b[k]:.10g}")
