r"""The labels given: detection ``i`` is track ``i``'s, as in every labelled scenario (the reference an
associator is compared with). Its association is the identity; the tracks are updated by their own
detection with the same Kalman update as the other associators, and :attr:`LabelsGiven.measurements` hands
the labelled measurements through unchanged (the same tensor) for a filter that runs its own update."""

from __future__ import annotations

import torch
from torch import Tensor

from dslearn.association.base import DTYPE, Association, check_inputs, innovations, kalman_update, predict_measurement
from dslearn.errors import ConfigError
from dslearn.models.base import ObservationModel


class LabelsGiven:
    """The labelled associator (:class:`~dslearn.association.base.Associator`): ``detections (T, Dz)``, row
    ``i`` measuring track ``i``; ``present (T,)`` False where track ``i`` has no measurement this step."""

    @staticmethod
    def measurements(detections: Tensor, present: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
        """The labelled measurements and their mask, as given (no copy, no cast)."""
        return detections, present

    def associate(self, mean: Tensor, cov: Tensor, observation: ObservationModel, detections: Tensor,
                  present: Tensor | None = None) -> Association:
        mean, cov, det, present = check_inputs(mean, cov, detections, present)
        t = mean.shape[0]
        if det.shape[0] != t:
            raise ConfigError(f"detections {tuple(det.shape)}: the labels given need one row per track ({t})")
        pred = predict_measurement(mean, cov, observation)
        nu = torch.diagonal(innovations(pred, observation, det), dim1=0, dim2=1).T  # (T, Dz): nu[i, i]
        upd_mean, upd_cov = kalman_update(mean, cov, pred, torch.where(present.unsqueeze(-1), nu, 0.0))
        weights = torch.diag(present.to(DTYPE))
        assigned = torch.where(present, torch.arange(t), -1)
        return Association(weights, (~present).to(DTYPE), assigned, torch.diag(present),
                           torch.zeros(t, dtype=torch.bool), torch.where(present.unsqueeze(-1), upd_mean, mean),
                           torch.where(present.view(-1, 1, 1), upd_cov, cov))
