"""The Python API: the same configurations, defaults and checks as ``dslearn-run``, without its app.

Every function composes the project's configuration (``conf/``, packaged as ``dslearn.conf``) with
``dslearn-run``-style overrides, validates it as the command line does (keys, types, ranges, the parts'
own refusals) and builds through the one composition root (:mod:`dslearn.compose`)::

    from dslearn import api

    study = api.yu_study(model="gp_increment", consensus="hybrid", train_episodes=20, test_episodes=5)
    df = study.run()                                   # tidy rows: node x episode x metric
    cfg = api.compose("task=yu", "model=lin")          # the composed configuration
    df = api.run("experiment=jiang_fg", "task.mc_runs=3")  # any task, like dslearn-run (no output folder)
"""

from __future__ import annotations

from typing import Any

#: shorthand keyword -> configuration key of :func:`yu_study`
SHORT_KEYS = {"train_episodes": "data.train_episodes", "test_episodes": "data.test_episodes"}


def compose(*overrides: str):
    """The configuration ``dslearn-run <overrides>`` would run (validated); a ``hydra.searchpath=[...]`` among them
    (or given earlier in the process) adds the user's config folders, as on the command line."""
    from hydra import compose as hydra_compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    import dslearn.schemas  # noqa: F401  (the task schemas the configs name)
    from dslearn.conf_paths import CONF_DIR
    from dslearn.search_path import add_search_path, search_overrides
    from dslearn.app.options import parse_override
    from dslearn.schemas.core import validate_config

    given = [parse_override(line) for line in overrides]
    for o in given:  # the user's config folders join the command's (their options count in every check)
        if o.key_or_group == "hydra.searchpath" and not o.is_delete():
            add_search_path(o.value())
    if not any(o.key_or_group == "hydra.searchpath" for o in given):
        overrides = (*search_overrides(), *overrides)
    if GlobalHydra.instance().is_initialized():
        cfg = hydra_compose("config", overrides=list(overrides))
    else:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
            cfg = hydra_compose("config", overrides=list(overrides))
    validate_config(cfg)
    return cfg


def build_study(cfg_or_override: Any = None, *overrides: str):
    """The study of a configuration (or of ``overrides``), its slots filled by the composition root."""
    from omegaconf import DictConfig

    from dslearn.compose import build_study as _build
    from dslearn.schemas.core import validate_config

    if isinstance(cfg_or_override, DictConfig):
        cfg = cfg_or_override
        validate_config(cfg)
    else:
        cfg = compose(*([cfg_or_override] if cfg_or_override else []), *overrides)
    return _build(cfg)


def yu_study(model: str = "gp", consensus: str = "hybrid", **options: Any):
    """Yu et al.'s synthetic study with ``model`` and ``consensus`` options and any other keys
    (``train_episodes=..``, ``test_episodes=..``, or full keys as ``**{"data.eval_at": "[0,5]"}``)."""
    ov = ["task=yu", f"model={model}", f"consensus={consensus}"]
    ov += [f"{SHORT_KEYS.get(k, k)}={v}" for k, v in options.items()]
    return build_study(None, *ov)


def run(*overrides: str, diagnostics=None):
    """Run any task as ``dslearn-run <overrides>`` would (one job, no output folder); its result table."""
    from dslearn.compose import build_study as _build

    return _build(compose(*overrides)).run(diagnostics=diagnostics)
