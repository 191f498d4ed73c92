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
(a quarter of the bytes; the query is quantised with the same per-dimension scales; a row
added later that outgrows a range widens every range to 1.25× its dimension's largest |x| so
far, so that adding rows one at a time stays linear: up to 1.25× coarser than an index built
at once), and
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
from vvloc._checks import positive_float, positive_int
from vvloc._io import atomic_write, check_readable_file
from vvloc.kernels import _as_f32, _asarray, _c_array

__all__ = [
    "CONDITIONING",
    "DTYPES",
    "TINY_NORM",
    "DescriptorIndex",
    "Exclusion",
]

DTYPES = ("float32", "float16", "bfloat16", "int8")

#: Rows whose mean squared spread about their mean is below this share of their largest
#: squared norm, or whose largest norm is below :data:`TINY_NORM`, warn (module docstring).
CONDITIONING = 1e-5
TINY_NORM = 1e-15


@dataclass(frozen=True)
class _Spread:
    """Running statistics of indexed rows, float64: count ``n``, ``mean`` (d,), ``m2`` =
    Σ‖x − mean‖², ``top`` = the largest ‖x‖²."""

    n: int
    mean: npt.NDArray[np.float64]
    m2: float
    top: float

    @staticmethod
    def of(rows: npt.NDArray[np.float32]) -> _Spread:
        """The statistics of ``rows`` (N, d), two passes over float64 chunks of 8 MiB (no
        float64 copy of the map)."""
        n, d = rows.shape
        step = max(1, (1 << 20) // max(d, 1))

        def chunks() -> Any:
            return (rows[i : i + step].astype(np.float64) for i in range(0, n, step))

        if n == 0:
            return _Spread(0, np.zeros(d), 0.0, 0.0)
        top = max(float((c * c).sum(axis=1).max()) for c in chunks())
        mean = sum(c.sum(axis=0) for c in chunks()) / n
        m2 = sum(float(((c - mean) ** 2).sum()) for c in chunks())
        return _Spread(n, mean, m2, top)

    def merged(self, other: _Spread) -> _Spread:
        """The statistics of both sets of rows (Chan et al.'s pairwise update, stable where
        Σ‖x‖²/n − ‖mean‖² would cancel)."""
        if self.n == 0 or other.n == 0:
            return other if self.n == 0 else self
        n = self.n + other.n
        delta = other.mean - self.mean
        mean = self.mean + delta * (other.n / n)
        m2 = self.m2 + other.m2 + float(delta @ delta) * self.n * other.n / n
        return _Spread(n, mean, m2, max(self.top, other.top))

    def problem(self) -> str | None:
        """Why the float32 distance expansion cannot order these rows, or None: a large shared
        offset or norms whose squares underflow (module docstring)."""
        if self.n < 2 or self.top == 0.0 or self.m2 == 0.0:
            return None  # one descriptor (repeated): every distance ties, whatever the rounding
        spread = self.m2 / self.n
        if np.sqrt(self.top) < TINY_NORM:
            return f"their norms are below {TINY_NORM:g} (their float32 squares underflow)"
        if spread < CONDITIONING * self.top:
            return (
                f"they share an offset far larger than their spread (mean squared spread "
                f"{spread:.3g}, largest squared norm {self.top:.3g})"
            )
        return None


def _warn_conditioning(name: str, why: str, what: str = "these rows", stacklevel: int = 4) -> None:
    """The conditioning warning, attributed to the caller ``stacklevel`` - 1 frames up."""
    warnings.warn(
        f"{name}: the index's float32 distances ‖q‖² + ‖x‖² − 2q·x cannot order {what}: "
        f"{why}; subtract their mean (and scale them) before indexing: L2 distances keep "
        "their order",
        UserWarning,
        stacklevel=stacklevel,
    )


def _check_conditioning(rows: npt.NDArray[np.float32], name: str) -> _Spread:
    """Warn (``UserWarning``) when the float32 distance expansion cannot order ``rows``
    (N, d) (:meth:`_Spread.problem`); returns their statistics."""
    spread = _Spread.of(rows)
    why = spread.problem()
    if why is not None:
        _warn_conditioning(name, why)
    return spread


def _as_i64(x: Any, name: str, n: int) -> npt.NDArray[np.int64]:
    if hasattr(x, "detach") and hasattr(x, "cpu"):
        x = x.detach().cpu().numpy()
    arr = _asarray(x, name, f" ({n},)")
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


#: The largest descriptor dimension d an index takes (the Rust core's ``MAX_DIM``).
MAX_DIM = 1 << 20


def _matrix(x: Any, name: str, dim: int | None) -> npt.NDArray[np.float32]:
    shape = getattr(x, "shape", None)  # an array's: refused before a float32 copy is made
    if shape is not None and len(shape) == 2 and int(shape[1]) > MAX_DIM:
        raise ValueError(f"{name}: dimension d must be <= {MAX_DIM}, got shape {tuple(shape)}")
    arr = _as_f32(x, name, 2, "(n, d)")
    if arr.shape[1] > MAX_DIM:
        raise ValueError(f"{name}: dimension d must be <= {MAX_DIM}, got shape {arr.shape}")
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
    window = positive_int(ex.window, "exclude.window", minimum=0)
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


def _path(path: Any) -> str | os.PathLike[str]:
    """``path`` (a str or ``os.PathLike``; bytes decoded as the file system does), or
    ``TypeError`` naming it."""
    if isinstance(path, bytes):
        return os.fsdecode(path)
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path: expected a str or os.PathLike, got {type(path).__name__}")
    return path


class DescriptorIndex:
    """Exact L2 nearest-neighbour index over N descriptors of dimension d (Rust, parallel).

    Args:
        descriptors: float array (N, d) (numpy or torch; converted to C-contiguous float32,
            must be finite). N may be 0; d ≤ :data:`MAX_DIM` (2²⁰).
        dtype: storage of the scanned copy, ``"float32"``, ``"float16"``, ``"bfloat16"`` or
            ``"int8"`` (d ≤ 65536).
        groups: group id per entry, int (N,); default 0.
        seqs: sequence number per entry, int (N,); default the entry index.

    Thread-safe: queries from several Python threads run concurrently with the GIL released;
    ``add`` waits for the queries under way, and queries wait for it. Fork-safe: ``os.fork()``
    waits until no thread is inside a call of any index, so a child (e.g. a DataLoader worker)
    gets each index whole and unlocked.
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
            self._spread: _Spread | None = None  # computed when first needed (add)
            return
        if isinstance(dtype, np.dtype):  # np.dtype("float16") compares equal to "float16"
            dtype = dtype.name
        if not isinstance(dtype, str):
            raise TypeError(f"dtype: expected one of {DTYPES}, got {type(dtype).__name__}")
        if dtype not in DTYPES:
            raise ValueError(f"dtype: expected one of {DTYPES}, got {dtype!r}")
        rows = _matrix(descriptors, "descriptors", None)
        if rows.shape[1] < 1:
            raise ValueError(f"descriptors: expected shape (N, d) with d >= 1, got {rows.shape}")
        n = rows.shape[0]
        g = None if groups is None else _as_i64(groups, "groups", n)
        s = None if seqs is None else _as_i64(seqs, "seqs", n)
        spread = _check_conditioning(rows, "descriptors")
        self._inner = _core.DescriptorIndex(rows, dtype, g, s)
        self._spread = spread

    def add(self, descriptors: Any, groups: Any = None, seqs: Any = None) -> None:
        """Append descriptors (n, d); ``groups`` default 0, ``seqs`` default their map index.

        Warns as the constructor does when the rows added, or the whole index with them,
        cannot be ordered by the float32 distances (an index built one row at a time too)."""
        rows = _matrix(descriptors, "descriptors", self.dim)
        n = rows.shape[0]
        g = None if groups is None else _as_i64(groups, "groups", n)
        s = None if seqs is None else _as_i64(seqs, "seqs", n)
        batch = _check_conditioning(rows, "descriptors")
        if self._spread is None:  # a loaded index: its statistics, once
            self._spread = _Spread.of(self._inner.descriptors())
        before = self._spread
        after = before.merged(batch)
        why = after.problem()
        if why is not None and batch.problem() is None and before.problem() is None:
            _warn_conditioning("descriptors", why, "the index with these rows", stacklevel=3)
        self._inner.add(rows, g, s)
        self._spread = after

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
        k = positive_int(k, "k")
        return self._inner.topk(q, k, _exclusion(exclude, q.shape[0]))

    def radius(
        self, queries: Any, r: float, exclude: Exclusion | None = None
    ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.float32]]:
        """Every entry at L2 distance ``< r`` of each query, in CSR form.

        Args:
            queries: float array (nq, d) (or (d,) for one query), the stored descriptors' units.
            r: radius, a finite float from float32's smallest (≈ 1.4013e-45) to its largest
                (≈ 3.4028e38). Distances are
                float32; ``r`` is rounded *up* to float32, so that ``distance < r`` holds for
                the real ``r`` (rounding to nearest could drop a distance just below it).
            exclude: optional :class:`Exclusion` (temporal neighbours).

        Returns:
            ``(offsets int64 (nq + 1,), indices int64 (M,), distances float32 (M,))``: query
            ``q``'s hits are ``indices[offsets[q]:offsets[q + 1]]``, sorted by distance then
            index.
        """
        q = _queries(queries, self.dim)
        r = positive_float(r, "r")
        f32 = np.finfo(np.float32)
        low, high = float(f32.smallest_subnormal), float(f32.max)  # both taken
        if not low <= r <= high:  # compared in float32
            raise ValueError(
                f"r: expected a radius float32 can hold ({low!r} .. {high!r}), got {r}"
            )
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
        path = _path(path)
        with atomic_write(path, "wb") as f:
            f.write(self._inner.to_bytes())

    @staticmethod
    def load(path: str | os.PathLike[str]) -> DescriptorIndex:
        """Read an index written by :meth:`save`.

        Raises ``FileNotFoundError`` when there is no file at ``path``, ``ValueError`` for a
        truncated, corrupted or foreign file, or one that is not a regular file (a named pipe
        blocked the reader forever), ``OSError`` when it cannot be read.
        """
        path = _path(path)
        if not os.path.lexists(path):  # the Rust reader's error was a bare OSError (os error 2)
            raise FileNotFoundError(f"index file not found: {os.fspath(path)}")
        check_readable_file(path)
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
