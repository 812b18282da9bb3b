r"""A content-addressed cache of fitted offline motion models, shared by every method that fits the same model.

In a matrix sweep the EKF and the UKF, each with individual, hybrid and centralised consensus (and the backprop
learner, which starts from the offline fit), train the SAME LSTM on the same scenario, seed and training episodes.
:func:`fit_offline_cached` fits a model once and stores what the fit produced; every later fit with the same
inputs loads it instead, bit for bit what a fresh fit gives.

The key is the SHA-256 of everything that changes the fit, never a preset's name: a format tag, the dslearn and
torch versions, the source of the modules that define the model's class and its bases (:func:`code_files`: an
edited fit is fitted again), the model's class and its :meth:`fit_cache_settings` (for the LSTM its network,
offline schedule, process-noise rule, dtype and device; for the fitted social force its grid and refinement), the
training states' dtype, shape and bytes, ``dt`` and the seed. The model supplies the rest of the protocol:
``fitted_state()`` (tensors and plain values only) and ``load_fitted_state(state)``.

Where: the data cache's folder (:func:`dslearn.data.cache.cache_dir`: ``$DSLEARN_CACHE_DIR``, default
``~/.cache/dslearn``; ``off`` disables it), subfolder ``offline_fits``. An entry is written atomically (temporary
file, fsync, rename), so a crashed write leaves no file that loads, and read with ``torch.load(weights_only=True)``;
an entry that cannot be read or does not fit the model is ignored, refitted and overwritten. Processes that fit the
same key at once (a sweep's parallel workers) take a lock on it first, so one fits and the others load.

Visible: each fit logs ``offline fit: fitted in ... s, stored in cache <key>`` or ``offline fit: loaded from cache
<key>``, and the run's diagnostics (``meta.json``) count ``offline_fit_cache_hits`` / ``_misses`` / ``_stored``
and time ``offline_fit_s`` (the fit, or the load).
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import logging
import time
import warnings
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

import dslearn
from dslearn import diagnostics
from dslearn.data.cache import cache_dir
from dslearn.io import atomic_write_bytes

#: bump when the stored layout of an entry changes
FORMAT = "dslearn-offline-fit-1"
#: the cache's subfolder
KIND = "offline_fits"
log = logging.getLogger(__name__)


def code_files(model: Any) -> list[Path]:
    """The source files of dslearn's modules that define ``model``'s class and its bases (their code is the fit)."""
    import sys

    out = []
    for cls in type(model).__mro__:
        mod = sys.modules.get(cls.__module__)
        f = getattr(mod, "__file__", None)
        if cls.__module__.startswith("dslearn.") and f and Path(f) not in out:
            out.append(Path(f))
    return out


def fit_key(model: Any, trajectories: Tensor, dt: float, seed: int) -> str:
    """SHA-256 (hex) of what changes the fit of ``model`` on ``trajectories`` (see the module's docstring)."""
    settings = model.fit_cache_settings()
    head = "\0".join([FORMAT, dslearn.__version__, torch.__version__, f"{type(model).__module__}.{type(model).__qualname__}",
                      *(f"{k}={settings[k]!r}" for k in sorted(settings)), f"dt={float(dt)!r}", f"seed={int(seed)}",
                      f"states={trajectories.dtype}{tuple(trajectories.shape)}"])
    h = hashlib.sha256(head.encode())
    for f in code_files(model):
        h.update(b"\0" + f.name.encode() + b"\0" + f.read_bytes())
    h.update(b"\0")
    h.update(trajectories.detach().to("cpu").contiguous().numpy().tobytes())
    return h.hexdigest()


def entry_path(key: str) -> Path | None:
    """Where the entry of ``key`` lives (``None``: the cache is off)."""
    root = cache_dir()
    return None if root is None else root / KIND / f"{key}.pt"


def _record(name: str, seconds: float | None = None) -> None:
    for d in diagnostics.active():
        d.count(f"offline_fit_cache_{name}")
        if seconds is not None:
            d.timings["offline_fit_s"] = round(d.timings.get("offline_fit_s", 0.0) + seconds, 3)


def _load(path: Path, key: str) -> dict | None:
    """The stored state of ``key`` (``None``: no entry, or one that cannot be read or is not this key's)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            blob = torch.load(path, weights_only=True, map_location="cpu")
    except FileNotFoundError:
        return None
    except Exception as e:  # noqa: BLE001 - truncated, corrupt, foreign: refitted and overwritten
        log.warning("offline fit: ignoring unreadable cache entry %s (%s)", key, type(e).__name__)
        return None
    if not isinstance(blob, dict) or blob.get("format") != FORMAT or blob.get("key") != key \
            or not isinstance(blob.get("state"), dict):
        log.warning("offline fit: ignoring malformed cache entry %s", key)
        return None
    return blob["state"]


@contextlib.contextmanager
def _locked(path: Path):
    """An exclusive lock on ``path``'s key while it is fitted (POSIX ``flock``; elsewhere none)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        f = open(path.with_name(path.name + ".lock"), "a")
    except OSError as e:  # a folder that cannot be written only costs the cache (and the lock)
        log.warning("offline fit: cannot lock cache entry %s (%s); continuing without the lock", path.stem, e)
        yield
        return
    with f:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def _try_load(model: Any, path: Path, key: str) -> bool:
    state = _load(path, key)
    if state is None:
        return False
    try:
        model.load_fitted_state(state)
    except Exception as e:  # noqa: BLE001 - an entry that does not fit this model: refitted and overwritten
        log.warning("offline fit: cache entry %s does not fit the model (%s); fitting again", key, type(e).__name__)
        return False
    return True


def fit_offline_cached(model: Any, trajectories: Tensor, dt: float, seed: int = 0) -> Any:
    """``model.fit_offline(trajectories, dt, seed=seed)``, or its result loaded from the cache (bit-identical).

    Sets ``model.fit_cache = {"key", "source"}`` (``source``: ``cache``, ``fit`` or ``off``). A model without the
    cache protocol (``fit_cache_settings``, ``fitted_state``, ``load_fitted_state``) is fitted as before."""
    protocol = all(hasattr(model, m) for m in ("fit_cache_settings", "fitted_state", "load_fitted_state"))
    path = key = None
    if protocol:
        key = fit_key(model, trajectories, dt, seed)
        path = entry_path(key)
    if path is None:
        t = time.perf_counter()
        model.fit_offline(trajectories, dt, seed=seed)
        for d in diagnostics.active():
            d.timings["offline_fit_s"] = round(d.timings.get("offline_fit_s", 0.0) + time.perf_counter() - t, 3)
        model.fit_cache = {"key": key, "source": "off"}
        return model
    t = time.perf_counter()
    with _locked(path):
        if _try_load(model, path, key):
            _record("hits", time.perf_counter() - t)
            log.info("offline fit: loaded from cache %s", key)
            model.fit_cache = {"key": key, "source": "cache"}
            return model
        t = time.perf_counter()
        model.fit_offline(trajectories, dt, seed=seed)
        fitted = time.perf_counter() - t
        _record("misses", fitted)
        buf = io.BytesIO()
        torch.save({"format": FORMAT, "key": key, "state": model.fitted_state()}, buf)
        try:
            atomic_write_bytes(path, buf.getvalue())
        except OSError as e:
            log.warning("offline fit: cannot write cache entry %s (%s); continuing without it", key, e)
        else:
            _record("stored")
            log.info("offline fit: fitted in %.1f s, stored in cache %s", fitted, key)
    model.fit_cache = {"key": key, "source": "fit"}
    return model
