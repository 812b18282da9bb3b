r"""Yu et al. synthetic study (Tables I–II, Fig. 2): learned vs parametric motion models
inside a distributed information-form EKF.

Python use, without Hydra::

    from dslearn.studies.yu import YuStudy
    study = YuStudy.from_options(model="gp_increment", consensus="hybrid", train_episodes=50)
    df = study.run()          # tidy DataFrame, one row per episode x node x metric
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd
import torch
from omegaconf import DictConfig

from dslearn.fusion.strategies import FUSIONS, make_fusion
from dslearn.fusion.weights import consensus_weights
from dslearn.progress import evaluation_bar, training_bar
from dslearn.errors import ConfigError, check_choice, check_positive
from dslearn.models import (
    ConstantVelocity,
    GPMotionModel,
    GPObservation,
    LinearPositionObservation,
    SocialForce,
)
from dslearn.models.base import MotionModel, ObservationModel
from dslearn.models.social_force import SOFTENING
from dslearn.sim.network import SensorNetwork, make_network
from dslearn.sim.scenario import SocialForceScenario, episode_streams
from dslearn.filters.distributed import initial_belief, prediction_error, track, tracking_metrics
from dslearn.types import JITTER

log = logging.getLogger(__name__)

MODEL_KINDS = ("lin", "sfm", "gp", "gp_aggregated")
DTYPES = {"float64": torch.float64, "float32": torch.float32}


def _resolve_device(device: str) -> torch.device:
    check_choice("device", str(device).split(":")[0], ("cpu", "cuda"))
    if str(device).startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError("device=cuda was asked for but no CUDA device is available; use device=cpu")
    return torch.device(device)


def build_scenario(c: Any) -> SocialForceScenario:
    return SocialForceScenario(
        desired_velocities=list(c.desired_velocities),
        start_corners=list(c.start_corners),
        start_size=c.start_size,
        tau=c.tau,
        alpha=c.alpha,
        beta=c.beta,
        process_std=c.process_std,
        horizon=c.horizon,
        dt=c.dt,
        area=list(c.area),
        softening=float(c.get("softening", SOFTENING)),
    )


def build_network(c: Any) -> SensorNetwork:
    return make_network(
        num_sensors=c.num_sensors,
        num_comm=c.num_comm,
        area=list(c.area),
        positions=None if c.get("positions") is None else [list(p) for p in c.positions],
        comm_radius=c.get("comm_radius"),
        edges=None if c.get("edges") is None else [list(e) for e in c.edges],
        k_nearest=c.get("k_nearest"),
        sensing_range=c.sensing_range,
        meas_std=c.meas_std,
        seed=c.get("seed", 0),
    )


def build_motion_model(c: Any, scenario: SocialForceScenario, num_nodes: int, dtype, device) -> MotionModel:
    """Motion model from its config: ``kind`` in ``lin | sfm | gp | gp_aggregated``; ``name`` is
    the label (``lin``, ``sfm``, or any name starting with ``gp``). ``gp_aggregated`` is the GP
    whose per-node predictions are fused by a product-of-experts rule (PoE/gPoE/BCM/rBCM) across
    all nodes, see :mod:`dslearn.models.aggregated`."""
    name = str(c.name)
    kind = str(c.get("kind", name))
    check_choice("model.kind", kind, MODEL_KINDS)
    if kind in ("gp", "gp_aggregated") and not name.startswith("gp"):
        raise ConfigError(f"model.name={name!r}: a GP variant's name must start with 'gp'")
    if kind in ("lin", "sfm") and name != kind:
        raise ConfigError(f"model.name={name!r} must be {kind!r} for model.kind={kind!r}")
    if kind == "lin":
        return ConstantVelocity(scenario.num_agents, c.noise_std).to(device)
    if kind == "sfm":
        s = scenario.sfm
        return SocialForce(s.desired.tolist(), s.tau.tolist(), s.alpha.tolist(), s.beta.tolist(), c.noise_std, s.softening).to(device)
    if kind == "gp_aggregated":
        from dslearn.models.aggregated import build_aggregated_motion

        return build_aggregated_motion(c, scenario.state_dim, num_nodes, dtype, device)
    return GPMotionModel(
        scenario.state_dim,
        num_nodes,
        outputscale=c.outputscale,
        lengthscale=c.lengthscale,
        noise_std=c.noise_std,
        mean=c.mean,
        noise=c.noise,
        jacobian=c.jacobian,
        fit_every=c.fit_every,
        fit_iters=c.fit_iters,
        fit_lr=c.fit_lr,
        capacity=int(c.get("capacity", 256)),  # initial per-node buffer (grows in chunks of 128)
        dtype=dtype,
        device=device,
        # scalable variants (dslearn.learning.sparse; conf/model/gp_{window,sgpr,ssgp}.yaml)
        variant=str(c.get("variant", "exact")),
        noise_fading=float(c.get("noise_fading", 0.9)),
        **{k: c[k] for k in ("window", "inducing", "features", "seed") if c.get(k) is not None},
    )


def build_observation(c: Any, num_nodes: int, dtype, device) -> ObservationModel:
    check_choice("observation.name", c.name, ("linear", "gp"))
    if c.name == "linear":
        return LinearPositionObservation(c.noise_std)
    return GPObservation(
        num_nodes, c.outputscale, c.lengthscale, c.noise_std, c.mean, c.noise, dtype=dtype, device=device
    )


@dataclass
class YuStudy:
    """One run of the synthetic study: a motion model x a fusion strategy on one data size."""

    cfg: DictConfig

    # construction ----------------------------------------------------------------------
    @classmethod
    def from_config(cls, cfg: DictConfig) -> "YuStudy":
        study = cls(cfg)
        study.validate()
        return study

    @classmethod
    def from_options(cls, model: str = "gp", consensus: str = "hybrid", **overrides) -> "YuStudy":
        """Compose the default configuration (``conf/``) with a few options, without Hydra's app."""
        from hydra import compose, initialize_config_dir

        from dslearn.config_schema import CONF_DIR

        conf_dir = str(CONF_DIR)
        ov = [f"model={model}", f"consensus={consensus}"]
        for k, v in overrides.items():
            key = k if "." in k else {"train_episodes": "data.train_episodes", "test_episodes": "data.test_episodes"}.get(k, k)
            ov.append(f"{key}={v}")
        with initialize_config_dir(config_dir=conf_dir, version_base=None):
            cfg = compose("config", overrides=ov)
        return cls.from_config(cfg)

    def validate(self) -> None:
        """Check every field before any work starts (ConfigError names the field)."""
        c = self.cfg
        check_choice("dtype", c.dtype, tuple(DTYPES))
        _resolve_device(c.device)
        check_choice("consensus.name", c.consensus.name, FUSIONS)
        check_choice("consensus.weights", c.consensus.weights, ("uniform", "metropolis", "max_degree"))
        it = c.consensus.iterations
        if not isinstance(it, int) or it < 0:
            raise ConfigError(f"consensus.iterations={it!r} must be an integer >= 0")
        d = c.data
        if not isinstance(d.train_episodes, int) or d.train_episodes < 0:
            raise ConfigError(f"data.train_episodes={d.train_episodes!r} must be an integer >= 0")
        if not isinstance(d.test_episodes, int) or d.test_episodes < 1:
            raise ConfigError(f"data.test_episodes={d.test_episodes!r} must be an integer >= 1")
        for k in self.checkpoints():
            if k > d.train_episodes or k < 0:
                raise ConfigError(
                    f"data.eval_at contains {k}, but only data.train_episodes={d.train_episodes} training "
                    f"episodes are run; use values in 0..{d.train_episodes} or raise data.train_episodes"
                )
        min_train = d.get("min_train_episodes", 0) or 0
        if d.train_episodes < min_train:
            raise ConfigError(
                f"data.train_episodes={d.train_episodes} is too few for study {c.study!r}: it needs >= {min_train}"
            )
        # building validates names, shapes, positivity and connectivity (network first)
        self.build()
        check_positive("model.noise_std", c.model.noise_std)
        check_positive("observation.noise_std", c.observation.noise_std)
        check_positive("filter.prior_pos_std", c.filter.prior_pos_std)
        check_positive("filter.prior_vel_std", c.filter.prior_vel_std)
        if c.filter.get("learn_gate_std") is not None:
            check_positive("filter.learn_gate_std", c.filter.learn_gate_std)

    def checkpoints(self) -> list[int]:
        ev = self.cfg.data.get("eval_at")
        if ev is None:
            return [int(self.cfg.data.train_episodes)]
        return sorted({int(v) for v in ev})

    def build(self):
        c = self.cfg
        dtype, device = DTYPES[c.dtype], _resolve_device(c.device)
        scenario = build_scenario(c.scenario)
        network = build_network(c.network)
        s = network.num_nodes
        model = build_motion_model(c.model, scenario, s, dtype, device)
        obs = build_observation(c.observation, s, dtype, device)
        w = consensus_weights(network.adjacency, c.consensus.weights)
        fusion = make_fusion(c.consensus.name, w, c.consensus.iterations, c.consensus.omega)
        return scenario, network, model, obs, fusion

    # running -----------------------------------------------------------------------------
    def sample(self, scenario: SocialForceScenario, network: SensorNetwork, dtype, device):
        """The (test, train) episodes of this run, on ``device`` in ``dtype``. One random stream per
        episode (:func:`~dslearn.sim.scenario.episode_streams`), so episode ``i`` of either set is
        the same whatever the number of training or test episodes."""
        seed, d = int(self.cfg.seed), self.cfg.data
        test = scenario.sample(d.test_episodes, network, episode_streams(seed, "test", 0, d.test_episodes))
        train = scenario.sample(d.train_episodes, network, episode_streams(seed, "train", 0, d.train_episodes))
        return _to(test, dtype, device), _to(train, dtype, device)

    def run(self, progress: bool = False) -> pd.DataFrame:
        """Train online on the training episodes, evaluate on the test episodes.

        Returns a tidy DataFrame (one row per checkpoint x test episode x node x metric).
        """
        c = self.cfg
        if c.get("threads"):
            torch.set_num_threads(int(c.threads))
        torch.manual_seed(int(c.seed))
        scenario, network, model, obs, fusion = self.build()
        dtype, device = DTYPES[c.dtype], _resolve_device(c.device)
        ctx = scenario.ctx()
        test, train = self.sample(scenario, network, dtype, device)

        def init(ep):
            return initial_belief(ep, network, ctx.dt, fusion, scenario.area, c.filter.prior_pos_std, c.filter.prior_vel_std)

        learnable = model.learnable or obs.learnable
        gate = c.filter.get("learn_gate_std")
        checkpoints = self.checkpoints() if learnable else [int(c.data.train_episodes)]
        frames, seen = [], 0
        t0 = time.perf_counter()
        jitter0 = JITTER.count
        bar = training_bar(max(checkpoints), scenario.steps, c.model, enable=progress and learnable, desc=f"train {c.model.name}/{fusion.name}")
        tbar = evaluation_bar(checkpoints, scenario.steps, c.model, enable=progress, learnable=learnable, desc="test", position=1)
        for k in checkpoints:
            while learnable and seen < k:
                ep = train.select(slice(seen, seen + 1))
                track(ep, network, model, obs, fusion, ctx, init(ep), learn=True, learn_gate_std=gate)
                seen += 1
                bar.update(1)
                if getattr(model, "fit_every", 0) and seen % model.fit_every == 0:
                    model.fit()
            frames.append(self._evaluate(test, network, model, obs, fusion, ctx, init(test), k, scenario))
            tbar.update(1)
            log.info("evaluated %s/%s after %d training episodes (%.1fs)", c.model.name, fusion.name, k, time.perf_counter() - t0)
        bar.close()
        tbar.close()
        df = pd.concat(frames, ignore_index=True)
        df.attrs["jitter_events"] = JITTER.count - jitter0
        self.model, self.network, self.fusion = model, network, fusion
        return df

    @torch.no_grad()
    def _evaluate(self, test, network, model, obs, fusion, ctx, init, seen, scenario) -> pd.DataFrame:
        c = self.cfg
        res = track(test, network, model, obs, fusion, ctx, init, learn=False)
        metrics = tracking_metrics(res, test.states)
        metrics["pred_err"] = prediction_error(model, test.states, network.num_nodes, ctx, per_node=model.learnable)
        s, b = metrics["track_err"].shape
        rows = []
        kinds = ["sensor" if network.is_sensor[i] else "comm" for i in range(s)]
        for name, val in metrics.items():
            v = val.detach().cpu().double()
            frame = pd.DataFrame(
                {
                    "node": [network.names[i] for i in range(s) for _ in range(b)],
                    "node_kind": [kinds[i] for i in range(s) for _ in range(b)],
                    "episode": list(range(b)) * s,
                    "metric": name,
                    "value": v.reshape(-1).numpy(),
                }
            )
            rows.append(frame)
        df = pd.concat(rows, ignore_index=True)
        df.insert(0, "model", c.model.name)
        df.insert(1, "consensus", fusion.name)
        df.insert(2, "omega", fusion.omega_label if fusion.uses_omega else "-")
        df.insert(3, "iterations", fusion.iterations if fusion.name not in ("individual", "centralized") else 0)
        df.insert(4, "weights", c.consensus.weights)
        df.insert(5, "train_episodes", int(c.data.train_episodes))
        df.insert(6, "test_episodes", int(c.data.test_episodes))
        df.insert(7, "train_seen", int(seen))
        return df


def _to(ep, dtype, device):
    from dslearn.sim.scenario import Episodes

    return Episodes(ep.states.to(device, dtype), ep.meas.to(device, dtype), ep.visible.to(device))


def run(cfg: DictConfig) -> pd.DataFrame:
    """Task entry point for ``dslearn-run`` (see :mod:`dslearn.run`)."""
    study = YuStudy.from_config(cfg)
    return study.run(progress=bool(cfg.get("progress", False)))


def report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path) -> str:
    """Paper-shaped tables and figures for the Yu study."""
    from dslearn.plotting.yu import yu_report

    return yu_report(results, summary, out_dir)
