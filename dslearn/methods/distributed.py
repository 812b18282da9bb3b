r"""Yu et al.'s method as parts: a distributed information filter (EKF or UKF prediction step) with a motion
model, an observation model and a fusion strategy, whose motion model learns online while tracking the
training episodes (Algorithm 1: the GP models) or offline from their true tracks before it (declared by the
model: the LSTM), or is fixed (LIN, the social force)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import pandas as pd
import torch

from dslearn.episodes import Episodes, Estimates, Measurements, Scenario, ScenarioSpec
from dslearn.filters.distributed import initial_belief
from dslearn.fusion.strategies import Fusion
from dslearn.learning.online import OnlineLearner
from dslearn.methods.base import require
from dslearn.models.base import MotionModel, ObservationModel
from dslearn.network import SensorNetwork
from dslearn.types import AGENT_DIM, agents, safe_cholesky


@dataclass
class DistributedFilter:
    """The distributed filter of Yu et al. Algorithm 1 on a scenario's network.

    Args:
        predict: the prediction step (``filter.predict``: EKF linearisation or the unscented transform).
        model, observation, fusion: the parts (sized for the scenario and its network).
        prior_pos_std, prior_vel_std: the diffuse prior of a node that knows nothing of a target.
        learn_gate_std: the learning gate of Algorithm 1 (``None``: off).
        model_name: the motion model's label (its ``conf/model`` option).
    """

    predict: Any
    model: MotionModel
    observation: ObservationModel
    fusion: Fusion
    prior_pos_std: float = 1000.0
    prior_vel_std: float = 1000.0
    learn_gate_std: float | None = 2.0
    model_name: str = "model"

    @property
    def label(self) -> str:
        omega = f" ω={self.fusion.omega_label}" if self.fusion.uses_omega and self.fusion.omega_label != "one" else ""
        return f"{getattr(self.predict, 'name', 'ekf')} {self.model_name} {self.fusion.name}{omega}"

    def fits(self, spec: ScenarioSpec) -> str | None:
        return require(spec, "the distributed filter (position sensors, agents [p, v] in 2-D, a network)",
                       measurement="position", state="pv2d", networked=True)

    def estimate(self, scenario: Scenario, network: SensorNetwork, train: Episodes, test: Measurements,
                 seed: int) -> Estimates:
        ctx, model, fusion = scenario.ctx(), self.model, self.fusion
        learner = OnlineLearner(
            network, model, self.observation, fusion, ctx,
            init=lambda ep: initial_belief(ep, network, ctx.dt, fusion, scenario.area, self.prior_pos_std,
                                           self.prior_vel_std),
            predict_step=self.predict, learn_gate_std=self.learn_gate_std,
        )
        if model.learns_offline:  # declared supervised: learns from the training episodes' true tracks
            model.fit_offline(train.states, ctx.dt, seed=seed)
        if learner.learnable:
            learner.run(train.measurements, [len(train)], lambda k: pd.DataFrame())  # no evaluation at checkpoints
        res = learner.estimate(test)
        return beliefs_to_estimates(res.mean, res.info, network)


def beliefs_to_estimates(mean: torch.Tensor, info: torch.Tensor, network: SensorNetwork) -> Estimates:
    """Information-form beliefs of every node, ``mean (S, B, K+1, 4A)``, ``info (S, B, K+1, 4A, 4A)``, as
    position estimates and their covariances (the position blocks of ``info^-1``)."""
    cov = torch.cholesky_inverse(safe_cholesky(info))
    a = mean.shape[-1] // AGENT_DIM
    blocks = cov.unflatten(-2, (a, AGENT_DIM)).unflatten(-1, (a, AGENT_DIM))  # (..., A, 4, A, 4)
    pos_cov = torch.diagonal(blocks, dim1=-4, dim2=-2).movedim(-1, -3)[..., :2, :2]  # (..., A, 2, 2)
    return Estimates(agents(mean)[..., :2], pos_cov, list(network.names), network.is_sensor.clone())
