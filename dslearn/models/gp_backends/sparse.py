r"""Scalable online GP variants behind the GP backend protocol of the exact
:class:`~dslearn.models.gp_backends.exact.OnlineGP`
(:class:`dslearn.models.gp_backends.protocol.GPBackend`).

All three keep ``S`` independent per-node models (one data set per sensor node) with one
RBF kernel shared by the ``Dy`` outputs, and give every method of the protocol: ``append(x, y,
valid)``, ``predict(x, jacobian, variance)``, ``variance_gradient(x)`` (closed form for each),
``differentiable_mean(x)`` (autograd reference for the closed-form Jacobian), ``reserve``,
``fit``, the hyperparameters, the model-file state, and the capability flags
(``supports_belief``: the window GP only; ``grows_per_append``: none of them).

* :class:`WindowGP` — budgeted exact GP on the last ``N`` points: after each append beyond
  ``N`` the oldest point is removed by a Cholesky *downdate of the leading row*, which is a
  rank-1 *update* of the trailing block (:func:`chol_update`), ``O(N^2)`` per step.
* :class:`SGPR` — inducing-point GP (DTC/VFE predictive, Titsias 2009 / Quiñonero-Candela &
  Rasmussen 2005) with the first ``M`` appended inputs as inducing points; online, the
  ``M x M`` statistic :math:`\Sigma = K_{uu} + \sigma^{-2} K_{uf} K_{fu}` is kept as a Cholesky
  factor with one rank-1 update per point, ``O(M^2)`` per step, independent of ``n``.
* :class:`SSGP` — sparse spectrum GP (Lázaro-Gredilla et al. 2010, Yu et al.'s ref. [6]):
  ``D/2`` random frequencies give ``D`` trigonometric features, Bayesian linear regression
  on the weights with a rank-1 Cholesky update of the ``D x D`` precision per point,
  ``O(D^2)`` per step, independent of ``n``.

Invalid points (a node had nothing to learn from) are appended as zero feature vectors, a
no-op update.
"""

from __future__ import annotations


import torch
from torch import Tensor, nn

from dslearn.errors import ConfigError, check_choice, check_positive
from dslearn.models.gp_backends.exact import MEANS, OnlineGP, PriorMean
from dslearn.models.kernels import se_kernel


def chol_update(L: Tensor, v: Tensor) -> Tensor:
    r"""Cholesky factor of :math:`L L^T + v v^T` in ``O(D^2)``, batched, without a loop over ``D``.

    With :math:`p = L^{-1} v`, :math:`L L^T + v v^T = L (I + p p^T) L^T` and the factor of
    :math:`I + p p^T` is :math:`M = \mathrm{diag}(d) + \mathrm{tril}(p\beta^T, -1)` with
    :math:`t_j = 1 + \sum_{k \le j} p_k^2`, :math:`d_j = \sqrt{t_j / t_{j-1}}`,
    :math:`\beta_j = p_j / \sqrt{t_j t_{j-1}}` (Gill, Golub, Murray & Saunders 1974), so
    :math:`(LM)_{ij} = L_{ij} d_j + \beta_j \sum_{k > j} L_{ik} p_k` — a reversed cumulative sum.

    Args:
        L: ``(*B, D, D)`` lower-triangular factor (positive diagonal).
        v: ``(*B, D)``; a zero vector leaves ``L`` unchanged.
    Returns:
        ``(*B, D, D)`` lower-triangular factor.
    """
    p = torch.linalg.solve_triangular(L, v.unsqueeze(-1), upper=False).squeeze(-1)
    t = 1.0 + torch.cumsum(p * p, -1)
    t_prev = torch.cat([torch.ones_like(t[..., :1]), t[..., :-1]], -1)
    d = torch.sqrt(t / t_prev)
    beta = p / torch.sqrt(t * t_prev)
    L = L.contiguous()  # elementwise passes on a strided view are several times slower
    lp = L * p.unsqueeze(-2)  # L_ik p_k
    cs = torch.cumsum(lp, -1)
    excl = torch.sub(cs[..., -1:], cs, out=cs)  # sum_{k > j} L_ik p_k = row sum - inclusive prefix
    out = L * d.unsqueeze(-2)
    return out.addcmul_(excl, beta.unsqueeze(-2))


# ------------------------------------------------------------------------------------------
class WindowGP(OnlineGP):
    r"""Exact GP on the last ``window`` appended points (budgeted / sliding window).

    Every append is the exact bordered update of :class:`OnlineGP`; when the data set then
    holds ``window + 1`` points, the oldest one is removed: with
    :math:`L = \begin{pmatrix} l_{11} & 0 \\ l_1 & L_2 \end{pmatrix}`, the factor of the
    trailing kernel block is ``chol_update(L_2, l_1)``; the cached
    :math:`\alpha` follows from the block inverse, :math:`\alpha' = \alpha_{2:} - b\,\alpha_1 / a`
    with :math:`(a, b)` the first column of :math:`K^{-1}` (two triangular solves), and
    :math:`V' = L'^T \alpha'`.
    Cost ``O(N^2)`` per step whatever the number of points seen.
    """

    #: the buffer holds ``window + 1`` rows from the start: :meth:`reserve` has nothing to do
    grows_per_append = False

    def __init__(self, num_nodes: int, input_dim: int, output_dim: int, window: int = 500, **kw):
        if not isinstance(window, int) or window < 2:
            raise ConfigError(f"model.window={window!r} must be an integer >= 2")
        kw.pop("capacity", None)
        if kw.pop("factor", "cholesky") not in ("auto", "cholesky"):
            raise ConfigError("model.factor: the window GP removes points through its Cholesky factor (choose auto or cholesky)")
        if kw.get("factor_dtype") not in (None, kw.get("dtype", torch.float64)):
            raise ConfigError("model.factor_dtype: the window GP keeps its factor in the run's dtype (choose null)")
        super().__init__(num_nodes, input_dim, output_dim, capacity=window + 1, factor="cholesky", **kw)
        self.window = int(window)
        self.seen = 0

    def _grow(self) -> None:  # the buffer never grows: window + 1 rows suffice
        raise RuntimeError("WindowGP buffer overflow")

    @torch.no_grad()
    def append(self, x: Tensor, y: Tensor, valid: Tensor | None = None) -> None:
        super().append(x, y, valid)
        self.seen += 1
        if self.n > self.window:
            self._drop_oldest()

    @torch.no_grad()
    def _drop_oldest(self) -> None:
        n = self.n
        alpha = self.alpha  # (S, n, Dy)
        e0 = self.L.new_zeros(self.num_nodes, n, 1)
        e0[:, 0, 0] = 1.0
        col = self._solve_pair(e0)[1][..., 0]  # K^{-1} e_0
        a, b = col[:, :1], col[:, 1:]
        new_alpha = alpha[:, 1:] - b.unsqueeze(-1) * (alpha[:, :1] / a.unsqueeze(-1))
        L2 = chol_update(self.L[:, 1:n, 1:n], self.L[:, 1:n, 0])
        self.L[:, : n - 1, : n - 1] = L2
        self.L[:, n - 1, :] = 0.0
        self.L[:, n - 1, n - 1] = 1.0
        for buf in (self.X, self.Xs, self.Xn, self.R, self.mask):  # with the kernel's cached scaled inputs
            buf[:, : n - 1] = buf[:, 1:n].clone()
            buf[:, n - 1] = 0  # the freed row: no point (mask False)
        self.V[:, : n - 1] = L2.transpose(-1, -2) @ new_alpha
        self.V[:, n - 1] = 0.0
        self.n = n - 1
        self.A[:, : n - 1] = new_alpha
        self._alpha = self.A[:, : n - 1]
        self._last = None

    def reset(self) -> None:
        super().reset()
        self.seen = 0

    def _max_points(self) -> int | None:
        return self.window


# ------------------------------------------------------------------------------------------
class _SparseBase(PriorMean, nn.Module):
    #: :class:`~dslearn.models.gp_backends.protocol.GPBackend` capabilities: no belief-averaged prediction;
    #: fixed-size statistics (nothing grows with the data, :meth:`reserve` has nothing to do)
    supports_belief = False
    grows_per_append = False

    def __init__(self, num_nodes, input_dim, output_dim, outputscale, lengthscale, noise_std, mean, dtype, device):
        super().__init__()
        check_positive("model.outputscale", outputscale)
        check_positive("model.lengthscale", lengthscale)
        check_positive("model.noise_std", noise_std)
        if mean == "constant":
            raise ConfigError("model.mean=constant is not available for the sparse GP variants (no fit); use zero or identity")
        self.num_nodes, self.input_dim, self.output_dim = int(num_nodes), int(input_dim), int(output_dim)
        self._set_mean(mean)
        self.dtype_, self.device_ = dtype, torch.device(device)
        kw = dict(dtype=dtype, device=self.device_)
        s = self.num_nodes
        self._sf2 = torch.full((s,), float(outputscale) ** 2, **kw)
        self._ls = torch.full((s,), float(lengthscale), **kw)
        self._noise = torch.full((s,), float(noise_std) ** 2, **kw)
        self.n = 0

    #: posterior state tensors of the variant (besides the hyperparameters), see state_tensors
    STATE: tuple[str, ...] = ()

    #: prefix of the state's names in a model file
    PREFIX = "sparse."

    def state_tensors(self) -> dict[str, Tensor]:
        """The whole posterior (hyperparameters, the variant's ``STATE``, point count) as plain
        tensors named ``sparse.<name>``, for :meth:`GPMotionModel.save`."""
        out = {self.PREFIX + k: getattr(self, k).clone() for k in ("_sf2", "_ls", "_noise", *self.STATE)}
        out[self.PREFIX + "n"] = torch.tensor(self.n)
        return out

    def load_state_tensors(self, state: dict[str, Tensor], source: str = "model file") -> None:
        """Inverse of :meth:`state_tensors`; every tensor must have this model's shape and dtype kind."""
        for k in ("_sf2", "_ls", "_noise", *self.STATE):
            cur, v = getattr(self, k), state[self.PREFIX + k]
            if v.shape != cur.shape or v.dtype.is_floating_point != cur.dtype.is_floating_point:
                raise ConfigError(f"{source}: {type(self).__name__} state {k!r} of shape {tuple(v.shape)} does not "
                                  f"match the configured model ({tuple(cur.shape)})")
        for k in ("_sf2", "_ls", "_noise", *self.STATE):
            cur = getattr(self, k)
            setattr(self, k, state[self.PREFIX + k].to(cur.device, cur.dtype))
        self.n = int(state[self.PREFIX + "n"])
        self._invalidate()

    def _invalidate(self) -> None:
        """Drop caches derived from the state (after it was replaced)."""

    @property
    def noise_var(self) -> Tensor:
        return self._noise

    @property
    def lengthscale(self) -> Tensor:
        return self._ls

    @property
    def outputscale(self) -> Tensor:
        return self._sf2

    def refactorize(self) -> None:
        """Nothing cached depends on hyperparameters that change (they are fixed)."""

    def reserve(self, points: int) -> None:
        """Nothing to allocate: the statistics have a fixed size."""

    def fit(self, iters: int = 50, lr: float = 0.05) -> list[float]:
        raise ConfigError("model.fit_every > 0 is not available for the sparse GP variants (fixed hyperparameters)")

    def predict_belief(self, x: Tensor, cov: Tensor, jacobian: bool = True, variance: bool = True):
        raise ConfigError(f"model.inputs=belief: the {type(self).__name__} GP variant does not average over the "
                          f"belief (only the exact and window GPs do; choose model.inputs=mean)")

    def _check(self, x: Tensor, y: Tensor, valid: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        s = self.num_nodes
        if x.shape != (s, self.input_dim) or y.shape != (s, self.output_dim):
            raise ValueError(f"append expects x (S={s}, {self.input_dim}) and y (S, {self.output_dim})")
        if valid is None:
            valid = torch.ones(s, dtype=torch.bool, device=self.device_)
        x, y = x.to(self.dtype_), y.to(self.dtype_)
        valid = valid & torch.isfinite(x).all(-1) & torch.isfinite(y).all(-1)
        x = torch.where(valid.unsqueeze(-1), x, torch.zeros_like(x))
        r = torch.where(valid.unsqueeze(-1), y - self.prior_mean(x), torch.zeros_like(y))
        return x, r, valid


class SSGP(_SparseBase):
    r"""Sparse spectrum GP (Lázaro-Gredilla et al. 2010): ``features`` = D trigonometric features.

    :math:`\phi(x) = \sigma_f \sqrt{2/D}\,[\cos(\omega_i^T x / l), \sin(\omega_i^T x / l)]_{i=1}^{D/2}`,
    :math:`\omega_i \sim \mathcal N(0, I)`, so :math:`\phi(x)^T\phi(x') \to k(x, x')` as ``D`` grows.
    Weights :math:`w \sim \mathcal N(0, I)`; posterior precision
    :math:`A = I + \sigma_\epsilon^{-2}\Phi^T\Phi` (kept as its Cholesky factor, one rank-1 update per
    point), :math:`b = \sigma_\epsilon^{-2}\Phi^T (Y - m(X))`, weight mean :math:`\mu = A^{-1} b`.
    Predictive mean :math:`m(x) + \phi(x)^T\mu`, latent variance :math:`\phi(x)^T A^{-1}\phi(x)`,
    Jacobian :math:`\partial m/\partial x + (\partial\phi/\partial x)^T \mu` in closed form.
    The frequencies are drawn once from ``seed`` and shared by all nodes.
    """

    STATE = ("omega", "Lc", "b")

    def _invalidate(self) -> None:
        self._mu = None

    def __init__(self, num_nodes, input_dim, output_dim, outputscale=1.0, lengthscale=2.0, noise_std=0.5,
                 mean="zero", features: int = 200, seed: int = 0, dtype=torch.float64, device="cpu"):
        super().__init__(num_nodes, input_dim, output_dim, outputscale, lengthscale, noise_std, mean, dtype, device)
        if not isinstance(features, int) or features < 2 or features % 2:
            raise ConfigError(f"model.features={features!r} must be an even integer >= 2")
        self.features = int(features)
        g = torch.Generator().manual_seed(int(seed))
        self.omega = torch.randn(self.features // 2, self.input_dim, generator=g, dtype=torch.float64).to(dtype=dtype, device=self.device_)
        self.reset()

    def reset(self) -> None:
        s, D, kw = self.num_nodes, self.features, dict(dtype=self.dtype_, device=self.device_)
        self.Lc = torch.eye(D, **kw).repeat(s, 1, 1)
        self.b = torch.zeros(s, D, self.output_dim, **kw)
        self._mu = None
        self.n = 0

    def _freq(self) -> Tensor:
        return self.omega.unsqueeze(0) / self._ls.reshape(-1, 1, 1)  # (S, m, d)

    def phi(self, x: Tensor) -> Tensor:
        """``(S, N, d) -> (S, N, D)`` features."""
        z = x @ self._freq().transpose(-1, -2)
        a = torch.sqrt(self._sf2 * 2.0 / self.features).reshape(-1, 1, 1)
        return a * torch.cat([torch.cos(z), torch.sin(z)], -1)

    @property
    def mu(self) -> Tensor:
        """Posterior weight mean ``(S, D, Dy)``, cached until the next append."""
        if self._mu is None:
            self._mu = torch.cholesky_solve(self.b, self.Lc)
        return self._mu

    @torch.no_grad()
    def append(self, x: Tensor, y: Tensor, valid: Tensor | None = None) -> None:
        x, r, valid = self._check(x, y, valid)
        f = self.phi(x.unsqueeze(1)).squeeze(1) * valid.unsqueeze(-1)  # (S, D)
        inv = (1.0 / self._noise).reshape(-1, 1)
        self.Lc = chol_update(self.Lc, f * inv.sqrt())
        self.b = self.b + (f * inv).unsqueeze(-1) * r.unsqueeze(-2)
        self._mu = None
        self.n += 1

    @torch.no_grad()
    def extend(self, X: Tensor, Y: Tensor) -> None:
        """Bulk load ``(S, n, d), (S, n, Dy)`` (all valid), equal to ``n`` appends (benchmarks)."""
        F = self.phi(X.to(self.dtype_))
        R = Y.to(self.dtype_) - self.prior_mean(X.to(self.dtype_))
        inv = (1.0 / self._noise).reshape(-1, 1, 1)
        A = self.Lc @ self.Lc.transpose(-1, -2) + inv * F.transpose(-1, -2) @ F
        self.Lc = torch.linalg.cholesky(A)
        self.b = self.b + inv * F.transpose(-1, -2) @ R
        self._mu = None
        self.n += X.shape[1]

    @torch.no_grad()
    def predict(self, x: Tensor, jacobian: bool = True, variance: bool = True):
        x = x.to(self.dtype_)
        F = self.phi(x)  # (S, N, D)
        mu = self.mu
        mean = self.prior_mean(x) + F @ mu
        var = jac = None
        if variance:
            w = torch.linalg.solve_triangular(self.Lc, F.transpose(-1, -2), upper=False)
            var = (w * w).sum(-2)
        if jacobian:
            om = self._freq()  # (S, m, d)
            z = x @ om.transpose(-1, -2)  # (S, N, m)
            a = torch.sqrt(self._sf2 * 2.0 / self.features).reshape(-1, 1, 1)
            # d phi / dx: cos part -a sin(z) om, sin part a cos(z) om
            m2 = self.features // 2
            # jac[s,n,o,:] = sum_i (-a sin z_i mu_c[i,o] + a cos z_i mu_s[i,o]) om_i
            coef_c = (-a * torch.sin(z)).unsqueeze(-1) * mu[:, None, :m2, :]  # (S, N, m, Dy)
            coef_s = (a * torch.cos(z)).unsqueeze(-1) * mu[:, None, m2:, :]
            jac = self.prior_mean_jacobian(x) + (coef_c + coef_s).transpose(-1, -2) @ om.unsqueeze(1)
        return mean, var, jac

    @torch.no_grad()
    def variance_gradient(self, x: Tensor) -> Tensor:
        r""":math:`\partial\sigma^2/\partial x = 2 (\partial\phi/\partial x)^T A^{-1}\phi(x)` in closed
        form, ``(S, N, d)``."""
        x = x.to(self.dtype_)
        g = torch.cholesky_solve(self.phi(x).transpose(-1, -2), self.Lc)  # A^{-1} phi: (S, D, N)
        om = self._freq()  # (S, m, d)
        z = x @ om.transpose(-1, -2)  # (S, N, m)
        a = torch.sqrt(self._sf2 * 2.0 / self.features).reshape(-1, 1, 1)
        m2 = self.features // 2
        # d phi_cos,i / dx = -a sin(z_i) om_i, d phi_sin,i / dx = a cos(z_i) om_i
        coef = a * (torch.cos(z) * g[:, m2:].transpose(-1, -2) - torch.sin(z) * g[:, :m2].transpose(-1, -2))
        return 2.0 * coef @ om

    def differentiable_mean(self, x: Tensor) -> Tensor:
        """Posterior mean with autograd through the features (reference for the Jacobian)."""
        return self.prior_mean(x) + self.phi(x) @ self.mu


class SGPR(_SparseBase):
    r"""Inducing-point GP with the DTC/VFE predictive (the SGPR posterior of Titsias 2009).

    Inducing inputs ``Z``: the first ``M`` appended inputs of each node (a slot of an invalid
    point stays empty). While they are being collected, the data *are* the inducing points and
    the posterior equals the exact GP (recomputed from the ``M`` points, ``O(M^3)``, only for the
    first ``M`` steps); afterwards ``Z`` is fixed and each point updates
    :math:`\Sigma = K_{uu} + \sigma^{-2} K_{uf}K_{fu}` by one rank-1 Cholesky update and
    :math:`b = \sigma^{-2} K_{uf} (Y - m(X))`, ``O(M^2)`` per step.

    Predictive mean :math:`m(x) + k_{xu}\Sigma^{-1} b`; latent variance
    :math:`k_{xx} - k_{xu}K_{uu}^{-1}k_{ux} + k_{xu}\Sigma^{-1}k_{ux}`; Jacobian in closed form
    (RBF kernel, as for :class:`OnlineGP` with :math:`\alpha = \Sigma^{-1} b` and ``X = Z``).
    """

    STATE = ("Z", "Rz", "zmask", "Lu", "Ls", "b")

    def _invalidate(self) -> None:
        self._c = None

    def __init__(self, num_nodes, input_dim, output_dim, outputscale=1.0, lengthscale=2.0, noise_std=0.5,
                 mean="zero", inducing: int = 128, jitter: float = 1e-8, dtype=torch.float64, device="cpu"):
        super().__init__(num_nodes, input_dim, output_dim, outputscale, lengthscale, noise_std, mean, dtype, device)
        if not isinstance(inducing, int) or inducing < 1:
            raise ConfigError(f"model.inducing={inducing!r} must be an integer >= 1")
        self.M = int(inducing)
        self.jitter = float(jitter)
        self.reset()

    def reset(self) -> None:
        s, M, kw = self.num_nodes, self.M, dict(dtype=self.dtype_, device=self.device_)
        self.Z = torch.zeros(s, M, self.input_dim, **kw)
        self.Rz = torch.zeros(s, M, self.output_dim, **kw)  # targets of the points while filling
        self.zmask = torch.zeros(s, M, dtype=torch.bool, device=self.device_)
        self.Lu = torch.eye(M, **kw).repeat(s, 1, 1)  # chol(K_uu + jitter)
        self.Ls = torch.eye(M, **kw).repeat(s, 1, 1)  # chol(Sigma)
        self.b = torch.zeros(s, M, self.output_dim, **kw)
        self._c = None
        self.n = 0

    def kernel(self, a: Tensor, b: Tensor) -> Tensor:
        return se_kernel(a, b, self._ls.reshape(-1, 1, 1), self._sf2.reshape(-1, 1, 1))

    @property
    def c(self) -> Tensor:
        r""":math:`\Sigma^{-1} b`, ``(S, M, Dy)``, cached until the next append."""
        if self._c is None:
            self._c = torch.cholesky_solve(self.b, self.Ls)
        return self._c

    def _kuu(self) -> Tensor:
        m = self.zmask
        pair = (m.unsqueeze(-1) & m.unsqueeze(-2)).to(self.dtype_)
        K = self.kernel(self.Z, self.Z) * pair
        eye = torch.eye(self.M, dtype=self.dtype_, device=self.device_)
        return K, K + eye * (self.jitter * self._sf2.reshape(-1, 1, 1) * m.unsqueeze(-1) + (~m).unsqueeze(-1).to(self.dtype_))

    @torch.no_grad()
    def append(self, x: Tensor, y: Tensor, valid: Tensor | None = None) -> None:
        x, r, valid = self._check(x, y, valid)
        if self.n < self.M:  # collecting the inducing inputs: exact GP on them
            i = self.n
            self.Z[:, i], self.Rz[:, i], self.zmask[:, i] = x, r, valid
            K, Kj = self._kuu()
            self.Lu = torch.linalg.cholesky(Kj)
            noise = self._noise.reshape(-1, 1, 1)
            m = self.zmask.to(self.dtype_)
            # Sigma = K_uu + K_uf K_fu / sigma^2 with f = the points so far (= Z)
            self.Ls = torch.linalg.cholesky(Kj + K @ K / noise)
            self.b = K @ (self.Rz * m.unsqueeze(-1)) / noise
        else:
            kuf = self.kernel(self.Z, x.unsqueeze(1)).squeeze(-1) * (self.zmask & valid.unsqueeze(-1))  # (S, M)
            inv = (1.0 / self._noise).reshape(-1, 1)
            self.Ls = chol_update(self.Ls, kuf * inv.sqrt())
            self.b = self.b + (kuf * inv).unsqueeze(-1) * r.unsqueeze(-2)
        self._c = None
        self.n += 1

    @torch.no_grad()
    def extend(self, X: Tensor, Y: Tensor) -> None:
        """Bulk load ``(S, n, d), (S, n, Dy)`` (all valid) after the inducing set is full (benchmarks)."""
        if self.n < self.M:
            k = min(self.M - self.n, X.shape[1])
            for i in range(k):
                self.append(X[:, i], Y[:, i])
            X, Y = X[:, k:], Y[:, k:]
        if X.shape[1] == 0:
            return
        X, Y = X.to(self.dtype_), Y.to(self.dtype_)
        kuf = self.kernel(self.Z, X) * self.zmask.unsqueeze(-1)
        noise = self._noise.reshape(-1, 1, 1)
        S = self.Ls @ self.Ls.transpose(-1, -2) + kuf @ kuf.transpose(-1, -2) / noise
        self.Ls = torch.linalg.cholesky(S)
        self.b = self.b + kuf @ (Y - self.prior_mean(X)) / noise
        self._c = None
        self.n += X.shape[1]

    @torch.no_grad()
    def predict(self, x: Tensor, jacobian: bool = True, variance: bool = True):
        x = x.to(self.dtype_)
        ku = self.kernel(self.Z, x) * self.zmask.unsqueeze(-1)  # (S, M, N)
        c = self.c
        mean = self.prior_mean(x) + ku.transpose(-1, -2) @ c
        var = jac = None
        if variance:
            wu = torch.linalg.solve_triangular(self.Lu, ku, upper=False)
            ws = torch.linalg.solve_triangular(self.Ls, ku, upper=False)
            var = (self._sf2.unsqueeze(-1) - (wu * wu).sum(-2) + (ws * ws).sum(-2)).clamp_min(0.0)
        if jacobian:
            ls2 = (self._ls**2).reshape(-1, 1, 1, 1)
            ksT = ku.transpose(-1, -2)  # (S, N, M)
            ka = ksT @ c
            kax = (ksT.unsqueeze(-1) * c.unsqueeze(1)).transpose(-1, -2) @ self.Z.unsqueeze(1)
            jac = self.prior_mean_jacobian(x) - (ka.unsqueeze(-1) * x.unsqueeze(-2) - kax) / ls2
        return mean, var, jac

    @torch.no_grad()
    def variance_gradient(self, x: Tensor) -> Tensor:
        r""":math:`\partial\sigma^2/\partial x` in closed form, ``(S, N, d)``: with
        :math:`c = (K_{uu}^{-1} - \Sigma^{-1}) k_u(x)`, :math:`2\sum_a c_a k(x, z_a)(x - z_a)/l^2`
        (as for the exact GP, whose :math:`c` is :math:`(K + \sigma_\epsilon^2 I)^{-1} k_*`)."""
        x = x.to(self.dtype_)
        ku = self.kernel(self.Z, x) * self.zmask.unsqueeze(-1)  # (S, M, N)
        ck = (torch.cholesky_solve(ku, self.Lu) - torch.cholesky_solve(ku, self.Ls)) * ku
        ls2 = (self._ls**2).reshape(-1, 1, 1)
        return 2.0 * (ck.sum(1).unsqueeze(-1) * x - ck.transpose(-1, -2) @ self.Z) / ls2

    def differentiable_mean(self, x: Tensor) -> Tensor:
        ku = self.kernel(self.Z, x) * self.zmask.unsqueeze(-1)
        return self.prior_mean(x) + ku.transpose(-1, -2) @ self.c


VARIANTS = ("exact", "window", "sgpr", "ssgp")


def make_online_gp(variant: str, num_nodes: int, input_dim: int, output_dim: int, *, outputscale: float,
                   lengthscale: float, noise_std: float, mean: str, dtype, device, window: int = 500,
                   inducing: int = 128, features: int = 200, seed: int = 0, capacity: int = 256):
    """The per-node GP backend for ``model.variant`` (``exact | window | sgpr | ssgp``)."""
    check_choice("model.variant", variant, VARIANTS)
    common = dict(outputscale=outputscale, lengthscale=lengthscale, noise_std=noise_std, mean=mean, dtype=dtype, device=device)
    if variant == "exact":
        return OnlineGP(num_nodes, input_dim, output_dim, capacity=capacity, **common)
    if variant == "window":
        return WindowGP(num_nodes, input_dim, output_dim, window=window, **common)
    if variant == "sgpr":
        return SGPR(num_nodes, input_dim, output_dim, inducing=inducing, **common)
    return SSGP(num_nodes, input_dim, output_dim, features=features, seed=seed, **common)
