r"""Metrics of multi-target tracking: distances between the set of true targets and the set of estimated
tracks (GOSPA, OSPA), and the identity errors of tracks over a sequence (identity switches, fragmentations).

Sets are padded tensors with batch dimensions first: ``truth (*B, N, d)`` and ``est (*B, M, d)``, each with an
optional presence mask ``(*B, N)`` / ``(*B, M)`` (a slot whose mask is False is not in the set; no mask: every
slot is). The base distance is the Euclidean distance between the vectors (pass positions for position errors).
Each optimal assignment is SciPy's :func:`scipy.optimize.linear_sum_assignment`.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from torch import Tensor

from dslearn.errors import ConfigError, check_positive


def _order(c, p) -> tuple[float, float]:
    """The checked cut-off ``c`` (> 0) and order ``p`` (>= 1) as floats."""
    check_positive("c", c)
    check_positive("p", p)
    if float(p) < 1:
        raise ConfigError(f"p={p!r} must be >= 1 (the order of the metric)")
    return float(c), float(p)


def _sets(truth: Tensor, est: Tensor, c, p, truth_mask: Tensor | None, est_mask: Tensor | None):
    """The checked cut-off ``c`` (> 0) and order ``p`` (>= 1) as floats, the batch shape and, per batch element, the
    two sets as float64 numpy arrays ``(n, d)``, ``(m, d)``."""
    c, p = _order(c, p)
    truth, est = torch.as_tensor(truth), torch.as_tensor(est)
    if truth.dim() < 2 or est.dim() < 2:
        raise ConfigError(f"truth {tuple(truth.shape)} and est {tuple(est.shape)} must be (*B, N, d) and (*B, M, d)")
    if truth.shape[:-2] != est.shape[:-2] or truth.shape[-1] != est.shape[-1]:
        raise ConfigError(f"truth {tuple(truth.shape)} and est {tuple(est.shape)} must share the batch shape and d")
    batch = truth.shape[:-2]
    nb = math.prod(batch)
    t = truth.detach().to("cpu", torch.float64).reshape(nb, *truth.shape[-2:]).numpy()
    e = est.detach().to("cpu", torch.float64).reshape(nb, *est.shape[-2:]).numpy()

    def mask(m, x, name):
        if m is None:
            return np.ones(x.shape[:2], dtype=bool)
        m = torch.as_tensor(m)
        if m.shape != torch.Size(batch) + x.shape[1:2]:
            raise ConfigError(f"{name} {tuple(m.shape)} must be {tuple(batch) + x.shape[1:2]}")
        return m.detach().to("cpu", torch.bool).reshape(x.shape[:2]).numpy()

    tm, em = mask(truth_mask, t, "truth_mask"), mask(est_mask, e, "est_mask")
    return float(c), float(p), batch, [(t[b][tm[b]], e[b][em[b]]) for b in range(t.shape[0])]


def _one_on_one(truth: Tensor, est: Tensor, *masks) -> np.ndarray | None:
    """The distances ``(*B)`` of batches whose every set holds one target and one track (no mask: one target,
    one track throughout, as on Liu's field): their optimal assignment is that pair; ``None`` otherwise."""
    truth, est = torch.as_tensor(truth), torch.as_tensor(est)
    if any(m is not None for m in masks) or truth.dim() < 2 or truth.shape[-2] != 1 or est.shape[-2:] != truth.shape[-2:] \
            or est.shape[:-2] != truth.shape[:-2]:
        return None
    x = truth.detach().to("cpu", torch.float64).numpy()[..., 0, :]
    y = est.detach().to("cpu", torch.float64).numpy()[..., 0, :]
    return np.sqrt(((x - y) ** 2).sum(-1))


def _distances(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.sqrt(((x[:, None, :] - y[None, :, :]) ** 2).sum(-1))


def _cut_assignment(x: np.ndarray, y: np.ndarray, c: float, p: float) -> np.ndarray:
    """The distances of the pairs of an assignment minimising :math:`\\sum \\min(d, c)^p` over the
    assignments of all of the smaller set (each pair's true distance; empty when either set is)."""
    if len(x) == 0 or len(y) == 0:
        return np.zeros(0)
    d = _distances(x, y)
    rows, cols = linear_sum_assignment(np.minimum(d, c) ** p)
    return d[rows, cols]


def gospa(truth: Tensor, est: Tensor, c: float, p: float = 2.0, *, truth_mask: Tensor | None = None,
          est_mask: Tensor | None = None) -> dict[str, Tensor]:
    r"""GOSPA with :math:`\alpha = 2` (Rahmathullah, García-Fernández, Svensson 2017):

    .. math:: d_p^{(c,2)}(X, Y) = \Big(\min_{\gamma} \sum_{(i,j) \in \gamma} d(x_i, y_j)^p
              + \tfrac{c^p}{2}\,(|X| + |Y| - 2|\gamma|)\Big)^{1/p}

    over the assignments :math:`\gamma` of pairs with :math:`d < c`. The three parts are the terms inside
    the bracket (units of distance to the power ``p``; they add up to ``gospa ** p``): ``gospa_loc`` the
    assigned pairs' :math:`d^p`, ``gospa_missed`` :math:`\tfrac{c^p}{2}` per true target left unassigned
    (missed), ``gospa_false`` :math:`\tfrac{c^p}{2}` per estimate left unassigned (false). A pair at
    :math:`d \ge c` costs the same as one missed target plus one false estimate and is counted as such.

    Args:
        truth: ``(*B, N, d)``; est: ``(*B, M, d)``; c: the cut-off (> 0); p: the order (>= 1);
        truth_mask, est_mask: ``(*B, N)``, ``(*B, M)`` presence masks (default: all present).
    Returns:
        ``{"gospa", "gospa_loc", "gospa_missed", "gospa_false"}``, each ``(*B)`` float64.
    """
    one = _one_on_one(truth, est, truth_mask, est_mask)
    if one is not None:  # one pair per set, batched: the loop's terms
        c, p = _order(c, p)
        batch, d = one.shape, one.reshape(-1)
        near, half = d < c, c**p / 2
        out = np.zeros((d.size, 4))
        out[:, 1] = np.where(near, d**p, 0.0)
        out[:, 2] = out[:, 3] = np.where(near, 0.0, half)
        out[:, 0] = out[:, 1:].sum(-1) ** (1 / p)
        sets = []
    else:
        c, p, batch, sets = _sets(truth, est, c, p, truth_mask, est_mask)
        out = np.zeros((len(sets), 4))
    for b, (x, y) in enumerate(sets):
        d = _cut_assignment(x, y, c, p)
        near = d[d < c]
        loc = float((near**p).sum())
        half = c**p / 2
        out[b] = 0.0, loc, half * (len(x) - len(near)), half * (len(y) - len(near))
        out[b, 0] = (out[b, 1:].sum()) ** (1 / p)
    t = torch.from_numpy(out).reshape(*batch, 4)
    return {"gospa": t[..., 0], "gospa_loc": t[..., 1], "gospa_missed": t[..., 2], "gospa_false": t[..., 3]}


def ospa(truth: Tensor, est: Tensor, c: float, p: float = 2.0, *, truth_mask: Tensor | None = None,
         est_mask: Tensor | None = None) -> dict[str, Tensor]:
    r"""OSPA (Schuhmacher, Vo, Vo 2008): for :math:`|X| = m \le |Y| = n` (symmetric),

    .. math:: \bar d_p^{(c)}(X, Y) = \Big(\frac1n \Big(\min_\pi \sum_{i=1}^m d^{(c)}(x_i, y_{\pi(i)})^p
              + c^p (n - m)\Big)\Big)^{1/p}, \quad d^{(c)} = \min(d, c),

    0 when both sets are empty. Its parts (their p-th powers add up to ``ospa ** p``): ``ospa_loc``
    :math:`(\frac1n \min_\pi \sum d^{(c)p})^{1/p}` and ``ospa_card`` :math:`(\frac1n c^p (n-m))^{1/p}`.

    Args and shapes as :func:`gospa`. Returns ``{"ospa", "ospa_loc", "ospa_card"}``, each ``(*B)`` float64.
    """
    one = _one_on_one(truth, est, truth_mask, est_mask)
    if one is not None:  # one pair per set, batched: n = m = 1, no cardinality term
        c, p = _order(c, p)
        batch, loc = one.shape, np.minimum(one.reshape(-1), c) ** p / 1
        out = np.zeros((loc.size, 3))
        out[:, 0] = out[:, 1] = loc ** (1 / p)  # the cardinality term is 0
        sets = []
    else:
        c, p, batch, sets = _sets(truth, est, c, p, truth_mask, est_mask)
        out = np.zeros((len(sets), 3))
    for b, (x, y) in enumerate(sets):
        n, m = max(len(x), len(y)), min(len(x), len(y))
        if n == 0:
            continue
        loc = float((np.minimum(_cut_assignment(x, y, c, p), c) ** p).sum()) / n
        card = c**p * (n - m) / n
        out[b] = (loc + card) ** (1 / p), loc ** (1 / p), card ** (1 / p)
    t = torch.from_numpy(out).reshape(*batch, 3)
    return {"ospa": t[..., 0], "ospa_loc": t[..., 1], "ospa_card": t[..., 2]}


def match_tracks(truth: Tensor, est: Tensor, threshold: float, *, truth_mask: Tensor | None = None,
                 est_mask: Tensor | None = None) -> Tensor:
    r"""The per-step assignment of estimated tracks to true targets, CLEAR-MOT style (Bernardin and
    Stiefelhagen 2008): at each step a correspondence of the previous step is kept while both are present and
    their distance is below ``threshold``; the remaining targets and tracks are then paired by an optimal
    assignment of their distances, pairs at or beyond ``threshold`` left unpaired.

    Args:
        truth: ``(T, N, d)`` (slot ``n`` is true target ``n`` at every step); est: ``(T, M, d)`` (slot ``m`` is
        track ``m`` at every step); threshold: > 0; masks ``(T, N)``, ``(T, M)``: present (default: all).
    Returns:
        ``(T, N)`` int64: the track matched to each target at each step, -1 where none is.
    """
    check_positive("threshold", threshold)
    truth, est = torch.as_tensor(truth), torch.as_tensor(est)
    if truth.dim() != 3 or est.dim() != 3 or truth.shape[0] != est.shape[0] or truth.shape[-1] != est.shape[-1]:
        raise ConfigError(f"truth {tuple(truth.shape)} and est {tuple(est.shape)} must be (T, N, d) and (T, M, d)")
    steps, n_true = truth.shape[:2]
    x = truth.detach().to("cpu", torch.float64).numpy()
    y = est.detach().to("cpu", torch.float64).numpy()
    tm = np.ones(x.shape[:2], bool) if truth_mask is None else torch.as_tensor(truth_mask).cpu().bool().numpy()
    em = np.ones(y.shape[:2], bool) if est_mask is None else torch.as_tensor(est_mask).cpu().bool().numpy()
    if tm.shape != x.shape[:2] or em.shape != y.shape[:2]:
        raise ConfigError(f"truth_mask {tm.shape} and est_mask {em.shape} must be {x.shape[:2]} and {y.shape[:2]}")
    if n_true == 1 and y.shape[1] == 1:  # one target, one track: paired wherever both are present and near
        d = np.sqrt(((x[:, 0] - y[:, 0]) ** 2).sum(-1))
        return torch.from_numpy(np.where(tm[:, 0] & em[:, 0] & (d < threshold), 0, -1).astype(np.int64)[:, None])
    match = np.full((steps, n_true), -1, dtype=np.int64)
    for t in range(steps):
        d = _distances(x[t], y[t])
        ok = tm[t][:, None] & em[t][None, :] & (d < threshold)
        taken_t, taken_e = np.zeros(x.shape[1], bool), np.zeros(y.shape[1], bool)
        if t > 0:
            for i in range(n_true):
                j = match[t - 1, i]
                if j >= 0 and ok[i, j]:
                    match[t, i], taken_t[i], taken_e[j] = j, True, True
        ok &= ~taken_t[:, None] & ~taken_e[None, :]
        rows_free, cols_free = np.flatnonzero(ok.any(1)), np.flatnonzero(ok.any(0))
        if len(rows_free) and len(cols_free):
            sub = d[np.ix_(rows_free, cols_free)]
            big = threshold * (len(rows_free) + len(cols_free) + 1)  # never better than leaving a pair out
            cost = np.where(ok[np.ix_(rows_free, cols_free)], sub, big)
            r, k = linear_sum_assignment(cost)
            keep = cost[r, k] < threshold
            match[t, rows_free[r[keep]]] = cols_free[k[keep]]
    return torch.from_numpy(match)


def identity_metrics(truth: Tensor, est: Tensor, threshold: float, *, truth_mask: Tensor | None = None,
                     est_mask: Tensor | None = None) -> dict[str, Tensor]:
    r"""Identity switches and track fragmentations over a sequence, from :func:`match_tracks`'s assignment.

    Conventions (those of CLEAR MOT and of py-motmetrics):

    * an **identity switch** is counted for a target at a step where it is matched to a track other than the
      last track it was matched to (at any earlier step, gaps in between included);
    * a **fragmentation** is counted for a target at each step where it goes from matched to unmatched while
      present, between its first and its last matched step (a track that is lost and picked up again; a
      target that is never matched again after a loss is not fragmented by it).

    Also ``matches``, ``misses`` (present targets unmatched) and ``false_tracks`` (present tracks unmatched),
    summed over steps and targets / tracks.

    Args:
        truth: ``(*B, T, N, d)``; est: ``(*B, T, M, d)``; threshold: the match distance (> 0); masks
        ``(*B, T, N)``, ``(*B, T, M)`` (default: all present).
    Returns:
        ``{"id_switches", "fragmentations", "matches", "misses", "false_tracks"}``, each ``(*B)`` int64.
    """
    truth, est = torch.as_tensor(truth), torch.as_tensor(est)
    if truth.dim() < 3 or est.dim() < 3 or truth.shape[:-2] != est.shape[:-2]:
        raise ConfigError(f"truth {tuple(truth.shape)} and est {tuple(est.shape)} must be (*B, T, N, d) and (*B, T, M, d)")
    batch = truth.shape[:-3]
    nb = math.prod(batch)
    xt, ye = truth.reshape(nb, *truth.shape[-3:]), est.reshape(nb, *est.shape[-3:])
    tms = None if truth_mask is None else torch.as_tensor(truth_mask).reshape(nb, *truth.shape[-3:-1])
    ems = None if est_mask is None else torch.as_tensor(est_mask).reshape(nb, *est.shape[-3:-1])
    out = np.zeros((xt.shape[0], 5), dtype=np.int64)
    for b in range(xt.shape[0]):
        tm = torch.ones(xt.shape[1:3], dtype=torch.bool) if tms is None else tms[b].bool()
        em = torch.ones(ye.shape[1:3], dtype=torch.bool) if ems is None else ems[b].bool()
        match = match_tracks(xt[b], ye[b], threshold, truth_mask=tm, est_mask=em).numpy()
        tmn = tm.cpu().numpy()
        switches = frags = 0
        for i in range(match.shape[1]):
            col, last = match[:, i], -1
            for j in col:
                if j >= 0:
                    switches += int(last >= 0 and j != last)
                    last = j
            hit = np.flatnonzero(col >= 0)
            if len(hit):
                span = slice(hit[0], hit[-1] + 1)
                matched = col[span] >= 0
                present = tmn[span, i]
                # steps where the target is present, in order: a fragment ends at a matched -> unmatched change
                seq = matched[present]
                frags += int((seq[:-1] & ~seq[1:]).sum())
        n_match = int((match >= 0).sum())
        out[b] = switches, frags, n_match, int(tmn.sum()) - n_match, int(em.sum()) - n_match
    t = torch.from_numpy(out).reshape(*batch, 5)
    keys = ("id_switches", "fragmentations", "matches", "misses", "false_tracks")
    return {k: t[..., i] for i, k in enumerate(keys)}


#: the default cut-off ``c`` (m) of GOSPA and OSPA and the match distance of the identity metrics
#: (:func:`tracking_metrics`): a track further than this from a target is not its; the matrix takes the scenario's
#: (``ScenarioSpec.match_distance``)
MATRIX_CUTOFF = 2.0
#: the order ``p`` of GOSPA and OSPA in the matrix's rows
MATRIX_ORDER = 2.0


def present(points: Tensor) -> Tensor:
    """Which slots of a padded set hold a point: ``(..., d) -> (...)`` bool, False where a coordinate is ``NaN`` (an
    absent target or track)."""
    return ~torch.as_tensor(points).isnan().any(-1)


def matched_order(est: Tensor, truth: Tensor, c: float = MATRIX_CUTOFF) -> Tensor:
    """The track matched to each target over a whole episode, ``(*N, B, A)`` int64: per reporting node and
    episode, the optimal assignment (SciPy's) of tracks to targets minimising the summed squared distances over the
    steps ``1..K``. ``est (*N, B, K+1, M, 2)`` (``M >= A``), ``truth (B, K+1, A, 2)``; with absent targets or tracks
    (``NaN``, :func:`present`) a step adds the squared distance where both are present, ``c`` squared (the
    scenario's match distance) where the target is and the track is not, nothing where the target is absent."""
    e = est.detach().to("cpu", torch.float64)
    x = truth.detach().to("cpu", torch.float64)
    sq = ((x[:, 1:, :, None] - e[..., 1:, None, :, :]) ** 2).sum(-1)  # (*N, B, K, A, M)
    if bool(sq.isnan().any()):  # absent targets or tracks (NaN): a present target without the track costs c^2
        tp = present(x[:, 1:])[:, :, :, None]  # (B, K, A, 1)
        ep = present(e[..., 1:, :, :])[..., None, :]  # (*N, B, K, 1, M)
        sq = torch.where(tp & ep, sq.nan_to_num(0.0), torch.where(tp, float(c) ** 2, 0.0))
    cost = sq.sum(-3)  # (*N, B, A, M)
    flat = cost.reshape(-1, *cost.shape[-2:]).numpy()
    out = np.zeros((flat.shape[0], cost.shape[-2]), dtype=np.int64)
    for i, c in enumerate(flat):
        rows, cols = linear_sum_assignment(c)
        out[i, rows] = cols
    return torch.from_numpy(out).reshape(*cost.shape[:-1]).to(est.device)


def tracking_metrics(est: Tensor, truth: Tensor, c: float = MATRIX_CUTOFF, p: float = MATRIX_ORDER) -> dict[str, Tensor]:
    """The multi-target metrics of the matrix, per reporting node and episode ``{name: (N, B)}``, over the steps
    ``1..K``: ``gospa`` and its parts ``gospa_loc``, ``gospa_missed``, ``gospa_false`` (:func:`gospa`, their
    means over the steps), ``ospa`` (:func:`ospa`, mean), and the identity errors of the sequence
    (:func:`identity_metrics`, match distance ``c``): ``id_switches``, ``fragmentations``. ``est (N, B, K+1, M,
    2)`` every node's tracks, ``truth (B, K+1, A, 2)``; a ``NaN`` position is an absent target or track (a target
    outside its existence interval, a slot without a confirmed track, :func:`present`): the sets then vary in
    cardinality from step to step."""
    e = est.detach().to("cpu", torch.float64)[:, :, 1:]
    x = truth.detach().to("cpu", torch.float64)[:, 1:].expand(e.shape[0], *truth.shape[:1], truth.shape[1] - 1,
                                                            *truth.shape[2:])
    masks = {}
    if bool(e.isnan().any() or x.isnan().any()):  # sets of varying cardinality: NaN = absent (births, deaths)
        masks = dict(truth_mask=present(x), est_mask=present(e))
        x, e = x.nan_to_num(0.0), e.nan_to_num(0.0)
    g = gospa(x, e, c, p, **masks)
    o = ospa(x, e, c, p, **masks)
    ids = identity_metrics(x, e, c, **masks)
    out = {k: v.mean(-1) for k, v in g.items()}
    out["ospa"] = o["ospa"].mean(-1)
    out["id_switches"] = ids["id_switches"].to(torch.float64)
    out["fragmentations"] = ids["fragmentations"].to(torch.float64)
    return out


def matched_position_metrics(mean: Tensor, cov: Tensor | None, truth: Tensor, c: float = MATRIX_CUTOFF
                             ) -> dict[str, Tensor]:
    r"""``rmse``, ``pos_err`` and (with ``cov``) ``nees_pos`` of the track matched to each target over the episode
    (:func:`matched_order`), per reporting node and episode ``{name: (N, B)}``, over the steps ``1..K`` and the
    (step, target) pairs where both the target and its matched track are present (a ``NaN`` position is absent,
    :func:`present`): what :func:`dslearn.metrics.positions.position_metrics` computes on the matched tracks, for sets
    of varying cardinality (births and deaths); ``nees_pos`` is the mean over those steps of
    :math:`\sum_a e^T P^{-1} e / (2 n_t)`, ``n_t`` the pairs present at the step. ``NaN`` where a node never holds a
    matched track. ``mean (N, B, K+1, M, 2)``, ``cov (N, B, K+1, M, 2, 2)`` or None, ``truth (B, K+1, A, 2)``."""
    idx = matched_order(mean, truth, c)  # (N, B, A)
    steps = mean.shape[2]
    gi = idx[:, :, None, :, None].expand(-1, -1, steps, -1, 2).to(mean.device)
    m = mean.gather(-2, gi)[:, :, 1:].to(torch.float64)  # (N, B, K, A, 2)
    x = truth[:, 1:].unsqueeze(0).to(m)
    both = present(m) & present(x)  # (N, B, K, A)
    err = (m - x).nan_to_num(0.0)
    sq = err.pow(2).sum(-1) * both
    n = both.sum((-1, -2)).to(torch.float64)
    out = {"rmse": (sq.sum((-1, -2)) / n).sqrt(), "pos_err": (sq.sqrt() * both).sum((-1, -2)) / n}
    if cov is not None:
        c = cov.gather(-3, gi.unsqueeze(-1).expand(*gi.shape, 2))[:, :, 1:].to(torch.float64)
        c = torch.where(both[..., None, None], c, torch.eye(2, dtype=torch.float64))
        e = err.unsqueeze(-1)
        d2 = (e.transpose(-1, -2) @ torch.linalg.solve(c, e)).squeeze(-1).squeeze(-1) * both  # (N, B, K, A)
        nt = both.sum(-1)  # (N, B, K)
        per_step = d2.sum(-1) / (2 * nt.clamp(min=1))
        out["nees_pos"] = (per_step * (nt > 0)).sum(-1) / (nt > 0).sum(-1)
    return out
