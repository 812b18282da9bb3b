r"""Yu et al. synthetic study (Tables I–II, Fig. 2): learned vs parametric motion models
inside a distributed information-form EKF.

Python use (the same defaults as ``dslearn-run``, :mod:`dslearn.api`)::

    from dslearn import api
    study = api.yu_study(model="gp_increment", consensus="hybrid", train_episodes=50)
    df = study.run()          # tidy DataFrame, one row per episode x node x metric
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import pandas as pd
import torch

from dslearn.diagnostics import Diagnostics
from dslearn.errors import ConfigError
from dslearn.io import attach_artifact
from dslearn.filters.distributed import FilterSettings, initial_belief
from dslearn.filters.information import ExtendedPredict, prediction_step
from dslearn.fusion.strategies import Fusion
from dslearn.learning.online import DataSettings, OnlineLearner, checkpoints as eval_points
from dslearn.models.base import MotionModel, ObservationModel
from dslearn.network import SensorNetwork
from dslearn.metrics import metric_rows, prediction_error, tracking_metrics
from dslearn.metrics.trajectories import TRACKS_FILE, track_record
from dslearn.progress import evaluation_bar, training_bar
from dslearn.sim.scenario import sample_split
from dslearn.types import agents

log = logging.getLogger(__name__)


@dataclass
class YuStudy:
    """One run of the synthetic study: a motion model x a fusion strategy on one data size.

    Its slots are filled by the composition root (:func:`dslearn.compose.build_study`) with the
    parts built from the config groups; the study is the protocol: which episodes, when to evaluate,
    what to record."""

    scenario: Any
    network: SensorNetwork
    model: MotionModel
    model_spec: dict
    observation: ObservationModel
    fusion: Fusion
    predict: Any
    filter: FilterSettings
    data: DataSettings
    seed: int
    dtype: torch.dtype
    device: torch.device

    def checkpoints(self) -> list[int]:
        return eval_points(self.data)

    def sample(self):
        """The run's (test, train) episodes (one random stream per episode)."""
        d = self.data
        return sample_split(self.scenario, self.network, self.seed, d.test_episodes, d.train_episodes, self.dtype,
                            self.device)

    def run(self, diagnostics=None, progress: bool = False) -> pd.DataFrame:
        """Train online on the training episodes, evaluate on the test episodes.

        Returns a tidy DataFrame (one row per checkpoint x test episode x node x metric). Its
        ``attrs["artifacts"]`` (:class:`dslearn.io.Artifacts`) hand the app ``tracks.npz``, the tracking
        figure's arrays after the last training episode (:meth:`track_arrays`).
        """
        scenario, network, model, fusion, f = self.scenario, self.network, self.model, self.fusion, self.filter
        name = str(self.model_spec["name"])
        ctx = scenario.ctx()
        test, train = self.sample()
        learner = OnlineLearner(
            network, model, self.observation, fusion, ctx,
            init=lambda ep: initial_belief(ep, network, ctx.dt, fusion, scenario.area, f.prior_pos_std, f.prior_vel_std),
            predict_step=self.predict, learn_gate_std=f.learn_gate_std,
        )
        learnable = learner.learnable
        checkpoints = self.checkpoints() if learnable else [int(self.data.train_episodes)]
        t0 = time.perf_counter()
        diag = diagnostics or Diagnostics()
        if model.learns_offline:  # an offline model (the LSTM) learns once, from the training episodes' true tracks
            with diag.timed("fit_offline"):
                model.fit_offline(offline_trajectories(model, train), ctx.dt, seed=self.seed)
        model.begin_episodes(test.states)
        bar = training_bar(max(checkpoints), scenario.steps, self.model_spec, enable=progress and learnable,
                           desc=f"train {name}/{fusion.name}")
        tbar = evaluation_bar(checkpoints, scenario.steps, self.model_spec, enable=progress, learnable=learnable,
                              desc="test", position=1)

        # the filter's prediction step, when not the EKF's, labels the model's rows (gp_increment+ukf)
        step = prediction_step(self.predict)
        model_label = name if isinstance(step, ExtendedPredict) else f"{name}+{step.name}"

        tracks = {}

        def evaluate(seen: int) -> pd.DataFrame:
            with diag.timed("evaluate"):
                res = learner.estimate(test.measurements)
                if seen == checkpoints[-1]:  # the tracking figure's arrays: after the last training episode
                    tracks.update(self.track_arrays(res, test, model=model_label, consensus=fusion.name,
                                                    train_seen=int(seen)))
            metrics = tracking_metrics(res, test.states)
            metrics["pred_err"] = prediction_error(model, test.states, network.num_nodes, ctx, per_node=model.learnable)
            tbar.update(1)
            log.info("evaluated %s/%s after %d training episodes (%.1fs)", name, fusion.name, seen, time.perf_counter() - t0)
            return metric_rows(
                metrics, network, model=model_label, consensus=fusion.name,
                omega=fusion.omega_label if fusion.uses_omega else "-",
                iterations=fusion.rounds,
                weights=fusion.weights_rule, train_episodes=int(self.data.train_episodes),
                test_episodes=int(self.data.test_episodes), train_seen=int(seen),
            )

        df = learner.run(train.measurements, checkpoints, evaluate, on_episode=lambda: bar.update(1))
        diag.timings["train_s"] = round(time.perf_counter() - t0 - diag.timings.get("evaluate_s", 0.0), 3)
        diag.count("train_episodes_seen", learner.seen)
        bar.close()
        tbar.close()
        if tracks:
            attach_artifact(df, TRACKS_FILE, tracks)
        return df

    def track_arrays(self, res, test, **labels) -> dict:
        """The tracking figure's arrays (:func:`~dslearn.metrics.trajectories.track_record`) of the beliefs
        ``res`` on the test episodes ``test``: the network, test episode 0's true and estimated tracks of
        every node, every node's position error and NEES per step over the test episodes."""
        from dslearn.methods.distributed import beliefs_to_estimates

        est = beliefs_to_estimates(res.mean, res.info, self.network)
        truth = agents(test.states)[..., :2]
        units = getattr(getattr(self.scenario, "spec", None), "units", "m")
        return track_record(est, truth, self.scenario.ctx().dt, self.network, units=units, **labels)


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
