r"""Liu et al.'s distributed GP tracker (DGPT, FUSION 2022) as a method of the matrix: every sensor is a
local GP expert on its own sliding window of position measurements, a fusion centre combines the experts'
predictions with one aggregation rule (the method's fusion part, :class:`~dslearn.fusion.aggregation.AggregationRule`)
and the experts' shared hyperparameters are learned online from the factorised likelihood (the method's learner,
:class:`~dslearn.learning.learners.OnlineHyperparameters`), all by :func:`dslearn.filters.dgpt.track`.

The tracker follows one target: every (episode, target) pair of a scenario is an independent single-target
episode (the sensors' measurements of that target), all of them one batch of the tracker. Its estimates are
the fusion centre's updated estimates (step ``k`` from the measurements up to ``k``), with the tracker's
per-axis variances as diagonal covariances. The GP's zero prior mean is put at the centre of the scenario's
area (the Liu scenarios are centred on the origin, as the study's trajectories are).

The tracker learns its hyperparameters within each episode, from that episode's measurements: the
training episodes teach it nothing (the learning is online, per episode, as in the paper).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import torch

from dslearn.episodes import Episodes, Estimates, Measurements, Scenario, ScenarioSpec
from dslearn.errors import ConfigError, check_choice, check_integer
from dslearn.filters.dgpt import GP_INPUTS, HyperConfig, track
from dslearn.learning.learners import OnlineHyperparameters, refuse
from dslearn.methods.base import require
from dslearn.network import SensorNetwork

#: the kind of fusion part the tracker takes (an aggregation rule of local GP experts)
FUSION_KIND = "aggregation"


@dataclasses.dataclass
class DGPTMethod:
    """Liu et al.'s DGPT on any scenario whose sensors measure the targets' positions.

    Args:
        fusion: the aggregation rule of the fusion centre (the ``consensus`` part:
            :class:`~dslearn.fusion.aggregation.AggregationRule`, ``kind = "aggregation"``).
        window: the sliding window of every expert, in steps.
        gp_input: ``temporal`` (``x = t``) or ``spatiotemporal`` (``x = (previous estimate, t)``).
        fusion_name: the fusion part's label (its ``conf/consensus`` option).
        learner: the online hyperparameter learning (:class:`~dslearn.learning.learners.OnlineHyperparameters`);
            ``None``: its defaults (``conf/learner/online_hyperparameters.yaml``). No other learner.
    """

    #: the kind of fusion part it takes (the composition's check compares it with the consensus part's ``kind``)
    fusion_kind = FUSION_KIND
    #: the learners it can use (the first: its own, taken when none is given)
    learners = ("online_hyperparameters",)

    fusion: Any
    window: int = 10
    gp_input: str = "temporal"
    fusion_name: str | None = None
    learner: Any = None

    def __post_init__(self) -> None:
        if getattr(self.fusion, "kind", None) != self.fusion_kind:
            name = self.fusion_name or type(self.fusion).__name__
            raise ConfigError(
                f"consensus={name} is not a GP aggregation rule: Liu's DGPT (filter=dgpt) combines its sensors' "
                f"local GP experts at a fusion centre with one, consensus=poe|gpoe|bcm|rbcm (an information-form "
                f"fusion is the distributed filter's: filter=default|ukf)")
        check_integer("filter.window", self.window, 1, note=" (steps)")
        check_choice("filter.gp_input", self.gp_input, GP_INPUTS)
        if self.learner is None:
            self.learner = OnlineHyperparameters()
        elif not isinstance(self.learner, OnlineHyperparameters):
            raise refuse(self.learner, "Liu's DGPT (filter=dgpt) learns its experts' hyperparameters online from "
                                       "the factorised likelihood", self.learners)

    @property
    def hyper(self) -> HyperConfig:
        """The online hyperparameter learning's settings (the learner's ``hyper``)."""
        return self.learner.hyper

    @property
    def label(self) -> str:
        rule = self.fusion.rule + (" normalised" if self.fusion.normalise_beta else "")
        return f"dgpt {rule}" + ("" if self.gp_input == "temporal" else f" {self.gp_input}")

    @staticmethod
    def spec_misfit(spec: ScenarioSpec) -> str | None:
        """What the engine needs of a scenario, declared (:func:`dslearn.methods.base.declared_misfit`): sensors that
        measure each target's position. Intrinsically so: DGPT has no state and no observation model to linearise;
        each sensor's expert is a GP regression of the position's coordinates on time from that sensor's own
        readings alone, with a Gaussian likelihood (its posterior, its marginal likelihood for the hyperparameters
        and the aggregation rules' products of Gaussian predictions all rest on it). A nonlinear reading of one
        scalar per sensor and step (a squared range, a range, a bearing, a terrain altitude) fixes no position (a
        circle, a ray, a contour), so a sensor's own expert has no position data to regress and its posterior over
        the position is not Gaussian (a ring about the sensor), and the sensors cannot be fused before the experts
        without giving up DGPT's local experts."""
        if spec.measurement != "position":
            return (f"Liu's DGPT needs measurement position; scenario {spec.name} has {spec.measurement}: each sensor's "
                    f"GP expert regresses the target's position on time from that sensor's own readings (Gaussian, per "
                    f"coordinate) and the fusion centre combines the experts' Gaussian predictions, but one "
                    f"{spec.measurement} reading per sensor fixes no position (a whole curve of positions fits it), so "
                    f"a sensor alone has no position to regress and no Gaussian posterior of it to fuse (filters that "
                    f"linearise the sensor do: ekf_lin_centralized, fg_ekf, rbpf_em_lin)")
        return require(spec, "Liu's DGPT (sensors that measure each target's position)", measurement="position")

    def fits(self, spec: ScenarioSpec) -> str | None:
        return DGPTMethod.spec_misfit(spec)

    def estimate(self, scenario: Scenario, network: SensorNetwork, train: Episodes, test: Measurements,
                 seed: int) -> Estimates:
        """The fusion centre's estimates of every target of every test episode (``train`` is not used: the
        tracker learns its hyperparameters online within each episode)."""
        mean, var = self.track(test, network, scenario.spec.dt, area_centre(scenario.area))
        cov = torch.diag_embed(var)
        return Estimates(mean[None], cov[None], ["fusion"], torch.ones(1, dtype=torch.bool))

    def track(self, meas: Measurements, network: SensorNetwork, dt: float, centre=(0.0, 0.0)):
        """The tracker on every (episode, target) of ``meas`` (the sensing nodes of ``network``), with the GP's
        prior mean at ``centre``: updated means and per-axis variances ``(B, K+1, A, 2)``."""
        sens = network.is_sensor.to(meas.meas.device)
        z, vis = meas.meas[sens], meas.visible[sens]  # (S, B, T, A, 2), (S, B, T, A)
        s, b, t, a = vis.shape
        z = z.permute(1, 3, 0, 2, 4).reshape(b * a, s, t, 2)
        vis = vis.permute(1, 3, 0, 2).reshape(b * a, s, t)
        c = torch.as_tensor(centre, dtype=z.dtype, device=z.device)
        z = torch.where(vis.unsqueeze(-1), z - c, torch.zeros_like(z))
        window = torch.full((b * a,), self.window, dtype=torch.long, device=z.device)
        res = track(z, vis, window, gp_input=self.gp_input, aggregations=(self.fusion.rule,), centralised=False,
                    hyper=self.hyper, dt=float(dt), normalise_beta=self.fusion.normalise_beta)
        mean = (res.upd_mean[:, 0] + c).reshape(b, a, t, 2).transpose(1, 2)
        var = res.upd_var[:, 0].reshape(b, a, t, 2).transpose(1, 2)
        return mean, var


def area_centre(area) -> tuple[float, float]:
    """The centre of ``area = (xmin, xmax, ymin, ymax)``."""
    x0, x1, y0, y1 = (float(v) for v in area)
    if not all(math.isfinite(v) for v in (x0, x1, y0, y1)):
        raise ConfigError(f"scenario.area={tuple(area)!r} must be finite")
    return 0.5 * (x0 + x1), 0.5 * (y0 + y1)
