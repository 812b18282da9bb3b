"""What the rooms of ``dslearn-run`` share: the program's name, the config folder, the status file, the
one line a user sees on stderr, and the state that :func:`dslearn.run.main` hands to the Hydra task
that runs in the same process (the user's command line, the run folder it locked)."""

from __future__ import annotations

import logging
import sys
from typing import TYPE_CHECKING

from dslearn.conf_paths import CONF_DIR as _CONF_DIR

if TYPE_CHECKING:
    from dslearn.io import RunLock

#: the app's logger: one name for every room (the lines of a run's ``run.log`` name it)
log = logging.getLogger("dslearn.run")
#: the package's config folder, as Hydra takes it
CONF_DIR = str(_CONF_DIR)
PROG = "dslearn-run"
#: a run's outcome, written last (``done | skipped | failed | interrupted``), read by the sweep summary
STATUS_FILE = "status.json"
#: the keys that choose the run folder, named when it is busy
BUSY_KEYS = "hydra.run.dir / hydra.sweep.dir"
#: the environment variable that tells a launcher's worker process (which inherits it) from the command's own
MAIN_PID = "DSLEARN_RUN_PID"
#: run folder (absolute) -> the lock :func:`dslearn.run.main` took on it before Hydra started (a single run)
PRELOCKED: dict[str, RunLock] = {}
#: the command line as the user gave it (recorded in meta.json; Hydra may get a resolved run folder)
USER_ARGV: list[str] | None = None


def say(kind: str, msg: str) -> None:
    """The one line a user sees on stderr."""
    print(f"{PROG}: {kind}: {' '.join(str(msg).split())}", file=sys.stderr, flush=True)
