r"""Episodes and what the network sees of them: batches of true joint states and every node's
measurements (the floor that simulation, filters, fusion and learning share)."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor


@dataclass
class Measurements:
    """What the filters and the fusion see of a batch of episodes: the measurements, not the truth.

    Attributes:
        meas: ``(S, B, K+1, A, 2)`` measurements of every node (zeros where not visible).
        visible: ``(S, B, K+1, A)`` bool, which node measured which target.
    """

    meas: Tensor
    visible: Tensor

    def __len__(self) -> int:
        return self.meas.shape[1]

    @property
    def steps(self) -> int:
        """``K``: the number of steps after t = 0."""
        return self.meas.shape[2] - 1

    def select(self, idx) -> "Measurements":
        return Measurements(self.meas[:, idx], self.visible[:, idx])


@dataclass
class Episodes:
    """A batch of episodes.

    Attributes:
        states: ``(B, K+1, Dx)`` true joint states at t = 0..K.
        meas: ``(S, B, K+1, A, 2)`` measurements of every node (zeros where not visible).
        visible: ``(S, B, K+1, A)`` bool, which node measured which target.
    """

    states: Tensor
    meas: Tensor
    visible: Tensor

    def __len__(self) -> int:
        return self.states.shape[0]

    def select(self, idx) -> "Episodes":
        return Episodes(self.states[idx], self.meas[:, idx], self.visible[:, idx])

    @property
    def measurements(self) -> Measurements:
        """The part of the episodes a filter may see (the truth stays with the metrics)."""
        return Measurements(self.meas, self.visible)

    def to(self, dtype, device) -> "Episodes":
        return Episodes(self.states.to(device, dtype), self.meas.to(device, dtype), self.visible.to(device))
