"""Nothing dropped at any depth: a key set inside a root group that the chosen part does not read is refused up
front, naming the key and why (:func:`dslearn.schemas.base.unread_keys`, from the start-up check
:func:`dslearn.app.precheck.precheck`); a key the part reads is accepted.

Every part x every key of its group: the options of each group (``conf/<group>/*.yaml``) and the keys under each
option's node are enumerated from the configs, in the tasks that build the group's option as that part (``yu``,
``matrix``, ``yu_faults``, ``ethucy_tracking``), and every task's own keys; each key is overridden with a
different value and the start-up check's part-key stage (:func:`dslearn.schemas.base.check_overrides`, what
:func:`dslearn.app.composer.validate_job` calls for each job) either accepts it or refuses it naming the key. The
refusals must be exactly :data:`REFUSED` (written from the parts: what each reads). A composition per option, not
per key, keeps this fast; a sample of every group goes through :func:`dslearn.app.precheck.precheck` itself, and
each example of issue 32 is checked one by one with its exact message.
"""

from __future__ import annotations

import copy
import functools

import pytest
from omegaconf import DictConfig, ListConfig, OmegaConf

import dslearn.schemas  # noqa: F401  (registers the task schemas the configs name)
from dslearn.conf_paths import CONF_DIR
from dslearn.app.job import _describe
from dslearn.app.options import override_keys
from dslearn.app.precheck import precheck
from dslearn.schemas import base as schema_base
from dslearn.schemas.base import check_overrides
from dslearn.schemas.core import check_engine_parts

#: keys of a part's node that name or build it (not settings)
PART_KEYS = ("_target_", "_partial_", "name")
#: the root groups each task builds as the part its option names (from dslearn/studies/<task>.py and the slots of
#: dslearn/compose.py): yu_faults' network links serve its own fusions (task.fusions), ethucy_tracking's consensus its
#: CM-fused tracks too (every key read)
PARTS = {"yu": ("scenario", "network", "model", "observation", "consensus", "filter"),
         "yu_faults": ("scenario", "observation", "filter"),
         "ethucy_tracking": ("filter", "observation", "model"),
         "matrix": ("scenario", "network", "model", "observation", "consensus", "filter", "learner", "associator")}


def unread_keys(cfg, group):
    """:func:`dslearn.schemas.base.unread_keys` (none where the tree has no part declarations)."""
    fn = getattr(schema_base, "unread_keys", None)
    return {} if fn is None else fn(cfg, group)

#: the matrix cells a group's option is tried in, first that reads it (a method preset, a scenario it fits)
MATRIX_BASES = (("ekf_gp_hybrid", "yu_two_agents"), ("dgpt_rbcm", "liu_s1"), ("rbpf_em", "braga"), ("fg_ekf", "jiang"),
                ("rbpf_em_lin", "yu_two_agents"))
#: the scenario of the matrix that each base method fits (scenario options: their cell)
SCENARIO_BASE = {"yu_two_agents": "ekf_gp_hybrid", "corridor": "ekf_gp_hybrid", "eth_zara1": "ekf_gp_hybrid",
                 "liu_s1": "dgpt_rbcm", "liu_s2": "dgpt_rbcm", "liu_s3": "dgpt_rbcm", "braga": "rbpf_em",
                 "jiang": "fg_ekf"}
#: the scenarios of Liu's own study (task=liu_dgpt reads them as its task.scenarios; no part here)
LIU_OWN = ("s1", "s2", "s3")
#: the context of each task whose parts are root groups
CONTEXTS = {"yu": ["task=yu"], "yu_faults": ["experiment=yu_faults"], "ethucy_tracking": ["experiment=real_tables"]}

#: (context, group option, key) refused; everything else enumerated is accepted. Written from the parts (what each
#: reads): the fusions without rounds read no iterations / weights / omega (individual, centralized), CI and CE no
#: omega; the distributed filter's learning gate only where something learns online (not with LIN, the social force,
#: the LSTMs, nor with learner=none | offline and the GP); the GP's refit settings only where it learns online and
#: refits (every GP option has fit_every=0), its noise fading only with noise=adaptive; Liu's Newton settings under
#: Adam; the links (network.edges) with a fusion that uses none. (learner=backprop refuses a model_lr without
#: learn: [model] itself, at construction: tests/test_backprop_models.py.) A key of another group counts where the option
#: makes it unread (against the same context without the option).
_GP = ("gp", "gp_adaptive", "gp_cv", "gp_increment", "gp_increment_rbcm", "gp_rbcm", "gp_sgpr", "gp_ssgp", "gp_window")
_NO_ONLINE = ("lin", "cv_damped", "sfm", "sfm_fit", "lstm", "social_lstm")


def _refused_table() -> set[tuple[str, str, str]]:
    out = set()
    for ctx in ("yu", "matrix"):
        for opt in ("individual", "centralized"):  # and the links they do not use
            out |= {(ctx, f"consensus={opt}", k) for k in
                    ("consensus.iterations", "consensus.weights", "consensus.omega", "network.edges")}
        out |= {(ctx, f"consensus={o}", "consensus.omega") for o in ("ci", "ce")}
        out |= {(ctx, f"model={m}", "filter.learn_gate_std") for m in _NO_ONLINE}
    for ctx in ("yu", "matrix", "ethucy_tracking"):
        for m in _GP:
            out |= {(ctx, f"model={m}", f"model.{k}") for k in ("fit_iters", "fit_lr")}
            if m != "gp_adaptive":
                out.add((ctx, f"model={m}", "model.noise_fading"))
    for opt in ("none", "offline"):
        out |= {("matrix", f"learner={opt}", k) for k in ("filter.learn_gate_std", "model.fit_every")}
    out |= {("matrix", "learner=online_hyperparameters", f"learner.hyper.{k}") for k in ("tol", "max_iters")}
    return out


REFUSED = _refused_table()


@pytest.fixture
def hydra_ctx():  # per test: precheck initialises Hydra itself (the compositions below are cached across tests)
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        yield


@functools.lru_cache(maxsize=None)
def _compose(lines: tuple[str, ...]) -> DictConfig:
    from hydra import compose

    return compose("config", overrides=list(lines))


@functools.lru_cache(maxsize=None)
def _option_node(group: str, option: str) -> DictConfig:
    """The node of ``conf/<group>/<option>.yaml`` with its defaults list (options of the same group) merged in its
    order, as Hydra composes ``group=option`` (without a composition per option: this module checks many)."""
    node = OmegaConf.load(CONF_DIR / group / f"{option}.yaml")
    defaults = list(node.pop("defaults", None) or [])
    if "_self_" not in defaults:
        defaults.append("_self_")
    parts = []
    for d in defaults:
        if d == "_self_":
            parts.append(node)
        elif isinstance(d, str):
            parts.append(_option_node(group, d))
        else:  # {/other_group@key: option}: that group's option at key
            (where, opt), = d.items()
            other, _, key = str(where).lstrip("/").partition("@")
            parts.append(OmegaConf.create({key: _option_node(other, str(opt))}))
    return OmegaConf.merge(*parts)


def _with(base: tuple[str, ...], group: str, option: str) -> DictConfig:
    """The configuration of ``base`` with ``group=option``: the option's node put into a copy of the base
    composition (every option here changes only its own group)."""
    cfg = copy.deepcopy(_compose(base))
    OmegaConf.set_struct(cfg, False)
    cfg[group] = copy.deepcopy(_option_node(group, option))
    OmegaConf.set_struct(cfg, True)
    return cfg


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


def _leaves(node, prefix: str):
    """``(dotted key, raw value)`` of every leaf under ``node`` (a part's own name / target keys left out; a nested
    mapping's leaves, and the mapping itself where it is empty)."""
    for k in node.keys():
        if k in PART_KEYS:
            continue
        raw = node._get_node(k)
        key = f"{prefix}.{k}"
        if isinstance(raw, DictConfig) and not raw._is_none() and len(raw):
            yield from _leaves(raw, key)
        else:
            yield key, (OmegaConf.to_container(raw, resolve=False) if isinstance(raw, (DictConfig, ListConfig))
                        else raw._value())


def _different(v):
    """A different value of the same type (strings, lists, null and interpolations as they are: the verdict on a key
    depends on the other keys, not on its own value)."""
    if isinstance(v, bool):
        return not v
    if isinstance(v, int):
        return v + 1
    if isinstance(v, float):
        return v * 2 if v else 1.0
    return v


def _line(key: str, v) -> str:
    if isinstance(v, bool):
        return f"{key}={str(v).lower()}"
    if v is None:
        return f"{key}=null"
    return f"{key}={v}"


def _verdict(cfg: DictConfig, key: str, value) -> str | None:
    """The start-up check's part-key stage on ``cfg`` for the line ``key=value``: the error or None (the verdict on a
    key depends on the other keys of the configuration, not on its own value: ``cfg`` is not changed)."""
    try:
        check_overrides(cfg, [(key, _line(key, value))])
    except Exception as e:  # noqa: BLE001 - the refusal
        return str(e)
    return None


def _reads_group(cfg: DictConfig, group: str, option: str) -> bool:
    try:
        check_overrides(cfg, [(group, f"{group}={option}")])
        check_engine_parts(cfg)
    except Exception:  # noqa: BLE001 - this task / engine does not take the option
        return False
    if group == "learner":  # the engine's own learners only
        from hydra.utils import get_object

        takes = getattr(get_object(str(cfg.filter._target_)), "learners", None)
        return takes is None or option in takes
    return True


@functools.lru_cache(maxsize=None)
def _cases():
    """``(context, 'group=option', cfg, base cfg)`` of every option of every part group, in each task that builds it
    as that part (the matrix: in the first cell that takes it)."""
    out = []
    for ctx, lines in CONTEXTS.items():
        for group in PARTS[ctx]:
            for opt in _options(group):
                if group == "scenario" and opt in LIU_OWN:
                    continue
                cfg = _with(tuple(lines), group, opt)
                if _reads_group(cfg, group, opt):
                    out.append((ctx, f"{group}={opt}", cfg, _compose(tuple(lines))))
    for group in PARTS["matrix"]:
        for opt in _options(group):
            bases = ([(SCENARIO_BASE[opt], opt)] if opt in SCENARIO_BASE else []) if group == "scenario" else MATRIX_BASES
            for method, scenario in bases:
                lines = ("task=matrix", f"method={method}", f"scenario={scenario}")
                cfg = _with(lines, group, opt)
                if _reads_group(cfg, group, opt):
                    out.append(("matrix", f"{group}={opt}", cfg, _compose(lines)))
                    break
    return out


def _refusals():
    """``{(context, option, key): message}``: each key of the option's group through the start-up check's part-key
    stage, and each key of the task's other part groups that the option makes unread (:func:`unread_keys`, against
    the context without the option)."""
    refused, seen = {}, 0
    for ctx, option, cfg, base in _cases():
        group = option.split("=")[0]
        for key, v in _leaves(cfg[group], group):
            seen += 1
            err = _verdict(cfg, key, _different(v))
            if err is not None:
                refused[(ctx, option, key)] = err
        for other in PARTS[ctx]:
            if other != group:
                before = unread_keys(base, other)
                for key, (who, why) in unread_keys(cfg, other).items():
                    if key not in before:
                        refused[(ctx, option, key)] = f"{key} is not used by {who} ({why})"
    return refused, seen


def test_every_part_and_key(hydra_ctx):
    """Each option of each part group, each key under it: accepted, or refused naming the key and the part; the
    refusals are exactly :data:`REFUSED`. Every option of every group is covered in some task."""
    refused, seen = _refusals()
    for (ctx, option, key), err in refused.items():
        assert err.startswith(f"{key} is not used by "), err
        if key.startswith(option.split("=")[0] + "."):
            assert f"; remove {key}=" in err, err
    covered = {option for _, option, _, _ in _cases()}
    missing = {f"{g}={o}" for g in ("consensus", "filter", "learner", "model", "network", "observation", "scenario")
               for o in _options(g)} - covered - {f"scenario={s}" for s in LIU_OWN}
    assert not missing, f"options no task builds here: {sorted(missing)}"
    assert seen > 1000
    assert set(refused) == REFUSED, (f"refused but not expected: {sorted(set(refused) - REFUSED)}; "
                                     f"expected but accepted: {sorted(REFUSED - set(refused))}")


def test_parts_declared_by_tasks():
    """What each task declares it builds as parts (``parts=`` of its registration) is :data:`PARTS`, and no other
    task builds a root group's option as a part."""
    from dslearn.schemas.base import TASKS

    assert {name: tuple(spec.parts) for name, spec in TASKS.items() if spec.parts} == PARTS


def test_declared_keys_exist(hydra_ctx):
    """What a part declares it does not read are keys of its node (a declaration naming no key is a typo)."""
    for ctx, option, cfg, _ in _cases():
        group = option.split("=")[0]
        keys = {k for k, _ in _leaves(cfg[group], group)} | {f"{group}.{k}" for k in cfg[group].keys()}
        for k in unread_keys(cfg, group):
            assert k in keys, (ctx, option, k)


#: every task's own keys: (context, key) refused with its default configuration (each task's ``unused``)
TASK_REFUSED = {("liu_dgpt", "task.hyper.tol"), ("liu_dgpt", "task.hyper.max_iters"),
                *{("ethucy_tracking", f"task.{k}") for k in ("data_sizes", "seeds", "synthetic")},
                *{("ethucy_tracking/data_size", f"task.{k}") for k in ("train_episodes", "plot_episodes")}}
TASK_CONTEXTS = {"yu": ["task=yu"], "yu_faults": ["experiment=yu_faults"], "liu_dgpt": ["experiment=liu_table1"],
                 "jiang_fg": ["experiment=jiang_fg"], "braga_tbn": ["experiment=braga_tbn"],
                 "ethucy_forecast": ["experiment=ethucy_forecast"], "ethucy_tracking": ["experiment=real_tables"],
                 "ethucy_tracking/data_size": ["experiment=gp_vs_lstm"], "matrix": ["task=matrix"], "gp_bayes_filters": ["experiment=gp_bayes_filters"]}


def test_every_task_key(hydra_ctx):
    """Each task's own keys (its branches): accepted, or refused naming the key; exactly :data:`TASK_REFUSED`."""
    refused = set()
    for ctx, lines in TASK_CONTEXTS.items():
        cfg = _compose(tuple(lines))
        for key, v in _leaves(cfg.task, "task"):
            err = _verdict(cfg, key, _different(v))
            if err is None:
                continue
            assert " is not used by task=" in err and f"; remove {key}=" in err, err
            refused.add((ctx, key))
    assert refused == TASK_REFUSED


# ------------------------------------------------------------------------------------------ through precheck
#: (command line, the exact message): the examples of issue 32, each refused before any job
EXAMPLES = [
    (["consensus=individual", "consensus.iterations=8"],
     "consensus.iterations is not used by consensus=individual (each node alone: no consensus rounds); "
     "remove consensus.iterations=8"),
    (["consensus=individual", "consensus.weights=metropolis"],
     "consensus.weights is not used by consensus=individual (each node alone: no consensus rounds); "
     "remove consensus.weights=metropolis"),
    (["consensus=centralized", "consensus.iterations=8"],
     "consensus.iterations is not used by consensus=centralized (a fusion centre: no consensus rounds); "
     "remove consensus.iterations=8"),
    (["task=matrix", "method=ekf_lin_centralized", "consensus.omega=nodes"],
     "consensus.omega is not used by consensus=centralized (a fusion centre: no consensus rounds); "
     "remove consensus.omega=nodes"),
    (["consensus=ci", "consensus.omega=nodes"],
     "consensus.omega is not used by consensus=ci (omega weighs the novel information of consensus=hybrid|cm only); "
     "remove consensus.omega=nodes"),
    (["-m", "consensus=individual", "consensus.iterations=2,8"],
     "consensus.iterations is not used by consensus=individual (each node alone: no consensus rounds); "
     "remove consensus.iterations=2 (sweep job 0: consensus=individual consensus.iterations=2)"),
    (["task=matrix", "method=ekf_gp_hybrid", "learner=none", "filter.learn_gate_std=1.0"],
     "filter.learn_gate_std is not used by the distributed filter (with learner=none nothing learns online: the "
     "learning gate only keeps estimates out of the data sets learned online); remove filter.learn_gate_std=1.0"),
    (["model=lin", "filter.learn_gate_std=1.0"],
     "filter.learn_gate_std is not used by the distributed filter (with model=lin and observation=linear nothing "
     "learns online: the learning gate only keeps estimates out of the data sets learned online); "
     "remove filter.learn_gate_std=1.0"),
    (["task=matrix", "method=ekf_lin_hybrid", "filter.learn_gate_std=1.0"],
     "filter.learn_gate_std is not used by the distributed filter (with learner=none nothing learns online: the "
     "learning gate only keeps estimates out of the data sets learned online); remove filter.learn_gate_std=1.0"),
    (["task=matrix", "method=ekf_gp_hybrid", "learner=none", "model.fit_every=2"],
     "model.fit_every is not used by model=gp_increment (with learner=none the motion model learns nothing online: "
     "the GP gathers no data and stays its prior); remove model.fit_every=2"),
    (["network=yu_blind", "consensus=individual", "network.comm_radius=3.0"],
     "network.comm_radius is not used by consensus=individual (each node alone: no consensus rounds; no links between "
     "nodes are used); remove network.comm_radius=3.0"),
    (["network.edges=[[0,1],[1,2],[2,3],[3,4],[4,5],[5,6],[6,7],[7,8],[8,9]]", "network.comm_radius=3.0"],
     "network.comm_radius is not used by the network part (network.edges gives the links); "
     "remove network.comm_radius=3.0"),
    (["task=matrix", "method=dgpt_rbcm", "scenario=liu_s1", "learner.hyper.tol=1e-3"],
     "learner.hyper.tol is not used by learner=online_hyperparameters (learner.hyper.optimizer=adam takes "
     "learner.hyper.iters steps of size learner.hyper.lr; no Newton solve); remove learner.hyper.tol=1e-3"),
    (["task=matrix", "method=dgpt_rbcm", "scenario=liu_s1", "learner.hyper.optimizer=newton", "learner.hyper.lr=0.2"],
     "learner.hyper.lr is not used by learner=online_hyperparameters (learner.hyper.optimizer=newton solves each "
     "problem to learner.hyper.tol; no fixed steps); remove learner.hyper.lr=0.2"),
    (["experiment=liu_table1", "task.hyper.max_iters=20"],
     "task.hyper.max_iters is not used by task=liu_dgpt (task.hyper.optimizer=adam takes task.hyper.iters steps of "
     "size task.hyper.lr; no Newton solve); remove task.hyper.max_iters=20"),
    (["experiment=ethucy_forecast", "task.predictors=[cv,gp]", "task.lstm.epochs=3"],
     "task.lstm is not used by task=ethucy_forecast with task.predictors=['cv', 'gp'] (no lstm or social_lstm); "
     "remove task.lstm.epochs=3"),
    (["task=matrix", "method=ekf_sfm_hybrid_backprop", "learner=none"],
     "method=ekf_sfm_hybrid_backprop sets learner.learn; learner=none takes no learn: remove learner=none (the "
     "preset's learner=backprop), or choose the parts without the preset: filter=default model=sfm "
     "observation=linear consensus=hybrid learner=none"),
    # the same in a matrix sweep (the sweeper chooses the cells first: refused there, before any job)
    (["-m", "task=matrix", "hydra/sweeper=matrix", "method=ekf_lin_hybrid,ekf_sfm_hybrid_backprop",
      "scenario=yu_two_agents", "learner=none"],
     "method=ekf_sfm_hybrid_backprop sets learner.learn; learner=none takes no learn: remove learner=none (the "
     "preset's learner=backprop), or choose the parts without the preset: filter=default model=sfm "
     "observation=linear consensus=hybrid learner=none"),
]


@pytest.mark.parametrize("argv,msg", EXAMPLES, ids=[" ".join(a) for a, _ in EXAMPLES])
def test_example(argv, msg, tmp_path):
    d = "hydra.sweep.dir" if "-m" in argv else "hydra.run.dir"
    assert precheck([*argv, f"{d}={tmp_path / 'out'}"]) == msg


#: keys each part reads: accepted by the whole start-up check
ACCEPTED = [
    ["consensus=ci", "consensus.iterations=8", "consensus.weights=metropolis"],
    ["consensus=hybrid_nodes", "consensus.omega=2.0"],
    ["consensus=individual", "network.comm_radius=5.0"],  # random positions: the radius decides which draw is connected
    ["filter.learn_gate_std=1.0"],
    ["model.fit_every=2", "model.fit_iters=3"],
    ["task=matrix", "method=ekf_gp_hybrid", "model.fit_every=2", "filter.learn_gate_std=1.0"],
    ["task=matrix", "method=dgpt_rbcm", "scenario=liu_s1", "learner.hyper.optimizer=newton", "learner.hyper.tol=1e-4"],
    ["task=matrix", "method=ekf_sfm_hybrid_backprop", "learner.model_lr=0.01"],
    ["task=matrix", "method=ekf_sfm_hybrid_backprop", "learner=backprop"],
    ["task=matrix", "method=ekf_lin_hybrid", "consensus=ci"],
    ["experiment=ethucy_forecast", "task.predictors=[cv,lstm]", "task.lstm.epochs=3"],
]


@pytest.mark.parametrize("argv", ACCEPTED, ids=[" ".join(a) for a in ACCEPTED])
def test_read_keys_accepted(argv, tmp_path):
    assert precheck([*argv, f"hydra.run.dir={tmp_path / 'out'}"]) is None


def test_preset_part_replaced_in_first_line(hydra_ctx):
    """A preset's part replaced on the command line is said in the run's first line (``run: starting ...``)."""
    cfg = _compose(("task=matrix", "method=ekf_lin_hybrid", "consensus=ci"))
    line = _describe(cfg, {"overrides": ["task=matrix", "method=ekf_lin_hybrid", "consensus=ci"]})
    assert line == ("task=matrix, study=default, seed=0, overrides: task=matrix method=ekf_lin_hybrid consensus=ci, "
                    "method=ekf_lin_hybrid with consensus=ci in place of its consensus=hybrid")
    plain = _describe(cfg, {"overrides": ["task=matrix", "method=ekf_lin_hybrid", "consensus=hybrid"]})
    assert plain == "task=matrix, study=default, seed=0, overrides: task=matrix method=ekf_lin_hybrid consensus=hybrid"


def test_override_keys_of_sweep_lines():
    """The part-key check sees each job's own lines (what :func:`dslearn.app.composer.validate_job` passes)."""
    assert override_keys(["consensus.iterations=2", "hydra.run.dir=x", "consensus=ci"]) == [
        ("consensus.iterations", "consensus.iterations=2"), ("consensus", "consensus=ci")]
