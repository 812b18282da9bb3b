"""Where the configs are: the packaged ``dslearn.conf`` (in a source checkout, the top-level
``conf/``) and the user's folders added to the config search path on the command line."""

from __future__ import annotations

from pathlib import Path


def _conf_dir() -> Path:
    from importlib.resources import files

    return Path(str(files("dslearn.conf")))


#: the packaged config folder; user config folders join it through the config search path
CONF_DIR = _conf_dir()
#: every config folder the current command composes from: CONF_DIR, then the user's search-path
#: folders (``dslearn-run`` extends this list from the command line before its up-front checks)
CONF_DIRS: list[Path] = [CONF_DIR]
