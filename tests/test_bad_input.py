"""Bad input everywhere: each case fails before any work with a message naming the field / file."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from dslearn.config_schema import validate_config
from dslearn.errors import ConfigError, DataFormatError

ROOT = Path(__file__).resolve().parents[1]

# (overrides, expected message fragment) -- checked by the schema pass (validate_config)
SCHEMA_CASES = [
    (["seed=abc"], "seed: Value 'abc' of type 'str' could not be converted to Integer"),
    (["seed=-1"], "seed=-1 must be an integer >= 0"),
    (["threads=0"], "threads=0 must be >= 1"),
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
    (["network.positions=[[0,0],[1,x]]"], "network.positions[1]=[1, 'x'] must hold two numbers"),
    (["network.edges=[[0,1.5]]"], "network.edges[0]=[0, 1.5] must hold two integers"),
    (["model.noise_std=-1"], "model.noise_std=-1.0 must be > 0"),
    (["model.lengthscale=0"], "model.lengthscale=0.0 must be > 0"),
    (["model.mean=linear"], "model.mean='linear' is not allowed"),
    (["consensus.iterations=-1"], "consensus.iterations=-1 must be an integer >= 0"),
    (["consensus.iterations=two"], "consensus.iterations: Value 'two' of type 'str' could not be converted to Integer"),
    (["consensus.weights=random"], "consensus.weights='random' is not allowed"),
    (["consensus.omega=-2"], "consensus.omega=-2 must be > 0, 'one' or 'nodes'"),
    (["consensus.name=gossip"], "consensus.name='gossip' is not allowed"),
    (["data.test_episodes=0"], "data.test_episodes=0 must be an integer >= 1"),
    (["data.eval_at=[0,99]", "data.train_episodes=10"], "data.eval_at contains [99]"),
    (["filter.prior_pos_std=0"], "filter.prior_pos_std=0.0 must be > 0"),
    (["observation.name=radar"], "observation.name='radar' is not allowed"),
]


@pytest.mark.parametrize("overrides,expected", SCHEMA_CASES, ids=lambda v: str(v)[:40])
def test_schema_rejects(make_cfg, overrides, expected):
    cfg = make_cfg(*overrides)
    with pytest.raises(ConfigError) as e:
        validate_config(cfg)
    assert expected in str(e.value)


def test_good_configs_pass(make_cfg):
    for ov in ([], ["model=lin"], ["model=gp_sgpr"], ["observation=gp"], ["experiment=yu_faults"],
               ["experiment=liu_table1"], ["experiment=jiang_fg"], ["experiment=braga_tbn"]):
        validate_config(make_cfg(*ov))


def test_bad_entry_and_network(make_cfg):
    from dslearn.run import resolve_entry
    from dslearn.studies.yu import YuStudy

    with pytest.raises(ConfigError, match="task.entry='nomodule' must look like 'package.module:function'"):
        resolve_entry("nomodule")
    with pytest.raises(ConfigError, match="cannot be imported"):
        resolve_entry("dslearn.nosuch:run")
    cfg = make_cfg("network.comm_radius=0.5")
    with pytest.raises(ConfigError, match="disconnected"):
        YuStudy.from_config(cfg)


def test_yu_faults_task_checks(make_cfg):
    from dslearn.studies.yu_faults import validate

    for ov, msg in (
        (["task.link_fail=[0.1,1.5]"], "task.link_fail contains 1.5"),
        (["task.fusions=[hybrid,gossip]"], "task.fusions[]='gossip' is not allowed"),
        (["task.models=[lin,nn]"], "task.models contains 'nn'"),
        (["task.node_fail_mode=sometimes"], "task.node_fail_mode='sometimes' is not allowed"),
        (["task.gate_prob=1.0"], "task.gate_prob=1.0 must be in (0, 1)"),
        (["+task.typo=1"], "task.typo: unknown key"),
    ):
        with pytest.raises(ConfigError) as e:
            validate(make_cfg("experiment=yu_faults", *ov))
        assert msg in str(e.value), (ov, str(e.value))


# ------------------------------------------------------------------------------------------
# data files


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


def test_trajectory_file_broken_line(tmp_path):
    from dslearn.data import ethucy
    p = tmp_path / "scene.txt"
    p.write_text("0 1 1.0 2.0\n10 1 1.5 2.5\n20 1 abc 3.0\n")
    with pytest.raises(DataFormatError, match=r"scene.txt:3: non-numeric field"):
        ethucy.read_trajectories(p)
    p.write_text("0 1 1.0 2.0\n10 1 1.5\n")
    with pytest.raises(DataFormatError, match=r"scene.txt:2: expected 4 fields"):
        ethucy.read_trajectories(p)


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


def test_cli_exit_code_2_one_line():
    """dslearn-run: a ConfigError is one line on stderr and exit code 2, before any work."""
    env = {**os.environ, "CI": "1"}
    r = subprocess.run([sys.executable, "-m", "dslearn.run", "network.meas_std=-1", "hydra.run.dir=/nonexistent/never"],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert lines == ["dslearn-run: configuration error: network.meas_std=-1.0 must be > 0"]
    r = subprocess.run([sys.executable, "-m", "dslearn.run", "-m", "model=lin,nosuchmodel"],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "nosuchmodel" in r.stderr and len(r.stderr.strip().splitlines()) == 1
