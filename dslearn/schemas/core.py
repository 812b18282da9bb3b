"""Structured-config schemas (dataclasses) for the root keys and the core study's groups.

The dataclasses are registered in Hydra's ConfigStore (group ``schema``; e.g. a config may list
``- schema/network@network`` in its defaults to merge against it), and :func:`validate_config`
checks a composed configuration against them before any work starts: wrong types, unknown keys
and out-of-range values raise :class:`dslearn.errors.ConfigError` naming the field
(``dslearn-run`` turns it into one line on stderr and exit code 2).

What is checked:

* root keys (every task): ``seed`` (int >= 0), ``device`` (cpu | cuda[:n]), ``dtype``,
  ``progress`` (bool or null), ``threads`` (int in 1..CPU count, or null), ``print_table``,
  ``resume``, ``study`` (str), ``max_memory_gb`` (the memory limit of the resource guard, set
  with ``+max_memory_gb=...``); an unknown top-level key fails (known: these, ``task``, and
  every config group under ``conf/``, so groups added later are accepted automatically);
* ``task._target_`` (a study class the composition root builds, :func:`dslearn.compose.build_study`)
  must be registered (:data:`TASK_TARGETS`: only the project's own studies are ever built) and ``task.name`` a
  non-empty string; the rest of ``task`` is the study's settings, checked by its schema;
* resource guard (core study): the estimated peak memory (:func:`estimate_core_memory`) must
  stay under ``max_memory_gb`` (default: 75 % of this machine's memory), so a run that would
  swamp the machine is refused up front with the estimate in the message;
* for the core study (``task.name`` = yu or yu_faults): ``scenario``, ``network``, ``model``,
  ``observation``, ``consensus``, ``data``, ``filter`` — closed schemas (unknown keys fail) with
  range checks. Other tasks' options of these groups (scenario s1..s3, ...) and the groups outside
  the root defaults (lstm, dataset, folds) stay open: their studies validate them; which root
  groups a task reads at all is declared with its schema (:func:`dslearn.schemas.base.register_task`),
  and the start-up check refuses an override of one it does not read
  (:func:`dslearn.schemas.base.check_overrides`);
* then the core study's parts are built (:func:`check_parts`: models on the ``meta`` device, no
  memory), so that what only a constructor can check (the aggregation rule of an aggregated GP,
  the UKF's parameters against the state dimension, the network's connectivity, ...) is refused
  up front too, naming the full key.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, List, Optional

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from dslearn.errors import ConfigError, check_finite, check_choice, check_positive



from dslearn.conf_paths import CONF_DIR, CONF_DIRS  # noqa: E402,F401  (re-exported)
from dslearn.learning.online import DataSettings  # noqa: E402  (the data group's schema is the study's slot type)
from dslearn.schemas.base import validate_task  # noqa: E402

CORE_TASKS = ("yu", "yu_faults")

#: the registry of studies: ``task.name`` -> the study class (``task._target_``). ``dslearn-run`` builds
#: only these, never an arbitrary importable callable.
TASK_TARGETS: dict[str, str] = {
    "yu": "dslearn.studies.yu.YuStudy",
    "yu_faults": "dslearn.studies.yu_faults.YuFaultsStudy",
    "ethucy_tracking": "dslearn.studies.ethucy_tracking.EthucyTrackingStudy",
    "ethucy_forecast": "dslearn.studies.ethucy_forecast.EthucyForecastStudy",
    "liu_dgpt": "dslearn.studies.liu_dgpt.LiuDgptStudy",
    "jiang_fg": "dslearn.studies.jiang_fg.JiangFgStudy",
    "braga_tbn": "dslearn.studies.braga_tbn.BragaStudy",
    "matrix": "dslearn.studies.matrix.MatrixCell",
    "gp_bayes_filters": "dslearn.studies.gp_bayes_filters.GPBayesFiltersStudy",
}
#: share of the machine's memory a run may plan to use unless ``+max_memory_gb=...`` says otherwise
MEMORY_SHARE = 0.75


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
    max_memory_gb: Optional[float] = None  # resource guard limit (null = MEMORY_SHARE of the machine)


@dataclass
class PartSchema:
    """The keys of a config part that Hydra instantiates (:mod:`dslearn.compose`)."""

    _target_: Optional[str] = None  # the class / factory Hydra instantiates (dslearn.compose)
    _partial_: bool = False


@dataclass
class ScenarioSchema(PartSchema):
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
    softening: float = 0.2  # m, interaction softening radius of the social force


@dataclass
class NetworkSchema(PartSchema):
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
class ModelSchema(PartSchema):
    name: str = "gp"
    noise_std: float = 0.5
    # GP models
    outputscale: Optional[float] = None
    lengthscale: Optional[float] = None
    mean: Optional[str] = None
    noise: Optional[str] = None
    noise_fading: Optional[float] = None
    jacobian: Optional[str] = None
    fit_every: Optional[int] = None
    fit_iters: Optional[int] = None
    fit_lr: Optional[float] = None
    capacity: Optional[int] = None
    factor_dtype: Optional[str] = None  # exact GP: null (the run's dtype) | float32 (the Cholesky factor)
    factor: Optional[str] = None  # exact GP: auto | inverse | cholesky (what the factor buffer holds)
    inputs: Optional[str] = None  # exact / window GP: mean (linearised at the mean) | belief (averaged over N(y, P))
    # scalable variants (dslearn.models.gp_backends.sparse)
    variant: Optional[str] = None
    window: Optional[int] = None
    inducing: Optional[int] = None
    features: Optional[int] = None
    seed: Optional[int] = None
    # aggregated GP (dslearn.models.aggregated)
    aggregation: Optional[str] = None
    normalise_beta: Optional[bool] = None
    aggregation_jacobian: Optional[str] = None
    # LSTM / Social-LSTM (dslearn.models.lstm.SocialLSTM.for_scenario; ranges: its constructor, built by check_parts)
    obs_len: Optional[int] = None
    pred_len: Optional[int] = None
    embed: Optional[int] = None
    hidden: Optional[int] = None
    pooling: Optional[str] = None
    grid: Optional[int] = None
    neighbourhood: Optional[float] = None
    schedule: Optional[str] = None
    epochs: Optional[int] = None
    batch_size: Optional[int] = None
    lr: Optional[float] = None
    patience: Optional[int] = None
    min_delta: Optional[float] = None
    lr_factor: Optional[float] = None
    lr_patience: Optional[int] = None
    min_lr: Optional[float] = None
    val_fraction: Optional[float] = None
    process_noise: Optional[str] = None
    weights_dtype: Optional[str] = None  # the LSTMs' weights: float32 | float64 | null (the run's dtype)
    train_on: Optional[str] = None  # offline models: truth | fused (real-data tracking only) | null (the study's recipe)
    # social force fitted offline (dslearn.learning.sfm_fit.FittedSocialForce.for_scenario; ranges: its factory)
    desired_steps: Optional[int] = None
    tau_grid: Optional[List[float]] = None
    alpha_grid: Optional[List[float]] = None
    beta_grid: Optional[List[float]] = None
    refine_iters: Optional[int] = None
    refine_lr: Optional[float] = None


@dataclass
class ObservationSchema(PartSchema):
    name: str = "linear"
    noise_std: Optional[float] = None  # null: the sensors' own noise (the run's network's meas_std)
    outputscale: Optional[float] = None
    lengthscale: Optional[float] = None
    mean: Optional[str] = None
    noise: Optional[str] = None


@dataclass
class ConsensusSchema(PartSchema):
    name: str = "hybrid"
    iterations: int = 4
    weights: str = "uniform"
    omega: Any = "one"


@dataclass
class FilterSchema(PartSchema):  # _target_: the method the filter engine makes (dslearn.methods.distributed)
    prior_pos_std: float = 1000.0
    prior_vel_std: float = 1000.0
    learn_gate_std: Optional[float] = 2.0
    predict: Optional[Any] = None  # the prediction step ({_target_: ...}: EKF or unscented)


GROUP_SCHEMAS = {
    "scenario": ScenarioSchema,
    "network": NetworkSchema,
    "model": ModelSchema,
    "observation": ObservationSchema,
    "consensus": ConsensusSchema,
    "data": DataSettings,
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


_SCHEMA_CACHE: dict[tuple, Any] = {}


def check_schema(node: Any, schema: type, prefix: str) -> DictConfig:
    """Merge ``node`` (a dict/DictConfig) into ``schema``; ConfigError naming the field on a
    wrong type or an unknown key. Returns the typed, merged config (a copy the caller owns)."""
    import copy

    out = copy.deepcopy(_checked(node, schema, prefix))
    OmegaConf.set_readonly(out, False)
    return out


def _checked(node: Any, schema: type, prefix: str) -> DictConfig:
    """:func:`check_schema`, memoised by the node's content (read-only result, shared):
    checking every job of a sweep repeats the same groups many times, and a structured merge
    costs ~10 ms."""
    if isinstance(node, DictConfig):
        try:
            node = OmegaConf.to_container(node, resolve=True)
        except OmegaConfBaseException as e:
            raise _field_error(prefix, e) from None
    try:
        key = (schema, prefix, json.dumps(node, sort_keys=True, default=repr))
    except (TypeError, ValueError):
        key = None
    hit = _SCHEMA_CACHE.get(key) if key is not None else None
    if hit is None:
        try:
            hit = _check_schema(node, schema, prefix)
            OmegaConf.set_readonly(hit, True)
        except ConfigError as e:
            hit = e
        if key is not None:
            if len(_SCHEMA_CACHE) > 4096:
                _SCHEMA_CACHE.clear()
            _SCHEMA_CACHE[key] = hit
    if isinstance(hit, ConfigError):
        raise ConfigError(str(hit))
    return hit


def _check_schema(node: Any, schema: type, prefix: str) -> DictConfig:
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
    groups = {p.name for d in CONF_DIRS if d.is_dir() for p in d.iterdir() if p.is_dir() and not p.name.startswith("_")}
    return {f.name for f in fields(RootSchema)} | {"task", "hydra"} | groups | set(GROUP_SCHEMAS)


def validate_config(cfg: DictConfig) -> None:
    """Check ``cfg`` (the composed config) before any work. Raises :class:`ConfigError`."""
    if not isinstance(cfg, DictConfig):
        cfg = OmegaConf.create(cfg)
    unknown = sorted(set(cfg.keys()) - known_root_keys())
    if unknown:
        raise ConfigError(f"unknown top-level key(s) {unknown}; known keys: {sorted(known_root_keys() - {'hydra'})}")
    root = {f.name: cfg[f.name] for f in fields(RootSchema) if f.name in cfg}
    r = _checked(root, RootSchema, "")
    if r.seed < 0:
        raise ConfigError(f"seed={r.seed} must be an integer >= 0")
    check_choice("device", str(r.device).split(":")[0], ("cpu", "cuda"))
    check_choice("dtype", r.dtype, ("float64", "float32"))
    ncpu = cpu_count()
    if r.threads is not None and not 1 <= r.threads <= ncpu:
        raise ConfigError(f"threads={r.threads} must be in 1..{ncpu} (this machine's CPU count), or null for torch's default")
    if r.max_memory_gb is not None:
        check_positive("max_memory_gb", r.max_memory_gb)
    if "task" not in cfg or cfg.task is None:
        raise ConfigError("task is missing; choose one with task=<name> or experiment=<study>")
    check_target(cfg.task.get("_target_"))
    if not isinstance(cfg.task.get("name"), str) or not cfg.task.name:
        raise ConfigError(f"task.name={cfg.task.get('name')!r} must be a non-empty string")
    check_engine_parts(cfg)
    if cfg.task.name in CORE_TASKS:
        validate_core(cfg)
    validate_task(cfg)
    if cfg.task.name in CORE_TASKS:
        check_memory(cfg, r.max_memory_gb)
        check_parts(cfg)


# ------------------------------------------------------------------------------------------------
# the kinds of filter and fusion part (the consensus and filter groups hold parts of more than one method)

#: the engine of the distributed-filter studies (their ``filter`` group's ``_target_``); task=matrix takes any method
DISTRIBUTED_FILTER = "dslearn.methods.distributed.DistributedFilter"
#: what a fusion part of each kind is, for the messages
FUSION_KINDS = {"information": "an information-form fusion of the distributed filter",
                "aggregation": "a GP aggregation rule of a fusion centre (Liu et al.'s DGPT)",
                "statistics": "a cooperation on sufficient statistics (Braga et al.'s RBPF + online EM)"}


def _target_class(target: str):
    """The class a ``_target_`` names (a ``Class.factory`` classmethod: its class); None if it cannot be imported."""
    from hydra.utils import get_object

    try:
        obj = get_object(str(target))
    except Exception:  # noqa: BLE001 - an import error is the builder's to report, naming the key
        return None
    return getattr(obj, "__self__", obj)


def fusion_kind(target: str) -> str | None:
    """The kind of the fusion part ``target`` builds: ``information`` (a :class:`dslearn.fusion.strategies.Fusion`),
    the kind the class declares (``kind``, e.g. ``aggregation``), or None where unknown."""
    from dslearn.fusion.strategies import Fusion

    cls = _target_class(target)
    if cls is None:
        return None
    if isinstance(cls, type) and issubclass(cls, Fusion):
        return "information"
    return getattr(cls, "kind", None)


def _kind_options(kind: str) -> list[str]:
    """The ``conf/consensus`` options (every config folder) whose part is of ``kind``."""
    names = []
    for d in CONF_DIRS:
        for p in sorted((Path(d) / "consensus").glob("*.yaml")):
            try:
                target = OmegaConf.load(p).get("_target_")
            except Exception:  # noqa: BLE001 - a broken option is reported where it is selected
                continue
            if target and fusion_kind(str(target)) == kind and p.stem not in names:
                names.append(p.stem)
    return names


def check_engine_parts(cfg: DictConfig) -> None:
    """The ``filter`` and ``consensus`` parts must be of the kinds the task takes: the distributed-filter
    studies run the distributed filter (``filter=default|ukf``), whose fusion is information-form;
    ``task=matrix`` takes any method as its filter part, with the kind of fusion part the method declares
    (``fusion_kind``; information-form where it declares none: Liu et al.'s DGPT takes an aggregation rule).
    ConfigError naming the option and the options of the kind that fits."""
    from dslearn.schemas.base import task_uses

    used = {u.split(".")[0] for u in task_uses(cfg)}
    task = str(cfg.task.name)
    matrix = task == "matrix"
    filt = cfg.get("filter")
    ftarget = str(filt.get("_target_")) if isinstance(filt, DictConfig) and filt.get("_target_") else None
    if "filter" in used and not matrix and ftarget is not None and ftarget != DISTRIBUTED_FILTER:
        raise ConfigError(f"filter._target_={ftarget} is a method of the comparison matrix (task=matrix); task={task} "
                          f"runs the distributed filter ({DISTRIBUTED_FILTER}): filter=default|ukf")
    cons = cfg.get("consensus")
    if "consensus" not in used or not isinstance(cons, DictConfig) or not cons.get("_target_"):
        return
    have = fusion_kind(str(cons._target_))
    if have is None:
        return
    want, who = "information", f"task={task}'s distributed filter"
    if matrix and ftarget is not None:
        cls = _target_class(ftarget)
        if cls is None:
            return
        want, who = getattr(cls, "fusion_kind", "information"), f"filter._target_={ftarget}"
    if have != want:
        name = cons.get("name") or cons._target_
        raise ConfigError(f"consensus={name} is {FUSION_KINDS.get(have, have)}; {who} takes "
                          f"{FUSION_KINDS.get(want, want)}: consensus={'|'.join(_kind_options(want))}")

def check_target(target) -> None:
    """ConfigError unless ``target`` (``task._target_``) is a registered study (:data:`TASK_TARGETS`)."""
    allowed = sorted(set(TASK_TARGETS.values()))
    if target not in allowed:
        raise ConfigError(
            f"task._target_={target!r} is not a registered study; choose one of {allowed} "
            f"(or pick a study with task=<name> / experiment=<study>)"
        )


def cpu_count() -> int:
    """CPUs this process may run on (the affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def machine_memory_bytes() -> int | None:
    """Physical memory, or the container's memory limit (cgroup v2/v1) where that is lower."""
    total = None
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, OSError, ValueError):
        pass
    for p in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            v = Path(p).read_text().strip()
        except OSError:
            continue
        if v.isdigit() and int(v) < (1 << 60):
            total = int(v) if total is None else min(total, int(v))
    return total


def memory_limit_gb(max_memory_gb: float | None) -> tuple[float, str]:
    """The guard's limit in GB and a phrase saying where it comes from."""
    if max_memory_gb is not None:
        return float(max_memory_gb), f"max_memory_gb={float(max_memory_gb):g}"
    total = machine_memory_bytes()
    if total is None:
        return 64.0, "the default max_memory_gb=64 (this machine's memory is unknown)"
    return MEMORY_SHARE * total / 1e9, f"{MEMORY_SHARE:.0%} of this machine's {total / 1e9:.1f} GB"


def estimate_core_memory(cfg: DictConfig) -> dict[str, float]:
    r"""Estimated peak memory in bytes of a core-study (Yu) run, by part (float64 = 8 bytes).

    * ``episodes``: the training and test episodes, all simulated at once: states
      ``(B, K+1, 4m)`` (and the stacked trajectory, twice), measurements and noise
      ``(S, B, K+1, m, 2)``;
    * ``tracking``: the test batch's stored means and information matrices and the
      covariances recovered from them for the metrics, ``5 x (S, B_test, K+1, 4m, 4m)``
      (measured: 2000 test episodes of the Yu scenario with ``model=lin`` peak 596 MB above
      the idle process, this term 666 MB);
    * ``gp``: the online GP of a learning model: per node a ``cap x cap`` Cholesky buffer
      (``cap`` = data points ``n = train_episodes x K`` rounded up to 128 rows, or the
      window / inducing / feature budget of a scalable variant), twice while the buffer
      grows, and the test predictions' kernel rows ``(S, B_test, n)``; a learned
      observation GP (``observation=gp``) adds its own (measured: 150 training + 50 test
      episodes of ``gp_increment`` peak 596 MB above the idle process, this term 776 MB);
    * ``adf`` (``filter=adf`` only): the GP-ADF's kept :math:`(K + \sigma^2 I)^{-1}` and data-only kernel
      factor, two ``cap x cap`` buffers per node (grown by half), and its per-query temporaries
      (:data:`dslearn.filters.adf.CHUNK_ELEMENTS` elements each, a few at a time);
    * ``particles`` (``filter=pf`` only): the particle clouds of one prediction of the test batch, the particles,
      their noise draws, means and predictive draws and the centred cloud, ``5 x (S, B_test, N, 4m)``, and the
      model's evaluation in chunks (:data:`dslearn.filters.particle.CHUNK_ELEMENTS` elements, a few at a time).

    ``K`` = horizon / dt steps, ``m`` agents, ``S`` nodes. The terms are upper-bound shaped;
    fixed costs (the Python process, torch: ~0.5 GB) are not included.
    """
    sc, nw, da = cfg.scenario, cfg.network, cfg.data
    t = cfg.task
    k = int(round(float(sc.horizon) / float(sc.dt)))
    m = len(sc.desired_velocities)
    d = 4 * m
    s = int(nw.num_sensors) + int(nw.num_comm)
    b_tr = int(t.get("train_episodes", da.train_episodes) if t.name == "yu_faults" else da.train_episodes)
    b_te = int(t.get("test_episodes", da.test_episodes) if t.name == "yu_faults" else da.test_episodes)
    f8 = 8.0
    per_ep = (k + 1) * (3 * d + 5 * s * m) * f8
    out = {"episodes": (b_tr + b_te) * per_ep, "tracking": 5.0 * s * b_te * (k + 1) * d * d * f8}
    mc = cfg.model
    kind = str(mc.get("kind", None) or mc.get("name", ""))
    learns_f = kind.startswith("gp")
    learns_h = str(cfg.observation.get("name", "linear")) == "gp"
    n = b_tr * k
    gp = 0.0
    if learns_f:
        variant = str(mc.get("variant", None) or "exact")
        budget = {"window": mc.get("window"), "sgpr": mc.get("inducing"), "ssgp": mc.get("features")}.get(variant)
        cap = min(n, int(budget)) if budget else n
        cap = 128 * math.ceil(max(cap, 1) / 128) + 256
        gp += s * (2.0 * cap * cap + 3 * cap * d) * f8 + s * b_te * n * f8 * 2
    if learns_h:
        cap = 128 * math.ceil(max(n, 1) / 128) + 256
        gp += s * (2.0 * cap * cap + 3 * cap * 2 * m) * f8 + s * b_te * n * f8 * 2
    out["gp"] = gp
    predict = cfg.filter.get("predict") if cfg.get("filter") is not None else None
    if learns_f and predict is not None and str(predict.get("_target_", "")).startswith("dslearn.filters.adf."):
        from dslearn.filters.adf import CHUNK_ELEMENTS  # filter=adf: its kept (K + s^2 I)^-1 and kernel factor,

        cap = 1.5 * n + 64  # (S, cap, cap) each, growing by half, and its per-query temporaries
        out["adf"] = s * 2.0 * cap * cap * f8 + 4.0 * min(CHUNK_ELEMENTS, s * max(b_te, 1) * n * n) * f8
    if predict is not None and str(predict.get("_target_", "")).startswith("dslearn.filters.particle."):
        from dslearn.filters.particle import CHUNK_ELEMENTS as PF_CHUNK  # filter=pf: the clouds and the chunks

        count = predict.get("particles", 500)
        if isinstance(count, int) and not isinstance(count, bool) and count > 0:  # else refused by its own check
            cloud = s * max(b_te, 1) * count * d
            out["particles"] = 5.0 * cloud * f8 + 4.0 * min(PF_CHUNK, cloud * max(n, 1)) * f8
    return out


def check_memory(cfg: DictConfig, max_memory_gb: float | None = None) -> None:
    """The resource guard: ConfigError when the estimated peak memory exceeds the limit."""
    est = estimate_core_memory(cfg)
    total = sum(est.values()) / 1e9
    limit, where = memory_limit_gb(max_memory_gb)
    if total > limit:
        sc, da = cfg.scenario, cfg.data
        part, big = max(est.items(), key=lambda kv: kv[1])
        steps = int(round(float(sc.horizon) / float(sc.dt)))
        raise ConfigError(
            f"estimated peak memory {total:.3g} GB exceeds the limit of {limit:.3g} GB ({where}); "
            f"largest part: {part} {big / 1e9:.3g} GB, from {len(sc.desired_velocities)} agents, "
            f"{int(cfg.network.num_sensors) + int(cfg.network.num_comm)} nodes, "
            f"{steps} steps (scenario.horizon/scenario.dt), data.train_episodes={da.train_episodes}, "
            f"data.test_episodes={da.test_episodes}; make the run smaller or raise the limit with +max_memory_gb=<GB>"
        )


def validate_core(cfg: DictConfig) -> None:
    """Schemas and ranges of the core (Yu) study's groups."""
    g = {name: _checked(cfg.get(name), schema, name) for name, schema in GROUP_SCHEMAS.items()}
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
    for k in ("tau", "alpha", "beta"):
        for j, v in enumerate(sc[k] if isinstance(sc[k], (list, tuple)) or hasattr(sc[k], "__len__") else [sc[k]]):
            check_positive(f"scenario.{k}" + (f"[{j}]" if hasattr(sc[k], "__len__") else ""), v, strict=k != "alpha")
    check_positive("scenario.process_std", sc.process_std, strict=False)
    check_positive("scenario.softening", sc.softening, strict=False)
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
        check_choice("model.noise", m.noise, ("latent", "predictive", "adaptive"))
    if m.noise_fading is not None and not 0.0 < m.noise_fading < 1.0:
        raise ConfigError(f"model.noise_fading={m.noise_fading!r} must be in (0, 1)")
    if m.jacobian is not None:
        check_choice("model.jacobian", m.jacobian, ("closed_form", "autograd"))
    if m.factor_dtype is not None:
        check_choice("model.factor_dtype", m.factor_dtype, ("float64", "float32"))
    if m.factor is not None:
        from dslearn.models.gp_backends.exact import FACTORS

        check_choice("model.factor", m.factor, FACTORS)
    if m.train_on is not None:
        check_choice("model.train_on", m.train_on, ("truth", "fused"))
        if m.train_on == "fused":
            raise ConfigError(f"model.train_on=fused is not available in task={cfg.task.name}: it trains offline models "
                              "on the true tracks of its training episodes (model.train_on=truth or null); the "
                              "network's CM-fused estimates are the real-data study's (task=ethucy_tracking)")
    # observation
    check_choice("observation.name", ob.name, ("linear", "gp"))
    if ob.noise_std is not None:  # null: the sensors' own (dslearn.compose.build_observation)
        check_positive("observation.noise_std", ob.noise_std)
    for k in ("outputscale", "lengthscale"):
        if ob[k] is not None:
            check_positive(f"observation.{k}", ob[k])
    if ob.name == "gp":
        for k in ("outputscale", "lengthscale", "mean", "noise"):
            if ob[k] is None:
                raise ConfigError(f"observation.{k} is null; observation=gp needs a value (see conf/observation/gp.yaml)")
        check_choice("observation.mean", ob.mean, ("zero", "constant", "identity"))
        check_choice("observation.noise", ob.noise, ("latent", "predictive"))
    # consensus
    from dslearn.fusion.strategies import FUSIONS, check_consensus
    from dslearn.fusion.weights import WEIGHT_METHODS

    check_choice("consensus.name", co.name, FUSIONS)
    check_choice("consensus.weights", co.weights, WEIGHT_METHODS)
    check_consensus(co.iterations, co.omega)
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
    min_train = da.min_train_episodes or 0
    if da.train_episodes < min_train:
        raise ConfigError(
            f"data.train_episodes={da.train_episodes} is too few for study {cfg.get('study')!r}: it needs >= {min_train}"
        )
    # filter
    check_positive("filter.prior_pos_std", fi.prior_pos_std)
    check_positive("filter.prior_vel_std", fi.prior_vel_std)
    if fi.learn_gate_std is not None:
        check_positive("filter.learn_gate_std", fi.learn_gate_std)


_PARTS_CACHE: dict[str, str | None] = {}
#: the groups the core study builds its parts from (the key of :func:`check_parts`' memo)
PART_GROUPS = ("scenario", "network", "model", "observation", "consensus", "filter")


def check_parts(cfg: DictConfig) -> None:
    """Build the core study's parts from ``cfg`` as the run does, so that every refusal of a
    constructor (which depends on the configuration only) happens in the start-up check.

    Built (:func:`_build_parts`, the study's slots): the scenario, the network (connectivity), the motion
    model (where the study takes the ``model`` slot; ``yu_faults`` composes ``task.models`` itself) and the
    observation model, on PyTorch's ``meta`` device (shapes only: no memory, whatever the buffer sizes), the
    fusion (where the study takes the ``fusion`` slot) and the filter's prediction step, checked against the
    scenario's state dimension (the UKF's ``kappa``) and, for a step that needs a kind of motion model
    (``check_model``: ``filter=adf``, ``filter=ukf_mm``), against the run's motion model (``task=yu``) or
    every model of ``task.models`` (``task=yu_faults``). The
    result is memoised by the groups' content (a sweep repeats the same parts). Raises the
    constructors' :class:`ConfigError`; any other exception (a constructor that cannot run on the
    ``meta`` device) is left to the run, which builds the parts for real.
    """
    import warnings

    nodes = {}
    for k in PART_GROUPS:
        node = cfg.get(k)
        try:
            nodes[k] = OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node
        except OmegaConfBaseException as e:
            raise _field_error(k, e) from None
    try:
        models = OmegaConf.to_container(cfg.task.models) if "models" in cfg.task else None  # task=yu_faults' grid
        key = json.dumps([str(cfg.task.name), str(cfg.get("dtype")), nodes, models], sort_keys=True, default=repr)
    except (TypeError, ValueError):
        key = None
    if key is None or key not in _PARTS_CACHE:
        err = None
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                _build_parts(cfg)
        except ConfigError as e:
            err = str(e)
        except Exception:  # noqa: BLE001 - not a configuration refusal: the run reports it
            err = None
        if key is None:
            if err is not None:
                raise ConfigError(err)
            return
        if len(_PARTS_CACHE) > 1024:
            _PARTS_CACHE.clear()
        _PARTS_CACHE[key] = err
    if _PARTS_CACHE[key] is not None:
        raise ConfigError(_PARTS_CACHE[key])


def _build_parts(cfg: DictConfig) -> None:
    """The parts :func:`check_parts` builds: the run's slots (:func:`dslearn.compose.study_slots`) on the meta
    device; the motion model and the fusion only where the study names them, a grid's models
    (``model_options``) only for a step that checks its motion model."""
    import torch

    from dslearn import compose as C

    takes = C.study_slots(cfg)[1]
    s = C._Slots(cfg, torch.device("meta"))
    scenario, network = s["scenario"], s["network"]
    model = s["model"] if "model" in takes else None
    if "fusion" in takes:
        s["fusion"]
    s["observation"]
    step = s["predict"]
    check = getattr(step, "check_state_dim", None)
    if check is not None:
        check(scenario.state_dim)
    check = getattr(step, "check_model", None)  # a step that needs a kind of motion model (filter=adf|ukf_mm)
    if check is None:
        return
    if model is not None:
        check(model, str(cfg.model.get("name", "")) or None)
    elif "model_options" in takes:  # task=yu_faults: every model of its grid
        for name, make in s["model_options"].items():
            check(make(scenario, network), name)


def _check_area(name: str, area) -> None:
    a = list(area)
    if len(a) == 4:
        check_finite(name, a)
    if len(a) != 4 or not (a[0] < a[1] and a[2] < a[3]):
        raise ConfigError(f"{name}={a!r} must be [xmin, xmax, ymin, ymax] with xmin < xmax and ymin < ymax")


def _check_pairs(name: str, value, kind) -> None:
    """A list of 2-element numeric lists (``kind`` int: integral values)."""
    for i, v in enumerate(value):
        if not hasattr(v, "__len__") or isinstance(v, str) or len(v) != 2:
            raise ConfigError(f"{name}[{i}]={v!r} must be a pair [a, b]")
        for x in v:
            if isinstance(x, bool) or not isinstance(x, (int, float)) or x != x or x in (float("inf"), float("-inf")) \
                    or (kind is int and float(x) != int(x)):
                raise ConfigError(f"{name}[{i}]={list(v)!r} must hold two finite {'integers' if kind is int else 'numbers'}")

