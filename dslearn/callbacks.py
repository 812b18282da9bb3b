"""Hydra callbacks: one results table per sweep, and a sweep summary.

``conf/config.yaml`` registers :class:`GatherResults` under ``hydra.callbacks.gather``. When a
multirun ends (whatever the launcher: basic, joblib, Ray, submitit), it reads every job
directory of the sweep, keeps the complete results (:func:`dslearn.io.check_complete`; broken or
partial job directories are skipped with a warning), adds each job's overrides as columns
(``ov.<key>``, e.g. ``ov.model``, ``ov.consensus.omega``) plus ``job`` and ``run_dir``, and writes
``<sweep dir>/sweep_results.parquet`` (if pyarrow is installed), ``sweep_results.csv`` and
``sweep.json`` (jobs done / skipped / failed / incomplete, wall time). ``dslearn-report <sweep dir>``
reads that table.

Use without Hydra: ``gather_sweep(sweep_dir)``.
"""

from __future__ import annotations

import json
import logging
import time
import warnings
from pathlib import Path
from typing import Any

import pandas as pd
from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from dslearn.io import (
    META_FILE,
    RESULTS_FILE,
    SWEEP_TABLE,
    RunDirBusy,
    RunLock,
    atomic_write_csv,
    atomic_write_text,
    check_complete,
)

log = logging.getLogger("dslearn.sweep")

#: overrides that do not change results: not turned into columns
RUNTIME_KEYS = {"resume", "progress", "print_table", "threads", "max_memory_gb"}


def parse_overrides(overrides: list[str]) -> dict[str, str]:
    """``["model=lin", "+resume=true", "consensus.omega=one"]`` -> ``{"model": "lin", ...}``.

    Hydra's own keys (``hydra...``), deletions (``~key``) and runtime-only keys are left out.
    """
    out = {}
    for o in overrides:
        if "=" not in o or o.startswith("~"):
            continue
        k, v = o.split("=", 1)
        k = k.lstrip("+")
        if k.startswith("hydra") or k in RUNTIME_KEYS:
            continue
        out[k] = v
    return out


def _job_overrides(job_dir: Path) -> list[str]:
    try:
        meta = json.loads((job_dir / META_FILE).read_text(encoding="utf-8"))
        if isinstance(meta, dict) and meta.get("overrides") is not None:
            return list(meta["overrides"])
    except (OSError, ValueError, TypeError):  # ValueError: bad JSON or not UTF-8
        pass
    p = job_dir / ".hydra" / "overrides.yaml"
    if p.is_file():
        from omegaconf import OmegaConf

        try:
            return [str(x) for x in OmegaConf.load(p)]
        except Exception:  # noqa: BLE001
            return []
    return []


def _job_dirs(sweep_dir: Path) -> list[Path]:
    """Job directories of a sweep: sub-directories that hold a Hydra job record or a result."""
    dirs = []
    for d in sweep_dir.iterdir() if sweep_dir.is_dir() else []:
        if d.is_dir() and any((d / f).exists() for f in (".hydra", RESULTS_FILE, META_FILE, "status.json")):
            dirs.append(d)
    return sorted(dirs, key=lambda d: (0, int(d.name)) if d.name.isdigit() else (1, d.name))


def gather_sweep(sweep_dir: str | Path, write: bool = True) -> tuple[pd.DataFrame, dict]:
    """Gather every complete job's ``results.csv`` of a sweep into one table.

    Returns ``(table, summary)``; ``summary`` counts the jobs by status
    (``done``, ``skipped`` = resumed from an earlier run, ``failed``, ``incomplete`` = no complete
    result and no failure record, e.g. killed). With ``write``, writes ``sweep_results.{parquet,csv}``
    and ``sweep.json`` into ``sweep_dir``.
    """
    sweep_dir = Path(sweep_dir)
    frames, counts, problems = [], {"done": 0, "skipped": 0, "failed": 0, "incomplete": 0}, []
    config_error = False
    for d in _job_dirs(sweep_dir):
        status = {}
        try:
            status = json.loads((d / "status.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            pass
        if not isinstance(status, dict):
            status = {}
        ok, why = check_complete(d)
        if not ok:
            if status.get("status") == "failed":
                counts["failed"] += 1
                config_error |= bool(status.get("config_error"))
                problems.append(f"{d.name}: failed: {status.get('error', '?')}")
            else:
                counts["incomplete"] += 1
                problems.append(f"{d.name}: {'interrupted; ' if status.get('status') == 'interrupted' else ''}{why}")
            if (d / RESULTS_FILE).exists():
                msg = f"ignoring broken result in {d}: {why}"
                warnings.warn(msg, stacklevel=2)
                log.warning(msg)
            continue
        counts["skipped" if status.get("status") == "skipped" else "done"] += 1
        df = pd.read_csv(d / RESULTS_FILE)
        ov = parse_overrides(_job_overrides(d))
        df.insert(0, "job", int(d.name) if d.name.isdigit() else d.name)
        for k, v in ov.items():
            df[f"ov.{k}"] = v
        df["run_dir"] = d.name
        frames.append(df)
    table = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    summary = {
        "sweep_dir": str(sweep_dir),
        "jobs": sum(counts.values()),
        **counts,
        "rows": len(table),
        "config_error": config_error,
        "problems": problems,
    }
    if write and len(table):
        atomic_write_csv(table, sweep_dir / f"{SWEEP_TABLE}.csv")
        summary["table"] = str(sweep_dir / f"{SWEEP_TABLE}.csv")
        try:
            import pyarrow  # noqa: F401

            tmp = sweep_dir / f".{SWEEP_TABLE}.parquet.tmp"
            _parquet_safe(table).to_parquet(tmp, index=False)
            tmp.replace(sweep_dir / f"{SWEEP_TABLE}.parquet")
            summary["table"] = str(sweep_dir / f"{SWEEP_TABLE}.parquet")
        except ImportError:
            log.info("pyarrow not installed: wrote %s.csv only (pip install pyarrow)", SWEEP_TABLE)
        except Exception as e:  # noqa: BLE001 - the CSV is the fallback
            log.warning("could not write %s.parquet (%s); the CSV has the same table", SWEEP_TABLE, e)
    if write:
        atomic_write_text(sweep_dir / "sweep.json", json.dumps(summary, indent=2))
    return table, summary


def _parquet_safe(df: pd.DataFrame) -> pd.DataFrame:
    """Object columns with mixed types (e.g. ``omega``: '-' and 'one') as strings for Parquet."""
    out = df.copy()
    for c in out.columns:
        if out[c].dtype == object or str(out[c].dtype).startswith("string"):
            out[c] = out[c].map(lambda v: v if v is None or isinstance(v, str) else str(v))
    return out


class GatherResults(Callback):
    """Gather the sweep's results table when a multirun ends, and log a sweep summary.

    Exits with code 2 (a job had a configuration error) or 1 (another failure) after gathering
    when any job failed, so a failing sweep is visible to scripts while the finished jobs' table
    is still written (``resume=true`` then re-runs only the failed and missing jobs).
    """

    def __init__(self, fail_exit: bool = True) -> None:
        self.fail_exit = fail_exit
        self._t0: float | None = None
        self._lock: RunLock | None = None

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        self._t0 = time.perf_counter()
        sweep_dir = Path(str(config.hydra.sweep.dir))
        existed = sweep_dir.is_dir()
        try:  # one sweep at a time in a sweep folder (a second one would overwrite the first's jobs)
            self._lock = RunLock(sweep_dir).acquire()
        except RunDirBusy as e:
            import sys

            log.error("%s", e)
            print(f"dslearn-run: sweep folder busy: {' '.join(str(e).split())} (hydra.sweep.dir)", file=sys.stderr, flush=True)
            raise SystemExit(2)
        if config.get("resume"):
            if existed:
                n = sum(1 for d in _job_dirs(sweep_dir) if check_complete(d)[0])
                log.info("resume: %s holds %d complete job result(s); jobs with the same overrides are skipped", sweep_dir, n)
            else:
                log.warning(
                    "resume=true but the sweep dir %s does not exist yet: nothing to resume. The default "
                    "sweep dir has a timestamp; give the same hydra.sweep.dir=... as the interrupted sweep",
                    sweep_dir,
                )
        log.info("sweep started: %s (launcher %s)", sweep_dir, config.hydra.launcher.get("_target_", "?"))

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(str(config.hydra.sweep.dir))
        table, s = gather_sweep(sweep_dir)
        wall = time.perf_counter() - self._t0 if self._t0 is not None else float("nan")
        s["wall_s"] = round(wall, 2)
        atomic_write_text(sweep_dir / "sweep.json", json.dumps(s, indent=2))
        line = (
            f"sweep summary: {s['jobs']} jobs: {s['done']} done, {s['skipped']} skipped (resumed), "
            f"{s['failed']} failed, {s['incomplete']} incomplete; wall {wall:.1f}s; "
            f"table: {s.get('table', 'none')} ({s['rows']} rows)"
        )
        log.info(line)
        for p in s["problems"]:
            log.warning("  %s", p)
        if self._lock is not None:
            self._lock.release()
            self._lock = None
        if self.fail_exit and s["failed"]:
            raise SystemExit(2 if s["config_error"] else 1)
