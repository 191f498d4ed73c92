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


# --- matching kernels (matching_cost, yaw_costs, estimate_yaw, rerank, TranslationSearch) ----
