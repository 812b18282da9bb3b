"""How a ``dslearn-run`` command ends other than with a finished run: a Ctrl-C or SIGTERM kept to one line
(none of the interpreter's "Exception ignored" tracebacks from callbacks; an interrupted sweep's workers shut
down and its resume command, :func:`resume_command`, printed by :func:`dslearn.run.main`), and exit code 1
after a matrix sweep whose cells failed while their parts were built (:func:`_exit_if_cells_failed`)."""

from __future__ import annotations

import os
import sys

from dslearn.app.common import PROG, say
from dslearn.app.options import parse_override
from dslearn.app.precheck import _run_dir_override


def _quiet_interrupts_in_callbacks() -> None:
    """A Ctrl-C that lands inside a finaliser or a weakref callback is "ignored" by the interpreter, which prints
    its traceback (``Exception ignored in: ...``) beside the one line this program promises; the interrupt
    itself reaches the main flow with the signal's next delivery or the launcher's shutdown. Only such
    KeyboardInterrupts are kept quiet; every other unraisable exception is reported as before."""
    hook = sys.unraisablehook
    if getattr(hook, "_dslearn", False):
        return

    def quiet(unraisable):
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            return
        hook(unraisable)

    quiet._dslearn = True
    sys.unraisablehook = quiet


def _exit_if_cells_failed() -> None:
    """Exit 1 after a matrix sweep in which cells failed in the up-front check (their parts raised while built:
    not run; :data:`dslearn.schemas.matrix.FAILED_CELLS`), once the sweep's other jobs ran and were gathered."""
    mx = sys.modules.get("dslearn.schemas.matrix")
    failed = list(getattr(mx, "FAILED_CELLS", None) or [])
    if failed:
        say("failed cells", f"{len(failed)} cell(s) of the matrix failed while their parts were built and did not "
                            f"run (matrix_cells.csv: status failed, with the error): "
                            + "; ".join(f"{r.get('method')} on {r.get('scenario')}" for r in failed))
        raise SystemExit(1)


def _interrupted_sweep() -> dict | None:
    """The sweep this process was running when interrupted (its status poller stopped, its folder lock
    released, the launcher's worker processes shut down), or ``None`` when no sweep had started."""
    cb = sys.modules.get("dslearn.callbacks")
    state = cb.interrupt_active() if cb is not None else None
    loky = sys.modules.get("joblib.externals.loky.reusable_executor")
    executor = getattr(loky, "_executor", None) if loky is not None else None
    if executor is not None:  # workers and their semaphores go now, not at exit (no leaked-semaphore warning)
        try:
            executor.shutdown(wait=True, kill_workers=True)
        except Exception:  # noqa: BLE001
            pass
    return state


def resume_command(argv: list[str], sweep_dir: str) -> str:
    """The command line that resumes a sweep: ``argv`` without its ``hydra.sweep.dir`` and ``resume``
    overrides, then ``hydra.sweep.dir=<sweep_dir>`` (absolute) and ``resume=true``, quoted for a POSIX shell."""
    import shlex

    keep = []
    for a in argv:
        if not a.startswith("-"):
            try:
                if parse_override(a).key_or_group in ("hydra.sweep.dir", "resume"):
                    continue
            except Exception:  # noqa: BLE001
                pass
        keep.append(a)
    where = os.path.abspath(sweep_dir)
    line = f"hydra.sweep.dir={where}"  # as the user would write it, where Hydra reads it back as this folder
    try:
        plain = str(parse_override(line).value()) == where
    except Exception:  # noqa: BLE001
        plain = False
    if not plain:
        line = _run_dir_override(where, "hydra.sweep.dir") or line
    return " ".join(shlex.quote(a) for a in [PROG, *keep, line, "resume=true"])
