"""Result files: atomic writes and loading of tidy result tables."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pandas as pd

RESULTS_FILE = "results.csv"
DONE_FILE = ".done"


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file and a rename.

    A crash leaves either the old file or the new one, never a half-written file.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_csv(df: pd.DataFrame, path: str | Path) -> None:
    """Write a DataFrame as CSV atomically (temp file + rename)."""
    atomic_write_text(path, df.to_csv(index=False))


def find_result_files(root: str | Path) -> list[Path]:
    """All complete ``results.csv`` files under ``root`` (a run or multirun directory)."""
    root = Path(root)
    return sorted(p for p in root.rglob(RESULTS_FILE) if p.is_file())


def load_results(root: str | Path) -> pd.DataFrame:
    """Concatenate every run's ``results.csv`` under ``root`` into one tidy table."""
    files = find_result_files(root)
    if not files:
        raise FileNotFoundError(f"no {RESULTS_FILE} found under {root}")
    frames = []
    for f in files:
        df = pd.read_csv(f)
        df["run_dir"] = str(f.parent.relative_to(Path(root))) if f.parent != Path(root) else "."
        frames.append(df)
    return pd.concat(frames, ignore_index=True)
