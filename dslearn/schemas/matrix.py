"""Schema of ``task=matrix`` (one cell of the comparison matrix: a method on a scenario), and what decides
whether a cell fits (:func:`cell`): the up-front check of one run refuses a cell that does not fit; the
matrix sweep (``hydra/sweeper=matrix``, ``experiment=matrix``) drops it and records why (:func:`select_cells`,
which the sweeper and ``dslearn-run``'s up-front check both apply)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from omegaconf import DictConfig

from dslearn.errors import ConfigError
from dslearn.schemas.base import register_task
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


class _MetaSlots:
    """The composition root's slots (:data:`dslearn.compose.SLOTS`) of one configuration, each built once,
    on PyTorch's meta device (no memory, no numbers)."""

    def __init__(self, cfg: DictConfig):
        self.cfg, self._built = cfg, {"device": torch.device("meta")}

    def __getitem__(self, name: str) -> Any:
        from dslearn.compose import SLOTS

        if name not in self._built:
            self._built[name] = SLOTS[name](self.cfg, self)
        return self._built[name]


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


def cell(cfg: DictConfig) -> Cell:
    """The cell of a ``task=matrix`` configuration: its method and scenario built as a run builds them (on the
    meta device, without consuming a random draw of the run) and the method's verdict on the scenario's
    declared spec (:meth:`dslearn.methods.base.Method.fits`). A configuration that cannot be built raises, as does
    one asking for more episodes than a recorded scenario's pools hold (:func:`check_pools`)."""
    slots = _MetaSlots(cfg)
    spec = slots["scenario"].spec
    check_pools(cfg, spec)
    with torch.random.fork_rng(devices=[]):
        method = slots["method"]
    return Cell(str(method.label), str(spec.name), str(spec.units), method.fits(spec))


def _sentence(c: Cell) -> str | None:
    return None if c.reason is None else f"{c.method} does not fit scenario {c.scenario}: {c.reason}"


def misfit(cfg: DictConfig) -> str | None:
    """Why the cell of ``cfg`` does not fit (one sentence naming the method, the scenario and what is missing),
    ``None`` where it fits or ``cfg`` is not a matrix cell."""
    if str(cfg.task.get("name")) != "matrix":
        return None
    try:
        return _sentence(cell(cfg))
    except ConfigError:
        raise  # a bad value: the configuration's error, not a verdict on the cell
    except Exception as e:  # noqa: BLE001 - a part that cannot be sized for this scenario (as judge and select_cells)
        spec = _MetaSlots(cfg)["scenario"].spec
        parts = ", ".join(f"{g} {cfg[g].get('name', cfg[g].get('_target_'))}" for g in ("filter", "model", "consensus")
                          if g in cfg and cfg[g] is not None)
        return f"the method ({parts}) does not fit scenario {spec.name}: its parts cannot be built for it: {_one_line(e)}"


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split()) or type(e).__name__


def judge(cfg: DictConfig) -> dict:
    """The record of one combination of a matrix sweep: ``method`` (label), ``scenario`` (name), ``units``,
    ``reason`` (``None``: the cell fits and runs) and ``unbuilt`` (the method's parts could not be built for
    this scenario: ``reason`` is the error, ``method`` empty). A scenario that cannot be built raises (a bad
    configuration), as does one asking for more episodes than a recorded scenario holds (:func:`check_pools`:
    a bad count, never an n/a cell). A configuration of another task is a job whatever it is (empty labels)."""
    if str(cfg.task.get("name")) != "matrix":
        return {"method": "", "scenario": "", "units": "", "reason": None, "unbuilt": False}
    from dslearn.learning.learners import LearnerRefused

    slots = _MetaSlots(cfg)
    spec = slots["scenario"].spec
    check_pools(cfg, spec)
    try:
        with torch.random.fork_rng(devices=[]):
            method = slots["method"]
    except LearnerRefused:
        raise  # a learner the engine cannot use with these parts: a bad configuration on any scenario, never n/a
    except Exception as e:  # noqa: BLE001 - a part that cannot be sized for this scenario (decided in select_cells)
        return {"method": "", "scenario": str(spec.name), "units": str(spec.units), "unbuilt": True,
                "reason": f"its parts cannot be built for scenario {spec.name}: {_one_line(e)}"}
    c = Cell(str(method.label), str(spec.name), str(spec.units), method.fits(spec))
    return {"method": c.method, "scenario": c.scenario, "units": c.units, "reason": _sentence(c), "unbuilt": False}


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


def left_out(cfg: DictConfig, combo) -> str | None:
    """Why the sweep leaves the combination ``combo`` out (``task.left_out``: a preset on some scenarios, with the
    reason), ``None`` where it does not. Each entry must name a ``conf/method`` preset, ``conf/scenario`` options
    and a reason: a :class:`~dslearn.errors.ConfigError` otherwise, before any job (a typo must not run the cells
    it meant to leave out)."""
    from dslearn.conf_paths import CONF_DIR

    entries = cfg.task.get("left_out") if str(cfg.task.get("name")) == "matrix" else None
    if not entries:
        return None
    methods = sorted(p.stem for p in (CONF_DIR / "method").glob("*.yaml"))
    scenarios = sorted(p.stem for p in (CONF_DIR / "scenario").glob("*.yaml"))
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


def select_cells(combos, compose) -> tuple[list[list[str]], list[dict]]:
    """The combinations of a sweep that become jobs (in order) and one record per combination: :func:`judge`'s,
    plus ``job`` (its job number, ``None`` where it does not run) and ``overrides`` (its lines).

    ``compose(lines)`` composes one combination. A combination whose method fits the scenario runs; one whose
    method declares that it does not fit (:meth:`~dslearn.methods.base.Method.fits`) is dropped with that
    reason. A method whose parts cannot be built for a scenario (e.g. the social force model with the
    simulation's parameters, on a scenario that simulates no social forces) does not fit that scenario
    either, provided it is built for another scenario of the sweep; a method built for no scenario of the
    sweep is a configuration error (:class:`~dslearn.errors.ConfigError` with the first error), so a bad
    value is never turned into "n/a" cells. A cell that fits but that the sweep's ``task.left_out`` lists
    (:func:`left_out`) is dropped with that reason."""
    records = []
    for combo in combos:
        cfg = compose(list(combo))
        rec = {**judge(cfg), "overrides": " ".join(combo)}
        why = left_out(cfg, combo)
        if why is not None and rec["reason"] is None:
            rec["reason"] = f"{rec['method']} on scenario {rec['scenario']} is left out of this sweep (task.left_out): {why}"
        records.append((list(combo), rec))
    built = {}
    for combo, rec in records:
        if not rec.get("unbuilt"):
            built.setdefault(_method_key(combo), rec["method"])
    kept, out = [], []
    for combo, rec in records:
        if rec.pop("unbuilt", False):
            label = built.get(_method_key(combo))
            if label is None:
                raise ConfigError(f"the method of {rec['overrides']} is built for no scenario of the sweep; on "
                                  f"scenario {rec['scenario']}: {rec['reason'].split(': ', 1)[1]}")
            rec["method"], rec["reason"] = label, f"{label} does not fit scenario {rec['scenario']}: {rec['reason']}"
        rec["job"] = len(kept) if rec["reason"] is None else None
        if rec["reason"] is None:
            kept.append(combo)
        out.append(rec)
    return kept, out


def check(cfg: DictConfig) -> None:
    """The method must fit the scenario: refused up front, before any job of a sweep, with the reason (a
    sweep with the matrix sweeper drops such a cell before it gets here)."""
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
                       "data": "task.train_episodes / task.test_episodes"})
