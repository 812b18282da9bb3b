"""Start-up time of the command-line programs: how long a command takes that does no work.

    python benchmarks/startup.py                  # every command, median of 5 runs each
    python benchmarks/startup.py --repeat 9 --only run-help,run-version
    python benchmarks/startup.py --src DIR        # another checkout's code (e.g. an exported older commit)

Each command runs as ``python -m <module> ARGS`` in a fresh interpreter (the console scripts do the same
import), in an empty temporary folder, with ``COMP_LINE`` set for the completion request. Printed per
command: the median, min and max wall time in seconds, the exit code, and whether PyTorch was imported
(``-X importtime`` on the last run). Target (issue 25): ``--help``, ``--version``, a refused option and a
completion request under 1 s on 2 cores; they do not import torch, gpytorch or numba.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: name -> (module, arguments, extra environment)
COMMANDS = {
    "run-help": ("dslearn.run", ["--help"], {}),
    "run-version": ("dslearn.run", ["--version"], {}),
    "run-bad-option": ("dslearn.run", ["model=typo"], {}),
    "run-complete-option": ("dslearn.run", ["-sc", "query=bash"], {"COMP_LINE": "dslearn-run model=gp_"}),
    "run-complete-root": ("dslearn.run", ["-sc", "query=bash"], {"COMP_LINE": "dslearn-run "}),
    "run-bad-key": ("dslearn.run", ["data.train_episode=2"], {}),  # needs the composed config (the schemas)
    "report-help": ("dslearn.report", ["--help"], {}),
    "bench-help": ("dslearn.bench", ["--help"], {}),
    "train-lstm-help": ("dslearn.train_lstm", ["--help"], {}),
}
HEAVY = ("torch", "gpytorch", "numba")


def _imported(stderr: str) -> list[str]:
    """The heavy modules named in ``-X importtime`` output."""
    seen = set()
    for ln in stderr.splitlines():
        if ln.startswith("import time:"):
            name = ln.rsplit("|", 1)[-1].strip()
            if name in HEAVY:
                seen.add(name)
    return sorted(seen)


def measure(name: str, repeat: int, src: str | None) -> dict:
    module, args, extra = COMMANDS[name]
    env = {**os.environ, **extra}
    env.pop("PYTHONWARNINGS", None)
    if src:
        env["PYTHONPATH"] = src + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    if "COMP_LINE" not in extra:
        env.pop("COMP_LINE", None)
    times, rc, heavy = [], None, []
    with tempfile.TemporaryDirectory(prefix="dslearn-startup-") as cwd:
        for i in range(repeat):
            last = i == repeat - 1
            cmd = [sys.executable] + (["-X", "importtime"] if last else []) + ["-m", module, *args]
            t0 = time.perf_counter()
            r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
            if not last:  # importtime's own output costs time: the timed runs go without it
                times.append(time.perf_counter() - t0)
            rc = r.returncode
            if last:
                heavy = _imported(r.stderr)
    return {"name": name, "median": statistics.median(times), "min": min(times), "max": max(times), "rc": rc,
            "heavy": heavy}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=5, help="timed runs per command (default 5; the median is shown)")
    ap.add_argument("--only", default="", help=f"comma-separated commands of {list(COMMANDS)}")
    ap.add_argument("--src", default=None, help="a source folder put first on PYTHONPATH (default: the installed dslearn)")
    a = ap.parse_args(argv)
    names = [n for n in a.only.split(",") if n] or list(COMMANDS)
    bad = [n for n in names if n not in COMMANDS]
    if bad:
        ap.error(f"--only: unknown command(s) {bad}; choose from {list(COMMANDS)}")
    if a.repeat < 1:
        ap.error("--repeat must be >= 1")
    print(f"python {sys.version.split()[0]}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}; "
          f"median of {a.repeat} (s)" + (f"; code from {Path(a.src).resolve()}" if a.src else ""))
    print(f"{'command':<22} {'median':>7} {'min':>7} {'max':>7} {'exit':>5}  heavy imports")
    for n in names:
        r = measure(n, a.repeat + 1, a.src)
        print(f"{n:<22} {r['median']:7.2f} {r['min']:7.2f} {r['max']:7.2f} {r['rc']:5d}  {','.join(r['heavy']) or '-'}",
              flush=True)


if __name__ == "__main__":
    main()
