r"""GP motion model (GP-EKF): a :class:`~dslearn.models.base.MotionModel` over one online GP
backend per node (:mod:`dslearn.models.gp_backends.exact`, :mod:`dslearn.models.gp_backends.sparse`),
used through the :class:`~dslearn.models.gp_backends.protocol.GPBackend` protocol only."""

from __future__ import annotations

import torch
from torch import Tensor

from dslearn.errors import ConfigError, check_choice
from dslearn.models.base import MotionModel
from dslearn.models.gp_backends import GPBackend, OnlineGP, make_online_gp
from dslearn.models.gp_backends.exact import FACTORS
from dslearn.types import AGENT_DIM, DTYPES, StepContext

NOISE_MODES = ("latent", "predictive", "adaptive")
INPUTS = ("mean", "belief")


class GPMotionModel(MotionModel):
    r"""GP motion model (GP-EKF, Yu et al. Section IV-A, Algorithm 2 lines 2–4).

    Each of the ``S`` nodes keeps its own data set :math:`D_{f,i}` of (ŷ^{t-1} → ŷ^t) pairs.
    :math:`f(y) = \mu_f(y)`, Jacobian :math:`\partial\mu_f/\partial y` (closed form or autograd),
    process covariance :math:`Q = \Sigma_f(y) I` (``noise=latent``, as printed),
    :math:`(\Sigma_f(y) + \sigma_\epsilon^2) I` (``noise=predictive``), or
    :math:`\Sigma_f(y) I + \mathrm{diag}(q)` (``noise=adaptive``): ``q`` holds one position and one
    velocity variance per node, learned while tracking like the data set: after each training
    episode the node smooths its own estimates and takes the EM (maximum-likelihood) step for
    the process noise (:meth:`update_noise`). The latent variance only says how well the GP
    knows the mean of its (noisy, biased) targets; ``q`` is the one-step model error the
    filter actually meets.

    Inputs to :meth:`forward` etc. must have the node dimension first: ``(S, *B, Dx)``.

    Args:
        state_dim: ``Dx``.
        num_nodes: ``S``.
        outputscale, lengthscale, noise_std: :math:`\sigma_f, l_f, \sigma_\epsilon`.
        mean: ``zero`` (as printed), ``constant``, or ``identity`` (learns the increment).
        noise: ``latent`` or ``predictive`` (see above).
        jacobian: ``closed_form`` or ``autograd``.
        fit_every: refit hyperparameters by marginal likelihood after this many training
            episodes (0 = never, the paper's fixed hyperparameters).
        noise_fading: fading factor ``b`` in (0, 1) of the ``adaptive`` noise estimate, per training
            episode (a memory of about ``1/(1-b)`` episodes).
        factor_dtype: ``null`` (the run's dtype) or ``float32``: the exact GP's factor in
            single precision, everything else in the run's dtype (:class:`OnlineGP`).
        factor: ``auto``, ``inverse`` or ``cholesky``: whether the exact GP keeps the inverse
            Cholesky factor (one pass over memory per learning step) or the factor itself
            (two triangular solves); ``auto`` takes the inverse on the CPU (:class:`OnlineGP`).
        inputs: where the filter's linearisation evaluates the GP. ``mean`` (the paper's EKF, as
            printed): mean, Jacobian and latent variance at the belief's mean. ``belief``: the
            same averaged over the belief :math:`\mathcal N(\hat y, P)` the filter hands in
            (``ctx.cov``; :meth:`OnlineGP.predict_belief`): the statistical linearisation of the
            GP, which a belief much wider than the length scale (a target the node has not
            localised yet) sees as the prior mean and its Jacobian instead of a local
            slope extrapolated over kilometres. Exact and window GPs; point evaluations
            (:meth:`forward`, roll-outs, sigma points) are unchanged.
        variant: ``exact`` (:class:`OnlineGP`) or a scalable variant of
            :mod:`dslearn.models.gp_backends.sparse`: ``window`` (option ``window``), ``sgpr`` (``inducing``),
            ``ssgp`` (``features``, ``seed``); options are passed as keywords.
    """

    learnable = True

    @classmethod
    def for_scenario(cls, *, scenario, num_nodes: int, dtype, device, **keys) -> "GPMotionModel":
        """The config factory (``conf/model/gp*.yaml``): the GP keys of the config (the constructor's
        keyword arguments), sized by the filter's state (``[p, v]`` per agent of the scenario, whatever the
        scenario's own layout: Jiang's source is a position, its filters track a position and a velocity) and the
        network's nodes."""
        return cls(AGENT_DIM * scenario.num_agents, num_nodes, dtype=dtype, device=device, **keys)

    def __init__(
        self,
        state_dim: int,
        num_nodes: int = 1,
        outputscale: float = 1.0,
        lengthscale: float = 2.0,
        noise_std: float = 0.5,
        mean: str = "zero",
        noise: str = "latent",
        jacobian: str = "closed_form",
        fit_every: int = 0,
        fit_iters: int = 50,
        fit_lr: float = 0.05,
        capacity: int = 256,
        dtype: torch.dtype = torch.float64,
        device: str | torch.device = "cpu",
        variant: str = "exact",
        noise_fading: float = 0.9,
        factor_dtype: str | None = None,
        factor: str = "auto",
        inputs: str = "mean",
        **variant_options,
    ):
        super().__init__()
        check_choice("model.inputs", inputs, INPUTS)
        if factor_dtype is not None:
            check_choice("model.factor_dtype", factor_dtype, tuple(DTYPES))
            if variant != "exact" or variant_options:
                raise ConfigError(f"model.factor_dtype={factor_dtype}: only the exact GP (model.variant=exact) has one")
        check_choice("model.factor", factor, FACTORS)
        if factor != "auto" and (variant != "exact" or variant_options):
            raise ConfigError(f"model.factor={factor}: only the exact GP (model.variant=exact) has one (choose auto)")
        check_choice("model.noise", noise, NOISE_MODES)
        if not 0.0 < float(noise_fading) < 1.0:
            raise ConfigError(f"model.noise_fading={noise_fading!r} must be in (0, 1)")
        if state_dim % 4:
            raise ConfigError(f"GPMotionModel: state_dim={state_dim} must be 4 x agents")
        check_choice("model.jacobian", jacobian, ("closed_form", "autograd"))
        if fit_every < 0:
            raise ConfigError(f"model.fit_every={fit_every} must be >= 0")
        self.state_dim = int(state_dim)
        self.noise_mode, self.jacobian_mode = noise, jacobian
        self.fit_every, self.fit_iters, self.fit_lr = int(fit_every), int(fit_iters), float(fit_lr)
        self.variant = variant
        self.gp: GPBackend
        if variant == "exact" and not variant_options:
            self.gp = OnlineGP(num_nodes, state_dim, state_dim, outputscale, lengthscale, noise_std, mean, capacity, dtype, device,
                               factor_dtype=None if factor_dtype is None else DTYPES[factor_dtype], factor=factor)
        else:  # scalable variants (dslearn.models.gp_backends.sparse): window | sgpr | ssgp
            if fit_every and variant != "exact":
                raise ConfigError(f"model.fit_every={fit_every}: hyperparameter fitting is only available for model.variant=exact")
            self.gp = make_online_gp(
                variant, num_nodes, state_dim, state_dim, outputscale=outputscale, lengthscale=lengthscale,
                noise_std=noise_std, mean=mean, dtype=dtype, device=device, capacity=capacity, **variant_options,
            )

        if inputs == "belief":
            if not self.gp.supports_belief:
                raise ConfigError(f"model.inputs=belief: only the exact and window GPs average over the belief "
                                  f"(model.variant={variant}; choose model.inputs=mean)")
            if jacobian != "closed_form":
                raise ConfigError("model.inputs=belief: the belief-averaged Jacobian is closed form (choose model.jacobian=closed_form)")
        self.inputs = inputs
        self.noise_fading = float(noise_fading)
        # adaptive process noise: running (position, velocity) variance per node, and the weight of
        # its fading average over episodes; it starts at sigma_eps^2, counted as one episode
        self.register_buffer("q_noise", torch.full((num_nodes, 2), float(noise_std) ** 2, dtype=dtype, device=device))
        self.register_buffer("q_weight", torch.ones(num_nodes, 1, dtype=dtype, device=device))

    adapts_noise = property(lambda self: self.noise_mode == "adaptive")

    @property
    def num_nodes(self) -> int:
        return self.gp.num_nodes

    def extra_noise(self, like: Tensor) -> Tensor:
        """``(S, Dx)`` diagonal added to the latent variance in ``noise=adaptive`` (zeros otherwise)."""
        if self.noise_mode != "adaptive":
            return like.new_zeros(self.num_nodes, self.state_dim)
        q = self.q_noise.clamp_min(0.0).to(like)  # (S, 2): position, velocity
        return q.repeat_interleave(2, dim=-1).repeat(1, self.state_dim // 4)

    @torch.no_grad()
    def update_noise(self, moments: Tensor, Q_used: Tensor, valid: Tensor) -> None:
        r"""EM update of the adaptive process noise (``noise=adaptive``) from one training episode.

        ``moments`` are the expected outer products of the one-step transition error given the
        whole episode (:func:`dslearn.filters.smoother.transition_error_moments`), whose
        average is the M-step estimate of the total process noise. The latent part
        :math:`\Sigma_f` the model already adds is taken off; what remains, pooled over agents
        and axes into one position and one velocity variance per node, joins a fading average
        over episodes (``noise_fading``; the initial value ``noise_std^2`` counts as one episode).

        Args:
            moments, Q_used: ``(S, K, Dx, Dx)``; valid: ``(S,)`` bool (nodes informed throughout).
        """
        if self.noise_mode != "adaptive":
            return
        d = lambda m: m.diagonal(dim1=-2, dim2=-1)  # noqa: E731
        latent = d(Q_used) - self.extra_noise(Q_used).unsqueeze(1)  # (S, K, Dx)
        sample = (d(moments) - latent).mean(1)  # (S, Dx)
        sample = sample.unflatten(-1, (-1, 2, 2)).mean((-3, -1)).to(self.q_noise)  # (S, 2): position, velocity
        ok = (valid.to(self.q_noise.device) & torch.isfinite(sample).all(-1)).unsqueeze(-1)
        b = self.noise_fading
        w_new = b * self.q_weight + 1.0
        upd = (b * self.q_weight * self.q_noise + sample) / w_new
        self.q_noise.copy_(torch.where(ok, upd, self.q_noise))
        self.q_weight.copy_(torch.where(ok, w_new, self.q_weight))

    #: a gradient learner trains each node's hyperparameters (an exact GP's, on the data it holds)
    gradient_parameters = "gp"

    def gradient_misfit(self) -> str | None:
        """Only an exact GP on the mean inputs has a differentiable posterior."""
        if not isinstance(self.gp, OnlineGP):
            return f"a GP with model.variant={self.variant} (only the exact GPs: model.variant=exact|window)"
        if self.inputs != "mean":
            return "a GP with model.inputs=belief (choose model.inputs=mean)"
        return None

    def _flat(self, x: Tensor) -> Tensor:
        if x.shape[0] != self.num_nodes:
            raise ValueError(f"GPMotionModel expects the node dimension first: got {tuple(x.shape)}, S={self.num_nodes}")
        return x.reshape(self.num_nodes, -1, self.state_dim)

    def linearize(self, x: Tensor, ctx: StepContext) -> tuple[Tensor, Tensor, Tensor]:
        if self.inputs == "belief" and ctx.cov is not None:  # averaged over N(x, ctx.cov)
            cov = ctx.cov.to(x).expand(*x.shape, x.shape[-1]).reshape(self.num_nodes, -1, self.state_dim, self.state_dim)
            mean, var, jac = self.gp.predict_belief(self._flat(x), cov)
            jac = jac.reshape(*x.shape, self.state_dim)
        else:
            mean, var, jac = self.gp.predict(self._flat(x), jacobian=self.jacobian_mode == "closed_form")
            if self.jacobian_mode == "autograd":
                jac = self._autograd_jacobian(x)
            else:
                jac = jac.reshape(*x.shape, self.state_dim)
        if self.noise_mode == "predictive":
            var = var + self.gp.noise_var.unsqueeze(-1)
        eye = torch.eye(self.state_dim, dtype=x.dtype, device=x.device)
        q = var.reshape(*x.shape[:-1], 1, 1) * eye
        if self.noise_mode == "adaptive":
            extra = self.extra_noise(x).reshape(self.num_nodes, *([1] * (x.dim() - 2)), self.state_dim)
            q = q + torch.diag_embed(extra.expand(*x.shape))
        return mean.reshape(x.shape).to(x.dtype), jac.to(x.dtype), q.to(x.dtype)

    def forward(self, x: Tensor, ctx: StepContext) -> Tensor:
        mean, _, _ = self.gp.predict(self._flat(x), jacobian=False, variance=False)
        return mean.reshape(x.shape).to(x.dtype)

    def noise_cov(self, x: Tensor, ctx: StepContext) -> Tensor:
        return self.linearize(x, ctx)[2]

    def jacobian(self, x: Tensor, ctx: StepContext) -> Tensor:
        return self.linearize(x, ctx)[1]

    def _autograd_jacobian(self, x: Tensor) -> Tensor:
        """Jacobian of the posterior mean by autograd (reference path)."""
        xf = self._flat(x).detach().requires_grad_(True)
        with torch.enable_grad():
            mean = self.gp.differentiable_mean(xf)
            rows = [torch.autograd.grad(mean[..., o].sum(), xf, retain_graph=True)[0] for o in range(self.state_dim)]
        return torch.stack(rows, -2).reshape(*x.shape, self.state_dim).detach()

    def add_data(self, inputs: Tensor, outputs: Tensor, valid: Tensor | None = None) -> None:
        self.gp.append(inputs, outputs, valid)

    def reserve(self, appends: int) -> None:
        if self.gp.grows_per_append:  # the exact GP (one point per node per append)
            self.gp.reserve(appends)

    def fit(self) -> "GPMotionModel":
        self.gp.fit(self.fit_iters, self.fit_lr)
        return self

    def save(self, path) -> None:
        """Save hyperparameters and the posterior state of every node: the data set (inputs,
        residual targets, mask) for the exact and window GPs, the sufficient statistics for
        SGPR / SSGP (the backend's :meth:`~dslearn.models.gp_backends.protocol.GPBackend.state_tensors`)."""
        torch.save(self._checkpoint(**self.gp.state_tensors()), path)

    def load(self, path) -> "GPMotionModel":
        """Safe-load what :meth:`save` wrote; checks class, hyperparameter shapes and that the
        saved state has this model's node count, dimensions and variant (the backend's
        :meth:`~dslearn.models.gp_backends.protocol.GPBackend.load_state_tensors`); the exact and window
        GPs factorise once, with the loaded hyperparameters. A refused file leaves the model as it was."""
        names = tuple(self.gp.state_tensors())
        blob = self._read_checkpoint(path, extra=names)
        before = {k: v.clone() for k, v in self.state_dict().items()}
        self.load_state_dict(blob["state_dict"])  # the hyperparameters first: the exact GP factorises with them
        try:
            self.gp.load_state_tensors({k: blob[k] for k in names}, str(path))
        except Exception:
            self.load_state_dict(before)  # a refused file changes nothing
            raise
        return self


#: what the config layer asks of the part (:func:`dslearn.schemas.base.unread_keys`, ``online_learning``)
GPMotionModel.config_learns_online = True

