"""Result files: atomic writes and loading of tidy result tables."""

from __future__ import annotations

import hashlib
import io as _io
import json
import logging
import os
import tempfile
import warnings
from pathlib import Path

import pandas as pd

from .errors import DataFormatError

RESULTS_FILE = "results.csv"
META_FILE = "meta.json"
DONE_FILE = ".done"
#: the gathered table of a sweep (written by :class:`dslearn.callbacks.GatherResults`)
SWEEP_TABLE = "sweep_results"
log = logging.getLogger("dslearn.io")


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


def sha256_text(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def results_text(df: pd.DataFrame) -> str:
    """The exact CSV text :func:`atomic_write_csv` writes (hashed into ``meta.json``)."""
    return df.to_csv(index=False)


def check_complete(run_dir: str | Path) -> tuple[bool, str]:
    """Whether ``run_dir`` holds a complete result: ``(ok, reason)``.

    Complete = ``results.csv`` exists, parses, is non-empty, and matches the completeness marker
    in ``meta.json`` (``rows`` and ``results_sha256``, written by :func:`dslearn.run.execute`
    *before* the results file, which is written last). A ``meta.json`` without the hash (older
    runs) is accepted when the file parses with the recorded row count.
    """
    run_dir = Path(run_dir)
    res, meta_p = run_dir / RESULTS_FILE, run_dir / META_FILE
    if not res.is_file():
        return False, f"no {RESULTS_FILE}"
    if not meta_p.is_file():
        return False, f"no {META_FILE} (completeness marker)"
    try:
        meta = json.loads(meta_p.read_text())
    except (OSError, json.JSONDecodeError) as e:
        return False, f"{META_FILE} is not valid JSON ({e})"
    try:
        text = res.read_text()
    except OSError as e:
        return False, f"cannot read {RESULTS_FILE} ({e})"
    digest = meta.get("results_sha256")
    if digest is not None and digest != sha256_text(text):
        return False, f"{RESULTS_FILE} does not match the hash in {META_FILE} (partial or stale)"
    try:
        df = pd.read_csv(_io.StringIO(text))
    except Exception as e:  # noqa: BLE001 - any parse failure means broken
        return False, f"{RESULTS_FILE} does not parse ({type(e).__name__}: {e})"
    if df.empty:
        return False, f"{RESULTS_FILE} is empty"
    if not {"metric", "value"} <= set(df.columns):
        return False, f"{RESULTS_FILE} lacks the 'metric'/'value' columns"
    if "rows" in meta and int(meta["rows"]) != len(df):
        return False, f"{RESULTS_FILE} has {len(df)} rows, {META_FILE} says {meta['rows']}"
    return True, "complete"


def find_result_files(root: str | Path) -> list[Path]:
    """Every run's ``results.csv`` under ``root`` (a run or multirun directory), complete or not."""
    root = Path(root)
    return sorted(p for p in root.rglob(RESULTS_FILE) if p.is_file())


def read_csv_checked(path: str | Path) -> pd.DataFrame:
    """``pd.read_csv`` that raises :class:`DataFormatError` naming the file (and line, if known)."""
    path = Path(path)
    try:
        return pd.read_csv(path)
    except pd.errors.EmptyDataError:
        raise DataFormatError(f"{path}:1: empty file (expected a CSV header)") from None
    except pd.errors.ParserError as e:
        import re

        m = re.search(r"line (\d+)", str(e))
        line = m.group(1) if m else "?"
        raise DataFormatError(f"{path}:{line}: malformed CSV ({e})") from None
    except UnicodeDecodeError as e:
        raise DataFormatError(f"{path}: not a text CSV file ({e})") from None


def load_results(root: str | Path, *, warn: bool = True) -> pd.DataFrame:
    """Concatenate every *complete* run's ``results.csv`` under ``root`` into one tidy table.

    Broken or partial run directories (see :func:`check_complete`) are skipped with a warning.
    If ``root`` is a gathered sweep table (``sweep_results.parquet``/``.csv``) or a directory that
    holds one, that table is returned as is.
    """
    root = Path(root)
    if root.is_file():
        return load_table(root)
    for ext in (".parquet", ".csv"):
        if (root / (SWEEP_TABLE + ext)).is_file():
            return load_table(root / (SWEEP_TABLE + ext))
    files = find_result_files(root)
    if not files:
        raise FileNotFoundError(f"no {RESULTS_FILE} found under {root}")
    frames = []
    for f in files:
        ok, why = check_complete(f.parent)
        if not ok:
            msg = f"skipping {f.parent}: {why}"
            if warn:
                warnings.warn(msg, stacklevel=2)
            log.warning(msg)
            continue
        df = pd.read_csv(f)
        df["run_dir"] = str(f.parent.relative_to(root)) if f.parent != root else "."
        frames.append(df)
    if not frames:
        raise FileNotFoundError(f"no complete {RESULTS_FILE} under {root}")
    return pd.concat(frames, ignore_index=True)


def load_table(path: str | Path) -> pd.DataFrame:
    """Read a tidy table from ``.parquet`` or ``.csv`` (DataFormatError on a broken file)."""
    path = Path(path)
    if path.suffix == ".parquet":
        try:
            return pd.read_parquet(path)
        except ImportError:
            csv = path.with_suffix(".csv")
            if csv.is_file():
                return read_csv_checked(csv)
            raise
        except Exception as e:  # noqa: BLE001
            raise DataFormatError(f"{path}: not a readable Parquet file ({e})") from None
    df = read_csv_checked(path)
    if not {"metric", "value"} <= set(df.columns):
        raise DataFormatError(f"{path}:1: header lacks the 'metric' and 'value' columns of a tidy result table")
    return df
