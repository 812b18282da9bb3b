r"""Monte Carlo engine: identification + EKF-FG tracking and the baselines on the same data.

Everything is vectorised over a grid of ``C`` configurations (``sigma_y``, number of FG
iterations) and ``B`` Monte Carlo runs; only the ``K`` timings are a Python loop. The truth
trajectories and the standard-normal sensor noise are shared by all configurations (common
random numbers), the noise is scaled by each configuration's ``sigma_y``. Every computation
is per run (no reduction over ``B``), so a run's results do not depend on the other runs of
its batch; :func:`~dslearn.sim.squared_range.run_noise` gives each run its own stream. The engine
returns estimates (and the truth it simulated from, apart); their errors against the truth and the
CRLB at the true state are computed in :mod:`dslearn.metrics.identification`.

:class:`TrackerSettings`' defaults are the paper's equations (``obs_var="crlb"``, no gate,
flooding, scalar graph); the study's configuration (``conf/task/jiang_fg.yaml``) switches the
tracker to ``obs_var="convergence"``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import torch
from torch import Tensor

from dslearn.learning.factor_graph.centralized import cv_predict, gauss_newton, iterated_ekf_update
from dslearn.learning.factor_graph.crlb import crlb
from dslearn.learning.factor_graph.identification import compress_measurements, identify
from dslearn.filters.ekf_fg import TrackState, ekf_fg_step, observation_variance, predict


@dataclass
class TrackerSettings:
    """Knobs of the identification + tracking loop (see ``conf/task/jiang_fg.yaml``)."""

    num_samples: int = 60
    init_guess: tuple[float, ...] = (0.0, 0.0)
    init_guess_mode: str = "fixed"            # "fixed" (paper: init_guess) | "prediction" (warm start)
    init_var: float = 100.0
    prior_var: float = float("inf")
    relinearize: bool = False
    schedule: str = "flooding"               # "flooding" (paper) | "sequential" (one parameter at a time)
    damping: float = 0.0                     # zeta damping d: (1-d) new + d old (0 = paper)
    graph: str = "scalar"                    # "scalar" (paper, Fig. 1) | "joint" (one vector node: Gauss-Newton FG)
    taylor_point: str = "prediction"         # first expansion point: "prediction" (paper) | "guess" (= the start)
    measurement_var: str = "sample"          # "sample" | "known"
    crlb_form: str = "trace_inverse"          # "trace_inverse" (Eq. 27) | "paper_eq33"
    initial_state: tuple[float, ...] = (2.0, -2.0)
    initial_state_var: float = 10.0
    initial_gradient_var: float = 10.0
    process_var: float = 1.0
    obs_var: str = "crlb"                    # "crlb" (paper: sigma_e^2 = CRLB) | "convergence" (+ last FG step^2)
    gate: float | None = None                # innovation gate on the FG output (None = paper, no gate)
    gradient_var: float = 0.01
    baseline_iters: int = 3
    lambda_tol: float = 1e-8
    converge_tol: float = 1e-3

    @classmethod
    def from_config(cls, **values) -> "TrackerSettings":
        """From plain configuration values: lists become tuples, ``prior_var=None`` (no prior node) becomes inf."""
        for key in ("init_guess", "initial_state"):
            if key in values:
                values[key] = tuple(float(v) for v in values[key])
        if "prior_var" in values and values["prior_var"] is None:
            values["prior_var"] = float("inf")
        return cls(**values)


@dataclass
class SimulationOutput:
    """Tensors of one Monte Carlo batch. ``C`` configs, ``B`` runs, ``K`` timings, ``M`` params."""

    truth: Tensor             # (B, K, M)
    fg_iter_means: Tensor     # (T+1, C, B, K, M) identification estimate after t = 0..T iterations
    estimates: dict = field(default_factory=dict)  # name -> (C, B, K, M)
    obs_var: Tensor = None     # (C, B, K) sigma_e^2 used by EKF-FG (mean over M)
    gated: Tensor = None       # (C, B) count of gated (inflated) FG outputs over timings and parameters
    near_zero_lambda: Tensor = None  # (C, B) count over timings
    floored: Tensor = None           # (C, B)
    iters_to_converge: Tensor = None  # (C, B, K) at the config's full T_max iterations


@dataclass
class TimingOutput:
    """What one timing of :class:`EkfFgTracker` computed, besides its new state (``C`` configurations, ``B`` runs)."""

    x_pred: Tensor     # (C, B, M) the prediction (Eq. 17)
    eta: Tensor        # (C, B, M) the identification's output after each configuration's t_c iterations
    obs_var: Tensor    # (C, B, M) sigma_e^2 of that output (Eq. 5, :func:`observation_variance`)
    gated: Tensor      # (C, B, M) bool, the outputs the innovation gate inflated
    ident: object      # the identification's trace (:func:`identify`)


class EkfFgTracker:
    """The EKF-FG loop (Jiang et al.): at every timing predict (Eq. 17), identify the parameters over the factor
    graph at the prediction from the sensors' compressed samples (Eqs. 6-16), refine with that output and update
    the gradient (Eqs. 18-19). The one implementation of the loop: the study's Monte Carlo engine
    (:func:`simulate`) and the matrix's method (:class:`dslearn.methods.factor_graph.FactorGraphMethod`) both step it.

    Args:
        h: measurement function ``(*B, M) -> (*B, N)``.
        settings: :class:`TrackerSettings` (its ``initial_state`` gives ``M``).
        sigma_y: ``(C, B)`` the sensors' noise std per configuration and run.
        num_iters: ``(C,)`` FG iterations per configuration (>= 1).
        num_samples: ``L``, samples per sensor and timing (the CRLB's).
    """

    def __init__(self, h: Callable[[Tensor], Tensor], settings: TrackerSettings, sigma_y: Tensor, num_iters: Tensor,
                 num_samples: int):
        c, b = sigma_y.shape
        dt, dev = sigma_y.dtype, sigma_y.device
        m = len(settings.initial_state)
        self.h, self.settings, self.sigma_y, self.num_iters, self.num_samples = h, settings, sigma_y, num_iters, num_samples
        self.max_iters = int(num_iters.max())
        self.guess = torch.tensor(settings.init_guess, dtype=dt, device=dev)
        self.cidx = torch.arange(c, device=dev)
        x0 = torch.tensor(settings.initial_state, dtype=dt, device=dev).expand(c, b, m)
        self.state = TrackState(x0.clone(), torch.full((c, b, m), settings.initial_state_var, dtype=dt, device=dev),
                                torch.zeros(c, b, m, dtype=dt, device=dev),
                                torch.full((c, b, m), settings.initial_gradient_var, dtype=dt, device=dev))

    def step(self, samples: Tensor) -> TimingOutput:
        """One timing on the raw samples ``(C, B, N, L)`` (or broadcastable to it); updates :attr:`state`."""
        s, h, st = self.settings, self.h, self.state
        x_pred, P_pred = predict(st, s.process_var)
        ym, yv = compress_measurements(samples, None if s.measurement_var == "sample" else self.sigma_y.square())
        start = x_pred if s.init_guess_mode == "prediction" else self.guess
        beta = x_pred if s.taylor_point == "prediction" else torch.broadcast_to(start, x_pred.shape)
        ident = identify(h, ym, yv, beta, start, self.max_iters, init_var=s.init_var, prior_var=s.prior_var,
                         relinearize=s.relinearize, lambda_tol=s.lambda_tol, tol=s.converge_tol,
                         schedule=s.schedule, damping=s.damping, graph=s.graph)
        eta = ident.mean[self.num_iters, self.cidx]                         # (C, B, M): output after t_c iterations
        bound = crlb(h, x_pred, self.sigma_y, self.num_samples, s.crlb_form)  # the paper's sigma_e^2 (Eq. 5, 27/33)
        obs_var, gated = observation_variance(bound, eta, ident.mean[self.num_iters - 1, self.cidx], x_pred, P_pred,
                                              s.obs_var, s.gate)
        self.state = ekf_fg_step(st, eta, obs_var, s.process_var, s.gradient_var, x_pred=x_pred, P_pred=P_pred)
        return TimingOutput(x_pred, eta, obs_var, gated, ident)

    def run(self, samples: Tensor) -> tuple[Tensor, Tensor]:
        """Every timing of ``samples (C, B, K, N, L)`` in turn: the refined means and variances ``(C, B, K, M)``."""
        means, variances = [], []
        for k in range(samples.shape[2]):
            self.step(samples[:, :, k])
            means.append(self.state.x_mean)
            variances.append(self.state.x_var)
        return torch.stack(means, 2), torch.stack(variances, 2)


def simulate(
    h: Callable[[Tensor], Tensor],
    truth: Tensor,
    noise: Tensor,
    sigma_y: Tensor,
    num_iters: Tensor,
    settings: TrackerSettings,
) -> SimulationOutput:
    """Run identification + EKF-FG and the centralised baselines.

    Args:
        h: measurement function ``(*B, M) -> (*B, N)``.
        truth: ``(B, K, M)`` true parameters.
        noise: ``(B, K, N, L)`` standard-normal sensor noise.
        sigma_y: ``(C,)`` sensor noise std per configuration.
        num_iters: ``(C,)`` FG iterations per configuration (>= 1).
        settings: :class:`TrackerSettings`.

    Returns:
        :class:`SimulationOutput`.
    """
    B, K, M = truth.shape
    C = sigma_y.shape[0]
    L = noise.shape[-1]
    assert noise.shape[:2] == (B, K) and num_iters.shape == (C,), (noise.shape, num_iters.shape)
    dev, dt = truth.device, truth.dtype
    assert len(settings.init_guess) == M, "init_guess must have M entries"
    sig = sigma_y.to(dt)[:, None]                                   # (C, 1) -> broadcast over B
    sig_cb = sig.expand(C, B)

    tracker = EkfFgTracker(h, settings, sig_cb, num_iters, L)
    x0 = tracker.state.x_mean
    z = torch.cat([x0, torch.zeros_like(x0)], -1)
    P = torch.diag_embed(torch.cat([torch.full((M,), settings.initial_state_var),
                                    torch.full((M,), settings.initial_gradient_var)]).to(z)).expand(C, B, 2 * M, 2 * M)

    fg_means, est = [], {k: [] for k in ("prediction", "fg_identification", "ekf_fg", "centralized_gn", "centralized_ekf")}
    obs_vars, conv = [], []
    near_zero = torch.zeros(C, B, dtype=torch.long, device=dev)
    floored = torch.zeros(C, B, dtype=torch.long, device=dev)
    gated = torch.zeros(C, B, dtype=torch.long, device=dev)
    for k in range(K):
        xk = truth[:, k]                                            # (B, M)
        with torch.no_grad():
            samples = h(xk).unsqueeze(-1) + sig[..., None, None] * noise[:, k]   # (C, B, N, L)
        # --- EKF-FG: predict (Eq. 17), identify at the prediction (Eqs. 6-16), refine (Eq. 18-19)
        out = tracker.step(samples)
        x_pred, eta, obs_var, ident, st = out.x_pred, out.eta, out.obs_var, out.ident, tracker.state
        gated += out.gated.sum(-1)
        fg_means.append(ident.mean)                                 # (T+1, C, B, M)
        near_zero += ident.near_zero_lambda
        floored += ident.floored
        conv.append(ident.iters_to_converge)
        # --- centralised baselines on the same raw samples
        z_pred, P_pred_c = cv_predict(z, P, settings.process_var, settings.gradient_var)
        gn = gauss_newton(h, samples, z_pred[..., :M], settings.baseline_iters)
        z, P = iterated_ekf_update(h, samples, sig_cb, z_pred, P_pred_c, settings.baseline_iters)
        obs_vars.append(obs_var.mean(-1))
        for name, val in (("prediction", x_pred), ("fg_identification", eta), ("ekf_fg", st.x_mean),
                          ("centralized_gn", gn), ("centralized_ekf", z[..., :M])):
            est[name].append(val)
    return SimulationOutput(
        truth=truth,
        fg_iter_means=torch.stack(fg_means, -2),
        estimates={k: torch.stack(v, 2) for k, v in est.items()},
        obs_var=torch.stack(obs_vars, -1),
        near_zero_lambda=near_zero,
        floored=floored,
        gated=gated,
        iters_to_converge=torch.stack(conv, -1),
    )
