"""Small SE(2) helpers for 3-DoF poses (DESIGN.md §3).

A 3-DoF pose is an array ``(..., 3)`` of ``(x, y, yaw)``: metres and radians, yaw counter-clockwise
positive about z. A pose ``T_a_b`` maps coordinates in frame ``b`` to frame ``a``:
``p_a = R(yaw) · p_b + (x, y)``. World frame: x east, y north; vehicle frame: x forward, y left.

All functions broadcast over leading dimensions, return float64 and wrap yaw to (−π, π]. They
take real numbers (numpy arrays, sequences, torch tensors; ``TypeError`` naming the argument for
anything else) and pass NaN through as NaN (a pose that is not known stays unknown).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = [
    "compose",
    "inverse",
    "relative",
    "wrap_angle",
]

F64Array = npt.NDArray[np.float64]


def _real(x: object, name: str, shape_doc: str) -> F64Array:
    """``x`` as float64, ``TypeError`` naming ``name`` unless it holds real numbers."""
    if hasattr(x, "detach") and hasattr(x, "cpu"):  # a torch tensor, without importing torch
        x = x.detach().cpu().numpy()  # type: ignore[attr-defined]
    if x is None or isinstance(x, (str, bytes)):
        raise TypeError(f"{name}: expected real numbers{shape_doc}, got {type(x).__name__}")
    try:
        arr = np.asarray(x)
    except ValueError:  # nested sequences of unequal lengths
        raise ValueError(f"{name}: expected a rectangular array{shape_doc}") from None
    if arr.dtype == object or arr.dtype.kind not in "fiu":
        raise TypeError(f"{name}: expected real numbers{shape_doc}, got dtype {arr.dtype}")
    return arr.astype(np.float64, copy=False)


def wrap_angle(angle: npt.ArrayLike) -> F64Array:
    """Wrap angles (radians) to the half-open interval (−π, π], elementwise.

    ``wrap_angle(π) == π`` and ``wrap_angle(−π) == π``; ``wrap_angle(3π/2) == −π/2``.
    Angles already in (−π, π] are returned bit-exactly (no round trip through a modulo). NaN
    passes through, and ±inf (no angle) gives NaN, without a warning. Any finite angle,
    however large, is reduced modulo ``2·np.pi`` (the float) without losing its remainder, by
    the Rust kernels' operations (``f64::rem_euclid``, then a turn off above π): the same bits
    on both sides.
    """
    a = _real(angle, "angle", "")
    two_pi = 2.0 * np.pi
    with np.errstate(invalid="ignore"):  # fmod(±inf): NaN, the documented answer
        # fmod is exact: a − n·2π with no rounding, for any finite a (a formula through
        # a / 2π lost the remainder beyond ~1e15 rad: 1e16 gave 2.0, 1e17 gave 0.0)
        w = np.fmod(a, two_pi)  # (−2π, 2π), the sign of a
    w = np.where(w < 0.0, w + two_pi, w)  # [0, 2π]: as f64::rem_euclid
    w = np.where(w > np.pi, w - two_pi, w)  # (−π, π]: exact (w and 2π within a factor 2)
    inside = (a > -np.pi) & (a <= np.pi)
    return np.where(inside, a, w)[()]  # [()]: a scalar stays a numpy scalar


def _as_pose(pose: npt.ArrayLike, name: str) -> F64Array:
    arr = _real(pose, name, " (..., 3) = (x, y, yaw)")
    if arr.ndim == 0 or arr.shape[-1] != 3:
        raise ValueError(f"{name}: expected poses of shape (..., 3) = (x, y, yaw), got {arr.shape}")
    return arr


def compose(a: npt.ArrayLike, b: npt.ArrayLike) -> F64Array:
    """Compose poses: ``T_w_c = T_w_b · T_b_c`` given ``a = T_w_b`` and ``b = T_b_c``.

    Args:
        a: ``(..., 3)`` pose of frame b in frame w.
        b: ``(..., 3)`` pose of frame c in frame b (broadcast against ``a``).

    Returns:
        ``(..., 3)`` pose of frame c in frame w: translation ``t_a + R(yaw_a) · t_b``,
        yaw ``wrap(yaw_a + yaw_b)``.
    """
    a = _as_pose(a, "a")
    b = _as_pose(b, "b")
    try:
        np.broadcast_shapes(a.shape, b.shape)
    except ValueError:
        raise ValueError(
            f"a, b: poses of shapes {a.shape} and {b.shape} do not broadcast against each other"
        ) from None
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def inverse(pose: npt.ArrayLike) -> F64Array:
    """Invert poses: given ``T_a_b`` return ``T_b_a`` (``(..., 3)`` → ``(..., 3)``).

    Translation ``−R(−yaw) · t``, yaw ``wrap(−yaw)``.
    """
    p = _as_pose(pose, "pose")
    c, s = np.cos(p[..., 2]), np.sin(p[..., 2])
    x = -(c * p[..., 0] + s * p[..., 1])
    y = -(-s * p[..., 0] + c * p[..., 1])
    return np.stack([x, y, wrap_angle(-p[..., 2])], axis=-1)


def relative(source: npt.ArrayLike, target: npt.ArrayLike) -> F64Array:
    """Relative pose ξ_{s→t} = T_world_s⁻¹ · T_world_t (DESIGN.md §3).

    Args:
        source: ``(..., 3)`` world pose of the source frame s.
        target: ``(..., 3)`` world pose of the target frame t (broadcast against ``source``).

    Returns:
        ``(..., 3)``: the target origin expressed in source coordinates (metres) and
        ``wrap(yaw_t − yaw_s)`` (radians), so that ``compose(source, ξ) == target``.
    """
    return compose(inverse(source), target)
