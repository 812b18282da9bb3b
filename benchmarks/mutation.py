"""Mutation testing of the filtering and fusion code: would the tests notice a small bug?

    python benchmarks/mutation.py run [--max-children 2]   # mutate and test (resumable: Ctrl-C, run again)
    python benchmarks/mutation.py run --sample 500 --seed 0  # a random sample of the mutants (an estimate)
    python benchmarks/mutation.py report                   # kill ratio, survivors -> benchmarks/mutation/

``run`` tests the last commit: it exports ``HEAD`` into ``.mutation/`` (not tracked; the working tree's
uncommitted edits are not seen) and calls mutmut there (``pip install mutmut``; its settings are
``[tool.mutmut]`` in ``pyproject.toml``: the modules under ``dslearn/fusion/``, ``dslearn/filters/`` and
``dslearn/metrics/``, the whole test suite, each mutant against the tests that cover the mutated
function). mutmut keeps every verdict in ``.mutation/mutants/``, so a second ``run`` tests only what is
left or what changed since; this is a benchmark, not part of CI (a full run takes hours on two cores).

``run --sample K --seed S`` tests a simple random sample of ``K`` of the mutants (drawn with
``random.Random(S)`` from their sorted names, kept in ``.mutation/sample.json``), so the kill ratio is
an estimate with a binomial confidence interval at a fraction of the cost; ``report`` then covers only
the sample and gives the 95 % Wilson interval.

``report`` reads those verdicts and writes ``benchmarks/mutation/summary.md`` and ``survivors.csv``:
the kill ratio per module and overall (killed, timed out or crashed, over every mutant tested), and
every survivor with its change. A survivor that cannot be killed because it changes nothing
observable (an equivalent mutant) is explained in ``benchmarks/mutation/explained.toml``, matched by
module, function and the changed line; the report marks each survivor explained or not and exits 1
while any is unexplained.
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import shutil
import subprocess
import sys
import tomllib
from collections import Counter, defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
WORK = ROOT / ".mutation"  # the exported commit and mutmut's mutants/ (not tracked)
OUT = ROOT / "benchmarks" / "mutation"
EXPLAINED = OUT / "explained.toml"

#: mutmut's exit codes -> verdict (mutmut.stats.status_by_exit_code, grouped)
KILLED = {1: "killed", 3: "killed", 36: "timeout", 24: "timeout", -24: "timeout", 152: "timeout", 255: "timeout",
          -11: "crashed", -9: "crashed", 37: "killed"}
SURVIVED = {0: "survived", 5: "no tests", 33: "no tests", 35: "suspicious"}
NOT_TESTED = {None: "not checked", 34: "skipped", 2: "interrupted"}


def _mutmut() -> str:
    exe = shutil.which("mutmut")
    if exe is None:
        raise SystemExit("mutation: mutmut is not installed (pip install mutmut)")
    return exe


def export_head() -> None:
    """``HEAD``'s tracked files into :data:`WORK` (over the previous export; mutmut's verdicts stay),
    with ``dslearn/conf`` pointing at the exported ``conf/`` (the packaged configs, as an install has)."""
    WORK.mkdir(exist_ok=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", "HEAD"], capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(WORK)], input=archive, check=True)
    link = WORK / "dslearn" / "conf"
    if not link.exists():
        link.symlink_to(Path("..") / "conf")
    # verdicts of modules that no longer exist (moved or deleted since the last run) are dropped
    tracked = set(subprocess.run(["git", "-C", str(ROOT), "ls-files"], capture_output=True, text=True,
                                 check=True).stdout.split())
    for meta in (WORK / "mutants").rglob("*.py.meta"):
        module = str(meta.relative_to(WORK / "mutants"))[: -len(".meta")]
        if module not in tracked:
            for stale in (meta, meta.with_suffix(".spans"), WORK / "mutants" / module, WORK / module):
                stale.unlink(missing_ok=True)


SAMPLE = WORK / "sample.json"  # the sampled mutant names (run --sample), read by report


def _all_names() -> dict[str, int | None]:
    out = {}
    for meta in sorted((WORK / "mutants").rglob("*.py.meta")):
        out.update(json.loads(meta.read_text())["exit_code_by_key"])
    return out


#: started with every Python subprocess of the tests (``PYTHONPATH``): mutmut's coverage pass ("stats") can only
#: be recorded in mutmut's own process, so a subprocess runs the original code then; under a mutant it runs it
SITECUSTOMIZE = """import os
if os.environ.get("MUTANT_UNDER_TEST") == "stats":
    os.environ["MUTANT_UNDER_TEST"] = ""
"""


def _env() -> dict:
    """The tests' environment: a test that starts ``dslearn-run`` in a subprocess imports the mutated copy in
    ``.mutation/mutants`` (the active mutant is passed on in ``MUTANT_UNDER_TEST``), not the installed
    project, whose working tree may differ from the exported commit."""
    import os

    hook = WORK / "hook"
    hook.mkdir(parents=True, exist_ok=True)
    (hook / "sitecustomize.py").write_text(SITECUSTOMIZE)
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(WORK / "mutants"), str(hook)])}


def _terminal_sigint() -> None:
    """In mutmut's process (before it starts): Ctrl-C as at a terminal. A command started in the background by a
    shell without job control inherits an ignored SIGINT, and the tests that interrupt a run would then fail in
    mutmut's coverage pass (which stops at the first failing test without saying which)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


def run(max_children: int, sample: int | None = None, seed: int = 0) -> int:
    """Export ``HEAD`` and run (or resume) mutmut there; with ``sample``, only a random sample of the
    mutants (their names, in one ``mutmut run`` call; the ones already judged are not run again)."""
    exe = _mutmut()
    export_head()
    if sample is None:
        SAMPLE.unlink(missing_ok=True)
        return subprocess.call([exe, "run", "--max-children", str(max_children)], cwd=WORK, env=_env(), preexec_fn=_terminal_sigint)
    if not _all_names():
        # generate the mutants and collect which tests cover what (mutmut does both before it filters
        # by name; a name that matches nothing stops it right after)
        print("mutation: generating mutants and collecting test coverage (once)", flush=True)
        subprocess.call([exe, "run", "--max-children", str(max_children), "__no_such_mutant__"], cwd=WORK,
                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=_env(), preexec_fn=_terminal_sigint)
    names = sorted(_all_names())
    if not names:
        raise SystemExit("mutation: mutmut generated no mutants (see `mutmut run` in .mutation/)")
    if sample > len(names):
        raise SystemExit(f"mutation: --sample {sample} is more than the {len(names)} mutants")
    import random

    chosen = sorted(random.Random(seed).sample(names, sample))
    SAMPLE.write_text(json.dumps({"seed": seed, "of": len(names), "names": chosen}, indent=0))
    verdicts = _all_names()
    todo = [n for n in chosen if verdicts.get(n) is None]
    print(f"mutation: sample of {sample} of {len(names)} mutants (seed {seed}); {len(todo)} left to test", flush=True)
    if not todo:
        return 0
    return subprocess.call([exe, "run", "--max-children", str(max_children), *todo], cwd=WORK, env=_env(), preexec_fn=_terminal_sigint)


def _verdicts() -> dict[str, tuple[str, int | None]]:
    """``{mutant name: (module path, exit code)}`` from mutmut's ``.meta`` files."""
    out = {}
    for meta in sorted((WORK / "mutants").rglob("*.py.meta")):
        module = str(meta.relative_to(WORK / "mutants"))[: -len(".meta")]
        for name, code in json.loads(meta.read_text())["exit_code_by_key"].items():
            out[name] = (module, code)
    if not out:
        raise SystemExit("mutation: no verdicts under .mutation/mutants/; run `python benchmarks/mutation.py run` first")
    return out


def _diff(name: str) -> tuple[str, str, str]:
    """The mutated function and the changed line (before, after) of one mutant (``mutmut show``)."""
    text = subprocess.run([_mutmut(), "show", name], cwd=WORK, capture_output=True, text=True).stdout
    minus = [ln[1:].strip() for ln in text.splitlines() if ln.startswith("-") and not ln.startswith("---")]
    plus = [ln[1:].strip() for ln in text.splitlines() if ln.startswith("+") and not ln.startswith("+++")]
    func = re.sub(r"__mutmut_\d+$", "", name.rsplit(".", 1)[-1]).removeprefix("x_").replace("xǁ", "").replace("ǁ", ".")
    return func, " / ".join(minus), " / ".join(plus)


def _explained() -> list[dict]:
    if not EXPLAINED.is_file():
        return []
    return tomllib.loads(EXPLAINED.read_text())["mutant"]


def _wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a binomial proportion ``k / n``."""
    if n == 0:
        return 0.0, 1.0
    p = k / n
    c = z * (p * (1 - p) / n + z * z / (4 * n * n)) ** 0.5
    d = 1 + z * z / n
    return (p + z * z / (2 * n) - c) / d, (p + z * z / (2 * n) + c) / d


def report() -> int:
    verdicts = _verdicts()
    sample = json.loads(SAMPLE.read_text()) if SAMPLE.is_file() else None
    if sample is not None:
        verdicts = {k: v for k, v in verdicts.items() if k in set(sample["names"])}
    explained = _explained()
    per_module: dict[str, Counter] = defaultdict(Counter)
    survivors = []
    for name, (module, code) in verdicts.items():
        if code in KILLED:
            per_module[module]["killed"] += 1
        elif code in NOT_TESTED:
            per_module[module]["not tested"] += 1
        else:
            per_module[module]["survived"] += 1
            func, before, after = _diff(name)
            why = next((e["why"] for e in explained if e["module"] == module and e["function"] == func
                        and e["before"] == before and e["after"] == after), "")
            survivors.append(dict(module=module, function=func, mutant=name, verdict=SURVIVED.get(code, "suspicious"),
                                  before=before, after=after, explained=why))
    OUT.mkdir(parents=True, exist_ok=True)
    with open(OUT / "survivors.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["module", "function", "mutant", "verdict", "before", "after", "explained"])
        w.writeheader()
        w.writerows(survivors)
    total = Counter()
    lines = ["# Mutation score", "",
             "Command: `python benchmarks/mutation.py run && python benchmarks/mutation.py report` (mutmut; "
             "settings in `pyproject.toml`, `[tool.mutmut]`). Kill ratio = killed (a test failed, timed out or "
             "crashed) / mutants tested. Survivors: `survivors.csv`; each one that changes nothing observable is "
             "explained in `explained.toml`.", "",
             "| module | mutants | killed | survived | explained | kill ratio |", "|---|---|---|---|---|---|"]
    n_expl = Counter(s["module"] for s in survivors if s["explained"])
    for module in sorted(per_module):
        c = per_module[module]
        total.update(c)
        tested = c["killed"] + c["survived"]
        lines.append(f"| `{module}` | {tested} | {c['killed']} | {c['survived']} | {n_expl[module]} | "
                     f"{c['killed'] / max(tested, 1):.1%} |")
    tested = total["killed"] + total["survived"]
    lines.append(f"| **all** | {tested} | {total['killed']} | {total['survived']} | {sum(n_expl.values())} | "
                 f"**{total['killed'] / max(tested, 1):.1%}** |")
    if sample is not None:
        lo, hi = _wilson(total["killed"], tested)
        n_eq = sum(n_expl.values())
        lo2, hi2 = _wilson(total["killed"], tested - n_eq)
        lines += ["", f"A random sample of {len(sample['names'])} of the {sample['of']} mutants "
                  f"(`run --sample {len(sample['names'])} --seed {sample['seed']}`): kill ratio "
                  f"{total['killed'] / max(tested, 1):.1%} (95 % Wilson interval {lo:.1%} to {hi:.1%}); "
                  f"leaving out the {n_eq} explained (equivalent) survivors, "
                  f"{total['killed'] / max(tested - n_eq, 1):.1%} ({lo2:.1%} to {hi2:.1%})."]
    if total["not tested"]:
        lines += ["", f"{total['not tested']} mutants not tested yet (run again to resume)."]
    unexplained = [s for s in survivors if not s["explained"]]
    lines += ["", f"Unexplained survivors: {len(unexplained)}."]
    for s in unexplained:
        lines.append(f"- `{s['module']}` `{s['function']}`: `{s['before']}` -> `{s['after']}` ({s['verdict']})")
    (OUT / "summary.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines[4:4 + len(per_module) + 3]))
    if sample is not None:
        print(next(ln for ln in lines if ln.startswith("A random sample")))
    print(f"wrote {OUT.relative_to(ROOT)}/summary.md and survivors.csv; unexplained survivors: {len(unexplained)}")
    return 1 if unexplained or total["not tested"] else 0


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("command", choices=["run", "report"])
    p.add_argument("--max-children", type=int, default=2, help="run: mutants tested in parallel (default 2)")
    p.add_argument("--sample", type=int, default=None, help="run: test a random sample of this many mutants")
    p.add_argument("--seed", type=int, default=0, help="run --sample: the sample's seed (default 0)")
    a = p.parse_args(argv)
    if a.sample is not None and a.sample < 1:
        p.error(f"--sample must be a positive number of mutants, got {a.sample}")
    sys.exit(run(a.max_children, a.sample, a.seed) if a.command == "run" else report())


if __name__ == "__main__":
    main()
