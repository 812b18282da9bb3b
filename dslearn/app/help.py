"""What ``dslearn-run`` answers without composing a configuration: ``--help`` (config groups and
experiments, one line each, read from the config folders; sweeps; outputs), ``--version``, and the common
shell-completion requests (``eval "$(dslearn-run -sc install=bash)"``: a group's options and the first
word at the root, as Hydra's completion gives them; everything else is left to Hydra)."""

from __future__ import annotations

import re
from pathlib import Path

from omegaconf import OmegaConf

from dslearn import __version__
from dslearn.app.common import CONF_DIR, PROG
from dslearn.app.options import _MULTIRUN_FLAGS, _group_options, _is_group
from dslearn.conf_paths import CONF_DIRS


def _first_comment(path: Path) -> str:
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError):
        return ""
    for ln in lines:  # the first whole-line comment (not a package directive)
        s = ln.strip()
        if s.startswith("#"):
            text = s.lstrip("#").strip()
            if text and not text.startswith("@package"):
                return text
    # no leading comment: the option's own keys, compactly
    try:
        c = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    except Exception:  # noqa: BLE001
        return ""
    if not isinstance(c, dict):
        return ""
    items = [f"{k}={v}" for k, v in c.items() if k != "defaults" and not isinstance(v, (dict, list))]
    return ", ".join(items)


def _defaults() -> dict[str, str]:
    try:
        d = OmegaConf.to_container(OmegaConf.load(Path(CONF_DIR) / "config.yaml").get("defaults", []))
    except Exception:  # noqa: BLE001
        return {}
    out = {}
    for item in d or []:
        if isinstance(item, dict):
            for k, v in item.items():
                out[str(k)] = str(v)
    return out


def help_text(width: int = 100) -> str:
    """``dslearn-run --help``: config groups and experiments, one line each, sweeps, outputs."""
    conf = Path(CONF_DIR)
    defaults = _defaults()

    def line(name: str, text: str, indent: int = 4, col: int = 22) -> str:
        head = " " * indent + name
        head = head + " " * max(1, col - len(head))
        room = max(20, width - len(head))
        return head + (text if len(text) <= room else text[: room - 3] + "...")

    out = [
        f"{PROG} {__version__}: run one study configuration, or a sweep of them; every run writes results.csv.",
        "",
        "usage:",
        f"  {PROG} experiment=<name> [key=value ...]      a paper's study (list below)",
        f"  {PROG} [group=option ...] [key=value ...]     one run of the default study (Yu et al., synthetic)",
        f"  {PROG} -m key=a,b group=x,y ...              a sweep: one job per combination",
        "",
        "experiments (experiment=<name>):",
    ]
    for p in sorted((conf / "experiment").glob("*.yaml")):
        out.append(line(p.stem, _first_comment(p), 2))
    out += ["", "config groups (group=option; * = default):"]
    for g in sorted(d.name for d in conf.iterdir() if d.is_dir() and d.name != "experiment" and not d.name.startswith("_")):
        out.append(f"  {g}:")
        for p in sorted((conf / g).glob("*.yaml")):
            mark = "*" if defaults.get(g) == p.stem else " "
            out.append(line(f"{mark} {p.stem}", _first_comment(p), 4))
    out += ["", "top-level keys (key=value):"]
    try:
        for ln in (conf / "config.yaml").read_text(encoding="utf-8").splitlines():
            m = re.match(r"^([a-z_]+):\s*([^#]*?)\s*(?:#\s*(.*))?$", ln)
            if m and m.group(1) not in ("defaults", "hydra"):
                out.append(line(f"{m.group(1)}={m.group(2)}", m.group(3) or "", 2))
    except OSError:
        pass
    out.append(line("+max_memory_gb=<GB>", "memory limit of the start-up resource guard (default: 75% of this machine)", 2))
    out += [
        "",
        "sweeps:",
        f"  {PROG} -m model=lin,gp consensus=individual,hybrid seed=0,1,2 hydra.sweep.dir=multirun/mine",
        "  every combination is checked before the first job starts; resume an interrupted sweep with the",
        "  same command plus resume=true; jobs run in parallel on every core (joblib; hydra/launcher=basic: one by one).",
        "",
        "outputs:",
        "  one run: outputs/<study>/<date_time>/ (or hydra.run.dir=DIR): results.csv (tidy: one row per",
        "  episode x node x metric), meta.json, config.yaml, status.json, run.log.",
        "  a sweep: multirun/<study>/<date_time>/<job>/ (or hydra.sweep.dir=DIR), plus sweep_results.csv.",
        "  then: dslearn-report DIR  -> report.md (open it first), figure.png, summary.csv.",
        "",
        f"more: {PROG} --cfg job [overrides] prints the composed config; --hydra-help lists Hydra's own options;",
        f"      {PROG} --version prints dslearn's version. Exit codes: 0 ok, 2 bad input, 130 Ctrl-C, 1 other.",
        f"      filter=default is the EKF (filter=ukf the UKF). TAB completion in bash: eval \"$({PROG} -sc install=bash)\"",
    ]
    return "\n".join(out)


# --------------------------------------------------------------------------------------------
# shell completion (``eval "$(dslearn-run -sc install=bash)"``): the common requests answered here


_APP_ARGS = re.compile(r"^\s*[\w_\-=\./]+\s*(.*)")  # Hydra's: the line without the program's name
_FILE_PREFIXES = (".", "/", "\\")


def _root_words() -> list[str]:
    """What completes an empty word at the root without composing: the config groups (``group=``; Hydra's
    ``hydra`` and the schemas' ``schema``, groups of groups and options), the root keys (``key=``) and the
    root nodes (``group.``, ``hydra.``)."""
    defaults = _defaults()
    out = {"hydra", "schema", "hydra."}
    for d in CONF_DIRS:
        for g in d.iterdir() if d.is_dir() else ():
            if g.is_dir() and not g.name.startswith(("_", ".")) and any(g.glob("*.yaml")):
                out.add(f"{g.name}=")
    for g, opt in defaults.items():
        if opt not in ("null", "None") and not g.startswith(("override ", "hydra", "_")):
            out.add(f"{g}.")
    try:
        root = OmegaConf.load(Path(CONF_DIR) / "config.yaml")
    except Exception:  # noqa: BLE001
        return sorted(out)
    for k in root.keys():
        if str(k) not in ("defaults", "hydra"):
            out.add(f"{k}.") if OmegaConf.is_config(root._get_node(k)) else out.add(f"{k}=")
    return sorted(out)


def light_completion(argv: list[str], line: str | None) -> list[str] | None:
    """The answer to a completion request (``-sc query=bash``, the shell's line in ``COMP_LINE``) where
    it needs no composed configuration: a group's options (``model=g`` -> ``model=gp ...``) and a first
    word at the root (groups and root keys), as Hydra's completion gives them. ``None``: Hydra answers
    (keys under a node, values, files, a line that chooses an experiment or a method preset, or adds or
    deletes keys)."""
    if len(argv) != 2 or argv[0] not in ("-sc", "--shell-completion") or argv[1] not in ("query=bash", "query=zsh"):
        return None
    if line is None:
        return None
    m = _APP_ARGS.match(line)
    if not m:
        return None
    rest = m.group(1)
    words = rest.split()
    if any(w.startswith("-") and w not in _MULTIRUN_FLAGS for w in words):
        return None
    words = [w for w in words if w not in _MULTIRUN_FLAGS]
    new_word = len(rest) == 0 or rest[-1] == " "
    word = "" if new_word or not words else words[-1]
    before = words if new_word else words[:-1]
    if any(w.startswith(("+", "~", "hydra")) or w.split("=")[0] in ("experiment", "method") for w in before):
        return None
    if word.startswith(("+", "~")) or "/" in word.split("=")[0]:
        return None
    if "=" in word:
        key, _, value = word.partition("=")
        if "." in key or key.startswith("hydra") or not _is_group(key) or key == "schema" or \
                value.lower().startswith(_FILE_PREFIXES):
            return None
        return sorted(f"{key}={o}" for o in _group_options(key) if f"{key}={o}".startswith(word))
    if "." in word:
        return None
    return [w for w in _root_words() if w.startswith(word)]


def version_text() -> str:
    return f"{PROG} (dslearn) {__version__}"
