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
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import List

import pandas as pd
import torch
from torch import Tensor

from dslearn.filters.gp_bayes import AdditiveModel, GPModel, adf_step, ekf_step, pf_step, ukf_step
from dslearn.filters.gp_moments import fit_gps
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
    return Benchmark(mu0, x0, x1, z, gps[0], gps[1])


# ------------------------------------------------------------------------------------------ the study
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

    def run(self, diagnostics=None, progress: bool = False) -> pd.DataFrame:
        s = self.settings
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
        for node, gp in (("gp_transition", bench.gp_f.gp), ("gp_observation", bench.gp_g.gp)):
            for metric, v in (("lengthscale", gp.lengthscales[0, 0]), ("signal_var", gp.signal_var[0]),
                              ("noise_var", gp.noise_var[0])):
                frames.append(rows([float(v)], ("episode",), metric, node=node, model="gp", consensus="none")
                              .assign(episode=-1))
        df = pd.concat(frames, ignore_index=True)
        cols = ["node", "model", "consensus", "episode", "metric", "value"]
        return df[cols]
