"""The common data model of every vvloc dataset: cameras, frames, sessions, datasets.

Frames follow DESIGN.md §3: world x-east/y-north/z-up, vehicle (ego) x-forward/y-left/z-up,
camera OpenCV (x right, y down, z forward). A pose is (x, y, yaw) in metres and radians.
Calibration arrays are float64 so that projections stay exact; networks cast as they need.
"""

from __future__ import annotations

import abc
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, overload

import numpy as np

from vvloc._checks import as_array, real_array


@dataclass(frozen=True, eq=False)
class Camera:
    """One calibrated pinhole camera of a rig.

    ``K`` (3, 3) float64 maps OpenCV camera coordinates to pixels, with pixel (0, 0)'s *centre*
    at coordinate (0, 0) (OpenCV convention). ``cam_to_ego`` (4, 4) float64 maps camera
    coordinates to ego (vehicle) coordinates, metres.
    """

    name: str
    width: int
    height: int
    K: np.ndarray
    cam_to_ego: np.ndarray

    def __post_init__(self) -> None:
        if (
            not isinstance(self.name, str)
            or not self.name
            or any(c in self.name for c in "/\\\0")
            or self.name.strip() != self.name
            or self.name.startswith(".")  # ".", "..": not a folder of its own
            or self.name in RESERVED_NAMES
        ):
            raise ValueError(
                f"camera name: expected a non-empty plain folder name (no '/', '\\', leading "
                f"'.', or {sorted(RESERVED_NAMES)}), got {self.name!r}"
            )
        for key in ("width", "height"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"camera {self.name!r}: {key} must be a positive int, got {v!r}")
        K = np.asarray(self.K, dtype=np.float64)
        T = np.asarray(self.cam_to_ego, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise ValueError(
                f"camera {self.name!r}: K must be a finite (3, 3) array, got {K.shape}"
            )
        if not is_pinhole(K):
            raise ValueError(f"camera {self.name!r}: K must be a {PINHOLE}, got {K.tolist()}")
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(
                f"camera {self.name!r}: cam_to_ego must be finite (4, 4), got {T.shape}"
            )
        if not is_rigid(T):
            raise ValueError(
                f"camera {self.name!r}: cam_to_ego must be a {RIGID}: {rigid_fault(T)}"
            )
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "cam_to_ego", T)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    def to_json(self) -> dict[str, Any]:
        """The camera as the ``rig.json`` entry of the vvloc dataset format."""
        return {
            "name": self.name,
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "cam_to_ego": self.cam_to_ego.tolist(),
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Camera:
        """Build a camera from a ``rig.json`` entry (raises ``ValueError`` on missing keys)."""
        if not isinstance(d, dict):
            raise ValueError(
                f"camera entry: expected an object with name, width, ..., got {d!r:.60}"
            )
        missing = [k for k in ("name", "width", "height", "K", "cam_to_ego") if k not in d]
        if missing:
            raise ValueError(f"camera entry {d.get('name', '?')!r} lacks keys {missing}")
        return cls(
            d["name"], d["width"], d["height"], np.asarray(d["K"]), np.asarray(d["cam_to_ego"])
        )

    def project_ego(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project ego-frame points (N, 3) metres (x forward, y left, z up) to pixels (N, 2)
        (u, v) float64 (OpenCV: pixel centres at integers); also returns their depth (N,) m
        along the camera's optical axis. A point behind the camera (depth <= 0) still gets a
        (u, v), through the projective division: keep only depth > 0 for points it sees. A
        single point may be given as (3,)."""
        p = as_array(points, "points", "(N, 3)")
        p = real_array(p[None] if p.ndim == 1 else p, "points", "(N, 3)", 2, 3)
        ego_to_cam = np.linalg.inv(self.cam_to_ego)
        pc = p @ ego_to_cam[:3, :3].T + ego_to_cam[:3, 3]
        uvw = pc @ self.K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = uvw[:, :2] / uvw[:, 2:3]
        return uv, pc[:, 2]

    def resized(self, width: int, height: int) -> Camera:
        """The same camera for images resized to (width, height) (pixel-centre exact)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, :] *= sx
        K[1, :] *= sy
        K[0, 2] = (self.K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (self.K[1, 2] + 0.5) * sy - 0.5
        return Camera(self.name, width, height, K, self.cam_to_ego)

    def rotated(self, quarter_turns: int) -> Camera:
        """The same camera for its images turned by ``np.rot90(image, quarter_turns)``.

        ``quarter_turns`` counts counter-clockwise quarter turns of the image (negative:
        clockwise). Exact: a pixel (u, v) of the turned image sees the ego point that the
        original image shows at the pixel it came from. Each counter-clockwise turn of a W-wide
        image maps pixel (u, v) to (v, W − 1 − u) (pixel-centre convention), so K becomes
        P·K·M with P that pixel map and M = [[0, −1, 0], [1, 0, 0], [0, 0, 1]] the new camera
        axes in the old camera frame, and ``cam_to_ego`` becomes ``cam_to_ego · M``.
        """
        if isinstance(quarter_turns, bool) or not isinstance(quarter_turns, (int, np.integer)):
            raise TypeError(f"quarter_turns: expected an int, got {type(quarter_turns).__name__}")
        cam = self
        for _ in range(int(quarter_turns) % 4):
            P = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, cam.width - 1.0], [0.0, 0.0, 1.0]])
            M = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
            T = cam.cam_to_ego.copy()
            T[:3, :3] = cam.cam_to_ego[:3, :3] @ M
            cam = Camera(cam.name, cam.height, cam.width, P @ cam.K @ M, T)
        return cam

    def upright_quarter_turns(self) -> int:
        """Counter-clockwise quarter turns (0-3) that bring this camera's images upright.

        Upright: the image's downward axis (camera y) points as far down in the ego frame
        (−z) as any of the four turns allows. 0 for a level camera; NCLT's Ladybug images,
        stored sideways, need 3 (one clockwise turn).
        """
        downs = [float(self.rotated(k).cam_to_ego[2, 1]) for k in range(4)]
        return int(np.argmin(downs))

    def with_ego_origin_lowered(self, height: float) -> Camera:
        """The same camera in an ego frame whose origin lies ``height`` metres lower.

        For a dataset whose vehicle frame sits above the ground (a roof camera, a body frame):
        vvloc's ego origin is on the ground under the vehicle (DESIGN.md §3), so every camera
        rises by ``height`` in it.
        """
        T = self.cam_to_ego.copy()
        T[2, 3] += float(height)
        return Camera(self.name, self.width, self.height, self.K, T)


@dataclass(frozen=True, eq=False)
class Frame:
    """One multi-camera keyframe.

    Attributes:
        images: (M, 3, H, W) uint8 RGB, cameras in rig order.
        K: (M, 3, 3) float64 intrinsics (OpenCV pixel-centre convention).
        cam_to_ego: (M, 4, 4) float64 camera (OpenCV) → ego (x fwd, y left, z up), metres.
        pose: (3,) float64 ego pose in the world (x east m, y north m, yaw rad CCW from east).
        t: timestamp, seconds.
        floor: storey index, one numbering for every session of the dataset
            (docs/dataset-format.md; 0 outdoors / ground level; the simulator's garages count
            downwards, floor k at z = −3.2·k m).
        session: name of the session the frame belongs to.
        index: index of the frame in its session.
        z: height of the ego origin (ground under the vehicle), metres.
        cameras: camera names, in the order of the first axis of ``images``.
    """

    images: np.ndarray
    K: np.ndarray
    cam_to_ego: np.ndarray
    pose: np.ndarray
    t: float
    floor: int
    session: str = ""
    index: int = -1
    z: float = 0.0
    cameras: tuple[str, ...] = field(default_factory=tuple)

    @property
    def num_cameras(self) -> int:
        """M, the number of cameras."""
        return int(self.images.shape[0])


#: :func:`has_image_content`'s block size (pixels) and threshold (grey levels on the 0-255
#: scale). Rendered frames of every lighting preset, the darkest garage's included, reach ≥ 11
#: on at least one camera (≥ 2.5 on every camera); they keep content down to about 4 stops
#: darker. Per-pixel noise of σ grey levels on a flat picture reaches about σ/8 when the three
#: channels share it (a demosaiced sensor; a block mean averages 64 pixels) and σ/14 when they
#: do not, so a covered lens with sensor noise up to σ ≈ 8 reads as having none (on sides of
#: 16 pixels and more; a shorter side is taken pixel by pixel, which averages no noise away).
CONTENT_BLOCK = 8
CONTENT_MIN_STD = 1.0


def has_image_content(images: Any) -> bool:
    """Whether a frame's pictures show anything: at least one camera whose coarse brightness
    varies, i.e. the standard deviation of its grey image's ``CONTENT_BLOCK`` × ``CONTENT_BLOCK``
    block means reaches :data:`CONTENT_MIN_STD` grey levels (0-255 scale; float images in
    [0, 1] are scaled by 255). Along a side shorter than two blocks (16 pixels) the blocks are
    single pixels, so that a small image keeps its variation along it; along a side that is no
    multiple of the block, the blocks are laid from either end in turn, so that no edge row or
    column is left out.

    A frame without content (a covered or failed rig, a black or blown-out stretch, flat
    sensor noise) encodes to the same descriptors as any other such frame, so two of them match
    at a cost near 0 wherever they were taken: :func:`vvloc.build_map` leaves such
    frames out of a map, and the localizer never accepts such a query. ``images`` (M, 3, H, W)
    uint8 or float, or a :class:`Frame` (its ``images``)."""
    arr = np.asarray(images.images if isinstance(images, Frame) else images)
    if arr.ndim != 4 or arr.shape[1] != 3 or 0 in arr.shape:
        raise ValueError(f"images: expected shape (M, 3, H, W), got {arr.shape}")
    if not (arr.dtype == np.uint8 or np.issubdtype(arr.dtype, np.floating)):
        raise TypeError(f"images: expected uint8 or float in [0, 1], got dtype {arr.dtype}")
    exact = arr.dtype == np.uint8  # integer sums: exact, and fast (2 ms a 1080p camera)
    _, _, h, w = arr.shape
    # one block along a side would hide the variation along it: single pixels there
    bh, bw = (CONTENT_BLOCK if n >= 2 * CONTENT_BLOCK else 1 for n in (h, w))
    hb, wb = h // bh, w // bw
    # the blocks from the top-left corner, and from the bottom-right one when pixels are left
    starts = {(0, 0), (h - hb * bh, w - wb * bw)}
    acc = np.uint32 if exact else np.float64
    for cam in arr:  # one camera at a time: most frames answer at the first
        grey = cam.sum(axis=0, dtype=np.uint16 if exact else np.float64)  # the three channels
        for r0, c0 in starts:
            # each block's rows, then its columns
            blocks = grey[r0 : r0 + hb * bh, c0 : c0 + wb * bw]
            blocks = blocks.reshape(hb, bh, wb * bw).sum(axis=1, dtype=acc)
            blocks = blocks.reshape(hb, wb, bw).sum(axis=2, dtype=acc)
            if float(blocks.std()) / (3 * bh * bw) * (1.0 if exact else 255.0) >= CONTENT_MIN_STD:
                return True
    return False


def stack_calibration(cameras: Sequence[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3, 3) intrinsics and (M, 4, 4) camera-to-ego transforms of ``cameras``."""
    return (
        np.stack([c.K for c in cameras]).astype(np.float64),
        np.stack([c.cam_to_ego for c in cameras]).astype(np.float64),
    )


class Session(Sequence[Frame], abc.ABC):
    """A sequence of keyframes of one drive, read lazily (images load on indexing).

    Attributes (all loaded without reading any image):
        name: session name.
        cameras: the rig, in image order.
        timestamps: (N,) int64 microseconds.
        poses: (N, 3) float64 (x, y, yaw) world poses of the ego frame: metres, yaw in radians
            counter-clockwise from the world x axis (DESIGN.md §3).
        z: (N,) float64 heights of the ego origin, metres.
        floors: (N,) int64 storey indices.
        frame_cam_to_ego: (N, M, 4, 4) float64 camera → ego transforms of each frame, or None
            when every frame has the rig's (``cameras[m].cam_to_ego``). Real vehicles tilt and
            their cameras fire at different times: a reader that levels the ego frame or
            compensates the motion between the cameras' exposures gives each frame its own
            (:func:`ego_frames`); ``Frame.cam_to_ego`` is then this row.
        left_out: the source's frames a raw reader left out, by reason (e.g. ``{"no ground
            truth within tolerance_us=50000": 12}``), in the order the reader checks them, each
            frame counted under the first reason it failed; empty when none was, and for
            sessions of the vvloc format (their frames are what was written).
    """

    def __init__(
        self,
        name: str,
        cameras: Sequence[Camera],
        timestamps: np.ndarray,
        poses: np.ndarray,
        z: np.ndarray,
        floors: np.ndarray,
        frame_cam_to_ego: np.ndarray | None = None,
        *,
        left_out: Mapping[str, int] | None = None,
    ) -> None:
        self.name = name
        self.left_out = {str(k): int(v) for k, v in (left_out or {}).items() if int(v) > 0}
        self.cameras = tuple(cameras)
        self.timestamps = np.asarray(timestamps, dtype=np.int64)
        self.poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        self.z = np.asarray(z, dtype=np.float64)
        self.floors = np.asarray(floors, dtype=np.int64)
        n = len(self.timestamps)
        if not (len(self.poses) == len(self.z) == len(self.floors) == n):
            raise ValueError(f"session {name!r}: timestamps, poses, z and floors differ in length")
        sizes = {(c.width, c.height) for c in self.cameras}
        if len(sizes) > 1:
            raise ValueError(
                f"session {name!r}: cameras must share one image size to stack a Frame, got {sizes}"
            )
        self._K, self._cam_to_ego = stack_calibration(self.cameras)
        self.frame_cam_to_ego: np.ndarray | None = None
        if frame_cam_to_ego is not None:
            T = np.asarray(frame_cam_to_ego, dtype=np.float64)
            want = (n, len(self.cameras), 4, 4)
            if T.shape != want:
                raise ValueError(
                    f"session {name!r}: frame_cam_to_ego must be {want}, got {T.shape}"
                )
            if not np.isfinite(T).all():
                raise ValueError(f"session {name!r}: frame_cam_to_ego has non-finite values")
            self.frame_cam_to_ego = T

    def __len__(self) -> int:
        return len(self.timestamps)

    @overload
    def __getitem__(self, i: int) -> Frame: ...

    @overload
    def __getitem__(self, i: slice) -> list[Frame]: ...

    def __getitem__(self, i: int | slice) -> Frame | list[Frame]:
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)):
            raise TypeError(f"index: expected an int or slice, got {type(i).__name__}")
        n = len(self)
        j = int(i) + n if i < 0 else int(i)
        if not 0 <= j < n:
            raise IndexError(f"frame index {i} out of range for session {self.name!r} of {n}")
        images = self._load_images(j)
        return Frame(
            images=images,
            K=self._K.copy(),
            cam_to_ego=(
                self._cam_to_ego if self.frame_cam_to_ego is None else self.frame_cam_to_ego[j]
            ).copy(),
            pose=self.poses[j].copy(),
            # an int below 2^53 divided: correctly rounded, so repr prints the microseconds
            # (× 1e-6 was a unit in the last place off for a third of them)
            t=int(self.timestamps[j]) / 1e6,
            floor=int(self.floors[j]),
            session=self.name,
            index=j,
            z=float(self.z[j]),
            cameras=tuple(c.name for c in self.cameras),
        )

    def __iter__(self) -> Iterator[Frame]:
        for j in range(len(self)):
            yield self[j]

    @abc.abstractmethod
    def _load_images(self, index: int) -> np.ndarray:
        """Read the (M, 3, H, W) uint8 images of frame ``index``."""


class Dataset:
    """A set of sessions recorded with one rig. ``ds.session(name)[i]`` is a :class:`Frame`."""

    def __init__(
        self,
        root: Path,
        cameras: Sequence[Camera],
        sessions: dict[str, Session],
        meta: dict[str, Any] | None = None,
    ) -> None:
        self.root = Path(root)
        self.cameras = tuple(cameras)
        self._sessions = dict(sessions)
        self.meta: dict[str, Any] = dict(meta or {})

    @property
    def sessions(self) -> list[str]:
        """Session names, sorted."""
        return sorted(self._sessions)

    def session(self, name: str) -> Session:
        """The session called ``name`` (``KeyError`` naming the known sessions otherwise)."""
        try:
            return self._sessions[name]
        except KeyError:
            raise KeyError(
                f"no session {name!r} in {self.root}; sessions: {self.sessions}"
            ) from None

    def __repr__(self) -> str:
        n = sum(len(s) for s in self._sessions.values())
        cams = [c.name for c in self.cameras]
        return f"Dataset({str(self.root)!r}, sessions={self.sessions}, frames={n}, cameras={cams})"


#: PIL modes of 8-bit images that :func:`load_rgb` converts to RGB (grey replicated, alpha
#: dropped, a palette looked up); 16-bit and float images are refused, not clipped.
EIGHT_BIT_MODES = frozenset({"RGB", "RGBA", "RGBX", "L", "LA", "P", "PA", "1", "CMYK", "YCbCr"})


def load_rgb(path: Path) -> np.ndarray:
    """Read an image file as (H, W, 3) uint8 RGB (grey images are replicated, alpha dropped).

    Raises:
        ValueError naming the file: an image of more than 8 bits per channel (16-bit PNG or
            TIFF, float), which converting would clip to white; a file that is not an image
            or is damaged (truncated by an interrupted copy: PIL finds out only when it
            decodes the pixels, and its message names no file).
        FileNotFoundError: no such file.
    """
    return _load_8bit(path, keep_grey=False)


def load_raw(path: Path) -> np.ndarray:
    """Read an 8-bit image file as it is stored: (H, W) uint8 for a single-channel image (a
    raw Bayer mosaic, a grey image), else (H, W, 3) uint8 RGB. Raises as :func:`load_rgb`."""
    return _load_8bit(path, keep_grey=True)


def _load_8bit(path: Path, keep_grey: bool) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            # Pillow opens a 16-bit RGB(A) PNG as mode RGB(A), its rawmode ';16B' keeping
            # only the high byte of each sample: a 12-bit image read nearly black
            sixteen = any(";16" in str(getattr(t, "args", "")) for t in (im.tile or []))
            if im.mode not in EIGHT_BIT_MODES or sixteen:
                what = (
                    f"image mode {im.mode!r} is not 8 bits per channel"
                    if im.mode not in EIGHT_BIT_MODES
                    else f"{im.mode} image of 16 bits per channel"
                )
                raise ValueError(
                    f"{path}: {what}; vvloc reads 8-bit RGB (or grey) images: scale it to 8 "
                    "bits first"
                )
            if keep_grey and im.mode == "L":
                return np.asarray(im, dtype=np.uint8)
            return np.asarray(im.convert("RGB"), dtype=np.uint8)
    except FileNotFoundError:
        raise
    except (UnidentifiedImageError, OSError, SyntaxError, Image.DecompressionBombError) as e:
        raise ValueError(f"{path}: not a readable image ({e})") from None  # PIL's errors


#: What :func:`is_rigid` accepts, for error messages.
RIGID = (
    "finite rigid transform (rotation orthonormal to 1e-6 with determinant +1, bottom row 0 0 0 1)"
)


#: File names of a session folder (vvloc_format) that a camera's image folder cannot take.
RESERVED_NAMES = frozenset({"poses.csv", "session.json", "cam_to_ego.csv"})


#: What :func:`is_pinhole` accepts, for messages.
PINHOLE = (
    "pinhole matrix [[fx, s, cx], [s', fy, cy], [0, 0, 1]] with focal lengths fx, fy > 0 "
    "(pixels; the skew s' below the diagonal only for a skewed camera turned by 90 degrees)"
)


def is_pinhole(K: np.ndarray) -> bool:
    """Whether ``K`` (..., 3, 3) holds finite pinhole intrinsics (:data:`PINHOLE`)."""
    K = np.asarray(K, dtype=np.float64)
    return bool(
        np.isfinite(K).all()
        and (K[..., 0, 0] > 0).all()
        and (K[..., 1, 1] > 0).all()
        and np.allclose(K[..., 2, :], (0.0, 0.0, 1.0), atol=1e-9)
    )


def rigid_fault(T: np.ndarray) -> str:
    """Why a (4, 4) ``T`` that :func:`is_rigid` refuses is not a :data:`RIGID` transform, for
    messages: a value not finite, its bottom row, its rotation's determinant, or how far the
    rotation is from orthonormal (a matrix typed with a few decimals misses the 1e-6 by about
    their rounding)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[:3, :3]
    if not np.isfinite(T).all():
        return "a value is not finite (inf or nan)"
    if not (T[3] == (0.0, 0.0, 0.0, 1.0)).all():
        return f"bottom row {T[3].tolist()}, not 0 0 0 1"
    det = float(np.linalg.det(R))
    if det <= 0:
        return f"the rotation's determinant is {det:.6g} (a reflection or a singular matrix)"
    off = float(np.abs(R.T @ R - np.eye(3)).max())
    return (
        f"the rotation is {off:.2g} from orthonormal (largest entry of RᵀR − I, above 1e-6): "
        "written with too few decimals? Re-orthonormalise it (U·Vᵀ of its SVD) or write it "
        "with more digits"
    )


def is_rigid(T: np.ndarray) -> bool:
    """Whether ``T`` (..., 4, 4) holds finite rigid transforms (:data:`RIGID`)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    return bool(
        np.isfinite(T).all()
        and np.allclose(np.swapaxes(R, -1, -2) @ R, np.eye(3), atol=1e-6)
        and (np.linalg.det(R) > 0).all()
        and (T[..., 3, :] == (0.0, 0.0, 0.0, 1.0)).all()
    )


def euler_to_matrix(
    x: float, y: float, z: float, roll: float, pitch: float, yaw: float
) -> np.ndarray:
    """4×4 rigid transform from a translation and ZYX Euler angles (R = Rz(yaw)·Ry(pitch)·Rx(roll)).

    This is the "x, y, z, roll, pitch, yaw" convention of both NCLT (``ssc``) and RobotCar.
    Angles in radians.
    """
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1.0]])
    Ry = np.array([[cp, 0, sp], [0, 1.0, 0], [-sp, 0, cp]])
    Rx = np.array([[1.0, 0, 0], [0, cr, -sr], [0, sr, cr]])
    T = np.eye(4)
    T[:3, :3] = Rz @ Ry @ Rx
    T[:3, 3] = (x, y, z)
    return T


# Flip between a (x fwd, y right, z down) body frame and vvloc's ego frame (x fwd, y left, z up);
# it is its own inverse.
FRD_TO_FLU = np.diag([1.0, -1.0, -1.0, 1.0])
# World NED (x north, y east, z down) → ENU (x east, y north, z up); its own inverse as well.
NED_TO_ENU = np.array([[0.0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1]])


def ego_frames(
    world_body: np.ndarray,
    rig: Sequence[Camera],
    *,
    height: float = 0.0,
    level: bool = True,
    world_body_at_cameras: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """vvloc poses and per-frame camera → ego transforms of a vehicle that tilts and whose
    cameras fire at different times (the NCLT and RobotCar readers).

    Args:
        world_body: (N, 4, 4) float64 body → world (ENU, metres) at each frame's time; the body
            frame is FLU (x forward, y left, z up) with its origin ``height`` metres above the
            ground, and tilts with the vehicle.
        rig: the M cameras, ``cam_to_ego`` in the body frame lowered by ``height``
            (:meth:`Camera.with_ego_origin_lowered`), as a level, standing vehicle has them.
        height: the body origin's height above the ground, metres.
        level: make the ego frame level (DESIGN.md §3: z up; the BEV's plane is the ground's):
            the ego frame is the lowered body frame's origin with its heading alone, and the
            body's roll and pitch go into each frame's ``cam_to_ego``. False keeps the tilting
            body frame as the ego frame.
        world_body_at_cameras: (N, M, 4, 4) body → world at each camera's own exposure (motion
            compensation: a camera that fired ``dt`` before the frame's time sees from where the
            vehicle was then), or None when the cameras fired at the frame's time.

    Returns:
        poses (N, 3) float64 (x, y, yaw) of the ego origin (the ground under the body origin,
        along the body's z axis) in the world; its heights z (N,); and ``frame_cam_to_ego``
        (N, M, 4, 4) float64 camera → ego of each frame, or None when every frame has the rig's
        (``level`` False and no motion compensation).
    """
    T = np.asarray(world_body, dtype=np.float64).reshape(-1, 4, 4)
    lower = np.eye(4)
    lower[2, 3] = -float(height)
    world_low = T @ lower  # the lowered body frame (the rig's cam_to_ego are in it)
    yaw = np.arctan2(world_low[:, 1, 0], world_low[:, 0, 0])
    poses = np.stack([world_low[:, 0, 3], world_low[:, 1, 3], yaw], axis=1)
    z = world_low[:, 2, 3].copy()
    if not level and world_body_at_cameras is None:
        return poses, z, None
    world_ego = world_low.copy()
    if level:  # the heading alone: a rotation about the world's z axis
        cos, sin = np.cos(yaw), np.sin(yaw)
        world_ego[:, :3, :3] = 0.0
        world_ego[:, 0, 0], world_ego[:, 0, 1] = cos, -sin
        world_ego[:, 1, 0], world_ego[:, 1, 1] = sin, cos
        world_ego[:, 2, 2] = 1.0
    cams = np.stack([cam.cam_to_ego for cam in rig]).astype(np.float64)  # (M, 4, 4)
    if world_body_at_cameras is None:
        at_cams = np.repeat(world_low[:, None], len(rig), axis=1)
    else:
        at_cams = np.asarray(world_body_at_cameras, dtype=np.float64)
        if at_cams.shape != (len(T), len(rig), 4, 4):
            raise ValueError(
                f"world_body_at_cameras: expected ({len(T)}, {len(rig)}, 4, 4), got {at_cams.shape}"
            )
        at_cams = at_cams @ lower
    ego_world = np.linalg.inv(world_ego)
    frame_cam_to_ego = ego_world[:, None] @ at_cams @ cams[None]
    frame_cam_to_ego[..., 3, :] = (0.0, 0.0, 0.0, 1.0)  # exact bottom rows after the products
    return poses, z, frame_cam_to_ego


#: The longest image side (pixels) a conversion may resize to: 100 000 pixels square was
#: accepted, and the process was killed for memory without a word.
MAX_IMAGE_SIDE = 16384


def check_image_size(image_size: Any) -> tuple[int, int] | None:
    """``image_size`` as (width, height) plain ints, or None; ``ValueError`` naming it unless
    it is None or two positive ints of at most :data:`MAX_IMAGE_SIDE`."""
    if image_size is None:
        return None
    if (
        isinstance(image_size, (str, bytes))
        or not hasattr(image_size, "__len__")
        or len(image_size) != 2
        or any(
            isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1 for v in image_size
        )
    ):
        raise ValueError(f"image_size: expected (width, height) positive ints, got {image_size!r}")
    if max(image_size) > MAX_IMAGE_SIDE:
        raise ValueError(
            f"image_size: expected sides of at most {MAX_IMAGE_SIDE} pixels, got "
            f"{tuple(int(v) for v in image_size)}"
        )
    return (int(image_size[0]), int(image_size[1]))


def check_reader_options(
    cameras: Sequence[Any], image_size: Any, tolerance_us: Any
) -> tuple[tuple[int, int] | None, int]:
    """Check a raw reader's shared options by name (``TypeError`` / ``ValueError``):
    ``cameras`` a non-empty list, each listed once; ``image_size`` None or (width, height)
    positive ints; ``tolerance_us`` an int >= 0 in microseconds. Returns ``(image_size,
    tolerance_us)`` as plain ints."""
    if isinstance(cameras, (str, bytes)) or not hasattr(cameras, "__iter__"):
        raise TypeError(f"cameras: expected a list of cameras, got {cameras!r}")
    names = list(cameras)
    if not names:
        raise ValueError("cameras: expected at least one camera")
    repeated = sorted({str(c) for c in names if names.count(c) > 1})
    if repeated:
        raise ValueError(f"cameras: {repeated} listed more than once")
    size = check_image_size(image_size)
    if isinstance(tolerance_us, bool) or not isinstance(tolerance_us, (int, np.integer)):
        raise TypeError(
            f"tolerance_us: expected an int (microseconds), got {type(tolerance_us).__name__}"
        )
    if tolerance_us < 0:
        raise ValueError(f"tolerance_us: expected microseconds >= 0, got {tolerance_us}")
    return size, int(tolerance_us)


def chosen_sessions(sessions: Any, found: Sequence[str], root: object) -> set[str] | None:
    """A raw reader's ``sessions`` option: None (every session ``found`` in the folder
    ``root``) or a list of names of ``found``, each once; returned as a set. ``TypeError`` for
    a str or a non-list, ``ValueError`` for a name listed twice, ``KeyError`` naming the
    folder's sessions for a name it lacks (as :meth:`Dataset.session` does)."""
    if sessions is None:
        return None
    if isinstance(sessions, (str, bytes)) or not hasattr(sessions, "__iter__"):
        raise TypeError(
            f"sessions: expected a list of session names, got {sessions!r} (one session: "
            f"[{sessions!r}])"
        )
    names = list(sessions)
    if not names or not all(isinstance(n, str) for n in names):
        raise TypeError(f"sessions: expected a non-empty list of session names, got {names!r}")
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ValueError(f"sessions: {repeated} listed more than once")
    for name in names:
        if name not in found:
            raise KeyError(f"sessions: no session {name!r} in {root}; sessions: {list(found)}")
    return set(names)


def nearest_within(
    reference: np.ndarray, queries: np.ndarray, tolerance: int
) -> tuple[np.ndarray, np.ndarray]:
    """For sorted int64 ``reference`` times, the nearest index for each query and a validity mask.

    A query is valid when its nearest reference lies within ``tolerance`` (same unit).
    """
    reference = np.asarray(reference, dtype=np.int64)
    queries = np.asarray(queries, dtype=np.int64)
    if len(reference) == 0:
        return np.zeros(len(queries), dtype=np.int64), np.zeros(len(queries), dtype=bool)
    pos = np.searchsorted(reference, queries)
    lo = np.clip(pos - 1, 0, len(reference) - 1)
    hi = np.clip(pos, 0, len(reference) - 1)
    pick = np.where(np.abs(reference[hi] - queries) < np.abs(reference[lo] - queries), hi, lo)
    ok = np.abs(reference[pick] - queries) <= tolerance
    return pick, ok


def interpolate_rows(
    times: np.ndarray,
    values: np.ndarray,
    queries: np.ndarray,
    tolerance: int,
    *,
    angle_columns: Sequence[int] = (),
) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``values`` linearly interpolated at ``queries`` times, and a validity mask.

    Args:
        times: (N,) sorted int64 times of the rows (e.g. microseconds).
        values: (N, C) float64 rows.
        queries: (Q,) int64 times.
        tolerance: a query is valid when its nearest row lies within it (the unit of times).
        angle_columns: columns holding angles (radians), interpolated along the shorter arc
            and wrapped to (−π, π].

    Returns:
        ((Q, C) float64, (Q,) bool). A valid query between two rows is interpolated between
        them; one before the first or after the last row takes that row.
    """
    t = np.asarray(times, dtype=np.int64)
    v = np.asarray(values, dtype=np.float64)
    if v.ndim == 0 or v.shape[0] != len(t):
        got = "a scalar" if v.ndim == 0 else v.shape[0]
        raise ValueError(f"values: expected {len(t)} rows, one per time, got {got}")
    if v.ndim != 2:  # (N,) rows of one value (reshape(0, -1) cannot take no rows)
        v = v.reshape(len(t), int(np.prod(v.shape[1:], dtype=np.int64)))
    q = np.asarray(queries, dtype=np.int64)
    _, ok = nearest_within(t, q, tolerance)
    if len(t) == 0:
        return np.zeros((len(q), v.shape[1])), ok
    hi = np.clip(np.searchsorted(t, q, side="right"), 1, max(len(t) - 1, 1))
    lo = hi - 1
    if len(t) == 1:
        lo = hi = np.zeros(len(q), np.int64)
    span = (t[hi] - t[lo]).astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(span > 0, (q - t[lo]) / span, 0.0)
    w = np.clip(w, 0.0, 1.0)[:, None]
    d = v[hi] - v[lo]
    cols = list(angle_columns)
    if cols:
        d[:, cols] = np.angle(np.exp(1j * d[:, cols]))  # the shorter arc
    out = v[lo] + w * d
    if cols:
        out[:, cols] = np.angle(np.exp(1j * out[:, cols]))
        out[:, cols] = np.where(out[:, cols] <= -np.pi, np.pi, out[:, cols])
    return out, ok
