"""Motion and observation models behind one interface."""

from .base import MotionModel, ObservationModel
from .constant_velocity import ConstantVelocity
from .social_force import SocialForce
from .gp import GPMotionModel, OnlineGP
from .sparse import SGPR, SSGP, WindowGP
from .observation import LinearPositionObservation, GPObservation

__all__ = [
    "MotionModel",
    "ObservationModel",
    "ConstantVelocity",
    "SocialForce",
    "GPMotionModel",
    "OnlineGP",
    "WindowGP",
    "SGPR",
    "SSGP",
    "LinearPositionObservation",
    "GPObservation",
]
