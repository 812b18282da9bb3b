"""Motion and observation models behind one interface."""

from dslearn.models.base import MotionModel, ObservationModel
from dslearn.models.constant_velocity import ConstantVelocity
from dslearn.models.social_force import SocialForce
from dslearn.models.gp import GPMotionModel
from dslearn.models.observation import LinearPositionObservation, GPObservation

__all__ = [
    "MotionModel",
    "ObservationModel",
    "ConstantVelocity",
    "SocialForce",
    "GPMotionModel",
    "LinearPositionObservation",
    "GPObservation",
]
