"""Schema of ``task=yu_faults`` (the Yu scenario on an unreliable network)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, List, Optional

from omegaconf import DictConfig

from dslearn.errors import ConfigError
from dslearn.schemas.base import ranged, register_task

FUSION_OPTIONS = ("individual", "ce", "cm", "ci", "hybrid", "hybrid_nodes", "centralized")


@dataclass
class FaultTask:
    entry: str = "dslearn.studies.yu_faults:run"
    name: str = "yu_faults"
    models: List[str] = ranged(factory=lambda: ["lin", "gp_increment"], min_len=1)  # conf/model/<name>.yaml
    fusions: List[str] = ranged(factory=lambda: ["individual", "ce", "cm", "ci", "hybrid", "centralized"],
                                min_len=1, each=True, choices=FUSION_OPTIONS)
    train_episodes: int = ranged(15, ge=0)
    test_episodes: int = ranged(20, ge=1)
    link_fail: List[float] = ranged(factory=lambda: [0.0, 0.1, 0.3, 0.5], each=True, ge=0.0, le=1.0)
    node_fail: List[float] = ranged(factory=lambda: [0.0, 0.1, 0.2, 0.4], each=True, ge=0.0, le=1.0)
    joint: List[Any] = ranged(factory=lambda: [[0.3, 0.2]])
    node_fail_mode: str = ranged("permanent", choices=("permanent", "transient"))
    node_fail_duration: int = ranged(4, ge=1)
    weights: str = ranged("metropolis", choices=("metropolis", "uniform"))
    outlier_frac: float = ranged(0.1, ge=0.0, le=1.0)
    outlier_std: float = ranged(3.0, gt=0.0)
    gate_prob: Optional[float] = ranged(0.99, gt=0.0, lt=1.0)
    outlier_settings: bool = True
    divergence_bound: float = ranged(2.0, gt=0.0)


def check(cfg: DictConfig) -> None:
    from dslearn.conf_paths import CONF_DIRS

    t = cfg.task
    for m in t.models:
        if not any((d / "model" / f"{m}.yaml").is_file() for d in CONF_DIRS):
            raise ConfigError(f"task.models contains {m!r}: no conf/model/{m}.yaml")
    for pair in t.joint:
        ok = hasattr(pair, "__len__") and len(pair) == 2 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and 0.0 <= v <= 1.0 for v in pair)
        if not ok:
            raise ConfigError(f"task.joint contains {pair!r}: must be [link_fail, node_fail] in [0, 1]")
    omega = cfg.consensus.get("omega", "one")
    if str(omega) not in ("one", "1", "1.0"):
        raise ConfigError(f"consensus.omega={omega!r} is not used by task=yu_faults: every fusion of task.fusions "
                          "takes omega from its own option (conf/consensus/<name>.yaml); list hybrid_nodes "
                          "(omega = number of nodes) in task.fusions instead")


#: the root groups the study reads (:mod:`dslearn.studies.yu_faults`): the scenario, the network, the
#: observation model and the filter as the Yu study; of ``consensus`` only the number of rounds
USES = ("scenario", "network", "observation", "filter", "consensus.iterations")
INSTEAD = {
    "model": "its motion models are task.models, options of conf/model/",
    "consensus": "its fusions are task.fusions, each composed from its own conf/consensus/<name>.yaml, "
                 "with the weights task.weights recomputed on the live graph",
    "data": "its episodes are task.train_episodes and task.test_episodes",
}

register_task("yu_faults", FaultTask, check, uses=USES, instead=INSTEAD)
