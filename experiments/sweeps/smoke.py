"""Launcher smoke check: the same 4-job sweep with each Hydra launcher, then compare the tables.

    python experiments/sweeps/smoke.py                       # basic + every installed launcher
    python experiments/sweeps/smoke.py --launchers basic joblib submitit_local
    python experiments/sweeps/smoke.py --launchers ray --python .venv-ray/bin/python

Each launcher runs ``dslearn-run -m model=lin,sfm consensus=individual,hybrid`` on tiny data
(``data.train_episodes=0 data.test_episodes=2``; override with --data) into
``<out>/<launcher>`` (a fixed ``hydra.sweep.dir``). The GatherResults callback writes each sweep's
``sweep_results.csv``; this script checks that every sweep has 4 jobs, 4 rows per
(metric, node, episode) key, and values identical to the basic launcher's (same seed).
Exit code 0 = all identical.
"""

from __future__ import annotations

import argparse
import importlib.util
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd

GRID = ["model=lin,sfm", "consensus=individual,hybrid"]
LAUNCHER_ARGS = {
    "basic": ["hydra/launcher=basic"],
    "joblib": ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"],
    # submitit's local executor starts every job of a batch at once: cap with the sweeper's batch size
    "submitit_local": ["hydra/launcher=submitit_local", "hydra.sweeper.max_batch_size=2", "hydra.launcher.timeout_min=10"],
    # a local Ray instance started by the launcher (Ray 2.60 has no local_mode); 2 CPUs for Ray
    "ray": ["hydra/launcher=ray", "+hydra.launcher.ray.init.num_cpus=2"],
}
PLUGIN = {"joblib": "hydra_plugins.hydra_joblib_launcher", "submitit_local": "hydra_plugins.hydra_submitit_launcher",
          "ray": "hydra_plugins.hydra_ray_launcher"}
KEYS = ["ov.model", "ov.consensus", "node", "episode", "metric"]


def run_sweep(launcher: str, out: Path, data: list[str], python: str) -> tuple[int, float]:
    d = out / launcher
    shutil.rmtree(d, ignore_errors=True)
    cmd = [python, "-m", "dslearn.run", "-m", *GRID, *data, *LAUNCHER_ARGS[launcher], f"hydra.sweep.dir={d}"]
    print("$", " ".join(cmd), flush=True)
    t0 = time.perf_counter()
    with open(out / f"{launcher}.log", "w") as log:
        rc = subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT)
    return rc, time.perf_counter() - t0


def compare(out: Path, launchers: list[str], ref: str = "basic") -> bool:
    tables = {}
    for la in launchers:
        p = out / la / "sweep_results.csv"
        if not p.is_file():
            print(f"{la}: no gathered table {p}")
            return False
        tables[la] = pd.read_csv(p).sort_values(KEYS).reset_index(drop=True)
    ok = True
    for la, t in tables.items():
        per_key = t.groupby(["metric", "node", "episode"]).size()
        jobs = t["job"].nunique()
        print(f"{la}: {jobs} jobs, {len(t)} rows, rows per (metric, node, episode) key: {sorted(per_key.unique())}")
        ok &= jobs == 4 and set(per_key.unique()) == {4}
    base = tables.get(ref, next(iter(tables.values())))
    for la, t in tables.items():
        same = t[KEYS].equals(base[KEYS]) and (t["value"].values == base["value"].values).all()
        print(f"{la}: values identical to {ref}: {bool(same)}")
        ok &= bool(same)
    return ok


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--launchers", nargs="+", default=None)
    p.add_argument("--out", default="sweep_smoke")
    p.add_argument("--python", default=sys.executable, help="interpreter for the sweeps (e.g. a venv with Ray)")
    p.add_argument("--data", nargs="*", default=["data.train_episodes=0", "data.test_episodes=2"])
    p.add_argument("--compare-only", action="store_true")
    a = p.parse_args()
    launchers = a.launchers or ["basic"] + [k for k, m in PLUGIN.items() if importlib.util.find_spec(m.split(".")[0]) and _has(m)]
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    if not a.compare_only:
        for la in launchers:
            rc, wall = run_sweep(la, out, a.data, a.python)
            print(f"{la}: exit {rc}, {wall:.1f}s (log {out / (la + '.log')})", flush=True)
    present = [la for la in ["basic", *PLUGIN] if (out / la / "sweep_results.csv").is_file()]
    ok = compare(out, present)
    print("ALL IDENTICAL" if ok else "MISMATCH")
    raise SystemExit(0 if ok else 1)


def _has(mod: str) -> bool:
    try:
        return importlib.util.find_spec(mod) is not None
    except ModuleNotFoundError:
        return False


if __name__ == "__main__":
    main()
