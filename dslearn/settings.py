"""Typed settings: the dataclass field helper that states a value's allowed range or choices.

A study's settings, a data-size block, a filter's options are plain dataclasses whose fields carry
their rules (``ranged(0.5, gt=0)``, ``ranged("a", choices=("a", "b"))``); the validation layer
(:mod:`dslearn.schemas`) applies those rules to a configuration before anything is built, and the
composition root hands the checked values to the study as instances of these dataclasses.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

#: the rules a field may carry
RULES = ("ge", "gt", "le", "lt", "choices", "integer", "each", "min_len", "max_len", "nullable")


def ranged(default: Any = dataclasses.MISSING, *, factory: Callable[[], Any] | None = None, **rules) -> Any:
    """A dataclass field with range / choice rules (``ge gt le lt choices min_len max_len``; ``each=True``
    applies the number/choice rules to every element of a list)."""
    bad = set(rules) - set(RULES)
    if bad:
        raise TypeError(f"unknown rule(s) {sorted(bad)}; known: {RULES}")
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata=rules)
    return dataclasses.field(default=default, metadata=rules)
