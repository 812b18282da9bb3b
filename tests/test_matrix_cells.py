"""A matrix cell is n/a only where its method says so from the scenario's declared spec, with a reason written for a
person; an exception while a cell's parts are built is a failed cell (recorded, not run, shown failed by the
report), never n/a, and a single run whose parts fail to build stops with the error."""

import re

import pandas as pd
import pytest
from hydra import compose, initialize_config_dir

from dslearn.conf_paths import CONF_DIR
from dslearn.data.ethucy import data_available
from dslearn.episodes import ScenarioSpec
from dslearn.errors import ConfigError
from dslearn.methods.base import declared_misfit
from dslearn.schemas.matrix import CellBuildError, judge, misfit, select_cells

#: what an n/a reason must never hold: the text of an exception (a fault shown as a grey cell)
EXCEPTION_TEXT = re.compile(r"object has no attribute|Error|Traceback|must be|torch\.Size|state_dim=|shape|"
                            r"cannot be built|raised|\bgot\b|unexpected keyword|not subscriptable|NoneType")
#: what an n/a reason names: what the scenario lacks (``needs measurement position; scenario jiang has
#: squared_range``) or cannot give the method (``..., which scenario s1 does not have``)
NAMES_WHAT = re.compile(r"needs (measurement|state|networked|kind) \S+; scenario \S+ has \S+|which scenario \S+ does "
                        r"not have|the sensors of scenario \S+ have none|on scenario \S+ every node navigates itself|scenario \S+ measures "
                        r"\S+|does not fix a target's 2-D position|scenario \S+ reports unlabelled detections|scenario \S+ gives every "
                        r"measurement labelled")


def _opt(combo, group):
    return next(x.split("=", 1)[1] for x in combo if x.startswith(group + "="))


def _sweep(overrides):
    """The combinations of ``experiment=matrix`` (methods x scenarios; the ETH/UCY scenes only with their data) and a
    compose function for them: each preset and each scenario composed once and a combination put together from
    them (the up-front check's cache, checked against Hydra's own composition of some)."""
    from dslearn.app.composer import sweep_combinations

    combos, multirun, master = sweep_combinations(["experiment=matrix", *overrides])
    assert multirun and master.hydra.sweeper._target_.endswith("MatrixSweeper")
    if not data_available():
        combos = [c for c in combos if not _opt(c, "scenario").startswith("eth_")]
    # the app's cache of compositions (the up-front check's: each preset and each scenario composed once)
    from dslearn.app.composer import composed_job, sweep_composer

    composer = sweep_composer(combos, lambda ov: compose("config", overrides=list(ov)))

    def composed(lines):
        return composed_job(composer, lines)

    for lines in (combos[1], combos[-1]):  # the same configuration as Hydra composes for the combination
        hydra_cfg = compose("config", overrides=list(lines))
        assert composed(lines) == hydra_cfg, lines
    return combos, composed


def test_every_n_a_cell_of_the_matrix_says_why_from_the_spec():
    """Every combination of experiment=matrix through select_cells on the meta device (no job runs): no cell
    fails, an n/a cell's reason is a sentence for a person naming what the scenario lacks, never an exception's
    text, and the cells are n/a exactly by the design's rules on the declared spec."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        combos, composed = _sweep([])
        kept, records = select_cells(combos, composed)
        specs = {_opt(c, "scenario"): None for c in combos}
        engines = {}
        for c in combos:
            if specs[_opt(c, "scenario")] is None:
                import torch

                from dslearn.compose import _Slots

                specs[_opt(c, "scenario")] = _Slots(composed(c), torch.device("meta"))["scenario"].spec
            if _opt(c, "method") in engines:
                continue
            cfg = composed(c)
            engines[_opt(c, "method")] = (str(cfg.filter._target_), str(cfg.model.get("name")),
                                          str(cfg.observation._target_), str(cfg.consensus.get("name")),
                                          str(cfg.get("associator", {}).get("_target_", "")).rsplit(".", 1)[-1])
    assert len(records) == len(combos) and len(kept) == sum(r["status"] == "run" for r in records)
    assert not [r for r in records if r["status"] == "failed"], [r["error"] for r in records if r["error"]]
    na = [r for r in records if r["status"] == "does_not_fit"]
    assert na and kept
    for r, c in zip(records, combos):
        assert r["status"] in ("run", "does_not_fit", "left_out"), r
        if r["status"] != "does_not_fit":
            continue
        reason = r["reason"]
        assert reason.startswith(f"{r['method']} does not fit scenario {r['scenario']}: "), reason
        assert not EXCEPTION_TEXT.search(reason), reason
        assert NAMES_WHAT.search(reason), reason
        assert r["error"] is None and r["job"] is None
    # n/a exactly where the design says, from the spec alone: the distributed filter needs position sensors of 2-D
    # [p, v] agents on a network and model=sfm a scenario that simulates social forces; DGPT position sensors; the
    # factor graph squared ranges; the RBPF terrain altitudes on a network
    for r, c in zip(records, combos):
        spec, (engine, model, obs, fusion, assoc) = specs[_opt(c, "scenario")], engines[_opt(c, "method")]
        associates = assoc in ("GNNAssociator", "JPDAAssociator")
        if associates or not spec.labelled:  # unlabelled detections: the distributed filter with an associator only
            fits = associates and not spec.labelled and engine.endswith("DistributedFilter") and \
                spec.measurement == "position" and (not getattr(spec, "births", False) or model in ("lin", "lstm"))
            # targets that enter and leave: managed tracks, along which nothing learns, each predicted alone (LIN
            # with learner=none, the LSTM fitted offline to the training tracks; not the online GP)
        elif engine.endswith("DGPTMethod"):
            fits = spec.measurement == "position"
        elif engine.endswith("FactorGraphMethod"):
            fits = spec.measurement == "squared_range"
        elif engine.endswith("RBPFMethod"):
            fits = spec.measurement == "terrain_altitude" and spec.networked
        elif engine.endswith("FactorGraphMotionMethod"):  # the FG identification of a [p, v] model: position sensors
            fits = spec.measurement == "position" and spec.state == "pv2d" and spec.kind == "targets"
        elif engine.endswith("RBPFModesMethod"):  # a Kalman filter of [p, v] per particle: position sensors; an
            # iterated EKF per particle at a fusion centre on the scenario's own nonlinear sensor (Jiang's)
            fits = (spec.measurement == "position" and spec.state == "pv2d") or (
                obs.endswith("scenario_sensor") and spec.measurement == "squared_range")
        elif spec.measurement == "position":
            fits = spec.state == "pv2d" and spec.networked and (model != "sfm" or spec.dynamics == "social_force")
        else:  # the scenario's own sensor (observation=sensor); consensus needs a graph of nodes sharing targets;
            # one squared range per node cannot fix a position alone; Braga's aircraft each navigate themselves
            sensor = obs.endswith("scenario_sensor")
            fits = sensor and (model != "sfm" or spec.dynamics == "social_force") and (
                fusion == "centralized" if spec.measurement == "squared_range" else fusion in ("individual", "centralized"))
        assert (r["status"] != "does_not_fit") == fits, (c, r)
    # the cells the issue found hidden behind exception texts: the LSTM and the GP on jiang, sfm on liu_s1
    by = {(_opt(c, "method"), _opt(c, "scenario")): r for r, c in zip(records, combos)}
    assert "scenario jiang" in by[("ekf_lstm_hybrid", "jiang")]["reason"].split(": ", 1)[1]
    assert by[("ekf_gp_hybrid", "jiang")]["reason"].startswith("ekf gp_increment hybrid does not fit scenario jiang")
    assert "which scenario s1 does not have" in by[("ekf_sfm_hybrid", "liu_s1")]["reason"]


def test_the_declarations_read_the_spec_alone():
    from dslearn.methods.distributed import DistributedFilter
    from dslearn.models.social_force import SocialForce
    from dslearn.learning.sfm_fit import FittedSocialForce

    jiang = ScenarioSpec("jiang", "squared_range", 1, "param2d", 1.0, 10, networked=False)
    liu = ScenarioSpec("s1", "position", 1, "pv2d", 1.0, 60)
    yu = ScenarioSpec("yu", "position", 2, "pv2d", 0.25, 12, dynamics="social_force")
    assert declared_misfit(DistributedFilter, jiang) is None  # squared ranges: observation=sensor explains them
    lidar = ScenarioSpec("scan", "point_cloud", 1, "pv2d", 1.0, 10)
    assert declared_misfit(DistributedFilter, lidar).endswith("; scenario scan has point_cloud")
    assert declared_misfit(DistributedFilter, liu) is None
    assert "which scenario s1 does not have" in declared_misfit(SocialForce.for_scenario, liu)
    assert declared_misfit(SocialForce.for_scenario, yu) is None
    assert declared_misfit(FittedSocialForce.for_scenario, liu) is None  # fitted to any tracks
    # ... but its desired velocities come from each agent's own (labelled) measurements
    crowd = ScenarioSpec("crowd", "position", 4, "pv2d", 0.25, 12, labelled=False)
    why = declared_misfit(FittedSocialForce.for_scenario, crowd)
    assert why.startswith("model=sfm_fit reads each agent's desired velocity") and "scenario crowd" in why


def _faulty_lin(monkeypatch):
    """The constant-velocity model's constructor with a bug in it."""
    from dslearn.models.constant_velocity import ConstantVelocity

    def broken(self, *a, **k):
        raise RuntimeError("injected fault in the constant-velocity model")

    monkeypatch.setattr(ConstantVelocity, "__init__", broken)


def test_a_cell_whose_parts_raise_is_failed_not_n_a(monkeypatch, tmp_path):
    from dslearn.reports import matrix as rep
    from hydra_plugins.dslearn_matrix.matrix_sweeper import write_records

    _faulty_lin(monkeypatch)
    combos = [["method=ekf_lin_hybrid", "scenario=yu_two_agents"], ["method=ekf_lin_hybrid", "scenario=jiang"],
              ["method=ekf_sfm_hybrid", "scenario=yu_two_agents"], ["method=ekf_sfm_hybrid", "scenario=liu_s1"]]
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        kept, records = select_cells(combos, lambda ov: compose("config", overrides=["task=matrix", *ov]))
        one = compose("config", overrides=["task=matrix", *combos[0]])
    assert kept == [combos[2]]
    assert [r["status"] for r in records] == ["failed", "does_not_fit", "run", "does_not_fit"]
    bad = records[0]
    assert bad["job"] is None and bad["reason"] is None and bad["scenario"] == "yu"
    assert bad["method"] == "ekf_lin_hybrid"  # built nowhere in this sweep: its preset names the row
    assert "RuntimeError: injected fault in the constant-velocity model" in bad["error"]
    assert "raised while built for scenario yu" in bad["error"]
    # not built where its engine declares it does not fit: n/a with the spec's reason, not the fault
    assert records[1]["reason"] == ("ekf_lin_hybrid does not fit scenario jiang: consensus=hybrid exchanges information "
                                    "with neighbours over a communication graph; the sensors of scenario jiang have "
                                    "none (they report to a fusion centre: consensus=centralized)")
    assert records[3]["reason"].startswith("ekf sfm hybrid does not fit scenario s1: model=sfm is the true")
    # a single run of that cell stops with the error, not "does not fit"
    with pytest.raises(CellBuildError, match="injected fault") as e:
        misfit(one)
    assert "does not fit" not in str(e.value)
    from dslearn.app.precheck import precheck

    msg = precheck(["task=matrix", *combos[0], "task.train_episodes=1", "task.test_episodes=1"])
    assert msg is not None and "injected fault in the constant-velocity model" in msg and "does not fit" not in msg
    # recorded in matrix_cells.csv (status, error), not in skipped_cells.csv; the report shows it failed with its
    # error
    write_records(tmp_path, records)
    cells = pd.read_csv(tmp_path / "matrix_cells.csv")
    assert list(cells["status"]) == ["failed", "does_not_fit", "run", "does_not_fit"]
    assert "injected fault" in cells.loc[0, "error"] and cells["error"].iloc[1:].isna().all()
    skipped = pd.read_csv(tmp_path / "skipped_cells.csv")
    assert list(skipped["scenario"]) == ["jiang", "s1"]
    results = pd.DataFrame(columns=["method", "scenario", "units", "node", "node_kind", "episode", "metric", "value"])
    vals = rep.matrix_values(results, tmp_path)
    row = vals[(vals["method_label"] == "ekf_lin_hybrid") & (vals["scenario_name"] == "yu")].iloc[0]
    assert row["status"] == "failed" and "injected fault" in row["reason"]
    assert rep.cell_text(row).startswith("✗ failed [")


def test_a_configuration_error_is_no_cell():
    """A bad value raises before any job (never a failed or n/a cell)."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = compose("config", overrides=["task=matrix", "method=ekf_lin_hybrid", "scenario=yu_two_agents",
                                           "model.noise_std=-1"])
        with pytest.raises(ConfigError, match="noise_std"):
            judge(cfg)


def test_a_sweep_records_a_failed_cell_says_so_and_the_report_shows_it(tmp_path):
    """Through the commands: a motion model (in the user's config folder) whose factory raises; its cell on yu is
    failed in matrix_cells.csv with the error, is not run, the sweep says so on stderr and exits 1 after running
    the other cells; dslearn-report marks the cell failed with its error."""
    import os
    import subprocess
    import sys

    (tmp_path / "conf" / "model").mkdir(parents=True)
    (tmp_path / "faulty_part.py").write_text(
        "def make(noise_std=0.1, *, scenario, device=None):\n"
        "    raise RuntimeError('injected fault in a motion model')\n")
    (tmp_path / "conf" / "model" / "faulty.yaml").write_text(
        "_target_: faulty_part.make\n_partial_: true\nname: faulty\nnoise_std: 0.1\n")
    env = {**os.environ, "CI": "1", "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    sweep = tmp_path / "sweep"
    cmd = [sys.executable, "-m", "dslearn.run", "-m", "task=matrix", "hydra/sweeper=matrix", "hydra/launcher=basic",
           "method=ekf_lin_hybrid", "model=lin,faulty", "scenario=yu_two_agents,jiang",
           f"hydra.searchpath=[file://{(tmp_path / 'conf').as_posix()}]", "task.train_episodes=1",
           "task.test_episodes=1", "progress=false", f"hydra.sweep.dir={sweep}"]
    r = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 1, r.stderr[-3000:]
    assert "1 combination(s) FAILED" in r.stderr and "RuntimeError: injected fault in a motion model" in r.stderr
    cells = pd.read_csv(sweep / "matrix_cells.csv", keep_default_na=False)
    assert list(cells["status"]) == ["run", "does_not_fit", "failed", "does_not_fit"]
    assert cells.loc[2, "method"] == "ekf_lin_hybrid model=faulty" and cells.loc[2, "job"] == ""
    assert cells.loc[2, "error"].endswith("raised while built for scenario yu: RuntimeError: injected fault in a "
                                          "motion model")
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir() and p.name.isdigit()) == ["0"]
    r = subprocess.run([sys.executable, "-m", "dslearn.report", str(sweep)], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    vals = pd.read_csv(sweep / "matrix.csv")
    row = vals[(vals["method_label"] == "ekf_lin_hybrid model=faulty") & (vals["scenario_name"] == "yu")].iloc[0]
    assert row["status"] == "failed" and "injected fault in a motion model" in row["reason"]
    md = (sweep / "matrix.md").read_text()
    note = int(row["note"])
    assert f"✗ failed [{note}]" in md and f"[{note}] failed in the sweep's up-front check (not run)" in md
