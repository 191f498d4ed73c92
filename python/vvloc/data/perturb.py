"""Seeded image perturbations for robustness evaluation (degraded scenarios).

Every function takes ``images`` (M, 3, H, W) uint8 — one multi-camera frame — and returns a new
array of the same shape and dtype; it changes only what its name says (the chosen cameras, the
chosen regions). :func:`perturb_frame` applies one to a :class:`~vvloc.data.Frame`, leaving its
calibration and pose untouched. Random choices come from ``seed`` only; :func:`frame_seed`
gives each frame a seed of its own.
"""

from __future__ import annotations

import dataclasses
import inspect
import zlib
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy.ndimage import convolve

from vvloc._checks import finite_float, positive_int, uint8_images
from vvloc.data.frame import Frame


def _fill(x: Any) -> np.uint8:
    if isinstance(x, bool) or not isinstance(x, (int, np.integer)) or not 0 <= x <= 255:
        raise ValueError(f"fill: expected a grey level, an int in 0..255, got {x!r}")
    return np.uint8(x)


def _camera_list(cameras: Sequence[int] | None, m: int) -> list[int]:
    if cameras is None:
        return list(range(m))
    if isinstance(cameras, (str, bytes)) or not isinstance(cameras, (Sequence, np.ndarray)):
        raise TypeError(f"cameras: expected a list of camera indices, got {type(cameras).__name__}")
    kinds = [
        c
        for c in cameras
        if isinstance(c, (bool, np.bool_)) or not isinstance(c, (int, np.integer))
    ]
    if kinds:
        raise TypeError(f"cameras: expected int camera indices, got {kinds[0]!r}")
    out = [int(c) for c in cameras]
    bad = [c for c in out if not 0 <= c < m]
    if bad:
        raise ValueError(f"cameras: indices {bad} out of range for {m} cameras")
    return out


def mask_cameras(
    images: np.ndarray,
    cameras: Sequence[int] | None = None,
    *,
    count: int = 1,
    seed: int = 0,
    fill: int = 0,
) -> np.ndarray:
    """Blank whole cameras (a failed or covered camera).

    ``cameras`` lists the indices to blank; if None, ``count`` distinct cameras are drawn.
    """
    images = uint8_images(images)
    seed = positive_int(seed, "seed", 0)  # None would draw fresh entropy: not reproducible
    m = images.shape[0]
    value = _fill(fill)
    if cameras is None:
        count = positive_int(count, "count", 0)
        if count > m:
            raise ValueError(f"count: expected 0..{m}, got {count}")
        cameras = np.random.default_rng(seed).choice(m, size=count, replace=False).tolist()
    out = images.copy()
    out[_camera_list(cameras, m)] = value
    return out


def motion_blur(
    images: np.ndarray,
    length: int = 9,
    angle_deg: float | None = 0.0,
    *,
    cameras: Sequence[int] | None = None,
    seed: int = 0,
) -> np.ndarray:
    """Linear motion blur of ``length`` pixels along ``angle_deg`` (image x axis = 0°, random
    per camera when None) on the chosen cameras (all by default); see :func:`line_kernel`."""
    images = uint8_images(images)
    length = positive_int(length, "length", 1)
    if angle_deg is not None:
        finite_float(angle_deg, "angle_deg")
    rng = np.random.default_rng(positive_int(seed, "seed", 0))
    out = images.copy()
    for c in _camera_list(cameras, images.shape[0]):
        ang = float(rng.uniform(0, 180)) if angle_deg is None else float(angle_deg)
        kernel = line_kernel(length, ang)
        img = images[c].astype(np.float64)
        res = np.stack([convolve(ch, kernel, mode="nearest") for ch in img])
        out[c] = np.clip(np.rint(res), 0, 255).astype(np.uint8)
    return out


def line_kernel(length: int, angle_deg: float) -> np.ndarray:
    """A normalised (k, k) kernel: a segment ``length`` pixels long through the centre at
    ``angle_deg`` (0° = image x axis, 90° = image y axis), drawn with bilinear weights from
    4·length points evenly spaced along it (the midpoints of equal parts, so that the segment
    spans ``length`` pixels: at 0° and an odd length ≥ 3, one row whose inner ``length − 2``
    taps weigh ``1/length`` each, the two end pixels a little less, and their bilinear spill
    onto the next pixel outside the rest).
    k = the odd number ≥ ``length``, plus 2 for the bilinear spill at the ends. ``length`` an
    int >= 1, ``angle_deg`` finite."""
    length = positive_int(length, "length", 1)
    angle_deg = finite_float(angle_deg, "angle_deg")
    k = (length if length % 2 == 1 else length + 1) + 2
    kern = np.zeros((k, k))
    c = (k - 1) / 2
    a = np.deg2rad(angle_deg)
    n = 4 * length
    for t in (np.arange(n) + 0.5) * (length / n) - length / 2:
        x, y = c + t * np.cos(a), c + t * np.sin(a)
        x0, y0 = int(np.floor(x)), int(np.floor(y))
        fx, fy = x - x0, y - y0
        for dy, wy in ((0, 1 - fy), (1, fy)):
            for dx, wx in ((0, 1 - fx), (1, fx)):
                if 0 <= y0 + dy < k and 0 <= x0 + dx < k:
                    kern[y0 + dy, x0 + dx] += wx * wy
    return kern / kern.sum()


def region_boxes(
    shape: tuple[int, ...], count: int, size: float, seed: int, cameras: Sequence[int] | None
) -> list[tuple[int, int, int, int, int]]:
    """The (camera, row0, row1, col0, col1) boxes :func:`mask_regions` blanks for these args:
    ``shape`` is the images' (M, 3, H, W), H, W >= 1 pixels."""
    if not isinstance(shape, (tuple, list)) or len(shape) != 4:
        raise ValueError(f"shape: expected the images' shape (M, 3, H, W), got {shape!r}")
    m, _, h, w = (positive_int(v, "shape", 0) for v in shape)
    if min(h, w) < 1:
        raise ValueError(f"shape: expected H, W >= 1 pixels, got {tuple(shape)}")
    count = positive_int(count, "count", 0)
    if not 0 < finite_float(size, "size") <= 1:
        raise ValueError(f"size: expected a fraction of the image side in (0, 1], got {size}")
    rng = np.random.default_rng(positive_int(seed, "seed", 0))
    bh, bw = max(1, round(size * h)), max(1, round(size * w))
    boxes = []
    for c in _camera_list(cameras, m):
        for _ in range(count):
            r0 = int(rng.integers(0, h - bh + 1))
            c0 = int(rng.integers(0, w - bw + 1))
            boxes.append((c, r0, r0 + bh, c0, c0 + bw))
    return boxes


def mask_regions(
    images: np.ndarray,
    count: int = 2,
    size: float = 0.25,
    *,
    cameras: Sequence[int] | None = None,
    seed: int = 0,
    fill: int = 0,
) -> np.ndarray:
    """Blank ``count`` rectangles per chosen camera (occlusion: dirt, a pedestrian, a truck).

    Each rectangle is ``size`` × the image height by ``size`` × the image width, placed at
    random; :func:`region_boxes` returns the same rectangles.
    """
    images = uint8_images(images)
    value = _fill(fill)
    out = images.copy()
    for c, r0, r1, c0, c1 in region_boxes(images.shape, count, size, seed, cameras):
        out[c, :, r0:r1, c0:c1] = value
    return out


def exposure(
    images: np.ndarray,
    gain: float = 0.5,
    gamma: float = 1.0,
    *,
    cameras: Sequence[int] | None = None,
) -> np.ndarray:
    """Exposure change: ``255 · (gain · x / 255) ** gamma``, clipped, on the chosen cameras."""
    images = uint8_images(images)
    if not (finite_float(gain, "gain") > 0 and finite_float(gamma, "gamma") > 0):
        raise ValueError(f"gain, gamma: expected finite values > 0, got {gain}, {gamma}")
    out = images.copy()
    for c in _camera_list(cameras, images.shape[0]):
        x = np.clip(gain * images[c].astype(np.float64) / 255.0, 0.0, 1.0) ** gamma
        out[c] = np.clip(np.rint(255.0 * x), 0, 255).astype(np.uint8)
    return out


def noise(
    images: np.ndarray,
    sigma: float = 8.0,
    *,
    cameras: Sequence[int] | None = None,
    seed: int = 0,
) -> np.ndarray:
    """Additive Gaussian noise of standard deviation ``sigma`` grey levels, clipped."""
    images = uint8_images(images)
    if finite_float(sigma, "sigma") < 0:
        raise ValueError(f"sigma: expected a finite value >= 0, got {sigma}")
    rng = np.random.default_rng(positive_int(seed, "seed", 0))
    out = images.copy()
    for c in _camera_list(cameras, images.shape[0]):
        x = images[c].astype(np.float64) + rng.normal(0.0, sigma, size=images[c].shape)
        out[c] = np.clip(np.rint(x), 0, 255).astype(np.uint8)
    return out


PERTURBATIONS: dict[str, Callable[..., np.ndarray]] = {
    "mask_cameras": mask_cameras,
    "motion_blur": motion_blur,
    "mask_regions": mask_regions,
    "exposure": exposure,
    "noise": noise,
}


#: The perturbations that draw anything at random (they take a ``seed``).
SEEDED = frozenset(
    name for name, fn in PERTURBATIONS.items() if "seed" in inspect.signature(fn).parameters
)


def perturb_frame(frame: Frame, name: str, **kwargs: Any) -> Frame:
    """A copy of ``frame`` whose images went through perturbation ``name`` (see PERTURBATIONS)
    with ``kwargs``; the calibration and pose are the original's."""
    if not isinstance(name, str):
        raise TypeError(f"name: expected one of {sorted(PERTURBATIONS)}, got {name!r}")
    try:
        fn = PERTURBATIONS[name]
    except KeyError:
        raise ValueError(f"name: expected one of {sorted(PERTURBATIONS)}, got {name!r}") from None
    accepted = set(inspect.signature(fn).parameters) - {"images"}
    unknown = sorted(set(kwargs) - accepted)
    if unknown:
        raise ValueError(f"kwargs: {name} takes {sorted(accepted)}, not {unknown}")
    return dataclasses.replace(frame, images=fn(frame.images, **kwargs))


def frame_seed(frame: Frame, base: int = 0) -> int:
    """A seed of its own for ``frame``, from its session name and index (and ``base``): the
    same frame gets the same perturbation in every run, process and order of evaluation, and
    different frames get different ones."""
    if not isinstance(frame, Frame):
        raise TypeError(f"frame: expected a vvloc.data.Frame, got {type(frame).__name__}")
    key = f"{base}/{frame.session}/{frame.index}".encode()
    return zlib.crc32(key)
