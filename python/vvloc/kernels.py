"""The one gateway to vvloc's kernels.

Every function validates its inputs (raising ``TypeError``/``ValueError`` that name the argument
and the expected shape/dtype), converts them to C-contiguous float32, and dispatches to the Rust
extension (``backend="rust"``, default) or to the pure-Python reference
(``backend="reference"``, :mod:`vvloc.reference`). Shapes follow DESIGN.md §4; angles are in
radians, lengths in metres, BEVs are channels-last (H, W, C) with row i ↔ x, column j ↔ y.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
import numpy.typing as npt

Backend = Literal["rust", "reference"]
F32Array = npt.NDArray[np.float32]


def _check_backend(backend: str) -> str:
    if backend not in ("rust", "reference"):
        raise ValueError(f"backend: expected 'rust' or 'reference', got {backend!r}")
    return backend


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
    if hasattr(x, "detach") and hasattr(x, "cpu"):  # torch.Tensor, without importing torch
        x = x.detach().cpu().numpy()
    if isinstance(x, (str, bytes)) or x is None:
        raise TypeError(f"{name}: expected a float array {shape_doc}, got {type(x).__name__}")
    arr = np.asarray(x)
    if arr.dtype == object or not (
        np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
    ):
        raise TypeError(
            f"{name}: expected a real-valued (float) array {shape_doc}, got dtype {arr.dtype}"
        )
    if ndim is not None:
        allowed = (ndim,) if isinstance(ndim, int) else ndim
        if arr.ndim not in allowed:
            raise ValueError(
                f"{name}: expected shape {shape_doc} ({' or '.join(map(str, allowed))}-D), "
                f"got shape {arr.shape}"
            )
    out = np.ascontiguousarray(arr, dtype=np.float32)
    if finite and out.size and not np.isfinite(out).all():
        raise ValueError(f"{name}: contains non-finite values (NaN or inf)")
    return out


def _positive_float(x: Any, name: str) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name}: expected a positive float, got {type(x).__name__}")
    v = float(x)
    if not np.isfinite(v) or v <= 0.0:
        raise ValueError(f"{name}: expected a finite value > 0, got {v}")
    return v


def _finite_float(x: Any, name: str) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name}: expected a float, got {type(x).__name__}")
    v = float(x)
    if not np.isfinite(v):
        raise ValueError(f"{name}: expected a finite value, got {v}")
    return v


def _positive_int(x: Any, name: str, minimum: int = 1) -> int:
    if isinstance(x, bool) or not isinstance(x, (int, np.integer)):
        raise TypeError(f"{name}: expected an int >= {minimum}, got {type(x).__name__}")
    v = int(x)
    if v < minimum:
        raise ValueError(f"{name}: expected an int >= {minimum}, got {v}")
    return v


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
    if hasattr(translations, "detach") and hasattr(translations, "cpu"):
        translations = translations.detach().cpu().numpy()
    if isinstance(translations, (str, bytes)) or translations is None:
        raise TypeError(f"translations: expected a float array (N, 2), got {type(translations)}")
    probe = np.asarray(translations)
    if probe.dtype == object or not (
        np.issubdtype(probe.dtype, np.floating) or np.issubdtype(probe.dtype, np.integer)
    ):
        raise TypeError(f"translations: expected a real-valued array (N, 2), got {probe.dtype}")
    if probe.ndim != 2 or probe.shape[1] != 2:
        raise ValueError(f"translations: expected shape (N, 2), got shape {probe.shape}")
    out = np.ascontiguousarray(probe, dtype=np.float64)
    if not np.isfinite(out).all():
        raise ValueError("translations: contains non-finite values (NaN or inf)")
    return out


def roll_interp(x: Any, shift: float, axis: int = 0, backend: Backend = "rust") -> F32Array:
    """Interpolated circular roll of ``x`` by ``shift`` elements along ``axis`` (DESIGN.md §3).

    ``roll(x, s)[i] = x[(i − s) mod n]`` (``torch.roll`` semantics); for real ``s``,
    ``(1 − w)·roll(x, ⌊s⌋) + w·roll(x, ⌊s⌋ + 1)`` with ``w = s − ⌊s⌋`` (continuous in ``s``).
    ``x``: any real array of ndim >= 1; ``axis`` may be negative. Returns float32, same shape.
    """
    backend = _check_backend(backend)
    arr = _as_f32(x, "x")
    if np.ndim(x) == 0:  # checked on the input: ascontiguousarray makes scalars 1-D
        raise ValueError("x: expected an array with at least 1 dimension, got a scalar")
    s = _finite_float(shift, "shift")
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

    ``bev``: (H, W, C) map, row i ↔ x, column j ↔ y, cells of ``grid_size`` metres.
    ``translations``: (N, 2) target origins (x, y) in metres in the map's frame.
    Returns (N, H, W, C) float32: the bilinear sample of ``bev`` at (i + x/g, j + y/g), 1 wherever
    a tap with non-zero weight falls outside the grid. Zero shift → unchanged; shifts of a map
    size or more → all ones. Shifts within 1e-6 cells of an integer are snapped to it.
    """
    backend = _check_backend(backend)
    q = _bev(bev)
    t = _translations(translations)
    g = _positive_float(grid_size, "grid_size")
    if backend == "reference":
        from vvloc.reference import spatial as ref

        return ref.bev_pad(q, t, g)
    from vvloc import _core

    return _core.bev_pad(q, t, g)


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
    t = _positive_int(num_angles, "num_angles")
    r = _positive_int(num_radii, "num_radii")
    g = _positive_float(grid_size, "grid_size")
    if backend == "reference":
        from vvloc.reference import spatial as ref

        return ref.polar_sample(q, t, r, g)
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
    t = _positive_int(num_angles, "num_angles")
    r = _positive_int(num_radii, "num_radii")
    g = _positive_float(grid_size, "grid_size")
    if backend == "reference":
        from vvloc.reference import spatial as ref

        return ref.pad_polar(q, tr, t, r, g)
    from vvloc import _core

    return _core.pad_polar(q, tr, t, r, g)


# --- matching kernels (matching_cost, yaw_costs, estimate_yaw, rerank, TranslationSearch) ----
