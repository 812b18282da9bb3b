"""Data sets by configuration: a new data set is one YAML (no code change), the packaged ETH/UCY
data sets compose and load, and both real-data studies run on a new data set end to end through
``dslearn-run`` with ``dslearn-report`` on the output."""

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hydra import compose, initialize_config_dir

from dslearn.schemas.core import CONF_DIR
from dslearn.data.datasets import DatasetSpec, leave_one_out, load_dataset, task_datasets
from dslearn.data.ethucy import data_available, default_root, split_scene
from dslearn.errors import ConfigError, DataFormatError
from dslearn.schemas import validate_task
from dslearn.schemas.datasets import packaged_dataset, packaged_folds, packaged_names, spec_from_config

ETHUCY = ("eth", "hotel", "zara1", "zara2", "univ", "zara3", "uni_examples")


def walkers_file(path: Path, scale: float = 1.0) -> Path:
    """Three pairs of pedestrians walking straight, side by side 1 m apart, in the 4-column format
    (frame, ped, x, y; a row every 10 frames, tab-separated), one pair after the other in time."""
    rows = []
    for k in range(3):
        f0, y0, v = 60 * k, 1.0 + 3.5 * k, (0.6 + 0.1 * k, 0.05 * (k - 1))  # start step, lane, m/s
        for j in range(2):
            for s in range(80):
                t = 0.4 * s
                rows.append((10 * (f0 + s), 2 * k + j + 1, (1.0 + v[0] * t) * scale, (y0 + j + v[1] * t) * scale))
    rows.sort()
    path.write_text("".join(f"{f}\t{float(p)}\t{x!r}\t{y!r}\n" for f, p, x, y in rows))
    return path


def walkers_yaml(folder: Path, data: Path, **extra) -> Path:
    conf = folder / "dataset"
    conf.mkdir(parents=True, exist_ok=True)
    fields = {"label": "'Walkers (synthetic)'", "files": f"[{data.name}]", "root": f"'{data.parent}'", "frame_step": 10,
              "dt": 0.4, "fps": 25.0, "units": "m", "val_first_frame": "[1500]", **extra}
    (conf / "walkers.yaml").write_text("".join(f"{k}: {v}\n" for k, v in fields.items()))
    return conf / "walkers.yaml"


def dslearn(module: str, *args) -> subprocess.CompletedProcess:
    env = dict(os.environ, CI="1", OMP_NUM_THREADS="1")
    return subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True, env=env, timeout=600)


def test_a_new_data_set_is_one_yaml(tmp_path):
    data = walkers_file(tmp_path / "walkers.txt")
    walkers_yaml(tmp_path / "conf", data)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = compose("config", overrides=["experiment=ethucy_forecast", f"hydra.searchpath=[file://{tmp_path / 'conf'}]",
                                           "+dataset@task.datasets.walkers=walkers", "task.scenes=[walkers]"])
    validate_task(cfg)
    specs = task_datasets(cfg.task)
    assert set(specs) == {*ETHUCY, "walkers"}
    w = specs["walkers"]
    assert (w.label, w.files, w.frame_step, w.step("benchmark"), w.step("physical")) == ("Walkers (synthetic)", ("walkers.txt",), 10, 0.4, 0.4)
    # the ETH/UCY folds are untouched by the new data set
    assert list(cfg.task.folds.pool) == list(ETHUCY) and "walkers" not in cfg.task.folds.test
    sc = load_dataset(w, None, "benchmark")
    assert (sc.name, sc.label, sc.df.ped.nunique(), len(sc.df)) == ("walkers", "Walkers (synthetic)", 6, 480)
    # positions exactly as written; step and time from frame_step and dt
    raw = pd.read_csv(data, sep="\t", header=None, names=["frame", "ped", "x", "y"]).sort_values(["frame", "ped"])
    np.testing.assert_array_equal(sc.df.x.to_numpy(), raw.x.to_numpy())
    assert sc.df.step.tolist() == (raw.frame // 10).tolist() and np.allclose(sc.df.t, sc.df.step * 0.4, rtol=0, atol=1e-12)
    # the benchmark split from val_first_frame: frames >= 1500 are the validation part
    tr, va = split_scene(sc, "train"), split_scene(sc, "val")
    assert len(tr.df) + len(va.df) == 480 and tr.df.frame.max() < 1500 <= va.df.frame.min()


def test_units_root_and_file_options(tmp_path):
    walkers_file(tmp_path / "w.txt")
    metres = load_dataset(DatasetSpec("m", "M", ("w.txt",), root=str(tmp_path)), None)
    walkers_file(tmp_path / "w_cm.txt", scale=100.0)
    cm = load_dataset(DatasetSpec("cm", "CM", ("w_cm.txt",), root=str(tmp_path), units="cm"), None)
    np.testing.assert_allclose(cm.df[["x", "y"]].to_numpy(), metres.df[["x", "y"]].to_numpy(), rtol=1e-12, atol=1e-12)
    # an absolute file needs no root at all; the data set's own root wins over task.data_root
    absolute = load_dataset(DatasetSpec("abs", "A", (str(tmp_path / "w.txt"),)), tmp_path / "nowhere")
    pd.testing.assert_frame_equal(absolute.df.drop(columns="file"), metres.df.drop(columns="file"))
    with pytest.raises(ConfigError, match=r"task\.datasets\.m\.root='.*missing' does not exist"):
        load_dataset(DatasetSpec("m", "M", ("w.txt",), root=str(tmp_path / "missing")), None)
    with pytest.raises(ConfigError, match=r"task\.data_root='.*' has no file nope\.txt \(scene x\)"):
        load_dataset(DatasetSpec("x", "X", ("nope.txt",)), tmp_path)
    # physical time from the frame rate: 10 frames at 15 fps
    assert DatasetSpec("e", "E", ("a",), fps=15.0).step("physical") == 10 / 15
    assert DatasetSpec("e", "E", ("a",), fps=None).step("physical") == 0.4
    with pytest.raises(DataFormatError, match="not a multiple of 20"):
        load_dataset(DatasetSpec("s", "S", ("w.txt",), root=str(tmp_path), frame_step=20), None)
    with pytest.raises(ConfigError, match="unknown keys"):
        spec_from_config("bad", {"label": "B", "files": ["a"], "colour": "red"})
    # a data set without a label is shown by its name (the report never needs a built-in label)
    assert spec_from_config("mall", {"files": ["a.txt"]}).label == "mall"


BAD_DATASETS = [
    {"files": []},
    {"files": ["a"], "frame_step": 0},
    {"files": ["a"], "frame_step": -3},
    {"files": ["a"], "dt": 0.0},
    {"files": ["a"], "dt": -0.4},
    {"files": ["a"], "dt": float("inf")},
    {"files": ["a"], "fps": 0.0},
    {"files": ["a"], "fps": float("nan")},
    {"files": ["a"], "units": "km"},
    {"files": ["a"], "colour": "red"},
    {"files": ["a"], "colour": "red", "shade": 1},
]
GOOD_DATASETS = [
    {"files": ["a"]},
    {"label": "L", "files": ["a", "b"], "root": None, "frame_step": 1, "dt": 1e-3, "fps": None, "units": "cm",
     "val_first_frame": [10, 20]},
    {"files": ["a"], "frame_step": True},  # a bool is no number here (the composed schema refuses its type)
]


@pytest.mark.parametrize("plain", [True, False], ids=["dict", "DictConfig"])
def test_the_data_layer_checks_a_data_set_as_the_schema_rules_say(plain):
    """``check_dataset`` (the data layer, plain Python) refuses exactly what the validation layer's
    ``check_ranges`` refuses under the same rules (:data:`DATASET_RULES` as ``ranged`` fields), with the
    same message, on plain values and on config nodes; it adds one ``val_first_frame`` per file."""
    import dataclasses

    from omegaconf import OmegaConf

    from dslearn.data.datasets import DATASET_RULES, check_dataset
    from dslearn.schemas.base import check_ranges, ranged

    rules = dataclasses.make_dataclass("Rules", [(k, object, ranged(None, **r)) for k, r in DATASET_RULES.items()])
    node = (lambda v: v) if plain else OmegaConf.create
    for values in BAD_DATASETS:
        with pytest.raises(ConfigError) as want:
            check_ranges(node(values), rules, "task.datasets.x")
        with pytest.raises(ConfigError) as got:
            check_dataset("x", node(values), "task.datasets.x")
        assert str(got.value) == str(want.value), values
    for values in GOOD_DATASETS:
        check_ranges(node(values), rules, "task.datasets.x")
        check_dataset("x", node(values), "task.datasets.x")
    with pytest.raises(ConfigError, match=r"^task\.datasets\.x\.val_first_frame has 1 entries for 2 files; give one per file or null$"):
        check_dataset("x", node({"files": ["a", "b"], "val_first_frame": [5]}), "task.datasets.x")
    with pytest.raises(ConfigError, match=r"^task\.datasets\.x\.frame_step=0 must be >= 1$"):
        check_dataset("x", node({"files": ["a"], "frame_step": 0}), "task.datasets.x")


def test_every_packaged_data_set_composes_and_matches_the_folds():
    assert set(packaged_names()) == set(ETHUCY)
    folds = packaged_folds("ethucy")
    assert folds["test"] == ["eth", "hotel", "univ", "zara1", "zara2"] and folds["pool"] == list(ETHUCY)
    assert leave_one_out("zara1", folds["pool"]) == ("eth", "hotel", "zara2", "univ", "zara3", "uni_examples")
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        for exp in ("ethucy_forecast", "real_tables", "gp_vs_lstm"):
            cfg = compose("config", overrides=[f"experiment={exp}"])
            validate_task(cfg)
            specs = task_datasets(cfg.task)
            assert set(specs) == set(ETHUCY), exp
            for name in ETHUCY:  # what the task composes is exactly the packaged YAML
                assert specs[name] == packaged_dataset(name), name
    eth = packaged_dataset("eth")
    assert eth.step("benchmark") == 0.4 and eth.step("physical") == 10.0 / 15.0 and eth.label == "ETH"
    assert packaged_dataset("univ").split() == {"students001.txt": 3550, "students003.txt": 4320}


@pytest.mark.skipif(not data_available(), reason="the ETH/UCY data folder ($DSLEARN_ETHUCY_ROOT or ../shared/data/eth_ucy) is absent")
def test_every_packaged_data_set_loads():
    counts = {"eth": 5492, "hotel": 6543, "zara1": 5153, "zara2": 9722, "univ": 21813 + 17953, "zara3": 5005, "uni_examples": 2747}
    for name in packaged_names():
        spec = packaged_dataset(name)
        sc = load_dataset(spec, default_root(), "physical")
        assert len(sc.df) == counts[name] and sc.label == spec.label and sc.dt == spec.step("physical"), name
        assert set(sc.val_first_frame) == set(spec.files)


def _run_and_report(tmp_path, name, *overrides):
    out = tmp_path / name
    r = dslearn("dslearn.run", *overrides, f"hydra.searchpath=[file://{tmp_path / 'conf'}]",
                "+dataset@task.datasets.walkers=walkers", f"hydra.run.dir={out}", "progress=false")
    assert r.returncode == 0, r.stderr[-3000:]
    res = pd.read_csv(out / "results.csv")
    rep = dslearn("dslearn.report", str(out))
    assert rep.returncode == 0, rep.stderr[-3000:]
    return res, out


def test_both_real_data_studies_run_on_a_new_data_set(tmp_path):
    """The acceptance test: a data set the code has never heard of, one YAML in the user's own
    config folder, both studies through ``dslearn-run`` and ``dslearn-report``."""
    walkers_yaml(tmp_path / "conf", walkers_file(tmp_path / "walkers.txt"))
    # forecasting: train and test on the new data set (its train / validation parts train the LSTM)
    res, out = _run_and_report(
        tmp_path, "forecast", "experiment=ethucy_forecast", "task.scenes=[walkers]", "task.train_scenes=[walkers]",
        "task.predictors=[cv,gp,lstm]", "task.max_test_windows=10", "task.lstm.epochs=2", "task.lstm.embed=8",
        "task.lstm.hidden=8", "task.gp.points=100", "task.gp.fit_points=40", "task.gp.fit_iters=2", "task.train_stride=5")
    assert set(res.scene) == {"walkers"} and set(res.model) == {"cv", "gp", "lstm"}
    ade = res[res.metric.isin(["ade", "fde"])]
    assert len(ade) == 6 and ade.value.map(math.isfinite).all()
    # straight walking at constant speed: constant velocity is exact, and so is the GP (identity prior mean
    # on the velocity: every training target equals its input, the correction k^T K^{-1} 0 is 0)
    exact = ade[ade.model.isin(["cv", "gp"])]
    assert len(exact) == 4 and (exact.value < 1e-9).all(), exact
    text = (out / "ethucy_forecast.md").read_text()
    assert "Walkers (synthetic)" in text and (out / "report.md").is_file()
    # the LSTM's learning curves go to the run folder (task.curves_file, relative: inside it)
    curves = pd.read_csv(out / "learning_curves.csv")
    assert set(curves.model) == {"lstm"} and set(curves.scene) == {"walkers"} and curves.epoch.tolist() == [1, 2]
    # tracking (Tables III-IV analogue) on the same data set
    res, out = _run_and_report(
        tmp_path, "tracking", "experiment=real_tables", "task.scenes=[walkers]", "task.train_episodes=3",
        "task.test_episodes=2", "task.plot_episodes=1", "task.models=[gp,lin,sfm]", "+task.model_keys.sfm.refine_iters=2",
        "+task.model_keys.sfm.tau_grid=[1.0]", "+task.model_keys.sfm.alpha_grid=[0.0,1.0]", "+task.model_keys.sfm.beta_grid=[1.0]")
    sens = res[res.node_kind == "sensor"]
    assert set(res.scene) == {"walkers"} and {"track_err", "pred_err"} <= set(sens.metric)
    assert sens.value.map(math.isfinite).all() and len(sens) > 0
    assert "Walkers (synthetic)" in (out / "ethucy_table3.md").read_text()
