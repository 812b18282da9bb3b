r"""Observation models: a sensor measures each target in range separately."""

from __future__ import annotations

import torch
from torch import Tensor

from dslearn.errors import check_choice, check_positive
from dslearn.types import AGENT_DIM
from dslearn.models.base import ObservationModel
from dslearn.models.gp_backends import GPBackend, OnlineGP


class LinearPositionObservation(ObservationModel):
    r"""Eq. (5): :math:`z_{ij} = x_j + \nu`, :math:`\nu \sim \mathcal N(0, \sigma_\nu^2 I_2)`.

    Args:
        noise_std: :math:`\sigma_\nu` (> 0).
    """

    def __init__(self, noise_std: float = 0.2):
        super().__init__()
        check_positive("observation.noise_std", noise_std)
        self.noise_std = float(noise_std)

    def matrix(self, dtype=torch.float64, device=None) -> Tensor:
        return torch.eye(2, AGENT_DIM, dtype=dtype, device=device)

    def forward(self, y: Tensor) -> Tensor:
        return y[..., :2]

    def jacobian(self, y: Tensor) -> Tensor:
        h = self.matrix(y.dtype, y.device)
        return h.expand(*y.shape[:-1], *h.shape)

    def noise_cov(self, y: Tensor) -> Tensor:
        r = self.noise_std**2 * torch.eye(2, dtype=y.dtype, device=y.device)
        return r.expand(*y.shape[:-1], 2, 2)


class GPObservation(ObservationModel):
    r"""Learned observation model :math:`h` (data set :math:`D_{h,i}` of Algorithm 1).

    One GP per node maps a target state (4) to its measurement (2), learned from the node's
    own (ŷ_j^t, z_ij^t) pairs. ``R`` is the GP covariance :math:`\Sigma_h` (``latent``, as
    printed) or with :math:`\sigma_\epsilon^2` added (``predictive``, default: with latent
    variance alone the filter would treat learned measurements as nearly noise-free once the
    data set is large).

    Inputs have the node dimension first: ``(S, *B, 4)``.
    """

    learnable = True
    config_learns_online = True  #: it learns online (:func:`dslearn.schemas.base.online_learning`)

    def __init__(
        self,
        num_nodes: int,
        outputscale: float = 1.0,
        lengthscale: float = 2.0,
        noise_std: float = 0.2,
        mean: str = "identity",
        noise: str = "predictive",
        dtype: torch.dtype = torch.float64,
        device: str | torch.device = "cpu",
    ):
        super().__init__()
        check_choice("observation.noise", noise, ("latent", "predictive"))
        self.noise_mode = noise
        # used through the GPBackend protocol: num_nodes, predict, noise_var, append
        self.gp: GPBackend = OnlineGP(num_nodes, AGENT_DIM, 2, outputscale, lengthscale, noise_std, mean, dtype=dtype, device=device)

    def linearize(self, y: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        s = self.gp.num_nodes
        flat = y.reshape(s, -1, AGENT_DIM)
        mean, var, jac = self.gp.predict(flat)
        if self.noise_mode == "predictive":
            var = var + self.gp.noise_var.unsqueeze(-1)
        r = var.reshape(*y.shape[:-1], 1, 1) * torch.eye(2, dtype=y.dtype, device=y.device)
        return mean.reshape(*y.shape[:-1], 2), jac.reshape(*y.shape[:-1], 2, AGENT_DIM), r

    def forward(self, y: Tensor) -> Tensor:
        return self.linearize(y)[0]

    def jacobian(self, y: Tensor) -> Tensor:
        return self.linearize(y)[1]

    def noise_cov(self, y: Tensor) -> Tensor:
        return self.linearize(y)[2]

    def add_data(self, inputs: Tensor, outputs: Tensor, valid: Tensor) -> None:
        for a in range(inputs.shape[1]):
            self.gp.append(inputs[:, a], outputs[:, a], valid[:, a])
