r"""Data association of unlabelled detections to tracks, for one node: gating with the predicted measurement
covariance (:mod:`.gating`), the associators behind one interface (:class:`.base.Associator`): the labels given
(:class:`.labels.LabelsGiven`, the labelled scenarios' behaviour), global nearest neighbour
(:class:`.gnn.GNN`) and JPDA (:class:`.jpda.JPDA`), and track management (:mod:`.tracks`: initiation,
confirmation, deletion); on a sensor network, every node's association with its own tracks before the consensus
and the ``associator=`` slot of the distributed filter (:mod:`.network`), and, where targets enter and leave, every
node's managed tracks matched to its neighbours' before a consensus per matched track (:mod:`.multitrack`). Float64 throughout; the measurement model is the project's
:class:`~dslearn.models.base.ObservationModel` (its reading, Jacobian and noise covariance)."""

from dslearn.association.base import Association, Associator, MeasurementPrediction, kalman_update, predict_measurement
from dslearn.association.gating import gate, gate_threshold, mahalanobis2
from dslearn.association.gnn import GNN
from dslearn.association.jpda import JPDA
from dslearn.association.labels import LabelsGiven
from dslearn.association.tracks import TrackManager, TrackManagerSettings

__all__ = ["Association", "Associator", "GNN", "JPDA", "LabelsGiven", "MeasurementPrediction", "TrackManager",
           "TrackManagerSettings", "gate", "gate_threshold", "kalman_update", "mahalanobis2", "predict_measurement"]
