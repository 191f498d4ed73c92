"""Bilinear image remapping shared by the undistortion of the public-dataset readers."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import map_coordinates


def remap_bilinear(image: np.ndarray, src_u: np.ndarray, src_v: np.ndarray) -> np.ndarray:
    """Sample (H, W, 3) uint8 ``image`` at source pixel coordinates (column ``src_u``, row
    ``src_v``), both shaped like the output (H', W'). Outside samples read 0."""
    out = np.empty((*src_u.shape, image.shape[2]), dtype=np.uint8)
    coords = np.stack([src_v, src_u])
    for c in range(image.shape[2]):
        v = map_coordinates(image[..., c].astype(np.float32), coords, order=1, cval=0.0)
        out[..., c] = np.clip(np.rint(v), 0, 255).astype(np.uint8)
    return out


def resize_rgb(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize (H, W, 3) uint8 to (height, width, 3) with bilinear filtering (Pillow)."""
    from PIL import Image

    if image.shape[1] == width and image.shape[0] == height:
        return image
    return np.asarray(Image.fromarray(image).resize((width, height), Image.Resampling.BILINEAR))
