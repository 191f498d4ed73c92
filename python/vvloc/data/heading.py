"""A check of a session's yaw against its own positions: heading against direction of travel.

A car drives where it points: on straight stretches the direction of travel of its positions,
atan2(Δy, Δx), equals its yaw up to a small sideslip. A constant offset between the two says
that the yaw and the positions are not in one frame: a yaw measured from true north beside
UTM grid coordinates (the grid convergence, about 1.4° at Oxford), a yaw of a sensor mounted
turned on the car. Every relative translation then turns by that offset. :func:`heading_offset`
measures it; the NCLT and Oxford readers warn when a session's is large. (A mirrored yaw
shows only on diagonal stretches: along the axes it looks like driving backwards, which is
left out.)
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from vvloc.geometry import wrap_angle

#: The readers warn when a session's median offset exceeds this, degrees.
WARN_OFFSET_DEG = 0.5
#: ... and has at least this many straight stretches behind it (of 2 m: 40 m of straight road).
MIN_STRETCHES = 20


def heading_offset(
    poses: npt.ArrayLike, *, step: float = 2.0, max_turn_deg: float = 1.0
) -> tuple[float, int]:
    """The median of yaw − direction of travel over a session's straight stretches.

    Args:
        poses: (N, 3) float ego poses (x, y metres; yaw radians, CCW from +x) in time order,
            world frame (DESIGN.md §3).
        step: length of a stretch, metres: the path is cut, as driven, into stretches from
            one pose to the first at least ``step`` further along (shorter ones leave position
            noise in the direction); they do not overlap.
        max_turn_deg: a stretch counts when its yaw changes by at most this much, degrees
            (straight driving, where heading and direction of travel agree).

    Returns:
        ``(offset_deg, count)``: the median over the counted stretches of
        wrap(mean yaw − atan2(Δy, Δx)) in degrees (NaN when none counts), and their number.
        Stretches driven backwards (offset beyond ±90°) are left out.
    """
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"poses: expected shape (N, 3), got {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError("poses: holds non-finite values (NaN or inf)")
    if not (np.isfinite(step) and step > 0):
        raise ValueError(f"step: expected a finite length > 0 m, got {step}")
    along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(p[:, :2], axis=0).T))])
    # stretches end to end along the path as driven: each from the end of the one before to
    # the first pose at least `step` further (independent samples, however dense the poses)
    nxt = np.searchsorted(along, along + step, side="left")
    starts = []
    k = 0
    while k < len(p) and nxt[k] < len(p):
        starts.append(k)
        # nxt[k] > k unless `along` is so large that adding `step` no longer changes it (past
        # ~1e16 m): that stretch then ends where it starts and does not count
        k = max(int(nxt[k]), k + 1)
    i = np.array(starts, dtype=np.int64)
    j = nxt[i]
    d = p[j, :2] - p[i, :2]
    far = np.hypot(d[:, 0], d[:, 1]) >= 0.5 * step  # not a loop back to the start
    turn = wrap_angle(p[j, 2] - p[i, 2])
    straight = far & (np.abs(turn) <= np.radians(max_turn_deg))
    heading = p[i, 2] + 0.5 * turn
    offset = wrap_angle(heading - np.arctan2(d[:, 1], d[:, 0]))[straight]
    offset = offset[np.abs(offset) < np.pi / 2]  # reversing
    if offset.size == 0:
        return float("nan"), 0
    return float(np.degrees(np.median(offset))), int(offset.size)


def heading_warning(
    name: str, poses: npt.ArrayLike, *, limit_deg: float = WARN_OFFSET_DEG
) -> str | None:
    """A warning text when session ``name``'s :func:`heading_offset` exceeds ``limit_deg``
    (degrees) over at least :data:`MIN_STRETCHES` stretches, else None."""
    offset, count = heading_offset(poses)
    if count < MIN_STRETCHES or abs(offset) <= limit_deg:
        return None
    return (
        f"session {name}: the yaw differs from the direction of travel by a median of "
        f"{offset:+.2f}° over {count} straight stretches; the yaw and the positions may not be "
        "in one frame (e.g. a yaw from true north beside UTM grid coordinates), and relative "
        "translations turn by that much (vvloc.data.heading)"
    )
