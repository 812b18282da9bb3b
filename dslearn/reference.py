r"""A straightforward reference implementation of the Yu et al. protocol, for benchmarks and tests.

Same mathematics as :mod:`dslearn.filters.distributed` / :mod:`dslearn.studies.yu`, written the way one
would write it first — and kept deliberately that way, as the baseline the fast path is
timed and tested against:

* Python loops over episodes (``B = 1`` at a time), sensor nodes, targets, consensus rounds
  and neighbours; every matrix is a single ``(Dx, Dx)`` matrix; inverses by ``torch.linalg.inv``.
* The GP motion model of each node is a GPyTorch ``ExactGP`` with GPyTorch defaults
  (``ZeroMean``, ``ScaleKernel(RBFKernel)``, ``GaussianLikelihood``; one batch entry per output,
  sharing the hyperparameter values), rebuilt from its data set whenever the data set changed,
  i.e. refactorised from scratch at every online-learning step; the Jacobian of the posterior
  mean by autograd (``torch.autograd.functional.jacobian``).
* LIN / SFM use the same model classes, called one node and one episode at a time, with the
  Jacobian by autograd.

Data (scenario, network, episodes, initial beliefs, seeds) and the metric formulas are shared
with the fast path (they are not the hot path), so the two produce the same numbers up to
floating-point rounding; ``tests/test_perf_paths.py`` checks that.
"""

from __future__ import annotations

import gpytorch
import pandas as pd
import torch
from torch import Tensor

from dslearn.errors import ConfigError
from dslearn.models import GPMotionModel
from dslearn.compose import build_parts
from dslearn.filters.distributed import TrackResult, initial_belief
from dslearn.learning.online import algorithm1, checkpoints as eval_points
from dslearn.metrics import metric_rows, tracking_metrics
from dslearn.sim.scenario import sample_split
from dslearn.types import AGENT_DIM, safe_cholesky, spd_inverse


class _ExactGP(gpytorch.models.ExactGP):
    def __init__(self, x, y, lik, dy):
        super().__init__(x, y, lik)
        bs = torch.Size([dy])
        self.mean_module = gpytorch.means.ZeroMean(batch_shape=bs)
        self.covar_module = gpytorch.kernels.ScaleKernel(gpytorch.kernels.RBFKernel(batch_shape=bs), batch_shape=bs)

    def forward(self, x):
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))


class ReferenceGP:
    """One node's GP motion model: a list of points and a GPyTorch ExactGP rebuilt on change."""

    def __init__(self, dim: int, outputscale: float, lengthscale: float, noise_std: float, mean: str, noise: str, dtype):
        self.dim, self.sf, self.ls, self.sn, self.mean_type, self.noise_mode = dim, outputscale, lengthscale, noise_std, mean, noise
        self.dtype = dtype
        self.xs: list[Tensor] = []
        self.ys: list[Tensor] = []
        self.model = None

    def prior(self, x: Tensor) -> Tensor:
        return x.clone() if self.mean_type == "identity" else torch.zeros_like(x)

    def add(self, x: Tensor, y: Tensor) -> None:
        if torch.isfinite(x).all() and torch.isfinite(y).all():
            self.xs.append(x.detach().clone())
            self.ys.append((y - self.prior(x)).detach().clone())
            self.model = None  # refactorise from scratch at the next use

    def _build(self):
        X = torch.stack(self.xs)  # (n, d)
        Y = torch.stack(self.ys)  # (n, Dy)
        lik = gpytorch.likelihoods.GaussianLikelihood(batch_shape=torch.Size([self.dim]))
        m = _ExactGP(X.unsqueeze(0).expand(self.dim, -1, -1), Y.T.contiguous(), lik, self.dim).to(self.dtype)
        m.covar_module.outputscale = torch.full((self.dim,), self.sf**2)
        m.covar_module.base_kernel.lengthscale = torch.full((self.dim, 1, 1), self.ls)
        lik.noise = torch.full((self.dim, 1), self.sn**2)
        m.eval()
        lik.eval()
        self.model = m

    def mean(self, x: Tensor) -> Tensor:
        if not self.xs:
            return self.prior(x)
        if self.model is None:
            self._build()
        out = self.model(x.reshape(1, 1, -1).expand(self.dim, 1, -1))
        return self.prior(x) + out.mean[:, 0]

    def linearize(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(Dx,) -> mean (Dx,), F (Dx, Dx), Q (Dx, Dx)``."""
        mean = self.mean(x)
        if self.xs:
            var = self.model(x.reshape(1, 1, -1).expand(self.dim, 1, -1)).variance[0, 0].detach()
        else:
            var = torch.tensor(self.sf**2, dtype=x.dtype)
        F = torch.autograd.functional.jacobian(self.mean, x)
        if self.noise_mode == "predictive":
            var = var + self.sn**2
        return mean.detach(), F.detach(), var * torch.eye(self.dim, dtype=x.dtype)


class _ParametricRef:
    """LIN / SFM model called one state at a time, Jacobian by autograd."""

    def __init__(self, model, ctx):
        self.model, self.ctx = model, ctx

    def linearize(self, x: Tensor):
        f = lambda z: self.model(z.unsqueeze(0), self.ctx)[0]  # noqa: E731
        return f(x).detach(), torch.autograd.functional.jacobian(f, x).detach(), self.model.noise_cov(x.unsqueeze(0), self.ctx)[0]

    def mean(self, x: Tensor) -> Tensor:
        return self.model(x.unsqueeze(0), self.ctx)[0]

    def add(self, x, y) -> None:
        pass


class ReferenceYu:
    """The Yu study through the naive implementation (same config, parts, data and seeds as
    :class:`dslearn.studies.yu.YuStudy`, the same Algorithm 1 loop; its own per-node filter)."""

    def __init__(self, cfg):
        self.cfg = cfg

    @classmethod
    def from_config(cls, cfg) -> "ReferenceYu":
        return cls(cfg)

    def run(self, progress: bool = False) -> pd.DataFrame:
        c = self.cfg
        torch.manual_seed(int(c.seed))
        p = build_parts(c)
        scenario, network, model, obs, fusion = p.scenario, p.network, p.model, p.observation, p.fusion
        if obs.learnable or c.observation.name != "linear":
            raise ConfigError(f"observation.name={c.observation.name!r}: the reference implementation supports 'linear' only")
        if fusion.name not in ("individual", "hybrid", "cm", "ci", "centralized"):
            raise ConfigError(f"consensus.name={fusion.name!r}: the reference implementation supports individual, hybrid, cm, ci, centralized")
        if getattr(model, "noise_mode", "latent") == "adaptive":
            raise ConfigError("model.noise=adaptive: the reference implementation supports latent and predictive only")
        if getattr(model, "fit_every", 0) or getattr(model, "variant", "exact") != "exact":
            raise ConfigError("model: the reference implementation supports the exact GP with fixed hyperparameters only (variant=exact, fit_every=0)")
        dtype = p.dtype
        ctx = scenario.ctx()
        test, train = sample_split(scenario, network, int(c.seed), c.data.test_episodes, c.data.train_episodes, dtype, p.device)
        S = network.num_nodes
        if isinstance(model, GPMotionModel):
            mc = c.model
            nodes = [ReferenceGP(scenario.state_dim, mc.outputscale, mc.lengthscale, mc.noise_std, mc.mean, mc.noise, dtype) for _ in range(S)]
        else:
            nodes = [_ParametricRef(model, ctx)] * S
        self.ref_nodes = nodes
        gate = c.filter.get("learn_gate_std")
        W = fusion.weights.to(dtype)
        sig2 = float(obs.noise_std) ** 2
        learnable = model.learnable
        checkpoints = eval_points(c.data) if learnable else [int(c.data.train_episodes)]

        def init(ep):
            return initial_belief(ep, network, ctx.dt, fusion, scenario.area, c.filter.prior_pos_std, c.filter.prior_vel_std)

        def learn(i: int) -> None:
            ep = train.measurements.select(slice(i, i + 1))
            m0, o0 = init(ep)
            self._track_one(ep, 0, nodes, fusion, W, sig2, m0[:, 0], o0[:, 0], learn=True, gate=gate)

        def evaluate(k: int) -> pd.DataFrame:  # one test episode at a time
            meas = test.measurements
            m0, o0 = init(meas)
            means, infos = [], []
            for b in range(len(test)):
                mb, ob = self._track_one(meas, b, nodes, fusion, W, sig2, m0[:, b], o0[:, b], learn=False, gate=None)
                means.append(mb)
                infos.append(ob)
            res = TrackResult(torch.stack(means, 1), torch.stack(infos, 1))
            metrics = tracking_metrics(res, test.states)
            metrics["pred_err"] = self._prediction_error(nodes, test.states, model.learnable, S)
            return metric_rows(metrics, network, model=c.model.name, consensus=fusion.name, train_seen=int(k))

        return algorithm1(learn, checkpoints, evaluate, learnable)

    # ------------------------------------------------------------------------------------
    def _track_one(self, ep, b, nodes, fusion, W, sig2, y0, o0, learn, gate):
        """One episode ``b``; ``y0 (S, Dx)``, ``o0 (S, Dx, Dx)``. Returns ``(S, K+1, Dx)``, ``(S, K+1, Dx, Dx)``."""
        S, K = len(nodes), ep.steps
        dx = y0.shape[-1]
        A = dx // AGENT_DIM
        y = [y0[i].clone() for i in range(S)]
        om = [o0[i].clone() for i in range(S)]
        hist_y, hist_o = [torch.stack(y)], [torch.stack(om)]
        C = torch.zeros(2, AGENT_DIM, dtype=y0.dtype)
        C[0, 0] = C[1, 1] = 1.0
        Rinv = torch.eye(2, dtype=y0.dtype) / sig2
        for t in range(1, K + 1):
            q_pred, o_pred, dq, do = [], [], [], []
            for i in range(S):
                mean, F, Q = nodes[i].linearize(y[i])
                P = spd_inverse(om[i])  # inverse through Cholesky, jitter as in the fast path
                Pp = F @ P @ F.T + Q
                Pp = 0.5 * (Pp + Pp.T)
                Op = spd_inverse(Pp)
                o_pred.append(Op)
                q_pred.append(Op @ mean)
                dqi = torch.zeros(dx, dtype=y0.dtype)
                doi = torch.zeros(dx, dx, dtype=y0.dtype)
                for j in range(A):
                    if bool(ep.visible[i, b, t, j]):
                        sl = slice(j * AGENT_DIM, (j + 1) * AGENT_DIM)
                        dqi[sl] += C.T @ Rinv @ ep.meas[i, b, t, j]
                        doi[sl, sl] += C.T @ Rinv @ C
                dq.append(dqi)
                do.append(doi)
            q_new, o_new = self._fuse(fusion, W, q_pred, o_pred, dq, do)
            y_new = [torch.cholesky_solve(q_new[i].unsqueeze(-1), safe_cholesky(o_new[i])).squeeze(-1) for i in range(S)]
            if learn:
                for i in range(S):
                    if gate is None or self._informed(hist_o[-1][i], gate):
                        nodes[i].add(y[i], y_new[i])
            y, om = y_new, o_new
            hist_y.append(torch.stack(y))
            hist_o.append(torch.stack(om))
        return torch.stack(hist_y, 1), torch.stack(hist_o, 1)

    @staticmethod
    def _informed(o: Tensor, gate: float) -> bool:
        var = spd_inverse(o).diagonal()
        for j in range(o.shape[-1] // AGENT_DIM):
            if var[j * AGENT_DIM] > gate**2 or var[j * AGENT_DIM + 1] > gate**2:
                return False
        return True

    @staticmethod
    def _rounds(W, xs, L):
        S = len(xs)
        for _ in range(L):
            xs = [sum(W[i, j] * xs[j] for j in range(S) if W[i, j] != 0) for i in range(S)]
        return xs

    def _fuse(self, fusion, W, q_pred, o_pred, dq, do):
        S, L, w = len(q_pred), fusion.iterations, fusion.omega
        sym = lambda m: 0.5 * (m + m.T)  # noqa: E731
        if fusion.name == "individual":
            return [q_pred[i] + dq[i] for i in range(S)], [sym(o_pred[i] + do[i]) for i in range(S)]
        if fusion.name == "centralized":
            sq, so = sum(dq), sum(do)
            return [q_pred[i] + sq for i in range(S)], [sym(o_pred[i] + so) for i in range(S)]
        if fusion.name == "ci":
            q = self._rounds(W, [q_pred[i] + dq[i] for i in range(S)], L)
            o = self._rounds(W, [o_pred[i] + do[i] for i in range(S)], L)
            return q, [sym(m) for m in o]
        dqL, doL = self._rounds(W, dq, L), self._rounds(W, do, L)
        if fusion.name == "cm":
            return [q_pred[i] + w * dqL[i] for i in range(S)], [sym(o_pred[i] + w * doL[i]) for i in range(S)]
        qL, oL = self._rounds(W, q_pred, L), self._rounds(W, o_pred, L)  # hybrid
        return [qL[i] + w * dqL[i] for i in range(S)], [sym(oL[i] + w * doL[i]) for i in range(S)]

    @staticmethod
    @torch.no_grad()
    def _prediction_error(nodes, truth, per_node, S):
        B, K = truth.shape[0], truth.shape[1] - 1
        out = torch.zeros(S, B, dtype=truth.dtype)
        for i in range(S if per_node else 1):
            for b in range(B):
                x, err = truth[b, 0], 0.0
                for t in range(1, K + 1):
                    x = nodes[i].mean(x).detach()
                    d = (x - truth[b, t]).reshape(-1, AGENT_DIM)[:, :2].norm(dim=-1)
                    err = err + d.mean()
                out[i, b] = err / K
        if not per_node:
            out[:] = out[0]
        return out


def run_reference(cfg) -> pd.DataFrame:
    """The reference implementation of :func:`dslearn.studies.yu.run` (same rows' values)."""
    return ReferenceYu.from_config(cfg).run()
