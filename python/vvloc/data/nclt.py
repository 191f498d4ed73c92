"""Reader of the University of Michigan North Campus Long-Term (NCLT) dataset, raw layout.

Layout read (as distributed; ``images/`` and ``ground_truth/`` levels are optional)::

    <root>/[images/]<date>/lb3/Cam{1..5}/<utime>.tiff      Ladybug3 images (RGB TIFF)
    <root>/[ground_truth/]groundtruth_<date>.csv            utime,x,y,z,roll,pitch,yaw (no header)
    <root>/cam_params/K_cam{i}.csv                          3×3 intrinsics, comma separated
    <root>/cam_params/x_lb3_c{i}.csv                        camera pose in the Ladybug frame
    <root>/cam_params/U2D_Cam{i}_*.txt                      optional undistortion map (or in
    <root>/U2D_ALL_*/, as NCLT's U2D_ALL_1616X1232.tar.gz unpacks, or in <root>/)

Conventions converted from:

* NCLT's body frame is x forward, y right, z down; ground truth is in a local NED frame
  (x north, y east, z down), angles in radians. vvloc ego/world are FLU/ENU (DESIGN.md §3), so
  ``T_world_ego = NED_TO_ENU · T_ned_body · FRD_TO_FLU`` and yaw is read off that matrix
  (π/2 − NCLT yaw for a level vehicle). Each session's yaw is checked against its direction
  of travel (:mod:`vvloc.data.heading`: a warning when they differ by more than 0.5°).
* Six-vector poses ("ssc": x, y, z, roll, pitch, yaw; R = Rz·Ry·Rx) — ``x_lb3_c{i}`` in metres and
  degrees, giving the camera in the Ladybug (lb3) frame; the lb3 frame in the body frame is the
  constant ``X_BODY_LB3`` of NCLT's own projection example.
* The camera frame that ``K_cam{i}`` projects from is treated as OpenCV (x right, y down,
  z forward); K applies to the (undistorted) image as stored. The Ladybug's images are stored
  sideways (their columns run down the scene), so by default (``upright=True``) each image is
  turned a quarter turn clockwise after undistortion, as NCLT's own tools show them, with K and
  ``cam_to_ego`` following exactly (:meth:`Camera.rotated`): rows then run top to bottom of the
  scene, as in vvloc's other datasets (the photometric augmentations assume that).
* The body frame's origin is not on the ground (the Ladybug sits 1.23 m above it); vvloc's ego
  origin is the ground under the vehicle, so pass ``ego_height`` (the body origin's height above
  the ground, metres) to move it there: cameras rise by it, pose heights drop by it. The default
  0 keeps the body origin. The ego frame is level by default (``level=True``): its origin is
  the ground under the body origin (along the body's z axis), its heading the body's, and the
  Segway's roll and pitch go into each frame's ``cam_to_ego`` (``Session.frame_cam_to_ego``;
  :func:`vvloc.data.frame.ego_frames`), so that every camera ray meets the ground where the BEV
  expects it. ``level=False`` keeps the tilting body frame as the ego frame.
* The undistortion map file starts with a header holding two integers ``a b`` (the map is b rows ×
  a columns); each further line ``row col v u`` gives the source pixel (u column, v row) that
  output pixel (row, col) samples — the way NCLT's ``undistort.py`` reads it.
* Images of one Ladybug capture share a ``utime``; a frame is a utime present for every camera,
  posed by the ground-truth row nearest in time, kept only within ``tolerance_us``. How many
  were left out, and why, is each session's ``left_out`` (``vvloc convert`` prints it).
* Without a ``U2D_Cam{i}_*.txt`` map the images are used distorted, with a warning: the pinhole
  K does not describe the Ladybug's wide-angle lenses.
"""

from __future__ import annotations

import csv
import os
import re
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from vvloc.data._remap import remap_bilinear, resize_rgb
from vvloc.data.frame import (
    FRD_TO_FLU,
    NED_TO_ENU,
    Camera,
    Dataset,
    Session,
    check_reader_options,
    chosen_sessions,
    ego_frames,
    euler_to_matrix,
    load_rgb,
    nearest_within,
)
from vvloc.data.heading import heading_warning
from vvloc.data.vvloc_format import DatasetFormatError

# Ladybug (lb3) frame in the body frame: x, y, z m; roll, pitch, yaw degrees (NCLT's example code).
X_BODY_LB3 = (0.035, 0.002, -1.23, -179.93, -0.23, 0.50)
DEFAULT_CAMERAS = (1, 2, 3, 4, 5)


def ssc_degrees_to_matrix(v: Sequence[float] | np.ndarray) -> np.ndarray:
    """4×4 transform of an NCLT six-vector (x, y, z m; roll, pitch, yaw degrees)."""
    x, y, z, r, p, h = (float(a) for a in v)
    return euler_to_matrix(x, y, z, np.deg2rad(r), np.deg2rad(p), np.deg2rad(h))


def _read_numbers(path: Path, shape: tuple[int, ...]) -> np.ndarray:
    if not path.is_file():
        raise DatasetFormatError(f"{path}: calibration file missing")
    try:
        vals = [float(v) for v in re.split(r"[,\s]+", path.read_text().strip()) if v]
    except ValueError as e:
        raise DatasetFormatError(f"{path}: malformed numbers: {e}") from e
    if len(vals) != int(np.prod(shape)):
        raise DatasetFormatError(f"{path}: expected {int(np.prod(shape))} numbers, got {len(vals)}")
    return np.array(vals, dtype=np.float64).reshape(shape)


def read_undistortion_map(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read an NCLT ``U2D_*.txt`` map into source (u, v) float32 arrays shaped like the output
    image (float32: 2 × 8 MB for a 1616 × 1232 map; exact to 1e-4 px)."""
    with path.open() as f:
        header = [int(v) for v in re.findall(r"\d+", f.readline())]
        if len(header) < 2:
            raise DatasetFormatError(f"{path}, line 1: expected two sizes in the header")
        cols, rows = header[0], header[1]
        try:
            data = np.loadtxt(f, dtype=np.float64, ndmin=2)
        except ValueError as e:  # numpy's message names no file
            raise DatasetFormatError(f"{path}: malformed map line: {e}") from None
    if data.shape[1] != 4:
        raise DatasetFormatError(
            f"{path}: expected lines 'row col v u', got {data.shape[1]} columns"
        )
    if not np.isfinite(data).all():
        k = int(np.flatnonzero(~np.isfinite(data).all(axis=1))[0]) + 1
        raise DatasetFormatError(f"{path}: map line {k}: non-finite value (nan or inf)")
    frac = data[:, :2] != np.round(data[:, :2])
    if frac.any():  # a fractional index was truncated to a neighbouring pixel
        k = int(np.flatnonzero(frac.any(axis=1))[0])
        raise DatasetFormatError(
            f"{path}: pixel indices must be integers, got row {data[k, 0]:g}, col {data[k, 1]:g}"
        )
    mapu = np.full((rows, cols), -1.0, dtype=np.float32)
    mapv = np.full((rows, cols), -1.0, dtype=np.float32)
    r, c = data[:, 0].astype(np.int64), data[:, 1].astype(np.int64)
    if r.min() < 0 or c.min() < 0 or r.max() >= rows or c.max() >= cols:
        raise DatasetFormatError(f"{path}: pixel index outside the {rows}x{cols} map")
    mapv[r, c] = data[:, 2]
    mapu[r, c] = data[:, 3]
    covered = np.zeros((rows, cols), dtype=bool)
    covered[r, c] = True
    if not covered.all():  # a file cut short: those pixels would be black in every image
        warnings.warn(
            f"{path}: the undistortion map lists {int(covered.sum())} of the {rows * cols} "
            f"output pixels (first missing: row {int(np.argmin(covered) // cols)}); the others "
            "read black in every converted image: is the file complete?",
            stacklevel=2,
        )
    return mapu, mapv


def _csv_lines(path: Path, f: Any) -> Iterator[tuple[int, list[str]]]:
    """(row number from 1, fields) of the open CSV file ``f``; the csv module's own errors (a
    field over its size limit) as a :class:`DatasetFormatError` naming ``path`` and the line."""
    reader = csv.reader(f)
    try:
        yield from enumerate(reader, start=1)
    except csv.Error as e:
        raise DatasetFormatError(f"{path}, line {reader.line_num}: {e}") from None


def read_groundtruth(path: Path) -> np.ndarray:
    """(N, 7) float64 rows utime, x, y, z, roll, pitch, yaw sorted by time; NaN rows dropped."""
    rows = []
    with path.open(newline="") as f:
        for line, row in _csv_lines(path, f):
            if not row:
                continue
            if len(row) != 7:
                raise DatasetFormatError(f"{path}, line {line}: expected 7 fields, got {len(row)}")
            try:
                vals = [float(v) for v in row]
            except ValueError as e:
                raise DatasetFormatError(
                    f"{path}, line {line}: malformed row {row!r:.200}: {e}"
                ) from e
            if all(np.isfinite(vals)):
                rows.append(vals)
    arr = np.array(rows, dtype=np.float64).reshape(-1, 7)
    return arr[np.argsort(arr[:, 0], kind="stable")]


class NcltSession(Session):
    """One NCLT date: lazily read, undistorted (when maps are given), optionally resized."""

    def __init__(
        self,
        name: str,
        image_dirs: list[Path],
        cameras: Sequence[Camera],
        native_size: tuple[int, int],
        maps: list[tuple[np.ndarray, np.ndarray] | None],
        turns: list[int],
        timestamps: np.ndarray,
        poses: np.ndarray,
        z: np.ndarray,
        frame_cam_to_ego: np.ndarray | None = None,
        *,
        left_out: dict[str, int] | None = None,
    ) -> None:
        floors = np.zeros(len(timestamps), np.int64)
        super().__init__(
            name, cameras, timestamps, poses, z, floors, frame_cam_to_ego, left_out=left_out
        )
        self._dirs = image_dirs
        self._native = native_size
        self._maps = maps
        self._turns = turns

    def _load_images(self, index: int) -> np.ndarray:
        out = []
        parts = zip(self.cameras, self._dirs, self._maps, self._turns, strict=True)
        for cam, d, m, k in parts:
            path = d / f"{int(self.timestamps[index])}.tiff"
            img = load_rgb(path)
            if (img.shape[1], img.shape[0]) != self._native:  # the size the map reads from
                raise DatasetFormatError(
                    f"{path}: image is {img.shape[1]}x{img.shape[0]}, expected {self._native}"
                )
            if m is not None:
                img = remap_bilinear(img, *m)
            img = np.ascontiguousarray(np.rot90(img, k))
            out.append(resize_rgb(img, cam.width, cam.height).transpose(2, 0, 1))
        return np.ascontiguousarray(np.stack(out))


def _find_date_dirs(root: Path) -> dict[str, Path]:
    found = {}
    for base in (root, root / "images"):
        if base.is_dir():
            for d in sorted(base.iterdir()):
                if (d / "lb3").is_dir():
                    found[d.name] = d / "lb3"
    return found


def is_nclt(root: Path) -> bool:
    """Whether ``root`` looks like an NCLT raw folder."""
    return bool(_find_date_dirs(root)) and (root / "cam_params").is_dir()


def open_nclt(
    root: str | os.PathLike[str],
    *,
    cameras: Sequence[int] = DEFAULT_CAMERAS,
    image_size: tuple[int, int] | None = None,
    tolerance_us: int = 50_000,
    upright: bool = True,
    ego_height: float = 0.0,
    level: bool = True,
    sessions: Sequence[str] | None = None,
) -> Dataset:
    """Open an NCLT raw folder as a :class:`Dataset` (one session per date).

    Args:
        root: dataset root (see the module docstring for the layout).
        cameras: Ladybug camera numbers to use, in image order.
        image_size: (width, height) to resize every image to (K adjusted), or None for native
            (of the upright image: 1232 × 1616 for NCLT's undistorted images).
        tolerance_us: largest image-to-ground-truth time gap kept, microseconds.
        upright: turn each camera's images by the quarter turns that make them upright
            (:meth:`Camera.upright_quarter_turns`; one clockwise turn for NCLT's); False keeps
            them as stored.
        ego_height: height of NCLT's body-frame origin above the ground, metres: vvloc's ego
            origin is moved down there (cameras rise by it, ``Frame.z`` drops by it).
        level: make each frame's ego frame level (:func:`vvloc.data.frame.ego_frames`): the
            Segway's roll and pitch (several degrees while it drives) go into that frame's
            ``cam_to_ego`` (``Session.frame_cam_to_ego``), so the BEV's plane is the ground's.
            False keeps the tilting body frame as the ego frame (every frame the rig's
            ``cam_to_ego``).
        sessions: the dates to read (default every date found); the others' images are not
            listed and their ground truth not read (``KeyError`` naming the found dates for
            one the folder lacks).
    """
    root = Path(root)
    image_size, tolerance_us = check_reader_options(cameras, image_size, tolerance_us)
    dates = _find_date_dirs(root)
    if not dates:
        raise DatasetFormatError(f"{root}: no <date>/lb3 folder found (NCLT layout)")
    wanted = chosen_sessions(sessions, list(dates), root)
    if wanted is not None:
        dates = {d: lb3 for d, lb3 in dates.items() if d in wanted}
    for flag, value in (("upright", upright), ("level", level)):
        if not isinstance(value, (bool, np.bool_)):
            raise TypeError(f"{flag}: expected a bool, got {type(value).__name__}")
    height = float(ego_height)
    if not np.isfinite(height):
        raise ValueError(f"ego_height: expected a finite height in metres, got {ego_height!r}")
    params = root / "cam_params"
    T_body_lb3 = ssc_degrees_to_matrix(X_BODY_LB3)
    map_cache: dict[Path, tuple[np.ndarray, np.ndarray]] = {}
    read: dict[str, Session] = {}
    rig: list[Camera] | None = None
    for date, lb3 in dates.items():
        dirs = [lb3 / f"Cam{i}" for i in cameras]
        for d in dirs:
            if not d.is_dir():
                raise DatasetFormatError(f"{d}: camera folder missing")
        stamps, seen = _common_stamps(dirs)
        utimes = np.array(sorted(stamps), dtype=np.int64)
        if len(utimes) == 0:
            raise DatasetFormatError(f"{lb3}: no <utime>.tiff present for every camera")
        maps: list[tuple[np.ndarray, np.ndarray] | None] = []
        turns: list[int] = []
        cams = []
        native = load_rgb(dirs[0] / f"{utimes[0]}.tiff").shape[1::-1]
        for i in cameras:
            K = _read_numbers(params / f"K_cam{i}.csv", (3, 3))
            T_lb3_c = ssc_degrees_to_matrix(_read_numbers(params / f"x_lb3_c{i}.csv", (6,)))
            m = _undistortion_map(params, i, native, dirs[0], map_cache, warn=rig is None)
            maps.append(m)
            size = (m[0].shape[1], m[0].shape[0]) if m is not None else tuple(native)
            cam = Camera(f"Cam{i}", size[0], size[1], K, FRD_TO_FLU @ T_body_lb3 @ T_lb3_c)
            k = cam.upright_quarter_turns() if upright else 0
            turns.append(k)
            cam = cam.rotated(k).with_ego_origin_lowered(height)
            if image_size is not None:
                cam = cam.resized(*image_size)
            cams.append(cam)
        gt = read_groundtruth(_groundtruth_path(root, lb3, date))
        pick, ok = nearest_within(gt[:, 0].astype(np.int64), utimes, tolerance_us)
        utimes, pick = utimes[ok], pick[ok]
        left_out = {
            "an image missing for some camera": len(seen) - len(stamps),
            f"no ground truth within tolerance_us={tolerance_us}": int((~ok).sum()),
        }
        world_body = np.array(
            [NED_TO_ENU @ euler_to_matrix(*row[1:7]) @ FRD_TO_FLU for row in gt[pick]]
        ).reshape(-1, 4, 4)  # (0, 4, 4) when no image has ground truth near it
        poses, zs, frame_cam_to_ego = ego_frames(world_body, cams, height=height, level=level)
        note = heading_warning(date, poses)
        if note is not None:
            warnings.warn(note, stacklevel=2)
        read[date] = NcltSession(
            date,
            dirs,
            cams,
            (int(native[0]), int(native[1])),  # the raw images' (width, height)
            maps,
            turns,
            utimes,
            poses,
            zs,
            frame_cam_to_ego,
            left_out=left_out,
        )
        rig = rig or cams
    assert rig is not None
    return Dataset(root, rig, read)


def _common_stamps(dirs: list[Path]) -> tuple[set[int], set[int]]:
    """The ``<utime>.tiff`` times (µs) that every camera folder of ``dirs`` has an image of,
    and those any of them has."""
    common: set[int] | None = None
    seen: set[int] = set()
    for d in dirs:
        s = {int(p.stem) for p in d.glob("*.tiff") if p.stem.isdigit()}
        common = s if common is None else common & s
        seen |= s
    return common or set(), seen


def _undistortion_map(
    params: Path,
    camera: int,
    native: tuple[int, ...],
    images: Path,
    cache: dict[Path, tuple[np.ndarray, np.ndarray]],
    *,
    warn: bool,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Camera ``camera``'s undistortion map (``U2D_Cam<i>_*.txt`` in ``cam_params/``, else in a
    ``U2D_ALL_*/`` folder beside it, as NCLT's archive of the maps unpacks, else beside
    ``cam_params/``), read once into ``cache`` for every date, or None without one (a
    ``UserWarning`` at :func:`open_nclt`'s caller when ``warn``: the images stay distorted).
    ``DatasetFormatError`` when it is not of the raw images' (width, height) ``native``
    (``images``: a camera folder, for the message)."""
    root = params.parent
    places = [params, *sorted(p for p in root.glob("U2D_ALL_*") if p.is_dir()), root]
    u2d: list[Path] = []
    for place in places:
        u2d = sorted(place.glob(f"U2D_Cam{camera}_*.txt"))
        if u2d:
            break
    if not u2d:
        if warn:
            warnings.warn(
                f"{params}: no U2D_Cam{camera}_*.txt undistortion map (looked there, in "
                f"{root}/U2D_ALL_*/ and in {root}); Cam{camera}'s images are used distorted, "
                "which its pinhole K does not describe",
                stacklevel=3,
            )
        return None
    if u2d[0] not in cache:
        cache[u2d[0]] = read_undistortion_map(u2d[0])
    m = cache[u2d[0]]
    if m[0].shape[::-1] != tuple(native):  # the map reads the raw image's pixels
        raise DatasetFormatError(
            f"{u2d[0]}: the undistortion map is {m[0].shape[1]}x{m[0].shape[0]}, "
            f"the images (e.g. {images}) are {native[0]}x{native[1]}: a map of "
            "another image size"
        )
    return m


def _groundtruth_path(root: Path, lb3: Path, date: str) -> Path:
    """``groundtruth_<date>.csv`` in ``root``, ``root/ground_truth`` or beside the date's
    folder (``lb3.parent``); ``DatasetFormatError`` when none holds it."""
    for p in (
        root / f"groundtruth_{date}.csv",
        root / "ground_truth" / f"groundtruth_{date}.csv",
        lb3.parent / f"groundtruth_{date}.csv",
    ):
        if p.is_file():
            return p
    raise DatasetFormatError(f"{root}: groundtruth_{date}.csv not found")
