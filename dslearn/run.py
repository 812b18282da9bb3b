"""``dslearn-run``: the Hydra app. One run = one task configuration -> ``results.csv``.

Every run writes, in its output directory: ``config.yaml`` (resolved config), ``meta.json``
(package version, git commit, library versions, seed, overrides, wall time, jitter counts, and
the completeness marker: the row count and SHA-256 of ``results.csv``), then — last, atomically —
``results.csv``, and finally ``status.json`` (``done | skipped | failed | interrupted``, read by
the sweep summary). An interrupted or failed run leaves no ``results.csv`` (or one whose hash
does not match). While a run works in a folder it holds the folder's lock (``.dslearn.lock``,
with its pid): a second run into the same folder is refused before it writes anything there (a
single run's lock is taken before Hydra starts, :func:`lock_run_dir`; a sweep's in its
``on_multirun_start``); a dead owner's lock is taken over.

Resume: ``dslearn-run -m ... hydra.sweep.dir=DIR resume=true`` (or ``hydra.run.dir=DIR
resume=true`` for one run) skips every job whose directory already holds a complete result
(:func:`dslearn.io.check_complete`) and re-runs missing or broken ones. The default sweep dir
contains a timestamp, so resuming needs the same fixed ``hydra.sweep.dir`` both times.

Before Hydra starts anything, :func:`precheck` composes and validates the configuration of every
job the command line asks for (each combination of a sweep, including an experiment's
``hydra.sweeper.params``), and checks the output folder and the launcher plugin.

Exit codes: 0 ok; 2 bad input (configuration, data file, busy run folder, too big for memory:
one line on stderr, ``dslearn-run: <what>: <message>``); 130 interrupted (Ctrl-C); 1 other
failure (in a sweep: after every job has run and the table of the finished ones is gathered).
"""

from __future__ import annotations

import os
import signal
import sys


def _interrupted_at_start(signum, frame):  # noqa: ARG001
    os.write(2, b"dslearn-run: interrupted: Ctrl-C before the run started; nothing was written\n")
    os._exit(130)


# Ctrl-C while the console script imports this module: one line and exit 130, not a traceback (main()
# takes over with its own handling; a module imported by other code keeps the interpreter's handler)
_SIGINT_BEFORE = None
if __name__ == "__main__" or os.path.basename(sys.argv[0] if sys.argv else "") == "dslearn-run":
    try:
        _SIGINT_BEFORE = signal.signal(signal.SIGINT, _interrupted_at_start)
    except (ValueError, OSError):  # not the main thread
        _SIGINT_BEFORE = None

import copy  # noqa: E402
import datetime as _dt
import importlib
import json
import logging
import platform
import re
import subprocess
import time
import warnings
from pathlib import Path

# known harmless third-party warnings (set before gpytorch is imported anywhere):
# gpytorch 1.11+ decorates with torch.jit.script, which torch >= 2.5 marks deprecated
warnings.filterwarnings("ignore", message=r".*torch\.jit\.script.* is deprecated", category=DeprecationWarning)
warnings.filterwarnings("ignore", message=r".*torch\.jit\.script.* is deprecated", category=FutureWarning)

# Start-up cost: this module imports only the standard library and dslearn's light root modules, so
# that --help, --version, a refused option and a completion request answer at once; Hydra, pandas
# and the schemas (which import PyTorch, GPyTorch and numba) are imported where work starts
# (benchmarks/startup.py measures it; tests/test_startup.py keeps it so).
from dslearn import __version__  # noqa: E402
from dslearn.conf_paths import CONF_DIR as _CONF_DIR, CONF_DIRS  # noqa: E402
from dslearn.errors import ConfigError, DataFormatError  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402  (light: ~0.1 s)

log = logging.getLogger("dslearn.run")
CONF_DIR = str(_CONF_DIR)
#: run folder (absolute) -> the lock :func:`main` took on it before Hydra started (a single run)
_PRELOCKED: dict[str, RunLock] = {}
#: the keys that choose the run folder, named when it is busy
_BUSY_KEYS = "hydra.run.dir / hydra.sweep.dir"
#: the command line as the user gave it (recorded in meta.json; Hydra may get a resolved run folder)
_USER_ARGV: list[str] | None = None
STATUS_FILE = "status.json"
PROG = "dslearn-run"


def resolve_entry(entry: str):
    """A registered study entry (``"pkg.module:function"``, one of
    :data:`dslearn.schemas.core.TASK_TARGETS`: a study not yet built as a component) -> the function."""
    from dslearn.schemas.core import check_target

    check_target(entry, "entry")
    mod, fn = entry.split(":", 1)
    try:
        return getattr(importlib.import_module(mod), fn)
    except (ImportError, AttributeError) as e:
        raise ConfigError(f"task.entry={entry!r} cannot be imported: {e}") from None


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


# --------------------------------------------------------------------------------------------
# one run


def execute(cfg: DictConfig, out_dir: str | Path) -> pd.DataFrame:
    """Validate ``cfg``, run its task and write the result files into ``out_dir``. Returns the results.

    Raises :class:`ConfigError` (before any work) for a bad configuration.
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
        if "_target_" in cfg.task:  # a component: the composition root fills its slots
            from dslearn.compose import build_study

            df = build_study(cfg).run(diagnostics=diag, progress=progress)
        else:
            import inspect

            fn = resolve_entry(cfg.task.entry)
            df = fn(cfg, diagnostics=diag) if "diagnostics" in inspect.signature(fn).parameters else fn(cfg)
    wall = time.perf_counter() - t0
    what = cfg.task.get("_target_") or cfg.task.get("entry")
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
        "argv": list(_USER_ARGV) if _USER_ARGV is not None else sys.argv[1:],
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


def _say(kind: str, msg: str) -> None:
    """The one line a user sees on stderr."""
    print(f"{PROG}: {kind}: {' '.join(str(msg).split())}", file=sys.stderr, flush=True)


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


def _app() -> None:
    """The Hydra application (Hydra, and the schemas its configs name, are imported here: where work starts)."""
    import hydra

    import dslearn.schemas  # noqa: F401  (registers the schemas the task configs name in Hydra's ConfigStore)

    hydra.main(version_base=None, config_path=CONF_DIR, config_name="config")(_hydra_task)()


def _hydra_task(cfg: DictConfig) -> dict:
    if os.environ.get(_MAIN_PID, str(os.getpid())) != str(os.getpid()):
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
    held = _PRELOCKED.get(os.path.abspath(out_dir))  # a single run: main() holds it already
    try:
        lock = held if held is not None else RunLock(out_dir).acquire()
    except RunDirBusy as e:  # not logged: the folder's run.log is its owner's
        _say("run folder busy", f"{e} ({_BUSY_KEYS})")
        raise SystemExit(2)
    try:
        return _run_locked(cfg, out_dir, multirun, job, tag, t0)
    except KeyboardInterrupt as e:
        what = "SIGTERM" if isinstance(e, Terminated) else "Ctrl-C"
        _write_status(out_dir, "interrupted", time.perf_counter() - t0, error=f"interrupted ({what})")
        log.warning("%s interrupted (%s); no results written", tag, what)
        if multirun:  # the sweep's process says the one line (with the resume command): on to it
            raise
        _say("interrupted", f"{what}: no results written; {out_dir / STATUS_FILE} says interrupted")
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
        _say(kind, e)
        _write_status(out_dir, "failed", time.perf_counter() - t0, error=f"{type(e).__name__}: {e}", config_error=True)
        if multirun:  # the sweep goes on; the sweep summary counts it and the exit code is 2
            return {"status": "failed", "dir": str(out_dir), "config_error": True}
        raise SystemExit(2)
    except Exception as e:
        if _out_of_memory(e):
            msg = (f"out of memory ({type(e).__name__}: {' '.join(str(e).split())[:200]}); make the run smaller "
                   "(episodes, horizon, agents, nodes) or run it on a machine with more memory")
            log.error("%s", msg)
            _say("resource error", msg)
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


# --------------------------------------------------------------------------------------------
# start-up check: compose the command line's configuration(s) before Hydra starts any job


_NO_CHECK_FLAGS = {"--hydra-help", "--cfg", "-c", "--info", "-i",
                   "--shell-completion", "-sc", "--resolve", "--package", "-p", "--config-name", "-cn",
                   "--config-path", "-cp", "--config-dir", "-cd", "--experimental-rerun"}
_MULTIRUN_FLAGS = {"-m", "--multirun"}
#: Hydra launcher option -> (plugin module, dslearn extra that installs it)
LAUNCHERS = {
    "basic": (None, None),
    "joblib": ("hydra_plugins.hydra_joblib_launcher", "joblib"),
    "ray": ("hydra_plugins.hydra_ray_launcher", "ray"),
    "submitit_local": ("hydra_plugins.hydra_submitit_launcher", "slurm"),
    "submitit_slurm": ("hydra_plugins.hydra_submitit_launcher", "slurm"),
}


def _plugin_installed(module: str) -> bool:
    import importlib.util

    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def _check_launcher(option: str) -> None:
    if option not in LAUNCHERS:
        raise ConfigError(f"hydra/launcher={option!r} is not a known launcher; choose one of {sorted(LAUNCHERS)}")
    module, extra = LAUNCHERS[option]
    if module is not None and not _plugin_installed(module):
        raise ConfigError(
            f"hydra/launcher={option} needs the Hydra plugin {module.split('.')[-1]}, which is not installed; "
            f'install it with: pip install "dslearn[{extra}]"'
        )


def _check_output_dir(key: str, value: str) -> None:
    """``hydra.run.dir`` / ``hydra.sweep.dir``: a folder that can be created (not a file)."""
    if "${" in value:
        return
    p = Path(value).expanduser()
    if p.exists() and not p.is_dir():
        raise ConfigError(f"{key}={value} is an existing file, not a folder; choose a folder for the outputs")
    parent = p
    while not parent.exists():
        if parent.parent == parent:
            break
        parent = parent.parent
    if parent.exists() and not parent.is_dir():
        raise ConfigError(f"{key}={value}: {parent} is a file, so the folder cannot be created")
    if parent.exists() and not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(f"{key}={value}: {parent} is not writable")


def _group_options(group: str) -> list[str]:
    return sorted({p.stem for d in CONF_DIRS for p in (d / group).glob("*.yaml")})


def _is_group(key: str) -> bool:
    return any((d / key).is_dir() for d in CONF_DIRS) or key == "schema"


def _user_search_dirs(value) -> list[Path]:
    """The folders of a ``hydra.searchpath=[...]`` override (:func:`dslearn.search_path.user_search_dirs`)."""
    from dslearn.search_path import user_search_dirs

    return user_search_dirs(value)


#: (group, a name users try) -> (the option meant, what it is): names from the papers that are not file names
ALIASES = {
    ("filter", "ekf"): ("default", "the extended information filter (EKF)"),
    ("filter", "eif"): ("default", "the extended information filter (EKF)"),
    ("filter", "unscented"): ("ukf", "the unscented filter"),
}


def did_you_mean(word: str, choices, n: int = 3) -> list[str]:
    """The ``choices`` closest to ``word`` (a misspelling), best first (none when nothing is close)."""
    import difflib

    choices = [str(c) for c in choices]
    close = difflib.get_close_matches(str(word), choices, n=n, cutoff=0.6)
    if not close:  # a prefix or a part of a name (``gp_incr``, ``increment``)
        w = str(word).lower()
        close = [c for c in choices if len(w) >= 3 and (c.lower().startswith(w) or w in c.lower())][:n]
    return close


def _check_group_option(group: str, option) -> None:
    opts = _group_options(group)
    if not opts or not isinstance(option, str):
        return
    if str(option) not in opts:
        hint = ""
        alias = ALIASES.get((group, str(option).lower()))
        if alias is not None and alias[0] in opts:
            hint = f"; {alias[1]} is {group}={alias[0]}"
        else:
            close = did_you_mean(str(option), opts)
            if close:
                hint = "; did you mean " + " or ".join(f"{group}={c}" for c in close) + "?"
        raise ConfigError(f"{group}={option!r} is not an option of the config group '{group}'; "
                          f"choose one of {opts}{hint}")


def _sweep_values(o) -> list:
    """The values of a choice sweep override (``group=a,b``), ``[]`` for other sweeps (range, glob)."""
    try:
        from hydra.core.override_parser.types import ChoiceSweep

        v = o.value()
        return [str(x) for x in v.list] if isinstance(v, ChoiceSweep) else []
    except Exception:  # noqa: BLE001
        return []


def _hydra_message(e: Exception) -> str:
    msg = " ".join(str(e).split()).split(" Config search path:")[0]
    cause = e.__cause__
    if cause is not None and str(cause).strip() and str(cause).split("\n")[0] not in msg:
        msg += ": " + str(cause).split("\n")[0]
    return msg or type(e).__name__


class _Composer:
    """Compose the configuration of many jobs cheaply (a Hydra compose costs ~0.3-0.6 s).

    The group choices every job shares are composed once (the base). A group choice that
    varies is composed once per option on top of the base; where it changes only its own
    group's node (checked against the base), that node is swapped into a copy of the base for
    each job; otherwise the job's group choices are composed in full (once per distinct set).
    Value overrides (``key=value``) are then applied with Hydra's own routine, so every job's
    configuration is exactly what Hydra composes for it."""

    def __init__(self, compose, base: tuple[str, ...]):
        self._compose = compose
        self.base = base
        self._full: dict[tuple, DictConfig] = {}
        self._single: dict[str, tuple | None] = {}
        self._jobs: dict[tuple, DictConfig] = {}
        self.composes = 0

    def full(self, groups: tuple[str, ...]) -> DictConfig:
        if groups not in self._full:
            self.composes += 1
            self._full[groups] = self._compose(list(groups))
        return self._full[groups]

    def config(self, varying: list, all_lines: list[str]) -> DictConfig:
        """The (cached, shared: do not modify) config of a job's group choices."""
        key = tuple(all_lines)
        if key in self._jobs:
            return self._jobs[key]
        base = self.full(self.base)
        swaps = []
        for line, o in varying:
            node = self._swap(base, line, o)
            if node is None:
                self._jobs[key] = self.full(key)
                return self._jobs[key]
            swaps.append(node)
        if not swaps:
            cfg = base
        else:
            # copy the base without the nodes about to be replaced, then put the options' nodes in
            cfg = _copy_without(base, {k for k, _ in swaps})
            with _open(cfg):
                for k, value in swaps:
                    if value is not None:
                        cfg[k] = copy.deepcopy(value)
        self._jobs[key] = cfg
        return cfg

    def _swap(self, base, line, o):
        if line not in self._single:
            key = o.key_or_group
            res = None
            if o.package is None and "/" not in key and not o.is_delete():
                one = self.full(self.base + (line,))
                keys = (set(base.keys()) | set(one.keys())) - {key}
                if all(key_equal(base, one, kk) for kk in keys):
                    res = (key, one._get_node(key) if key in one else None)
            self._single[line] = res
        return self._single[line]


def _scalar_changes(values: list, cfg: DictConfig) -> list | None:
    """For overrides that only change existing scalar leaves: ``(parent, leaf, old raw value)``
    per override, to undo them; ``None`` when any override adds, deletes or sets a container."""
    undo = []
    for o in values:
        if o.is_delete() or o.is_add() or o.is_force_add() or o.package is not None:
            return None
        v = o.value()
        if isinstance(v, (dict, list)) or o.is_sweep_override():
            return None
        key = o.key_or_group
        parent_key, _, leaf = key.rpartition(".")
        parent = OmegaConf.select(cfg, parent_key, throw_on_missing=False) if parent_key else cfg
        if not isinstance(parent, DictConfig) or leaf not in parent:
            return None
        node = parent._get_node(leaf)
        if node is None or OmegaConf.is_config(node) or not type(node).__name__ == "AnyNode":
            return None
        undo.append((parent, leaf, node._value()))
    return undo


def _copy_without(cfg: DictConfig, skip: set) -> DictConfig:
    """A deep copy of ``cfg`` without its top-level keys in ``skip`` (``cfg`` is unchanged)."""
    content = cfg.__dict__.get("_content")
    if not skip or not isinstance(content, dict):
        out = copy.deepcopy(cfg)
        with _open(out):
            for k in skip:
                out.pop(k, None)
        return out
    orig = dict(content)
    for k in skip:
        content.pop(k, None)
    try:
        return copy.deepcopy(cfg)
    finally:
        content.clear()
        content.update(orig)


class _open:
    def __init__(self, cfg):
        self.cfg = cfg

    def __enter__(self):
        self.flag = OmegaConf.is_struct(self.cfg)
        OmegaConf.set_struct(self.cfg, False)

    def __exit__(self, *exc):
        OmegaConf.set_struct(self.cfg, self.flag)


def key_equal(a: DictConfig, b: DictConfig, key: str) -> bool:
    if (key in a) != (key in b):
        return False
    if key not in a:
        return True
    va, vb = a._get_node(key), b._get_node(key)
    try:
        ca = OmegaConf.to_container(va, resolve=False) if OmegaConf.is_config(va) else va._value()
        cb = OmegaConf.to_container(vb, resolve=False) if OmegaConf.is_config(vb) else vb._value()
    except Exception:  # noqa: BLE001
        return False
    return ca == cb


_PARSED: dict[str, object] = {}


def parse_override(line: str):
    """One command-line override parsed by Hydra's parser (memoised: parsing a long list value
    costs seconds, and a line is parsed several times on the way)."""
    if line not in _PARSED:
        from hydra.core.override_parser.overrides_parser import OverridesParser

        if len(_PARSED) > 10000:
            _PARSED.clear()
        _PARSED[line] = OverridesParser.create().parse_overrides([line])[0]
    return _PARSED[line]


def _parse_all(lines: list[str]) -> list:
    return [parse_override(x) for x in lines]


def _is_group_override(o) -> bool:
    return o.package is not None or _is_group(o.key_or_group)


def sweep_combinations(argv: list[str]) -> tuple[list[list[str]], bool, DictConfig | None]:
    """The job override lists a command line runs, whether it is a multirun, and the master
    config it was decided on (group choices and Hydra's own overrides, with ``hydra``). A
    multirun includes an experiment's ``hydra.sweeper.params`` as Hydra's basic sweeper does
    (command-line values of the same key win). Needs an initialised Hydra
    (``initialize_config_dir``)."""
    from hydra.core.global_hydra import GlobalHydra
    from hydra.types import RunMode

    import dslearn.schemas  # noqa: F401  (the task configs name the schemas' ConfigStore entries)

    overrides = [a for a in argv if not a.startswith("-")]
    parsed = _parse_all(overrides)
    user = [o for o in parsed if not o.key_or_group.startswith("hydra")]
    flag = any(a in _MULTIRUN_FLAGS for a in argv)
    sweeps = [o.input_line for o in user if o.is_sweep_override()]
    # the master config only tells the mode and the sweeper's params: compose it from the group
    # choices and Hydra's own overrides (a bad value override is reported per job, with context)
    head = [o.input_line for o in parsed if o.key_or_group.startswith("hydra") or _is_group_override(o)]
    cl = GlobalHydra.instance().config_loader()
    master = cl.load_configuration("config", head, run_mode=RunMode.MULTIRUN, validate_sweep_overrides=False)
    multirun = flag or master.hydra.get("mode") == RunMode.MULTIRUN
    if not multirun:
        if sweeps:
            raise ConfigError(
                f"{sweeps[0]} is a sweep (one job per value); add -m (--multirun) to run them, "
                f"or write {sweeps[0].split('=', 1)[0]}=[a,b] for a list value"
            )
        return [[o.input_line for o in user]], False, master
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper

    params = [f"{k}={v}" for k, v in (master.hydra.sweeper.get("params") or {}).items()]
    allp = [o for o in _parse_all(params) if not o.key_or_group.startswith("hydra")] + user
    combos = BasicSweeper.split_arguments(allp, None)[0] if allp else [[]]
    return combos, True, master


def check_jobs(combos: list[list[str]], compose, visit=None) -> tuple[int, int]:
    """Validate every job's configuration; ConfigError naming the job on the first bad one.
    ``compose(overrides)`` composes one configuration (Hydra's ``compose``); ``visit(cfg)``
    (default :func:`validate_job`) is called with each job's configuration, which is only valid
    during the call, and with the job's override lines as ``lines=`` where it takes them.
    Returns ``(jobs checked, full compositions made)``."""
    import inspect

    from hydra._internal.config_loader_impl import ConfigLoaderImpl

    visit = visit or validate_job
    try:
        takes_lines = "lines" in inspect.signature(visit).parameters
    except (TypeError, ValueError):
        takes_lines = False
    many = len(combos) > 1
    split = []
    for i, combo in enumerate(combos):
        where = f" (sweep job {i}: {' '.join(combo)})" if many else ""
        try:
            parsed = _parse_all(list(combo))
        except Exception as e:  # noqa: BLE001
            raise ConfigError(f"{_friendly(e)}{where}") from None
        groups, values = [], []
        for line, o in zip(combo, parsed):
            if _is_group_override(o):
                if not o.is_delete():
                    try:
                        _check_group_option(o.key_or_group, o.value())
                    except ConfigError as e:
                        raise ConfigError(f"{e}{where}") from None
                groups.append((line, o))
            else:
                values.append(o)
        split.append((groups, values, where))
    constant = [g for g in split[0][0] if all(g[0] in {x[0] for x in s[0]} for s in split)] if split else []
    composer = _Composer(compose, tuple(g[0] for g in constant))
    const_lines = {g[0] for g in constant}
    for (groups, values, where), combo in zip(split, combos):
        cfg = None
        job_visit = (lambda c, _lines=list(combo): visit(c, lines=_lines)) if takes_lines else visit
        try:
            cfg = composer.config([g for g in groups if g[0] not in const_lines], [g[0] for g in groups])
            undo = _scalar_changes(values, cfg)
            if undo is None:  # adds, deletes, containers: on a copy
                cfg = copy.deepcopy(cfg)
                ConfigLoaderImpl._apply_overrides_to_config(values, cfg)
                job_visit(cfg)
            else:  # plain key=scalar changes: in place, undone afterwards (no copy: ~10 ms a job)
                try:
                    ConfigLoaderImpl._apply_overrides_to_config(values, cfg)
                    job_visit(cfg)
                finally:
                    for parent, leaf, old in reversed(undo):
                        with _open(parent):
                            parent[leaf] = old
        except ConfigError as e:
            raise ConfigError(f"{e}{where}") from None
        except Exception as e:  # noqa: BLE001 - Hydra/OmegaConf composition errors
            raise ConfigError(f"{_friendly(e, cfg)}{where}") from None
    return len(combos), composer.composes


def override_keys(lines) -> list[tuple[str, str]]:
    """``(key, line)`` of each override line that sets the configuration (``consensus=ci`` ->
    ``consensus``, ``+consensus.x=1`` / ``~consensus.x`` -> ``consensus.x``); Hydra's own keys and
    options written into another package (``group@pkg=option``) are left out."""
    out = []
    for line in lines:
        o = parse_override(line)
        key = o.key_or_group
        if key.startswith("hydra") or o.package is not None:
            continue
        out.append((key, line))
    return out


def validate_job(cfg: DictConfig, lines=()) -> None:
    """One job's whole check: :func:`~dslearn.schemas.core.validate_config`, after refusing an
    override (of the job's ``lines``: command line and sweep) of a root group its task does not
    read, or of a task key its configuration does not read
    (:func:`~dslearn.schemas.base.check_overrides`)."""
    from dslearn.schemas.base import check_overrides
    from dslearn.schemas.core import validate_config

    if lines and "task" in cfg and cfg.task is not None and cfg.task.get("name") is not None:
        check_overrides(cfg, override_keys(lines))
        from dslearn.studies.matrix import check_method_chosen

        check_method_chosen(cfg, [k for k, _ in override_keys(lines)])
    validate_config(cfg)
    device = cfg.get("device")
    if device is not None and str(device).startswith("cuda"):  # here, not in the run: no run folder for it
        from dslearn.compose import resolve_device

        resolve_device(str(device))


def sweep_select(master: DictConfig):
    """The function by which the sweep's sweeper chooses the combinations that become jobs (its ``select``
    key, e.g. ``hydra/sweeper=matrix``: :func:`dslearn.schemas.matrix.select_cells`, the cells whose method
    fits the scenario), ``None`` for a sweeper that runs every combination."""
    name = OmegaConf.select(master, "hydra.sweeper.select", default=None)
    if not name:
        return None
    from dslearn.compose import import_object

    return import_object(name, "hydra.sweeper.select")


#: the root groups and keys of task ``liu_dgpt`` that became its own keys (:func:`_moved`)
MOVED = {
    "tracker": ("task.tracker", "{}"),
    "aggregation": ("task.aggregations", "[{}]"),
    "gp_input": ("task.gp_input", "{}"),
    "noise": ("task.noises", "[{}]"),
}


def _moved(o) -> str | None:
    """The message for an override of a group / key that moved into task ``liu_dgpt`` (or None)."""
    key = o.key_or_group
    if key not in MOVED or _is_group(key) or o.is_delete() or o.package is not None:
        return None
    new_key, form = MOVED[key]
    try:
        vals = list(o.sweep_string_iterator()) if o.is_sweep_override() else [o.get_value_element_as_str()]
    except Exception:  # noqa: BLE001 - e.g. a range sweep: show the value as written
        vals = [o.input_line.split("=", 1)[-1]]
    new = f"{new_key}=" + ",".join(form.format(v) for v in vals)
    return f"{o.input_line}: {key} is no longer a root group or key; it is a key of task=liu_dgpt: write {new}"


def _friendly(e: Exception, cfg: DictConfig | None = None) -> str:
    msg = _hydra_message(e)
    m = re.search(r"Could not override '([^']+)'", msg)
    if m:
        key = m.group(1)
        return _unknown_key(key, cfg)
    return msg


def _unknown_key(key: str, cfg) -> str:
    """An override of a key the configuration does not have: the closest keys (full paths, each a
    working override) and the keys that are there. No ``+key`` is suggested: the schemas refuse keys
    they do not define, so adding one would fail too."""
    parent, _, leaf = key.rpartition(".")
    node = None
    if cfg is not None:
        try:
            node = OmegaConf.select(cfg, parent, default=None) if parent else cfg
        except Exception:  # noqa: BLE001
            node = None
    if not isinstance(node, DictConfig):
        return f"{key}: no such key in the configuration"
    keys = sorted(str(k) for k in node.keys())
    where = f" of {parent}" if parent else ""
    close = did_you_mean(leaf, [k for k in keys if k != "hydra"])
    hint = ("; did you mean " + " or ".join(f"{parent + '.' if parent else ''}{c}=..." for c in close) + "?"
            if close else "")
    return f"{key}: no such key in the configuration (known keys{where}: {keys}){hint}"


def precheck(argv: list[str], plan: dict | None = None) -> str | None:
    """Compose and validate the configuration the command line asks for; the error line or ``None``.

    Sweep overrides (``a=1,2``, ``range(...)``) and an experiment's sweep parameters are expanded
    and every combination is checked (:func:`~dslearn.schemas.core.validate_config`, which also
    builds the core study's parts), so a bad value anywhere in a sweep fails before its first
    job runs; a combination that the sweep's sweeper drops (``hydra/sweeper=matrix``: a method that does
    not fit the scenario, :func:`sweep_select`) is no job.
    ``hydra.run.dir`` / ``hydra.sweep.dir`` must name a folder (or a place one can be made) and the
    chosen launcher's plugin must be installed. Options that Hydra handles itself
    (``--cfg``, ``--info``, ...) skip the check. For a single run, ``plan["run_dir"]`` is set to
    its output folder (``hydra.run.dir`` resolved; absent when it cannot be resolved here).
    """
    if any(a.split("=")[0] in _NO_CHECK_FLAGS for a in argv):
        return None
    overrides = [a for a in argv if not a.startswith("-")]
    try:
        from hydra import compose, initialize_config_dir

        parsed = []
        for line in overrides:
            try:
                parsed.append(parse_override(line))
            except Exception as e:  # noqa: BLE001
                msg = _hydra_message(e).split(" See https://hydra.cc")[0]
                return (f"{line}: not a valid override ({msg}); write key=value, group=option, +key=value "
                        "to add, or key=a,b with -m to sweep")
        for o in parsed:  # user config folders first: their groups and options count in the checks below
            if o.key_or_group == "hydra.searchpath" and not o.is_delete():
                from dslearn.search_path import add_search_path

                add_search_path(o.value())  # and every composition below gets the same search path
        for o in parsed:
            moved = _moved(o)
            if moved is not None:
                return moved
            if o.key_or_group in ("hydra.run.dir", "hydra.sweep.dir"):
                _check_output_dir(o.key_or_group, str(o.value()))
            if o.key_or_group == "hydra/launcher":
                _check_launcher(str(o.value()))
            elif o.key_or_group.startswith("hydra/"):
                continue
            elif _is_group(o.key_or_group) and not o.is_delete():
                for v in (_sweep_values(o) if o.is_sweep_override() else [o.value()]):
                    _check_group_option(o.key_or_group, v)
        # the cheap checks are done: now the task schemas (they import PyTorch) and the composition
        import dslearn.schemas  # noqa: F401  (registers the schemas the task configs name in Hydra's ConfigStore)

        with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
            combos, multirun, master = sweep_combinations(argv)
            seeded = {}
            if not multirun:  # one job: its group choices are the master's; reuse that composition
                groups = tuple(o.input_line for o in _parse_all(combos[0]) if _is_group_override(o))
                seeded[groups] = master

            from dslearn.search_path import search_overrides

            def _compose(ov):  # each job with the user's search path (Hydra applies it per composition)
                key = tuple(ov)
                return seeded.pop(key) if key in seeded else compose("config", overrides=[*search_overrides(), *ov])

            select = sweep_select(master) if multirun else None
            if select is not None:  # the sweeper's choice (the matrix: the cells that fit); the others are no jobs
                composed = {}

                def _compose(ov, _plain=_compose):  # each combination composed once for both checks
                    key = tuple(ov)
                    if key not in composed:
                        composed[key] = _plain(ov)
                    return composed[key]

                combos = select(combos, _compose)[0]

            def _visit(cfg, lines=()):
                validate_job(cfg, lines)
                if plan is not None and not multirun:
                    where = _resolved_run_dir(cfg)
                    if where is not None:
                        plan["run_dir"] = where

            check_jobs(combos, _compose, visit=_visit)
            if plan is not None and multirun:  # the sweep's job count: its overall status line counts to it
                plan["jobs"] = len(combos)
    except ConfigError as e:
        return str(e)
    except Exception as e:  # Hydra/OmegaConf composition errors: unknown key, group option, type
        return _friendly(e)
    return None


def _resolved_run_dir(cfg: DictConfig) -> str | None:
    """``hydra.run.dir`` of a composed job configuration, resolved (``None`` if it cannot be here)."""
    try:
        d = OmegaConf.select(cfg, "hydra.run.dir", throw_on_missing=True)
    except Exception:  # noqa: BLE001 - e.g. ${hydra:...}, only known inside the app
        return None
    return None if d is None or not str(d) else str(d)


_BARE_PATH = re.compile(r"[A-Za-z0-9_./:+@%~-]+")


def _run_dir_override(run_dir: str, key: str = "hydra.run.dir") -> str | None:
    """``<key>=<run_dir>`` as an override Hydra parses back to exactly ``run_dir`` (or ``None``)."""
    if "${" in run_dir:
        return None
    quoted = "'" + run_dir.replace("\\", "\\\\").replace("'", "\\'") + "'"
    for value in ([run_dir] if _BARE_PATH.fullmatch(run_dir) else []) + [quoted]:
        line = f"{key}={value}"
        try:
            if str(parse_override(line).value()) == run_dir:
                return line
        except Exception:  # noqa: BLE001
            continue
    return None


def lock_run_dir(argv: list[str], run_dir: str | None) -> tuple[list[str], RunLock | None]:
    """Take a single run's folder lock before Hydra starts: Hydra writes ``.hydra/`` and opens
    ``run.log`` in the folder before the task runs, so a run refused as busy must be refused
    here to leave an existing run folder untouched. Where ``hydra.run.dir`` was not given as a
    plain path (the default has a timestamp), Hydra gets the resolved folder as an override, so
    that it writes where the lock is. Returns Hydra's command line and the lock (``None``: not
    resolvable here; the app then locks the folder itself). Raises :class:`RunDirBusy`."""
    if run_dir is None:
        return argv, None
    given = []
    for i, a in enumerate(argv):
        if not a.startswith("-"):
            try:
                if parse_override(a).key_or_group == "hydra.run.dir":
                    given.append(i)
            except Exception:  # noqa: BLE001
                continue
    out = list(argv)
    if not given or "${" in argv[given[-1]]:
        line = _run_dir_override(run_dir)
        if line is None:
            return argv, None
        out = [a for i, a in enumerate(argv) if i not in given] + [line]
    from dslearn.io import RunLock

    lock = RunLock(run_dir).acquire()
    _PRELOCKED[os.path.abspath(run_dir)] = lock
    return out, lock


# --------------------------------------------------------------------------------------------
# --help and --version


def _first_comment(path: Path) -> str:
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError):
        return ""
    for ln in lines:  # the first whole-line comment (not a package directive)
        s = ln.strip()
        if s.startswith("#"):
            text = s.lstrip("#").strip()
            if text and not text.startswith("@package"):
                return text
    # no leading comment: the option's own keys, compactly
    try:
        c = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    except Exception:  # noqa: BLE001
        return ""
    if not isinstance(c, dict):
        return ""
    items = [f"{k}={v}" for k, v in c.items() if k != "defaults" and not isinstance(v, (dict, list))]
    return ", ".join(items)


def _defaults() -> dict[str, str]:
    try:
        d = OmegaConf.to_container(OmegaConf.load(Path(CONF_DIR) / "config.yaml").get("defaults", []))
    except Exception:  # noqa: BLE001
        return {}
    out = {}
    for item in d or []:
        if isinstance(item, dict):
            for k, v in item.items():
                out[str(k)] = str(v)
    return out


def help_text(width: int = 100) -> str:
    """``dslearn-run --help``: config groups and experiments, one line each, sweeps, outputs."""
    conf = Path(CONF_DIR)
    defaults = _defaults()

    def line(name: str, text: str, indent: int = 4, col: int = 22) -> str:
        head = " " * indent + name
        head = head + " " * max(1, col - len(head))
        room = max(20, width - len(head))
        return head + (text if len(text) <= room else text[: room - 3] + "...")

    out = [
        f"{PROG} {__version__}: run one study configuration, or a sweep of them; every run writes results.csv.",
        "",
        "usage:",
        f"  {PROG} experiment=<name> [key=value ...]      a paper's study (list below)",
        f"  {PROG} [group=option ...] [key=value ...]     one run of the default study (Yu et al., synthetic)",
        f"  {PROG} -m key=a,b group=x,y ...              a sweep: one job per combination",
        "",
        "experiments (experiment=<name>):",
    ]
    for p in sorted((conf / "experiment").glob("*.yaml")):
        out.append(line(p.stem, _first_comment(p), 2))
    out += ["", "config groups (group=option; * = default):"]
    for g in sorted(d.name for d in conf.iterdir() if d.is_dir() and d.name != "experiment" and not d.name.startswith("_")):
        out.append(f"  {g}:")
        for p in sorted((conf / g).glob("*.yaml")):
            mark = "*" if defaults.get(g) == p.stem else " "
            out.append(line(f"{mark} {p.stem}", _first_comment(p), 4))
    out += ["", "top-level keys (key=value):"]
    try:
        for ln in (conf / "config.yaml").read_text(encoding="utf-8").splitlines():
            m = re.match(r"^([a-z_]+):\s*([^#]*?)\s*(?:#\s*(.*))?$", ln)
            if m and m.group(1) not in ("defaults", "hydra"):
                out.append(line(f"{m.group(1)}={m.group(2)}", m.group(3) or "", 2))
    except OSError:
        pass
    out.append(line("+max_memory_gb=<GB>", "memory limit of the start-up resource guard (default: 75% of this machine)", 2))
    out += [
        "",
        "sweeps:",
        f"  {PROG} -m model=lin,gp consensus=individual,hybrid seed=0,1,2 hydra.sweep.dir=multirun/mine",
        "  every combination is checked before the first job starts; resume an interrupted sweep with the",
        "  same command plus resume=true; jobs run in parallel on every core (joblib; hydra/launcher=basic: one by one).",
        "",
        "outputs:",
        "  one run: outputs/<study>/<date_time>/ (or hydra.run.dir=DIR): results.csv (tidy: one row per",
        "  episode x node x metric), meta.json, config.yaml, status.json, run.log.",
        "  a sweep: multirun/<study>/<date_time>/<job>/ (or hydra.sweep.dir=DIR), plus sweep_results.csv.",
        "  then: dslearn-report DIR  -> report.md (open it first), figure.png, summary.csv.",
        "",
        f"more: {PROG} --cfg job [overrides] prints the composed config; --hydra-help lists Hydra's own options;",
        f"      {PROG} --version prints dslearn's version. Exit codes: 0 ok, 2 bad input, 130 Ctrl-C, 1 other.",
        f"      filter=default is the EKF (filter=ukf the UKF). TAB completion in bash: eval \"$({PROG} -sc install=bash)\"",
    ]
    return "\n".join(out)


# --------------------------------------------------------------------------------------------
# shell completion (``eval "$(dslearn-run -sc install=bash)"``): the common requests answered here


_APP_ARGS = re.compile(r"^\s*[\w_\-=\./]+\s*(.*)")  # Hydra's: the line without the program's name
_FILE_PREFIXES = (".", "/", "\\")


def _root_words() -> list[str]:
    """What completes an empty word at the root without composing: the config groups (``group=``; Hydra's
    ``hydra`` and the schemas' ``schema``, groups of groups and options), the root keys (``key=``) and the
    root nodes (``group.``, ``hydra.``)."""
    defaults = _defaults()
    out = {"hydra", "schema", "hydra."}
    for d in CONF_DIRS:
        for g in d.iterdir() if d.is_dir() else ():
            if g.is_dir() and not g.name.startswith(("_", ".")) and any(g.glob("*.yaml")):
                out.add(f"{g.name}=")
    for g, opt in defaults.items():
        if opt not in ("null", "None") and not g.startswith(("override ", "hydra", "_")):
            out.add(f"{g}.")
    try:
        root = OmegaConf.load(Path(CONF_DIR) / "config.yaml")
    except Exception:  # noqa: BLE001
        return sorted(out)
    for k in root.keys():
        if str(k) not in ("defaults", "hydra"):
            out.add(f"{k}.") if OmegaConf.is_config(root._get_node(k)) else out.add(f"{k}=")
    return sorted(out)


def light_completion(argv: list[str], line: str | None) -> list[str] | None:
    """The answer to a completion request (``-sc query=bash``, the shell's line in ``COMP_LINE``) where
    it needs no composed configuration: a group's options (``model=g`` -> ``model=gp ...``) and a first
    word at the root (groups and root keys), as Hydra's completion gives them. ``None``: Hydra answers
    (keys under a node, values, files, a line that chooses an experiment or a method preset, or adds or
    deletes keys)."""
    if len(argv) != 2 or argv[0] not in ("-sc", "--shell-completion") or argv[1] not in ("query=bash", "query=zsh"):
        return None
    if line is None:
        return None
    m = _APP_ARGS.match(line)
    if not m:
        return None
    rest = m.group(1)
    words = rest.split()
    if any(w.startswith("-") and w not in _MULTIRUN_FLAGS for w in words):
        return None
    words = [w for w in words if w not in _MULTIRUN_FLAGS]
    new_word = len(rest) == 0 or rest[-1] == " "
    word = "" if new_word or not words else words[-1]
    before = words if new_word else words[:-1]
    if any(w.startswith(("+", "~", "hydra")) or w.split("=")[0] in ("experiment", "method") for w in before):
        return None
    if word.startswith(("+", "~")) or "/" in word.split("=")[0]:
        return None
    if "=" in word:
        key, _, value = word.partition("=")
        if "." in key or key.startswith("hydra") or not _is_group(key) or key == "schema" or \
                value.lower().startswith(_FILE_PREFIXES):
            return None
        return sorted(f"{key}={o}" for o in _group_options(key) if f"{key}={o}".startswith(word))
    if "." in word:
        return None
    return [w for w in _root_words() if w.startswith(word)]


def version_text() -> str:
    return f"{PROG} (dslearn) {__version__}"


# --------------------------------------------------------------------------------------------


def _quiet_interrupts_in_callbacks() -> None:
    """A Ctrl-C that lands inside a finaliser or a weakref callback is "ignored" by the interpreter, which prints
    its traceback (``Exception ignored in: ...``) beside the one line this program promises; the interrupt
    itself reaches the main flow with the signal's next delivery or the launcher's shutdown. Only such
    KeyboardInterrupts are kept quiet; every other unraisable exception is reported as before."""
    hook = sys.unraisablehook
    if getattr(hook, "_dslearn", False):
        return

    def quiet(unraisable):
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            return
        hook(unraisable)

    quiet._dslearn = True
    sys.unraisablehook = quiet


#: the environment variable that tells a launcher's worker process (which inherits it) from the command's own
_MAIN_PID = "DSLEARN_RUN_PID"


def main(argv: list[str] | None = None) -> None:
    """The ``dslearn-run`` console script (``argv`` defaults to ``sys.argv[1:]``)."""
    if argv is None:
        argv = sys.argv[1:]
    argv = list(argv)
    _quiet_interrupts_in_callbacks()
    os.environ[_MAIN_PID] = str(os.getpid())
    try:
        if any(a in ("--help", "-h") for a in argv):
            try:
                print(help_text())
            except BrokenPipeError:  # e.g. | head
                sys.stdout = open(os.devnull, "w")
            return
        if "--version" in argv:
            print(version_text())
            return
        answer = light_completion(argv, os.environ.get("COMP_LINE"))
        if answer is not None:
            print(" ".join(answer))
            return
        plan: dict = {}
        err = precheck(argv, plan)
        if err is not None:
            _say("configuration error", err)
            raise SystemExit(2)
        from dslearn.io import RunDirBusy

        try:
            hydra_argv, held = lock_run_dir(argv, plan.get("run_dir"))
        except RunDirBusy as e:  # before Hydra wrote anything into the folder
            _say("run folder busy", f"{e} ({_BUSY_KEYS})")
            raise SystemExit(2)
        if "jobs" in plan:  # a sweep: its overall status line counts to this
            from dslearn.callbacks import expect_jobs

            expect_jobs(plan["jobs"])
        global _USER_ARGV
        old = sys.argv
        sys.argv = [old[0] if old else PROG, *hydra_argv]
        _USER_ARGV = argv
        old_term = None
        try:
            import signal
            import threading

            if threading.current_thread() is threading.main_thread():
                old_term = signal.signal(signal.SIGTERM, _on_sigterm)
        except (ValueError, OSError, AttributeError):
            old_term = None
        try:
            _app()
            _exit_if_cells_failed()
        finally:
            sys.argv = old
            _USER_ARGV = None
            if held is not None:
                _PRELOCKED.pop(os.path.abspath(plan["run_dir"]), None)
                held.release()
            if old_term is not None:
                signal.signal(signal.SIGTERM, old_term)
    except KeyboardInterrupt as e:
        code = 143 if isinstance(e, Terminated) else 130
        sweep = _interrupted_sweep()
        if sweep is not None:
            print(f"{PROG}: interrupted: {sweep['done']} of {sweep['jobs']} jobs done; resume with: "
                  f"{resume_command(argv, sweep['dir'])}", file=sys.stderr, flush=True)
            raise SystemExit(code) from None
        what = "SIGTERM" if isinstance(e, Terminated) else "Ctrl-C"
        _say("interrupted", f"{what} before the run started; nothing was written")
        raise SystemExit(code) from None


def _exit_if_cells_failed() -> None:
    """Exit 1 after a matrix sweep in which cells failed in the up-front check (their parts raised while built:
    not run; :data:`dslearn.schemas.matrix.FAILED_CELLS`), once the sweep's other jobs ran and were gathered."""
    mx = sys.modules.get("dslearn.schemas.matrix")
    failed = list(getattr(mx, "FAILED_CELLS", None) or [])
    if failed:
        _say("failed cells", f"{len(failed)} cell(s) of the matrix failed while their parts were built and did not "
                             f"run (matrix_cells.csv: status failed, with the error): "
                             + "; ".join(f"{r.get('method')} on {r.get('scenario')}" for r in failed))
        raise SystemExit(1)


def _interrupted_sweep() -> dict | None:
    """The sweep this process was running when interrupted (its status poller stopped, its folder lock
    released, the launcher's worker processes shut down), or ``None`` when no sweep had started."""
    cb = sys.modules.get("dslearn.callbacks")
    state = cb.interrupt_active() if cb is not None else None
    loky = sys.modules.get("joblib.externals.loky.reusable_executor")
    executor = getattr(loky, "_executor", None) if loky is not None else None
    if executor is not None:  # workers and their semaphores go now, not at exit (no leaked-semaphore warning)
        try:
            executor.shutdown(wait=True, kill_workers=True)
        except Exception:  # noqa: BLE001
            pass
    return state


def resume_command(argv: list[str], sweep_dir: str) -> str:
    """The command line that resumes a sweep: ``argv`` without its ``hydra.sweep.dir`` and ``resume``
    overrides, then ``hydra.sweep.dir=<sweep_dir>`` (absolute) and ``resume=true``, quoted for a POSIX shell."""
    import shlex

    keep = []
    for a in argv:
        if not a.startswith("-"):
            try:
                if parse_override(a).key_or_group in ("hydra.sweep.dir", "resume"):
                    continue
            except Exception:  # noqa: BLE001
                pass
        keep.append(a)
    where = os.path.abspath(sweep_dir)
    line = f"hydra.sweep.dir={where}"  # as the user would write it, where Hydra reads it back as this folder
    try:
        plain = str(parse_override(line).value()) == where
    except Exception:  # noqa: BLE001
        plain = False
    if not plain:
        line = _run_dir_override(where, "hydra.sweep.dir") or line
    return " ".join(shlex.quote(a) for a in [PROG, *keep, line, "resume=true"])


if _SIGINT_BEFORE is not None:  # imported: KeyboardInterrupt again, handled by main()
    signal.signal(signal.SIGINT, _SIGINT_BEFORE)

if __name__ == "__main__":
    main()
