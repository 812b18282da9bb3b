r"""The learner of a matrix method (the ``learner`` config group, ``task=matrix``): what the method's parts learn,
from what and when. A learner holds its settings, checked at construction; the method's engine (the ``filter``
part) carries it out and refuses one it cannot use, at composition (:class:`LearnerRefused`).

- :class:`OnlineLearning` (``learner=online``): Yu et al. Algorithm 1: the motion and observation models that
  learn online learn while the network tracks the training episodes' measurements.
- :class:`OfflineLearning` (``learner=offline``): supervised: the motion model is fitted once to the training
  episodes' true tracks (``fit_offline``: the LSTMs, the fitted social force), then frozen.
- :class:`NoLearning` (``learner=none``): nothing is learned; the parts as configured (a GP without data is
  its prior mean).
- :class:`OnlineEM` (``learner=online_em``): Braga et al.'s online EM of the altimeter's noise modes, within
  each flight.
- :class:`OnlineHyperparameters` (``learner=online_hyperparameters``): Liu et al.'s online learning of the
  GP experts' hyperparameters from the factorised likelihood, within each episode.
- :class:`FactorGraphIdentification` (``learner=fg_identification``): Jiang et al.'s identification of the
  source over the factor graph at every timing; for the distributed filter, the identification of the damped
  constant-velocity model's ``(a, q)`` (``model=cv_damped``) from the training episodes' true tracks, once, before
  any tracking (:meth:`FactorGraphIdentification.fit_motion`).
- :class:`~dslearn.learning.backprop.BackpropLearning` (``learner=backprop``): Q, R, the consensus weights,
  omega and a linear motion model's matrix learned by backpropagating through the distributed information
  filter and its consensus rounds (innovation likelihood; or supervised).
- :class:`~dslearn.learning.calibrate.CalibrateLearning` (``learner=calibrate``): a scale of the process noise
  Q and of the sensors' R fitted to the training measurements (maximum likelihood of each node's innovations,
  the nodes alone; a batched grid search), then tracked with the configured fusion.

``learner: null`` (the default): each engine uses its own (natural) learner with these defaults, the values of
``conf/learner/<name>.yaml``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

from dslearn.errors import ConfigError, check_choice, check_flag, check_integer, check_keys, check_number, check_positive
from dslearn.learning import Learner


class LearnerRefused(ConfigError):
    """A method's engine cannot use the learner it was given (a configuration error, never an n/a cell)."""


def refuse(learner: Any, why: str, allowed) -> LearnerRefused:
    """The one-line refusal of ``learner`` (``learner=<name>: <why>; allowed: learner=a|b``)."""
    return LearnerRefused(f"learner={learner_name(learner)}: {why}; allowed: learner={'|'.join(allowed)}")


def learner_name(learner: Any) -> str:
    return str(getattr(learner, "name", type(learner).__name__))


@dataclass(frozen=True)
class OnlineLearning(Learner):
    """Yu et al. Algorithm 1: the parts that learn online learn while tracking the training episodes."""

    name: ClassVar[str] = "online"
    learns_online = True
    #: the parts it lets learn online while tracking (:func:`dslearn.schemas.base.online_learning`)
    config_online_parts: ClassVar[tuple] = ("model", "observation")


@dataclass(frozen=True)
class OfflineLearning(Learner):
    """The motion model fitted once to the training episodes' true tracks (``fit_offline``), then frozen (an
    observation model that learns online still does, as with ``online``)."""

    name: ClassVar[str] = "offline"
    fits_offline = True
    learns_online = True
    #: the parts it lets learn online while tracking (:func:`dslearn.schemas.base.online_learning`)
    config_online_parts: ClassVar[tuple] = ("observation",)


@dataclass(frozen=True)
class NoLearning(Learner):
    """Nothing is learned: the parts as configured."""

    name: ClassVar[str] = "none"
    #: the parts it lets learn online while tracking (:func:`dslearn.schemas.base.online_learning`)
    config_online_parts: ClassVar[tuple] = ()


# ------------------------------------------------------------------------------------------------ helpers
def _block(value: Any, defaults: dict, prefix: str) -> dict:
    """``defaults`` updated with the mapping ``value`` (``None``: the defaults); ConfigError naming ``prefix`` on
    something that is not a mapping or on an unknown key (:func:`~dslearn.errors.check_keys`)."""
    return {**defaults, **({} if value is None else check_keys(prefix, value, defaults))}


# ------------------------------------------------------------------------------------------- Braga: EM
#: the online EM's settings and the initial guess of the noise modes (``conf/learner/online_em.yaml``)
EM_DEFAULTS = {"eta_exponent": 0.7, "burn_in": 50, "sigma_floor": 1e-3, "init_mode": "true"}
MODE_DEFAULTS = {"mu_init": [-5.0, 25.0], "sigma_init": [5.0, 5.0], "pi_init": [[0.5, 0.5], [0.5, 0.5]]}
#: the same for position sensors (:class:`OnlineEMSensor`): modes in sensor stds, zero-mean, no known first mode
EM_SENSOR_DEFAULTS = {"eta_exponent": 0.7, "burn_in": 10, "sigma_floor": 1e-3, "init_mode": "uniform"}
MODE_SENSOR_DEFAULTS = {"mu_init": [0.0, 0.0], "sigma_init": [1.0, 3.0], "pi_init": [[0.9, 0.1], [0.3, 0.7]]}


@dataclass
class OnlineEM(Learner):
    """Braga et al.'s online EM of the jump-Markov altimeter noise, afresh within each flight.

    Args:
        em: ``eta_exponent`` (``eta_t = t^-a``, in (0.5, 1]), ``burn_in`` (steps before the first M-step),
            ``sigma_floor`` [m], ``init_mode`` (``true``: the mode known at ``t = 0``; ``uniform``).
        modes: the initial guess of the noise parameters ``mu_init``, ``sigma_init``, ``pi_init``.
    """

    name: ClassVar[str] = "online_em"
    #: the units of ``mu_init`` and ``sigma_init``: metres (Braga et al.'s altimeter)
    units: ClassVar[str] = "m"

    em: Any = field(default_factory=lambda: dict(EM_DEFAULTS))
    modes: Any = field(default_factory=lambda: {k: (list(map(list, v)) if k == "pi_init" else list(v))
                                                for k, v in MODE_DEFAULTS.items()})

    def __post_init__(self) -> None:
        from dslearn.models.jmnls import make_params

        em = _block(self.em, EM_DEFAULTS, "learner.em")
        if em["init_mode"] is True:  # `init_mode=true` on the command line is a bool
            em["init_mode"] = "true"
        check_choice("learner.em.init_mode", em["init_mode"], ("true", "uniform"))
        em["eta_exponent"] = check_number("learner.em.eta_exponent", em["eta_exponent"], 0.5, strict=True, high=1.0)
        check_integer("learner.em.burn_in", em["burn_in"], 0)
        em["sigma_floor"] = check_number("learner.em.sigma_floor", em["sigma_floor"], 0.0, strict=True)
        self.em = em
        modes = _block(self.modes, MODE_DEFAULTS, "learner.modes")
        #: the checked initial noise parameters (:class:`~dslearn.models.jmnls.NoiseParams`)
        self.init = make_params(modes["mu_init"], modes["sigma_init"], modes["pi_init"], prefix="learner.modes")
        self.modes = modes



@dataclass
class OnlineEMSensor(OnlineEM):
    """The online EM of jump-Markov measurement noise for position sensors (the RBPF over noise modes,
    :class:`dslearn.methods.rbpf_modes.RBPFModesMethod`): the same settings as :class:`OnlineEM`, with the initial
    modes' ``mu_init`` and ``sigma_init`` in multiples of the scenario's sensor noise std (the method scales them, so
    one setting fits sensors of any accuracy), zero-mean modes (a common bias of a position sensor moves every
    measurement of a target the same way and cannot be told from the target's position) and no mode known at
    ``t = 0`` (the sensors report none: ``init_mode: uniform``)."""

    name: ClassVar[str] = "online_em_sensor"
    units: ClassVar[str] = "sensor_std"

    em: Any = field(default_factory=lambda: dict(EM_SENSOR_DEFAULTS))
    modes: Any = field(default_factory=lambda: {k: (list(map(list, v)) if k == "pi_init" else list(v))
                                                for k, v in MODE_SENSOR_DEFAULTS.items()})

    def __post_init__(self) -> None:
        if isinstance(self.em, dict):
            self.em = {**EM_SENSOR_DEFAULTS, **self.em}
        if isinstance(self.modes, dict):
            self.modes = {**MODE_SENSOR_DEFAULTS, **self.modes}
        super().__post_init__()
        if self.em["init_mode"] != "uniform":
            raise ConfigError(f"learner.em.init_mode={self.em['init_mode']}: position sensors report no noise mode at "
                              "t = 0; learner.em.init_mode=uniform")
        if bool((self.init.mu != 0).any()):
            raise ConfigError(f"learner.modes.mu_init={self.modes['mu_init']}: the modes of a position sensor are "
                              "zero-mean (a common bias moves every measurement of a target the same way and cannot be "
                              "told from the target's position); mu_init must be zeros")

# ---------------------------------------------------------------------------------- Liu: hyperparameters
def _hyper_defaults() -> Any:
    from dslearn.filters.dgpt import HyperConfig

    return HyperConfig()


#: hyperparameter box: (lower key, upper key, the initial values that must lie inside)
_BOX = (("min_noise", "max_noise", ("init_noise",)),
        ("min_outputscale", "max_outputscale", ("init_outputscale",)),
        ("min_lengthscale", "max_lengthscale", ("init_lengthscale_t", "init_lengthscale_r")))


def hyper_config(hyper: Any, prefix: str = "learner.hyper") -> Any:
    """A checked :class:`~dslearn.filters.dgpt.HyperConfig` from a mapping of its fields (``None``: the
    defaults). ConfigError naming ``prefix.<key>`` on an unknown key, a value out of range or an initial value
    outside its box."""
    from dslearn.filters.dgpt import OPTIMISERS, HyperConfig

    keys = tuple(f.name for f in dataclasses.fields(HyperConfig))
    if hyper is None:
        hc = HyperConfig()
    elif isinstance(hyper, HyperConfig):
        hc = hyper
    else:
        hc = HyperConfig(**check_keys(prefix, hyper, keys))
    check_choice(f"{prefix}.optimizer", hc.optimizer, OPTIMISERS)
    for key in ("iters", "iters_first", "max_iters"):
        check_integer(f"{prefix}.{key}", getattr(hc, key), 1 if key == "max_iters" else 0)
    check_flag(f"{prefix}.gap_check", hc.gap_check)
    for key in ("lr", "tol", *(k for k in keys if k.startswith(("init_", "min_", "max_")) and k != "max_iters")):
        check_positive(f"{prefix}.{key}", getattr(hc, key))
    for lo, hi, inits in _BOX:
        for f in inits:
            if not getattr(hc, lo) <= getattr(hc, f) <= getattr(hc, hi):
                raise ConfigError(f"{prefix}.{f}={getattr(hc, f)!r} must lie in [{prefix}.{lo}, {prefix}.{hi}] "
                                  f"= [{getattr(hc, lo)!r}, {getattr(hc, hi)!r}]")
    return hc


@dataclass
class OnlineHyperparameters(Learner):
    """Liu et al.'s online learning of the GP experts' shared hyperparameters (factorised likelihood), within
    each episode.

    Args:
        hyper: :class:`~dslearn.filters.dgpt.HyperConfig` or a mapping of its fields (missing ones: its
            defaults): the optimiser, its steps, the initial values and the box.
    """

    name: ClassVar[str] = "online_hyperparameters"

    hyper: Any = field(default_factory=_hyper_defaults)

    @staticmethod
    def config_unused(cfg, node) -> dict:
        """The keys of ``learner.hyper`` the chosen optimiser does not read (:func:`hyper_unused`)."""
        return hyper_unused(node.get("hyper"), "learner.hyper")

    def __post_init__(self) -> None:
        self.hyper = hyper_config(self.hyper, "learner.hyper")


#: the keys of the hyperparameter settings each kind of optimiser reads (the others: Newton's, or the steps')
_NEWTON_KEYS, _STEP_KEYS = ("tol", "max_iters"), ("lr", "iters", "iters_first")


def hyper_unused(hyper: Any, prefix: str) -> dict[str, str]:
    """``{key: why}`` of the hyperparameter settings (``learner.hyper`` / ``task.hyper``, relative to ``hyper``)
    that its ``optimizer`` does not read: Newton's tolerance and cap under Adam / SGD, the steps' size and counts
    under Newton."""
    if hyper is None or not hasattr(hyper, "get"):
        return {}
    opt = hyper.get("optimizer", "adam")
    if opt == "newton":
        keys, why = _STEP_KEYS, f"{prefix}.optimizer=newton solves each problem to {prefix}.tol; no fixed steps"
    elif opt in ("adam", "sgd"):
        keys, why = _NEWTON_KEYS, f"{prefix}.optimizer={opt} takes {prefix}.iters steps of size {prefix}.lr; no Newton solve"
    else:
        return {}
    return {f"hyper.{k}": why for k in keys if k in hyper}


# --------------------------------------------------------------------------- Jiang: factor-graph identification
#: the identification's settings (``conf/learner/fg_identification.yaml``: the paper's choices)
FG_DEFAULTS = {"init_guess": [0.0, 0.0], "init_guess_mode": "fixed", "init_var": 100.0, "prior_var": None,
               "relinearize": False, "taylor_point": "prediction", "schedule": "flooding", "damping": 0.0,
               "graph": "scalar", "measurement_var": "sample", "crlb_form": "trace_inverse", "lambda_tol": 1.0e-8,
               "converge_tol": 1.0e-3}
#: (key, lower bound, strict); ``None`` allowed for prior_var (no prior node)
_FG_RANGES = (("init_var", 0.0, True), ("prior_var", 0.0, True), ("damping", 0.0, False), ("lambda_tol", 0.0, False),
              ("converge_tol", 0.0, True))


#: the settings (``learner.fg``) the identification of a motion model from true tracks needs: (key, value, why)
MOTION_NEEDS = (
    ("init_guess_mode", "fixed", "the identification runs on the training episodes' true tracks before any tracking, "
                                 "so there is no prediction to start from; the start is learner.fg.init_guess"),
    ("taylor_point", "guess", "the first Taylor point is learner.fg.init_guess (there is no tracker prediction in the "
                              "training episodes); each round re-expands at its estimate"),
    ("measurement_var", "known", "the true positions are measurements of a declared variance, one per agent and step "
                                 "(no repeated samples to take a variance from)"),
    ("relinearize", False, "the rounds re-expand the innovations at every estimate"),
    ("crlb_form", "trace_inverse", "the filter tracks with the identified model, which takes no CRLB"),
)
#: the most rounds of the identification from true tracks (each re-expands the innovations at its estimate; the
#: default of ``filter.rounds`` of ``filter=fg_ekf_lin``)
MOTION_ROUNDS = 10
#: the standard deviation [m] of the noise added to the true positions taken as measurements, and declared to the
#: identification. Not zero: the identification minimises the filter's weighted prediction errors, and the filter's
#: predictions depend on q only through q / r (r the measurements' variance; the diffuse prior aside), so exact
#: positions (r -> 0) leave q unidentified (it stays at its guess or runs off); positions with noise of the declared
#: variance identify q / r, hence q
TRUTH_STD = 1e-2


@dataclass
class FactorGraphIdentification(Learner):
    """Jiang et al.'s identification of the source's parameter over the factor graph (Gaussian BP from the
    sensors' compressed samples) at every timing.

    Args:
        iterations: message-passing iterations per timing (the study's ``max_iter``).
        fg: the identification's settings (missing keys: the paper's choices, :data:`FG_DEFAULTS`).
    """

    name: ClassVar[str] = "fg_identification"

    iterations: int = 10
    fg: Any = field(default_factory=lambda: {k: (list(v) if isinstance(v, list) else v)
                                             for k, v in FG_DEFAULTS.items()})

    def __post_init__(self) -> None:
        from dslearn.learning.factor_graph.crlb import CRLB_FORMS
        from dslearn.learning.factor_graph.identification import GRAPHS, SCHEDULES

        check_integer("learner.iterations", self.iterations, 1)
        fg = _block(self.fg, FG_DEFAULTS, "learner.fg")
        choices = {"init_guess_mode": ("fixed", "prediction"), "taylor_point": ("prediction", "guess"),
                   "schedule": SCHEDULES, "graph": GRAPHS, "measurement_var": ("sample", "known"),
                   "crlb_form": CRLB_FORMS}
        for key, allowed in choices.items():
            check_choice(f"learner.fg.{key}", fg[key], allowed)
        check_flag("learner.fg.relinearize", fg["relinearize"])
        for key, low, strict in _FG_RANGES:
            if fg[key] is not None or key != "prior_var":
                check_number(f"learner.fg.{key}", fg[key], low, strict=strict, note=" (finite)")
        if fg["damping"] >= 1.0:
            raise ConfigError(f"learner.fg.damping={fg['damping']!r} must be >= 0 and < 1 (finite)")
        guess = fg["init_guess"]
        if not isinstance(guess, (list, tuple)) or len(guess) != 2:
            raise ConfigError(f"learner.fg.init_guess={guess!r} must be a list of 2 numbers (the source's 2 parameters)")
        for x in guess:
            check_number("learner.fg.init_guess", x)
        self.fg = fg

    # the identification of a motion model from true tracks (the distributed filter's learner)
    @staticmethod
    def motion_misfit(model: Any) -> str | None:
        """Why the identification cannot learn ``model`` (``None`` where it can): it identifies the damped
        constant-velocity model's ``(a, q)`` (:class:`~dslearn.models.constant_velocity.DampedConstantVelocity`)."""
        from dslearn.models.constant_velocity import DampedConstantVelocity

        if isinstance(model, DampedConstantVelocity):
            return None
        return (f"the factor-graph identification sets the damped constant-velocity model's (a, q) "
                f"(model=cv_damped), not {type(model).__name__}'s")

    def check_motion_settings(self, engine: str, needs: tuple = MOTION_NEEDS) -> None:
        """Refuse the settings (``learner.fg``) the identification of a motion model cannot use (``needs``: (key,
        the value it needs, why); by default those of the identification from true tracks, :data:`MOTION_NEEDS`):
        ConfigError naming the key, the engine and the value it needs."""
        for key, need, why in needs:
            if self.fg[key] != need:
                shown = str(need).lower() if isinstance(need, bool) else need
                raise ConfigError(f"learner.fg.{key}={self.fg[key]!r} does not apply to {engine}: {why}; "
                                  f"allowed: {shown}")

    def fit_motion(self, model: Any, states: Any, dt: float, prior_pos_std: float, prior_vel_std: float,
                   seed: int = 0) -> Any:
        """Identify ``theta = (a, ln q)`` from the true tracks ``states (B, K+1, 4A)`` (each agent of each episode a
        track; its true positions measurements of std :data:`TRUTH_STD`, that noise drawn from the stream
        ``(seed, "fg_identification")``) with the factor graph's messages
        (:func:`~dslearn.learning.factor_graph.motion.identify_motion`, at most :data:`MOTION_ROUNDS` rounds of
        ``iterations`` iterations, from ``fg.init_guess``), each track's filter from the diffuse prior
        (``prior_pos_std``, ``prior_vel_std``) at its first measured position, and set ``model``'s ``(a, q)``. Returns the
        :class:`~dslearn.learning.factor_graph.motion.MotionIdentification`."""
        import torch

        from dslearn.learning.factor_graph.motion import identify_motion, truth_tracks
        from dslearn.streams import stream_seed

        why = self.motion_misfit(model)
        if why is not None:
            raise ConfigError(f"learner=fg_identification: {why}")
        gen = torch.Generator().manual_seed(stream_seed(int(seed), "fg_identification"))
        z, n = truth_tracks(states.detach().to(torch.float64), model.num_agents, TRUTH_STD, gen)
        m0 = torch.cat([z[:, 0], torch.zeros_like(z[:, 0])], -1)
        p0 = torch.diag(torch.tensor([prior_pos_std ** 2] * 2 + [prior_vel_std ** 2] * 2, dtype=z.dtype,
                                     device=z.device)).expand(z.shape[0], 4, 4)
        fg = self.fg
        ident = identify_motion(z, n, float(dt), TRUTH_STD, m0, p0, fg["init_guess"], iterations=self.iterations,
                                rounds=MOTION_ROUNDS, init_var=float(fg["init_var"]),
                                prior_var=float("inf") if fg["prior_var"] is None else float(fg["prior_var"]),
                                schedule=fg["schedule"], damping=float(fg["damping"]), graph=fg["graph"],
                                lambda_tol=float(fg["lambda_tol"]), converge_tol=float(fg["converge_tol"]))
        a, q = float(ident.theta[0]), float(ident.theta[1].exp())
        if not (math.isfinite(a) and math.isfinite(q) and q > 0.0):
            raise FloatingPointError(f"learner=fg_identification identified a={a!r}, q={q!r} (not a model)")
        model.set_parameters(a, q, prefix="learner=fg_identification")
        return ident


#: ``conf/learner/<name>.yaml`` -> its class
def _backprop():
    from dslearn.learning.backprop import BackpropLearning

    return BackpropLearning


def _calibrate():
    from dslearn.learning.calibrate import CalibrateLearning

    return CalibrateLearning


LEARNERS = {c.name: c for c in (OnlineLearning, OfflineLearning, NoLearning, OnlineEM, OnlineEMSensor,
                                OnlineHyperparameters,
                                FactorGraphIdentification, _backprop(), _calibrate())}
