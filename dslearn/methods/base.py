r"""What every method of the matrix is: built from parts by the composition root, it says whether it fits a
scenario (:meth:`Method.fits`, from the scenario's declared :class:`~dslearn.episodes.ScenarioSpec` alone)
and estimates the targets' positions on test episodes after learning what its learner learns from the
training episodes (:meth:`Method.estimate`)."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from dslearn.episodes import Episodes, Estimates, Measurements, Scenario, ScenarioSpec
from dslearn.network import SensorNetwork


@runtime_checkable
class Method(Protocol):
    """A method of the matrix.

    ``label``: its row in the tables. ``fits(spec)``: ``None`` where the method can run on a scenario with
    that spec, else the reason in one sentence (what the scenario lacks or the method cannot use).
    ``estimate``: learn (online from the training episodes' measurements, or offline where the learner is
    declared supervised, e.g. the LSTM's) and return the estimates on the test measurements; the test truth
    is never seen.
    """

    label: str

    def fits(self, spec: ScenarioSpec) -> str | None: ...

    def estimate(self, scenario: Scenario, network: SensorNetwork, train: Episodes, test: Measurements,
                 seed: int) -> Estimates: ...


def require(spec: ScenarioSpec, what: str, **need) -> str | None:
    """The reason a scenario does not fit a method that needs ``spec.<key> == value`` (or one of a tuple of
    values) for every ``key=value`` of ``need``, ``None`` if it fits. ``what`` names the method."""
    for key, want in need.items():
        have = getattr(spec, key)
        ok = have in want if isinstance(want, tuple) else have == want
        if not ok:
            allowed = " or ".join(map(str, want)) if isinstance(want, tuple) else str(want)
            return f"{what} needs {key} {allowed}; scenario {spec.name} has {have}"
    return None
