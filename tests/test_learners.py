"""The ``learner`` root group of the matrix (``conf/learner``): what a method's parts learn. ``learner=none`` leaves
a GP motion model at its prior (the numbers of a GP that saw no training episode, not those of the online GP);
``learner: null`` is the engine's natural learner (the same numbers and row label as the explicit one); an engine
refuses a learner it cannot use at composition, in one line naming it and the allowed ones (exit 2 through
``dslearn-run``; in a sweep: a configuration error, never an n/a cell); every other task refuses an override of
the group; the YAML files hold the dataclasses' defaults."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from omegaconf import OmegaConf

from dslearn import api
from dslearn.compose import build, build_study
from dslearn.conf_paths import CONF_DIR
from dslearn.errors import ConfigError
from dslearn.learning import learners as L
from dslearn.app.precheck import precheck
from dslearn.schemas.base import TASKS
from test_task_groups import _cli  # dslearn-run in process: (exit code, stderr lines)

OPTIONS = sorted(p.stem for p in (CONF_DIR / "learner").glob("*.yaml"))


def _run(*overrides) -> tuple[str, torch.Tensor]:
    """One small cell on yu_two_agents (1 test episode): its row label and its rmse per node."""
    cfg = api.compose("task=matrix", "scenario=yu_two_agents", "task.test_episodes=1", *overrides)
    df = build_study(cfg).run()
    labels = set(df["method"])
    assert len(labels) == 1
    rmse = df[df["metric"] == "rmse"].sort_values("node")["value"].to_numpy()
    return labels.pop(), torch.tensor(rmse, dtype=torch.float64)


# ------------------------------------------------------------------------------------- the YAML files
def test_options_and_yaml_defaults_equal_the_dataclass_defaults(make_cfg):
    assert OPTIONS == sorted(L.LEARNERS) == sorted(["backprop", "calibrate", "fg_identification", "none", "offline",
                                                    "online", "online_em", "online_em_sensor",
                                                    "online_hyperparameters"])
    for name in OPTIONS:
        node = make_cfg("task=matrix", f"learner={name}").learner  # composed only (the default engine takes few)
        cls = L.LEARNERS[name]
        assert node._target_ == f"{cls.__module__}.{cls.__name__}" and cls.name == name
        # every setting in the file, nothing else; and the file's values are the defaults
        assert set(node) - {"_target_"} == {f.name for f in dataclasses.fields(cls)}, name
        assert build(node, "learner") == cls(), name
    # the moved blocks: no longer keys of the engines
    for filt, keys in {"rbpf_em": ("em", "modes"), "rbpf_em_lin": ("em", "modes"), "dgpt": ("hyper",), "fg_ekf": ("fg", "iterations")}.items():
        f = make_cfg(f"filter={filt}").filter
        assert not set(keys) & set(f), filt


def test_learner_settings_are_checked_at_construction():
    cases = [
        (lambda: L.OnlineEM(em={"burn_in": -1}), "learner.em.burn_in=-1 must be an integer >= 0"),
        (lambda: L.OnlineEM(em={"eta_exponent": 0.5}), "learner.em.eta_exponent=0.5 must be > 0.5 and <= 1"),
        (lambda: L.OnlineEM(em={"lr": 1}), "learner.em: unknown key(s) ['lr']"),
        (lambda: L.OnlineEM(modes={"sigma_init": [5.0, -1.0]}), "learner.modes"),
        (lambda: L.OnlineHyperparameters(hyper={"lr": 0.0}), "learner.hyper.lr"),
        (lambda: L.OnlineHyperparameters(hyper={"init_noise": 1e9}), "learner.hyper.init_noise=1000000000.0 must lie "
                                                                     "in [learner.hyper.min_noise, learner.hyper.max_noise]"),
        (lambda: L.OnlineHyperparameters(hyper={"optimizer": "lbfgs"}), "learner.hyper.optimizer"),
        (lambda: L.FactorGraphIdentification(iterations=0), "learner.iterations=0 must be an integer >= 1"),
        (lambda: L.FactorGraphIdentification(fg={"damping": 1.0}), "learner.fg.damping=1.0 must be >= 0 and < 1"),
        (lambda: L.FactorGraphIdentification(fg={"init_guess": [1.0]}), "learner.fg.init_guess=[1.0] must be a list of 2"),
        (lambda: L.FactorGraphIdentification(fg={"schedule": "random"}), "learner.fg.schedule"),
    ]
    for make, needle in cases:
        with pytest.raises(ConfigError) as e:
            make()
        assert needle in str(e.value) and "\n" not in str(e.value), (needle, str(e.value))
    # a partial block keeps the other defaults
    assert L.OnlineEM(em={"burn_in": 3}).em == {**L.EM_DEFAULTS, "burn_in": 3}
    assert L.FactorGraphIdentification(fg={"damping": 0.5}).fg["schedule"] == "flooding"


# ----------------------------------------------------------------------------- what each learner does
def test_learner_none_leaves_the_gp_at_its_prior():
    """With two training episodes, learner=none gives the numbers of the online GP that saw none (its prior mean)
    bit for bit, and not those of the online GP that learned from them; its row says so."""
    online_label, online = _run("method=ekf_gp_hybrid", "task.train_episodes=2")
    none_label, none = _run("method=ekf_gp_hybrid", "learner=none", "task.train_episodes=2")
    _, prior = _run("method=ekf_gp_hybrid", "task.train_episodes=0")
    assert online_label == "ekf gp_increment hybrid" and none_label == "ekf gp_increment hybrid learner=none"
    assert torch.equal(none, prior)
    assert (none - online).abs().max() > 1e-6
    assert bool(torch.isfinite(online).all()) and len(online) == len(none) > 0


def test_null_learner_is_the_natural_one():
    """learner: null (no preset: the root's parts) = the explicit natural learner: the same row, the same numbers."""
    assert api.compose("task=matrix").get("learner") is None
    a = _run("task.train_episodes=1")  # filter=default, model=gp_increment, observation=linear, consensus=hybrid
    b = _run("learner=online", "task.train_episodes=1")
    assert a[0] == b[0] == "ekf gp_increment hybrid" and torch.equal(a[1], b[1])
    a = _run("model=lin", "task.train_episodes=1")
    b = _run("model=lin", "learner=none", "task.train_episodes=1")
    assert a[0] == b[0] == "ekf lin hybrid" and torch.equal(a[1], b[1])


@pytest.mark.parametrize("filt,scenario,cls", [("fg_ekf", "jiang", L.FactorGraphIdentification),
                                               ("rbpf_em", "braga", L.OnlineEM),
                                               ("dgpt", "liu_s1", L.OnlineHyperparameters)])
def test_paper_engines_take_their_own_learner_by_default(filt, scenario, cls):
    """Without a learner each paper's engine takes its own with the file's values; a changed setting reaches it."""
    from dslearn.compose import build_cell_parts

    fusion = {"fg_ekf": [], "rbpf_em": ["consensus=statistics"], "dgpt": ["consensus=rbcm"]}[filt]
    base = ["task=matrix", f"filter={filt}", f"scenario={scenario}", *fusion]
    _, _, null = build_cell_parts(api.compose(*base), check_only=True)
    own = cls.name
    _, _, explicit = build_cell_parts(api.compose(*base, f"learner={own}"), check_only=True)
    assert type(null.learner) is cls and null.learner == explicit.learner == cls()
    assert null.label == explicit.label and "learner=" not in null.label
    key = {"fg_ekf": "learner.iterations=4", "rbpf_em": "learner.em.burn_in=7", "dgpt": "learner.hyper.iters=5"}[filt]
    _, _, changed = build_cell_parts(api.compose(*base, f"learner={own}", key), check_only=True)
    got = {"fg_ekf": lambda m: m.iterations, "rbpf_em": lambda m: m.em["burn_in"], "dgpt": lambda m: m.hyper.iters}
    assert got[filt](changed) == int(key.split("=")[1]) != got[filt](null)


# ------------------------------------------------------------------------------------------- refusals
REFUSALS = [
    (["method=ekf_lin_hybrid", "learner=online"], "learner=online: model lin learns nothing online",
     "allowed: learner=none|backprop|calibrate"),
    (["method=ekf_gp_hybrid", "learner=offline"], "learner=offline: model gp_increment has no offline fit",
     "allowed: learner=online|none|backprop|calibrate"),
    (["method=ekf_lstm_hybrid", "learner=none"], "learner=none: model lstm has no weights until trained offline",
     "allowed: learner=offline|backprop|calibrate"),
    (["method=ekf_social_lstm_hybrid", "learner=online"], "learner=online: model social_lstm has no weights",
     "allowed: learner=offline|backprop|calibrate"),
    (["method=ekf_gp_hybrid", "learner=online_em"], "learner=online_em: the distributed filter",
     "allowed: learner=online|none|backprop|calibrate"),
    (["method=ekf_gp_hybrid", "model=gp_sgpr", "learner=offline"],
     "learner=offline: model gp_sgpr has no offline fit", "allowed: learner=online|none|calibrate"),
    (["method=dgpt_rbcm", "scenario=liu_s1", "learner=online"], "learner=online: Liu's DGPT",
     "allowed: learner=online_hyperparameters"),
    (["method=fg_ekf", "scenario=jiang", "learner=none"], "learner=none: Jiang's EKF-FG",
     "allowed: learner=fg_identification"),
    (["method=rbpf_em", "scenario=braga", "learner=fg_identification"], "learner=fg_identification: Braga",
     "allowed: learner=online_em"),
]


@pytest.mark.parametrize("overrides,needle,allowed", REFUSALS, ids=[" ".join(o) for o, _, _ in REFUSALS])
def test_engines_refuse_a_learner_they_cannot_use(overrides, needle, allowed):
    with pytest.raises(L.LearnerRefused) as e:
        api.compose("task=matrix", *overrides)
    msg = str(e.value)
    assert msg.startswith(needle) and msg.endswith(allowed) and "\n" not in msg, msg


def test_dslearn_run_exits_2_with_one_line(tmp_path):
    code, lines = _cli(["task=matrix", "method=ekf_lin_hybrid", "learner=online", f"hydra.run.dir={tmp_path / 'r'}"])
    assert code == 2 and lines == ["dslearn-run: configuration error: learner=online: model lin learns nothing "
                                   "online, nor does the observation model; allowed: learner=none|backprop|calibrate"], lines
    assert not (tmp_path / "r").exists()


def test_a_sweep_treats_a_refused_learner_as_a_configuration_error(tmp_path):
    """The matrix sweeper does not turn a refused learner into n/a cells (not even beside scenarios the method does
    not fit): the up-front check refuses the sweep before any job, naming the learner."""
    from dslearn.schemas.matrix import select_cells

    combos = [["method=ekf_lin_hybrid", "learner=online", f"scenario={s}"] for s in ("yu_two_agents", "jiang")]
    with pytest.raises(L.LearnerRefused, match="learner=online: model lin learns nothing online"):
        select_cells(combos, lambda lines: api.compose("task=matrix", *lines))
    err = precheck(["-m", "task=matrix", "hydra/sweeper=matrix", "method=ekf_lin_hybrid,ekf_gp_hybrid",
                    "learner=none,online", "scenario=yu_two_agents", f"hydra.sweep.dir={tmp_path / 's'}"])
    assert err is not None and err.startswith("learner=online: model lin learns nothing online"), err
    assert not (tmp_path / "s").exists()
    # learners the engines take: every combination is a job
    kept, _ = select_cells([["method=ekf_gp_hybrid", f"learner={n}", "scenario=yu_two_agents"] for n in ("none", "online")],
                           lambda lines: api.compose("task=matrix", *lines))
    assert len(kept) == 2


@pytest.mark.parametrize("task", sorted(t for t in TASKS if t != "matrix"))
def test_every_other_task_refuses_a_learner(task, tmp_path):
    from test_task_groups import CONTEXT

    err = precheck([*CONTEXT[task], "learner=online", f"hydra.run.dir={tmp_path / 'r'}"])
    assert err is not None and err.startswith(f"task={task} does not use the root group learner (") and \
        err.endswith("; remove learner=online"), err
    assert TASKS[task].instead["learner"] in err


def test_matrix_reads_the_learner(tmp_path):
    assert precheck(["task=matrix", "method=ekf_gp_hybrid", "learner=none", f"hydra.run.dir={tmp_path / 'r'}"]) is None
    cfg = api.compose("task=matrix", "method=rbpf_em", "scenario=braga")
    assert OmegaConf.select(cfg, "learner.em.burn_in") == 50 and "em" not in cfg.filter
