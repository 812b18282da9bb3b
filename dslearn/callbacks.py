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
import os
import sys
import threading
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


#: the number of jobs of the sweep about to start (``dslearn-run`` counts them before Hydra starts)
_EXPECTED_JOBS: int | None = None
#: the sweep running in this process (its callback), for the Ctrl-C line of ``dslearn-run``
_ACTIVE: "GatherResults | None" = None


def expect_jobs(n: int | None) -> None:
    """Tell the next sweep's status line how many jobs it has."""
    global _EXPECTED_JOBS
    _EXPECTED_JOBS = None if n is None else int(n)


def _duration(s: float) -> str:
    s = int(round(max(s, 0.0)))
    h, rest = divmod(s, 3600)
    m, sec = divmod(rest, 60)
    return f"{h}h{m:02d}m" if h else (f"{m}m{sec:02d}s" if m else f"{sec}s")


def launcher_workers(launcher: Any, cpus: int | None = None) -> int:
    """How many jobs a sweep's launcher runs at once: joblib's ``n_jobs`` (negative: ``cpus + 1 + n_jobs``,
    as joblib counts), 1 for the basic launcher, the CPU count otherwise."""
    cpus = cpus or os.cpu_count() or 1
    target = str(_get(launcher, "_target_") or "")
    if "Joblib" in target:
        n = _get(launcher, "n_jobs")
        n = -1 if n is None else int(n)
        return max(1, cpus + 1 + n if n < 0 else n)
    if target.endswith("BasicLauncher") or not target:
        return 1
    return cpus


def _get(cfg: Any, key: str):
    try:
        return cfg.get(key)
    except Exception:  # noqa: BLE001
        return None


def status_line(done: int, failed: int, running: int, jobs: int | None, walls: list[float], workers: int) -> str:
    """``[sweep] 5/18 done, 0 failed, 2 running, ETA 1m20s``: ETA = mean job wall time so far x jobs
    left / workers (the workers busy at most with the jobs left)."""
    finished = done + failed
    head = f"[sweep] {finished}/{jobs}" if jobs is not None else f"[sweep] {finished}"
    line = f"{head} done, {failed} failed, {running} running"
    if jobs is not None:
        left = max(jobs - finished, 0)
        if left == 0:
            return line + ", ETA 0s"
        if walls:
            return line + f", ETA {_duration(sum(walls) / len(walls) * left / max(1, min(workers, left)))}"
        return line + ", ETA ?"
    return line


class SweepStatus:
    """The sweep's overall status, one line per finished job, printed by the sweep's own process.

    Jobs may run in other processes (joblib's workers), so it polls the sweep folder: a job has
    started when its ``.hydra/`` record is written and finished when its ``status.json`` is, both
    after the sweep started (older files are a resumed sweep's earlier run). ``done`` counts the
    results made or kept (``skipped`` by ``resume=true``), ``failed`` the failures."""

    def __init__(self, sweep_dir: Path, jobs: int | None, workers: int, stream=None, interval: float = 0.2,
                 since: float | None = None) -> None:
        self.sweep_dir = Path(sweep_dir)
        self.jobs, self.workers, self.interval = jobs, max(1, int(workers)), interval
        self.stream = stream
        self.since = time.time() if since is None else since
        self.finished: dict[str, str] = {}
        self.walls: list[float] = []
        self.done = self.failed = 0
        self.lines: list[str] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._mutex = threading.Lock()

    def _fresh(self, p: Path) -> float | None:
        try:
            t = p.stat().st_mtime
        except OSError:
            return None
        return t if t >= self.since else None

    def poll(self) -> list[str]:
        """Read the folder; print (and return) one line per job finished since the last poll."""
        with self._mutex:
            new, started = [], 0
            for d in _job_dirs(self.sweep_dir):
                if self._fresh(d / ".hydra") is not None or self._fresh(d / ".hydra" / "overrides.yaml") is not None:
                    started += 1
                if d.name in self.finished:
                    continue
                t = self._fresh(d / "status.json")
                if t is None:
                    continue
                try:
                    st = json.loads((d / "status.json").read_text(encoding="utf-8"))
                except (OSError, ValueError):
                    continue  # being written: next poll
                status = st.get("status") if isinstance(st, dict) else None
                if status in ("done", "skipped", "failed"):
                    new.append((t, d.name, status, st.get("wall_s")))
            out = []
            for _, name, status, wall in sorted(new):
                self.finished[name] = status
                if status == "failed":
                    self.failed += 1
                else:
                    self.done += 1
                if status == "done" and isinstance(wall, (int, float)):
                    self.walls.append(float(wall))
                running = max(0, min(started - len(self.finished), self.workers))
                line = status_line(self.done, self.failed, running, self.jobs, self.walls, self.workers)
                out.append(line)
                print(line, file=self.stream or sys.stdout, flush=True)
            self.lines += out
            return out

    def _loop(self) -> None:
        while not self._stop.wait(self.interval):
            try:
                self.poll()
            except Exception:  # noqa: BLE001 - a status line is never worth a failed sweep
                pass

    def start(self) -> "SweepStatus":
        self._thread = threading.Thread(target=self._loop, name="dslearn-sweep-status", daemon=True)
        self._thread.start()
        return self

    def stop(self, final: bool = True) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        if final:
            try:
                self.poll()
            except Exception:  # noqa: BLE001
                pass


def interrupt_active() -> dict | None:
    """Stop the sweep running in this process (after Ctrl-C): its status poller and folder lock.
    Returns ``{"dir", "done", "jobs"}`` (``done``: the jobs whose folder holds a complete result), or
    ``None`` when no sweep is running."""
    global _ACTIVE
    cb, _ACTIVE = _ACTIVE, None
    if cb is None or cb._sweep_dir is None:
        return None
    if cb._status is not None:  # a job that finished before the interrupt still gets its status line
        cb._status.stop(final=True)
    if cb._lock is not None:
        cb._lock.release()
        cb._lock = None
    dirs = _job_dirs(cb._sweep_dir)
    jobs = cb._jobs if cb._jobs is not None else len(dirs)
    done = sum(1 for d in dirs if check_complete(d)[0] and (not d.name.isdigit() or int(d.name) < jobs))
    return {"dir": str(cb._sweep_dir), "done": done, "jobs": jobs}


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
        self._status: SweepStatus | None = None
        self._sweep_dir: Path | None = None
        self._jobs: int | None = None

    def __getstate__(self) -> dict:  # the launcher sends the callbacks to its workers: not the status thread
        return {**self.__dict__, "_status": None}

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
        global _ACTIVE
        self._sweep_dir, self._jobs = sweep_dir, _EXPECTED_JOBS
        workers = launcher_workers(config.hydra.launcher)
        launcher = str(config.hydra.launcher.get("_target_", "?")).rsplit(".", 1)[-1]
        jobs = f"{self._jobs} jobs" if self._jobs is not None else "jobs"
        log.info("sweep started: %s in %s (%s, %d at a time)", jobs, sweep_dir, launcher, workers)
        self._status = SweepStatus(sweep_dir, self._jobs, workers).start()
        _ACTIVE = self

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        global _ACTIVE
        if self._status is not None:  # the last jobs' lines before the summary
            self._status.stop()
            self._status = None
        _ACTIVE = None
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
