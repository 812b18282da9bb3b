"""A sweep's console output: one overall status line per finished job, no launcher lines, and
Ctrl-C = one line with the command that resumes the sweep (exit 130)."""

import contextlib
import io
import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from dslearn.callbacks import SweepStatus, launcher_workers, status_line
from dslearn.io import check_complete

ROOT = Path(__file__).resolve().parents[1]
# 4 jobs of ~2 s each (no training): two at a time under the default launcher
GRID = ["model=lin,sfm", "consensus=individual,hybrid", "data.train_episodes=0", "data.test_episodes=2"]
STATUS = re.compile(r"^\[sweep\] (\d+)/(\d+) done, (\d+) failed, (\d+) running, ETA (\S+)$")


def _cmd(*args):
    return [sys.executable, "-m", "dslearn.run", *args]


def _env():
    return {**os.environ, "CI": "1"}


def _table(sweep_dir):
    t = pd.read_csv(Path(sweep_dir) / "sweep_results.csv").drop(columns=["run_dir"])
    return t.sort_values(["job", "node", "episode", "metric"]).reset_index(drop=True)


def test_status_line_eta_and_workers():
    # ETA = mean wall of the finished jobs x jobs left / workers busy (at most the jobs left)
    assert status_line(5, 0, 2, 18, [10.0, 20.0, 30.0, 20.0, 20.0], 2) == \
        "[sweep] 5/18 done, 0 failed, 2 running, ETA 2m10s"  # 20 s x 13 / 2
    assert status_line(2, 1, 1, 4, [4.0, 8.0], 4) == "[sweep] 3/4 done, 1 failed, 1 running, ETA 6s"  # 6 x 1 / 1
    assert status_line(3, 1, 0, 4, [1.0], 2) == "[sweep] 4/4 done, 1 failed, 0 running, ETA 0s"
    assert status_line(1, 0, 1, 4, [], 2) == "[sweep] 1/4 done, 0 failed, 1 running, ETA ?"  # only resumed jobs yet
    assert status_line(0, 1, 0, 100, [3600.0 * 3], 4).endswith("ETA 74h15m")  # 3 h x 99 / 4
    # joblib's n_jobs: negative counts from the CPUs (-1 = all, -2 = all but one)
    assert launcher_workers({"_target_": "x.JoblibLauncher", "n_jobs": -1}, cpus=8) == 8
    assert launcher_workers({"_target_": "x.JoblibLauncher", "n_jobs": -2}, cpus=8) == 7
    assert launcher_workers({"_target_": "x.JoblibLauncher", "n_jobs": 3}, cpus=8) == 3
    assert launcher_workers({"_target_": "hydra._internal.core_plugins.basic_launcher.BasicLauncher"}, cpus=8) == 1


def test_status_poller_counts_fresh_jobs_only(tmp_path):
    """The poller reads the sweep folder: a job started = its .hydra record, finished = its status.json,
    both written after the sweep started; an older status (a resumed sweep's earlier run) is not counted."""
    def job(i, status=None, wall=None, started=True):
        d = tmp_path / str(i)
        if started:
            (d / ".hydra").mkdir(parents=True, exist_ok=True)
            (d / ".hydra" / "overrides.yaml").write_text("[]")
        if status is not None:
            (d / "status.json").write_text(json.dumps({"status": status, "wall_s": wall}))

    job(0, "done", 99.0)  # a finished job of an earlier run of this sweep folder
    old = time.time() - 100
    os.utime(tmp_path / "0" / "status.json", (old, old))
    os.utime(tmp_path / "0" / ".hydra" / "overrides.yaml", (old, old))
    os.utime(tmp_path / "0" / ".hydra", (old, old))
    out = io.StringIO()
    st = SweepStatus(tmp_path, jobs=4, workers=2, stream=out, since=time.time() - 1)
    assert st.poll() == []
    job(1)
    job(2)
    assert st.poll() == []
    job(1, "done", 6.0)
    assert st.poll() == ["[sweep] 1/4 done, 0 failed, 1 running, ETA 9s"]  # 6 s x 3 left / 2 workers
    job(3)
    job(2, "failed", 100.0)  # a failure counts as finished; its wall time is not a job's
    job(0, "skipped", 0.01)  # resumed: counted done, no wall time
    # one line per job, in the order they finished (job 2, then job 0: its .hydra record is rewritten, so it ran)
    assert st.poll() == ["[sweep] 2/4 done, 1 failed, 2 running, ETA 6s",  # 6 s x 2 left / 2
                         "[sweep] 3/4 done, 1 failed, 1 running, ETA 6s"]  # 6 s x 1 left / 1
    job(3, "interrupted")
    assert st.poll() == []  # an interrupted job is not finished
    job(3, "done", 12.0)
    assert st.poll() == ["[sweep] 4/4 done, 1 failed, 0 running, ETA 0s"]
    assert out.getvalue().splitlines() == st.lines and len(st.lines) == 4


@pytest.fixture(scope="module")
def clean_sweep(tmp_path_factory):
    d = tmp_path_factory.mktemp("clean")
    r = subprocess.run(_cmd("-m", *GRID, f"hydra.sweep.dir={d}"), cwd=ROOT, env=_env(), capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    return d, r


def test_sweep_prints_one_status_line_per_job_and_no_launcher_lines(clean_sweep):
    d, r = clean_sweep
    lines = [STATUS.match(ln) for ln in r.stdout.splitlines() if ln.startswith("[sweep]")]
    assert all(lines), r.stdout
    counts = [(int(m[1]), int(m[2]), int(m[3]), int(m[4])) for m in lines]
    assert [c[0] for c in counts] == [1, 2, 3, 4] and all(c[1] == 4 and c[2] == 0 for c in counts), counts
    assert all(0 <= c[3] <= 2 for c in counts) and counts[-1][3] == 0 and lines[-1][5] == "0s"
    assert "Joblib.Parallel" not in r.stdout and "Launching jobs" not in r.stdout and "#0 :" not in r.stdout
    assert r.stderr.strip() == "", r.stderr  # no bars, no warnings
    assert json.loads((d / "sweep.json").read_text())["done"] == 4


@pytest.mark.serial  # signals and timing: run alone, before the parallel run (the README's test command)
def test_ctrl_c_in_sweep_one_line_and_resume_command_finishes_it(tmp_path):
    d = tmp_path / "sweep dir"  # a space: the resume command must quote it
    clean = tmp_path / "clean"  # the uninterrupted sweep, meanwhile, on the core the serial pass leaves free
    baseline = subprocess.Popen(_cmd("-m", *GRID, f"hydra.sweep.dir={clean}"), cwd=ROOT, env=_env(),
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    # the child gets SIGINT's default disposition whatever the test runner inherited
    p = subprocess.Popen(_cmd("-m", *GRID, f"hydra.sweep.dir={d}"), cwd=ROOT, env=_env(), stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    t0 = time.time()
    try:
        while not any(check_complete(d / str(i))[0] for i in range(4)):
            assert p.poll() is None, p.communicate()
            assert time.time() - t0 < 300
            time.sleep(0.02)
        os.killpg(p.pid, signal.SIGINT)  # Ctrl-C in a terminal: the whole process group
        out, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    assert p.returncode == 130, (err, out[-2000:])
    done = sum(check_complete(d / str(i))[0] for i in range(4))
    assert 1 <= done < 4, "the sweep finished before Ctrl-C reached it"
    expected = shlex.join(["dslearn-run", "-m", *GRID, f"hydra.sweep.dir={d}", "resume=true"])
    assert err.splitlines() == [f"dslearn-run: interrupted: {done} of 4 jobs done; resume with: {expected}"], err
    assert "Traceback" not in out and "leaked" not in err
    # the printed command, as a shell splits it, resumes the sweep: the same table as the uninterrupted one
    args = shlex.split(err.split("resume with: ", 1)[1])
    assert args[0] == "dslearn-run"
    r = subprocess.run(_cmd(*args[1:]), cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    s = json.loads((d / "sweep.json").read_text())
    assert (s["jobs"], s["skipped"], s["done"], s["failed"]) == (4, done, 4 - done, 0)
    assert baseline.wait(timeout=600) == 0
    pd.testing.assert_frame_equal(_table(d), _table(clean))


@pytest.mark.serial  # signals and timing: run alone, before the parallel run (the README's test command)
def test_ctrl_c_in_a_basic_launcher_sweep_in_process(tmp_path, monkeypatch):
    """The basic launcher runs the jobs in this process: an interrupt in job 1 is the sweep's one line."""
    from dslearn.run import main
    from dslearn.studies.yu import YuStudy

    real = YuStudy.run
    calls = []

    def run(self, *a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt()
        return real(self, *a, **k)

    monkeypatch.setattr(YuStudy, "run", run)
    d = tmp_path / "s"
    argv = ["-m", "model=lin,sfm", "data.train_episodes=0",
            "data.test_episodes=1", "hydra/launcher=basic", f"hydra.sweep.dir={d}"]
    out, err = io.StringIO(), io.StringIO()
    monkeypatch.setenv("CI", "1")
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 130
    expected = shlex.join(["dslearn-run", *[a for a in argv if not a.startswith("hydra.sweep.dir")],
                           f"hydra.sweep.dir={d}", "resume=true"])
    assert err.getvalue().splitlines() == [f"dslearn-run: interrupted: 1 of 2 jobs done; resume with: {expected}"]
    status = [ln for ln in out.getvalue().splitlines() if ln.startswith("[sweep]")]
    assert len(status) == 1 and re.fullmatch(r"\[sweep\] 1/2 done, 0 failed, [01] running, ETA \d+s", status[0]), status
    assert json.loads((d / "1" / "status.json").read_text())["status"] == "interrupted"
    from dslearn.io import RunLock

    with RunLock(d):  # the sweep folder's lock was released
        pass
