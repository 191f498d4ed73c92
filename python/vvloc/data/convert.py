"""Convert any dataset vvloc reads (NCLT, Oxford RobotCar, vvloc) into the vvloc format.

A public dataset's raw folder is slow to read (TIFFs of 1616 × 1232, Bayer PNGs, undistortion
maps) and dense (NCLT's cameras run at 5 Hz). Training and evaluation want small images at
keyframes a little apart, read many times: convert once, then point every command at the
result. :func:`convert_dataset` keeps every n-th frame or keyframes spaced in distance and
heading, resizes the images (K follows exactly) and writes atomically (a failure leaves no
partial folder). ``vvloc convert`` is its command line.
"""

from __future__ import annotations

import json
import math
import numbers
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from vvloc._checks import int_array, real_array
from vvloc.data._remap import resize_rgb
from vvloc.data.frame import Camera, Dataset, Session

if TYPE_CHECKING:
    from vvloc.data.vvloc_format import SessionWriter

__all__ = ["convert_dataset", "select_keyframes"]


def select_keyframes(
    poses: Any,
    *,
    min_distance: float = 0.0,
    min_angle_deg: float = 0.0,
    z: Any = None,
    floors: Any = None,
) -> np.ndarray:
    """Indices of keyframes along a trajectory: the first pose, then each pose that has moved
    at least ``min_distance`` metres or turned at least ``min_angle_deg`` degrees from the last
    keyframe kept, or that lies on another floor than it.

    Args:
        poses: (N, 3) float (x, y, yaw) in metres and radians, in time order.
        min_distance: metres (0: no distance criterion), in space when ``z`` is given (a climb
            up a ramp or in a car lift counts), in the plane otherwise.
        min_angle_deg: degrees (0: no heading criterion). With both 0 every pose is kept.
        z: optional (N,) float heights of the poses, metres.
        floors: optional (N,) int storey of each pose: a pose on another floor than the last
            keyframe is kept whatever it moved (the first view of a floor is a place of its own).

    Returns:
        (K,) int64 increasing indices, K ≥ 1 when N ≥ 1.
    """
    p = real_array(poses, "poses", "(N, 3)", 2, 3)  # real, finite: named otherwise
    min_distance, min_angle_deg = _spacing(min_distance, min_angle_deg)
    n = len(p)
    height = np.zeros(n) if z is None else real_array(z, "z", f"({n},)", 1)
    storey = np.zeros(n, np.int64) if floors is None else int_array(floors, "floors", f"({n},)", 1)
    for name, values in (("z", height), ("floors", storey)):
        if values.shape != (n,):
            raise ValueError(f"{name}: expected shape ({n},), got {values.shape}")
    if n == 0:
        return np.zeros(0, np.int64)
    if min_distance == 0 and min_angle_deg == 0:
        return np.arange(n, dtype=np.int64)
    keep = [0]
    angle = math.radians(min_angle_deg)
    for i in range(1, n):
        k = keep[-1]
        moved = math.hypot(p[i, 0] - p[k, 0], p[i, 1] - p[k, 1], height[i] - height[k])
        turned = abs(math.remainder(p[i, 2] - p[k, 2], 2 * math.pi))
        if (
            storey[i] != storey[k]
            or (min_distance > 0 and moved >= min_distance)
            or (min_angle_deg > 0 and turned >= angle)
        ):
            keep.append(i)
    return np.array(keep, dtype=np.int64)


def _spacing(min_distance: Any, min_angle_deg: Any) -> tuple[float, float]:
    """``(min_distance, min_angle_deg)`` as floats; ``ValueError`` naming one that is not a
    finite number >= 0 (numpy scalars count as numbers, bools do not)."""
    for name, v in (("min_distance", min_distance), ("min_angle_deg", min_angle_deg)):
        if isinstance(v, bool) or not (
            isinstance(v, numbers.Real) and math.isfinite(v) and float(v) >= 0
        ):
            raise ValueError(f"{name}: expected a finite number >= 0, got {v!r}")
    return float(min_distance), float(min_angle_deg)


def convert_dataset(
    src: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    format: str = "auto",
    sessions: Sequence[str] | None = None,
    every: int = 1,
    min_distance: float = 0.0,
    min_angle_deg: float = 0.0,
    image_size: tuple[int, int] | None = None,
    overwrite: bool = False,
    progress: bool = False,
    **reader_options: Any,
) -> Path:
    """Write the frames of ``src`` chosen as keyframes into a vvloc-format dataset at ``out``.

    Args:
        src: a dataset :func:`vvloc.data.open_dataset` reads (NCLT or Oxford RobotCar raw
            folder, or a vvloc dataset).
        out: the vvloc dataset to write (must not exist or be empty unless ``overwrite``).
        format: ``auto``, ``nclt``, ``oxford`` or ``vvloc`` (as ``open_dataset``).
        sessions: the sessions to convert (default all), written under the same names.
        every: keep every n-th frame of a session first (1: all).
        min_distance, min_angle_deg: then keep keyframes spaced this far apart in metres or
            degrees (:func:`select_keyframes`; both 0: all).
        image_size: (width, height) of the written images (default: the source's); the
            intrinsics are rescaled exactly (pixel-centre convention).
        overwrite: replace an existing ``out``.
        progress: a tqdm progress bar over the written frames.
        **reader_options: passed to the source's reader (e.g. ``ego_height``, ``cameras``,
            ``upright`` for NCLT; ``ego_height``, ``cameras``, ``tolerance_us`` for RobotCar).
            A vvloc source takes ``cameras`` alone: the names of the rig's cameras to keep,
            in the written image order (e.g. to leave out a broken camera).

    Raises:
        FileExistsError: ``out`` exists and is not empty (without ``overwrite``), before the
            source is read.
        DatasetFormatError: a chosen session holds no frame (e.g. NCLT images without ground
            truth within ``tolerance_us``); leave it out with ``sessions``.

    Returns:
        ``out``. Poses, heights (``Frame.z``), floors and microsecond timestamps are copied,
        and each frame's own ``cam_to_ego`` where the source gives frames their own (NCLT's
        and RobotCar's levelled, motion-compensated frames: ``cam_to_ego.csv``);
        ``rig.json``'s meta records the source, its options and the source's own meta (e.g.
        RobotCar's ``origin_enu``) and, per session, the frames the reader gave and those it
        left out by reason (``converted_from["source_frames"]``; ``Session.left_out``).
        Nothing is left at ``out`` if any frame fails.
    """
    from vvloc.data import detect_format, open_dataset
    from vvloc.data.frame import check_image_size
    from vvloc.data.sampling import inside_folder
    from vvloc.data.vvloc_format import DatasetFormatError, DatasetWriter, check_dataset_target

    if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
        raise ValueError(f"every: expected an int >= 1, got {every!r}")
    every = int(every)
    min_distance, min_angle_deg = _spacing(min_distance, min_angle_deg)
    if isinstance(sessions, str):
        raise TypeError(
            f"sessions: expected a list of session names, got the str {sessions!r} "
            f"(one session: [{sessions!r}])"
        )
    size = check_image_size(image_size)
    options = dict(reader_options)
    fmt = detect_format(src, format)
    if inside_folder(out, src) or inside_folder(src, out):
        # writing into the source (or around it) would replace or corrupt what is read
        raise ValueError(
            f"out: {out} is, lies inside or holds the source {src}; write the converted "
            "dataset to a folder of its own"
        )
    if size is not None:
        if "image_size" in options:
            raise TypeError("image_size: give it once, not also as a reader option")
        # the readers resize as they read (one interpolation); a vvloc rig of cameras of
        # different sizes is read only so
        options["image_size"] = size
    keep = options.pop("cameras", None) if fmt == "vvloc" else None
    check_dataset_target(out, overwrite)  # before the source is read (slow for raw folders)
    if sessions is not None and fmt != "vvloc":
        options["sessions"] = list(sessions)  # a raw reader reads only these
    ds = open_dataset(src, format=fmt, **options)
    picked = None if keep is None else _camera_indices(keep, [c.name for c in ds.cameras])
    names = _session_names(ds, sessions)
    empty = [name for name in names if len(ds.session(name)) == 0]
    if empty:
        raise DatasetFormatError(
            f"{src}: sessions {empty} hold no frame as read"
            + (
                f" (tolerance_us={options['tolerance_us']}: no image has a pose that near)"
                if "tolerance_us" in options
                else " (e.g. no image with a pose near it in time)"
            )
            + "; leave them out with sessions (--sessions) or check the source"
        )
    cameras = list(ds.cameras) if picked is None else [ds.cameras[i] for i in picked]
    if size is not None and (cameras[0].width, cameras[0].height) != size:
        cameras = [c.resized(*size) for c in cameras]
    picks = {
        name: _keyframe_picks(ds.session(name), every, min_distance, min_angle_deg)
        for name in names
    }
    converted_from: dict[str, Any] = {
        "path": str(Path(src).resolve()),
        "format": fmt,
        "options": {k: _jsonable(v) for k, v in reader_options.items()},
        "image_size": None if size is None else list(size),  # (width, height); None: kept
        "every": every,
        "min_distance": min_distance,
        "min_angle_deg": min_angle_deg,
        # per session: the frames the source's reader gave, and those it left out, by reason
        "source_frames": {
            name: {"read": len(ds.session(name)), "left_out": ds.session(name).left_out}
            for name in names
        },
    }
    if "converted_from" in ds.meta:  # a converted dataset converted again: its history
        converted_from["source_converted_from"] = ds.meta["converted_from"]
    meta = {**ds.meta, "converted_from": converted_from}
    bar = None  # opened once the writer accepted ``out`` (a refusal prints no empty bar)
    try:
        with DatasetWriter(out, cameras, overwrite=overwrite, meta=meta) as writer:
            if progress:
                from tqdm import tqdm

                total = sum(len(v) for v in picks.values())
                bar = tqdm(total=total, desc="vvloc convert", unit="frame")
            for name in names:
                w = writer.add_session(name, meta=_session_meta(src, fmt, name))
                _write_session(w, ds.session(name), picks[name], picked, cameras[0], bar)
    finally:
        if bar is not None:
            bar.close()
    return Path(out)


def _session_names(ds: Dataset, sessions: Sequence[str] | None) -> list[str]:
    """The sessions of ``ds`` to convert: ``sessions``, or all of them when None;
    ``ValueError`` for a name listed twice, ``KeyError`` naming ``sessions`` and the known
    sessions for one ``ds`` lacks (before anything is written)."""
    names = list(ds.sessions) if sessions is None else list(sessions)
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ValueError(f"sessions: {repeated} listed more than once")
    for name in names:
        try:
            ds.session(name)
        except KeyError as e:
            raise KeyError(f"sessions: {e.args[0] if e.args else name}") from None
    return names


def _keyframe_picks(
    session: Session, every: int, min_distance: float, min_angle_deg: float
) -> np.ndarray:
    """(K,) int64 increasing indices of the frames of ``session`` to write: every
    ``every``-th frame, then among those the keyframes :func:`select_keyframes` keeps."""
    strided = np.arange(0, len(session), every, dtype=np.int64)
    chosen = select_keyframes(
        session.poses[strided],
        min_distance=min_distance,
        min_angle_deg=min_angle_deg,
        z=session.z[strided],
        floors=session.floors[strided],
    )
    return strided[chosen]


def _write_session(
    w: SessionWriter,
    session: Session,
    picks: np.ndarray,
    picked: list[int] | None,
    camera: Camera,
    bar: Any,
) -> None:
    """Write the frames ``picks`` of ``session`` to ``w``: the cameras ``picked`` (indices in
    the source's rig order; None: all), images resized to ``camera``'s size where they differ,
    and each frame's own ``cam_to_ego`` where the source gives frames their own; ``bar`` (a
    tqdm bar or None) counts the frames."""
    own = session.frame_cam_to_ego is not None  # a tilting or unsynchronised rig
    for i in picks:
        f = session[int(i)]
        images = f.images if picked is None else f.images[picked]
        if images.shape[2:] != (camera.height, camera.width):
            images = np.stack(
                [
                    resize_rgb(img.transpose(1, 2, 0), camera.width, camera.height).transpose(
                        2, 0, 1
                    )
                    for img in images
                ]
            )
        cam_to_ego = None
        if own:
            cam_to_ego = f.cam_to_ego if picked is None else f.cam_to_ego[picked]
        w.add(
            int(session.timestamps[i]), f.pose, images, z=f.z, floor=f.floor, cam_to_ego=cam_to_ego
        )
        if bar is not None:
            bar.update(1)


def _camera_indices(keep: Any, rig: list[str]) -> list[int]:
    """The indices in ``rig`` (the source's camera names, in image order) of the cameras
    ``keep`` names, in its order; ``TypeError``/``ValueError`` naming ``cameras`` unless it
    is a non-empty sequence of the rig's names, each once."""
    if isinstance(keep, str) or not isinstance(keep, Sequence):
        raise TypeError(f"cameras: expected a list of camera names of the rig, got {keep!r}")
    names = list(keep)
    if not names or not all(isinstance(n, str) for n in names):
        raise ValueError(f"cameras: expected a non-empty list of camera names, got {keep!r}")
    unknown = [n for n in names if n not in rig]
    if unknown:
        raise ValueError(f"cameras: {unknown} not in the source's rig {rig}")
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ValueError(f"cameras: {repeated} listed more than once")
    return [rig.index(n) for n in names]


def _session_meta(src: str | os.PathLike[str], fmt: str, name: str) -> dict[str, Any]:
    """The written ``session.json`` of session ``name``: a vvloc source's own (a rendered
    session's lighting and seed, which the trained-on check compares) and ``source_session``."""
    meta: dict[str, Any] = {}
    if fmt == "vvloc":
        path = Path(src) / "sessions" / name / "session.json"
        try:
            own = json.loads(path.read_text(encoding="utf-8-sig"))
        except (OSError, ValueError):  # none, or unreadable: the reader ignores it too
            own = None
        if isinstance(own, dict):
            meta.update(own)
    meta["source_session"] = name
    return meta


def _jsonable(v: Any) -> Any:
    if isinstance(v, (str, int, float, bool)) or v is None:
        return v
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    return str(v)
