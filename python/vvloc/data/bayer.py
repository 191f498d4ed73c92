"""Bilinear Bayer demosaicing in numpy (normalised convolution: exact at sampled pixels)."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import convolve

_K_G = np.array([[0, 1, 0], [1, 4, 1], [0, 1, 0]], dtype=np.float64)
_K_RB = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]], dtype=np.float64)
PATTERNS = ("rggb", "bggr", "grbg", "gbrg")


def demosaic_bilinear(raw: np.ndarray, pattern: str) -> np.ndarray:
    """Demosaic a Bayer mosaic.

    Args:
        raw: (H, W) uint8 or uint16 raw mosaic.
        pattern: colours of the top-left 2×2 block read row-major, one of ``PATTERNS``.

    Returns:
        (H, W, 3) RGB of ``raw``'s dtype. Known samples are kept exactly; missing ones are the
        mean of their nearest same-colour neighbours (weights renormalised at the border).
    """
    pattern = pattern.lower()
    if pattern not in PATTERNS:
        raise ValueError(f"pattern: expected one of {PATTERNS}, got {pattern!r}")
    raw = np.asarray(raw)
    if raw.ndim != 2:
        raise ValueError(f"raw: expected a (H, W) mosaic, got shape {raw.shape}")
    h, w = raw.shape
    x = raw.astype(np.float64)
    out = np.empty((h, w, 3), dtype=np.float64)
    for c, name in enumerate("rgb"):
        mask = np.zeros((h, w), dtype=np.float64)
        for k, p in enumerate(pattern):
            if p == name:
                mask[k // 2 :: 2, k % 2 :: 2] = 1.0
        kernel = _K_G if name == "g" else _K_RB
        num = convolve(x * mask, kernel, mode="constant")
        den = convolve(mask, kernel, mode="constant")
        out[..., c] = num / den
    info = np.iinfo(raw.dtype) if np.issubdtype(raw.dtype, np.integer) else None
    if info is not None:
        return np.clip(np.rint(out), info.min, info.max).astype(raw.dtype)
    return out.astype(raw.dtype)


def mosaic(rgb: np.ndarray, pattern: str) -> np.ndarray:
    """The Bayer mosaic (H, W) of an (H, W, 3) image (the inverse sampling, used by fixtures)."""
    pattern = pattern.lower()
    if pattern not in PATTERNS:
        raise ValueError(f"pattern: expected one of {PATTERNS}, got {pattern!r}")
    out = np.empty(rgb.shape[:2], dtype=rgb.dtype)
    for k, p in enumerate(pattern):
        out[k // 2 :: 2, k % 2 :: 2] = rgb[k // 2 :: 2, k % 2 :: 2, "rgb".index(p)]
    return out
