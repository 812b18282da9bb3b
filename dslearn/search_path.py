"""The user's config folders on the command line (``hydra.searchpath=[...]``): they join every listing of a group's
options (:data:`dslearn.conf_paths.CONF_DIRS`) and every composition made outside Hydra's app
(:func:`search_overrides`). Above the library: only the composition root, the app and the sweeper use it."""

from __future__ import annotations

from pathlib import Path

from dslearn.conf_paths import CONF_DIRS

#: the ``hydra.searchpath`` entries of the current command, as given (``file://`` folders and ``pkg://`` packages)
SEARCH_PATH: list[str] = []


def user_search_dirs(entries) -> list[Path]:
    """The folders of ``hydra.searchpath`` entries (``file://`` or plain paths; ``pkg://`` entries are packages,
    not folders, and are left to Hydra); :class:`~dslearn.errors.ConfigError` for one that is not a folder."""
    from dslearn.errors import ConfigError

    out = []
    for item in [entries] if isinstance(entries, str) else list(entries):
        s = str(item)
        if s.startswith("pkg://"):
            continue
        d = Path(s[len("file://"):] if s.startswith("file://") else s).expanduser()
        if not d.is_dir():
            raise ConfigError(f"hydra.searchpath: {s} is not a folder (give config folders as file:///abs/path "
                              "or pkg://package.module)")
        out.append(d.resolve())
    return out


def add_search_path(entries) -> None:
    """Make the user's ``hydra.searchpath`` entries part of the command's configs: their folders join
    :data:`~dslearn.conf_paths.CONF_DIRS` (every listing of a group's options reads them) and the entries :data:`SEARCH_PATH` (every
    composition outside Hydra's app adds them, :func:`search_overrides`). Called by ``dslearn-run``'s up-front
    check, by each job (in a launcher's worker process too) and by the matrix sweeper; repeated entries count
    once."""
    items = [str(x) for x in ([entries] if isinstance(entries, str) else list(entries))]
    for d in user_search_dirs(items):
        if d not in CONF_DIRS:
            CONF_DIRS.append(d)
    for s in items:
        if s not in SEARCH_PATH:
            SEARCH_PATH.append(s)


def search_overrides() -> list[str]:
    """``["hydra.searchpath=[...]"]`` with the user's entries (:data:`SEARCH_PATH`), to compose with them
    (``[]`` where there are none): Hydra applies a search path to the one composition whose overrides hold it."""
    if not SEARCH_PATH:
        return []
    quoted = ["'" + s.replace("\\", "\\\\").replace("'", "\\'") + "'" for s in SEARCH_PATH]
    return [f"hydra.searchpath=[{','.join(quoted)}]"]
