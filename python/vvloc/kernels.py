"""The one gateway to vvloc's kernels.

Every function validates its inputs (raising ``TypeError``/``ValueError`` that name the argument
and the expected shape/dtype), converts them to C-contiguous float32, and dispatches to the Rust
extension (``backend="rust"``, default) or to the pure-Python reference
(``backend="reference"``, :mod:`vvloc.reference`). Shapes follow DESIGN.md §4; angles are in
radians, lengths in metres, BEVs are channels-last (H, W, C) with row i ↔ x, column j ↔ y.

Limits, the same for both backends: descriptor rows whose squared norm exceeds
:data:`MAX_ROW_SQNORM` (1e37) are refused with ``ValueError`` (float32 Gram products would
overflow); a search stage holds at most :data:`MAX_STAGE_POINTS` hypotheses. An output or work
buffer larger than the machine can allocate raises ``MemoryError`` naming the argument that sets
its size, instead of aborting the process. No Rust panic reaches Python.
"""

from __future__ import annotations

import math
from typing import Any, Literal, NamedTuple

import numpy as np
import numpy.typing as npt

from vvloc import _core
from vvloc._checks import finite_float, positive_float, positive_int

__all__ = [
    "MAX_ROLL_NDIM",
    "MAX_ROW_SQNORM",
    "MAX_STAGE_POINTS",
    "MIN_YAW_BINS",
    "Backend",
    "Rerank",
    "SearchHistory",
    "SearchHypothesis",
    "TranslationSearch",
    "YawEstimate",
    "bev_pad",
    "estimate_yaw",
    "matching_cost",
    "pad_polar",
    "polar_sample",
    "rerank",
    "roll_interp",
    "yaw_costs",
]

Backend = Literal["rust", "reference"]
"""A kernel's implementation: ``"rust"`` (the extension, the default) or ``"reference"`` (the
readable numpy/torch version in :mod:`vvloc.reference`, which the tests hold the kernel to)."""
F32Array = npt.NDArray[np.float32]


def _check_backend(backend: str) -> Backend:
    if backend == "rust":
        return "rust"
    if backend == "reference":
        return "reference"
    raise ValueError(f"backend: expected 'rust' or 'reference', got {backend!r}")


def _numpy(x: Any) -> Any:
    """A torch tensor as a numpy array (moved to the CPU; bfloat16, which numpy lacks, widened
    exactly to float32); anything else as it is."""
    if hasattr(x, "detach") and hasattr(x, "cpu"):  # torch.Tensor, without importing torch
        x = x.detach().cpu()
        if str(x.dtype) == "torch.bfloat16":
            x = x.float()
        x = x.numpy()
    return x


def _asarray(x: Any, name: str, shape_doc: str) -> Any:
    """``np.asarray(x)``, with nested sequences of unequal lengths refused naming ``name``
    (numpy says "setting an array element with a sequence ... inhomogeneous shape")."""
    try:
        return np.asarray(x)
    except ValueError:
        raise ValueError(
            f"{name}: expected a rectangular array{shape_doc}, got nested sequences of unequal "
            "lengths"
        ) from None


def _c_array(arr: Any, dtype: Any) -> Any:
    """``arr`` as a C-contiguous, aligned array of ``dtype`` (copied only when needed): the
    Rust kernels view the memory directly, and ``np.ascontiguousarray`` keeps a misaligned
    buffer (``np.frombuffer(..., offset=1)``) misaligned. numpy calls every empty array
    aligned, whatever its address: an empty one's address is tested too (only an empty one's:
    ``ctypes.data`` costs ~0.9 µs a call, on the kernels' per-query path)."""
    out = np.ascontiguousarray(arr, dtype=dtype)
    aligned = out.flags.aligned and (out.size > 0 or out.ctypes.data % out.dtype.alignment == 0)
    return out if aligned else out.copy()


def _as_f32(
    x: Any,
    name: str,
    ndim: int | tuple[int, ...] | None = None,
    shape_doc: str = "",
    *,
    finite: bool = True,
) -> F32Array:
    """Validate an array argument and return it as C-contiguous float32.

    Accepts numpy arrays, torch tensors (moved to CPU) and nested sequences of real numbers.
    ``ndim`` restricts the number of dimensions; ``shape_doc`` is shown in errors, e.g.
    ``"(H, W, C)"``. Non-finite values are rejected when ``finite`` is true.
    """
    shape_doc = f" {shape_doc}" if shape_doc else ""
    x = _numpy(x)
    if isinstance(x, (str, bytes)) or x is None:
        raise TypeError(f"{name}: expected a float array{shape_doc}, got {type(x).__name__}")
    arr = _asarray(x, name, shape_doc)
    if arr.dtype == object or not (
        np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
    ):
        raise TypeError(
            f"{name}: expected a real-valued (float) array{shape_doc}, got dtype {arr.dtype}"
        )
    if ndim is not None:
        allowed = (ndim,) if isinstance(ndim, int) else ndim
        if arr.ndim not in allowed:
            raise ValueError(
                f"{name}: expected shape{shape_doc} ({' or '.join(map(str, allowed))}-D), "
                f"got shape {arr.shape}"
            )
    if np.issubdtype(arr.dtype, np.floating) and arr.dtype.itemsize > 4:
        # wider than float32: a finite value beyond its range would become inf in the cast
        f32_max = float(np.finfo(np.float32).max)
        with np.errstate(invalid="ignore"):
            a = np.abs(arr)
            too_big = arr.size and bool(((a > f32_max) & (a < np.inf)).any())
        if too_big:
            raise ValueError(
                f"{name}: values beyond float32's range (|x| > {f32_max:.3g}); the kernels "
                "compute in float32"
            )
    out = _c_array(arr, np.float32)
    if finite and out.size and not np.isfinite(out).all():
        raise ValueError(f"{name}: contains non-finite values (NaN or inf)")
    return out


# --- spatial kernels (roll_interp, bev_pad, polar_sample, pad_polar) -------------------------


def _bev(bev: Any, batched: bool = False) -> F32Array:
    """A channels-last BEV (H, W, C) (or (B, H, W, C) when ``batched``) as float32, H, W >= 1."""
    doc = "(H, W, C) or (B, H, W, C)" if batched else "(H, W, C)"
    arr = _as_f32(bev, "bev", (3, 4) if batched else 3, doc)
    if arr.shape[-3] < 1 or arr.shape[-2] < 1:
        raise ValueError(f"bev: expected shape {doc} with H, W >= 1, got shape {arr.shape}")
    return arr


def _translations(translations: Any) -> npt.NDArray[np.float64]:
    """Translations (N, 2) metres as C-contiguous float64 (kept in double: they set fill rows)."""
    # Validated in float64: a float32 copy would overflow huge (valid) shifts.
    translations = _numpy(translations)
    if isinstance(translations, (str, bytes)) or translations is None:
        raise TypeError(f"translations: expected a float array (N, 2), got {type(translations)}")
    probe = _asarray(translations, "translations", " (N, 2)")
    if probe.dtype == object or not (
        np.issubdtype(probe.dtype, np.floating) or np.issubdtype(probe.dtype, np.integer)
    ):
        raise TypeError(f"translations: expected a real-valued array (N, 2), got {probe.dtype}")
    if probe.ndim != 2 or probe.shape[1] != 2:
        raise ValueError(f"translations: expected shape (N, 2), got shape {probe.shape}")
    out = _c_array(probe, np.float64)
    if not np.isfinite(out).all():
        raise ValueError("translations: contains non-finite values (NaN or inf)")
    return out


#: The most dimensions :func:`roll_interp` takes (numpy allows 64; the Rust binding's dynamic
#: arrays hold 32).
MAX_ROLL_NDIM = 32


def roll_interp(x: Any, shift: float, axis: int = 0, backend: Backend = "rust") -> F32Array:
    """Interpolated circular roll of ``x`` by ``shift`` elements along ``axis`` (DESIGN.md §3).

    ``roll(x, s)[i] = x[(i − s) mod n]`` (``torch.roll`` semantics); for real ``s``,
    ``(1 − w)·roll(x, ⌊s⌋) + w·roll(x, ⌊s⌋ + 1)`` with ``w = s − ⌊s⌋`` (continuous in ``s``).
    ``x``: any real array of 1 to :data:`MAX_ROLL_NDIM` dimensions; ``axis`` may be negative.
    Returns float32, same shape.
    """
    backend = _check_backend(backend)
    arr = _as_f32(x, "x")
    if np.ndim(x) == 0:  # checked on the input: ascontiguousarray makes scalars 1-D
        raise ValueError("x: expected an array with at least 1 dimension, got a scalar")
    if arr.ndim > MAX_ROLL_NDIM:  # rust-numpy's dynamic arrays panic beyond it
        raise ValueError(f"x: expected at most {MAX_ROLL_NDIM} dimensions, got {arr.ndim}")
    s = finite_float(shift, "shift")
    if isinstance(axis, bool) or not isinstance(axis, (int, np.integer)):
        raise TypeError(f"axis: expected an int, got {type(axis).__name__}")
    if not -arr.ndim <= int(axis) < arr.ndim:
        raise ValueError(f"axis: expected -{arr.ndim} <= axis < {arr.ndim}, got {axis}")
    ax = int(axis) % arr.ndim
    if backend == "reference":
        from vvloc.reference import spatial as ref

        return ref.roll_interp(arr, s, ax)
    from vvloc import _core

    return _core.roll_interp(arr, s, ax)


def bev_pad(bev: Any, translations: Any, grid_size: float, backend: Backend = "rust") -> F32Array:
    """BEV padding (paper Alg. 1, corrected fill) for N translation hypotheses.

    ``bev``: (H, W, C) BEV, row i ↔ ego x, column j ↔ ego y, cells of ``grid_size`` metres.
    ``translations``: (N, 2) hypothesised target origins (x, y), metres, in this BEV's ego
    frame (the source's; the localizer pads the query's BEV, DESIGN.md §3).
    ``backend``: ``"rust"`` (the kernel) or ``"reference"`` (the readable numpy version).
    Returns (N, H, W, C) float32: the bilinear sample of ``bev`` at (i + x/g, j + y/g), 1 wherever
    a tap with non-zero weight falls outside the grid. Zero shift → unchanged; shifts of a map
    size or more → all ones. Shifts within 1e-6 cells of an integer are snapped to it.
    """
    backend = _check_backend(backend)
    q = _bev(bev)
    t = _translations(translations)
    g = positive_float(grid_size, "grid_size")
    if backend == "reference":
        from vvloc.reference import spatial as ref

        return _reference_output("translations", lambda: ref.bev_pad(q, t, g))
    from vvloc import _core

    return _core.bev_pad(q, t, g)


def _check_polar_radius(bev: F32Array, grid_size: float) -> None:
    """``ValueError`` naming ``grid_size`` when the polar radius min(H, W)·g/2 overflows (the
    Rust kernels' check, made here for both backends)."""
    if not math.isfinite(min(bev.shape[-3], bev.shape[-2]) * grid_size / 2.0):
        raise ValueError(
            f"grid_size: expected the polar radius min(H, W)·g/2 to be finite, got g = {grid_size}"
        )


def _reference_output(arg: str, call: Any) -> Any:
    """``call()`` of a reference kernel, with numpy's refusal to allocate its output (a
    ``MemoryError``, or "array is too big" for a size past the address space) said as the Rust
    backend says it: a ``MemoryError`` naming ``arg``, the argument that sets the size."""
    try:
        return call()
    except MemoryError as e:
        detail = f" ({e})" if str(e) else ""  # Python's own MemoryError says nothing
        raise MemoryError(
            f"{arg}: the result needs more than this machine can allocate{detail}"
        ) from None
    except ValueError as e:
        if "array is too big" not in str(e):
            raise
        raise MemoryError(
            f"{arg}: the result needs an array larger than this machine can allocate ({e})"
        ) from None


def polar_sample(
    bev: Any, num_angles: int, num_radii: int, grid_size: float, backend: Backend = "rust"
) -> F32Array:
    """Polar sampling of a BEV (DESIGN.md §3 polar grid), bilinear, fill 1 outside.

    ``bev``: (H, W, C) or (B, H, W, C). Angle bin k is centred on θ_k = (k + 0.5)·2π/T, measured
    from +y towards +x; radius bin m on r_m = (m + 0.5)·r_max/R, r_max = min(H, W)·g/2 metres.
    A tap outside the grid reads 1 with its bilinear weight (a zero-weight tap contributes
    nothing). Returns (T, R, C) or (B, T, R, C) float32.
    """
    backend = _check_backend(backend)
    q = _bev(bev, batched=True)
    t = positive_int(num_angles, "num_angles")
    r = positive_int(num_radii, "num_radii")
    g = positive_float(grid_size, "grid_size")
    _check_polar_radius(q, g)
    if backend == "reference":
        from vvloc.reference import spatial as ref

        return _reference_output("num_angles", lambda: ref.polar_sample(q, t, r, g))
    from vvloc import _core

    return _core.polar_sample(q, t, r, g)


def pad_polar(
    bev: Any,
    translations: Any,
    num_angles: int,
    num_radii: int,
    grid_size: float,
    backend: Backend = "rust",
) -> F32Array:
    """Fused BEV padding + polar sampling: ``polar_sample(bev_pad(bev, translations, g), T, R, g)``.

    ``bev`` (H, W, C), ``translations`` (N, 2) metres → (N, T, R, C) float32. The Rust kernel never
    materialises the padded maps and agrees with the composition to 1e-5.
    """
    backend = _check_backend(backend)
    q = _bev(bev)
    tr = _translations(translations)
    t = positive_int(num_angles, "num_angles")
    r = positive_int(num_radii, "num_radii")
    g = positive_float(grid_size, "grid_size")
    _check_polar_radius(q, g)
    if backend == "reference":
        from vvloc.reference import spatial as ref

        return _reference_output("num_angles", lambda: ref.pad_polar(q, tr, t, r, g))
    from vvloc import _core

    return _core.pad_polar(q, tr, t, r, g)


# --- matching kernels (matching_cost, yaw_costs, estimate_yaw, rerank, TranslationSearch) ----


class YawEstimate(NamedTuple):
    """Per-pair yaw estimates: ``shift`` s* ∈ [0, T) bins, ``yaw`` φ̂ = 2π·s*/T wrapped to
    (−π, π] radians, ``cost`` c(s*); each (P,) float64."""

    shift: npt.NDArray[np.float64]
    yaw: npt.NDArray[np.float64]
    cost: npt.NDArray[np.float64]


class Rerank(NamedTuple):
    """Re-ranking of K candidates: ``order`` (K,) int64 (cost ascending, ties by lower index);
    ``cost``, ``yaw`` (radians), ``shift`` (bins), each (K,) float64 in *input* order."""

    order: npt.NDArray[np.int64]
    cost: npt.NDArray[np.float64]
    yaw: npt.NDArray[np.float64]
    shift: npt.NDArray[np.float64]


class SearchHypothesis(NamedTuple):
    """One hypothesis of the translation search: metres, metres, radians, cost."""

    x: float
    y: float
    yaw: float
    cost: float


class SearchHistory(NamedTuple):
    """Every evaluated hypothesis: ``xy`` (M, 2) metres, ``yaw`` (M,) radians, ``cost`` (M,),
    ``stage`` (M,) int64."""

    xy: npt.NDArray[np.float64]
    yaw: npt.NDArray[np.float64]
    cost: npt.NDArray[np.float64]
    stage: npt.NDArray[np.int64]


def _f64_vector(x: Any, name: str, n: int) -> npt.NDArray[np.float64]:
    """Validate a finite real vector of length ``n`` and return it as C-contiguous float64."""
    arr = _asarray(_numpy(x), name, f" ({n},)")
    if arr.dtype == object or not (
        np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
    ):
        raise TypeError(f"{name}: expected a real-valued array ({n},), got dtype {arr.dtype}")
    if arr.shape != (n,):
        raise ValueError(f"{name}: expected shape ({n},), got {arr.shape}")
    out = _c_array(arr, np.float64)
    if not np.isfinite(out).all():
        raise ValueError(f"{name}: contains non-finite values (NaN or inf)")
    return out


#: The largest squared norm of a descriptor row the yaw and retrieval kernels take: their
#: float32 Gram products would overflow beyond it (``vvloc_core::cost::MAX_ROW_SQNORM``).
MAX_ROW_SQNORM = 1e37
#: The most hypotheses one search stage may propose (``vvloc_core::search::MAX_STAGE_POINTS``).
MAX_STAGE_POINTS = 100_000_000


def _check_row_norms(x: F32Array, name: str) -> None:
    """``ValueError`` naming ``name`` when a row (last axis) of ``x`` has a squared norm above
    :data:`MAX_ROW_SQNORM` (both backends refuse what float32 arithmetic cannot hold)."""
    c = max(x.shape[-1], 1) if x.ndim else 1
    if x.size == 0 or float(np.abs(x).max()) <= math.sqrt(MAX_ROW_SQNORM / c):
        return
    sq = np.einsum("...c,...c->...", x.astype(np.float64), x.astype(np.float64))
    if float(sq.max()) > MAX_ROW_SQNORM:
        limit = f"{MAX_ROW_SQNORM:.0e}".replace("e+", "e")  # 1e37, as the Rust kernels write it
        raise ValueError(
            f"{name}: values too large: a descriptor row's squared norm exceeds {limit}, "
            "beyond what float32 arithmetic holds (scale the descriptors down)"
        )


def _check_rows(x: F32Array, name: str) -> None:
    """The reference backend's copy of the Rust matching kernels' row check, in its order:
    non-finite values, then rows too large (the Rust backend checks in the kernel, after the
    gateway's shape checks, so both backends name the same fault first)."""
    if x.size and not np.isfinite(x).all():
        raise ValueError(f"{name}: contains non-finite values (NaN or inf)")
    _check_row_norms(x, name)


def _check_pair_norms(s: F32Array, t: F32Array) -> None:
    """:func:`_check_rows` of both sides of a batch of pairs, ``src`` first as in Rust."""
    _check_rows(s, "src")
    _check_rows(t, "tgt")


#: The fewest angle bins a yaw estimate takes: with T = 2 the interpolated roll by s and by
#: 2 − s (= −s) are the same, so every cost curve is symmetric and a minimum off s = 1 has an
#: equally good twin of the opposite yaw (the Rust kernel's ``MIN_YAW_BINS``).
MIN_YAW_BINS = 3


def _pairs(
    src: Any, tgt: Any, *, shared_ok: bool = True, min_bins: int = 2
) -> tuple[F32Array, F32Array]:
    """Validate descriptor pairs: ``src`` (P, T, C) with T >= ``min_bins``; ``tgt`` (P, T, C),
    or (1, T, C) / (T, C) shared by every pair when ``shared_ok``. Returns both as 3-D
    C-contiguous float32.

    Non-finite values are refused later, after the shapes: by the Rust kernels' row check, or
    for the reference backend by its copy, :func:`_check_pair_norms` (testing them here as well
    cost the Rust backend 3 ms per 200 pairs).
    """
    s = _as_f32(src, "src", 3, "(P, T, C)", finite=False)
    t = _as_f32(tgt, "tgt", (2, 3) if shared_ok else 3, "(P, T, C)", finite=False)
    if t.ndim == 2:
        t = t[None]
    p, nt, c = s.shape  # P = 0, an empty batch, passes: its results are empty
    if nt < max(min_bins, 2):
        why = (
            " (with 2 bins, rolling by s and by -s give one curve: a yaw's sign is undetermined)"
            if min_bins > 2
            else ""
        )
        raise ValueError(
            f"src: expected (P, T, C) with T >= {max(min_bins, 2)} angle bins{why}, got {s.shape}"
        )
    if c == 0:
        raise ValueError(f"src: expected (P, T, C) with C >= 1 channels, got {s.shape}")
    if t.shape[1:] != (nt, c) or t.shape[0] not in ((p, 1) if shared_ok else (p,)):
        shapes = [f"({p}, {nt}, {c})"]
        if shared_ok:
            shapes += ([] if p == 1 else [f"(1, {nt}, {c})"]) + [f"({nt}, {c})"]
        want = " or ".join(shapes)
        raise ValueError(f"tgt: expected shape {want} to match src, got {t.shape}")
    return s, t


def matching_cost(a: Any, b: Any, *, backend: Backend = "rust") -> npt.NDArray[np.float64]:
    """Matching cost ``δ(A, B) = (1/T)·Σᵢ ‖Aᵢ − Bᵢ‖₂`` (no shift) of ``a``, ``b`` (..., T, C)
    float → (...) float64. Leading dimensions must be equal; T, C ≥ 1. An empty batch (a
    leading dimension 0) gives an empty result of the leading shape."""
    _check_backend(backend)
    # values are checked after the shapes: by the Rust kernel, or by its copy for the reference
    x = _as_f32(a, "a", None, "(..., T, C)", finite=False)
    y = _as_f32(b, "b", None, "(..., T, C)", finite=False)
    if x.ndim < 2 or x.shape[-2] == 0 or x.shape[-1] == 0:
        raise ValueError(f"a: expected shape (..., T, C) with T, C >= 1, got shape {x.shape}")
    if y.shape != x.shape:
        raise ValueError(f"b: expected shape {x.shape} like a, got {y.shape}")
    lead, (t, c) = x.shape[:-2], x.shape[-2:]
    if backend == "reference":
        _check_rows(x, "a")
        _check_rows(y, "b")
        from vvloc.reference import matching as ref_matching

        return np.asarray(ref_matching.matching_cost(x, y), dtype=np.float64).reshape(lead)
    out = _core.matching_cost(x.reshape(-1, t, c), y.reshape(-1, t, c))
    return out.reshape(lead)


def yaw_costs(src: Any, tgt: Any, *, backend: Backend = "rust") -> npt.NDArray[np.float64]:
    """Yaw cost curves at every integer shift: ``out[p, k] = c_p(k)`` for k = 0..T−1.

    ``src`` (P, T, C), ``tgt`` (P, T, C) or (T, C) shared; float → (P, T) float64 (P = 0, an
    empty batch: (0, T)).
    """
    _check_backend(backend)
    s, t = _pairs(src, tgt)
    if backend == "reference":
        _check_pair_norms(s, t)
        from vvloc.reference import matching as ref_matching

        return ref_matching.yaw_costs(s, t)
    return _core.yaw_costs(s, t)


def estimate_yaw(src: Any, tgt: Any, *, backend: Backend = "rust") -> YawEstimate:
    """Exact global continuous yaw minimum of each pair (DESIGN.md §3 "Yaw").

    ``src`` (P, T, C) source local-view descriptors, ``tgt`` (P, T, C) or (T, C) shared target.
    Returns :class:`YawEstimate` (shift (P,) bins in [0, T), yaw (P,) radians in (−π, π],
    a half turn exactly π; cost (P,) = c(shift) in f64; empty for P = 0). Rust: Gram-based
    exact minimiser (float32 tables prune the shift intervals, the best are re-minimised on
    rows recomputed in float64); a pair the float32 stage cannot resolve, rows whose norms
    span more than 32× (over both descriptors, zero rows aside) or a near-perfect match (an
    approximate cost ≤ 1 % of the rms row norm), is minimised on float64 rows throughout,
    ~5× slower (1.0-1.4 ms of one core a pair at T = 120, C = 256; BENCHMARKS.md); learned
    descriptors have unit rows and take it only for near-identical views. The answer is the
    same for a pair scaled by a power of two (its cost scaled), while its values stay normal
    float32 numbers within the size limit. Between basins whose costs differ by less than
    ~1e-5 of the rms row norm plus the cost, the float32 stage's margin, either may be
    returned: observed, not proven (a fuzz of rows spanning 10⁶ with a large common part: 1
    pair in ~6 400, 6e-6 apart). Reference: dense 0.01-bin scan + refinement. T >= 3
    (:data:`MIN_YAW_BINS`: with 2 bins the yaw's sign is undetermined).
    """
    _check_backend(backend)
    s, t = _pairs(src, tgt, min_bins=MIN_YAW_BINS)
    if backend == "reference":
        _check_pair_norms(s, t)
        from vvloc.reference import matching as ref_matching

        return YawEstimate(*ref_matching.estimate_yaw(s, t))
    return YawEstimate(*_core.estimate_yaw(s, t))


def rerank(src: Any, tgt: Any, *, backend: Backend = "rust") -> Rerank:
    """Re-rank K candidates by matching cost (exact yaw minimum, no padding).

    ``src`` (K, T, C) the K pairs' source local-view descriptors, ``tgt`` (K, T, C) their
    targets, or (T, C) one target shared by all. Returns :class:`Rerank` (order by cost
    ascending, ties by lower index; cost, yaw, shift in input order; all empty for K = 0,
    e.g. when a floor filter left no candidate), each pair's yaw that of
    its target relative to its source (:func:`estimate_yaw`, DESIGN.md §3 "Yaw"). The localizer
    passes the query as the source of every pair and the K candidates as the targets, so its
    yaw is the candidate keyframe's in the query's frame (ξ_{q→m}'s yaw). T >= 3
    (:data:`MIN_YAW_BINS`).
    """
    _check_backend(backend)
    s, t = _pairs(src, tgt, min_bins=MIN_YAW_BINS)
    if backend == "reference":
        _check_pair_norms(s, t)
        from vvloc.reference import matching as ref_matching

        return Rerank(*ref_matching.rerank(s, t))
    return Rerank(*_core.rerank(s, t))


class TranslationSearch:
    """Coarse-to-fine translation hypothesis search (the paper's hypothesis verification).

    Stage 0 proposes the square grid ``{i·step : |i·step| ≤ half_range}²`` (metres, source
    frame); each later stage proposes ``fine_samples`` seeded uniform samples in a square of
    half-size ``step·shrink^(stage−1)`` around the best hypothesis so far, each coordinate
    clamped to ``[−half_range, half_range]``: the search never leaves its square, so a true
    translation beyond it is answered by a pose on the square's edge (samples that fall
    outside pile up there). Ties keep the earliest hypothesis. Drive it as::

        search = TranslationSearch(3.0, 0.6, fine_samples=32, stages=3, seed=0)
        while not search.done:
            xy = search.proposals()              # (N, 2) float64 metres
            search.report(costs, yaws)           # (N,), (N,) for those proposals
        best = search.best()                     # SearchHypothesis(x, y, yaw, cost)

    Deterministic for a seed (SplitMix64; identical on both backends) and any thread count.
    """

    def __init__(
        self,
        half_range: float,
        step: float,
        fine_samples: int = 32,
        stages: int = 3,
        shrink: float = 0.5,
        seed: int = 0,
        *,
        backend: Backend = "rust",
    ) -> None:
        _check_backend(backend)
        hr = positive_float(half_range, "half_range")
        st = positive_float(step, "step")
        if hr < st:
            raise ValueError(f"half_range: expected a value >= step ({st}), got {hr}")
        nst = positive_int(stages, "stages")
        nfs = positive_int(fine_samples, "fine_samples", 1 if nst > 1 else 0)
        if nfs > MAX_STAGE_POINTS:
            raise ValueError(
                f"fine_samples: expected at most {MAX_STAGE_POINTS} samples per stage, got {nfs}"
            )
        ratio = hr / st
        if not ratio * ratio < MAX_STAGE_POINTS:  # also inf (1e300 / 1e-300)
            raise ValueError(
                f"step: the coarse grid of half_range / step = {ratio:.3g} steps a side would "
                f"exceed {MAX_STAGE_POINTS} points; use a larger step"
            )
        n_side = 2 * math.floor(ratio + 1e-9) + 1
        if n_side * n_side > MAX_STAGE_POINTS:
            raise ValueError(
                f"step: the coarse grid would have {n_side}×{n_side} points; use a larger step"
            )
        sh = positive_float(shrink, "shrink")
        if sh > 1.0:
            raise ValueError(f"shrink: expected a value in (0, 1], got {sh}")
        sd = positive_int(seed, "seed", 0, maximum=2**64 - 1)
        self.backend = backend
        if backend == "rust":
            self._impl: Any = _core.TranslationSearch(hr, st, nfs, nst, sh, sd)
        else:
            from vvloc.reference import matching as ref_matching

            # a coarse grid that does not fit: MemoryError naming `step`, as the Rust backend
            self._impl = _reference_output(
                "step", lambda: ref_matching.TranslationSearch(hr, st, nfs, nst, sh, sd)
            )

    @property
    def done(self) -> bool:
        """Whether every stage has been evaluated."""
        return bool(self._impl.done)

    @property
    def stage(self) -> int:
        """The current stage index (``stages`` when done)."""
        return int(self._impl.stage)

    def proposals(self) -> npt.NDArray[np.float64]:
        """The current stage's translations (N, 2) float64, metres ((0, 2) when done)."""
        return np.asarray(self._impl.proposals(), dtype=np.float64)

    def report(self, costs: Any, yaws: Any) -> None:
        """Report (N,) costs and (N,) yaws (radians, wrapped to (−π, π] here) of the current
        proposals; next stage."""
        if self.done:
            raise ValueError("report: the search is already done")
        n = len(self._impl.proposals())
        c = _f64_vector(costs, "costs", n)
        y = _f64_vector(yaws, "yaws", n)
        self._impl.report(c, y)  # both backends store the yaws wrapped to (−π, π]

    def best(self) -> SearchHypothesis | None:
        """The best hypothesis so far, or None before the first report."""
        b = self._impl.best()
        return None if b is None else SearchHypothesis(*map(float, b))

    def history(self) -> SearchHistory:
        """Every evaluated hypothesis, in evaluation order."""
        return SearchHistory(*self._impl.history())
