"""The GP motion model with a constant-velocity prior mean (``conf/model/gp_cv.yaml``).

The GP learns the deviation of the one-step transition from constant velocity
(:class:`~dslearn.models.gp_backends.means.ConstantVelocityMean`), so far from its data it falls back to
LIN instead of to "stand still" (identity mean) or to the origin (zero mean). The mean's step is
the scenario's ``dt``; every other key is the GP's (:class:`~dslearn.models.gp.GPMotionModel`).
"""

from __future__ import annotations

from dslearn.errors import ConfigError
from dslearn.models.gp import GPMotionModel
from dslearn.models.gp_backends import ConstantVelocityMean


def gp_cv_for_scenario(*, scenario, num_nodes: int, dtype, device, mean=None, **keys) -> GPMotionModel:
    """The config factory: :meth:`GPMotionModel.for_scenario` with the prior mean
    ``ConstantVelocityMean(scenario.dt)``; ``mean`` must be left null (ConfigError otherwise)."""
    if mean is not None:
        raise ConfigError(f"model.mean={mean!r}: the gp_cv model's prior mean is the constant-velocity step with the "
                          "scenario's dt; leave model.mean null (or choose model=gp_increment for another mean)")
    return GPMotionModel.for_scenario(scenario=scenario, num_nodes=num_nodes, dtype=dtype, device=device,
                                      mean=ConstantVelocityMean(float(scenario.ctx().dt)), **keys)


#: a GP that learns online (the keys it does not read: dslearn.schemas.base.hook_of)
gp_cv_for_scenario.config_learns_online = True

