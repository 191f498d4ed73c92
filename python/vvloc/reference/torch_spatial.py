"""Vectorised, differentiable torch versions of BEV padding and polar sampling.

This is the training path (gradients flow to the BEV) and the "best vectorised torch" baseline
of the benchmarks. It follows DESIGN.md §3 exactly like the Rust kernels and the literal
reference (:mod:`vvloc.reference.spatial`) and is tested equal to them.

Both steps use :func:`torch.nn.functional.grid_sample` with ``align_corners=False``: there the
normalised coordinate −1 is the outer edge of cell 0 and +1 the outer edge of cell n−1, so the
centre of (fractional) cell index ``i`` on an axis of ``n`` cells is ``(2i + 1)/n − 1``. This
mapping works for n = 1 too (``align_corners=True`` would collapse it). The grid's last axis is
(x ↔ width/columns j, y ↔ height/rows i). In float32 the coordinate round trip costs about
``n·2⁻²⁴`` cells, so results agree with the kernels to ~1e-5·|∇Q| (float64 tensors: exactly to
float rounding).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from vvloc.reference.spatial import SHIFT_SNAP, polar_points


def _normalised(index: torch.Tensor, n: int) -> torch.Tensor:
    """Fractional cell index → grid_sample coordinate (``align_corners=False``)."""
    return (2.0 * index + 1.0) / n - 1.0


def _axis_shift(metres: torch.Tensor, grid_size: float, n: int) -> torch.Tensor:
    """Shift in cells (float64), snapped to integers within SHIFT_SNAP, clamped to ±(n + 2)."""
    u = metres.to(torch.float64) / grid_size
    nearest = torch.round(u)
    u = torch.where((u - nearest).abs() <= SHIFT_SNAP, nearest, u)
    return u.clamp(-(n + 2.0), n + 2.0)


def _valid_rows(u: torch.Tensor, n: int) -> torch.Tensor:
    """(…, n) bool: padded row a is valid iff its non-zero-weight taps a+⌊u⌋ (and a+⌊u⌋+1 when
    u is fractional) lie inside the grid; invalid rows are filled with 1."""
    k = torch.floor(u)
    f = u - k
    a = torch.arange(n, dtype=torch.float64, device=u.device) + k[..., None]
    return (a >= 0) & (a < n) & ((f[..., None] == 0) | (a + 1 < n))


def _pad_channels_first(
    maps: torch.Tensor, translations: torch.Tensor, grid_size: float
) -> torch.Tensor:
    """Padding of ``maps`` (B, C, H, W) for translations (B, N, 2) → (B, N, C, H, W)."""
    b, c, h, w = maps.shape
    n = translations.shape[1]
    u = _axis_shift(translations[..., 0], grid_size, h)  # (B, N)
    v = _axis_shift(translations[..., 1], grid_size, w)
    rows = torch.arange(h, dtype=torch.float64, device=maps.device)
    cols = torch.arange(w, dtype=torch.float64, device=maps.device)
    gy = _normalised(rows + u[..., None], h)[..., :, None].expand(b, n, h, w)
    gx = _normalised(cols + v[..., None], w)[..., None, :].expand(b, n, h, w)
    # The N hypotheses go into the grid's height so that the map is not copied N times.
    grid = torch.stack([gx, gy], dim=-1).reshape(b, n * h, w, 2).to(maps.dtype)
    sampled = F.grid_sample(maps, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    sampled = sampled.reshape(b, c, n, h, w).transpose(1, 2)
    valid = _valid_rows(u, h)[..., :, None] & _valid_rows(v, w)[..., None, :]  # (B, N, H, W)
    return torch.where(valid[:, :, None], sampled, torch.ones((), dtype=maps.dtype))


def _batched_translations(translations: torch.Tensor, batch: int) -> torch.Tensor:
    t = torch.as_tensor(translations)
    if t.ndim == 2:
        t = t[None].expand(batch, *t.shape)
    if t.ndim != 3 or t.shape[0] != batch or t.shape[2] != 2:
        raise ValueError(
            f"translations: expected shape (N, 2) or (B, N, 2) with B = {batch}, "
            f"got {tuple(t.shape)}"
        )
    return t


def torch_bev_pad(bev: torch.Tensor, translations: torch.Tensor, grid_size: float) -> torch.Tensor:
    """Differentiable BEV padding: ``bev`` (B, H, W, C), ``translations`` (N, 2) or (B, N, 2)
    metres → (B, N, H, W, C), same dtype/device as ``bev`` (a channels-last view).

    Value at (i, j): bilinear sample of the map at (i + x/g, j + y/g), 1 where a tap with
    non-zero weight falls outside the grid (DESIGN.md §3).
    """
    b = bev.shape[0]
    t = _batched_translations(translations, b).to(bev.device)
    padded = _pad_channels_first(bev.permute(0, 3, 1, 2), t, grid_size)
    return padded.permute(0, 1, 3, 4, 2)


def _polar_channels_first(
    maps: torch.Tensor, num_angles: int, num_radii: int, grid_size: float
) -> torch.Tensor:
    """Polar sampling of ``maps`` (B, C, H, W) → (B, C, T, R); taps outside read 1."""
    b, _, h, w = maps.shape
    pts = torch.from_numpy(polar_points(h, w, num_angles, num_radii, grid_size))
    grid = torch.stack([_normalised(pts[..., 1], w), _normalised(pts[..., 0], h)], dim=-1)
    grid = grid.to(device=maps.device, dtype=maps.dtype)[None].expand(b, -1, -1, -1)
    # Zero padding of (Q − 1), plus 1: every outside tap reads 1, weighted.
    shifted = maps - 1.0
    out = F.grid_sample(shifted, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    return out + 1.0


def torch_polar_sample(
    bev: torch.Tensor, num_angles: int, num_radii: int, grid_size: float
) -> torch.Tensor:
    """Differentiable polar sampling: ``bev`` (B, H, W, C) → (B, T, R, C) (DESIGN.md §3 grid)."""
    out = _polar_channels_first(bev.permute(0, 3, 1, 2), num_angles, num_radii, grid_size)
    return out.permute(0, 2, 3, 1)


def torch_pad_polar(
    bev: torch.Tensor,
    translations: torch.Tensor,
    num_angles: int,
    num_radii: int,
    grid_size: float,
    chunk: int = 16,
) -> torch.Tensor:
    """Padding then polar sampling: ``bev`` (B, H, W, C), ``translations`` (N, 2) or (B, N, 2)
    → (B, N, T, R, C) contiguous. Hypotheses go through in chunks of ``chunk`` to bound the
    memory of the padded maps (B·chunk·C·H·W values)."""
    b, h, w, c = bev.shape
    t = _batched_translations(translations, b).to(bev.device)
    maps = bev.permute(0, 3, 1, 2)
    parts = []
    for s in range(0, t.shape[1], chunk):
        padded = _pad_channels_first(maps, t[:, s : s + chunk], grid_size)  # (B, n, C, H, W)
        n = padded.shape[1]
        flat = padded.reshape(b * n, c, h, w)
        polar = _polar_channels_first(flat, num_angles, num_radii, grid_size)
        parts.append(polar.reshape(b, n, c, num_angles, num_radii).permute(0, 1, 3, 4, 2))
    if not parts:
        return bev.new_empty((b, 0, num_angles, num_radii, c))
    return torch.cat(parts, dim=1).contiguous()
