r"""What the GP models ask of a GP backend: the :class:`GPBackend` protocol.

A GP backend holds ``S`` independent GP regressions (one data set per sensor node) with one RBF
kernel shared by its ``Dy`` outputs. The GP motion model (:class:`~dslearn.models.gp.GPMotionModel`),
the aggregated GP (:class:`~dslearn.models.aggregated.AggregatedGPMotion`) and the GP observation
model (:class:`~dslearn.models.observation.GPObservation`) use a backend through this protocol
only: no ``hasattr`` probing, no test of the backend's class, no reading of its buffers.

The backends: the exact online GP (:class:`dslearn.models.gp_backends.exact.OnlineGP`) and the scalable
variants of :mod:`dslearn.models.gp_backends.sparse` (``WindowGP``, ``SGPR``, ``SSGP``). Shapes: queries
``(S, N, Din)`` (node dimension first), means ``(S, N, Dy)``, latent variances ``(S, N)`` (shared
by every output), mean Jacobians ``(S, N, Dy, Din)``.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from torch import Tensor


@runtime_checkable
class GPBackend(Protocol):
    """``S`` online GPs, one per node, behind what the GP models use."""

    # sizes -------------------------------------------------------------------------------
    #: ``S``, the independent data sets (nodes)
    num_nodes: int
    #: ``Din``, the input dimension
    input_dim: int
    #: ``Dy``, the output dimension (every output has the same kernel and latent variance)
    output_dim: int

    # capabilities (instead of probing for methods) ----------------------------------------
    #: :meth:`predict_belief` is available (otherwise it raises ``ConfigError``)
    supports_belief: bool
    #: the backend keeps one more point per node at every :meth:`append`, so its buffers grow
    #: with the data and :meth:`reserve` can allocate them once (otherwise ``reserve`` does nothing)
    grows_per_append: bool

    # hyperparameters: (S,) tensors -------------------------------------------------------
    @property
    def outputscale(self) -> Tensor:
        r"""Output variances :math:`\sigma_f^2` (the prior variance of every output), ``(S,)``."""

    @property
    def lengthscale(self) -> Tensor:
        """Length scales :math:`l`, ``(S,)``."""

    @property
    def noise_var(self) -> Tensor:
        r"""Observation noise variances :math:`\sigma_\epsilon^2`, ``(S,)``."""

    # prediction --------------------------------------------------------------------------
    def prior_mean(self, x: Tensor) -> Tensor:
        """Prior mean ``m(x)``: ``(S, N, Din) -> (S, N, Dy)``."""

    def prior_mean_jacobian(self, x: Tensor) -> Tensor:
        """Its Jacobian: ``(S, N, Din) -> (S, N, Dy, Din)``."""

    def predict(self, x: Tensor, jacobian: bool = True,
                variance: bool = True) -> tuple[Tensor, Tensor | None, Tensor | None]:
        """Posterior mean ``(S, N, Dy)``, latent variance ``(S, N)`` or None, mean Jacobian
        ``(S, N, Dy, Din)`` or None at ``x (S, N, Din)``."""

    def predict_belief(self, x: Tensor, cov: Tensor, jacobian: bool = True,
                       variance: bool = True) -> tuple[Tensor, Tensor | None, Tensor | None]:
        """As :meth:`predict`, the mean and its Jacobian averaged over ``N(x, cov)``
        (``cov (S, N, Din, Din)``); only where :attr:`supports_belief`."""

    def variance_gradient(self, x: Tensor) -> Tensor:
        r""":math:`\partial\sigma^2(x)/\partial x` of the latent variance, ``(S, N, Din)``."""

    def differentiable_mean(self, x: Tensor) -> Tensor:
        """The posterior mean with an autograd graph to ``x`` (the reference for the closed-form
        Jacobian), ``(S, N, Dy)``."""

    # learning ----------------------------------------------------------------------------
    def append(self, x: Tensor, y: Tensor, valid: Tensor | None = None) -> None:
        """One example per node, ``x (S, Din) -> y (S, Dy)``; ``valid (S,)`` bool, False (or a
        non-finite value) = no effect for that node."""

    def reserve(self, points: int) -> None:
        """Room for ``points`` more appends per node (a no-op unless :attr:`grows_per_append`)."""

    def fit(self, iters: int = 50, lr: float = 0.05) -> list[float]:
        """Fit the hyperparameters to the data (marginal likelihood); the loss curve. Backends
        with fixed hyperparameters raise ``ConfigError``."""

    # model files -------------------------------------------------------------------------
    def state_tensors(self) -> dict[str, Tensor]:
        """The posterior state besides the module's ``state_dict``, as plain tensors under the
        names a model file keeps them."""

    def load_state_tensors(self, state: dict[str, Tensor], source: str = "model file") -> None:
        """Replace the posterior state by what :meth:`state_tensors` gave (the same names),
        after checking it against this backend's sizes (``ConfigError`` naming ``source``, nothing
        changed). What depends on the hyperparameters is rebuilt with those the backend holds
        then (a caller loads the module's ``state_dict`` first)."""
