r"""One diagnostics object per run: numerical jitter, measurement gating, timings.

:func:`dslearn.run.execute` opens a :class:`Diagnostics` around the study, hands it to the study's
entry (``run(cfg, diagnostics=...)`` when the entry takes it) and writes :meth:`Diagnostics.as_dict`
into ``meta.json`` (key ``diagnostics``) for every study. The counters are read as differences
over the run of the process-wide counters the numerical kernels keep
(:data:`dslearn.types.JITTER`, :data:`dslearn.filters.information.GATE_STATS`), so kernels deep in a
model need no extra argument; a study adds its own timings and counts with :meth:`timed` and
:meth:`count`.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Any


class Diagnostics:
    """Counters and timings of one run (open it with ``with Diagnostics() as d:``)."""

    def __init__(self) -> None:
        self.timings: dict[str, float] = {}
        self.counts: dict[str, float] = {}
        self.jitter_events = 0
        self.jitter_max = 0.0
        self.gate_tested = 0
        self.gate_rejected = 0
        self._open = False

    def __enter__(self) -> "Diagnostics":
        from dslearn.filters.information import GATE_STATS

        self._g0 = dict(GATE_STATS)
        self._t0 = time.perf_counter()
        self._open = True
        return self

    def __exit__(self, *exc) -> None:
        from dslearn.filters.information import GATE_STATS

        self.gate_tested += GATE_STATS["tested"] - self._g0["tested"]
        self.gate_rejected += GATE_STATS["rejected"] - self._g0["rejected"]
        self.timings.setdefault("total_s", round(time.perf_counter() - self._t0, 3))
        self._open = False

    def set_jitter(self, events: int, max_jitter: float) -> None:
        """Jitter added to near-singular matrices during the run (from the run's warning ledger)."""
        self.jitter_events, self.jitter_max = int(events), float(max_jitter)

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
            "jitter_events": self.jitter_events,
            "jitter_max": self.jitter_max,
            "gating": {"tested": self.gate_tested, "rejected": self.gate_rejected},
            "timings": dict(self.timings),
            "counts": dict(self.counts),
        }
