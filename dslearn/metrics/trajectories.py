r"""Errors of any method's position estimates (:class:`~dslearn.episodes.Estimates`) step by step: what a
tracking figure draws (the error and the NEES over time, one episode's true and estimated tracks)."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from dslearn.episodes import Estimates
from dslearn.io import TRACKS_FILE  # noqa: F401  (the run-folder file of track_record)


def position_series(est: Estimates, truth: Tensor) -> dict[str, Tensor]:
    r"""Per reporting node and step :math:`t = 1..K`, the mean over the ``B`` episodes of

    * ``pos_err``: the mean over targets of :math:`\lVert \hat p_{a,t} - p_{a,t} \rVert` (its mean over
      ``t`` is the mean over episodes of :func:`~dslearn.metrics.positions.position_metrics`' ``pos_err``,
      Yu et al.'s tracking error ``track_err``);
    * ``nees_pos`` (where the method gives covariances): :math:`\sum_a e_{a,t}^T P_{aa,t}^{-1} e_{a,t} / (2A)`,
      the position NEES of every target's block over its ``2A`` degrees of freedom (1 for a consistent
      estimator; the band of :func:`nees_band`).

    Args:
        est: ``mean (N, B, K+1, A, 2)``, ``cov (N, B, K+1, A, 2, 2)`` or None; truth: ``(B, K+1, A, 2)``.
    Returns:
        ``{name: (N, K)}``.
    """
    err = est.mean[:, :, 1:] - truth[:, 1:].unsqueeze(0).to(est.mean)  # (N, B, K, A, 2)
    out = {"pos_err": err.pow(2).sum(-1).sqrt().mean(-1).mean(1)}
    if est.cov is not None:
        e = err.unsqueeze(-1)
        d2 = (e.transpose(-1, -2) @ torch.linalg.solve(est.cov[:, :, 1:], e)).squeeze(-1).squeeze(-1)  # (N, B, K, A)
        out["nees_pos"] = (d2.sum(-1) / (2 * truth.shape[-2])).mean(1)
    return out


def nees_band(dof: int, episodes: int, prob: float = 0.95) -> tuple[float, float]:
    r"""The two-sided ``prob`` interval of the NEES over its degrees of freedom, averaged over ``episodes``
    independent episodes, for a consistent estimator (Bar-Shalom et al., 2001, 5.4.2): the sum of
    ``episodes`` NEES values is :math:`\chi^2` with ``dof * episodes`` degrees of freedom, so the band is
    :math:`\chi^2_{n}\big((1 \mp prob)/2\big) / n` with :math:`n = dof \cdot episodes`."""
    from scipy.special import gammaincinv  # scipy.stats.chi2.ppf's own formula, without importing scipy.stats (~1.5 s)

    if dof < 1 or episodes < 1 or not 0 < prob < 1:
        raise ValueError(f"nees_band: dof={dof} and episodes={episodes} must be >= 1, prob={prob} in (0, 1)")
    n = dof * episodes
    lo, hi = 2 * gammaincinv(n / 2, np.asarray([(1 - prob) / 2, (1 + prob) / 2]))
    return float(lo) / n, float(hi) / n


def episode_track(est: Estimates, truth: Tensor, episode: int = 0) -> dict[str, Tensor]:
    """One episode's true and estimated tracks, steps ``0..K`` (step 0 is the prior belief):
    ``truth (K+1, A, 2)``, ``mean (N, K+1, A, 2)`` and, where the method gives covariances,
    ``cov (N, K+1, A, 2, 2)``."""
    out = {"truth": truth[episode], "mean": est.mean[:, episode]}
    if est.cov is not None:
        out["cov"] = est.cov[:, episode]
    return out



def track_record(est: Estimates, truth: Tensor, dt: float, network=None, units: str = "m", episode: int = 0,
                 **labels) -> dict:
    """What a tracking figure needs, as numpy arrays (the content of :data:`TRACKS_FILE`):

    * the network (where there is one): ``positions (S, 2)``, ``is_sensor (S,)``, ``sensing_range``,
      ``adjacency (S, S)``;
    * the reporting nodes: ``nodes (N,)`` names, ``sensing (N,)``;
    * episode ``episode`` (:func:`episode_track`): ``truth (K+1, A, 2)``, ``mean (N, K+1, A, 2)``,
      ``cov (N, K+1, A, 2, 2)``, at ``track_time`` ``(K+1,)`` (step 0 is the prior);
    * over every episode (:func:`position_series`): ``pos_err (N, K)``, ``nees_pos (N, K)`` at ``time``
      ``(K,)`` (steps 1..K), with ``nees_dof`` (2A), ``episodes`` (B) and ``nees_band`` (the 95 % band of
      :func:`nees_band`);
    * ``dt``, ``units``, ``episode`` and the ``labels`` (strings or numbers, e.g. the model's name).

    Only one episode's beliefs are kept."""
    import numpy as np

    def a(t):
        return t.detach().cpu().numpy()

    b, k1 = truth.shape[0], truth.shape[1]
    if not 0 <= episode < b:
        raise ValueError(f"track_record: episode {episode} of {b} episodes")
    out = {f"{k}": a(v) for k, v in episode_track(est, truth, episode).items()}
    out.update({k: a(v) for k, v in position_series(est, truth).items()})
    out["nodes"] = np.asarray([str(n) for n in est.nodes])
    out["sensing"] = a(est.sensing).astype(bool)
    steps = np.arange(k1, dtype=np.float64)
    out["track_time"] = steps * float(dt)
    out["time"] = steps[1:] * float(dt)
    dof = 2 * truth.shape[-2]
    out["nees_dof"] = np.asarray(dof)
    out["episodes"] = np.asarray(b)
    if est.cov is not None:
        out["nees_band"] = np.asarray(nees_band(dof, b))
    out["dt"] = np.asarray(float(dt))
    out["units"] = np.asarray(str(units))
    out["episode"] = np.asarray(int(episode))
    if network is not None:
        out["positions"] = a(network.positions).astype(np.float64)
        out["is_sensor"] = a(network.is_sensor).astype(bool)
        out["sensing_range"] = np.asarray(float(network.sensing_range))
        out["adjacency"] = a(network.adjacency).astype(bool)
    for k, v in labels.items():
        if k in out:
            raise ValueError(f"track_record: label {k!r} is one of the arrays' names")
        out[k] = np.asarray(v if isinstance(v, (int, float)) else str(v))
    return out
