"""dslearn: learning motion models while tracking with a network of sensors."""

from importlib.metadata import PackageNotFoundError, version as _version

try:  # the one version number is pyproject.toml's, read from the installed package's metadata
    __version__ = _version("dslearn")
except PackageNotFoundError:  # not installed (the source folder on sys.path only)
    __version__ = "0+unknown"
