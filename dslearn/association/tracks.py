r"""Track management for one node: initiation from the detections no track took, confirmation, deletion.

A track's state is a target block ``[px, py, vx, vy]`` and the detections are positions (an observation
model that ``measures_position``). Per step the caller predicts the tracks (its motion model), associates the
detections (an :class:`~dslearn.association.base.Associator`) and hands the result to :meth:`TrackManager.step`,
which keeps the updated tracks, counts hits and misses, deletes and starts tracks:

* ``initiation="two_point"``: a detection left over at one step and one left over at the next within
  ``max_speed * dt`` of it (paired by an optimal assignment of their distances) start a track:
  position the second detection, velocity their difference over ``dt``, covariance
  :math:`\begin{bmatrix} R & R/\Delta t \\ R/\Delta t & 2R/\Delta t^2 \end{bmatrix}` (two-point differencing);
* ``initiation="single_point"``: each left-over detection starts a tentative track (its position, velocity 0 with
  standard deviation ``velocity_std`` per axis, default ``max_speed / 2``);

a tentative track is confirmed once it has been detected at ``confirm_m`` of its first ``confirm_n`` steps (a
two-point track counts its two detections as its first two steps: with ``confirm_m <= 2`` it starts confirmed) and
deleted as soon as it no longer can be; a confirmed track is deleted after ``delete_after`` consecutive missed
steps. A track is detected at a step when
its most probable hypothesis is a detection (:attr:`~dslearn.association.base.Association.assigned`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from torch import Tensor

from dslearn.association.base import DTYPE, Association
from dslearn.errors import ConfigError, check_choice, check_integer, check_positive
from dslearn.models.base import ObservationModel
from dslearn.types import AGENT_DIM


#: the ways a track starts (``tracks.initiation``)
INITIATIONS = ("two_point", "single_point")


def check_track_counts(prefix: str, confirm_m, confirm_n, delete_after) -> None:
    """M-of-N confirmation and deletion counts: integers >= 1 with ``confirm_m <= confirm_n``; a
    :class:`ConfigError` naming ``<prefix><key>`` otherwise."""
    for name, v in (("confirm_m", confirm_m), ("confirm_n", confirm_n), ("delete_after", delete_after)):
        check_integer(f"{prefix}{name}", v, 1)
    if confirm_m > confirm_n:
        raise ConfigError(f"{prefix}confirm_m={confirm_m} must be <= {prefix}confirm_n={confirm_n}")


@dataclass(frozen=True)
class TrackManagerSettings:
    """Track management settings (the ``associator`` slot's ``tracks``), checked when built."""

    initiation: str = "two_point"  #: ``two_point`` or ``single_point``
    confirm_m: int = 2  #: M of M-of-N confirmation
    confirm_n: int = 3  #: N of M-of-N confirmation
    delete_after: int = 3  #: consecutive missed steps that delete a confirmed track
    max_speed: float = 3.0  #: the fastest a target moves (m/s): the two-point pairing distance is ``max_speed * dt``
    dt: float = 1.0  #: the time step (s)
    velocity_std: float | None = None  #: single-point initiation's velocity std per axis (m/s); None: max_speed / 2

    def __post_init__(self):
        check_choice("tracks.initiation", self.initiation, INITIATIONS)
        check_track_counts("tracks.", self.confirm_m, self.confirm_n, self.delete_after)
        check_positive("tracks.max_speed", self.max_speed)
        check_positive("tracks.dt", self.dt)
        if self.velocity_std is not None:
            check_positive("tracks.velocity_std", self.velocity_std)

    @property
    def single_point_velocity_std(self) -> float:
        return self.max_speed / 2 if self.velocity_std is None else float(self.velocity_std)


class TrackManager:
    """The tracks of one node and their bookkeeping. ``mean (T, 4)``, ``cov (T, 4, 4)``, ``ids (T,)`` (unique,
    increasing), ``confirmed (T,)``; :meth:`step` once per time step."""

    def __init__(self, settings: TrackManagerSettings | None = None):
        self.settings = settings or TrackManagerSettings()
        self.mean = torch.zeros(0, AGENT_DIM, dtype=DTYPE)
        self.cov = torch.zeros(0, AGENT_DIM, AGENT_DIM, dtype=DTYPE)
        self.ids = torch.zeros(0, dtype=torch.int64)
        self.confirmed = torch.zeros(0, dtype=torch.bool)
        self.hits = torch.zeros(0, dtype=torch.int64)  #: steps detected since the track started (its first included)
        self.age = torch.zeros(0, dtype=torch.int64)  #: steps since the track started (its first = 1)
        self.missed_run = torch.zeros(0, dtype=torch.int64)  #: consecutive missed steps
        self._pending = torch.zeros(0, 2, dtype=DTYPE)  # last step's left-over detections (two-point)
        self._next_id = 0

    def __len__(self) -> int:
        return int(self.mean.shape[0])

    def _keep(self, keep: Tensor) -> None:
        for name in ("mean", "cov", "ids", "confirmed", "hits", "age", "missed_run"):
            setattr(self, name, getattr(self, name)[keep])

    def _add(self, mean: Tensor, cov: Tensor, confirmed: bool, hits: int) -> None:
        """Start ``K`` tracks that have been detected at each of their first ``hits`` steps."""
        k = mean.shape[0]
        if not k:
            return
        self.mean = torch.cat([self.mean, mean])
        self.cov = torch.cat([self.cov, cov])
        self.ids = torch.cat([self.ids, torch.arange(self._next_id, self._next_id + k)])
        self._next_id += k
        self.confirmed = torch.cat([self.confirmed, torch.full((k,), confirmed)])
        self.hits = torch.cat([self.hits, torch.full((k,), hits)])
        self.age = torch.cat([self.age, torch.full((k,), hits, dtype=torch.int64)])
        self.missed_run = torch.cat([self.missed_run, torch.zeros(k, dtype=torch.int64)])

    def adopt(self, mean: Tensor, cov: Tensor, missed_run: Tensor) -> None:
        """Take ``K`` confirmed tracks from elsewhere (a neighbour's, :mod:`.multitrack`): ``mean (K, 4)``, ``cov
        (K, 4, 4)``, their consecutive missed steps ``missed_run (K,)``; new ids, confirmed."""
        k = len(self)
        self._add(mean.to(DTYPE), cov.to(DTYPE), confirmed=True, hits=self.settings.confirm_m)
        self.missed_run[k:] = torch.as_tensor(missed_run, dtype=torch.int64)

    def step(self, association: Association | None, detections: Tensor, observation: ObservationModel,
             present: Tensor | None = None, hit: Tensor | None = None) -> None:
        """Keep the associated tracks, count, delete and start tracks. ``association``: the associator's result
        on this manager's predicted tracks (None when there are no tracks: every detection is left over);
        ``detections (M, 2)`` positions, ``present (M,)``; ``hit (T,)``: which tracks count as detected at this
        step (default: those whose most probable hypothesis is a detection; on a network: detected by any node
        holding the track, :mod:`.multitrack`)."""
        s = self.settings
        if not observation.measures_position:
            raise ConfigError("track initiation starts tracks from position detections; the observation model "
                              "does not measure positions")
        det = torch.as_tensor(detections).to(DTYPE)
        present = torch.ones(det.shape[0], dtype=torch.bool) if present is None else torch.as_tensor(present).bool()
        if association is None:
            if len(self):
                raise ConfigError(f"an association is needed for the {len(self)} tracks")
            left = present
        else:
            if association.mean.shape[0] != len(self):
                raise ConfigError(f"the association has {association.mean.shape[0]} tracks, the manager {len(self)}")
            self.mean, self.cov = association.mean.to(DTYPE), association.cov.to(DTYPE)
            hit = association.assigned >= 0 if hit is None else torch.as_tensor(hit, dtype=torch.bool)
            self.age = self.age + 1
            self.hits = self.hits + hit.long()
            self.missed_run = torch.where(hit, 0, self.missed_run + 1)
            left = association.unassigned & present
            # confirmation (M of the first N steps) and deletion
            tentative = ~self.confirmed
            self.confirmed = self.confirmed | (tentative & (self.hits >= s.confirm_m) & (self.age <= s.confirm_n))
            hopeless = tentative & ~self.confirmed & (self.age - self.hits > s.confirm_n - s.confirm_m)
            dead = (self.confirmed & (self.missed_run >= s.delete_after)) | hopeless
            self._keep(~dead)
        z = det[left]
        r = observation.noise_cov(torch.zeros(z.shape[0], AGENT_DIM, dtype=DTYPE)).to(DTYPE)  # (K, 2, 2)
        if s.initiation == "single_point":
            vel = torch.eye(2, dtype=DTYPE) * s.single_point_velocity_std ** 2
            cov = torch.zeros(z.shape[0], AGENT_DIM, AGENT_DIM, dtype=DTYPE)
            cov[:, :2, :2], cov[:, 2:, 2:] = r, vel
            mean = torch.cat([z, torch.zeros_like(z)], dim=-1)
            self._add(mean, cov, confirmed=s.confirm_m == 1, hits=1)
            return
        # two-point: pair last step's left-overs with this step's
        prev, self._pending = self._pending, z
        if not prev.shape[0] or not z.shape[0]:
            return
        d = torch.cdist(prev, z).numpy()
        reach = s.max_speed * s.dt
        cost = np.where(d <= reach, d, reach * (d.shape[0] + d.shape[1] + 1))
        rows, cols = linear_sum_assignment(cost)
        ok = d[rows, cols] <= reach
        rows, cols = rows[ok], cols[ok]
        if not len(rows):
            return
        z1, z2, rr = prev[rows], z[cols], r[cols]
        cov = torch.zeros(len(rows), AGENT_DIM, AGENT_DIM, dtype=DTYPE)
        cov[:, :2, :2], cov[:, :2, 2:], cov[:, 2:, :2] = rr, rr / s.dt, rr / s.dt
        cov[:, 2:, 2:] = 2 * rr / s.dt**2
        self._add(torch.cat([z2, (z2 - z1) / s.dt], dim=-1), cov, confirmed=s.confirm_m <= 2, hits=2)
        keep = torch.ones(z.shape[0], dtype=torch.bool)
        keep[torch.from_numpy(cols)] = False
        self._pending = z[keep]
