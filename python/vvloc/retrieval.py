"""Exact descriptor retrieval: :class:`DescriptorIndex` (top-K and radius queries by L2 distance).

A thin validating wrapper around the Rust ``vvloc._core.DescriptorIndex`` (DESIGN.md §3
"Retrieval", §4). Distances are L2 distances (not squared) in float32, computed as
``sqrt(max(0, ‖q‖² + ‖x‖² − 2 q·x))`` with the stored norms (normalisation is not assumed).
Top-K rows are sorted by distance ascending, ties broken by the lower map index; radius queries
return every entry with distance ``< r`` as CSR arrays, each query's hits sorted the same way.

Storage ``dtype``: ``"float32"`` scans the float32 map (when d >= 64, single queries test the
leading d/8 dimensions of each block of rows first and skip the rest when a rigorous lower
bound already rules the whole block out); ``"float16"`` and ``"bfloat16"`` scan a compressed
copy (half the bytes per single query), ``"int8"`` a copy quantised symmetrically per dimension
(a quarter of the bytes; the query is quantised with the same per-dimension scales), and
re-score a provably sufficient shortlist (every row within the approximate k-th distance + 2ε,
ε a per-query bound on the quantisation and rounding error) exactly from the float32
originals, which the index keeps (1.5× resp. 1.25× the float32 memory): their results are
identical to ``"float32"``. The compressed copy serves single queries and batches of fewer
than 8; batches of 8 or more (compute-bound) and, when d >= 64, every radius query (the
early-abandoning float32 scan reads fewer bytes) scan the float32 originals for every dtype.

The expansion suits descriptors spread around the origin, as the network's unit-norm ones are
(its float32 error, about 2⁻²³·(‖q‖² + ‖x‖²), is 1e-7 of their distances). It cannot order
descriptors that share a large offset (a spread of 1e-3 of their norm is lost to cancellation)
or whose squares underflow float32 (norms below about 1e-15): building or extending an index
with such rows warns (:data:`CONDITIONING`); subtract their mean or scale them first, which
leaves the order of L2 distances as it was.

Loop closure excludes temporal neighbours with an :class:`Exclusion`: each map entry has a group
id (e.g. a session; default 0) and a sequence number (default: its index in the map).
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from vvloc import _core
from vvloc._io import atomic_write
from vvloc.kernels import _as_f32, _c_array, _positive_float, _positive_int

DTYPES = ("float32", "float16", "bfloat16", "int8")

#: Rows whose mean squared spread about their mean is below this share of their largest
#: squared norm, or whose largest norm is below :data:`TINY_NORM`, warn (module docstring).
CONDITIONING = 1e-5
TINY_NORM = 1e-15


def _check_conditioning(rows: npt.NDArray[np.float32], name: str) -> None:
    """Warn (``UserWarning``) when the float32 distance expansion cannot order ``rows``
    (N, d): a large shared offset or norms whose squares underflow (module docstring)."""
    n = rows.shape[0]
    if n < 2:
        return
    step = max(1, (1 << 20) // rows.shape[1])

    def chunks() -> Any:  # float64 chunks of 8 MiB, one at a time: no copy of the map
        return (rows[i : i + step].astype(np.float64) for i in range(0, n, step))

    top = max(float((c * c).sum(axis=1).max()) for c in chunks())
    if top == 0.0:
        return
    mean = sum(c.sum(axis=0) for c in chunks()) / n
    spread = sum(float(((c - mean) ** 2).sum()) for c in chunks()) / n
    if spread == 0.0:
        return  # one descriptor repeated: every distance ties, whatever the rounding
    if np.sqrt(top) < TINY_NORM:
        why = f"their norms are below {TINY_NORM:g} (their float32 squares underflow)"
    elif spread < CONDITIONING * top:
        why = (
            f"they share an offset far larger than their spread (mean squared spread "
            f"{spread:.3g}, largest squared norm {top:.3g})"
        )
    else:
        return
    warnings.warn(
        f"{name}: the index's float32 distances ‖q‖² + ‖x‖² − 2q·x cannot order these rows: "
        f"{why}; subtract their mean (and scale them) before indexing: L2 distances keep "
        "their order",
        UserWarning,
        stacklevel=3,
    )


def _as_i64(x: Any, name: str, n: int) -> npt.NDArray[np.int64]:
    if hasattr(x, "detach") and hasattr(x, "cpu"):
        x = x.detach().cpu().numpy()
    arr = np.asarray(x)
    if arr.ndim == 0 and n >= 0:
        arr = np.full(n, arr)
    if not np.issubdtype(arr.dtype, np.integer):
        raise TypeError(f"{name}: expected an integer array ({n},), got dtype {arr.dtype}")
    if arr.shape != (n,):
        raise ValueError(f"{name}: expected shape ({n},), got {arr.shape}")
    if arr.dtype.kind == "u" and arr.size and arr.max() > np.iinfo(np.int64).max:
        raise ValueError(f"{name}: values must fit in int64, got {arr.max()}")
    return _c_array(arr, np.int64)


@dataclass(frozen=True)
class Exclusion:
    """Which map entries a query may not return.

    Entry ``i`` is excluded for query ``q`` when ``map_groups[i] == groups[q]`` and either
    ``whole_group`` is true or ``|map_seqs[i] - seqs[q]| <= window``.

    Attributes:
        groups: group id of each query, int (nq,) (a scalar applies to all queries).
        seqs: sequence number of each query, int (nq,).
        window: half-width of the excluded sequence window, int >= 0.
        whole_group: exclude every entry of the query's group.
    """

    groups: Any
    seqs: Any
    window: int = 0
    whole_group: bool = False


def _matrix(x: Any, name: str, dim: int | None) -> npt.NDArray[np.float32]:
    arr = _as_f32(x, name, 2, "(n, d)")
    if dim is not None and arr.shape[1] != dim:
        raise ValueError(f"{name}: expected shape (n, {dim}), got {arr.shape}")
    return arr


def _queries(x: Any, dim: int) -> npt.NDArray[np.float32]:
    arr = _as_f32(x, "queries", (1, 2), "(nq, d) or (d,)")
    if arr.ndim == 1:
        arr = arr[None, :]
    if arr.shape[1] != dim:
        raise ValueError(f"queries: expected shape (nq, {dim}), got {arr.shape}")
    return arr


def _exclusion(ex: Exclusion | None, nq: int) -> tuple[Any, Any, int, bool] | None:
    if ex is None:
        return None
    if not isinstance(ex, Exclusion):
        raise TypeError(f"exclude: expected a vvloc.Exclusion or None, got {type(ex).__name__}")
    window = _positive_int(ex.window, "exclude.window", minimum=0)
    if not isinstance(ex.whole_group, (bool, np.bool_)):  # bool("no") would be True
        raise TypeError(
            f"exclude.whole_group: expected a bool, got {type(ex.whole_group).__name__}"
        )
    return (
        _as_i64(ex.groups, "exclude.groups", nq),
        _as_i64(ex.seqs, "exclude.seqs", nq),
        window,
        bool(ex.whole_group),
    )


class DescriptorIndex:
    """Exact L2 nearest-neighbour index over N descriptors of dimension d (Rust, parallel).

    Args:
        descriptors: float array (N, d) (numpy or torch; converted to C-contiguous float32,
            must be finite). N may be 0.
        dtype: storage of the scanned copy, ``"float32"``, ``"float16"``, ``"bfloat16"`` or
            ``"int8"`` (d ≤ 65536).
        groups: group id per entry, int (N,); default 0.
        seqs: sequence number per entry, int (N,); default the entry index.

    Thread-safe: queries from several Python threads run concurrently with the GIL released.
    """

    def __init__(
        self,
        descriptors: Any,
        dtype: str = "float32",
        groups: Any = None,
        seqs: Any = None,
        *,
        _inner: _core.DescriptorIndex | None = None,
    ) -> None:
        if _inner is not None:
            self._inner = _inner
            return
        if dtype not in DTYPES:
            raise ValueError(f"dtype: expected one of {DTYPES}, got {dtype!r}")
        rows = _matrix(descriptors, "descriptors", None)
        if rows.shape[1] < 1:
            raise ValueError(f"descriptors: expected shape (N, d) with d >= 1, got {rows.shape}")
        n = rows.shape[0]
        g = None if groups is None else _as_i64(groups, "groups", n)
        s = None if seqs is None else _as_i64(seqs, "seqs", n)
        _check_conditioning(rows, "descriptors")
        self._inner = _core.DescriptorIndex(rows, dtype, g, s)

    def add(self, descriptors: Any, groups: Any = None, seqs: Any = None) -> None:
        """Append descriptors (n, d); ``groups`` default 0, ``seqs`` default their map index."""
        rows = _matrix(descriptors, "descriptors", self.dim)
        n = rows.shape[0]
        g = None if groups is None else _as_i64(groups, "groups", n)
        s = None if seqs is None else _as_i64(seqs, "seqs", n)
        _check_conditioning(rows, "descriptors")
        self._inner.add(rows, g, s)

    def topk(
        self, queries: Any, k: int, exclude: Exclusion | None = None
    ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]:
        """The ``k`` nearest entries of each query.

        Args:
            queries: float array (nq, d) (or (d,) for one query).
            k: number of neighbours, int >= 1 (may exceed N).
            exclude: optional :class:`Exclusion` (temporal neighbours).

        Returns:
            ``(indices int64 (nq, k), distances float32 (nq, k))``, sorted by distance then
            index; when fewer than ``k`` entries are eligible the row is padded with index -1
            and distance +inf.
        """
        q = _queries(queries, self.dim)
        k = _positive_int(k, "k")
        return self._inner.topk(q, k, _exclusion(exclude, q.shape[0]))

    def radius(
        self, queries: Any, r: float, exclude: Exclusion | None = None
    ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.float32]]:
        """Every entry at L2 distance ``< r`` of each query, in CSR form.

        Args:
            queries: float array (nq, d) (or (d,) for one query), the stored descriptors' units.
            r: radius, a finite float in [1.4e-45, 3.4e38] (what float32 holds). Distances are
                float32; ``r`` is rounded *up* to float32, so that ``distance < r`` holds for
                the real ``r`` (rounding to nearest could drop a distance just below it).
            exclude: optional :class:`Exclusion` (temporal neighbours).

        Returns:
            ``(offsets int64 (nq + 1,), indices int64 (M,), distances float32 (M,))``: query
            ``q``'s hits are ``indices[offsets[q]:offsets[q + 1]]``, sorted by distance then
            index.
        """
        q = _queries(queries, self.dim)
        r = _positive_float(r, "r")
        f32 = np.finfo(np.float32)
        if not float(f32.smallest_subnormal) <= r <= float(f32.max):  # compared in float32
            raise ValueError(f"r: expected a radius float32 can hold (1e-45 .. 3.4e38), got {r}")
        r32 = np.float32(r)
        if float(r32) < r:  # float32 distances d < r  ⇔  d < r rounded up
            r32 = np.nextafter(r32, np.float32(np.inf))
        return self._inner.radius(q, float(r32), _exclusion(exclude, q.shape[0]))

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the index atomically to ``path`` (format: ``vvloc_core::retrieval::format``),
        as every vvloc file is written (:class:`vvloc._io.AtomicPath`): a temporary sibling
        renamed over ``path`` once complete, an existing file's mode kept, a symbolic link's
        target replaced (the link kept), a device or pipe written into, never renamed over.
        The destination is checked before the index is serialised; the serialised bytes are
        held in memory while they are written (about N · d · the storage dtype's bytes)."""
        with atomic_write(path, "wb") as f:
            f.write(self._inner.to_bytes())

    @staticmethod
    def load(path: str | os.PathLike[str]) -> DescriptorIndex:
        """Read an index written by :meth:`save`.

        Raises ``ValueError`` for a truncated, corrupted or foreign file, ``OSError`` when it
        cannot be read.
        """
        return DescriptorIndex(None, _inner=_core.DescriptorIndex.load(os.fspath(path)))

    @property
    def descriptors(self) -> npt.NDArray[np.float32]:
        """A copy of the stored descriptors, float32 (N, d)."""
        return self._inner.descriptors()

    @property
    def groups(self) -> npt.NDArray[np.int64]:
        """Group id of every entry, int64 (N,)."""
        return self._inner.groups()

    @property
    def seqs(self) -> npt.NDArray[np.int64]:
        """Sequence number of every entry, int64 (N,)."""
        return self._inner.seqs()

    def __len__(self) -> int:
        return len(self._inner)

    @property
    def dim(self) -> int:
        """Descriptor dimension d."""
        return self._inner.dim

    @property
    def dtype(self) -> str:
        """Storage of the scanned copy: ``"float32"``, ``"float16"``, ``"bfloat16"``, ``"int8"``."""
        return self._inner.dtype

    def __repr__(self) -> str:
        return f"DescriptorIndex(N={len(self)}, d={self.dim}, dtype={self.dtype!r})"
