r"""Progress bars whose ETA is weighted by the expected cost of each item.

A plain ``tqdm`` bar over training episodes assumes every episode costs the same; an online
exact GP slows down as its data set grows (each of an episode's ``K`` steps solves with the
``n x n`` Cholesky factor of the data so far), so the plain ETA is 2-3x optimistic. Here each
item ``k`` carries a relative cost ``c_k`` and the bar counts cost, not items: after ``j``
items it shows ``done = sum_{k<j} c_k`` of ``total = sum_k c_k``, so tqdm's remaining time
``elapsed * (total - done) / done`` is exact when the real times follow the cost model.

Cost model of one training episode of a GP motion model (:func:`gp_episode_cost`):
``c(n) = 1 + b n + c n^2`` with ``n`` the data points per node before the episode
(``k x K`` after ``k`` episodes of ``K`` steps; capped at the budget of a windowed, inducing
or feature variant, whose per-step cost does not grow past it), fitted to CPU times per episode
(see :data:`GP_COST`). Non-learning models cost 1 per episode.

Bars are shown only when asked for (``progress=true``, the default on a terminal) and never
in non-terminal logs; log lines printed while a bar is shown go through
``tqdm.contrib.logging.logging_redirect_tqdm`` (``dslearn-run`` wraps every run in it), so
they do not break the bar.

Use::

    bar = training_bar(num_episodes, steps, cfg.model, enable=progress, desc="train gp/hybrid")
    for ep in ...:
        ...
        bar.update(1)          # one episode done; the bar advances by that episode's cost
    bar.close()
"""

from __future__ import annotations

import sys
import time
from typing import Any, Callable, Iterable, Iterator, Sequence

#: relative cost per episode of the exact online GP, ``1 + b n + c n^2`` (``n`` = data points per
#: node before the episode). Fitted to the CPU time of 150 training episodes of gp_increment and
#: gp (Yu scenario, 10 nodes, 12 steps, one thread): 0.056 s + 4.0e-5 s n + 8.1e-8 s n^2.
GP_COST = {"b": 7.1e-4, "c": 1.45e-6}


def gp_episode_cost(n: float, b: float = GP_COST["b"], c: float = GP_COST["c"]) -> float:
    """Relative cost of one training episode starting with ``n`` data points per node."""
    return 1.0 + b * n + c * n * n


def _get(cfg: Any, key: str, default=None):
    if cfg is None:
        return default
    if isinstance(cfg, dict):
        return cfg.get(key, default)
    getter = getattr(cfg, "get", None)
    if callable(getter):
        try:
            return getter(key, default)
        except Exception:  # noqa: BLE001
            return default
    return getattr(cfg, key, default)


def data_budget(model_cfg: Any) -> int | None:
    """The points a scalable GP variant keeps (window / inducing / features), ``None`` = all."""
    variant = str(_get(model_cfg, "variant", None) or "exact")
    key = {"window": "window", "sgpr": "inducing", "ssgp": "features"}.get(variant)
    v = _get(model_cfg, key) if key else None
    return int(v) if v is not None else None


def episode_costs(num_episodes: int, steps: int, model_cfg: Any = None, learnable: bool = True) -> list[float]:
    """Relative cost of each training episode ``k = 0..num_episodes-1``."""
    kind = str(_get(model_cfg, "kind", None) or _get(model_cfg, "name", "gp") or "gp")
    if not learnable or not kind.startswith("gp"):
        return [1.0] * int(num_episodes)
    cap = data_budget(model_cfg)
    out = []
    for k in range(int(num_episodes)):
        n = k * int(steps)
        out.append(gp_episode_cost(min(n, cap) if cap is not None else n))
    return out


class CostBar:
    """A tqdm bar over items of known relative cost (shows %, items done, cost-weighted ETA).

    ``clock`` is injectable for tests. With ``enable=False`` nothing is drawn, but the
    bookkeeping (``done``, ``eta_s``) still works."""

    def __init__(self, costs: Sequence[float], desc: str = "", enable: bool = True, unit: str = "episode",
                 file=None, clock: Callable[[], float] = time.perf_counter, position: int | None = None,
                 leave: bool = True) -> None:
        self.costs = [float(c) for c in costs]
        if any(not c > 0 for c in self.costs):
            raise ValueError("every cost must be > 0")
        self.total = float(sum(self.costs))
        self.items = 0
        self.done = 0.0
        self.unit = unit
        self._clock = clock
        self._t0 = clock()
        self._bar = None
        if enable and self.costs:
            from tqdm.auto import tqdm

            self._bar = tqdm(
                total=self.total, desc=desc, file=file or sys.stderr, position=position, leave=leave,
                smoothing=0.0,  # the average rate over the whole run: exact under the cost model
                bar_format="{desc}: {percentage:3.0f}%|{bar}| {postfix} [{elapsed}<{remaining}]",
                postfix=f"0/{len(self.costs)} {unit}s",
            )

    def update(self, n: int = 1) -> None:
        """``n`` more items are done."""
        step = 0.0
        for _ in range(int(n)):
            if self.items < len(self.costs):
                step += self.costs[self.items]
                self.items += 1
        self.done += step
        if self._bar is not None:
            self._bar.set_postfix_str(f"{self.items}/{len(self.costs)} {self.unit}s", refresh=False)
            self._bar.update(step)

    @property
    def elapsed_s(self) -> float:
        return self._clock() - self._t0

    def eta_s(self) -> float | None:
        """Remaining seconds: elapsed time scaled by the remaining share of the cost."""
        if self.done <= 0:
            return None
        return self.elapsed_s * (self.total - self.done) / self.done

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> "CostBar":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def training_bar(num_episodes: int, steps: int, model_cfg: Any = None, enable: bool = True, desc: str = "train",
                 learnable: bool = True, **kw) -> CostBar:
    """The bar of the online-learning phase: one item per training episode, weighted by
    :func:`episode_costs`. ``update(1)`` per episode, as with a plain tqdm bar."""
    return CostBar(episode_costs(num_episodes, steps, model_cfg, learnable), desc=desc, enable=enable and num_episodes > 0,
                   unit="episode", **kw)


def evaluation_bar(checkpoints: Sequence[int], steps: int, model_cfg: Any = None, enable: bool = True, desc: str = "test",
             learnable: bool = True, **kw) -> CostBar:
    """The bar of the test phase: one item per evaluation (after ``k`` training episodes for each
    ``k`` in ``checkpoints``), weighted like a training episode at that data size (the test
    batch's GP predictions solve with the same factor)."""
    kind = str(_get(model_cfg, "kind", None) or _get(model_cfg, "name", "gp") or "gp")
    cap = data_budget(model_cfg)
    costs = []
    for k in checkpoints:
        n = int(k) * int(steps)
        costs.append(gp_episode_cost(min(n, cap) if cap is not None else n) if learnable and kind.startswith("gp") else 1.0)
    return CostBar(costs, desc=desc, enable=enable and bool(costs), unit="evaluation", **kw)


def track(iterable: Iterable, costs: Sequence[float] | None = None, desc: str = "", enable: bool = True,
          unit: str = "item", **kw) -> Iterator:
    """Wrap an iterable: yields its items and advances a :class:`CostBar` after each one
    (``costs`` default: 1 per item, which needs ``len(iterable)``)."""
    items = list(iterable) if costs is None else iterable
    if costs is None:
        costs = [1.0] * len(items)
    bar = CostBar(costs, desc=desc, enable=enable, unit=unit, **kw)
    try:
        for x in items:
            yield x
            bar.update(1)
    finally:
        bar.close()
