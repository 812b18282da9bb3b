"""Schema of ``task=yu_faults`` (the Yu scenario on an unreliable network): the study's settings
(:class:`dslearn.studies.yu_faults.FaultTask`), its cross-field check, and the slots of the grid that
the composition root fills from the config groups (``yu_faults_fusions``, ``yu_faults_model_labels``)."""

from __future__ import annotations

from omegaconf import DictConfig

from dslearn.compose import build_fusion, group_options, register_slot
from dslearn.errors import ConfigError
from dslearn.schemas.base import register_task
from dslearn.studies.yu_faults import FaultGridFusions, FaultTask


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


def grid_fusion_nodes(cfg: DictConfig) -> dict[str, DictConfig]:
    """The config node of every fusion of ``task.fusions``, composed from its own ``consensus`` option.

    Each keeps its own ``omega`` (``hybrid``: 1, ``hybrid_nodes``: S) and type; only the number of
    rounds ``L`` is the grid's, ``consensus.iterations``. The weight rule of the option is not used:
    :class:`~dslearn.fusion.faults.FaultyFusion` recomputes the weights on every step's live graph
    (``task.weights``). A root ``consensus.omega`` other than ``one`` would apply to no fusion:
    :func:`check` refuses it; the grid lists the omega variants as options
    (``task.fusions=[hybrid,hybrid_nodes]``).
    """
    same = (f"consensus.iterations={int(cfg.consensus.iterations)}", "consensus.weights=uniform")
    return group_options("consensus", list(cfg.task.fusions), same)


def _grid_fusions(cfg: DictConfig, slots) -> FaultGridFusions:
    """Slot ``yu_faults_fusions``: a maker per fusion of ``task.fusions`` (:func:`grid_fusion_nodes`)."""
    nodes = grid_fusion_nodes(cfg)

    def maker(node):
        return lambda network: build_fusion(node, network)

    return FaultGridFusions(rounds=int(cfg.consensus.iterations), make={n: maker(node) for n, node in nodes.items()})


def _model_labels(cfg: DictConfig, slots) -> dict[str, str]:
    """Slot ``yu_faults_model_labels``: the rows' label of every option of ``task.models`` (its ``name``:
    ``gp_cv`` is ``gp_increment_cv``, ``gp_rbcm`` ``gp_<aggregation>``)."""
    return {n: str(node.name) for n, node in group_options("model", [str(m) for m in cfg.task.models]).items()}


register_slot("yu_faults_fusions", _grid_fusions)
register_slot("yu_faults_model_labels", _model_labels)

#: the root groups the study reads (:mod:`dslearn.studies.yu_faults`): the scenario, the network, the
#: observation model and the filter as the Yu study; of ``consensus`` only the number of rounds
USES = ("scenario", "network", "observation", "filter", "consensus.iterations")
INSTEAD = {
    "model": "its motion models are task.models, options of conf/model/",
    "consensus": "its fusions are task.fusions, each composed from its own conf/consensus/<name>.yaml, "
                 "with the weights task.weights recomputed on the live graph",
    "data": "its episodes are task.train_episodes and task.test_episodes",
}

#: the root groups whose option is the part it builds (the keys each reads: :func:`dslearn.schemas.base.unread_keys`);
#: not the network, whose links the fusions of task.fusions use
PARTS = ("scenario", "observation", "filter")

register_task("yu_faults", FaultTask, check, uses=USES, instead=INSTEAD, parts=PARTS)
