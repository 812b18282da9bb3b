"""dslearn-run's command line: --help, --version, the start-up check of every sweep job (exactly
Hydra's compositions, cheaply), numerical-warning accounting, and the cost-weighted progress ETA."""

import io
import logging
import time
import warnings
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from dslearn import __version__
from dslearn.progress import CostBar, episode_costs, evaluation_bar, gp_episode_cost, track, training_bar
from dslearn.app.common import CONF_DIR
from dslearn.app.composer import check_jobs, sweep_combinations
from dslearn.app.help import help_text, version_text
from dslearn.app.record import WarningLedger
from dslearn.run import main

ROOT = Path(__file__).resolve().parents[1]


def test_help_lists_groups_and_experiments(capsys):
    main(["--help"])
    out = capsys.readouterr().out
    lines = out.splitlines()
    # every experiment and every option of every group, with the first comment line of its YAML
    for p in sorted((ROOT / "conf" / "experiment").glob("*.yaml")):
        assert any(ln.strip().startswith(p.stem + " ") for ln in lines), p.stem
    for group in ("model", "consensus", "data", "network", "observation", "scenario", "task"):
        assert f"  {group}:" in lines, group
        for p in (ROOT / "conf" / group).glob("*.yaml"):
            assert any(ln.strip().lstrip("* ").startswith(p.stem + " ") for ln in lines), (group, p.stem)
    assert any("gp_increment" in ln and "GP with identity prior mean" in ln and "*" in ln for ln in lines)
    assert any("yu_table1" in ln and "Table I of Yu et al." in ln for ln in lines)
    for text in ("sweeps:", "-m model=lin,gp", "outputs:", "dslearn-report DIR", "+max_memory_gb=<GB>", "resume=true"):
        assert text in out, text
    assert "Hydra" not in lines[0] and "Powered by Hydra" not in out
    assert help_text() == out.rstrip("\n")


def test_version(capsys):
    main(["--version"])
    assert capsys.readouterr().out.strip() == f"dslearn-run (dslearn) {__version__}" == version_text()


def _jobs(argv, compose):
    from hydra import initialize_config_dir

    got = []
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        combos, multirun, _ = sweep_combinations(argv)
        n, composes = check_jobs(combos, compose, visit=lambda c: got.append(OmegaConf.to_container(c, resolve=True)))
    return combos, multirun, got, composes


@pytest.mark.parametrize("argv", [
    ["-m", "model=lin,gp_sgpr", "consensus=individual,hybrid_nodes", "network.meas_std=0.1,0.3"],
    ["experiment=yu_table1", "model=lin,sfm"],     # the experiment's sweeper params; the command line's model wins
    ["-m", "experiment=liu_table1", "scenario=s1,s2", "task.noises=[1],[4]", "task.mc_runs=2,3"],
    ["-m", "data.eval_at=[0],[1,2]", "data.train_episodes=2,3", "+max_memory_gb=5"],
])
def test_every_job_config_equals_hydras(argv):
    """The cheap per-job configurations are exactly what Hydra composes for each job."""
    from hydra import compose, initialize_config_dir

    def comp(ov):
        return compose("config", overrides=list(ov))

    combos, multirun, got, _ = _jobs(argv, comp)
    assert multirun and len(got) == len(combos) > 1
    if argv[0] == "experiment=yu_table1":
        assert sorted({c["model"]["name"] for c in got}) == ["lin", "sfm"] and len(combos) == 2 * 3
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        ref = [OmegaConf.to_container(compose("config", overrides=list(c)), resolve=True) for c in combos]
    assert got == ref


def test_experiment_sweep_expands_its_params():
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        combos, multirun, _ = sweep_combinations(["experiment=yu_table1", "seed=0,1"])
    assert multirun and len(combos) == 5 * 3 * 2  # models x fusions (hydra.sweeper.params) x seeds
    assert {tuple(c) for c in combos} == {
        (f"model={m}", f"consensus={f}", "experiment=yu_table1", f"seed={s}")
        for m in ("lin", "sfm", "gp", "gp_increment", "gp_adaptive") for f in ("individual", "hybrid", "hybrid_nodes")
        for s in (0, 1)
    }


def test_hundred_job_grid_composes_few_times():
    """A 5 x 4 x 5 grid: one composition for the base + one per group option (not one per job)."""
    from hydra import compose

    argv = ["-m", "model=lin,sfm,gp,gp_increment,gp_adaptive", "consensus=individual,hybrid,hybrid_nodes,ci", "seed=range(5)"]
    t0, c0 = time.perf_counter(), time.process_time()
    combos, _, got, composes = _jobs(argv, lambda ov: compose("config", overrides=list(ov)))
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    assert len(combos) == len(got) == 100
    assert composes == 1 + 5 + 4
    print(f"100-job grid checked: {composes} compositions, wall {wall:.2f} s, cpu {cpu:.2f} s")


def test_warning_ledger_counts_jitter_and_shows_others_once():
    from gpytorch.utils.warnings import NumericalWarning

    from dslearn.diagnostics import record_jitter

    with warnings.catch_warnings(record=True) as outer:
        warnings.simplefilter("always")
        with WarningLedger() as led:
            warnings.warn("A not p.d., added jitter of 1.0e-06 to the diagonal", NumericalWarning)
            warnings.warn("A not p.d., added jitter of 1.0e-04 to the diagonal", NumericalWarning)
            record_jitter(3e-8)  # what safe_cholesky records inside a run
            warnings.warn("OnlineGP.append: new point nearly dependent on the data; diagonal clamped")
            for _ in range(3):
                warnings.warn("scene zara1: only 5 training episodes", UserWarning)
    assert led.jitter_warnings == 2 and led.events == 1 and led.total == 3
    assert led.total_max == pytest.approx(1e-4)
    shown = [str(w.message) for w in outer]
    assert shown == ["scene zara1: only 5 training episodes (x3)"]


def test_meta_records_jitter(make_cfg, tmp_path):
    import json

    from dslearn.app.record import execute

    execute(make_cfg("model=lin", "data.train_episodes=0", "data.test_episodes=1"), tmp_path)
    meta = json.loads((tmp_path / "meta.json").read_text())
    assert meta["jitter_events"] == 0 and meta["jitter_max"] == 0.0


# ------------------------------------------------------------------------------------------
# progress


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def test_cost_weighted_eta_is_exact_under_the_cost_model():
    """Episodes whose real times follow the cost model: the weighted ETA equals the true remaining
    time after every episode; the plain (equal-weight) ETA is 2-3x optimistic early on."""
    n, steps = 150, 12
    costs = episode_costs(n, steps, {"name": "gp_increment"})
    assert costs[0] == 1.0 and costs[10] == pytest.approx(gp_episode_cost(120))
    assert all(b > a for a, b in zip(costs, costs[1:]))  # slows down as the data grows
    clock = Clock()
    bar = CostBar(costs, enable=False, clock=clock)
    sec = 0.056  # seconds per unit cost
    for j in range(n):
        clock.t += sec * costs[j]
        bar.update(1)
        true_left = sec * sum(costs[j + 1:])
        assert bar.eta_s() == pytest.approx(true_left, rel=1e-9, abs=1e-9)
        if j + 1 == 15:
            plain = (clock.t - 100.0) / (j + 1) * (n - j - 1)
            assert 2.0 < true_left / plain < 3.5
    assert bar.done == pytest.approx(bar.total, rel=1e-12) and bar.items == n


def test_cost_models_of_variants_and_parametric_models():
    assert episode_costs(4, 12, {"name": "lin", "kind": "lin"}) == [1.0] * 4
    assert episode_costs(3, 12, {"name": "gp"}, learnable=False) == [1.0] * 3
    win = episode_costs(100, 12, {"name": "gp_window", "variant": "window", "window": 500})
    assert win[50] == win[99] == pytest.approx(gp_episode_cost(500))  # flat past the window
    ssgp = episode_costs(40, 12, {"name": "gp_ssgp", "variant": "ssgp", "features": 200})
    assert ssgp[-1] == pytest.approx(gp_episode_cost(200))
    ev = evaluation_bar([0, 10, 20], 12, {"name": "gp"}, enable=False)
    assert ev.costs == [gp_episode_cost(0), gp_episode_cost(120), gp_episode_cost(240)]


def test_bar_draws_percent_and_items():
    buf = io.StringIO()
    bar = training_bar(5, 12, {"name": "gp"}, enable=True, desc="train gp/hybrid", file=buf)
    for _ in range(5):
        bar.update(1)
    bar.close()
    text = buf.getvalue()
    assert "train gp/hybrid" in text and "100%" in text and "5/5 episodes" in text
    assert [x for x in track(range(3), enable=False)] == [0, 1, 2]
    quiet = training_bar(5, 12, {"name": "gp"}, enable=False)
    assert quiet._bar is None


def test_log_lines_do_not_break_the_bar():
    from dslearn.app.job import _progress_context

    root = logging.getLogger()
    h = logging.StreamHandler()  # a console handler like Hydra's
    root.addHandler(h)
    try:
        with _progress_context(True):
            names = [type(x).__name__ for x in root.handlers]
            assert "_TqdmLoggingHandler" in names and h not in root.handlers
        assert h in root.handlers
        with _progress_context(False):
            assert h in root.handlers
    finally:
        root.removeHandler(h)


def test_train_lstm_console_refuses_in_one_line(tmp_path):
    """``dslearn-train-lstm`` (the console entry, a real interpreter): an unknown key is one line
    naming the key and the group's keys, exit code 2, no traceback, and no run folder made."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "CI": "1", "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    r = subprocess.run([sys.executable, "-m", "dslearn.train_lstm", "lstm.warmup=3"], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=300)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert lines[0].startswith("dslearn-train-lstm: configuration error: lstm.warmup: no such key in the configuration "
                               "(known keys of lstm: ['batch_size', 'embed', 'epochs',"), lines[0]
    assert "Traceback" not in r.stderr + r.stdout
    assert list(tmp_path.iterdir()) == []  # no outputs/train_lstm/<time> folder
