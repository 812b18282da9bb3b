"""Golden outputs: every study's small run, recorded so a restructuring can prove it moved no number.

    python benchmarks/golden.py record --out DIR     # run them all, write DIR/<name>.csv.gz + DIR/manifest.json
    python benchmarks/golden.py check  [--out DIR]   # run them again and compare with DIR (default: benchmarks/golden)
    python benchmarks/golden.py check --only yu_default,jiang_small
    python benchmarks/golden.py check --rtol 1e-9   # CI: pass where every value is within the tolerance

Each small run is one ``dslearn-run`` command (below). Its ``results.csv`` is reduced to a canonical
table: timing rows (wall clock) dropped, rows sorted by every key column, values written with 17
significant digits, so equal numbers give equal files. ``check`` reports per run whether the table is
bit-identical (same SHA-256), else the largest absolute and relative difference of ``value`` over the
rows the two share, and rows only on one side. Float results are bit-identical only on the same CPU
kernel path and library versions (the manifest records them); across machines read the differences, or
give ``--rtol``: a run then passes when it has the same rows and every value is within
``atol + rtol * |golden|`` (``--atol``, default 1e-12), which is what CI checks.
The ETH/UCY runs need the data (``$DSLEARN_ETHUCY_ROOT`` or ``../shared/data/eth_ucy``) and are
skipped without it.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import gzip
import hashlib
import io
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "benchmarks" / "golden"

#: name -> (dslearn-run overrides, needs the ETH/UCY data)
RUNS: dict[str, tuple[list[str], bool]] = {
    "yu_default": ([], False),
    "yu_lin_individual": (["model=lin", "consensus=individual", "data.train_episodes=4", "data.test_episodes=3"], False),
    "yu_sfm_individual_blind": (["model=sfm", "consensus=individual", "network=yu_blind", "data.train_episodes=4",
                                 "data.test_episodes=3"], False),
    "yu_gp_hybrid": (["model=gp", "consensus=hybrid", "data.train_episodes=6", "data.test_episodes=3"], False),
    "yu_gp_adaptive_hybrid_nodes": (["model=gp_adaptive", "consensus=hybrid_nodes", "data.train_episodes=6",
                                     "data.test_episodes=3"], False),
    "yu_faults_small": (["experiment=yu_faults", "task.train_episodes=2", "task.test_episodes=2"], False),
    "liu_small": (["experiment=liu_table1", "task.mc_runs=2", "task.scenarios=[s1]", "task.noises=[2.0]"], False),
    "jiang_small": (["experiment=jiang_fg", "task.mc_runs=3"], False),
    "braga_small": (["experiment=braga_tbn", "task.mc_runs=1", "task.mc_batch=1", "task.workers=1", "task.steps=200",
                     "task.steady_state_s=5.0", "task.zoom_s=1.0"], False),
    "real_tables_small": (["experiment=real_tables", "task.scenes=[zara1]", "task.train_episodes=8",
                           "task.test_episodes=4", "task.models=[gp,gp_cv,lin,sfm]"], True),
    "forecast_small": (["experiment=ethucy_forecast", "task.quick=true", "task.scenes=[zara1]",
                        "task.predictors=[cv,gp]"], True),
    "gp_bayes_small": (["experiment=gp_bayes_filters", "task.num_cases=40", "task.num_particles=200"], False),
}

TIMING = re.compile(r"(?:wall|seconds|_ms$|_s$)")


def canonical(results: Path) -> str:
    """The canonical text of a results table (see the module docstring)."""
    df = pd.read_csv(results)
    if "metric" in df.columns:
        df = df[~df["metric"].astype(str).str.contains(TIMING)]
    keys = [c for c in df.columns if c != "value"]
    df = df.sort_values(keys, kind="mergesort").reset_index(drop=True)
    buf = io.StringIO()
    df.to_csv(buf, index=False, float_format="%.17g")
    return buf.getvalue()


def run_one(name: str, work: Path) -> tuple[str, float]:
    overrides, _ = RUNS[name]
    out = work / name
    cmd = [sys.executable, "-m", "dslearn.run", *overrides, f"hydra.run.dir={out}", "progress=false"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=work)
    wall = time.perf_counter() - t0
    if r.returncode != 0 or not (out / "results.csv").is_file():
        raise RuntimeError(f"{name}: dslearn-run failed (exit {r.returncode}): {r.stderr.strip().splitlines()[-1:]}")
    return canonical(out / "results.csv"), wall


def _commit() -> str | None:
    try:
        return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def _select(only: str | None) -> list[str]:
    names = list(RUNS) if not only else [n.strip() for n in only.split(",") if n.strip()]
    unknown = [n for n in names if n not in RUNS]
    if unknown:
        raise SystemExit(f"golden: unknown run(s) {unknown}; choose from {list(RUNS)}")
    from dslearn.data.ethucy import data_available

    data = data_available()
    return [n for n in names if data or not RUNS[n][1]]


def record(out: Path, only: str | None) -> None:
    import torch

    out.mkdir(parents=True, exist_ok=True)
    manifest = {"recorded_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                "git_commit": _commit(), "python": platform.python_version(), "torch": torch.__version__,
                "pandas": pd.__version__, "machine": platform.machine(), "processor": platform.processor(),
                "runs": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for name in _select(only):
            text, wall = run_one(name, Path(tmp))
            (out / f"{name}.csv.gz").write_bytes(gzip.compress(text.encode(), mtime=0))
            manifest["runs"][name] = {"command": ("dslearn-run " + " ".join(RUNS[name][0])).strip(),
                                      "sha256": hashlib.sha256(text.encode()).hexdigest(),
                                      "rows": text.count("\n") - 1, "wall_s": round(wall, 1)}
            print(f"{name}: {manifest['runs'][name]['rows']} rows, {wall:.1f} s")
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    print(f"wrote {out}/manifest.json")


def compare(old: str, new: str, rtol: float | None = None, atol: float = 1e-12) -> tuple[str, bool]:
    """Verdict and whether it passes: bit-identical, or (with ``rtol``) the same rows and every value
    within ``atol + rtol * |golden|``."""
    if old == new:
        return "bit-identical", True
    a, b = pd.read_csv(io.StringIO(old)), pd.read_csv(io.StringIO(new))
    keys = [c for c in a.columns if c != "value"]
    if list(a.columns) != list(b.columns):
        return f"DIFFERENT columns: {list(a.columns)} vs {list(b.columns)}"
    m = a.merge(b, on=keys, how="outer", suffixes=("_old", "_new"), indicator=True)
    both = m[m["_merge"] == "both"]
    va = pd.to_numeric(both["value_old"], errors="coerce")
    vb = pd.to_numeric(both["value_new"], errors="coerce")
    d = (va - vb).abs()
    rel = d / va.abs().clip(lower=1e-300)
    only_old, only_new = int((m["_merge"] == "left_only").sum()), int((m["_merge"] == "right_only").sum())
    same_nan = va.isna() & vb.isna()
    within = bool(rtol is not None and only_old == only_new == 0
                  and ((d <= atol + rtol * va.abs()) | same_nan).all())
    label = f"within rtol {rtol:g}" if within else "DIFFERENT"
    return (f"{label}: max |diff| {d.max():.3g}, max rel {rel.max():.3g} over {len(both)} shared rows; "
            f"{only_old} rows only in the golden file, {only_new} only in the new run"), within


#: runs whose numbers move more than rounding across CPUs, with the tolerance they get under ``--rtol`` (the larger
#: of the two) and why: the GP-Bayes benchmark fits its GPs' hyperparameters by an optimiser and draws particles, so
#: a CPU's own rounding is amplified (measured: up to 3.7e-7 relative between an AMD EPYC and the recording
#: machine, the same on the code before and after a change that touched none of it)
CROSS_CPU = {"gp_bayes_small": (1e-6, 1e-9)}


def check(out: Path, only: str | None, rtol: float | None = None, atol: float = 1e-12, jobs: int = 1) -> int:
    """Run every selected study's small run (``jobs`` at a time, each a single-threaded process) and compare it
    with its golden file; the verdicts are printed in the runs' order. Exit status 1 if any differs."""
    from concurrent.futures import ThreadPoolExecutor

    manifest = json.loads((out / "manifest.json").read_text())
    bad = 0
    names = _select(only)
    with tempfile.TemporaryDirectory() as tmp, ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        runs = {n: pool.submit(run_one, n, Path(tmp)) for n in names if n in manifest["runs"]}
        for name in names:
            if name not in manifest["runs"]:
                print(f"{name}: not recorded")
                bad += 1
                continue
            old = gzip.decompress((out / f"{name}.csv.gz").read_bytes()).decode()
            new, wall = runs[name].result()
            r, a = rtol, atol
            if rtol is not None and name in CROSS_CPU:
                r, a = max(rtol, CROSS_CPU[name][0]), max(atol, CROSS_CPU[name][1])
            verdict, ok = compare(old, new, r, a)
            bad += not ok
            print(f"{name}: {verdict} ({wall:.1f} s)")
    return 1 if bad else 0


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("command", choices=["record", "check"])
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"golden folder (default {DEFAULT_OUT.relative_to(ROOT)})")
    p.add_argument("--only", default=None, help="comma-separated run names")
    p.add_argument("--rtol", type=float, default=None,
                   help="check: pass a run whose values are all within atol + rtol*|golden| (default: bit-identity)")
    p.add_argument("--atol", type=float, default=1e-12, help="check: absolute part of the tolerance (with --rtol)")
    p.add_argument("--jobs", type=int, default=1, help="check: runs at a time (each one single-threaded process)")
    a = p.parse_args(argv)
    if a.command == "record":
        if "--out" not in (argv if argv is not None else sys.argv[1:]):
            p.error("record needs --out DIR (it never writes over the committed golden files by default)")
        record(a.out, a.only)
    else:
        sys.exit(check(a.out, a.only, a.rtol, a.atol, a.jobs))


if __name__ == "__main__":
    main()
