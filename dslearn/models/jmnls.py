r"""Jump Markov nonlinear system (JMNLS) with mode-dependent Gaussian observation noise.

Braga et al., Section II, Eq. (1):

.. math::
    r_{s,t} \sim \Pi(r_{s,t}|r_{s,t-1}),\quad x_{s,t} \sim f(x_{s,t}|x_{s,t-1}),\quad
    y_{s,t} \sim g(y_{s,t}|x_{s,t}, \theta_{r_{s,t}}),

with :math:`g(y|x,\theta_k) = \mathcal N(y;\, h(x) + \mu_k,\, \sigma_k^2)` (the TBN model, Eq. 25) and
:math:`\Pi` a K×K transition probability matrix (TPM), :math:`\pi_{k\ell} = P(r_t=\ell | r_{t-1}=k)` (Eq. 2).

Sufficient statistics (Eq. 5-6) are stored as one flat vector of length ``D = K*K + 3*K``::

    [ S1 (K*K, row-major over (k, l)) | S2 (K) | S3a (K) | S3b (K) ]

with ``S1_{kl} = 1(r_{t-1}=k, r_t=l)``, ``S2_k = 1(r_t=k)``, ``S3a_k = 1(r_t=k) e_t``, ``S3b_k = 1(r_t=k) e_t^2``
and ``e_t = y_t - h(x_t)`` the terrain-elevation residual. The M-step of Eq. (8) maps them to
``mu_k = S3a_k / S2_k``, ``sigma_k^2 = S3b_k / S2_k - mu_k^2`` and ``pi_kl = S1_kl / sum_j S1_kj``.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

from dslearn.errors import ConfigError

LOG_2PI = math.log(2.0 * math.pi)


def stats_dim(k: int) -> int:
    """Length ``K*K + 3*K`` of the sufficient-statistics vector (10 for K = 2, as in Section VI-B)."""
    return k * k + 3 * k


def params_dim(k: int) -> int:
    """Number of free parameters ``2K + K(K-1)`` (mu, sigma, off-row-sum TPM entries; 6 for K = 2)."""
    return 2 * k + k * (k - 1)


@dataclass
class NoiseParams:
    """Mode-dependent noise parameters theta = ({mu_k, sigma_k}, Pi) (Eq. 3), batched.

    Attributes:
        mu: (..., K) mode means.
        sigma: (..., K) mode standard deviations (> 0).
        pi: (..., K, K) row-stochastic TPM, ``pi[..., k, l] = P(r_t = l | r_{t-1} = k)``.
    """

    mu: Tensor
    sigma: Tensor
    pi: Tensor

    @property
    def k(self) -> int:
        return self.mu.shape[-1]

    def expand(self, *shape: int) -> "NoiseParams":
        """Broadcast to batch shape ``shape`` (returns contiguous clones)."""
        k = self.k
        return NoiseParams(
            self.mu.expand(*shape, k).clone(),
            self.sigma.expand(*shape, k).clone(),
            self.pi.expand(*shape, k, k).clone(),
        )


def validate_params(mu, sigma, pi, prefix: str = "task.modes", atol: float = 1e-8) -> None:
    """Check one parameter set before any work starts.

    Args:
        mu: length-K sequence of means.
        sigma: length-K sequence of standard deviations (must be > 0).
        pi: K×K nested sequence, rows summing to one, entries in [0, 1].
        prefix: config path used in error messages.

    Raises:
        ConfigError: on K mismatch, non-positive sigma, non-finite values or a non-stochastic TPM.
    """
    mu_t = torch.as_tensor(mu, dtype=torch.float64)
    sg_t = torch.as_tensor(sigma, dtype=torch.float64)
    try:
        pi_t = torch.as_tensor(pi, dtype=torch.float64)
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{prefix}: transition matrix must be a K×K list of lists ({exc})") from None
    if mu_t.ndim != 1 or mu_t.numel() < 1:
        raise ConfigError(f"{prefix}: mu must be a non-empty list, got {mu!r}")
    k = mu_t.numel()
    if sg_t.shape != (k,):
        raise ConfigError(f"{prefix}: K mismatch: mu has {k} modes but sigma has shape {tuple(sg_t.shape)}")
    if pi_t.shape != (k, k):
        raise ConfigError(f"{prefix}: K mismatch: mu has {k} modes but the transition matrix has shape "
                          f"{tuple(pi_t.shape)} (expected ({k}, {k}))")
    for name, t in (("mu", mu_t), ("sigma", sg_t), ("pi", pi_t)):
        if not torch.isfinite(t).all():
            raise ConfigError(f"{prefix}: {name} must be finite, got {t.tolist()}")
    if (sg_t <= 0).any():
        raise ConfigError(f"{prefix}: sigma must be > 0 for every mode, got {sg_t.tolist()}")
    if (pi_t < 0).any() or (pi_t > 1).any():
        raise ConfigError(f"{prefix}: transition probabilities must lie in [0, 1], got {pi_t.tolist()}")
    rows = pi_t.sum(-1)
    if not torch.allclose(rows, torch.ones_like(rows), atol=atol):
        raise ConfigError(f"{prefix}: every row of the transition matrix must sum to 1, row sums are {rows.tolist()}")


def make_params(mu, sigma, pi, *, dtype=torch.float64, device="cpu", prefix="task.modes") -> NoiseParams:
    """Validated :class:`NoiseParams` from plain lists. ``pi`` may be a K×K matrix or, for K = 2,
    the diagonal ``[pi_11, pi_22]`` as in Table I."""
    pi_t = torch.as_tensor(pi, dtype=torch.float64)
    if pi_t.ndim == 1 and pi_t.numel() == len(mu) == 2:  # Table I shorthand [pi_11, pi_22]
        if ((pi_t < 0) | (pi_t > 1)).any():
            raise ConfigError(f"{prefix}: transition probabilities must lie in [0, 1], got {pi_t.tolist()}")
        pi_t = torch.stack([torch.stack([pi_t[0], 1 - pi_t[0]]), torch.stack([1 - pi_t[1], pi_t[1]])])
    validate_params(mu, sigma, pi_t.tolist(), prefix=prefix)
    kw = dict(dtype=dtype, device=device)
    return NoiseParams(torch.as_tensor(mu, **kw), torch.as_tensor(sigma, **kw), pi_t.to(**kw))


def obs_loglik(e: Tensor, mu: Tensor, sigma: Tensor) -> Tensor:
    """Log of g(y | x, theta_l) for every mode (Eq. 12, first factor).

    Args:
        e: (B..., N) residuals ``y - h(x)``.
        mu, sigma: (B..., K).

    Returns:
        (B..., N, K) log-densities.
    """
    z = (e[..., None] - mu[..., None, :]) / sigma[..., None, :]
    return -0.5 * z * z - torch.log(sigma[..., None, :]) - 0.5 * LOG_2PI


def m_step(stats: Tensor, prev: NoiseParams, *, sigma_floor: float = 1e-3, pi_floor: float = 1e-10,
           counters: dict | None = None) -> NoiseParams:
    """M-step of Eq. (8) for Gaussian modes and the TPM.

    Args:
        stats: (B..., D) sufficient statistics (layout in the module docstring).
        prev: previous parameters (B..., K); kept where a statistic is degenerate (zero occupancy).
        sigma_floor: lower bound on sigma (a clamp event is counted in ``counters['sigma_clamped']``).
        pi_floor: lower bound on TPM entries before row re-normalisation.

    Returns:
        New :class:`NoiseParams` with the batch shape of ``stats``.
    """
    k = prev.k
    s1 = stats[..., : k * k].unflatten(-1, (k, k))
    s2 = stats[..., k * k: k * k + k]
    s3a = stats[..., k * k + k: k * k + 2 * k]
    s3b = stats[..., k * k + 2 * k:]
    tiny = torch.finfo(stats.dtype).tiny * 1e10
    ok = s2 > tiny
    s2s = torch.where(ok, s2, torch.ones_like(s2))
    mu = torch.where(ok, s3a / s2s, prev.mu)
    var = torch.where(ok, s3b / s2s - mu * mu, prev.sigma ** 2)
    low = var < sigma_floor ** 2
    if counters is not None and bool(low.any()):
        counters["sigma_clamped"] = counters.get("sigma_clamped", 0) + int(low.sum())
    sigma = torch.sqrt(var.clamp_min(sigma_floor ** 2))
    rows = s1.sum(-1, keepdim=True)
    rok = rows > tiny
    pi = torch.where(rok, s1 / torch.where(rok, rows, torch.ones_like(rows)), prev.pi).clamp_min(pi_floor)
    pi = pi / pi.sum(-1, keepdim=True)
    bad = ~(torch.isfinite(mu).all() and torch.isfinite(sigma).all() and torch.isfinite(pi).all())
    if bad:  # never propagate NaN estimates
        warnings.warn("m_step produced non-finite parameters; keeping the previous ones where non-finite")
        mu = torch.where(torch.isfinite(mu), mu, prev.mu)
        sigma = torch.where(torch.isfinite(sigma), sigma, prev.sigma)
        pi = torch.where(torch.isfinite(pi), pi, prev.pi)
    return NoiseParams(mu, sigma, pi)


def stationary(pi: Tensor) -> Tensor:
    """Stationary distribution of a K×K TPM (left eigenvector, via a linear solve). pi: (K, K) -> (K,)."""
    k = pi.shape[-1]
    a = (pi.T - torch.eye(k, dtype=pi.dtype, device=pi.device))
    a = torch.cat([a[:-1], torch.ones(1, k, dtype=pi.dtype, device=pi.device)], 0)
    b = torch.zeros(k, dtype=pi.dtype, device=pi.device)
    b[-1] = 1.0
    p = torch.linalg.solve(a, b).clamp_min(0)
    return p / p.sum()


def simulate_modes(pi: Tensor, shape: tuple, steps: int, gen, r0: Tensor | None = None) -> Tensor:
    """Sample mode sequences r_0..r_T of the Markov chain (Eq. 1a), vectorised over ``shape``.

    Args:
        pi: (K, K) TPM.
        shape: batch shape.
        steps: T (number of transitions).
        gen: torch generator, or :class:`dslearn.streams.Streams` over leading dims of ``shape``.
        r0: optional (shape) initial modes; default drawn from the stationary distribution.

    Returns:
        (*shape, T+1) long tensor of modes.
    """
    from dslearn.streams import rand

    shape = tuple(shape)
    n = int(torch.tensor(shape).prod()) if len(shape) else 1
    cum = pi.cumsum(-1)
    if r0 is None:
        p0 = stationary(pi)
        u = rand(shape, gen, dtype=pi.dtype, device=pi.device).reshape(n)
        r = torch.searchsorted(p0.cumsum(0).contiguous(), u[:, None]).squeeze(-1).clamp_max(pi.shape[0] - 1)
    else:
        r = r0.reshape(n).to(pi.device)
    out = [r]
    u = rand((*shape, steps), gen, dtype=pi.dtype, device=pi.device).reshape(n, steps)
    for t in range(steps):
        r = (u[:, t, None] > cum[r]).sum(-1).clamp_max(pi.shape[0] - 1)
        out.append(r)
    return torch.stack(out, -1).reshape(*shape, steps + 1)
