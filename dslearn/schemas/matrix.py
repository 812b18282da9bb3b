"""Schema of ``task=matrix`` (one cell of the comparison matrix: a method on a scenario)."""

from __future__ import annotations

from omegaconf import DictConfig

from dslearn.schemas.base import register_task
from dslearn.studies.matrix import MatrixSettings


def check(cfg: DictConfig) -> None:
    """The method must fit the scenario: refused up front, before any job of a sweep, with the reason."""
    from dslearn.compose import build_cell_parts

    build_cell_parts(cfg, check_only=True)


def uses(cfg: DictConfig) -> tuple[str, ...]:
    """The root groups a cell reads: the scenario; the network part only for a scenario without sensors of its
    own; the filter (the method's engine) and the parts that engine takes (:func:`dslearn.compose.method_takes`)."""
    from hydra.utils import get_object

    from dslearn.compose import method_takes

    own = getattr(get_object(str(cfg.scenario._target_)), "owns_network", False)
    return ("scenario", "filter", *method_takes(cfg), *(() if own else ("network",)))


register_task("matrix", MatrixSettings, check, uses=uses,
              instead={"network": "this scenario places its own sensors",
                       "model": "this method's engine takes no motion model part",
                       "observation": "this method's engine takes no observation model part",
                       "consensus": "this method's engine takes no fusion part", "data": "task.train_episodes / task.test_episodes"})
