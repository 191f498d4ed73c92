"""Rig comparison (vvloc.data.rig) on hand-made rigs: what counts as the same rig to a map and to
a model, and what the difference is called."""

from __future__ import annotations

import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vvloc.data import Camera
from vvloc.data.frame import stack_calibration
from vvloc.data.rig import SAME_MAP, SAME_MODEL, describe_rig, rig_difference

# OpenCV camera axes (x right, y down, z forward) in the ego frame (x forward, y left, z up) of
# a camera looking forward
FORWARD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _camera(name: str, yaw_deg: float, width: int = 160, height: int = 96) -> Camera:
    """A level camera 1.5 m up at the vehicle's centre, looking ``yaw_deg`` left of forward."""
    t = np.eye(4)
    t[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix() @ FORWARD
    t[2, 3] = 1.5
    f = 0.6 * width
    K = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return Camera(name, width, height, K, t)


RIG = [_camera(n, yaw) for n, yaw in (("front", 0), ("left", 90), ("back", 180), ("right", -90))]


def _difference(cameras: list[Camera], tolerance=SAME_MODEL) -> str:
    K, cam_to_ego = stack_calibration(cameras)
    return rig_difference(RIG, K, cam_to_ego, (cameras[0].width, cameras[0].height), tolerance)


def _with(i: int, *, K=None, turn_deg: float = 0.0, move: float = 0.0) -> list[Camera]:
    """RIG with camera ``i`` given ``K``, turned about ego z and moved along ego x."""
    cams = list(RIG)
    c = cams[i]
    t = c.cam_to_ego.copy()
    t[:3, :3] = Rotation.from_euler("z", turn_deg, degrees=True).as_matrix() @ t[:3, :3]
    t[0, 3] += move
    cams[i] = Camera(c.name, c.width, c.height, c.K if K is None else K, t)
    return cams


@pytest.mark.parametrize("tolerance", [SAME_MAP, SAME_MODEL])
def test_a_rig_is_the_same_as_itself(tolerance):
    assert _difference(list(RIG), tolerance) == ""
    assert describe_rig(RIG) == "4 cameras of 160x96 px"
    assert describe_rig(RIG[:1]) == "1 camera of 160x96 px"


def test_another_camera_count_or_image_size_is_another_rig():
    assert _difference(RIG[:3]) == "3 cameras, against 4"
    # the same cameras for images of half the size: the same geometry, other pixels
    half = [c.resized(80, 48) for c in RIG]
    assert _difference(half) == "images of 80x48 px, against 160x96"
    # a few pixels of cropping are not, to a model; to a map (the very rig) they are
    cropped = [c.resized(156, 96) for c in RIG]
    assert _difference(cropped, SAME_MODEL) == ""
    assert _difference(cropped, SAME_MAP) == "images of 156x96 px, against 160x96"


def test_a_recalibration_is_the_same_rig_to_a_model_but_not_to_a_map():
    K = RIG[2].K.copy()
    K[0, 0] *= 1.05  # fx 5 % longer
    K[1, 2] += 3.0  # cy 3 px lower (3 % of the height)
    assert _difference(_with(2, K=K, turn_deg=3.0, move=0.2), SAME_MODEL) == ""
    assert _difference(_with(2, K=K), SAME_MAP).startswith("other intrinsics (camera 2: fx, fy")
    # focal length 20 % longer (a narrower lens) is another camera, named by its index
    K[0, 0] = K[1, 1] = 1.2 * RIG[2].K[0, 0]
    assert _difference(_with(2, K=K)) == (
        "other intrinsics (camera 2: fx, fy 115.2, 115.2 px against 96.0, 96.0)"
    )
    # a principal point 10 % of the width off
    K = RIG[1].K.copy()
    K[0, 2] += 16.0
    assert _difference(_with(1, K=K)) == (
        "other intrinsics (camera 1: cx, cy, skew 95.5, 47.5, 0.0 px against 79.5, 47.5, 0.0)"
    )
    # a skewed K (another camera model, a transposed calibration) is not the map's rig
    K = RIG[3].K.copy()
    K[0, 1] = 2.0
    assert _difference(_with(3, K=K), SAME_MODEL) == ""
    assert "camera 3: cx, cy, skew 79.5, 47.5, 2.0 px" in _difference(_with(3, K=K), SAME_MAP)


def test_another_mounting_is_another_rig():
    # within 14° and 1 m: a levelled tilting vehicle's frame, a rig copied on another vehicle
    assert _difference(_with(0, turn_deg=10.0, move=0.9)) == ""
    assert _difference(_with(3, turn_deg=20.0)) == (
        "cameras turned by up to 20.0° and moved by up to 0.00 m from where the other rig has them"
    )
    assert _difference(_with(1, move=1.5)).endswith(
        "moved by up to 1.50 m from where the other rig has them"
    )
    # the same cameras in another order: slots 0 and 2 hold each other's camera (180° apart),
    # said as such (test_the_same_cameras_in_another_order_are_named_so)
    assert _difference([RIG[2], RIG[1], RIG[0], RIG[3]]).startswith(
        "the same cameras in another order: this rig's camera 0 is the other's camera 2, this "
        "rig's camera 2 is the other's camera 0;"
    )


def test_calibration_that_cannot_be_compared_is_refused_not_called_the_same_rig():
    K, cam_to_ego = stack_calibration(RIG)
    size = (160, 96)
    k_nan = K.copy()
    k_nan[0, 0, 0] = np.nan
    t_nan = cam_to_ego.copy()
    t_nan[1, 0, 3] = np.nan
    for args, error, match in (
        ((k_nan, cam_to_ego, size), ValueError, r"^K: contains non-finite"),  # was ""
        ((K, t_nan, size), ValueError, r"^cam_to_ego: contains non-finite"),  # was ""
        ((K, cam_to_ego, (float("nan"), 96)), ValueError, r"^size: expected a finite"),  # was ""
        ((K, cam_to_ego, (float("inf"), 96)), ValueError, r"^size: expected a finite"),
        ((K, cam_to_ego[:1], size), ValueError, r"^cam_to_ego: expected shape \(4, 4, 4\)"),
        ((K[0], cam_to_ego, size), ValueError, r"^K: expected shape \(M, 3, 3\)"),
        ((K, cam_to_ego, (160,)), TypeError, r"^size: expected \(width, height\)"),
    ):
        with pytest.raises(error, match=match):
            rig_difference(RIG, *args, SAME_MODEL)
    with pytest.raises(ValueError, match=r"^reference: expected at least one camera"):
        rig_difference([], K, cam_to_ego, size, SAME_MODEL)


def _mounted(T: np.ndarray) -> list[Camera]:
    """RIG's front camera with ``cam_to_ego`` T, the other three as they are."""
    c = RIG[0]
    return [Camera(c.name, c.width, c.height, c.K, T), *RIG[1:]]


def test_rig_warnings_name_extrinsics_no_vehicle_has():
    from vvloc.data.rig import rig_warnings

    assert rig_warnings(RIG) == []
    front = RIG[0].cam_to_ego.copy()  # 2 m ahead of the ego origin, looking 20° down
    front[:3, :3] = Rotation.from_euler("y", 20, degrees=True).as_matrix() @ front[:3, :3]
    front[0, 3] = 2.0
    assert rig_warnings(_mounted(front)) == []
    # a narrow level camera sees the ground only far away, and one at the origin's height (to
    # rounding) is not below it: no warning either
    # (a 2.7° vertical field of view 1.5 m up: the ground from 63 m on)
    tele = np.array([[2000.0, 0.0, 79.5], [0.0, 2000.0, 47.5], [0.0, 0.0, 1.0]])
    narrow = Camera("front", 160, 96, tele, RIG[0].cam_to_ego)
    level = RIG[0].cam_to_ego.copy()
    level[2, 3] = -1e-9
    assert rig_warnings([narrow]) == [] and rig_warnings(_mounted(level)) == []
    # one warning per camera: below the ground and seeing no ground is said once
    upside = np.linalg.inv(front)
    upside[:3, :3] = np.eye(3)
    assert len(rig_warnings(_mounted(upside))) == 1
    mm = front.copy()
    mm[:3, 3] *= 1000.0  # millimetres
    inverse = np.linalg.inv(front)  # ego -> camera given for cam_to_ego
    body = front.copy()
    body[:3, :3] = np.eye(3)  # the camera's axes as the vehicle's (x forward): it looks up
    cases = [
        (mm, r"'front' sits 2500 m from the ego origin: millimetres\?"),
        (inverse, r"'front' sits 1.37 m below the ego origin .*ego -> camera transform, or"),
        (body, r"'front' sees no ground: no ray .* along ego \(0.00, 0.00, 1.00\)"),
    ]
    for T, match in cases:
        notes = rig_warnings(_mounted(T))
        assert len(notes) == 1 and notes[0].startswith("camera 'front'"), notes
        assert re.search(match, notes[0]), notes[0]
        assert "OpenCV: x right, y down, z forward" in notes[0]


def test_opening_a_dataset_warns_about_its_rigs_extrinsics(tmp_path):
    from vvloc.data import DatasetWriter, open_dataset

    mm = RIG[0].cam_to_ego.copy()
    mm[:3, 3] *= 1000.0
    rig = _mounted(mm)
    with DatasetWriter(tmp_path / "ds", rig) as w:
        w.add_session("s0").add(0, (0.0, 0.0, 0.0), np.zeros((4, 3, 96, 160), np.uint8))
    with pytest.warns(UserWarning, match=r"rig.json: camera 'front' sits 1500 m"):
        ds = open_dataset(tmp_path / "ds")
    assert ds.sessions == ["s0"]


def test_frames_whose_own_extrinsics_no_rig_has_are_warned_about(tmp_path):
    from vvloc.data import DatasetWriter, open_dataset
    from vvloc.data.frame import ego_frames
    from vvloc.data.rig import frame_extrinsics_warnings

    rig_t = np.stack([c.cam_to_ego for c in RIG])
    # a truck's far camera on a 16 % ramp (levelled: 9° about the ego origin, 1.2 m of shift),
    # a 25° tilt, and a fast car's cameras fired 50 ms apart (1.5 m): frames of this rig
    truck = [*RIG[:3], Camera(RIG[3].name, 160, 96, RIG[3].K, rig_t[3].copy())]
    truck[3].cam_to_ego[:3, 3] = (7.0, 0.0, 3.0)
    pitched = np.eye(4)
    pitched[:3, :3] = Rotation.from_euler("y", -9.1, degrees=True).as_matrix()
    _, _, levelled = ego_frames(pitched[None], truck, height=0.0, level=True)
    assert levelled is not None
    tilt = np.eye(4)
    tilt[:3, :3] = Rotation.from_euler("xy", [25, -10], degrees=True).as_matrix()
    fast = rig_t.copy()
    fast[:, 0, 3] += [0.0, 1.5, 0.0, 1.5]
    truck_t = np.stack([c.cam_to_ego for c in truck])
    assert np.linalg.norm(levelled[0, 3, :3, 3] - truck_t[3, :3, 3]) > 1.0
    assert frame_extrinsics_warnings(truck, [1], levelled) == []
    frames = np.stack([rig_t, tilt @ rig_t, fast])
    assert frame_extrinsics_warnings(RIG, [10, 20, 30], frames) == []
    # millimetres in one row, an inverted transform in another, camera 0's rows for camera 3
    bad = frames.copy()
    bad[1, 2, :3, 3] *= 1000.0
    bad[2, 2] = np.linalg.inv(fast[2])
    bad[0, 3] = rig_t[0]
    notes = frame_extrinsics_warnings(RIG, [10, 20, 30], bad)
    assert len(notes) == 2, notes  # one per camera, the others' rows not blamed
    assert notes[0].startswith(f"2 of 3 frames give camera {RIG[2].name!r} a mounting no rig")
    assert re.search(
        r"\(first at timestamp 20: \d+ m from the ego origin: millimetres\?\)", notes[0]
    )
    assert notes[1].startswith(f"1 of 3 frames give camera {RIG[3].name!r} a mounting no rig")
    assert re.search(r"first at timestamp 10: turned by 90° against the frame's other", notes[1])
    for args, match in [
        (([10, 20], bad), r"^cam_to_ego: expected \(2, 4, 4, 4\) for 2 timestamps and 4 cameras"),
        (([[10, 20, 30]], bad), r"^timestamps: expected shape \(N,\), got \(1, 3\)"),
    ]:
        with pytest.raises(ValueError, match=match):
            frame_extrinsics_warnings(RIG, *args)
    # opening a dataset warns, naming the session's cam_to_ego.csv
    with DatasetWriter(tmp_path / "ds", RIG) as w:
        s = w.add_session("s0")
        for k, t in enumerate(bad[:2]):
            s.add(k, (k * 1.0, 0.0, 0.0), np.zeros((4, 3, 96, 160), np.uint8), cam_to_ego=t)
    with pytest.warns(UserWarning, match=r"s0/cam_to_ego\.csv: 1 of 2 frames give camera") as w:
        open_dataset(tmp_path / "ds")
    assert len(w) == 2  # camera 3 at frame 0, camera 2 at frame 1


def test_without_levelling_takes_out_a_turn_and_shift_common_to_every_camera():
    from vvloc.data.rig import without_levelling

    rig_t = np.stack([c.cam_to_ego for c in RIG])
    common = np.eye(4)
    common[:3, :3] = Rotation.from_euler("xy", [15, -20], degrees=True).as_matrix()
    common[:3, 3] = (1.0, 0.5, 0.0)
    np.testing.assert_allclose(without_levelling(RIG, common @ rig_t), rig_t, atol=1e-12)
    # a camera mounted otherwise stays off by its own turn; the others come back
    lower = common @ rig_t
    lower[1, :3, :3] = Rotation.from_euler("y", 20, degrees=True).as_matrix() @ lower[1, :3, :3]
    back = without_levelling(RIG, lower)
    np.testing.assert_allclose(back[[0, 2, 3]], rig_t[[0, 2, 3]], atol=1e-12)
    turn = back[1, :3, :3] @ rig_t[1, :3, :3].T
    assert np.degrees(np.arccos((np.trace(turn) - 1) / 2)) == pytest.approx(20.0)
    # no vehicle's turn or shift, one camera, or another count: left as they are
    for T, rig in [
        (_turned(50) @ rig_t, RIG),
        (_shifted(4.0) @ rig_t, RIG),
        (common @ rig_t[:1], RIG[:1]),
        (common @ rig_t[:3], RIG),
    ]:
        np.testing.assert_array_equal(without_levelling(rig, T), T)


def _turned(degrees: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("y", degrees, degrees=True).as_matrix()
    return T


def _shifted(metres: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = metres
    return T


def test_the_same_cameras_in_another_order_are_named_so():
    # a rig.json listing the map's cameras in another order: it read as other intrinsics or a
    # 90° turn of camera 0, which sent users looking for a calibration error
    swapped = [RIG[1], RIG[0], RIG[2], RIG[3]]
    assert _difference(swapped, SAME_MAP) == (
        "the same cameras in another order: this rig's camera 0 is the other's camera 1, this "
        "rig's camera 1 is the other's camera 0; list them in the other rig's order, e.g. with "
        "vvloc convert --cameras"
    )
    rotated = [RIG[3], RIG[0], RIG[1], RIG[2]]
    assert _difference(rotated).startswith(
        "the same cameras in another order: this rig's camera 0 is the other's camera 3, this "
        "rig's camera 1 is the other's camera 0, this rig's camera 2 is the other's camera 1, "
        "this rig's camera 3 is the other's camera 2;"
    )
    # another camera in the mix: no order makes it the same rig, the first difference is said
    other = [RIG[1], RIG[0], RIG[2], _camera("up", 45.0)]
    assert _difference(other).startswith("cameras turned by up to")
