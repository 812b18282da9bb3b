r"""LSTM encoder–decoder trajectory predictor and its Social-LSTM variant, as a MotionModel.

Architecture (Yu et al. Section VI-C, after Alahi et al. 2016 [20]): per agent, the 2-D
input of each observed step goes through an MLP (``Linear(2, embed) + ReLU``) to an
``embed``-d feature; an encoder LSTM (``hidden``) reads the observed steps; a decoder LSTM
(``hidden``, initialised with the encoder's state) runs one step per predicted step and a
``Linear(hidden, 2)`` maps its hidden state to the 2-D output. Trained with Adam and an L2
(mean squared error) loss on the predicted positions (:func:`train_lstm`): either the paper's
fixed schedule (50 epochs, batch 8, lr 1e-3, last weights) or early stopping on a validation
set with the best weights restored and an optional on-plateau learning-rate decay
(:func:`schedule_from_config` reads either from a config; :func:`holdout_split` holds out
whole episodes for validation).

Inputs and outputs are **displacements**: the input of step ``t`` is ``p_t - p_{t-1}``
(0 for the first observed step) and the output of each decoder step is the next
displacement; positions are the last observed position plus the cumulative sum of the
predicted displacements (standard practice, e.g. Social GAN; it makes the model
translation-invariant, so it transfers between scenes with different world frames). The
decoder's input at each step is the embedding of the previous displacement (the last
observed one first, then its own predictions).

``pooling="social"`` adds the social pooling of Alahi et al. (2016), Eq. 1: around agent
``i`` a ``grid x grid`` square of side ``neighbourhood`` metres (centred on the agent) is
divided into cells; the hidden states of the other agents in each cell are summed,
:math:`H_i(m,n,:) = \sum_{j \ne i} 1_{mn}[p_j - p_i]\, h_j`, flattened, embedded
(``Linear(grid^2 hidden, embed) + ReLU``) and concatenated with the input embedding
before every encoder and decoder step (the hidden states are those of the previous step;
positions are observed ones in the encoder and predicted ones in the decoder).

The hyperparameters (paper defaults) live in ``conf/lstm/default.yaml`` (config group
``lstm``, used by ``dslearn-train-lstm``), and in the motion-model options ``conf/model/lstm.yaml`` /
``social_lstm.yaml`` (:meth:`SocialLSTM.for_scenario`: the Yu studies and real-data tracking,
trained offline by :meth:`SocialLSTM.fit_offline`); the forecasting study
(``dslearn/studies/ethucy_forecast.py``) keeps its own copy under ``task.lstm``.

Agents that are absent (NaN positions) in a window are masked: they are neither pooled
nor counted in the loss, and their predictions are NaN.
"""

from __future__ import annotations

import copy
import math
import time
from pathlib import Path

import pandas as pd
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from dslearn.errors import ConfigError, check_choice, check_integer, check_positive
from dslearn.types import AGENT_DIM, DTYPES, POS, StepContext, agents, distinct_rows, joint
from dslearn.models.base import MotionModel

POOLINGS = ("none", "social")
CHECKPOINT_FORMAT = "dslearn.lstm/1"
HPARAMS = ("obs_len", "pred_len", "embed", "hidden", "pooling", "grid", "neighbourhood", "dt")
#: where the process noise reported to filters comes from (``model.process_noise``)
PROCESS_NOISES = ("residuals", "fixed")
#: what an offline fit learns from (``model.train_on``; ``None`` = the study's default)
TRAIN_ON = ("truth", "fused")


class SocialLSTM(MotionModel):
    r"""LSTM encoder–decoder (``pooling="none"``) or Social-LSTM (``pooling="social"``).

    As a :class:`MotionModel` on the project state layout (per agent
    ``[px, py, vx, vy]``, ``Dx = 4A``): the history is rebuilt from the state as
    ``[p - (obs_len-1) v dt, ..., p - v dt, p]`` (for ``obs_len=2``: ``[p - v dt, p]``),
    the next position is the first predicted one, and the velocity of the output is the
    finite difference ``(p^{t+1} - p^t) / dt``. Process noise :math:`Q = \sigma^2 I`
    (``noise_std``) until :meth:`fit_offline` estimates it (``process_noise="residuals"``).

    As a ``model`` option (``conf/model/lstm.yaml``, ``conf/model/social_lstm.yaml``,
    :meth:`for_scenario`) it is an **offline** model: a study calls :meth:`fit_offline` once
    with its training episodes' trajectories before it tracks anything; filters use it through
    :meth:`linearize` (Jacobian by autograd) or at sigma points (UKF).

    Args:
        num_agents: ``A`` (state layout only; the network is shared by all agents, so a
            model trained on any number of agents runs on any other).
        obs_len: observed steps fed to the encoder (paper: 2).
        pred_len: steps predicted by the decoder (paper: 10).
        embed: input embedding size (paper: 64).
        hidden: LSTM hidden size (paper: 64).
        pooling: ``none`` | ``social``.
        grid: cells per side of the pooling grid.
        neighbourhood: side of the pooling square in metres.
        dt: seconds per step of the data it is trained on.
        dtype, device: parameters' dtype and device.
        noise_std: :math:`\sigma` of the process noise reported to filters.
        seed: if given, the weights are initialised from this seed (global RNG untouched).
    """

    def __init__(
        self,
        num_agents: int,
        obs_len: int = 2,
        pred_len: int = 10,
        embed: int = 64,
        hidden: int = 64,
        pooling: str = "none",
        grid: int = 4,
        neighbourhood: float = 2.0,
        dt: float = 0.4,
        dtype: torch.dtype = torch.float64,
        device: str | torch.device = "cpu",
        noise_std: float = 0.1,
        seed: int | None = None,
    ):
        super().__init__()
        for field, v in (("lstm.obs_len", obs_len), ("lstm.pred_len", pred_len), ("lstm.embed", embed),
                         ("lstm.hidden", hidden), ("lstm.grid", grid), ("num_agents", num_agents)):
            check_integer(field, v, 1)
        if obs_len < 2:
            raise ConfigError(f"lstm.obs_len={obs_len} must be >= 2 (one displacement at least)")
        check_choice("lstm.pooling", pooling, POOLINGS)
        check_positive("lstm.neighbourhood", neighbourhood)
        check_positive("lstm.dt", dt)
        check_positive("lstm.noise_std", noise_std)
        self.num_agents = int(num_agents)
        self.state_dim = AGENT_DIM * self.num_agents
        self.obs_len, self.pred_len = int(obs_len), int(pred_len)
        self.embed, self.hidden = int(embed), int(hidden)
        self.pooling, self.grid, self.neighbourhood = pooling, int(grid), float(neighbourhood)
        self.dt, self.noise_std = float(dt), float(noise_std)
        # the per-agent (4, 4) process covariance fitted by fit_offline (NaN: none yet, Q = noise_std^2 I);
        # not part of the state dict, so checkpoints of dslearn-train-lstm are unchanged
        self.register_buffer("process_cov", torch.full((AGENT_DIM, AGENT_DIM), float("nan")), persistent=False)
        self.offline = dict(OFFLINE_DEFAULTS)
        self.fit_info: dict[str, float] = {}
        self.training_curve: pd.DataFrame | None = None
        with torch.random.fork_rng(devices=[]):
            if seed is not None:
                torch.manual_seed(int(seed))
            self.input_embed = nn.Sequential(nn.Linear(2, embed), nn.ReLU())
            in_dim = embed
            if pooling == "social":
                self.pool_embed = nn.Sequential(nn.Linear(grid * grid * hidden, embed), nn.ReLU())
                in_dim += embed
            self.encoder = nn.LSTMCell(in_dim, hidden)
            self.decoder = nn.LSTMCell(in_dim, hidden)
            self.output = nn.Linear(hidden, 2)
        self.to(dtype=dtype, device=device)

    # the model option -------------------------------------------------------------------
    learns_offline = True

    @property
    def independent_targets(self) -> bool:
        """Without social pooling (``pooling="none"``) each agent's prediction is its own history's alone."""
        return self.pooling == "none"

    def one_agent(self) -> "SocialLSTM":
        """The same network over one agent's state ``(*B, 4)`` (the weights and the fitted noise shared, not
        copied): a model of independent targets predicts each track alone with it, its Jacobian ``4 x 4`` from
        two backward passes instead of the joint model's ``2A`` (:func:`dslearn.association.multitrack.predict_tracks`)."""
        if not self.independent_targets:
            raise ValueError("one_agent: a model with social pooling predicts its agents together")
        one = copy.copy(self)  # a shallow copy: the same modules and buffers
        one.num_agents, one.state_dim = 1, AGENT_DIM
        return one

    #: a gradient learner fine-tunes every weight of the encoder-decoder (after its offline fit)
    gradient_parameters = "lstm"

    @classmethod
    def for_scenario(
        cls,
        noise_std: float = 0.1,
        obs_len: int = 2,
        pred_len: int = 10,
        embed: int = 64,
        hidden: int = 64,
        pooling: str = "none",
        grid: int = 4,
        neighbourhood: float = 2.0,
        schedule: str = "fixed",
        epochs: int = 50,
        batch_size: int = 8,
        lr: float = 1e-3,
        patience: int | None = 10,
        min_delta: float = 0.0,
        lr_factor: float | None = None,
        lr_patience: int = 3,
        min_lr: float = 0.0,
        val_fraction: float = 0.2,
        process_noise: str = "residuals",
        train_on: str | None = None,
        weights_dtype: str | None = None,
        *,
        scenario,
        dtype: torch.dtype = torch.float64,
        device: str | torch.device = "cpu",
    ) -> "SocialLSTM":
        """The config factory (``conf/model/lstm.yaml``, ``social_lstm.yaml``): the network sized by the
        scenario (its agents ``num_agents`` lay out the state; its step ``dt`` is the model's), the
        offline training schedule and the process-noise rule (see :meth:`configure_offline`). Initial
        weights from seed 0 (:meth:`fit_offline` draws its own from the study's seed). ConfigError
        naming ``model.<key>`` for a bad value, or for ``obs_len + pred_len`` longer than the
        scenario's episodes (``scenario.steps + 1`` states) when it says how long they are.

        ``weights_dtype`` (``float32`` | ``float64`` | None = the run's ``dtype``): the network's weights and
        arithmetic; the filter around it stays in the run's dtype (the prediction and its Jacobian are cast
        back), so a float32 network inside a float64 filter trains and predicts about twice as fast."""
        if weights_dtype is not None:
            check_choice("model.weights_dtype", str(weights_dtype), tuple(DTYPES))
            dtype = DTYPES[str(weights_dtype)]
        try:
            model = cls(int(scenario.num_agents), obs_len, pred_len, embed, hidden, pooling, grid, neighbourhood,
                        float(scenario.ctx().dt), dtype, device, noise_std, seed=0)
        except ConfigError as e:  # the constructor names lstm.<key>; here they are model keys
            raise ConfigError(str(e).replace("lstm.", "model.")) from None
        model.configure_offline(schedule=schedule, epochs=epochs, batch_size=batch_size, lr=lr, patience=patience,
                                min_delta=min_delta, lr_factor=lr_factor, lr_patience=lr_patience, min_lr=min_lr,
                                val_fraction=val_fraction, process_noise=process_noise, train_on=train_on)
        steps = getattr(scenario, "steps", None)
        if steps is not None and obs_len + pred_len > int(steps) + 1:
            raise ConfigError(
                f"model.obs_len + model.pred_len = {obs_len + pred_len} must be <= the episodes' {int(steps) + 1} states "
                f"(the training windows are cut from them); lower model.pred_len"
            )
        return model

    def configure_offline(self, prefix: str = "model", **keys) -> "SocialLSTM":
        """Set the offline fit's settings (:data:`OFFLINE_DEFAULTS` for the keys not given): the
        schedule of :func:`train_lstm` (``schedule epochs batch_size lr patience min_delta lr_factor
        lr_patience min_lr``, :func:`schedule_from_config`), ``val_fraction`` (the share of whole
        training episodes held out), ``process_noise`` (``residuals`` | ``fixed``) and ``train_on``
        (``truth`` | ``fused`` | None). ConfigError naming ``{prefix}.<key>``."""
        unknown = sorted(set(keys) - set(OFFLINE_DEFAULTS))
        if unknown:
            raise ConfigError(f"{prefix}: unknown offline key(s) {unknown}; allowed: {sorted(OFFLINE_DEFAULTS)}")
        c = {**OFFLINE_DEFAULTS, **keys}
        schedule_from_config(c, prefix=prefix)
        check_positive(f"{prefix}.val_fraction", c["val_fraction"])
        if float(c["val_fraction"]) >= 1.0:
            raise ConfigError(f"{prefix}.val_fraction={c['val_fraction']!r} must be in (0, 1)")
        check_choice(f"{prefix}.process_noise", c["process_noise"], PROCESS_NOISES)
        if c["train_on"] is not None:
            check_choice(f"{prefix}.train_on", c["train_on"], TRAIN_ON)
        self.offline = c
        self.train_on = c["train_on"]
        return self

    # offline fit -------------------------------------------------------------------------
    def reinitialise(self, seed: int) -> "SocialLSTM":
        """Fresh weights drawn from ``seed`` (those of ``SocialLSTM(..., seed=seed)``; global RNG untouched)."""
        fresh = SocialLSTM(self.num_agents, **{k: getattr(self, k) for k in HPARAMS}, dtype=self.param_dtype,
                           device=self.param_device, noise_std=self.noise_std, seed=int(seed))
        self.load_state_dict(fresh.state_dict())
        return self

    def fit_offline(self, trajectories: Tensor, dt: float, seed: int = 0) -> "SocialLSTM":
        r"""Train on whole trajectories ``(B, K+1, 4A)`` (true tracks, or tracks a network estimated)
        with the configured schedule, from fresh weights drawn from ``seed`` (which also seeds the
        hold-out split and the shuffling), and set the process noise.

        Windows of ``obs_len + pred_len`` states slide over every trajectory
        (:func:`episode_windows`). Whole episodes are held out (``val_fraction``, seeded,
        :func:`holdout_groups`) when the schedule stops early (they are its validation set) or the
        process noise is estimated (``process_noise="residuals"``): the network is trained on the
        others, and :math:`Q` is the per-agent second moment of the one-step residuals
        :math:`x^{t+1} - f(x^t)` of the held-out true states (one ``(4, 4)`` block, shared by the
        agents, :math:`Q = I_A \otimes \Sigma`: out-of-sample, so the filter is not told the
        training error). With the fixed schedule the network is then trained again on **every**
        episode from the same fresh weights (the paper's recipe; those weights are kept: trained on
        more episodes, their one-step error on new data is expected no larger than that of the
        network the residuals came from, so :math:`Q` errs on the conservative side). ``process_noise="fixed"``: :math:`Q = \sigma^2 I`
        (``noise_std``) and, with the fixed schedule, one fit on every episode.

        Sets ``training_curve`` (the kept fit's :func:`train_lstm` table) and ``fit_info``
        (``train_loss``: the kept epoch's training loss; ``q_pos_std``, ``q_vel_std``: the fitted
        noise's mean position / velocity standard deviation, with residuals). ConfigError for a
        step that is not the model's ``dt``, trajectories shorter than a window, or fewer than 2
        episodes where some are held out.
        """
        if not math.isclose(float(dt), self.dt, rel_tol=1e-6):
            raise ConfigError(f"SocialLSTM was built for dt={self.dt} s but its training trajectories step dt={dt} s")
        c = self.offline
        if trajectories.dim() != 3 or trajectories.shape[-1] != self.state_dim:
            raise ValueError(f"trajectories must be (B, K+1, 4A={self.state_dim}), got {tuple(trajectories.shape)}")
        b, k1 = trajectories.shape[:2]
        if k1 < self.obs_len + self.pred_len:
            raise ConfigError(f"model.obs_len + model.pred_len = {self.obs_len + self.pred_len} must be <= the "
                              f"training episodes' {k1} states; lower model.pred_len")
        dev, dty = self.param_device, self.param_dtype
        self.process_cov = torch.full_like(self.process_cov, float("nan"))  # a refit starts from noise_std
        traj = trajectories.detach()
        win, groups = episode_windows(traj, self.obs_len, self.pred_len)
        sched = schedule_from_config(c, prefix="model")
        early = "patience" in sched
        residuals = c["process_noise"] == "residuals"
        seed = int(seed)
        if early or residuals:
            if b < 2:
                raise ConfigError(
                    f"model.schedule={c['schedule']} / model.process_noise={c['process_noise']} hold whole training "
                    f"episodes out, which needs >= 2 episodes (got {b}); use more, or model.schedule=fixed with "
                    f"model.process_noise=fixed"
                )
            held = holdout_groups(groups, float(c["val_fraction"]), seed)
            train_w, val_w = win[~held], win[held]
            self.reinitialise(seed)
            curve = train_lstm(self, train_w.to(dev, dty), **sched, val_windows=val_w.to(dev, dty) if early else None,
                               seed=seed)
            if residuals:
                ids = torch.unique(groups[held])
                self._set_process_cov(traj[ids.to(traj.device)])
        if not early:  # the fixed schedule keeps a fit on every episode
            self.reinitialise(seed)
            curve = train_lstm(self, win.to(dev, dty), **sched, seed=seed)
        self.training_curve = curve
        kept = curve.iloc[int(curve.attrs.get("restored_epoch", len(curve))) - 1]
        self.fit_info = {"train_loss": float(kept["train_loss"])}
        if residuals:
            d = torch.diagonal(self.process_cov).sqrt()
            self.fit_info.update(q_pos_std=float(d[:2].mean()), q_vel_std=float(d[2:].mean()))
        self.eval()
        return self

    # the offline-fit cache (dslearn.learning.fit_cache) ----------------------------------------
    def fit_cache_settings(self) -> dict:
        """Everything besides the data, ``dt`` and the seed that changes :meth:`fit_offline`'s result: the
        network's hyperparameters and agents, the offline settings, the noise, the parameters' dtype and device."""
        return {"num_agents": self.num_agents, **self.hparams(), "noise_std": self.noise_std,
                "offline": sorted(self.offline.items()), "dtype": str(self.param_dtype),
                "device": self.param_device.type}

    def fitted_state(self) -> dict:
        """What :meth:`fit_offline` produced, as tensors and plain values (:meth:`load_fitted_state` restores it)."""
        curve = self.training_curve
        return {"state_dict": {k: v.detach().cpu().clone() for k, v in self.state_dict().items()},
                "process_cov": self.process_cov.detach().cpu().clone(), "fit_info": dict(self.fit_info),
                "curve": {str(c): curve[c].tolist() for c in curve.columns}, "curve_attrs": dict(curve.attrs)}

    def load_fitted_state(self, state: dict) -> "SocialLSTM":
        """The model as :meth:`fit_offline` left it, from :meth:`fitted_state` (bit for bit)."""
        self.load_state_dict(state["state_dict"])  # strict: names and shapes must match
        cov = state["process_cov"]
        if tuple(cov.shape) != tuple(self.process_cov.shape):
            raise ValueError(f"process_cov {tuple(cov.shape)} != {tuple(self.process_cov.shape)}")
        self.process_cov = cov.to(self.process_cov)
        self.fit_info = dict(state["fit_info"])
        curve = pd.DataFrame(state["curve"])
        curve.attrs.update(state["curve_attrs"])
        self.training_curve = curve
        self.eval()
        return self

    @torch.no_grad()
    def one_step_residuals(self, trajectories: Tensor) -> Tensor:
        """``x^{t+1} - f(x^t)`` per agent over ``(B, K+1, 4A)`` true states: ``(B K A, 4)``."""
        x = trajectories.to(self.param_device, self.param_dtype)
        ctx = StepContext(dt=self.dt)
        pred = self(x[:, :-1], ctx)
        return agents(x[:, 1:] - pred).reshape(-1, AGENT_DIM)

    def _set_process_cov(self, held_out: Tensor) -> None:
        r = self.one_step_residuals(held_out)
        r = r[torch.isfinite(r).all(-1)]
        if r.shape[0] < AGENT_DIM:
            raise ConfigError(f"model.process_noise=residuals: only {r.shape[0]} finite one-step residuals on the "
                              "held-out episodes; use more episodes or model.process_noise=fixed")
        sigma = r.T @ r / r.shape[0]
        sigma = 0.5 * (sigma + sigma.T)
        evals, evecs = torch.linalg.eigh(sigma)  # floor: a direction the residuals never moved in keeps 1 mm
        sigma = (evecs * evals.clamp_min(1e-6)) @ evecs.T
        self.process_cov = 0.5 * (sigma + sigma.T).to(self.process_cov)

    # hyperparameters / checkpoints --------------------------------------------------------
    def hparams(self) -> dict:
        """The hyperparameters that define the network (saved with every checkpoint)."""
        return {k: getattr(self, k) for k in HPARAMS}

    @property
    def param_dtype(self) -> torch.dtype:
        return self.output.weight.dtype

    @property
    def param_device(self) -> torch.device:
        return self.output.weight.device

    def save(self, path: str | Path, history: pd.DataFrame | None = None) -> None:
        """Save a checkpoint (see :func:`save_checkpoint`)."""
        save_checkpoint(self, path, history)

    def load(self, path: str | Path) -> "SocialLSTM":
        """Load a checkpoint into this model; ConfigError if its hyperparameters differ."""
        load_checkpoint(path, self)
        return self

    # network ---------------------------------------------------------------------------
    def _pool(self, pos: Tensor, h: Tensor, mask: Tensor) -> Tensor:
        r"""Social pooling tensor, flattened: ``pos (B, A, 2), h (B, A, H), mask (B, A) -> (B, A, G^2 H)``.

        Cell of neighbour ``j`` around ``i``: ``floor((p_j - p_i + N/2) / (N/G))`` per axis;
        neighbours outside the ``N x N`` square, absent agents and ``j = i`` are left out.
        """
        b, a, _ = pos.shape
        g, nb = self.grid, self.neighbourhood
        rel = pos.unsqueeze(1) - pos.unsqueeze(2)  # (B, i, j, 2) = p_j - p_i
        cell = torch.floor((rel.detach() + 0.5 * nb) / (nb / g))
        inside = ((cell >= 0) & (cell < g)).all(-1)
        eye = torch.eye(a, dtype=torch.bool, device=pos.device)
        inside = inside & mask.unsqueeze(1) & mask.unsqueeze(2) & ~eye
        idx = (cell[..., 0] * g + cell[..., 1]).long().clamp(0, g * g - 1)
        onehot = F.one_hot(idx, g * g).to(h.dtype) * inside.unsqueeze(-1).to(h.dtype)  # (B, i, j, G^2)
        pooled = onehot.permute(0, 1, 3, 2).reshape(b, a * g * g, a) @ h  # (B, i*G^2, H)
        return pooled.reshape(b, a, g * g * self.hidden)

    def _pooled_embedding(self, pos: Tensor, h: Tensor, mask: Tensor) -> Tensor:
        r"""``ReLU(W vec(H_i) + b)`` without forming ``H_i``: ``(B, A, 2), (B, A, H), (B, A) -> (B, A, E)``.

        ``W vec(H_i) = \sum_{j \ne i \text{ in cell } c} W_c h_j`` with ``W_c`` the weight block
        of cell ``c``; only the neighbour pairs inside the grid are touched (equal to
        ``pool_embed(_pool(...))``, which is tested): each agent that is a neighbour of some
        pair is projected through all ``G^2`` blocks in one matmul, and each pair adds its
        cell's block, so the cost grows with the number of agents in close pairs, not with
        ``A^2 G^2 H``.
        """
        b, a, _ = pos.shape
        g, nb, hd = self.grid, self.neighbourhood, self.hidden
        lin = self.pool_embed[0]
        with torch.no_grad():
            rel = pos.unsqueeze(1) - pos.unsqueeze(2)  # (B, i, j, 2) = p_j - p_i
            cell = torch.floor((rel + 0.5 * nb) / (nb / g))
            inside = ((cell >= 0) & (cell < g)).all(-1)
            eye = torch.eye(a, dtype=torch.bool, device=pos.device)
            inside &= mask.unsqueeze(1) & mask.unsqueeze(2) & ~eye
            bi, ii, jj = inside.nonzero(as_tuple=True)
            cc = (cell[bi, ii, jj, 0] * g + cell[bi, ii, jj, 1]).long()
        out = lin.bias.expand(b * a, -1)
        if bi.numel():
            # project each neighbour that occurs in a pair through all G^2 weight blocks in one
            # matmul, then pick block c of neighbour j for every pair and add it to row i
            rows_i, rows_j = bi * a + ii, bi * a + jj
            uj, inv = torch.unique(rows_j, return_inverse=True)
            proj = h.reshape(b * a, hd)[uj] @ lin.weight.reshape(-1, hd).T  # (U, E * G^2), column e * G^2 + c
            contrib = proj.view(uj.numel(), -1, g * g)[inv, :, cc]  # (P, E) = W_c h_j
            out = out.index_add(0, rows_i, contrib)
        return torch.relu(out).view(b, a, -1)

    def _step_input(self, disp: Tensor, pos: Tensor, h: Tensor, mask: Tensor) -> Tensor:
        e = self.input_embed(disp)
        if self.pooling == "social":
            e = torch.cat([e, self._pooled_embedding(pos, h, mask)], dim=-1)
        return e

    def _decode(self, history: Tensor, steps: int) -> Tensor:
        """Core: ``(B, T_obs, A, 2)`` finite positions + mask -> ``(B, steps, A, 2)`` positions."""
        b, t_obs, a, _ = history.shape
        if a == 0:  # no agent (a batch of windows where every agent is absent somewhere, compacted away)
            return history.new_zeros(b, steps, 0, 2)
        mask = torch.isfinite(history).all(-1).all(1)  # (B, A)
        hist = torch.where(mask[:, None, :, None], history, torch.zeros_like(history))
        disp = torch.cat([torch.zeros_like(hist[:, :1]), hist[:, 1:] - hist[:, :-1]], dim=1)
        h = hist.new_zeros(b * a, self.hidden)
        c = hist.new_zeros(b * a, self.hidden)
        for t in range(t_obs):
            x = self._step_input(disp[:, t], hist[:, t], h.view(b, a, -1), mask)
            h, c = self.encoder(x.reshape(b * a, -1), (h, c))
        pos, d = hist[:, -1], disp[:, -1]
        out = []
        for _ in range(steps):
            x = self._step_input(d, pos, h.view(b, a, -1), mask)
            h, c = self.decoder(x.reshape(b * a, -1), (h, c))
            d = self.output(h).view(b, a, 2)
            pos = pos + d
            out.append(pos)
        pred = torch.stack(out, dim=1)
        return torch.where(mask[:, None, :, None], pred, torch.full_like(pred, float("nan")))

    def predict(self, history: Tensor, steps: int | None = None) -> Tensor:
        """Predicted positions ``(B, obs_len, A, 2) -> (B, pred_len, A, 2)`` (differentiable).

        The ``A`` agents are one scene window: with ``pooling="social"`` they pool each
        other. Agents with any NaN in their history are absent (NaN output). ``steps``
        (default ``pred_len``) runs the decoder for another number of steps.
        """
        if history.dim() != 4 or history.shape[-1] != 2 or history.shape[1] != self.obs_len:
            raise ValueError(f"history must be (B, obs_len={self.obs_len}, A, 2), got {tuple(history.shape)}")
        out = self._decode(history.to(self.param_device, self.param_dtype), self.pred_len if steps is None else int(steps))
        return out.to(history.device, history.dtype)

    # MotionModel interface -----------------------------------------------------------------
    def _check_ctx(self, ctx: StepContext) -> None:
        if not math.isclose(float(ctx.dt), self.dt, rel_tol=1e-6):
            raise ConfigError(f"SocialLSTM was built for dt={self.dt} s but the filter steps dt={ctx.dt} s")

    def history_from_state(self, x: Tensor) -> Tensor:
        """``(N, 4A) -> (N, obs_len, A, 2)``: ``p - k v dt`` for ``k = obs_len-1, ..., 0``."""
        ag = agents(x)
        p, v = ag[..., 0:2], ag[..., 2:4]
        k = torch.arange(self.obs_len - 1, -1, -1, dtype=x.dtype, device=x.device) * self.dt
        return p.unsqueeze(-3) - k.view(-1, 1, 1) * v.unsqueeze(-3)

    def _check_state(self, x: Tensor) -> None:
        if x.shape[-1] != self.state_dim:
            raise ValueError(f"state must be (..., 4A={self.state_dim}), got {tuple(x.shape)}")

    def forward(self, x: Tensor, ctx: StepContext) -> Tensor:
        """One step ``(*B, 4A) -> (*B, 4A)``: first predicted position, velocity by finite difference."""
        self._check_ctx(ctx)
        self._check_state(x)
        flat, inverse = distinct_rows(x.reshape(-1, self.state_dim))  # each distinct state once
        hist = self.history_from_state(flat)
        p1 = self.predict(hist, steps=1)[:, 0]
        p0 = hist[:, -1]
        out = torch.cat([p1, (p1 - p0) / self.dt], dim=-1)
        return joint(out if inverse is None else out[inverse]).reshape(x.shape)

    def noise_cov(self, x: Tensor, ctx: StepContext) -> Tensor:
        r""":math:`Q = I_A \otimes \Sigma` with :math:`\Sigma` fitted by :meth:`fit_offline`
        (``process_noise="residuals"``), else :math:`\sigma^2 I` (``noise_std``)."""
        if self.process_cov.device.type != "meta" and bool(torch.isfinite(self.process_cov).all()):
            q = torch.block_diag(*[self.process_cov.to(x.dtype)] * self.num_agents).to(x.device)
        else:
            q = self.noise_std**2 * torch.eye(self.state_dim, dtype=x.dtype, device=x.device)
        return q.expand(*x.shape[:-1], *q.shape)

    def linearize(self, x: Tensor, ctx: StepContext) -> tuple[Tensor, Tensor, Tensor]:
        r"""Mean, Jacobian (autograd) and process noise at ``x (*B, 4A)``: one forward pass; the
        ``2A`` position rows by reverse mode (one backward pass each, the batch rows together:
        they are independent), the velocity rows from them, :math:`\partial v' / \partial x =
        (\partial p' / \partial x - \partial p / \partial x) / dt` (the output velocity is the
        finite difference). Measured (200 rows, 2 agents, one thread; this call also returns the mean):
        43 ms plain / 59 ms social, against 67 / 104 ms for :func:`~dslearn.types.batch_jacobian` (all
        ``4A`` rows), 80 / 120 ms for ``torch.func.jacrev`` of the batch sum (vmapped backward) and
        ~280 / 700 ms for forward mode (the LSTM cell has no fused forward-mode kernel)."""
        self._check_ctx(ctx)
        self._check_state(x)
        flat, inverse = distinct_rows(x.detach().reshape(-1, self.state_dim))  # each distinct state once
        with torch.enable_grad():
            z = (x.detach() if inverse is None else flat).requires_grad_(True)
            y = self(z, ctx)
            pos = agents(y)[..., POS].reshape(*y.shape[:-1], -1)  # (*B, 2A)
            n = pos.shape[-1]
            rows = [torch.autograd.grad(pos[..., i].sum(), z, retain_graph=i < n - 1)[0] for i in range(n)]
        jp = torch.stack(rows, -2).unflatten(-2, (self.num_agents, 2))  # (*B, A, 2, Dx)
        sel = torch.eye(self.state_dim, dtype=x.dtype, device=x.device).view(self.num_agents, AGENT_DIM, -1)[:, POS]
        jv = (jp - sel) / self.dt
        F = torch.cat([jp, jv], dim=-2).flatten(-3, -2)  # (*B, 4A, Dx): per agent [p, v] rows
        y = y.detach()
        if inverse is not None:  # the distinct rows' mean and Jacobian, back to every row
            y, F = y[inverse].reshape(x.shape), F[inverse].reshape(*x.shape, self.state_dim)
        return y, F, self.noise_cov(x, ctx)

    def jacobian(self, x: Tensor, ctx: StepContext) -> Tensor:
        return self.linearize(x, ctx)[1]

    @torch.no_grad()
    def rollout(self, x0: Tensor, steps: int, ctx: StepContext) -> Tensor:
        """``(*B, 4A) -> (*B, steps, 4A)``: ``pred_len`` steps per decoder run; longer rollouts
        restart the encoder from the last ``obs_len`` predicted positions."""
        self._check_ctx(ctx)
        self._check_state(x0)
        flat = x0.reshape(-1, self.state_dim)
        hist = self.history_from_state(flat)
        seq = [hist]
        done = 0
        while done < steps:
            chunk = self.predict(hist, steps=min(self.pred_len, steps - done))
            seq.append(chunk)
            done += chunk.shape[1]
            hist = torch.cat(seq, dim=1)[:, -self.obs_len :]
        pos = torch.cat(seq, dim=1)[:, self.obs_len - 1 :]  # last observed + predicted
        vel = (pos[:, 1:] - pos[:, :-1]) / self.dt
        out = joint(torch.cat([pos[:, 1:], vel], dim=-1))  # (N, steps, 4A)
        return out.reshape(*x0.shape[:-1], steps, self.state_dim)


# training -------------------------------------------------------------------------------
def _masked_mse(pred: Tensor, target: Tensor) -> tuple[Tensor, int]:
    """Mean squared error over present agents (finite targets and predictions); returns (loss, count)."""
    ok = torch.isfinite(target).all(-1) & torch.isfinite(pred).all(-1)
    n = int(ok.sum())
    if n == 0:
        return pred.new_zeros(()), 0
    diff = torch.where(ok.unsqueeze(-1), pred - target, torch.zeros_like(pred))
    return diff.pow(2).sum() / (2 * n), n


def _compact(w: Tensor) -> Tensor:
    """Drop agent columns absent from every window of a batch ``(B, T, A, 2)``."""
    present = torch.isfinite(w).all(-1).all(1).any(0)
    return w[:, :, present] if not bool(present.all()) else w


def _check_windows(model: SocialLSTM, w: Tensor, name: str) -> None:
    t = model.obs_len + model.pred_len
    if w.dim() != 4 or w.shape[1] != t or w.shape[-1] != 2 or w.shape[0] < 1:
        raise ConfigError(f"{name} must be (N>=1, obs_len+pred_len={t}, A, 2), got {tuple(w.shape)}")


@torch.no_grad()
def evaluate_loss(model: SocialLSTM, windows: Tensor, batch_size: int = 256) -> float:
    """Mean L2 (MSE) loss of the predicted positions over ``windows (N, obs+pred, A, 2)``."""
    model.eval()
    tot, cnt = 0.0, 0
    dev, dt = model.param_device, model.param_dtype
    for i in range(0, windows.shape[0], batch_size):
        w = _compact(windows[i : i + batch_size]).to(dev, dt)
        loss, n = _masked_mse(model.predict(w[:, : model.obs_len]), w[:, model.obs_len :])
        tot += float(loss) * n
        cnt += n
    return tot / max(cnt, 1)


@torch.no_grad()
def lstm_predict(model: SocialLSTM, obs: Tensor, batch: int = 64) -> Tensor:
    """``(N, T_obs, A, 2)`` windows -> ``(N, pred_len, A, 2)`` in batches (trimmed padding)."""
    outs = []
    for i in range(0, obs.shape[0], batch):
        o = obs[i : i + batch]
        present = torch.isfinite(o).all(-1).all(1).any(0)
        k = int(present.nonzero().max()) + 1 if bool(present.any()) else 1  # windows are packed
        pred = model.predict(o[:, :, :k])
        full = torch.full((o.shape[0], pred.shape[1], o.shape[2], 2), float("nan"), dtype=o.dtype)
        full[:, :, :k] = pred
        outs.append(full)
    return torch.cat(outs, 0)


SCHEDULES = ("fixed", "early_stopping")
#: the offline fit's settings of a ``model`` option and their defaults (:meth:`SocialLSTM.configure_offline`)
OFFLINE_DEFAULTS = {"schedule": "fixed", "epochs": 50, "batch_size": 8, "lr": 1e-3, "patience": 10, "min_delta": 0.0,
                    "lr_factor": None, "lr_patience": 3, "min_lr": 0.0, "val_fraction": 0.2,
                    "process_noise": "residuals", "train_on": None}
#: ``task.lstm`` / ``lstm`` keys of the training schedule (read by :func:`schedule_from_config`)
SCHEDULE_KEYS = ("schedule", "epochs", "batch_size", "lr", "patience", "min_delta", "lr_factor", "lr_patience", "min_lr")


def check_schedule(
    *, epochs, batch_size, lr, patience=None, min_delta=0.0, lr_factor=None, lr_patience=2, min_lr=0.0,
    prefix: str = "lstm",
) -> None:
    """ConfigError (naming ``{prefix}.<field>`` and the allowed values) for a bad training schedule."""
    check_integer(f"{prefix}.epochs", epochs, 1)
    check_integer(f"{prefix}.batch_size", batch_size, 1)
    check_positive(f"{prefix}.lr", lr)
    if patience is not None:
        check_integer(f"{prefix}.patience", patience, 1)
    check_positive(f"{prefix}.min_delta", min_delta, strict=False)
    if float(min_delta) >= 1.0:
        raise ConfigError(f"{prefix}.min_delta={min_delta!r} is a relative improvement and must be in [0, 1)")
    if lr_factor is not None:
        check_positive(f"{prefix}.lr_factor", lr_factor)
        if float(lr_factor) >= 1.0:
            raise ConfigError(f"{prefix}.lr_factor={lr_factor!r} must be in (0, 1) or null (constant learning rate)")
    check_integer(f"{prefix}.lr_patience", lr_patience, 1)
    check_positive(f"{prefix}.min_lr", min_lr, strict=False)


def schedule_from_config(c, prefix: str = "lstm") -> dict:
    """Keyword arguments of :func:`train_lstm` from a config mapping (``task.lstm`` / ``lstm``).

    Keys (all but ``epochs``, ``batch_size``, ``lr`` optional; see :data:`SCHEDULE_KEYS`):
    ``schedule`` = ``fixed`` (default; the paper: all ``epochs`` at a constant ``lr``, the last
    weights) or ``early_stopping`` (``epochs`` is the cap; stop after ``patience`` epochs
    without a new best validation loss, restore the best weights; optional on-plateau decay
    of the learning rate by ``lr_factor`` after ``lr_patience`` epochs without a new best,
    down to ``min_lr``). Raises :class:`ConfigError` naming the field for bad values.
    """
    get = (lambda k, d=None: c.get(k, d)) if hasattr(c, "get") else (lambda k, d=None: getattr(c, k, d))
    schedule = get("schedule", "fixed")
    check_choice(f"{prefix}.schedule", schedule, SCHEDULES)
    kw = dict(epochs=get("epochs"), batch_size=get("batch_size"), lr=get("lr"))
    if schedule == "early_stopping":
        kw.update(
            patience=get("patience", 10), min_delta=get("min_delta", 0.0), lr_factor=get("lr_factor"),
            lr_patience=get("lr_patience", 2), min_lr=get("min_lr", 0.0),
        )
        if kw["patience"] is None:
            raise ConfigError(f"{prefix}.patience=None: {prefix}.schedule=early_stopping needs an integer >= 1")
    else:  # the fixed schedule ignores the early-stopping keys but still rejects bad values
        check_schedule(
            epochs=kw["epochs"], batch_size=kw["batch_size"], lr=kw["lr"], patience=get("patience"),
            min_delta=get("min_delta", 0.0), lr_factor=get("lr_factor"), lr_patience=get("lr_patience", 2),
            min_lr=get("min_lr", 0.0), prefix=prefix,
        )
    check_schedule(**kw, prefix=prefix)
    kw["epochs"], kw["batch_size"], kw["lr"] = int(kw["epochs"]), int(kw["batch_size"]), float(kw["lr"])
    return kw


def episode_windows(states: Tensor, obs_len: int, pred_len: int) -> tuple[Tensor, Tensor]:
    """Sliding windows of positions: ``(B, K+1, 4A) -> (N, obs_len + pred_len, A, 2)``, start-major
    (every episode's first window, then every episode's second, ...), and the episode each window
    was cut from, ``(N,)`` (a hold-out keeps whole episodes apart)."""
    pos = agents(states)[..., POS]
    w = obs_len + pred_len
    k1 = pos.shape[1]
    starts = range(0, k1 - w + 1)
    groups = torch.arange(pos.shape[0]).repeat(len(starts))
    return torch.cat([pos[:, s : s + w] for s in starts], 0), groups


def holdout_groups(groups: Tensor, val_fraction: float, seed: int) -> Tensor:
    """Which entries of ``groups`` (an episode or file id per window) are held out: ``round(val_fraction
    * G)`` of the ``G`` distinct groups (at least 1, at most ``G - 1``), drawn with
    ``torch.Generator().manual_seed(seed)``. ConfigError for a fraction outside (0, 1) or fewer than
    2 groups. Returns a bool mask like ``groups``."""
    check_positive("lstm.val_fraction", val_fraction)
    if float(val_fraction) >= 1.0:
        raise ConfigError(f"lstm.val_fraction={val_fraction!r} must be in (0, 1)")
    groups = torch.as_tensor(groups).reshape(-1)
    ids = torch.unique(groups)
    if ids.numel() < 2:
        raise ConfigError(f"early stopping needs >= 2 groups (episodes) to hold some out for validation, got {ids.numel()}")
    k = min(max(int(round(float(val_fraction) * ids.numel())), 1), ids.numel() - 1)
    perm = torch.randperm(ids.numel(), generator=torch.Generator().manual_seed(int(seed)))
    return torch.isin(groups, ids[perm[:k]])


def holdout_split(windows: Tensor, groups: Tensor, val_fraction: float, seed: int) -> tuple[Tensor, Tensor]:
    """Split windows into (train, validation) **by group** (e.g. the episode or file each
    window was cut from), so that overlapping windows never straddle the split.

    ``round(val_fraction * G)`` of the ``G`` distinct groups (at least 1, at most ``G - 1``),
    drawn with ``torch.Generator().manual_seed(seed)``, go to validation. ConfigError for a
    fraction outside (0, 1) or fewer than 2 groups.
    """
    check_positive("lstm.val_fraction", val_fraction)
    if float(val_fraction) >= 1.0:
        raise ConfigError(f"lstm.val_fraction={val_fraction!r} must be in (0, 1)")
    groups = torch.as_tensor(groups).reshape(-1)
    if groups.numel() != windows.shape[0]:
        raise ValueError(f"groups has {groups.numel()} entries for {windows.shape[0]} windows")
    is_val = holdout_groups(groups, val_fraction, seed)
    return windows[~is_val], windows[is_val]


def train_lstm(
    model: SocialLSTM,
    windows: Tensor,
    *,
    epochs: int,
    batch_size: int,
    lr: float,
    val_windows: Tensor | None = None,
    seed: int = 0,
    progress: bool = False,
    checkpoint: str | Path | None = None,
    patience: int | None = None,
    min_delta: float = 0.0,
    restore_best: bool = True,
    lr_factor: float | None = None,
    lr_patience: int = 2,
    min_lr: float = 0.0,
) -> pd.DataFrame:
    """Train with Adam on the L2 (mean squared error) loss of the predicted positions.

    Without ``patience`` (the default) this is the fixed schedule: all ``epochs`` at the
    constant ``lr``, the final weights are kept (the paper: 50 epochs, batch 8, lr 1e-3).
    With ``patience`` it is **early stopping** on ``val_windows`` (required): training stops
    after ``patience`` consecutive epochs without a new best validation loss (a new best
    must be below ``best * (1 - min_delta)``), or at ``epochs`` (the cap), and the weights of
    the best validation epoch are restored (``restore_best``). ``lr_factor`` (needs
    ``val_windows``) multiplies the learning rate by that factor after ``lr_patience``
    epochs without a new best (not below ``min_lr``; the counter restarts after each cut).
    The first epochs of an early-stopping run are bit-identical to the fixed schedule with
    the same seed as long as the learning rate has not been cut (tested).

    Args:
        model: the network (trained in place).
        windows: ``(N, obs_len + pred_len, A, 2)`` positions; NaN = agent absent (masked).
            With ``pooling="social"`` the ``A`` agents of a window pool each other.
        epochs, batch_size, lr: Adam schedule; a batch is ``batch_size`` windows.
        val_windows: optional validation windows (same layout); ``val_loss`` is NaN without.
        seed: seeds the shuffling (``torch.Generator``).
        progress: tqdm bar over epochs.
        checkpoint: if given, the returned weights (best or final) are saved there.
        patience, min_delta, restore_best, lr_factor, lr_patience, min_lr: see above.
    Returns:
        DataFrame, one row per epoch run: ``epoch, train_loss, val_loss, seconds, lr, best``
        (``train_loss`` = mean over the epoch's batches while training, ``val_loss`` = after
        the epoch, ``lr`` = the learning rate the epoch ran with, ``best`` = a new best
        validation loss). ``attrs``: ``best_epoch``, ``best_val_loss``, ``stopped_early``,
        ``restored_epoch`` (the epoch whose weights the model holds).
    """
    check_schedule(epochs=epochs, batch_size=batch_size, lr=lr, patience=patience, min_delta=min_delta,
                   lr_factor=lr_factor, lr_patience=lr_patience, min_lr=min_lr)
    _check_windows(model, windows, "windows")
    if val_windows is not None:
        _check_windows(model, val_windows, "val_windows")
    elif patience is not None or lr_factor is not None:
        raise ConfigError("lstm.schedule=early_stopping (patience / lr_factor) needs validation windows (val_windows)")
    from tqdm.auto import tqdm

    gen = torch.Generator().manual_seed(int(seed))
    opt = torch.optim.Adam(model.parameters(), lr=float(lr))
    dev, dt = model.param_device, model.param_dtype
    n = windows.shape[0]
    rows = []
    best_val, best_epoch, best_state = math.inf, 0, None
    since_best, since_cut, cur_lr, stopped = 0, 0, float(lr), False
    bar = tqdm(range(1, epochs + 1), desc=f"train lstm ({model.pooling})", disable=not progress, leave=False)
    for epoch in bar:
        t0 = time.perf_counter()
        model.train()
        perm = torch.randperm(n, generator=gen)
        tot, cnt = 0.0, 0
        for i in range(0, n, batch_size):
            w = _compact(windows[perm[i : i + batch_size]]).to(dev, dt)
            loss, k = _masked_mse(model.predict(w[:, : model.obs_len]), w[:, model.obs_len :])
            if k == 0:
                continue
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            tot += float(loss.detach()) * k
            cnt += k
        train_loss = tot / max(cnt, 1)
        val_loss = evaluate_loss(model, val_windows) if val_windows is not None else float("nan")
        improved = math.isfinite(val_loss) and val_loss < best_val * (1.0 - float(min_delta))
        if improved:
            best_val, best_epoch, since_best, since_cut = val_loss, epoch, 0, 0
            if patience is not None and restore_best:
                best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
        else:
            since_best += 1
            since_cut += 1
        rows.append({"epoch": epoch, "train_loss": train_loss, "val_loss": val_loss, "seconds": time.perf_counter() - t0,
                     "lr": cur_lr, "best": bool(improved)})
        bar.set_postfix(train=f"{train_loss:.4f}", val=f"{val_loss:.4f}")
        if patience is not None and since_best >= int(patience):
            stopped = epoch < epochs
            break
        if lr_factor is not None and since_cut >= int(lr_patience) and cur_lr > float(min_lr):
            cur_lr = max(cur_lr * float(lr_factor), float(min_lr))
            for grp in opt.param_groups:
                grp["lr"] = cur_lr
            since_cut = 0
    restored = rows[-1]["epoch"]
    if best_state is not None and best_epoch != restored:
        model.load_state_dict(best_state)
        restored = best_epoch
    model.eval()
    hist = pd.DataFrame(rows)
    hist.attrs.update(best_epoch=int(best_epoch), best_val_loss=float(best_val) if best_epoch else float("nan"),
                      stopped_early=bool(stopped), restored_epoch=int(restored))
    if checkpoint is not None:
        save_checkpoint(model, checkpoint, hist)
    return hist


def save_checkpoint(model: SocialLSTM, path: str | Path, history: pd.DataFrame | None = None) -> None:
    """``torch.save`` of ``{format, hparams, state_dict, history}`` (plain tensors and
    builtins only, so :func:`load_checkpoint` can use ``weights_only=True``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    blob = {
        "format": CHECKPOINT_FORMAT,
        "hparams": model.hparams(),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "history": {} if history is None else {c: [float(v) for v in history[c]] for c in history.columns},
    }
    tmp = path.with_name(path.name + ".tmp")
    torch.save(blob, tmp)
    tmp.replace(path)


def _same(a, b) -> bool:
    if isinstance(a, float) or isinstance(b, float):
        return isinstance(a, (int, float)) and isinstance(b, (int, float)) and math.isclose(float(a), float(b), rel_tol=1e-9)
    return a == b


def _read_blob(path: Path) -> dict:
    """``torch.load(weights_only=True)`` of ``path``: DataFormatError naming the file for a missing,
    empty, truncated or corrupt file, and for one that pickles Python objects (which could run
    code when loaded: refused, never unpickled), or whose content is not a checkpoint dict."""
    import pickle
    import re
    import warnings

    from dslearn.errors import DataFormatError

    if path.is_dir():
        raise DataFormatError(f"{path}: is a folder, not an LSTM checkpoint file")
    if not path.exists():
        raise DataFormatError(f"{path}: no such LSTM checkpoint file")
    try:
        size = path.stat().st_size
    except OSError as e:
        raise DataFormatError(f"{path}: cannot be read ({e.strerror or e})") from None
    if size == 0:
        raise DataFormatError(f"{path}: empty file, not an LSTM checkpoint")
    try:
        with warnings.catch_warnings():  # torch's notes on pickle protocols: the error below says it all
            warnings.simplefilter("ignore")
            blob = torch.load(path, weights_only=True, map_location="cpu")
    except pickle.UnpicklingError as e:
        text = str(e)
        if "Weights only load failed" in text:
            g = re.search(r"GLOBAL (\S+)", text)
            op = re.search(r"(Unsupported operand \S+)", text)
            what = (f"it pickles the Python object {g.group(1)}, which could run code when loaded" if g else
                    f"not a weights-only pickle ({op.group(1) if op else 'the safe loader cannot read it'})")
            raise DataFormatError(
                f"{path}: refused: {what}; an LSTM checkpoint holds only tensors and plain values "
                "(written by dslearn-train-lstm / save_checkpoint)"
            ) from None
        raise DataFormatError(f"{path}: not a readable torch checkpoint (truncated or corrupt: UnpicklingError: "
                              f"{' '.join(text.split())[:160]})") from None
    except PermissionError:
        raise DataFormatError(f"{path}: cannot be read (permission denied)") from None
    except Exception as e:  # noqa: BLE001 - EOFError, zip/stream errors, OSError(EINVAL), KeyError, ...
        why = " ".join(str(e).split())[:160]
        raise DataFormatError(
            f"{path}: not a readable torch checkpoint (truncated or corrupt: {type(e).__name__}{': ' + why if why else ''})"
        ) from None
    if not isinstance(blob, dict) or blob.get("format") != CHECKPOINT_FORMAT:
        got = f"format {blob.get('format')!r}" if isinstance(blob, dict) else f"a {type(blob).__name__}"
        raise DataFormatError(f"{path}: not a {CHECKPOINT_FORMAT} checkpoint ({got}); write one with dslearn-train-lstm")
    return blob


def _check_blob(path: Path, blob: dict) -> tuple[dict, dict, dict]:
    """The checkpoint's ``(hparams, state_dict, history)``, each checked for its form (DataFormatError)."""
    from dslearn.errors import DataFormatError

    saved = blob.get("hparams")
    if not isinstance(saved, dict):
        raise DataFormatError(f"{path}: hparams is {type(saved).__name__}, not a mapping of {list(HPARAMS)}")
    missing, unknown = [k for k in HPARAMS if k not in saved], sorted(str(k) for k in saved if k not in HPARAMS)
    if missing or unknown:
        raise DataFormatError(
            f"{path}: hparams " + "; ".join(filter(None, [f"lacks {missing}" if missing else "",
                                                         f"has unknown keys {unknown}" if unknown else ""]))
            + f" (expected {list(HPARAMS)})"
        )
    state = blob.get("state_dict")
    if not isinstance(state, dict) or not all(isinstance(k, str) and isinstance(v, Tensor) for k, v in state.items()):
        raise DataFormatError(f"{path}: state_dict is not a mapping of parameter names to tensors")
    for k, v in state.items():
        if v.is_floating_point() and not bool(torch.isfinite(v).all()):
            raise DataFormatError(f"{path}: state_dict[{k!r}] holds NaN or infinite weights")
    history = blob.get("history") or {}
    ok = isinstance(history, dict) and all(isinstance(v, (list, tuple)) for v in history.values())
    if not ok or len({len(v) for v in history.values()}) > 1:
        raise DataFormatError(f"{path}: history is not a mapping of equally long per-epoch lists")
    return saved, state, history


def load_checkpoint(
    path: str | Path,
    model: SocialLSTM | None = None,
    *,
    num_agents: int = 1,
    dtype: torch.dtype = torch.float64,
    device: str | torch.device = "cpu",
) -> SocialLSTM:
    """Load a checkpoint with ``torch.load(weights_only=True)``.

    Into ``model`` if given (its hyperparameters must equal the saved ones, else
    :class:`ConfigError` naming every mismatch), else into a new :class:`SocialLSTM` built
    from the saved hyperparameters with ``num_agents``, ``dtype``, ``device``.

    Raises:
        DataFormatError: naming the file: missing, a folder, empty, truncated or corrupt; a pickle
            of Python objects (refused unread: it could run code); not a ``dslearn.lstm/1``
            checkpoint; hyperparameters, weights or history of the wrong form; weights whose
            names or shapes disagree with the saved hyperparameters; non-finite weights.
        ConfigError: naming the file: the given ``model``'s hyperparameters differ from the saved ones.
    """
    from dslearn.errors import DataFormatError

    path = Path(path)
    saved, state, history = _check_blob(path, _read_blob(path))
    if model is None:
        try:
            model = SocialLSTM(num_agents, **saved, dtype=dtype, device=device)
        except ConfigError as e:  # the saved values themselves are out of range
            raise DataFormatError(f"{path}: invalid saved hyperparameters: {e}") from None
    else:
        mine = model.hparams()
        bad = [f"{k}: checkpoint {saved.get(k)!r} vs model {mine[k]!r}" for k in HPARAMS if not _same(saved.get(k), mine[k])]
        if bad:
            raise ConfigError(f"checkpoint {str(path)!r} does not match the model's lstm hyperparameters: " + "; ".join(bad))
    own = model.state_dict()
    missing, unexpected = sorted(set(own) - set(state)), sorted(set(state) - set(own))
    shapes = [f"{k}: file {tuple(state[k].shape)} vs hparams {tuple(own[k].shape)}"
              for k in own if k in state and tuple(state[k].shape) != tuple(own[k].shape)]
    if missing or unexpected or shapes:
        hp = ", ".join(f"{k}={saved[k]!r}" for k in ("pooling", "embed", "hidden", "grid"))
        more = f"; ... ({len(shapes) - 3} more)" if len(shapes) > 3 else ""
        raise DataFormatError(
            f"{path}: the weights do not match the saved hyperparameters ({hp}): "
            + "; ".join(filter(None, [f"missing {missing}" if missing else "",
                                      f"unexpected {unexpected}" if unexpected else "", *shapes[:3]])) + more
        )
    try:
        model.load_state_dict(state)
    except (RuntimeError, ValueError, TypeError) as e:
        raise DataFormatError(f"{path}: the weights cannot be loaded ({' '.join(str(e).split())[:200]})") from None
    model.checkpoint_history = pd.DataFrame(history)
    model.eval()
    return model
