"""Structured-config schemas (dataclasses) for the root keys and the core study's groups.

The dataclasses are registered in Hydra's ConfigStore (group ``schema``; e.g. a config may list
``- schema/network@network`` in its defaults to merge against it), and :func:`validate_config`
checks a composed configuration against them before any work starts: wrong types, unknown keys
and out-of-range values raise :class:`dslearn.errors.ConfigError` naming the field
(``dslearn-run`` turns it into one line on stderr and exit code 2).

What is checked:

* root keys (every task): ``seed`` (int >= 0), ``device`` (cpu | cuda[:n]), ``dtype``,
  ``progress`` (bool or null), ``threads`` (int >= 1 or null), ``print_table``, ``resume``,
  ``study`` (str); an unknown top-level key fails (known: these, ``task``, and every config group
  under ``conf/``, so groups added later are accepted automatically);
* ``task.entry`` / ``task.name`` (every task); the rest of ``task`` is the study's to validate;
* for the core study (``task.name`` = yu or yu_faults): ``scenario``, ``network``, ``model``,
  ``observation``, ``consensus``, ``data``, ``filter`` — closed schemas (unknown keys fail) with
  range checks. Other tasks' groups (tracker, aggregation, gp_input, lstm, scenario s1..s3, ...)
  stay open: their studies validate them.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, List, Optional

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from .errors import ConfigError, check_choice, check_positive

CONF_DIR = Path(__file__).resolve().parent.parent / "conf"
CORE_TASKS = ("yu", "yu_faults")


@dataclass
class RootSchema:
    study: str = "default"
    seed: int = 0
    device: str = "cpu"
    dtype: str = "float64"
    progress: Optional[bool] = None
    threads: Optional[int] = 1
    print_table: bool = True
    resume: bool = False


@dataclass
class TaskHead:
    entry: str = "dslearn.studies.yu:run"
    name: str = "yu"


@dataclass
class ScenarioSchema:
    # nested lists: List[Any] (OmegaConf does not convert ints inside nested typed lists); checked below
    desired_velocities: List[Any] = field(default_factory=lambda: [[1.0, -1.0], [-1.0, -1.0]])
    start_corners: List[Any] = field(default_factory=lambda: [[1.5, 5.0], [5.0, 5.0]])
    start_size: float = 1.5
    tau: Any = 0.25  # a number or one per agent
    alpha: Any = 6.0
    beta: Any = 5.0
    process_std: float = 0.001
    horizon: float = 3.0
    dt: float = 0.25
    area: List[float] = field(default_factory=lambda: [0.0, 8.0, 0.0, 8.0])


@dataclass
class NetworkSchema:
    num_sensors: int = 4
    num_comm: int = 6
    area: List[float] = field(default_factory=lambda: [0.0, 8.0, 0.0, 8.0])
    positions: Optional[List[Any]] = None  # [[x, y], ...]
    seed: int = 0
    comm_radius: Optional[float] = 4.0
    k_nearest: Optional[int] = None
    edges: Optional[List[Any]] = None  # [[i, j], ...]
    sensing_range: float = 4.0
    meas_std: float = 0.2


@dataclass
class ModelSchema:
    name: str = "gp"
    kind: Optional[str] = None
    noise_std: float = 0.5
    # GP models
    outputscale: Optional[float] = None
    lengthscale: Optional[float] = None
    mean: Optional[str] = None
    noise: Optional[str] = None
    jacobian: Optional[str] = None
    fit_every: Optional[int] = None
    fit_iters: Optional[int] = None
    fit_lr: Optional[float] = None
    capacity: Optional[int] = None
    # scalable variants (dslearn.models.sparse)
    variant: Optional[str] = None
    window: Optional[int] = None
    inducing: Optional[int] = None
    features: Optional[int] = None
    seed: Optional[int] = None
    # aggregated GP (dslearn.models.aggregated)
    aggregation: Optional[str] = None
    normalise_beta: Optional[bool] = None
    aggregation_jacobian: Optional[str] = None


@dataclass
class ObservationSchema:
    name: str = "linear"
    noise_std: float = 0.2
    outputscale: Optional[float] = None
    lengthscale: Optional[float] = None
    mean: Optional[str] = None
    noise: Optional[str] = None


@dataclass
class ConsensusSchema:
    name: str = "hybrid"
    iterations: int = 4
    weights: str = "uniform"
    omega: Any = "one"


@dataclass
class DataSchema:
    train_episodes: int = 30
    test_episodes: int = 20
    eval_at: Optional[List[int]] = None
    min_train_episodes: int = 0


@dataclass
class FilterSchema:
    prior_pos_std: float = 4.0
    prior_vel_std: float = 2.0
    learn_gate_std: Optional[float] = None


GROUP_SCHEMAS = {
    "scenario": ScenarioSchema,
    "network": NetworkSchema,
    "model": ModelSchema,
    "observation": ObservationSchema,
    "consensus": ConsensusSchema,
    "data": DataSchema,
    "filter": FilterSchema,
}


def register_configs() -> None:
    """Register the schemas in Hydra's ConfigStore (group ``schema``)."""
    from hydra.core.config_store import ConfigStore

    cs = ConfigStore.instance()
    cs.store(name="root", node=RootSchema, group="schema")
    for g, s in GROUP_SCHEMAS.items():
        cs.store(name=g, node=s, group="schema")


register_configs()


def _field_error(prefix: str, e: OmegaConfBaseException) -> ConfigError:
    key = getattr(e, "full_key", None) or ""
    full = f"{prefix}.{key}" if prefix and key else (prefix or key)
    msg = getattr(e, "msg", None) or str(e).splitlines()[0]
    msg = msg.splitlines()[0]
    if "not in struct" in msg or "not in " in msg and "Key" in msg:
        return ConfigError(f"{full}: unknown key ({msg})")
    return ConfigError(f"{full}: {msg}")


def check_schema(node: Any, schema: type, prefix: str) -> DictConfig:
    """Merge ``node`` (a dict/DictConfig) into ``schema``; ConfigError naming the field on a
    wrong type or an unknown key. Returns the typed, merged config."""
    if node is None:
        raise ConfigError(f"{prefix} is missing (null); expected a mapping with keys {[f.name for f in fields(schema)]}")
    if isinstance(node, DictConfig):
        try:
            node = OmegaConf.to_container(node, resolve=True)
        except OmegaConfBaseException as e:
            raise _field_error(prefix, e) from None
    if not isinstance(node, dict):
        raise ConfigError(f"{prefix}={node!r} must be a mapping with keys {[f.name for f in fields(schema)]}")
    base = OmegaConf.structured(schema)
    try:
        return OmegaConf.merge(base, node)
    except OmegaConfBaseException as e:
        raise _field_error(prefix, e) from None


def known_root_keys() -> set[str]:
    groups = {p.name for p in CONF_DIR.iterdir() if p.is_dir()} if CONF_DIR.is_dir() else set()
    return {f.name for f in fields(RootSchema)} | {"task", "hydra", "noise"} | groups | set(GROUP_SCHEMAS)


def validate_config(cfg: DictConfig) -> None:
    """Check ``cfg`` (the composed config) before any work. Raises :class:`ConfigError`."""
    if not isinstance(cfg, DictConfig):
        cfg = OmegaConf.create(cfg)
    unknown = sorted(set(cfg.keys()) - known_root_keys())
    if unknown:
        raise ConfigError(f"unknown top-level key(s) {unknown}; known keys: {sorted(known_root_keys() - {'hydra'})}")
    root = {f.name: cfg[f.name] for f in fields(RootSchema) if f.name in cfg}
    r = check_schema(root, RootSchema, "")
    if r.seed < 0:
        raise ConfigError(f"seed={r.seed} must be an integer >= 0")
    check_choice("device", str(r.device).split(":")[0], ("cpu", "cuda"))
    check_choice("dtype", r.dtype, ("float64", "float32"))
    if r.threads is not None and r.threads < 1:
        raise ConfigError(f"threads={r.threads} must be >= 1 (or null for torch's default)")
    if "task" not in cfg or cfg.task is None:
        raise ConfigError("task is missing; choose one with task=<name> or experiment=<study>")
    for k in ("entry", "name"):
        v = cfg.task.get(k)
        if not isinstance(v, str) or not v:
            raise ConfigError(f"task.{k}={v!r} must be a non-empty string")
    if cfg.task.name in CORE_TASKS:
        validate_core(cfg)


def validate_core(cfg: DictConfig) -> None:
    """Schemas and ranges of the core (Yu) study's groups."""
    g = {name: check_schema(cfg.get(name), schema, name) for name, schema in GROUP_SCHEMAS.items()}
    sc, nw, m, ob, co, da, fi = (g[k] for k in ("scenario", "network", "model", "observation", "consensus", "data", "filter"))
    # scenario
    for name in ("desired_velocities", "start_corners"):
        _check_pairs(f"scenario.{name}", sc[name], float)
    if nw.positions is not None:
        _check_pairs("network.positions", nw.positions, float)
    if nw.edges is not None:
        _check_pairs("network.edges", nw.edges, int)
    if len(sc.desired_velocities) < 1:
        raise ConfigError(f"scenario.desired_velocities={list(sc.desired_velocities)!r} must be a list of [vx, vy] pairs")
    if len(sc.start_corners) != len(sc.desired_velocities) or any(len(v) != 2 for v in sc.start_corners):
        raise ConfigError(
            f"scenario.start_corners must hold one [x, y] pair per agent ({len(sc.desired_velocities)}), "
            f"got {list(sc.start_corners)!r}"
        )
    _check_area("scenario.area", sc.area)
    for k in ("start_size", "dt", "horizon"):
        check_positive(f"scenario.{k}", sc[k])
    check_positive("scenario.process_std", sc.process_std, strict=False)
    if sc.horizon < 2 * sc.dt:
        raise ConfigError(f"scenario.horizon={sc.horizon} must be >= 2 * scenario.dt={2 * sc.dt} (two steps initialise the filter)")
    # network
    if nw.num_sensors < 1:
        raise ConfigError(f"network.num_sensors={nw.num_sensors} must be >= 1")
    if nw.num_comm < 0:
        raise ConfigError(f"network.num_comm={nw.num_comm} must be >= 0")
    _check_area("network.area", nw.area)
    check_positive("network.sensing_range", nw.sensing_range)
    check_positive("network.meas_std", nw.meas_std)
    if nw.comm_radius is not None:
        check_positive("network.comm_radius", nw.comm_radius)
    if nw.k_nearest is not None and nw.k_nearest < 1:
        raise ConfigError(f"network.k_nearest={nw.k_nearest} must be >= 1")
    if nw.comm_radius is None and nw.k_nearest is None and nw.edges is None:
        raise ConfigError("network: give one of comm_radius, k_nearest or edges")
    # model
    check_positive("model.noise_std", m.noise_std)
    for k in ("outputscale", "lengthscale", "fit_lr"):
        if m[k] is not None:
            check_positive(f"model.{k}", m[k])
    for k in ("fit_every",):
        if m[k] is not None and m[k] < 0:
            raise ConfigError(f"model.{k}={m[k]} must be >= 0")
    for k in ("fit_iters", "capacity", "window", "inducing", "features"):
        if m[k] is not None and m[k] < 1:
            raise ConfigError(f"model.{k}={m[k]} must be >= 1")
    if m.mean is not None:
        check_choice("model.mean", m.mean, ("zero", "constant", "identity"))
    if m.noise is not None:
        check_choice("model.noise", m.noise, ("latent", "predictive"))
    if m.jacobian is not None:
        check_choice("model.jacobian", m.jacobian, ("closed_form", "autograd"))
    # observation
    check_choice("observation.name", ob.name, ("linear", "gp"))
    check_positive("observation.noise_std", ob.noise_std)
    # consensus
    from .consensus.fusion import FUSIONS
    from .consensus.weights import WEIGHT_METHODS

    check_choice("consensus.name", co.name, FUSIONS)
    check_choice("consensus.weights", co.weights, WEIGHT_METHODS)
    if co.iterations < 0:
        raise ConfigError(f"consensus.iterations={co.iterations} must be an integer >= 0")
    om = co.omega
    if isinstance(om, str):
        check_choice("consensus.omega", om, ("one", "nodes"))
    elif isinstance(om, bool) or not isinstance(om, (int, float)) or not om > 0:
        raise ConfigError(f"consensus.omega={om!r} must be > 0, 'one' or 'nodes'")
    # data
    if da.train_episodes < 0:
        raise ConfigError(f"data.train_episodes={da.train_episodes} must be an integer >= 0")
    if da.test_episodes < 1:
        raise ConfigError(f"data.test_episodes={da.test_episodes} must be an integer >= 1")
    if da.eval_at is not None:
        bad = [k for k in da.eval_at if not 0 <= k <= da.train_episodes]
        if bad:
            raise ConfigError(
                f"data.eval_at contains {bad}, but only data.train_episodes={da.train_episodes} training "
                f"episodes are run; use values in 0..{da.train_episodes}"
            )
    # filter
    check_positive("filter.prior_pos_std", fi.prior_pos_std)
    check_positive("filter.prior_vel_std", fi.prior_vel_std)
    if fi.learn_gate_std is not None:
        check_positive("filter.learn_gate_std", fi.learn_gate_std)


def _check_area(name: str, area) -> None:
    a = list(area)
    if len(a) != 4 or not (a[0] < a[1] and a[2] < a[3]):
        raise ConfigError(f"{name}={a!r} must be [xmin, xmax, ymin, ymax] with xmin < xmax and ymin < ymax")


def _check_pairs(name: str, value, kind) -> None:
    """A list of 2-element numeric lists (``kind`` int: integral values)."""
    for i, v in enumerate(value):
        if not hasattr(v, "__len__") or isinstance(v, str) or len(v) != 2:
            raise ConfigError(f"{name}[{i}]={v!r} must be a pair [a, b]")
        for x in v:
            if isinstance(x, bool) or not isinstance(x, (int, float)) or (kind is int and float(x) != int(x)):
                raise ConfigError(f"{name}[{i}]={list(v)!r} must hold two {'integers' if kind is int else 'numbers'}")
