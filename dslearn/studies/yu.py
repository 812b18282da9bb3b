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

import pandas as pd
import torch
from omegaconf import DictConfig

from dslearn.compose import build_parts
from dslearn.diagnostics import Diagnostics
from dslearn.errors import ConfigError
from dslearn.filters.distributed import initial_belief
from dslearn.learning.online import OnlineLearner, checkpoints as eval_points
from dslearn.metrics import metric_rows, prediction_error, tracking_metrics
from dslearn.progress import evaluation_bar, training_bar
from dslearn.sim.scenario import sample_split

log = logging.getLogger(__name__)


@dataclass
class YuStudy:
    """One run of the synthetic study: a motion model x a fusion strategy on one data size.
    The parts come from the config groups (:func:`dslearn.compose.build_parts`); the study is the
    protocol: which episodes, when to evaluate, what to record."""

    cfg: DictConfig

    @classmethod
    def from_config(cls, cfg: DictConfig) -> "YuStudy":
        from dslearn.schemas.core import validate_config

        validate_config(cfg)  # keys, types and ranges (dslearn.schemas.core, dslearn.schemas)
        study = cls(cfg)
        study.build()  # then what needs the built parts: shapes and connectivity
        return study

    @classmethod
    def from_options(cls, model: str = "gp", consensus: str = "hybrid", **overrides) -> "YuStudy":
        """Compose the default configuration (``conf/``) with a few options, without Hydra's app."""
        from hydra import compose, initialize_config_dir

        import dslearn.schemas  # noqa: F401  (the task schemas the configs name)
        from dslearn.conf_paths import CONF_DIR

        ov = [f"model={model}", f"consensus={consensus}"]
        for k, v in overrides.items():
            key = k if "." in k else {"train_episodes": "data.train_episodes", "test_episodes": "data.test_episodes"}.get(k, k)
            ov.append(f"{key}={v}")
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
            cfg = compose("config", overrides=ov)
        return cls.from_config(cfg)

    def checkpoints(self) -> list[int]:
        return eval_points(self.cfg.data)

    def build(self):
        parts = build_parts(self.cfg)
        self.parts = parts
        return parts.scenario, parts.network, parts.model, parts.observation, parts.fusion

    def sample(self, scenario, network, dtype, device):
        d = self.cfg.data
        return sample_split(scenario, network, int(self.cfg.seed), d.test_episodes, d.train_episodes, dtype, device)

    def run(self, progress: bool = False, diagnostics=None) -> pd.DataFrame:
        """Train online on the training episodes, evaluate on the test episodes.

        Returns a tidy DataFrame (one row per checkpoint x test episode x node x metric).
        """
        c = self.cfg
        torch.manual_seed(int(c.seed))
        p = build_parts(c)
        self.parts = p
        scenario, network, model, fusion = p.scenario, p.network, p.model, p.fusion
        ctx = scenario.ctx()
        test, train = self.sample(scenario, network, p.dtype, p.device)
        learner = OnlineLearner(
            network, model, p.observation, fusion, ctx,
            init=lambda ep: initial_belief(ep, network, ctx.dt, fusion, scenario.area, c.filter.prior_pos_std, c.filter.prior_vel_std),
            predict_step=p.predict, learn_gate_std=c.filter.get("learn_gate_std"),
        )
        learnable = learner.learnable
        checkpoints = self.checkpoints() if learnable else [int(c.data.train_episodes)]
        t0 = time.perf_counter()
        diag = diagnostics or Diagnostics()
        if model.learns_offline:  # an offline model (the LSTM) learns once, from the training episodes' true tracks
            with diag.timed("fit_offline"):
                model.fit_offline(offline_trajectories(model, train), ctx.dt, seed=int(c.seed))
        model.begin_episodes(test.states)
        bar = training_bar(max(checkpoints), scenario.steps, c.model, enable=progress and learnable, desc=f"train {c.model.name}/{fusion.name}")
        tbar = evaluation_bar(checkpoints, scenario.steps, c.model, enable=progress, learnable=learnable, desc="test", position=1)

        # the filter's prediction step, when not the EKF's, labels the model's rows (gp_increment+ukf)
        step = getattr(p.predict, "name", "ekf")
        model_label = str(c.model.name) if step == "ekf" else f"{c.model.name}+{step}"

        def evaluate(seen: int) -> pd.DataFrame:
            with diag.timed("evaluate"):
                res = learner.estimate(test.measurements)
            metrics = tracking_metrics(res, test.states)
            metrics["pred_err"] = prediction_error(model, test.states, network.num_nodes, ctx, per_node=model.learnable)
            tbar.update(1)
            log.info("evaluated %s/%s after %d training episodes (%.1fs)", c.model.name, fusion.name, seen, time.perf_counter() - t0)
            return metric_rows(
                metrics, network, model=model_label, consensus=fusion.name,
                omega=fusion.omega_label if fusion.uses_omega else "-",
                iterations=fusion.iterations if fusion.name not in ("individual", "centralized") else 0,
                weights=c.consensus.weights, train_episodes=int(c.data.train_episodes),
                test_episodes=int(c.data.test_episodes), train_seen=int(seen),
            )

        df = learner.run(train.measurements, checkpoints, evaluate, on_episode=lambda: bar.update(1))
        diag.timings["train_s"] = round(time.perf_counter() - t0 - diag.timings.get("evaluate_s", 0.0), 3)
        diag.count("train_episodes_seen", learner.seen)
        bar.close()
        tbar.close()
        self.model, self.network, self.fusion = model, network, fusion
        return df


def check_offline(model) -> None:
    """ConfigError unless the synthetic studies can give the offline ``model`` what it learns from
    (``model.train_on`` truth or null: the true tracks)."""
    if (model.train_on or "truth") != "truth":
        raise ConfigError(f"model.train_on={model.train_on}: the synthetic studies train offline models on the true "
                          "tracks of their training episodes (model.train_on=truth or null)")


def offline_trajectories(model, train) -> torch.Tensor:
    """What an offline model learns from in the synthetic study: the true tracks ``(B, K+1, Dx)`` of the
    training episodes (``model.train_on`` truth or null; the filter still sees only measurements)."""
    check_offline(model)
    return train.states


def run(cfg: DictConfig, diagnostics=None) -> pd.DataFrame:
    """Task entry point for ``dslearn-run`` (see :mod:`dslearn.run`)."""
    study = YuStudy.from_config(cfg)
    return study.run(progress=bool(cfg.get("progress", False)), diagnostics=diagnostics)
