r"""Trajectory data sets as plain values: what the loader needs to know about a set of files.

A data set is a set of plain-text files in the ETH/UCY 4-column format (``frame ped x y``, read by
:func:`dslearn.data.ethucy.read_trajectories`) described by a :class:`DatasetSpec`: ``label``
(tables, figures), ``files`` (relative to ``root``; an absolute path is used as is), ``root``
(``None`` = the caller's data folder, else ``$DSLEARN_ETHUCY_ROOT`` or ``<repo>/../shared/data/eth_ucy``),
``frame_step`` (frames between a pedestrian's rows), ``dt`` (seconds per row step under the
``benchmark`` convention), ``fps`` (video frame rate: the ``physical`` step is ``frame_step / fps``;
``None`` = ``dt``), ``units`` (of ``x, y``) and ``val_first_frame`` (per file, the first frame of the
benchmark's validation part; ``None`` = the whole file trains). :func:`check_dataset` checks a data
set's values (the keys of :data:`DATASET_KEYS`) and :func:`dataset_spec` makes the spec of them.

A fold of the leave-one-scene-out protocol trains on the pool minus its test scene
(:func:`leave_one_out`). Where the data sets and folds are described (one file per data set, the
packaged ones and the user's) is the validation layer's business (:mod:`dslearn.schemas.datasets`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from dslearn.data.ethucy import Scene, default_root, read_trajectories
from dslearn.errors import ConfigError, check_choice, check_rules

CONVENTIONS = ("benchmark", "physical")
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}
#: offset that makes pedestrian ids unique across the files of one data set
PED_OFFSET = 100_000
#: name of the data-root key in every study's task config (one name everywhere)
DATA_ROOT_KEY = "task.data_root"
#: where a study's config holds its data sets
DATASETS_KEY = "task.datasets"
#: the keys of a data set's values and the rules :func:`check_dataset` applies to them
DATASET_RULES: dict[str, dict] = {
    "label": {},
    "files": {"min_len": 1},
    "root": {},
    "frame_step": {"ge": 1},
    "dt": {"gt": 0.0},
    "fps": {"gt": 0.0},
    "units": {"choices": tuple(UNITS)},
    "val_first_frame": {},
}
DATASET_KEYS = tuple(DATASET_RULES)


@dataclass(frozen=True)
class DatasetSpec:
    """A checked data set: ``name`` (its key in ``task.datasets``) and its values (:data:`DATASET_KEYS`)."""

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


def check_dataset(name: str, values: Mapping, prefix: str) -> None:
    """The values of one data set (a mapping of :data:`DATASET_KEYS`): no unknown key, the rules of
    :data:`DATASET_RULES`, one ``val_first_frame`` per file. ConfigError naming ``prefix.<key>``."""
    unknown = sorted(str(k) for k in values.keys() if k not in DATASET_RULES)
    if unknown:
        where = ", ".join(f"{prefix}.{k}" if prefix else k for k in unknown)
        raise ConfigError(f"{where}: unknown key; {prefix or 'the config'} takes {list(DATASET_KEYS)}")
    for key, rules in DATASET_RULES.items():
        if key in values:
            check_rules(f"{prefix}.{key}" if prefix else key, values[key], rules)
    vf = values.get("val_first_frame")
    if vf is not None and len(vf) != len(values["files"]):
        raise ConfigError(f"{prefix}.val_first_frame has {len(vf)} entries for {len(values['files'])} files; give one per file or null")


def dataset_spec(name: str, values: Mapping) -> DatasetSpec:
    """A :class:`DatasetSpec` from the values of a data set (a mapping of :data:`DATASET_KEYS`; a
    key left out takes the spec's default, ``label`` the name)."""
    get = values.get
    unknown = set(values.keys()) - set(DATASET_KEYS)
    if unknown:
        raise ConfigError(f"dataset {name!r} has unknown keys {sorted(unknown)}; allowed: {list(DATASET_KEYS)}")
    vf = get("val_first_frame")
    fps = get("fps")
    return DatasetSpec(
        name=str(name), label=str(get("label") or name), files=tuple(str(f) for f in get("files")), root=get("root"),
        frame_step=int(get("frame_step", 10)), dt=float(get("dt", 0.4)), fps=None if fps is None else float(fps),
        units=str(get("units", "m")), val_first_frame=None if vf is None else tuple(int(v) for v in vf),
    )


def task_datasets(task: Mapping) -> dict[str, DatasetSpec]:
    """Every data set of ``task["datasets"]`` (a mapping of name -> the data set's values) as specs."""
    ds = task.get("datasets") or {}
    return {str(k): dataset_spec(str(k), v) for k, v in ds.items()}


def leave_one_out(test_scene: str, pool) -> tuple[str, ...]:
    """Training scenes of the fold of ``test_scene``: the pool (in its order) minus the test scene."""
    return tuple(str(s) for s in pool if s != test_scene)


def resolve_root(spec: DatasetSpec, data_root, root_key: str = DATA_ROOT_KEY,
                 datasets_key: str = DATASETS_KEY) -> tuple[Path, str]:
    """The folder the data set's relative files are in, and the config key that named it.
    ``root_key`` / ``datasets_key`` are the keys of the data folder and of the data sets in the
    caller's configuration (the studies': ``task.data_root``, ``task.datasets``)."""
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
