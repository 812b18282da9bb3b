r"""A recorded data set (ETH/UCY, or any set of files in its text format) as a scenario of the matrix.

The files are read strictly (:func:`dslearn.data.datasets.load_dataset`: ``frame ped x y`` lines; a malformed
line is a :class:`~dslearn.errors.ConfigError` naming ``file:line``), cut into tracking episodes of
``episodes.agents`` interacting pedestrians over ``episodes.steps`` steps of ``episodes.dt`` seconds
(:func:`dslearn.data.episodes.extract_episodes`, as the real-data tracking study does) and split into a
training and a test pool (:func:`dslearn.data.episodes.split_episodes`: ``time`` = the last
``test_fraction`` of each file's time range is the test period, no moment in both pools; ``random``).
The sensors are Yu et al.'s LiDAR-like network placed around the data set's extent
(:func:`dslearn.sim.real.arena_network`), which measures the recorded positions with simulated noise, one
random stream per episode (:func:`dslearn.sim.scenario.measure`).

Which recorded episodes a run gets: the training pool in the order :func:`split_episodes` shuffles it with the
run's ``seed``, the test pool in an order drawn from the same seed; a run asking for ``n`` episodes of a pool
gets its first ``n`` (so test episode ``i`` is the same whatever the number asked), and asking for more than
the pool holds is refused with the pool's size. Unlike a simulator, the scenario knows which pool a draw
comes from: :meth:`RecordedScenario.sample` takes ``split`` (``train`` or ``test``), and
:func:`dslearn.sim.scenario.sample_split` passes it to every scenario whose spec says ``source="recorded"``.

The data set's folder: the data set's ``root`` if given (``pkg://<package>/<folder>`` = a folder shipped inside
an installed package, e.g. ``pkg://dslearn.data/corridor``), else ``data_root``, else ``$DSLEARN_ETHUCY_ROOT``
or the default data folder (:func:`dslearn.data.ethucy.default_root`). A folder or file that is missing is a
:class:`~dslearn.errors.ConfigError` naming the key that sets the folder, raised when the scenario is built
(at composition, before any work).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from importlib import resources
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from dslearn.data.datasets import CONVENTIONS, check_dataset, dataset_spec, load_dataset
from dslearn.data.episodes import CRITERIA, EpisodeSet, extract_episodes, split_episodes
from dslearn.episodes import Episodes, ScenarioSpec
from dslearn.errors import ConfigError, DataFormatError, check_choice, check_integer, check_keys, check_positive
from dslearn.network import SensorNetwork
from dslearn.sim.real import arena_network, scene_extent
from dslearn.sim.scenario import measure
from dslearn.streams import Streams, stream_seed
from dslearn.types import StepContext, agents

#: the pools a recorded scenario draws from
SPLITS = ("train", "test")
#: how the episodes are split into the two pools (:func:`dslearn.data.episodes.split_episodes`)
SPLIT_MODES = ("time", "random")
#: a data set's root inside an installed package: ``pkg://<package>/<folder>``
PACKAGE_ROOT = "pkg://"


@dataclasses.dataclass(frozen=True)
class EpisodeCut:
    """How the recorded tracks are cut into episodes (``scenario.episodes``; the real-data tracking study's
    ``task.agents steps dt max_dist stride criterion min_speed split test_fraction``, the same defaults)."""

    agents: int = 2
    steps: int = 11
    dt: float = 0.4
    max_dist: float = 3.0
    stride: int = 4
    criterion: str = "mutual"
    min_speed: float = 0.3
    split: str = "time"
    test_fraction: float = 0.2


@dataclasses.dataclass(frozen=True)
class ArenaCut:
    """The LiDAR-like sensors around the data set's extent (``scenario.network``; :func:`arena_network`)."""

    num_sensors: int = 4
    k_nearest: int = 2
    sensing_range: float = 8.0
    meas_std: float = 0.2
    margin: float = 0.0


def _settings(cls, values: Mapping | None, prefix: str):
    """``cls`` from a mapping of its fields (``None``: the defaults); ConfigError naming ``prefix.<key>``."""
    return cls() if values is None else cls(**check_keys(prefix, values, [f.name for f in dataclasses.fields(cls)]))


def check_window(c, prefix: str = "scenario.episodes") -> None:
    """The settings every cut of a recording has: ``steps``, ``stride``, ``dt``, ``split``, ``test_fraction``."""
    check_integer(f"{prefix}.steps", c.steps, 2)
    check_integer(f"{prefix}.stride", c.stride, 1)
    check_positive(f"{prefix}.dt", c.dt)
    check_choice(f"{prefix}.split", c.split, SPLIT_MODES)
    check_positive(f"{prefix}.test_fraction", c.test_fraction)
    if not c.test_fraction < 1.0:
        raise ConfigError(f"{prefix}.test_fraction={c.test_fraction!r} must lie in (0, 1)")


def check_cut(c: EpisodeCut, prefix: str = "scenario.episodes") -> None:
    check_integer(f"{prefix}.agents", c.agents, 2)
    check_window(c, prefix)
    check_positive(f"{prefix}.max_dist", c.max_dist)
    check_positive(f"{prefix}.min_speed", c.min_speed, strict=False)
    check_choice(f"{prefix}.criterion", c.criterion, CRITERIA)


def check_arena(a: ArenaCut, prefix: str = "scenario.network") -> None:
    check_integer(f"{prefix}.num_sensors", a.num_sensors, 1)
    check_integer(f"{prefix}.k_nearest", a.k_nearest, 1)
    check_positive(f"{prefix}.sensing_range", a.sensing_range)
    check_positive(f"{prefix}.meas_std", a.meas_std)
    check_positive(f"{prefix}.margin", a.margin, strict=False)


def package_folder(root: str, key: str) -> str:
    """The folder of ``pkg://<package>/<folder>`` (inside the installed package); ConfigError naming ``key``."""
    rest = root[len(PACKAGE_ROOT):]
    package, _, sub = rest.partition("/")
    try:
        base = resources.files(package)
    except (ModuleNotFoundError, TypeError, ValueError):
        raise ConfigError(f"{key}={root!r}: no installed package {package!r} (pkg://<package>/<folder>)") from None
    folder = Path(str(base.joinpath(sub) if sub else base))
    if not folder.is_dir():
        raise ConfigError(f"{key}={root!r}: package {package!r} has no folder {sub!r}")
    return str(folder)


class RecordedScenario:
    r"""The episodes of a recorded data set, measured by a LiDAR-like network around it.

    Args:
        dataset: the data set's values (the keys of ``conf/dataset``: ``label files root frame_step dt fps units
            val_first_frame``; :func:`dslearn.data.datasets.check_dataset`).
        name: the scenario's label in the tables.
        data_root: the folder of the data set's files when its ``root`` is null (``None``:
            ``$DSLEARN_ETHUCY_ROOT`` or the default data folder).
        convention: ``physical`` (a row step is ``frame_step / fps``, the tracking studies') or ``benchmark``.
        episodes: how the tracks are cut and split (:class:`EpisodeCut`'s fields).
        network: the sensors (:class:`ArenaCut`'s fields).
        seed: the run seed (the order of the pools).
    """

    #: the scenario places its own sensors (the run's ``network`` part is not used)
    owns_network = True

    def __init__(self, dataset: Mapping, name: str = "recorded", data_root: str | None = None,
                 convention: str = "physical", episodes: Mapping | None = None, network: Mapping | None = None,
                 seed: int = 0):
        if not isinstance(dataset, Mapping):
            raise ConfigError(f"scenario.dataset={dataset!r} must be a mapping of a data set's values "
                              "(label, files, root, frame_step, dt, fps, units, val_first_frame)")
        check_dataset("dataset", dataset, "scenario.dataset")
        if not dataset.get("files"):
            raise ConfigError("scenario.dataset.files must name at least one file")
        check_choice("scenario.convention", convention, CONVENTIONS)
        self.cut = self._cut(episodes)
        arena = _settings(ArenaCut, network, "scenario.network")
        check_arena(arena)
        check_integer("scenario.seed", seed, 0)
        self.name, self.seed, self.convention = str(name), int(seed), str(convention)
        values = dict(dataset)
        root = values.get("root")
        if isinstance(root, str) and root.startswith(PACKAGE_ROOT):
            values["root"] = package_folder(root, "scenario.dataset.root")
        spec = dataset_spec("dataset", values)
        try:
            scene = load_dataset(spec, data_root, self.convention, root_key="scenario.data_root",
                                 datasets_key="scenario")
        except DataFormatError as e:
            raise ConfigError(f"scenario.dataset.files: {e}") from None
        self.scene = dataclasses.replace(scene, name=self.name)
        c = self.cut
        self.episodes: EpisodeSet = self._extract()
        train, test = split_episodes(self.episodes, c.split, c.test_fraction, None, self.seed)
        if len(test) == 0:
            raise ConfigError(
                f"scenario {self.name}: the data set gives {len(self.episodes)} episodes of {self._what} "
                f"and none in the test pool; {self._lower} or raise scenario.episodes.test_fraction")
        order = np.random.default_rng(stream_seed(self.seed, "recorded_test_order", self.name)).permutation(len(test))
        self.pools = {"train": np.asarray(train, dtype=np.int64), "test": np.asarray(test, dtype=np.int64)[order]}
        self.area = scene_extent(torch.tensor(self.scene.df[["x", "y"]].to_numpy()))
        self.network: SensorNetwork = arena_network(self.area, arena.num_sensors, arena.k_nearest,
                                                    arena.sensing_range, arena.meas_std, arena.margin,
                                                    key="scenario.network")

    # how the recorded tracks become episodes (a subclass cuts them otherwise: dslearn.sim.crowd) ------------
    @staticmethod
    def _cut(episodes: Mapping | None) -> EpisodeCut:
        cut = _settings(EpisodeCut, episodes, "scenario.episodes")
        check_cut(cut)
        return cut

    def _extract(self) -> EpisodeSet:
        c = self.cut
        return extract_episodes(self.scene, c.agents, c.steps, c.dt, c.max_dist, c.stride, c.criterion, c.min_speed)

    @property
    def _what(self) -> str:  # what an episode holds, for the messages
        return f"{self.cut.agents} pedestrians"

    _lower = "lower scenario.episodes.max_dist/min_speed/stride/steps"

    # what model factories read of a scenario -------------------------------------------------------
    @property
    def num_agents(self) -> int:
        return int(self.cut.agents)

    @property
    def state_dim(self) -> int:
        return 4 * self.num_agents

    @property
    def dt(self) -> float:
        return float(self.cut.dt)

    @property
    def steps(self) -> int:
        return int(self.cut.steps)

    @property
    def spec(self) -> ScenarioSpec:
        """``A`` recorded pedestrians measured by range-limited position sensors, state ``[p, v]`` per agent; the
        sizes of the training and test pools (known once the scenario is built, at composition)."""
        return ScenarioSpec(self.name, "position", self.num_agents, "pv2d", self.dt, self.steps, source="recorded",
                            pools=(self.pool_size("train"), self.pool_size("test")))

    def ctx(self) -> StepContext:
        return StepContext(dt=self.dt)

    def positions(self, states: Tensor) -> Tensor:
        """``(B, K+1, 4A) -> (B, K+1, A, 2)``."""
        return agents(states)[..., :2]

    # the episodes -----------------------------------------------------------------------------------
    def pool_size(self, split: str) -> int:
        check_choice("split", split, SPLITS)
        return len(self.pools[split])

    def chosen(self, split: str, num: int) -> np.ndarray:
        """Indices into :attr:`episodes` of the first ``num`` episodes of pool ``split``."""
        check_choice("split", split, SPLITS)
        pool = self.pools[split]
        if isinstance(num, bool) or not isinstance(num, int) or num < 0:
            raise ConfigError(f"the number of {split} episodes ({num!r}) must be an integer >= 0")
        if num > len(pool):
            raise ConfigError(
                f"scenario {self.name}: {num} {split} episodes asked for, its {split} pool holds {len(pool)} "
                f"(episodes of {self._what} over {self.cut.steps} steps, split "
                f"{self.cut.split} with test_fraction {self.cut.test_fraction:g}); ask for at most {len(pool)} "
                f"(task.{split}_episodes) or change scenario.episodes")
        return pool[:num]

    def meta(self, split: str, num: int):
        """The recorded episodes behind the first ``num`` of pool ``split``: ``file, peds, t0, t1, ...``."""
        return self.episodes.meta.iloc[self.chosen(split, num)].reset_index(drop=True)

    def sample(self, num: int, network: SensorNetwork, generator: torch.Generator | Streams,
               split: str | None = None) -> Episodes:
        """The first ``num`` episodes of pool ``split`` (``train`` or ``test``), measured by ``network`` with
        noise from ``generator`` (per-episode :class:`~dslearn.streams.Streams`: episode ``i``'s noise depends
        only on its own stream)."""
        return measure(self.pool_states(split, num), network, generator)

    def pool_states(self, split: str | None, num: int) -> Tensor:
        """The true states ``(num, K+1, 4A)`` of the first ``num`` episodes of pool ``split``."""
        if split is None:
            raise ValueError(f"{type(self).__name__}.sample: a recorded scenario draws from a pool, "
                             f"split={list(SPLITS)} (dslearn.sim.scenario.sample_split passes it)")
        return self.episodes.states[torch.as_tensor(self.chosen(split, num), dtype=torch.long)]
