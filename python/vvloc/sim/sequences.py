"""Drives through a world: smooth routes along the aisles, lateral offsets, reversals, keyframes.

A route is a closed loop of waypoints; corners are rounded with circular fillets and sampled
densely. Keyframes are taken every ``key_distance`` metres or ``key_yaw_deg`` degrees of heading
change, whichever comes first (as VVLoc keyframes its sequences).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vvloc._checks import finite_float, positive_float, positive_int, real_array


def _wrap(a: np.ndarray | float) -> np.ndarray | float:
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def sample_loop(waypoints: np.ndarray, radius: float = 4.0, step: float = 0.05) -> np.ndarray:
    """Dense samples (S, 4) of x, y (m), yaw (rad, in [−π, π): a sample heading the −x way
    reads −π), arclength (m) along a closed loop of ``waypoints`` (K, 2) m, K >= 3, each
    distinct from the next, with corners rounded by circular arcs of ``radius`` m (>= 0;
    shrunk where segments are short), sampled every ``step`` m (> 0)."""
    P = real_array(waypoints, "waypoints", "(K, 2)", 2, 2)
    k = len(P)
    if k < 3:
        raise ValueError(f"waypoints: expected (K>=3, 2), got {P.shape}")
    if (np.linalg.norm(P - np.roll(P, 1, axis=0), axis=1) == 0).any():
        raise ValueError("waypoints: a waypoint repeats the one before it (a segment of length 0)")
    radius, step = finite_float(radius, "radius"), positive_float(step, "step")
    if radius < 0:
        raise ValueError(f"radius: expected metres >= 0, got {radius}")
    corners = []
    for i in range(k):
        prev, cur, nxt = P[i - 1], P[i], P[(i + 1) % k]
        din = (cur - prev) / np.linalg.norm(cur - prev)
        dout = (nxt - cur) / np.linalg.norm(nxt - cur)
        theta = math.atan2(din[0] * dout[1] - din[1] * dout[0], float(din @ dout))
        half = min(float(np.linalg.norm(cur - prev)), float(np.linalg.norm(nxt - cur))) / 2
        t = min(radius * math.tan(abs(theta) / 2), half)
        r = t / math.tan(abs(theta) / 2) if abs(theta) > 1e-9 else 0.0
        corners.append((cur - din * t, cur + dout * t, din, theta, r))
    pts: list[np.ndarray] = []
    for i in range(k):
        a_prev = corners[i - 1][1]
        A, _B, din, theta, r = corners[i]
        seg = A - a_prev
        L = float(np.linalg.norm(seg))
        n = max(1, math.ceil(L / step))
        s = np.arange(n) / n
        h0 = math.atan2(din[1], din[0])
        pts.append(
            np.column_stack([a_prev[0] + s * seg[0], a_prev[1] + s * seg[1], np.full(n, h0)])
        )
        if r > 0:
            sign = 1.0 if theta > 0 else -1.0
            left = np.array([-din[1], din[0]])
            C = A + left * r * sign
            m = max(1, math.ceil(abs(theta) * r / step))
            phi = np.arange(m) / m * theta
            start = math.atan2(A[1] - C[1], A[0] - C[0])
            ang = start + phi
            pts.append(np.column_stack([C[0] + r * np.cos(ang), C[1] + r * np.sin(ang), h0 + phi]))
    xyh = np.concatenate(pts)
    d = np.linalg.norm(np.diff(xyh[:, :2], axis=0, append=xyh[:1, :2]), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(d[:-1])])
    xyh[:, 2] = _wrap(xyh[:, 2])
    return np.column_stack([xyh, arc])


@dataclass(frozen=True)
class Drive:
    """How one session drives a loop: lateral offset (m, + = left of the loop's direction),
    reversed direction, and a slow seeded lateral wobble of ``wobble`` m amplitude."""

    offset: float = 0.0
    reverse: bool = False
    wobble: float = 0.3
    seed: int = 0


def drive_keyframes(
    loop: np.ndarray,
    drive: Drive,
    count: int,
    *,
    key_distance: float = 2.0,
    key_yaw_deg: float = 5.0,
    speed: float = 5.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Keyframe poses (count, 3) x, y (m), yaw (rad, (−π, π]) and times (count,) s of laps
    around ``loop``, in the loop's world frame.

    ``loop`` are dense samples (S, 4) from :func:`sample_loop`. A keyframe is taken once the
    vehicle has moved ``key_distance`` m (>= 0) or turned ``key_yaw_deg`` degrees (>= 0) from
    the last, driving at ``speed`` m/s (> 0). Laps repeat until ``count`` (an int >= 1)
    keyframes are taken; each lap has its own wobble phase so laps do not coincide exactly.
    """
    count = positive_int(count, "count")  # 2.5 never equalled len: the whole lap was taken
    loop = real_array(loop, "loop", "(S, 4) from sample_loop", 2, 4)
    speed = positive_float(speed, "speed")
    for name, value in (("key_distance", key_distance), ("key_yaw_deg", key_yaw_deg)):
        if finite_float(value, name) < 0:
            raise ValueError(f"{name}: expected a value >= 0, got {value}")
    rng = np.random.default_rng([drive.seed, 3])
    phase = rng.uniform(0, 2 * np.pi, size=2)
    xy, yaw, arc = loop[:, :2], loop[:, 2], loop[:, 3]
    n = len(xy)
    lap_length = float(arc[-1] + np.linalg.norm(xy[0] - xy[-1]))
    left = np.column_stack([-np.sin(yaw), np.cos(yaw)])

    def positions(k: np.ndarray) -> np.ndarray:
        """Driven positions of global sample indices ``k`` (lap · n + index in the loop)."""
        lap, j = np.divmod(k, n)
        if drive.reverse:
            j = n - 1 - j
        # the wobble follows the distance driven in total, so laps differ and seams are smooth
        s = lap * lap_length + (lap_length - arc[j] if drive.reverse else arc[j])
        lat = drive.offset + drive.wobble * (
            0.6 * np.sin(2 * np.pi * s / 37.0 + phase[0])
            + 0.4 * np.sin(2 * np.pi * s / 13.0 + phase[1])
        )
        return xy[j] + left[j] * lat[:, None]

    out_p: list[np.ndarray] = []
    out_t: list[float] = []
    last: np.ndarray | None = None
    travelled = 0.0
    lap = 0
    while len(out_p) < count:
        k = np.arange(lap * n - 1, (lap + 1) * n + 1)
        ext = positions(np.maximum(k, 0))
        p = ext[1:-1]
        # the heading follows the driven path (the wobble included)
        tangent = ext[2:] - ext[:-2]
        h = np.arctan2(tangent[:, 1], tangent[:, 0])
        step = np.linalg.norm(p - ext[:-2], axis=1)
        if lap == 0:
            step[0] = 0.0
        for j in range(n):
            travelled += float(step[j])
            if last is None or (
                np.linalg.norm(p[j] - last[:2]) >= key_distance
                or abs(float(_wrap(h[j] - last[2]))) >= math.radians(key_yaw_deg)
            ):
                last = np.array([p[j, 0], p[j, 1], float(h[j])])
                out_p.append(last)
                out_t.append(travelled / speed)
                if len(out_p) == count:
                    break
        lap += 1
        if lap > 10_000:  # pragma: no cover - a degenerate loop
            raise RuntimeError("could not take keyframes on this loop")
    return np.array(out_p), np.array(out_t)
