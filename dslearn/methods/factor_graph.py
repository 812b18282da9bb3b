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
"""

from __future__ import annotations

import dataclasses
from typing import Any

import torch

from dslearn.episodes import Episodes, Estimates, Measurements, Scenario, ScenarioSpec
from dslearn.errors import ConfigError, check_choice
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


def _block(value, keys: tuple[str, ...], prefix: str) -> dict:
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise ConfigError(f"{prefix}={value!r} must be a mapping with keys {list(keys)}")
    unknown = sorted(str(k) for k in value if k not in keys)
    if unknown:
        raise ConfigError(f"{prefix}: unknown key(s) {unknown}; allowed: {list(keys)}")
    return dict(value)


def _number(key: str, v) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or v != v:
        raise ConfigError(f"{key}={v!r} must be a number")
    return float(v)


def tracker_settings(fg: dict, tracker: dict, initial_state) -> TrackerSettings:
    """Checked :class:`TrackerSettings` from the identification's settings ``fg`` (checked by the learner,
    :class:`~dslearn.learning.learners.FactorGraphIdentification`) and the ``filter.tracker`` block (the defaults
    of :class:`TrackerSettings` for missing keys: the paper's equations). ConfigError naming the key."""
    values = _block(tracker, TRACKER_KEYS, "filter.tracker")
    if "obs_var" in values:
        check_choice("filter.tracker.obs_var", values["obs_var"], OBS_VAR_MODES)
    for key, low, strict in _RANGES:
        v = values.get(key)
        if v is None:
            if key in values and key != "gate":
                raise ConfigError(f"filter.tracker.{key} must be a number, not null")
            continue
        x = _number(f"filter.tracker.{key}", v)
        if (x <= low if strict else x < low) or x == float("inf"):
            raise ConfigError(f"filter.tracker.{key}={v!r} must be {'>' if strict else '>='} {low:g} (finite)")
    if not isinstance(initial_state, (list, tuple)) or len(initial_state) != 2:
        raise ConfigError(f"filter.initial_state={initial_state!r} must be a list of 2 numbers (the source's 2 "
                          f"parameters)")
    for x in initial_state:
        _number("filter.initial_state", x)
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
