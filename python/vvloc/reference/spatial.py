"""Reference spatial kernels: interpolated roll, BEV padding (Alg. 1), polar sampling.

Literal and readable on purpose (the tests' oracle, the benchmarks' slow baseline); see
DESIGN.md §3 for the conventions and ``rust/vvloc-core/src/{roll,pad,polar}.rs`` for the fast
kernels. Inputs are validated by :mod:`vvloc.kernels`; maps are float32 channels-last
(H, W, C) with row i ↔ x and column j ↔ y, translations are metres, angles radians.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import torch

F32Array = npt.NDArray[np.float32]
F64Array = npt.NDArray[np.float64]

#: Shifts (in cells) closer than this to an integer are rounded to it (same rule as the Rust
#: kernels): a float32 translation of 0.3 m on a 0.3 m grid is a one-cell shift, not a shift of
#: 1.0000000397 cells that would fill a second row because of a tap weighted 4e-8.
SHIFT_SNAP = 1e-6


def roll_interp(x: F32Array, shift: float, axis: int = 0) -> F32Array:
    """Interpolated roll ρ(x, s) along ``axis`` (DESIGN.md §3), with ``torch.roll``.

    ``roll(x, s)[i] = x[(i − s) mod n]``; for real ``s`` with ``k = ⌊s⌋``, ``w = s − k``:
    ``ρ = (1 − w)·roll(x, k) + w·roll(x, k + 1)``. Returns float32, same shape as ``x``.
    """
    arr = np.ascontiguousarray(x, dtype=np.float32)
    if not arr.flags.writeable:  # torch warns on a read-only array; it only reads this one
        arr = arr.copy()
    t = torch.from_numpy(arr)
    n = t.shape[axis]
    if n == 0 or t.numel() == 0:
        return t.numpy().copy()
    k = math.floor(shift)
    w = shift - k
    k %= n  # the same roll, and keeps huge shifts inside int64
    out = (1.0 - w) * torch.roll(t, k, dims=axis) + w * torch.roll(t, k + 1, dims=axis)
    return out.numpy()


def shift_in_cells(metres: float, grid_size: float, n: int) -> float:
    """Translation ``metres`` as a shift in cells of ``grid_size`` m (snapped, see SHIFT_SNAP)
    along an axis of ``n`` cells, clamped to ±(n + 2): beyond that every cell is filled anyway
    (and a shift of 1e300 m / 1e-300 m, infinite in float64, stays a number)."""
    u = float(metres) / float(grid_size)
    u = min(max(u, -(n + 2.0)), n + 2.0)
    if abs(u - round(u)) <= SHIFT_SNAP:
        u = float(round(u))
    return u


def _fill_wrapped(q: F32Array, u: float, axis: int) -> None:
    """Set the rows (axis 0) or columns (axis 1) that Alg. 1's roll by ``−u`` wrapped in to 1."""
    n = q.shape[axis]
    if u >= 0:
        lo, hi = max(n - math.ceil(u), 0), n  # rows [H − ⌈u⌉, H)
    else:
        lo, hi = 0, min(math.ceil(-u), n)  # rows [0, ⌈−u⌉)
    index: list[slice] = [slice(None)] * q.ndim
    index[axis] = slice(lo, hi)
    q[tuple(index)] = 1.0


def bev_pad(bev: F32Array, translations: F64Array, grid_size: float) -> F32Array:
    """BEV padding, paper Alg. 1 with the corrected fill, one translation at a time.

    ``bev`` (H, W, C) float32, ``translations`` (N, 2) metres (x, y), ``grid_size`` g metres.
    Returns (N, H, W, C) float32: ``Qᵗ = ρ(ρ(Q, −x/g, 0), −y/g, 1)`` with the wrapped-in
    rows/columns set to 1, i.e. the source BEV re-centred at the hypothesised target origin.
    """
    h, w, c = bev.shape
    out = np.empty((len(translations), h, w, c), dtype=np.float32)
    for n, (x, y) in enumerate(translations):
        u, v = shift_in_cells(x, grid_size, h), shift_in_cells(y, grid_size, w)
        q = roll_interp(roll_interp(bev, -u, axis=0), -v, axis=1)
        _fill_wrapped(q, u, axis=0)
        _fill_wrapped(q, v, axis=1)
        out[n] = q
    return out


def polar_points(
    height: int, width: int, num_angles: int, num_radii: int, grid_size: float
) -> F64Array:
    """Fractional (row, column) cell index of every polar sample point, shape (T, R, 2).

    θ_k = (k + 0.5)·2π/T from +y towards +x, r_m = (m + 0.5)·r_max/R, r_max = min(H, W)·g/2;
    the point (x, y) = (r sin θ, r cos θ) metres sits at (x/g + (H−1)/2, y/g + (W−1)/2).
    """
    theta = (np.arange(num_angles) + 0.5) * 2.0 * np.pi / num_angles
    r_max = min(height, width) * grid_size / 2.0
    radius = (np.arange(num_radii) + 0.5) * r_max / num_radii
    x = radius[None, :] * np.sin(theta)[:, None]
    y = radius[None, :] * np.cos(theta)[:, None]
    return np.stack([x / grid_size + (height - 1) / 2, y / grid_size + (width - 1) / 2], axis=-1)


def polar_sample(bev: F32Array, num_angles: int, num_radii: int, grid_size: float) -> F32Array:
    """Polar sampling of a (H, W, C) or (B, H, W, C) BEV → (T, R, C) or (B, T, R, C) float32.

    An explicit bilinear loop over the sample points. A tap outside the grid reads the fill
    value 1 and is blended with its bilinear weight; a tap of weight zero contributes nothing.
    """
    single = bev.ndim == 3
    maps = bev[None] if single else bev
    b, h, w, c = maps.shape
    points = polar_points(h, w, num_angles, num_radii, grid_size)
    out = np.empty((b, num_angles, num_radii, c), dtype=np.float32)
    for k in range(num_angles):
        for m in range(num_radii):
            p, q = points[k, m]
            i0, j0 = math.floor(p), math.floor(q)
            fi, fj = p - i0, q - j0
            acc = np.zeros((b, c), dtype=np.float64)
            for i, wi in ((i0, 1.0 - fi), (i0 + 1, fi)):
                for j, wj in ((j0, 1.0 - fj), (j0 + 1, fj)):
                    if wi * wj == 0.0:
                        continue
                    inside = 0 <= i < h and 0 <= j < w
                    acc += wi * wj * (maps[:, i, j, :] if inside else 1.0)
            out[:, k, m, :] = acc
    return out[0] if single else out


def pad_polar(
    bev: F32Array,
    translations: F64Array,
    num_angles: int,
    num_radii: int,
    grid_size: float,
) -> F32Array:
    """Padding then polar sampling, one hypothesis at a time → (N, T, R, C) float32."""
    c = bev.shape[-1]
    out = np.empty((len(translations), num_angles, num_radii, c), dtype=np.float32)
    for n in range(len(translations)):
        padded = bev_pad(bev, translations[n : n + 1], grid_size)[0]
        out[n] = polar_sample(padded, num_angles, num_radii, grid_size)
    return out
