"""How far one camera rig is from another: a query frame's from its map's, a map's from the rig
its model was trained on.

A network meets only the cameras it was trained with: each camera slot has its own learnt
embedding, and the image features depend on how many pixels an object covers (the focal length)
and on which way the camera looks. :func:`rig_difference` says, in words, where a rig leaves a
reference rig by more than a :class:`RigTolerance`; an empty string means "the same rig" within
it. Frames follow DESIGN.md §3 (ego x-forward/y-left/z-up, cameras OpenCV).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from vvloc._checks import positive_float, real_array
from vvloc.data.frame import Camera

__all__ = [
    "BELOW_TOLERANCE_M",
    "MAX_CAMERA_DISTANCE_M",
    "SAME_MAP",
    "SAME_MODEL",
    "RigTolerance",
    "describe_rig",
    "frame_extrinsics_warnings",
    "rig_difference",
    "rig_warnings",
    "without_levelling",
]


@dataclass(frozen=True)
class RigTolerance:
    """How far a rig may stray from a reference and still count as the same.

    ``size`` and ``focal`` are relative (0.1: 10 % of the reference's image width/height, of
    its fx/fy); ``principal`` is a share of the image size (cx and the skew of the width, cy of
    the height); ``angle`` (radians) and ``shift`` (metres) bound each camera's turn and move
    from where the reference has it in the ego frame.
    """

    size: float
    focal: float
    principal: float
    angle: float
    shift: float


#: A query frame against its map's rig (:class:`vvloc.Localizer`): the very rig, its
#: calibration to rounding, except that a frame's own extrinsics may differ by a tilting
#: vehicle's levelling (a few degrees) and motion compensation (speed × exposure gap, 0.4 m at
#: 14 m/s and 30 ms): 14° and 1 m. (The localizer also compares the frame with the turn and
#: shift common to all its cameras taken out, :func:`without_levelling`: steeper slopes and
#: faster travel.)
SAME_MAP = RigTolerance(size=0.0, focal=1e-3, principal=1e-3, angle=0.25, shift=1.0)

#: A map's rig against the rig the model was trained on: a recalibration or a copy of the rig on
#: another vehicle (focal lengths within 10 %, principal points within 5 % of the image, image
#: sizes within 10 %, cameras within 14° and 1 m) is the same rig to the networks; other
#: cameras, another image size or another mounting is not.
SAME_MODEL = RigTolerance(size=0.1, focal=0.1, principal=0.05, angle=0.25, shift=1.0)


def describe_rig(cameras: Sequence[Camera]) -> str:
    """A rig in a few words, e.g. ``"4 cameras of 160x96 px"``."""
    sizes = sorted({f"{c.width}x{c.height}" for c in cameras})
    n = len(cameras)
    return f"{n} camera{'' if n == 1 else 's'} of {' / '.join(sizes)} px"


#: The farthest a camera may sit from the ego origin (metres) before :func:`rig_warnings` reads
#: its translation as another unit (a long truck's cameras are within 10 m).
MAX_CAMERA_DISTANCE_M = 30.0
#: How far below the ego origin (metres) a camera may sit before :func:`rig_warnings` says so
#: (a camera at the origin's height, rounded: not below).
BELOW_TOLERANCE_M = 0.05


def rig_warnings(cameras: Sequence[Camera]) -> list[str]:
    """Warnings about extrinsics that no vehicle has, which a BEV network trains on without a
    word, one per camera at most: a camera farther than :data:`MAX_CAMERA_DISTANCE_M` from the
    ego origin (a translation in millimetres), below the ego origin (the ground under the
    vehicle: an ego → camera transform given for ``cam_to_ego``, or a dataset whose origin is
    above the ground), or seeing no ground at all: no ray of its image points below the
    horizon (another camera axis convention than OpenCV's, an inverted transform, or a camera
    that sees only sky). Each camera's ``cam_to_ego`` (4, 4) maps its OpenCV coordinates
    (x right, y down, z forward) to the ego frame (x forward, y left, z up, origin on the
    ground), metres (DESIGN.md §3). A frame's own extrinsics are checked against the rig by
    :func:`frame_extrinsics_warnings`; a plausible mounting in the wrong place (a transposed
    rotation that still looks down) passes."""
    hint = (
        "cam_to_ego maps camera coordinates (OpenCV: x right, y down, z forward) to the ego "
        "frame (x forward, y left, z up, origin on the ground), in metres (docs/dataset-format.md)"
    )
    notes = []
    for cam in cameras:
        centre = cam.cam_to_ego[:3, 3]
        far = float(np.linalg.norm(centre))
        if far > MAX_CAMERA_DISTANCE_M:
            notes.append(
                f"camera {cam.name!r} sits {far:.0f} m from the ego origin: millimetres? {hint}"
            )
            continue
        if centre[2] < -BELOW_TOLERANCE_M:
            notes.append(
                f"camera {cam.name!r} sits {-centre[2]:.2f} m below the ego origin (the ground "
                "under the vehicle): an ego -> camera transform, or an origin above the ground "
                f"(the NCLT and RobotCar readers' ego_height, vvloc convert --ego_height)? {hint}"
            )
            continue
        # the rays through the image's corners, in the ego frame: a ray's z is linear in the
        # pixel (u, v), so the image's lowest ray is one of them
        w, h = cam.width - 0.5, cam.height - 0.5
        corners = np.array([[-0.5, -0.5, 1.0], [w, -0.5, 1.0], [-0.5, h, 1.0], [w, h, 1.0]])
        rays = corners @ np.linalg.inv(cam.K).T @ cam.cam_to_ego[:3, :3].T
        if rays[:, 2].min() >= 0.0:
            look = cam.cam_to_ego[:3, 2]  # the optical axis in the ego frame
            notes.append(
                f"camera {cam.name!r} sees no ground: no ray of its image points below the "
                f"horizon (it looks along ego ({look[0]:.2f}, {look[1]:.2f}, {look[2]:.2f})): "
                f"another axis convention, or an inverted transform? (A camera that sees only "
                f"sky adds nothing to a BEV.) {hint}"
            )
    return notes


def _turns(
    rig: Sequence[Camera], rotations: npt.NDArray[np.float64]
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Each camera's turn of ``rig``'s mounting in N frames, ``L = R_frame R_rig^T`` (N, M, 3,
    3), the same for every camera of a frame that is the rig levelled, and the (lower) median
    of each camera's angles to the other cameras' turns (N, M) radians: with three cameras, one
    wrong camera leaves the others' low. ``rotations``: (N, M, 3, 3) the frames' camera → ego
    rotations; M ≥ 2."""
    m = len(rig)
    ref = np.stack([c.cam_to_ego[:3, :3] for c in rig])
    lift = np.einsum("nmij,mkj->nmik", rotations, ref)
    angle = _rotation_angle(np.einsum("naji,nbjk->nabik", lift, lift))  # L_a^T L_b
    others = angle[:, ~np.eye(m, dtype=bool)].reshape(len(lift), m, m - 1)
    return lift, np.sort(others, axis=2)[:, :, (m - 2) // 2]


def frame_extrinsics_warnings(
    cameras: Sequence[Camera], timestamps: npt.ArrayLike, cam_to_ego: npt.ArrayLike
) -> list[str]:
    """Warnings about frames whose own extrinsics no rig of these cameras has, one per camera
    at most, naming the first such frame: a camera farther than
    :data:`MAX_CAMERA_DISTANCE_M` from the ego origin (millimetres), or one turned by more than
    :data:`SAME_MAP`'s angle (14°) against the frame's other cameras, measured from how the
    rig turns them against each other (an inverted transform, another camera's rows).

    Levelling a tilting vehicle turns every camera of a frame alike (about the ego origin, so
    far cameras move most), and motion compensation moves each camera by the vehicle's travel
    between exposures: neither changes how the cameras are turned against each other, so both
    pass whatever the slope and speed. A camera is named when the (lower) median of its turns
    against the others' exceeds the angle: one wrong camera of three or more is named alone
    (of two, both are). A one-camera rig gets the distance check alone.

    Args:
        cameras: the rig, M cameras in image order (``rig.json``).
        timestamps: (N,) int the frames' timestamps (microseconds), named in the warnings.
        cam_to_ego: (N, M, 4, 4) float each frame's camera → ego transforms, metres.
    """
    stamps = np.asarray(timestamps)
    t = np.asarray(cam_to_ego, dtype=np.float64)
    if stamps.ndim != 1:
        raise ValueError(f"timestamps: expected shape (N,), got {stamps.shape}")
    if t.shape != (len(stamps), len(cameras), 4, 4):
        raise ValueError(
            f"cam_to_ego: expected ({len(stamps)}, {len(cameras)}, 4, 4) for {len(stamps)} "
            f"timestamps and {len(cameras)} cameras, got {t.shape}"
        )
    n, m = t.shape[:2]
    far = np.linalg.norm(t[:, :, :3, 3], axis=2) > MAX_CAMERA_DISTANCE_M  # (N, M)
    worst = np.zeros((n, m))
    if m > 1:
        _, worst = _turns(cameras, t[:, :, :3, :3])
    turned = worst > SAME_MAP.angle
    notes = []
    for c, cam in enumerate(cameras):
        off = far[:, c] | turned[:, c]
        if not off.any():
            continue
        k = int(np.argmax(off))
        if far[k, c]:
            dist = float(np.linalg.norm(t[k, c, :3, 3]))
            why = f"{dist:.0f} m from the ego origin: millimetres?"
        else:
            why = (
                f"turned by {np.degrees(worst[k, c]):.0f}° against the frame's other cameras, "
                f"beyond {np.degrees(SAME_MAP.angle):.0f}° from how the rig turns them: an "
                "inverted transform, or another camera's rows?"
            )
        notes.append(
            f"{int(off.sum())} of {n} frames give camera {cam.name!r} a mounting no rig of "
            f"these cameras has (first at timestamp {int(stamps[k])}: {why})"
        )
    return notes


#: The largest turn (radians) and shift (metres) of a whole rig that :func:`without_levelling`
#: takes for a tilting vehicle's levelling and motion compensation: beyond any slope a vehicle
#: drives (``vvloc sim`` tilts up to 30°) or its travel between two cameras' exposures.
MAX_LEVELLING = (np.radians(35.0), 3.0)


def without_levelling(reference: Sequence[Camera], cam_to_ego: npt.ArrayLike) -> np.ndarray:
    """A frame's own extrinsics with the turn and shift they give every camera of
    ``reference`` alike taken out: (M, 4, 4) float64 camera → ego transforms, metres.

    Levelling a tilting vehicle's ego frame turns all its cameras about the ego origin, and
    motion compensation moves them by the vehicle's travel: a frame of ``reference``'s rig then
    comes back as ``reference``'s own mountings, and a camera mounted otherwise stays off. The
    common turn is the one of the camera that agrees best with the others (the lowest median
    turn against theirs), the shift the median camera's; ``cam_to_ego`` is returned as it is
    when that turn exceeds 35° or that shift 3 m (:data:`MAX_LEVELLING`: no vehicle's), or the
    rig has one camera (its levelling cannot be told from its mounting) or another camera count.
    """
    t = np.asarray(cam_to_ego, dtype=np.float64)
    m = len(reference)
    if m < 2 or t.shape != (m, 4, 4):
        return t
    lift, spread = _turns(reference, t[None, :, :3, :3])
    turn = lift[0, int(np.argmin(spread[0]))]
    ref = np.stack([c.cam_to_ego for c in reference])
    shift = np.median(t[:, :3, 3] - ref[:, :3, 3] @ turn.T, axis=0)
    if _rotation_angle(turn) > MAX_LEVELLING[0] or np.linalg.norm(shift) > MAX_LEVELLING[1]:
        return t
    undo = np.eye(4)
    undo[:3, :3] = turn.T
    undo[:3, 3] = -turn.T @ shift
    return undo @ t


def _alike(
    k: npt.NDArray[np.float64],
    t: npt.NDArray[np.float64],
    ref_k: npt.NDArray[np.float64],
    ref_t: npt.NDArray[np.float64],
    ref_size: tuple[int, int],
    tolerance: RigTolerance,
) -> npt.NDArray[np.bool_]:
    """(M, M) bool: compared camera i (``k[i]``, ``t[i]``) within ``tolerance`` of reference
    camera j in intrinsics and mounting."""
    w, h = ref_size
    focal = np.abs(k[:, None, [0, 1], [0, 1]] / ref_k[None, :, [0, 1], [0, 1]] - 1.0)
    offset = np.abs(k[:, None, [0, 1, 0], [2, 2, 1]] - ref_k[None, :, [0, 1, 0], [2, 2, 1]])
    offset /= np.array([w, h, w])
    d = np.linalg.inv(ref_t)[None] @ t[:, None]  # camera i in reference camera j's frame
    return (
        (focal <= tolerance.focal).all(axis=2)
        & (offset <= tolerance.principal).all(axis=2)
        & (_rotation_angle(d[..., :3, :3]) <= tolerance.angle)
        & (np.linalg.norm(d[..., :3, 3], axis=2) <= tolerance.shift)
    )


def _matching(same: npt.NDArray[np.bool_]) -> list[int] | None:
    """A one-to-one assignment ``order[i] = j`` with ``same[i, j]`` for every row i of the
    (M, M) ``same``, or None (augmenting paths: O(M³))."""
    m = len(same)
    owner = [-1] * m  # owner[j]: the row assigned to column j

    def augment(i: int, seen: list[bool]) -> bool:
        for j in np.flatnonzero(same[i]).tolist():
            if not seen[j]:
                seen[j] = True
                if owner[j] < 0 or augment(owner[j], seen):
                    owner[j] = i
                    return True
        return False

    if not all(augment(i, [False] * m) for i in range(m)):
        return None
    order = [0] * m
    for j, i in enumerate(owner):
        order[i] = j
    return order


def _rotation_angle(r: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Angles (radians) of rotation matrices (..., 3, 3)."""
    cos = (np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1.0, 1.0))


def _entries(k: npt.NDArray[np.float64], what: str) -> list[float]:
    """The entries of one K (3, 3) that ``what`` names ("fx, fy" or "cx, cy, skew")."""
    if what == "fx, fy":
        return [float(k[0, 0]), float(k[1, 1])]
    return [float(k[0, 2]), float(k[1, 2]), float(k[0, 1])]


def rig_difference(
    reference: Sequence[Camera],
    K: npt.ArrayLike,
    cam_to_ego: npt.ArrayLike,
    size: tuple[int, int],
    tolerance: RigTolerance,
) -> str:
    """Where a rig leaves ``reference`` by more than ``tolerance``, in words ("" when it does
    not): the first of camera count, image size, camera order (the reference's cameras, each
    within ``tolerance``, listed in another order), intrinsics, mounting that differs.

    Args:
        reference: the reference rig's cameras, in image order (one image size: a vvloc rig).
        K: (M, 3, 3) intrinsics of the rig compared, pixels, image order.
        cam_to_ego: (M, 4, 4) camera-to-ego transforms of the rig compared, metres.
        size: (width, height) of the compared rig's images, pixels.
        tolerance: how far counts as the same rig (:data:`SAME_MAP`, :data:`SAME_MODEL`).
    """
    if not reference:
        raise ValueError("reference: expected at least one camera")
    k = real_array(K, "K", "(M, 3, 3)", 3)  # finite: NaN compared as 'the same rig'
    t = real_array(cam_to_ego, "cam_to_ego", "(M, 4, 4)", 3)
    if k.shape[1:] != (3, 3):
        raise ValueError(f"K: expected shape (M, 3, 3), got {k.shape}")
    if t.shape != (len(k), 4, 4):  # (1, 4, 4) was broadcast over every camera
        raise ValueError(f"cam_to_ego: expected shape ({len(k)}, 4, 4) like K, got {t.shape}")
    if not isinstance(size, (tuple, list)) or len(size) != 2:
        raise TypeError(f"size: expected (width, height) pixels, got {size!r}")
    for v in size:  # finite, > 0: inf compared as "another size" in words of inf
        positive_float(v, "size")
    width, height = size  # as given: 80x48, not 80.0x48.0, in the message
    m = len(reference)
    if k.shape[0] != m:
        return f"{k.shape[0]} cameras, against {m}"
    ref_w, ref_h = reference[0].width, reference[0].height
    if abs(width - ref_w) > tolerance.size * ref_w or abs(height - ref_h) > tolerance.size * ref_h:
        return f"images of {width}x{height} px, against {ref_w}x{ref_h}"
    ref_k = np.stack([c.K for c in reference])
    ref_t = np.stack([c.cam_to_ego for c in reference])
    same = _alike(k, t, ref_k, ref_t, (ref_w, ref_h), tolerance)  # (M, M): camera i as ref j
    if not same.diagonal().all():
        order = _matching(same)
        if order is not None:
            pairs = [(i, j) for i, j in enumerate(order) if i != j]
            moved = ", ".join(f"this rig's camera {i} is the other's camera {j}" for i, j in pairs)
            return (
                f"the same cameras in another order: {moved}; list them in the other rig's "
                "order, e.g. with vvloc convert --cameras"
            )
    # fx, fy relative to the reference's; cx, cy and the skew as shares of the image size
    focal = np.abs(k[:, [0, 1], [0, 1]] / ref_k[:, [0, 1], [0, 1]] - 1.0)
    offset = np.abs(k[:, [0, 1, 0], [2, 2, 1]] - ref_k[:, [0, 1, 0], [2, 2, 1]])
    offset /= np.array([ref_w, ref_h, ref_w])
    for values, bound, what in (
        (focal, tolerance.focal, "fx, fy"),
        (offset, tolerance.principal, "cx, cy, skew"),
    ):
        if (values > bound).any():
            i = int(np.argmax(values.max(axis=1)))
            ours = ", ".join(f"{v:.1f}" for v in _entries(k[i], what))
            theirs = ", ".join(f"{v:.1f}" for v in _entries(ref_k[i], what))
            return f"other intrinsics (camera {i}: {what} {ours} px against {theirs})"
    # each compared camera in the reference camera's frame: a turn and a move
    ego_to_ref = np.linalg.inv(np.stack([c.cam_to_ego for c in reference]))
    d = ego_to_ref @ t
    angle = _rotation_angle(d[:, :3, :3])
    shift = np.linalg.norm(d[:, :3, 3], axis=1)
    if (angle > tolerance.angle).any() or (shift > tolerance.shift).any():
        return (
            f"cameras turned by up to {np.degrees(angle.max()):.1f}° and moved by up to "
            f"{shift.max():.2f} m from where the other rig has them"
        )
    return ""
