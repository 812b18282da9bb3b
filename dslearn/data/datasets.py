r"""Trajectory data sets described by configuration: one YAML per data set (``conf/dataset/<name>.yaml``).

A data set is a set of plain-text files in the ETH/UCY 4-column format (``frame ped x y``, read by
:func:`dslearn.data.ethucy.read_trajectories`) with what the loader needs to know about them
(:class:`DatasetSchema`): ``label`` (tables, figures), ``files`` (relative to ``root``; an absolute
path is used as is), ``root`` (``null`` = ``task.data_root``, else ``$DSLEARN_ETHUCY_ROOT`` or
``<repo>/../shared/data/eth_ucy``), ``frame_step`` (frames between a pedestrian's rows), ``dt``
(seconds per row step under the ``benchmark`` convention), ``fps`` (video frame rate: the
``physical`` step is ``frame_step / fps``; ``null`` = ``dt``), ``units`` (of ``x, y``) and
``val_first_frame`` (per file, the first frame of the benchmark's validation part; ``null`` = the
whole file trains).

The studies compose the data sets they may use into ``task.datasets.<name>`` (their task config
lists the ETH/UCY scenes); a user's data set joins with one YAML in their own config folder::

    dslearn-run experiment=ethucy_forecast hydra.searchpath=[file://my_conf] \
        +dataset@task.datasets.mall=mall task.scenes=[mall] task.train_scenes=[mall]

The ETH/UCY leave-one-scene-out folds are config too (``conf/folds/ethucy.yaml``, ``task.folds``):
a fold trains on the pool minus its test scene (:func:`leave_one_out`); a new data set is in no
fold unless it is added to the pool.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional

import numpy as np
import pandas as pd

from dslearn.errors import ConfigError, check_choice

CONVENTIONS = ("benchmark", "physical")
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}
#: offset that makes pedestrian ids unique across the files of one data set
PED_OFFSET = 100_000
#: name of the data-root key in every study's task config (one name everywhere)
DATA_ROOT_KEY = "task.data_root"
#: where a study's config holds its data sets
DATASETS_KEY = "task.datasets"


def ranged(default=dataclasses.MISSING, *, factory=None, **rules):
    """A field with range / choice rules, as :func:`dslearn.schemas.base.ranged` (which this module
    cannot import at load time: the schemas package imports the task schemas, which import this)."""
    if factory is not None:
        return field(default_factory=factory, metadata=rules)
    return field(default=default, metadata=rules)


@dataclass
class DatasetSchema:
    """One data set (the fields of ``conf/dataset/<name>.yaml``)."""

    label: str = ""
    files: List[str] = ranged(factory=list, min_len=1)
    root: Optional[str] = None
    frame_step: int = ranged(10, ge=1)
    dt: float = ranged(0.4, gt=0.0)
    fps: Optional[float] = ranged(None, gt=0.0)
    units: str = ranged("m", choices=tuple(UNITS))
    val_first_frame: Optional[List[int]] = None


@dataclass
class FoldsSchema:
    """Leave-one-scene-out folds (``conf/folds/<name>.yaml``): test scenes, and the training pool."""

    test: List[str] = field(default_factory=list)
    pool: List[str] = field(default_factory=list)


@dataclass(frozen=True)
class DatasetSpec:
    """A checked data set: ``name`` (its key in ``task.datasets``) and the :class:`DatasetSchema` fields."""

    name: str
    label: str
    files: tuple[str, ...]
    root: str | None = None
    frame_step: int = 10
    dt: float = 0.4
    fps: float | None = None
    units: str = "m"
    val_first_frame: tuple[int, ...] | None = None

    def step(self, convention: str = "benchmark") -> float:
        """Seconds per row step: ``dt`` (benchmark), ``frame_step / fps`` (physical, when ``fps`` is given)."""
        check_choice("convention", convention, CONVENTIONS)
        if convention == "physical" and self.fps is not None:
            return self.frame_step / self.fps
        return self.dt

    def split(self) -> dict[str, int]:
        """File name -> first frame of the validation part."""
        return {} if self.val_first_frame is None else dict(zip(self.files, self.val_first_frame))


def check_dataset(name: str, node, prefix: str) -> None:
    """Ranges of one ``task.datasets.<name>`` node and its cross-field rules."""
    from dslearn.schemas.base import check_ranges

    check_ranges(node, DatasetSchema, prefix)
    vf = node.get("val_first_frame")
    if vf is not None and len(vf) != len(node["files"]):
        raise ConfigError(f"{prefix}.val_first_frame has {len(vf)} entries for {len(node['files'])} files; give one per file or null")


def spec_from_config(name: str, node) -> DatasetSpec:
    """A :class:`DatasetSpec` from a config node (DictConfig / dict) with the :class:`DatasetSchema` keys."""
    get = node.get
    unknown = set(node.keys()) - {f.name for f in dataclasses.fields(DatasetSchema)}
    if unknown:
        raise ConfigError(f"dataset {name!r} has unknown keys {sorted(unknown)}; allowed: {[f.name for f in dataclasses.fields(DatasetSchema)]}")
    vf = get("val_first_frame")
    fps = get("fps")
    return DatasetSpec(
        name=str(name), label=str(get("label") or name), files=tuple(str(f) for f in get("files")), root=get("root"),
        frame_step=int(get("frame_step", 10)), dt=float(get("dt", 0.4)), fps=None if fps is None else float(fps),
        units=str(get("units", "m")), val_first_frame=None if vf is None else tuple(int(v) for v in vf),
    )


def task_datasets(task) -> dict[str, DatasetSpec]:
    """Every data set composed into ``task.datasets`` (name -> spec)."""
    ds = task.get("datasets") or {}
    return {str(k): spec_from_config(str(k), v) for k, v in ds.items()}


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


def leave_one_out(test_scene: str, pool) -> tuple[str, ...]:
    """Training scenes of the fold of ``test_scene``: the pool (in its order) minus the test scene."""
    return tuple(str(s) for s in pool if s != test_scene)


def resolve_root(spec: DatasetSpec, data_root, root_key: str = DATA_ROOT_KEY,
                 datasets_key: str = DATASETS_KEY) -> tuple[Path, str]:
    """The folder the data set's relative files are in, and the config key that named it.
    ``root_key`` / ``datasets_key`` are the keys of the data folder and of the data sets in the
    caller's configuration (the studies': ``task.data_root``, ``task.datasets``)."""
    from dslearn.data.ethucy import default_root

    if spec.root is None and all(Path(f).is_absolute() for f in spec.files):
        return Path("/"), f"{datasets_key}.{spec.name}.files"
    if spec.root is not None:
        root, key = Path(str(spec.root)), f"{datasets_key}.{spec.name}.root"
    elif data_root is not None:
        root, key = Path(str(data_root)), root_key
    else:
        root, key = default_root(root_key), root_key
    if not root.is_dir() and not all(Path(f).is_absolute() for f in spec.files):
        what = "is a file, not a folder" if root.exists() else "does not exist"
        raise ConfigError(f"{key}={str(root)!r} {what}; give the folder holding {', '.join(spec.files)}")
    return root, key


def check_files(spec: DatasetSpec, data_root=None, root_key: str = DATA_ROOT_KEY,
                datasets_key: str = DATASETS_KEY) -> list[Path]:
    """The data set's files, each checked to exist (ConfigError naming the key of its folder)."""
    root, key = resolve_root(spec, data_root, root_key, datasets_key)
    paths = []
    for fname in spec.files:
        path = root / fname
        if not path.is_file():
            what = "is a folder, not" if path.is_dir() else "has no"
            raise ConfigError(f"{key}={str(root)!r} {what} file {fname} (scene {spec.name})")
        paths.append(path)
    return paths


def load_dataset(spec: DatasetSpec, data_root=None, convention: str = "benchmark", *,
                 root_key: str = DATA_ROOT_KEY, datasets_key: str = DATASETS_KEY):
    """Load a data set as a :class:`dslearn.data.ethucy.Scene` (every file strictly checked).
    ``root_key`` / ``datasets_key``: the caller's config keys, named in the errors (see :func:`resolve_root`).

    Raises:
        ConfigError: missing root / file, unknown convention.
        DataFormatError: a malformed file, or a frame id that is not a multiple of ``frame_step``
            (``file:line``).
    """
    from dslearn.data.ethucy import Scene, read_trajectories

    check_choice("convention", convention, CONVENTIONS)
    paths = check_files(spec, data_root, root_key, datasets_key)
    dt = spec.step(convention)
    scale = UNITS[spec.units]
    parts = []
    for k, (fname, path) in enumerate(zip(spec.files, paths)):
        d = read_trajectories(path, spec.frame_step, f"{datasets_key}.{spec.name}.frame_step")
        if scale != 1.0:
            d["x"], d["y"] = d["x"] * scale, d["y"] * scale
        step = d["frame"] // spec.frame_step
        d.insert(0, "file", fname)
        d["ped"] = d["ped"] + k * PED_OFFSET
        d["step"] = (step - step.min()).astype(np.int64)
        d["t"] = d["step"] * dt
        parts.append(d[["file", "frame", "ped", "step", "t", "x", "y"]])
    return Scene(name=spec.name, dt=dt, convention=convention, df=pd.concat(parts, ignore_index=True),
                 label=spec.label, val_first_frame=spec.split())


# ------------------------------------------------------------------------------------------
# the packaged data sets (conf/dataset/*.yaml), for the Python API and the labels of a report
def packaged_names() -> list[str]:
    from dslearn.conf_paths import CONF_DIR

    return sorted(p.stem for p in (Path(CONF_DIR) / "dataset").glob("*.yaml"))


def packaged_dataset(name: str) -> DatasetSpec:
    """The spec of ``conf/dataset/<name>.yaml`` in the packaged config folder."""
    from omegaconf import OmegaConf

    from dslearn.conf_paths import CONF_DIR

    check_choice("scene", name, tuple(packaged_names()))
    return spec_from_config(name, OmegaConf.load(Path(CONF_DIR) / "dataset" / f"{name}.yaml"))


def packaged_folds(name: str = "ethucy") -> dict[str, list[str]]:
    from omegaconf import OmegaConf

    from dslearn.conf_paths import CONF_DIR

    node = OmegaConf.load(Path(CONF_DIR) / "folds" / f"{name}.yaml")
    return {"test": [str(s) for s in node.test], "pool": [str(s) for s in node.pool]}


def run_labels(out_dir) -> dict[str, str]:
    """Data set name -> label from the ``config.yaml`` of every run at or below ``out_dir`` (the
    resolved config each run writes), falling back to the packaged data sets' labels."""
    from omegaconf import OmegaConf

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
