"""Real data sets (ETH/UCY pedestrian trajectories)."""

from dslearn.data.ethucy import (
    ALL_SCENES,
    SCENES,
    Scene,
    default_root,
    fold_scenes,
    load_scene,
    read_trajectories,
    scene_dt,
    split_scene,
    windows,
)

__all__ = [
    "ALL_SCENES",
    "SCENES",
    "Scene",
    "default_root",
    "fold_scenes",
    "load_scene",
    "read_trajectories",
    "scene_dt",
    "split_scene",
    "windows",
]
