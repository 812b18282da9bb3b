"""A user's config folder (``hydra.searchpath=[file:///abs/folder]``) is part of the configuration everywhere: its
scenario, motion model and method preset options work in a single run, in the up-front check of a sweep (every
job composed with the user's folder) and in every launcher (the default joblib one, whose workers are other
processes, and the basic one), and the listings of a group's options (``task.left_out``, a task's models) count
them."""

import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml

from dslearn import conf_paths, search_path

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
TINY = ["task.train_episodes=1", "task.test_episodes=1", "progress=false"]


def _user_folder(tmp_path) -> Path:
    """A folder of the user's own options: scenario ``my_scene`` (Yu's two agents), model ``my_lin`` (the constant
    velocity with another noise and name) and method preset ``my_preset`` (Yu's EKF with ``my_lin``)."""
    folder = tmp_path / "my conf"  # a space in the path: quoted where it is passed on
    for group in ("scenario", "model", "method"):
        (folder / group).mkdir(parents=True)
    (folder / "scenario" / "my_scene.yaml").write_text((CONF / "scenario" / "yu_two_agents.yaml").read_text())
    lin = yaml.safe_load((CONF / "model" / "lin.yaml").read_text())
    assert lin["noise_std"] != 0.25
    (folder / "model" / "my_lin.yaml").write_text(yaml.safe_dump({**lin, "name": "my_lin", "noise_std": 0.25}))
    preset = (CONF / "method" / "ekf_lin_hybrid.yaml").read_text()
    assert "override /model: lin\n" in preset
    (folder / "method" / "my_preset.yaml").write_text(preset.replace("override /model: lin\n",
                                                                     "override /model: my_lin\n"))
    return folder


def _run(tmp_path, *args):
    cmd = [sys.executable, "-m", "dslearn.run", *args]
    env = {**os.environ, "CI": "1"}
    return subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)


def _search(folder: Path) -> str:
    return f"hydra.searchpath=['file://{folder.as_posix()}']"


def test_a_sweep_over_the_users_scenario_and_model_with_the_default_launcher(tmp_path):
    """Any -m sweep over a user's scenario passes the up-front check and runs, with the default (joblib)
    launcher; the user's model joins the sweep too."""
    folder = _user_folder(tmp_path)
    sweep = tmp_path / "sweep"
    r = _run(tmp_path, "-m", "task=matrix", "method=ekf_lin_hybrid", "model=lin,my_lin", "scenario=my_scene",
             _search(folder), *TINY, f"hydra.sweep.dir={sweep}")
    assert r.returncode == 0, r.stderr[-3000:]
    for job, (model, noise) in enumerate((("lin", 0.1), ("my_lin", 0.25))):
        res = pd.read_csv(sweep / str(job) / "results.csv")
        assert set(res["method"]) == {f"ekf {model} hybrid"} and set(res["scenario"]) == {"yu"}
        assert res.loc[res["metric"] == "rmse", "value"].notna().all()
        cfg = yaml.safe_load((sweep / str(job) / "config.yaml").read_text())
        assert cfg["model"]["name"] == model and cfg["model"]["noise_std"] == noise


def test_a_matrix_sweep_of_the_users_preset_with_the_basic_launcher(tmp_path):
    """The matrix sweeper over the user's preset and scenario (with a packaged one it does not fit and one that
    task.left_out names): the up-front check, the sweeper's judgement and the basic launcher's jobs all find the
    user's options."""
    folder = _user_folder(tmp_path)
    sweep = tmp_path / "sweep"
    r = _run(tmp_path, "-m", "task=matrix", "hydra/sweeper=matrix", "hydra/launcher=basic", "method=my_preset",
             "scenario=my_scene,yu_two_agents,jiang",
             "task.left_out=[{method: my_preset, scenarios: [yu_two_agents], why: 'the packaged one: not mine'}]",
             _search(folder), *TINY, f"hydra.sweep.dir={sweep}")
    assert r.returncode == 0, r.stderr[-3000:]
    cells = pd.read_csv(sweep / "matrix_cells.csv", keep_default_na=False)
    assert list(cells["status"]) == ["run", "left_out", "does_not_fit"]
    assert list(cells["method"]) == ["ekf my_lin hybrid"] * 3 and cells["job"].tolist() == ["0", "", ""]
    assert cells["reason"].iloc[1].endswith("(task.left_out): the packaged one: not mine")
    assert "the sensors of scenario jiang have none" in cells["reason"].iloc[2]  # hybrid consensus needs a graph
    res = pd.read_csv(sweep / "0" / "results.csv")
    assert set(res["method"]) == {"ekf my_lin hybrid"} and set(res["scenario"]) == {"yu"}
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir() and p.name.isdigit()) == ["0"]
    cfg = yaml.safe_load((sweep / "0" / "config.yaml").read_text())
    assert cfg["model"]["noise_std"] == 0.25


@pytest.fixture
def user_dirs():
    """The process's config folders restored after the test (adding a search path is for the whole command)."""
    dirs, path = list(conf_paths.CONF_DIRS), list(search_path.SEARCH_PATH)
    yield
    conf_paths.CONF_DIRS[:] = dirs
    search_path.SEARCH_PATH[:] = path


def test_the_option_listings_and_compositions_include_the_users_folder(tmp_path, user_dirs):
    """In one process: the up-front check of a single run, the listing of a group's options (task.left_out) and
    the composition of several options of a group (a task's models) see the user's options once their folder is
    on the search path; a search path that is no folder is refused naming it."""
    from omegaconf import OmegaConf

    from dslearn import api
    from dslearn.compose import group_options
    from dslearn.errors import ConfigError
    from dslearn.app.precheck import precheck
    from dslearn.schemas.matrix import left_out

    folder = _user_folder(tmp_path)
    entry = "[{method: my_preset, scenarios: [my_scene], why: mine}]"
    assert precheck(["task=matrix", "method=my_preset", "scenario=my_scene", f"task.left_out={entry}",
                     _search(folder), *TINY]) is None
    assert folder.resolve() in conf_paths.CONF_DIRS
    cfg = api.compose("task=matrix", "method=my_preset", "scenario=my_scene", *TINY)  # the folder is the command's
    assert cfg.model.name == "my_lin" and cfg.model.noise_std == 0.25
    assert left_out(OmegaConf.merge(cfg, {"task": {"left_out": [{"method": "my_preset", "scenarios": ["my_scene"],
                                                                   "why": "mine"}]}}),
                    ["method=my_preset", "scenario=my_scene"]) == "mine"
    nodes = group_options("model", ["lin", "my_lin"])
    assert (nodes["lin"].noise_std, nodes["my_lin"].noise_std) == (0.1, 0.25)
    with pytest.raises(ConfigError, match="hydra.searchpath: file:///no/such/folder is not a folder"):
        search_path.add_search_path(["file:///no/such/folder"])
