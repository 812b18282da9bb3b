r"""ETH/UCY pedestrian trajectories: the strict reader, scenes, their benchmark time split, windows.

The data and its quirks are described in ``../shared/data/eth_ucy/README.md`` (read it):
plain-text files, one observation per line, 4 tab-separated fields ``frame_id ped_id x y``
(metres), one row per pedestrian every 10 video frames.

Scenes are data sets described by plain values (:class:`dslearn.data.datasets.DatasetSpec`, loaded
by :func:`dslearn.data.datasets.load_dataset`); the packaged ones (``eth``: ``biwi_eth.txt``;
``hotel``; ``zara1``; ``zara2``; ``univ``: ``students001.txt`` + ``students003.txt``; the
training-only ``zara3`` and ``uni_examples``), with their files, labels, frame steps, time steps and
benchmark train/validation splits, and the leave-one-scene-out folds are described in the package's
config files and read by :mod:`dslearn.schemas.datasets` (``load_scene``, ``fold_scenes``, ``SCENES``).

Time step: one row step (10 frames) is 0.4 s under the ``benchmark`` convention for every file
(what published ADE/FDE numbers use). Under the ``physical`` convention it is ``frame_step / fps``:
10/15 s ≈ 0.667 s for ``biwi_eth.txt`` (its video is ~15 fps, see the data README's time-step
note), 0.4 s for every other file.

Python use::

    from dslearn.schemas.datasets import load_scene
    sc = load_scene("zara1")                 # Scene(name, dt, convention, df)
    tracks = sc.tracks()                     # ped -> (T_i, 3) [step, x, y]
    pos, meta = windows(sc, length=20)       # (N, 20, A_max, 2), NaN-padded
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from dslearn.data.cache import cached_arrays
from dslearn.errors import ConfigError, DataFormatError, check_choice

ENV_ROOT = "DSLEARN_ETHUCY_ROOT"
SPLIT_PARTS = ("all", "train", "val")


def _default_path() -> Path:
    env = os.environ.get(ENV_ROOT)
    return Path(env) if env else Path(__file__).resolve().parents[2].parent / "shared" / "data" / "eth_ucy"


def data_available() -> bool:
    """Whether the default data folder (:func:`default_root`) exists."""
    return _default_path().is_dir()


def default_root(key: str = "task.data_root") -> Path:
    """The data folder: ``$DSLEARN_ETHUCY_ROOT`` if set, else ``<repo>/../shared/data/eth_ucy``.

    Raises:
        ConfigError: naming ``key`` (the config key of the data folder: ``task.data_root`` in the
            studies, ``data_root`` in ``dslearn-train-lstm``) when the folder does not exist.
    """
    env = os.environ.get(ENV_ROOT)
    root = _default_path()
    if not root.is_dir():
        where = f"${ENV_ROOT}={env}" if env else "the default data folder"
        raise ConfigError(
            f"{where} ({str(root)!r}) does not exist; set {key}=<folder> (or ${ENV_ROOT}) to the "
            "eth_ucy folder, the one holding biwi_eth.txt, crowds_zara01.txt, ..."
        )
    return root


def _decode(path: Path, raw: bytes) -> str:
    """The file's text; DataFormatError naming the file and line for binary, BOM or non-UTF-8 bytes."""
    if raw.startswith(b"\xef\xbb\xbf"):
        raise DataFormatError(f"{path}:1: starts with a UTF-8 byte-order mark (BOM); save it as plain UTF-8 without BOM")
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise DataFormatError(f"{path}:1: UTF-16 text; save it as plain UTF-8 (ASCII numbers)")
    if b"\x00" in raw[:65536]:
        line = raw[: raw.index(b"\x00")].count(b"\n") + 1
        raise DataFormatError(f"{path}:{line}: binary file (NUL byte); expected plain-text lines 'frame ped x y'")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as e:
        line = raw[: e.start].count(b"\n") + 1
        raise DataFormatError(
            f"{path}:{line}: byte 0x{raw[e.start]:02x} is not UTF-8 text (a Latin-1 or binary file?); "
            "expected plain-text lines 'frame ped x y'"
        ) from None


def read_trajectories(path: str | Path, frame_step: int | None = None, step_key: str | None = None) -> pd.DataFrame:
    """Read one standard ``frame ped x y`` file strictly.

    Every line must have exactly 4 whitespace-separated finite numbers; ``frame`` and ``ped``
    must be integral (``780`` and ``780.0`` are both accepted); frames must not decrease from
    one line to the next; no ``(frame, ped)`` pair may repeat; with ``frame_step``, every frame
    must be a multiple of it. Nothing is returned unless the whole file is valid.

    Args:
        path: the file.
        frame_step: frames between a pedestrian's rows (``None``: not checked).
        step_key: the config key that set ``frame_step``, named in the error (e.g.
            ``task.datasets.zara1.frame_step``).
    Returns:
        DataFrame with columns ``frame`` (int64), ``ped`` (int64), ``x``, ``y`` (float64, m),
        sorted by ``(frame, ped)``.
    Raises:
        DataFormatError: ``"<file>:<line>: <what is wrong>"`` (1-based line numbers); an
            empty file is reported at line 1.
        FileNotFoundError: the file does not exist.

    A valid file's parse is cached by its content and ``frame_step`` (:mod:`dslearn.data.cache`;
    ``$DSLEARN_CACHE_DIR=off`` disables it).
    """
    path = Path(path)
    if path.is_dir():
        raise DataFormatError(f"{path}: is a folder, expected a trajectory file")
    try:
        raw = path.read_bytes()
    except PermissionError:
        raise DataFormatError(f"{path}: cannot be read (permission denied)") from None
    step = None if frame_step is None else int(frame_step)
    a = cached_arrays("trajectories", raw, {"frame_step": step}, TRAJECTORY_ARRAYS,
                      lambda: _parse_trajectories(path, raw, step, step_key))
    return pd.DataFrame({k: a[k] for k in TRAJECTORY_ARRAYS})


#: the parsed columns of a trajectory file: name -> (dtype, ndim) (the cache's layout, :mod:`dslearn.data.cache`)
TRAJECTORY_ARRAYS = {"frame": ("int64", 1), "ped": ("int64", 1), "x": ("float64", 1), "y": ("float64", 1)}


def _parse_trajectories(path: Path, raw: bytes, frame_step: int | None, step_key: str | None) -> dict[str, np.ndarray]:
    """The strict parse of :func:`read_trajectories`: the columns of :data:`TRAJECTORY_ARRAYS`, sorted by (frame, ped)."""
    lines = _decode(path, raw).splitlines()
    if not lines:
        raise DataFormatError(f"{path}:1: empty file (expected lines 'frame ped x y')")
    n = len(lines)
    vals = np.empty((n, 4), dtype=np.float64)
    for i, line in enumerate(lines):
        parts = line.split()
        if len(parts) != 4:
            raise DataFormatError(f"{path}:{i + 1}: expected 4 fields 'frame ped x y', got {len(parts)}: {line!r}")
        try:
            row = [float(p) for p in parts]
        except ValueError:
            hint = " (a header line? the files have none)" if i == 0 and not any(_is_number(p) for p in parts) else ""
            raise DataFormatError(f"{path}:{i + 1}: non-numeric field in {line!r}{hint}") from None
        if not all(math.isfinite(v) for v in row):
            raise DataFormatError(f"{path}:{i + 1}: NaN or infinite value in {line!r}")
        vals[i] = row
    for col, name in ((0, "frame"), (1, "ped_id")):
        bad = np.nonzero(vals[:, col] != np.round(vals[:, col]))[0]
        if bad.size:
            i = int(bad[0])
            raise DataFormatError(f"{path}:{i + 1}: {name} {float(vals[i, col])!r} is not an integer")
    frame = vals[:, 0].astype(np.int64)
    ped = vals[:, 1].astype(np.int64)
    dec = np.nonzero(np.diff(frame) < 0)[0]
    if dec.size:
        i = int(dec[0]) + 1
        raise DataFormatError(
            f"{path}:{i + 1}: frame {frame[i]} after frame {frame[i - 1]} (frames must not decrease)"
        )
    if frame_step is not None:
        off = np.nonzero(frame % int(frame_step) != 0)[0]
        if off.size:
            i = int(off[0])
            key = f", {step_key}" if step_key else ""
            raise DataFormatError(
                f"{path}:{i + 1}: frame {frame[i]} is not a multiple of {int(frame_step)} (the frame step{key}: "
                "frames between a pedestrian's rows)"
            )
    df = pd.DataFrame({"frame": frame, "ped": ped, "x": vals[:, 2], "y": vals[:, 3], "line": np.arange(1, n + 1)})
    dup = df.duplicated(["frame", "ped"], keep="first")
    if dup.any():
        j = int(np.nonzero(dup.to_numpy())[0][0])
        first = int(df[(df.frame == frame[j]) & (df.ped == ped[j])].line.iloc[0])
        raise DataFormatError(
            f"{path}:{j + 1}: duplicate (frame, ped) = ({frame[j]}, {ped[j]}), first seen at line {first}"
        )
    df = df.sort_values(["frame", "ped"], kind="stable").drop(columns="line").reset_index(drop=True)
    return {k: df[k].to_numpy(dtype=dt) for k, (dt, _) in TRAJECTORY_ARRAYS.items()}


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


@dataclass
class Scene:
    """One scene (one or more files) as a tidy table.

    Attributes:
        name: scene name (its data set's name).
        dt: seconds per step under ``convention``.
        convention: ``benchmark`` or ``physical``.
        df: columns ``file`` (str), ``frame`` (int64), ``ped`` (int64, unique across the
            scene's files: ``file_index * 100000 + ped_id``), ``step`` (int64,
            ``frame // 10`` minus the file's first ``frame // 10``), ``t`` (``step * dt``, s),
            ``x``, ``y`` (m); sorted by (file, frame, ped).
    """

    name: str
    dt: float
    convention: str
    df: pd.DataFrame
    label: str = ""
    #: file -> first frame of the benchmark's validation part (files not in it go wholly to train)
    val_first_frame: dict = field(default_factory=dict)

    def tracks(self) -> dict[int, Tensor]:
        """``ped -> (T_i, 3)`` float64 rows ``[step, x, y]`` at consecutive steps.

        Raises:
            DataFormatError: a pedestrian's steps have a gap (the standard files have none).
        """
        out = {}
        for ped, g in self.df.groupby("ped", sort=True):
            steps = g["step"].to_numpy()
            if steps.size > 1 and not (np.diff(steps) == 1).all():
                raise DataFormatError(f"scene {self.name}: pedestrian {ped} has a gap in its steps")
            out[int(ped)] = torch.as_tensor(g[["step", "x", "y"]].to_numpy(dtype=np.float64))
        return out


def split_scene(scene: Scene, part: str) -> Scene:
    """The benchmark's train or validation part of a scene (split in time per file at the scene's
    ``val_first_frame``); ``part="all"`` returns the scene itself.

    Files without a known split (fixture files) go wholly to ``train``.
    """
    check_choice("part", part, SPLIT_PARTS)
    if part == "all":
        return scene
    files = scene.df["file"].to_numpy()
    first = np.full(files.shape, np.iinfo(np.int64).max, dtype=np.int64)
    for f, frame in scene.val_first_frame.items():
        first[files == f] = frame
    is_val = scene.df["frame"].to_numpy() >= first
    keep = is_val if part == "val" else ~is_val
    return Scene(name=f"{scene.name}:{part}", dt=scene.dt, convention=scene.convention, df=scene.df[keep].reset_index(drop=True),
                 label=scene.label, val_first_frame=scene.val_first_frame)


def windows(
    scene: Scene, length: int = 20, stride: int = 1, min_peds: int = 1
) -> tuple[Tensor, pd.DataFrame]:
    """Sliding windows of ``length`` steps with every pedestrian present at all of them.

    As in the Social GAN loader (``skip`` = ``stride``): a pedestrian belongs to a window
    only if it is present at every step of it; a window is kept if it has at least
    ``min_peds`` such pedestrians (the benchmark keeps windows with >= 2). Windows never
    cross files.

    Returns:
        positions ``(N, length, A_max, 2)`` float64, NaN-padded in the agent dimension
        (present agents first, in increasing ped id), and a DataFrame with one row per
        window: ``file``, ``start_step``, ``num_peds``, ``peds`` (tuple of ped ids).
    """
    if length < 1 or stride < 1 or min_peds < 1:
        raise ConfigError(f"windows: length={length}, stride={stride}, min_peds={min_peds} must all be >= 1")
    blocks, metas = [], []
    for fname, d in scene.df.groupby("file", sort=False):
        peds = np.sort(d["ped"].unique())
        col = np.searchsorted(peds, d["ped"].to_numpy())
        steps = d["step"].to_numpy()
        n_steps = int(steps.max()) + 1
        if n_steps < length:
            continue
        grid = np.full((n_steps, peds.size, 2), np.nan)
        grid[steps, col] = d[["x", "y"]].to_numpy()
        present = ~np.isnan(grid[..., 0])
        csum = np.concatenate([np.zeros((1, peds.size), np.int64), np.cumsum(present, 0)], 0)
        starts = np.arange(0, n_steps - length + 1, stride)
        full = (csum[starts + length] - csum[starts]) == length  # (W, P)
        keep = full.sum(1) >= min_peds
        for s, row in zip(starts[keep], full[keep]):
            idx = np.nonzero(row)[0]
            blocks.append(grid[s : s + length, idx])
            metas.append({"file": fname, "start_step": int(s), "num_peds": int(idx.size), "peds": tuple(int(p) for p in peds[idx])})
    if not blocks:
        return torch.empty(0, length, 0, 2, dtype=torch.float64), pd.DataFrame(columns=["file", "start_step", "num_peds", "peds"])
    a_max = max(b.shape[1] for b in blocks)
    out = np.full((len(blocks), length, a_max, 2), np.nan)
    for i, b in enumerate(blocks):
        out[i, :, : b.shape[1]] = b
    return torch.as_tensor(out), pd.DataFrame(metas)
