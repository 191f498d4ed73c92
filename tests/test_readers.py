"""NCLT and Oxford RobotCar readers on tiny fixtures written here in each dataset's raw layout."""

from __future__ import annotations

import math
import re
import warnings

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from vvloc.data import DatasetFormatError, convert_dataset, open_dataset, select_keyframes
from vvloc.data.bayer import demosaic_bilinear, mosaic
from vvloc.data.frame import (
    FRD_TO_FLU,
    NED_TO_ENU,
    Camera,
    ego_frames,
    euler_to_matrix,
    interpolate_rows,
)
from vvloc.data.nclt import X_BODY_LB3

# NCLT's published calibration of Ladybug camera 5 (the forward one): cam_params/x_lb3_c5.csv
X_LB3_C5 = (0.041862, -0.001905, -0.000212, 160.868615, 89.914152, 160.619894)
# the Oxford RobotCar SDK's extrinsics/mono_left.txt
SDK_MONO_LEFT = "-0.0905 1.6375 0.2803 0.2079 -0.2339 1.2321"

DATE = "2012-01-08"

#: A camera 1.5 m above the ground looking forward (OpenCV axes into the ego frame): an
#: identity cam_to_ego looks straight up, which opening a dataset warns about.
FORWARD = np.array([[0.0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 1.5], [0, 0, 0, 1]])


def test_euler_convention_matches_scipy_zyx():
    T = euler_to_matrix(1, 2, 3, 0.1, -0.2, 0.3)
    R = Rotation.from_euler("ZYX", [0.3, -0.2, 0.1]).as_matrix()
    assert np.allclose(T[:3, :3], R) and np.allclose(T[:3, 3], [1, 2, 3])


def _nclt(root, with_map=True):
    params = root / "cam_params"
    params.mkdir(parents=True)
    w, h = 8, 6
    utimes = [1_000_000, 1_200_000, 1_400_000]
    for i in (1, 2):
        np.savetxt(
            params / f"K_cam{i}.csv", [[5.0, 0, 3.5], [0, 5.0, 2.5], [0, 0, 1]], delimiter=","
        )
        # camera 5's mounting turned by 72° steps about the Ladybug's axis: looking sideways
        roll, pitch, yaw = X_LB3_C5[3:]
        x_lb3 = [[0.1 * i, 0, 0, roll, pitch, yaw + 72.0 * i]]
        np.savetxt(params / f"x_lb3_c{i}.csv", x_lb3, delimiter=",")
        d = root / DATE / "lb3" / f"Cam{i}"
        d.mkdir(parents=True)
        for k, t in enumerate(utimes):
            img = np.zeros((h, w, 3), np.uint8)
            img[..., 0] = np.arange(w, dtype=np.uint8)[None, :] * 10  # a horizontal ramp
            img[..., 1] = 40 * i + k
            Image.fromarray(img).save(d / f"{t}.tiff")
    if with_map:  # camera 1: a map that mirrors the image horizontally
        lines = [f"{w} {h}"] + [f"{r} {c} {r} {w - 1 - c}" for r in range(h) for c in range(w)]
        (params / f"U2D_Cam1_{w}X{h}.txt").write_text("\n".join(lines) + "\n")
    gt = [
        [900_000, "nan", "nan", "nan", "nan", "nan", "nan"],
        [1_000_010, 10.0, 5.0, -1.0, 0.0, 0.0, 0.3],
        [1_200_020, 11.0, 5.5, -1.0, 0.0, 0.0, 0.4],
        # no ground truth near 1_400_000: that frame is dropped
        [2_000_000, 12.0, 6.0, -1.0, 0.0, 0.0, 0.5],
    ]
    (root / f"groundtruth_{DATE}.csv").write_text("\n".join(",".join(map(str, r)) for r in gt))


def test_nclt_reader_converts_frames_and_matches_poses(tmp_path):
    _nclt(tmp_path)
    with pytest.warns(UserWarning, match=r"no U2D_Cam2_\*\.txt undistortion map") as caught:
        ds = open_dataset(tmp_path, cameras=(1, 2), upright=False)  # images as stored
    assert not caught[0].filename.endswith("nclt.py")  # said at open_nclt's caller
    assert ds.sessions == [DATE]
    s = ds.session(DATE)
    assert len(s) == 2 and list(s.timestamps) == [1_000_000, 1_200_000]
    assert s.left_out == {"no ground truth within tolerance_us=50000": 1}
    # NED (x north, y east) → ENU (x east, y north); yaw from north-clockwise to east-CCW
    assert np.allclose(s.poses[0], [5.0, 10.0, math.pi / 2 - 0.3])
    assert np.allclose(s.z, [1.0, 1.0])
    f = s[1]
    assert f.images.shape == (2, 3, 6, 8) and f.cameras == ("Cam1", "Cam2")
    assert np.array_equal(f.images[1, 0, 0], np.arange(8) * 10)
    assert np.array_equal(f.images[0, 0, 0], (7 - np.arange(8)) * 10)  # undistortion map applied
    assert np.all(f.images[1, 1] == 81)
    # calibration: cam_to_ego = FRD→FLU · T_body_lb3 · T_lb3_cam, ssc angles in degrees
    r, p, y = np.deg2rad(X_BODY_LB3[3:])
    T_body_lb3 = euler_to_matrix(*X_BODY_LB3[:3], r, p, y)
    T_lb3_c2 = euler_to_matrix(0.2, 0, 0, *np.deg2rad([*X_LB3_C5[3:5], X_LB3_C5[5] + 144.0]))
    assert np.allclose(f.cam_to_ego[1], FRD_TO_FLU @ T_body_lb3 @ T_lb3_c2)
    assert np.allclose(f.K[0], [[5, 0, 3.5], [0, 5, 2.5], [0, 0, 1]])
    with pytest.warns(UserWarning, match="U2D_Cam2"):
        small = open_dataset(tmp_path, cameras=(2,), image_size=(4, 3), upright=False)
    f = small.session(DATE)[0]
    assert f.images.shape == (1, 3, 3, 4) and f.K[0, 0, 0] == pytest.approx(2.5)


def test_nclt_undistortion_maps_are_found_where_their_archive_unpacks(tmp_path):
    # NCLT ships the maps apart from cam_params (U2D_ALL_1616X1232.tar.gz): a map in a
    # U2D_ALL_* folder beside cam_params, or beside cam_params itself, is used as one inside it
    _nclt(tmp_path)
    inside = tmp_path / "cam_params" / "U2D_Cam1_8X6.txt"
    with pytest.warns(UserWarning, match="U2D_Cam2"):
        want = open_dataset(tmp_path, cameras=(1, 2), upright=False).session(DATE)[1].images
    for folder in (tmp_path / "U2D_ALL_8X6", tmp_path):
        folder.mkdir(exist_ok=True)
        moved = folder / inside.name
        (inside if inside.exists() else tmp_path / "U2D_ALL_8X6" / inside.name).rename(moved)
        with pytest.warns(UserWarning) as caught:
            got = open_dataset(tmp_path, cameras=(1, 2), upright=False).session(DATE)[1].images
        messages = [str(w.message) for w in caught]
        assert not any("U2D_Cam1" in m for m in messages), messages  # Cam1's map was found
        assert any("looked there, in" in m and "U2D_Cam2" in m for m in messages), messages
        assert np.array_equal(got, want), folder


def test_nclt_images_are_turned_upright_and_the_ego_origin_lowered(tmp_path):
    _nclt(tmp_path)
    np.savetxt(tmp_path / "cam_params" / "x_lb3_c1.csv", [X_LB3_C5], delimiter=",")
    stored = open_dataset(tmp_path, cameras=(1,), upright=False)
    ds = open_dataset(tmp_path, cameras=(1,), ego_height=0.4)
    cam0, cam = stored.cameras[0], ds.cameras[0]
    T = cam.cam_to_ego
    # the forward camera looks forward, 1.23 m above NCLT's body origin (+0.4 m: the ground)
    assert T[0, 2] > 0.99 and T[2, 3] == pytest.approx(1.23 + 0.4, abs=0.01)
    # stored, its image's rows run sideways (camera y along ego y, not down) ...
    assert abs(cam0.cam_to_ego[2, 1]) < 0.01
    # ... upright, right is ego right (-y) and down is ego down (-z)
    assert T[1, 0] < -0.99 and T[2, 1] < -0.99
    assert (cam.width, cam.height) == (6, 8)
    s0, s = stored.session(DATE), ds.session(DATE)
    np.testing.assert_allclose(s.z, s0.z - 0.4)
    np.testing.assert_array_equal(s.poses, s0.poses)
    img0, img = s0[1].images[0], s[1].images[0]  # (3, H, W): stored 6 x 8, upright 8 x 6
    assert img.shape == (3, 8, 6)
    # one quarter turn clockwise: upright pixel (u', v') = stored (v', H - 1 - u')
    np.testing.assert_array_equal(img, np.rot90(img0, -1, axes=(1, 2)))
    assert np.array_equal(img[0, :, 5], img0[0, 0, :])  # the stored top row is the right column
    # the calibration follows the pixels: a point seen at stored (u, v) is at (H - 1 - v, u)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(3, 9, 20), rng.uniform(-1, 1, 20), rng.uniform(0, 3, 20)])
    uv0, _ = (
        Camera("c", cam0.width, cam0.height, cam0.K, cam0.cam_to_ego)
        .with_ego_origin_lowered(0.4)
        .project_ego(pts)
    )
    uv, _ = cam.project_ego(pts)
    np.testing.assert_allclose(uv, np.column_stack([cam0.height - 1 - uv0[:, 1], uv0[:, 0]]))


@pytest.mark.parametrize("turns", [-1, 0, 1, 2, 3, 5])
def test_a_turned_camera_sees_each_point_where_np_rot90_puts_its_pixel(turns):
    rng = np.random.default_rng(turns + 7)
    w, h = 9, 5
    K = np.array([[6.0, 0.3, 4.2], [0, 5.5, 1.9], [0, 0, 1]])  # skewed, off-centre
    R = Rotation.from_euler("xyz", rng.uniform(-0.5, 0.5, 3)).as_matrix()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, rng.normal(size=3)
    cam = Camera("c", w, h, K, T)
    turned = cam.rotated(turns)
    # the integer pixel (u, v) of every image pixel, moved as np.rot90 moves it
    index = np.arange(h * w).reshape(h, w)
    moved = np.rot90(index, turns)
    assert (turned.height, turned.width) == moved.shape
    for v in range(h):
        for u in range(w):
            # the ego point 4 m along the ray of the pixel's centre
            ray = np.linalg.solve(K, [u, v, 1.0]) * 4.0
            p = T[:3, :3] @ ray + T[:3, 3]
            uv, depth = turned.project_ego(p[None])
            v2, u2 = np.argwhere(moved == v * w + u)[0]
            np.testing.assert_allclose(uv[0], [u2, v2], atol=1e-9)
            assert depth[0] == pytest.approx(4.0)
    # a level camera looking forward (OpenCV axes in the FLU ego frame) is upright as it is;
    # turned by k, it needs the turns back
    level = np.eye(4)
    level[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]
    forward = Camera("f", w, h, K, level)
    assert forward.upright_quarter_turns() == 0
    assert forward.rotated(turns).upright_quarter_turns() == (-turns) % 4
    with pytest.raises(TypeError, match="quarter_turns"):
        cam.rotated(1.0)  # type: ignore[arg-type]


def test_interpolate_rows_takes_the_shorter_arc_and_keeps_the_ends():
    t = np.array([0, 100, 200], np.int64)
    v = np.array([[0.0, 3.0], [10.0, -3.0], [20.0, -2.0]])
    out, ok = interpolate_rows(t, v, np.array([-5, 25, 150, 200, 260]), 50, angle_columns=(1,))
    assert ok.tolist() == [True, True, True, True, False]
    np.testing.assert_allclose(out[:4, 0], [0.0, 2.5, 15.0, 20.0])
    # from 3 rad to -3 rad the shorter arc passes through pi (0.283 rad long), not through 0
    arc = 2 * math.pi - 6.0
    np.testing.assert_allclose(out[1, 1], 3.0 + 0.25 * arc)
    np.testing.assert_allclose(out[2, 1], -2.5)
    assert out[0, 1] == 3.0 and out[3, 1] == -2.0  # before the first / at the last row
    # no rows: every query invalid (it was a reshape error); rows that are not one per time
    none, ok = interpolate_rows(t[:0], v[:0], np.array([5, 6]), 50)
    assert none.shape == (2, 2) and not ok.any()
    with pytest.raises(ValueError, match=r"^values: expected 3 rows, one per time, got 2"):
        interpolate_rows(t, v[:2], np.array([5]), 50)
    with pytest.raises(ValueError, match=r"^values: expected 3 rows, one per time, got 6"):
        interpolate_rows(t, v.ravel(), np.array([5]), 50)  # it was taken as (3, 2)
    none, ok = interpolate_rows(t[:0], [], np.array([5]), 50)  # one value a row, no rows
    assert none.shape == (1, 1) and not ok.any()


def test_nclt_reader_reports_bad_files(tmp_path):
    _nclt(tmp_path, with_map=True)
    (tmp_path / f"groundtruth_{DATE}.csv").write_text("1,2,3\n")
    with pytest.raises(DatasetFormatError, match=r"groundtruth_2012-01-08\.csv, line 1"):
        open_dataset(tmp_path, cameras=(1,))
    with pytest.raises(TypeError, match="upright: expected a bool"):
        open_dataset(tmp_path, cameras=(1,), upright="yes")
    with pytest.raises(ValueError, match="ego_height"):
        open_dataset(tmp_path, cameras=(1,), ego_height=float("nan"))
    (tmp_path / "cam_params" / "K_cam1.csv").write_text("1,2\n")
    with pytest.raises(DatasetFormatError, match=r"K_cam1\.csv"):
        open_dataset(tmp_path, cameras=(1,))


def test_nclt_reader_checks_its_options_and_the_raw_image_size(tmp_path):
    _nclt(tmp_path, with_map=True)
    for kw, err, match in (
        ({"cameras": (1, 1)}, ValueError, r"cameras: \['1'\] listed more than once"),
        ({"cameras": ()}, ValueError, "cameras: expected at least one camera"),
        ({"cameras": 1}, TypeError, "cameras: expected a list"),
        ({"cameras": (1,), "tolerance_us": -1}, ValueError, "tolerance_us: expected"),
        ({"cameras": (1,), "tolerance_us": "50000"}, TypeError, "tolerance_us: expected an int"),
        ({"cameras": (1,), "image_size": (96,)}, ValueError, "image_size: expected"),
    ):
        with pytest.raises(err, match=match):
            open_dataset(tmp_path, **kw)
    # the map reads the raw image's pixels: a raw image of another size is refused, not
    # undistorted with a map for another size (nor cropped by it)
    d = tmp_path / DATE / "lb3" / "Cam1"
    Image.fromarray(np.zeros((30, 40, 3), np.uint8)).save(d / "1200000.tiff")
    s = open_dataset(tmp_path, cameras=(1,)).session(DATE)
    with pytest.raises(DatasetFormatError, match=r"1200000\.tiff: image is 40x30"):
        s[1]
    for t in (1_000_000, 1_400_000):
        Image.fromarray(np.zeros((30, 40, 3), np.uint8)).save(d / f"{t}.tiff")
    with pytest.raises(DatasetFormatError, match="the undistortion map is 8x6"):
        open_dataset(tmp_path, cameras=(1,))
    # a damaged map names its file
    (tmp_path / "cam_params" / "U2D_Cam1_8X6.txt").write_text("8 6\n0 0 x 1\n")
    with pytest.raises(DatasetFormatError, match=r"U2D_Cam1_8X6\.txt: malformed map line"):
        open_dataset(tmp_path, cameras=(1,))


def test_an_undistortion_map_cut_short_or_with_fractional_indices_is_said(tmp_path):
    from vvloc.data.nclt import read_undistortion_map

    w, h = 8, 6
    lines = [f"{w} {h}"] + [f"{r} {c} {r} {c}" for r in range(h) for c in range(w)]
    path = tmp_path / "U2D_Cam1_8X6.txt"
    path.write_text("\n".join(lines[: 1 + 20]) + "\n")  # cut after 20 of 48 pixels
    with pytest.warns(
        UserWarning, match=r"lists 20 of the 48 output pixels \(first missing: row 2"
    ):
        mapu, _ = read_undistortion_map(path)
    assert (mapu[3:] == -1).all()  # they read outside the image: black
    path.write_text("\n".join([*lines[:-1], "5.9 7.9 5 7"]) + "\n")  # was read as row 5, col 7
    with pytest.raises(DatasetFormatError, match=r"indices must be integers, got row 5.9, col 7.9"):
        read_undistortion_map(path)
    path.write_text("\n".join([*lines[:-1], "5 7 nan 7"]) + "\n")
    with pytest.raises(DatasetFormatError, match=r"map line 48: non-finite value"):
        read_undistortion_map(path)
    path.write_text("\n".join(lines) + "\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mapu, mapv = read_undistortion_map(path)  # complete: no warning
    assert (mapu == np.arange(w)[None, :]).all() and (mapv == np.arange(h)[:, None]).all()


def test_demosaic_is_exact_on_constant_and_linear_images():
    for pattern in ("rggb", "gbrg", "grbg", "bggr"):
        rgb = np.empty((8, 10, 3), np.uint8)
        rgb[...] = (200, 100, 30)
        assert np.array_equal(demosaic_bilinear(mosaic(rgb, pattern), pattern), rgb)
        ramp = np.repeat((np.arange(10, dtype=np.uint8) * 20)[None, :, None], 8, axis=0)
        ramp = np.repeat(ramp, 3, axis=2)
        out = demosaic_bilinear(mosaic(ramp, pattern), pattern)
        assert np.array_equal(out[2:-2, 2:-2], ramp[2:-2, 2:-2])  # interior: exact on a ramp
    with pytest.raises(ValueError, match="pattern"):
        demosaic_bilinear(np.zeros((4, 4), np.uint8), "rgbg")


G_CAMERA_IMAGE = [[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]


# the INS in the vehicle frame (x forward, y right, z down: behind, right of and below the
# stereo camera), and the rows of ins.csv: time, status, northing, easting, yaw
INS_LEVER = (-1.7132, 0.1181, 1.1948)
INS_ROWS = (
    (90, "INS_SOLUTION_GOOD", 5_700_000.0, 620_000.0, 0.2),
    (100_000, "INS_ALIGNMENT_COMPLETE", 5_700_090.0, 620_090.0, 2.0),  # not a good solution
    (200_010, "INS_SOLUTION_GOOD", 5_700_001.0, 620_000.5, 0.3),
)


def _vehicle_enu(north, east, yaw):
    """The stereo camera's (east, north) and ENU yaw for an INS fix, derived by hand: the INS
    lies at INS_LEVER in the vehicle's forward-right frame, so the vehicle origin is the fix
    minus the lever arm turned by the heading (yaw clockwise from north)."""
    fwd, right = -INS_LEVER[0], -INS_LEVER[1]
    n = north + fwd * math.cos(yaw) - right * math.sin(yaw)
    e = east + fwd * math.sin(yaw) + right * math.cos(yaw)
    return e, n, math.pi / 2 - yaw


def _oxford(root):
    sess = root / "2019-01-10-11-46-21-radar-oxford-10k"
    (root / "models").mkdir(parents=True)
    (root / "extrinsics").mkdir()
    for model, (fx, cx) in (("stereo_narrow_left", (8.0, 3.5)), ("mono_left", (6.0, 2.5))):
        lines = [f"{fx} {fx} {cx} {cx - 1}"] + [" ".join(map(str, r)) for r in G_CAMERA_IMAGE]
        (root / "models" / f"{model}.txt").write_text("\n".join(lines) + "\n")
    (root / "extrinsics" / "mono_left.txt").write_text(SDK_MONO_LEFT + "\n")
    (root / "extrinsics" / "ins.txt").write_text(" ".join(map(str, INS_LEVER)) + " 0 0 0\n")
    # identity undistortion LUTs: source (u, v) of every output pixel
    for model, (w, h) in (("mono_left", (6, 6)), ("stereo_narrow_left", (8, 6))):
        vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
        np.concatenate([uu.ravel(), vv.ravel()]).tofile(
            root / "models" / f"{model}_distortion_lut.bin"
        )
    stamps = {"stereo": [100, 200_000, 400_000], "mono_left": [120, 200_030, 400_010]}
    colours = {"stereo": (200, 100, 30), "mono_left": (20, 220, 120)}
    for cam, folder, pattern, (w, h) in (
        ("stereo", "stereo/centre", "gbrg", (8, 6)),
        ("mono_left", "mono_left", "rggb", (6, 6)),
    ):
        d = sess / folder
        d.mkdir(parents=True)
        for t in stamps[cam]:
            rgb = np.empty((h, w, 3), np.uint8)
            rgb[...] = colours[cam]
            Image.fromarray(mosaic(rgb, pattern)).save(d / f"{t}.png")
        (sess / f"{cam}.timestamps").write_text("".join(f"{t} 1\n" for t in stamps[cam]))
    (sess / "gps").mkdir()
    header = (
        "timestamp,ins_status,latitude,longitude,altitude,northing,easting,down,utm_zone,"
        "velocity_north,velocity_east,velocity_down,roll,pitch,yaw"
    )
    rows = [
        f"{t},{status},51.7,-1.2,100,{n},{e},-100,30U,0,0,0,0,0,{yaw}"
        for t, status, n, e, yaw in INS_ROWS
    ]
    (sess / "gps" / "ins.csv").write_text(header + "\n" + "\n".join(rows) + "\n")
    return sess


def test_oxford_reader_demosaics_and_converts_frames(tmp_path):
    sess = _oxford(tmp_path)
    ds = open_dataset(tmp_path, cameras=("stereo_centre", "mono_left"), ego_height=1.5)
    s = ds.session(sess.name)
    assert len(s) == 2  # the 400_000 frame has no INS row within the tolerance
    assert s.left_out == {"no INS row within tolerance_us=50000": 1}
    # poses interpolated in time between the good INS rows (the middle row is left out)
    (t0, _, n0, e0, y0), _, (t1, _, n1, e1, y1) = INS_ROWS
    expected = []
    for t in (100, 200_000):
        w = (t - t0) / (t1 - t0)
        expected.append(_vehicle_enu(n0 + w * (n1 - n0), e0 + w * (e1 - e0), y0 + w * (y1 - y0)))
    (ex0, ny0, yaw0), (ex1, ny1, yaw1) = expected
    np.testing.assert_allclose(ds.meta["origin_enu"], [ex0, ny0, 100 + INS_LEVER[2] - 1.5])
    np.testing.assert_allclose(s.poses[0], [0.0, 0.0, yaw0], atol=1e-9)
    np.testing.assert_allclose(s.poses[1], [ex1 - ex0, ny1 - ny0, yaw1], atol=1e-9)
    np.testing.assert_allclose(s.z, 0.0, atol=1e-9)
    f = s[1]
    assert f.images.shape == (2, 3, 6, 8)  # mono resized to the stereo camera's size
    assert np.all(f.images[0].transpose(1, 2, 0) == (200, 100, 30))  # GBRG demosaiced
    assert np.all(f.images[1].transpose(1, 2, 0) == (20, 220, 120))  # RGGB demosaiced
    # stereo (the vehicle frame, 1.5 m above the ground): optical axis forward, image right =
    # ego right (-y)
    assert np.allclose(f.cam_to_ego[0][:3, 2], [1, 0, 0]) and np.allclose(
        f.cam_to_ego[0][:3, 0], [0, -1, 0]
    )
    np.testing.assert_allclose(f.cam_to_ego[0][:3, 3], [0, 0, 1.5], atol=1e-12)
    # the SDK's mono_left.txt puts the camera on the car's left, 1.5 m behind the stereo camera
    # (robotcar-dataset-sdk issue #22: about (-1.55, 0.59) forward-left), looking 71° left
    left = f.cam_to_ego[1]
    assert -1.6 < left[0, 3] < -1.5 and 0.55 < left[1, 3] < 0.65
    axis = left[:3, 2]
    assert math.degrees(math.atan2(axis[1], axis[0])) == pytest.approx(70.6, abs=1.0)
    assert np.allclose(f.K[0], [[8, 0, 3.5], [0, 8, 2.5], [0, 0, 1]])
    assert f.K[1, 0, 0] == pytest.approx(6.0 * 8 / 6) and f.K[1, 1, 1] == pytest.approx(6.0)


def test_oxford_lut_rows_are_source_u_then_v(tmp_path):
    from vvloc.data._remap import remap_bilinear
    from vvloc.data.oxford import read_lut

    w, h = 5, 3
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    path = tmp_path / "m_distortion_lut.bin"
    np.concatenate([(w - 1 - uu).ravel(), vv.ravel()]).tofile(path)  # mirror left-right
    img = np.zeros((h, w, 3), np.uint8)
    img[..., 0] = np.arange(w)[None, :] * 40 + np.arange(h)[:, None]
    out = remap_bilinear(img, *read_lut(path, w, h))
    np.testing.assert_array_equal(out, img[:, ::-1])
    with pytest.raises(DatasetFormatError, match="expected 2x3x6"):
        read_lut(path, h, w + 1)


def test_oxford_reader_reports_bad_files(tmp_path):
    sess = _oxford(tmp_path)
    (tmp_path / "models" / "stereo_narrow_left_distortion_lut.bin").unlink()
    with pytest.warns(UserWarning, match="no stereo_narrow_left_distortion_lut.bin"):
        open_dataset(tmp_path, cameras=("stereo_centre",))
    with pytest.raises(DatasetFormatError, match="no frame has an image of every camera"):
        open_dataset(tmp_path, cameras=("mono_left",), tolerance_us=1)
    # a truncated download, an INS that never aligned: the file named (a numpy reshape error)
    lines = (sess / "gps" / "ins.csv").read_text().splitlines()
    aligning = [line.replace("INS_SOLUTION_GOOD", "INS_ALIGNMENT_COMPLETE") for line in lines]
    assert aligning != lines
    for text in (lines[:1], aligning):
        (sess / "gps" / "ins.csv").write_text("\n".join(text) + "\n")
        with pytest.raises(
            DatasetFormatError, match=r"ins\.csv: no INS rows with ins_status INS_SOLUTION_GOOD$"
        ):
            open_dataset(tmp_path, cameras=("stereo_centre",))
    (sess / "gps" / "ins.csv").write_text("timestamp,northing\n1,2\n")
    with pytest.raises(DatasetFormatError, match=r"ins\.csv, line 1: header lacks"):
        open_dataset(tmp_path, cameras=("stereo_centre",))
    with pytest.raises(ValueError, match="cameras"):
        open_dataset(tmp_path, cameras=("roof",))


def test_the_readers_count_the_frames_they_leave_out(tmp_path):
    _nclt(tmp_path / "nclt")
    (tmp_path / "nclt" / DATE / "lb3" / "Cam2" / "1200000.tiff").unlink()
    with pytest.warns(UserWarning, match="U2D_Cam2"):
        s = open_dataset(tmp_path / "nclt", cameras=(1, 2), upright=False).session(DATE)
    assert list(s.timestamps) == [1_000_000]
    assert s.left_out == {  # each frame under the first reason it failed, in the checks' order
        "an image missing for some camera": 1,
        "no ground truth within tolerance_us=50000": 1,
    }
    (tmp_path / "ox").mkdir()
    sess = _oxford(tmp_path / "ox")
    (sess / "stereo" / "centre" / "400000.png").unlink()  # listed, but no file
    (sess / "mono_left" / "200030.png").unlink()  # the 200 ms frame has no mono image near it
    (sess / "mono_left.timestamps").write_text("120 1\n400010 1\n")
    s = open_dataset(tmp_path / "ox", cameras=("stereo_centre", "mono_left")).session(sess.name)
    assert list(s.timestamps) == [100]
    assert s.left_out == {
        "listed in stereo.timestamps but no image file": 1,
        "no image of every camera within tolerance_us=50000": 1,
    }
    # another camera's image listed near in time but absent is said as such, not as a gap
    (sess / "mono_left" / "120.png").unlink()
    (sess / "mono_left.timestamps").write_text("120 1\n200030 1\n400010 1\n")
    Image.open(sess / "mono_left" / "400010.png").save(sess / "mono_left" / "200030.png")
    s = open_dataset(tmp_path / "ox", cameras=("stereo_centre", "mono_left")).session(sess.name)
    assert list(s.timestamps) == [200_000]
    assert s.left_out == {
        "listed in stereo.timestamps but no image file": 1,
        "listed in mono_left.timestamps but no image file": 1,
    }
    # the INS at the frame's time, then at each camera's exposure (mono 30 µs after the INS)
    (tmp_path / "mc").mkdir()
    sess = _unsynchronised_oxford(tmp_path / "mc", -5)  # the middle mono image 5 µs late
    cams = ("stereo_centre", "mono_left")
    s = open_dataset(tmp_path / "mc", cameras=cams, tolerance_us=28).session(sess.name)
    assert list(s.timestamps) == [200_000]
    assert s.left_out == {
        "no INS row within tolerance_us=28": 1,  # 400 ms: the last INS row is at 200 ms
        "no INS row near some camera's exposure (motion_compensation)": 1,  # 100 µs: mono at 120
    }
    s = open_dataset(
        tmp_path / "mc", cameras=cams, tolerance_us=28, motion_compensation=False
    ).session(sess.name)
    assert s.left_out == {"no INS row within tolerance_us=28": 1}


def test_oxford_reader_refuses_what_it_would_read_wrong(tmp_path):
    sess = _oxford(tmp_path)
    with pytest.raises(ValueError, match="listed more than once"):
        open_dataset(tmp_path, cameras=("stereo_centre", "stereo_centre"))
    with pytest.raises(TypeError, match="cameras: expected a list"):
        open_dataset(tmp_path, cameras="stereo_centre")
    # a 16-bit mosaic would keep only its low 8 bits: refused, naming the file
    first = sess / "stereo" / "centre" / "100.png"
    good = first.read_bytes()
    Image.fromarray(mosaic(np.full((6, 8, 3), 1000, np.uint16), "gbrg")).save(first)
    s = open_dataset(tmp_path, cameras=("stereo_centre",)).session(sess.name)
    with pytest.raises(DatasetFormatError, match=r"100\.png: image mode 'I;16' is not 8 bits"):
        s[0]
    # a damaged image, read lazily or when the reader opens: a DatasetFormatError naming it
    first.write_bytes(good[:60])
    s = open_dataset(tmp_path, cameras=("stereo_centre",)).session(sess.name)
    with pytest.raises(DatasetFormatError, match=r"100\.png: not a readable image"):
        s[0]
    first.write_bytes(b"not a png")
    with pytest.raises(DatasetFormatError, match=r"100\.png: not a readable image"):
        open_dataset(tmp_path, cameras=("stereo_centre",))
    first.write_bytes(good)
    # a timestamp listed twice would give two frames of one image
    (sess / "stereo.timestamps").write_text("100 1\n200000 1\n200000 1\n400000 1\n")
    with pytest.raises(DatasetFormatError, match=r"stereo\.timestamps: timestamps listed more"):
        open_dataset(tmp_path, cameras=("stereo_centre",))


# ---------------------------------------------------------------------------------------------
# conversion into the vvloc format


def test_select_keyframes_by_distance_or_heading():
    poses = np.array(
        [[0, 0, 0], [0.4, 0, 0], [1.0, 0, 0], [1.2, 0, 0.3], [1.3, 0, 0.35], [5, 0, 0.35]],
        dtype=np.float64,
    )
    assert select_keyframes(poses).tolist() == [0, 1, 2, 3, 4, 5]
    assert select_keyframes(poses, min_distance=1.0).tolist() == [0, 2, 5]
    # 0.3 rad = 17.2°: frame 3 turned far enough; frame 4 moved 0.1 m and turned 2.9° more
    assert select_keyframes(poses, min_distance=1.0, min_angle_deg=15).tolist() == [0, 2, 3, 5]
    # headings across ±π are 0.2 rad apart, not 6.08
    wrap = np.array([[0, 0, 3.04], [0, 0, -3.04]])
    assert select_keyframes(wrap, min_angle_deg=15).tolist() == [0]
    assert select_keyframes(np.zeros((0, 3))).tolist() == []
    with pytest.raises(ValueError, match="min_distance"):
        select_keyframes(poses, min_distance=-1.0)
    with pytest.raises(ValueError, match=r"poses: expected shape \(N, 3\)"):
        select_keyframes(poses[:, :2])


def test_select_keyframes_keeps_the_first_view_of_a_floor():
    # a car lift: floor 1 begins 3.2 m above floor 0's last frame; the plane saw no movement
    x = [10.0, 8, 6, 4, 2, 0, 0, 2, 4]
    poses = np.column_stack([x, np.zeros(9), np.zeros(9)])
    floors, z = [0] * 6 + [1] * 3, [0.0] * 6 + [3.2] * 3
    assert select_keyframes(poses, min_distance=2.0).tolist() == [0, 1, 2, 3, 4, 5, 7, 8]
    every = list(range(9))
    assert select_keyframes(poses, min_distance=2.0, floors=floors).tolist() == every
    assert select_keyframes(poses, min_distance=2.0, z=z).tolist() == every  # moved 3.2 m
    # a ramp: 1.2 m along and 1.6 m up is 2 m moved
    ramp = select_keyframes(poses[:2] * [0.6, 0, 0], min_distance=2.0, z=[0.0, 1.6])
    assert ramp.tolist() == [0, 1]
    with pytest.raises(ValueError, match=r"floors: expected shape \(9,\)"):
        select_keyframes(poses, min_distance=2.0, floors=[0, 1])
    with pytest.raises(TypeError, match="floors"):
        select_keyframes(poses, min_distance=2.0, floors=np.zeros(9))
    with pytest.raises(ValueError, match="z"):
        select_keyframes(poses, min_distance=2.0, z=[np.nan] * 9)


def test_convert_keeps_the_first_keyframe_of_a_floor(tmp_path):
    from vvloc.data import DatasetWriter

    cam = Camera("front", 8, 6, np.array([[4.0, 0, 3.5], [0, 4, 2.5], [0, 0, 1]]), FORWARD)
    src = tmp_path / "lift"
    with DatasetWriter(src, [cam]) as w:
        s = w.add_session("s0")
        for k, (x, floor) in enumerate(zip([4.0, 2, 0, 0, 2], [0, 0, 0, 1, 1], strict=True)):
            s.add(k, (x, 0.0, 0.0), np.zeros((1, 3, 6, 8), np.uint8), z=3.2 * floor, floor=floor)
    out = open_dataset(convert_dataset(src, tmp_path / "every-2m", min_distance=2.0))
    assert out.session("s0").floors.tolist() == [0, 0, 0, 1, 1]


def test_convert_nclt_writes_what_the_reader_reads(tmp_path):
    src = tmp_path / "nclt"
    _nclt(src)
    out = tmp_path / "converted"
    path = convert_dataset(src, out, image_size=(3, 4), ego_height=0.4, cameras=(1,))
    read = open_dataset(src, image_size=(3, 4), ego_height=0.4, cameras=(1,))
    conv = open_dataset(path)
    assert conv.sessions == [DATE]
    (cam,), (ref,) = conv.cameras, read.cameras
    assert (cam.width, cam.height, cam.name) == (3, 4, "Cam1")
    np.testing.assert_allclose(cam.K, ref.K)
    np.testing.assert_allclose(cam.cam_to_ego, ref.cam_to_ego)
    s, r = conv.session(DATE), read.session(DATE)
    np.testing.assert_array_equal(s.timestamps, r.timestamps)
    np.testing.assert_allclose(s.poses, r.poses)
    np.testing.assert_allclose(s.z, r.z)
    np.testing.assert_array_equal(s[1].images, r[1].images)  # PNG is lossless
    src_meta = conv.meta["converted_from"]
    assert src_meta["format"] == "nclt" and src_meta["options"]["ego_height"] == 0.4
    assert src_meta["image_size"] == [3, 4]  # (width, height), whatever the source's format
    assert src_meta["source_frames"] == {
        DATE: {"read": 2, "left_out": {"no ground truth within tolerance_us=50000": 1}}
    }
    # keyframes: every 2nd frame of the two
    again = convert_dataset(src, tmp_path / "every2", every=2, cameras=(1,))
    assert len(open_dataset(again).session(DATE)) == 1


def test_convert_oxford_keeps_the_origin_and_resizes_a_vvloc_dataset(tmp_path):
    src = tmp_path / "oxford"
    src.mkdir()
    sess = _oxford(src)
    oxf = convert_dataset(src, tmp_path / "oxf", cameras=("stereo_centre", "mono_left"))
    # the vehicle frame's origin kept (no ego_height): mono_left sits below it
    with pytest.warns(UserWarning, match="'mono_left' sits 0.21 m below the ego origin"):
        conv = open_dataset(oxf)
    read = open_dataset(src, cameras=("stereo_centre", "mono_left"))
    assert conv.meta["origin_enu"] == read.meta["origin_enu"]
    np.testing.assert_allclose(conv.session(sess.name).poses, read.session(sess.name).poses)
    # vvloc → vvloc: the images are resized here, the intrinsics with them
    with pytest.warns(UserWarning, match="'mono_left' sits 0.21 m below the ego origin"):
        small = open_dataset(convert_dataset(oxf, tmp_path / "small", image_size=(4, 3)))
    for c_small, c in zip(small.cameras, conv.cameras, strict=True):
        np.testing.assert_allclose(c_small.K, c.resized(4, 3).K)
    assert small.session(sess.name)[0].images.shape == (2, 3, 3, 4)


def test_raw_readers_read_only_the_chosen_sessions(tmp_path):
    import shutil

    # NCLT: a second date whose ground truth is broken; choosing the first never reads it
    src = tmp_path / "nclt"
    _nclt(src)
    shutil.copytree(src / DATE, src / "2013-04-05")
    (src / "groundtruth_2013-04-05.csv").write_text("not,a,ground,truth\n")
    with pytest.raises(DatasetFormatError, match=r"groundtruth_2013-04-05\.csv, line 1"):
        open_dataset(src, cameras=(1,))
    ds = open_dataset(src, cameras=(1,), sessions=[DATE])
    assert ds.sessions == [DATE] and len(ds.session(DATE)) == 2
    out = convert_dataset(src, tmp_path / "one", sessions=[DATE], cameras=(1,))
    assert open_dataset(out).sessions == [DATE]
    for sessions, error, match in [
        (["2099-01-01"], KeyError, r"sessions: no session '2099-01-01' in .*'2012-01-08', '2013"),
        ([DATE, DATE], ValueError, r"sessions: \['2012-01-08'\] listed more than once"),
        (DATE, TypeError, r"^sessions: expected a list of session names"),
        ([], TypeError, r"^sessions: expected a non-empty list"),
    ]:
        with pytest.raises(error, match=match):
            open_dataset(src, cameras=(1,), sessions=sessions)
    # RobotCar: the folder's first session is read for the world origin, chosen or not, so
    # sessions read apart share one world frame; a later unchosen session is never read
    src = tmp_path / "oxford"
    src.mkdir()
    first = _oxford(src)
    second = src / "2019-01-11-12-26-55-radar-oxford-10k"
    third = src / "2019-01-12-00-00-00-radar-oxford-10k"
    shutil.copytree(first, second)
    ins = second / "gps" / "ins.csv"
    lines = ins.read_text().splitlines()  # the second drive 3 m further north
    for k in range(1, len(lines)):
        f = lines[k].split(",")
        f[5] = str(float(f[5]) + 3.0)
        lines[k] = ",".join(f)
    ins.write_text("\n".join(lines) + "\n")
    shutil.copytree(first, third)
    (third / "gps" / "ins.csv").write_text("broken\n")
    cams = ("stereo_centre", "mono_left")
    with pytest.raises(DatasetFormatError):
        open_dataset(src, cameras=cams)
    both = open_dataset(src, cameras=cams, sessions=[first.name, second.name])
    alone = open_dataset(src, cameras=cams, sessions=[second.name])
    assert alone.sessions == [second.name]
    assert alone.meta["origin_enu"] == both.meta["origin_enu"]
    np.testing.assert_array_equal(alone.session(second.name).poses, both.session(second.name).poses)
    (first / "mono_left.timestamps").unlink()  # the first session now fails to read
    with pytest.raises(DatasetFormatError, match=r"read only for the world origin, which"):
        open_dataset(src, cameras=cams, sessions=[second.name])
    np.testing.assert_allclose(
        both.session(second.name).poses[:, :2] - both.session(first.name).poses[:, :2],
        [[0.0, 3.0]] * len(both.session(first.name)), atol=1e-9,
    )  # fmt: skip


def test_convert_leaves_nothing_behind_on_failure(tmp_path, monkeypatch):
    from vvloc.data.nclt import NcltSession

    src = tmp_path / "nclt"
    _nclt(src)
    with pytest.raises(KeyError, match="no session 'nope'"):
        convert_dataset(src, tmp_path / "a", sessions=["nope"], cameras=(1,))
    with pytest.raises(ValueError, match="every"):
        convert_dataset(src, tmp_path / "a", every=0, cameras=(1,))
    # writing into the source, or around it, would replace or corrupt what is read
    for out in (src, src / "converted", tmp_path):
        with pytest.raises(ValueError, match="is, lies inside or holds the source"):
            convert_dataset(src, out, cameras=(1,), overwrite=True)
    with pytest.raises(ValueError, match=r"sessions: \['2012-01-08'\] listed more than once"):
        convert_dataset(src, tmp_path / "a", sessions=[DATE, DATE], cameras=(1,))
    calls = []

    def failing(self, index):
        calls.append(index)
        if len(calls) == 2:
            raise OSError("disk went away")
        return original(self, index)

    original = NcltSession._load_images
    monkeypatch.setattr(NcltSession, "_load_images", failing)
    with pytest.raises(OSError, match="disk went away"):
        convert_dataset(src, tmp_path / "a", cameras=(1,))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["nclt"]  # no folder, no partial one


def test_convert_refuses_before_reading_and_leaves_no_folder_it_made(tmp_path, monkeypatch):
    import vvloc.data as data_module

    src = tmp_path / "nclt"
    _nclt(src)
    with pytest.raises(TypeError, match="sessions: expected a list of session names"):
        convert_dataset(src, tmp_path / "a", sessions=DATE, cameras=(1,))
    # numpy scalars are numbers
    out = convert_dataset(
        src, tmp_path / "np", every=np.int64(1), min_distance=np.float32(0.5), cameras=(1,)
    )
    assert len(open_dataset(out).session(DATE)) == 2
    # a non-empty out is refused before the (slow) source is read
    opened = []
    monkeypatch.setattr(data_module, "open_dataset", lambda *a, **k: opened.append(a))
    with pytest.raises(FileExistsError, match="exists and is not empty"):
        convert_dataset(src, out, cameras=(1,))
    assert not opened
    monkeypatch.undo()
    # a session without any frame (no ground truth near its images) is refused, not written
    gt = src / f"groundtruth_{DATE}.csv"
    gt.write_text("5000000,1,2,3,0,0,0\n")
    with pytest.raises(DatasetFormatError, match=r"sessions \['2012-01-08'\] hold no frame"):
        convert_dataset(src, tmp_path / "new" / "deeper" / "out", cameras=(1,), tolerance_us=10)
    # a failure leaves none of the folders the writer made above out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["nclt", "np"]


def test_the_writer_refuses_cameras_of_one_name_and_removes_parents_it_made(tmp_path):
    from vvloc.data import DatasetWriter

    cam = Camera("front", 8, 6, np.array([[4.0, 0, 3.5], [0, 4, 2.5], [0, 0, 1]]), FORWARD)
    with pytest.raises(ValueError, match=r"cameras: names \['front'\] repeated"):
        DatasetWriter(tmp_path / "a", [cam, cam])
    with pytest.raises(RuntimeError, match="stop"):
        with DatasetWriter(tmp_path / "b" / "c" / "d", [cam]) as w:
            w.add_session("s0").add(0, (0.0, 0.0, 0.0), np.zeros((1, 3, 6, 8), np.uint8))
            raise RuntimeError("stop")
    assert list(tmp_path.iterdir()) == []


def test_a_converted_rendered_session_keeps_its_plan(tmp_path):
    # the trained-on check of eval / calibrate / targets compares a rendered session's
    # lighting and seed (session.json): a resized or thinned copy keeps them
    import json

    from vvloc.data import DatasetWriter
    from vvloc.localize.evaluation import trained_on
    from vvloc.sim.simulate import session_plan

    cam = Camera("front", 8, 6, np.array([[4.0, 0, 3.5], [0, 4, 2.5], [0, 0, 1]]), FORWARD)
    src = tmp_path / "synth"
    meta = {"generator": "vvloc.sim", "scene": "parking", "seed": 0}
    with DatasetWriter(src, [cam], meta=meta) as w:
        for spec in session_plan("parking", 3, 0):
            s = w.add_session(spec.name, meta={"lighting": spec.lighting, "seed": spec.seed})
            for k in range(3):
                s.add(k, (float(k), 0.0, 0.0), np.zeros((1, 3, 6, 8), np.uint8))
    copy = convert_dataset(src, tmp_path / "synth-every2", every=2)
    own = json.loads((src / "sessions" / "s1" / "session.json").read_text())
    assert json.loads((copy / "sessions" / "s1" / "session.json").read_text()) == {
        **own,
        "source_session": "s1",
    }
    record = {
        "runs": [
            {
                "config": {
                    "dataset": "elsewhere/synth-parking",
                    "train_sessions": ["s0", "s1"],
                    "sim": {"scene": "parking", "seed": 0},
                }
            }
        ]
    }
    assert trained_on(record, src, ["s1", "s2"]) == ["s1"]
    assert trained_on(record, copy, ["s1", "s2"]) == ["s1"]


def test_a_converted_dataset_converted_again_records_both_conversions(tmp_path):
    src = tmp_path / "nclt"
    _nclt(src)
    once = convert_dataset(src, tmp_path / "once", cameras=(1,), min_distance=0.5)
    twice = convert_dataset(once, tmp_path / "twice", every=2, image_size=(2, 3))
    meta = open_dataset(twice).meta["converted_from"]
    assert meta["path"] == str(once.resolve()) and meta["every"] == 2
    assert meta["image_size"] == [2, 3] and meta["source_converted_from"]["image_size"] is None
    assert meta["format"] == "vvloc" and meta["min_distance"] == 0.0
    first = meta["source_converted_from"]
    assert first["path"] == str(src.resolve()) and first["min_distance"] == 0.5


def test_cli_convert(tmp_path):
    import subprocess
    import sys

    src = tmp_path / "nclt"
    _nclt(src)
    exe = [sys.executable, "-m", "vvloc.cli", "convert", "--src", str(src)]
    run = lambda *a: subprocess.run([*exe, *a], capture_output=True, text=True)  # noqa: E731
    r = run("--out", str(tmp_path / "c"), "--cameras", "1", "--width", "3", "--height", "4")
    assert r.returncode == 0, r.stderr
    assert open_dataset(tmp_path / "c").cameras[0].width == 3
    # the default keeps the body frame's origin, above the ground where vvloc's BEV plane lies
    assert "warning: --ego_height not given: the ego origin stays at NCLT's body frame" in r.stderr
    # the frames the reader left out are counted, by reason
    said = f"{DATE}: the reader left out 1 of 3 frames (1: no ground truth within tolerance_us"
    assert f"{said}=50000)" in r.stdout, r.stdout
    r = run("--out", str(tmp_path / "g"), "--cameras", "1", "--ego_height", "0.5")
    assert r.returncode == 0 and "--ego_height" not in r.stderr, r.stderr
    # the last frame's ground truth is 0.2 s away: kept under a tolerance of 0.2 s
    r = run("--out", str(tmp_path / "h"), "--cameras", "1", "--tolerance_us", "200000")
    assert r.returncode == 0 and "left out" not in r.stdout, r.stdout
    assert len(open_dataset(tmp_path / "h").session(DATE)) == 3
    r = run("--out", str(tmp_path / "i"), "--cameras", "1", "--tolerance_us", "-1")
    assert r.returncode == 2 and "--tolerance_us" in r.stderr, r.stderr
    r = run("--out", str(tmp_path / "c"), "--cameras", "1")  # exists
    assert r.returncode == 2 and "exists" in r.stderr and r.stderr.count("\n") == 1, r.stderr
    r = run("--out", str(tmp_path / "d"), "--cameras", "left")
    assert r.returncode == 2 and "--cameras: NCLT cameras are numbers" in r.stderr
    r = run("--out", str(tmp_path / "d"), "--width", "16")
    assert r.returncode == 2 and "--width and --height go together" in r.stderr
    r = run("--out", str(tmp_path / "d"), "--motion_compensation")
    assert r.returncode == 2 and "--motion_compensation applies to RobotCar" in r.stderr
    assert r.stderr.count("\n") == 1, r.stderr  # a refused command says one line, no warning
    # the library's errors are said with the options they came from
    for args, said in (
        (("--cameras", "1", "--min_angle", "inf"), "--min_angle: expected a finite number"),
        (("--cameras", "1,1"), "--cameras: ['1'] listed more than once"),
        (("--cameras", "1", "--sessions", "nope"), "--sessions: no session 'nope' in"),
        (("--sessions", '"nope'), "--sessions: cannot read '\"nope' as comma-separated names"),
    ):
        r = run("--out", str(tmp_path / "d"), *args)
        assert r.returncode == 2 and said in r.stderr, r.stderr
    assert not (tmp_path / "d").exists()
    # the Segway's frames are levelled unless --no_level (this fixture's Segway stands level:
    # every frame's extrinsics are the rig's, written all the same)
    r = run("--out", str(tmp_path / "e"), "--cameras", "1")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "e" / "sessions" / DATE / "cam_to_ego.csv").is_file()
    r = run("--out", str(tmp_path / "f"), "--cameras", "1", "--no_level")
    assert r.returncode == 0, r.stderr
    assert not (tmp_path / "f" / "sessions" / DATE / "cam_to_ego.csv").exists()


def test_commands_given_a_raw_folder_warn_that_they_read_it_with_the_readers_defaults(tmp_path):
    import subprocess
    import sys

    src = tmp_path / "nclt"
    _nclt(src)
    r = subprocess.run(
        [sys.executable, "-m", "vvloc.cli", "map", "build", "--dataset", str(src), "--sessions",
         "nope", "--checkpoint", "models/synth-small", "--out", str(tmp_path / "map.h5")],
        capture_output=True, text=True,
    )  # fmt: skip
    assert r.returncode == 2, r.stderr
    assert f"--dataset: {src} is an NCLT raw folder, read with the reader's defaults" in r.stderr
    assert "convert it once with vvloc convert --ego_height" in r.stderr
    # then what the reader says (its default cameras are NCLT's 1-5; this folder holds 1 and 2)
    assert r.stderr.splitlines()[-1].endswith("Cam3: camera folder missing"), r.stderr


def test_convert_keeps_the_named_cameras_of_a_vvloc_dataset(tmp_path):
    import subprocess
    import sys

    from vvloc.data import DatasetWriter

    K = np.array([[4.0, 0, 3.5], [0, 4, 2.5], [0, 0, 1]])
    rig = [Camera(n, 8, 6, K, FORWARD) for n in ("front", "left", "broken")]
    src = tmp_path / "rig3"
    with DatasetWriter(src, rig) as w:
        s = w.add_session("s0")
        for k in range(3):
            own = np.stack([FORWARD] * 3)
            own[:, 0, 3] = [0.0, 0.3, 0.6]  # each camera's own extrinsics, told apart by x
            images = np.stack([np.full((3, 6, 8), 10 * c + k, np.uint8) for c in range(3)])
            s.add(k, (float(k), 0.0, 0.0), images, cam_to_ego=own)
    out = convert_dataset(src, tmp_path / "two", cameras=["left", "front"])
    two = open_dataset(out)
    assert [c.name for c in two.cameras] == ["left", "front"]
    frame = two.session("s0")[2]
    assert frame.images[:, 0, 0, 0].tolist() == [12, 2]  # left's pixels, then front's
    assert frame.cam_to_ego[:, 0, 3].tolist() == [0.3, 0.0]
    assert two.meta["converted_from"]["options"] == {"cameras": ["left", "front"]}
    for cameras, match in (
        (["back"], r"cameras: \['back'\] not in the source's rig \['front', 'left', 'broken'\]"),
        (["left", "left"], r"cameras: \['left'\] listed more than once"),
        ([], "cameras: expected a non-empty list"),
    ):
        with pytest.raises(ValueError, match=match):
            convert_dataset(src, tmp_path / "bad", cameras=cameras)
    with pytest.raises(TypeError, match="cameras: expected a list"):
        convert_dataset(src, tmp_path / "bad", cameras="left")
    assert not (tmp_path / "bad").exists()
    exe = [sys.executable, "-m", "vvloc.cli", "convert", "--src", str(src)]
    r = subprocess.run(
        [*exe, "--out", str(tmp_path / "cli"), "--cameras", "front"], text=True, capture_output=True
    )
    assert r.returncode == 0, r.stderr
    assert [c.name for c in open_dataset(tmp_path / "cli").cameras] == ["front"]
    r = subprocess.run(
        [*exe, "--out", str(tmp_path / "cli2"), "--cameras", "rear"], text=True, capture_output=True
    )
    assert r.returncode == 2 and "--cameras: ['rear'] not in the source's rig" in r.stderr


def test_a_rendered_session_round_trips_through_nclts_raw_layout(tiny_world, tmp_path):
    """Write a rendered session the way NCLT stores its data (sideways TIFFs, Ladybug-frame
    extrinsics as ssc six-vectors in degrees, NED ground truth in radians), read it back with
    the NCLT reader and convert it: the images, calibration and poses come back."""
    from vvloc.data.frame import NED_TO_ENU
    from vvloc.data.nclt import ssc_degrees_to_matrix

    sim = open_dataset(tiny_world)
    session = sim.session("s0")
    frames = [session[i] for i in range(4)]
    root = tmp_path / "nclt"
    params = root / "cam_params"
    params.mkdir(parents=True)
    T_body_lb3 = ssc_degrees_to_matrix(X_BODY_LB3)
    for i, cam in enumerate(sim.cameras, start=1):
        stored = cam.rotated(1)  # NCLT keeps its images a quarter turn from upright
        np.savetxt(params / f"K_cam{i}.csv", stored.K, delimiter=",")
        T = np.linalg.inv(T_body_lb3) @ FRD_TO_FLU @ stored.cam_to_ego
        yaw, pitch, roll = Rotation.from_matrix(T[:3, :3]).as_euler("ZYX", degrees=True)
        np.savetxt(params / f"x_lb3_c{i}.csv", [[*T[:3, 3], roll, pitch, yaw]], delimiter=",")
        d = root / DATE / "lb3" / f"Cam{i}"
        d.mkdir(parents=True)
        for f in frames:
            img = np.rot90(f.images[i - 1].transpose(1, 2, 0), 1)
            Image.fromarray(np.ascontiguousarray(img)).save(d / f"{round(f.t * 1e6)}.tiff")
    rows = []
    for f in frames:
        x, y, yaw = f.pose
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("z", yaw).as_matrix()
        T[:3, 3] = (x, y, f.z)
        T_ned_body = NED_TO_ENU @ T @ FRD_TO_FLU
        h, p, r = Rotation.from_matrix(T_ned_body[:3, :3]).as_euler("ZYX")
        rows.append([round(f.t * 1e6), *T_ned_body[:3, 3], r, p, h])
    np.savetxt(root / f"groundtruth_{DATE}.csv", rows, delimiter=",", fmt="%.17g")

    with pytest.warns(UserWarning, match="undistortion map"):
        nclt = open_dataset(root, cameras=(1, 2, 3, 4))
    back = nclt.session(DATE)
    assert len(back) == 4
    np.testing.assert_allclose(back.poses[:, :2], session.poses[:4, :2], atol=1e-9)
    np.testing.assert_allclose(np.cos(back.poses[:, 2] - session.poses[:4, 2]), 1.0, atol=1e-12)
    np.testing.assert_allclose(back.z, session.z[:4], atol=1e-9)
    for cam, orig in zip(nclt.cameras, sim.cameras, strict=True):
        assert (cam.width, cam.height) == (orig.width, orig.height)
        np.testing.assert_allclose(cam.K, orig.K, atol=1e-9)
        np.testing.assert_allclose(cam.cam_to_ego, orig.cam_to_ego, atol=1e-9)
    np.testing.assert_array_equal(back[2].images, frames[2].images)
    # and through vvloc convert, into the vvloc format the commands read
    with pytest.warns(UserWarning, match="undistortion map"):
        out = convert_dataset(root, tmp_path / "converted", cameras=(1, 2, 3, 4))
    conv = open_dataset(out).session(DATE)
    np.testing.assert_array_equal(conv[3].images, frames[3].images)
    np.testing.assert_allclose(conv.poses, back.poses)


# --- a tilting vehicle and cameras that fire apart: per-frame extrinsics -------------------------


def _world_ego(pose, z):
    """4×4 ego → world of a vvloc pose (x, y, yaw) at height z: level by DESIGN.md §3."""
    T = euler_to_matrix(pose[0], pose[1], z, 0.0, 0.0, pose[2])
    return T


def _random_rigid(rng, scale=1.0):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    T[:3, 3] = rng.normal(size=3) * scale
    return T


def test_ego_frames_level_the_ego_frame_and_keep_every_camera_where_it_was():
    rng = np.random.default_rng(3)
    n, h = 6, 1.3
    world_body = np.stack(
        [
            euler_to_matrix(
                *rng.normal(size=3) * 20, *rng.uniform(-0.2, 0.2, 2), rng.uniform(-3, 3)
            )
            for _ in range(n)
        ]
    )
    rig = [
        Camera(f"c{m}", 8, 6, np.eye(3), _random_rigid(rng)).with_ego_origin_lowered(h)
        for m in range(3)
    ]
    lower = np.eye(4)
    lower[2, 3] = -h
    poses, z, per_frame = ego_frames(world_body, rig, height=h)
    assert per_frame is not None and per_frame.shape == (n, 3, 4, 4)
    for k in range(n):
        # the ego origin is the ground point h below the body origin along the body's z axis,
        # and its heading is the body's
        ground = world_body[k] @ lower
        np.testing.assert_allclose([*poses[k, :2], z[k]], ground[:3, 3], atol=1e-12)
        fwd = world_body[k][:3, 0]
        assert poses[k, 2] == pytest.approx(math.atan2(fwd[1], fwd[0]), abs=1e-12)
        # every camera sits where the 6-DoF chain puts it: level ego · frame's cam_to_ego
        for m, cam in enumerate(rig):
            want = world_body[k] @ lower @ cam.cam_to_ego
            got = _world_ego(poses[k], z[k]) @ per_frame[k, m]
            np.testing.assert_allclose(got, want, atol=1e-9)
    # level=False: the tilting body frame is the ego frame; every frame has the rig's extrinsics
    poses0, z0, none = ego_frames(world_body, rig, height=h, level=False)
    assert none is None
    np.testing.assert_array_equal(poses0, poses)
    np.testing.assert_array_equal(z0, z)
    # motion compensation: each camera from where the body was at its own exposure
    at_cams = np.stack([world_body @ _random_rigid(rng, 0.3) for _ in rig], axis=1)
    poses1, z1, moved = ego_frames(world_body, rig, height=h, world_body_at_cameras=at_cams)
    np.testing.assert_array_equal(poses1, poses)
    for k in range(n):
        for m, cam in enumerate(rig):
            want = at_cams[k, m] @ lower @ cam.cam_to_ego
            np.testing.assert_allclose(_world_ego(poses1[k], z1[k]) @ moved[k, m], want, atol=1e-9)
    with pytest.raises(ValueError, match=r"world_body_at_cameras: expected \(6, 3, 4, 4\)"):
        ego_frames(world_body, rig, world_body_at_cameras=at_cams[:, :2])


def _tilt_nclt(root, roll=0.06, pitch=-0.09):
    """_nclt with a Segway that rolls and pitches (radians, NCLT's NED ground truth)."""
    _nclt(root)
    gt = [
        [1_000_010, 10.0, 5.0, -1.0, roll, pitch, 0.3],
        [1_200_020, 11.0, 5.5, -1.0, -roll, 2 * pitch, 0.4],
    ]
    (root / f"groundtruth_{DATE}.csv").write_text("\n".join(",".join(map(str, r)) for r in gt))
    return gt


def test_nclt_frames_are_levelled_by_the_segways_roll_and_pitch(tmp_path):
    gt = _tilt_nclt(tmp_path)
    h = 0.4
    with pytest.warns(UserWarning, match="U2D_Cam2"):
        ds = open_dataset(tmp_path, cameras=(1, 2), ego_height=h, upright=False)
    s = ds.session(DATE)
    assert s.frame_cam_to_ego is not None
    lower = np.eye(4)
    lower[2, 3] = -h
    for k, row in enumerate(gt):
        f = s[k]
        world_body = NED_TO_ENU @ euler_to_matrix(*row[1:]) @ FRD_TO_FLU
        for m, cam in enumerate(ds.cameras):
            # the level ego frame with this frame's cam_to_ego puts the camera where the
            # ground truth's full attitude does
            want = world_body @ lower @ cam.cam_to_ego
            np.testing.assert_allclose(_world_ego(f.pose, f.z) @ f.cam_to_ego[m], want, atol=1e-9)
        # a tilted frame's cameras differ from the rig's by the body's attitude (about 6-10°)
        angle = Rotation.from_matrix(f.cam_to_ego[0][:3, :3] @ ds.cameras[0].cam_to_ego[:3, :3].T)
        assert 3.0 < math.degrees(angle.magnitude()) < 12.0
    with pytest.warns(UserWarning, match="U2D_Cam2"):
        flat = open_dataset(tmp_path, cameras=(1, 2), ego_height=h, level=False, upright=False)
    fs = flat.session(DATE)
    assert fs.frame_cam_to_ego is None
    np.testing.assert_array_equal(fs[0].cam_to_ego[0], flat.cameras[0].cam_to_ego)
    np.testing.assert_array_equal(fs.poses, s.poses)  # the same origin and heading
    with pytest.raises(TypeError, match="level: expected a bool"):
        open_dataset(tmp_path, cameras=(1,), level=1)


def test_per_frame_extrinsics_survive_conversion_to_the_vvloc_format(tmp_path):
    _tilt_nclt(tmp_path / "raw")
    with pytest.warns(UserWarning, match="U2D_Cam2"):
        src = open_dataset(tmp_path / "raw", cameras=(1, 2), ego_height=0.4, upright=False)
    with pytest.warns(UserWarning, match="U2D_Cam2"):
        convert_dataset(
            tmp_path / "raw", tmp_path / "out", cameras=(1, 2), ego_height=0.4, upright=False
        )
    path = tmp_path / "out" / "sessions" / DATE / "cam_to_ego.csv"
    assert path.read_text().startswith("timestamp,camera,m00,m01,m02,m03,m10,")
    out = open_dataset(tmp_path / "out").session(DATE)
    a, b = src.session(DATE), out
    np.testing.assert_array_equal(b.frame_cam_to_ego, a.frame_cam_to_ego)  # exact (repr floats)
    np.testing.assert_array_equal(b[1].cam_to_ego, a[1].cam_to_ego)
    # the rig's own frames write no file
    with pytest.warns(UserWarning, match="U2D_Cam2"):
        convert_dataset(
            tmp_path / "raw",
            tmp_path / "flat",
            cameras=(1, 2),
            ego_height=0.4,
            level=False,
            upright=False,
        )
    assert not (tmp_path / "flat" / "sessions" / DATE / "cam_to_ego.csv").exists()
    assert open_dataset(tmp_path / "flat").session(DATE).frame_cam_to_ego is None
    # malformed files are refused, naming the file and the line
    lines = path.read_text().splitlines()
    for bad, match in (
        (lines[:-1], r"cam_to_ego\.csv: no row for timestamp 1200000, camera 'Cam2'"),
        ([*lines, lines[-1]], r"cam_to_ego\.csv, line 6: a second row for timestamp 1200000"),
        ([lines[0], lines[1].replace("Cam1", "Cam9"), *lines[2:]], r"line 2: camera 'Cam9'"),
        ([lines[0], "1000000,Cam1," + ",".join(["2.0"] * 12), *lines[2:]], r"line 2: not a"),
        ([lines[0], "7,Cam1," + ",".join(["0"] * 12)], r"line 2: timestamp 7 is not in poses"),
        (["timestamp,camera", *lines[1:]], r"cam_to_ego\.csv, line 1: header must be"),
    ):
        path.write_text("\n".join(bad) + "\n")
        with pytest.raises(DatasetFormatError, match=match):
            open_dataset(tmp_path / "out")


def test_the_writer_takes_per_frame_extrinsics_from_every_frame_or_none(tmp_path):
    from vvloc.data.vvloc_format import DatasetWriter

    cam = Camera("front", 4, 3, np.eye(3), FORWARD)
    img = np.zeros((1, 3, 3, 4), np.uint8)
    with DatasetWriter(tmp_path / "a", [cam]) as w:
        s = w.add_session("s0")
        s.add(0, (0, 0, 0), img, cam_to_ego=FORWARD[None])
        with pytest.raises(ValueError, match=r"cam_to_ego: every frame .* had its own"):
            s.add(1, (0, 0, 0), img)
        with pytest.raises(ValueError, match=r"cam_to_ego: expected float \(1, 4, 4\)"):
            s.add(1, (0, 0, 0), img, cam_to_ego=np.eye(4))
        with pytest.raises(ValueError, match="cam_to_ego: expected finite rigid"):
            s.add(1, (0, 0, 0), img, cam_to_ego=2 * np.eye(4)[None])
        skewed = np.eye(4)[None].copy()
        skewed[0, 3, 0] = 0.5  # not a rigid transform's bottom row (the file keeps 3 rows)
        with pytest.raises(ValueError, match="bottom row 0 0 0 1"):
            s.add(1, (0, 0, 0), img, cam_to_ego=skewed)
        s.add(1, (0, 0, 0), img, cam_to_ego=FORWARD[None])
        t = w.add_session("s1")
        t.add(0, (0, 0, 0), img)
        with pytest.raises(ValueError, match="the first frame of this session had the rig's"):
            t.add(1, (0, 0, 0), img, cam_to_ego=np.eye(4)[None])
    ds = open_dataset(tmp_path / "a")
    assert ds.session("s0").frame_cam_to_ego.shape == (2, 1, 4, 4)
    assert len(ds.session("s1")) == 1 and ds.session("s1").frame_cam_to_ego is None


def _unsynchronised_oxford(root, gap_us):
    """_oxford with the second stereo frame's mono_left image taken ``gap_us`` earlier."""
    sess = _oxford(root)
    mono = sess / "mono_left"
    (mono / "200030.png").rename(mono / f"{200_000 - gap_us}.png")
    (sess / "mono_left.timestamps").write_text(f"120 1\n{200_000 - gap_us} 1\n400010 1\n")
    return sess


def test_oxford_cameras_are_placed_where_they_were_at_their_own_exposure(tmp_path):
    sess = _unsynchronised_oxford(tmp_path, 40_000)
    cams = ("stereo_centre", "mono_left")
    ds = open_dataset(tmp_path, cameras=cams, ego_height=1.5)
    still = open_dataset(tmp_path, cameras=cams, ego_height=1.5, motion_compensation=False)
    f, g = ds.session(sess.name)[1], still.session(sess.name)[1]
    np.testing.assert_array_equal(f.pose, g.pose)  # the frame's pose is the stereo camera's
    np.testing.assert_allclose(f.cam_to_ego[0], g.cam_to_ego[0], atol=1e-9)
    # the mono camera fired 40 ms earlier: it is where the vehicle's frame at that time put it
    (t0, _, n0, e0, y0), _, (t1, _, n1, e1, y1) = INS_ROWS
    poses = []
    for t in (100, 200_000, 160_000):
        w = (t - t0) / (t1 - t0)
        poses.append(_vehicle_enu(n0 + w * (n1 - n0), e0 + w * (e1 - e0), y0 + w * (y1 - y0)))
    (ex0, ny0, _), _, (ex, ny, yaw) = poses
    at_exposure = euler_to_matrix(ex - ex0, ny - ny0, 0.0, 0.0, 0.0, yaw)
    world_cam = _world_ego(f.pose, 0.0) @ f.cam_to_ego[1]
    want = at_exposure @ still.cameras[1].cam_to_ego
    np.testing.assert_allclose(world_cam[:2], want[:2], atol=1e-6)
    # which is about 0.24 m from where the rig puts it at the frame's time: in those 40 ms the
    # INS moved 0.22 m and turned 1.1°, which swings the camera 1.6 m behind it by 3 cm more
    shift = np.linalg.norm((f.cam_to_ego[1] - g.cam_to_ego[1])[:2, 3])
    assert 0.2 < shift < 0.28
    # a camera whose exposure the INS does not cover is not joined
    (sess / "gps" / "ins.csv").write_text(
        "\n".join((sess / "gps" / "ins.csv").read_text().splitlines()[:2]) + "\n"
    )
    with pytest.raises(DatasetFormatError, match="no frame has an image of every camera"):
        open_dataset(tmp_path, cameras=cams, tolerance_us=20)  # mono at 120 µs, INS at 90 µs
    kept = open_dataset(tmp_path, cameras=cams, tolerance_us=20, motion_compensation=False)
    assert len(kept.session(sess.name)) == 1
    with pytest.raises(TypeError, match="motion_compensation: expected a bool"):
        open_dataset(tmp_path, cameras=cams, motion_compensation="no")


def test_oxford_frames_are_levelled_by_the_cars_roll_and_pitch(tmp_path):
    """The full chain of a tilting car whose cameras fire apart: every camera where the INS
    (interpolated at its own exposure, roll and pitch included) puts it, poses and heights of
    the ground point under the vehicle origin, and a frame the INS does not cover dropped."""
    sess = _unsynchronised_oxford(tmp_path, -60_000)  # mono of frame 2 at 260 ms, 60 ms late
    rows = [  # time, northing, easting, down, roll, pitch, yaw (the INS's NED frame)
        (90, 5_700_000.0, 620_000.0, -100.0, 0.05, -0.08, 0.2),
        (200_010, 5_700_001.0, 620_000.5, -100.2, -0.04, 0.06, 0.3),
        (400_020, 5_700_003.0, 620_001.5, -100.1, 0.02, 0.03, 0.5),
    ]
    header = (
        "timestamp,ins_status,latitude,longitude,altitude,northing,easting,down,utm_zone,"
        "velocity_north,velocity_east,velocity_down,roll,pitch,yaw"
    )
    lines = [
        f"{t},INS_SOLUTION_GOOD,0,0,0,{n},{e},{d},30U,0,0,0,{r},{p},{y}"
        for t, n, e, d, r, p, y in rows
    ]
    (sess / "gps" / "ins.csv").write_text(header + "\n" + "\n".join(lines) + "\n")
    h, cams = 1.5, ("stereo_centre", "mono_left")
    ds = open_dataset(tmp_path, cameras=cams, ego_height=h)
    s = ds.session(sess.name)
    # the 200 ms frame's mono image is 60 ms away, beyond the 50 ms tolerance: not joined
    assert s.timestamps.tolist() == [100, 400_000]
    ins_t, ins = np.array([r[0] for r in rows]), np.array([r[1:] for r in rows])
    T_vehicle_ins = euler_to_matrix(*INS_LEVER, 0, 0, 0)

    def world_vehicle(t):  # linear interpolation of the INS rows, as the SDK does
        v = [np.interp(t, ins_t, ins[:, c]) for c in range(6)]
        return NED_TO_ENU @ euler_to_matrix(*v) @ np.linalg.inv(T_vehicle_ins) @ FRD_TO_FLU

    lower = np.eye(4)
    lower[2, 3] = -h
    origin = np.asarray(ds.meta["origin_enu"])
    np.testing.assert_allclose(origin, (world_vehicle(100) @ lower)[:3, 3], atol=1e-6)
    for k, (t, t_mono) in enumerate(((100, 120), (400_000, 400_010))):
        f = s[k]
        ground = world_vehicle(t) @ lower
        np.testing.assert_allclose([*f.pose[:2], f.z], ground[:3, 3] - origin, atol=1e-6)
        world_ego = euler_to_matrix(*(origin + np.array([*f.pose[:2], f.z])), 0.0, 0.0, f.pose[2])
        for m, t_cam in enumerate((t, t_mono)):
            want = world_vehicle(t_cam) @ lower @ ds.cameras[m].cam_to_ego
            np.testing.assert_allclose(world_ego @ f.cam_to_ego[m], want, atol=1e-6)
        # the tilt is in the frame's extrinsics: 3-10° from the rig's
        turn = Rotation.from_matrix(f.cam_to_ego[0][:3, :3] @ ds.cameras[0].cam_to_ego[:3, :3].T)
        assert 2.0 < math.degrees(turn.magnitude()) < 10.0
    flat = open_dataset(
        tmp_path, cameras=cams, ego_height=h, level=False, motion_compensation=False
    )
    assert flat.session(sess.name).frame_cam_to_ego is None
    np.testing.assert_array_equal(flat.session(sess.name).poses, s.poses)


def test_readers_without_any_usable_frame_say_so(tmp_path):
    sess = _oxford(tmp_path / "ox")
    for p in (sess / "mono_left").glob("*.png"):
        p.unlink()  # a partial download: timestamps listed, images missing
    with pytest.raises(DatasetFormatError, match="no frame has an image of every camera"):
        open_dataset(tmp_path / "ox", cameras=("stereo_centre", "mono_left"))
    _nclt(tmp_path / "nclt")
    (tmp_path / "nclt" / f"groundtruth_{DATE}.csv").write_text("5000000,1,2,3,0,0,0\n")
    with pytest.warns(UserWarning, match="U2D_Cam2"):
        s = open_dataset(tmp_path / "nclt", cameras=(1, 2), upright=False).session(DATE)
    assert len(s) == 0 and s.frame_cam_to_ego.shape == (0, 2, 4, 4)


def _drive(offset_deg: float, *, n: int = 200, spacing: float = 0.5) -> np.ndarray:
    """(N, 3) poses of a drive: 40 m east, a quarter turn left, 40 m north, ..., the yaw
    `offset_deg` off the direction of travel, with centimetre position noise."""
    rng = np.random.default_rng(0)
    poses, x, y, yaw = [], 0.0, 0.0, 0.0
    for k in range(n):
        if k % 100 >= 80:  # a 90° turn over the last 20 poses of every 100
            yaw += math.radians(90.0 / 20)
        x += spacing * math.cos(yaw)
        y += spacing * math.sin(yaw)
        poses.append((x, y, yaw))
    p = np.array(poses)
    p[:, :2] += rng.normal(0.0, 0.01, (n, 2))
    p[:, 2] += math.radians(offset_deg)
    return p


def test_heading_offset_measures_a_yaw_off_the_direction_of_travel():
    from vvloc.data.heading import MIN_STRETCHES, heading_offset, heading_warning

    for offset in (0.0, 1.4, -3.0, 12.0):
        got, count = heading_offset(_drive(offset))
        assert got == pytest.approx(offset, abs=0.1) and count >= MIN_STRETCHES
    # driven backwards: the yaw points against the travel, those stretches are left out ...
    back = _drive(0.0)
    back[:, 2] += math.pi
    got, _ = heading_offset(np.concatenate([_drive(0.7), back]))
    assert got == pytest.approx(0.7, abs=0.1)
    # ... but a whole session "reversing" is a yaw pointing backwards (it went unmeasured)
    for offset in (100.0, 180.0, -135.0):
        got, count = heading_offset(_drive(offset, n=400))
        assert (got - offset + 180) % 360 - 180 == pytest.approx(0.0, abs=0.1)
        assert count >= MIN_STRETCHES
    # a car standing still, or too few poses: nothing to measure
    assert heading_offset(np.zeros((50, 3)))[1] == 0
    assert heading_offset(np.zeros((0, 3)))[1] == 0
    with pytest.raises(ValueError, match=r"poses: expected shape \(N, 3\)"):
        heading_offset(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="poses: holds non-finite"):
        heading_offset(np.array([[0.0, 0.0, 0.0], [np.nan, 1.0, 0.0]]))
    assert heading_warning("s", _drive(0.3)) is None
    note = heading_warning("s", _drive(1.4))
    assert note is not None and note.startswith("session s: the yaw differs from the direction")
    assert heading_warning("s", _drive(1.4, n=70)) is None  # too few stretches to tell
    # a compass heading (90° − yaw) fits 90° minus the direction of travel, whichever way the
    # roads run (this drive's run along the axes, where heading_offset sees ±90° and leaves
    # them out), and driven backwards too
    from vvloc.data.heading import compass_fit

    drive = _drive(0.0)
    travel, compass, n = compass_fit(drive)
    assert travel == pytest.approx(0.0, abs=0.5) and compass > 45 and n >= MIN_STRETCHES
    for p, said in ((drive, "a compass heading"), (back, "clockwise: -90.0° minus")):
        mirrored = p.copy()
        mirrored[:, 2] = math.pi / 2 - p[:, 2]
        travel, compass, _ = compass_fit(mirrored)
        assert compass == pytest.approx(0.0, abs=0.5) and travel > 45
        # (a whole session facing backwards is read as a car driving forwards: the compass
        # heading of the reversed yaw is 90° - (yaw + 180°), clockwise from -90°)
        note = heading_warning("s", mirrored)
        assert note is not None and note.startswith(f"session s: the yaw reads as {said}")
    assert compass_fit(np.zeros((3, 3)))[2] == 0


def test_heading_warning_tells_a_mirrored_yaw_from_a_constant_offset():
    from vvloc.data.heading import heading_warning, mirror_fit
    from vvloc.geometry import wrap_angle

    drive = _drive(0.0, n=400)  # along the axes: where the two readings agree modulo 180°
    assert heading_warning("s", drive) is None
    assert mirror_fit(drive)[1] is False
    # a yaw off by a quarter turn or more: said as an offset (a quarter turn read as a compass
    # heading before, and from 90° on nothing was said: every stretch counted as reversing)
    for offset in (90.0, -90.0, 100.0, 180.0):
        note = heading_warning("s", _drive(offset, n=400))
        assert note is not None, offset
        said = re.search(r"differs from the direction of travel by a median of ([-+.0-9]+)°", note)
        assert said is not None
        assert (float(said[1]) - offset + 180) % 360 - 180 == pytest.approx(0, abs=0.5)
        assert "the yaw's x axis is not the vehicle's forward" in note
    assert "x axis is not" not in (heading_warning("s", _drive(12.0)) or "")
    # a clockwise (negated) yaw: right on the east-west roads, a half turn off on the others
    negated = drive.copy()
    negated[:, 2] = -drive[:, 2]
    assert mirror_fit(negated)[:2] == (pytest.approx(0.0, abs=0.5), True)
    note = heading_warning("s", negated)
    assert note is not None and "the yaw reads as clockwise (the y axis flipped)" in note
    # clockwise from another axis (here 40°), on roads that do not run along the axes either
    turned = drive.copy()
    turned[:, :2] = drive[:, :2] @ np.array([[0.8, 0.6], [-0.6, 0.8]])  # rotated by 36.87°
    turned[:, 2] = drive[:, 2] + math.atan2(0.6, 0.8)
    assert heading_warning("s", turned) is None
    turned[:, 2] = math.radians(40.0) - turned[:, 2]
    note = heading_warning("s", turned)
    assert note is not None and "clockwise: 40.0° minus the direction of travel" in note
    # the compass heading is still named as such; clockwise from the x axis's other end (a
    # flipped x axis) is no negated yaw
    compass = drive.copy()
    compass[:, 2] = math.pi / 2 - drive[:, 2]
    note = heading_warning("s", compass)
    assert note is not None and note.startswith("session s: the yaw reads as a compass")
    for c in (180.0, -90.0):
        other = drive.copy()
        other[:, 2] = wrap_angle(math.radians(c) - drive[:, 2])
        note = heading_warning("s", other)
        assert note is not None and f"clockwise: {c:.1f}° minus the direction" in note, c
    # a single road, its yaw noisy (10 cm GPS, a slowly wandering 2° yaw error): a correct
    # yaw is not read as mirrored (mirror and offset fit such a road alike)
    for seed in range(40):
        rng = np.random.default_rng(seed)
        n = 400
        slow = np.convolve(rng.normal(size=n + 79), np.ones(80) / np.sqrt(80), "valid")
        xy = np.column_stack([np.arange(n) * 0.5, np.zeros(n)]) + rng.normal(0, 0.1, (n, 2))
        for road in (0.0, 45.0):
            turn = np.array(
                [
                    [math.cos(math.radians(road)), math.sin(math.radians(road))],
                    [-math.sin(math.radians(road)), math.cos(math.radians(road))],
                ]
            )
            p = np.column_stack([xy @ turn, math.radians(road) + math.radians(2) * slow])
            assert heading_warning("s", p, limit_deg=5.0) is None, (seed, road)


def test_the_readers_check_each_sessions_yaw_against_its_travel(tmp_path, monkeypatch):
    import vvloc.data.nclt as nclt_reader
    import vvloc.data.oxford as oxford_reader

    seen = []

    def warn(name, poses):
        seen.append((name, np.asarray(poses).shape))
        return f"session {name}: the yaw differs (test)"

    sess = _oxford(tmp_path / "oxford")
    _nclt(tmp_path / "nclt")
    for module in (oxford_reader, nclt_reader):
        monkeypatch.setattr(module, "heading_warning", warn)
    with pytest.warns(UserWarning, match=f"session {sess.name}: the yaw differs"):
        open_dataset(tmp_path / "oxford", cameras=("stereo_centre", "mono_left"))
    with pytest.warns(UserWarning) as record:
        open_dataset(tmp_path / "nclt", cameras=(1, 2), upright=False)
    assert any(f"session {DATE}: the yaw differs" in str(w.message) for w in record)
    assert seen == [(sess.name, (2, 3)), (DATE, (2, 3))]
