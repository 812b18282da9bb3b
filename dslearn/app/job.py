"""One job of ``dslearn-run`` (a single run, or one job of a sweep) in its output folder: the body of the
Hydra task (:func:`run_job`, called by :func:`dslearn.run._hydra_task`).

It holds the folder's lock (``.dslearn.lock``, with its pid; a single run's was taken by
:func:`dslearn.app.precheck.lock_run_dir` before Hydra started, a sweep's job takes its own), skips a
complete result when resuming (``resume=true``: :func:`dslearn.io.check_complete`, made with the same
overrides), runs :func:`dslearn.app.record.execute` and records the outcome in ``status.json``: a bad
configuration or data file, or a run too big for memory, is one line on stderr and exit code 2 (in a
sweep: the job fails, the others go on); Ctrl-C or SIGTERM records ``interrupted``."""

from __future__ import annotations

import json
import logging
import os
import sys
import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from dslearn.app.common import BUSY_KEYS, MAIN_PID, PRELOCKED, STATUS_FILE, log, say
from dslearn.app.record import _hydra_job, _write_status, execute
from dslearn.errors import ConfigError, DataFormatError


def _same_job(out_dir: Path, job: dict) -> bool:
    """Whether the result in ``out_dir`` was made with this job's overrides (runtime keys aside)."""
    from dslearn.callbacks import parse_overrides
    from dslearn.io import META_FILE

    try:
        meta = json.loads((out_dir / META_FILE).read_text())
    except (OSError, ValueError):  # unreadable, not UTF-8, not JSON
        return False
    if not isinstance(meta, dict) or meta.get("overrides") is None or "overrides" not in job:
        return isinstance(meta, dict)
    return parse_overrides(meta["overrides"]) == parse_overrides(job["overrides"])


def _progress_default() -> bool:
    """Bars on a terminal, off when stderr is not a TTY or the ``CI`` environment variable is set."""
    return sys.stderr.isatty() and not os.environ.get("CI")


def _describe(cfg: DictConfig, job: dict) -> str:
    """The run's (a sweep's job's) first line: task, study, seed, its overrides and which parts of a method preset
    they replace (:func:`~dslearn.schemas.base.preset_replaced`)."""
    parts = [f"task={cfg.task.name}", f"study={cfg.study}", f"seed={cfg.seed}"]
    if job.get("overrides"):
        parts.append("overrides: " + " ".join(job["overrides"]))
        from dslearn.schemas.base import preset_replaced

        swapped = preset_replaced(job["overrides"])
        if swapped:
            parts.append(swapped)
    return ", ".join(parts)


class Terminated(KeyboardInterrupt):
    """SIGTERM, turned into an interrupt so that the run records ``interrupted`` (exit 143)."""


def _on_sigterm(signum, frame):  # noqa: ARG001
    raise Terminated()


def _out_of_memory(e: BaseException) -> bool:
    return isinstance(e, MemoryError) or (isinstance(e, RuntimeError) and "can't allocate memory" in str(e))


def _progress_context(enabled: bool):
    """Log lines that do not break the progress bars (tqdm's logging redirect)."""
    if not enabled:
        import contextlib

        return contextlib.nullcontext()
    from tqdm.contrib.logging import logging_redirect_tqdm

    return logging_redirect_tqdm(loggers=[logging.getLogger()])


def run_job(cfg: DictConfig) -> dict:
    """One job of the Hydra app (the body of :func:`dslearn.run._hydra_task`): its folder locked, run, its
    status recorded; a dict ``status`` (``done | skipped | failed``), ``dir`` and, when done, ``rows``."""
    if os.environ.get(MAIN_PID, str(os.getpid())) != str(os.getpid()):
        # a launcher's worker process: Ctrl-C reaches the whole process group, and the sweep's own process
        # handles it (it stops the workers and prints the resume command); a worker interrupted mid-job
        # would only add its traceback
        import signal

        signal.signal(signal.SIGINT, signal.SIG_IGN)
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from dslearn.io import RunDirBusy, RunLock

    hc = HydraConfig.get()
    if hc.get("searchpath"):  # the user's config folders count in this process too (a launcher's worker)
        from dslearn.search_path import add_search_path

        add_search_path(list(hc.searchpath))
    out_dir = Path(hc.runtime.output_dir)
    multirun = hc.mode == RunMode.MULTIRUN
    job = _hydra_job()
    tag = f"job {job['job_num']}" if multirun and job.get("job_num") is not None else "run"
    t0 = time.perf_counter()
    held = PRELOCKED.get(os.path.abspath(out_dir))  # a single run: main() holds it already
    try:
        lock = held if held is not None else RunLock(out_dir).acquire()
    except RunDirBusy as e:  # not logged: the folder's run.log is its owner's
        say("run folder busy", f"{e} ({BUSY_KEYS})")
        raise SystemExit(2)
    try:
        return _run_locked(cfg, out_dir, multirun, job, tag, t0)
    except KeyboardInterrupt as e:
        what = "SIGTERM" if isinstance(e, Terminated) else "Ctrl-C"
        _write_status(out_dir, "interrupted", time.perf_counter() - t0, error=f"interrupted ({what})")
        log.warning("%s interrupted (%s); no results written", tag, what)
        if multirun:  # the sweep's process says the one line (with the resume command): on to it
            raise
        say("interrupted", f"{what}: no results written; {out_dir / STATUS_FILE} says interrupted")
        raise SystemExit(143 if isinstance(e, Terminated) else 130)
    finally:
        if held is None:
            lock.release()


def _run_locked(cfg: DictConfig, out_dir: Path, multirun: bool, job: dict, tag: str, t0: float) -> dict:
    from dslearn.io import RESULTS_FILE

    if cfg.get("progress") is None:  # a sweep's jobs show no bars: the sweep prints one status line per job
        OmegaConf.set_struct(cfg, False)
        cfg.progress = False if multirun else _progress_default()
        OmegaConf.set_struct(cfg, True)
    if cfg.get("resume"):
        from dslearn.io import check_complete

        ok, why = check_complete(out_dir)
        if ok and not _same_job(out_dir, job):
            ok, why = False, "it holds the result of other overrides (was the grid changed?)"
        if ok:
            log.info("%s: resume: %s is complete, skipping (%s)", tag, out_dir, _describe(cfg, job))
            _write_status(out_dir, "skipped", time.perf_counter() - t0)
            return {"status": "skipped", "dir": str(out_dir)}
        log.info("%s: resume: re-running %s (%s)", tag, out_dir, why)
    (out_dir / STATUS_FILE).unlink(missing_ok=True)  # an old status must not describe this run
    log.info("%s: starting %s -> %s", tag, _describe(cfg, job), out_dir)
    try:
        with _progress_context(bool(cfg.get("progress"))):
            df = execute(cfg, out_dir)
    except (ConfigError, DataFormatError) as e:
        kind = "configuration error" if isinstance(e, ConfigError) else "data error"
        log.error("%s: %s", kind, e)
        say(kind, e)
        _write_status(out_dir, "failed", time.perf_counter() - t0, error=f"{type(e).__name__}: {e}", config_error=True)
        if multirun:  # the sweep goes on; the sweep summary counts it and the exit code is 2
            return {"status": "failed", "dir": str(out_dir), "config_error": True}
        raise SystemExit(2)
    except Exception as e:
        if _out_of_memory(e):
            msg = (f"out of memory ({type(e).__name__}: {' '.join(str(e).split())[:200]}); make the run smaller "
                   "(episodes, horizon, agents, nodes) or run it on a machine with more memory")
            log.error("%s", msg)
            say("resource error", msg)
            _write_status(out_dir, "failed", time.perf_counter() - t0, error=msg, config_error=True)
            if multirun:
                return {"status": "failed", "dir": str(out_dir), "config_error": True}
            raise SystemExit(2)
        log.exception("%s failed: %s", tag, e)
        _write_status(out_dir, "failed", time.perf_counter() - t0, error=f"{type(e).__name__}: {e}")
        if multirun:  # keep the other jobs; the sweep ends with exit code 1 after gathering
            return {"status": "failed", "dir": str(out_dir)}
        raise
    wall = time.perf_counter() - t0
    _write_status(out_dir, "done", wall, rows=len(df))
    if cfg.get("print_table", True) and not multirun:
        from dslearn.report import console_table, summarize

        print(console_table(summarize(df)))
        print(f"results: {out_dir / RESULTS_FILE}")
    log.info("%s summary: done, %d rows, wall %.1fs, results %s", tag, len(df), wall, out_dir / RESULTS_FILE)
    if not multirun:  # the next step: the run's tables and figures
        print(f"next: dslearn-report {out_dir}", flush=True)
    return {"status": "done", "dir": str(out_dir), "rows": len(df)}
