"""Real data sets: trajectory files described by configuration (``conf/dataset/*.yaml``,
:mod:`dslearn.data.datasets`), the ETH/UCY reader and windows (:mod:`dslearn.data.ethucy`),
interacting-pedestrian episodes (:mod:`dslearn.data.episodes`)."""

from dslearn.data.datasets import DatasetSpec, leave_one_out, load_dataset, packaged_dataset, task_datasets
from dslearn.data.ethucy import (
    Scene,
    default_root,
    fold_scenes,
    load_scene,
    read_trajectories,
    scene_dt,
    split_scene,
    windows,
)


def __getattr__(name: str):
    """``SCENES`` / ``ALL_SCENES``: read from the packaged YAMLs when first asked for."""
    if name in ("SCENES", "ALL_SCENES"):
        from dslearn.data import ethucy

        return getattr(ethucy, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "ALL_SCENES",
    "DatasetSpec",
    "SCENES",
    "Scene",
    "default_root",
    "fold_scenes",
    "leave_one_out",
    "load_dataset",
    "load_scene",
    "packaged_dataset",
    "read_trajectories",
    "scene_dt",
    "split_scene",
    "task_datasets",
    "windows",
]
