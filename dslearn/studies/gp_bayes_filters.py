r"""Study ``gp_bayes_filters``: GP-Bayes filters on the scalar benchmark of Deisenroth, Huber, Hanebeck,
*Analytic moment-based Gaussian process filtering*, ICML 2009 (Sec. 5.1).

The model (one node, scalar state):

.. math::
    x_1 = \tfrac12 x_0 + \frac{25 x_0}{1 + x_0^2} + w,\quad z_1 = 5 \sin(2 x_1) + v,\quad
    w \sim \mathcal N(0, \sigma_w^2),\ v \sim \mathcal N(0, \sigma_v^2).

Two GPs (GPyTorch, SE-ARD kernel, exact marginal likelihood: :func:`~dslearn.filters.gp_moments.fit_gps`)
learn the transition and the measurement function from ``train_points`` inputs drawn uniformly on
``train_range`` each, with noisy targets. For every one of ``num_cases`` prior means
:math:`\mu_0` on ``linspace(prior_mean_range)``, the true initial state is drawn from
:math:`\mathcal N(\mu_0, \sigma_0^2)`, the true next state and its measurement from the model, and
every filter of ``filters`` runs one predict + update step from the prior :math:`\mathcal N(\mu_0, \sigma_0^2)`
(all cases at once, batched): ``ekf``, ``ukf``, ``pf`` on the true model; ``gp_ekf``, ``gp_ukf``
(Ko & Fox), ``gp_ukf_mm`` (GP-UKF with the sigma-point average of the GP variance), ``gp_pf`` and
``gp_adf`` on the GPs (:mod:`dslearn.filters.gp_bayes`).

Rows (``node`` = the filter, the one node's estimator; ``model`` = ``true`` or ``gp``; ``episode`` = the
case): ``nll_x``, ``maha_x``, ``rmse_x``, ``nll_z`` (:mod:`dslearn.metrics.filtering`), ``ess`` for the
particle filters, the trained hyperparameters (``node`` = ``gp_transition`` / ``gp_observation``,
``episode = -1``) and ``runtime_s`` per filter. The report (:mod:`dslearn.reports.gp_bayes_filters`)
averages over the cases (mean and standard error). Random streams: the training data, the truth and each
particle filter draw from their own generators seeded by ``(seed, name)``
(:func:`dslearn.streams.stream_seed`), so one filter's numbers do not depend on which others run.
Python use::

    from dslearn import api
    df = api.run("experiment=gp_bayes_filters", "task.num_cases=50")

**On a network** (``task.nodes`` :math:`S > 1`; the paper has no network version): ``nodes`` sensors on
``graph`` (``ring``, ``complete``, ``path``) all estimate the same :math:`x_1`. Every node has the same prior
:math:`\mathcal N(\mu_0, \sigma_0^2)` and the same prediction (the filter's own), and its own measurement
:math:`z_{1,i} = 5 \sin(2 x_1) + v_i`, :math:`v_i` independent (stream ``network_measurements``; the
single-node draws are unchanged). The filter's measurement moments at the prediction (:math:`\mu_z`, :math:`S_z`,
:math:`C = \mathrm{Cov}[x, z]`) become each node's novel information by statistical linear regression
(:func:`~dslearn.filters.gp_bayes.slr_information`: :math:`H = C^T P^{-1}`, :math:`R = S_z - H P H^T`,
:math:`\delta\Omega = H^T R^{-1} H`, :math:`\delta q_i = H^T R^{-1} (z_i - \mu_z + H m)`); alone, a node
gets exactly the filter's own update from its measurement. The fusion ``consensus`` (:mod:`dslearn.fusion.strategies`:
``individual``, ``ce``, ``cm``, ``ci``, ``hybrid``, ``centralized``) with ``rounds`` rounds of the
``weights`` rule (:func:`~dslearn.fusion.weights.consensus_weights`) and ``omega`` gives each node's posterior.
The particle filters take the same road: their predicted particles give the moments (a Gaussian posterior;
their own weights and resampling are not used, so no ``ess`` row). Every node shares :math:`H` and :math:`R`, so
the effective noise :math:`R` (which holds the linearisation error of :math:`g` at the prediction, common
to every node, not only :math:`\sigma_v^2`) counts as independent at every node. Rows then carry
``sensor`` (the node's index; ``-1`` for a row of every node: ``runtime_s``, ``slr_clamped`` = 1 where
:math:`R` was floored in that case, the GPs' hyperparameters), ``consensus`` (the fusion), ``graph``,
``rounds`` (0 for ``individual`` / ``centralized``), ``weights``, ``omega`` (``-`` where the fusion has
none). With ``nodes: 1`` (the default) the rows are those of the single node above, and every network
setting must keep its default (:func:`check_network`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, List, Optional

import pandas as pd
import torch
from torch import Tensor

from dslearn.errors import ConfigError, check_choice
from dslearn.filters.gp_bayes import (AdditiveModel, GPModel, StepResult, adf_step, ekf_step, pf_step, slr_information,
                                      ukf_step)
from dslearn.filters.gp_moments import fit_gps
from dslearn.filters.information import to_information, to_moment
from dslearn.fusion.strategies import FUSIONS, Fusion, make_fusion
from dslearn.fusion.weights import WEIGHT_METHODS, consensus_weights
from dslearn.metrics.filtering import filter_step_metrics
from dslearn.metrics.rows import rows
from dslearn.settings import ranged
from dslearn.streams import stream_seed

TASK = "gp_bayes_filters"
#: the filters, in the order of the paper's table (true model first)
FILTERS = ("ekf", "ukf", "pf", "gp_ekf", "gp_ukf", "gp_ukf_mm", "gp_pf", "gp_adf")
LABELS = {"ekf": "EKF", "ukf": "UKF", "pf": "PF", "gp_ekf": "GP-EKF", "gp_ukf": "GP-UKF",
          "gp_ukf_mm": "GP-UKF (moment matching)", "gp_pf": "GP-PF", "gp_adf": "GP-ADF"}
METRICS = ("nll_x", "maha_x", "rmse_x", "nll_z")
#: communication graphs of the network version (``task.graph``)
GRAPHS = ("ring", "complete", "path")
#: the settings that only a network (``task.nodes > 1``) reads
NETWORK_KEYS = ("graph", "consensus", "rounds", "weights", "omega")


# ------------------------------------------------------------------------------------------ settings
@dataclass
class GPTraining:
    """GPyTorch training of both GPs: Adam on the exact marginal likelihood."""

    iterations: int = ranged(200, ge=1)
    lr: float = ranged(0.1, gt=0.0)
    min_noise: float = ranged(1e-8, gt=0.0)  # lower bound of the likelihood's noise variance (GPyTorch: 1e-4)


@dataclass
class UKFParams:
    """Scaled unscented transform (the reference code's alpha = 1, beta = 0, kappa = 2 = 3 - D)."""

    alpha: float = ranged(1.0, gt=0.0)
    beta: float = 0.0
    kappa: float = 2.0  # alpha^2 (1 + kappa) > 0 is checked (scalar state)


@dataclass
class GPBayesTask:
    """The settings of task ``gp_bayes_filters`` (``conf/task/gp_bayes_filters.yaml``)."""

    _target_: str = "dslearn.studies.gp_bayes_filters.GPBayesFiltersStudy"
    name: str = TASK
    prior_std: float = ranged(0.5, gt=0.0)          # sigma_0
    process_std: float = ranged(0.2, gt=0.0)        # sigma_w
    measurement_std: float = ranged(0.01, gt=0.0)   # sigma_v
    train_points: int = ranged(100, ge=2)           # per GP
    train_range: List[float] = ranged(factory=lambda: [-10.0, 10.0], min_len=2, max_len=2)
    num_cases: int = ranged(200, ge=1)
    prior_mean_range: List[float] = ranged(factory=lambda: [-10.0, 10.0], min_len=2, max_len=2)
    num_particles: int = ranged(1000, ge=1)
    filters: List[str] = ranged(factory=lambda: list(FILTERS), choices=FILTERS, each=True, min_len=1)
    ukf: UKFParams = field(default_factory=UKFParams)
    gp: GPTraining = field(default_factory=GPTraining)
    # the network version (module docstring); with nodes = 1 the others must keep their defaults
    nodes: int = ranged(1, ge=1)                                    # S sensors
    graph: str = ranged("ring", choices=GRAPHS)
    consensus: str = ranged("hybrid", choices=FUSIONS)              # dslearn.fusion.strategies
    rounds: int = ranged(4, ge=1)                                   # L
    weights: str = ranged("uniform", choices=WEIGHT_METHODS)        # dslearn.fusion.weights
    omega: Any = "one"                                              # one | nodes | a number > 0 (hybrid, cm)


def check_network(t) -> None:
    """The network settings' cross-field rules (``t``: the task's settings, a dataclass or its config node):
    ``omega`` is ``one``, ``nodes`` or a finite number > 0, and with ``nodes == 1`` every key of
    :data:`NETWORK_KEYS` keeps its default (a single node reads none of them). Raises :class:`ConfigError`."""
    om = t.omega
    if isinstance(om, str):
        check_choice("task.omega", om, ("one", "nodes"))
    elif isinstance(om, bool) or not isinstance(om, (int, float)) or not 0 < om < float("inf"):
        raise ConfigError(f"task.omega={om!r} must be > 0 and finite, 'one' or 'nodes'")
    default = GPBayesTask()
    if int(t.nodes) == 1:
        for k in NETWORK_KEYS:
            v = getattr(t, k)
            if v != getattr(default, k):
                raise ConfigError(f"task.{k}={v!r} is a network setting but task.nodes=1 (one node reads none); "
                                  f"remove it or set task.nodes >= 2")
        return
    # a fusion without consensus rounds (individual, centralized) reads no rounds nor weights; only cm and hybrid
    # read omega: a changed setting it would not read is refused
    from dslearn.learning.backprop import OMEGA_FUSIONS, WEIGHTED_FUSIONS

    unused = {"rounds": WEIGHTED_FUSIONS, "weights": WEIGHTED_FUSIONS, "omega": OMEGA_FUSIONS}
    for k, users in unused.items():
        v = getattr(t, k)
        if t.consensus not in users and v != getattr(default, k):
            raise ConfigError(f"task.{k}={v!r}: task.consensus={t.consensus} does not use it (only "
                              f"{'|'.join(users)} do); remove it")


def graph_adjacency(graph: str, nodes: int) -> Tensor:
    """Adjacency ``(S, S)`` bool of ``graph``: ``ring`` (node i linked to i +- 1 mod S), ``complete``, ``path``
    (i to i + 1)."""
    check_choice("task.graph", graph, GRAPHS)
    S = int(nodes)
    if graph == "complete":
        adj = torch.ones(S, S, dtype=torch.bool)
    else:
        adj = torch.zeros(S, S, dtype=torch.bool)
        i = torch.arange(S - 1 if graph == "path" else S)
        adj[i, (i + 1) % S] = True
        adj = adj | adj.T
    adj.fill_diagonal_(False)
    return adj


def network_fusion(s: GPBayesTask) -> Fusion:
    """The fusion of ``s.consensus`` over ``s.graph`` with ``s.nodes`` nodes (``s.rounds``, ``s.weights``,
    ``s.omega``)."""
    adj = graph_adjacency(s.graph, s.nodes)
    return make_fusion(s.consensus, consensus_weights(adj, s.weights), int(s.rounds), s.omega)


# ------------------------------------------------------------------------------------------ the model
def transition(x: Tensor) -> Tensor:
    """:math:`f(x) = x/2 + 25 x / (1 + x^2)` (elementwise)."""
    return 0.5 * x + 25.0 * x / (1.0 + x * x)


def measurement(x: Tensor) -> Tensor:
    """:math:`g(x) = 5 \\sin(2x)` (elementwise)."""
    return 5.0 * torch.sin(2.0 * x)


def _gen(seed: int, name: str) -> torch.Generator:
    return torch.Generator().manual_seed(stream_seed(int(seed), TASK, name))


def _draw(shape, gen: torch.Generator, dtype, device, uniform: bool = False) -> Tensor:
    fn = torch.rand if uniform else torch.randn
    return fn(shape, generator=gen, dtype=dtype).to(device)


@dataclass
class Benchmark:
    """The truth, the measurements and the trained GPs of one run."""

    prior_mean: Tensor   # (B, 1)
    x0: Tensor           # (B, 1)
    x1: Tensor           # (B, 1)
    z: Tensor            # (B, 1)
    gp_f: GPModel
    gp_g: GPModel
    z_nodes: Optional[Tensor] = None  # (S, B, 1): the network's measurements of x1 (task.nodes > 1)


def make_benchmark(s: GPBayesTask, seed: int, dtype, device) -> Benchmark:
    """Train the GPs and draw the truth (each from its own stream of ``seed``)."""
    lo, hi = (float(v) for v in s.train_range)
    n = int(s.train_points)
    gps = []
    for name, fn, std in (("train_transition", transition, s.process_std),
                          ("train_measurement", measurement, s.measurement_std)):
        g = _gen(seed, name)
        X = lo + (hi - lo) * _draw((n, 1), g, dtype, device, uniform=True)
        Y = fn(X) + std * _draw((n, 1), g, dtype, device)
        gps.append(GPModel(fit_gps(X, Y, s.gp.iterations, s.gp.lr, s.gp.min_noise)))
    a, b = (float(v) for v in s.prior_mean_range)
    mu0 = torch.linspace(a, b, int(s.num_cases), dtype=dtype, device=device).unsqueeze(-1)
    g = _gen(seed, "truth")
    x0 = mu0 + s.prior_std * _draw(mu0.shape, g, dtype, device)
    x1 = transition(x0) + s.process_std * _draw(mu0.shape, g, dtype, device)
    z = measurement(x1) + s.measurement_std * _draw(mu0.shape, g, dtype, device)
    z_nodes = None
    if int(s.nodes) > 1:  # its own stream: the draws above are those of the single node
        g = _gen(seed, "network_measurements")
        z_nodes = measurement(x1) + s.measurement_std * _draw((int(s.nodes), *mu0.shape), g, dtype, device)
    return Benchmark(mu0, x0, x1, z, gps[0], gps[1], z_nodes)


@dataclass
class NetworkStep:
    """One filter's step on the network: each node's posterior ``mean`` ``(S, B, 1)``, ``cov`` ``(S, B, 1, 1)``;
    ``step``: the filter's own step (its prediction and measurement moments, shared by every node);
    ``clamped`` ``(B,)``: where the effective noise of the regression was floored."""

    mean: Tensor
    cov: Tensor
    step: StepResult
    clamped: Tensor


# ------------------------------------------------------------------------------------------ the study
def _gp_rows(bench: Benchmark, **keys) -> list[pd.DataFrame]:
    """The trained GPs' hyperparameters (``node`` = ``gp_transition`` / ``gp_observation``, ``episode = -1``)."""
    frames = []
    for node, gp in (("gp_transition", bench.gp_f.gp), ("gp_observation", bench.gp_g.gp)):
        for metric, v in (("lengthscale", gp.lengthscales[0, 0]), ("signal_var", gp.signal_var[0]),
                          ("noise_var", gp.noise_var[0])):
            frames.append(rows([float(v)], ("episode",), metric, node=node, model="gp", consensus="none", **keys)
                          .assign(episode=-1))
    return frames


@dataclass
class GPBayesFiltersStudy:
    """Every filter of ``settings.filters`` on the scalar benchmark (module docstring). Slots: ``settings``,
    the run's ``seed``, ``dtype``, ``device``."""

    settings: GPBayesTask
    seed: int
    dtype: torch.dtype
    device: torch.device

    def true_models(self) -> tuple[AdditiveModel, AdditiveModel]:
        s, kw = self.settings, dict(dtype=self.dtype, device=self.device)
        return (AdditiveModel(transition, torch.full((1, 1), s.process_std ** 2, **kw)),
                AdditiveModel(measurement, torch.full((1, 1), s.measurement_std ** 2, **kw)))

    def step(self, name: str, bench: Benchmark, m: Tensor, P: Tensor):
        """One predict + update step of filter ``name`` from ``N(m, P)`` with the measurements of ``bench``."""
        s = self.settings
        f, g = self.true_models() if not name.startswith("gp_") else (bench.gp_f, bench.gp_g)
        u = dict(alpha=s.ukf.alpha, beta=s.ukf.beta, kappa=s.ukf.kappa)
        kind = name.removeprefix("gp_")
        if kind == "ekf":
            return ekf_step(f, g, m, P, bench.z)
        if kind in ("ukf", "ukf_mm"):
            return ukf_step(f, g, m, P, bench.z, noise="expected" if kind == "ukf_mm" else "mean", **u)
        if kind == "pf":
            return pf_step(f, g, m, P, bench.z, s.num_particles, _gen(self.seed, f"particles_{name}"))
        if kind == "adf":
            return adf_step(f, g, m, P, bench.z)
        raise ValueError(f"unknown filter {name!r}; choose from {list(FILTERS)}")

    def network_step(self, name: str, bench: Benchmark, m: Tensor, P: Tensor, fusion: Fusion) -> NetworkStep:
        """Filter ``name`` on the network (module docstring): its step from ``N(m, P)`` gives the prediction
        and the measurement moments (its own update is not used), the regression each node's novel information
        from ``bench.z_nodes``, ``fusion`` each node's posterior."""
        res = self.step(name, bench, m, P)
        z = bench.z_nodes
        S = z.shape[0]
        dq, domega, clamped = slr_information(res.pred_mean, res.pred_cov, res.z_mean, res.z_cov, res.cross, z)
        q_pred, o_pred = to_information(res.pred_mean, res.pred_cov)
        q, o = fusion(q_pred.expand(S, *q_pred.shape), o_pred.expand(S, *o_pred.shape), dq,
                      domega.expand(S, *domega.shape))
        mean, cov = to_moment(q, o)
        return NetworkStep(mean, cov, res, clamped)

    def run(self, diagnostics=None, progress: bool = False) -> pd.DataFrame:
        s = self.settings
        check_network(s)
        if int(s.nodes) > 1:
            return self.run_network()
        bench = make_benchmark(s, self.seed, self.dtype, self.device)
        m = bench.prior_mean
        P = torch.full((*m.shape, 1), s.prior_std ** 2, dtype=self.dtype, device=self.device)
        frames = []
        for name in s.filters:
            t0 = time.perf_counter()
            res = self.step(name, bench, m, P)
            wall = time.perf_counter() - t0
            keys = dict(node=name, model="gp" if name.startswith("gp_") else "true", consensus="none")
            metrics = filter_step_metrics(bench.x1, res.mean, res.cov, bench.z, res.z_mean, res.z_cov)
            if res.ess is not None:
                metrics["ess"] = res.ess
            for metric, v in metrics.items():
                frames.append(rows(v, ("episode",), metric, **keys))
            frames.append(rows([wall], ("episode",), "runtime_s", **keys))
        frames += _gp_rows(bench)
        df = pd.concat(frames, ignore_index=True)
        cols = ["node", "model", "consensus", "episode", "metric", "value"]
        return df[cols]

    def run_network(self) -> pd.DataFrame:
        """The network version (``task.nodes > 1``): the rows of :meth:`run` per node, with the columns of the
        module docstring."""
        s = self.settings
        bench = make_benchmark(s, self.seed, self.dtype, self.device)
        fusion = network_fusion(s)
        m = bench.prior_mean
        P = torch.full((*m.shape, 1), s.prior_std ** 2, dtype=self.dtype, device=self.device)
        net = dict(graph=str(s.graph), rounds=fusion.rounds, weights=str(s.weights),
                   omega=fusion.omega_label if fusion.uses_omega else "-")
        frames = []
        for name in s.filters:
            t0 = time.perf_counter()
            res = self.network_step(name, bench, m, P, fusion)
            wall = time.perf_counter() - t0
            keys = dict(node=name, model="gp" if name.startswith("gp_") else "true", consensus=fusion.name, **net)
            metrics = filter_step_metrics(bench.x1, res.mean, res.cov, bench.z_nodes, res.step.z_mean, res.step.z_cov)
            for metric, v in metrics.items():
                frames.append(rows(v, ("sensor", "episode"), metric, **keys))
            frames.append(rows(res.clamped.to(torch.float64), ("episode",), "slr_clamped", sensor=-1, **keys))
            frames.append(rows([wall], ("episode",), "runtime_s", sensor=-1, **keys))
        frames += _gp_rows(bench, sensor=-1, **net)
        df = pd.concat(frames, ignore_index=True)
        cols = ["node", "sensor", "model", "consensus", "graph", "rounds", "weights", "omega", "episode", "metric",
                "value"]
        return df[cols]
