"""``dslearn-run``: the Hydra app. One run = one task configuration -> ``results.csv``.

Every run writes, in its output directory: ``config.yaml`` (resolved config), ``meta.json``
(package version, git commit, library versions, seed, overrides, wall time, and the
completeness marker: the row count and SHA-256 of ``results.csv``), then — last, atomically —
``results.csv``, and finally ``status.json`` (``done | skipped | failed``, read by the sweep
summary). An interrupted run leaves no ``results.csv`` (or one whose hash does not match).

Resume: ``dslearn-run -m ... hydra.sweep.dir=DIR resume=true`` (or ``hydra.run.dir=DIR
resume=true`` for one run) skips every job whose directory already holds a complete result
(:func:`dslearn.io.check_complete`) and re-runs missing or broken ones. The default sweep dir
contains a timestamp, so resuming needs the same fixed ``hydra.sweep.dir`` both times.

Exit codes: 0 ok; 2 configuration error (one line on stderr, before any work); 1 other failure
(in a sweep: after every job has run and the table of the finished ones is gathered).
"""

from __future__ import annotations

import datetime as _dt
import importlib
import json
import logging
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import hydra
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from . import __version__
from .errors import ConfigError
from .io import META_FILE, RESULTS_FILE, atomic_write_text, check_complete, results_text, sha256_text

log = logging.getLogger("dslearn.run")
CONF_DIR = str(Path(__file__).resolve().parent.parent / "conf")
STATUS_FILE = "status.json"


def resolve_entry(entry: str):
    """``"pkg.module:function"`` -> the function."""
    if not isinstance(entry, str) or ":" not in entry:
        raise ConfigError(f"task.entry={entry!r} must look like 'package.module:function'")
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


def execute(cfg: DictConfig, out_dir: str | Path) -> pd.DataFrame:
    """Validate ``cfg``, run its task and write the result files into ``out_dir``. Returns the results.

    Raises :class:`ConfigError` (before any work) for a bad configuration.
    """
    from .config_schema import validate_config

    out_dir = Path(out_dir)
    validate_config(cfg)
    if cfg.get("threads"):
        import torch

        torch.set_num_threads(int(cfg.threads))
    fn = resolve_entry(cfg.task.entry)
    started = _dt.datetime.now(_dt.timezone.utc)
    t0 = time.perf_counter()
    df = fn(cfg)
    wall = time.perf_counter() - t0
    if not isinstance(df, pd.DataFrame) or not {"metric", "value"} <= set(df.columns):
        raise RuntimeError(f"task {cfg.task.entry} must return a tidy DataFrame with 'metric' and 'value' columns")
    if df.empty:
        raise RuntimeError(f"task {cfg.task.entry} returned an empty result table")
    df = df.copy()
    for col, val in (("seed", int(cfg.seed)), ("task", str(cfg.task.name)), ("study", str(cfg.study))):
        if col not in df.columns:
            df.insert(0, col, val)
    text = results_text(df)
    atomic_write_text(out_dir / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))
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
        "results_sha256": sha256_text(text),  # completeness marker checked by dslearn.io.check_complete
        "jitter_events": int(df.attrs.get("jitter_events", 0)),
        "argv": sys.argv[1:],
        **_hydra_job(),
    }
    atomic_write_text(out_dir / META_FILE, json.dumps(meta, indent=2))
    atomic_write_text(out_dir / RESULTS_FILE, text)  # last: its presence (matching meta) means the run finished
    log.info("wrote %s (%d rows, %.1fs)", out_dir / RESULTS_FILE, len(df), wall)
    return df


def _write_status(out_dir: Path, status: str, wall: float, **extra) -> None:
    try:
        atomic_write_text(out_dir / STATUS_FILE, json.dumps({"status": status, "wall_s": round(wall, 3), **extra}))
    except OSError:
        pass


def _same_job(out_dir: Path, job: dict) -> bool:
    """Whether the result in ``out_dir`` was made with this job's overrides (runtime keys aside)."""
    from .callbacks import parse_overrides

    try:
        meta = json.loads((out_dir / META_FILE).read_text())
    except (OSError, json.JSONDecodeError):
        return False
    if meta.get("overrides") is None or "overrides" not in job:
        return True
    return parse_overrides(meta["overrides"]) == parse_overrides(job["overrides"])


def _progress_default() -> bool:
    """Bars on a terminal, off when stderr is not a TTY or the ``CI`` environment variable is set."""
    return sys.stderr.isatty() and not os.environ.get("CI")


def _describe(cfg: DictConfig, job: dict) -> str:
    parts = [f"task={cfg.task.name}", f"study={cfg.study}", f"seed={cfg.seed}"]
    if job.get("overrides"):
        parts.append("overrides: " + " ".join(job["overrides"]))
    return ", ".join(parts)


@hydra.main(version_base=None, config_path=CONF_DIR, config_name="config")
def _app(cfg: DictConfig) -> dict:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    hc = HydraConfig.get()
    out_dir = Path(hc.runtime.output_dir)
    multirun = hc.mode == RunMode.MULTIRUN
    job = _hydra_job()
    tag = f"job {job['job_num']}" if multirun and job.get("job_num") is not None else "run"
    t0 = time.perf_counter()
    if cfg.get("progress") is None:
        OmegaConf.set_struct(cfg, False)
        cfg.progress = _progress_default()
        OmegaConf.set_struct(cfg, True)
    if cfg.get("resume"):
        ok, why = check_complete(out_dir)
        if ok and not _same_job(out_dir, job):
            ok, why = False, "it holds the result of other overrides (was the grid changed?)"
        if ok:
            log.info("%s: resume: %s is complete, skipping (%s)", tag, out_dir, _describe(cfg, job))
            _write_status(out_dir, "skipped", time.perf_counter() - t0)
            return {"status": "skipped", "dir": str(out_dir)}
        log.info("%s: resume: re-running %s (%s)", tag, out_dir, why)
    log.info("%s: starting %s -> %s", tag, _describe(cfg, job), out_dir)
    try:
        df = execute(cfg, out_dir)
    except ConfigError as e:
        log.error("configuration error: %s", e)
        print(f"dslearn-run: configuration error: {e}", file=sys.stderr)
        _write_status(out_dir, "failed", time.perf_counter() - t0, error=f"ConfigError: {e}", config_error=True)
        if multirun:  # the sweep goes on; the sweep summary counts it and the exit code is 2
            return {"status": "failed", "dir": str(out_dir), "config_error": True}
        raise SystemExit(2)
    except Exception as e:
        log.exception("%s failed: %s", tag, e)
        _write_status(out_dir, "failed", time.perf_counter() - t0, error=f"{type(e).__name__}: {e}")
        if multirun:  # keep the other jobs; the sweep ends with exit code 1 after gathering
            return {"status": "failed", "dir": str(out_dir)}
        raise
    wall = time.perf_counter() - t0
    _write_status(out_dir, "done", wall, rows=len(df))
    if cfg.get("print_table", True) and not multirun:
        from .report import console_table, summarize

        summary = summarize(df)
        text = None
        if str(cfg.task.name) != "yu":  # other studies print their own paper-shaped tables
            mod = importlib.import_module(str(cfg.task.entry).split(":")[0])
            if hasattr(mod, "report"):
                text = mod.report(df, summary, out_dir)
        print(text or console_table(summary))
        print(f"results: {out_dir / RESULTS_FILE}")
    log.info("%s summary: done, %d rows, wall %.1fs, results %s", tag, len(df), wall, out_dir / RESULTS_FILE)
    return {"status": "done", "dir": str(out_dir), "rows": len(df)}


# --------------------------------------------------------------------------------------------
# start-up check: compose the command line's configuration once, before Hydra starts any job


_NO_CHECK_FLAGS = {"--help", "-h", "--hydra-help", "--version", "--cfg", "-c", "--info", "-i",
                   "--shell-completion", "-sc", "--resolve", "--package", "-p", "--config-name", "-cn",
                   "--config-path", "-cp", "--config-dir", "-cd", "--experimental-rerun"}


def precheck(argv: list[str]) -> str | None:
    """Compose and validate the configuration the command line asks for; the error line or ``None``.

    Sweep overrides (``a=1,2``, ``range(...)``) are expanded and every combination is checked,
    so a bad value in a sweep fails before its first job runs. Options that Hydra handles itself
    (``--help``, ``--cfg``, ...) skip the check.
    """
    if any(a.split("=")[0] in _NO_CHECK_FLAGS for a in argv):
        return None
    overrides = [a for a in argv if not a.startswith("-")]
    try:
        from hydra import compose, initialize_config_dir
        from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
        from hydra.core.override_parser.overrides_parser import OverridesParser

        parsed = OverridesParser.create().parse_overrides(overrides)
        user = [o for o in parsed if not o.key_or_group.startswith("hydra")]
        combos = BasicSweeper.split_arguments(user, None)[0] if user else [[]]
        if len(combos) > 16:  # a huge grid: check the first and last jobs only
            combos = [combos[0], combos[-1]]
        from .config_schema import validate_config

        with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
            for combo in combos:
                cfg = compose("config", overrides=list(combo))
                validate_config(cfg)
    except ConfigError as e:
        return str(e)
    except Exception as e:  # Hydra/OmegaConf composition errors: unknown key, group option, type
        msg = " ".join(str(e).split()).split(" Config search path:")[0]
        return msg or type(e).__name__
    return None


def main() -> None:
    argv = sys.argv[1:]
    err = precheck(argv)
    if err is not None:
        print(f"dslearn-run: configuration error: {err}", file=sys.stderr)
        raise SystemExit(2)
    _app()


if __name__ == "__main__":
    main()
