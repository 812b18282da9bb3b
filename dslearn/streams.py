r"""Independent random streams per batch entry (per episode, per Monte Carlo run and strategy, ...).

A single ``torch.Generator`` shared by a batch makes every entry's draws depend on the batch size and on
which entries share the batch: the ``i``-th run of a batch of 2 gets different noise from the same run
alone. :class:`Streams` holds one generator per entry of the leading batch dims (``shape``, e.g. ``(R,)``
or ``(R, C)``) and draws ``randn`` / ``rand`` tensors of a larger shape ``(*shape, *rest)`` by drawing
``rest`` from each entry's own generator and stacking. Computation stays vectorised; only the (cheap)
noise draws loop over the entries.

Sampling functions (:mod:`dslearn.sim.scenario`, :mod:`dslearn.filters.rbpf`) take either a plain ``torch.Generator`` (one stream for the
whole tensor) or a :class:`Streams`; :func:`randn` and :func:`rand` dispatch on the type.
Seeds come from :func:`stream_seed`, a hash of the key (e.g. ``(seed, "filter", run, strategy)``), so a
run's streams depend only on its key.
"""

from __future__ import annotations

import hashlib
from typing import Sequence

import torch
from torch import Tensor


def stream_seed(*key) -> int:
    """63-bit seed from a key tuple (BLAKE2b of its ``repr``): distinct keys give unrelated seeds."""
    digest = hashlib.blake2b(repr(tuple(key)).encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") & ((1 << 63) - 1)


class Streams:
    """One generator per entry of the leading batch dims ``shape`` (row-major order).

    Args:
        gens: ``prod(shape)`` generators.
        shape: the batch dims they cover.
    """

    def __init__(self, gens: Sequence[torch.Generator], shape: tuple[int, ...]):
        n = 1
        for s in shape:
            n *= int(s)
        if len(gens) != n:
            raise ValueError(f"Streams: {len(gens)} generators for batch shape {tuple(shape)} ({n} entries)")
        self.gens = list(gens)
        self.shape = tuple(int(s) for s in shape)

    @classmethod
    def from_keys(cls, keys, shape: tuple[int, ...], device="cpu") -> "Streams":
        """Generators seeded by :func:`stream_seed` of each key (``keys``: ``prod(shape)`` tuples, row-major)."""
        gens = [torch.Generator(device=device).manual_seed(stream_seed(*k)) for k in keys]
        return cls(gens, shape)

    def _draw(self, fn, shape, dtype, device) -> Tensor:
        shape = tuple(int(s) for s in shape)
        d = len(self.shape)
        if shape[:d] != self.shape:
            raise ValueError(f"Streams: cannot draw shape {shape} from streams over batch shape {self.shape}")
        rest = shape[d:]
        if not self.gens:  # an empty batch
            return torch.empty(shape, dtype=dtype, device=device)
        parts = [fn(rest, generator=g, dtype=dtype, device=device) for g in self.gens]
        return torch.stack(parts).reshape(shape)

    def randn(self, shape, *, dtype=torch.float64, device="cpu") -> Tensor:
        return self._draw(torch.randn, shape, dtype, device)

    def rand(self, shape, *, dtype=torch.float64, device="cpu") -> Tensor:
        return self._draw(torch.rand, shape, dtype, device)

    def select(self, i: int) -> "Streams":
        """The streams of entry ``i`` of the first batch dim (shares the generator objects)."""
        m = len(self.gens) // self.shape[0]
        return Streams(self.gens[i * m:(i + 1) * m], self.shape[1:])


def randn(shape, gen, *, dtype=torch.float64, device="cpu") -> Tensor:
    """Standard normal draws of ``shape`` from a ``torch.Generator`` or per-entry :class:`Streams`."""
    if isinstance(gen, Streams):
        return gen.randn(shape, dtype=dtype, device=device)
    return torch.randn(*shape, generator=gen, dtype=dtype, device=device)


def rand(shape, gen, *, dtype=torch.float64, device="cpu") -> Tensor:
    """Uniform [0, 1) draws of ``shape`` from a ``torch.Generator`` or per-entry :class:`Streams`."""
    if isinstance(gen, Streams):
        return gen.rand(shape, dtype=dtype, device=device)
    return torch.rand(*shape, generator=gen, dtype=dtype, device=device)
