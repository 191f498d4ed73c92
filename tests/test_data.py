"""The vvloc dataset format, triplet sampling, evaluation splits and perturbations (no EGL)."""

from __future__ import annotations

import json
import os
import re
import warnings

import numpy as np
import pytest

import vvloc.data.vvloc_format as fmt
from vvloc._io import FLOAT_TEXT
from vvloc.data import (
    DatasetFormatError,
    DatasetWriter,
    TripletSampler,
    evaluation_split,
    open_dataset,
    perturb,
)
from vvloc.data.sampling import rendered_world
from vvloc.sim.rig import make_rig
from vvloc.sim.sequences import Drive, drive_keyframes, sample_loop
from vvloc.sim.world import parking_world

W, H = 16, 12


def _write(root, sessions: dict[str, tuple[np.ndarray, np.ndarray]], cameras=None, seed=0):
    """Write sessions {name: (poses (N, 3), floors (N,))} with random pixels."""
    cams = cameras or make_rig(4, W, H)
    rng = np.random.default_rng(seed)
    with DatasetWriter(root, cams) as w:
        for name, (poses, floors) in sessions.items():
            s = w.add_session(name, meta={"note": name})
            for k, (p, f) in enumerate(zip(poses, floors, strict=True)):
                imgs = rng.integers(0, 256, size=(len(cams), 3, H, W), dtype=np.uint8)
                s.add(1000 + 100_000 * k, p, imgs, z=-3.2 * f, floor=int(f))
    return cams


def _line(n, y=0.0, floor=0):
    poses = np.column_stack([np.arange(n) * 2.0, np.full(n, y), np.zeros(n)])
    return poses, np.full(n, floor)


def test_a_session_of_images_of_another_size_is_named_when_the_dataset_opens(tmp_path):
    # rig.json said one size, every PNG had another: open_dataset passed, and training failed
    # in a DataLoader worker at its first frame
    from PIL import Image

    cams = _write(tmp_path / "ds", {"s0": _line(3), "s1": _line(3)})
    front = sorted((tmp_path / "ds" / "sessions" / "s1" / cams[0].name).glob("*.png"))
    small = np.zeros((H // 2, W // 2, 3), np.uint8)
    Image.fromarray(small).save(front[1])  # a later frame: said when it is read, as before
    ds = open_dataset(tmp_path / "ds")
    with pytest.raises(DatasetFormatError, match=rf"image is {W // 2}x{H // 2}, rig.json says"):
        ds.session("s1")[1]
    Image.fromarray(small).save(front[0])  # the first frame: said on opening
    want = rf"{front[0]}: image is {W // 2}x{H // 2}, rig.json says {W}x{H} \(the session's first"
    with pytest.raises(DatasetFormatError, match=want):
        open_dataset(tmp_path / "ds")
    front[0].write_bytes(b"not a png")  # no PNG: named by the decoder when read, as before
    open_dataset(tmp_path / "ds")


def test_a_frames_time_in_seconds_prints_its_microseconds(tmp_path):
    # t was timestamps × 1e-6: a unit in the last place off for about a third of the
    # microseconds, which the trajectories and keyframes.csv then printed (…0.1234589)
    cams = make_rig(4, W, H)
    us = [1_700_000_000_123_459, 1_700_000_000_123_464, 1_700_000_000_999_999]
    with DatasetWriter(tmp_path / "ds", cams) as w:
        s = w.add_session("s0")
        for k, t in enumerate(us):
            s.add(t, (2.0 * k, 0.0, 0.0), np.full((4, 3, H, W), 100 + k, np.uint8))
    session = open_dataset(tmp_path / "ds").session("s0")
    assert [repr(f.t) for f in session] == [
        "1700000000.123459",
        "1700000000.123464",
        "1700000000.999999",
    ]


def test_writer_and_reader_round_trip_lazily(tmp_path, monkeypatch):
    root = tmp_path / "ds"
    cams = _write(root, {"s0": _line(5), "s1": _line(4, y=1.0, floor=1)})
    calls = []
    real = fmt.load_rgb
    monkeypatch.setattr(fmt, "load_rgb", lambda p: calls.append(p) or real(p))
    ds = open_dataset(root)
    assert calls == []  # opening reads no image
    assert ds.sessions == ["s0", "s1"] and [c.name for c in ds.cameras] == [c.name for c in cams]
    s1 = ds.session("s1")
    assert len(s1) == 4 and s1.poses.shape == (4, 3) and list(s1.floors) == [1] * 4
    f = s1[2]
    assert len(calls) == 4  # one image per camera of that frame
    assert f.images.shape == (4, 3, H, W) and f.images.dtype == np.uint8
    assert np.allclose(f.K, np.stack([c.K for c in cams]))
    assert np.allclose(f.cam_to_ego, np.stack([c.cam_to_ego for c in cams]))
    assert np.allclose(f.pose, [4.0, 1.0, 0.0]) and f.floor == 1 and f.z == pytest.approx(-3.2)
    assert f.t == pytest.approx((1000 + 200_000) * 1e-6) and (f.session, f.index) == ("s1", 2)
    assert s1[-1].index == 3 and len(s1[1:3]) == 2
    with pytest.raises(IndexError):
        s1[4]
    with pytest.raises(KeyError, match="s9"):
        ds.session("s9")
    # the written pixels come back exactly (PNG is lossless)
    first = np.random.default_rng(0).integers(0, 256, size=(4, 3, H, W), dtype=np.uint8)
    assert np.array_equal(ds.session("s0")[0].images, first)


def test_malformed_row_names_file_and_line(tmp_path):
    root = tmp_path / "ds"
    _write(root, {"s0": _line(3)})
    p = root / "sessions" / "s0" / "poses.csv"
    lines = p.read_text().splitlines()
    lines[2] = lines[2].replace(",0.0,", ",abc,", 1)
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetFormatError, match=r"poses\.csv, line 3: malformed"):
        open_dataset(root)
    lines[2] = "1,2,3"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetFormatError, match=r"poses\.csv, line 3: expected 6 fields"):
        open_dataset(root)


def test_files_that_are_not_utf8_text_are_named(tmp_path):
    # a binary file in place of poses.csv or rig.json said "'utf-8' codec can't decode" alone
    root = tmp_path / "ds"
    _write(root, {"s0": _line(3)})
    p = root / "sessions" / "s0" / "poses.csv"
    good = p.read_bytes()
    p.write_bytes(good + b"\x89PNG\r\n")
    with pytest.raises(DatasetFormatError, match=r"poses\.csv: not UTF-8 text \(.* in position"):
        open_dataset(root)
    p.write_bytes(good)
    (root / "rig.json").write_bytes(b"\x89PNG\r\n\x1a\n")
    with pytest.raises(DatasetFormatError, match=r"rig\.json: cannot read rig: 'utf-8' codec"):
        open_dataset(root)


def _with_x(row: str, x: str) -> str:
    """A poses.csv row with its x field replaced by ``x``."""
    fields = row.split(",")
    return ",".join([fields[0], x, *fields[2:]])


def test_csv_errors_and_a_rig_that_is_no_file_are_named(tmp_path):
    import csv as csv_module

    root = tmp_path / "ds"
    _write(root, {"s0": _line(3)})
    p = root / "sessions" / "s0" / "poses.csv"
    good = p.read_text()
    lines = good.splitlines()
    # a field beyond the csv module's limit raised _csv.Error, naming neither file nor line
    big = "0." + "0" * (csv_module.field_size_limit() + 10)
    p.write_text("\n".join([*lines[:2], _with_x(lines[2], big), *lines[3:]]) + "\n")
    with pytest.raises(DatasetFormatError, match=r"poses\.csv, line 3: field larger than"):
        open_dataset(root)
    p.write_text(good)
    if hasattr(os, "mkfifo"):  # a named pipe as rig.json blocked format="vvloc" for good
        (root / "rig.json").unlink()
        os.mkfifo(root / "rig.json")
        with pytest.raises(DatasetFormatError, match=r"rig\.json: not a regular file"):
            open_dataset(root, format="vvloc")
        assert rendered_world(root) is None


def test_a_long_number_field_is_refused_at_once_and_quoted_short(tmp_path):
    # FLOAT_TEXT split a run of digits between two parts in every way: a 40 000-digit field
    # that failed to match took 23 s, one of 10^6 digits hours; the message quoted it whole
    root = tmp_path / "ds"
    _write(root, {"s0": _line(3)})
    p = root / "sessions" / "s0" / "poses.csv"
    lines = p.read_text().splitlines()
    field = "1" * 100_000 + "x"
    p.write_text("\n".join([*lines[:2], _with_x(lines[2], field), *lines[3:]]) + "\n")
    with pytest.raises(DatasetFormatError, match=r"expected a number, got '1{50,}") as e:
        open_dataset(root)
    assert len(str(e.value)) < 1000
    assert FLOAT_TEXT.fullmatch("1" * 100_000) and FLOAT_TEXT.fullmatch("-12.5e-3")
    assert not FLOAT_TEXT.fullmatch("1" * 100_000 + "x")


def test_a_missing_dataset_and_a_file_are_told_apart(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such dataset folder"):
        open_dataset(tmp_path / "nothing")
    (tmp_path / "map.h5").write_bytes(b"not a folder")
    with pytest.raises(NotADirectoryError, match=r"map\.h5: is a file, not a dataset folder"):
        open_dataset(tmp_path / "map.h5")


def test_missing_image_and_unknown_camera_are_named(tmp_path):
    root = tmp_path / "ds"
    _write(root, {"s0": _line(3)})
    img = root / "sessions" / "s0" / "left" / "201000.png"
    img.unlink()
    with pytest.raises(DatasetFormatError, match=r"left/201000\.png: image missing.*line 4"):
        open_dataset(root)
    root2 = tmp_path / "ds2"
    _write(root2, {"s0": _line(2)})
    (root2 / "sessions" / "s0" / "roof").mkdir()
    with pytest.raises(DatasetFormatError, match=r"camera 'roof' is not in rig\.json"):
        open_dataset(root2)
    with pytest.raises(FileNotFoundError):
        open_dataset(tmp_path / "nope")


def _edit_rig(root, edit):
    """Apply ``edit(doc)`` to ``root``'s rig.json."""
    doc = json.loads((root / "rig.json").read_text())
    edit(doc)
    (root / "rig.json").write_text(json.dumps(doc))


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda c: c["K"][0].__setitem__(0, -40.0), r"focal lengths fx, fy > 0"),
        (lambda c: c["K"][1].__setitem__(1, 0.0), r"focal lengths fx, fy > 0"),
        (lambda c: c["K"].__setitem__(2, [0.0, 0.1, 1.0]), r"pinhole matrix"),
        (lambda c: c.__setitem__("name", ".."), r"camera name: expected a non-empty plain"),
        (lambda c: c.__setitem__("name", "poses.csv"), r"camera name: expected a non-empty"),
        (  # the rotation scaled by 1.5
            lambda c: c.__setitem__(
                "cam_to_ego", (np.array(c["cam_to_ego"]) @ np.diag([1.5, 1.5, 1.5, 1.0])).tolist()
            ),
            "rigid",
        ),
        (  # a reflection: orthonormal, determinant -1
            lambda c: c.__setitem__("cam_to_ego", np.diag([1.0, 1.0, -1.0, 1.0]).tolist()),
            "determinant",
        ),
        (lambda c: c.__setitem__("width", W + 8), r"share one image size.*'front' 24x12"),
    ],
)
def test_a_rig_of_ones_own_is_checked_camera_by_camera(tmp_path, edit, match):
    # a user's own rig.json: a camera that is no pinhole, extrinsics that are no rigid motion
    # and a camera of another size are refused by name, before any image is read
    root = tmp_path / "ds"
    _write(root, {"s0": _line(2)})
    _edit_rig(root, lambda doc: edit(doc["cameras"][0]))
    with pytest.raises(DatasetFormatError, match=r"rig\.json: .*" + match):
        open_dataset(root)


def test_a_rig_of_cameras_of_different_sizes_is_read_at_one_size_when_asked(tmp_path):
    # a front camera at twice the others' resolution: refused as such (a Frame stacks the
    # cameras), read with image_size, and converted to a dataset of one size
    from PIL import Image

    from vvloc.data import convert_dataset
    from vvloc.data._remap import resize_rgb

    root = tmp_path / "ds"
    cams = _write(root, {"s0": _line(2)})
    ds = open_dataset(root)
    want = [ds.session("s0")[k].images for k in range(2)]
    front = cams[0]
    bigs = []
    for png in sorted((root / "sessions" / "s0" / front.name).glob("*.png")):
        with Image.open(png) as im:  # the same picture at 2x
            bigs.append(np.asarray(im.convert("RGB")).repeat(2, axis=0).repeat(2, axis=1))
        Image.fromarray(bigs[-1]).save(png)

    def twice(doc):
        cam = doc["cameras"][0]
        cam["width"], cam["height"] = 2 * W, 2 * H
        cam["K"] = front.resized(2 * W, 2 * H).K.tolist()

    _edit_rig(root, twice)
    with pytest.raises(DatasetFormatError, match=r"share one image size.* image_size=\(W, H\)"):
        open_dataset(root)
    one = open_dataset(root, image_size=(W, H))
    assert [(c.width, c.height) for c in one.cameras] == [(W, H)] * len(cams)
    np.testing.assert_allclose(one.cameras[0].K, front.K, atol=1e-12)
    for k in range(2):
        got = one.session("s0")[k].images
        assert got.shape == want[k].shape
        np.testing.assert_array_equal(got[1:], want[k][1:])  # the others as they were
        # the front camera resized down from its 2x copy, as the raw readers resize
        np.testing.assert_array_equal(got[0], resize_rgb(bigs[k], W, H).transpose(2, 0, 1))
    out = convert_dataset(root, tmp_path / "one", image_size=(W, H))
    np.testing.assert_array_equal(open_dataset(out).session("s0")[1].images, got)
    with pytest.raises(TypeError, match=r"the vvloc format takes one option, image_size"):
        open_dataset(root, ego_height=1.0)


def test_rig_entries_and_versions_other_than_the_formats_are_refused(tmp_path):
    root = tmp_path / "ds"
    _write(root, {"s0": _line(2)})
    good = json.loads((root / "rig.json").read_text())
    _edit_rig(root, lambda doc: doc["cameras"].__setitem__(0, "front"))
    with pytest.raises(DatasetFormatError, match=r"camera 0: camera entry: expected an object"):
        open_dataset(root)
    for version in (2, "banana", True, 1.0):
        (root / "rig.json").write_text(json.dumps({**good, "version": version}))
        with pytest.raises(DatasetFormatError, match=f"version {version!r} is not supported"):
            open_dataset(root)
    (root / "rig.json").write_text(json.dumps({k: v for k, v in good.items() if k != "version"}))
    assert len(open_dataset(root).session("s0")) == 2  # a hand-written rig.json may omit it


def test_timestamps_and_floors_beyond_int64_are_named_by_line(tmp_path):
    root = tmp_path / "ds"
    _write(root, {"s0": _line(2)})
    p = root / "sessions" / "s0" / "poses.csv"
    lines = p.read_text().splitlines()
    big = "9" * 20
    for row, name in ((f"{big},0,0,0,0,0", "timestamp"), (f"{10**15},0,0,0,0,{big}", "floor")):
        p.write_text("\n".join([lines[0], row]) + "\n")
        with pytest.raises(DatasetFormatError, match=rf"poses\.csv, line 2: {name} 9+ is outside"):
            open_dataset(root)


def test_a_huge_but_finite_path_does_not_hang_the_heading_check():
    from vvloc.data.heading import heading_offset

    # past ~1e16 m adding the 2 m stretch no longer changes the path length: the loop stood
    offset, count = heading_offset(np.array([[0, 0, 0], [1e20, 0, 0], [1e20, 0, 0.0]]))
    assert count <= 1 and (count == 0 or np.isfinite(offset))


def test_rows_out_of_time_order_are_refused_by_line(tmp_path):
    root = tmp_path / "ds"
    _write(root, {"s0": _line(3)})
    p = root / "sessions" / "s0" / "poses.csv"
    lines = p.read_text().splitlines()
    for rows, line in (
        ([lines[0], lines[1], lines[3], lines[2]], 4),
        ([lines[0], lines[1], lines[1]], 3),
    ):
        p.write_text("\n".join(rows) + "\n")
        with pytest.raises(DatasetFormatError, match=rf"poses\.csv, line {line}: timestamp"):
            open_dataset(root)


def _png16(rgb: np.ndarray, size: tuple[int, int] | None = None, bits: int = 16) -> bytes:
    """A PNG of ``rgb`` (H, W, 3) with ``bits`` per sample, written by hand (``size``: the
    header's width and height, the pixel data left as it is)."""
    import struct
    import zlib

    h, w = rgb.shape[:2]
    width, height = size or (w, h)
    dtype = ">u2" if bits == 16 else "u1"
    raw = b"".join(b"\x00" + rgb[y].astype(dtype).tobytes() for y in range(h))

    def chunk(tag: bytes, data: bytes) -> bytes:
        body = tag + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    head = struct.pack(">IIBBBBB", width, height, bits, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", head)
        + chunk(b"IDAT", zlib.compress(raw))
        + chunk(b"IEND", b"")
    )


def test_images_other_than_8_bit_are_refused_and_grey_or_alpha_converted(tmp_path):
    from PIL import Image

    root = tmp_path / "ds"
    _write(root, {"s0": _line(1)})
    png = root / "sessions" / "s0" / "front" / "1000.png"
    with Image.open(png) as im:
        rgb = np.asarray(im.convert("RGB"))
    Image.fromarray(rgb[..., 1]).save(png)  # grey: replicated
    assert np.array_equal(
        open_dataset(root).session("s0")[0].images[0], np.stack([rgb[..., 1]] * 3)
    )
    Image.fromarray(np.dstack([rgb, np.full((H, W), 7, np.uint8)])).save(png)  # RGBA: alpha dropped
    assert np.array_equal(open_dataset(root).session("s0")[0].images[0], rgb.transpose(2, 0, 1))
    Image.fromarray(rgb[..., 0].astype(np.uint16) * 257).save(png)  # 16-bit grey: not clipped white
    with Image.open(png) as im:
        assert im.mode.startswith("I")
    with pytest.raises(DatasetFormatError, match=r"front/1000\.png: image mode .* not 8 bits"):
        open_dataset(root).session("s0")[0]
    # 16-bit RGB: Pillow opens it as mode RGB and keeps the high bytes (12-bit data: black)
    png.write_bytes(_png16(rgb.astype(np.uint16) * 16))
    with Image.open(png) as im:
        assert im.mode == "RGB"
    with pytest.raises(DatasetFormatError, match=r"front/1000\.png: RGB image of 16 bits"):
        open_dataset(root).session("s0")[0]
    # a header claiming a decompression bomb: named, not PIL's DecompressionBombError (when
    # the frame is read, for a dataset opened before; opening it names the header's size)
    opened = open_dataset(root)
    png.write_bytes(_png16(np.zeros((1, 1, 3), np.uint16), size=(40_000, 40_000), bits=8))
    with pytest.raises(DatasetFormatError, match=r"front/1000\.png: not a readable image"):
        opened.session("s0")[0]
    with pytest.raises(DatasetFormatError, match=r"1000\.png: image is 40000x40000, rig.json"):
        open_dataset(root)
    # a copy cut short: PIL reads the header and fails only when decoding, naming no file
    Image.fromarray(rgb).save(png)
    png.write_bytes(png.read_bytes()[: png.stat().st_size // 2])
    with pytest.raises(
        DatasetFormatError, match=r"front/1000\.png: not a readable image \(.*trunc"
    ):
        open_dataset(root).session("s0")[0]
    png.write_text("not an image")
    with pytest.raises(DatasetFormatError, match=r"front/1000\.png: not a readable image"):
        open_dataset(root).session("s0")[0]


def test_a_yaw_in_degrees_or_as_a_compass_heading_is_warned_about(tmp_path):
    # a drive along three straight roads, heading along each (yaw CCW from x, radians); not
    # along the axes, where a compass heading would look like driving backwards
    side = np.arange(0.0, 60.0, 1.0)
    yaw = np.repeat(np.radians([30.0, 120.0, 210.0]), len(side))
    steps = np.column_stack([np.cos(yaw), np.sin(yaw)])
    xy = np.cumsum(steps, axis=0)
    floors = np.zeros(len(yaw), int)
    root = tmp_path / "ds"
    _write(root, {"good": (np.column_stack([xy, yaw]), floors)})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        open_dataset(root)  # the right convention: no warning
    p = root / "sessions" / "good" / "poses.csv"
    rows = [line.split(",") for line in p.read_text().splitlines()]
    for row, v in zip(rows[1:], yaw + np.radians(1.4), strict=True):
        row[4] = repr(float(v))
    p.write_text("\n".join(",".join(r) for r in rows) + "\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        open_dataset(root)  # a grid convergence's 1.4°: the converters warned, not every open
    for values, match in (
        (np.degrees(yaw), r"yaw reaches 210\.0 .*degrees\?"),
        (np.pi / 2 - yaw, r"the yaw reads as a compass heading .* 0\.0° from 90° minus .* 30\.0°"),
        (yaw + np.radians(12.0), r"the yaw differs from the direction of travel by .*\+12\.00°"),
    ):
        for row, v in zip(rows[1:], values, strict=True):
            row[4] = repr(float(v))
        p.write_text("\n".join(",".join(r) for r in rows) + "\n")
        with pytest.warns(UserWarning) as caught:
            open_dataset(root)
        texts = [str(w.message) for w in caught]
        assert any(re.search(r"^session good: " + match, t) for t in texts), texts
    # ... and along the axes, where a compass heading is 90° off the direction of travel (it
    # went unwarned: heading_offset leaves offsets of 90° out as driving backwards), driven
    # forwards and backwards, and with the yaw a little noisy
    axis = np.repeat(np.radians([0.0, 90.0, 180.0, 270.0]), len(side))
    xy = np.cumsum(np.column_stack([np.cos(axis), np.sin(axis)]), axis=0)
    noise = np.random.default_rng(0).normal(0.0, np.radians(0.3), len(axis))
    level = np.zeros(len(axis), int)
    # (a whole session facing backwards reads as a car driving forwards, its yaw clockwise
    # from -90°: 90° minus the reversed yaw)
    for name, travel, said in (
        ("fwd", axis, "a compass heading"),
        ("back", axis + np.pi, "clockwise: -90.0° minus the direction of travel"),
    ):
        compass = np.pi / 2 - travel + noise
        compass = np.arctan2(np.sin(compass), np.cos(compass))  # within ±π, as a compass logs
        _write(tmp_path / name, {name: (np.column_stack([xy, compass]), level)})
        with pytest.warns(UserWarning, match=rf"^session {name}: the yaw reads as {said}"):
            open_dataset(tmp_path / name)
    right = tmp_path / "right"  # the same roads in the format's convention: no warning
    _write(right, {"r": (np.column_stack([xy, axis + noise]), level)})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        open_dataset(right)


def test_writer_leaves_nothing_behind_on_error(tmp_path):
    cams = make_rig(4, W, H)
    with pytest.raises(RuntimeError), DatasetWriter(tmp_path / "ds", cams) as w:
        s = w.add_session("s0")
        s.add(1, (0, 0, 0), np.zeros((4, 3, H, W), np.uint8))
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    with DatasetWriter(tmp_path / "ds", cams) as w:
        s = w.add_session("s0")
        with pytest.raises(ValueError, match="images"):
            s.add(1, (0, 0, 0), np.zeros((3, 3, H, W), np.uint8))
        s.add(5, (0, 0, 0), np.zeros((4, 3, H, W), np.uint8))
        with pytest.raises(ValueError, match="timestamp"):
            s.add(5, (0, 0, 0), np.zeros((4, 3, H, W), np.uint8))
    with pytest.raises(FileExistsError):
        DatasetWriter(tmp_path / "ds", cams)


def test_writer_leaves_out_sessions_without_frames_and_says_so(tmp_path):
    # a session without frames was written, and every command that reads one refuses it
    cams = make_rig(4, W, H)
    with pytest.warns(UserWarning, match=r"sessions \['e1', 'e2'\] left out: no frame") as caught:
        with DatasetWriter(tmp_path / "ds", cams) as w:
            w.add_session("e1")
            w.add_session("s0").add(1, (0, 0, 0), np.zeros((4, 3, H, W), np.uint8))
            w.add_session("e2", meta={"note": "nothing"})
    assert caught[0].filename == __file__  # at the with block, not in the writer
    w = DatasetWriter(tmp_path / "ds2", cams)
    w.add_session("s0").add(1, (0, 0, 0), np.zeros((4, 3, H, W), np.uint8))
    w.add_session("e")
    with pytest.warns(UserWarning, match=r"sessions \['e'\] left out") as caught:
        w.close()
    assert caught[0].filename == __file__
    assert open_dataset(tmp_path / "ds").sessions == ["s0"]
    assert sorted(p.name for p in (tmp_path / "ds" / "sessions").iterdir()) == ["s0"]
    # no frame at all: refused, and nothing is left behind, in a with block or not
    for sessions in ([], ["e"]):
        with pytest.raises(ValueError, match=r"no frame was added to any session"):
            with DatasetWriter(tmp_path / "none", cams) as w:
                for name in sessions:
                    w.add_session(name)
        assert not (tmp_path / "none").exists()
        w = DatasetWriter(tmp_path / "none", cams)
        for name in sessions:
            w.add_session(name)
        with pytest.raises(ValueError, match=r"no frame was added to any session"):
            w.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds", "ds2"]


def test_session_names_with_control_characters_are_refused(tmp_path):
    # a line break in a session name split the rows of the CSV files that name sessions
    # (queries.csv, keyframes.csv): refused when writing and when reading a dataset
    cams = make_rig(4, W, H)
    with DatasetWriter(tmp_path / "ds", cams) as w:
        # ... and a space at either end, which the command line's --sessions strips: such a
        # session could be written and read, but never named there
        for bad in ("day\n1", "a\tb", "x\x85", "drive ", " drive", 5):
            with pytest.raises(ValueError, match=r"^name: expected a new plain session name"):
                w.add_session(bad)  # type: ignore[arg-type]
        w.add_session("day 1").add(1, (0, 0, 0), np.zeros((4, 3, H, W), np.uint8))  # inner: fine
        w.add_session("s0").add(1, (0, 0, 0), np.zeros((4, 3, H, W), np.uint8))
    open_dataset(tmp_path / "ds")
    os.rename(tmp_path / "ds" / "sessions" / "s0", tmp_path / "ds" / "sessions" / "s\n0")
    with pytest.raises(DatasetFormatError, match="a session folder name with a control character"):
        open_dataset(tmp_path / "ds")


def _dead_pid() -> int:
    """The process id of a process that has ended (reused by another only after wrapping)."""
    import subprocess
    import sys

    child = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                           capture_output=True, text=True, check=True)  # fmt: skip
    return int(child.stdout)


def test_what_a_writer_killed_outright_left_is_cleaned_up_by_the_next(tmp_path, caplog):
    import os
    import signal
    import subprocess
    import sys

    from vvloc._io import temp_tag

    root = tmp_path / "ds"
    # a writer killed outright (no handler runs) leaves its hidden partial folder behind
    script = (
        "import os, signal, sys, numpy as np\n"
        "from vvloc.data import DatasetWriter\n"
        "from vvloc.sim.rig import make_rig\n"
        f"w = DatasetWriter(sys.argv[1], make_rig(2, {W}, {H}))\n"
        f"w.add_session('s0').add(1, (0, 0, 0), np.zeros((2, 3, {H}, {W}), np.uint8))\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    r = subprocess.run([sys.executable, "-c", script, str(root)], capture_output=True)
    assert r.returncode == -signal.SIGKILL, r.stderr
    (left,) = tmp_path.iterdir()
    assert left.name.startswith(".ds.partial-")
    # ... beside one a running writer is writing (this process), another machine's, and a
    # name of another form: only the dead process's goes
    mine = tmp_path / f".ds.partial-{temp_tag()}"
    other_host = tmp_path / f".ds.partial-00000000-{_dead_pid()}-{'a' * 12}"
    other_form = tmp_path / ".ds.partial-0123456789ab"
    for d in (mine, other_host, other_form):
        d.mkdir()
    with caplog.at_level("WARNING"):
        _write(root, {"s0": _line(3)})
    assert "which a stopped vvloc process left" in caplog.text
    assert not left.exists() and mine.is_dir() and other_host.is_dir() and other_form.is_dir()
    assert len(open_dataset(root).session("s0")) == 3
    # killed between its two renames: the dataset it had moved aside goes back, whole
    dead = _dead_pid()
    aside = tmp_path / f".ds.replaced-{temp_tag().replace(f'-{os.getpid()}-', f'-{dead}-')}"
    os.replace(root, aside)
    with pytest.raises(FileExistsError, match="exists and is not empty"):
        DatasetWriter(root, make_rig(4, W, H))
    assert not aside.exists() and len(open_dataset(root).session("s0")) == 3
    # ... and is removed when the new one took its place
    aside.mkdir()
    DatasetWriter(root, make_rig(4, W, H), overwrite=True).abort()
    assert not aside.exists() and len(open_dataset(root).session("s0")) == 3


def test_the_writer_refuses_what_the_reader_would_refuse_naming_the_argument(tmp_path):
    cams = make_rig(2, W, H)
    img = np.zeros((2, 3, H, W), np.uint8)
    with DatasetWriter(tmp_path / "ds", cams) as w:
        s = w.add_session("s0")
        bad = [
            (dict(pose=(np.nan, 0.0, 0.0)), ValueError, "pose: expected 3 finite numbers"),
            (dict(pose=(0.0, 0.0, np.inf)), ValueError, "pose"),
            (dict(pose=(0.0, 0.0)), ValueError, "pose"),
            (dict(pose="0 0 0"), ValueError, "pose"),
            (dict(timestamp=3000.7), ValueError, "timestamp: expected a whole number"),
            (dict(timestamp="3000"), TypeError, "timestamp: expected an int"),
            (dict(floor=1.9), ValueError, "floor: expected a whole number"),
            (dict(floor=True), TypeError, "floor"),
            (dict(z=np.nan), ValueError, "z: expected a finite value"),
            (dict(z=10**400), ValueError, "z: expected a finite value"),
            (dict(z="0"), TypeError, "z: expected a float"),
            (dict(timestamp=2**70), ValueError, "timestamp: expected a whole number within int64"),
            (dict(timestamp=np.inf), ValueError, "timestamp: expected a whole number"),
        ]
        for change, error, match in bad:
            args = {"timestamp": 1000, "pose": (0.0, 0.0, 0.0), **change}
            kw = {k: change[k] for k in ("floor", "z") if k in change}
            with pytest.raises(error, match=match):
                s.add(args["timestamp"], args["pose"], img, **kw)
        with pytest.raises(TypeError, match=r"images: expected a uint8 numpy array"):
            s.add(1000, (0.0, 0.0, 0.0), img.tolist())
        s.add(2000.0, np.array([1.0, 2.0, 0.5]), img, floor=np.int64(1), z=np.float32(-3.0))
    (frame,) = open_dataset(tmp_path / "ds").session("s0")
    assert (frame.t, frame.floor) == (0.002, 1)  # seconds
    np.testing.assert_array_equal(frame.pose, [1.0, 2.0, 0.5])


def test_a_session_meta_json_cannot_hold_leaves_no_half_made_session(tmp_path):
    # a numpy int in meta: a bare TypeError once left the session's folders in the output,
    # unregistered, so that the same name could not be added again and the closed dataset
    # failed to open ("poses file missing")
    cams = make_rig(2, W, H)
    img = np.zeros((2, 3, H, W), np.uint8)
    with DatasetWriter(tmp_path / "ds", cams) as w:
        with pytest.raises(TypeError, match=r"meta: expected plain JSON values"):
            w.add_session("s0", meta={"seed": np.int64(3)})
        w.add_session("s0", meta={"seed": 3}).add(1000, (0.0, 0.0, 0.0), img)
        w.add_session("s1").add(1000, (0.0, 0.0, 0.0), img)
    ds = open_dataset(tmp_path / "ds")
    assert ds.sessions == ["s0", "s1"]


def test_timestamps_beyond_2_32_seconds_are_refused_as_likely_nanoseconds(tmp_path):
    # nanoseconds since 1970 (1.7e18) opened silently: Frame.t = 1.7e12 s, and round(t·1e6),
    # which the exports name frames by, no longer gave the poses.csv timestamp back (from
    # 2^32 s on, e.g. 4294967296000507 came back as ...508)
    top = fmt.MAX_TIMESTAMP_US
    assert top == 2**32 * 10**6
    rng = np.random.default_rng(0)  # below it every timestamp comes back
    below = np.concatenate([rng.integers(top - 10**12, top, 100_000), [top, top - 1]])
    assert all(round((int(ts) / 1e6) * 1e6) == ts for ts in below)
    cams = make_rig(2, W, H)
    img = np.zeros((2, 3, H, W), np.uint8)
    with DatasetWriter(tmp_path / "ds", cams) as w:
        s = w.add_session("s0")
        for beyond in (1_700_000_000_100_000_123, 4_294_967_296_000_507):
            with pytest.raises(ValueError, match=rf"^timestamp: {beyond} µs lies beyond ±2\^32 s"):
                s.add(beyond, (0.0, 0.0, 0.0), img)
        s.add(top - 1, (0.0, 0.0, 0.0), img)
        s.add(top, (0.0, 0.0, 0.0), img)  # the largest taken
    frames = list(open_dataset(tmp_path / "ds").session("s0"))
    assert [round(f.t * 1e6) for f in frames] == [top - 1, top]
    poses = tmp_path / "ds" / "sessions" / "s0" / "poses.csv"
    poses.write_text(poses.read_text().replace(str(top - 1), "1700000000100000123"))
    with pytest.raises(
        DatasetFormatError,
        match=r"poses.csv, line 2: timestamp: 1700000000100000123 µs lies beyond .*\(nanosec",
    ):
        open_dataset(tmp_path / "ds")


def test_the_writer_names_cameras_that_are_no_cameras(tmp_path):
    cams = make_rig(2, W, H)
    with pytest.raises(TypeError, match=r"cameras\[0\]: expected a vvloc.data.Camera .* got dict"):
        DatasetWriter(tmp_path / "ds", [c.to_json() for c in cams])
    assert not list(tmp_path.iterdir())  # refused before any folder was made
    # a generator is taken whole (it was used up by the checks, leaving no camera)
    with DatasetWriter(tmp_path / "ds", (c for c in cams)) as w:
        assert w.cameras == tuple(cams)
        w.add_session("s0").add(1000, (0.0, 0.0, 0.0), np.zeros((2, 3, H, W), np.uint8))
    assert len(open_dataset(tmp_path / "ds").cameras) == 2


def test_a_byte_order_mark_and_hidden_folders_are_read_as_nothing(tmp_path):
    cams = _write(tmp_path / "ds", {"s0": _line(3)})
    root = tmp_path / "ds"
    for f in (root / "rig.json", root / "sessions" / "s0" / "poses.csv"):
        f.write_bytes(b"\xef\xbb\xbf" + f.read_bytes())  # Excel's "CSV UTF-8"
    (root / "sessions" / ".ipynb_checkpoints").mkdir()
    (root / "sessions" / "s0" / ".ipynb_checkpoints").mkdir()
    ds = open_dataset(root)
    assert ds.sessions == ["s0"] and len(ds.session("s0")) == 3
    assert [c.name for c in ds.cameras] == [c.name for c in cams]
    doc = json.loads((root / "rig.json").read_text(encoding="utf-8-sig"))
    doc["meta"] = {"scene": "mine"}
    (root / "rig.json").write_text("\ufeff" + json.dumps(doc), encoding="utf-8")
    assert fmt.rig_meta(root) == {"scene": "mine"} == open_dataset(root).meta
    with DatasetWriter(root, cams, overwrite=True) as w:  # still a vvloc dataset to replace
        w.add_session("s1").add(1000, (0.0, 0.0, 0.0), np.zeros((4, 3, H, W), np.uint8))
    assert open_dataset(root).sessions == ["s1"]


def test_a_rotation_typed_with_few_decimals_is_refused_with_how_far_it_is_off(tmp_path):
    _write(tmp_path / "ds", {"s0": _line(2)})
    root = tmp_path / "ds"
    # forward-looking, pitched down 10°, the cosine and sine typed as 0.9848 and 0.1736
    c, n = 0.9848, 0.1736
    typed = [[0, -n, c, 0], [-1, 0, 0, 0], [0, -c, -n, 1.5], [0, 0, 0, 1]]
    _edit_rig(root, lambda doc: doc["cameras"][1].__setitem__("cam_to_ego", typed))
    with pytest.raises(DatasetFormatError, match=r"is 3.2e-05 from orthonormal .*Re-orthonorm"):
        open_dataset(root)
    far = np.eye(4)
    far[0, 3] = np.inf  # FLOAT_TEXT takes 1e999
    assert fmt.rigid_fault(far) == "a value is not finite (inf or nan)"


def test_an_interrupted_overwrite_keeps_the_old_dataset_whole(tmp_path, monkeypatch):
    """The old dataset is renamed aside, not deleted, until the new one is in place: an
    interrupt between the two renames puts it back (it was left half deleted before)."""
    import os

    import vvloc.data.vvloc_format as vf

    cams = make_rig(1, W, H)
    root = tmp_path / "ds"
    _write(root, {"s0": _line(2), "s1": _line(2)}, cameras=cams)
    real_replace, calls = os.replace, []

    def interrupted(src, dst):
        calls.append((src, dst))
        if len(calls) == 2:  # the new dataset moving in
            raise KeyboardInterrupt
        return real_replace(src, dst)

    monkeypatch.setattr(vf.os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt), DatasetWriter(root, cams, overwrite=True) as w:
        w.add_session("s9").add(1, (0, 0, 0), np.zeros((1, 3, H, W), np.uint8))
    monkeypatch.setattr(vf.os, "replace", real_replace)
    assert open_dataset(root).sessions == ["s0", "s1"]  # whole, as before
    assert [len(open_dataset(root).session(s)) for s in ("s0", "s1")] == [2, 2]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]  # and nothing hidden beside it
    with DatasetWriter(root, cams, overwrite=True) as w:  # uninterrupted: replaced, no leftover
        w.add_session("s9").add(1, (0, 0, 0), np.zeros((1, 3, H, W), np.uint8))
    assert open_dataset(root).sessions == ["s9"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]


def test_overwrite_replaces_a_dataset_and_nothing_else(tmp_path):
    cams = make_rig(1, W, H)
    frame = np.zeros((1, 3, H, W), np.uint8)
    # a folder with a rig.json of another tool: not a dataset, kept whole
    other = tmp_path / "proj"
    (other / "src").mkdir(parents=True)
    (other / "rig.json").write_text("{}")
    (other / "src" / "main.py").write_text("code")
    with pytest.raises(FileExistsError, match=r"its rig\.json is not a vvloc rig"):
        DatasetWriter(other, cams, overwrite=True)
    # a dataset holding a user's files besides rig.json and sessions/: they are named, kept
    root = tmp_path / "ds"
    _write(root, {"s0": _line(2)}, cameras=cams)
    (root / "notes.txt").write_text("mine")
    (root / "runs" / "important").mkdir(parents=True)
    with pytest.raises(
        FileExistsError, match=r"holds more than a vvloc dataset \(notes.txt, runs\)"
    ):
        DatasetWriter(root, cams, overwrite=True)
    assert (other / "src" / "main.py").read_text() == "code"
    assert (root / "notes.txt").read_text() == "mine" and (root / "runs" / "important").is_dir()
    assert open_dataset(root).sessions == ["s0"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds", "proj"]  # nothing hidden left
    (root / "notes.txt").unlink()
    (root / "runs" / "important").rmdir()
    (root / "runs").rmdir()
    with DatasetWriter(root, cams, overwrite=True) as w:  # a dataset alone is replaced
        w.add_session("s9").add(1, (0, 0, 0), frame)
    assert open_dataset(root).sessions == ["s9"]


def test_writer_refuses_the_working_folder_and_replaces_symlink_targets(tmp_path, monkeypatch):
    import os
    import stat

    cams = make_rig(1, W, H)
    poses, floors = _line(2)
    monkeypatch.chdir(tmp_path)
    for root in (".", tmp_path, tmp_path.parent):
        with pytest.raises(ValueError, match="working directory"):
            DatasetWriter(root, cams, overwrite=True)
    # a new dataset gets a plain mkdir's mode, a replaced one keeps its own
    old = os.umask(0o022)
    try:
        _write(tmp_path / "ds", {"s0": (poses, floors)}, cameras=cams)
        assert stat.S_IMODE((tmp_path / "ds").stat().st_mode) == 0o755
        (tmp_path / "ds").chmod(0o750)
        (tmp_path / "link").symlink_to(tmp_path / "ds")
        with DatasetWriter(tmp_path / "link", cams, overwrite=True) as w:
            w.add_session("s9").add(1, (0, 0, 0), np.zeros((1, 3, H, W), np.uint8))
    finally:
        os.umask(old)
    assert (tmp_path / "link").is_symlink()  # the link stays, its target is the new dataset
    assert stat.S_IMODE((tmp_path / "ds").stat().st_mode) == 0o750
    assert open_dataset(tmp_path / "link").sessions == ["s9"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds", "link"]


def _drive_dataset(root):
    loop = sample_loop(parking_world(0).routes[0])
    sessions = {}
    for name, drive in (
        ("s0", Drive()),
        ("s1", Drive(1.5, False, seed=1)),
        ("s2", Drive(-1.5, True, seed=2)),
    ):
        poses, _ = drive_keyframes(loop, drive, 200)  # about one lap
        sessions[name] = (poses, np.zeros(len(poses), int))
    _write(root, sessions, cameras=make_rig(1, W, H))
    return open_dataset(root)


def test_revisits_in_other_sessions_are_positives(tmp_path):
    ds = _drive_dataset(tmp_path / "ds")
    sampler = TripletSampler(ds, pos_radius=2.0, neg_radius=3.0, seed=0)
    t = sampler.sample(64)
    assert t.shape == (64, 3)
    d_pos = np.linalg.norm(sampler.positions[t[:, 0]] - sampler.positions[t[:, 1]], axis=1)
    d_neg = np.linalg.norm(sampler.positions[t[:, 0]] - sampler.positions[t[:, 2]], axis=1)
    assert np.all(d_pos <= 2.0) and np.all(d_neg > 3.0)
    assert np.all(sampler.session_of[t[:, 0]] != sampler.session_of[t[:, 1]])
    # the offset (+1.5 m) and the reversed (-1.5 m) drives revisit s0 within the radius
    s0 = ds.session("s0")
    for other in ("s1", "s2"):
        d = np.linalg.norm(ds.session(other).poses[:, None, :2] - s0.poses[None, :, :2], axis=2)
        assert np.median(d.min(axis=1)) < 2.0
    assert np.array_equal(
        TripletSampler(ds, seed=0).sample(16), TripletSampler(ds, seed=0).sample(16)
    )
    name, idx = sampler.locate(int(t[0, 0]))
    assert sampler.frame(int(t[0, 0])).session == name and sampler.frame(int(t[0, 0])).index == idx


def test_hard_triplets_are_redrawn_until_resolved(tmp_path):
    ds = _drive_dataset(tmp_path / "ds")
    sampler = TripletSampler(ds, seed=1, hard_fraction=0.5)
    hard = sampler.sample(4)
    sampler.update(hard, np.array([False, False, True, False]))
    assert len(sampler.hard) == 3
    for _ in range(3):
        drawn = {tuple(r) for r in sampler.sample(8).tolist()}
        assert {tuple(r) for r in sampler.hard.tolist()} <= drawn
    sampler.resolve(sampler.hard)
    assert len(sampler.hard) == 0


def test_triplets_and_frame_ids_of_other_forms_are_refused_not_reshaped(tmp_path):
    ds = _drive_dataset(tmp_path / "ds")
    sampler = TripletSampler(ds, seed=1)
    n = len(sampler)
    with pytest.raises(TypeError, match=r"^triplets: expected an integer array \(T, 3\)"):
        sampler.mark_hard(np.array([[0.5, 6.7, 2.2]]))  # was stored as (0, 6, 2)
    with pytest.raises(ValueError, match=r"^triplets: expected shape \(T, 3\), got \(3, 2\)"):
        sampler.mark_hard(np.array([[1, 2], [3, 4], [5, 6]]))  # was (1, 2, 3), (4, 5, 6)
    with pytest.raises(ValueError, match=r"^triplets: expected shape"):
        sampler.resolve(np.arange(6))
    assert len(sampler.hard) == 0
    with pytest.raises(ValueError, match=r"^gid: expected an int >= 0, got -1"):
        sampler.locate(-1)  # was the last frame
    with pytest.raises(ValueError, match=rf"^gid: expected an int <= {n - 1}, got {n}"):
        sampler.frame(n)
    with pytest.raises(TypeError, match=r"^gid: "):
        sampler.locate(1.0)  # type: ignore[arg-type]
    assert sampler.locate(np.int64(n - 1)) == sampler.locate(n - 1)


def test_a_camera_projects_points_of_shape_n_3_only():
    cam = make_rig(1, W, H)[0]
    pts = np.array([[5.0, 0.0, 0.0], [0.0, 5.0, 1.0]])
    uv, depth = cam.project_ego(pts)
    assert uv.shape == (2, 2) and depth.shape == (2,)
    uv1, depth1 = cam.project_ego(pts[0])  # one point as (3,)
    assert depth1.shape == (1,)
    np.testing.assert_array_equal(uv1, uv[:1])
    # (3, 2) was read as two points of 3 coordinates each, silently
    with pytest.raises(ValueError, match=r"^points: expected shape \(N, 3\), got \(3, 2\)"):
        cam.project_ego(np.array([[5.0, 0], [0, 5], [1, 0]]))
    with pytest.raises(ValueError, match=r"^points: contains non-finite"):
        cam.project_ego([[np.nan, 0, 0]])


def test_image_content_tells_pictures_from_flat_and_noisy_ones(tiny_world):
    from vvloc.data import has_image_content

    ds = open_dataset(tiny_world)
    images = ds.session("s1")[0].images
    assert has_image_content(images)
    assert has_image_content(ds.session("s1")[0])  # a Frame: its images (it read shape ())
    assert has_image_content(images.astype(np.float32) / 255)
    flat = np.zeros_like(images)
    assert not has_image_content(flat)
    assert not has_image_content(np.full_like(images, 255))
    rng = np.random.default_rng(0)
    noisy = np.clip(np.rint(60 + 8 * rng.standard_normal(images.shape)), 0, 255).astype(np.uint8)
    assert not has_image_content(noisy)  # a covered lens with sensor noise
    one = flat.copy()
    one[2] = images[2]  # one camera that sees something is enough
    assert has_image_content(one)
    half = flat.copy()
    half[0, :, :, : images.shape[3] // 2] = 200  # a hard edge in one camera
    assert has_image_content(half)
    shared = 60 + 6 * rng.standard_normal((images.shape[0], 1, *images.shape[2:]))
    shared = np.clip(np.rint(np.broadcast_to(shared, images.shape)), 0, 255).astype(np.uint8)
    assert not has_image_content(shared)  # the same noise in the three channels
    # a side shorter than two blocks is taken pixel by pixel: one 8-pixel block along it hid
    # its variation (12 × 12 images had no content at all)
    for h, w in ((12, 12), (15, 40), (9, 200), (40, 15)):
        small = np.zeros((1, 3, h, w), np.uint8)
        small[0, :, : h // 2] = 255
        assert has_image_content(small), (h, w)
        assert has_image_content(np.ascontiguousarray(np.swapaxes(small, 2, 3))), (h, w)
    for h, w in ((23, 40), (31, 8), (40, 23)):  # variation only beyond the last whole block
        edge = np.zeros((1, 3, h, w), np.uint8)
        edge[0, :, -(h % 8 or 1) :] = 255
        assert has_image_content(edge), (h, w)
        assert has_image_content(np.ascontiguousarray(np.swapaxes(edge, 2, 3))), (h, w)
    tiny = np.zeros((1, 3, 4, 5), np.uint8)  # smaller than a block: pixel by pixel
    assert not has_image_content(tiny)
    tiny[0, :, 0, 0] = 255
    assert has_image_content(tiny)
    with pytest.raises(ValueError, match=r"^images: expected shape \(M, 3, H, W\)"):
        has_image_content(images[0])
    with pytest.raises(TypeError, match=r"^images: expected uint8 or float .* int16"):
        has_image_content(images.astype(np.int16))


def test_keyframe_selection_and_blur_kernels_name_bad_arguments():
    from vvloc.data import select_keyframes
    from vvloc.data.perturb import line_kernel

    with pytest.raises(TypeError, match=r"^poses: expected a real array .* dtype complex128"):
        select_keyframes(np.ones((2, 3), complex))  # the imaginary part was dropped
    with pytest.raises(TypeError, match=r"^poses: .* dtype <U1"):
        select_keyframes([["a", "b", "c"]])
    with pytest.raises(
        ValueError, match=r"^poses: expected an array of shape \(N, 3\), got a ragged"
    ):
        select_keyframes([[0, 0, 0], [1, 0]])
    with pytest.raises(ValueError, match=r"^poses: contains non-finite"):
        select_keyframes([[0, 0, np.nan]])
    with pytest.raises(ValueError, match=r"^length: expected an int >= 1, got 0"):
        line_kernel(0, 0.0)  # ZeroDivisionError
    with pytest.raises(ValueError, match=r"^angle_deg: expected a finite value, got nan"):
        line_kernel(3, float("nan"))


def test_a_sampler_given_another_ones_state_draws_what_that_one_would(tmp_path):
    ds = _drive_dataset(tmp_path / "ds")
    live = TripletSampler(ds, seed=1, hard_fraction=0.5)
    drawn = live.sample(12)
    live.update(drawn, np.arange(12) % 3 == 0)  # 8 hard
    live.sample(6)  # takes 3 of the pool: the next draw starts inside it
    state = live.state_dict()
    assert state["hard_cursor"] == 3 and len(state["hard"]) == 8
    copy = TripletSampler(ds, seed=99, hard_fraction=0.5)
    copy.mark_hard(copy.sample_random(2))  # a pool of its own, replaced by the state's
    copy.load_state_dict(state)
    for _ in range(3):
        assert np.array_equal(copy.sample(6), live.sample(6))
    assert np.array_equal(copy.hard, live.hard)
    # a state saved before the cursor was kept restarts at the pool's first triplet
    old = TripletSampler(ds, seed=99, hard_fraction=0.5)
    old.load_state_dict({"rng": state["rng"], "hard": state["hard"]})
    fresh = TripletSampler(ds, seed=1, hard_fraction=0.5)
    fresh.load_state_dict({**state, "hard_cursor": 0})
    assert np.array_equal(old.sample(6), fresh.sample(6))


def test_excluded_frames_are_never_drawn_again_and_a_state_carries_them(tmp_path):
    ds = _drive_dataset(tmp_path / "ds")
    plain = TripletSampler(ds, seed=4, cross_floor_fraction=0.5)
    live = TripletSampler(ds, seed=4, cross_floor_fraction=0.5)
    assert np.array_equal(live.exclude(np.array([], dtype=np.int64)), [])  # nothing: no change
    assert np.array_equal(plain.sample(32), live.sample(32))
    drawn = live.sample(40)
    live.update(drawn, np.zeros(40, dtype=bool))  # every one hard
    gone = np.unique(drawn[:5].reshape(-1))
    assert np.array_equal(live.exclude(np.concatenate([gone, gone[:2]])), gone)
    assert np.array_equal(live.exclude(gone[:3]), [])  # excluded before: not new
    assert np.array_equal(live.excluded, gone) and not live.usable[gone].any()
    assert not np.isin(live.hard, gone).any() and len(live.hard) > 0
    assert not np.isin(live.anchors, gone).any()
    assert all(not np.isin(live.positives[a], gone).any() for a in live.anchors)
    for _ in range(20):
        assert not np.isin(live.sample(32), gone).any()  # hard and fresh, every slot
    state = live.state_dict()
    copy = TripletSampler(ds, seed=4, cross_floor_fraction=0.5)
    copy.load_state_dict(state)
    assert np.array_equal(copy.excluded, gone)
    for _ in range(3):
        assert np.array_equal(copy.sample(16), live.sample(16))
    other = TripletSampler(ds, seed=4, cross_floor_fraction=0.5)
    other.exclude([int(np.setdiff1d(np.arange(len(other)), gone)[0])])
    with pytest.raises(ValueError, match=r"^state: this sampler excludes frames the state does "):
        other.load_state_dict(state)  # it would draw otherwise than the state's sampler
    with pytest.raises(ValueError, match=r"^gids: frame ids must lie in \[0, "):
        live.exclude([len(live)])
    with pytest.raises(TypeError, match=r"^gids: expected an integer array \(E,\)"):
        live.exclude([0.5])
    with pytest.raises(ValueError, match=r"^exclude: no anchor would be left"):
        live.exclude(np.arange(len(live)))
    assert np.array_equal(live.excluded, gone)  # a refused exclusion changes nothing


def test_an_anchor_whose_negatives_are_all_excluded_is_no_anchor(tmp_path):
    # s0@0 and s1@0 keep a positive, but every frame left lies within neg_radius of them
    x0, x1 = [-1.0, 0.0, 2.9, 10.0], [0.0, 2.9, 10.0]
    line = [
        (np.column_stack([x, np.zeros(len(x)), np.zeros(len(x))]), np.zeros(len(x), int))
        for x in (x0, x1)
    ]
    _write(tmp_path / "ds", {"s0": line[0], "s1": line[1]}, cameras=make_rig(1, W, H))
    sampler = TripletSampler(open_dataset(tmp_path / "ds"), seed=0)
    assert sampler.anchors.tolist() == [0, 1, 2, 3, 4, 5, 6]
    sampler.exclude([3, 6])  # the frames at x = 10 m
    assert sampler.anchors.tolist() == [0, 2, 5]
    t = sampler.sample(64)
    d_neg = np.linalg.norm(sampler.positions[t[:, 0]] - sampler.positions[t[:, 2]], axis=1)
    assert np.all(d_neg > 3.0) and not np.isin(t, [3, 6]).any()


def test_floors_are_different_places(tmp_path):
    root = tmp_path / "ds"
    _write(root, {"s0": _line(5, floor=0), "s1": _line(5, floor=1), "s2": _line(5, y=0.5)})
    ds = open_dataset(root)
    sampler = TripletSampler(ds, seed=0)
    for a in sampler.anchors:
        for p in sampler.positives[a]:
            assert (
                ds.session(sampler.locate(int(p))[0]).floors[0]
                == ds.session(sampler.locate(int(a))[0]).floors[0]
            )
    split = evaluation_split(ds, database="s0", revisit_radius=1.0)
    assert set(split.query_sessions.tolist()) == {"s2"}  # s1 is on another floor
    assert np.all(split.nearest_distance <= 1.0) and len(split.query_indices) == 5
    assert np.array_equal(split.nearest_database, np.arange(5))
    assert evaluation_split(ds, database="s0").revisit_radius == 2.0  # vvloc eval's keep radius
    with pytest.raises(ValueError, match="more than once"):
        evaluation_split(ds, database="s0", queries=["s2", "s2"])
    # one str was split into sessions 's' and '2': "no session 's'"
    with pytest.raises(
        TypeError, match=r"queries: expected a sequence of session names, .*\['s2'\]"
    ):
        evaluation_split(ds, database="s0", queries="s2")
    gen = evaluation_split(ds, database="s0", queries=(n for n in ["s2"]))  # read once
    assert np.array_equal(gen.query_indices, evaluation_split(ds, "s0", ["s2"]).query_indices)
    assert len(gen.query_indices) == 5
    for bad in ("2", np.nan, np.inf, True):
        with pytest.raises(ValueError, match="revisit_radius: expected a finite distance"):
            evaluation_split(ds, database="s0", revisit_radius=bad)
    for bad in (0.0, -5.0, 1.5):  # floors apart by less than a radius would pair
        with pytest.raises(ValueError, match="floor_separation"):
            evaluation_split(ds, database="s0", floor_separation=bad)
        with pytest.raises(ValueError, match="floor_separation"):
            TripletSampler(ds, seed=0, floor_separation=bad)
    with pytest.raises(TypeError, match="sessions"):
        TripletSampler(ds, seed=0, sessions="s0")
    with pytest.raises(ValueError, match="sessions: names repeated"):
        TripletSampler(ds, seed=0, sessions=["s0", "s0", "s2"])


def test_anchors_without_a_negative_are_never_drawn(tmp_path):
    # three places 2.9 m apart in two sessions: the middle one has no frame beyond 3 m
    xs = np.array([-2.9, 0.0, 2.9])
    poses = np.column_stack([xs, np.zeros(3), np.zeros(3)])
    _write(tmp_path / "ds", {"s0": (poses, np.zeros(3)), "s1": (poses, np.zeros(3))})
    sampler = TripletSampler(open_dataset(tmp_path / "ds"), seed=0)
    anchors = {sampler.locate(int(a)) for a in sampler.anchors}
    assert anchors == {("s0", 0), ("s0", 2), ("s1", 0), ("s1", 2)}  # not the middle ones
    for _ in range(20):
        sampler.sample(4)  # used to fail at random: "frame 4 has no negative beyond 3.0 m"
    near = np.column_stack([np.zeros(3), np.zeros(3), np.zeros(3)])
    _write(tmp_path / "one", {"s0": (near, np.zeros(3)), "s1": (near, np.zeros(3))})
    with pytest.raises(ValueError, match="no frame with a positive has a negative"):
        TripletSampler(open_dataset(tmp_path / "one"), seed=0)


def _frame_images(seed=0):
    return np.random.default_rng(seed).integers(0, 256, size=(4, 3, 24, 32), dtype=np.uint8)


def test_perturbations_change_only_what_they_say():
    x = _frame_images()
    m = perturb.mask_cameras(x, [1, 3])
    assert np.all(m[[1, 3]] == 0) and np.array_equal(m[[0, 2]], x[[0, 2]])
    drawn = perturb.mask_cameras(x, count=2, seed=4)
    blank = [k for k in range(4) if not drawn[k].any()]
    assert len(blank) == 2 and np.array_equal(drawn, perturb.mask_cameras(x, count=2, seed=4))
    r = perturb.mask_regions(x, count=2, size=0.25, cameras=[0], seed=3)
    inside = np.zeros(x.shape, bool)
    for c, r0, r1, c0, c1 in perturb.region_boxes(x.shape, 2, 0.25, 3, [0]):
        inside[c, :, r0:r1, c0:c1] = True
    assert np.all(r[inside] == 0) and np.array_equal(r[~inside], x[~inside])
    b = perturb.motion_blur(x, length=5, angle_deg=0.0, cameras=[2])
    assert np.array_equal(b[[0, 1, 3]], x[[0, 1, 3]]) and not np.array_equal(b[2], x[2])
    # horizontal blur of a vertical-stripe-free image (constant rows) changes nothing
    rows = np.repeat(np.arange(24, dtype=np.uint8)[None, None, :, None], 32, axis=3)
    rows = np.repeat(np.repeat(rows, 3, axis=1), 4, axis=0)
    assert np.array_equal(perturb.motion_blur(rows, 7, 0.0), rows)
    assert perturb.motion_blur(x, 7, None, seed=1).shape == x.shape
    e = perturb.exposure(x, gain=0.5, cameras=[0])
    assert np.array_equal(e[1:], x[1:]) and e[0].mean() < 0.6 * x[0].mean()
    n = perturb.noise(x, sigma=10.0, cameras=[3], seed=2)
    assert np.array_equal(n[:3], x[:3])
    diff = n[3].astype(float) - x[3]
    assert 5 < diff.std() < 12 and np.array_equal(n, perturb.noise(x, 10.0, cameras=[3], seed=2))
    with pytest.raises(ValueError, match="images"):
        perturb.noise(x[0])
    # a float image (0-1 or 0-255) is a wrong type, said as such, not a wrong shape
    with pytest.raises(TypeError, match=r"^images: expected a uint8 .* got dtype float64"):
        perturb.noise(x / 255.0)
    with pytest.raises(ValueError, match="cameras"):
        perturb.mask_cameras(x, [7])
    for bad in ("01", 2, [1.7], [True]):  # were read as cameras [0, 1], an error, [1], [1]
        with pytest.raises(TypeError, match="cameras: expected"):
            perturb.mask_cameras(x, bad)  # type: ignore[arg-type]


def test_perturb_frame_keeps_calibration_and_pose(tmp_path):
    root = tmp_path / "ds"
    _write(root, {"s0": _line(2)})
    f = open_dataset(root).session("s0")[1]
    g = perturb.perturb_frame(f, "mask_cameras", cameras=[0])
    assert g.images[0].max() == 0 and np.array_equal(g.K, f.K) and np.array_equal(g.pose, f.pose)
    with pytest.raises(ValueError, match="name"):
        perturb.perturb_frame(f, "smudge")
    with pytest.raises(ValueError, match=r"exposure takes .* not \['seed'\]"):
        perturb.perturb_frame(f, "exposure", seed=3)


def test_perturbation_arguments_are_checked_by_name():
    x = np.random.default_rng(0).integers(0, 256, (2, 3, 12, 16), dtype=np.uint8)
    for call, match in (
        (lambda: perturb.noise(x, sigma=float("nan")), "sigma"),
        (lambda: perturb.exposure(x, gain=float("inf")), "gain"),
        (lambda: perturb.mask_regions(x, count=-1), "count"),
        (lambda: perturb.mask_regions(x, count=2.5), "count"),
        (lambda: perturb.mask_cameras(x, count=2.5), "count"),
        (lambda: perturb.mask_cameras(x, fill=300), "fill"),
        (lambda: perturb.mask_regions(x, fill=-1), "fill"),
        (lambda: perturb.motion_blur(x, length=2.5), "length"),
        (lambda: perturb.motion_blur(x, angle_deg=float("nan")), "angle_deg"),
        # None would draw fresh entropy (not reproducible); -1 and 1.5 failed in numpy
        (lambda: perturb.noise(x, seed=None), "seed"),
        (lambda: perturb.noise(x, seed=-1), "seed"),
        (lambda: perturb.mask_regions(x, seed=1.5), "seed"),
        (lambda: perturb.mask_cameras(x, seed=None), "seed"),
        (lambda: perturb.motion_blur(x, angle_deg=None, seed=None), "seed"),
    ):
        with pytest.raises((TypeError, ValueError), match=match):
            call()


@pytest.mark.parametrize("length", [3, 4, 9])
def test_motion_blur_kernel_spans_its_length(length):
    row = perturb.line_kernel(length, 0.0)
    row = row[row.shape[0] // 2]
    assert row.sum() == pytest.approx(1.0)
    x = np.arange(len(row)) - (len(row) - 1) / 2
    std = np.sqrt((row * x**2).sum())
    # a uniform segment `length` pixels long: variance length²/12, plus 1/6 from the bilinear
    # splat (E[f(1 − f)] over uniform fractional positions); the old kernel spanned length − 1
    assert std == pytest.approx(np.sqrt(length**2 / 12 + 1 / 6), rel=0.01)
    if length % 2:
        inner = row[2:-2]
        assert np.allclose(inner, 1.0 / length)
    np.testing.assert_allclose(
        perturb.line_kernel(length, 90.0), perturb.line_kernel(length, 0.0).T, atol=1e-9
    )


def test_robustness_draws_each_query_frames_own_perturbation(tmp_path):
    from vvloc.localize.evaluation import ROBUSTNESS, perturbed

    root = tmp_path / "ds"
    _write(root, {"s0": _line(6)})
    frames = list(open_dataset(root).session("s0"))
    masked = [
        tuple(k for k in range(4) if not perturbed(f, "one camera masked").images[k].any())
        for f in frames
    ]
    assert all(len(m) == 1 for m in masked) and len(set(masked)) > 1  # not one camera for all
    noisy = [perturbed(f, "noise").images.astype(int) - f.images for f in frames[:2]]
    assert not np.array_equal(noisy[0], noisy[1])
    for label in ROBUSTNESS:  # the same frame, the same perturbation, in any order or run
        assert np.array_equal(
            perturbed(frames[3], label).images, perturbed(frames[3], label).images
        )


def test_camera_resize_keeps_projection_exact():
    cam = make_rig(4, 160, 96)[0]
    small = cam.resized(80, 48)
    pts = np.array([[10.0, 1.0, 1.2], [5.0, -2.0, 0.3]])
    uv, _ = cam.project_ego(pts)
    uv2, _ = small.project_ego(pts)
    # pixel-centre convention: u' + 0.5 = (u + 0.5) / 2
    assert np.allclose(uv2 + 0.5, (uv + 0.5) / 2)


def test_extra_datasets_are_other_worlds_and_cross_floor_negatives_share_the_place(tmp_path):
    # two worlds with the same coordinates; the second has a floor above the first's track
    _write(tmp_path / "lot", {"s0": _line(6), "s1": _line(6, y=0.5)})
    _write(
        tmp_path / "garage",
        {
            "s0": _line(6),
            "s1": _line(6, y=0.5),
            "s2": _line(6, floor=1),
            "s3": _line(6, y=0.5, floor=1),
        },
        seed=1,
    )
    lot, garage = open_dataset(tmp_path / "lot"), open_dataset(tmp_path / "garage")
    sampler = TripletSampler(
        lot, seed=0, extra=[(garage, None)], hard_fraction=0.0, cross_floor_fraction=1.0
    )
    assert sampler.sessions == ["s0", "s1", "garage/s0", "garage/s1", "garage/s2", "garage/s3"]
    world = sampler.level_of // 1000
    t = sampler.sample(200)
    # positives never cross worlds or floors, although the coordinates coincide
    assert np.all(sampler.level_of[t[:, 0]] == sampler.level_of[t[:, 1]])
    # in the garage every negative is the look-alike place on the other floor (fraction 1)
    g = t[world[t[:, 0]] == 1]
    assert len(g) > 0
    assert np.all(world[g[:, 2]] == 1) and np.all(
        sampler.level_of[g[:, 2]] != sampler.level_of[g[:, 0]]
    )
    xy = sampler.positions[:, :2]
    assert np.all(np.linalg.norm(xy[g[:, 2]] - xy[g[:, 0]], axis=1) <= sampler.neg_radius)
    # the lot has one floor: its negatives are ordinary ones (beyond neg_radius, or in the garage)
    lt = t[world[t[:, 0]] == 0]
    d = np.linalg.norm(sampler.positions[lt[:, 0]] - sampler.positions[lt[:, 2]], axis=1)
    assert np.all(d > sampler.neg_radius)
    # frames come from their own dataset
    gid = int(np.flatnonzero(sampler.session_of == 4)[2])
    assert sampler.locate(gid) == ("garage/s2", 2)
    f = sampler.frame(gid)
    assert (f.session, f.index, f.floor) == ("s2", 2, 1)
    assert np.array_equal(f.images, garage.session("s2")[2].images)
    # without extra datasets and cross-floor negatives the draws are unchanged
    assert np.array_equal(
        TripletSampler(lot, seed=0).sample(16),
        TripletSampler(lot, seed=0, cross_floor_fraction=0.0).sample(16),
    )
    with pytest.raises(ValueError, match="cross_floor_fraction"):
        TripletSampler(lot, cross_floor_fraction=1.5)
    with pytest.raises(ValueError, match="cross_floor_same_session"):
        TripletSampler(lot, cross_floor_same_session=-0.1)
    for kwargs, error, match in [
        ({"pos_radius": "2"}, TypeError, "pos_radius: expected a number"),
        ({"hard_fraction": None}, TypeError, "hard_fraction: expected a number"),
        ({"hard_fraction": True}, TypeError, "hard_fraction: expected a number"),
        ({"cross_floor_fraction": "0.5"}, TypeError, "cross_floor_fraction: expected a number"),
        ({"floor_separation": float("inf")}, ValueError, "floor_separation: expected a finite"),
        ({"seed": -1}, ValueError, "seed: expected an int >= 0"),
        ({"cross_session": "no"}, TypeError, "cross_session: expected a bool"),
    ]:
        with pytest.raises(error, match=match):
            TripletSampler(lot, **kwargs)
    assert TripletSampler(lot, floor_separation=np.float32(5)).pos_radius == 2.0
    pool = TripletSampler(lot, seed=0)
    with pytest.raises(ValueError, match=r"triplets: frame ids must lie in \[0, "):
        pool.mark_hard([[0, 1, len(pool)]])
    with pytest.raises(TypeError, match="correct: expected"):
        pool.update(pool.sample_random(2), np.array([0.0, 1.0]))
    with pytest.raises(ValueError, match=r"extra: dataset 1 .* is listed twice"):
        TripletSampler(lot, extra=[(garage, None), (garage, None)])
    # one world as two (its own places would be drawn as negatives): refused
    with pytest.raises(ValueError, match=r"extra: dataset 0 .* is the primary dataset"):
        TripletSampler(lot, extra=[(lot, None)])
    with pytest.raises(ValueError, match=r"extra: dataset 0 .* is the primary dataset"):
        TripletSampler(lot, extra=[(open_dataset(lot.root), ["s0"])])
    # anchor shares: the garage (2/3 of the frames) drawn for a fifth of the anchors
    weighted = TripletSampler(lot, seed=0, extra=[(garage, None)], anchor_shares=[0.2])
    a = weighted.sample_random(4000)[:, 0]
    assert abs(np.mean(world[a] == 1) - 0.2) < 0.03
    assert (
        abs(
            np.mean(
                world[TripletSampler(lot, seed=0, extra=[(garage, None)]).sample_random(4000)[:, 0]]
                == 1
            )
            - 2 / 3
        )
        < 0.03
    )
    assert np.array_equal(  # no share set: the draws of a sampler without the argument
        TripletSampler(lot, seed=0, extra=[(garage, None)], anchor_shares=[None]).sample(16),
        TripletSampler(lot, seed=0, extra=[(garage, None)]).sample(16),
    )
    for bad in ([0.0], [1.0], [True], [0.5, 0.2]):
        with pytest.raises(ValueError, match="anchor_shares"):
            TripletSampler(lot, extra=[(garage, None)], anchor_shares=bad)


def _two_floor_drive(n, y=0.0):
    """One drive along the same line on floor 0, then on floor 1 (as the garage sessions)."""
    (p0, f0), (p1, f1) = _line(n, y=y), _line(n, y=y, floor=1)
    return np.concatenate([p0, p1]), np.concatenate([f0, f1])


def test_same_session_cross_floor_negatives_come_from_the_anchors_own_drive(tmp_path):
    _write(tmp_path / "garage", {"s0": _two_floor_drive(6), "s1": _two_floor_drive(6, y=0.5)})
    garage = open_dataset(tmp_path / "garage")
    kw = {"seed": 0, "hard_fraction": 0.0, "cross_floor_fraction": 1.0}
    own = TripletSampler(garage, cross_floor_same_session=1.0, **kw).sample(300)
    mixed = TripletSampler(garage, **kw)
    t = mixed.sample(300)
    s, level = mixed.session_of, mixed.level_of
    # every negative is the other floor at the anchor's place; with share 1 from its own drive
    assert np.all(level[own[:, 2]] != level[own[:, 0]])
    assert np.all(s[own[:, 2]] == s[own[:, 0]])
    xy = mixed.positions[:, :2]
    assert np.all(np.linalg.norm(xy[own[:, 2]] - xy[own[:, 0]], axis=1) <= mixed.neg_radius)
    # by default both drives supply them
    assert np.all(level[t[:, 2]] != level[t[:, 0]])
    assert 0.2 < np.mean(s[t[:, 2]] == s[t[:, 0]]) < 0.8
    # share 0 draws exactly what a sampler without the argument draws
    assert np.array_equal(
        TripletSampler(garage, cross_floor_same_session=0.0, **kw).sample(50),
        TripletSampler(garage, **kw).sample(50),
    )


def test_basement_floors_below_zero_are_levels_like_any_other(tmp_path):
    def sampler_of(f0, f1):
        root = tmp_path / f"ds{f0}"
        sessions = {
            "s0": _line(5, floor=f0),
            "s1": _line(5, floor=f1),
            "s2": _line(5, y=0.5, floor=f0),
        }
        _write(root, sessions)
        return TripletSampler(open_dataset(root), seed=0)

    below, above = sampler_of(-1, 0), sampler_of(0, 1)
    assert below.anchors.tolist() == above.anchors.tolist()
    for a in below.anchors:
        assert below.positives[a].tolist() == above.positives[a].tolist()
    np.testing.assert_array_equal(below.positions, above.positions)


def test_a_single_drive_that_returns_gives_positives_with_a_revisit_gap(tmp_path):
    # one session: out along a line (frames 0-4, 2 m apart) and back over the same places
    out_poses, floors = _line(5)
    poses = np.concatenate([out_poses, out_poses[::-1]])
    root = tmp_path / "ds"
    _write(root, {"s0": (poses, np.concatenate([floors, floors]))})
    ds = open_dataset(root)
    with pytest.raises(ValueError, match="set revisit_gap"):
        TripletSampler(ds, seed=0)  # positives from other sessions only: there are none
    sampler = TripletSampler(ds, seed=0, revisit_gap=3)
    for a in sampler.anchors:
        for p in sampler.positives[a]:
            assert abs(int(p) - int(a)) >= 3  # the return pass, not the frame's own pass
            assert np.linalg.norm(poses[int(p), :2] - poses[int(a), :2]) <= 2.0
    # every place is revisited but the turning point, where frames 4 and 5 are one pass
    assert sorted(sampler.anchors.tolist()) == [0, 1, 2, 3, 6, 7, 8, 9]
    with pytest.raises(ValueError, match="revisit_gap"):
        TripletSampler(ds, revisit_gap=-1)


def test_perturbation_helpers_name_arguments_they_cannot_use(tmp_path):
    from vvloc.checkpoints import check_checkpoint_files
    from vvloc.data.perturb import frame_seed, mask_regions, perturb_frame, region_boxes

    with pytest.raises(ValueError, match=r"^images: expected H, W >= 1"):
        mask_regions(np.zeros((1, 3, 0, 4), np.uint8))  # numpy's "high <= 0"
    with pytest.raises(ValueError, match=r"^shape: expected the images' shape \(M, 3, H, W\)"):
        region_boxes((2, 8, 10), 1, 0.5, 0, None)  # "not enough values to unpack"
    with pytest.raises(TypeError, match=r"^name: expected one of"):
        perturb_frame(None, ["noise"])  # type: ignore[arg-type]  # "unhashable type"
    with pytest.raises(TypeError, match=r"^frame: expected a vvloc.data.Frame"):
        frame_seed(None)  # type: ignore[arg-type]
    with pytest.raises(FileNotFoundError, match=r"^directory: .* does not exist"):
        check_checkpoint_files(str(tmp_path / "none"))  # type: ignore[arg-type]  # AttributeError
    boxes = region_boxes((1, 3, 8, 8), 1, 0.5, 0, None)
    assert boxes == region_boxes([1, 3, 8, 8], 1, 0.5, 0, None) and len(boxes) == 1


def test_poses_and_extrinsics_take_numbers_as_c_writes_them(tmp_path):
    root = tmp_path / "ds"
    _write(root, {"s0": _line(2)})
    p = root / "sessions" / "s0" / "poses.csv"
    header, first, _second = p.read_text().splitlines()
    # Python's int() and float() read these; no writer means them
    for row, said in (
        ("2000000,-9_0.5,0,0,0,0", "-9_0.5"),  # read as -90.5
        ("1_000_000_000,0,0,0,0,0", "1_000_000_000"),
        ("2000000,0,0,0,0,\u0661", "\u0661"),  # an Arabic-Indic one, read as floor 1
    ):
        p.write_text("\n".join([header, first, row]) + "\n")
        with pytest.raises(DatasetFormatError, match=rf"line 3: malformed row .*{said}"):
            open_dataset(root)
