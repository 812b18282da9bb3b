"""``dslearn-train-lstm``: train one LSTM encoder–decoder / Social-LSTM baseline and save it.

A Hydra app with its own config, ``conf/train_lstm.yaml`` (network and schedule from the
``lstm`` group, ``conf/lstm/default.yaml``)::

    dslearn-train-lstm                                   # paper defaults: obs 2, pred 10, 50 epochs, batch 8
    dslearn-train-lstm lstm.schedule=early_stopping lstm.epochs=200 lstm.patience=10   # stop on val_scenes' loss
    dslearn-train-lstm lstm.pooling=social lstm.epochs=5 train_scenes=[zara1,zara2] val_scenes=[zara3] \\
        train_part=all val_part=all checkpoint=slstm.pt device=cuda

Windows of ``lstm.obs_len + lstm.pred_len`` steps (every pedestrian of a window present
at all of them) come from ``train_scenes`` (data sets of ``datasets``, ``conf/dataset/*.yaml``) (``train_part`` of each file) and
``val_scenes`` (``val_part``). Writes the checkpoint (``torch.save`` of state dict +
hyperparameters; load with :func:`dslearn.models.lstm.load_checkpoint`, safe loading)
and ``history.csv`` (per-epoch train/val loss, learning rate, new-best flag) into the run
directory. ``lstm.schedule=early_stopping`` stops on the validation loss of ``val_scenes``
(``lstm.patience``, cap ``lstm.epochs``) and saves the best-validation weights.

Bad input is refused as by ``dslearn-run``: one line on stderr, ``dslearn-train-lstm: <what>:
<message>`` naming this app's own keys (``data_root``, ``datasets.<name>``, ``checkpoint``,
``lstm.<key>``), exit code 2. Everything that depends only on the configuration (keys, types,
ranges, the data files' presence, a checkpoint path that can be written) is checked before
Hydra starts (:func:`precheck`), so a refused command leaves nothing behind; a malformed data
file is refused (``file:line``) before training, and the checkpoint is written last.
"""

from __future__ import annotations

import logging
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from dslearn.compose import DTYPES
from dslearn.schemas.core import CONF_DIR as _CONF_DIR
from dslearn.data.datasets import CONVENTIONS, check_dataset, check_files, load_dataset, task_datasets
from dslearn.data.ethucy import SPLIT_PARTS, split_scene, windows
from dslearn.data.window_tensors import cat_windows, per_agent, subsample
from dslearn.errors import ConfigError, DataFormatError, check_choice
from dslearn.io import atomic_write_csv
from dslearn.models.lstm import SCHEDULE_KEYS, SocialLSTM, save_checkpoint, schedule_from_config, train_lstm
from dslearn.schemas.base import ranged
from dslearn.schemas.datasets import DatasetSchema

log = logging.getLogger("dslearn.train_lstm")
CONF_DIR = str(_CONF_DIR)
PROG = "dslearn-train-lstm"
#: keys of the ``lstm`` group (unknown keys are a ConfigError)
LSTM_GROUP_KEYS = ("embed", "hidden", "obs_len", "pred_len", "pooling", "grid", "neighbourhood", "noise_std") + SCHEDULE_KEYS
#: this app's keys of the data folder and the data sets (named in the data loader's errors)
ROOT_KEY, DATASETS_KEY = "data_root", "datasets"
#: the kinds of refusal (the ``<what>`` of ``dslearn-train-lstm: <what>: <message>``)
CONFIG, DATA = "configuration error", "data error"


@dataclass
class TrainLstmSchema:
    """The top-level keys of ``conf/train_lstm.yaml`` (``lstm`` and ``datasets`` are checked apart)."""

    train_scenes: List[str] = ranged(factory=list, min_len=1)
    val_scenes: List[str] = field(default_factory=list)
    train_part: str = ranged("train", choices=SPLIT_PARTS)
    val_part: str = ranged("val", choices=SPLIT_PARTS)
    convention: str = ranged("benchmark", choices=CONVENTIONS)
    data_root: Optional[str] = None
    stride: int = ranged(1, ge=1)
    min_peds: int = ranged(1, ge=1)
    max_windows: Optional[int] = ranged(None, ge=1)
    checkpoint: Optional[str] = None
    seed: int = ranged(0, ge=0)
    device: str = "cpu"
    dtype: str = ranged("float32", choices=tuple(DTYPES))
    progress: bool = True
    threads: Optional[int] = ranged(1, ge=1)


def _load(cfg: DictConfig, name: str):
    return load_dataset(task_datasets(cfg)[name], cfg.get("data_root"), str(cfg.convention),
                        root_key=ROOT_KEY, datasets_key=DATASETS_KEY)


def _windows(names, part: str, cfg: DictConfig, length: int) -> torch.Tensor | None:
    parts = []
    for n in names:
        sc = split_scene(_load(cfg, n), part)
        parts.append(windows(sc, length, int(cfg.stride), int(cfg.min_peds))[0])
    parts = [p for p in parts if p.shape[0] > 0]
    return cat_windows(parts) if parts else None


def _check_output_file(key: str, value) -> Path:
    """A file path that can be written: not a folder, in a folder that exists or can be made, writable."""
    p = Path(str(value)).expanduser()
    if str(value).endswith(("/", os.sep)) or p.is_dir():
        raise ConfigError(f"{key}={value} is a folder; give the checkpoint's file path (e.g. {key}={p / 'lstm.pt'})")
    parent = p.parent
    while not parent.exists() and parent.parent != parent:
        parent = parent.parent
    if not parent.is_dir():
        raise ConfigError(f"{key}={value}: {parent} is a file, so the checkpoint's folder cannot be created")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(f"{key}={value}: {parent} is not writable")
    return p


def check_config(cfg: DictConfig) -> dict:
    """Every refusal that depends only on the configuration, before any data is read: keys, types
    and ranges (:class:`TrainLstmSchema`, the ``lstm`` group, each ``datasets.<name>``), the
    network's hyperparameters (built on the ``meta`` device: no memory), the schedule, the data
    files' presence and the checkpoint path. Raises :class:`ConfigError` naming the key; returns
    ``{"schedule": train_lstm keywords, "dt": seconds per step}``."""
    from dslearn.schemas.base import check_ranges
    from dslearn.schemas.core import check_schema, cpu_count

    top = {k: v for k, v in cfg.items() if k not in ("lstm", "datasets")}
    t = check_schema(top, TrainLstmSchema, "")
    check_ranges(t, TrainLstmSchema, "")
    check_choice("device", str(t.device).split(":")[0], ("cpu", "cuda"))
    if str(t.device).startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError("device=cuda was asked for but no CUDA device is available (torch.cuda.is_available() is False); use device=cpu")
    if t.threads is not None and t.threads > cpu_count():
        raise ConfigError(f"threads={t.threads} must be in 1..{cpu_count()} (this machine's CPU count), or null")
    ds = cfg.get("datasets") or {}
    if not OmegaConf.is_dict(ds) and not isinstance(ds, dict):
        raise ConfigError(f"datasets={ds!r} must be a mapping of data set name -> conf/dataset/<name>.yaml keys")
    for name, node in ds.items():
        check_schema(node, DatasetSchema, f"{DATASETS_KEY}.{name}")  # types (no schema types them at composition)
        check_dataset(str(name), node, f"{DATASETS_KEY}.{name}")
    specs = task_datasets(cfg)
    known = sorted(specs)
    for fld in ("train_scenes", "val_scenes"):
        for s in t[fld]:
            if s not in specs:
                raise ConfigError(f"{fld} names {s!r}, not a data set of datasets; choose from {known} or add one "
                                  f"with +dataset@datasets.{s}=<name>")
    c = cfg.get("lstm")
    if not OmegaConf.is_dict(c):
        raise ConfigError(f"lstm={c!r} must be the lstm group (conf/lstm/*.yaml)")
    unknown = sorted(set(c.keys()) - set(LSTM_GROUP_KEYS))
    if unknown:
        raise ConfigError(f"lstm has unknown keys {unknown}; allowed: {list(LSTM_GROUP_KEYS)}")
    sched = schedule_from_config(c, prefix="lstm")
    if "patience" in sched and not list(t.val_scenes):
        raise ConfigError("lstm.schedule=early_stopping needs validation windows: val_scenes must name at least one scene")
    dts = {specs[s].step(str(t.convention)) for s in t.train_scenes}
    if len(dts) > 1:
        raise ConfigError(f"train_scenes mix time steps {sorted(dts)} under convention={t.convention}; use convention=benchmark")
    dt = dts.pop()
    with torch.device("meta"):  # the constructor's checks of the network's keys, without its memory
        SocialLSTM(1, **_net_keys(c), dt=dt, dtype=DTYPES[str(t.dtype)], device="meta")
    for s in dict.fromkeys([*t.train_scenes, *t.val_scenes]):
        check_files(specs[s], t.data_root, ROOT_KEY, DATASETS_KEY)
    if t.checkpoint:
        _check_output_file("checkpoint", t.checkpoint)
    return {"schedule": sched, "dt": dt}


def _net_keys(c) -> dict:
    """The ``lstm`` group's network keys as the config holds them (the constructor checks types and ranges)."""
    keys = ("obs_len", "pred_len", "embed", "hidden", "pooling", "grid", "neighbourhood")
    out = {k: c.get(k) for k in keys if c.get(k) is not None}
    out["noise_std"] = c.get("noise_std", 0.1)
    return out


def train(cfg: DictConfig, out_dir: str | Path) -> tuple[SocialLSTM, "object", Path]:
    """Validate ``cfg``, build the data, train, save. Returns (model, history, checkpoint path)."""
    checked = check_config(cfg)
    sched = checked["schedule"]
    c = cfg.lstm
    ckpt = Path(cfg.checkpoint) if cfg.get("checkpoint") else Path(out_dir) / f"lstm_{c.get('pooling', 'none')}.pt"
    _check_output_file("checkpoint", ckpt)  # before any work (the default: in the run folder)
    model = SocialLSTM(1, **_net_keys(c), dt=checked["dt"], dtype=DTYPES[str(cfg.dtype)], device=str(cfg.device),
                       seed=int(cfg.seed))
    length = model.obs_len + model.pred_len
    tr = _windows(cfg.train_scenes, str(cfg.train_part), cfg, length)
    if tr is None:
        raise ConfigError(f"train_scenes {list(cfg.train_scenes)} give no window of {length} steps")
    if cfg.get("max_windows") is not None:
        tr = subsample(tr, int(cfg.max_windows))
    va = _windows(cfg.val_scenes, str(cfg.val_part), cfg, length) if list(cfg.val_scenes) else None
    if model.pooling == "none":  # independent pedestrians: one sequence each, no padding
        tr = per_agent(tr).unsqueeze(2)
        va = None if va is None else per_agent(va).unsqueeze(2)
    log.info("training %s on %d windows (%s), validating on %s", model.pooling, tr.shape[0], list(cfg.train_scenes),
             "none" if va is None else f"{va.shape[0]} windows")
    if "patience" in sched and va is None:
        raise ConfigError(f"lstm.schedule=early_stopping: val_scenes {list(cfg.val_scenes)} give no validation window")
    hist = train_lstm(model, tr, **sched, val_windows=va, seed=int(cfg.seed), progress=bool(cfg.progress))
    if "patience" in sched:
        log.info("early stopping: %d epochs run, best validation loss %.5f at epoch %d (weights restored)",
                 len(hist), hist.attrs["best_val_loss"], hist.attrs["best_epoch"])
    try:
        save_checkpoint(model, ckpt, hist)
    except BaseException:
        Path(str(ckpt) + ".tmp").unlink(missing_ok=True)  # save_checkpoint's temporary file
        raise
    atomic_write_csv(hist, Path(out_dir) / "history.csv")
    return model, hist, ckpt


def _say(kind: str, msg) -> None:
    """The one line a user sees on stderr."""
    print(f"{PROG}: {kind}: {' '.join(str(msg).split())}", file=sys.stderr, flush=True)


@hydra.main(version_base=None, config_path=CONF_DIR, config_name="train_lstm")
def _app(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    out_dir = HydraConfig.get().runtime.output_dir
    try:
        check_config(cfg)  # threads among the rest, before it is used
        if cfg.get("threads"):
            torch.set_num_threads(int(cfg.threads))
        _, hist, ckpt = train(cfg, out_dir)
    except ConfigError as e:
        _say(CONFIG, e)
        raise SystemExit(2)
    except DataFormatError as e:
        _say(DATA, e)
        raise SystemExit(2)
    print(hist.to_string(index=False))
    print(f"checkpoint: {ckpt}")


# --------------------------------------------------------------------------------------------
# start-up check: compose and check the command line's configuration before Hydra starts


def precheck(argv: list[str]) -> tuple[str, str] | None:
    """Compose and check the configuration of every job the command line asks for (a ``-m`` sweep
    is expanded) and read its data files (strictly: :func:`~dslearn.data.ethucy.read_trajectories`;
    ~0.2 s for every default scene); ``(what, message)`` of the first refusal or ``None``. Options
    Hydra handles itself (``--help``, ``--cfg``, ...) skip the check."""
    from hydra import compose, initialize_config_dir

    from dslearn.app.options import (
        _MULTIRUN_FLAGS,
        _NO_CHECK_FLAGS,
        _check_group_option,
        _check_output_dir,
        _friendly,
        _hydra_message,
        _is_group,
        parse_override,
    )

    if any(a.split("=")[0] in _NO_CHECK_FLAGS or a in ("--help", "-h") for a in argv):
        return None
    parsed = []
    for line in (a for a in argv if not a.startswith("-")):
        try:
            parsed.append(parse_override(line))
        except Exception as e:  # noqa: BLE001
            msg = _hydra_message(e).split(" See https://hydra.cc")[0]
            return CONFIG, f"{line}: not a valid override ({msg}); write key=value, group=option or +key=value to add"
    try:
        for o in parsed:
            if o.key_or_group in ("hydra.run.dir", "hydra.sweep.dir"):
                _check_output_dir(o.key_or_group, str(o.value()))
            elif o.key_or_group.startswith("hydra"):
                continue
            elif _is_group(o.key_or_group) and not o.is_sweep_override() and not o.is_delete():
                _check_group_option(o.key_or_group, o.value())
    except ConfigError as e:
        return CONFIG, str(e)
    user = [o for o in parsed if not o.key_or_group.startswith("hydra")]
    sweeps = [o.input_line for o in user if o.is_sweep_override()]
    if sweeps and not any(a in _MULTIRUN_FLAGS for a in argv):
        return CONFIG, (f"{sweeps[0]} is a sweep (one job per value); add -m (--multirun) to run them, "
                        f"or write {sweeps[0].split('=', 1)[0]}=[a,b] for a list value")
    if sweeps:
        from hydra._internal.core_plugins.basic_sweeper import BasicSweeper

        combos = BasicSweeper.split_arguments(user, None)[0]
    else:
        combos = [[o.input_line for o in user]]
    read: set = set()
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        base = None
        for i, combo in enumerate(combos):
            where = f" (sweep job {i}: {' '.join(combo)})" if len(combos) > 1 else ""
            try:
                cfg = compose("train_lstm", overrides=list(combo))
                check_config(cfg)
                specs = task_datasets(cfg)
                for n in dict.fromkeys([*cfg.train_scenes, *cfg.val_scenes]):
                    key = (specs[n], cfg.get("data_root"), str(cfg.convention))
                    if key not in read:
                        _load(cfg, n)
                        read.add(key)
            except ConfigError as e:
                return CONFIG, f"{e}{where}"
            except DataFormatError as e:
                return DATA, str(e)
            except Exception as e:  # noqa: BLE001 - Hydra/OmegaConf composition errors
                if base is None:
                    try:
                        base = compose("train_lstm")
                    except Exception:  # noqa: BLE001
                        base = None
                return CONFIG, f"{_friendly(e, base)}{where}"
    return None


def _yaml_keys(path: Path) -> list[tuple[str, str, str]]:
    """``(key, value, comment)`` of each top-level ``key: value  # comment`` line of a config file."""
    import re

    out = []
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError:
        return out
    for ln in lines:
        m = re.match(r"^([a-z_]+):\s*([^#]*?)\s*(?:#\s*(.*))?$", ln)
        if m and m.group(1) not in ("defaults", "hydra") and m.group(2):
            out.append((m.group(1), m.group(2), m.group(3) or ""))
    return out


def help_text(width: int = 100) -> str:
    """``dslearn-train-lstm --help``: what it does, its keys (with defaults), the data sets, outputs."""
    from dslearn import __version__

    conf = Path(CONF_DIR)

    def line(name: str, text: str, indent: int = 2, col: int = 28) -> str:
        import textwrap

        head = " " * indent + name
        parts = textwrap.wrap(text, max(20, width - col)) or [""]
        if len(head) >= col:  # a long key=value: its text on the next lines
            return "\n".join([head] + [" " * col + p for p in parts if p])
        return "\n".join([(head + " " * (col - len(head)) + parts[0]).rstrip()] + [" " * col + p for p in parts[1:]])

    out = [
        f"{PROG} {__version__}: train one LSTM encoder-decoder or Social-LSTM on ETH/UCY windows and save",
        "a checkpoint (for model=lstm / model=social_lstm and the ETH/UCY studies).",
        "",
        "usage:",
        f"  {PROG} [key=value ...]",
        "",
        "examples:",
        f"  {PROG}                          the paper's defaults (obs 2, pred 10, 50 epochs, batch 8)",
        f"  {PROG} lstm.schedule=early_stopping lstm.epochs=200 lstm.patience=10",
        "                                              stop on the loss of val_scenes, keep the best weights",
        f"  {PROG} lstm.pooling=social lstm.epochs=5 train_scenes=[zara1,zara2] val_scenes=[zara3] \\",
        "      checkpoint=slstm.pt                     a Social-LSTM on two scenes, validated on a third",
        "",
        "keys (key=value; default shown):",
    ]
    out += [line(f"{k}={v}", c) for k, v, c in _yaml_keys(conf / "train_lstm.yaml")]
    out += ["", "network and schedule (lstm.<key>=value; conf/lstm/default.yaml):"]
    out += [line(f"lstm.{k}={v}", c) for k, v, c in _yaml_keys(conf / "lstm" / "default.yaml")]
    scenes = sorted(p.stem for p in (conf / "dataset").glob("*.yaml"))
    out += [
        "",
        "data sets (train_scenes / val_scenes name them): " + ", ".join(scenes),
        "  their files are read from data_root, else $DSLEARN_ETHUCY_ROOT, else ../shared/data/eth_ucy beside",
        "  the repository; add a data set with +dataset@datasets.<name>=<name> (a YAML in conf/dataset/).",
        "",
        "outputs: outputs/train_lstm/<date_time>/ (or hydra.run.dir=DIR): the checkpoint (lstm_<pooling>.pt,",
        "  or checkpoint=PATH; load with dslearn.models.lstm.load_checkpoint) and history.csv (loss per epoch).",
        "",
        f"more: {PROG} --cfg job [overrides] prints the composed config; --hydra-help lists Hydra's own options.",
        "Exit codes: 0 ok, 2 bad input (one line naming the key, before any work), 130 Ctrl-C, 1 other.",
    ]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> None:
    """The ``dslearn-train-lstm`` console script (``argv`` defaults to ``sys.argv[1:]``)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if any(a in ("--help", "-h") for a in argv):
        try:
            print(help_text())
        except BrokenPipeError:  # e.g. | head
            sys.stdout = open(os.devnull, "w")
        return
    if "--version" in argv:
        from dslearn import __version__

        print(f"{PROG} (dslearn) {__version__}")
        return
    err = precheck(argv)
    if err is not None:
        _say(*err)
        raise SystemExit(2)
    old = sys.argv
    sys.argv = [old[0] if old else PROG, *argv]
    try:
        _app()
    finally:
        sys.argv = old


if __name__ == "__main__":
    main()
