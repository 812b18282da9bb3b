"""The GP backends: ``S`` independent GP regressions (one per sensor node) behind one protocol
(:class:`GPBackend`, :mod:`.protocol`): the exact online GP (:mod:`.exact`, its CPU step through the
inverse Cholesky factor of :mod:`.inverse_factor`), the scalable variants (:mod:`.sparse`: window,
SGPR, SSGP; :func:`make_online_gp` builds any of them by name) and the prior means (:mod:`.means`)."""

from dslearn.models.gp_backends.exact import OnlineGP
from dslearn.models.gp_backends.means import ConstantVelocityMean, IdentityMean, PriorMeanModule, ZeroMean
from dslearn.models.gp_backends.protocol import GPBackend
from dslearn.models.gp_backends.sparse import make_online_gp

__all__ = ["ConstantVelocityMean", "GPBackend", "IdentityMean", "OnlineGP", "PriorMeanModule", "ZeroMean",
           "make_online_gp"]
