"""Learning procedures: the learn-while-tracking loop, online EM, factor-graph identification, LSTM training,
social-force fitting (the models they learn are :mod:`dslearn.models`).

:class:`Learner` is the base of the learners (the ``learner`` part, :mod:`dslearn.learning.learners`): what each
does, declared; the engine that carries a learner out reads these flags, never the learner's name."""

from __future__ import annotations

from typing import ClassVar


class Learner:
    """Base of the learners: what each does, declared (all ``False`` here)."""

    #: the parts that learn online learn while tracking the training episodes (Yu et al. Algorithm 1)
    learns_online: ClassVar[bool] = False
    #: the motion model is fitted to the training episodes' true tracks before any tracking (``fit_offline``)
    fits_offline: ClassVar[bool] = False
    #: it learns through the filter's update of labelled measurements (so not from an associator's detections)
    learns_through_update: ClassVar[bool] = False
    #: it runs every node's filter alone (each node's own model state), whatever the fusion: a motion model with
    #: per-node state is then built for every node even under a fusion centre
    runs_nodes_alone: ClassVar[bool] = False
