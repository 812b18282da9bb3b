"""The command line, read before anything is composed: overrides parsed by Hydra's parser (memoised),
group options checked against the config folders (with "did you mean" hints and the papers' names for
them), the launcher's plugin and the output folders checked, overrides of keys that moved named with
their new form, and Hydra's and OmegaConf's errors turned into one line.

Everything here is cheap: a refused group option or launcher is answered without Hydra's composition
and without PyTorch (:mod:`dslearn.app.precheck` runs these checks first)."""

from __future__ import annotations

import os
import re
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from dslearn.conf_paths import CONF_DIRS
from dslearn.errors import ConfigError


_NO_CHECK_FLAGS = {"--hydra-help", "--cfg", "-c", "--info", "-i",
                   "--shell-completion", "-sc", "--resolve", "--package", "-p", "--config-name", "-cn",
                   "--config-path", "-cp", "--config-dir", "-cd", "--experimental-rerun"}
_MULTIRUN_FLAGS = {"-m", "--multirun"}
#: Hydra launcher option -> (plugin module, dslearn extra that installs it)
LAUNCHERS = {
    "basic": (None, None),
    "joblib": ("hydra_plugins.hydra_joblib_launcher", "joblib"),
    "ray": ("hydra_plugins.hydra_ray_launcher", "ray"),
    "submitit_local": ("hydra_plugins.hydra_submitit_launcher", "slurm"),
    "submitit_slurm": ("hydra_plugins.hydra_submitit_launcher", "slurm"),
}


def _plugin_installed(module: str) -> bool:
    import importlib.util

    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def _check_launcher(option: str) -> None:
    if option not in LAUNCHERS:
        raise ConfigError(f"hydra/launcher={option!r} is not a known launcher; choose one of {sorted(LAUNCHERS)}")
    module, extra = LAUNCHERS[option]
    if module is not None and not _plugin_installed(module):
        raise ConfigError(
            f"hydra/launcher={option} needs the Hydra plugin {module.split('.')[-1]}, which is not installed; "
            f'install it with: pip install "dslearn[{extra}]"'
        )


def _check_output_dir(key: str, value: str) -> None:
    """``hydra.run.dir`` / ``hydra.sweep.dir``: a folder that can be created (not a file)."""
    if "${" in value:
        return
    p = Path(value).expanduser()
    if p.exists() and not p.is_dir():
        raise ConfigError(f"{key}={value} is an existing file, not a folder; choose a folder for the outputs")
    parent = p
    while not parent.exists():
        if parent.parent == parent:
            break
        parent = parent.parent
    if parent.exists() and not parent.is_dir():
        raise ConfigError(f"{key}={value}: {parent} is a file, so the folder cannot be created")
    if parent.exists() and not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(f"{key}={value}: {parent} is not writable")


def _group_options(group: str) -> list[str]:
    return sorted({p.stem for d in CONF_DIRS for p in (d / group).glob("*.yaml")})


def _is_group(key: str) -> bool:
    return any((d / key).is_dir() for d in CONF_DIRS) or key == "schema"


#: (group, a name users try) -> (the option meant, what it is): names from the papers that are not file names
ALIASES = {
    ("filter", "ekf"): ("default", "the extended information filter (EKF)"),
    ("filter", "eif"): ("default", "the extended information filter (EKF)"),
    ("filter", "unscented"): ("ukf", "the unscented filter"),
}


def did_you_mean(word: str, choices, n: int = 3) -> list[str]:
    """The ``choices`` closest to ``word`` (a misspelling), best first (none when nothing is close)."""
    import difflib

    choices = [str(c) for c in choices]
    close = difflib.get_close_matches(str(word), choices, n=n, cutoff=0.6)
    if not close:  # a prefix or a part of a name (``gp_incr``, ``increment``)
        w = str(word).lower()
        close = [c for c in choices if len(w) >= 3 and (c.lower().startswith(w) or w in c.lower())][:n]
    return close


def _check_group_option(group: str, option) -> None:
    opts = _group_options(group)
    if not opts or not isinstance(option, str):
        return
    if str(option) not in opts:
        hint = ""
        alias = ALIASES.get((group, str(option).lower()))
        if alias is not None and alias[0] in opts:
            hint = f"; {alias[1]} is {group}={alias[0]}"
        else:
            close = did_you_mean(str(option), opts)
            if close:
                hint = "; did you mean " + " or ".join(f"{group}={c}" for c in close) + "?"
        raise ConfigError(f"{group}={option!r} is not an option of the config group '{group}'; "
                          f"choose one of {opts}{hint}")


def _sweep_values(o) -> list:
    """The values of a choice sweep override (``group=a,b``), ``[]`` for other sweeps (range, glob)."""
    try:
        from hydra.core.override_parser.types import ChoiceSweep

        v = o.value()
        return [str(x) for x in v.list] if isinstance(v, ChoiceSweep) else []
    except Exception:  # noqa: BLE001
        return []


def _hydra_message(e: Exception) -> str:
    msg = " ".join(str(e).split()).split(" Config search path:")[0]
    cause = e.__cause__
    if cause is not None and str(cause).strip() and str(cause).split("\n")[0] not in msg:
        msg += ": " + str(cause).split("\n")[0]
    return msg or type(e).__name__


_PARSED: dict[str, object] = {}


def parse_override(line: str):
    """One command-line override parsed by Hydra's parser (memoised: parsing a long list value
    costs seconds, and a line is parsed several times on the way)."""
    if line not in _PARSED:
        from hydra.core.override_parser.overrides_parser import OverridesParser

        if len(_PARSED) > 10000:
            _PARSED.clear()
        _PARSED[line] = OverridesParser.create().parse_overrides([line])[0]
    return _PARSED[line]


def _parse_all(lines: list[str]) -> list:
    return [parse_override(x) for x in lines]


def _is_group_override(o) -> bool:
    return o.package is not None or _is_group(o.key_or_group)


def override_keys(lines) -> list[tuple[str, str]]:
    """``(key, line)`` of each override line that sets the configuration (``consensus=ci`` ->
    ``consensus``, ``+consensus.x=1`` / ``~consensus.x`` -> ``consensus.x``); Hydra's own keys and
    options written into another package (``group@pkg=option``) are left out."""
    out = []
    for line in lines:
        o = parse_override(line)
        key = o.key_or_group
        if key.startswith("hydra") or o.package is not None:
            continue
        out.append((key, line))
    return out


#: the root groups and keys of task ``liu_dgpt`` that became its own keys (:func:`_moved`)
MOVED = {
    "tracker": ("task.tracker", "{}"),
    "aggregation": ("task.aggregations", "[{}]"),
    "gp_input": ("task.gp_input", "{}"),
    "noise": ("task.noises", "[{}]"),
}


def _moved(o) -> str | None:
    """The message for an override of a group / key that moved into task ``liu_dgpt`` (or None)."""
    key = o.key_or_group
    if key not in MOVED or _is_group(key) or o.is_delete() or o.package is not None:
        return None
    new_key, form = MOVED[key]
    try:
        vals = list(o.sweep_string_iterator()) if o.is_sweep_override() else [o.get_value_element_as_str()]
    except Exception:  # noqa: BLE001 - e.g. a range sweep: show the value as written
        vals = [o.input_line.split("=", 1)[-1]]
    new = f"{new_key}=" + ",".join(form.format(v) for v in vals)
    return f"{o.input_line}: {key} is no longer a root group or key; it is a key of task=liu_dgpt: write {new}"


def _friendly(e: Exception, cfg: DictConfig | None = None) -> str:
    msg = _hydra_message(e)
    m = re.search(r"Could not override '([^']+)'", msg)
    if m:
        key = m.group(1)
        return _unknown_key(key, cfg)
    return msg


def _unknown_key(key: str, cfg) -> str:
    """An override of a key the configuration does not have: the closest keys (full paths, each a
    working override) and the keys that are there. No ``+key`` is suggested: the schemas refuse keys
    they do not define, so adding one would fail too."""
    parent, _, leaf = key.rpartition(".")
    node = None
    if cfg is not None:
        try:
            node = OmegaConf.select(cfg, parent, default=None) if parent else cfg
        except Exception:  # noqa: BLE001
            node = None
    if not isinstance(node, DictConfig):
        return f"{key}: no such key in the configuration"
    keys = sorted(str(k) for k in node.keys())
    where = f" of {parent}" if parent else ""
    close = did_you_mean(leaf, [k for k in keys if k != "hydra"])
    hint = ("; did you mean " + " or ".join(f"{parent + '.' if parent else ''}{c}=..." for c in close) + "?"
            if close else "")
    return f"{key}: no such key in the configuration (known keys{where}: {keys}){hint}"
