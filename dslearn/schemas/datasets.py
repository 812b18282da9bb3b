r"""Trajectory data sets described by configuration: one YAML per data set (``conf/dataset/<name>.yaml``).

A data set's YAML holds the values of a :class:`dslearn.data.datasets.DatasetSpec` (:class:`DatasetSchema`
types them while Hydra composes; :func:`dslearn.data.datasets.check_dataset` checks their ranges):
``label``, ``files`` (relative to ``root``; an absolute path is used as is), ``root`` (``null`` =
``task.data_root``, else ``$DSLEARN_ETHUCY_ROOT`` or ``<repo>/../shared/data/eth_ucy``), ``frame_step``,
``dt``, ``fps``, ``units`` and ``val_first_frame``.

The studies compose the data sets they may use into ``task.datasets.<name>`` (their task config
lists the ETH/UCY scenes); a user's data set joins with one YAML in their own config folder::

    dslearn-run experiment=ethucy_forecast hydra.searchpath=[file://my_conf] \
        +dataset@task.datasets.mall=mall task.scenes=[mall] task.train_scenes=[mall]

The ETH/UCY leave-one-scene-out folds are config too (``conf/folds/ethucy.yaml``, ``task.folds``):
a fold trains on the pool minus its test scene (:func:`dslearn.data.datasets.leave_one_out`); a new
data set is in no fold unless it is added to the pool.

The packaged data sets and folds are read here, for the Python API and the labels of a report
(:func:`packaged_dataset`, :func:`packaged_folds`, :func:`load_scene`, :func:`fold_scenes`,
:func:`scene_dt`, :data:`SCENES`, :data:`ALL_SCENES`, :data:`TRAIN_ONLY`, :data:`VAL_FIRST_FRAME`,
:func:`run_labels`): no scene, file or split is fixed in code.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional

from omegaconf import OmegaConf

from dslearn.conf_paths import CONF_DIR
from dslearn.data.datasets import CONVENTIONS, DatasetSpec, dataset_spec, leave_one_out, load_dataset
from dslearn.data.ethucy import Scene
from dslearn.errors import ConfigError, check_choice
from dslearn.schemas.base import to_plain


@dataclass
class DatasetSchema:
    """One data set (the fields of ``conf/dataset/<name>.yaml``): their types; their ranges are
    :data:`dslearn.data.datasets.DATASET_RULES`, checked by :func:`dslearn.data.datasets.check_dataset`."""

    label: str = ""
    files: List[str] = field(default_factory=list)
    root: Optional[str] = None
    frame_step: int = 10
    dt: float = 0.4
    fps: Optional[float] = None
    units: str = "m"
    val_first_frame: Optional[List[int]] = None


@dataclass
class FoldsSchema:
    """Leave-one-scene-out folds (``conf/folds/<name>.yaml``): test scenes, and the training pool."""

    test: List[str] = field(default_factory=list)
    pool: List[str] = field(default_factory=list)


def spec_from_config(name: str, node) -> DatasetSpec:
    """A :class:`~dslearn.data.datasets.DatasetSpec` from a config node (DictConfig / dict) with the
    :class:`DatasetSchema` keys (:func:`dslearn.data.datasets.dataset_spec` of its plain values)."""
    return dataset_spec(name, to_plain(node))


def check_scene_names(field_name: str, names, task) -> None:
    """Every name must be a data set of ``task.datasets`` (ConfigError naming the field and the choices)."""
    known = list((task.get("datasets") or {}).keys())
    for s in names:
        if s not in known:
            raise ConfigError(
                f"{field_name}={s!r} is not a data set of task.datasets; choose one of {known} or add one with "
                f"+dataset@task.datasets.{s}={s} (a conf/dataset/{s}.yaml in your hydra.searchpath folder)"
            )
    if len(set(names)) != len(list(names)):
        raise ConfigError(f"{field_name}={list(names)} has duplicates")


# ------------------------------------------------------------------------------------------
# the packaged data sets (conf/dataset/*.yaml), for the Python API and the labels of a report
def packaged_names() -> list[str]:
    return sorted(p.stem for p in (Path(CONF_DIR) / "dataset").glob("*.yaml"))


def packaged_dataset(name: str) -> DatasetSpec:
    """The spec of ``conf/dataset/<name>.yaml`` in the packaged config folder."""
    check_choice("scene", name, tuple(packaged_names()))
    return spec_from_config(name, OmegaConf.load(Path(CONF_DIR) / "dataset" / f"{name}.yaml"))


def packaged_folds(name: str = "ethucy") -> dict[str, list[str]]:
    node = OmegaConf.load(Path(CONF_DIR) / "folds" / f"{name}.yaml")
    return {"test": [str(s) for s in node.test], "pool": [str(s) for s in node.pool]}


def _scene_files(names) -> dict[str, tuple[str, ...]]:
    return {n: packaged_dataset(n).files for n in names}


def __getattr__(name: str):
    """``SCENES`` (the five benchmark test scenes), ``ALL_SCENES`` (the fold pool), ``TRAIN_ONLY`` and
    ``VAL_FIRST_FRAME`` (file -> first validation frame), read from ``conf/dataset/*.yaml`` and
    ``conf/folds/ethucy.yaml`` (no scene, file or split is fixed in code)."""
    if name not in ("SCENES", "ALL_SCENES", "TRAIN_ONLY", "VAL_FIRST_FRAME"):
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    folds = packaged_folds("ethucy")
    if name == "SCENES":
        return _scene_files(folds["test"])
    if name == "ALL_SCENES":
        return _scene_files(folds["pool"])
    if name == "TRAIN_ONLY":
        return _scene_files([s for s in folds["pool"] if s not in folds["test"]])
    return {f: v for n in folds["pool"] for f, v in packaged_dataset(n).split().items()}


def scene_dt(file_name: str, convention: str = "benchmark") -> float:
    """Seconds per row step of a packaged data set's file (by its base name), from its YAML:
    ``dt`` under ``benchmark``, ``frame_step / fps`` under ``physical``."""
    check_choice("convention", convention, CONVENTIONS)
    base = Path(file_name).name
    for n in packaged_names():
        spec = packaged_dataset(n)
        if base in spec.files:
            return spec.step(convention)
    raise ConfigError(f"file {base!r} is in no conf/dataset/*.yaml data set")


def load_scene(name: str, root: str | Path | None = None, convention: str = "benchmark") -> Scene:
    """Load a packaged data set (``conf/dataset/<name>.yaml``) from ``root`` (default
    :func:`dslearn.data.ethucy.default_root`).

    Raises:
        ConfigError: unknown scene or convention, missing data root.
        DataFormatError: a malformed file, or a frame id that is not a multiple of the frame step.
    """
    return load_dataset(packaged_dataset(name), root, convention)


def fold_scenes(test_scene: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Leave-one-scene-out fold of ``conf/folds/ethucy.yaml``: ``(test scenes, training scenes)``
    (training = the pool minus the test scene, so ``zara3`` and ``uni_examples`` always train)."""
    folds = packaged_folds("ethucy")
    check_choice("test scene", test_scene, tuple(folds["test"]))
    return (test_scene,), leave_one_out(test_scene, folds["pool"])


def run_labels(out_dir) -> dict[str, str]:
    """Data set name -> label from the ``config.yaml`` of every run at or below ``out_dir`` (the
    resolved config each run writes), falling back to the packaged data sets' labels."""
    labels = {}
    for n in packaged_names():
        try:
            labels[n] = packaged_dataset(n).label
        except Exception:  # a broken packaged file must not break a report
            pass
    out_dir = Path(out_dir)
    files = [out_dir / "config.yaml"] if (out_dir / "config.yaml").is_file() else sorted(out_dir.rglob("config.yaml"))
    for f in files:
        try:
            ds = OmegaConf.load(f).get("task", {}).get("datasets") or {}
            labels.update({str(k): str(v.get("label") or k) for k, v in ds.items()})
        except Exception:  # not a run config
            continue
    return labels
