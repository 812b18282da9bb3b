"""The content-keyed cache of parsed trajectory files (dslearn.data.cache)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from dslearn.data import cache as C
from dslearn.data.ethucy import read_trajectories
from dslearn.errors import ConfigError, DataFormatError

TEXT = "10\t1\t1.5\t2.25\n10\t2\t-3.0\t4.0\n20\t2\t-2.5\t4.5\n20\t1\t1.75\t2.5\n30\t1\t2.0\t2.75\n"


def _expected() -> pd.DataFrame:
    """The parse of TEXT, written out by hand (sorted by frame, ped)."""
    return pd.DataFrame({
        "frame": np.array([10, 10, 20, 20, 30], dtype=np.int64),
        "ped": np.array([1, 2, 1, 2, 1], dtype=np.int64),
        "x": [1.5, -3.0, 1.75, -2.5, 2.0],
        "y": [2.25, 4.0, 2.5, 4.5, 2.75],
    })


@pytest.fixture
def cdir(tmp_path, monkeypatch) -> Path:
    d = tmp_path / "cache"
    monkeypatch.setenv(C.ENV_CACHE, str(d))
    return d


def _entries(d: Path) -> list[Path]:
    return sorted(d.rglob("*.npz")) if d.exists() else []


def test_cached_load_equals_fresh_parse(cdir, tmp_path, monkeypatch):
    f = tmp_path / "a.txt"
    f.write_text(TEXT)
    first = read_trajectories(f, 10)
    assert len(_entries(cdir)) == 1
    calls = []
    real = C.cached_arrays.__globals__["_read"]
    monkeypatch.setattr(C, "_read", lambda *a: calls.append(1) or real(*a))
    second = read_trajectories(f, 10)
    assert calls == [1]
    pd.testing.assert_frame_equal(first, _expected(), check_exact=True)
    pd.testing.assert_frame_equal(second, _expected(), check_exact=True)
    monkeypatch.setenv(C.ENV_CACHE, "off")
    pd.testing.assert_frame_equal(read_trajectories(f, 10), _expected(), check_exact=True)


def test_hit_does_not_parse(cdir, tmp_path, monkeypatch):
    f = tmp_path / "a.txt"
    f.write_text(TEXT)
    read_trajectories(f, 10)
    import dslearn.data.ethucy as E

    monkeypatch.setattr(E, "_parse_trajectories", lambda *a: pytest.fail("parsed despite a cache entry"))
    pd.testing.assert_frame_equal(read_trajectories(f, 10), _expected(), check_exact=True)


def test_edit_invalidates(cdir, tmp_path):
    f = tmp_path / "a.txt"
    f.write_text(TEXT)
    read_trajectories(f, 10)
    f.write_text(TEXT.replace("2.0\t2.75", "9.0\t2.75"))  # same size, other content
    got = read_trajectories(f, 10)
    want = _expected()
    want.loc[4, "x"] = 9.0
    pd.testing.assert_frame_equal(got, want, check_exact=True)
    assert len(_entries(cdir)) == 2


def test_settings_are_part_of_the_key(cdir, tmp_path):
    f = tmp_path / "a.txt"
    f.write_text(TEXT)
    read_trajectories(f, 10)  # valid with frame step 10 ...
    with pytest.raises(DataFormatError, match=r"a.txt:1: frame 10 is not a multiple of 20"):
        read_trajectories(f, 20)  # ... not with 20: never answered from the step-10 entry
    read_trajectories(f, None)
    assert len(_entries(cdir)) == 2


def test_invalid_file_is_not_cached(cdir, tmp_path):
    f = tmp_path / "bad.txt"
    f.write_text("10 1 2.0\n")
    for _ in range(2):
        with pytest.raises(DataFormatError, match="bad.txt:1: expected 4 fields"):
            read_trajectories(f, 10)
    assert _entries(cdir) == []


@pytest.mark.parametrize("damage", ["garbage", "truncate", "wrong_arrays", "wrong_dtype"])
def test_corrupt_entry_is_rebuilt(cdir, tmp_path, damage):
    f = tmp_path / "a.txt"
    f.write_text(TEXT)
    read_trajectories(f, 10)
    (entry,) = _entries(cdir)
    if damage == "garbage":
        entry.write_bytes(b"not an npz at all")
    elif damage == "truncate":
        entry.write_bytes(entry.read_bytes()[:100])
    elif damage == "wrong_arrays":
        np.savez(entry, frame=np.zeros(5, np.int64))
    else:
        np.savez(entry, frame=np.zeros(5), ped=np.zeros(5, np.int64), x=np.zeros(5), y=np.zeros(5))
    pd.testing.assert_frame_equal(read_trajectories(f, 10), _expected(), check_exact=True)
    with np.load(entry, allow_pickle=False) as z:  # rebuilt in place
        assert z["frame"].dtype == np.int64 and z["x"].tolist() == [1.5, -3.0, 1.75, -2.5, 2.0]


def test_off_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv(C.ENV_CACHE, "off")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    f = tmp_path / "a.txt"
    f.write_text(TEXT)
    before = sorted(p for p in tmp_path.rglob("*"))
    pd.testing.assert_frame_equal(read_trajectories(f, 10), _expected(), check_exact=True)
    assert sorted(tmp_path.rglob("*")) == before
    assert C.cache_dir() is None


def test_cache_folder_outside_the_repo(monkeypatch, tmp_path):
    repo = Path(__file__).resolve().parents[1]
    monkeypatch.delenv(C.ENV_CACHE, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    assert C.cache_dir() == tmp_path / ".cache" / "dslearn"
    for inside in (repo / "dslearn" / "cache", repo / ".cache"):
        monkeypatch.setenv(C.ENV_CACHE, str(inside))
        with pytest.raises(ConfigError, match=C.ENV_CACHE):
            C.cache_dir()


def test_unwritable_cache_folder_only_costs_the_cache(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    monkeypatch.setenv(C.ENV_CACHE, str(blocker / "sub"))  # a folder under a file: cannot be made
    f = tmp_path / "a.txt"
    f.write_text(TEXT)
    pd.testing.assert_frame_equal(read_trajectories(f, 10), _expected(), check_exact=True)


def test_key_covers_content_settings_and_version(monkeypatch):
    k = C.content_key("trajectories", b"abc", {"frame_step": 10})
    assert k != C.content_key("trajectories", b"abd", {"frame_step": 10})
    assert k != C.content_key("trajectories", b"abc", {"frame_step": None})
    assert k != C.content_key("other", b"abc", {"frame_step": 10})
    monkeypatch.setattr(C.dslearn, "__version__", "999")
    assert k != C.content_key("trajectories", b"abc", {"frame_step": 10})
