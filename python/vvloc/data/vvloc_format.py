"""The vvloc dataset format: writer and lazy, validating reader (see docs/dataset-format.md).

Layout::

    <root>/rig.json                                  {"format": "vvloc", "version": 1, "cameras"}
    <root>/sessions/<name>/poses.csv                 timestamp,x,y,z,yaw,floor  (one row per frame)
    <root>/sessions/<name>/<camera>/<timestamp>.png  RGB, the camera's image size
    <root>/sessions/<name>/session.json              optional metadata (ignored by the reader)
    <root>/sessions/<name>/cam_to_ego.csv            optional per-frame extrinsics (see below)

``cam_to_ego.csv`` (optional) gives every frame its own camera → ego transforms, for real
vehicles that tilt or whose cameras fire apart (``Session.frame_cam_to_ego``): header
``timestamp,camera,m00,…,m23``, one row per frame and camera of the rig, the top three rows of
the 4×4 matrix row by row. Without it every frame has ``rig.json``'s.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import shutil
import stat
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from vvloc._checks import finite_float, flag
from vvloc._io import (
    FLOAT_TEXT,
    INT_TEXT,
    check_readable_file,
    list_entries,
    remove_stale_temps,
    stale_temps,
    symlink_loop,
    temp_tag,
)
from vvloc.data._remap import resize_rgb
from vvloc.data.frame import (
    RIGID,
    Camera,
    Dataset,
    Session,
    check_image_size,
    is_rigid,
    load_rgb,
    rigid_fault,
)
from vvloc.data.heading import heading_warning
from vvloc.data.rig import frame_extrinsics_warnings, rig_warnings

_log = logging.getLogger(__name__)

FORMAT_NAME = "vvloc"
FORMAT_VERSION = 1
POSES_HEADER = ("timestamp", "x", "y", "z", "yaw", "floor")
EXTRINSICS_FILE = "cam_to_ego.csv"
EXTRINSICS_HEADER = ("timestamp", "camera", *(f"m{r}{c}" for r in range(3) for c in range(4)))


class DatasetFormatError(ValueError):
    """A dataset on disk does not follow its format; the message names the file (and line)."""


# ------------------------------------------------------------------------------------------ reader
class VvlocSession(Session):
    """A session of a vvloc-format dataset; images are read from PNG on indexing."""

    def __init__(
        self,
        directory: Path,
        name: str,
        cameras: Sequence[Camera],
        rows: np.ndarray,
        frame_cam_to_ego: np.ndarray | None = None,
        native: Sequence[Camera] | None = None,
    ):
        self.directory = directory
        # the cameras as rig.json gives them (their PNGs' sizes); ``cameras`` may be resized
        self._native = list(cameras if native is None else native)
        super().__init__(
            name,
            cameras,
            timestamps=rows["timestamp"],
            poses=np.stack([rows["x"], rows["y"], rows["yaw"]], axis=1),
            z=rows["z"],
            floors=rows["floor"],
            frame_cam_to_ego=frame_cam_to_ego,
        )

    def image_path(self, index: int, camera: str) -> Path:
        """Path of the PNG of camera ``camera`` at frame ``index``."""
        return self.directory / camera / f"{int(self.timestamps[index])}.png"

    def _load_images(self, index: int) -> np.ndarray:
        out = []
        for cam, nat in zip(self.cameras, self._native, strict=True):
            path = self.image_path(index, cam.name)
            if not path.is_file():
                raise DatasetFormatError(f"{path}: image missing (frame {index})")
            try:
                img = load_rgb(path)
            except ValueError as e:
                raise DatasetFormatError(str(e)) from e
            if img.shape != (nat.height, nat.width, 3):
                raise DatasetFormatError(
                    f"{path}: image is {img.shape[1]}x{img.shape[0]}, "
                    f"rig.json says {nat.width}x{nat.height}"
                )
            if (cam.width, cam.height) != (nat.width, nat.height):  # open_vvloc's image_size
                img = resize_rgb(img, cam.width, cam.height)
            out.append(img.transpose(2, 0, 1))
        return np.ascontiguousarray(np.stack(out))


def rig_meta(root: str | os.PathLike[str]) -> dict[str, Any] | None:
    """The ``meta`` object of the dataset folder ``root``'s ``rig.json`` (what ``vvloc sim``
    or ``vvloc convert`` recorded); None when there is no ``rig.json`` that is a regular file
    (a named pipe would block the read for good), it is not JSON, or it has no such object."""
    rig = Path(root) / "rig.json"
    if not rig.is_file():
        return None
    try:
        meta = json.loads(rig.read_text(encoding="utf-8-sig")).get("meta")
    except (OSError, ValueError, AttributeError, RecursionError):  # not a vvloc rig.json
        return None
    return meta if isinstance(meta, dict) else None


def read_rig(path: Path, *, one_size: bool = True) -> tuple[list[Camera], dict[str, Any]]:
    """Read ``rig.json``: the cameras and the whole document. ``one_size``: refuse cameras of
    different image sizes (a Frame stacks them), unless the reader resizes them to one."""
    try:
        check_readable_file(path)  # a pipe would block the read for good
    except ValueError as e:
        raise DatasetFormatError(str(e)) from None
    try:
        doc = json.loads(path.read_text(encoding="utf-8-sig"))  # a byte-order mark too
    except (OSError, ValueError, RecursionError) as e:  # JSON, UTF-8 errors; too deep nesting
        raise DatasetFormatError(f"{path}: cannot read rig: {e}") from e
    if not isinstance(doc, dict) or not isinstance(doc.get("cameras"), list) or not doc["cameras"]:
        raise DatasetFormatError(f"{path}: expected an object with a non-empty 'cameras' list")
    if doc.get("format", FORMAT_NAME) != FORMAT_NAME:
        raise DatasetFormatError(f"{path}: format {doc.get('format')!r} is not {FORMAT_NAME!r}")
    version = doc.get("version", FORMAT_VERSION)  # optional in a hand-written rig.json
    if type(version) is not int or version != FORMAT_VERSION:
        raise DatasetFormatError(
            f"{path}: version {version!r} is not supported (expected {FORMAT_VERSION}: a dataset "
            "written by a newer vvloc?)"
        )
    cameras = []
    for i, entry in enumerate(doc["cameras"]):
        try:
            cameras.append(Camera.from_json(entry))
        except (ValueError, TypeError) as e:
            raise DatasetFormatError(f"{path}: camera {i}: {e}") from e
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise DatasetFormatError(f"{path}: duplicate camera names {names}")
    if one_size and len({(c.width, c.height) for c in cameras}) > 1:
        sizes = [f"{c.name!r} {c.width}x{c.height}" for c in cameras]
        raise DatasetFormatError(
            f"{path}: cameras must share one image size (a Frame stacks them into one "
            f"(M, 3, H, W) array), got {', '.join(sizes)}: open it with "
            "open_dataset(..., image_size=(W, H)), which resizes every camera to one size and "
            "scales K, or write such a copy with vvloc convert --width W --height H"
        )
    return cameras, doc


_ROW_DTYPE = np.dtype(
    [("timestamp", np.int64), ("x", "f8"), ("y", "f8"), ("z", "f8"), ("yaw", "f8"), ("floor", "i8")]
)


def _number_texts(fields: Sequence[str], kinds: str) -> None:
    """``ValueError`` for a field that is not an integer (kind ``i``) or a number (``f``) as
    C writes them (:data:`vvloc._io.INT_TEXT`, :data:`vvloc._io.FLOAT_TEXT`)."""
    for text, kind in zip(fields, kinds, strict=False):
        pattern, what = (INT_TEXT, "an integer") if kind == "i" else (FLOAT_TEXT, "a number")
        if not pattern.fullmatch(text.strip()):
            raise ValueError(f"expected {what}, got {text!r:.60}")


#: The largest timestamp magnitude (microseconds) a dataset takes: 2^32 s, the year 2106.
#: Up to it a timestamp survives the float seconds of ``Frame.t`` (``ts / 1e6``) and
#: ``round(t·1e6)`` back exactly, by which the exported trajectories and keyframe tables name
#: frames (t's rounding errs by at most 2^-22 s, the product's by 0.25 µs below 2^52: under
#: half a microsecond); beyond it about 4 % of timestamps came back off by one. Nanoseconds
#: since 1970 (≈ 1.7e18) lie far above it.
MAX_TIMESTAMP_US = 2**32 * 10**6


def _check_timestamp(ts: int) -> None:
    """``ValueError`` for a timestamp beyond ±:data:`MAX_TIMESTAMP_US` (the writer's and the
    reader's one rule)."""
    if not -MAX_TIMESTAMP_US <= ts <= MAX_TIMESTAMP_US:
        raise ValueError(
            f"timestamp: {ts} µs lies beyond ±2^32 s (the year 2106); timestamps are "
            "microseconds since 1970 (nanoseconds? divide by 1000)"
        )


def read_poses(path: Path) -> np.ndarray:
    """Parse ``poses.csv`` into a structured array; errors name the file and the line."""
    if not path.is_file():
        raise DatasetFormatError(f"{path}: poses file missing")
    rows = []
    last: int | None = None
    for line, row in _csv_rows(path, POSES_HEADER):
        try:
            _number_texts(row[:6], "iffffi")  # what int() and float() take beyond C: 9_0, ١
            ts = int(row[0])
            x, y, z, yaw = (float(v) for v in row[1:5])
            floor = int(row[5])
        except ValueError as e:
            raise DatasetFormatError(f"{path}, line {line}: malformed row {row!r:.200}: {e}") from e
        for name, v in (("timestamp", ts), ("floor", floor)):
            if not -(2**63) <= v < 2**63:
                raise DatasetFormatError(
                    f"{path}, line {line}: {name} {row[0] if name == 'timestamp' else row[5]:.60} "
                    "is outside the int64 range"
                )
        try:
            _check_timestamp(ts)
        except ValueError as e:
            raise DatasetFormatError(f"{path}, line {line}: {e}") from None
        if not all(math.isfinite(v) for v in (x, y, z, yaw)):
            raise DatasetFormatError(f"{path}, line {line}: non-finite value in {row!r:.200}")
        if last is not None and ts <= last:
            raise DatasetFormatError(
                f"{path}, line {line}: timestamp {ts} does not follow the row before's {last} "
                "(rows in time order, each timestamp once: the order is the drive's, which "
                "the loop detector's temporal window and sequence check read)"
            )
        last = ts
        rows.append((ts, x, y, z, yaw, floor))
    return np.array(rows, dtype=_ROW_DTYPE)


def _has_control(name: str) -> bool:
    """Whether ``name`` holds a control character (C0, DEL or C1: line breaks, tabs, ...)."""
    return any(ord(c) < 32 or 127 <= ord(c) < 160 for c in name)


def _csv_rows(path: Path, header: tuple[str, ...]) -> Iterator[tuple[int, list[str]]]:
    """(line number, fields) of every non-blank row of a CSV file whose first line must be
    ``header`` and whose rows must have as many fields; errors name the file and the line (a
    file that is not UTF-8 text: the file and the byte)."""
    # utf-8-sig: a byte-order mark (Excel's "CSV UTF-8") is read as none
    with path.open(newline="", encoding="utf-8-sig") as f:
        reader = csv.reader(f)
        try:
            yield from _checked_rows(path, reader, header)
        except UnicodeDecodeError as e:
            raise DatasetFormatError(f"{path}: not UTF-8 text ({e})") from None
        except csv.Error as e:  # a field over the csv module's size limit, ...
            raise DatasetFormatError(f"{path}, line {reader.line_num}: {e}") from None


def _checked_rows(
    path: Path, reader: Any, header: tuple[str, ...]
) -> Iterator[tuple[int, list[str]]]:
    """:func:`_csv_rows` of an open ``csv.reader``."""
    first = next(reader, None)
    if first is None or tuple(h.strip() for h in first) != header:
        raise DatasetFormatError(f"{path}, line 1: header must be {','.join(header)}, got {first}")
    for row in reader:
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise DatasetFormatError(
                f"{path}, line {reader.line_num}: expected {len(header)} fields, got {len(row)}"
            )
        yield reader.line_num, row


def read_extrinsics(path: Path, timestamps: np.ndarray, cameras: Sequence[Camera]) -> np.ndarray:
    """Parse a session's ``cam_to_ego.csv`` into (N, M, 4, 4) float64, frames in the order of
    ``timestamps`` (N,), cameras in rig order. Every frame needs one row per camera, each a
    rigid transform (rotation orthonormal to 1e-6, determinant +1); errors name the file and
    the line."""
    names = [c.name for c in cameras]
    frame_of = {int(t): k for k, t in enumerate(timestamps)}
    cam_of = {n: m for m, n in enumerate(names)}
    out = np.full((len(timestamps), len(names), 4, 4), np.nan)
    out[..., 3, :] = (0.0, 0.0, 0.0, 1.0)
    seen = np.zeros((len(timestamps), len(names)), dtype=bool)
    for line, row in _csv_rows(path, EXTRINSICS_HEADER):
        try:
            _number_texts([row[0], *row[2:]], "i" + "f" * len(row[2:]))
            ts = int(row[0])
            vals = np.array([float(v) for v in row[2:]], dtype=np.float64).reshape(3, 4)
        except ValueError as e:
            raise DatasetFormatError(f"{path}, line {line}: malformed row: {e}") from e
        if ts not in frame_of:
            raise DatasetFormatError(f"{path}, line {line}: timestamp {ts} is not in poses.csv")
        if row[1] not in cam_of:
            raise DatasetFormatError(
                f"{path}, line {line}: camera {row[1]!r} is not in rig.json (cameras: {names})"
            )
        k, m = frame_of[ts], cam_of[row[1]]
        if seen[k, m]:
            raise DatasetFormatError(
                f"{path}, line {line}: a second row for timestamp {ts}, camera {row[1]!r}"
            )
        out[k, m, :3] = vals
        if not is_rigid(out[k, m]):
            raise DatasetFormatError(
                f"{path}, line {line}: not a {RIGID}: {rigid_fault(out[k, m])}"
            )
        seen[k, m] = True
    if not seen.all():
        k, m = np.argwhere(~seen)[0]
        raise DatasetFormatError(
            f"{path}: no row for timestamp {int(timestamps[k])}, camera {names[m]!r} "
            "(every frame needs one row per camera of the rig)"
        )
    return out


#: Opening a dataset warns about a session whose yaw keeps a steady offset of more than this
#: (degrees) from its direction of travel: a yaw convention other than the format's.
CONVENTION_OFFSET_DEG = 5.0


def yaw_warnings(name: str, rows: np.ndarray) -> list[str]:
    """Warnings about a session's yaw convention (``poses.csv`` rows from :func:`read_poses`).

    A yaw beyond ±2π is most likely in degrees; a yaw that reads as mirrored (a compass
    heading, clockwise from north; a clockwise yaw) or keeps a steady offset of more than
    :data:`CONVENTION_OFFSET_DEG` from the direction of travel
    (:func:`vvloc.data.heading.heading_warning`) is in another convention. Each turns every
    relative pose. (The NCLT and
    RobotCar readers warn from 0.5° when they convert; a dataset keeps such an offset, and
    opening it does not warn again.)"""
    notes = []
    yaw = rows["yaw"]
    if len(yaw) and float(np.abs(yaw).max()) > 2 * math.pi:
        notes.append(
            f"session {name}: yaw reaches {float(np.abs(yaw).max()):.1f} in poses.csv; vvloc "
            "reads yaw in radians (counter-clockwise from the world's x axis): degrees?"
        )
    poses = np.stack([rows["x"], rows["y"], yaw], axis=1)
    note = heading_warning(name, poses, limit_deg=CONVENTION_OFFSET_DEG)
    if note is not None:
        notes.append(
            f"{note}; in the vvloc format yaw is radians counter-clockwise from the world's x "
            "axis (docs/dataset-format.md)"
        )
    return notes


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _check_png_size(path: Path, cam: Camera) -> None:
    """``DatasetFormatError`` when the PNG at ``path`` declares another size than ``cam``'s
    (read from its IHDR header, 24 bytes); a file that is no PNG is left to the decoder, which
    names it when the frame is read."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except OSError:
        return  # unreadable: said with the reason when the frame is read
    if len(head) < 24 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        return
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if (width, height) != (cam.width, cam.height):
        raise DatasetFormatError(
            f"{path}: image is {width}x{height}, rig.json says {cam.width}x{cam.height} (the "
            "session's first frame)"
        )


def open_vvloc(root: str | os.PathLike[str], image_size: tuple[int, int] | None = None) -> Dataset:
    """Open a vvloc-format dataset lazily and validate its structure.

    ``image_size``: (width, height) pixels to resize every camera's images to as frames are
    read (``K`` scaled exactly, pixel-centre convention); None (default) keeps ``rig.json``'s
    size, which then must be one for all cameras. A rig of cameras of different sizes is read
    only with it.

    Reads ``rig.json`` and every ``poses.csv``, lists the image folders and reads the size in
    the PNG header of each session's first frame (no image is decoded).
    ``ds.meta`` is ``rig.json``'s optional ``meta`` object (``vvloc sim`` records its world:
    scene, seed, floors, floor_marking).
    Raises :class:`DatasetFormatError` (a ``ValueError``) naming the file and line for a malformed
    row, rows out of time order, a camera that is not a pinhole with a rigid ``cam_to_ego``,
    cameras of different image sizes, a camera folder that is not in the rig, a missing
    image, or a session whose first frame's PNGs are of another size than ``rig.json`` says.
    Warns (``UserWarning``) when a camera's extrinsics look wrong (another unit, axis
    convention or direction: :func:`vvloc.data.rig.rig_warnings`), when a session's
    ``cam_to_ego.csv`` gives a camera a mounting no rig of these cameras has (millimetres, a
    camera turned against the others: :func:`vvloc.data.rig.frame_extrinsics_warnings`) and
    when a session's yaw looks like degrees or another convention (:func:`yaw_warnings`).
    """
    root = Path(root)
    size = check_image_size(image_size)
    native, doc = read_rig(root / "rig.json", one_size=size is None)
    cameras = [
        c if size is None or (c.width, c.height) == size else c.resized(*size) for c in native
    ]
    for note in rig_warnings(cameras):
        warnings.warn(f"{root / 'rig.json'}: {note}", stacklevel=2)
    names = {c.name for c in cameras}
    sess_root = root / "sessions"
    if not sess_root.is_dir():
        raise DatasetFormatError(f"{sess_root}: sessions folder missing")
    sessions: dict[str, Session] = {}
    # hidden folders (.ipynb_checkpoints, ...) are no sessions: the writer names none so
    for d in sorted(p for p in sess_root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        if _has_control(d.name):  # a line break in a name would split the CSV rows vvloc writes
            raise DatasetFormatError(
                f"{d.parent / repr(d.name)}: a session folder name with a control character "
                "(a line break, tab, ...); rename the folder"
            )
        poses_path = d / "poses.csv"
        rows = read_poses(poses_path)
        for sub in sorted(p for p in d.iterdir() if p.is_dir() and not p.name.startswith(".")):
            if sub.name not in names:
                raise DatasetFormatError(
                    f"{sub}: camera {sub.name!r} is not in rig.json (cameras: {sorted(names)})"
                )
        for cam in native:
            cam_dir = d / cam.name
            present = set(os.listdir(cam_dir)) if cam_dir.is_dir() else set()
            for k, ts in enumerate(rows["timestamp"]):
                if f"{ts}.png" not in present:
                    raise DatasetFormatError(
                        f"{cam_dir / f'{ts}.png'}: image missing "
                        f"(listed in {poses_path}, line {k + 2})"
                    )
            if len(rows["timestamp"]):  # a whole session at another size: said now, not
                # when training reads its frames (the PNG's header only, no decoding)
                _check_png_size(cam_dir / f"{rows['timestamp'][0]}.png", cam)
        extrinsics = None
        if (d / EXTRINSICS_FILE).is_file():
            extrinsics = read_extrinsics(d / EXTRINSICS_FILE, rows["timestamp"], cameras)
            for note in frame_extrinsics_warnings(cameras, rows["timestamp"], extrinsics):
                warnings.warn(f"{d / EXTRINSICS_FILE}: {note}", stacklevel=2)
        for note in yaw_warnings(d.name, rows):
            warnings.warn(note, stacklevel=2)
        sessions[d.name] = VvlocSession(d, d.name, cameras, rows, extrinsics, native)
    meta = doc.get("meta")
    return Dataset(root, cameras, sessions, meta=meta if isinstance(meta, dict) else None)


# ------------------------------------------------------------------------------------------ writer
def _whole(value: Any, name: str) -> int:
    """``value`` as an int when it is a whole number (an int, or a float without a fraction),
    else ``TypeError``/``ValueError`` naming ``name``: a fraction is never cut silently."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name}: expected an int, got {type(value).__name__}")
    if isinstance(value, (float, np.floating)) and not float(value).is_integer():
        raise ValueError(f"{name}: expected a whole number, got {value!r}")  # nan, inf too
    whole = int(value)
    if not -(2**63) <= whole < 2**63:  # what the readers' int64 columns hold
        raise ValueError(f"{name}: expected a whole number within int64, got {value!r}")
    return whole


class SessionWriter:
    """Appends frames to one session of a :class:`DatasetWriter` (use via ``add_session``)."""

    def __init__(self, directory: Path, cameras: Sequence[Camera], meta: dict[str, Any] | None):
        self.directory = directory
        self.cameras = tuple(cameras)
        try:  # before any folder is made: a meta JSON cannot hold leaves nothing behind
            meta_text = None if meta is None else json.dumps(meta, indent=2)
        except (TypeError, ValueError) as e:
            raise TypeError(f"meta: expected plain JSON values (str, int, float, ...): {e}") from e
        directory.mkdir(parents=True)
        try:
            for cam in self.cameras:
                (directory / cam.name).mkdir()
            if meta_text is not None:
                (directory / "session.json").write_text(meta_text)
            self._file = (directory / "poses.csv").open("w", newline="")
        except BaseException:  # e.g. a full disk: the session is not left half made
            shutil.rmtree(directory, ignore_errors=True)
            raise
        self._csv = csv.writer(self._file, lineterminator="\n")
        self._csv.writerow(POSES_HEADER)
        self._last_ts: int | None = None
        self._extrinsics: Any = None  # the cam_to_ego.csv writer once a frame brings its own
        self._extrinsics_file: Any = None
        self.count = 0

    def add(
        self,
        timestamp: int,
        pose: Sequence[float] | np.ndarray,
        images: np.ndarray,
        *,
        z: float = 0.0,
        floor: int = 0,
        cam_to_ego: np.ndarray | None = None,
    ) -> None:
        """Append one frame.

        Args:
            timestamp: microseconds, strictly increasing within the session.
            pose: (x, y, yaw) metres, radians, world frame.
            images: (M, 3, H, W) uint8, cameras in rig order.
            z: height of the ego origin, metres.
            floor: storey index.
            cam_to_ego: (M, 4, 4) camera → ego transforms of this frame (rigid, metres), written
                to ``cam_to_ego.csv``, or None for the rig's. Either every frame of a session
                gives them or none does.
        """
        from PIL import Image

        ts = _whole(timestamp, "timestamp")
        _check_timestamp(ts)
        if self._last_ts is not None and ts <= self._last_ts:
            raise ValueError(f"timestamp: must increase, got {ts} after {self._last_ts}")
        floor = _whole(floor, "floor")
        try:
            p = None if isinstance(pose, str) else np.asarray(pose, dtype=np.float64)
        except (TypeError, ValueError):
            p = None
        if p is None or p.shape != (3,) or not np.isfinite(p).all():
            raise ValueError(f"pose: expected 3 finite numbers (x, y, yaw) m, m, rad, got {pose!r}")
        x, y, yaw = (float(v) for v in p)
        z = finite_float(z, "z")  # metres
        m = len(self.cameras)
        h, w = self.cameras[0].height, self.cameras[0].width
        if not isinstance(images, np.ndarray):
            raise TypeError(
                f"images: expected a uint8 numpy array ({m}, 3, {h}, {w}), got "
                f"{type(images).__name__}"
            )
        if images.dtype != np.uint8 or images.shape != (m, 3, h, w):
            raise ValueError(
                f"images: expected uint8 ({m}, 3, {h}, {w}), got {images.dtype} {images.shape}"
            )
        rows = self._extrinsic_rows(ts, cam_to_ego)
        for cam, img in zip(self.cameras, images, strict=True):
            Image.fromarray(np.ascontiguousarray(img.transpose(1, 2, 0))).save(
                self.directory / cam.name / f"{ts}.png", compress_level=1
            )
        self._csv.writerow([ts, repr(x), repr(y), repr(float(z)), repr(yaw), int(floor)])
        if rows:
            if self._extrinsics is None:
                self._extrinsics_file = (self.directory / EXTRINSICS_FILE).open("w", newline="")
                self._extrinsics = csv.writer(self._extrinsics_file, lineterminator="\n")
                self._extrinsics.writerow(EXTRINSICS_HEADER)
            self._extrinsics.writerows(rows)
        self._last_ts = ts
        self.count += 1

    def _extrinsic_rows(self, ts: int, cam_to_ego: np.ndarray | None) -> list[list[Any]]:
        """The ``cam_to_ego.csv`` rows of one frame (checked before anything is written)."""
        per_frame = cam_to_ego is not None
        if self.count and per_frame != (self._extrinsics is not None):
            had = "its own cam_to_ego" if self._extrinsics is not None else "the rig's cam_to_ego"
            raise ValueError(
                f"cam_to_ego: every frame of a session gives its own or none does; the first "
                f"frame of this session had {had}"
            )
        if cam_to_ego is None:
            return []
        m = len(self.cameras)
        T = np.asarray(cam_to_ego)
        if T.shape != (m, 4, 4) or not np.issubdtype(T.dtype, np.floating):
            raise ValueError(f"cam_to_ego: expected float ({m}, 4, 4), got {T.dtype} {T.shape}")
        T = T.astype(np.float64)
        if not is_rigid(T):
            raise ValueError(f"cam_to_ego: expected finite rigid transforms ({RIGID}s)")
        return [
            [ts, cam.name, *(repr(float(v)) for v in T[k, :3].ravel())]
            for k, cam in enumerate(self.cameras)
        ]

    def close(self) -> None:
        """Flush ``poses.csv`` (and ``cam_to_ego.csv``)."""
        if not self._file.closed:
            self._file.close()
        if self._extrinsics_file is not None and not self._extrinsics_file.closed:
            self._extrinsics_file.close()


def _check_replaceable(root: Path) -> None:
    """Refuse to let ``overwrite`` replace ``root`` unless it holds a vvloc dataset and nothing
    else: a ``rig.json`` of this format beside ``sessions/``. Replacing removes the whole
    folder, so anything a user keeps there (notes, runs, another tool's files) would go too."""
    rig = root / "rig.json"
    try:
        doc = json.loads(rig.read_text(encoding="utf-8-sig")) if rig.is_file() else None
    except (OSError, UnicodeDecodeError, ValueError):
        doc = None
    if not (isinstance(doc, dict) and doc.get("format") == FORMAT_NAME):
        why = "no rig.json" if not rig.is_file() else "its rig.json is not a vvloc rig"
        raise FileExistsError(
            f"{root} is not a vvloc dataset ({why}): overwrite replaces only a dataset; "
            "choose another folder or empty this one"
        )
    others = sorted(p.name for p in root.iterdir() if p.name not in ("rig.json", "sessions"))
    if others:
        raise FileExistsError(
            f"{root} holds more than a vvloc dataset ({list_entries(others)}): overwrite would "
            "delete them with it; move them out or choose another folder"
        )


def check_dataset_target(root: str | os.PathLike[str], overwrite: bool) -> None:
    """Refuse ``root`` as the folder of a dataset to write, before any work: the working
    directory or a folder above it (``ValueError``), a file, or a non-empty folder without
    ``overwrite`` (``FileExistsError``), or one with ``overwrite`` that is not a vvloc dataset
    (:func:`_check_replaceable`). What a writer of ``root`` killed outright left is recovered
    first (:func:`recover_dataset_target`)."""
    flag(overwrite, "overwrite")  # "no" is truthy: it replaced a dataset
    root = Path(root)
    loop = symlink_loop(root)
    if loop:  # found only when the finished dataset was renamed into place
        raise FileExistsError(f"{loop}; expected a folder for the dataset")
    target = Path(os.path.realpath(root))
    cwd = Path.cwd().resolve()
    if target == cwd or target in cwd.parents:
        raise ValueError(
            f"{root}: is the working directory or a folder above it; write the "
            "dataset to a folder of its own (e.g. data/synth)"
        )
    recover_dataset_target(target)  # before judging it: a dataset may go back into place
    if root.exists() and not root.is_dir():
        raise FileExistsError(f"{root} exists and is a file, not a dataset folder")
    if root.is_dir() and any(root.iterdir()):
        if not overwrite:
            raise FileExistsError(
                f"{root} exists and is not empty (--overwrite, or overwrite=True in "
                "Python, replaces a dataset there)"
            )
        _check_replaceable(root)


def recover_dataset_target(target: Path) -> None:
    """Undo what a :class:`DatasetWriter` of ``target`` (a real path) that was killed outright
    left beside it (SIGKILL, the out-of-memory killer: no handler runs;
    :func:`vvloc._io.stale_temps`): its half-written hidden ``.partial-`` folder is removed, and
    the dataset it had renamed aside to replace it (a hidden ``.replaced-`` folder) is put back
    when the new one never took its place, and removed when it did. Each is a logged warning."""
    remove_stale_temps(target.parent, f".{target.name}.partial-")
    if not os.path.lexists(target):  # stopped between the two renames: the old dataset goes back
        for old in stale_temps(target.parent, f".{target.name}.replaced-")[:1]:
            os.replace(old, target)
            _log.warning("put back %s, which a stopped vvloc process had moved to %s", target, old)
    # the new dataset took its place: the old one's leftovers
    remove_stale_temps(target.parent, f".{target.name}.replaced-")


class DatasetWriter:
    """Writes a vvloc-format dataset atomically: into a hidden temporary folder beside ``root``,
    renamed to ``root`` by :meth:`close`; on an exception inside ``with`` nothing is left behind.
    With ``overwrite``, the dataset at ``root`` stays whole until the new one has taken its
    place (it is renamed aside, then deleted).

    Example::

        with DatasetWriter("data/synth", cameras) as w:
            s = w.add_session("s0")
            s.add(0, (1.0, 2.0, 0.1), images)
    """

    def __init__(
        self,
        root: str | os.PathLike[str],
        cameras: Sequence[Camera],
        *,
        overwrite: bool = False,
        meta: dict[str, Any] | None = None,
    ) -> None:
        self.root = Path(root)
        # Work on the real folder: "." has no name to put a temporary folder beside, and a
        # symlink is kept while its target is replaced (as vvloc._io's atomic files do).
        self._target = Path(os.path.realpath(self.root))
        cameras = tuple(cameras)  # a generator would be used up by the checks below
        if not cameras:
            raise ValueError("cameras: expected at least one camera")
        for i, c in enumerate(cameras):
            if not isinstance(c, Camera):
                raise TypeError(
                    f"cameras[{i}]: expected a vvloc.data.Camera (Camera.from_json reads a "
                    f"rig.json entry), got {type(c).__name__}"
                )
        if len({(c.width, c.height) for c in cameras}) != 1:
            raise ValueError("cameras: all cameras of a written dataset must share one image size")
        names = [c.name for c in cameras]
        repeated = sorted({n for n in names if names.count(n) > 1})
        if repeated:
            raise ValueError(f"cameras: names {repeated} repeated (each camera has its own folder)")
        check_dataset_target(self.root, overwrite)  # recovers what a killed writer left
        self.cameras = tuple(cameras)
        self.overwrite = overwrite
        doc = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "cameras": [c.to_json() for c in cameras],
        }
        if meta:
            doc["meta"] = meta
        try:  # before any folder is made: a meta JSON cannot hold leaves nothing behind
            rig_text = json.dumps(doc, indent=2)
        except (TypeError, ValueError) as e:
            raise TypeError(f"meta: expected plain JSON values (str, int, float, ...): {e}") from e
        # the folders above the target that this writer makes, removed again by abort()
        self._made_parents = [d for d in self._target.parents if not d.exists()]
        self._target.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._tmp = self._make_temp()
            (self._tmp / "rig.json").write_text(rig_text)
            (self._tmp / "sessions").mkdir()
        except BaseException:
            if hasattr(self, "_tmp"):
                shutil.rmtree(self._tmp, ignore_errors=True)
            self._remove_made_parents()
            raise
        self._sessions: dict[str, SessionWriter] = {}

    def _make_temp(self) -> Path:
        """The hidden temporary folder beside the target, with the mode a plain ``mkdir``
        gives (0o777 minus the umask), or the replaced dataset's mode."""
        for _ in range(100):
            tmp = self._target.parent / f".{self._target.name}.partial-{temp_tag()}"
            try:
                tmp.mkdir(0o777)
            except FileExistsError:
                continue
            if self._target.is_dir():
                os.chmod(tmp, stat.S_IMODE(self._target.stat().st_mode))
            return tmp
        raise FileExistsError(f"could not create a temporary folder next to {self._target}")

    def add_session(self, name: str, meta: dict[str, Any] | None = None) -> SessionWriter:
        """Start session ``name`` (a plain folder name: no ``/``, no leading ``.``, no control
        character such as a line break, no space at either end, which the command line's
        ``--sessions`` strips: such a session could not be named there) and return its
        writer."""
        if (
            not isinstance(name, str)
            or not name
            or "/" in name
            or name.startswith(".")
            or _has_control(name)
            or name != name.strip()
            or name in self._sessions
        ):
            raise ValueError(
                f"name: expected a new plain session name (no '/', leading '.', control "
                f"character or space at either end), got {name!r}"
            )
        w = SessionWriter(self._tmp / "sessions" / name, self.cameras, meta)
        self._sessions[name] = w
        return w

    def close(self) -> Path:
        """Finish: close every session and move the dataset into place. Returns ``root``.

        A session to which no frame was added is left out, with a ``UserWarning`` naming it
        (every command refuses a session without frames); ``ValueError`` when no session has
        a frame, and nothing is written."""
        return self._close(stacklevel=3)

    def _close(self, stacklevel: int) -> Path:
        """:meth:`close`, its warning ``stacklevel`` frames up (at the caller of ``close`` or of
        the ``with`` block)."""
        for w in self._sessions.values():
            w.close()
        empty = [name for name, w in self._sessions.items() if w.count == 0]
        if len(empty) == len(self._sessions):
            self.abort()  # called outside a with block as well: nothing is left behind
            raise ValueError(
                f"{self.root}: no frame was added to any session ({empty or 'no session'}); "
                "a dataset needs at least one frame"
            )
        if empty:
            for name in empty:
                shutil.rmtree(self._sessions[name].directory)
            warnings.warn(
                f"{self.root}: sessions {empty} left out: no frame was added to them",
                stacklevel=stacklevel,
            )
        replaced: Path | None = None
        if self._target.exists():
            if self.overwrite and self._target.is_dir() and any(self._target.iterdir()):
                # the old dataset is renamed aside, not deleted, until the new one is in
                # place: an interrupt in between puts it back (deleting it took seconds,
                # and an interrupt then left it half gone and the new one discarded)
                replaced = self._target.parent / f".{self._target.name}.replaced-{temp_tag()}"
                os.replace(self._target, replaced)
            else:
                self._target.rmdir()  # empty by the constructor's check
        try:
            os.replace(self._tmp, self._target)
        except BaseException:
            if replaced is not None:
                os.replace(replaced, self._target)
            raise
        if replaced is not None:
            # the new dataset is in place; an interrupt here leaves only the hidden old folder
            shutil.rmtree(replaced, ignore_errors=True)
        return self.root

    def abort(self) -> None:
        """Discard everything written so far."""
        for w in self._sessions.values():
            w.close()
        shutil.rmtree(self._tmp, ignore_errors=True)
        self._remove_made_parents()

    def _remove_made_parents(self) -> None:
        """Remove the folders above the target that this writer made, deepest first, where
        they are still empty (another process may have written into one since)."""
        for d in self._made_parents:  # Path.parents runs from the deepest up
            try:
                d.rmdir()
            except OSError:
                break

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            try:
                self._close(stacklevel=3)
            except BaseException:
                self.abort()  # no partial folder left behind
                raise
        else:
            self.abort()
