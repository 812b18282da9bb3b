"""The start-up check of ``dslearn-run``: before Hydra starts anything, :func:`precheck` composes and
validates the configuration of every job the command line asks for (each combination of a sweep,
including an experiment's ``hydra.sweeper.params``) and checks the output folder and the launcher plugin;
then :func:`lock_run_dir` takes a single run's folder lock, so that a run refused as busy leaves the folder
untouched."""

from __future__ import annotations

import os
import re
from typing import TYPE_CHECKING

from omegaconf import DictConfig, OmegaConf

from dslearn.app.common import CONF_DIR, PRELOCKED
from dslearn.app.composer import (
    check_jobs,
    composed_job,
    sweep_combinations,
    sweep_composer,
    sweep_select,
    validate_job,
)
from dslearn.app.options import (
    _NO_CHECK_FLAGS,
    _check_group_option,
    _check_launcher,
    _check_output_dir,
    _friendly,
    _hydra_message,
    _is_group,
    _is_group_override,
    _moved,
    _parse_all,
    _sweep_values,
    parse_override,
)
from dslearn.errors import ConfigError

if TYPE_CHECKING:
    from dslearn.io import RunLock


def precheck(argv: list[str], plan: dict | None = None) -> str | None:
    """Compose and validate the configuration the command line asks for; the error line or ``None``.

    Sweep overrides (``a=1,2``, ``range(...)``) and an experiment's sweep parameters are expanded
    and every combination is checked (:func:`~dslearn.schemas.core.validate_config`, which also
    builds the core study's parts), so a bad value anywhere in a sweep fails before its first
    job runs; a combination that the sweep's sweeper drops (``hydra/sweeper=matrix``: a method that does
    not fit the scenario, :func:`~dslearn.app.composer.sweep_select`) is no job.
    ``hydra.run.dir`` / ``hydra.sweep.dir`` must name a folder (or a place one can be made) and the
    chosen launcher's plugin must be installed. Options that Hydra handles itself
    (``--cfg``, ``--info``, ...) skip the check. For a single run, ``plan["run_dir"]`` is set to
    its output folder (``hydra.run.dir`` resolved; absent when it cannot be resolved here).
    """
    if any(a.split("=")[0] in _NO_CHECK_FLAGS for a in argv):
        return None
    overrides = [a for a in argv if not a.startswith("-")]
    try:
        from hydra import compose, initialize_config_dir

        parsed = []
        for line in overrides:
            try:
                parsed.append(parse_override(line))
            except Exception as e:  # noqa: BLE001
                msg = _hydra_message(e).split(" See https://hydra.cc")[0]
                return (f"{line}: not a valid override ({msg}); write key=value, group=option, +key=value "
                        "to add, or key=a,b with -m to sweep")
        for o in parsed:  # user config folders first: their groups and options count in the checks below
            if o.key_or_group == "hydra.searchpath" and not o.is_delete():
                from dslearn.search_path import add_search_path

                add_search_path(o.value())  # and every composition below gets the same search path
        for o in parsed:
            moved = _moved(o)
            if moved is not None:
                return moved
            if o.key_or_group in ("hydra.run.dir", "hydra.sweep.dir"):
                _check_output_dir(o.key_or_group, str(o.value()))
            if o.key_or_group == "hydra/launcher":
                _check_launcher(str(o.value()))
            elif o.key_or_group.startswith("hydra/"):
                continue
            elif _is_group(o.key_or_group) and not o.is_delete():
                for v in (_sweep_values(o) if o.is_sweep_override() else [o.value()]):
                    _check_group_option(o.key_or_group, v)
        # the cheap checks are done: now the task schemas (they import PyTorch) and the composition
        import dslearn.schemas  # noqa: F401  (registers the schemas the task configs name in Hydra's ConfigStore)

        with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
            combos, multirun, master = sweep_combinations(argv)
            seeded = {}
            if not multirun:  # one job: its group choices are the master's; reuse that composition
                groups = tuple(o.input_line for o in _parse_all(combos[0]) if _is_group_override(o))
                seeded[groups] = master

            from dslearn.search_path import search_overrides

            def _compose(ov):  # each job with the user's search path (Hydra applies it per composition)
                key = tuple(ov)
                return seeded.pop(key) if key in seeded else compose("config", overrides=[*search_overrides(), *ov])

            select = sweep_select(master) if multirun else None
            composer = None
            if select is not None:  # the sweeper's choice (the matrix: the cells that fit); the others are no jobs
                composer = sweep_composer(combos, _compose)  # each preset and each scenario composed once, and
                # each combination once for both checks

                def _cell(ov, _plain=_compose):
                    try:
                        return composed_job(composer, ov)
                    except ConfigError:
                        raise
                    except Exception:  # noqa: BLE001 - a composition error: Hydra's own message, as a run has it
                        return _plain(ov)

                judged = select(combos, _cell)
                from dslearn.schemas.matrix import remember_judgement

                remember_judgement(select, combos, judged)  # the sweeper takes it instead of judging again
                combos = judged[0]

            def _visit(cfg, lines=()):
                validate_job(cfg, lines)
                if plan is not None and not multirun:
                    where = _resolved_run_dir(cfg)
                    if where is not None:
                        plan["run_dir"] = where

            check_jobs(combos, _compose, visit=_visit, composer=composer)
            if plan is not None and multirun:  # the sweep's job count: its overall status line counts to it
                plan["jobs"] = len(combos)
    except ConfigError as e:
        return str(e)
    except Exception as e:  # Hydra/OmegaConf composition errors: unknown key, group option, type
        return _friendly(e)
    return None


def _resolved_run_dir(cfg: DictConfig) -> str | None:
    """``hydra.run.dir`` of a composed job configuration, resolved (``None`` if it cannot be here)."""
    try:
        d = OmegaConf.select(cfg, "hydra.run.dir", throw_on_missing=True)
    except Exception:  # noqa: BLE001 - e.g. ${hydra:...}, only known inside the app
        return None
    return None if d is None or not str(d) else str(d)


_BARE_PATH = re.compile(r"[A-Za-z0-9_./:+@%~-]+")


def _run_dir_override(run_dir: str, key: str = "hydra.run.dir") -> str | None:
    """``<key>=<run_dir>`` as an override Hydra parses back to exactly ``run_dir`` (or ``None``)."""
    if "${" in run_dir:
        return None
    quoted = "'" + run_dir.replace("\\", "\\\\").replace("'", "\\'") + "'"
    for value in ([run_dir] if _BARE_PATH.fullmatch(run_dir) else []) + [quoted]:
        line = f"{key}={value}"
        try:
            if str(parse_override(line).value()) == run_dir:
                return line
        except Exception:  # noqa: BLE001
            continue
    return None


def lock_run_dir(argv: list[str], run_dir: str | None) -> tuple[list[str], RunLock | None]:
    """Take a single run's folder lock before Hydra starts: Hydra writes ``.hydra/`` and opens
    ``run.log`` in the folder before the task runs, so a run refused as busy must be refused
    here to leave an existing run folder untouched. Where ``hydra.run.dir`` was not given as a
    plain path (the default has a timestamp), Hydra gets the resolved folder as an override, so
    that it writes where the lock is. Returns Hydra's command line and the lock (``None``: not
    resolvable here; the app then locks the folder itself). Raises :class:`~dslearn.io.RunDirBusy`."""
    if run_dir is None:
        return argv, None
    given = []
    for i, a in enumerate(argv):
        if not a.startswith("-"):
            try:
                if parse_override(a).key_or_group == "hydra.run.dir":
                    given.append(i)
            except Exception:  # noqa: BLE001
                continue
    out = list(argv)
    if not given or "${" in argv[given[-1]]:
        line = _run_dir_override(run_dir)
        if line is None:
            return argv, None
        out = [a for i, a in enumerate(argv) if i not in given] + [line]
    from dslearn.io import RunLock

    lock = RunLock(run_dir).acquire()
    PRELOCKED[os.path.abspath(run_dir)] = lock
    return out, lock
