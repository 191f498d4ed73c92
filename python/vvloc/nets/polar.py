"""Differentiable torch versions of the spatial kernels (training path), DESIGN.md §3.

``polar_sample`` and ``bev_pad`` equal :func:`vvloc.kernels.polar_sample` and
:func:`vvloc.kernels.bev_pad` (to float32 rounding) but are built from ``grid_sample`` so that
gradients flow back into the BEV. ``roll_interp`` is the interpolated roll ρ with per-row shifts.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor


def _check_bev(bev: Tensor, name: str = "bev") -> None:
    if not isinstance(bev, Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor (B, H, W, C), got {type(bev).__name__}")
    if bev.ndim != 4 or bev.shape[1] < 2 or bev.shape[2] < 2:
        raise ValueError(
            f"{name}: expected shape (B, H, W, C) with H, W >= 2, got {tuple(bev.shape)}"
        )


def polar_points(
    height: int, width: int, num_angles: int, num_radii: int, grid_size: float
) -> tuple[Tensor, Tensor]:
    """Fractional BEV indices (row, col) of the polar sample points, each (T, R) float64.

    θ_k = (k + 0.5)·2π/T from +y towards +x, r_m = (m + 0.5)·r_max/R, r_max = min(H, W)·g/2,
    (x, y) = (r sin θ, r cos θ), row = x/g + (H−1)/2, col = y/g + (W−1)/2.
    """
    r_max = min(height, width) * grid_size / 2.0
    theta = (torch.arange(num_angles, dtype=torch.float64) + 0.5) * (2.0 * math.pi / num_angles)
    radius = (torch.arange(num_radii, dtype=torch.float64) + 0.5) * (r_max / num_radii)
    x = radius[None, :] * torch.sin(theta)[:, None]
    y = radius[None, :] * torch.cos(theta)[:, None]
    return x / grid_size + (height - 1) / 2.0, y / grid_size + (width - 1) / 2.0


def polar_sample(bev: Tensor, num_angles: int, num_radii: int, grid_size: float) -> Tensor:
    """Sample a BEV on the polar grid: (B, H, W, C) → (B, T, R, C), differentiable.

    Bilinear interpolation at the fractional cell indices of :func:`polar_points`; a tap outside
    the grid reads 1 (implemented as ``grid_sample(bev − 1, zeros padding) + 1``, exact because the
    bilinear weights sum to one).
    """
    _check_bev(bev)
    b, h, w, _c = bev.shape
    rows, cols = polar_points(h, w, num_angles, num_radii, grid_size)
    # align_corners=True: normalised −1 ↔ index 0, +1 ↔ index size−1.
    gx = cols * (2.0 / (w - 1)) - 1.0
    gy = rows * (2.0 / (h - 1)) - 1.0
    grid = torch.stack([gx, gy], dim=-1).to(bev.dtype).to(bev.device)
    grid = grid.unsqueeze(0).expand(b, -1, -1, -1)
    src = bev.permute(0, 3, 1, 2) - 1.0
    out = F.grid_sample(src, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    return (out + 1.0).permute(0, 2, 3, 1).contiguous()


def _valid_taps(shift: Tensor, size: int) -> Tensor:
    """(N, size) bool: index i + shift[n] has every tap with non-zero weight inside [0, size)."""
    idx = torch.arange(size, dtype=torch.float64, device=shift.device)
    pos = idx[None, :] + shift[:, None]
    lo = torch.floor(pos)
    frac = pos - lo
    inside_lo = (lo >= 0) & (lo <= size - 1)
    inside_hi = (frac == 0) | (lo + 1 <= size - 1)
    return inside_lo & inside_hi


def bev_pad(bev: Tensor, translations: Tensor, grid_size: float) -> Tensor:
    """BEV padding (paper Alg. 1, DESIGN.md §3), differentiable w.r.t. ``bev``.

    ``bev`` (H, W, C) with ``translations`` (N, 2) metres → (N, H, W, C), or a batch ``bev``
    (N, H, W, C) with one translation per item (N, 2) → (N, H, W, C). Output cell (i, j) is the
    bilinear sample of the BEV at (i + x/g, j + y/g), or 1 wherever a tap with non-zero weight
    falls outside the grid: Qᵗ(p) = Q(p + t).
    """
    if not isinstance(bev, Tensor) or bev.ndim not in (3, 4):
        raise ValueError("bev: expected a tensor of shape (H, W, C) or (N, H, W, C)")
    t = torch.as_tensor(translations, dtype=torch.float64, device=bev.device)
    if t.ndim != 2 or t.shape[1] != 2:
        raise ValueError(f"translations: expected shape (N, 2), got {tuple(t.shape)}")
    n = t.shape[0]
    if bev.ndim == 3:
        bev = bev.unsqueeze(0).expand(n, -1, -1, -1)
    elif bev.shape[0] != n:
        raise ValueError(
            f"translations: expected {bev.shape[0]} rows to match bev (N, H, W, C), got {n}"
        )
    _check_bev(bev)
    _, h, w, _c = bev.shape
    sx, sy = t[:, 0] / grid_size, t[:, 1] / grid_size  # shift in cells, (N,)
    rows = torch.arange(h, dtype=torch.float64, device=bev.device)[None, :] + sx[:, None]
    cols = torch.arange(w, dtype=torch.float64, device=bev.device)[None, :] + sy[:, None]
    gy = (rows * (2.0 / (h - 1)) - 1.0)[:, :, None].expand(n, h, w)
    gx = (cols * (2.0 / (w - 1)) - 1.0)[:, None, :].expand(n, h, w)
    grid = torch.stack([gx, gy], dim=-1).to(bev.dtype)
    out = F.grid_sample(
        bev.permute(0, 3, 1, 2), grid, mode="bilinear", padding_mode="zeros", align_corners=True
    ).permute(0, 2, 3, 1)
    valid = _valid_taps(sx, h)[:, :, None] & _valid_taps(sy, w)[:, None, :]  # (N, H, W)
    return torch.where(valid[..., None], out, torch.ones_like(out)).contiguous()


def roll_interp(x: Tensor, shift: Tensor | float, dim: int = 1) -> Tensor:
    """Interpolated roll ρ(x, s) along ``dim`` with one real shift per leading item.

    ``x`` (P, ..., n, ...) with ``shift`` (P,) or a scalar: out[p] = (1 − w)·roll(x[p], k) +
    w·roll(x[p], k + 1), k = ⌊s_p⌋, w = s_p − k, roll(D, k)[i] = D[(i − k) mod n] (torch.roll
    semantics, DESIGN.md §3). Differentiable w.r.t. ``x`` (not the shift).
    """
    n = x.shape[dim]
    s = torch.as_tensor(shift, dtype=torch.float64, device=x.device).reshape(-1)
    if s.numel() == 1:
        s = s.expand(x.shape[0])
    if s.shape[0] != x.shape[0]:
        raise ValueError(f"shift: expected a scalar or {x.shape[0]} shifts, got {s.shape[0]}")
    k = torch.floor(s)
    w = (s - k).to(x.dtype)
    idx = torch.arange(n, device=x.device)
    src0 = (idx[None, :] - k.long()[:, None]) % n  # (P, n)
    src1 = (src0 - 1) % n
    shape = [1] * x.ndim
    shape[0], shape[dim] = x.shape[0], n
    exp = list(x.shape)
    g0 = torch.gather(x, dim, src0.reshape(shape).expand(exp))
    g1 = torch.gather(x, dim, src1.reshape(shape).expand(exp))
    wshape = [x.shape[0]] + [1] * (x.ndim - 1)
    w = w.reshape(wshape)
    return (1.0 - w) * g0 + w * g1
