"""Differentiable spatial operations of the training path (DESIGN.md §3).

``polar_sample`` and ``bev_pad`` are the networks' entry points to the vectorised torch
implementation in :mod:`vvloc.reference.torch_spatial` (the one implementation; it equals
:func:`vvloc.kernels.polar_sample` / :func:`vvloc.kernels.bev_pad` to 1e-5); they add the
shapes the networks and losses use. ``roll_interp`` is the interpolated roll ρ with one real
shift per leading item (per pair), differentiable w.r.t. the descriptors.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from vvloc._checks import positive_float, positive_int
from vvloc.reference.torch_spatial import torch_bev_pad, torch_polar_sample


def float_tensor(x: Any, name: str, shape: str) -> None:
    """``TypeError`` naming ``name`` unless ``x`` is a floating-point torch tensor (``shape``
    says what the caller expects, for the message)."""
    shape = f" {shape}" if shape else ""
    if not isinstance(x, Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor{shape}, got {type(x).__name__}")
    if not x.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor{shape}, got {x.dtype}")


def _real64(values: Any, name: str, unit: str, device: torch.device) -> Tensor:
    """``values`` (a tensor, array, list or number) as float64 on ``device``, never through
    float32 (a Python float keeps its last bits), ``TypeError`` naming ``name`` for complex or
    bool values and ``ValueError`` for NaN or inf. Values on a GPU are not checked for
    finiteness: the check would make the GPU wait on every call of the training step."""
    raw = values if isinstance(values, Tensor) else np.asarray(values)
    if isinstance(raw, Tensor):
        bad = raw.is_complex() or raw.dtype == torch.bool
    else:
        bad = raw.dtype.kind not in "fiu"
    if bad:
        raise TypeError(f"{name}: expected real numbers ({unit}), got {raw.dtype}")
    finite: Any
    if isinstance(raw, Tensor):
        finite = None if raw.device.type != "cpu" else raw.detach().double().isfinite().all()
    else:
        finite = np.isfinite(raw.astype(np.float64)).all()
    if finite is not None and not bool(finite):
        raise ValueError(f"{name}: contains non-finite values (NaN or inf)")
    return torch.as_tensor(raw, dtype=torch.float64, device=device)


def _check_bev(bev: Tensor, name: str = "bev", *, single: bool = False) -> None:
    """``TypeError``/``ValueError`` naming ``name`` unless ``bev`` is a floating-point tensor
    (B, H, W, C), or with ``single`` also (H, W, C), with H, W, C >= 1."""
    shapes = "(H, W, C) or (N, H, W, C)" if single else "(B, H, W, C)"
    float_tensor(bev, name, shapes)
    if bev.ndim != 4 and not (single and bev.ndim == 3):
        raise ValueError(f"{name}: expected shape {shapes}, got {tuple(bev.shape)}")
    if min(bev.shape[-3:]) < 1:
        raise ValueError(f"{name}: expected H, W, C >= 1, got shape {tuple(bev.shape)}")


def polar_sample(bev: Tensor, num_angles: int, num_radii: int, grid_size: float) -> Tensor:
    """Sample a BEV on the polar grid: (B, H, W, C) → (B, T, R, C), differentiable.

    Bilinear interpolation at the polar sample points of DESIGN.md §3; a tap outside the grid
    reads 1. Delegates to :func:`vvloc.reference.torch_spatial.torch_polar_sample`.
    ``num_angles``, ``num_radii`` ints >= 1 and ``grid_size`` (m, finite, > 0) are checked
    as the kernels check them.
    """
    _check_bev(bev)
    t, r = positive_int(num_angles, "num_angles"), positive_int(num_radii, "num_radii")
    g = positive_float(grid_size, "grid_size")
    return torch_polar_sample(bev, t, r, g).contiguous()


def bev_pad(bev: Tensor, translations: Tensor, grid_size: float) -> Tensor:
    """BEV padding (paper Alg. 1, DESIGN.md §3), differentiable w.r.t. ``bev``.

    ``bev`` (H, W, C) with ``translations`` (N, 2) metres → (N, H, W, C), or a batch ``bev``
    (N, H, W, C) with one translation per item (N, 2) → (N, H, W, C). Output cell (i, j) is the
    bilinear sample of the BEV at (i + x/g, j + y/g), or 1 wherever a tap with non-zero weight
    falls outside the grid: Qᵗ(p) = Q(p + t). Delegates to
    :func:`vvloc.reference.torch_spatial.torch_bev_pad`. ``grid_size`` (m, finite, > 0) and
    the translations (finite; not checked when they are a GPU tensor, see :func:`_real64`) are
    checked as the kernels check them.
    """
    _check_bev(bev, single=True)
    grid_size = positive_float(grid_size, "grid_size")
    t = _real64(translations, "translations", "metres", bev.device)
    if t.ndim != 2 or t.shape[1] != 2:
        raise ValueError(f"translations: expected shape (N, 2), got {tuple(t.shape)}")
    if bev.ndim == 3:
        return torch_bev_pad(bev[None], t, grid_size)[0].contiguous()
    if bev.shape[0] != t.shape[0]:
        raise ValueError(
            f"translations: expected {bev.shape[0]} rows to match bev (N, H, W, C), "
            f"got {t.shape[0]}"
        )
    return torch_bev_pad(bev, t[:, None, :], grid_size)[:, 0].contiguous()


def roll_interp(x: Tensor, shift: Tensor | float, dim: int = 1) -> Tensor:
    """Interpolated roll ρ(x, s) along ``dim`` with one real shift per leading item.

    ``x`` (P, ..., n, ...) with ``shift`` (P,) or a scalar: out[p] = (1 − w)·roll(x[p], k) +
    w·roll(x[p], k + 1), k = ⌊s_p⌋, w = s_p − k, roll(D, k)[i] = D[(i − k) mod n] (torch.roll
    semantics, DESIGN.md §3). Differentiable w.r.t. ``x`` (not the shift). ``x`` a
    floating-point tensor with ``dim`` one of its axes after the first; shifts finite, in bins
    (not checked when they are a GPU tensor, see :func:`_real64`).
    """
    float_tensor(x, "x", "(P, ..., n, ...)")
    if x.ndim < 2:
        raise ValueError(f"x: expected shape (P, ..., n, ...), 2 axes or more, got {x.ndim}")
    if (
        isinstance(dim, bool)
        or not isinstance(dim, int)
        or not -x.ndim <= dim < x.ndim
        or dim % x.ndim == 0
    ):
        raise ValueError(
            f"dim: expected an axis of x after its first (1..{x.ndim - 1} or negative), got {dim!r}"
        )
    dim %= x.ndim
    n = x.shape[dim]
    s = _real64(shift, "shift", "bins", x.device).reshape(-1)
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
