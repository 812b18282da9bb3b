r"""Jiang et al.'s method (ISITA 2022) as a method of the matrix: at every timing the fusion centre identifies
the source's parameter over the factor graph from the sensors' compressed squared-range samples (Gaussian
belief propagation, Eqs. 6-16, expanded at the tracker's prediction) and the EKF-FG refines its prediction
with that output (Eqs. 17-19) — the loop of :class:`dslearn.learning.factor_graph.engine.EkfFgTracker`, the one
that the study's :func:`~dslearn.learning.factor_graph.engine.simulate` steps, here on the measurements alone (no
truth, no centralised baselines, one configuration).

Its estimates are the EKF-FG's refined means ``x_{k|k}`` with the diagonal covariances
``diag(P_{x,k|k})`` (the tracker follows each parameter as an independent scalar, Eq. 18), reported by one
node, the fusion centre. The identification is online within every episode: the training episodes teach
it nothing. It takes no motion model, observation model or fusion part: the sensors' squared-range model is
the scenario's (its sensor positions and ``sigma_y``, the scenario's network), the fusion is the factor
graph's own message passing.

:class:`FactorGraphMotionMethod` (``filter=fg_ekf_lin``) is the family's form for position sensors: the same
messages identify the parameters of a motion model, a damped constant-velocity model ``theta = (a, ln q)``, from
the training episodes' measurements (:mod:`dslearn.learning.factor_graph.motion`), and a Kalman filter with the
identified model tracks every target of the test episodes at the fusion centre.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import torch

from dslearn.episodes import Episodes, Estimates, Measurements, Scenario, ScenarioSpec
from dslearn.errors import ConfigError, check_choice, check_integer, check_keys, check_number
from dslearn.filters.ekf_fg import OBS_VAR_MODES
from dslearn.learning.factor_graph.engine import EkfFgTracker, TrackerSettings
from dslearn.learning.learners import FactorGraphIdentification, refuse
from dslearn.methods.base import require
from dslearn.network import SensorNetwork
from dslearn.sim.squared_range import SquaredRange

#: the tracker's keys (``filter.tracker``), as in ``conf/task/jiang_fg.yaml`` (the factor graph's, ``learner.fg``:
#: :data:`dslearn.learning.learners.FG_DEFAULTS`)
TRACKER_KEYS = ("initial_state_var", "initial_gradient_var", "process_var", "gradient_var", "obs_var", "gate")
#: (key, lower bound, strict); ``None`` allowed for gate (off)
_RANGES = (("initial_state_var", 0.0, True), ("initial_gradient_var", 0.0, True), ("process_var", 0.0, False),
           ("gradient_var", 0.0, False), ("gate", 0.0, True))
#: the reporting node (the study's ``node`` column)
NODE = "fusion_center"


def tracker_settings(fg: dict, tracker: dict, initial_state) -> TrackerSettings:
    """Checked :class:`TrackerSettings` from the identification's settings ``fg`` (checked by the learner,
    :class:`~dslearn.learning.learners.FactorGraphIdentification`) and the ``filter.tracker`` block (the defaults
    of :class:`TrackerSettings` for missing keys: the paper's equations). ConfigError naming the key."""
    values = {} if tracker is None else check_keys("filter.tracker", tracker, TRACKER_KEYS)
    if "obs_var" in values:
        check_choice("filter.tracker.obs_var", values["obs_var"], OBS_VAR_MODES)
    for key, low, strict in _RANGES:
        if key in values and (values[key] is not None or key != "gate"):
            check_number(f"filter.tracker.{key}", values[key], low, strict=strict, note=" (finite)")
    if not isinstance(initial_state, (list, tuple)) or len(initial_state) != 2:
        raise ConfigError(f"filter.initial_state={initial_state!r} must be a list of 2 numbers (the source's 2 "
                          f"parameters)")
    for x in initial_state:
        check_number("filter.initial_state", x)
    return TrackerSettings.from_config(initial_state=list(initial_state), **dict(fg or {}), **values)


@dataclasses.dataclass
class FactorGraphMethod:
    """FG identification + EKF-FG (Jiang et al.) on any scenario whose sensors measure squared ranges.

    Args:
        initial_state: the tracker's start ``x_{0}`` (the study's ``scenario.initial_state``).
        tracker: the EKF-FG's settings (the study's ``tracker`` block).
        learner: the identification (:class:`~dslearn.learning.learners.FactorGraphIdentification`: its
            ``iterations`` per timing, the study's ``max_iter``, and its ``fg`` settings); ``None``: its defaults
            (``conf/learner/fg_identification.yaml``). No other learner.
    """

    #: the learners it can use (the first: its own, taken when none is given)
    learners = ("fg_identification",)

    initial_state: Any = (2.0, -2.0)
    tracker: Any = None
    learner: Any = None

    def __post_init__(self) -> None:
        if self.learner is None:
            self.learner = FactorGraphIdentification()
        elif not isinstance(self.learner, FactorGraphIdentification):
            raise refuse(self.learner, "Jiang's EKF-FG (filter=fg_ekf) refines its prediction with the factor "
                                       "graph's identification at every timing", self.learners)
        self.settings = tracker_settings(self.learner.fg, self.tracker, self.initial_state)

    @property
    def iterations(self) -> int:
        """FG message-passing iterations per timing (the learner's ``iterations``)."""
        return self.learner.iterations

    @property
    def label(self) -> str:
        s = self.settings
        extra = "" if s.obs_var == "convergence" else f" {s.obs_var}"
        return f"fg_ekf t={self.iterations}{extra}"

    @staticmethod
    def spec_misfit(spec: ScenarioSpec) -> str | None:
        """What the engine needs of a scenario, declared (:func:`dslearn.methods.base.declared_misfit`)."""
        return require(spec, "Jiang's factor-graph identification + EKF-FG (sensors that measure squared ranges "
                           "to a 2-D source)", measurement="squared_range")

    def fits(self, spec: ScenarioSpec) -> str | None:
        return FactorGraphMethod.spec_misfit(spec)

    def estimate(self, scenario: Scenario, network: SensorNetwork, train: Episodes, test: Measurements,
                 seed: int) -> Estimates:
        """The EKF-FG's estimates of every test episode (``train`` is not used: the identification is online)."""
        meas, vis = test.meas, test.visible
        if meas.shape[3] != 1:
            raise ConfigError(f"scenario {scenario.spec.name}: the factor graph identifies one source; the "
                              f"measurements hold {meas.shape[3]}")
        if not bool(vis.all()):
            raise ConfigError(f"scenario {scenario.spec.name}: the factor graph needs every sensor's samples at "
                              "every timing (some are not visible)")
        sensors = network.positions[:network.num_sensors].to(meas)
        samples = meas[:network.num_sensors, :, :, 0].permute(1, 2, 0, 3)  # (B, K, N, L)
        mean, var = self.track(SquaredRange(sensors), samples, float(network.meas_std))
        return Estimates(mean[None, :, :, None], torch.diag_embed(var)[None, :, :, None], [NODE],
                         torch.ones(1, dtype=torch.bool))

    def track(self, h, samples: torch.Tensor, sigma_y: float):
        """The EKF-FG loop (:class:`~dslearn.learning.factor_graph.engine.EkfFgTracker`, the study's engine, one
        configuration ``C = 1``) on raw samples ``(B, K, N, L)``: the refined means and variances ``(B, K, M)``."""
        b, _, _, lsm = samples.shape
        sig = torch.full((1, b), float(sigma_y), dtype=samples.dtype, device=samples.device)
        tracker = EkfFgTracker(h, self.settings, sig, torch.tensor([self.iterations], device=samples.device), lsm)
        mean, var = tracker.run(samples[None])
        return mean[0], var[0]


# ------------------------------------------------------------------------------- the position-sensor form
#: the learner's settings (``learner.fg``) the position form cannot use: (key, the value it needs, why)
_LIN_NEEDS = (
    ("init_guess_mode", "fixed", "the identification runs on the training episodes before any tracking, so there is "
                                 "no prediction to start from; the start is learner.fg.init_guess"),
    ("taylor_point", "guess", "the first Taylor point is learner.fg.init_guess (there is no tracker prediction in "
                              "the training episodes); each round re-expands at its estimate"),
    ("measurement_var", "known", "the innovations' variances follow from the scenario's sensors' known noise, one "
                                 "measurement per node and step (no repeated samples to take a variance from)"),
    ("relinearize", False, "the rounds (filter.rounds) re-expand the innovations at every estimate"),
    ("crlb_form", "trace_inverse", "its tracker is a Kalman filter of the identified model, which takes no CRLB"),
)


@dataclasses.dataclass
class FactorGraphMotionMethod:
    """The factor-graph identification of a motion model from position measurements + a Kalman filter with it: the
    position-sensor form of Jiang et al.'s method (:mod:`dslearn.learning.factor_graph.motion`).

    From the training episodes' measurements (never their truth) the fusion centre identifies
    ``theta = (a, ln q)`` of the damped constant-velocity model ``x_{k+1} = F(a) x_k + w``, ``w ~ N(0, q G G^T)``
    by the factor graph's Gaussian messages over the innovations of a Kalman filter through every training track
    (each target of each episode; a step no node sees is a prediction alone); then it tracks every target of the
    test episodes with that model and the scenario's sensors (their noise ``sigma``, the nodes that see each target
    at each step), each target from the diffuse prior at its prior point (:func:`dslearn.filters.distributed.prior_means`).
    With a linear model and linear sensors the EKF is the Kalman filter.

    Args:
        rounds: the most rounds of the identification (each re-expands the innovations at its estimate and runs
            ``learner.iterations`` message-passing iterations).
        prior_pos_std, prior_vel_std: the diffuse prior of a target not yet seen [m], [m/s].
        learner: the identification (:class:`~dslearn.learning.learners.FactorGraphIdentification`: its
            ``iterations`` per round and ``fg`` settings, ``init_guess = (a, ln q)``); ``None``: its defaults with the
            position form's start, ``init_guess = (1, 0)`` (constant velocity, ``q = 1``), ``taylor_point=guess``,
            ``measurement_var=known``.
    """

    learners = ("fg_identification",)

    rounds: int = 10
    prior_pos_std: float = 1000.0
    prior_vel_std: float = 1000.0
    learner: Any = None

    def __post_init__(self) -> None:
        if self.learner is None:
            self.learner = FactorGraphIdentification(fg={"init_guess": [1.0, 0.0], "taylor_point": "guess",
                                                         "measurement_var": "known"})
        elif not isinstance(self.learner, FactorGraphIdentification):
            raise refuse(self.learner, "the factor-graph EKF on position sensors (filter=fg_ekf_lin) identifies its "
                                       "motion model over the factor graph", self.learners)
        self.learner.check_motion_settings("filter=fg_ekf_lin", _LIN_NEEDS)
        self.rounds = check_integer("filter.rounds", self.rounds, 1)
        for key in ("prior_pos_std", "prior_vel_std"):
            setattr(self, key, check_number(f"filter.{key}", getattr(self, key), 0.0, strict=True, note=" (finite)"))
        #: the last identification (:class:`~dslearn.learning.factor_graph.motion.MotionIdentification`)
        self.identified = None

    @property
    def iterations(self) -> int:
        """FG message-passing iterations per round (the learner's ``iterations``)."""
        return self.learner.iterations

    @property
    def label(self) -> str:
        return f"fg_ekf_lin t={self.iterations}"

    @staticmethod
    def spec_misfit(spec: ScenarioSpec) -> str | None:
        """What the engine needs of a scenario, declared (:func:`dslearn.methods.base.declared_misfit`): sensors that
        measure the targets' positions, ``[px, py, vx, vy]`` targets (the model's state)."""
        return require(spec, "the factor-graph identification of a motion model + EKF on position sensors (sensors "
                             "that measure the positions of targets with a [px, py, vx, vy] state)",
                       measurement="position", state="pv2d", kind="targets")

    def fits(self, spec: ScenarioSpec) -> str | None:
        return FactorGraphMotionMethod.spec_misfit(spec)

    def _start(self, num_tracks: int, num_agents: int, area, dtype, device):
        from dslearn.filters.distributed import prior_means

        m0 = prior_means(num_agents, area).to(device, dtype).repeat(num_tracks // num_agents, 1)
        p0 = torch.diag(torch.tensor([self.prior_pos_std ** 2] * 2 + [self.prior_vel_std ** 2] * 2, dtype=dtype,
                                     device=device)).expand(num_tracks, 4, 4)
        return m0, p0

    def learn(self, train: Measurements, sigma: float, dt: float, area):
        """The identification on the training episodes' measurements: a
        :class:`~dslearn.learning.factor_graph.motion.MotionIdentification`."""
        from dslearn.learning.factor_graph.motion import fuse, identify_motion

        z, n = fuse(train.meas.to(torch.float64), train.visible)
        m0, p0 = self._start(z.shape[0], train.meas.shape[3], area, z.dtype, z.device)
        fg = self.learner.fg
        prior = float("inf") if fg["prior_var"] is None else float(fg["prior_var"])
        return identify_motion(z, n, dt, sigma, m0, p0, fg["init_guess"], iterations=self.iterations,
                               rounds=self.rounds, init_var=float(fg["init_var"]), prior_var=prior,
                               schedule=fg["schedule"], damping=float(fg["damping"]), graph=fg["graph"],
                               lambda_tol=float(fg["lambda_tol"]), converge_tol=float(fg["converge_tol"]))

    def track(self, test: Measurements, theta: torch.Tensor, sigma: float, dt: float, area):
        """The Kalman filter of the model ``theta`` at the fusion centre on every target of ``test``: position means
        ``(B, K+1, A, 2)`` and covariances ``(B, K+1, A, 2, 2)``."""
        from dslearn.learning.factor_graph.motion import fuse, kalman

        z, n = fuse(test.meas.to(torch.float64), test.visible)
        b, t1, a = test.meas.shape[1], test.meas.shape[2], test.meas.shape[3]
        m0, p0 = self._start(z.shape[0], a, area, z.dtype, z.device)
        with torch.no_grad():
            kp = kalman(theta.to(z), z, n, dt, sigma, m0, p0)
        mean = kp.mean[..., :2].reshape(b, a, t1, 2).transpose(1, 2)
        cov = kp.cov[..., :2, :2].reshape(b, a, t1, 2, 2).transpose(1, 2)
        return mean, cov

    def estimate(self, scenario: Scenario, network: SensorNetwork, train: Episodes, test: Measurements,
                 seed: int) -> Estimates:
        """Identify the model on ``train``'s measurements, then track ``test`` with it (one reporting node, the
        fusion centre)."""
        sigma, dt = float(network.meas_std), float(scenario.spec.dt)
        self.identified = self.learn(train.measurements, sigma, dt, scenario.area)
        mean, cov = self.track(test, self.identified.theta, sigma, dt, scenario.area)
        if not (torch.isfinite(mean).all() and torch.isfinite(cov).all()):
            raise FloatingPointError("non-finite estimate of the factor-graph EKF on position sensors (this is a bug)")
        dtype = test.meas.dtype
        return Estimates(mean[None].to(dtype), cov[None].to(dtype), [NODE],
                         torch.ones(1, dtype=torch.bool, device=mean.device))
