r"""Exact moments of a Gaussian-process prediction at a Gaussian input (Deisenroth, Huber, Hanebeck,
*Analytic moment-based Gaussian process filtering*, ICML 2009; Quinonero-Candela et al. 2003).

Independent GPs, one per output ``a = 1..E``, each with the squared-exponential (ARD) kernel

.. math::
    k_a(x, x') = \alpha_a^2 \exp\big(-\tfrac12 (x - x')^T \Lambda_a^{-1} (x - x')\big),\quad
    \Lambda_a = \mathrm{diag}(\ell_{a,1}^2, \dots, \ell_{a,D}^2),

trained on inputs :math:`X` (n, D) with noise variance :math:`\sigma_{a}^2`;
:math:`\beta_a = (K_a + \sigma_a^2 I)^{-1} y_a` and :math:`L_a L_a^T = K_a + \sigma_a^2 I`. For the input
:math:`x \sim \mathcal N(m, S)` and :math:`\nu_i = x_i - m`:

.. math::
    \mu_a = \beta_a^T q_a,\quad q_{a,i} = \alpha_a^2 |S \Lambda_a^{-1} + I|^{-1/2}
            \exp\big(-\tfrac12 \nu_i^T (S + \Lambda_a)^{-1} \nu_i\big),

    \Sigma_{ab} = \beta_a^T Q_{ab} \beta_b - \mu_a \mu_b
                 + \delta_{ab}\big(\alpha_a^2 - \mathrm{tr}((K_a + \sigma_a^2 I)^{-1} Q_{aa}) + \sigma_a^2\big),

    Q_{ab,ij} = \frac{k_a(x_i, m)\, k_b(x_j, m)}{\sqrt{|R_{ab}|}}
               \exp\big(\tfrac12 z_{ij}^T R_{ab}^{-1} S z_{ij}\big),\quad
    R_{ab} = S (\Lambda_a^{-1} + \Lambda_b^{-1}) + I,\quad z_{ij} = \Lambda_a^{-1} \nu_i + \Lambda_b^{-1} \nu_j,

    \mathrm{Cov}[x, f_a(x)] = S (S + \Lambda_a)^{-1} \sum_i \beta_{a,i} q_{a,i} \nu_i.

The :math:`\sigma_a^2` term of :math:`\Sigma` is there with ``include_noise=True`` (the prediction of a
noisy target, as the filters use it: the GP's noise is the model's additive noise), not for the latent
:math:`f`. Every function is batched (batch dims first), works in the inputs' dtype (float64 expected)
on their device, and is differentiable. :class:`GPPosterior` holds the trained GPs' arrays;
:func:`fit_gps` trains them with GPyTorch (exact marginal likelihood, ``torch.optim.Adam``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from dslearn.models.kernels import se


def _sq_lengthscales(lengthscales: Tensor) -> Tensor:
    return lengthscales * lengthscales


def predictive_moments(m: Tensor, S: Tensor, X: Tensor, alpha: Tensor, lengthscales: Tensor, signal_var: Tensor,
                       noise_var: Tensor, chol: Tensor, include_noise: bool = True) -> tuple[Tensor, Tensor, Tensor]:
    r"""Mean ``(*B, E)``, covariance ``(*B, E, E)`` and input-output cross-covariance ``Cov[x, f(x)]``
    ``(*B, D, E)`` of the GP prediction at ``x ~ N(m, S)`` (module docstring).

    Args:
        m: ``(*B, D)`` input mean; S: ``(*B, D, D)`` input covariance (positive semi-definite).
        X: ``(n, D)`` training inputs; alpha: ``(E, n)`` ``(K + s_n^2 I)^{-1} y`` per output;
        lengthscales: ``(E, D)``; signal_var: ``(E,)`` (:math:`\alpha^2`); noise_var: ``(E,)``;
        chol: ``(E, n, n)`` lower Cholesky factor of ``K + s_n^2 I`` per output.
        include_noise: add ``noise_var`` to the diagonal (the prediction of a noisy target).
    """
    E, D = lengthscales.shape
    lam = _sq_lengthscales(lengthscales)                       # (E, D) diagonal of Lambda_a
    ilam = 1.0 / lam
    eye = torch.eye(D, dtype=m.dtype, device=m.device)
    nu = X - m.unsqueeze(-2)                                  # (*B, n, D)
    # mean and cross-covariance: (S + Lambda_a)^{-1} nu_i
    SL = S.unsqueeze(-3) + torch.diag_embed(lam)              # (*B, E, D, D)
    cSL = torch.linalg.cholesky(SL)
    nuE = nu.unsqueeze(-3).expand(*nu.shape[:-2], E, *nu.shape[-2:])  # (*B, E, n, D)
    t = torch.cholesky_solve(nuE.transpose(-1, -2), cSL).transpose(-1, -2)  # (*B, E, n, D)
    logdet_SL = 2.0 * torch.log(torch.diagonal(cSL, dim1=-2, dim2=-1)).sum(-1)  # (*B, E)
    # |S Lambda^{-1} + I| = |S + Lambda| / |Lambda|
    log_c = torch.log(signal_var) - 0.5 * (logdet_SL - torch.log(lam).sum(-1))  # (*B, E)
    q = torch.exp(log_c.unsqueeze(-1) - 0.5 * (nuE * t).sum(-1))  # (*B, E, n)
    bq = alpha * q                                             # (*B, E, n)
    mean = bq.sum(-1)                                          # (*B, E)
    cross = S @ (bq.unsqueeze(-1) * t).sum(-2).transpose(-1, -2)  # (*B, D, E)

    # covariance: Q_ab (*B, E, E, n, n)
    zeta = nuE * ilam.unsqueeze(-2)                            # (*B, E, n, D): Lambda_a^{-1} nu_i
    R = S.unsqueeze(-3).unsqueeze(-3) * (ilam.unsqueeze(1) + ilam.unsqueeze(0)).unsqueeze(-2) + eye  # (*B,E,E,D,D)
    T = torch.linalg.solve(R, S.unsqueeze(-3).unsqueeze(-3).expand_as(R))  # R^{-1} S (symmetric)
    T = 0.5 * (T + T.transpose(-1, -2))
    za = zeta.unsqueeze(-3)                                    # (*B, E, 1, n, D): output a, point i
    zb = zeta.unsqueeze(-4)                                    # (*B, 1, E, n, D): output b, point j
    zaT = za @ T                                               # (*B, E, E, n, D)
    quad_a = (zaT * za).sum(-1)                                # (*B, E, E, n)
    quad_b = ((zb @ T) * zb).sum(-1)                           # (*B, E, E, n)
    cross_ab = zaT @ zb.transpose(-1, -2)                      # (*B, E, E, n, n)
    kmaha = (nuE * zeta).sum(-1)                               # (*B, E, n): nu_i^T Lambda_a^{-1} nu_i
    log_k_a = torch.log(signal_var).unsqueeze(-1) - 0.5 * kmaha  # (*B, E, n): log k_a(x_i, m)
    logdet_R = torch.linalg.slogdet(R)[1]                      # (*B, E, E)
    logQ = (log_k_a.unsqueeze(-2).unsqueeze(-1) + log_k_a.unsqueeze(-3).unsqueeze(-2)
            + 0.5 * (quad_a.unsqueeze(-1) + quad_b.unsqueeze(-2) + 2.0 * cross_ab)
            - 0.5 * logdet_R.unsqueeze(-1).unsqueeze(-1))
    Q = torch.exp(logQ)                                        # (*B, E, E, n, n)
    bQb = (alpha.unsqueeze(1).unsqueeze(-2) @ Q @ alpha.unsqueeze(0).unsqueeze(-1)).squeeze(-1).squeeze(-1)  # (*B,E,E)
    cov = bQb - mean.unsqueeze(-1) * mean.unsqueeze(-2)
    # expected GP variance: alpha_a^2 - tr((K_a + s_n^2 I)^{-1} Q_aa)
    Qaa = torch.diagonal(Q, dim1=-4, dim2=-3).movedim(-1, -3)  # (*B, E, n, n)
    tr = torch.diagonal(torch.cholesky_solve(Qaa, chol), dim1=-2, dim2=-1).sum(-1)  # (*B, E)
    diag = signal_var - tr + (noise_var if include_noise else 0.0)
    cov = cov + torch.diag_embed(diag)
    cov = 0.5 * (cov + cov.transpose(-1, -2))
    return mean, cov, cross


@dataclass
class GPPosterior:
    """The arrays of E independent trained SE-ARD GPs on common inputs (see :func:`predictive_moments`)."""

    X: Tensor             # (n, D)
    alpha: Tensor         # (E, n)
    lengthscales: Tensor  # (E, D)
    signal_var: Tensor    # (E,)
    noise_var: Tensor     # (E,)
    chol: Tensor          # (E, n, n)

    @classmethod
    def from_data(cls, X: Tensor, Y: Tensor, lengthscales: Tensor, signal_var: Tensor, noise_var: Tensor) -> "GPPosterior":
        """The posterior arrays for targets ``Y`` ``(n, E)`` under the given hyperparameters."""
        K = kernel(X, X, lengthscales, signal_var)                          # (E, n, n)
        n = X.shape[0]
        K = K + noise_var[:, None, None] * torch.eye(n, dtype=X.dtype, device=X.device)
        chol = torch.linalg.cholesky(K)
        alpha = torch.cholesky_solve(Y.T.unsqueeze(-1), chol).squeeze(-1)   # (E, n)
        return cls(X, alpha, lengthscales, signal_var, noise_var, chol)

    @property
    def input_dim(self) -> int:
        return self.X.shape[-1]

    @property
    def output_dim(self) -> int:
        return self.alpha.shape[0]

    def to(self, device=None, dtype=None) -> "GPPosterior":
        f = lambda t: t.to(device=device, dtype=dtype)  # noqa: E731
        return GPPosterior(*(f(t) for t in (self.X, self.alpha, self.lengthscales, self.signal_var, self.noise_var,
                                            self.chol)))

    def mean(self, x: Tensor) -> Tensor:
        """Predictive mean ``(*B, E)`` at deterministic inputs ``x`` ``(*B, D)``."""
        k = kernel(x.unsqueeze(-2), self.X, self.lengthscales, self.signal_var).squeeze(-2)  # (*B, E, n)
        return (k * self.alpha).sum(-1)

    def variance(self, x: Tensor, include_noise: bool = True) -> Tensor:
        """Predictive variance ``(*B, E)`` at ``x`` (of the noisy target with ``include_noise``)."""
        return self.mean_variance(x, include_noise)[1]

    def mean_variance(self, x: Tensor, include_noise: bool = True) -> tuple[Tensor, Tensor]:
        """Predictive mean and variance ``(*B, E)`` at ``x`` (one kernel evaluation)."""
        k = kernel(x.unsqueeze(-2), self.X, self.lengthscales, self.signal_var).squeeze(-2)  # (*B, E, n)
        mean = (k * self.alpha).sum(-1)
        E, n = k.shape[-2:]
        rhs = k.reshape(-1, E, n).permute(1, 2, 0)               # (E, n, M): one solve per output, M columns
        v = torch.linalg.solve_triangular(self.chol, rhs, upper=False)
        var = self.signal_var - (v * v).sum(-2).T.reshape(k.shape[:-1])
        return mean, (var + self.noise_var if include_noise else var)

    def moments(self, m: Tensor, S: Tensor, include_noise: bool = True) -> tuple[Tensor, Tensor, Tensor]:
        """:func:`predictive_moments` of these GPs at ``N(m, S)``."""
        return predictive_moments(m, S, self.X, self.alpha, self.lengthscales, self.signal_var, self.noise_var,
                                  self.chol, include_noise)


def kernel(a: Tensor, b: Tensor, lengthscales: Tensor, signal_var: Tensor) -> Tensor:
    """SE-ARD kernel matrices ``(*B, E, na, nb)`` of ``a`` ``(*B, na, D)`` and ``b`` ``(nb, D)`` (or batched)."""
    a_ = a.unsqueeze(-3) / lengthscales.unsqueeze(-2)         # (*B, E, na, D)
    b_ = b.unsqueeze(-3) / lengthscales.unsqueeze(-2)         # (*, E, nb, D)
    d2 = (a_.unsqueeze(-2) - b_.unsqueeze(-3)).pow(2).sum(-1)  # (*B, E, na, nb)
    return se(d2, signal_var.unsqueeze(-1).unsqueeze(-1))


def fit_gps(X: Tensor, Y: Tensor, iterations: int = 200, lr: float = 0.1, min_noise: float = 1e-8) -> GPPosterior:
    """Train one GPyTorch ``ExactGP`` with ``ScaleKernel(RBFKernel(ard_num_dims=D))`` per output column of
    ``Y`` ``(n, E)`` by the exact marginal likelihood (``torch.optim.Adam``, ``iterations`` steps of ``lr``,
    from GPyTorch's default initial values), and return the posterior arrays under the trained
    hyperparameters. Deterministic given the data (no random initialisation)."""
    import gpytorch

    D = X.shape[-1]

    class _GP(gpytorch.models.ExactGP):
        def __init__(self, x, y, likelihood):
            super().__init__(x, y, likelihood)
            self.mean_module = gpytorch.means.ZeroMean()
            self.covar_module = gpytorch.kernels.ScaleKernel(gpytorch.kernels.RBFKernel(ard_num_dims=D))

        def forward(self, x):
            return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))

    ls, sv, nv = [], [], []
    for e in range(Y.shape[-1]):
        y = Y[:, e].contiguous()
        lik = gpytorch.likelihoods.GaussianLikelihood(
            noise_constraint=gpytorch.constraints.GreaterThan(min_noise)).to(device=X.device, dtype=X.dtype)
        model = _GP(X, y, lik).to(device=X.device, dtype=X.dtype)
        model.train()
        lik.train()
        opt = torch.optim.Adam(model.parameters(), lr=lr)
        mll = gpytorch.mlls.ExactMarginalLogLikelihood(lik, model)
        with gpytorch.settings.max_cholesky_size(10 ** 9):  # exact Cholesky, never CG
            for _ in range(iterations):
                opt.zero_grad()
                loss = -mll(model(X), y)
                loss.backward()
                opt.step()
        ls.append(model.covar_module.base_kernel.lengthscale.detach().reshape(D))
        sv.append(model.covar_module.outputscale.detach().reshape(()))
        nv.append(lik.noise.detach().reshape(()))
    return GPPosterior.from_data(X, Y, torch.stack(ls), torch.stack(sv), torch.stack(nv))

