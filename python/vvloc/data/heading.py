"""A check of a session's yaw against its own positions: heading against direction of travel.

A car drives where it points: on straight stretches the direction of travel of its positions,
atan2(Δy, Δx), equals its yaw up to a small sideslip. A constant offset between the two says
that the yaw and the positions are not in one frame: a yaw measured from true north beside
UTM grid coordinates (the grid convergence, about 1.4° at Oxford), a yaw of a sensor mounted
turned on the car. Every relative translation then turns by that offset. :func:`heading_offset`
measures it; the NCLT and Oxford readers warn when a session's is large. A compass heading
(clockwise from north, 90° minus the yaw) is no constant offset: it is the yaw mirrored about
the diagonal, off the direction of travel by 90° − 2 × that direction, ±90° along the axes and
0 on the diagonals; a clockwise yaw (a flipped y axis) is the yaw mirrored about the x axis.
:func:`compass_fit` tests the compass shape directly, whatever the roads' directions, and
:func:`mirror_fit` any mirror, telling it from a constant offset on roads along two axes too
(where the two agree up to a half turn); :func:`heading_warning` says which it finds.
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
        Stretches driven backwards (more than 90° off the direction most stretches give) are
        left out: a car drives forwards mostly, so a whole session "driven backwards" is a yaw
        whose axis points to the rear, measured as an offset of about 180°.
    """
    return _offset(*_straight_stretches(poses, step, max_turn_deg))


def _offset(heading: np.ndarray, travel: np.ndarray) -> tuple[float, int]:
    """:func:`heading_offset` of the stretches' mean yaws and directions of travel."""
    offset = wrap_angle(heading - travel)
    if offset.size == 0:
        return float("nan"), 0
    # about the direction most stretches give (0 for a car that drives where its yaw points,
    # the half turn for a yaw whose axis points to the rear); the others were driven backwards
    centre = _centre(offset)
    about = wrap_angle(offset - centre)
    kept = about[np.abs(about) < np.pi / 2]
    return float(np.degrees(wrap_angle(centre + np.median(kept)))), int(kept.size)


def _centre(x: np.ndarray) -> float:
    """The direction (radians) most of the angles ``x`` point to: the axis of their doubled
    angles' circular mean (an angle and its reverse agree on it), at the end holding more."""
    axis = float(np.angle(np.exp(2j * x).sum())) / 2.0
    near = np.abs(wrap_angle(x - axis)) < np.pi / 2
    return axis if 2 * near.sum() >= x.size else float(wrap_angle(axis + np.pi))


def _spread_deg(x: np.ndarray, centre: float) -> float:
    """The median distance (degrees) of the angles ``x`` from the axis through ``centre``,
    modulo 180° (a stretch driven backwards fits as well)."""
    return float(np.degrees(np.median(np.abs(wrap_angle(2.0 * (x - centre))) / 2.0)))


def _half_open(deg: float) -> float:
    """``deg`` rounded to 0.1°, in (−180°, 180°] (a half turn printed as 180.0, never −180.0)."""
    r = round(deg, 1)
    return 180.0 if r <= -180.0 else r


def _reversing(x: np.ndarray, centre: float) -> int:
    """How many of the angles ``x`` lie more than 90° from ``centre``: the stretches a reading
    with that centre takes as driven backwards."""
    return int(np.count_nonzero(np.abs(wrap_angle(x - centre)) > np.pi / 2))


def mirror_fit(
    poses: npt.ArrayLike, *, step: float = STEP_M, max_turn_deg: float = MAX_TURN_DEG
) -> tuple[float, bool, int]:
    """Whether a session's yaw reads as a *mirrored* angle, c − τ for one constant c, rather
    than the format's τ + offset (τ: the direction of travel of its straight stretches, those
    of :func:`heading_offset`). c = 90° is a compass heading (clockwise from north), c = 0 a
    clockwise yaw (a flipped y axis); any other c a clockwise angle from another axis.

    Decided in two steps. Modulo 180° (a stretch driven backwards fits either way): the
    mirror fits within :data:`COMPASS_FIT_DEG` and a constant offset is at least
    :data:`COMPASS_MISFIT_DEG` off (medians over the stretches). Where both fit modulo 180°
    (roads along one axis, or along two perpendicular ones, where c − τ and τ + c′ agree up to
    a half turn), by full angles: a car drives forwards mostly, so the mirror must take at least
    a tenth of the stretches fewer as driven backwards (more than 90° off the direction most
    stretches give) than the offset. On roads of one direction that never holds (the two
    readings reverse the same stretches): a mirrored yaw there reads as an offset. On a grid
    driven partly in reverse gear the two can trade places (a clockwise yaw with the north legs
    reversed is a correct one with the south legs reversed): the offset is then said.

    Returns ``(c_deg, mirrored, count)``: the mirror's constant (degrees, in (−180°, 180°]),
    the verdict, and the number of stretches (NaN, False, 0 without any).
    """
    return _mirror(*_straight_stretches(poses, step, max_turn_deg))


def _mirror(heading: np.ndarray, travel: np.ndarray) -> tuple[float, bool, int]:
    """:func:`mirror_fit` of the stretches' mean yaws and directions of travel."""
    n = int(heading.size)
    if n == 0:
        return float("nan"), False, 0
    offset, flipped = wrap_angle(heading - travel), wrap_angle(heading + travel)
    c_off, c_mir = _centre(offset), _centre(flipped)
    mir_spread, off_spread = _spread_deg(flipped, c_mir), _spread_deg(offset, c_off)
    if mir_spread > COMPASS_FIT_DEG:
        mirrored = False
    elif off_spread >= COMPASS_MISFIT_DEG:
        mirrored = True
    elif off_spread > COMPASS_FIT_DEG:
        mirrored = False  # in between: neither reading is clear
    else:
        # Both fit modulo 180°: roads along one axis, or along two perpendicular ones. A car
        # drives forwards mostly, so the mirror is taken only when it has at least a tenth of
        # the stretches fewer driven backwards than the offset; on roads of one direction the
        # two readings reverse the same stretches, and the offset stands.
        mirrored = _reversing(offset, c_off) - _reversing(flipped, c_mir) >= max(1.0, 0.1 * n)
    return float(np.degrees(c_mir)), bool(mirrored), n


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
    """A warning text when session ``name``'s yaw reads as mirrored (:func:`mirror_fit`:
    named a compass heading when its constant is 90°, a clockwise yaw when 0, within
    :data:`COMPASS_FIT_DEG`), or when its :func:`heading_offset` exceeds ``limit_deg``
    (degrees, any size up to 180°), each over at least :data:`MIN_STRETCHES` stretches; else
    None. ``poses`` (N, 3) world x, y (m), yaw (rad), in time order."""
    stretches = _straight_stretches(poses, STEP_M, MAX_TURN_DEG)  # once, for every test
    c_mir, mirrored, n = _mirror(*stretches)
    if n >= MIN_STRETCHES and mirrored:
        travel, compass, _ = _compass(*stretches)
        if abs(float(np.degrees(wrap_angle(np.radians(c_mir - 90.0))))) <= COMPASS_FIT_DEG:
            return (
                f"session {name}: the yaw reads as a compass heading (clockwise from north): "
                f"over {n} straight stretches it lies a median of {compass:.1f}° from 90° minus "
                f"the direction of travel and {travel:.1f}° from the direction itself; every "
                "relative pose turns with it (vvloc.data.heading)"
            )
        what = (
            "clockwise (the y axis flipped): the negated direction of travel"
            if abs(c_mir) <= COMPASS_FIT_DEG
            else f"clockwise: {_half_open(c_mir):.1f}° minus the direction of travel"
        )
        return (
            f"session {name}: the yaw reads as {what}, over {n} straight stretches, not "
            "counter-clockwise from the world's x axis; every relative pose turns with it "
            "(vvloc.data.heading)"
        )
    offset, count = _offset(*stretches)
    if count < MIN_STRETCHES or abs(offset) <= limit_deg:
        return None
    askew = (
        " (the yaw's x axis is not the vehicle's forward: a sensor's frame taken for the "
        "vehicle's?)"
        if abs(offset) > 45.0
        else ""
    )
    return (
        f"session {name}: the yaw differs from the direction of travel by a median of "
        f"{offset:+.2f}° over {count} straight stretches{askew}; the yaw and the positions "
        "may not be in one frame (e.g. a yaw from true north beside UTM grid coordinates), and "
        "relative translations turn by that much (vvloc.data.heading)"
    )
