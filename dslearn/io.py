"""Result files: atomic writes and loading of tidy result tables."""

from __future__ import annotations

import hashlib
import io as _io
import json
import logging
import os
import socket
import tempfile
import warnings
from pathlib import Path

import pandas as pd

from dslearn.errors import DataFormatError

RESULTS_FILE = "results.csv"
META_FILE = "meta.json"
DONE_FILE = ".done"
#: the gathered table of a sweep (written by :class:`dslearn.callbacks.GatherResults`)
SWEEP_TABLE = "sweep_results"
#: a run's tracking-figure arrays (written by the studies that track, drawn by ``dslearn-report`` as tracking.png)
TRACKS_FILE = "tracks.npz"
#: lock of a run folder while a run works in it (holds the owner's pid)
LOCK_FILE = ".dslearn.lock"
log = logging.getLogger("dslearn.io")


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file and a rename.

    A crash leaves either the old file or the new one, never a half-written file. The file gets
    the permissions a plain ``open(path, "w")`` would give (``0o666`` less the umask), not the
    owner-only mode of the temporary file.
    """
    _atomic_write(path, text, "w")


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (as :func:`atomic_write_text`)."""
    _atomic_write(path, data, "wb")


def _atomic_write(path: str | Path, content, mode: str) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as f:
            f.write(content)
            f.flush()
            os.fsync(f.fileno())
            os.fchmod(f.fileno(), 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_csv(df: pd.DataFrame, path: str | Path) -> None:
    """Write a DataFrame as CSV atomically (temp file + rename)."""
    atomic_write_text(path, df.to_csv(index=False))


def atomic_write_npz(path: str | Path, arrays: dict) -> None:
    """Write ``{name: array}`` as a compressed ``.npz`` file atomically (strings as unicode arrays:
    ``numpy.load`` reads it back without pickles)."""
    import numpy as np

    buf = _io.BytesIO()
    np.savez_compressed(buf, **{k: np.asarray(v) for k, v in arrays.items()})
    atomic_write_bytes(path, buf.getvalue())


class Artifacts(dict):
    """Extra files of one run, ``{file name: content}``, that a study hands to the app beside its result
    table, in the table's ``attrs[ARTIFACTS]`` (:func:`attach_artifact`); the app writes them into the
    run folder before ``results.csv`` (:func:`write_artifacts`). Content by the name's suffix: ``.npz``
    a dict of arrays, ``.csv`` a DataFrame, anything else text.

    Compared by identity and never copied when pandas copies a table's ``attrs`` (arrays have no
    truth value, and a result table is copied and concatenated many times)."""

    def __eq__(self, other) -> bool:
        return self is other

    def __ne__(self, other) -> bool:
        return self is not other

    __hash__ = object.__hash__

    def __copy__(self) -> "Artifacts":
        return self

    def __deepcopy__(self, memo) -> "Artifacts":
        return self


#: the key of a result table's ``attrs`` that holds its run's :class:`Artifacts`
ARTIFACTS = "artifacts"


def attach_artifact(df: pd.DataFrame, name: str, content) -> pd.DataFrame:
    """Hand ``content`` to the app as the run-folder file ``name`` (a plain file name) with the result
    table ``df`` (in place; returns ``df``)."""
    if not name or Path(name).name != name or name.startswith("."):
        raise ValueError(f"artifact name {name!r}: give a plain file name (no folder, not hidden)")
    art = df.attrs.get(ARTIFACTS)
    if not isinstance(art, Artifacts):
        art = Artifacts()
        df.attrs[ARTIFACTS] = art
    art[name] = content
    return df


def write_artifacts(out_dir: str | Path, artifacts) -> list[Path]:
    """Write a run's :class:`Artifacts` (``None``: nothing) into ``out_dir``, each atomically;
    returns the paths written."""
    written = []
    for name, content in (artifacts or {}).items():
        path = Path(out_dir) / name
        if path.suffix == ".npz":
            atomic_write_npz(path, content)
        elif path.suffix == ".csv":
            atomic_write_csv(content, path)
        else:
            atomic_write_text(path, str(content))
        written.append(path)
    return written


def sha256_text(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def results_text(df: pd.DataFrame) -> str:
    """The exact CSV text :func:`atomic_write_csv` writes (hashed into ``meta.json``)."""
    return df.to_csv(index=False)


def check_complete(run_dir: str | Path) -> tuple[bool, str]:
    """Whether ``run_dir`` holds a complete result: ``(ok, reason)``.

    Complete = ``results.csv`` exists, parses, is non-empty, and matches the completeness marker
    in ``meta.json`` (``rows`` and ``results_sha256``, written by :func:`dslearn.app.record.execute`
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
        meta = json.loads(meta_p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:  # ValueError: JSONDecodeError and UnicodeDecodeError
        return False, f"{META_FILE} is not valid JSON ({type(e).__name__})"
    if not isinstance(meta, dict):
        return False, f"{META_FILE} is not a JSON object"
    try:
        text = res.read_text(encoding="utf-8")
    except OSError as e:
        return False, f"cannot read {RESULTS_FILE} ({e})"
    except UnicodeDecodeError as e:
        return False, f"{RESULTS_FILE} is not UTF-8 text (byte {e.start}): corrupted"
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
    try:
        rows = int(meta["rows"]) if "rows" in meta else None
    except (TypeError, ValueError):
        return False, f"{META_FILE} has a non-integer 'rows'"
    if rows is not None and rows != len(df):
        return False, f"{RESULTS_FILE} has {len(df)} rows, {META_FILE} says {meta['rows']}"
    return True, "complete"


class RunDirBusy(RuntimeError):
    """Another live process holds the run folder's lock."""


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    except OSError:
        return False
    return True


class RunLock:
    """An exclusive lock on a run folder: ``<dir>/.dslearn.lock`` holding the owner's pid.

    On POSIX the file is also ``flock``-ed, so the kernel frees the lock when its owner dies
    (a stale file of a dead pid is simply taken over); elsewhere the file is created
    exclusively and a lock whose pid is no longer alive is taken over. ``acquire`` raises
    :class:`RunDirBusy` naming the owner's pid when a live process holds it."""

    def __init__(self, run_dir: str | Path) -> None:
        self.path = Path(run_dir) / LOCK_FILE
        self._fd: int | None = None

    def _owner(self) -> str:
        try:
            return self.path.read_text(encoding="utf-8", errors="replace").strip() or "?"
        except OSError:
            return "?"

    def _busy(self) -> RunDirBusy:
        owner = self._owner()
        pid = owner.split()[0] if owner != "?" else "?"
        return RunDirBusy(
            f"{self.path.parent} is in use by another dslearn-run (pid {pid}, lock file {self.path}); "
            "wait for it to finish or choose another run folder"
        )

    def acquire(self) -> "RunLock":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        me = f"{os.getpid()} {socket.gethostname()}\n"
        try:
            import fcntl
        except ImportError:  # no flock (Windows): exclusive create + pid liveness
            fcntl = None
        if fcntl is not None:
            import errno

            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as e:
                os.close(fd)
                if e.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EACCES):
                    raise self._busy() from None
                fcntl = None  # no flock on this file system: the pid method below
        if fcntl is not None:
            old = self._owner()
            if old not in ("?", "") and old.split()[0] != str(os.getpid()):
                log.info("took over the stale lock %s of pid %s (not running)", self.path, old.split()[0])
            os.ftruncate(fd, 0)
            os.write(fd, me.encode())
            self._fd = fd
            return self
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            except FileExistsError:
                owner = self._owner()
                try:
                    pid = int(owner.split()[0])
                except (ValueError, IndexError):
                    pid = -1
                if _pid_alive(pid):
                    raise self._busy() from None
                log.info("taking over the stale lock %s of pid %s (not running)", self.path, pid)
                self.path.unlink(missing_ok=True)
                continue
            os.write(fd, me.encode())
            os.close(fd)
            self._fd = -1
            return self
        raise self._busy()

    def release(self) -> None:
        if self._fd is None:
            return
        try:
            if self._fd >= 0:
                os.ftruncate(self._fd, 0)  # the file stays (unlinking would race a waiting locker)
                os.close(self._fd)
            else:
                self.path.unlink(missing_ok=True)
        except OSError:
            pass
        self._fd = None

    def __enter__(self) -> "RunLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def find_result_files(root: str | Path) -> list[Path]:
    """Every run's ``results.csv`` under ``root`` (a run or multirun directory), complete or not."""
    root = Path(root)
    return sorted(p for p in root.rglob(RESULTS_FILE) if p.is_file())


def read_csv_checked(path: str | Path) -> pd.DataFrame:
    """``pd.read_csv`` that raises :class:`DataFormatError` naming the file (and line, if known)."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(65536)
    except OSError as e:
        raise DataFormatError(f"{path}: cannot be read ({e.strerror or e})") from None
    if b"\x00" in head:
        line = head[: head.index(b"\x00")].count(b"\n") + 1
        raise DataFormatError(f"{path}:{line}: binary file (NUL byte), not a text CSV table")
    try:
        return pd.read_csv(path)
    except pd.errors.EmptyDataError:
        raise DataFormatError(f"{path}:1: empty file (expected a CSV header)") from None
    except pd.errors.ParserError as e:
        import re

        m = re.search(r"line (\d+)", str(e))
        line = m.group(1) if m else "?"
        raise DataFormatError(f"{path}:{line}: malformed CSV ({e})") from None
    except UnicodeDecodeError:
        line, offset = _first_bad_utf8(path)
        raise DataFormatError(f"{path}:{line}: not a UTF-8 text CSV file (undecodable byte at offset {offset})") from None
    except (OSError, ValueError) as e:
        raise DataFormatError(f"{path}: cannot be read as CSV ({type(e).__name__}: {' '.join(str(e).split())[:160]})") from None


def _first_bad_utf8(path: Path) -> tuple[int | str, int | str]:
    """(line, byte offset) of the first byte of ``path`` that is not UTF-8."""
    try:
        raw = Path(path).read_bytes()
        raw.decode("utf-8")
    except UnicodeDecodeError as e:
        return raw[: e.start].count(b"\n") + 1, e.start
    except OSError:
        pass
    return "?", "?"


def check_values(df: pd.DataFrame, path: str | Path) -> pd.DataFrame:
    """The ``value`` column as floats; DataFormatError naming the file and the first bad line."""
    v = pd.to_numeric(df["value"], errors="coerce")
    bad = v.isna() & df["value"].notna()
    if bad.any():
        i = int(bad.to_numpy().nonzero()[0][0])
        line = f"{i + 2}" if Path(path).suffix == ".csv" else f"row {i}"
        raise DataFormatError(f"{path}:{line}: non-numeric value {df['value'].iloc[i]!r} in the 'value' column")
    if v.dtype != df["value"].dtype:
        df = df.copy()
        df["value"] = v.astype(float)
    return df


def load_results(root: str | Path, *, warn: bool = True) -> pd.DataFrame:
    """Concatenate every *complete* run's ``results.csv`` under ``root`` into one tidy table.

    Broken or partial run directories (see :func:`check_complete`) are skipped with a warning.
    If ``root`` is a gathered sweep table (``sweep_results.parquet``/``.csv``) or a directory that
    holds one, that table is returned as is.
    """
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"{root}: no such file or folder")
    if root.is_file():
        return load_table(root)
    for ext in (".parquet", ".csv"):
        if (root / (SWEEP_TABLE + ext)).is_file():
            return load_table(root / (SWEEP_TABLE + ext))
    files = find_result_files(root)
    if not files:
        raise FileNotFoundError(f"no {RESULTS_FILE} found under {root}")
    frames, skipped = [], []
    for f in files:
        ok, why = check_complete(f.parent)
        if not ok:
            msg = f"skipping {f.parent}: {why}"
            skipped.append(msg)
            if warn:
                warnings.warn(msg, stacklevel=2)
            log.warning(msg)
            continue
        df = check_values(read_csv_checked(f), f)
        df["run_dir"] = str(f.parent.relative_to(root)) if f.parent != root else "."
        frames.append(df)
    if not frames:
        raise FileNotFoundError(f"no complete {RESULTS_FILE} under {root} ({len(skipped)} broken: {skipped[0]})")
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
            raise DataFormatError(f"{path}: not a readable Parquet file ({type(e).__name__})") from None
    else:
        df = read_csv_checked(path)
    if not {"metric", "value"} <= set(df.columns):
        where = f"{path}:1" if path.suffix != ".parquet" else f"{path}"
        raise DataFormatError(f"{where}: header lacks the 'metric' and 'value' columns of a tidy result table")
    if df.empty:
        raise DataFormatError(f"{path}: the table has no rows")
    return check_values(df, path)
