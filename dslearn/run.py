"""``dslearn-run``: the Hydra app. One run = one task configuration -> ``results.csv``.

Every run writes, in its output directory: ``config.yaml`` (resolved config), ``meta.json``
(package version, git commit, library versions, seed, overrides, wall time, jitter counts, and
the completeness marker: the row count and SHA-256 of ``results.csv``), then — last, atomically —
``results.csv``, and finally ``status.json`` (``done | skipped | failed | interrupted``, read by
the sweep summary). An interrupted or failed run leaves no ``results.csv`` (or one whose hash
does not match). While a run works in a folder it holds the folder's lock (``.dslearn.lock``,
with its pid): a second run into the same folder is refused before it writes anything there (a
single run's lock is taken before Hydra starts, :func:`dslearn.app.precheck.lock_run_dir`; a sweep's
in its ``on_multirun_start``); a dead owner's lock is taken over.

Resume: ``dslearn-run -m ... hydra.sweep.dir=DIR resume=true`` (or ``hydra.run.dir=DIR
resume=true`` for one run) skips every job whose directory already holds a complete result
(:func:`dslearn.io.check_complete`) and re-runs missing or broken ones. The default sweep dir
contains a timestamp, so resuming needs the same fixed ``hydra.sweep.dir`` both times.

Before Hydra starts anything, :func:`dslearn.app.precheck.precheck` composes and validates the
configuration of every job the command line asks for (each combination of a sweep, including an
experiment's ``hydra.sweeper.params``), and checks the output folder and the launcher plugin.

Exit codes: 0 ok; 2 bad input (configuration, data file, busy run folder, too big for memory:
one line on stderr, ``dslearn-run: <what>: <message>``); 130 interrupted (Ctrl-C); 1 other
failure (in a sweep: after every job has run and the table of the finished ones is gathered).

This module is the entry point (the console script ``dslearn-run`` and ``python -m dslearn.run``):
:func:`main` and the Hydra task it starts. The work is done in :mod:`dslearn.app`, in rooms by role:
the command line's options, the sweep's up-front check, the start-up check, one job, its result files,
help and completion, and how a command ends when interrupted.
"""

from __future__ import annotations

import os
import signal
import sys


def _interrupted_at_start(signum, frame):  # noqa: ARG001
    os.write(2, b"dslearn-run: interrupted: Ctrl-C before the run started; nothing was written\n")
    os._exit(130)


# Ctrl-C while the console script imports the app: one line and exit 130, not a traceback (main()
# takes over with its own handling; a module imported by other code keeps the interpreter's handler)
_SIGINT_BEFORE = None
if __name__ == "__main__" or os.path.basename(sys.argv[0] if sys.argv else "") == "dslearn-run":
    try:
        _SIGINT_BEFORE = signal.signal(signal.SIGINT, _interrupted_at_start)
    except (ValueError, OSError):  # not the main thread
        _SIGINT_BEFORE = None

# the app's rooms import only the standard library, OmegaConf and dslearn's light root modules (start-up cost:
# see dslearn.app); Hydra and the schemas are imported where work starts
from typing import TYPE_CHECKING  # noqa: E402

from dslearn.app import common  # noqa: E402
from dslearn.app.common import BUSY_KEYS, CONF_DIR, MAIN_PID, PRELOCKED, PROG, say  # noqa: E402
from dslearn.app.endings import (  # noqa: E402
    _exit_if_cells_failed,
    _interrupted_sweep,
    _quiet_interrupts_in_callbacks,
    resume_command,
)
from dslearn.app.help import help_text, light_completion, version_text  # noqa: E402
from dslearn.app.job import Terminated, _on_sigterm, run_job  # noqa: E402
from dslearn.app.precheck import lock_run_dir, precheck  # noqa: E402

if TYPE_CHECKING:
    from omegaconf import DictConfig


def main(argv: list[str] | None = None) -> None:
    """The ``dslearn-run`` console script (``argv`` defaults to ``sys.argv[1:]``)."""
    if argv is None:
        argv = sys.argv[1:]
    argv = list(argv)
    _quiet_interrupts_in_callbacks()
    os.environ[MAIN_PID] = str(os.getpid())
    try:
        if any(a in ("--help", "-h") for a in argv):
            try:
                print(help_text())
            except BrokenPipeError:  # e.g. | head
                sys.stdout = open(os.devnull, "w")
            return
        if "--version" in argv:
            print(version_text())
            return
        answer = light_completion(argv, os.environ.get("COMP_LINE"))
        if answer is not None:
            print(" ".join(answer))
            return
        plan: dict = {}
        err = precheck(argv, plan)
        if err is not None:
            say("configuration error", err)
            raise SystemExit(2)
        from dslearn.io import RunDirBusy

        try:
            hydra_argv, held = lock_run_dir(argv, plan.get("run_dir"))
        except RunDirBusy as e:  # before Hydra wrote anything into the folder
            say("run folder busy", f"{e} ({BUSY_KEYS})")
            raise SystemExit(2)
        if "jobs" in plan:  # a sweep: its overall status line counts to this
            from dslearn.callbacks import expect_jobs

            expect_jobs(plan["jobs"])
        old = sys.argv
        sys.argv = [old[0] if old else PROG, *hydra_argv]
        common.USER_ARGV = argv
        old_term = None
        try:
            import signal
            import threading

            if threading.current_thread() is threading.main_thread():
                old_term = signal.signal(signal.SIGTERM, _on_sigterm)
        except (ValueError, OSError, AttributeError):
            old_term = None
        try:
            _app()
            _exit_if_cells_failed()
        finally:
            sys.argv = old
            common.USER_ARGV = None
            if held is not None:
                PRELOCKED.pop(os.path.abspath(plan["run_dir"]), None)
                held.release()
            if old_term is not None:
                signal.signal(signal.SIGTERM, old_term)
    except KeyboardInterrupt as e:
        code = 143 if isinstance(e, Terminated) else 130
        sweep = _interrupted_sweep()
        if sweep is not None:
            print(f"{PROG}: interrupted: {sweep['done']} of {sweep['jobs']} jobs done; resume with: "
                  f"{resume_command(argv, sweep['dir'])}", file=sys.stderr, flush=True)
            raise SystemExit(code) from None
        what = "SIGTERM" if isinstance(e, Terminated) else "Ctrl-C"
        say("interrupted", f"{what} before the run started; nothing was written")
        raise SystemExit(code) from None


def _app() -> None:
    """The Hydra application (Hydra, and the schemas its configs name, are imported here: where work starts)."""
    import hydra

    import dslearn.schemas  # noqa: F401  (registers the schemas the task configs name in Hydra's ConfigStore)

    hydra.main(version_base=None, config_path=CONF_DIR, config_name="config")(_hydra_task)()


def _hydra_task(cfg: DictConfig) -> dict:
    """The task Hydra runs for each job (:func:`dslearn.app.job.run_job`). It lives in this module because
    Hydra names the job after the module of its task function: the job is ``run`` (its log file ``run.log``)."""
    return run_job(cfg)


if _SIGINT_BEFORE is not None:  # imported: KeyboardInterrupt again, handled by main()
    signal.signal(signal.SIGINT, _SIGINT_BEFORE)

if __name__ == "__main__":
    main()
