r"""A cache of parsed data files, keyed by the files' content.

Parsing the plain-text trajectory files strictly (:func:`dslearn.data.ethucy.read_trajectories`) is a
Python loop over every line; its result depends only on the file's bytes and the parsing settings. A
parsed file is stored as an uncompressed ``.npz`` of plain arrays under a key that is the SHA-256 of
(a format tag, the dslearn version, the parsing settings, the file's bytes), so a changed file, a
changed setting or a new dslearn version never reads an old entry.

Where: ``$DSLEARN_CACHE_DIR`` (``off`` disables the cache: nothing is read or written), default
``~/.cache/dslearn``. A folder inside the package or its source tree is refused (ConfigError): the
cache holds user data, not code. Entries are written atomically (temporary file + rename) and read
with ``numpy.load(..., allow_pickle=False)``; an entry that cannot be read, or whose arrays are not
what the key promises (a truncated, corrupt or foreign file), is ignored and rebuilt, never an error.
Only successful parses are stored: a malformed file is parsed (and reported) every time.
"""

from __future__ import annotations

import hashlib
import io as _io
import logging
import os
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

import dslearn
from dslearn.errors import ConfigError
from dslearn.io import atomic_write_bytes

ENV_CACHE = "DSLEARN_CACHE_DIR"
#: the value of ``$DSLEARN_CACHE_DIR`` that turns the cache off
OFF = "off"
#: bump when the stored layout of an entry changes
FORMAT = "dslearn-data-cache-1"
log = logging.getLogger(__name__)

_PKG = Path(__file__).resolve().parents[1]


def cache_dir() -> Path | None:
    """The cache folder (``$DSLEARN_CACHE_DIR``, default ``~/.cache/dslearn``), or None when it is ``off``.

    Raises:
        ConfigError: ``$DSLEARN_CACHE_DIR`` names a folder inside the package or its source tree.
    """
    env = os.environ.get(ENV_CACHE, "").strip()
    if env.lower() == OFF:
        return None
    root = Path(env).expanduser() if env else Path.home() / ".cache" / "dslearn"
    resolved = root.resolve()
    for forbidden in (_PKG, _PKG.parent) if (_PKG.parent / "pyproject.toml").is_file() else (_PKG,):
        if resolved == forbidden or forbidden in resolved.parents:
            raise ConfigError(
                f"${ENV_CACHE}={env!r} is inside {forbidden}; the data cache must live outside the package and its "
                f"source tree (unset it for ~/.cache/dslearn, or set it to another folder, or to {OFF!r})"
            )
    return root


def content_key(kind: str, raw: bytes, settings: Mapping) -> str:
    """SHA-256 (hex) of the entry's kind, the format tag, the dslearn version, the settings and the bytes."""
    h = hashlib.sha256()
    head = f"{FORMAT}\0{kind}\0{dslearn.__version__}\0" + "\0".join(f"{k}={settings[k]!r}" for k in sorted(settings))
    h.update(head.encode())
    h.update(b"\0")
    h.update(raw)
    return h.hexdigest()


def _read(path: Path, spec: Mapping[str, tuple[str, int]]) -> dict[str, np.ndarray] | None:
    """The entry's arrays if it holds exactly ``spec`` (name -> (dtype, ndim)) with one common length; else None."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if set(z.files) != set(spec):
                return None
            arrays = {k: z[k] for k in spec}
    except FileNotFoundError:
        return None
    except Exception as e:  # corrupt, truncated, not an npz: rebuilt by the caller
        log.warning("data cache: ignoring unreadable entry %s (%s)", path, type(e).__name__)
        return None
    lengths = {a.shape[0] if a.ndim else -1 for a in arrays.values()}
    if len(lengths) != 1 or any(arrays[k].dtype != np.dtype(dt) or arrays[k].ndim != nd for k, (dt, nd) in spec.items()):
        log.warning("data cache: ignoring malformed entry %s", path)
        return None
    return arrays


def cached_arrays(kind: str, raw: bytes, settings: Mapping, spec: Mapping[str, tuple[str, int]],
                  build: Callable[[], dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """The arrays ``build()`` returns for this content and these settings, from the cache when it has them.

    ``spec``: name -> (dtype, ndim) of every array (an entry that does not match is rebuilt). ``build``'s
    exceptions propagate (nothing is stored). A cache folder that cannot be written only costs the cache.
    """
    root = cache_dir()
    if root is None:
        return build()
    path = root / kind / f"{content_key(kind, raw, settings)}.npz"
    got = _read(path, spec)
    if got is not None:
        return got
    arrays = build()
    buf = _io.BytesIO()
    np.savez(buf, **{k: np.ascontiguousarray(arrays[k]) for k in spec})
    try:
        atomic_write_bytes(path, buf.getvalue())
    except OSError as e:
        log.warning("data cache: cannot write %s (%s); continuing without it", path, e)
    return arrays
