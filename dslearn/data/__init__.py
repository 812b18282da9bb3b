"""Real data sets as plain values: trajectory files described by a :class:`DatasetSpec`
(:mod:`dslearn.data.datasets`), the strict ETH/UCY reader, scenes and windows (:mod:`dslearn.data.ethucy`),
interacting-pedestrian episodes (:mod:`dslearn.data.episodes`). The packaged data sets' config files
are read by :mod:`dslearn.schemas.datasets`."""

from dslearn.data.datasets import DatasetSpec, leave_one_out, load_dataset, task_datasets
from dslearn.data.ethucy import Scene, default_root, read_trajectories, split_scene, windows

__all__ = [
    "DatasetSpec",
    "Scene",
    "default_root",
    "leave_one_out",
    "load_dataset",
    "read_trajectories",
    "split_scene",
    "task_datasets",
    "windows",
]
