"""One run's work and its files: :func:`execute` validates a configuration, runs its study and writes,
in the run's folder, ``config.yaml`` (resolved config), ``meta.json`` (package version, git commit,
library versions, seed, overrides, wall time, jitter counts, and the completeness marker: the row count
and SHA-256 of ``results.csv``), then — last, atomically — ``results.csv``; :func:`_write_status` writes
``status.json`` after it. The numerical warnings raised meanwhile are counted, not printed
(:class:`WarningLedger`)."""

from __future__ import annotations

import datetime as _dt
import importlib
import json
import platform
import re
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

from omegaconf import DictConfig, OmegaConf

from dslearn import __version__
from dslearn.app import common
from dslearn.app.common import STATUS_FILE, log

if TYPE_CHECKING:
    import pandas as pd


def _git_commit() -> str | None:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True, text=True, timeout=5
        )
        return out.stdout.strip() or None
    except Exception:
        return None


def _git_dirty() -> bool | None:
    try:
        out = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=Path(__file__).parent, capture_output=True, text=True, timeout=5,
        )
        return bool(out.stdout.strip()) if out.returncode == 0 else None
    except Exception:
        return None


def _versions() -> dict:
    vs = {"python": platform.python_version(), "platform": platform.platform()}
    for m in ("torch", "gpytorch", "numpy", "pandas", "hydra", "omegaconf", "matplotlib", "tqdm"):
        try:
            vs[m] = importlib.import_module(m).__version__
        except Exception:
            pass
    return vs


def _hydra_job() -> dict:
    """Overrides and job number of the running Hydra job (empty outside Hydra)."""
    try:
        from hydra.core.hydra_config import HydraConfig

        hc = HydraConfig.get()
        return {
            "overrides": list(hc.overrides.task),
            "job_num": int(hc.job.num) if hc.job.get("num") is not None else None,
            "mode": str(hc.mode.name) if hc.get("mode") is not None else None,
        }
    except Exception:
        return {}


# --------------------------------------------------------------------------------------------
# numerical warnings: counted into meta.json, one summary line per run


_JITTER_RE = re.compile(r"added jitter of ([0-9.eE+-]+)")


class WarningLedger:
    """Collects the warnings raised while a task runs.

    Numerical-jitter warnings (GPyTorch's ``NumericalWarning`` "added jitter of ..." and the
    online GP's "diagonal clamped") are counted, not printed: with the project's own jitter
    records (:mod:`dslearn.diagnostics`) they make ``jitter_events`` / ``jitter_max`` in
    ``meta.json`` and one summary line. Every other warning is shown once per distinct message
    after the task (with its count when it repeated)."""

    def __init__(self, diagnostics=None) -> None:
        self.jitter_warnings = 0
        self.jitter_max = 0.0
        self.other: dict[tuple, list] = {}
        self._cm = None
        self._diag = diagnostics

    @staticmethod
    def _is_jitter(w) -> bool:
        name = type(w.message).__name__ if isinstance(w.message, Warning) else w.category.__name__
        text = str(w.message)
        return name == "NumericalWarning" or "added jitter" in text or "diagonal clamped" in text

    def __enter__(self) -> "WarningLedger":
        from dslearn.diagnostics import Diagnostics

        if self._diag is None:  # a ledger of its own: count the kernels' jitter records here
            self._own = Diagnostics().__enter__()
            self._diag = self._own
        else:
            self._own = None
        self._cm = warnings.catch_warnings(record=True)
        self._log = self._cm.__enter__()
        warnings.simplefilter("always")
        warnings.filterwarnings("ignore", message=r".*torch\.jit\.script.* is deprecated")
        return self

    def __exit__(self, *exc) -> None:
        self._cm.__exit__(*exc)
        if self._own is not None:
            self._own.__exit__(*exc)
        self.events = self._diag.jitter.count
        self.max = self._diag.jitter.max_jitter
        for w in self._log:
            if self._is_jitter(w):
                m = _JITTER_RE.search(str(w.message))
                if m:
                    try:
                        self.jitter_max = max(self.jitter_max, float(m.group(1)))
                    except ValueError:
                        pass
                if "diagonal clamped" not in str(w.message):  # those are already in the diagnostics
                    self.jitter_warnings += 1
                continue
            key = (w.category, str(w.message))
            self.other.setdefault(key, [w, 0])[1] += 1
        for (cat, text), (w, n) in self.other.items():
            warnings.warn_explicit(text + (f" (x{n})" if n > 1 else ""), cat, w.filename, w.lineno,
                                   registry={})

    @property
    def total(self) -> int:
        return self.events + self.jitter_warnings

    @property
    def total_max(self) -> float:
        return max(self.max, self.jitter_max)


def execute(cfg: DictConfig, out_dir: str | Path) -> pd.DataFrame:
    """Validate ``cfg``, run its task and write the result files into ``out_dir``. Returns the results.

    Raises :class:`~dslearn.errors.ConfigError` (before any work) for a bad configuration.
    """
    import pandas as pd

    from dslearn.io import META_FILE, RESULTS_FILE, atomic_write_text, results_text, sha256_text
    from dslearn.schemas.core import validate_config

    out_dir = Path(out_dir)
    validate_config(cfg)
    if cfg.get("threads"):
        import torch

        torch.set_num_threads(int(cfg.threads))
    started = _dt.datetime.now(_dt.timezone.utc)
    t0 = time.perf_counter()
    from dslearn.diagnostics import Diagnostics

    progress = bool(cfg.get("progress", False))
    with Diagnostics() as diag, WarningLedger(diag) as ledger:
        from dslearn.compose import build_study  # the composition root fills the study's slots

        df = build_study(cfg).run(diagnostics=diag, progress=progress)
    wall = time.perf_counter() - t0
    what = cfg.task._target_
    if not isinstance(df, pd.DataFrame) or not {"metric", "value"} <= set(df.columns):
        raise RuntimeError(f"task {what} must return a tidy DataFrame with 'metric' and 'value' columns")
    if df.empty:
        raise RuntimeError(f"task {what} returned an empty result table")
    df = df.copy()
    for col, val in (("seed", int(cfg.seed)), ("task", str(cfg.task.name)), ("study", str(cfg.study))):
        if col not in df.columns:
            df.insert(0, col, val)
    text = results_text(df)
    atomic_write_text(out_dir / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))
    from dslearn.io import ARTIFACTS, write_artifacts

    artifacts = [p.name for p in write_artifacts(out_dir, df.attrs.get(ARTIFACTS))]  # the study's extra files
    jitter = ledger.total
    meta = {
        "dslearn_version": __version__,
        "git_commit": _git_commit(),
        "git_dirty": _git_dirty(),
        "versions": _versions(),
        "seed": int(cfg.seed),
        "task": str(cfg.task.name),
        "study": str(cfg.study),
        "started_utc": started.isoformat(timespec="seconds"),
        "wall_time_s": round(wall, 3),
        "rows": len(df),
        "artifacts": artifacts,
        "results_sha256": sha256_text(text),  # completeness marker checked by dslearn.io.check_complete
        "jitter_events": jitter,
        "jitter_max": ledger.total_max,
        "argv": list(common.USER_ARGV) if common.USER_ARGV is not None else sys.argv[1:],
        "diagnostics": {**diag.as_dict(), "jitter_events": jitter, "jitter_max": ledger.total_max},
        **_hydra_job(),
    }
    if jitter:
        log.info("jitter added to %d near-singular matrices (max %.3g); counted in meta.json", jitter, ledger.total_max)
    atomic_write_text(out_dir / META_FILE, json.dumps(meta, indent=2))
    atomic_write_text(out_dir / RESULTS_FILE, text)  # last: its presence (matching meta) means the run finished
    log.info("wrote %s (%d rows, %.1fs)", out_dir / RESULTS_FILE, len(df), wall)
    return df


def _write_status(out_dir: Path, status: str, wall: float, **extra) -> None:
    from dslearn.io import atomic_write_text

    try:
        atomic_write_text(out_dir / STATUS_FILE, json.dumps({"status": status, "wall_s": round(wall, 3), **extra}))
    except OSError:
        pass
