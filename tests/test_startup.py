"""Instant commands (issue 25): ``dslearn-run --help``, ``--version``, a refused group option and a
completion request import neither PyTorch nor GPyTorch nor numba (checked in a fresh interpreter's
``sys.modules``, not by timing); what they print is checked against independent sources (the
package metadata, the config folders, Hydra's own completion). Also: "did you mean" hints whose
suggested fix works, ``device=cuda`` without CUDA refused before a run folder exists, Ctrl-C at
start-up (one line, exit 130), the other programs' help, LICENSE / CHANGELOG / version."""

from __future__ import annotations

import importlib.metadata
import json
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
HEAVY = ("torch", "gpytorch", "numba")

# runs dslearn-run's main() as the console script does, then reports the exit code and which heavy
# modules the process imported; TRIGGER (optional): send this process SIGINT when that module is imported
WRAPPER = r"""
import json, os, signal, sys
# Ctrl-C as at a terminal: a process started in the background by a shell without job control inherits an
# ignored SIGINT, and dslearn-run (rightly) keeps ignoring it
signal.signal(signal.SIGINT, signal.default_int_handler)
argv, trigger = json.loads(sys.argv[1]), sys.argv[2]
if trigger:
    class _Hook:
        def find_spec(self, name, path=None, target=None):
            if name == trigger:
                os.kill(os.getpid(), signal.SIGINT)
            return None
    sys.meta_path.insert(0, _Hook())
sys.argv = ["dslearn-run"] + argv
from dslearn.run import main
code = 0
try:
    main(argv)
except SystemExit as e:
    code = e.code if isinstance(e.code, int) else 1
sys.stdout.flush()
print("\n@@" + json.dumps({"code": code, "heavy": sorted(m for m in %r if m in sys.modules)}))
""" % (HEAVY,)


def run_cli(argv, trigger="", env=None, cwd=None):
    """``(exit code, stdout without the report line, stderr, heavy modules imported)``."""
    e = {**os.environ, "CI": "1", **(env or {})}
    if "COMP_LINE" not in (env or {}):
        e.pop("COMP_LINE", None)
    r = subprocess.run([sys.executable, "-c", WRAPPER, json.dumps(list(argv)), trigger], cwd=cwd or ROOT, env=e,
                       capture_output=True, text=True, timeout=300)
    out, sep, tail = r.stdout.rpartition("\n@@")
    if not sep:  # the process ended before the wrapper's report (os._exit): its own exit code
        return r.returncode, r.stdout, r.stderr, None
    rep = json.loads(tail)
    return rep["code"], out, r.stderr, rep["heavy"]


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


def test_help_version_and_refused_option_import_no_heavy_module():
    code, out, err, heavy = run_cli(["--help"])
    assert (code, heavy) == (0, []), err
    assert out.startswith(f"dslearn-run {importlib.metadata.version('dslearn')}:")
    for g in ("model", "filter", "consensus", "experiment"):  # every option of every group is listed
        for o in options(g):
            assert re.search(rf"^\s+[* ]?\s*{re.escape(o)}\b", out, re.M), (g, o)

    code, out, err, heavy = run_cli(["--version"])
    assert (code, heavy, out.strip()) == (0, [], f"dslearn-run (dslearn) {importlib.metadata.version('dslearn')}")

    code, out, err, heavy = run_cli(["model=typo", "hydra.run.dir=never"])
    assert (code, heavy) == (2, []), err
    assert err.strip().splitlines() == [
        f"dslearn-run: configuration error: model='typo' is not an option of the config group 'model'; "
        f"choose one of {options('model')}"]

    # a misspelt option: the closest names as working fixes; a sweep value is checked as cheaply
    code, out, err, heavy = run_cli(["-m", "model=lin,gp_incremnt"])
    assert (code, heavy) == (2, []), err
    assert err.strip().endswith("; did you mean model=gp_increment or model=gp_increment_rbcm?"), err
    # filter=ekf: refused, naming the EKF's option
    code, out, err, heavy = run_cli(["filter=ekf"])
    assert (code, heavy) == (2, []), err
    assert err.strip().endswith("the extended information filter (EKF) is filter=default"), err
    assert not (ROOT / "never").exists()


def test_the_detector_sees_a_heavy_import():
    """The same wrapper reports torch where the command needs the schemas (an unknown key is found by
    composing the configuration): the check above is not blind. The hint names the key that works."""
    code, out, err, heavy = run_cli(["data.train_episode=2"])
    assert code == 2 and "torch" in heavy, (code, heavy, err)
    assert err.strip().endswith("; did you mean data.train_episodes=... or data.min_train_episodes=... "
                                "or data.test_episodes=...?"), err
    assert "+data.train_episode" not in err  # no `+key` fix: the schemas refuse unknown keys


def _hydra_completion():
    import dslearn.schemas  # noqa: F401  (the ConfigStore entries the task configs name)
    from hydra._internal.config_loader_impl import ConfigLoaderImpl
    from hydra._internal.core_plugins.bash_completion import BashCompletion
    from hydra._internal.utils import create_config_search_path

    from dslearn.app.common import CONF_DIR

    bc = BashCompletion(ConfigLoaderImpl(config_search_path=create_config_search_path(CONF_DIR)))
    return lambda line: bc._query(config_name="config", line=bc.strip_python_or_app_name(line))


LIGHT = ["dslearn-run ", "dslearn-run m", "dslearn-run mo", "dslearn-run model=", "dslearn-run model=gp_",
         "dslearn-run s", "dslearn-run -m model=lin con", "dslearn-run consensus=h", "dslearn-run t",
         "dslearn-run filter=", "dslearn-run d", "dslearn-run model=lin ", "dslearn-run experiment=y",
         "dslearn-run h", "dslearn-run --multirun seed=1 method="]
HEAVY_LINES = ["dslearn-run data.", "dslearn-run data.tr", "dslearn-run seed=", "dslearn-run experiment=yu_table1 ",
               "dslearn-run +", "dslearn-run hydra/launcher=", "dslearn-run hydra.run.dir=./"]


def test_light_completion_answers_as_hydra_does():
    from dslearn.app.help import light_completion

    hydra_answer = _hydra_completion()
    for line in LIGHT:
        assert light_completion(["-sc", "query=bash"], line) == hydra_answer(line), line
    for line in HEAVY_LINES:  # these need the composed config (or files): left to Hydra
        assert light_completion(["-sc", "query=bash"], line) is None, line
    assert light_completion(["-sc", "install=bash"], "dslearn-run ") is None
    assert light_completion(["-sc", "query=bash"], None) is None


def test_completion_request_imports_no_heavy_module():
    code, out, err, heavy = run_cli(["-sc", "query=bash"], env={"COMP_LINE": "dslearn-run consensus="})
    assert (code, heavy) == (0, []), err
    assert out.split() == [f"consensus={o}" for o in options("consensus")]
    code, out, err, heavy = run_cli(["-sc", "query=bash"], env={"COMP_LINE": "dslearn-run "})
    assert (code, heavy) == (0, []), err
    assert {f"{g}=" for g in ("model", "filter", "task", "experiment")} | {"seed=", "task.", "hydra."} <= set(out.split())


def test_did_you_mean():
    from dslearn.app.options import did_you_mean

    assert did_you_mean("gp_incremnt", options("model"))[0] == "gp_increment"
    assert did_you_mean("hybird", options("consensus"))[0] == "hybrid"
    assert did_you_mean("increment", options("model")) == ["gp_increment", "gp_increment_rbcm"]  # a part of a name
    assert did_you_mean("zzz", options("model")) == []


def test_suggested_key_fix_works(capsys):
    """The suggested fix of a misspelt key is itself accepted (every suggested fix must work)."""
    from dslearn.app.precheck import precheck

    err = precheck(["sed=3"])
    assert err.startswith("sed: no such key in the configuration") and err.endswith("; did you mean seed=...?"), err
    assert precheck(["seed=3"]) is None
    err = precheck(["network.meas_sdt=0.2"])
    fix = re.search(r"did you mean (network\.\w+)=\.\.\.", err).group(1)
    assert fix == "network.meas_std" and precheck([f"{fix}=0.2"]) is None


def test_device_cuda_without_cuda_refused_before_a_run_folder(tmp_path, monkeypatch, capsys):
    import torch

    from dslearn.run import main

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    run = tmp_path / "run"
    with pytest.raises(SystemExit) as e:
        main(["device=cuda", "data.train_episodes=2", f"hydra.run.dir={run}"])
    assert e.value.code == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "dslearn-run: configuration error: device=cuda was asked for but no CUDA device is available; use device=cpu"]
    assert not run.exists()


@pytest.mark.serial  # signals and timing: run alone, before the parallel run (the README's test command)
@pytest.mark.parametrize("trigger", ["omegaconf", "torch"])
def test_ctrl_c_at_start_one_line_exit_130(tmp_path, trigger):
    """Ctrl-C while the program imports itself (omegaconf) or the schemas (torch): one line, 130, nothing made."""
    run = tmp_path / "run"
    code, out, err, heavy = run_cli(["data.train_episodes=2", f"hydra.run.dir={run}"], trigger=trigger)
    assert code == 130, (code, err)
    assert err.strip().splitlines() == ["dslearn-run: interrupted: Ctrl-C before the run started; nothing was written"]
    assert not run.exists()


def test_other_programs_help(tmp_path, capsys):
    from dslearn import bench, report, train_lstm

    text = train_lstm.help_text()
    keys = [m.group(1) for m in re.finditer(r"^([a-z_]+):", (CONF / "train_lstm.yaml").read_text(), re.M)]
    lstm_keys = [m.group(1) for m in re.finditer(r"^([a-z_]+):", (CONF / "lstm" / "default.yaml").read_text(), re.M)]
    for k in [k for k in keys if k not in ("defaults", "hydra", "lstm")]:
        assert re.search(rf"^  {k}=", text, re.M), k
    for k in lstm_keys:
        assert re.search(rf"^  lstm\.{k}=", text, re.M), k
    assert "== Config ==" not in text and len(text.splitlines()) < 80
    with pytest.raises(SystemExit):
        bench.main(["--help"])
    out = capsys.readouterr().out
    assert "``" not in out and not re.search(r":(mod|data|func|class):`", out) and "PREVIOUS_RELEASE" in out
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(SystemExit) as e:
        report.main([str(tmp_path)])
    err = capsys.readouterr().err.strip()
    assert e.value.code == 2 and len(err.splitlines()) == 1
    assert "Expected a dslearn-run output folder: a run folder holds results.csv" in err and err.endswith("holds: notes.txt")


def test_license_changelog_version():
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    import dslearn

    assert dslearn.__version__ == importlib.metadata.version("dslearn") == meta["version"]
    assert meta["license"] == "MIT" and (ROOT / "LICENSE").read_text().startswith("MIT License")
    log = (ROOT / "CHANGELOG.md").read_text()
    assert "keepachangelog.com" in log and re.search(r"^## \[Unreleased\]$", log, re.M)
