"""Packaging: the Hydra configs ship inside the package (``dslearn.conf``), every package is listed in
``pyproject.toml``, and users add their own config folders through ``hydra.searchpath``."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from dslearn.schemas.core import CONF_DIR

ROOT = Path(__file__).resolve().parents[1]

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    tomllib = None


@pytest.mark.skipif(tomllib is None, reason="tomllib needs Python >= 3.11")
def test_pyproject_lists_every_package_and_the_configs():
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    found = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "dslearn").rglob("__init__.py")}
    listed = set(meta["packages"])
    assert listed == found | {"dslearn.conf", "hydra_plugins.dslearn_matrix"}, (found - listed, listed - found)
    assert meta["package-dir"] == {"dslearn.conf": "conf"}
    patterns = meta["package-data"]["dslearn.conf"]
    # every config file is matched by a package-data pattern (top level or one group folder deep)
    for f in (ROOT / "conf").rglob("*"):
        if f.is_file() and f.name != "__init__.py" and "__pycache__" not in f.parts:
            rel = f.relative_to(ROOT / "conf")
            assert f.suffix == ".yaml", f"conf/{rel}: only YAML files ship as configs"
            assert any(rel.match(p) for p in patterns) and len(rel.parts) <= 2, f"conf/{rel} would not ship"


@pytest.mark.skipif(tomllib is None, reason="tomllib needs Python >= 3.11")
def test_shipped_data_sets_are_package_data():
    """Every file of a data folder inside a package (a scenario's ``pkg://dslearn.data/<folder>`` root) ships."""
    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["dslearn.data"]
    data = ROOT / "dslearn" / "data"
    files = [f for f in data.rglob("*") if f.is_file() and f.parent != data and "__pycache__" not in f.parts]
    assert any(f.name == "corridor.txt" for f in files)
    for f in files:
        rel = f.relative_to(data)
        assert any(rel.match(p) for p in patterns), f"dslearn/data/{rel} would not ship"


def test_packaged_config_folder_is_the_one_composed():
    assert (CONF_DIR / "config.yaml").is_file() and (CONF_DIR / "experiment" / "yu_table1.yaml").is_file()


def _run(args, cwd):
    return subprocess.run([sys.executable, "-m", "dslearn.run", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=300)


def test_user_config_folder_through_searchpath(tmp_path):
    user = tmp_path / "my_conf"
    (user / "model").mkdir(parents=True)
    text = (CONF_DIR / "model" / "lin.yaml").read_text().replace("noise_std: 0.1", "noise_std: 0.25")
    assert "noise_std: 0.25" in text
    (user / "model" / "my_lin.yaml").write_text(text)
    out = tmp_path / "run"
    work = tmp_path / "elsewhere"
    work.mkdir()
    common = ["data.train_episodes=2", "data.test_episodes=2", "progress=false"]
    r = _run([f"hydra.searchpath=[file://{user}]", "model=my_lin", f"hydra.run.dir={out}", *common], work)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (out / "results.csv").is_file()
    cfg = (out / ".hydra" / "config.yaml").read_text()
    assert "noise_std: 0.25" in cfg
    # without the search path the option is unknown: one line naming the group and its options, exit 2
    r = _run(["model=my_lin", f"hydra.run.dir={tmp_path / 'never'}", *common], work)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    line = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(line) == 1 and "'model'" in line[0] and "'lin'" in line[0], r.stderr
    assert not (tmp_path / "never").exists()
    # a search-path entry that is not a folder
    r = _run([f"hydra.searchpath=[file://{tmp_path / 'missing'}]", f"hydra.run.dir={tmp_path / 'never'}"], work)
    assert r.returncode == 2 and "hydra.searchpath" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "never").exists()
    shutil.rmtree(out)
