"""Reader of the Oxford (Radar) RobotCar dataset, raw layout.

Layout read (the dataset's own folders plus the SDK's ``models/`` and ``extrinsics/``)::

    <root>/<session>/stereo/centre/<utime>.png   Bayer GBRG, 8 bit   + <session>/stereo.timestamps
    <root>/<session>/mono_{left,right,rear}/<utime>.png   Bayer RGGB  + <session>/mono_*.timestamps
    <root>/<session>/gps/ins.csv                 timestamp,ins_status,..,northing,easting,down,
                                                 ..,roll,pitch,yaw
    <models_dir>/<model>.txt                     "fx fy cx cy" then the 4×4 G_camera_image
    <models_dir>/<model>_distortion_lut.bin      optional float64 LUT 2 × (H·W): source u, v rows
    <extrinsics_dir>/<sensor>.txt                "x y z roll pitch yaw" (m, rad); see below for
                                                 which way each file maps (stereo.txt optional:
                                                 identity)

Conventions converted from:

* RobotCar's vehicle, INS and camera frames are x forward, y right, z down; poses use
  R = Rz(yaw)·Ry(pitch)·Rx(roll). The vehicle frame is the stereo camera's. ``G_camera_image``
  maps the image frame (OpenCV: x right, y down, z forward) into the camera frame.
* The camera extrinsics (``mono_*.txt``) hold the *vehicle* in the camera frame,
  ``T_camera_vehicle``: the SDK's ``project_laser_into_camera`` uses them as ``G_camera_vehicle``,
  and only their inverse puts ``mono_left`` on the left of the car (robotcar-dataset-sdk issues
  #22, #40). So ``cam_to_ego = FRD_TO_FLU · T_camera_vehicle⁻¹ · G_camera_image``.
* ``ins.txt`` holds the INS in the vehicle frame, ``T_vehicle_ins`` (as the SDK's
  ``build_pointcloud`` uses it). The INS pose (northing, easting, down; roll, pitch, yaw in a NED
  world) is moved to the vehicle frame and then to ENU/FLU: ``T_world_ego = NED_TO_ENU ·
  T_ned_ins · T_vehicle_ins⁻¹ · FRD_TO_FLU``. It is interpolated at each frame's time between
  the two nearest INS rows (linear in position, along the shorter arc in each angle), as the
  SDK does; rows whose ``ins_status`` is not ``INS_SOLUTION_GOOD`` are left out (when the column
  is there). World coordinates are re-centred on the first pose of the first session
  (``ds.meta["origin_enu"]``) so that float32 consumers keep centimetres.
* Unverified on real data: (northing, easting) are UTM grid coordinates, and the INS yaw is
  taken as measured from grid north. If it is measured from true north (as a NovAtel INS
  reports its azimuth), the two differ by the UTM grid convergence, about 1.4° at Oxford
  (zone 30), and every relative translation turns by that much (2.4 cm per metre). Neither the
  SDK nor this reader corrects for it. The reader checks every session: on straight stretches
  the direction of travel of the ego poses should equal their yaw, and a median offset above
  0.5° is warned about (:mod:`vvloc.data.heading`).
* The vehicle frame's origin is the stereo camera on the roof; vvloc's ego origin is the ground
  under the vehicle. Pass ``ego_height`` (the stereo camera's height above the ground, metres)
  to move it there; the default 0 keeps the roof origin.
* Mono and stereo intrinsics stay apart: the stereo centre camera uses ``stereo_narrow_left``,
  each mono camera its own model; mono images are RGGB, stereo GBRG.
* The cameras are not synchronised: a frame is a timestamp of the first camera, joined with the
  nearest image of each other camera (within ``tolerance_us``), posed at the first camera's
  time (an INS row within ``tolerance_us``). With ``motion_compensation`` (default) each camera
  is placed where it was at its own exposure (the INS interpolated at its image's timestamp),
  in the ego frame of the frame's time: at 14 m/s a 30 ms gap is 0.4 m. How many of the first
  camera's timestamps were left out, and why, is each session's ``left_out`` (``vvloc
  convert`` prints it).
* The ego frame is level by default (``level=True``): its origin is the ground under the
  vehicle frame's origin (along the vehicle's z axis), its heading the vehicle's; the car's
  roll and pitch, and the motion compensation, go into each frame's ``cam_to_ego``
  (``Session.frame_cam_to_ego``; :func:`vvloc.data.frame.ego_frames`).
* Without a camera's ``*_distortion_lut.bin`` its images are used distorted, with a warning.
* Images of different native sizes are resized to ``image_size`` (default: the first camera's),
  with K adjusted exactly.
"""

from __future__ import annotations

import csv
import os
import re
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vvloc._checks import flag
from vvloc.data._remap import remap_bilinear, resize_rgb
from vvloc.data.bayer import demosaic_bilinear
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
    interpolate_rows,
    load_raw,
    nearest_within,
)
from vvloc.data.heading import heading_warning
from vvloc.data.vvloc_format import DatasetFormatError

DEFAULT_CAMERAS = ("stereo_centre", "mono_left", "mono_rear", "mono_right")
# camera name → (image folder, timestamps file, model name, extrinsics name, Bayer pattern)
CAMERA_SPECS = {
    "stereo_centre": ("stereo/centre", "stereo.timestamps", "stereo_narrow_left", "stereo", "gbrg"),
    "mono_left": ("mono_left", "mono_left.timestamps", "mono_left", "mono_left", "rggb"),
    "mono_right": ("mono_right", "mono_right.timestamps", "mono_right", "mono_right", "rggb"),
    "mono_rear": ("mono_rear", "mono_rear.timestamps", "mono_rear", "mono_rear", "rggb"),
}
INS_COLUMNS = ("timestamp", "northing", "easting", "down", "roll", "pitch", "yaw")
INS_GOOD = "INS_SOLUTION_GOOD"


def read_timestamps(path: Path) -> np.ndarray:
    """(N,) int64 microsecond timestamps of a ``.timestamps`` file ("utime chunk" per line)."""
    if not path.is_file():
        raise DatasetFormatError(f"{path}: timestamps file missing")
    out = []
    for line, text in enumerate(path.read_text().splitlines(), start=1):
        parts = text.split()
        if not parts:
            continue
        try:
            out.append(int(parts[0]))
        except ValueError as e:
            raise DatasetFormatError(f"{path}, line {line}: malformed timestamp {text!r}") from e
    stamps = np.array(sorted(out), dtype=np.int64)
    repeated = np.unique(stamps[1:][np.diff(stamps) == 0])
    if len(repeated):
        raise DatasetFormatError(
            f"{path}: timestamps listed more than once: {repeated[:5].tolist()}"
            + (f" and {len(repeated) - 5} more" if len(repeated) > 5 else "")
            + " (one image per timestamp; remove the repeated lines)"
        )
    return stamps


def read_ins(path: Path, *, good_only: bool = True) -> np.ndarray:
    """(N, 7) float64 rows timestamp, northing, easting, down, roll, pitch, yaw, sorted by time.

    With ``good_only``, rows whose ``ins_status`` is not ``INS_SOLUTION_GOOD`` are dropped (a
    file without that column keeps every row). ``DatasetFormatError`` naming the file when no
    row is left (an empty or truncated file, an INS that never aligned).
    """
    if not path.is_file():
        raise DatasetFormatError(f"{path}: INS file missing")
    rows = []
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in INS_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise DatasetFormatError(f"{path}, line 1: header lacks columns {missing}")
        has_status = "ins_status" in (reader.fieldnames or [])
        for row in reader:
            if good_only and has_status and (row["ins_status"] or "").strip() != INS_GOOD:
                continue
            try:
                rows.append([float(row[c]) for c in INS_COLUMNS])
            except (TypeError, ValueError) as e:
                raise DatasetFormatError(
                    f"{path}, line {reader.line_num}: malformed row: {e}"
                ) from e
    if not rows:  # a truncated download, or an INS that never aligned
        which = f" with ins_status {INS_GOOD}" if good_only and has_status else ""
        raise DatasetFormatError(f"{path}: no INS rows{which}")
    arr = np.array(rows, dtype=np.float64).reshape(-1, 7)
    return arr[np.argsort(arr[:, 0], kind="stable")]


def read_model(models_dir: Path, model: str) -> tuple[np.ndarray, np.ndarray, Path | None]:
    """K (3, 3), G_camera_image (4, 4) and the LUT path (or None) of a RobotCar camera model."""
    path = models_dir / f"{model}.txt"
    if not path.is_file():
        raise DatasetFormatError(f"{path}: camera model missing")
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    try:
        fx, fy, cx, cy = (float(v) for v in lines[0])
        G = np.array([[float(v) for v in ln] for ln in lines[1:5]], dtype=np.float64)
    except (ValueError, IndexError) as e:
        raise DatasetFormatError(f"{path}: expected 'fx fy cx cy' then a 4x4 matrix: {e}") from e
    if G.shape != (4, 4):
        raise DatasetFormatError(f"{path}: G_camera_image must be 4x4, got {G.shape}")
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    lut = models_dir / f"{model}_distortion_lut.bin"
    return K, G, lut if lut.is_file() else None


def read_extrinsics(extrinsics_dir: Path, sensor: str, *, required: bool = True) -> np.ndarray:
    """The 4×4 transform of an extrinsics file as written (identity if optional and missing).

    Which way it maps depends on the sensor (module docstring): ``ins.txt`` is the INS in the
    vehicle frame, a camera's file the vehicle in the camera frame.
    """
    path = extrinsics_dir / f"{sensor}.txt"
    if not path.is_file():
        if required:
            raise DatasetFormatError(f"{path}: extrinsics missing")
        return np.eye(4)
    try:
        vals = [float(v) for v in re.split(r"[,\s]+", path.read_text().strip()) if v]
    except ValueError as e:
        raise DatasetFormatError(f"{path}: malformed extrinsics: {e}") from e
    if len(vals) != 6:
        raise DatasetFormatError(f"{path}: expected 'x y z roll pitch yaw', got {len(vals)} values")
    return euler_to_matrix(*vals)


def read_lut(path: Path, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Source (u, v) float32 maps (height, width) of a RobotCar undistortion LUT."""
    lut = np.fromfile(path, dtype=np.float64)
    if lut.size != 2 * width * height:
        raise DatasetFormatError(f"{path}: {lut.size} values, expected 2x{width}x{height}")
    lut = lut.reshape(2, height, width).astype(np.float32)
    return lut[0], lut[1]


class OxfordSession(Session):
    """One RobotCar session: demosaiced, undistorted (when a LUT is present) and resized lazily."""

    def __init__(
        self,
        name: str,
        paths: list[list[Path]],
        patterns: list[str],
        luts: list[tuple[np.ndarray, np.ndarray] | None],
        cameras: Sequence[Camera],
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
        self._paths = paths
        self._patterns = patterns
        self._luts = luts

    def _load_images(self, index: int) -> np.ndarray:
        out = []
        parts = zip(self.cameras, self._paths, self._patterns, self._luts, strict=True)
        for cam, paths, pattern, lut in parts:
            try:
                raw = load_raw(paths[index])  # 8-bit only: a 16-bit image is refused, not cut
            except ValueError as e:
                raise DatasetFormatError(str(e)) from e
            img = demosaic_bilinear(raw, pattern) if raw.ndim == 2 else raw
            img = np.asarray(img, dtype=np.uint8)
            if lut is not None:
                img = remap_bilinear(img, *lut)
            out.append(resize_rgb(img, cam.width, cam.height).transpose(2, 0, 1))
        return np.ascontiguousarray(np.stack(out))


def _world_vehicle(rows: np.ndarray, ins_to_flu: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """(N, 4, 4) vehicle (FLU) → world (ENU, re-centred on ``origin``) of (N, 6) INS rows
    (northing, easting, down m; roll, pitch, yaw rad)."""
    T = np.stack([NED_TO_ENU @ euler_to_matrix(*r) @ ins_to_flu for r in rows]).reshape(-1, 4, 4)
    T[:, :3, 3] -= origin
    return T


#: The INS angle columns (roll, pitch, yaw) of ``read_ins``'s rows after the time column.
_INS_ANGLES = (3, 4, 5)


@dataclass
class _SessionReader:
    """How :func:`open_oxford` reads each session folder: its options, checked, and what the
    sessions share (undistortion LUTs read once, one warning per camera without a LUT)."""

    cameras: tuple[str, ...]
    models: Path
    extrinsics: Path
    image_size: tuple[int, int] | None
    tolerance_us: int
    height: float  # ego_height, m
    ins_good_only: bool
    level: bool
    motion_compensation: bool
    ins_to_flu: np.ndarray  # (4, 4) INS → vehicle (FLU)
    luts: dict[tuple[Path, int, int], tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    warned: set[str] = field(default_factory=set)

    def join_cameras(
        self, sdir: Path
    ) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray, dict[str, int]]:
        """The frames of ``sdir``: each camera's timestamps with an image file (C lists of
        int64 µs), its image nearest each first-camera timestamp (C index arrays), which of
        those timestamps have every camera within ``tolerance_us`` ((N,) bool), and how many
        were left out, under the first reason each fails."""
        cameras, tol = self.cameras, self.tolerance_us
        listed = [read_timestamps(sdir / CAMERA_SPECS[c][1]) for c in cameras]
        stamps = [
            s[[(sdir / CAMERA_SPECS[c][0] / f"{t}.png").is_file() for t in s]]
            for c, s in zip(cameras, listed, strict=True)
        ]
        if len(stamps[0]) == 0:
            raise DatasetFormatError(f"{sdir}: no images of {cameras[0]} listed and present")
        ref = stamps[0]
        # each frame left out is counted under the first reason it fails, in this order
        first = f"listed in {CAMERA_SPECS[cameras[0]][1]} but no image file"
        left_out = {first: len(listed[0]) - len(ref)}
        keep = np.ones(len(ref), dtype=bool)
        picks = []
        far = 0  # frames with no image of some camera listed within tolerance_us
        for c, s, all_listed in zip(cameras, stamps, listed, strict=True):
            p, ok = nearest_within(s, ref, tol)
            picks.append(p)
            _, near_listed = nearest_within(all_listed, ref, tol)
            absent = keep & ~ok & near_listed  # listed near in time, but its file is missing
            key = f"listed in {CAMERA_SPECS[c][1]} but no image file"
            left_out[key] = left_out.get(key, 0) + int(absent.sum())
            far += int((keep & ~ok & ~near_listed).sum())
            keep &= ok
        left_out[f"no image of every camera within tolerance_us={tol}"] = far
        return stamps, picks, keep, left_out

    def join_ins(
        self,
        sdir: Path,
        stamps: list[np.ndarray],
        picks: list[np.ndarray],
        keep: np.ndarray,
        left_out: dict[str, int],
    ) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
        """The INS rows (N, 6) at the first camera's timestamps and, with
        ``motion_compensation``, at each camera's own exposure (C arrays (N, 6); else empty),
        and ``keep`` narrowed to the frames the INS covers (``left_out`` counts the rest)."""
        tol = self.tolerance_us
        ins = read_ins(sdir / "gps" / "ins.csv", good_only=self.ins_good_only)
        ins_t = ins[:, 0].astype(np.int64)
        ins_at, ok = interpolate_rows(ins_t, ins[:, 1:7], stamps[0], tol, angle_columns=_INS_ANGLES)
        # the rows read_ins kept: INS_SOLUTION_GOOD ones with ins_good_only
        left_out[f"no INS row within tolerance_us={tol}"] = int((keep & ~ok).sum())
        keep = keep & ok
        # the INS at each camera's own exposure (motion compensation); a camera without any
        # image has joined no frame (keep is all False)
        ins_cams = []
        if self.motion_compensation and keep.any():
            covered = np.ones(len(keep), dtype=bool)
            for t_cam in (s[p] for s, p in zip(stamps, picks, strict=True)):
                row, ok = interpolate_rows(
                    ins_t, ins[:, 1:7], t_cam, tol, angle_columns=_INS_ANGLES
                )
                ins_cams.append(row)
                covered &= ok
            left_out["no INS row near some camera's exposure (motion_compensation)"] = int(
                (keep & ~covered).sum()
            )
            keep &= covered
        return ins_at, ins_cams, keep

    def rig(
        self, first_images: list[Path]
    ) -> tuple[list[Camera], list[tuple[np.ndarray, np.ndarray] | None], list[str]]:
        """The cameras (resized to ``image_size``; ego origin lowered by ``height``), their
        undistortion LUTs (None without one, warned once a camera) and Bayer patterns, each
        camera's native size read from its image ``first_images[c]``."""
        from PIL import Image

        cams: list[Camera] = []
        luts: list[tuple[np.ndarray, np.ndarray] | None] = []
        patterns: list[str] = []
        for c, image in zip(self.cameras, first_images, strict=True):
            _, _, model, sensor, pattern = CAMERA_SPECS[c]
            K, G, lut_path = read_model(self.models, model)
            try:
                with Image.open(image) as im:
                    w, h = im.size
            except (OSError, SyntaxError) as e:  # FileNotFoundError, PIL's decoder errors
                raise DatasetFormatError(f"{image}: not a readable image ({e})") from None
            T_camera_vehicle = read_extrinsics(self.extrinsics, sensor, required=sensor != "stereo")
            cam_to_ego = FRD_TO_FLU @ np.linalg.inv(T_camera_vehicle) @ G
            cams.append(Camera(c, w, h, K, cam_to_ego).with_ego_origin_lowered(self.height))
            if lut_path is not None:
                if (lut_path, w, h) not in self.luts:  # one LUT per camera, every session
                    self.luts[(lut_path, w, h)] = read_lut(lut_path, w, h)
                luts.append(self.luts[(lut_path, w, h)])
            else:
                luts.append(None)
                if c not in self.warned:
                    self.warned.add(c)
                    warnings.warn(
                        f"{self.models}: no {model}_distortion_lut.bin; {c}'s images are used "
                        "distorted, which its pinhole K does not describe",
                        stacklevel=4,  # open_oxford's caller
                    )
            patterns.append(pattern)
        size = self.image_size or (cams[0].width, cams[0].height)
        return [cam.resized(*size) for cam in cams], luts, patterns

    def read(self, sdir: Path, origin: np.ndarray | None) -> tuple[OxfordSession, np.ndarray]:
        """Session folder ``sdir`` in the world frame re-centred on ``origin`` (ENU, m), and
        that origin: None takes this session's first ego origin (the ground under the roof)."""
        stamps, picks, keep, left_out = self.join_cameras(sdir)
        ins_at, ins_cams, keep = self.join_ins(sdir, stamps, picks, keep, left_out)
        if not keep.any():
            raise DatasetFormatError(
                f"{sdir}: no frame has an image of every camera {list(self.cameras)} and an INS "
                f"row within tolerance_us={self.tolerance_us}"
            )
        paths = [
            [sdir / CAMERA_SPECS[c][0] / f"{t}.png" for t in s[p[keep]]]
            for c, s, p in zip(self.cameras, stamps, picks, strict=True)
        ]
        cams, luts, patterns = self.rig([ps[0] for ps in paths])
        if origin is None:
            T0 = NED_TO_ENU @ euler_to_matrix(*ins_at[keep][0]) @ self.ins_to_flu
            origin = T0[:3, 3] - self.height * T0[:3, 2]
        at_cams = None
        if self.motion_compensation:
            at_cams = np.stack(
                [_world_vehicle(rows[keep], self.ins_to_flu, origin) for rows in ins_cams], axis=1
            )
        poses, zs, frame_cam_to_ego = ego_frames(
            _world_vehicle(ins_at[keep], self.ins_to_flu, origin),
            cams,
            height=self.height,
            level=self.level,
            world_body_at_cameras=at_cams,
        )
        session = OxfordSession(
            sdir.name,
            paths,
            patterns,
            luts,
            cams,
            stamps[0][keep],
            poses,
            zs,
            frame_cam_to_ego,
            left_out=left_out,
        )
        return session, origin


def _sessions_in(root: Path) -> list[Path]:
    return sorted(d for d in root.iterdir() if d.is_dir() and (d / "gps" / "ins.csv").is_file())


def is_oxford(root: Path) -> bool:
    """Whether ``root`` looks like an Oxford RobotCar raw folder."""
    return root.is_dir() and bool(_sessions_in(root))


def open_oxford(
    root: str | os.PathLike[str],
    *,
    cameras: Sequence[str] = DEFAULT_CAMERAS,
    models_dir: str | os.PathLike[str] | None = None,
    extrinsics_dir: str | os.PathLike[str] | None = None,
    image_size: tuple[int, int] | None = None,
    tolerance_us: int = 50_000,
    ego_height: float = 0.0,
    ins_good_only: bool = True,
    level: bool = True,
    motion_compensation: bool = True,
    sessions: Sequence[str] | None = None,
) -> Dataset:
    """Open an Oxford RobotCar raw folder as a :class:`Dataset` (one session per folder).

    Args:
        root: folder holding the session folders (see the module docstring for the layout).
        cameras: names from ``CAMERA_SPECS``, in image order (default front, left, rear, right).
        models_dir, extrinsics_dir: the SDK's folders (default ``<root>/models``,
            ``<root>/extrinsics``).
        image_size: (width, height) for every camera; default the first camera's native size.
        tolerance_us: largest time gap joined between cameras and to the INS, microseconds.
        ego_height: height of the stereo camera (the vehicle frame's origin) above the ground,
            metres: vvloc's ego origin is moved down there (cameras rise by it, ``Frame.z``
            drops by it).
        ins_good_only: use only INS rows whose ``ins_status`` is ``INS_SOLUTION_GOOD``.
        level: make each frame's ego frame level (:func:`vvloc.data.frame.ego_frames`): the
            car's roll and pitch go into that frame's ``cam_to_ego``
            (``Session.frame_cam_to_ego``). False keeps the tilting vehicle frame.
        motion_compensation: pose each camera at its own exposure (the INS interpolated at its
            image's timestamp) in the ego frame at the first camera's time, so that a camera
            that fired 30 ms apart at 14 m/s is placed 0.4 m away from where the rig puts it.
            A frame is kept only when the INS covers every camera's time within
            ``tolerance_us``. False places every camera where the rig says.
        sessions: the session folders to read (default every one found; ``KeyError`` naming
            them for one the folder lacks). The folder's first session (in name order) is read
            too, chosen or not: its first pose is the world origin of every session, so that
            sessions read apart with the same options share one world frame.
    """
    root = Path(root)
    models = Path(models_dir) if models_dir is not None else root / "models"
    extr = Path(extrinsics_dir) if extrinsics_dir is not None else root / "extrinsics"
    image_size, tolerance_us = check_reader_options(cameras, image_size, tolerance_us)
    unknown = [c for c in cameras if c not in CAMERA_SPECS]
    if unknown:
        raise ValueError(
            f"cameras: expected names from {sorted(CAMERA_SPECS)}, got {list(cameras)}"
        )
    for name, value in (
        ("ins_good_only", ins_good_only),
        ("level", level),
        ("motion_compensation", motion_compensation),
    ):
        flag(value, name)
    height = float(ego_height)
    if not np.isfinite(height):
        raise ValueError(f"ego_height: expected a finite height in metres, got {ego_height!r}")
    dirs = _sessions_in(root)
    if not dirs:
        raise DatasetFormatError(f"{root}: no <session>/gps/ins.csv found (RobotCar layout)")
    wanted = chosen_sessions(sessions, [d.name for d in dirs], root)
    T_vehicle_ins = read_extrinsics(extr, "ins")
    reader = _SessionReader(
        cameras=tuple(cameras),
        models=models,
        extrinsics=extr,
        image_size=image_size,
        tolerance_us=tolerance_us,
        height=height,
        ins_good_only=bool(ins_good_only),
        level=bool(level),
        motion_compensation=bool(motion_compensation),
        ins_to_flu=np.linalg.inv(T_vehicle_ins) @ FRD_TO_FLU,  # INS → vehicle (FLU)
    )
    read: dict[str, Session] = {}
    rig: Sequence[Camera] = []
    origin: np.ndarray | None = None
    origin_only: str | None = None  # the unchosen first session, read for the origin
    try:
        for sdir in dirs:
            chosen = wanted is None or sdir.name in wanted
            if not chosen and origin is not None:
                continue  # the world origin is the first session's, chosen or not
            origin_only = None if chosen else sdir.name
            session, origin = reader.read(sdir, origin)
            if not chosen:
                continue
            note = heading_warning(sdir.name, session.poses)
            if note is not None:
                warnings.warn(note, stacklevel=2)
            read[sdir.name] = session
            rig = rig or session.cameras
    except DatasetFormatError as e:
        if origin_only is None:
            raise
        raise DatasetFormatError(
            f"{e} ({origin_only} is the folder's first session, read only for the world "
            "origin, which its first pose sets: mend it, or move it out of the folder and the "
            "origin moves with it)"
        ) from None
    meta = {"origin_enu": [float(v) for v in (origin if origin is not None else np.zeros(3))]}
    return Dataset(root, list(rig), read, meta=meta)
