"""Bad input everywhere: every case is refused with ONE stderr line naming the problem, exit code 2
(130 for Ctrl-C), no traceback, and nothing left that looks like a result.

Most cases run the real command-line entry point in-process (``dslearn.run.main(argv)`` /
``dslearn.report.main(argv)``: the same code path as the console scripts, without the ~3 s
interpreter start); a representative few run the console script in a subprocess.
"""

import contextlib
import io
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from dslearn.schemas.core import validate_config
from dslearn.errors import ConfigError, DataFormatError

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------------------
# harness


def cli(argv, main=None):
    """Run ``dslearn-run`` (or another console main) in-process: ``(exit code, stdout, stderr)``."""
    if main is None:
        from dslearn.run import main
    out, err = io.StringIO(), io.StringIO()
    code = 0
    old = os.environ.get("CI")
    os.environ["CI"] = "1"  # no progress bars
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                main(list(argv))
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else 1
    finally:
        if old is None:
            os.environ.pop("CI", None)
        else:
            os.environ["CI"] = old
    return code, out.getvalue(), err.getvalue()


def assert_refused(code, out, err, fragment, where=None, exit_code=2, prog="dslearn-run"):
    """Exit code, one stderr line naming the problem, no traceback, no result left in ``where``."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == exit_code, (code, err[-2000:], out[-2000:])
    assert len(lines) == 1, err
    assert lines[0].startswith(f"{prog}: "), lines[0]
    assert fragment in lines[0], (fragment, lines[0])
    assert "Traceback" not in err and "Traceback" not in out
    if where is not None:
        where = Path(where)
        left = list(where.rglob("results.csv")) if where.exists() else []  # a missing folder holds no result
        assert left == [], left
        for st in where.rglob("status.json") if where.exists() else []:
            assert json.loads(st.read_text())["status"] in ("failed", "interrupted"), st.read_text()


def run_refused(argv, fragment, tmp_path, exit_code=2):
    run = tmp_path / "run"
    code, out, err = cli([*argv, f"hydra.run.dir={run}"] if not any(a.startswith("hydra.") for a in argv) else argv)
    assert_refused(code, out, err, fragment, run if run.exists() else tmp_path, exit_code)
    return err


# ------------------------------------------------------------------------------------------
# configuration values: the start-up check (precheck) refuses them before Hydra starts a job

SCHEMA_CASES = [
    (["seed=abc"], "seed: Value 'abc' of type 'str' could not be converted to Integer"),
    (["seed=-1"], "seed=-1 must be an integer >= 0"),
    (["threads=0"], "threads=0 must be in 1.."),
    (["dtype=float16"], "dtype='float16' is not allowed"),
    (["device=tpu"], "device='tpu' is not allowed"),
    (["progress=maybe"], "progress: Value 'maybe' is not a valid bool"),
    (["+colour=red"], "unknown top-level key(s) ['colour']"),
    (["+network.colour=red"], "network.colour: unknown key"),
    (["+model.typo_std=1"], "model.typo_std: unknown key"),
    (["network.num_sensors=1.5"], "network.num_sensors: Value '1.5' of type 'float' could not be converted to Integer"),
    (["network.num_sensors=0"], "network.num_sensors=0 must be >= 1"),
    (["network.meas_std=-0.2"], "network.meas_std=-0.2 must be > 0"),
    (["network.comm_radius=0"], "network.comm_radius=0.0 must be > 0"),
    (["network.area=[0,8,8,0]"], "network.area=[0.0, 8.0, 8.0, 0.0] must be [xmin, xmax, ymin, ymax]"),
    (["scenario.dt=0"], "scenario.dt=0.0 must be > 0"),
    (["scenario.horizon=0.25"], "scenario.horizon=0.25 must be >= 2 * scenario.dt"),
    (["scenario.start_corners=[[1,1]]"], "scenario.start_corners must hold one [x, y] pair per agent (2)"),
    (["network.positions=[[0,0],[1,x]]"], "network.positions[1]=[1, 'x'] must hold two finite numbers"),
    (["network.edges=[[0,1.5]]"], "network.edges[0]=[0, 1.5] must hold two finite integers"),
    (["model.noise_std=-1"], "model.noise_std=-1.0 must be > 0"),
    (["model.lengthscale=0"], "model.lengthscale=0.0 must be > 0"),
    (["model.mean=linear"], "model.mean='linear' is not allowed"),
    (["consensus.iterations=-1"], "consensus.iterations=-1 must be an integer >= 0"),
    (["consensus.iterations=two"], "consensus.iterations: Value 'two' of type 'str' could not be converted to Integer"),
    (["consensus.weights=random"], "consensus.weights='random' is not allowed"),
    (["consensus.omega=-2"], "consensus.omega=-2 must be > 0 and finite, 'one' or 'nodes'"),
    (["consensus.name=gossip"], "consensus.name='gossip' is not allowed"),
    (["data.test_episodes=0"], "data.test_episodes=0 must be an integer >= 1"),
    (["data.eval_at=[0,99]", "data.train_episodes=10"], "data.eval_at contains [99]"),
    (["filter.prior_pos_std=0"], "filter.prior_pos_std=0.0 must be > 0"),
    (["observation.name=radar"], "observation.name='radar' is not allowed"),
]

# inf passes a range check that nan fails; nan/inf positions and velocities; misleading messages
NONFINITE_CASES = [
    (["model.lengthscale=inf"], "model.lengthscale=inf must be finite"),
    (["model.noise_std=inf"], "model.noise_std=inf must be finite"),
    (["model.outputscale=-inf"], "model.outputscale=-inf must be > 0"),
    (["filter.prior_pos_std=inf"], "filter.prior_pos_std=inf must be finite"),
    (["network.meas_std=inf"], "network.meas_std=inf must be finite"),
    (["network.sensing_range=nan"], "network.sensing_range=nan must be > 0"),
    (["consensus.omega=inf"], "consensus.omega=inf must be > 0 and finite"),
    (["scenario.area=[0,inf,0,8]"], "scenario.area[1]=inf must be a finite number"),
    (["scenario.tau=inf"], "scenario.tau=inf must be finite"),
    (["scenario.dt=nan"], "scenario.dt=nan must be > 0"),
    (["network.positions=[[nan,0],[1,1]]"], "network.positions[0]=[nan, 0] must hold two finite numbers"),
    (["scenario.desired_velocities=[[nan,1],[1,1]]"], "scenario.desired_velocities[0]=[nan, 1] must hold two finite numbers"),
    (["observation=gp", "observation.lengthscale=-1"], "observation.lengthscale=-1.0 must be > 0"),
    (["observation=gp", "observation.mean=linear"], "observation.mean='linear' is not allowed"),
]

# resource guard, study registry, unknown keys/options, command-line syntax
OTHER_CASES = [
    (["scenario.horizon=10000000"], "estimated peak memory"),
    (["data.train_episodes=1000000000"], "data.train_episodes=1000000000"),
    ([f"scenario.desired_velocities=[{','.join(['[1,-1]'] * 100)}]",
      f"scenario.start_corners=[{','.join(['[1,5]'] * 100)}]", "+max_memory_gb=8"], "from 100 agents"),
    (["+max_memory_gb=0.001"], "exceeds the limit of 0.001 GB (max_memory_gb=0.001)"),
    (["+max_memory_gb=-1"], "max_memory_gb=-1.0 must be > 0"),
    (["threads=1000000"], "threads=1000000 must be in 1.."),
    (["task._target_=builtins.len"], "task._target_='builtins.len' is not a registered study; choose one of ["),
    (["task._target_=os.system"], "task._target_='os.system' is not a registered study"),
    (["task._target_=dslearn.studies.yu.check_offline"], "is not a registered study"),
    (["network.colr=3"], "network.colr: no such key in the configuration (known keys of network: ["),
    (["model=nosuch"], "model='nosuch' is not an option of the config group 'model'; choose one of ['cv_damped'"),
    (["experiment=nosuch"], "experiment='nosuch' is not an option of the config group 'experiment'"),
    (["nosuchkey=1"], "nosuchkey: no such key in the configuration"),
    (["model=[lin"], "model=[lin"),
    (["model=lin,sfm"], "model=lin,sfm is a sweep (one job per value); add -m (--multirun)"),
]


@pytest.mark.parametrize("overrides,expected", SCHEMA_CASES + NONFINITE_CASES + OTHER_CASES, ids=lambda v: str(v)[:40])
def test_cli_refuses_bad_values(tmp_path, overrides, expected):
    run_refused(overrides, expected, tmp_path)


def test_memory_estimate_names_the_numbers(make_cfg):
    from dslearn.schemas.core import estimate_core_memory, memory_limit_gb

    est = estimate_core_memory(make_cfg("data.train_episodes=30", "data.test_episodes=20"))
    # GP: 30 episodes x 12 steps = 360 points -> buffer 384 + 256 = 640 rows; 10 nodes
    cap, s, n, d = 640, 10, 360, 8
    assert est["gp"] == pytest.approx(s * (2.0 * cap * cap + 3 * cap * d) * 8 + s * 20 * n * 8 * 2, rel=1e-12)
    assert est["tracking"] == pytest.approx(5.0 * s * 20 * 13 * d * d * 8, rel=1e-12)
    lin = estimate_core_memory(make_cfg("model=lin"))
    assert lin["gp"] == 0.0
    assert memory_limit_gb(3.5) == (3.5, "max_memory_gb=3.5")


def test_good_configs_pass(make_cfg):
    for ov in ([], ["model=lin"], ["model=gp_sgpr"], ["observation=gp"], ["experiment=yu_faults"],
               ["experiment=liu_table1"], ["experiment=jiang_fg"], ["experiment=braga_tbn"],
               ["data=paper"], ["+max_memory_gb=40"], ["threads=null"]):
        validate_config(make_cfg(*ov))


def test_registry_matches_the_task_configs():
    """``task._target_`` must be registered; the registry is exactly the task configs' study classes."""
    from omegaconf import OmegaConf

    from dslearn.schemas.core import TASK_TARGETS

    found = {}
    for p in (ROOT / "conf" / "task").glob("*.yaml"):
        c = OmegaConf.load(p)
        found[str(c.name)] = str(c._target_)
    assert found == TASK_TARGETS


# ------------------------------------------------------------------------------------------
# sweeps: every combination is checked before the first job


def test_sweep_bad_value_in_the_middle(tmp_path):
    vals = ",".join(str(0.1 + 0.01 * i) for i in range(17)) + ",-1,0.5"
    code, out, err = cli(["-m", f"network.meas_std={vals}", "model=lin,sfm", f"hydra.sweep.dir={tmp_path / 'sw'}"])
    assert_refused(code, out, err, "network.meas_std=-1.0 must be > 0 (sweep job 34: network.meas_std=-1 model=lin)")
    assert not (tmp_path / "sw").exists()  # no job started


def test_sweep_bad_group_option_and_experiment_params(tmp_path):
    code, out, err = cli(["-m", "model=lin,nosuchmodel", f"hydra.sweep.dir={tmp_path / 'a'}"])
    assert_refused(code, out, err, "model='nosuchmodel' is not an option of the config group 'model'")
    # an experiment's own sweep (hydra.sweeper.params: 5 models x 3 fusions) is expanded too
    code, out, err = cli(["experiment=yu_table1", "data.test_episodes=1,0", f"hydra.sweep.dir={tmp_path / 'b'}"])
    assert_refused(code, out, err, "data.test_episodes=0 must be an integer >= 1 (sweep job 1: model=lin consensus=individual")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_output_dir_and_launcher(tmp_path, monkeypatch):
    f = tmp_path / "afile"
    f.write_text("x")
    for argv, frag in (
        ([f"hydra.run.dir={f}"], f"hydra.run.dir={f} is an existing file, not a folder"),
        ([f"hydra.run.dir={f}/sub"], f"hydra.run.dir={f}/sub: {f} is a file"),
        (["-m", "model=lin", f"hydra.sweep.dir={f}"], f"hydra.sweep.dir={f} is an existing file"),
        (["-m", "hydra/launcher=nosuch", "model=lin", f"hydra.sweep.dir={tmp_path / 's'}"],
         "hydra/launcher='nosuch' is not a known launcher; choose one of ['basic', 'joblib'"),
    ):
        code, out, err = cli(argv)
        assert_refused(code, out, err, frag, tmp_path)
    import dslearn.app.options as options

    monkeypatch.setattr(options, "_plugin_installed", lambda module: False)  # as without the extra
    code, out, err = cli(["-m", "hydra/launcher=joblib", "model=lin", f"hydra.sweep.dir={tmp_path / 's'}"])
    assert_refused(code, out, err, 'hydra/launcher=joblib needs the Hydra plugin hydra_joblib_launcher, which is not '
                                   'installed; install it with: pip install "dslearn[joblib]"', tmp_path)
    assert f.read_text() == "x" and not (tmp_path / "s").exists()


# ------------------------------------------------------------------------------------------
# during the run: data files, data root, Ctrl-C, memory, busy run folder

BAD_FILES = {
    "binary": (b"0\t1\t1.0\x00\x01\x02\n", "crowds_zara01.txt:1: binary file (NUL byte)"),
    "latin1": ("0\t1\t1.0\t2.0\n10\t1\tcaf\xe9\t2.0\n".encode("latin-1"), "crowds_zara01.txt:2: byte 0xe9 is not UTF-8 text"),
    "bom": (b"\xef\xbb\xbf0\t1\t1.0\t2.0\n", "crowds_zara01.txt:1: starts with a UTF-8 byte-order mark (BOM)"),
    "header": (b"frame\tped\tx\ty\n0\t1\t1.0\t2.0\n", "crowds_zara01.txt:1: non-numeric field in 'frame\\tped\\tx\\ty' (a header line?"),
    "backwards": (b"10\t1\t1.0\t2.0\n0\t1\t1.0\t2.0\n", "crowds_zara01.txt:2: frame 0 after frame 10 (frames must not decrease)"),
    "off_step": (b"0\t1\t1.0\t2.0\n10\t1\t1.1\t2.0\n10\t2\t3.0\t2.0\n25\t2\t3.1\t2.0\n25\t1\t1.2\t2.0\n",
                 "crowds_zara01.txt:4: frame 25 is not a multiple of 10 (the frame step, task.datasets.zara1.frame_step"),
}


@pytest.mark.parametrize("kind", sorted(BAD_FILES))
def test_malformed_trajectory_file_through_the_cli(tmp_path, kind):
    data = tmp_path / "data"
    data.mkdir()
    raw, frag = BAD_FILES[kind]
    (data / "crowds_zara01.txt").write_bytes(raw)
    code, out, err = cli(["experiment=real_tables", f"task.data_root={data}", "task.scenes=[zara1]",
                          f"hydra.run.dir={tmp_path / 'run'}"])
    assert_refused(code, out, err, "dslearn-run: data error: " + str(data / frag.split(":")[0]) + ":" + frag.split(":", 1)[1],
                   tmp_path / "run")
    status = json.loads((tmp_path / "run" / "status.json").read_text())
    assert status["status"] == "failed" and status["config_error"] is True


def test_data_root_errors_name_task_data_root(tmp_path):
    f = tmp_path / "afile"
    f.write_text("x")
    for root, frag in ((tmp_path / "missing", "does not exist"), (f, "is a file, not a folder"), (tmp_path, "has no file crowds_zara01.txt")):
        code, out, err = cli(["experiment=real_tables", f"task.data_root={root}", "task.scenes=[zara1]",
                              f"hydra.run.dir={tmp_path / 'run'}"])
        assert_refused(code, out, err, f"dslearn-run: configuration error: task.data_root='{root}' {frag}", tmp_path / "run")


def test_interrupt_and_out_of_memory_in_process(tmp_path, monkeypatch):
    from dslearn.studies.yu import YuStudy

    def boom(exc):
        def run(self, progress=False, diagnostics=None):
            raise exc
        return run

    for i, (exc, code_, frag, status) in enumerate((
        (KeyboardInterrupt(), 130, "dslearn-run: interrupted: Ctrl-C: no results written;", "interrupted"),
        (MemoryError(), 2, "dslearn-run: resource error: out of memory (MemoryError", "failed"),
        (RuntimeError("[enforce fail at alloc_cpu.cpp:116] DefaultCPUAllocator: can't allocate memory: you tried "
                      "to allocate 34359738368 bytes"), 2, "can't allocate memory", "failed"),
    )):
        monkeypatch.setattr(YuStudy, "run", boom(exc))
        run = tmp_path / f"r{i}"
        code, out, err = cli(["model=lin", "data.train_episodes=0", "data.test_episodes=1", f"hydra.run.dir={run}"])
        assert_refused(code, out, err, frag, run, exit_code=code_)
        assert json.loads((run / "status.json").read_text())["status"] == status


def test_busy_run_folder_is_refused_and_stale_lock_taken_over(tmp_path):
    from dslearn.io import LOCK_FILE, RunLock

    run = tmp_path / "run"
    with RunLock(run):  # another live run (this process) holds the folder
        code, out, err = cli(["model=lin", "data.train_episodes=0", "data.test_episodes=1", f"hydra.run.dir={run}"])
        assert_refused(code, out, err, f"dslearn-run: run folder busy: {run} is in use by another dslearn-run (pid {os.getpid()}", run)
        assert not (run / "status.json").exists()  # the owner's status is not touched
        with pytest.raises(Exception, match="is in use by another dslearn-run"):
            RunLock(run).acquire()
    # a lock left by a dead process is taken over
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    (run / LOCK_FILE).write_text(f"{dead.stdout.strip()} somehost\n")
    code, out, err = cli(["model=lin", "data.train_episodes=0", "data.test_episodes=1", "print_table=false", f"hydra.run.dir={run}"])
    assert code == 0 and (run / "results.csv").is_file(), err
    assert json.loads((run / "status.json").read_text())["status"] == "done"
    assert out.splitlines()[-1] == f"next: dslearn-report {run}"  # a single run ends with the next step


# ------------------------------------------------------------------------------------------
# dslearn-report


def test_report_bad_inputs(tmp_path):
    from dslearn.report import main as report_main

    (tmp_path / "bin.csv").write_bytes(bytes(range(256)) * 4)
    (tmp_path / "latin1.csv").write_bytes("model,metric,value\ncaf\xe9,track_err,0.1\n".encode("latin-1"))
    (tmp_path / "nonnum.csv").write_text("model,metric,value\nlin,track_err,0.1\nlin,track_err,abc\n")
    (tmp_path / "nohead.csv").write_text("model,score\nlin,0.1\n")
    (tmp_path / "empty.csv").write_text("")
    (tmp_path / "bad.parquet").write_bytes(b"not parquet")
    (tmp_path / "emptydir").mkdir()
    (tmp_path / "afile").write_text("x")
    good = tmp_path / "good.csv"
    good.write_text("model,metric,value\nlin,track_err,0.1\n")
    missing = tmp_path / "nosuch" / "dir"
    for argv, frag in (
        ([str(tmp_path / "bin.csv")], "bin.csv:1: binary file (NUL byte), not a text CSV table"),
        ([str(tmp_path / "latin1.csv")], "latin1.csv:2: not a UTF-8 text CSV file"),
        ([str(tmp_path / "nonnum.csv")], "nonnum.csv:3: non-numeric value 'abc' in the 'value' column"),
        ([str(tmp_path / "nohead.csv")], "nohead.csv:1: header lacks the 'metric' and 'value' columns"),
        ([str(tmp_path / "empty.csv")], "empty.csv:1: empty file"),
        ([str(tmp_path / "bad.parquet")], "bad.parquet: not a readable Parquet file"),
        ([str(tmp_path / "emptydir")], "no results.csv found under"),
        ([str(missing)], f"{missing}: no such file or folder"),
        ([str(good), "--out", str(tmp_path / "afile")], f"--out {tmp_path / 'afile'} is an existing file; give a folder"),
    ):
        code, out, err = cli(argv, main=report_main)
        assert_refused(code, out, err, frag, prog="dslearn-report")
    assert not (tmp_path / "nosuch").exists()  # a nonexistent path is not created
    assert (tmp_path / "afile").read_text() == "x"
    assert not list(tmp_path.rglob("report.md")) and not list(tmp_path.rglob("summary.csv"))


# ------------------------------------------------------------------------------------------
# function-level checks


def test_bad_task_target_and_network(make_cfg):
    """Every study is a registered class the composition root builds (``task._target_``): a ``task.entry`` (a
    function, as studies once were) is an unknown key, and a task without a ``_target_`` is refused naming the
    registered studies."""
    from omegaconf import OmegaConf

    from dslearn import api

    with pytest.raises(ConfigError, match=re.escape("task.entry: unknown key; task takes ['_target_', 'name']")):
        validate_config(make_cfg("+task.entry=dslearn.studies.yu:run"))
    cfg = OmegaConf.create(OmegaConf.to_container(make_cfg("task=jiang_fg")))
    cfg.task = {"name": "jiang_fg", "entry": "dslearn.studies.jiang_fg:run"}
    with pytest.raises(ConfigError, match=re.escape("task._target_=None is not a registered study; choose one of [")):
        validate_config(cfg)
    cfg = make_cfg("network.comm_radius=0.5")
    with pytest.raises(ConfigError, match="disconnected"):
        api.build_study(cfg)


def test_yu_faults_task_checks(make_cfg):
    """Ranges and choices declared on the task schema (dslearn.schemas.yu_faults) name the field."""
    from dslearn.schemas.core import validate_config

    for ov, msg in (
        (["task.link_fail=[0.1,1.5]"], "task.link_fail[1]=1.5 must be >= 0.0 and <= 1.0"),
        (["task.fusions=[hybrid,gossip]"], "task.fusions[1]='gossip' is not allowed; choose one of"),
        (["task.models=[lin,nn]"], "task.models contains 'nn'"),
        (["task.node_fail_mode=sometimes"], "task.node_fail_mode='sometimes' is not allowed"),
        (["task.gate_prob=1.0"], "task.gate_prob=1.0 must be > 0.0 and < 1.0"),
        (["task.joint=[[0.3,2.0]]"], "task.joint contains [0.3, 2.0]"),
    ):
        with pytest.raises(ConfigError) as e:
            validate_config(make_cfg("experiment=yu_faults", *ov))
        assert msg in str(e.value), (ov, str(e.value))


def test_task_schema_rejects_unknown_keys_and_types_at_composition(make_cfg):
    """The task's schema is linked from its config file: Hydra refuses an unknown key or a wrong type."""
    from hydra.errors import ConfigCompositionException

    from dslearn.schemas.core import validate_config

    for ov in (["task.typo=1"], ["task.train_episodes=abc"], ["task.link_fail=[a]"]):
        with pytest.raises(ConfigCompositionException):
            make_cfg("experiment=yu_faults", *ov)
    with pytest.raises(ConfigError, match=r"task\.typo: unknown key"):  # '+' bypasses Hydra's check, not ours
        validate_config(make_cfg("experiment=yu_faults", "+task.typo=1"))


def test_result_tables(tmp_path):
    from dslearn.io import check_complete, load_table

    p = tmp_path / "t.csv"
    p.write_text("")
    with pytest.raises(DataFormatError, match=r"t.csv:1: empty file"):
        load_table(p)
    p.write_text("model,metric,value\nlin,track_err,0.1\nlin,track_err,0.2,extra,fields\n")
    with pytest.raises(DataFormatError, match=r"t.csv:3: malformed CSV"):
        load_table(p)
    p.write_text("model,score\nlin,0.1\n")
    with pytest.raises(DataFormatError, match=r"t.csv:1: header lacks the 'metric' and 'value' columns"):
        load_table(p)
    q = tmp_path / "t.parquet"
    q.write_bytes(b"not parquet")
    with pytest.raises(DataFormatError, match="not a readable Parquet file"):
        load_table(q)
    run = tmp_path / "run"
    run.mkdir()
    (run / "results.csv").write_text("metric,value\ntrack_err,0.1\n")
    (run / "meta.json").write_text("{broken")
    assert "meta.json is not valid JSON" in check_complete(run)[1]
    (run / "meta.json").write_text(json.dumps({"rows": 5}))
    assert "has 1 rows, meta.json says 5" in check_complete(run)[1]
    (run / "meta.json").write_text("[1, 2]")
    assert check_complete(run) == (False, "meta.json is not a JSON object")
    # corrupted files of a sweep being resumed: refused as broken, never a crash
    (run / "meta.json").write_bytes(b"\xff\xfe\x00garbage")
    assert check_complete(run) == (False, "meta.json is not valid JSON (UnicodeDecodeError)")
    (run / "meta.json").write_text(json.dumps({"rows": 1}))
    (run / "results.csv").write_bytes(b"metric,value\n\x89PNG\x00\xff")
    assert check_complete(run) == (False, "results.csv is not UTF-8 text (byte 13): corrupted")


def test_trajectory_file_broken_line(tmp_path):
    from dslearn.data import ethucy
    p = tmp_path / "scene.txt"
    p.write_text("0 1 1.0 2.0\n10 1 1.5 2.5\n20 1 abc 3.0\n")
    with pytest.raises(DataFormatError, match=r"scene.txt:3: non-numeric field"):
        ethucy.read_trajectories(p)
    p.write_text("0 1 1.0 2.0\n10 1 1.5\n")
    with pytest.raises(DataFormatError, match=r"scene.txt:2: expected 4 fields"):
        ethucy.read_trajectories(p)


def test_frame_off_the_frame_step_names_file_and_line(tmp_path):
    """The first line whose frame is not a multiple of the frame step, in file order (the loader
    sorts by (frame, ped), which puts ped 1 of frame 30 before ped 3 at line 5)."""
    from dslearn.data import ethucy
    from dslearn.data.datasets import DatasetSpec, load_dataset

    p = tmp_path / "scene.txt"
    p.write_text("0 1 1.0 2.0\n0 2 3.0 2.0\n20 2 3.1 2.0\n30 3 5.0 1.0\n30 1 1.2 2.0\n35 2 3.2 2.0\n")
    assert len(ethucy.read_trajectories(p)) == 6  # no step given: not checked
    assert len(ethucy.read_trajectories(p, frame_step=5)) == 6
    with pytest.raises(DataFormatError) as e:
        ethucy.read_trajectories(p, frame_step=10, step_key="task.datasets.s.frame_step")
    assert str(e.value) == (f"{p}:6: frame 35 is not a multiple of 10 (the frame step, task.datasets.s.frame_step: "
                            "frames between a pedestrian's rows)")
    with pytest.raises(DataFormatError, match=rf"{p}:3: frame 20 is not a multiple of 15 \(the frame step, task\.datasets\.s\.frame_step"):
        load_dataset(DatasetSpec("s", "S", ("scene.txt",), root=str(tmp_path), frame_step=15), None)
    with pytest.raises(DataFormatError, match=rf"{p}:3: .*\(the frame step, datasets\.s\.frame_step"):
        load_dataset(DatasetSpec("s", "S", ("scene.txt",), root=str(tmp_path), frame_step=15), None,
                     root_key="data_root", datasets_key="datasets")


def test_model_files_safe_and_matching(tmp_path):
    from dslearn.models import ConstantVelocity, SocialForce

    sfm = SocialForce([[1.0, -1.0], [-1.0, -1.0]], [0.25, 0.25], [6.0, 6.0], [5.0, 5.0], 0.001)
    p = tmp_path / "sfm.pt"
    sfm.save(p)
    SocialForce([[0.0, 0.0], [0.0, 0.0]], [1.0, 1.0], [1.0, 1.0], [1.0, 1.0], 0.001).load(p)  # same shapes: fine
    three = SocialForce([[1.0, -1.0]] * 3, [0.25] * 3, [6.0] * 3, [5.0] * 3, 0.001)
    with pytest.raises(ConfigError, match=r"does not match the configured SocialForce: desired: file \(2, 2\) vs config \(3, 2\)"):
        three.load(p)
    with pytest.raises(ConfigError, match="saved by model class 'SocialForce', but the config builds 'ConstantVelocity'"):
        ConstantVelocity(2, 0.1).load(p)
    evil = tmp_path / "evil.pt"
    torch.save({"obj": Path("x")}, evil)  # an arbitrary pickled object: refused by weights-only loading
    with pytest.raises(DataFormatError, match="not a safe \\(weights-only\\) dslearn model file"):
        sfm.load(evil)
    with pytest.raises(DataFormatError, match="no such model file"):
        sfm.load(tmp_path / "missing.pt")


# ------------------------------------------------------------------------------------------
# the console script itself (subprocess: the real interpreter start, signals)


def _env():
    return {**os.environ, "CI": "1"}


def test_cli_exit_code_2_one_line(tmp_path):
    """dslearn-run: a ConfigError is one line on stderr and exit code 2, before any work."""
    r = subprocess.run([sys.executable, "-m", "dslearn.run", "network.meas_std=-1", f"hydra.run.dir={tmp_path / 'never'}"],
                       cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=300)
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert lines == ["dslearn-run: configuration error: network.meas_std=-1.0 must be > 0"]
    assert not (tmp_path / "never").exists()
    r = subprocess.run([sys.executable, "-m", "dslearn.run", "-m", "model=lin,nosuchmodel", f"hydra.sweep.dir={tmp_path / 's'}"],
                       cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "nosuchmodel" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert "Traceback" not in r.stderr + r.stdout


@pytest.mark.serial  # signals and timing: run alone, before the parallel run (the README's test command)
def test_cli_ctrl_c_exit_130_status_interrupted(tmp_path):
    run = tmp_path / "run"
    # the child gets SIGINT's default disposition whatever the test runner inherited (a runner
    # started in the background has SIGINT ignored, and Python then installs no Ctrl-C handler)
    p = subprocess.Popen([sys.executable, "-m", "dslearn.run", "model=gp_increment", "data.train_episodes=400",
                          "data.test_episodes=2", f"hydra.run.dir={run}"],
                         cwd=ROOT, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    t0 = time.time()
    try:
        while not ((run / "run.log").is_file() and "starting" in (run / "run.log").read_text()):
            assert p.poll() is None, p.communicate()
            assert time.time() - t0 < 240
            time.sleep(0.1)
        time.sleep(0.5)
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    assert_refused(p.returncode, out, err, "dslearn-run: interrupted: Ctrl-C: no results written;", run, exit_code=130)
    assert json.loads((run / "status.json").read_text())["status"] == "interrupted"


# ------------------------------------------------------------------------------------------
# refusals that only a part's constructor can state: in the start-up check too, full key named

BUILD_CASES = [
    (["model=gp_rbcm", "model.aggregation=grbcm"],
     "model.aggregation='grbcm' is not available for the aggregated GP motion model"),
    (["model=gp_increment_rbcm", "model.aggregation=rbcm2"], "model.aggregation='rbcm2' is not allowed; choose one of ['poe'"),
    (["model=gp_rbcm", "model.noise=adaptive"], "model.noise='adaptive' is not available for an aggregated GP"),
    (["filter=ukf", "filter.predict.alpha=-1"], "filter.predict.alpha=-1 must be > 0"),
    (["filter=ukf", "filter.predict.beta=-0.5"], "filter.predict.beta=-0.5 must be >= 0"),
    (["filter=ukf", "filter.predict.kappa=-8"],  # Dx = 8 (two agents): Dx + kappa must be > 0
     "filter.predict.kappa=-8 with state dimension Dx=8 gives Dx + lambda = alpha^2 (Dx + kappa) = 0"),
    (["experiment=yu_faults", "filter=ukf", "filter.predict.kappa=nan"], "filter.predict.kappa=nan must be a finite number"),
    (["network.comm_radius=0.5"], "network communication graph is disconnected"),
]


@pytest.mark.parametrize("overrides,expected", BUILD_CASES, ids=lambda v: str(v)[:48])
def test_constructor_refusals_come_before_the_run(tmp_path, overrides, expected):
    run = tmp_path / "run"
    # the run's size: task=yu_faults takes its episodes from task.* (it refuses the root data group)
    size = "task" if "experiment=yu_faults" in overrides else "data"
    code, out, err = cli([*overrides, f"{size}.train_episodes=1", f"{size}.test_episodes=1", f"hydra.run.dir={run}"])
    assert_refused(code, out, err, "dslearn-run: configuration error: " + expected)
    assert not run.exists()  # refused by the start-up check: no run folder, no run.log


def test_parts_check_passes_good_parts(make_cfg):
    """Good UKF / aggregated settings pass the parts check (kappa = -7 is legal for Dx = 8, -8 is not)."""
    from dslearn.schemas.core import check_parts

    for ov in (["model=gp_rbcm", "model.aggregation=poe", "model.noise=predictive"], ["model=gp_increment_rbcm"],
               ["filter=ukf", "filter.predict.kappa=-7", "filter.predict.alpha=0.5", "filter.predict.beta=0"],
               ["experiment=yu_faults", "filter=ukf"]):
        validate_config(make_cfg(*ov))
    with pytest.raises(ConfigError, match=r"^filter\.predict\.kappa=-9 with state dimension Dx=8"):
        check_parts(make_cfg("filter=ukf", "filter.predict.kappa=-9"))


@pytest.mark.parametrize("sweep,expected", [
    (["model=gp_rbcm", "model.aggregation=rbcm,grbcm,bcm"],
     "model.aggregation='grbcm' is not available for the aggregated GP motion model: grBCM needs a communication "
     "expert (a data subset shared by every node), which this setting does not have; choose one of "
     "['poe', 'gpoe', 'bcm', 'rbcm'] (sweep job 1: model=gp_rbcm model.aggregation=grbcm data.train_episodes=1"),
    (["model=gp_rbcm,gp_increment_rbcm", "model.noise=latent,adaptive"],
     "model.noise='adaptive' is not available for an aggregated GP (model.aggregation=rbcm); choose "
     "model.noise=latent or model.noise=predictive (sweep job 1: model=gp_rbcm model.noise=adaptive data.train_episodes=1"),
    (["filter=ukf", "filter.predict.alpha=1,0.5,-1,2"],
     "filter.predict.alpha=-1 must be > 0 (sweep job 2: filter=ukf filter.predict.alpha=-1 data.train_episodes=1"),
], ids=["grbcm", "adaptive", "ukf_alpha"])
def test_sweep_with_one_bad_job_runs_none(tmp_path, sweep, expected):
    sw = tmp_path / "sw"
    code, out, err = cli(["-m", *sweep, "data.train_episodes=1", "data.test_episodes=1", "hydra/launcher=basic",
                          f"hydra.sweep.dir={sw}"])
    assert_refused(code, out, err, "dslearn-run: configuration error: " + expected)
    assert not sw.exists()  # no job folder: no job started


# ------------------------------------------------------------------------------------------
# a run refused from a busy run folder touches nothing of it


def _snapshot(root: Path) -> dict:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_busy_run_folder_is_left_byte_identical(tmp_path):
    from dslearn.io import RunLock

    argv = ["model=lin", "data.train_episodes=0", "data.test_episodes=1", "print_table=false"]
    run = tmp_path / "run"
    code, out, err = cli([*argv, f"hydra.run.dir={run}"])
    assert code == 0, err
    assert {".hydra/config.yaml", ".hydra/overrides.yaml", "run.log", "config.yaml", "meta.json", "results.csv"} <= set(_snapshot(run))
    with RunLock(run):  # its owner is back at work in it
        before = _snapshot(run)
        code, out, err = cli(["model=sfm", "seed=3", "data.train_episodes=0", "data.test_episodes=1", f"hydra.run.dir={run}"])
        assert_refused(code, out, err, f"dslearn-run: run folder busy: {run} is in use by another dslearn-run (pid {os.getpid()}")
        assert _snapshot(run) == before  # .hydra/, run.log, config.yaml, meta.json: not a byte changed
    # a run folder named with interpolations (the default has a timestamp) is resolved and locked
    # before Hydra starts too, and the run then writes there; meta.json keeps the command line given
    code, out, err = cli([*argv, f"hydra.run.dir={tmp_path}/${{study}}_x"])
    done = tmp_path / "default_x"
    assert code == 0 and (done / "results.csv").is_file(), err
    assert json.loads((done / "meta.json").read_text())["argv"] == [*argv, f"hydra.run.dir={tmp_path}/${{study}}_x"]
    with RunLock(done):
        before = _snapshot(done)
        code, out, err = cli([*argv, "seed=3", f"hydra.run.dir={tmp_path}/${{study}}_x"])
        assert_refused(code, out, err, f"dslearn-run: run folder busy: {done} is in use")
        assert _snapshot(done) == before


# ------------------------------------------------------------------------------------------
# LSTM checkpoints: every broken file is one error naming the file


class _Planted:
    """A pickled object whose unpickling would create a file (code execution, if it ran)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_lstm_checkpoint_bad_files(tmp_path):
    from dslearn.models.lstm import CHECKPOINT_FORMAT, SocialLSTM, load_checkpoint, save_checkpoint

    m = SocialLSTM(1, embed=8, hidden=8, seed=0)
    good = tmp_path / "good.pt"
    save_checkpoint(m, good)
    raw = good.read_bytes()
    blob = torch.load(good, weights_only=True)
    h = torch.randn(3, 2, 1, 2, dtype=torch.float64)
    assert torch.equal(load_checkpoint(good).predict(h), m.predict(h))

    def put(name, content):
        p = tmp_path / name
        if isinstance(content, bytes):
            p.write_bytes(content)
        else:
            torch.save(content, p)
        return p

    marker = tmp_path / "code_ran"
    nan_state = {**blob["state_dict"], "output.bias": torch.tensor([float("nan"), 0.0])}
    cases = [
        (tmp_path / "missing.pt", DataFormatError, "no such LSTM checkpoint file"),
        (tmp_path, DataFormatError, "is a folder, not an LSTM checkpoint file"),
        (put("empty.pt", b""), DataFormatError, "empty file, not an LSTM checkpoint"),
        (put("half.pt", raw[: len(raw) // 2]), DataFormatError, "not a readable torch checkpoint (truncated or corrupt"),
        (put("text.pt", b"epoch,loss\n1,0.5\n"), DataFormatError, "not a readable torch checkpoint (truncated or corrupt"),
        (put("code.pt", {"format": CHECKPOINT_FORMAT, "hparams": _Planted(marker)}), DataFormatError,
         "refused: it pickles the Python object io.open, which could run code when loaded"),
        (put("list.pt", [1, 2]), DataFormatError, f"not a {CHECKPOINT_FORMAT} checkpoint (a list)"),
        (put("wider.pt", {**blob, "hparams": {**blob["hparams"], "hidden": 16}}), DataFormatError,
         "the weights do not match the saved hyperparameters (pooling='none', embed=8, hidden=16, grid=4): "
         "encoder.weight_ih: file (32, 8) vs hparams (64, 8)"),
        (put("social.pt", {**blob, "hparams": {**blob["hparams"], "pooling": "social"}}), DataFormatError,
         "the weights do not match the saved hyperparameters (pooling='social', embed=8, hidden=8, grid=4): "
         "missing ['pool_embed.0.bias', 'pool_embed.0.weight']"),
        (put("range.pt", {**blob, "hparams": {**blob["hparams"], "grid": 0}}), DataFormatError,
         "invalid saved hyperparameters: lstm.grid=0 must be an integer >= 1"),
        (put("lacks.pt", {**blob, "hparams": {k: v for k, v in blob["hparams"].items() if k != "dt"}}), DataFormatError,
         "hparams lacks ['dt']"),
        (put("nan.pt", {**blob, "state_dict": nan_state}), DataFormatError, "state_dict['output.bias'] holds NaN or infinite weights"),
        (put("hist.pt", {**blob, "history": {"epoch": [1.0, 2.0], "train_loss": [0.5]}}), DataFormatError,
         "history is not a mapping of equally long per-epoch lists"),
    ]
    for path, exc, frag in cases:
        with pytest.raises(exc) as e:
            load_checkpoint(path)
        msg = str(e.value)
        assert type(e.value) is exc and msg.startswith(f"{path}: ") and frag in msg, (path.name, msg)
        assert "\n" not in msg
    assert not marker.exists()  # the pickled call was refused, never run
    # the model given disagrees with the file: a configuration error naming the file
    with pytest.raises(ConfigError, match=rf"checkpoint '{good}' does not match the model's lstm hyperparameters: hidden: checkpoint 8 vs model 16"):
        load_checkpoint(good, SocialLSTM(1, embed=8, hidden=16))


# ------------------------------------------------------------------------------------------
# dslearn-train-lstm refuses like dslearn-run: one line, exit 2, its own keys, nothing left


def _zara1(folder: Path, text: str | bytes | None = None) -> Path:
    """A small crowds_zara01.txt: 3 pedestrians on straight lines for 25 steps (or ``text``)."""
    folder.mkdir(parents=True, exist_ok=True)
    if text is None:
        rows = [f"{10 * k}\t{p}\t{0.4 * k + p:.2f}\t{1.0 * p:.2f}" for k in range(25) for p in (1, 2, 3)]
        text = "\n".join(rows) + "\n"
    (folder / "crowds_zara01.txt").write_bytes(text if isinstance(text, bytes) else text.encode())
    return folder


def _train_cli(argv):
    from dslearn.train_lstm import main

    return cli(argv, main=main)


def test_train_lstm_refuses_bad_input(tmp_path):
    data = _zara1(tmp_path / "data")
    small = [f"data_root={data}", "train_scenes=[zara1]", "val_scenes=[]", "train_part=all", "lstm.embed=4",
             "lstm.hidden=4", "lstm.epochs=1", "progress=false"]
    ckdir = tmp_path / "ck"
    ckdir.mkdir()
    (ckdir / "keep.txt").write_text("x")
    afile = tmp_path / "afile"
    afile.write_text("x")
    runs = tmp_path / "runs"
    binary = _zara1(tmp_path / "bin", b"0\t1\t1.0\t2.0\n10\t1\t1.0\x00\x01\n")
    for argv, kind, frag in (
        (["colour=red"], "configuration error", "colour: no such key in the configuration (known keys: ['checkpoint'"),
        (["lstm.warmup=3"], "configuration error", "lstm.warmup: no such key in the configuration (known keys of lstm: ["),
        (["+lstm.warmup=3"], "configuration error", "lstm has unknown keys ['warmup']"),
        (["seed=abc"], "configuration error", "seed: Value 'abc' of type 'str' could not be converted to Integer"),
        (["lstm.hidden=abc"], "configuration error", "lstm.hidden='abc' must be an integer >= 1"),
        (["lstm=nosuch"], "configuration error", "lstm='nosuch' is not an option of the config group 'lstm'"),
        (["datasets.zara1.frame_step=0"], "configuration error", "datasets.zara1.frame_step=0 must be >= 1"),
        ([f"checkpoint={ckdir}"], "configuration error", f"checkpoint={ckdir} is a folder; give the checkpoint's file path"),
        ([f"checkpoint={afile}/lstm.pt"], "configuration error", f"checkpoint={afile}/lstm.pt: {afile} is a file"),
        ([f"data_root={tmp_path / 'nowhere'}"], "configuration error",
         f"data_root='{tmp_path / 'nowhere'}' does not exist; give the folder holding crowds_zara01.txt"),
        ([f"data_root={binary}"], "data error", f"{binary / 'crowds_zara01.txt'}:2: binary file (NUL byte)"),
        (["-m", "lstm.epochs=1,0"], "configuration error", "lstm.epochs=0 must be an integer >= 1 (sweep job 1: "),
    ):
        code, out, err = _train_cli([*small, *argv, f"hydra.run.dir={runs}", f"hydra.sweep.dir={runs}"])
        assert_refused(code, out, err, f"dslearn-train-lstm: {kind}: {frag}", prog="dslearn-train-lstm")
        assert "task.data_root" not in err and "task.datasets" not in err
        assert not runs.exists(), argv  # refused before Hydra made a run folder
    assert sorted(p.name for p in ckdir.iterdir()) == ["keep.txt"] and afile.read_text() == "x"


def test_train_lstm_failed_save_leaves_nothing(tmp_path, monkeypatch):
    """A checkpoint that cannot be written after training (the disk fills up): exit 1 with the
    error, no checkpoint, no temporary file, no history.csv."""
    import dslearn.models.lstm as lstm_mod

    data = _zara1(tmp_path / "data")
    ck = tmp_path / "ck" / "m.pt"
    real_save = torch.save

    def full_disk(obj, f, *a, **k):
        real_save(obj, f, *a, **k)  # the temporary file is written, then the disk is full
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(lstm_mod.torch, "save", full_disk)
    run = tmp_path / "run"
    argv = [f"data_root={data}", "train_scenes=[zara1]", "val_scenes=[]", "train_part=all", "lstm.embed=4",
            "lstm.hidden=4", "lstm.epochs=1", "progress=false", f"checkpoint={ck}", f"hydra.run.dir={run}"]
    code, out, err = _train_cli(argv)
    assert code == 1 and "No space left on device" in err, err
    assert list(ck.parent.iterdir()) == [] and not (run / "history.csv").exists()
    monkeypatch.setattr(lstm_mod.torch, "save", real_save)
    code, out, err = _train_cli(argv)
    assert code == 0 and ck.is_file() and (run / "history.csv").is_file(), err
    assert sorted(p.name for p in ck.parent.iterdir()) == ["m.pt"]
