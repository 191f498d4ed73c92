"""Synthetic camera rigs: M pinhole cameras spread evenly around the vehicle."""

from __future__ import annotations

import math

import numpy as np

from vvloc._checks import finite_float, positive_float, positive_int
from vvloc.data.frame import Camera

RIG_NAMES = {
    4: ("front", "left", "rear", "right"),
    5: ("front", "front_left", "rear_left", "rear_right", "front_right"),
    6: ("front", "front_left", "rear_left", "rear", "rear_right", "front_right"),
}


def camera_to_ego(yaw: float, pitch: float, position: tuple[float, float, float]) -> np.ndarray:
    """4×4 OpenCV-camera → ego transform of a camera looking along ego azimuth ``yaw`` (rad,
    CCW from the vehicle's x axis), tilted down by ``pitch`` (rad), mounted at ``position`` (m)."""
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    z_c = np.array([cy * cp, sy * cp, -sp])  # optical axis
    x_c = np.array([sy, -cy, 0.0])  # image right
    y_c = np.cross(z_c, x_c)  # image down
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x_c, y_c, z_c])
    T[:3, 3] = position
    return T


def make_rig(
    num_cameras: int = 4,
    width: int = 160,
    height: int = 96,
    *,
    hfov_deg: float | None = None,
    pitch_deg: float = 10.0,
    mount_height: float = 1.6,
) -> list[Camera]:
    """A rig of ``num_cameras`` (4, 5 or 6; other counts get generic names) cameras.

    Camera k looks along azimuth 2πk/M (front first, then counter-clockwise: left before rear),
    mounted on the outline of a 2.0 m × 1.8 m box centred 1.3 m ahead of the ego origin (the
    rear axle centre projected to the ground, x forward; the front camera at x = 2.3 m, the
    rear one at x = 0.3 m) at ``mount_height``. Default horizontal field of view: 360°/M + 10°
    of overlap, at most 120° (so rigs of 1 or 2 cameras leave gaps between their views, and 3
    just cover the circle without overlap; pass
    ``hfov_deg`` up to 150° for wider lenses). Square pixels, principal point at the image
    centre ((W−1)/2, (H−1)/2). ``width``, ``height``: ints >= 8 pixels; ``hfov_deg``,
    ``pitch_deg`` (downward tilt) degrees; ``mount_height`` metres > 0 above the ground.
    """
    num_cameras = positive_int(num_cameras, "num_cameras")  # numpy ints too
    width, height = (positive_int(v, key, 8) for key, v in (("width", width), ("height", height)))
    pitch_deg = finite_float(pitch_deg, "pitch_deg")
    mount_height = positive_float(mount_height, "mount_height")  # "1.6" was cast silently
    if hfov_deg is not None:
        hfov_deg = finite_float(hfov_deg, "hfov_deg")
    fov = hfov_deg if hfov_deg is not None else min(360.0 / num_cameras + 10.0, 120.0)
    if not 10.0 <= fov <= 150.0:
        raise ValueError(f"hfov_deg: expected 10..150 degrees, got {fov}")
    f = (width / 2.0) / math.tan(math.radians(fov) / 2.0)
    K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    names = RIG_NAMES.get(num_cameras, tuple(f"cam{k}" for k in range(num_cameras)))
    cams = []
    for k, name in enumerate(names):
        yaw = 2.0 * math.pi * k / num_cameras
        # on the vehicle's outline: a 2.0 × 1.8 m box centred 1.3 m ahead of the origin
        c, s = math.cos(yaw), math.sin(yaw)
        scale = min(1.0 / max(abs(c), 1e-9), 0.9 / max(abs(s), 1e-9))
        pos = (1.3 + c * scale, s * scale, mount_height)
        cams.append(
            Camera(name, width, height, K, camera_to_ego(yaw, math.radians(pitch_deg), pos))
        )
    return cams
