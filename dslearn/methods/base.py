r"""What every method of the matrix is: built from parts by the composition root, it says whether it fits a
scenario (:meth:`Method.fits`, from the scenario's declared :class:`~dslearn.episodes.ScenarioSpec` alone)
and estimates the targets' positions on test episodes after learning what its learner learns from the
training episodes (:meth:`Method.estimate`)."""

from __future__ import annotations

from typing import Callable, Protocol, runtime_checkable

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

    What a method needs of a scenario is also declared before it is built: the engine's class (the ``filter``
    part's ``_target_``) and the classes of the parts it takes (the ``model`` part's, ...) may each have a
    ``spec_misfit(spec) -> str | None`` (a class or static method), the reason read from the spec alone
    (:func:`declared_misfit`). The matrix asks these first and builds only the cells they let through, so a
    part that cannot be sized for a scenario is never built for it; ``fits`` then adds what only the built
    parts can tell (e.g. a prediction step that needs a kind of motion model).
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


def declared(target) -> Callable[[ScenarioSpec], str | None] | None:
    """The ``spec_misfit`` a part's ``_target_`` declares (the object the composition root calls: a class, a factory
    classmethod, whose class is asked, or a function with a ``spec_misfit`` attribute), ``None`` where it
    declares nothing."""
    for owner in (target, getattr(target, "__self__", None)):
        check = getattr(owner, "spec_misfit", None) if owner is not None else None
        if callable(check):
            return check
    return None


def declared_misfit(target, spec: ScenarioSpec) -> str | None:
    """Why the part built by ``target`` cannot be built for a scenario with ``spec`` (its declared
    ``spec_misfit``, :func:`declared`), ``None`` where it can or declares nothing."""
    check = declared(target)
    return None if check is None else check(spec)
