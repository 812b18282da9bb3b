r"""Learning while tracking (Yu et al. Algorithm 1), one loop for every study that does it.

Training episodes come one after another: every node runs the distributed filter
(:func:`~dslearn.filters.distributed.track`) on the episode's measurements and appends what it
estimated to its model's data set (:math:`D_f`, :math:`D_h`); at the checkpoints the study
evaluates the models learned so far. The studies (synthetic Yu, network faults, real-data
tracking, the reference implementation) differ only in what they hand in: the parts, how a
belief starts, what happens before an episode (a fault schedule) and what an evaluation records.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, List, Optional

import pandas as pd
import torch

from dslearn.episodes import Measurements
from dslearn.filters.distributed import TrackResult, track
from dslearn.settings import ranged


@dataclass
class OnlineLearner:
    """The parts of Algorithm 1: network, motion and observation models, fusion, the step
    context, the initial belief ``init(measurements) -> (mean, info)`` and the filter's options."""

    network: Any
    model: Any
    obs: Any
    fusion: Any
    ctx: Any
    init: Callable[[Measurements], tuple]
    predict_step: Any = None
    learn_gate_std: float | None = None
    gate_prob: float | None = None
    seen: int = field(default=0, init=False)

    @property
    def learnable(self) -> bool:
        return bool(self.model.learnable or self.obs.learnable)

    def learn(self, ep: Measurements) -> None:
        """One training episode (``B = 1``): track it and learn from the estimates; refit the
        hyperparameters every ``model.fit_every`` episodes."""
        track(ep, self.network, self.model, self.obs, self.fusion, self.ctx, self.init(ep), learn=True,
              learn_gate_std=self.learn_gate_std, gate_prob=self.gate_prob, predict_step=self.predict_step)
        self.seen += 1
        every = int(getattr(self.model, "fit_every", 0) or 0)
        if every and self.seen % every == 0:
            self.model.fit()

    @torch.no_grad()
    def estimate(self, ep: Measurements) -> TrackResult:
        """Track a batch of episodes with the models as they are (no learning)."""
        return track(ep, self.network, self.model, self.obs, self.fusion, self.ctx, self.init(ep), learn=False,
                     gate_prob=self.gate_prob, predict_step=self.predict_step)

    def run(self, train: Measurements, checkpoints: list[int], evaluate: Callable[[int], pd.DataFrame],
            before: Callable[[int], None] | None = None, on_episode: Callable[[], None] | None = None) -> pd.DataFrame:
        """:func:`algorithm1` with this learner's :meth:`learn` on ``train``'s episodes. The motion
        model is told beforehand how many examples will come (one per step of every episode to
        learn), so that its data set is allocated once."""
        if self.learnable and self.model.learnable and checkpoints:
            self.model.reserve(min(max(checkpoints), len(train)) * train.steps)
        def learn(i: int) -> None:
            if before is not None:
                before(i)
            self.learn(train.select(slice(i, i + 1)))
            if on_episode is not None:
                on_episode()

        return algorithm1(learn, checkpoints, evaluate, self.learnable)


def algorithm1(learn: Callable[[int], None], checkpoints: list[int], evaluate: Callable[[int], pd.DataFrame],
               learnable: bool = True) -> pd.DataFrame:
    """Learn while tracking: ``learn(i)`` for training episodes ``i = 0, 1, ...`` and ``evaluate(k)``
    at every checkpoint ``k`` (training episodes seen so far); one table of every evaluation.
    A model that learns nothing is not trained."""
    frames, seen = [], 0
    for k in checkpoints:
        while learnable and seen < k:
            learn(seen)
            seen += 1
        frames.append(evaluate(k))
    return pd.concat(frames, ignore_index=True)


@dataclass
class DataSettings:
    """How many episodes a learn-while-tracking study draws (the ``data`` group): ``train_episodes``
    learned one after another, ``test_episodes`` evaluated at every checkpoint (``eval_at``: the
    training-episode counts at which to evaluate; ``None`` = at the end)."""

    train_episodes: int = ranged(30, ge=0)
    test_episodes: int = ranged(20, ge=1)
    eval_at: Optional[List[int]] = None
    min_train_episodes: int = ranged(0, ge=0)


def checkpoints(data: DataSettings) -> list[int]:
    """The training-episode counts at which a study evaluates: ``data.eval_at`` (sorted, unique) or
    just ``data.train_episodes``."""
    ev = data.eval_at
    return [int(data.train_episodes)] if ev is None else sorted({int(v) for v in ev})
