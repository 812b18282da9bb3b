r"""The model interfaces every filter uses.

A :class:`MotionModel` describes :math:`y^{t+1} = f(y^t) + \eta^t`,
:math:`\eta^t \sim \mathcal N(0, Q(y^t))`. Models with per-node state (learned models,
one data set per sensor node) take inputs whose leading dimension is the node dimension
``S``; parametric models broadcast over any leading dimensions.
"""

from __future__ import annotations

import abc
from pathlib import Path

import torch
from torch import Tensor, nn

from dslearn.types import StepContext, batch_jacobian


class MotionModel(nn.Module, abc.ABC):
    r"""Motion model :math:`y^{t+1} = f(y^t) + \eta`, :math:`\eta \sim \mathcal N(0, Q(y^t))`.

    Implement :meth:`forward` and :meth:`noise_cov`; :meth:`jacobian` defaults to autograd.
    Learned models also implement :meth:`add_data` (and optionally :meth:`fit`).
    """

    state_dim: int
    #: whether :meth:`add_data` changes the model (the runner skips training otherwise)
    learnable: bool = False

    @staticmethod
    def spec_misfit(spec) -> str | None:
        """What the model needs of a scenario beyond what the engine that takes it needs, declared on the class
        and read from the scenario's :class:`~dslearn.episodes.ScenarioSpec` alone, before the model is built
        (:func:`dslearn.methods.base.declared_misfit`); ``None``: nothing more."""
        return None

    @abc.abstractmethod
    def forward(self, x: Tensor, ctx: StepContext) -> Tensor:
        """Predicted mean. ``(*B, Dx) -> (*B, Dx)``."""

    @abc.abstractmethod
    def noise_cov(self, x: Tensor, ctx: StepContext) -> Tensor:
        """Process noise covariance at ``x``. ``(*B, Dx) -> (*B, Dx, Dx)``."""

    def jacobian(self, x: Tensor, ctx: StepContext) -> Tensor:
        """:math:`\\partial f / \\partial y` at ``x``. ``(*B, Dx) -> (*B, Dx, Dx)``."""
        return batch_jacobian(lambda z: self(z, ctx), x)

    def linearize(self, x: Tensor, ctx: StepContext) -> tuple[Tensor, Tensor, Tensor]:
        """Mean, Jacobian and process covariance at ``x`` in one call (what an EKF needs).

        Models override this to share work between the three. Returns
        ``(mean (*B, Dx), F (*B, Dx, Dx), Q (*B, Dx, Dx))``.
        """
        return self(x, ctx), self.jacobian(x, ctx), self.noise_cov(x, ctx)

    @torch.no_grad()
    def rollout(self, x0: Tensor, steps: int, ctx: StepContext) -> Tensor:
        """Mean trajectory from ``x0``: ``(*B, Dx) -> (*B, steps, Dx)`` (``x0`` excluded)."""
        out = []
        x = x0
        for _ in range(steps):
            x = self(x, ctx)
            out.append(x)
        return torch.stack(out, dim=-2)

    # learned models -------------------------------------------------------------------
    def add_data(self, inputs: Tensor, outputs: Tensor, valid: Tensor | None = None) -> None:
        """Append input/output examples ``(S, Dx)`` (one per node). No-op for fixed models."""

    def reserve(self, appends: int) -> None:
        """Make room for ``appends`` more :meth:`add_data` calls before they come (a learner that
        knows its protocol says so once; the data set then does not regrow). No-op by default."""

    def fit(self) -> "MotionModel":
        """Fit hyperparameters to the current data (marginal likelihood). No-op by default."""
        return self

    #: whether the agents move independently of each other (the transition's Jacobian and noise block-diagonal per
    #: agent): a managed track (:mod:`dslearn.association.multitrack`) can then be predicted alone, as one block
    independent_targets: bool = False

    # offline models -------------------------------------------------------------------
    #: whether :meth:`fit_offline` learns (a model is learned online, :attr:`learnable` /
    #: :meth:`add_data`, or offline, :meth:`fit_offline`, before the study tracks anything)
    learns_offline: bool = False
    #: what an offline model learns from: ``"truth"`` (the training episodes' true tracks),
    #: ``"fused"`` (the tracks a sensor network estimated) or ``None`` (the study's default)
    train_on: str | None = None

    def fit_offline(self, trajectories: Tensor, dt: float, seed: int = 0) -> "MotionModel":
        """Learn from whole training trajectories ``(B, K+1, Dx)`` (``dt`` seconds per step), once,
        before any tracking; ``seed`` seeds whatever the fit draws. No-op by default."""
        return self

    # gradient learning ----------------------------------------------------------------
    #: which of its numbers a gradient learner (``learner=backprop``) may train, by the ``kind`` of
    #: :class:`~dslearn.learning.backprop.MotionParameters` that holds them: ``lin`` (the transition matrix's agent
    #: block), ``sfm`` (the social force's numbers), ``gp`` (an exact GP's hyperparameters), ``lstm`` (the network's
    #: weights); ``None``: none of them
    gradient_parameters: str | None = None

    def gradient_misfit(self) -> str | None:
        """Why a gradient learner cannot train the numbers this model declares (:attr:`gradient_parameters`) after
        all (``None``: nothing against it)."""
        return None

    def begin_episodes(self, states: Tensor) -> None:
        """The episodes about to be tracked or rolled out, ``(B, K+1, Dx)``, for a model conditioned
        per episode on what the protocol gives it (the fitted social force's desired velocities:
        the velocity at t = 0, the state every roll-out starts from). No-op by default."""

    def begin_measured(self, meas: Tensor, visible: Tensor, dt: float) -> None:
        """The same for a protocol that gives the filter measurements only (the matrix): the episodes about to be
        tracked as the network measures them, ``meas (S, B, K+1, A, 2)`` and ``visible (S, B, K+1, A)``, with the
        scenario's step ``dt``. No-op by default."""

    def save(self, path: str | Path) -> None:
        """Save parameters and data: ``torch.save`` of ``{format, class, state_dict}`` (plain tensors)."""
        torch.save(self._checkpoint(), path)

    def load(self, path: str | Path) -> "MotionModel":
        """Load what :meth:`save` wrote with safe (weights-only) loading, and check that it matches
        this model (class, parameter names and shapes = the configuration it was built from).

        Raises:
            DataFormatError: the file is missing, not a weights-only checkpoint, or malformed.
            ConfigError: the checkpoint was saved by another model class or configuration.
        """
        self.load_state_dict(self._read_checkpoint(path)["state_dict"])
        return self

    def _checkpoint(self, **extra: Tensor) -> dict:
        """The saved form: ``{format, class, state_dict, **extra}`` (weights-only loadable)."""
        return {"format": "dslearn-motion-v1", "class": type(self).__name__, "state_dict": self.state_dict(), **extra}

    def _read_checkpoint(self, path: str | Path, extra: tuple[str, ...] = ()) -> dict:
        """Safe-load ``path`` and check class, state-dict names and shapes, and that the
        tensors named in ``extra`` are present. Returns the checkpoint dict (``state_dict`` set)."""
        from dslearn.errors import ConfigError, DataFormatError

        try:
            blob = torch.load(path, weights_only=True, map_location="cpu")
        except FileNotFoundError:
            raise DataFormatError(f"{path}: no such model file") from None
        except Exception as e:  # unpickling refused (not weights-only) or corrupt file
            raise DataFormatError(f"{path}: not a safe (weights-only) dslearn model file: {str(e).splitlines()[0]}") from None
        if isinstance(blob, dict) and blob.get("format") == "dslearn-motion-v1":
            if blob.get("class") != type(self).__name__:
                raise ConfigError(f"{path}: saved by model class {blob.get('class')!r}, but the config builds {type(self).__name__!r}")
            state = blob.get("state_dict")
        elif isinstance(blob, dict) and not extra and all(isinstance(v, torch.Tensor) for v in blob.values()):
            state, blob = blob, {"state_dict": blob}  # a plain state dict (older files)
        else:
            raise DataFormatError(f"{path}: not a dslearn {type(self).__name__} file")
        if not isinstance(state, dict):
            raise DataFormatError(f"{path}: no state_dict in the model file")
        absent = [k for k in extra if not isinstance(blob.get(k), torch.Tensor)]
        if absent:
            raise DataFormatError(f"{path}: model file lacks {absent}")
        own = self.state_dict()
        missing, unexpected = sorted(set(own) - set(state)), sorted(set(state) - set(own))
        shapes = [f"{k}: file {tuple(state[k].shape)} vs config {tuple(own[k].shape)}"
                  for k in own if k in state and tuple(state[k].shape) != tuple(own[k].shape)]
        if missing or unexpected or shapes:
            raise ConfigError(
                f"{path} does not match the configured {type(self).__name__}: "
                + "; ".join(filter(None, [f"missing {missing}" if missing else "",
                                          f"unexpected {unexpected}" if unexpected else "", *shapes]))
            )
        return blob


class ObservationModel(nn.Module, abc.ABC):
    r"""Per-target observation model :math:`z_{ij} = h(y_j) + \nu`, :math:`\nu \sim \mathcal N(0, R(y_j))`.

    ``forward``: ``(*B, 4) -> (*B, Dz)``; ``noise_cov``: ``(*B, Dz, Dz)``;
    ``jacobian``: ``(*B, Dz, 4)``. A sensor measures each target in range separately.
    """

    meas_dim: int = 2
    learnable: bool = False
    #: whether it measures the targets' positions directly (a node's first two readings then give it a first
    #: estimate of a target, :func:`dslearn.filters.distributed.first_observations`); a nonlinear sensor does not
    measures_position: bool = True
    #: whether :meth:`forward` is linear in the state (a filter's statistical linearisation then changes nothing)
    linear: bool = False

    def reading(self, meas: Tensor) -> Tensor:
        """The measurement ``z (*B, Dz)`` this model explains, from a scenario's raw channels ``(*B, C)`` (its
        samples averaged, its auxiliary channels left out); the raw channels themselves by default."""
        return meas

    def residual(self, z: Tensor, h: Tensor) -> Tensor:
        """``z - h`` in the measurement's own geometry (an angle is wrapped to (-pi, pi])."""
        return z - h

    @abc.abstractmethod
    def forward(self, y: Tensor) -> Tensor: ...

    @abc.abstractmethod
    def noise_cov(self, y: Tensor) -> Tensor: ...

    def jacobian(self, y: Tensor) -> Tensor:
        return batch_jacobian(self, y)

    def linearize(self, y: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(h (*B, Dz), C (*B, Dz, 4), R (*B, Dz, Dz))`` at per-target states ``y (*B, 4)``."""
        return self(y), self.jacobian(y), self.noise_cov(y)

    def add_data(self, inputs: Tensor, outputs: Tensor, valid: Tensor) -> None:
        """Append per-target examples: inputs ``(S, A, 4)``, outputs ``(S, A, Dz)``, valid ``(S, A)``."""
