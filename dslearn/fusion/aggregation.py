r"""Aggregation of local GP predictions (paper Sec. II-B) and the UCB of Theorem 1.

All functions work on the last axis = experts, with arbitrary leading batch dims and a boolean
``mask`` (False = expert left out: empty window, paper Sec. III-B). ``prior_var`` is the
prior variance :math:`\sigma_{**}^2` of f at the test input (the SE amplitude, shared by all
experts); it broadcasts against the batch shape.

* ``poe``  : :math:`\sigma^{-2} = \sum_i \sigma_i^{-2}`, :math:`\mu = \sigma^2 \sum_i \sigma_i^{-2}\mu_i`.
* ``gpoe`` : Eqs. 9-10 with :math:`\beta_i = \tfrac12(\log\sigma_{**}^2 - \log\sigma_i^2)` (Eq. 7).
* ``bcm``  : :math:`\sigma^{-2} = \sum_i \sigma_i^{-2} + (1 - M)\sigma_{**}^{-2}` (Tresp 2000).
* ``rbcm`` : Eqs. 12-13 with the Eq. 7 weights.
* ``grbcm``: generalised robust BCM (Liu, Cai, Zhang, Ong, ICML 2018), :func:`aggregate_grbcm`:
  needs a *communication expert* ``c`` (a data subset shared by all experts) and experts
  ``+i`` trained on :math:`D_c \cup D_i`;
  :math:`\sigma^{-2} = \sum_i \beta_i\sigma_{+i}^{-2} + (1 - \sum_i\beta_i)\sigma_c^{-2}`,
  :math:`\mu = \sigma^2[\sum_i \beta_i\sigma_{+i}^{-2}\mu_{+i} + (1 - \sum_i\beta_i)\sigma_c^{-2}\mu_c]`,
  :math:`\beta_i = \tfrac12(\log\sigma_c^2 - \log\sigma_{+i}^2)` (entropy gain over the
  communication expert instead of over the prior). With an empty communication set it is rBCM.

With no expert at all the result is the GP prior (mean 0, variance :math:`\sigma_{**}^2`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from dslearn.errors import ConfigError, check_choice

AGGREGATIONS = ("poe", "gpoe", "bcm", "rbcm", "grbcm")


def entropy_weights(var: Tensor, prior_var: Tensor, mask: Tensor) -> Tensor:
    """Eq. 7: :math:`\\beta_i = 0.5(\\log\\sigma_{**}^2 - \\log\\sigma_i^2)` (>= 0), 0 where masked.

    Args:
        var: (..., M) expert variances; prior_var: broadcastable to (..., 1); mask: (..., M) bool.
    """
    pv = torch.as_tensor(prior_var, dtype=var.dtype, device=var.device)
    if pv.dim() < var.dim():
        pv = pv.unsqueeze(-1)
    beta = 0.5 * (torch.log(pv) - torch.log(var))
    return torch.where(mask, beta.clamp_min(0.0), torch.zeros_like(beta))


def aggregate(mean: Tensor, var: Tensor, mask: Tensor, prior_var, method: str,
              normalise_beta: bool = False):
    """Aggregate local predictive distributions into one.

    Args:
        mean, var: (..., M) local predictive means / variances (Eqs. 5-6).
        mask: (..., M) bool, which experts take part.
        prior_var: prior variance of f, shape broadcastable to (...).
        method: one of :data:`AGGREGATIONS`.
        normalise_beta: gPoE/rBCM with :math:`\\beta_i / \\sum_j \\beta_j` instead of raw Eq. 7.

    Returns:
        (mean, var, beta): aggregated mean (...), variance (...) > 0, and the weights (..., M)
        actually used (1 for PoE/BCM).
    """
    check_choice("task.aggregations", method, AGGREGATIONS)
    if method == "grbcm":
        raise ValueError("grbcm needs a communication expert: use aggregate_grbcm()")
    pv = torch.as_tensor(prior_var, dtype=var.dtype, device=var.device).expand(var.shape[:-1])
    var = var.clamp_min(1e-12)
    maskf = mask.to(var.dtype)
    if method in ("poe", "bcm"):
        beta = maskf
    else:
        beta = entropy_weights(var, pv, mask)
        if normalise_beta:
            s = beta.sum(-1, keepdim=True)
            beta = torch.where(s > 0, beta / s.clamp_min(1e-300), beta)
    prec_i = beta / var                         # beta_i sigma_i^{-2}
    prec = prec_i.sum(-1)
    if method == "bcm":
        prec = prec + (1.0 - maskf.sum(-1)) / pv
    elif method == "rbcm":
        prec = prec + (1.0 - beta.sum(-1)) / pv
    num = (prec_i * mean).sum(-1)
    # no usable expert (or all weights 0 for gPoE) -> prior; floor at the prior precision
    empty = prec_i.sum(-1) <= 0
    prec = torch.where(empty, 1.0 / pv, prec)
    if method in ("bcm", "rbcm"):
        prec = torch.maximum(prec, 1.0 / pv)   # exact-arithmetic property, guards round-off
    agg_var = 1.0 / prec
    agg_mean = torch.where(empty, torch.zeros_like(num), agg_var * num)
    return agg_mean, agg_var, beta


def aggregate_grbcm(mean: Tensor, var: Tensor, mask: Tensor, comm_mean: Tensor, comm_var: Tensor,
                    normalise_beta: bool = False):
    r"""Generalised robust BCM (Liu et al. 2018) with a communication expert.

    Args:
        mean, var: (..., M) predictions of the augmented experts :math:`+i` (data
            :math:`D_c \cup D_i`).
        mask: (..., M) bool, experts taking part (non-empty own data :math:`D_i`).
        comm_mean, comm_var: (...) prediction of the communication expert (data :math:`D_c`
            only; the GP prior when :math:`D_c` is empty).
        normalise_beta: :math:`\beta_i / \sum_j \beta_j`.

    Returns:
        (mean (...), var (...), beta (..., M)). No expert -> the communication expert.
    """
    cv = comm_var.clamp_min(1e-12)
    var = var.clamp_min(1e-12)
    beta = entropy_weights(var, cv, mask)
    if normalise_beta:
        s = beta.sum(-1, keepdim=True)
        beta = torch.where(s > 0, beta / s.clamp_min(1e-300), beta)
    prec_i = beta / var
    wc = 1.0 - beta.sum(-1)
    prec = prec_i.sum(-1) + wc / cv
    # each beta_i (sigma_{+i}^-2 - sigma_c^-2) >= 0 because sigma_{+i}^2 <= sigma_c^2: prec >= sigma_c^-2
    prec = torch.maximum(prec, 1.0 / cv)
    agg_var = 1.0 / prec
    agg_mean = agg_var * ((prec_i * mean).sum(-1) + wc / cv * comm_mean)
    return agg_mean, agg_var, beta


def ucb_gamma(num_experts: Tensor, delta: float) -> Tensor:
    """Equal :math:`\\gamma_i` with :math:`\\sum_i e^{-\\gamma_i/2} = \\delta`: :math:`\\gamma = 2\\log(M/\\delta)`."""
    m = num_experts.clamp_min(1).to(torch.float64)
    return 2.0 * torch.log(m / delta)


def ucb_bound(var: Tensor, beta: Tensor, mask: Tensor, prior_var, delta: float) -> Tensor:
    """Theorem 1 (Eq. 24) error bound, holding with probability >= 1 - delta.

    .. math:: |f - \\mu| \\le \\frac{\\sum_i \\beta_i\\gamma_i^{1/2}\\sigma_i^{-1}}{\\sum_i \\beta_i\\sigma_i^{-2}},
        \\quad \\gamma_i = 2\\log(M/\\delta).

    Args:
        var, beta, mask: (..., M); prior_var broadcastable to (...); delta in (0, 1).

    Returns:
        (...,) bound; where no expert has positive weight: Lemma 1 on the prior,
        :math:`\\sqrt{2\\log(1/\\delta)}\\,\\sigma_{**}`.
    """
    pv = torch.as_tensor(prior_var, dtype=var.dtype, device=var.device).expand(var.shape[:-1])
    m = mask.sum(-1)
    g = ucb_gamma(m, delta).to(var.dtype)
    b = torch.where(mask, beta, torch.zeros_like(beta))
    sd = var.clamp_min(1e-12).sqrt()
    den = (b / sd ** 2).sum(-1)
    num = g.sqrt() * (b / sd).sum(-1)
    prior_bound = math.sqrt(2 * math.log(1 / delta)) * pv.sqrt()
    return torch.where(den > 0, num / den.clamp_min(1e-300), prior_bound)


def ucb_bound_grbcm(var: Tensor, beta: Tensor, mask: Tensor, comm_var: Tensor, delta: float) -> Tensor:
    r"""Error bound for grBCM's mean by Theorem 1's argument, including the communication expert.

    grBCM's mean is :math:`\mu = \sum_i \omega_i\mu_{+i} + \omega_c\mu_c` with
    :math:`\omega_i = \beta_i\sigma^2/\sigma_{+i}^2`, :math:`\omega_c = (1 - \sum_i\beta_i)\sigma^2/\sigma_c^2`
    (:math:`\sum\omega = 1`; :math:`\omega_c < 0` when :math:`\sum_i\beta_i > 1`), so when Lemma 1
    holds for all :math:`M + 1` GPs (probability :math:`\ge 1 - \delta` by the union bound with
    :math:`\gamma = 2\log((M + 1)/\delta)`),

    .. math:: |f - \mu| \le \gamma^{1/2}\Big(\sum_i |\omega_i|\sigma_{+i} + |\omega_c|\sigma_c\Big).

    Continuous in the weights: with every :math:`\beta_i = 0` (grBCM = the communication expert)
    it is :math:`\gamma^{1/2}\sigma_c`. (Eq. 24 applied to the augmented experts alone drops
    :math:`\omega_c` and falls back to the prior when all :math:`\beta_i = 0`.)

    Args:
        var, beta, mask: (..., M) augmented experts' variances, the weights returned by
            :func:`aggregate_grbcm`, which experts take part; comm_var: (...); delta in (0, 1).
    """
    cv = comm_var.clamp_min(1e-12)
    v = var.clamp_min(1e-12)
    b = torch.where(mask, beta, torch.zeros_like(beta))
    prec = torch.maximum((b / v).sum(-1) + (1.0 - b.sum(-1)) / cv, 1.0 / cv)
    agg = 1.0 / prec
    w_i = b * agg.unsqueeze(-1) / v
    w_c = (1.0 - b.sum(-1)) * agg / cv
    g = ucb_gamma(mask.sum(-1) + 1, delta).to(var.dtype)
    return g.sqrt() * ((w_i.abs() * v.sqrt()).sum(-1) + w_c.abs() * cv.sqrt())


#: the rules a fusion centre of local GP experts can apply by itself (grBCM also needs a communication set
#: shared with every sensor: the Liu study runs it, ``task.aggregations``)
CENTRE_RULES = ("poe", "gpoe", "bcm", "rbcm")
#: the rules that weight the experts by Eq. 7 (``normalise_beta`` applies to them only)
WEIGHTED_RULES = ("gpoe", "rbcm")


class AggregationRule:
    """The fusion part of a method whose local GP experts are combined at a fusion centre (Liu et al.'s
    DGPT): one aggregation rule of :func:`aggregate`. It is a part of a different kind from the
    information-form fusions of :mod:`dslearn.fusion.strategies` (``kind = "aggregation"``): a method
    declares the kind it takes.

    Args:
        rule: one of :data:`CENTRE_RULES`.
        normalise_beta: gPoE / rBCM with :math:`\\beta_i / \\sum_j \\beta_j` (Eq. 7 normalised); the
            unweighted rules (PoE, BCM) refuse ``True``.
    """

    kind = "aggregation"
    #: the experts' predictions go to a fusion centre: the network's links are not read
    #: (:func:`dslearn.schemas.base.unread_keys`)
    uses_links = False
    config_unread = "a GP aggregation rule at a fusion centre"

    def __init__(self, rule: str, normalise_beta: bool = False):
        check_choice("consensus.rule", rule, CENTRE_RULES)
        if not isinstance(normalise_beta, bool):
            raise ConfigError(f"consensus.normalise_beta={normalise_beta!r} must be true or false")
        if normalise_beta and rule not in WEIGHTED_RULES:
            raise ConfigError(f"consensus.normalise_beta=true weights the experts of {list(WEIGHTED_RULES)}; "
                              f"consensus.rule={rule!r} has no weights to normalise")
        self.rule = rule
        self.normalise_beta = normalise_beta

    @property
    def name(self) -> str:
        return self.rule

    def __call__(self, mean: Tensor, var: Tensor, mask: Tensor, prior_var):
        """:func:`aggregate` with this rule: ``(mean, var, beta)``."""
        return aggregate(mean, var, mask, prior_var, self.rule, self.normalise_beta)

    def __repr__(self) -> str:
        return f"AggregationRule(rule={self.rule!r}, normalise_beta={self.normalise_beta})"
