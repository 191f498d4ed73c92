"""Argument checks shared by the package: numbers and arrays, each refusal a ``TypeError`` (wrong
type) or ``ValueError`` (wrong value or shape) that names the argument and says what was expected
(README, "Errors"). The kernels' gateway (:mod:`vvloc.kernels`) has its own array conversion for
the Rust extension (float32, C order, aligned); these are for everything else."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

F64Array = npt.NDArray[np.float64]
I64Array = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]


def to_float(x: Any, name: str) -> float:
    """``float(x)``, with an int too large for a float (10**400) named in a ``ValueError``."""
    try:
        return float(x)
    except OverflowError:
        raise ValueError(
            f"{name}: expected a finite value, got an int too large for a float"
        ) from None


def positive_float(x: Any, name: str) -> float:
    """A finite real number > 0 (an int or float, numpy's too; not a bool) as a float."""
    if isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name}: expected a positive float, got {type(x).__name__}")
    v = to_float(x, name)
    if not np.isfinite(v) or v <= 0.0:
        raise ValueError(f"{name}: expected a finite value > 0, got {v}")
    return v


def finite_float(x: Any, name: str) -> float:
    """A finite real number (an int or float, numpy's too; not a bool) as a float."""
    if isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name}: expected a float, got {type(x).__name__}")
    v = to_float(x, name)
    if not np.isfinite(v):
        raise ValueError(f"{name}: expected a finite value, got {v}")
    return v


def positive_int(x: Any, name: str, minimum: int = 1, maximum: int = 2**63 - 1) -> int:
    """An int in [minimum, maximum] (default: what the Rust kernels' sizes hold), named in the
    error otherwise (not Python's 'int too big to convert')."""
    if isinstance(x, bool) or not isinstance(x, (int, np.integer)):
        raise TypeError(f"{name}: expected an int >= {minimum}, got {type(x).__name__}")
    v = int(x)
    if v < minimum:
        raise ValueError(f"{name}: expected an int >= {minimum}, got {v}")
    if v > maximum:
        raise ValueError(f"{name}: expected an int <= {maximum}, got {v}")
    return v


def flag(x: Any, name: str) -> bool:
    """A bool (numpy's too), refused otherwise: a string ``"no"`` is truthy."""
    if not isinstance(x, (bool, np.bool_)):
        raise TypeError(f"{name}: expected a bool, got {type(x).__name__}")
    return bool(x)


def as_array(x: Any, name: str, shape_doc: str) -> npt.NDArray[Any]:
    """``np.asarray(x)``, a ragged nested sequence refused naming ``name``. A torch tensor is
    taken as the kernels' gateway takes it: detached, moved to the CPU, bfloat16 (which numpy
    lacks) widened exactly to float32."""
    if hasattr(x, "detach") and hasattr(x, "cpu"):  # torch.Tensor, without importing torch
        x = x.detach().cpu()
        if str(x.dtype) == "torch.bfloat16":
            x = x.float()
        x = x.numpy()
    try:
        return np.asarray(x)
    except ValueError as e:  # numpy's "inhomogeneous shape after 1 dimensions"
        raise ValueError(f"{name}: expected an array of shape {shape_doc}, got a ragged one") from e


def real_number(x: Any, name: str) -> float:
    """A real number, ±inf allowed, NaN refused (a threshold: ``inf`` accepts everything)."""
    if isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name}: expected a real number, got {type(x).__name__}")
    v = float(x)
    if np.isnan(v):
        raise ValueError(f"{name}: expected a number, got nan")
    return v


def real_array(x: Any, name: str, shape_doc: str, ndim: int, last: int | None = None) -> F64Array:
    """Return ``x`` as a finite float64 array of ``ndim`` dimensions (last axis ``last``)."""
    if x is None or isinstance(x, (str, bytes)):
        raise TypeError(f"{name}: expected a real array of shape {shape_doc}, got {x!r}")
    arr = as_array(x, name, shape_doc)
    if arr.dtype == np.bool_ or not (
        np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
    ):
        raise TypeError(
            f"{name}: expected a real array of shape {shape_doc}, got dtype {arr.dtype}"
        )
    if arr.ndim != ndim or (last is not None and arr.shape[-1] != last):
        raise ValueError(f"{name}: expected shape {shape_doc}, got {arr.shape}")
    out = arr.astype(np.float64)
    if out.size and not np.isfinite(out).all():
        raise ValueError(f"{name}: contains non-finite values (NaN or inf)")
    return out


def int_array(x: Any, name: str, shape_doc: str, ndim: int, last: int | None = None) -> I64Array:
    """Return ``x`` as an int64 array of ``ndim`` dimensions (last axis ``last``)."""
    arr = as_array(x, name, shape_doc)
    if arr.dtype == np.bool_ or not np.issubdtype(arr.dtype, np.integer):
        if not (arr.size == 0 and arr.dtype == np.float64):  # np.asarray([]) is float64
            raise TypeError(f"{name}: expected an integer array {shape_doc}, got dtype {arr.dtype}")
    if arr.ndim != ndim or (last is not None and arr.shape[-1] != last):
        raise ValueError(f"{name}: expected shape {shape_doc}, got {arr.shape}")
    if arr.dtype == np.uint64 and arr.size and int(arr.max()) > np.iinfo(np.int64).max:
        # astype would wrap 2**64 - 1 to -1, which several callers read as "no entry"
        raise ValueError(f"{name}: expected values that fit int64, got {int(arr.max())}")
    return arr.astype(np.int64)


def bool_array(x: Any, name: str, length: int) -> BoolArray:
    """``x`` as it is, when it is a bool array of shape ``(length,)`` (an empty list too)."""
    arr = as_array(x, name, f"({length},)")
    if arr.size == 0 and arr.dtype == np.float64:  # np.asarray([]) is float64
        arr = arr.astype(np.bool_)
    if arr.dtype != np.bool_:
        raise TypeError(
            f"{name}: expected a bool array of shape ({length},), got dtype {arr.dtype}"
        )
    if arr.shape != (length,):
        raise ValueError(f"{name}: expected shape ({length},), got {arr.shape}")
    return arr


def uint8_images(images: Any) -> npt.NDArray[np.uint8]:
    """``images`` if it is a uint8 numpy array (M, 3, H, W), H, W ≥ 1: a ``TypeError`` for
    another type or dtype, a ``ValueError`` for another shape (both naming ``images``)."""
    if not isinstance(images, np.ndarray):
        raise TypeError(
            f"images: expected a uint8 numpy array (M, 3, H, W), got {type(images).__name__}"
        )
    if images.dtype != np.uint8:  # a float image in [0, 1] would be taken as near black
        raise TypeError(f"images: expected a uint8 (M, 3, H, W) array, got dtype {images.dtype}")
    if images.ndim != 4:
        raise ValueError(f"images: expected a uint8 (M, 3, H, W) array, got shape {images.shape}")
    if images.shape[1] != 3:
        raise ValueError(f"images: expected 3 channels on axis 1, got shape {images.shape}")
    if min(images.shape[2:]) < 1:
        raise ValueError(f"images: expected H, W >= 1, got shape {images.shape}")
    return images
