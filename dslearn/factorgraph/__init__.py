"""Factor-graph model identification and EKF-FG tracking (Jiang et al., ISITA 2022).

* :mod:`.messages` -- Taylor coefficients by autograd and the Gaussian messages (Eqs. 6-16).
* :mod:`.identification` -- sensor compression and the iterated identification FG.
* :mod:`.tracking` -- EKF-FG state/gradient tracker (Eqs. 2-5, 17-19).
* :mod:`.crlb` -- Fisher information and CRLB (Appendix, Eqs. 27-33).
* :mod:`.centralized` -- centralised Gauss-Newton / iterated EKF baselines on the raw samples.
* :mod:`.scenario` -- the paper's sensors, squared-range ``h`` and trajectories (Sec. IV).
* :mod:`.simulation` -- the vectorised Monte Carlo engine used by ``dslearn.studies.jiang_fg``.
"""

from .crlb import crlb, crlb_from_fisher, fisher_information
from .identification import IdentificationResult, compress_measurements, identify
from .messages import linearize, marginal, rho_from_zeta, zeta_moment, zeta_natural
from .scenario import SquaredRange, polynomial_trajectory
from .simulation import SimulationOutput, TrackerSettings, simulate
from .tracking import TrackState, ekf_fg_step

__all__ = [
    "IdentificationResult", "SimulationOutput", "SquaredRange", "TrackState", "TrackerSettings", "compress_measurements",
    "crlb", "crlb_from_fisher", "ekf_fg_step", "fisher_information", "identify", "linearize", "marginal",
    "polynomial_trajectory", "rho_from_zeta", "simulate", "zeta_moment", "zeta_natural",
]
