"""NCLT and Oxford RobotCar readers on tiny fixtures written here in each dataset's raw layout."""

from __future__ import annotations

import math

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from vvloc.data import DatasetFormatError, open_dataset
from vvloc.data.bayer import demosaic_bilinear, mosaic
from vvloc.data.frame import FRD_TO_FLU, euler_to_matrix
from vvloc.data.nclt import X_BODY_LB3

DATE = "2012-01-08"


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
        np.savetxt(params / f"x_lb3_c{i}.csv", [[0.1 * i, 0, 0, 0, 0, 72.0 * i]], delimiter=",")
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
    ds = open_dataset(tmp_path, cameras=(1, 2))
    assert ds.sessions == [DATE]
    s = ds.session(DATE)
    assert len(s) == 2 and list(s.timestamps) == [1_000_000, 1_200_000]
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
    T_lb3_c2 = euler_to_matrix(0.2, 0, 0, 0, 0, np.deg2rad(144.0))
    assert np.allclose(f.cam_to_ego[1], FRD_TO_FLU @ T_body_lb3 @ T_lb3_c2)
    assert np.allclose(f.K[0], [[5, 0, 3.5], [0, 5, 2.5], [0, 0, 1]])
    small = open_dataset(tmp_path, cameras=(2,), image_size=(4, 3)).session(DATE)[0]
    assert small.images.shape == (1, 3, 3, 4) and small.K[0, 0, 0] == pytest.approx(2.5)


def test_nclt_reader_reports_bad_files(tmp_path):
    _nclt(tmp_path, with_map=False)
    (tmp_path / f"groundtruth_{DATE}.csv").write_text("1,2,3\n")
    with pytest.raises(DatasetFormatError, match=r"groundtruth_2012-01-08\.csv, line 1"):
        open_dataset(tmp_path, cameras=(1,))
    (tmp_path / "cam_params" / "K_cam1.csv").write_text("1,2\n")
    with pytest.raises(DatasetFormatError, match=r"K_cam1\.csv"):
        open_dataset(tmp_path, cameras=(1,))


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


def _oxford(root):
    sess = root / "2019-01-10-11-46-21-radar-oxford-10k"
    (root / "models").mkdir(parents=True)
    (root / "extrinsics").mkdir()
    for model, (fx, cx) in (("stereo_narrow_left", (8.0, 3.5)), ("mono_left", (6.0, 2.5))):
        lines = [f"{fx} {fx} {cx} {cx - 1}"] + [" ".join(map(str, r)) for r in G_CAMERA_IMAGE]
        (root / "models" / f"{model}.txt").write_text("\n".join(lines) + "\n")
    (root / "extrinsics" / "mono_left.txt").write_text(f"0.5 -0.8 0 0 0 {-math.pi / 2}\n")
    (root / "extrinsics" / "ins.txt").write_text("0 0 0 0 0 0\n")
    # identity undistortion LUT for mono_left (6x6): source (u, v) of every output pixel
    vv, uu = np.mgrid[0:6, 0:6].astype(np.float64)
    np.concatenate([uu.ravel(), vv.ravel()]).tofile(
        root / "models" / "mono_left_distortion_lut.bin"
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
        f"{t},INS_SOLUTION_GOOD,51.7,-1.2,100,{n},{e},-100,30U,0,0,0,0,0,{yaw}"
        for t, n, e, yaw in (
            (90, 5_700_000.0, 620_000.0, 0.2),
            (200_010, 5_700_001.0, 620_000.5, 0.3),
        )
    ]
    (sess / "gps" / "ins.csv").write_text(header + "\n" + "\n".join(rows) + "\n")
    return sess


def test_oxford_reader_demosaics_and_converts_frames(tmp_path):
    sess = _oxford(tmp_path)
    ds = open_dataset(tmp_path, cameras=("stereo_centre", "mono_left"))
    s = ds.session(sess.name)
    assert len(s) == 2  # the 400_000 frame has no INS row within the tolerance
    assert np.allclose(ds.meta["origin_enu"][:2], [620_000.0, 5_700_000.0])
    assert np.allclose(s.poses[0], [0.0, 0.0, math.pi / 2 - 0.2])
    assert np.allclose(s.poses[1], [0.5, 1.0, math.pi / 2 - 0.3])
    f = s[1]
    assert f.images.shape == (2, 3, 6, 8)  # mono resized to the stereo camera's size
    assert np.all(f.images[0].transpose(1, 2, 0) == (200, 100, 30))  # GBRG demosaiced
    assert np.all(f.images[1].transpose(1, 2, 0) == (20, 220, 120))  # RGGB demosaiced
    # stereo (vehicle frame, identity): optical axis forward, image right = ego right (-y)
    assert np.allclose(f.cam_to_ego[0][:3, 2], [1, 0, 0]) and np.allclose(
        f.cam_to_ego[0][:3, 0], [0, -1, 0]
    )
    # mono_left yawed -90° in the FRD vehicle frame looks left (+y in FLU), sits at y = +0.8
    assert np.allclose(f.cam_to_ego[1][:3, 2], [0, 1, 0]) and np.allclose(
        f.cam_to_ego[1][:3, 3], [0.5, 0.8, 0]
    )
    assert np.allclose(f.K[0], [[8, 0, 3.5], [0, 8, 2.5], [0, 0, 1]])
    assert f.K[1, 0, 0] == pytest.approx(6.0 * 8 / 6) and f.K[1, 1, 1] == pytest.approx(6.0)


def test_oxford_reader_reports_bad_files(tmp_path):
    sess = _oxford(tmp_path)
    (sess / "gps" / "ins.csv").write_text("timestamp,northing\n1,2\n")
    with pytest.raises(DatasetFormatError, match=r"ins\.csv, line 1: header lacks"):
        open_dataset(tmp_path, cameras=("stereo_centre",))
    with pytest.raises(ValueError, match="cameras"):
        open_dataset(tmp_path, cameras=("roof",))
