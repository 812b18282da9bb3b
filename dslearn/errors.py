"""Errors raised for bad configuration or input, before any work starts."""

import math
from collections.abc import Mapping, Sequence
from numbers import Integral


class ConfigError(ValueError):
    """A configuration value is invalid. The message names the field and what is allowed."""


class DataFormatError(ValueError):
    """An input file is malformed. The message names the file and line number."""


def check_choice(field: str, value, allowed) -> None:
    """Raise :class:`ConfigError` unless ``value`` is one of ``allowed``."""
    allowed = list(allowed)
    if value not in allowed:
        raise ConfigError(f"{field}={value!r} is not allowed; choose one of {allowed}")


def _fmt(v) -> str:
    return repr(v) if not isinstance(v, float) or math.isfinite(v) else str(v)


def check_rules(field: str, value, rules: Mapping) -> None:
    """One value against declared rules (a schema field's or a data set key's): ``min_len`` / ``max_len`` of a list,
    ``choices``, the bounds ``ge`` / ``gt`` / ``le`` / ``lt`` (a bounded number must be finite); ``None`` passes.
    :class:`ConfigError` naming ``field``."""
    if isinstance(value, Sequence) and not isinstance(value, (str, bytes)):
        n = len(value)
        if "min_len" in rules and n < rules["min_len"]:
            raise ConfigError(f"{field} has {n} entries; it needs at least {rules['min_len']}")
        if "max_len" in rules and n > rules["max_len"]:
            raise ConfigError(f"{field} has {n} entries; it allows at most {rules['max_len']}")
        return
    if value is None:
        return
    if rules.get("choices") is not None:
        check_choice(field, value, rules["choices"])
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return
    bounds = {k: rules.get(k) for k in ("ge", "gt", "le", "lt") if rules.get(k) is not None}
    if isinstance(value, float) and not math.isfinite(value) and bounds:
        raise ConfigError(f"{field}={value} must be a finite number")
    words = {"ge": ">=", "gt": ">", "le": "<=", "lt": "<"}
    broken = {"ge": lambda b: value < b, "gt": lambda b: value <= b, "le": lambda b: value > b,
              "lt": lambda b: value >= b}
    if any(broken[k](b) for k, b in bounds.items()):
        raise ConfigError(f"{field}={value!r} must be " + " and ".join(f"{words[k]} {_fmt(b)}" for k, b in bounds.items()))


def _number(field: str, value) -> float:
    """``value`` as a float, or :class:`ConfigError` naming ``field`` (booleans are not numbers)."""
    if isinstance(value, bool):
        raise ConfigError(f"{field}={value!r} must be a number, not a boolean")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{field}={value!r} must be a number") from None


def check_positive(field: str, value, *, strict: bool = True, finite: bool = True) -> None:
    """Raise :class:`ConfigError` unless ``value`` > 0 (or >= 0 when ``strict`` is False) and,
    unless ``finite`` is False, finite (``inf`` would pass a range check that ``nan`` fails)."""
    v = _number(field, value)
    bound = "> 0" if strict else ">= 0"
    if v != v or (v <= 0 if strict else v < 0):
        raise ConfigError(f"{field}={value!r} must be {bound}")
    if finite and v == float("inf"):
        raise ConfigError(f"{field}={value!r} must be finite (and {bound})")


def check_number(field: str, value, low: float | None = None, *, strict: bool = False,
                 high: float | None = None, note: str = "") -> float:
    """``value`` as a float; :class:`ConfigError` unless it is a finite number (not a boolean) ``>= low`` (``> low``
    when ``strict``) and ``<= high`` (each bound optional). ``note`` follows the bounds in the message."""
    if value is None:
        raise ConfigError(f"{field} must be a number, not null")
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != value \
            or value in (float("inf"), float("-inf")):
        raise ConfigError(f"{field}={value!r} must be a finite number")
    if low is not None and (value <= low if strict else value < low) or (high is not None and value > high):
        rule = " and ".join(s for s in ("" if low is None else f"{'>' if strict else '>='} {low:g}",
                                        "" if high is None else f"<= {high:g}") if s)
        raise ConfigError(f"{field}={value!r} must be {rule}{note}")
    return float(value)


def check_integer(field: str, value, low: int = 0, *, note: str = "") -> int:
    """``value`` as an int; :class:`ConfigError` unless it is an integer (not a boolean) ``>= low``. ``note`` (what
    the count is) follows the bound in the message."""
    if isinstance(value, bool) or not isinstance(value, Integral) or value < low:
        raise ConfigError(f"{field}={value!r} must be an integer >= {low}{note}")
    return int(value)


def check_flag(field: str, value) -> bool:
    """``value``; :class:`ConfigError` unless it is a boolean."""
    if not isinstance(value, bool):
        raise ConfigError(f"{field}={value!r} must be true or false")
    return value


def check_keys(field: str, value, keys) -> dict:
    """The mapping ``value`` as a dict; :class:`ConfigError` naming ``field`` and the allowed ``keys`` if it is not a
    mapping or has a key not in ``keys``."""
    keys = list(keys)
    if not isinstance(value, Mapping):
        raise ConfigError(f"{field}={value!r} must be a mapping with keys {keys}")
    unknown = sorted(str(k) for k in value if k not in keys)
    if unknown:
        raise ConfigError(f"{field}: unknown key(s) {unknown}; allowed: {keys}")
    return dict(value)


def check_finite(field: str, value) -> None:
    """Raise :class:`ConfigError` unless ``value`` is a finite number (or a nested list of them)."""
    if isinstance(value, (list, tuple)) or (hasattr(value, "__iter__") and not isinstance(value, str)):
        for k, v in enumerate(value):
            check_finite(f"{field}[{k}]", v)
        return
    v = _number(field, value)
    if v != v or v in (float("inf"), float("-inf")):
        raise ConfigError(f"{field}={value!r} must be a finite number")


def as_list(field: str, value, *, none_as_empty: bool = False) -> list:
    """A config value as a list: a scalar becomes a one-element list; ``None`` becomes ``[]`` when
    ``none_as_empty``; anything else that is not iterable raises :class:`ConfigError`."""
    if value is None and none_as_empty:
        return []
    if isinstance(value, (str, int, float)):
        return [value]
    try:
        return list(value)
    except TypeError:
        raise ConfigError(f"{field}={value!r} must be a list") from None
