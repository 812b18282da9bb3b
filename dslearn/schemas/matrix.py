"""Schema of ``task=matrix`` (one cell of the comparison matrix: a method on a scenario), and what decides
whether a cell fits (:func:`cell`): the up-front check of one run refuses a cell that does not fit; the
matrix sweep (``hydra/sweeper=matrix``, ``experiment=matrix``) drops it and records why (:func:`select_cells`,
which the sweeper and ``dslearn-run``'s up-front check both apply).

A cell is n/a only by what its method says of the scenario's declared spec: what the engine and its parts'
classes declare (``spec_misfit``, read before any part is built: a part that cannot be sized for a scenario is
never built for it), then the built method's ``fits``. An exception while its parts are built is no verdict: a
single run stops with it, a sweep records the cell as failed (``matrix_cells.csv``: ``status`` failed and the
``error``; not run; ``dslearn-report`` shows it failed)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from omegaconf import DictConfig

from dslearn.compose import _Slots
from dslearn.errors import ConfigError, DataFormatError
from dslearn.schemas.base import check_preset_keys, register_task
from dslearn.studies.matrix import MatrixSettings


def _register_sweeper() -> None:
    """Make the matrix sweeper (``hydra/sweeper=matrix``) known to Hydra also where Hydra's scan of the
    ``hydra_plugins`` namespace misses it: in an editable install (``pip install -e .``) setuptools serves the
    package through an import hook the scan cannot list, and ``dslearn-run`` started from any folder would
    not find the sweeper. Hydra's scan runs first: it executes the modules it loads anew, and a sweeper class
    imported before it would subclass a stale copy of Hydra's basic sweeper."""
    from hydra.core.plugins import Plugins

    plugins = Plugins.instance()
    from hydra_plugins.dslearn_matrix.matrix_sweeper import MatrixSweeper

    plugins.register(MatrixSweeper)


_register_sweeper()


@dataclass(frozen=True)
class Cell:
    """A composed matrix cell: its row (the method's label), its column (the scenario's name), the unit of
    the scenario's positions, and ``reason`` = why the method does not fit the scenario (``None``: it fits)."""

    method: str
    scenario: str
    units: str
    reason: str | None
    #: whether ``method`` is the method's label; ``False``: refused by what its engine or parts declare of the spec,
    #: the method was not built (``method`` names its parts, :func:`parts_label`)
    built: bool = True


def check_pools(cfg: DictConfig, spec) -> None:
    """A recorded scenario holds so many training and test episodes (``spec.pools``, known once it is built): a
    cell asking for more is refused here, at composition (the up-front check of a run and of every combination
    of a sweep, before any job starts), not when it draws them. One line naming the key, the number asked for
    and the pool's size."""
    pools = getattr(spec, "pools", None)
    if pools is None:
        return
    over = []
    for split, word, held in zip(("train", "test"), ("training", "test"), pools):
        asked = cfg.task.get(f"{split}_episodes")
        if isinstance(asked, int) and not isinstance(asked, bool) and asked > held:
            over.append(f"task.{split}_episodes={asked}: scenario {spec.name}'s {word} pool holds {held} episodes "
                        f"(ask for at most {held})")
    if over:
        raise ConfigError("; ".join(over) + " or change scenario.episodes (how the recording is cut and split)")


class CellBuildError(RuntimeError):
    """A cell whose parts raised while they were built for its scenario although the method declares that it
    fits (a fault in a part, not a verdict on the cell): a single run stops with it, a sweep records the cell as
    failed (:func:`select_cells`)."""


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split()) or type(e).__name__


def _error_text(e: BaseException) -> str:
    """``Type: message`` on one line (a :class:`CellBuildError`: its own message, which says it already)."""
    if isinstance(e, CellBuildError):
        return _one_line(e)
    return f"{type(e).__name__}: {_one_line(e)}"


def _part_target(node, key: str):
    """The object a part's ``_target_`` names (ConfigError naming ``<key>._target_`` where it cannot be imported)."""
    from dslearn.compose import import_object

    target = node.get("_target_") if isinstance(node, DictConfig) else None
    return import_object(target, f"{key}._target_") if target else None


def declared_reason(cfg: DictConfig, spec) -> str | None:
    """Why the method of ``cfg`` does not fit a scenario with ``spec``, by what its engine (``filter._target_``)
    and the parts that engine takes (:func:`dslearn.compose.method_takes`) declare of a spec
    (:func:`dslearn.methods.base.declared_misfit`): read from the spec alone, before any part is built;
    ``None`` where nothing declared refuses it."""
    from dslearn.compose import method_takes
    from dslearn.methods.base import declared_misfit

    engine = _part_target(cfg.filter, "filter")
    reason = declared_misfit(engine, spec) if engine is not None else None
    if reason is None and not getattr(spec, "labelled", True) and "associator" not in method_takes(cfg):
        reason = (f"it needs every measurement labelled with its target (its engine takes no associator); scenario "
                  f"{spec.name} reports unlabelled detections")
    for group in () if reason is not None else method_takes(cfg):
        target = _part_target(cfg.get(group), group)
        reason = declared_misfit(target, spec) if target is not None else None
        if reason is not None:
            break
    return reason


def parts_label(cfg: DictConfig) -> str:
    """A method named by its parts (``filter DistributedFilter, model sfm, consensus hybrid``): the row of a cell
    whose method was not built (its own label is known only once it is)."""
    from dslearn.compose import method_takes

    out = []
    for g in ("filter", *[g for g in method_takes(cfg) if g != "learner"]):
        node = cfg.get(g)
        if isinstance(node, DictConfig):
            out.append(f"{g} {node.get('name') or str(node.get('_target_', '?')).rsplit('.', 1)[-1]}")
    return ", ".join(out)


def _build_method(slots: _Slots, spec):
    """The cell's method built on the meta device (no random draw of the run consumed). A configuration error
    (a bad value, a learner the engine refuses) raises as it is; any other exception is a fault in a part:
    :class:`CellBuildError` naming the scenario and the error."""
    try:
        with torch.random.fork_rng(devices=[]):
            return slots["method"]
    except (ConfigError, DataFormatError):
        raise
    except Exception as e:  # noqa: BLE001 - any other error is a fault, never an n/a cell
        raise CellBuildError(f"the method's parts ({parts_label(slots.cfg)}) raised while built for scenario "
                             f"{spec.name}: {type(e).__name__}: {_one_line(e)}") from e


def cell(cfg: DictConfig) -> Cell:
    """The cell of a ``task=matrix`` configuration: first what its engine and parts declare of the scenario's
    spec (:func:`declared_reason`: a method refused there is not built, and its row is named by its parts,
    :func:`parts_label`), then its method built as a run builds it (on the meta device, without consuming a random
    draw of the run) and the method's verdict on the spec (:meth:`dslearn.methods.base.Method.fits`). A
    configuration that cannot be built raises (a bad value: ConfigError; a fault in a part:
    :class:`CellBuildError`), as does one asking for more episodes than a recorded scenario's pools hold
    (:func:`check_pools`)."""
    slots = _Slots(cfg, torch.device("meta"))
    spec = slots["scenario"].spec
    check_pools(cfg, spec)
    return _cell(slots, spec, label=True)


def _label_if_built(slots: _Slots) -> str | None:
    """The method's label where its parts can be built for the cell's scenario, else ``None``: for the row of a
    method already refused by what it declares (never a verdict: an error here only leaves the label unknown)."""
    try:
        with torch.random.fork_rng(devices=[]):
            return str(slots["method"].label)
    except Exception:  # noqa: BLE001 - a part refused for this scenario may not be sized for it
        return None


def _cell(slots: _Slots, spec, label: bool = False) -> Cell:
    """:func:`cell` on built slots; ``label``: a method refused by its declaration is still built, if it can be, for
    its label (a single run's message; a sweep takes the label from the method's other cells)."""
    reason = declared_reason(slots.cfg, spec)
    if reason is not None:
        own = _label_if_built(slots) if label else None
        return Cell(own or parts_label(slots.cfg), str(spec.name), str(spec.units), reason, built=own is not None)
    method = _build_method(slots, spec)
    return Cell(str(method.label), str(spec.name), str(spec.units), method.fits(spec))


def _sentence(c: Cell) -> str | None:
    if c.reason is None:
        return None
    who = c.method if c.built else f"the method ({c.method})"
    return f"{who} does not fit scenario {c.scenario}: {c.reason}"


def misfit(cfg: DictConfig) -> str | None:
    """Why the cell of ``cfg`` does not fit (one sentence naming the method, the scenario and what is missing),
    ``None`` where it fits or ``cfg`` is not a matrix cell. Parts that raise while built for a scenario they
    declare they fit raise :class:`CellBuildError` (a single run stops with that error, not "does not fit")."""
    if str(cfg.task.get("name")) != "matrix":
        return None
    return _sentence(cell(cfg))


#: the status of a combination of a matrix sweep (``matrix_cells.csv``'s ``status``): a job; the method does not
#: fit the scenario (``reason``; the report's "n/a", a word CSV readers would take for a missing value); the
#: sweep's ``task.left_out`` leaves it out (``reason``); its parts raised while the up-front check built them
#: (``error``): not run, shown failed by ``dslearn-report``
STATUSES = ("run", "does_not_fit", "left_out", "failed")
#: the records of the cells that failed in this process's matrix sweep (the sweeper adds them; ``dslearn-run``
#: exits 1 after the sweep where there are any)
FAILED_CELLS: list[dict] = []

#: the up-front check's judgement of a sweep's combinations (its ``select`` function's result), which the matrix
#: sweeper takes for the same combinations instead of judging them again: a cell is composed and built once per run
_JUDGED: dict[tuple, tuple] = {}


def remember_judgement(select, combos, judged) -> None:
    """Keep the judgement ``select(combos, ...)`` returned (only the latest: one sweep per run)."""
    _JUDGED.clear()
    _JUDGED[(select, tuple(tuple(c) for c in combos))] = judged


def take_judgement(select, combos):
    """The judgement :func:`remember_judgement` kept for these combinations and this ``select``, once; ``None``
    where there is none (the up-front check did not run, or judged other combinations)."""
    return _JUDGED.pop((select, tuple(tuple(c) for c in combos)), None)


def _scenario_key(cfg: DictConfig) -> str:
    """The scenario node of ``cfg`` resolved (what :func:`dslearn.compose.build_scenario` builds from)."""
    import json

    from omegaconf import OmegaConf

    return json.dumps(OmegaConf.to_container(cfg.scenario, resolve=True), sort_keys=True, default=str)


def judge(cfg: DictConfig, scenarios: dict | None = None) -> dict:
    """The record of one combination of a matrix sweep: ``method`` (label), ``scenario`` (name), ``units``,
    ``status`` (:data:`STATUSES`: ``run``, ``does_not_fit`` or ``failed``), ``reason`` (why it does not fit, ``None``
    otherwise), ``error`` (``failed``: the exception, one line) and ``built`` (whether the method was built:
    its ``method`` is then its label, else its parts, :func:`parts_label`).

    A cell is n/a only by what its method says of the scenario's declared spec (:func:`declared_reason` before
    any part is built, then :meth:`~dslearn.methods.base.Method.fits`); an exception while its scenario or its
    method is built is a failed cell. A configuration error (a bad value, a learner the engine cannot use, more
    episodes than a recorded scenario holds: :func:`check_pools`) raises, never a cell. A configuration of
    another task is a job whatever it is (empty labels). ``scenarios``: the scenarios built so far (by their
    resolved config node), shared by the combinations of a sweep (a scenario is built once, not once per method)."""
    rec = {"method": "", "scenario": "", "units": "", "status": "run", "reason": None, "error": None, "built": True}
    if str(cfg.task.get("name")) != "matrix":
        return rec
    slots = _Slots(cfg, torch.device("meta"))
    key = _scenario_key(cfg) if scenarios is not None else None
    if key is not None and key in scenarios:
        slots._built["scenario"] = scenarios[key]
    try:
        spec = slots["scenario"].spec
        if key is not None:
            scenarios[key] = slots["scenario"]
    except (ConfigError, DataFormatError):
        raise
    except Exception as e:  # noqa: BLE001 - a fault in the scenario: a failed cell, never n/a
        return {**rec, "status": "failed", "built": False, "method": parts_label(cfg),
                "error": f"scenario {cfg.scenario.get('_target_')} raised while built: {_error_text(e)}"}
    check_pools(cfg, spec)
    rec.update(scenario=str(spec.name), units=str(spec.units))
    try:
        c = _cell(slots, spec)
    except CellBuildError as e:
        return {**rec, "status": "failed", "built": False, "method": parts_label(cfg), "error": _error_text(e)}
    return {**rec, "method": c.method, "built": c.built, "reason": _sentence(c),
            "status": "run" if c.reason is None else "does_not_fit"}


def _method_key(combo) -> tuple[str, ...]:
    """A combination's override lines less those of the scenario group: the same method on every scenario."""
    def head(line: str) -> str:
        return line.split("=", 1)[0].lstrip("+~").split("@")[0]

    return tuple(line for line in combo if head(line) != "scenario" and not head(line).startswith("scenario."))


def _option(combo, group: str) -> str | None:
    """The ``group=<option>`` of a combination's override lines (``None`` where it has none)."""
    for line in combo:
        key, _, value = line.partition("=")
        if key.lstrip("+~") == group:
            return value
    return None


def group_options(group: str) -> list[str]:
    """The options of a config group in every config folder of the command (the package's and the user's
    ``hydra.searchpath`` folders, :data:`dslearn.conf_paths.CONF_DIRS`)."""
    from dslearn.conf_paths import CONF_DIRS

    return sorted({p.stem for d in CONF_DIRS for p in (d / group).glob("*.yaml")})


def left_out(cfg: DictConfig, combo) -> str | None:
    """Why the sweep leaves the combination ``combo`` out (``task.left_out``: a preset on some scenarios, with the
    reason), ``None`` where it does not. Each entry must name a ``method`` preset, ``scenario`` options (of the
    package's config folder or the user's ``hydra.searchpath`` folders) and a reason: a
    :class:`~dslearn.errors.ConfigError` otherwise, before any job (a typo must not run the cells it meant to
    leave out)."""
    entries = cfg.task.get("left_out") if str(cfg.task.get("name")) == "matrix" else None
    if not entries:
        return None
    methods, scenarios = group_options("method"), group_options("scenario")
    method, scenario = _option(combo, "method"), _option(combo, "scenario")
    found = None
    for k, e in enumerate(entries):
        if e.method not in methods:
            raise ConfigError(f"task.left_out[{k}].method={e.method!r} is not a method preset; choose one of {methods}")
        bad = [sc for sc in e.scenarios if sc not in scenarios]
        if bad or not e.scenarios:
            raise ConfigError(f"task.left_out[{k}].scenarios={list(e.scenarios)!r}: each must be one of {scenarios} "
                              f"(at least one)")
        if not str(e.why).strip():
            raise ConfigError(f"task.left_out[{k}].why is empty: say why the cells are left out")
        if found is None and e.method == method and scenario in e.scenarios:
            found = str(e.why).strip()
    return found


#: the override keys that choose a cell's method: its preset, or its parts
_METHOD_GROUPS = ("method", "filter", "model", "observation", "consensus", "learner")


def _row_label(combo, rec: dict, labels: dict) -> str:
    """The row of a combination whose method was not built: the method's label where the sweep built it on
    another scenario, else its options (``ekf_lin_hybrid model=mine``: the preset and the parts the combination
    sets), else its parts (:func:`parts_label`)."""
    if _method_key(combo) in labels:
        return labels[_method_key(combo)]
    preset = _option(combo, "method")
    parts = [f"{g}={_option(combo, g)}" for g in _METHOD_GROUPS[1:] if _option(combo, g) is not None]
    return " ".join(([preset] if preset else []) + parts) or rec["method"]


def select_cells(combos, compose) -> tuple[list[list[str]], list[dict]]:
    """The combinations of a sweep that become jobs (in order) and one record per combination: :func:`judge`'s
    (``method``, ``scenario``, ``units``, ``status``, ``reason``, ``error``), plus ``job`` (its job number,
    ``None`` where it does not run) and ``overrides`` (its lines).

    ``compose(lines)`` composes one combination. A combination whose method fits the scenario runs; one whose
    method declares that it does not fit (before it is built, then :meth:`~dslearn.methods.base.Method.fits`)
    is ``does_not_fit`` with that reason (an "n/a" cell); one whose parts raise while they are built is
    ``failed`` with the error (not run, never n/a); a cell that fits but that the sweep's ``task.left_out`` lists
    (:func:`left_out`) is ``left_out`` with that reason. A configuration error in any combination raises
    (:class:`~dslearn.errors.ConfigError`), so a bad value is never turned into cells. The row of a method that
    was not built is its label from another scenario of the sweep (:func:`_row_label`)."""
    records, scenarios = [], {}
    for combo in combos:
        cfg = compose(list(combo))
        check_preset_keys(cfg, [(line.split("=", 1)[0], line) for line in combo])  # a preset's key another part lacks
        rec = {**judge(cfg, scenarios), "overrides": " ".join(combo)}
        rec["scenario"] = rec["scenario"] or (_option(combo, "scenario") or "")
        why = left_out(cfg, combo)
        if why is not None and rec["status"] == "run":
            rec["status"] = "left_out"
            rec["reason"] = (f"{rec['method']} on scenario {rec['scenario']} is left out of this sweep "
                             f"(task.left_out): {why}")
        records.append((list(combo), rec))
    labels = {}
    for combo, rec in records:
        if rec["built"]:
            labels.setdefault(_method_key(combo), rec["method"])
    for combo, rec in records:  # a method refused on every scenario of the sweep: its label, where it can be built
        if rec["status"] == "does_not_fit" and not rec["built"] and _method_key(combo) not in labels:
            own = _label_if_built(_Slots(compose(list(combo)), torch.device("meta")))
            if own is not None:
                labels[_method_key(combo)] = own
    kept, out = [], []
    for combo, rec in records:
        if not rec.pop("built"):
            label = _row_label(combo, rec, labels)
            if rec["status"] == "does_not_fit":
                head = f"the method ({rec['method']}) does not fit scenario {rec['scenario']}: "
                rec["reason"] = f"{label} does not fit scenario {rec['scenario']}: {rec['reason'][len(head):]}"
            rec["method"] = label
        rec["job"] = len(kept) if rec["status"] == "run" else None
        if rec["status"] == "run":
            kept.append(combo)
        out.append(rec)
    return kept, out


def check(cfg: DictConfig) -> None:
    """The method must fit the scenario: refused up front, before any job of a sweep, with the reason (a
    sweep with the matrix sweeper drops such a cell before it gets here). Parts that raise while built raise
    :class:`CellBuildError` (the run stops with the error)."""
    reason = misfit(cfg)
    if reason is not None:
        raise ConfigError(reason)


def uses(cfg: DictConfig) -> tuple[str, ...]:
    """The root groups a cell reads: the method preset and the scenario; the network part only for a scenario
    without sensors of its own; the filter (the method's engine) and the parts that engine takes, its learner
    among them (:func:`dslearn.compose.method_takes`)."""
    from hydra.utils import get_object

    from dslearn.compose import method_takes

    own = getattr(get_object(str(cfg.scenario._target_)), "owns_network", False)
    return ("method", "scenario", "filter", *method_takes(cfg), *(() if own else ("network",)))


register_task("matrix", MatrixSettings, check, uses=uses,
              instead={"network": "this scenario places its own sensors",
                       "model": "this method's engine takes no motion model part",
                       "observation": "this method's engine takes no observation model part",
                       "consensus": "this method's engine takes no fusion part",
                       "learner": "this method's engine takes no learner part",
                       "associator": "this method's engine takes no associator part: it needs labelled measurements",
                       "data": "task.train_episodes / task.test_episodes"},
              parts=("scenario", "network", "model", "observation", "consensus", "filter", "learner", "associator"))
