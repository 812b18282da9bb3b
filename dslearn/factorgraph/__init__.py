"""Factor-graph model identification and EKF-FG tracking (Jiang et al., ISITA 2022).

* :mod:`.messages` -- Taylor coefficients by autograd and the Gaussian messages (Eqs. 6-16).
* :mod:`.identification` -- sensor compression and the iterated identification FG (flooding or
  sequential schedule, optional damping and re-linearisation; the paper's scalar graph or one
  vector node, i.e. a Gauss-Newton FG).
* :mod:`.tracking` -- EKF-FG state/gradient tracker (Eqs. 2-5, 17-19) and the FG output's
  observation variance (the paper's CRLB, or CRLB + the FG's convergence term, optional gate).
* :mod:`.crlb` -- Fisher information and CRLB (Appendix, Eqs. 27-33).
* :mod:`.centralized` -- centralised Gauss-Newton / iterated EKF baselines on the raw samples.
* :mod:`.scenario` -- the paper's sensors, squared-range ``h`` and trajectories (Sec. IV), and
  the per-run random streams of the Monte Carlo runs.
* :mod:`.simulation` -- the vectorised Monte Carlo engine used by ``dslearn.studies.jiang_fg``.
"""

from .crlb import crlb, crlb_from_fisher, fisher_information
from .identification import IdentificationResult, compress_measurements, identify
from .messages import linearize, marginal, rho_from_zeta, zeta_moment, zeta_natural
from .scenario import SquaredRange, polynomial_trajectory, run_noise, run_seed
from .simulation import SimulationOutput, TrackerSettings, simulate
from .tracking import TrackState, ekf_fg_step, observation_variance

__all__ = [
    "IdentificationResult", "SimulationOutput", "SquaredRange", "TrackState", "TrackerSettings", "compress_measurements",
    "crlb", "crlb_from_fisher", "ekf_fg_step", "fisher_information", "identify", "linearize", "marginal",
    "observation_variance", "polynomial_trajectory", "rho_from_zeta", "run_noise", "run_seed", "simulate",
    "zeta_moment", "zeta_natural",
]
