r"""Online exact Gaussian-process regression with incremental Cholesky updates (the GP backend).

GPyTorch supplies the kernel (``ScaleKernel(RBFKernel)``), the Gaussian likelihood and the
marginal-likelihood objective used by :meth:`OnlineGP.fit`; the per-step posterior is kept
by hand as a Cholesky factor extended by one row per appended point (``O(n^2)``), because
GPyTorch's fantasy updates and its CG path above 800 points are slow or inexact for this
use (measured; see the README).

One :class:`OnlineGP` holds ``S`` independent data sets (one per sensor node), all of the
same length ``n`` (every node appends one example per step), so every operation is a
batched tensor operation over nodes. All ``Dy`` outputs share one kernel (independent
outputs, as in Yu et al. Section IV-A). Points can be appended as *invalid* (a node had
nothing to learn from): they are kept as decoupled unit rows of the factor and contribute
exactly nothing to predictions. While no node holds a valid point (a field of sensors whose learning gate
has admitted nothing yet, e.g. Liu's 200 sensors), every prediction is the prior and an append only writes
its unit row: both skip the ``O(S n^2)`` passes over the factor, with the same numbers, bit for bit
(:attr:`OnlineGP.skip_void`). Where some nodes hold valid points and others none (the few sensors near a
target), a prediction runs its passes on the former only and gives the others the prior; the numbers are the
full passes', bit for bit, but for the latent variance at several queries per node through the inverse factor,
whose batched product over the active nodes may sum in another order (1e-12 relative, tested).
"""

from __future__ import annotations

import warnings

import gpytorch
import torch
from torch import Tensor, nn

from dslearn.diagnostics import record_jitter
from dslearn.errors import ConfigError, check_choice, check_positive
from dslearn.models.gp_backends import inverse_factor
from dslearn.models.gp_backends.means import NAMED, PriorMeanModule
from dslearn.models.kernels import se_kernel
from dslearn.types import StepContext, safe_cholesky

MEANS = ("zero", "constant", "identity")
FACTORS = ("auto", "inverse", "cholesky")


def _same_input(a: Tensor, b: Tensor, version: int) -> bool:
    """Whether ``b`` holds the values ``a`` had when it was predicted at (``a._version`` was
    ``version``): the same memory, unmodified since (no host sync, any device), or, on CPU
    only, equal values."""
    if a.shape != b.shape:
        return False
    if a.data_ptr() == b.data_ptr() and a.stride() == b.stride() and b._version == version:
        return True
    return a.device.type == "cpu" and torch.equal(a, b)


class PriorMean:
    """The prior mean m(x) and its Jacobian for GP backends: a module of
    :mod:`dslearn.models.gp_backends.means` (``self.mean_module``), or the backend's own learned constant
    (``mean_type == "constant"``, the parameter ``constant``). Shapes ``(S, N, d) -> (S, N, Dy)``
    and ``(S, N, Dy, d)``."""

    mean_type: str
    output_dim: int
    input_dim: int
    mean_module: PriorMeanModule | None

    def _set_mean(self, mean) -> None:
        """``mean``: a name in :data:`MEANS` or a :class:`~dslearn.models.gp_backends.means.PriorMeanModule`."""
        if isinstance(mean, PriorMeanModule):
            self.mean_type, module = mean.name, mean
        else:
            check_choice("model.mean", mean, MEANS)
            self.mean_type = str(mean)
            module = None if mean == "constant" else NAMED[mean]()
        self.mean_module = None if module is None else module.bind(self.input_dim, self.output_dim)

    def prior_mean(self, x: Tensor) -> Tensor:
        if self.mean_module is None:
            return self.constant.detach().unsqueeze(-2).expand(*x.shape[:-1], self.output_dim)
        return self.mean_module(x)

    def prior_mean_jacobian(self, x: Tensor) -> Tensor:
        if self.mean_module is None:
            return x.new_zeros(*x.shape[:-1], self.output_dim, self.input_dim)
        return self.mean_module.jacobian(x)


class OnlineGP(PriorMean, nn.Module):
    r"""``S`` exact GPs with a shared RBF kernel per node, updated online.

    Prior :math:`f \sim \mathcal{GP}(m, k)`, :math:`k(a,b) = \sigma_f^2 \exp(-\|a-b\|^2 / 2l^2)`,
    observations :math:`y = f(x) + \epsilon`, :math:`\epsilon \sim \mathcal N(0, \sigma_\epsilon^2)`.

    Args:
        num_nodes: ``S`` independent data sets.
        input_dim: ``Dx``.
        output_dim: ``Dy``.
        outputscale: :math:`\sigma_f` (standard deviation, > 0).
        lengthscale: :math:`l` (> 0).
        noise_std: :math:`\sigma_\epsilon` (> 0).
        mean: prior mean: ``zero``; ``constant`` (learned by :meth:`fit`); ``identity``
            (``m(x) = x[..., :Dy]``, so the GP learns the increment); or a module of
            :mod:`dslearn.models.gp_backends.means` (e.g. ``ConstantVelocityMean(dt)``).
        capacity: initial buffer size (grows in chunks of 128 rows with the Cholesky factor, by
            half with the inverse one; :meth:`reserve` allocates a known total at once).
        factor_dtype: storage of the factor (default ``dtype``). ``torch.float32`` halves
            the memory every step streams (the step is bound by it) while kernel values, targets,
            ``alpha`` and the diagonal stay in ``dtype``; the accuracy cost on the Yu tables is
            measured in the README.
        factor: what the buffer ``L`` holds. ``cholesky``: the factor :math:`L` of
            :math:`K + \sigma^2 I`; a prediction and the append after it cost a forward and a
            backward triangular solve, two passes over the factor. ``inverse``: :math:`L^{-1}`,
            extended by one row per append; the same step is one pass
            (:mod:`dslearn.models.gp_backends.inverse_factor`). ``auto`` (default): ``inverse`` on the CPU
            where its compiled kernel is available, ``cholesky`` otherwise (CUDA, whose path
            was measured with the solves).
    """

    #: :class:`~dslearn.models.gp_backends.protocol.GPBackend` capabilities: :meth:`predict_belief` is closed
    #: form; one point per node per append, so :meth:`reserve` can allocate the buffers at once
    supports_belief = True
    grows_per_append = True
    #: while no node holds a valid point, :meth:`predict` returns the prior and :meth:`append` writes the unit row
    #: of an invalid point without the passes over the factor (CPU: the check is a host read; the numbers are
    #: those of the full passes, bit for bit, tested); while some do not, :meth:`predict` and
    #: :meth:`predict_belief` run the passes on the nodes that do only (the module docstring); False: always
    #: the full passes
    skip_void = True

    def __init__(
        self,
        num_nodes: int,
        input_dim: int,
        output_dim: int,
        outputscale: float = 1.0,
        lengthscale: float = 2.0,
        noise_std: float = 0.5,
        mean: str | PriorMeanModule = "zero",
        capacity: int = 256,
        dtype: torch.dtype = torch.float64,
        device: str | torch.device = "cpu",
        factor_dtype: torch.dtype | None = None,
        factor: str = "auto",
    ):
        super().__init__()
        check_choice("model.factor", factor, FACTORS)
        check_positive("model.outputscale", outputscale)
        check_positive("model.lengthscale", lengthscale)
        check_positive("model.noise_std", noise_std)
        self.num_nodes, self.input_dim, self.output_dim = int(num_nodes), int(input_dim), int(output_dim)
        self._set_mean(mean)
        bs = torch.Size([self.num_nodes])
        # the modules in the run's dtype before their values are set, so that a float64 GP holds its
        # hyperparameters exactly (set in float32 first, they would be rounded to float32)
        self.covar_module = gpytorch.kernels.ScaleKernel(gpytorch.kernels.RBFKernel(batch_shape=bs), batch_shape=bs)
        self.likelihood = gpytorch.likelihoods.GaussianLikelihood(batch_shape=bs)
        self.covar_module.to(dtype=dtype)
        self.likelihood.to(dtype=dtype)
        self.covar_module.outputscale = torch.full(bs, float(outputscale) ** 2, dtype=dtype)
        self.covar_module.base_kernel.lengthscale = torch.full((*bs, 1, 1), float(lengthscale), dtype=dtype)
        self.likelihood.noise = torch.full((*bs, 1), float(noise_std) ** 2, dtype=dtype)
        self.constant = nn.Parameter(torch.zeros(self.num_nodes, self.output_dim), requires_grad=mean == "constant")
        self.to(dtype=dtype, device=device)
        self.dtype_, self.device_ = dtype, torch.device(device)
        self.factor_dtype_ = dtype if factor_dtype is None else factor_dtype
        self.inverse = factor == "inverse" or (
            factor == "auto" and self.device_.type == "cpu" and inverse_factor.HAVE_KERNEL)
        self.n = 0
        self._any_valid = False  # whether some node may hold a valid point (conservative: once True, stays)
        self.clamped = torch.zeros((), dtype=torch.long, device=self.device_)  # clamped diagonals (CUDA)
        self._snapshot_hypers()
        self._streaming = True  # predict at one point then append there (Algorithm 1): solve both at once
        self._pending = False  # a paired solve of predict() not yet used by an append
        self._alloc(int(capacity))

    # storage -----------------------------------------------------------------------------
    def _alloc(self, cap: int, factor: bool = True) -> None:
        s, d, o = self.num_nodes, self.input_dim, self.output_dim
        kw = dict(dtype=self.dtype_, device=self.device_)
        self.X = torch.zeros(s, cap, d, **kw)
        self.Xs = torch.zeros(s, cap, d, **kw)  # X / lengthscale: the kernel's scaled inputs
        self.Xn = torch.zeros(s, cap, **kw)  # their squared norms (the kernel needs no (S, n, d) temporary)
        self.R = torch.zeros(s, cap, o, **kw)  # residual targets y - m(x)
        self.V = torch.zeros(s, cap, o, **kw)  # L^{-1} R
        self.A = torch.zeros(s, cap, o, **kw)  # alpha = K^{-1} R, updated in place by append
        # Cholesky factor of K + sigma^2 I (or its inverse) in the top-left n x n block, identity
        # below: solves run on the whole contiguous buffer (a strided n x n view takes a ~20x
        # slower path)
        if factor:
            self.L = torch.zeros(s, cap, cap, dtype=self.factor_dtype_, device=self.device_)
            self.L.diagonal(dim1=-2, dim2=-1).fill_(1.0)
        self.mask = torch.zeros(s, cap, dtype=torch.bool, device=self.device_)
        self._alpha = None
        self._last = None

    def reserve(self, points: int) -> None:
        """Room for ``points`` more examples per node, allocated once. Only the inverse factor
        takes it: its pass reads the first ``n`` rows, so unused rows cost memory, not time (every
        Cholesky solve runs over the whole buffer, which grows as it fills instead)."""
        if self.inverse and self.n + int(points) > self.X.shape[1]:
            self._grow(self.n + int(points))

    def _grow(self, cap: int | None = None) -> None:
        rows = ("X", "Xs", "Xn", "R", "V", "A", "mask")  # the per-point buffers, copied row-wise
        old = {k: getattr(self, k) for k in rows}
        old_L, has_alpha, n, last = self.L, self._alpha is not None, self.n, self._last
        # Cholesky: grow in chunks of 128 rows, as every solve runs over the whole buffer and slack
        # rows cost time at every step (a growth factor of 1.25 wasted up to 56% of a solve). The
        # inverse factor's pass reads only the first n rows: grow by half (fewer O(n^2) copies)
        old_cap = self.X.shape[1]
        if cap is None:
            cap = old_cap + (max(128, old_cap // 2) if self.inverse else 128)
        self._alloc(cap, factor=False)
        for k in rows:
            getattr(self, k)[:, :n] = old[k][:, :n]
        # the new factor written once: the old block, zeros around it, identity below
        self.L = torch.empty(self.num_nodes, cap, cap, dtype=self.factor_dtype_, device=self.device_)
        self.L[:, :n, :n] = old_L[:, :n, :n]
        self.L[:, :n, n:] = 0.0
        self.L[:, n:] = 0.0
        self.L[:, n:, n:].diagonal(dim1=-2, dim2=-1).fill_(1.0)
        if has_alpha:
            self._alpha = self.A[:, :n]
        self._last = last  # a prediction's solves stay valid: the factor is the same

    # hyperparameters ---------------------------------------------------------------------
    @property
    def noise_var(self) -> Tensor:
        """(S,) observation noise variances."""
        return self.likelihood.noise.reshape(self.num_nodes).detach()

    @property
    def lengthscale(self) -> Tensor:
        return self.covar_module.base_kernel.lengthscale.reshape(self.num_nodes).detach()

    @property
    def outputscale(self) -> Tensor:
        return self.covar_module.outputscale.reshape(self.num_nodes).detach()

    def kernel(self, a: Tensor, b: Tensor) -> Tensor:
        r"""Kernel matrix ``(S, Na, d), (S, Nb, d) -> (S, Na, Nb)``.

        Evaluates the GPyTorch ``ScaleKernel(RBFKernel)`` hyperparameters directly,
        :math:`\sigma_f^2 \exp(-\|a-b\|^2 / 2 l^2)` (the per-step hot path; equality with
        ``covar_module(a, b)`` is tested).
        """
        with torch.no_grad():
            ls = self.covar_module.base_kernel.lengthscale.to(a)  # (S, 1, 1)
            return se_kernel(a, b, ls, self.covar_module.outputscale.to(a).reshape(-1, 1, 1))

    def _snapshot_hypers(self) -> None:
        """The hyperparameters the factor was built with, as plain tensors: ``(S, 1, 1)`` lengthscales,
        ``(S,)`` output variances and noise variances (the per-step path reads these, not GPyTorch's
        transformed parameters). Taken at construction and by :meth:`refactorize`, which every
        hyperparameter change must be followed by (:meth:`fit` does it)."""
        kw = dict(dtype=self.dtype_, device=self.device_)
        if torch.device(self.device_).type == "meta":  # shapes only (the start-up check's build): GPyTorch's
            # transforms dispatch to torch._refs there, whose first call imports torch._dynamo (~1.5 s)
            raw = self.covar_module.base_kernel.raw_lengthscale
            self._ls = torch.empty(raw.shape, **kw).reshape(-1, 1, 1)
            self._os = torch.empty(self.num_nodes, **kw)
            self._noise = torch.empty(self.num_nodes, **kw)
            return
        self._ls = self.covar_module.base_kernel.lengthscale.detach().to(**kw).reshape(-1, 1, 1).clone()
        self._os = self.outputscale.to(**kw).clone()
        self._noise = self.noise_var.to(**kw).clone()

    def _cross(self, x: Tensor, idx: Tensor | None = None) -> Tensor:
        r"""``k(X, x) (S, n, N)`` against the stored inputs for ``x (S, N, d)``, zero at invalid points:
        :math:`\|a-b\|^2 = \|a\|^2 + \|b\|^2 - 2 a^T b` on the cached scaled inputs and their norms
        (one ``(S, n, N)`` result, no ``(S, n, d)`` temporary; equals :meth:`kernel`, tested). ``idx``: only
        these nodes (``x`` then holds their queries, ``(len(idx), N, d)``)."""
        n = self.n
        sel = slice(None) if idx is None else idx
        xs = x / self._ls[sel]
        xn = (xs * xs).sum(-1)  # (S, N)
        d2 = torch.baddbmm(self.Xn[sel, :n].unsqueeze(-1) + xn.unsqueeze(-2), self.Xs[sel, :n], xs.transpose(-1, -2),
                           alpha=-2.0)
        k = d2.clamp_min_(0.0).mul_(-0.5).exp_().mul_(self._os[sel].reshape(-1, 1, 1))
        return k.mul_(self.mask[sel, :n].unsqueeze(-1))

    def _active(self) -> Tensor | None:
        """The nodes that hold a valid point, as an index tensor, where some do not (and the shortcuts are on, on
        the CPU); ``None``: every node's computation runs (all of them hold one, or no shortcut)."""
        if not (self.skip_void and self.device_.type == "cpu"):
            return None
        act = self.mask[:, : self.n].any(-1)
        if bool(act.all()):
            return None
        return act.nonzero().squeeze(-1)

    def _cache_inputs(self, lo: int, hi: int) -> None:
        """Refresh the scaled inputs and norms of rows ``lo:hi`` (after writing ``X`` or the lengthscale)."""
        xs = self.X[:, lo:hi] / self._ls
        self.Xs[:, lo:hi] = xs
        self.Xn[:, lo:hi] = (xs * xs).sum(-1)

    def _solve_pair(self, rhs: Tensor) -> tuple[Tensor, Tensor]:
        r"""``w = L^{-1} rhs`` and ``b = L^{-T} w = (K + \sigma^2 I)^{-1} rhs`` for ``rhs (S, n, 1)``:
        the prediction's variance solve and the append's, done together at the predicted point
        (one pass over the inverse factor, or two triangular solves)."""
        n = self.n
        if self.inverse:
            w, b = inverse_factor.pair(self.L, rhs[..., 0], n)
            return w.unsqueeze(-1), b.unsqueeze(-1)
        w = self._tri(self._pad(rhs), upper=False)
        b = self._tri(w, upper=True)
        return w[:, :n].to(self.dtype_), b[:, :n].to(self.dtype_)

    def _inverse_mm(self, rhs: Tensor, transpose: bool = False, idx: Tensor | None = None) -> Tensor:
        """``M rhs`` (or ``M^T rhs``) for the inverse factor ``M`` and ``rhs (S, n, k)``, in ``dtype``:
        products over blocks of 256 rows that skip the zero upper triangle (a full product does
        twice the work and measured three times slower). ``idx``: the factors of these nodes only (``rhs``
        then holds theirs)."""
        n, M = self.n, self.L
        rhs = rhs.to(M.dtype)
        out = rhs.new_zeros(rhs.shape) if transpose else rhs.new_empty(rhs.shape)
        for i0 in range(0, n, 256):
            i1 = min(n, i0 + 256)
            blk = M[:, i0:i1, :i1] if idx is None else M[idx, i0:i1, :i1]
            if transpose:
                out[:, :i1] += blk.transpose(-1, -2) @ rhs[:, i0:i1]
            else:
                out[:, i0:i1] = blk @ rhs[:, :i1]
        return out.to(self.dtype_)

    def _pad(self, rhs: Tensor) -> Tensor:
        """``rhs (S, n, k)`` as a right-hand side for the whole buffer ``(S, cap, k)`` in the factor's
        dtype, zero below ``n``: the factor is block-diagonal ``[L_n, 0; 0, I]``, so solving on the
        whole contiguous buffer is exact (a strided ``n x n`` view takes a much slower path)."""
        full = rhs.new_zeros(rhs.shape[0], self.L.shape[-1], rhs.shape[-1], dtype=self.L.dtype)
        full[:, : self.n] = rhs
        return full

    def _tri(self, full: Tensor, upper: bool) -> Tensor:
        """``L^{-1} full`` or (``upper``) ``L^{-T} full`` on the whole buffer."""
        return torch.linalg.solve_triangular(self.L.transpose(-1, -2) if upper else self.L, full, upper=upper)

    # online update -----------------------------------------------------------------------
    @torch.no_grad()
    def append(self, x: Tensor, y: Tensor, valid: Tensor | None = None) -> None:
        r"""Append one example per node, updating the Cholesky factor by one row (:math:`O(n^2)`).

        With :math:`K_n = L L^T`, the new row is :math:`l = L^{-1} k(X, x)` and the new
        diagonal :math:`d = \sqrt{k(x,x) + \sigma_\epsilon^2 - l^T l}`; :math:`\alpha` is updated in
        place through :math:`b = L^{-T} l`. When ``x`` is the point :meth:`predict` was just asked
        about (Algorithm 1: ŷ^{t-1} is both), both solves are the ones that prediction did.

        Args:
            x: (S, Dx) inputs; y: (S, Dy) outputs; valid: (S,) bool, False = skip (no effect).
        """
        s = self.num_nodes
        if x.shape != (s, self.input_dim) or y.shape != (s, self.output_dim):
            raise ValueError(f"append expects x (S={s}, {self.input_dim}) and y (S, {self.output_dim})")
        if valid is None:
            valid = torch.ones(s, dtype=torch.bool, device=self.device_)
        valid = valid & torch.isfinite(x).all(-1) & torch.isfinite(y).all(-1)
        if self.n == self.X.shape[1]:
            self._grow()
        n = self.n
        x = x.to(self.X)
        xs = x.unsqueeze(1)
        kxx, noise = self._os, self._noise  # k(x, x) = sigma_f^2 for the RBF kernel
        last, bvec = self._last, None
        reuse = n > 0 and last is not None and last[2] == n and _same_input(last[0], xs, last[3])
        if reuse:
            self._streaming, self._pending = True, False
        if self._void() and not bool(valid.any()):  # nothing valid, before or now: only the unit row
            self._append_void(n)
            return
        if self.device_.type != "cpu" or bool(valid.any()):
            self._any_valid = True
        if reuse and last[1] is None:  # predicted while void (no solves kept): this append does them
            reuse = False
        if reuse:
            l, bvec = last[1], last[4]  # the solves done by predict() at this very input
        if n == 0:
            l = x.new_zeros(s, 0)
        elif self.inverse and bvec is None:  # no paired pass to reuse: one pass gives both
            l, bvec = (t[..., 0] for t in self._solve_pair(self._cross(xs)))
        elif not reuse:
            l = self._solve_lower(self._cross(xs)).squeeze(-1)
        d2 = kxx + noise - (l * l).sum(-1)
        floor = 1e-10 * (kxx + noise)
        if self.device_.type == "cpu":  # on CUDA no host round-trip: clamp silently (counted on device)
            if bool((d2[valid] < floor[valid]).any()):
                record_jitter(float((floor - d2).clamp_min(0).max()))
                warnings.warn("OnlineGP.append: new point nearly dependent on the data; diagonal clamped")
        else:
            self.clamped = self.clamped + ((d2 < floor) & valid).sum()
        d = torch.where(valid, d2.clamp_min(floor).sqrt(), torch.ones_like(d2))
        vcol = valid.unsqueeze(-1)
        l = torch.where(vcol, l, torch.zeros_like(l))  # a non-finite input gives a NaN row: zero it
        r = torch.where(vcol, y.to(self.X) - self.prior_mean(xs).squeeze(1), torch.zeros_like(y, dtype=self.X.dtype))
        # k^T alpha = (L^{-1} k)^T (L^{-1} R) = l^T V: the residual of the new output
        resid = r - (l.unsqueeze(-2) @ self.V[:, :n]).squeeze(-2)
        v = resid / d.unsqueeze(-1)
        # block-inverse update of alpha = K^{-1} R with b = K^{-1} k = L^{-T} l, c = d^2:
        # alpha_old += -b resid / c ; alpha_new = resid / c       (O(n), in place)
        self.alpha  # A[:, :n] holds alpha of the current data before its in-place update
        q = resid / (d * d).unsqueeze(-1)
        if n > 0:
            if bvec is None:
                bvec = self._tri(self._pad(l.unsqueeze(-1)), upper=True)[:, :n, 0].to(self.dtype_)
            else:
                bvec = torch.where(vcol, bvec, torch.zeros_like(bvec))
            self.A[:, :n].addcmul_(bvec.unsqueeze(-1), q.unsqueeze(1), value=-1.0)
        self.A[:, n] = q
        if self.inverse:  # the new row of L^{-1}: [-b^T, 1] / d
            if n > 0:
                self.L[:, n, :n] = -bvec / d.unsqueeze(-1)
            self.L[:, n, n] = 1.0 / d
        else:
            self.L[:, n, :n] = l
            self.L[:, n, n] = d
        self.X[:, n] = torch.where(vcol, x, torch.zeros_like(x))
        self._cache_inputs(n, n + 1)
        self.R[:, n] = r
        self.V[:, n] = v * vcol
        self.mask[:, n] = valid
        self.n = n + 1
        self._alpha = self.A[:, : n + 1]
        self._last = None

    def void_nodes(self) -> Tensor:
        """``(S,)`` bool: the nodes that hold no valid point. Their :meth:`predict` is the prior at any input
        (``k_* = 0``): mean :meth:`prior_mean`, latent variance :meth:`prior_variance`, Jacobian
        :meth:`prior_mean_jacobian`. A read of the mask, nothing computed (a host read on the CPU)."""
        return ~self.mask[:, : self.n].any(-1)

    def prior_variance(self) -> Tensor:
        r"""``(S,)`` the prior's latent variance :math:`k(x, x) = \sigma_f^2` (the RBF kernel's, at any input), the
        value :meth:`predict` gives where ``k_* = 0``."""
        return self._os

    def _void(self) -> bool:
        """No node holds a valid point (and the shortcuts are on, on the CPU)."""
        return self.skip_void and not self._any_valid and self.device_.type == "cpu"

    def _append_void(self, n: int) -> None:
        """Append an invalid point at every node while no node holds a valid one: row ``n`` as the full update
        writes it (every solve there is of a zero right-hand side: zero input, residual, alpha and ``V`` entries,
        off-diagonal factor entries zero, ``-0.0`` in the inverse factor, unit diagonal), in ``O(S n)``."""
        self.alpha  # as the full update: alpha of the current data cached first
        self.A[:, n] = 0.0
        if n > 0:
            self.L[:, n, :n] = -0.0 if self.inverse else 0.0
        self.L[:, n, n] = 1.0
        self.X[:, n] = 0.0
        self._cache_inputs(n, n + 1)
        self.R[:, n] = 0.0
        self.V[:, n] = 0.0
        self.mask[:, n] = False
        self.n = n + 1
        self._alpha = self.A[:, : n + 1]
        self._last = None

    def _solve_lower(self, rhs: Tensor, idx: Tensor | None = None) -> Tensor:
        """``L^{-1} rhs`` for ``rhs (S, n, k)``: a solve through the full buffer (rows past n are
        identity), or a product with the inverse factor. ``idx``: the factors of these nodes only (``rhs`` holds
        theirs; a single right-hand side is taken for every node)."""
        n = self.n
        if idx is not None and (rhs.shape[-1] == 1 or not self.inverse):  # every node's system, zero elsewhere
            full = rhs.new_zeros(self.num_nodes, *rhs.shape[1:])
            full[idx] = rhs
            return self._solve_lower(full)[idx]
        if self.inverse:
            if rhs.shape[-1] == 1:
                return inverse_factor.pair(self.L, rhs[..., 0], n, need_b=False)[0].unsqueeze(-1)
            return self._inverse_mm(rhs, idx=idx)
        return self._tri(self._pad(rhs), upper=False)[:, :n].to(self.dtype_)

    @torch.no_grad()
    def refactorize(self) -> None:
        """Recompute the factor from scratch (after a hyperparameter change)."""
        self._snapshot_hypers()
        n = self.n
        if n == 0:
            return
        X, m = self.X[:, :n], self.mask[:, :n]
        self._cache_inputs(0, n)
        self._last = None
        self.R[:, :n] = torch.where(m.unsqueeze(-1), self.R[:, :n], torch.zeros_like(self.R[:, :n]))
        K = self.kernel(X, X) * (m.unsqueeze(-1) & m.unsqueeze(-2))
        diag = torch.where(m, self.noise_var.unsqueeze(-1).expand(-1, n), torch.zeros_like(K[..., 0]))
        K = K + torch.diag_embed(diag)
        K = K + torch.diag_embed((~m).to(K.dtype))  # decoupled unit rows for invalid points
        L = safe_cholesky(K)  # in dtype, stored in factor_dtype
        if self.inverse:
            self.V[:, :n] = torch.linalg.solve_triangular(L, self.R[:, :n], upper=False)
            eye = torch.eye(n, dtype=L.dtype, device=L.device).expand_as(L)
            self.L[:, :n, :n] = torch.linalg.solve_triangular(L, eye, upper=False)
        else:
            self.L[:, :n, :n] = L
            self.V[:, :n] = self._solve_lower(self.R[:, :n])
        self._alpha = None

    def reset(self) -> None:
        """Forget all data."""
        self.n = 0
        self._any_valid = False
        self._alloc(self.X.shape[1])

    # the data protocol: what code outside the GP may do with its data set ------------------
    def set_data(self, x: Tensor, y: Tensor, valid: Tensor | None = None, *, residual: bool = False,
                 capacity: int | None = None) -> None:
        """Replace every node's data set by ``x (S, n, Din) -> y (S, n, Dy)`` (``residual``: ``y`` is
        already the target minus the prior mean; ``valid (S, n)`` bool, default all) and factorise
        once. The buffers hold ``capacity`` rows (default exactly ``n``)."""
        n = x.shape[1]
        if x.shape[0] != self.num_nodes or x.shape[-1] != self.input_dim or y.shape[:2] != x.shape[:2] \
                or y.shape[-1] != self.output_dim:
            raise ValueError(f"set_data: x {tuple(x.shape)}, y {tuple(y.shape)} do not fit {self.num_nodes} nodes, "
                             f"input dim {self.input_dim}, output dim {self.output_dim}")
        self.n = 0
        self._alloc(max(n, int(capacity or 0), 1))
        xs = x.to(self.X)
        self.X[:, :n] = xs
        self.R[:, :n] = y.to(self.X) if residual else y.to(self.X) - self.prior_mean(xs)
        self.mask[:, :n] = True if valid is None else valid.to(self.mask.device)
        self.n = n
        self._any_valid = self.device_.type != "cpu" or bool(self.mask[:, :n].any())
        self.refactorize()

    def data(self) -> tuple[Tensor, Tensor, Tensor]:
        """The data sets: inputs ``(S, n, Din)``, residual targets ``(S, n, Dy)``, valid ``(S, n)``."""
        n = self.n
        return self.X[:, :n], self.R[:, :n], self.mask[:, :n]

    def state_tensors(self) -> dict[str, Tensor]:
        """The data sets as a model file keeps them: ``X (S, n, Din)``, residual targets ``R (S, n, Dy)``,
        ``mask (S, n)`` (copies)."""
        X, R, mask = self.data()
        return {"X": X.clone(), "R": R.clone(), "mask": mask.clone()}

    def _max_points(self) -> int | None:
        """The most points per node a loaded data set may hold (None: any)."""
        return None

    def load_state_tensors(self, state: dict[str, Tensor], source: str = "model file") -> None:
        """Replace the data sets by what :meth:`state_tensors` gave, after checking their shapes
        against this GP (``ConfigError`` naming ``source``, nothing changed); factorised once with the
        current hyperparameters. The buffers grow in chunks of 128 rows past the current capacity."""
        X, R, mask = state["X"], state["R"], state["mask"]
        s, d, o = self.num_nodes, self.input_dim, self.output_dim
        n = X.shape[1] if X.dim() == 3 else -1
        if (X.dim(), R.dim(), mask.dim()) != (3, 3, 2) or X.shape != (s, n, d) or R.shape != (s, n, o) \
                or mask.shape != (s, n) or mask.dtype != torch.bool:
            raise ConfigError(
                f"{source}: GP data of shape X {tuple(X.shape)}, R {tuple(R.shape)}, mask {tuple(mask.shape)} does not "
                f"match the configured model ({s} nodes, input dim {d}, output dim {o})"
            )
        most = self._max_points()
        if most is not None and n > most:
            raise ConfigError(f"{source}: holds {n} points per node, more than model.window={most}")
        cap = self.X.shape[1]
        self.set_data(X, R, mask, residual=True, capacity=cap + 128 * max(0, -(-(n - cap) // 128)))

    def solve(self, rhs: Tensor) -> Tensor:
        r""":math:`(K + \sigma^2 I)^{-1} \mathrm{rhs}` for ``rhs (S, n, k)`` through the current factor."""
        if self.inverse:
            return self._inverse_mm(self._inverse_mm(rhs), transpose=True)
        return torch.cholesky_solve(self._pad(rhs), self.L)[:, : self.n].to(self.dtype_)

    @property
    def alpha(self) -> Tensor:
        r""":math:`(K + \sigma^2 I)^{-1} (Y - m(X))`, ``(S, n, Dy)``, cached until the next append."""
        if self._alpha is None:
            n = self.n
            if self.inverse:
                self.A[:, :n] = self._inverse_mm(self.V[:, :n], transpose=True)
            else:
                self.A[:, :n] = self._tri(self.V.to(self.L.dtype), upper=True)[:, :n]
            self._alpha = self.A[:, :n]
        return self._alpha

    # prediction --------------------------------------------------------------------------
    @torch.no_grad()
    def predict(
        self, x: Tensor, jacobian: bool = True, variance: bool = True
    ) -> tuple[Tensor, Tensor | None, Tensor | None]:
        r"""Posterior mean, latent variance and mean Jacobian at ``x``.

        Mean :math:`m(x) + k_*^T \alpha`; latent variance :math:`k(x,x) - k_*^T (K+\sigma^2 I)^{-1} k_*`;
        Jacobian in closed form for the RBF kernel,
        :math:`\partial \mu / \partial x = \partial m/\partial x - \sum_a \alpha_a k(x, x_a)(x - x_a)^T / l^2`.

        Cost: one triangular solve against the factor for the variance (memory-bound,
        ``O(n^2)``); mean and Jacobian use the cached :math:`\alpha`. With a single query
        per node the solve is reused by :meth:`append` when the next appended input is the
        point just predicted (as in Algorithm 1, where ŷ^{t-1} is both).

        Args:
            x: ``(S, N, Dx)`` query points (one batch per node).
        Returns:
            mean ``(S, N, Dy)``, var ``(S, N)`` or None, jac ``(S, N, Dy, Dx)`` or None.
        """
        n = self.n
        x = x.to(self.X)
        s_, nq, dx = x.shape
        kxx = self._os.unsqueeze(-1).expand(s_, nq)
        mean = self.prior_mean(x)
        jac = self.prior_mean_jacobian(x) if jacobian else None
        self._last = None
        if self._pending:  # the last paired solve went unused: predicted again without appending
            self._streaming = self._pending = False
        if n == 0:
            return mean, (kxx.clone() if variance else None), jac
        idx = self._active()
        if self._void() or (idx is not None and idx.numel() == 0):
            # every point invalid: k_* = 0, so the prior (the full pass's numbers, bit for bit)
            if variance and nq == 1:  # what the full pass leaves for the append at this input (without its solves)
                self._pending = self._streaming
                self._last = (x, None, n, x._version, None)
            # copies, as the full pass returns new tensors (the identity mean is a view of x)
            return mean.clone(), (kxx.clone() if variance else None), (None if jac is None else jac.clone())
        # idx: the nodes that hold a valid point where some do not (None: all). The others' k_* is zero: their
        # mean, variance and Jacobian are the prior's, which the full pass gives them bit for bit, so the passes
        # run on the active nodes only (the void nodes' rows of the solves below are zero, as the full pass's)
        sel = slice(None) if idx is None else idx
        xa = x if idx is None else x[idx]
        X = self.X[sel, :n]
        ks = self._cross(xa, idx)  # (S, n, N)
        ls2 = (self._ls[sel] ** 2).reshape(-1, 1, 1, 1)
        var = None
        alpha = self.alpha if idx is None else self.alpha[idx]
        ksT = ks.transpose(-1, -2)  # (S, N, n)
        ka = ksT @ alpha  # sum_a k_a alpha_a  (S, N, Dy)
        mean_a = mean[sel] + ka
        pair = variance and nq == 1 and self._streaming
        if variance:
            rhs = ks
            if idx is not None and nq == 1:  # the append after it takes every node's solve: zero at the void nodes
                rhs = ks.new_zeros(s_, n, 1)
                rhs[idx] = ks
            if pair:  # training: the append's backward solve too, while the factor is in cache
                w, b = self._solve_pair(rhs)
            else:
                w = self._solve_lower(rhs, None if nq == 1 else idx)
            wa = w if idx is None or nq != 1 else w[idx]
            var = (kxx[sel] - (wa * wa).sum(-2)).clamp_min(0.0)
        if jacobian:
            # sum_a k_a alpha_a x_a^T  (S, N, Dy, Dx): through the smaller temporary
            if nq == 1:  # (k * alpha)^T X: an (S, n, Dy) temporary
                kax = ((ks * alpha).transpose(-1, -2) @ X).unsqueeze(1)
            elif nq < dx:
                kax = (ksT.unsqueeze(-1) * alpha.unsqueeze(1)).transpose(-1, -2) @ X.unsqueeze(1)
            else:  # (S, n, Dy Dx), whatever the number of queries
                ax = (alpha.unsqueeze(-1) * X.unsqueeze(-2)).flatten(-2)
                kax = (ksT @ ax).unflatten(-1, (self.output_dim, dx))
            jac_a = jac[sel] - (ka.unsqueeze(-1) * xa.unsqueeze(-2) - kax) / ls2
        if idx is None:
            mean, jac = mean_a, (jac_a if jacobian else None)
        else:  # the void nodes keep the prior (copies: the full pass returns new tensors)
            mean = mean.clone()
            mean[idx] = mean_a
            if variance:
                var_a, var = var, kxx.clone()
                var[idx] = var_a
            if jacobian:
                jac = jac.clone()
                jac[idx] = jac_a
        if variance and nq == 1:
            # keep the input itself (not a copy): its storage cannot be reused while referenced,
            # so pointer + version identify it without a device-to-host comparison
            self._pending = pair
            self._last = (x, w[..., 0], n, x._version, b[..., 0] if pair else None)
        return mean, var, jac

    @torch.no_grad()
    def variance_gradient(self, x: Tensor) -> Tensor:
        r""":math:`\partial\sigma^2(x)/\partial x` of the latent variance at ``x (S, N, Din)`` -> ``(S, N, Din)``,
        closed form for the RBF kernel: :math:`2\sum_a c_a k(x, x_a)(x - x_a)/l^2` with
        :math:`c = (K + \sigma_\epsilon^2 I)^{-1} k_*`."""
        n = self.n
        if n == 0:
            return torch.zeros_like(x)
        X, _, m = self.data()
        ks = self.kernel(X, x) * m.unsqueeze(-1)  # (S, n, N)
        c = self.solve(ks)  # (K + s^2 I)^{-1} k_*
        ck = c * ks
        ls2 = (self.lengthscale**2).reshape(-1, 1, 1)
        return 2.0 * (ck.sum(1).unsqueeze(-1) * x - ck.transpose(-1, -2) @ X) / ls2

    def differentiable_mean(self, x: Tensor) -> Tensor:
        """Posterior mean ``(S, N, Dy)`` with autograd through the GPyTorch kernel (the reference for
        the closed-form Jacobian of :meth:`predict`)."""
        mean = self.prior_mean(x)
        if self.n > 0:
            X, _, valid = self.data()
            ks = self.covar_module(X, x).to_dense() * valid.unsqueeze(-1)
            mean = mean + torch.einsum("snk,sno->sko", ks, self.alpha)
        return mean

    @torch.no_grad()
    def predict_belief(
        self, x: Tensor, cov: Tensor, jacobian: bool = True, variance: bool = True
    ) -> tuple[Tensor, Tensor | None, Tensor | None]:
        r"""Posterior mean, latent variance and mean Jacobian averaged over a Gaussian input
        :math:`y \sim \mathcal N(x, P)` (uncertain inputs: Girard et al. 2003; Deisenroth et al. 2009).

        For the RBF kernel the expected cross-kernel is closed form,

        .. math::
            q_a = \mathbb E[k(y, x_a)] = \sigma_f^2 \,|I + P/l^2|^{-1/2}
                  \exp\!\big(-\tfrac12 (x - x_a)^T (l^2 I + P)^{-1} (x - x_a)\big),

        so the expected mean is :math:`\mathbb E[\mu(y)] = m(x) + q^T \alpha` (the prior means
        are linear: :math:`\mathbb E[m(y)] = m(x)`), and its gradient,
        :math:`\partial m/\partial x - \sum_a \alpha_a q_a \big((l^2 I + P)^{-1}(x - x_a)\big)^T`,
        equals :math:`\mathbb E[\partial\mu/\partial y] = \mathrm{Cov}(\mu(y), y) P^{-1}` (Stein's
        lemma): the statistical linearisation of the GP mean over the belief. At :math:`P = 0` this
        is :meth:`predict`; as :math:`P` grows past the length scale the learned part fades, and a
        belief that knows nothing gets the prior's mean and Jacobian back instead of a local slope
        extrapolated over its whole spread.

        The variance is the latent variance at the mean, :math:`\Sigma_f(x)`, as in the GP-UKF
        (:mod:`dslearn.filters.ukf`; Ko & Fox 2009): the belief's own spread enters the filter
        through :math:`A P A^T`. (The exact :math:`\mathbb E[\Sigma_f(y)]` needs
        :math:`\mathbb E[k k^T]`, ``n x n`` per query; its cheap Jensen bound
        :math:`\sigma_f^2 - q^T (K + \sigma_\epsilon^2 I)^{-1} q` was measured worse: near
        :math:`\sigma_f^2` for a belief whose velocity is known to ~1 m/s, it widens that
        belief further at every step, README of ``experiments/ethucy_tracking``.) With one query
        per node the solve is the one :meth:`append` reuses, as after :meth:`predict`.

        Args:
            x: ``(S, N, Dx)`` belief means; cov: ``(S, N, Dx, Dx)`` their covariances.
        Returns:
            mean ``(S, N, Dy)``, var ``(S, N)`` or None, jac ``(S, N, Dy, Dx)`` or None.
        """
        n = self.n
        x, cov = x.to(self.X), cov.to(self.X)
        s_, nq, dx = x.shape
        if cov.shape != (s_, nq, dx, dx):
            raise ValueError(f"predict_belief: cov {tuple(cov.shape)} does not match x {tuple(x.shape)}")
        # the variance at the mean first: predict() keeps its solve for the append that follows
        var = None
        if variance:
            var = self.predict(x, jacobian=False)[1]
        else:
            self._last = None
        mean = self.prior_mean(x)
        jac = self.prior_mean_jacobian(x) if jacobian else None
        if n == 0:
            return mean, var, jac
        idx = self._active()
        if self._void() or (idx is not None and idx.numel() == 0):  # q = 0 at every node: the prior (copies)
            return mean.clone(), var, (None if jac is None else jac.clone())
        # idx: the nodes that hold a valid point where some do not (None: all); the others keep the prior, as
        # their q = 0 gives them in the full pass
        sel = slice(None) if idx is None else idx
        xa, cova = (x, cov) if idx is None else (x[idx], cov[idx])
        ls2 = self._ls[sel].reshape(-1, 1, 1, 1) ** 2  # (S, 1, 1, 1)
        C = cova + ls2 * torch.eye(dx, dtype=x.dtype, device=x.device)  # l^2 I + P: (S, N, Dx, Dx)
        Lc = torch.linalg.cholesky(C)
        diff = (xa.unsqueeze(-2) - self.X[sel, :n].unsqueeze(1)).transpose(-1, -2)  # (S, N, Dx, n)
        u = torch.linalg.solve_triangular(Lc, diff, upper=False)
        # log |I + P/l^2| = log |C| - Dx log l^2
        logdet = 2 * Lc.diagonal(dim1=-2, dim2=-1).log().sum(-1) - dx * ls2.reshape(-1, 1).log()  # (S, N)
        q = torch.exp(-0.5 * ((u * u).sum(-2) + logdet.unsqueeze(-1)))  # (S, N, n)
        q = q * (self._os[sel].reshape(-1, 1, 1) * self.mask[sel, :n].unsqueeze(1))
        alpha = self.alpha if idx is None else self.alpha[idx]  # (S, n, Dy)
        mean_a = mean[sel] + q @ alpha
        if jacobian:
            cd = torch.linalg.solve_triangular(Lc.transpose(-1, -2), u, upper=True)  # C^{-1} (x - x_a): (S, N, Dx, n)
            jac_a = jac[sel] - (alpha.transpose(-1, -2).unsqueeze(1) * q.unsqueeze(-2)) @ cd.transpose(-1, -2)
        if idx is None:
            return mean_a, var, (jac_a if jacobian else None)
        mean = mean.clone()
        mean[idx] = mean_a
        if jacobian:
            jac = jac.clone()
            jac[idx] = jac_a
        return mean, var, jac

    # hyperparameter fitting ----------------------------------------------------------------
    def fit(self, iters: int = 50, lr: float = 0.05) -> list[float]:
        """Maximise the exact log marginal likelihood of the current data (GPyTorch objective).

        All outputs share the kernel, so the objective is the sum over outputs and nodes of
        GPyTorch's ``MultivariateNormal.log_prob``. Refactorises afterwards. Returns the loss curve.
        """
        n = self.n
        if n < 2:
            return []
        X, m = self.X[:, :n], self.mask[:, :n]
        pair = (m.unsqueeze(-1) & m.unsqueeze(-2)).unsqueeze(1)  # (S, 1, n, n)
        # targets of the GP part: the stored residuals against a fixed (zero/identity) mean, or the
        # raw outputs when the constant mean is learned alongside the kernel
        const = self.mean_type == "constant"
        Y = self.R[:, :n] + (self.constant.detach().unsqueeze(1) if const else 0.0)
        params = list(self.covar_module.parameters()) + list(self.likelihood.parameters())
        if const:
            params.append(self.constant)
        opt = torch.optim.Adam(params, lr=lr)
        losses = []
        eye = torch.eye(n, dtype=X.dtype, device=X.device)
        for _ in range(int(iters)):
            opt.zero_grad()
            K = self.covar_module(X).to_dense().unsqueeze(1) * pair
            noise = self.likelihood.noise.reshape(-1, 1, 1, 1)
            mm = m.unsqueeze(1).unsqueeze(-1).to(X.dtype)
            K = K + eye * (noise * mm + (1 - mm))
            mu = self.constant.unsqueeze(-1) * m.unsqueeze(1) if const else torch.zeros_like(Y.transpose(-1, -2))
            dist = gpytorch.distributions.MultivariateNormal(mu, K)
            loss = -dist.log_prob(Y.transpose(-1, -2) * m.unsqueeze(1)).sum() / max(1, int(m.sum()))
            loss.backward()
            opt.step()
            losses.append(float(loss.detach()))
        if const:
            with torch.no_grad():
                self.R[:, :n] = (Y - self.constant.unsqueeze(1)) * m.unsqueeze(-1)
        self.refactorize()
        return losses
