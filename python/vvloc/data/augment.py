"""Photometric training augmentation: lighting and weather changes that leave geometry alone.

Place recognition across sessions has to ignore the time of day and the weather; a rig's
training data rarely covers every condition it will meet. :class:`PhotometricAugment` draws, per
multi-camera frame, one global change of exposure (gain), contrast, gamma, colour tint and haze
(a blend towards a grey-blue airlight that grows towards the top of the image, where the scene
is far away), plus a small per-camera jitter of gain (cameras meter independently) and sensor
noise. Calibration and pose are untouched, so every loss stays valid.

It is deliberately different from :mod:`vvloc.data.perturb` (masked cameras/regions, motion
blur, under-exposure, noise of evaluation strength): robustness figures measure conditions the
training did not manufacture.
"""

from __future__ import annotations

import dataclasses
import numbers
from dataclasses import dataclass
from typing import Any

import numpy as np

from vvloc._checks import uint8_images

#: The largest log range (``brightness``, ``contrast``, ``gamma``, ``camera_jitter``) allowed.
LOG_RANGE_MAX = 5.0


@dataclass(frozen=True)
class PhotometricAugment:
    """Random photometric change of one frame's images (M, 3, H, W) uint8 → same shape, uint8.

    Fields (all ≥ 0; 0 disables that change; log ranges at most :data:`LOG_RANGE_MAX`, noise at
    most 255):

    - ``brightness``: gain drawn log-uniformly in [e^-b, e^b].
    - ``contrast``: contrast factor drawn log-uniformly in [e^-c, e^c] around each camera's
      own mean (one factor for all cameras).
    - ``gamma``: gamma drawn log-uniformly in [e^-g, e^g].
    - ``tint``: per-channel gain drawn uniformly in [1 - t, 1 + t] (white balance).
    - ``haze``: with probability ``haze_prob``, blend weight up to ``haze`` (uniform) towards an
      airlight grey level in [150, 230], the weight ramping from 40 % at the bottom row to 100 %
      at the top row.
    - ``camera_jitter``: extra per-camera gain, log-uniform in [e^-j, e^j].
    - ``noise``: Gaussian noise with standard deviation drawn uniformly in [0, noise] grey levels.
    - ``prob``: probability that a frame is augmented at all.
    """

    prob: float = 0.8
    brightness: float = 0.5
    contrast: float = 0.4
    gamma: float = 0.4
    tint: float = 0.1
    haze: float = 0.7
    haze_prob: float = 0.3
    camera_jitter: float = 0.1
    noise: float = 4.0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            ok = isinstance(v, numbers.Real) and not isinstance(v, bool | np.bool_)
            if not (ok and np.isfinite(v) and v >= 0):
                raise ValueError(f"augment.{f.name}: expected a finite number >= 0, got {v!r}")
            if isinstance(v, np.generic):  # np.float32(0.5): kept as the plain float
                object.__setattr__(self, f.name, float(v))
        for name in ("prob", "haze_prob", "haze", "tint"):
            if getattr(self, name) > 1:
                raise ValueError(f"augment.{name}: expected a value in [0, 1]")
        # log ranges: e^5 is a gain of 148, beyond which images are all black or all white
        for name in ("brightness", "contrast", "gamma", "camera_jitter"):
            if getattr(self, name) > LOG_RANGE_MAX:
                raise ValueError(
                    f"augment.{name}: expected a log range in [0, {LOG_RANGE_MAX}], "
                    f"got {getattr(self, name)}"
                )
        if self.noise > 255:
            raise ValueError(f"augment.noise: expected grey levels in [0, 255], got {self.noise}")

    @classmethod
    def from_dict(cls, raw: dict[str, Any] | None) -> PhotometricAugment:
        """Build from a config mapping (``{}`` or None = defaults); unknown keys raise
        ``ValueError``, anything but a mapping ``TypeError``."""
        if raw is not None and not isinstance(raw, dict):  # [("prob", 1)] passed dict()
            raise TypeError(f"augment: expected a mapping of fields, got {type(raw).__name__}")
        raw = dict(raw or {})
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(raw) - names)
        if unknown:
            raise ValueError(f"augment: unknown keys {unknown}; known: {sorted(names)}")
        return cls(**raw)

    def __call__(self, images: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Augmented copy of ``images`` (M, 3, H, W) uint8; random draws come from ``rng``."""
        uint8_images(images)
        if not isinstance(rng, np.random.Generator):
            raise TypeError(f"rng: expected a numpy Generator, got {type(rng).__name__}")
        if rng.random() >= self.prob:
            return images.copy()
        m, _, h, _ = images.shape
        x = images.astype(np.float32) / 255.0
        u = lambda a: float(rng.uniform(-a, a))  # noqa: E731
        gain = np.exp(u(self.brightness)) * np.exp(rng.uniform(-1, 1, m) * self.camera_jitter)
        tint = 1.0 + rng.uniform(-self.tint, self.tint, 3)
        x = x * (gain[:, None] * tint[None, :]).astype(np.float32)[:, :, None, None]
        mean = x.mean(axis=(1, 2, 3), keepdims=True)
        x = np.clip((x - mean) * np.float32(np.exp(u(self.contrast))) + mean, 0.0, 1.0)
        x = x ** np.float32(np.exp(u(self.gamma)))
        if self.haze > 0 and rng.random() < self.haze_prob:
            w = float(rng.uniform(0.0, self.haze))
            ramp = np.linspace(1.0, 0.4, h, dtype=np.float32)[None, None, :, None]
            air = np.float32(rng.uniform(150.0, 230.0) / 255.0)
            x = x + (air - x) * (w * ramp)
        if self.noise > 0:
            sigma = float(rng.uniform(0.0, self.noise)) / 255.0
            x = x + rng.normal(0.0, sigma, x.shape).astype(np.float32)
        return np.clip(np.rint(x * 255.0), 0, 255).astype(np.uint8)
