"""``dslearn-run``: the Hydra app. One run = one task configuration -> ``results.csv``.

Every run writes, in its output directory: ``results.csv`` (tidy, written atomically at the
end — an interrupted run leaves none), ``config.yaml`` (resolved config) and ``meta.json``
(package version, git commit, library versions, seed, wall time).
"""

from __future__ import annotations

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
from .io import RESULTS_FILE, atomic_write_csv, atomic_write_text

log = logging.getLogger("dslearn.run")
CONF_DIR = str(Path(__file__).resolve().parent.parent / "conf")


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


def _versions() -> dict:
    vs = {"python": platform.python_version()}
    for m in ("torch", "gpytorch", "numpy", "pandas", "hydra", "omegaconf"):
        try:
            vs[m] = importlib.import_module(m).__version__
        except Exception:
            pass
    return vs


def execute(cfg: DictConfig, out_dir: str | Path) -> pd.DataFrame:
    """Run the task in ``cfg`` and write its result files into ``out_dir``. Returns the results."""
    out_dir = Path(out_dir)
    if cfg.get("threads"):
        import torch

        torch.set_num_threads(int(cfg.threads))
    fn = resolve_entry(cfg.task.entry)
    t0 = time.perf_counter()
    df = fn(cfg)
    wall = time.perf_counter() - t0
    if not isinstance(df, pd.DataFrame) or not {"metric", "value"} <= set(df.columns):
        raise RuntimeError(f"task {cfg.task.entry} must return a tidy DataFrame with 'metric' and 'value' columns")
    df = df.copy()
    for col, val in (("seed", int(cfg.seed)), ("task", str(cfg.task.name)), ("study", str(cfg.study))):
        if col not in df.columns:
            df.insert(0, col, val)
    atomic_write_text(out_dir / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))
    meta = {
        "dslearn_version": __version__,
        "git_commit": _git_commit(),
        "versions": _versions(),
        "seed": int(cfg.seed),
        "wall_time_s": round(wall, 3),
        "rows": len(df),
        "jitter_events": int(df.attrs.get("jitter_events", 0)),
        "argv": sys.argv[1:],
    }
    atomic_write_text(out_dir / "meta.json", json.dumps(meta, indent=2))
    atomic_write_csv(df, out_dir / RESULTS_FILE)  # last: its presence means the run finished
    log.info("wrote %s (%d rows, %.1fs)", out_dir / RESULTS_FILE, len(df), wall)
    return df


@hydra.main(version_base=None, config_path=CONF_DIR, config_name="config")
def _app(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    out_dir = HydraConfig.get().runtime.output_dir
    if cfg.get("progress") is False and sys.stderr.isatty() and not os.environ.get("CI"):
        OmegaConf.set_struct(cfg, False)
        cfg.progress = True
    try:
        df = execute(cfg, out_dir)
    except ConfigError as e:
        log.error("configuration error: %s", e)
        print(f"dslearn-run: configuration error: {e}", file=sys.stderr)
        raise SystemExit(2)
    if cfg.get("print_table", True):
        from .report import console_table, summarize

        summary = summarize(df)
        text = None
        if str(cfg.task.name) != "yu":  # other studies print their own paper-shaped tables
            mod = importlib.import_module(str(cfg.task.entry).split(":")[0])
            if hasattr(mod, "report"):
                text = mod.report(df, summary, Path(out_dir))
        print(text or console_table(summary))
        print(f"results: {Path(out_dir) / RESULTS_FILE}")


def main() -> None:
    _app()


if __name__ == "__main__":
    main()
