r"""Prior means of the GP backends as modules: :math:`m(x)` and its Jacobian.

A backend (:class:`~dslearn.models.gp_backends.exact.OnlineGP`, the sparse variants) takes ``mean=`` as a
name (``zero``, ``identity``, ``constant``: the last one is learned with the kernel by
``fit``) or as one of these modules, e.g. ``ConstantVelocityMean(dt)``. Shapes
``(S, N, Dx) -> (S, N, Dy)`` and ``(S, N, Dy, Dx)``.
"""

from __future__ import annotations

import abc

from torch import Tensor, nn


class PriorMeanModule(nn.Module, abc.ABC):
    """A fixed prior mean ``m(x)`` with its Jacobian; ``output_dim`` and ``input_dim`` are set by
    the backend that holds it (:meth:`bind`)."""

    name = "prior mean"
    output_dim: int
    input_dim: int

    def bind(self, input_dim: int, output_dim: int) -> "PriorMeanModule":
        self.input_dim, self.output_dim = int(input_dim), int(output_dim)
        return self

    @abc.abstractmethod
    def forward(self, x: Tensor) -> Tensor:
        """``m(x)``: ``(S, N, Dx) -> (S, N, Dy)``."""

    @abc.abstractmethod
    def jacobian(self, x: Tensor) -> Tensor:
        """``dm/dx``: ``(S, N, Dx) -> (S, N, Dy, Dx)``."""


class ZeroMean(PriorMeanModule):
    name = "zero"

    def forward(self, x: Tensor) -> Tensor:
        return x.new_zeros(*x.shape[:-1], self.output_dim)

    def jacobian(self, x: Tensor) -> Tensor:
        return x.new_zeros(*x.shape[:-1], self.output_dim, self.input_dim)


class IdentityMean(PriorMeanModule):
    """``m(x) = x[..., :Dy]``: the GP learns the increment."""

    name = "identity"

    def bind(self, input_dim: int, output_dim: int) -> "IdentityMean":
        if output_dim > input_dim:
            from dslearn.errors import ConfigError

            raise ConfigError("model.mean=identity needs output_dim <= input_dim")
        return super().bind(input_dim, output_dim)

    def forward(self, x: Tensor) -> Tensor:
        return x[..., : self.output_dim]

    def jacobian(self, x: Tensor) -> Tensor:
        j = x.new_zeros(*x.shape[:-1], self.output_dim, self.input_dim)
        j[..., range(self.output_dim), range(self.output_dim)] = 1.0
        return j


class ConstantVelocityMean(PriorMeanModule):
    r""":math:`m(y) = F_{cv} y` (``p + v \Delta t``, ``v`` per agent): the GP learns the deviation of
    the one-step transition from constant velocity; far from its data it falls back to LIN
    instead of to "stand still" (identity) or to the origin (zero)."""

    name = "constant_velocity"

    def __init__(self, dt: float):
        super().__init__()
        self.dt = float(dt)

    def bind(self, input_dim: int, output_dim: int) -> "ConstantVelocityMean":
        from dslearn.models.constant_velocity import ConstantVelocity

        super().bind(input_dim, output_dim)
        self.F = ConstantVelocity(self.input_dim // 4).matrix(self.dt)
        return self

    def forward(self, x: Tensor) -> Tensor:
        return x @ self.F.to(x).T

    def jacobian(self, x: Tensor) -> Tensor:
        return self.F.to(x).expand(*x.shape[:-1], *self.F.shape)


#: the named means a config may give as ``model.mean`` (``constant`` is the backend's own, learned)
NAMED = {"zero": ZeroMean, "identity": IdentityMean}
