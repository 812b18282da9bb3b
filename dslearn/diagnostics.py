r"""Diagnostics as an object: numerical jitter, measurement gating, timings of one run.

A :class:`Diagnostics` is a context (like ``gpytorch.settings``): while it is open, the numerical
kernels record into it (``safe_cholesky`` the jitter it added, the online GP the diagonals it
clamped, the filter's chi-square gate what it tested and rejected), through :func:`current`;
nested contexts all receive the records. :func:`dslearn.app.record.execute` opens one around every
study, hands it to the study's entry (``run(cfg, diagnostics=...)`` when the entry takes it) so
the study adds its own timings and counts, and writes :meth:`Diagnostics.as_dict` into
``meta.json``. Nothing diffs a module-level counter. Outside any run the records go to
:data:`SESSION` (a library user's Python session).
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any


class JitterLog:
    """Counts the times a near-singular matrix needed jitter or a fallback."""

    def __init__(self) -> None:
        self.count = 0
        self.max_jitter = 0.0

    def record(self, jitter: float) -> None:
        self.count += 1
        self.max_jitter = max(self.max_jitter, float(jitter))


class Diagnostics:
    """Counters and timings of one run (``with Diagnostics() as d: ...``)."""

    def __init__(self) -> None:
        self.jitter = JitterLog()
        self.gate_tested = 0
        self.gate_rejected = 0
        self.timings: dict[str, float] = {}
        self.counts: dict[str, float] = {}
        self._token = None

    # the context ------------------------------------------------------------------------
    def __enter__(self) -> "Diagnostics":
        self._t0 = time.perf_counter()
        self._token = _ACTIVE.set(_ACTIVE.get() + (self,))
        return self

    def __exit__(self, *exc) -> None:
        _ACTIVE.reset(self._token)
        self._token = None
        self.timings.setdefault("total_s", round(time.perf_counter() - self._t0, 3))

    # what the kernels record --------------------------------------------------------------
    def record_jitter(self, jitter: float) -> None:
        self.jitter.record(jitter)

    def record_gate(self, tested: int, rejected: int) -> None:
        self.gate_tested += int(tested)
        self.gate_rejected += int(rejected)

    # what a study records ---------------------------------------------------------------
    @contextmanager
    def timed(self, name: str):
        """Add the wall time of the block to ``timings[name + '_s']``."""
        t = time.perf_counter()
        try:
            yield
        finally:
            key = f"{name}_s"
            self.timings[key] = round(self.timings.get(key, 0.0) + time.perf_counter() - t, 3)

    def count(self, name: str, value: float = 1) -> None:
        self.counts[name] = self.counts.get(name, 0) + value

    def as_dict(self) -> dict[str, Any]:
        return {
            "jitter_events": self.jitter.count,
            "jitter_max": self.jitter.max_jitter,
            "gating": {"tested": self.gate_tested, "rejected": self.gate_rejected},
            "timings": dict(self.timings),
            "counts": dict(self.counts),
        }


#: where records go outside any run (a library user's session)
SESSION = Diagnostics()
_ACTIVE: ContextVar[tuple[Diagnostics, ...]] = ContextVar("dslearn_diagnostics", default=())


def active() -> tuple[Diagnostics, ...]:
    """Every open context, outermost first; :data:`SESSION` when none is open."""
    return _ACTIVE.get() or (SESSION,)


def current() -> Diagnostics:
    """The innermost open context (:data:`SESSION` when none is open)."""
    return active()[-1]


def record_jitter(jitter: float) -> None:
    for d in active():
        d.record_jitter(jitter)


def record_gate(tested: int, rejected: int) -> None:
    for d in active():
        d.record_gate(tested, rejected)


def record_count(name: str, value: float = 1) -> None:
    """Add ``value`` to the count ``name`` of every open context (a fallback taken, for example)."""
    for d in active():
        d.count(name, value)
