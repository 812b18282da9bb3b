"""Errors raised for bad configuration or input, before any work starts."""


class ConfigError(ValueError):
    """A configuration value is invalid. The message names the field and what is allowed."""


class DataFormatError(ValueError):
    """An input file is malformed. The message names the file and line number."""


def check_choice(field: str, value, allowed) -> None:
    """Raise :class:`ConfigError` unless ``value`` is one of ``allowed``."""
    allowed = list(allowed)
    if value not in allowed:
        raise ConfigError(f"{field}={value!r} is not allowed; choose one of {allowed}")


def check_positive(field: str, value, *, strict: bool = True) -> None:
    """Raise :class:`ConfigError` unless ``value`` > 0 (or >= 0 when ``strict`` is False)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{field}={value!r} must be a number") from None
    if v != v or (v <= 0 if strict else v < 0):
        raise ConfigError(f"{field}={value!r} must be {'> 0' if strict else '>= 0'}")
