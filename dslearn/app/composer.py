"""The up-front check of a sweep: the job override lists a command line runs
(:func:`sweep_combinations`, an experiment's ``hydra.sweeper.params`` included), each job's configuration
composed cheaply (:class:`_Composer`: the shared group choices once, a varying group's node swapped in,
scalar overrides applied in place and undone) and validated (:func:`check_jobs`, :func:`validate_job`),
and the sweeper's choice of the combinations that become jobs (:func:`sweep_select`)."""

from __future__ import annotations

import copy

from omegaconf import DictConfig, OmegaConf

from dslearn.app.options import (
    _MULTIRUN_FLAGS,
    _check_group_option,
    _friendly,
    _is_group_override,
    _parse_all,
    override_keys,
)
from dslearn.errors import ConfigError


class _Composer:
    """Compose the configuration of many jobs cheaply (a Hydra compose costs ~0.3-0.6 s).

    The group choices every job shares are composed once (the base). A group choice that
    varies is composed once per option on top of the base; where it changes only its own
    group's node (checked against the base), that node is swapped into a copy of the base for
    each job; otherwise the job's group choices are composed in full (once per distinct set).
    Value overrides (``key=value``) are then applied with Hydra's own routine, so every job's
    configuration is exactly what Hydra composes for it."""

    def __init__(self, compose, base: tuple[str, ...]):
        self._compose = compose
        self.base = base
        self._full: dict[tuple, DictConfig] = {}
        self._single: dict[str, tuple | None] = {}
        self._jobs: dict[tuple, DictConfig] = {}
        self.composes = 0

    def full(self, groups: tuple[str, ...]) -> DictConfig:
        if groups not in self._full:
            self.composes += 1
            self._full[groups] = self._compose(list(groups))
        return self._full[groups]

    def config(self, varying: list, all_lines: list[str]) -> DictConfig:
        """The (cached, shared: do not modify) config of a job's group choices.

        The choices that change only their own group's node (a scenario) are swapped into the composition of the
        others (a method preset, which sets several groups: composed once per preset with the shared choices), where
        those others leave that node as the shared choices have it; anything else is composed in full."""
        key = tuple(all_lines)
        if key in self._jobs:
            return self._jobs[key]
        base = self.full(self.base)
        swaps, whole = [], []
        for line, o in varying:
            node = self._swap(base, line, o)
            if node is None:
                whole.append(line)
            else:
                swaps.append(node)
        start = self.full(self.base + tuple(whole)) if whole else base
        if whole and not all(key_equal(base, start, k) for k, _ in swaps):
            start, swaps = self.full(key), []  # the other choices touch a swapped node too: compose it whole
        if not swaps:
            cfg = start
        else:
            # copy the start without the nodes about to be replaced, then put the options' nodes in
            cfg = _copy_without(start, {k for k, _ in swaps})
            with _open(cfg):
                for k, value in swaps:
                    if value is not None:
                        cfg[k] = copy.deepcopy(value)
        self._jobs[key] = cfg
        return cfg

    def _swap(self, base, line, o):
        if line not in self._single:
            key = o.key_or_group
            res = None
            if o.package is None and "/" not in key and not o.is_delete():
                one = self.full(self.base + (line,))
                keys = (set(base.keys()) | set(one.keys())) - {key}
                if all(key_equal(base, one, kk) for kk in keys):
                    res = (key, one._get_node(key) if key in one else None)
            self._single[line] = res
        return self._single[line]


def _scalar_changes(values: list, cfg: DictConfig) -> list | None:
    """For overrides that only change existing scalar leaves: ``(parent, leaf, old raw value)``
    per override, to undo them; ``None`` when any override adds, deletes or sets a container."""
    undo = []
    for o in values:
        if o.is_delete() or o.is_add() or o.is_force_add() or o.package is not None:
            return None
        v = o.value()
        if isinstance(v, (dict, list)) or o.is_sweep_override():
            return None
        key = o.key_or_group
        parent_key, _, leaf = key.rpartition(".")
        parent = OmegaConf.select(cfg, parent_key, throw_on_missing=False) if parent_key else cfg
        if not isinstance(parent, DictConfig) or leaf not in parent:
            return None
        node = parent._get_node(leaf)
        if node is None or OmegaConf.is_config(node) or not type(node).__name__ == "AnyNode":
            return None
        undo.append((parent, leaf, node._value()))
    return undo


def _copy_without(cfg: DictConfig, skip: set) -> DictConfig:
    """A deep copy of ``cfg`` without its top-level keys in ``skip`` (``cfg`` is unchanged)."""
    content = cfg.__dict__.get("_content")
    if not skip or not isinstance(content, dict):
        out = copy.deepcopy(cfg)
        with _open(out):
            for k in skip:
                out.pop(k, None)
        return out
    orig = dict(content)
    for k in skip:
        content.pop(k, None)
    try:
        return copy.deepcopy(cfg)
    finally:
        content.clear()
        content.update(orig)


class _open:
    def __init__(self, cfg):
        self.cfg = cfg

    def __enter__(self):
        self.flag = OmegaConf.is_struct(self.cfg)
        OmegaConf.set_struct(self.cfg, False)

    def __exit__(self, *exc):
        OmegaConf.set_struct(self.cfg, self.flag)


def key_equal(a: DictConfig, b: DictConfig, key: str) -> bool:
    if (key in a) != (key in b):
        return False
    if key not in a:
        return True
    va, vb = a._get_node(key), b._get_node(key)
    try:
        ca = OmegaConf.to_container(va, resolve=False) if OmegaConf.is_config(va) else va._value()
        cb = OmegaConf.to_container(vb, resolve=False) if OmegaConf.is_config(vb) else vb._value()
    except Exception:  # noqa: BLE001
        return False
    return ca == cb


def sweep_combinations(argv: list[str]) -> tuple[list[list[str]], bool, DictConfig | None]:
    """The job override lists a command line runs, whether it is a multirun, and the master
    config it was decided on (group choices and Hydra's own overrides, with ``hydra``). A
    multirun includes an experiment's ``hydra.sweeper.params`` as Hydra's basic sweeper does
    (command-line values of the same key win). Needs an initialised Hydra
    (``initialize_config_dir``)."""
    from hydra.core.global_hydra import GlobalHydra
    from hydra.types import RunMode

    import dslearn.schemas  # noqa: F401  (the task configs name the schemas' ConfigStore entries)

    overrides = [a for a in argv if not a.startswith("-")]
    parsed = _parse_all(overrides)
    user = [o for o in parsed if not o.key_or_group.startswith("hydra")]
    flag = any(a in _MULTIRUN_FLAGS for a in argv)
    sweeps = [o.input_line for o in user if o.is_sweep_override()]
    # the master config only tells the mode and the sweeper's params: compose it from the group
    # choices and Hydra's own overrides (a bad value override is reported per job, with context)
    head = [o.input_line for o in parsed if o.key_or_group.startswith("hydra") or _is_group_override(o)]
    cl = GlobalHydra.instance().config_loader()
    master = cl.load_configuration("config", head, run_mode=RunMode.MULTIRUN, validate_sweep_overrides=False)
    multirun = flag or master.hydra.get("mode") == RunMode.MULTIRUN
    if not multirun:
        if sweeps:
            raise ConfigError(
                f"{sweeps[0]} is a sweep (one job per value); add -m (--multirun) to run them, "
                f"or write {sweeps[0].split('=', 1)[0]}=[a,b] for a list value"
            )
        return [[o.input_line for o in user]], False, master
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper

    params = [f"{k}={v}" for k, v in (master.hydra.sweeper.get("params") or {}).items()]
    allp = [o for o in _parse_all(params) if not o.key_or_group.startswith("hydra")] + user
    combos = BasicSweeper.split_arguments(allp, None)[0] if allp else [[]]
    return combos, True, master


def _lines(combo) -> tuple[list, list]:
    """A job's override lines split into group choices ``(line, override)`` and value overrides."""
    groups, values = [], []
    for line, o in zip(combo, _parse_all(list(combo))):
        if _is_group_override(o):
            groups.append((line, o))
        else:
            values.append(o)
    return groups, values


def sweep_composer(combos: list[list[str]], compose) -> _Composer:
    """One cache of compositions for the jobs of a sweep (:class:`_Composer`, its shared group choices those of
    every job): the sweeper's choice of cells and :func:`check_jobs` share it, so a cell is composed once."""
    split = [_lines(c)[0] for c in combos]
    constant = [g for g in split[0] if all(g[0] in {x[0] for x in s} for s in split)] if split else []
    return _Composer(compose, tuple(g[0] for g in constant))


def composed_job(composer: _Composer, combo) -> DictConfig:
    """A job's whole configuration through ``composer`` (its own copy where value overrides apply; else the
    shared composition: do not modify)."""
    from hydra._internal.config_loader_impl import ConfigLoaderImpl

    groups, values = _lines(combo)
    cfg = composer.config([g for g in groups if g[0] not in composer.base], [g[0] for g in groups])
    if values:
        cfg = copy.deepcopy(cfg)
        ConfigLoaderImpl._apply_overrides_to_config(values, cfg)
    return cfg


def check_jobs(combos: list[list[str]], compose, visit=None, composer: _Composer | None = None) -> tuple[int, int]:
    """Validate every job's configuration; ConfigError naming the job on the first bad one.
    ``compose(overrides)`` composes one configuration (Hydra's ``compose``); ``visit(cfg)``
    (default :func:`validate_job`) is called with each job's configuration, which is only valid
    during the call, and with the job's override lines as ``lines=`` where it takes them.
    ``composer``: a cache already holding compositions of these jobs (:func:`sweep_composer`).
    Returns ``(jobs checked, full compositions made)``."""
    import inspect

    from hydra._internal.config_loader_impl import ConfigLoaderImpl

    visit = visit or validate_job
    try:
        takes_lines = "lines" in inspect.signature(visit).parameters
    except (TypeError, ValueError):
        takes_lines = False
    many = len(combos) > 1
    split = []
    for i, combo in enumerate(combos):
        where = f" (sweep job {i}: {' '.join(combo)})" if many else ""
        try:
            parsed = _parse_all(list(combo))
        except Exception as e:  # noqa: BLE001
            raise ConfigError(f"{_friendly(e)}{where}") from None
        groups, values = [], []
        for line, o in zip(combo, parsed):
            if _is_group_override(o):
                if not o.is_delete():
                    try:
                        _check_group_option(o.key_or_group, o.value())
                    except ConfigError as e:
                        raise ConfigError(f"{e}{where}") from None
                groups.append((line, o))
            else:
                values.append(o)
        split.append((groups, values, where))
    if composer is None:
        constant = [g for g in split[0][0] if all(g[0] in {x[0] for x in s[0]} for s in split)] if split else []
        composer = _Composer(compose, tuple(g[0] for g in constant))
    const_lines = set(composer.base)
    for (groups, values, where), combo in zip(split, combos):
        cfg = None
        job_visit = (lambda c, _lines=list(combo): visit(c, lines=_lines)) if takes_lines else visit
        try:
            cfg = composer.config([g for g in groups if g[0] not in const_lines], [g[0] for g in groups])
            undo = _scalar_changes(values, cfg)
            if undo is None:  # adds, deletes, containers: on a copy
                cfg = copy.deepcopy(cfg)
                ConfigLoaderImpl._apply_overrides_to_config(values, cfg)
                job_visit(cfg)
            else:  # plain key=scalar changes: in place, undone afterwards (no copy: ~10 ms a job)
                try:
                    ConfigLoaderImpl._apply_overrides_to_config(values, cfg)
                    job_visit(cfg)
                finally:
                    for parent, leaf, old in reversed(undo):
                        with _open(parent):
                            parent[leaf] = old
        except ConfigError as e:
            raise ConfigError(f"{e}{where}") from None
        except Exception as e:  # noqa: BLE001 - Hydra/OmegaConf composition errors
            raise ConfigError(f"{_friendly(e, cfg)}{where}") from None
    return len(combos), composer.composes


def validate_job(cfg: DictConfig, lines=()) -> None:
    """One job's whole check: :func:`~dslearn.schemas.core.validate_config`, after refusing an
    override (of the job's ``lines``: command line and sweep) of a root group its task does not
    read, or of a task key its configuration does not read
    (:func:`~dslearn.schemas.base.check_overrides`)."""
    from dslearn.schemas.base import check_overrides
    from dslearn.schemas.core import validate_config

    if lines and "task" in cfg and cfg.task is not None and cfg.task.get("name") is not None:
        check_overrides(cfg, override_keys(lines))
        from dslearn.studies.matrix import check_method_chosen

        check_method_chosen(cfg, [k for k, _ in override_keys(lines)])
    validate_config(cfg)
    device = cfg.get("device")
    if device is not None and str(device).startswith("cuda"):  # here, not in the run: no run folder for it
        from dslearn.compose import resolve_device

        resolve_device(str(device))


def sweep_select(master: DictConfig):
    """The function by which the sweep's sweeper chooses the combinations that become jobs (its ``select``
    key, e.g. ``hydra/sweeper=matrix``: :func:`dslearn.schemas.matrix.select_cells`, the cells whose method
    fits the scenario), ``None`` for a sweeper that runs every combination."""
    name = OmegaConf.select(master, "hydra.sweeper.select", default=None)
    if not name:
        return None
    from dslearn.compose import import_object

    return import_object(name, "hydra.sweeper.select")
