"""A check of a session's yaw against its own positions: heading against direction of travel.

A car drives where it points: on straight stretches the direction of travel of its positions,
atan2(Δy, Δx), equals its yaw up to a small sideslip. A constant offset between the two says
that the yaw and the positions are not in one frame: a yaw measured from true north beside
UTM grid coordinates (the grid convergence, about 1.4° at Oxford), a yaw of a sensor mounted
turned on the car. Every relative translation then turns by that offset. :func:`heading_offset`
measures it; the NCLT and Oxford readers warn when a session's is large. A compass heading
(clockwise from north, 90° minus the yaw) is no constant offset: it is the yaw mirrored about
the diagonal, off the direction of travel by 90° − 2 × that direction, ±90° along the axes,
where :func:`heading_offset` leaves it out with the stretches driven backwards, and 0 on the
diagonals. :func:`compass_fit` tests that shape directly, whatever the roads' directions.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from vvloc.geometry import wrap_angle

#: The readers warn when a session's median offset exceeds this, degrees.
WARN_OFFSET_DEG = 0.5
#: ... and has at least this many straight stretches behind it (of 2 m: 40 m of straight road).
MIN_STRETCHES = 20
#: A session's yaw reads as a compass heading when, over its straight stretches (driven
#: forwards or backwards), it lies a median of at most ``COMPASS_FIT_DEG`` from 90° minus the
#: direction of travel and at least ``COMPASS_MISFIT_DEG`` from the direction itself (degrees).
COMPASS_FIT_DEG = 5.0
COMPASS_MISFIT_DEG = 20.0
#: The stretches' length (metres) and the most they may turn (degrees) to count as straight.
STEP_M = 2.0
MAX_TURN_DEG = 1.0


def heading_offset(
    poses: npt.ArrayLike, *, step: float = STEP_M, max_turn_deg: float = MAX_TURN_DEG
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
    return _offset(*_straight_stretches(poses, step, max_turn_deg))


def _offset(heading: np.ndarray, travel: np.ndarray) -> tuple[float, int]:
    """:func:`heading_offset` of the stretches' mean yaws and directions of travel."""
    offset = wrap_angle(heading - travel)
    offset = offset[np.abs(offset) < np.pi / 2]  # reversing
    if offset.size == 0:
        return float("nan"), 0
    return float(np.degrees(np.median(offset))), int(offset.size)


def compass_fit(
    poses: npt.ArrayLike, *, step: float = STEP_M, max_turn_deg: float = MAX_TURN_DEG
) -> tuple[float, float, int]:
    """How well a session's yaw fits its direction of travel τ, and how well a compass
    heading's, 90° − τ, over its straight stretches (those of :func:`heading_offset`, driven
    forwards or backwards: each residual is taken modulo 180°, in [0°, 90°]).

    Returns ``(travel_deg, compass_deg, count)``: the median residuals against τ and against
    90° − τ, degrees (NaN when no stretch counts), and the number of stretches. A yaw in the
    format's convention has a small first one; a compass heading a small second and, unless
    every road runs diagonally (where the two agree), a large first."""
    return _compass(*_straight_stretches(poses, step, max_turn_deg))


def _compass(heading: np.ndarray, travel: np.ndarray) -> tuple[float, float, int]:
    """:func:`compass_fit` of the stretches' mean yaws and directions of travel."""
    if heading.size == 0:
        return float("nan"), float("nan"), 0

    def residual(expected: np.ndarray) -> float:
        r = np.abs(wrap_angle(2.0 * (heading - expected))) / 2.0  # modulo 180°: reversing too
        return float(np.degrees(np.median(r)))

    return residual(travel), residual(np.pi / 2 - travel), int(heading.size)


def _straight_stretches(
    poses: npt.ArrayLike, step: float, max_turn_deg: float
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """The mean yaw and the direction of travel atan2(Δy, Δx) (radians) of each straight
    stretch of :func:`heading_offset` (reversing ones included)."""
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
    return heading[straight], np.arctan2(d[:, 1], d[:, 0])[straight]


def heading_warning(
    name: str, poses: npt.ArrayLike, *, limit_deg: float = WARN_OFFSET_DEG
) -> str | None:
    """A warning text when session ``name``'s yaw reads as a compass heading
    (:func:`compass_fit`: within :data:`COMPASS_FIT_DEG` of 90° minus the direction of travel,
    at least :data:`COMPASS_MISFIT_DEG` off the direction), or when its
    :func:`heading_offset` exceeds ``limit_deg`` (degrees), each over at least
    :data:`MIN_STRETCHES` stretches; else None."""
    stretches = _straight_stretches(poses, STEP_M, MAX_TURN_DEG)  # once, for both tests
    travel, compass, n = _compass(*stretches)
    if n >= MIN_STRETCHES and compass <= COMPASS_FIT_DEG and travel >= COMPASS_MISFIT_DEG:
        return (
            f"session {name}: the yaw reads as a compass heading (clockwise from north): over "
            f"{n} straight stretches it lies a median of {compass:.1f}° from 90° minus the "
            f"direction of travel and {travel:.1f}° from the direction itself; every relative "
            "pose turns with it (vvloc.data.heading)"
        )
    offset, count = _offset(*stretches)
    if count < MIN_STRETCHES or abs(offset) <= limit_deg:
        return None
    return (
        f"session {name}: the yaw differs from the direction of travel by a median of "
        f"{offset:+.2f}° over {count} straight stretches; the yaw and the positions may not be "
        "in one frame (e.g. a yaw from true north beside UTM grid coordinates), and relative "
        "translations turn by that much (vvloc.data.heading)"
    )
