"""ETH/UCY loader: malformed files, round trip, real-data counts, dt rules, windows."""


import numpy as np
import pandas as pd
import pytest
import torch

from dslearn.data import ethucy
from dslearn.data.ethucy import default_root, read_trajectories, windows
from dslearn.errors import ConfigError, DataFormatError
from dslearn.schemas.datasets import SCENES, fold_scenes, load_scene, scene_dt

GOOD = "780\t1.0\t8.46\t3.59\n790\t1.0\t9.57\t3.79\n800\t2.0\t13.64\t5.8\n800\t1.0\t10.67\t3.99\n"


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.mark.parametrize(
    "name, text, line, words",
    [
        ("nonnum.txt", "0\t1\t1.0\t2.0\n10\t1\tabc\t2.0\n", 2, "non-numeric"),
        ("cols3.txt", "0\t1\t1.0\t2.0\n10\t1\t2.0\n", 2, "expected 4 fields"),
        ("cols5.txt", "0\t1\t1.0\t2.0\t7\n", 1, "expected 4 fields"),
        ("nan.txt", "0\t1\t1.0\t2.0\n10\t1\t1.5\t2.0\n20\t1\tnan\t2.0\n", 3, "NaN or infinite"),
        ("inf.txt", "0\t1\tinf\t2.0\n", 1, "NaN or infinite"),
        ("dup.txt", "0\t1\t1.0\t2.0\n0\t2\t1.0\t2.0\n0\t1\t1.5\t2.5\n", 3, "duplicate (frame, ped) = (0, 1), first seen at line 1"),
        ("decr.txt", "0\t1\t1.0\t2.0\n10\t1\t1.0\t2.0\n5\t2\t1.0\t2.0\n", 3, "frames must not decrease"),
        ("frac.txt", "0\t1\t1.0\t2.0\n10.5\t1\t1.0\t2.0\n", 2, "frame 10.5 is not an integer"),
        ("fracped.txt", "0\t1.25\t1.0\t2.0\n", 1, "ped_id 1.25 is not an integer"),
        ("blank.txt", "0\t1\t1.0\t2.0\n\n10\t1\t1.0\t2.0\n", 2, "expected 4 fields"),
        ("empty.txt", "", 1, "empty file"),
        ("header.txt", "frame\tped\tx\ty\n0\t1\t1.0\t2.0\n", 1, "(a header line? the files have none)"),
        ("binary.txt", b"\x00\x01\x02\x03", 1, "binary file (NUL byte)"),
        ("binary2.txt", b"0\t1\t1.0\t2.0\n\x7fELF\x02\x01\x00\x00", 2, "binary file (NUL byte)"),
        ("latin1.txt", "0\t1\t1.0\t2.0\n10\t1\t1.5\t2.0\n20\t1\tcaf\xe9\t2\n".encode("latin-1"), 3,
         "byte 0xe9 is not UTF-8 text (a Latin-1 or binary file?)"),
        ("bom.txt", b"\xef\xbb\xbf0\t1\t1.0\t2.0\n", 1, "UTF-8 byte-order mark (BOM)"),
        ("utf16.txt", "0\t1\t1.0\t2.0\n".encode("utf-16"), 1, "UTF-16 text"),
        ("dupfirst.txt", "0\t1\t1.0\t2.0\n0\t1\t1.0\t2.0\n", 2, "duplicate (frame, ped) = (0, 1), first seen at line 1"),
        ("crlf_nan.txt", "0\t1\t1.0\t2.0\r\n10\t1\t-inf\t2.0\r\n", 2, "NaN or infinite value"),
    ],
)
def test_malformed_files(tmp_path, name, text, line, words):
    """Every malformed file is refused with ONE line ``<file>:<line>: <what>`` (the CLI prints it
    as ``dslearn-run: data error: ...``, exit code 2; see tests/test_bad_input.py)."""
    p = tmp_path / name
    p.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(DataFormatError) as e:
        read_trajectories(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}:{line}: "), msg
    assert words in msg
    assert "\n" not in msg


def test_folder_instead_of_file(tmp_path):
    (tmp_path / "biwi_eth.txt").mkdir()
    with pytest.raises(DataFormatError, match="biwi_eth.txt: is a folder, expected a trajectory file"):
        read_trajectories(tmp_path / "biwi_eth.txt")


def test_good_file_round_trip(tmp_path):
    p = _write(tmp_path, "good.txt", GOOD)
    df = read_trajectories(p)
    assert list(df.columns) == ["frame", "ped", "x", "y"]
    assert df.dtypes["frame"] == np.int64 and df.dtypes["ped"] == np.int64
    assert df.dtypes["x"] == np.float64 and df.dtypes["y"] == np.float64
    # sorted by (frame, ped): the two rows of frame 800 swap
    assert df[["frame", "ped"]].values.tolist() == [[780, 1], [790, 1], [800, 1], [800, 2]]
    assert df.x.tolist() == [8.46, 9.57, 10.67, 13.64]
    # write it back in the standard format and read it again: identical
    q = tmp_path / "again.txt"
    q.write_text("".join(f"{r.frame}\t{float(r.ped)}\t{r.x!r}\t{r.y!r}\n" for r in df.itertuples()))
    pd.testing.assert_frame_equal(read_trajectories(q), df)


def test_scene_from_fixture_files(tmp_path, monkeypatch):
    # two-file scene: ped ids made unique, steps rebased per file, t = step * dt
    _write(tmp_path, "students001.txt", "10.0\t1.0\t0.0\t0.0\n20.0\t1.0\t0.5\t0.0\n30.0\t1.0\t1.0\t0.0\n")
    _write(tmp_path, "students003.txt", "100.0\t1.0\t5.0\t5.0\n110.0\t1.0\t5.0\t5.5\n")
    sc = load_scene("univ", root=tmp_path)
    assert sc.dt == 0.4 and sc.convention == "benchmark"
    assert sc.df.ped.tolist() == [1, 1, 1, 100001, 100001]
    assert sc.df.step.tolist() == [0, 1, 2, 0, 1]
    assert np.allclose(sc.df.t, [0.0, 0.4, 0.8, 0.0, 0.4])
    tr = sc.tracks()
    assert set(tr) == {1, 100001}
    assert tr[1].dtype == torch.float64 and tr[1].shape == (3, 3)
    assert torch.equal(tr[100001][:, 0], torch.tensor([0.0, 1.0], dtype=torch.float64))
    # windows of 2 steps: both files contribute; peds present in all steps only
    pos, meta = windows(sc, length=2, stride=1, min_peds=1)
    assert pos.shape == (3, 2, 1, 2) and meta.num_peds.tolist() == [1, 1, 1]
    assert torch.isfinite(pos).all()
    # data root from the environment
    monkeypatch.setenv(ethucy.ENV_ROOT, str(tmp_path))
    assert default_root() == tmp_path
    monkeypatch.setenv(ethucy.ENV_ROOT, str(tmp_path / "missing"))
    with pytest.raises(ConfigError, match=r"set task.data_root=<folder> \(or \$DSLEARN_ETHUCY_ROOT\)"):
        default_root()
    with pytest.raises(ConfigError, match=r"task.data_root='.*missing' does not exist"):
        load_scene("zara1", root=tmp_path / "missing")


def test_frame_not_multiple_of_ten(tmp_path):
    _write(tmp_path, "crowds_zara01.txt", "0\t1\t0.0\t0.0\n15\t1\t0.5\t0.0\n")
    with pytest.raises(DataFormatError, match="crowds_zara01.txt.*multiple of 10"):
        load_scene("zara1", root=tmp_path)


def test_tracks_gap_is_an_error(tmp_path):
    _write(tmp_path, "crowds_zara01.txt", "0\t1\t0.0\t0.0\n10\t1\t0.5\t0.0\n30\t1\t1.0\t0.0\n")
    sc = load_scene("zara1", root=tmp_path)
    with pytest.raises(DataFormatError, match="gap"):
        sc.tracks()


def test_dt_rules_and_config_errors():
    assert scene_dt("biwi_eth.txt") == 0.4
    assert scene_dt("biwi_eth.txt", "physical") == pytest.approx(10 / 15)
    assert scene_dt("/some/where/biwi_eth.txt", "physical") == pytest.approx(2 / 3)
    for f in ("biwi_hotel.txt", "crowds_zara01.txt", "students001.txt", "uni_examples.txt"):
        assert scene_dt(f, "physical") == 0.4 and scene_dt(f, "benchmark") == 0.4
    with pytest.raises(ConfigError, match="convention"):
        scene_dt("biwi_eth.txt", "wallclock")
    with pytest.raises(ConfigError, match="scene"):
        load_scene("atlantis")
    assert fold_scenes("zara1") == (("zara1",), ("eth", "hotel", "zara2", "univ", "zara3", "uni_examples"))
    assert SCENES["univ"] == ("students001.txt", "students003.txt")


def _real_root():
    try:
        return default_root()
    except ConfigError:
        return None


REAL = _real_root()
README_ROWS = {  # the README's section-2 table: rows, pedestrians, peds with >= 20 rows
    "biwi_eth.txt": (5492, 360, 44),
    "biwi_hotel.txt": (6543, 389, 122),
    "crowds_zara01.txt": (5153, 148, 142),
    "crowds_zara02.txt": (9722, 204, 189),
    "crowds_zara03.txt": (5005, 137, 120),
    "students001.txt": (21813, 415, 352),
    "students003.txt": (17953, 434, 370),
    "uni_examples.txt": (2747, 118, 82),
}


@pytest.mark.skipif(REAL is None, reason="ETH/UCY data root not found")
def test_real_data_counts_and_dt():
    for fname, (rows, peds, long_) in README_ROWS.items():
        df = read_trajectories(REAL / fname)
        assert len(df) == rows, fname
        assert df.ped.nunique() == peds, fname
        assert int((df.groupby("ped").size() >= 20).sum()) == long_, fname
    eth_b, eth_p = load_scene("eth"), load_scene("eth", convention="physical")
    assert eth_b.dt == 0.4 and eth_p.dt == pytest.approx(2 / 3)
    assert np.allclose(eth_p.df.t, eth_p.df.step * (2 / 3))
    univ = load_scene("univ")
    assert len(univ.df) == 21813 + 17953 and univ.df.ped.nunique() == 415 + 434
    # the README's median step speeds (Delta t = 0.4 s): ETH 2.45, ZARA1 1.15 m/s
    for name, med in (("eth", 2.45), ("zara1", 1.15)):
        sc = load_scene(name)
        d = sc.df.sort_values(["ped", "step"])
        dx = d.groupby("ped")[["x", "y"]].diff().dropna()
        assert np.median(np.hypot(dx.x, dx.y)) / 0.4 == pytest.approx(med, abs=0.01)
    # windows: every agent of a window present at all 20 steps, >= 2 agents (benchmark rule)
    pos, meta = windows(load_scene("zara1"), length=20, stride=1, min_peds=2)
    assert (meta.num_peds >= 2).all()
    present = torch.isfinite(pos).all(-1)
    for i in range(0, len(meta), 37):
        k = meta.num_peds[i]
        assert present[i, :, :k].all() and not present[i, :, k:].any()


def test_split_scene_by_time_per_file(tmp_path):
    """The benchmark's validation part starts at each file's first validation frame (the data set
    YAML's ``val_first_frame``, carried by the Scene): a time split (no row in both parts, nothing
    lost); files without a split go wholly to train."""
    from dslearn.data.ethucy import Scene, split_scene
    from dslearn.schemas.datasets import VAL_FIRST_FRAME

    cut = VAL_FIRST_FRAME["crowds_zara01.txt"]
    frames = [cut - 20, cut - 10, cut, cut + 10]
    df = pd.DataFrame({"frame": frames * 2, "ped": [1] * 4 + [2] * 4, "x": np.arange(8.0), "y": np.zeros(8),
                       "file": ["crowds_zara01.txt"] * 4 + ["fixture.txt"] * 4})
    sc = Scene(name="toy", dt=0.4, convention="benchmark", df=df, val_first_frame={"crowds_zara01.txt": cut})
    assert cut == 7110  # conf/dataset/zara1.yaml, as the data README's section 3
    tr, va = split_scene(sc, "train"), split_scene(sc, "val")
    assert sorted(va.df["frame"]) == [cut, cut + 10]
    assert (va.df["file"] == "crowds_zara01.txt").all()
    assert len(tr.df) == 6 and (tr.df[tr.df["file"] == "crowds_zara01.txt"]["frame"] < cut).all()
    assert split_scene(sc, "all") is sc
    with pytest.raises(ConfigError, match="part"):
        split_scene(sc, "test")


def test_physical_time_step_of_eth(tmp_path):
    """Under the physical convention the biwi_eth rows are 10/15 s apart, the others 0.4 s, and the
    scene carries that step."""
    root = tmp_path
    (root / "biwi_eth.txt").write_text(GOOD)
    (root / "biwi_hotel.txt").write_text(GOOD)
    eth = load_scene("eth", root=root, convention="physical")
    hotel = load_scene("hotel", root=root, convention="physical")
    assert eth.dt == pytest.approx(2 / 3) and hotel.dt == pytest.approx(0.4)
    assert load_scene("eth", root=root, convention="benchmark").dt == pytest.approx(0.4)
