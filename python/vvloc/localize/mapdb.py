"""The map database: keyframes with poses and descriptors, stored as one HDF5 file.

A map holds, per keyframe (row ``i`` of every per-keyframe dataset, ``N`` rows):

* ``ids`` (N,) int64: keyframe id, unique in the map;
* ``session_index`` (N,) int32: row of ``session_names`` (S,) utf-8, the recording sessions in
  order of first appearance;
* ``seq`` (N,) int64: sequence number of the frame in its session;
* ``timestamps`` (N,) float64: seconds;
* ``poses`` (N, 3) float64: (x, y, yaw) in the world frame (x east, y north, metres; yaw
  counter-clockwise about z, radians);
* ``floors`` (N,) int64: floor / level number;
* ``global_descriptors`` (N, Dg) float32 or float16: global descriptor G (L2-normalised);
* ``local_descriptors`` (N, T, C) float32 or float16: local-view descriptor D;
* ``bev`` (N, H, W, C) float16, optional: BEV queries Q (channels-last), for loop closure;

and as file attributes: ``format`` (``"vvloc-map"``), ``format_version``, ``vvloc_version``,
``created_utc`` (ISO 8601), ``model_config_hash``, ``model_config_json``, ``grid_size`` (BEV
cell size g, metres), ``descriptor_dtype`` and ``num_keyframes``; optionally
``model_weights_hash``, the fingerprint of the weights the map was built with, and
``rig_json``, the cameras that built it.

Integrity (format version 2): the file uses HDF5 1.10's structures (``libver="v110"``), whose
metadata (superblock, object headers with their attributes, chunk indexes) carries checksums
that HDF5 verifies before it parses them; text (attributes, ``session_names``) is stored as
fixed-length UTF-8; and a file attribute ``attributes_sha256`` holds the SHA-256 of every
other file attribute (HDF5 stores a value over about 4 KiB, such as a long model config, in a
heap object without a checksum of its own). Every per-keyframe dataset is chunked
with HDF5's Fletcher-32 filter (a corrupted chunk fails when it is read), and every dataset
carries a ``sha256`` attribute of its stored bytes (little-endian, C order).
:meth:`MapDatabase.open` verifies the SHA-256 of every small dataset (all but the local
descriptors and the BEVs, which are read lazily); :meth:`MapDatabase.verify` checks all of them
(and that the lazy ones are finite). Before it reads anything, :meth:`MapDatabase.open` refuses
a file that says version 2 without those structures (superblock version 2 or later, version-2
object headers), and a dataset that does not store, uncompressed, every byte its shape declares
(a crafted shape would otherwise be allocated by the first read). So a damaged file is refused
with :class:`MapError` instead of being read as other values (``tests/test_mapdb.py`` flips
single bits all over a map file). Version 1 (vvloc before
2026-12-05) stored text as HDF5 variable-length strings in the global heap, which has no
checksum, and used HDF5's oldest structures: a flipped bit could change an attribute unnoticed,
or crash or hang HDF5 itself. Version-1 maps are still read, without that protection;
``MapDatabase.open(old).save(new)`` rewrites one as version 2.

Files are written atomically (:mod:`vvloc._io`): a temporary file in the same directory, fsync,
``os.replace``. A failed or interrupted write leaves no temporary file and leaves an existing
map at the destination untouched. Maps are opened read-only (h5py mode ``"r"``); the arrays
held in memory (poses, global descriptors, ids, ...) are returned as read-only arrays, lazy
reads (local descriptors, BEVs) as fresh float32 copies.

A map built with another model is refused: pass the model's config hash as
``expected_config_hash`` (and its weights fingerprint as ``expected_weights_hash``: two trained
models of one architecture share a config hash) to :meth:`MapDatabase.open`.
"""

from __future__ import annotations

import datetime as _dt
import errno
import hashlib
import json
import os
import shutil
import warnings
import weakref
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import h5py
import numpy as np
import numpy.typing as npt

from vvloc._checks import positive_float
from vvloc._io import AtomicPath
from vvloc.geometry import wrap_angle

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "MapDatabase",
    "MapError",
    "MapMetadata",
    "MapWriter",
    "check_weights",
    "model_config_hash",
]

FORMAT_NAME = "vvloc-map"
FORMAT_VERSION = 2
#: Format versions this vvloc reads (1: before the checksummed HDF5 structures of version 2).
READABLE_FORMAT_VERSIONS = (1, 2)
# HDF5 file-format bounds of version 2: HDF5 1.10's structures, every one of them checksummed.
_LIBVER = ("v110", "v110")
# The file attribute that holds the SHA-256 of all the others (version 2).
_ATTRS_DIGEST = "attributes_sha256"

DescriptorDType = Literal["float32", "float16"]
PathLike = str | os.PathLike[str]

# Per-keyframe datasets: name -> stored dtype (None: the map's descriptor dtype).
_META_DATASETS: dict[str, np.dtype[Any]] = {
    "ids": np.dtype("<i8"),
    "session_index": np.dtype("<i4"),
    "seq": np.dtype("<i8"),
    "timestamps": np.dtype("<f8"),
    "poses": np.dtype("<f8"),
    "floors": np.dtype("<i8"),
}
_BEV_DTYPE = np.dtype("<f2")
# Datasets loaded (and SHA-256 verified) on open; the others are read lazily.
_SMALL = (*_META_DATASETS, "global_descriptors")
_LAZY = ("local_descriptors", "bev")
_REQUIRED_ATTRS = (
    "format",
    "format_version",
    "vvloc_version",
    "created_utc",
    "model_config_hash",
    "model_config_json",
    "grid_size",
    "descriptor_dtype",
    "num_keyframes",
)
_SMALL_CHUNK_BYTES = 1 << 16
_LAZY_CHUNK_BYTES = 1 << 14  # paper-sized rows (>= 16 KiB) get one chunk per keyframe
_COPY_BLOCK_BYTES = 64 << 20
#: Free space a map writer keeps beyond its estimate of the file (HDF5's metadata, the chunk
#: index, the attributes): HDF5 crashes the interpreter when the disk fills under it.
_SPACE_MARGIN_BYTES = 1 << 20
_CHUNK_INDEX_BYTES = 128  # an upper bound per chunk: its index entry and checksum


class MapError(ValueError):
    """A map file is refused: not a vvloc map, corrupted, truncated, or built by another model."""


def model_config_hash(config: Mapping[str, Any] | str) -> str:
    """SHA-256 (hex) of a model config's canonical JSON (sorted keys, no whitespace).

    ``config`` is a JSON-serialisable mapping or JSON text. Two configs with the same content
    hash equally whatever their key order.
    """
    return hashlib.sha256(_canonical_json(config).encode("utf-8")).hexdigest()


def _canonical_json(config: Mapping[str, Any] | str) -> str:
    if isinstance(config, str):
        try:
            config = json.loads(config)
        except (json.JSONDecodeError, RecursionError) as e:  # RecursionError: too deep nesting
            raise ValueError(f"model_config: not valid JSON text: {e}") from e
    if not isinstance(config, Mapping):
        raise TypeError(
            f"model_config: expected a mapping or JSON object text, got {type(config).__name__}"
        )
    try:
        return json.dumps(config, sort_keys=True, separators=(",", ":"), allow_nan=False)
    except (TypeError, ValueError) as e:
        raise ValueError(f"model_config: not JSON-serialisable: {e}") from e


def _check_weights_hash(weights_hash: str | None, name: str = "weights_hash") -> str | None:
    """``weights_hash`` (a non-empty str, e.g. the 64 hex digits of ``VVLocNet.weights_hash()``,
    or None) unchanged; ``TypeError`` naming ``name`` otherwise."""
    if weights_hash is not None and (not isinstance(weights_hash, str) or not weights_hash):
        raise TypeError(f"{name}: expected a non-empty str or None, got {weights_hash!r}")
    return weights_hash


def check_weights(stored: str | None, expected: str | None, where: object) -> None:
    """Refuse a map whose weights fingerprint ``stored`` differs from ``expected`` (both the
    full strings, e.g. 64 hex digits, or None).

    Raises :class:`MapError` (naming ``where``, the map) when both are given and differ; warns
    (``UserWarning``) when ``expected`` is given and the map records no fingerprint (written
    before vvloc stored one), since such a map cannot be checked; does nothing without
    ``expected``.
    """
    expected = _check_weights_hash(expected, "expected_weights_hash")
    if expected is None:
        return
    if stored is None:
        warnings.warn(
            f"{where}: the map records no weights fingerprint (written by an older vvloc), so "
            "it cannot be checked that it was built with these weights; rebuild it to be sure",
            UserWarning,
            # this function, then MapDatabase._load or check_map_model, then MapDatabase.open,
            # Localizer() or detect_loops: the warning names their caller
            stacklevel=4,
        )
    elif stored != expected:
        raise MapError(
            f"{where}: map built with other weights of this architecture (weights {stored}, "
            f"the model in use has {expected}); rebuild the map with this model"
        )


@dataclass(frozen=True)
class MapMetadata:
    """Map-level metadata.

    ``grid_size`` is the BEV cell size g in metres; ``created_utc`` an ISO 8601 UTC time;
    ``descriptor_dtype`` the stored dtype of the global and local descriptors;
    ``model_weights_hash`` the fingerprint of the weights that built the map (``None`` for maps
    written before vvloc recorded it); ``rig`` the cameras whose frames built it
    (``vvloc.data.Camera.to_json`` entries: name, width, height, K, cam_to_ego; ``None`` when not
    recorded), which the localizer compares query frames with.
    """

    model_config_hash: str
    model_config: dict[str, Any]
    grid_size: float
    vvloc_version: str
    format_version: int
    created_utc: str
    descriptor_dtype: str
    model_weights_hash: str | None = None
    rig: list[dict[str, Any]] | None = None


# ---------------------------------------------------------------------------------------------
# Input validation


def _check_rig(rig: Any) -> list[dict[str, Any]] | None:
    """``rig``: None or a list of camera entries (``Camera.to_json``), validated by building
    each camera; returned as plain JSON-able dicts."""
    if rig is None:
        return None
    from vvloc.data.frame import Camera

    if isinstance(rig, (str, bytes, Mapping)) or not isinstance(rig, Sequence) or not rig:
        raise TypeError("rig: expected a non-empty list of camera entries (Camera.to_json)")
    try:
        return [(c if isinstance(c, Camera) else Camera.from_json(dict(c))).to_json() for c in rig]
    except (TypeError, ValueError) as e:
        raise ValueError(f"rig: {e}") from e


def _to_numpy(x: Any, name: str) -> np.ndarray:
    if hasattr(x, "detach") and hasattr(x, "cpu"):  # torch.Tensor, without importing torch
        x = x.detach().cpu().numpy()
    if x is None or isinstance(x, (str, bytes)):
        raise TypeError(f"{name}: expected an array, got {type(x).__name__}")
    try:
        return np.asarray(x)
    except ValueError as e:  # nested lists of unequal lengths
        raise ValueError(f"{name}: expected a rectangular array, got ragged rows ({e})") from None


def _float_array(
    x: Any, name: str, shape_doc: str, ndim: int, rows: int | None, dtype: npt.DTypeLike
) -> np.ndarray:
    arr = _to_numpy(x, name)
    if arr.dtype == object or arr.dtype.kind not in "fiu":
        raise TypeError(f"{name}: expected a real-valued array {shape_doc}, got dtype {arr.dtype}")
    if arr.ndim != ndim:
        raise ValueError(f"{name}: expected shape {shape_doc}, got shape {arr.shape}")
    if rows is not None and arr.shape[0] != rows:
        raise ValueError(f"{name}: expected {rows} rows {shape_doc}, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: contains non-finite values (NaN or inf)")
    with np.errstate(over="ignore"):  # overflow is detected just below
        # a copy of its own: the map neither freezes the caller's array nor sees later edits
        out = np.array(arr, dtype=dtype, order="C", copy=True)
    if not np.isfinite(out).all():
        raise ValueError(f"{name}: values overflow {np.dtype(dtype).name} (|x| too large)")
    return out


def _int_array(x: Any, name: str, rows: int) -> np.ndarray:
    arr = _to_numpy(x, name)
    if arr.ndim == 1 and arr.size == 0 and rows == 0:
        return np.zeros(0, np.int64)
    if arr.dtype.kind not in "iu":
        raise TypeError(f"{name}: expected an integer array ({rows},), got dtype {arr.dtype}")
    if arr.shape != (rows,):
        raise ValueError(f"{name}: expected shape ({rows},), got shape {arr.shape}")
    if arr.dtype.kind == "u" and arr.size and arr.max() > np.iinfo(np.int64).max:
        raise ValueError(f"{name}: values exceed the int64 range")
    return np.array(arr, dtype=np.int64, order="C", copy=True)  # the map's own copy


def _check_dtype(dtype: Any) -> DescriptorDType:
    try:
        name = np.dtype(dtype).name if not isinstance(dtype, str) else dtype
    except TypeError as e:  # np.dtype(5): "Cannot interpret '5' as a data type"
        raise TypeError(f"dtype: expected 'float32' or 'float16', got {dtype!r}") from e
    if name not in ("float32", "float16"):
        raise ValueError(f"dtype: expected 'float32' or 'float16', got {dtype!r}")
    return name  # type: ignore[return-value]


def _session_labels(sessions: Any, rows: int) -> list[str]:
    if isinstance(sessions, str):
        labels = [sessions] * rows
    else:
        if isinstance(sessions, bytes) or not isinstance(sessions, (Sequence, np.ndarray)):
            raise TypeError(
                f"sessions: expected a str or a sequence of {rows} str, got "
                f"{type(sessions).__name__}"
            )
        labels = list(sessions)
        if len(labels) != rows:
            raise ValueError(f"sessions: expected {rows} session names, got {len(labels)}")
        bad = [s for s in labels if not isinstance(s, str)]
        if bad:
            raise TypeError(f"sessions: expected str names, got {type(bad[0]).__name__}")
    if any(s == "" for s in labels):
        raise ValueError("sessions: session names must be non-empty")
    for s in labels:
        # a line break splits the CSV rows the exports write, and their readers strip fields:
        # such a session came back under another name (vvloc loops --reuse matched none of it)
        if any(ord(c) < 32 or 127 <= ord(c) < 160 for c in s):
            raise ValueError(
                f"sessions: session name {s!r} holds a control character (a line break, tab, "
                "NUL, ...): exported CSV rows would split; rename the session"
            )
        if s != s.strip():
            raise ValueError(
                f"sessions: session name {s!r} begins or ends with white space, which CSV "
                "exports do not keep; rename the session"
            )
        try:
            s.encode("utf-8")
        except UnicodeEncodeError as e:
            raise ValueError(f"sessions: session name {s!r} is not valid UTF-8 text: {e}") from e
    return labels


@dataclass
class _Batch:
    """One validated batch of k keyframes, in stored dtypes (descriptors: float32 here)."""

    ids: np.ndarray
    session_labels: list[str]
    seq: np.ndarray
    timestamps: np.ndarray
    poses: np.ndarray
    floors: np.ndarray
    global_descriptors: np.ndarray
    local_descriptors: np.ndarray
    bev: np.ndarray | None

    def __len__(self) -> int:
        return int(self.ids.shape[0])


#: How far from 1 the L2 norm of a global descriptor may be: float16 storage moves it by
#: about 1e-3; a descriptor that was never normalised is off by far more.
UNIT_TOLERANCE = 1e-2


def check_unit_rows(g: np.ndarray, name: str) -> None:
    """``ValueError`` naming ``name`` when a row of ``g`` (``(N, Dg)`` or one ``(Dg,)``
    descriptor) is not of unit L2 norm within :data:`UNIT_TOLERANCE`: descriptor distances,
    the loop radius (≤ 0.5) and re-ranking weights are defined on unit vectors, and an
    unnormalised descriptor ranks by its length instead."""
    norms = np.linalg.norm(np.atleast_2d(g).astype(np.float64), axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > UNIT_TOLERANCE)
    if bad.size:
        where = f"row {bad[0]} has" if g.ndim == 2 else "it has"
        raise ValueError(
            f"{name}: expected L2-normalised global descriptors (unit length, as the encoder "
            f"gives them), but {where} norm {norms[bad[0]]:.4g} ({bad.size} of {norms.size} not "
            "unit); divide each by its norm"
        )


def _validate_batch(
    *,
    poses: Any,
    timestamps: Any,
    sessions: Any,
    global_descriptors: Any,
    local_descriptors: Any,
    ids: Any,
    seq: Any,
    floors: Any,
    bevs: Any,
    id_start: int,
    next_seq: Mapping[str, int],
) -> _Batch:
    p = _float_array(poses, "poses", "(N, 3)", 2, None, np.float64)
    k = p.shape[0]
    if p.shape[1] != 3:
        raise ValueError(f"poses: expected shape (N, 3) = (x, y, yaw), got shape {p.shape}")
    if not ((p[:, 2] > -np.pi) & (p[:, 2] <= np.pi)).all():
        p = p.copy()  # stored as every other yaw of the package: wrapped (4π + 0.3 read back)
        p[:, 2] = wrap_angle(p[:, 2])
    t = _float_array(timestamps, "timestamps", f"({k},)", 1, k, np.float64)
    labels = _session_labels(sessions, k)
    g = _float_array(global_descriptors, "global_descriptors", f"({k}, Dg)", 2, k, np.float32)
    loc = _float_array(local_descriptors, "local_descriptors", f"({k}, T, C)", 3, k, np.float32)
    if g.shape[1] == 0 or loc.shape[1] == 0 or loc.shape[2] == 0:
        raise ValueError(
            f"descriptors: dimensions must be > 0, got global {g.shape}, local {loc.shape}"
        )
    check_unit_rows(g, "global_descriptors")
    b = None
    if bevs is not None:
        b = _float_array(bevs, "bevs", f"({k}, H, W, C)", 4, k, _BEV_DTYPE)
        if 0 in b.shape[1:]:
            raise ValueError(f"bevs: dimensions must be > 0, got shape {b.shape}")
    if ids is None:
        id_arr = np.arange(id_start, id_start + k, dtype=np.int64)
    else:
        id_arr = _int_array(ids, "ids", k)
    if seq is None:
        counters = dict(next_seq)
        seq_arr = np.empty(k, np.int64)
        for r, s in enumerate(labels):
            seq_arr[r] = counters.get(s, 0)
            counters[s] = seq_arr[r] + 1
    else:
        seq_arr = _int_array(seq, "seq", k)
    floor_arr = np.zeros(k, np.int64) if floors is None else _int_array(floors, "floors", k)
    if np.unique(id_arr).size != k:
        raise ValueError("ids: keyframe ids must be unique")
    pairs = set(zip(labels, seq_arr.tolist(), strict=True))
    if len(pairs) != k:
        raise ValueError(
            "seq: sequence numbers must be unique within a session (the sequence and loop "
            "checks find a keyframe's neighbours by them)"
        )
    return _Batch(id_arr, labels, seq_arr, t, p, floor_arr, g, loc, b)


# ---------------------------------------------------------------------------------------------
# Writing


def _mib(n: int) -> str:
    return f"{n / (1 << 20):.1f} MiB"


def _file_size_limit() -> int | None:
    """The largest file this process may write (bytes; ``RLIMIT_FSIZE``, ``ulimit -f``), or
    None when unlimited or unknown (no ``resource`` module: Windows)."""
    try:
        import resource
    except ImportError:
        return None
    soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    return None if soft == resource.RLIM_INFINITY else int(soft)


def _rows_per_chunk(row_bytes: int, target: int) -> int:
    return max(1, min(1 << 16, target // max(row_bytes, 1)))


def _le(arr: np.ndarray, dtype: np.dtype[Any]) -> np.ndarray:
    return np.ascontiguousarray(arr, dtype=dtype.newbyteorder("<"))


def _set_text(attrs: h5py.AttributeManager, key: str, value: str) -> None:
    """Store ``value`` as a fixed-length UTF-8 string attribute (format version 2).

    Fixed-length strings live inside the checksummed object header; HDF5's variable-length
    strings (version 1) live in its global heap, which has no checksum.
    """
    data = value.encode("utf-8")
    attrs.create(key, np.array(data, dtype=h5py.string_dtype("utf-8", max(1, len(data)))))


def _text(attrs: h5py.AttributeManager, key: str) -> str:
    """Read a string attribute written by :func:`_set_text` or as a version-1 str.

    Raises ``ValueError`` (reported as a corrupted map) if it is neither text nor valid UTF-8.
    """
    return _decode(attrs[key], key)


def _decode(value: Any, key: str) -> str:
    """An attribute's value as text: version 2's UTF-8 bytes decoded, version 1's str as is."""
    if isinstance(value, bytes):  # np.bytes_ is a bytes
        return value.decode("utf-8")
    if isinstance(value, str):
        return value
    raise ValueError(f"attribute {key!r} is not text: {type(value).__name__}")


def _attrs_digest(attrs: h5py.AttributeManager) -> str:
    """SHA-256 of every file attribute but :data:`_ATTRS_DIGEST` (format version 2), as
    canonical JSON: text as str, numbers as Python numbers.

    HDF5 checksums small attributes with the structures that hold them, but stores a value
    over about 4 KiB (a long model config, a rig of many cameras) in a heap object of its own
    without one."""
    values: dict[str, Any] = {}
    for key in sorted(attrs):
        if key == _ATTRS_DIGEST:
            continue
        value = attrs[key]
        if isinstance(value, (bytes, str)):
            values[key] = _decode(value, key)
        elif isinstance(value, (np.integer, int)) and not isinstance(value, bool):
            values[key] = int(value)
        elif isinstance(value, (np.floating, float)):
            values[key] = float(value).hex()  # exact
        else:
            raise ValueError(f"attribute {key!r} is neither text nor a number")
    return hashlib.sha256(json.dumps(values, sort_keys=True).encode("utf-8")).hexdigest()


def _names_digest(names: Sequence[str]) -> str:
    return hashlib.sha256(json.dumps(list(names)).encode("utf-8")).hexdigest()


def _abandon(h5: h5py.File, atomic: AtomicPath) -> None:
    """Close and delete an unfinished map (used on error and by the garbage collector)."""
    try:
        if h5.id.valid:
            h5.close()
    finally:
        atomic.abort()


class MapWriter:
    """Write a map to ``path`` batch by batch, atomically.

    ``model_config`` is the model's config (mapping or JSON text), stored as JSON; its hash is
    ``config_hash`` if given (use the model's own hash when it defines one), else
    :func:`model_config_hash`. ``weights_hash`` (optional, e.g. ``VVLocNet.weights_hash()``) is
    stored as the fingerprint of the weights that computed the descriptors. ``grid_size`` is
    the BEV cell size g (metres). ``dtype`` is the stored dtype of the global and local
    descriptors (``"float32"`` or ``"float16"``); BEVs are always stored as float16.
    ``expected_keyframes`` (optional, a hint) caps the HDF5 chunk size so that a small map does
    not occupy whole default-sized chunks. ``rig`` (optional): the cameras whose frames built
    the map, as a list of ``Camera.to_json()`` entries (:attr:`MapMetadata.rig`), against which
    the localizer checks its queries' rig.

    Usage::

        with MapWriter("map.h5", model_config=cfg, grid_size=0.3) as w:
            for batch in batches:
                w.append(poses=..., timestamps=..., sessions="s0",
                         global_descriptors=..., local_descriptors=..., bevs=...)
        # the map exists at "map.h5" only now, complete

    The data goes to a temporary file next to ``path``; :meth:`close` (the end of the ``with``
    block) writes the metadata and checksums and renames it over ``path``. An exception in the
    block, :meth:`abort`, or a failed write removes the temporary file and leaves an existing
    file at ``path`` untouched. Invalid input to :meth:`append` raises ``TypeError`` /
    ``ValueError`` before anything is written and leaves the writer usable; an error while
    writing aborts the writer.

    Before each batch and before the metadata the writer checks that the file system holds the
    map as it will be (whole chunks, their index, the metadata, a few MiB spare) and raises
    ``OSError`` (``ENOSPC``) naming the space needed, before HDF5 writes: with the disk full
    under it, HDF5 (2.0, h5py 3.16) crashes the interpreter at close. The process's file size
    limit (``ulimit -f``) is checked against the same estimate, margin included (``EFBIG``).
    Another process filling the disk between the check and the write, or a disk quota (not
    checked: no portable way to read one), can still reach that crash.
    """

    def __init__(
        self,
        path: PathLike,
        *,
        model_config: Mapping[str, Any] | str,
        grid_size: float,
        config_hash: str | None = None,
        weights_hash: str | None = None,
        dtype: DescriptorDType = "float32",
        expected_keyframes: int | None = None,
        rig: Sequence[Any] | None = None,
    ) -> None:
        self._config_json = _canonical_json(model_config)
        self._rig = _check_rig(rig)
        if config_hash is None:
            config_hash = model_config_hash(self._config_json)
        if not isinstance(config_hash, str) or not config_hash:
            raise TypeError("config_hash: expected a non-empty str")
        self._config_hash = config_hash
        self._weights_hash = _check_weights_hash(weights_hash)
        self._grid_size = positive_float(grid_size, "grid_size")
        self._dtype = np.dtype(_check_dtype(dtype)).newbyteorder("<")
        if expected_keyframes is not None and (
            isinstance(expected_keyframes, bool)
            or not isinstance(expected_keyframes, (int, np.integer))
            or expected_keyframes < 1
        ):
            raise ValueError(
                f"expected_keyframes: expected an int >= 1, got {expected_keyframes!r}"
            )
        self._max_chunk_rows = 1 << 16 if expected_keyframes is None else int(expected_keyframes)
        self.path = Path(os.fspath(path))
        self._atomic = AtomicPath(self.path, streams=False)  # HDF5 needs a seekable file
        try:
            self._h5 = h5py.File(self._atomic.tmp, "w", libver=_LIBVER)
        except BaseException:
            self._atomic.abort()
            raise
        self._finalizer = weakref.finalize(self, _abandon, self._h5, self._atomic)
        self._n = 0
        self._sessions: dict[str, int] = {}
        self._next_seq: dict[str, int] = {}
        self._seqs: dict[str, set[int]] = {}
        self._ids: set[int] = set()
        self._digests: dict[str, Any] = {}
        self._shapes: dict[str, tuple[int, ...]] = {}
        self._has_bev: bool | None = None
        self._layout: dict[str, tuple[int, int]] = {}  # dataset → (rows per chunk, row bytes)
        self._state = "open"

    def __len__(self) -> int:
        """Number of keyframes appended so far."""
        return self._n

    def append(
        self,
        *,
        poses: Any,
        timestamps: Any,
        sessions: str | Sequence[str],
        global_descriptors: Any,
        local_descriptors: Any,
        ids: Any = None,
        seq: Any = None,
        floors: Any = None,
        bevs: Any = None,
    ) -> None:
        """Append k keyframes.

        Args:
            poses: (k, 3) world-frame (x, y, yaw): metres, radians CCW (stored wrapped to
                (−π, π]).
            timestamps: (k,) seconds.
            sessions: one session name for all k, or k names.
            global_descriptors: (k, Dg) float, each row of unit L2 norm (as the encoder gives
                them; :func:`check_unit_rows`, ``ValueError`` otherwise).
            local_descriptors: (k, T, C) float.
            ids: (k,) int keyframe ids, unique in the map; default: running row numbers.
            seq: (k,) int sequence numbers, unique within a session; default: a running count
                per session.
            floors: (k,) int; default 0.
            bevs: (k, H, W, C) float BEVs, stored float16; every batch or none has them.
        """
        self._check_open()
        b = _validate_batch(
            poses=poses,
            timestamps=timestamps,
            sessions=sessions,
            global_descriptors=global_descriptors,
            local_descriptors=local_descriptors,
            ids=ids,
            seq=seq,
            floors=floors,
            bevs=bevs,
            id_start=self._n,
            next_seq=self._next_seq,
        )
        k = len(b)
        if k == 0:
            return
        with np.errstate(over="ignore"):  # overflow is detected just below
            g = _le(b.global_descriptors, self._dtype)
            loc = _le(b.local_descriptors, self._dtype)
        if not (np.isfinite(g).all() and np.isfinite(loc).all()):
            raise ValueError(f"descriptors: values overflow {self._dtype.name} (|x| too large)")
        dup = self._ids.intersection(b.ids.tolist())
        if dup:
            raise ValueError(f"ids: keyframe ids already in the map: {sorted(dup)[:5]}")
        taken = [
            (s, q)
            for s, q in zip(b.session_labels, b.seq.tolist(), strict=True)
            if q in self._seqs.get(s, ())
        ]
        if taken:
            raise ValueError(
                f"seq: (session, sequence number) already in the map: {taken[:5]} (sequence "
                "numbers must be unique within a session)"
            )
        has_bev = b.bev is not None
        if self._has_bev is not None and has_bev != self._has_bev:
            raise ValueError(
                "bevs: every batch must have BEVs or none may "
                f"(earlier batches {'had' if self._has_bev else 'had none'})"
            )
        shapes = {"global_descriptors": g.shape[1:], "local_descriptors": loc.shape[1:]}
        if b.bev is not None:
            shapes["bev"] = b.bev.shape[1:]
        for name, shape in shapes.items():
            if name in self._shapes and self._shapes[name] != shape:
                raise ValueError(
                    f"{name}: per-keyframe shape {shape} differs from earlier batches "
                    f"{self._shapes[name]}"
                )
        session_index = np.empty(k, np.int32)
        new_sessions = dict(self._sessions)
        for r, s in enumerate(b.session_labels):
            session_index[r] = new_sessions.setdefault(s, len(new_sessions))
        data: dict[str, np.ndarray] = {
            "ids": b.ids,
            "session_index": session_index,
            "seq": b.seq,
            "timestamps": b.timestamps,
            "poses": b.poses,
            "floors": b.floors,
            "global_descriptors": g,
            "local_descriptors": loc,
        }
        if b.bev is not None:
            data["bev"] = b.bev
        if self._n == 0:
            self._layout = {name: self._chunking(name, arr) for name, arr in data.items()}
        self._check_space(self._n + k)
        try:
            if self._n == 0:
                self._create_datasets(data)
            for name, arr in data.items():
                stored = _le(arr, self._h5[name].dtype)
                ds = self._h5[name]
                ds.resize(self._n + k, axis=0)
                ds[self._n : self._n + k] = stored
                self._digests[name].update(stored.data)
        except BaseException:
            self.abort()
            raise
        self._n += k
        self._sessions = new_sessions
        self._ids.update(b.ids.tolist())
        for s, q in zip(b.session_labels, b.seq.tolist(), strict=True):
            self._next_seq[s] = max(self._next_seq.get(s, 0), q + 1)
            self._seqs.setdefault(s, set()).add(q)
        self._shapes.update(shapes)
        self._has_bev = has_bev

    def append_map(self, db: MapDatabase) -> None:
        """Append every keyframe of ``db`` as it stores them: ids, session names, sequence
        numbers, times, poses, floors, descriptors (converted to this writer's dtype) and
        BEVs, in ``db``'s row order, a block of rows at a time.

        ``db`` must come from the model this writer records: :class:`MapError` (a
        ``ValueError``) when its model config hash or grid size differs, or its weights
        fingerprint does, or it records none while this writer records one (its keyframes
        would then pass for these weights'); ``ValueError`` when its ids or (session, sequence
        number) pairs are already in this writer, or it has BEVs and earlier batches had none
        or the reverse. Nothing is written then. The rigs are not compared (the caller's part:
        :func:`vvloc.build_map` with ``base`` does).
        """
        self._check_open()
        if not isinstance(db, MapDatabase):
            raise TypeError(f"db: expected a MapDatabase, got {type(db).__name__}")
        db._check_open()
        where = db.label
        meta = db.metadata
        if meta.model_config_hash != self._config_hash:
            raise MapError(
                f"db: {where} was built with model {meta.model_config_hash}, this writer's is "
                f"{self._config_hash}: one map holds the descriptors of one model"
            )
        theirs, ours = meta.model_weights_hash, self._weights_hash
        if ours is not None and theirs is None:
            raise MapError(
                f"db: {where} records no weights fingerprint (written by an older vvloc), so "
                f"nothing shows that the weights {ours} built it; build the map anew"
            )
        if ours is not None and theirs != ours:
            raise MapError(
                f"db: {where} was built with other weights (weights {theirs}, this writer's "
                f"{ours}): one map holds the descriptors of one model"
            )
        if meta.grid_size != self._grid_size:
            raise MapError(
                f"db: {where} has BEV cells of {meta.grid_size:g} m, this writer "
                f"{self._grid_size:g} m"
            )
        if len(db) == 0:
            return
        dup = self._ids.intersection(db.ids.tolist())
        if dup:
            raise ValueError(f"db: keyframe ids already in the map: {sorted(dup)[:5]}")
        sessions = db.sessions
        taken = [
            (sessions[s], q)
            for s, q in zip(db.session_index.tolist(), db.seq.tolist(), strict=True)
            if q in self._seqs.get(sessions[s], ())
        ]
        if taken:  # checked here for every block: a refusal half-way would keep half the map
            raise ValueError(
                f"db: (session, sequence number) already in the map: {taken[:5]} (sequence "
                "numbers are unique within a session)"
            )
        if self._has_bev is not None and db.has_bev != self._has_bev:
            raise ValueError(
                f"db: {where} {'has' if db.has_bev else 'has no'} BEVs and earlier batches "
                f"{'had' if self._has_bev else 'had none'}: every keyframe of a map has a BEV "
                "or none has"
            )
        row_bytes = int(np.prod(db.local_shape)) * 4
        if db.bev_shape is not None:
            row_bytes += int(np.prod(db.bev_shape)) * 2
        block = max(1, _COPY_BLOCK_BYTES // row_bytes)
        for start in range(0, len(db), block):
            rows = np.arange(start, min(start + block, len(db)))
            self.append(
                ids=db.ids[rows],
                sessions=[sessions[s] for s in db.session_index[rows]],
                seq=db.seq[rows],
                timestamps=db.timestamps[rows],
                poses=db.poses[rows],
                floors=db.floors[rows],
                global_descriptors=db.global_descriptors[rows],
                local_descriptors=db.local_descriptors(rows),
                bevs=db.bev(rows) if db.has_bev else None,
            )

    def _stored_dtype(self, name: str) -> np.dtype[Any]:
        return _META_DATASETS.get(name, _BEV_DTYPE if name == "bev" else self._dtype)

    def _chunking(self, name: str, arr: np.ndarray) -> tuple[int, int]:
        """(rows per chunk, bytes per row) of dataset ``name`` holding rows like ``arr``'s."""
        row_bytes = int(np.prod(arr.shape[1:], dtype=np.int64)) * self._stored_dtype(name).itemsize
        target = _LAZY_CHUNK_BYTES if name in _LAZY else _SMALL_CHUNK_BYTES
        return min(self._max_chunk_rows, _rows_per_chunk(row_bytes, target)), row_bytes

    def _check_space(self, rows: int) -> None:
        """``OSError`` (``ENOSPC``) unless the temporary file's file system can take the map of
        ``rows`` keyframes (whole chunks, their index, the metadata and a margin) beyond what
        the file holds now; ``OSError`` (``EFBIG``) when the process may not write a file of
        that size (``ulimit -f``: HDF5 crashes at close on that as on a full disk)."""
        size = _SPACE_MARGIN_BYTES + 2 * len(self._config_json) + 64 * (len(self._sessions) + 1)
        if self._rig is not None:
            size += 2 * len(json.dumps(self._rig))
        for chunk_rows, row_bytes in self._layout.values():
            chunks = -(-rows // chunk_rows)
            size += chunks * (chunk_rows * row_bytes + _CHUNK_INDEX_BYTES)
        limit = _file_size_limit()
        if limit is not None and size > limit:
            raise OSError(
                errno.EFBIG,
                f"{self.path}: the map is too large for this process's file size limit: "
                f"{rows} keyframes need about {_mib(size)}, files may hold {_mib(limit)} "
                "(ulimit -f)",
            )
        try:
            held = os.stat(self._atomic.tmp).st_blocks * 512
            free = shutil.disk_usage(self._atomic.tmp.parent).free
        except (OSError, AttributeError):  # no st_blocks (Windows) or no statvfs: unchecked
            return
        if free < size - held:
            raise OSError(
                errno.ENOSPC,
                f"{self.path}: not enough free space for the map: {rows} keyframes need about "
                f"{_mib(size - held)} more, {_mib(free)} are free on {self._atomic.tmp.parent}",
            )

    def _create_datasets(self, data: Mapping[str, np.ndarray]) -> None:
        for name, arr in data.items():
            tail = arr.shape[1:]
            chunk_rows, _ = self._layout[name]
            self._h5.create_dataset(
                name,
                shape=(0, *tail),
                maxshape=(None, *tail),
                dtype=self._stored_dtype(name),
                chunks=(chunk_rows, *tail),
                fletcher32=True,
            )
            self._digests[name] = hashlib.sha256()

    def close(self) -> Path:
        """Finish the map: write metadata and checksums, then rename it to ``path``.

        Returns the path. Raises ``ValueError`` (and aborts) if no keyframe was appended.
        """
        self._check_open()
        if self._n == 0:
            self.abort()
            raise ValueError(f"{self.path}: a map needs at least one keyframe; nothing written")
        from vvloc import __version__

        try:
            self._check_space(self._n)  # the disk may have filled since the last batch
            names = list(self._sessions)
            width = max(1, *(len(n.encode("utf-8")) for n in names))
            ds = self._h5.create_dataset(
                "session_names",
                data=[n.encode("utf-8") for n in names],
                dtype=h5py.string_dtype("utf-8", width),
            )
            _set_text(ds.attrs, "sha256", _names_digest(names))
            for name, digest in self._digests.items():
                _set_text(self._h5[name].attrs, "sha256", digest.hexdigest())
            attrs = self._h5.attrs
            text = {
                "format": FORMAT_NAME,
                "vvloc_version": __version__,
                "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                "model_config_hash": self._config_hash,
                "model_config_json": self._config_json,
                "descriptor_dtype": self._dtype.name,
            }
            if self._weights_hash is not None:
                text["model_weights_hash"] = self._weights_hash
            if self._rig is not None:
                text["rig_json"] = json.dumps(self._rig)
            for key, value in text.items():
                _set_text(attrs, key, value)
            attrs["format_version"] = np.int64(FORMAT_VERSION)
            attrs["grid_size"] = np.float64(self._grid_size)
            attrs["num_keyframes"] = np.int64(self._n)
            _set_text(attrs, _ATTRS_DIGEST, _attrs_digest(attrs))
            self._h5.close()
            self._finalizer.detach()
            self._atomic.commit()
        except BaseException:
            self.abort()
            raise
        self._state = "closed"
        return self.path

    def abort(self) -> None:
        """Discard everything written; ``path`` is left as it was. Idempotent."""
        self._state = "aborted" if self._state != "closed" else self._state
        if self._finalizer.alive:
            self._finalizer()

    def _check_open(self) -> None:
        if self._state != "open":
            raise ValueError(f"{self.path}: map writer is {self._state}")

    def __enter__(self) -> MapWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is not None:
            self.abort()
        elif self._state == "open":
            self.close()
        elif self._state == "aborted":  # a failed write was caught inside the block
            raise MapError(f"{self.path}: the map writer was aborted; nothing was written")


def is_map_file(path: PathLike) -> bool:
    """Whether ``path`` is an HDF5 file whose ``format`` attribute names a vvloc map (of any
    version, its data not checked): what ``vvloc map build --overwrite`` may replace."""
    try:
        with h5py.File(os.fspath(path), "r") as h5:
            fmt = h5.attrs["format"] if "format" in h5.attrs else None
    except Exception:  # not HDF5, unreadable, damaged header: not known to be a map
        return False
    if isinstance(fmt, bytes):
        fmt = fmt.decode("utf-8", errors="replace")
    return fmt == FORMAT_NAME


# ---------------------------------------------------------------------------------------------
# Reading


def _readonly(arr: np.ndarray) -> np.ndarray:
    arr.setflags(write=False)
    return arr


def _as_indices(indices: Any, n: int) -> tuple[np.ndarray, bool]:
    """Validate keyframe row indices: (int64 (k,), whether a scalar was given)."""
    if isinstance(indices, (bool, np.bool_)):
        raise TypeError("indices: expected an int or a 1-D integer array, got bool")
    arr = _to_numpy(indices, "indices")
    if arr.size == 0 and arr.ndim == 1:
        return np.zeros(0, np.int64), False
    if arr.dtype.kind not in "iu":
        raise TypeError(f"indices: expected integer indices, got dtype {arr.dtype}")
    if arr.ndim > 1:
        raise ValueError(f"indices: expected an int or a 1-D array, got shape {arr.shape}")
    if arr.size and (arr.min() < 0 or arr.max() >= n):
        raise IndexError(
            f"indices: keyframe rows must be in [0, {n}), got values in [{arr.min()}, {arr.max()}]"
        )
    return arr.astype(np.int64).reshape(-1), arr.ndim == 0


def _take(storage: np.ndarray | h5py.Dataset, idx: np.ndarray) -> np.ndarray:
    if isinstance(storage, np.ndarray):
        return storage[idx]
    if idx.size == 0:
        return np.empty((0, *storage.shape[1:]), storage.dtype)
    uniq, inverse = np.unique(idx, return_inverse=True)
    # One hyperslab read per run of consecutive rows: h5py's point (fancy) selection is ~40x
    # slower than plain slices for a handful of scattered rows.
    breaks = np.flatnonzero(np.diff(uniq) != 1) + 1
    starts = np.concatenate([[0], breaks])
    stops = np.concatenate([breaks, [uniq.size]])
    data = np.empty((uniq.size, *storage.shape[1:]), storage.dtype)
    for a, b in zip(starts.tolist(), stops.tolist(), strict=True):
        data[a:b] = storage[int(uniq[a]) : int(uniq[b - 1]) + 1]
    return data[inverse.reshape(-1)]


class MapDatabase:
    """A map of keyframes, in memory (:meth:`from_arrays`) or opened from a file (:meth:`open`).

    Row ``i`` of every accessor is keyframe ``i``. Small arrays (poses, global descriptors, ids,
    ...) are held in memory as read-only arrays; the local descriptors and BEVs of an opened map
    are read from the file on demand (:meth:`local_descriptors`, :meth:`bev`). An opened map
    holds the file open (read-only) until :meth:`close` or the end of a ``with`` block.
    """

    def __init__(
        self,
        *,
        metadata: MapMetadata,
        ids: np.ndarray,
        session_names: Sequence[str],
        session_index: np.ndarray,
        seq: np.ndarray,
        timestamps: np.ndarray,
        poses: np.ndarray,
        floors: np.ndarray,
        global_descriptors: np.ndarray,
        local_descriptors: np.ndarray | h5py.Dataset,
        bev: np.ndarray | h5py.Dataset | None,
        path: Path | None = None,
        h5file: h5py.File | None = None,
    ) -> None:
        """Internal: use :meth:`from_arrays` or :meth:`open`."""
        self._metadata = metadata
        self._ids = _readonly(ids)
        self._session_names = tuple(session_names)
        self._session_index = _readonly(session_index)
        self._seq = _readonly(seq)
        self._timestamps = _readonly(timestamps)
        self._poses = _readonly(poses)
        self._floors = _readonly(floors)
        self._global = _readonly(global_descriptors)
        self._local = local_descriptors
        self._bev = bev
        t, c = local_descriptors.shape[1:]
        self._local_shape = (int(t), int(c))
        self._bev_shape = None if bev is None else tuple(int(d) for d in bev.shape[1:])
        self._path = path
        self._h5 = h5file
        self._id_to_row: dict[int, int] | None = None
        self._closed = False

    # -- construction ---------------------------------------------------------------------

    @classmethod
    def from_arrays(
        cls,
        *,
        poses: Any,
        timestamps: Any,
        sessions: str | Sequence[str],
        global_descriptors: Any,
        local_descriptors: Any,
        model_config: Mapping[str, Any] | str,
        grid_size: float,
        config_hash: str | None = None,
        weights_hash: str | None = None,
        ids: Any = None,
        seq: Any = None,
        floors: Any = None,
        bevs: Any = None,
        rig: Sequence[Any] | None = None,
    ) -> MapDatabase:
        """Build an in-memory map of N keyframes (see :meth:`MapWriter.append` for the arrays).

        Descriptors are held as float32, BEVs as float16. ``model_config`` /
        ``config_hash`` / ``weights_hash`` / ``grid_size`` as for :class:`MapWriter`. Save
        with :meth:`save`; to build a map too large for memory batch by batch, use
        :class:`MapWriter`.
        """
        b = _validate_batch(
            poses=poses,
            timestamps=timestamps,
            sessions=sessions,
            global_descriptors=global_descriptors,
            local_descriptors=local_descriptors,
            ids=ids,
            seq=seq,
            floors=floors,
            bevs=bevs,
            id_start=0,
            next_seq={},
        )
        if len(b) == 0:
            raise ValueError("poses: a map needs at least one keyframe, got 0")
        config_json = _canonical_json(model_config)
        if config_hash is None:
            config_hash = model_config_hash(config_json)
        if not isinstance(config_hash, str) or not config_hash:
            raise TypeError("config_hash: expected a non-empty str")
        weights_hash = _check_weights_hash(weights_hash)
        from vvloc import __version__

        names: dict[str, int] = {}
        session_index = np.array(
            [names.setdefault(s, len(names)) for s in b.session_labels], np.int32
        )
        metadata = MapMetadata(
            model_config_hash=config_hash,
            model_config=json.loads(config_json),
            grid_size=positive_float(grid_size, "grid_size"),
            vvloc_version=__version__,
            format_version=FORMAT_VERSION,
            created_utc=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            descriptor_dtype="float32",
            model_weights_hash=weights_hash,
            rig=_check_rig(rig),
        )
        return cls(
            metadata=metadata,
            ids=b.ids,
            session_names=list(names),
            session_index=session_index,
            seq=b.seq,
            timestamps=b.timestamps,
            poses=b.poses,
            floors=b.floors,
            global_descriptors=b.global_descriptors,
            local_descriptors=b.local_descriptors,
            bev=b.bev,
        )

    @classmethod
    def open(
        cls,
        path: PathLike,
        expected_config_hash: str | None = None,
        *,
        expected_weights_hash: str | None = None,
        verify: bool = True,
    ) -> MapDatabase:
        """Open a map file read-only.

        Args:
            path: the HDF5 map file.
            expected_config_hash: if given, the map must have been built with a model of this
                config hash (refused otherwise).
            expected_weights_hash: if given, the map must have been built with weights of this
                fingerprint (refused otherwise; a map that records none, written before vvloc
                stored it, is opened with a ``UserWarning`` that it cannot be checked).
            verify: check the SHA-256 of the small datasets (poses, global descriptors, ...);
                :meth:`verify` checks the lazily read ones too.

        Raises:
            FileNotFoundError: no file at ``path``.
            TypeError: ``path`` not a str or ``os.PathLike``; ``expected_config_hash`` or
                ``expected_weights_hash`` neither a non-empty str nor None.
            MapError: not an HDF5 file, not a vvloc map, corrupted or truncated, missing
                datasets or attributes, another format version, inconsistent lengths, checksum
                mismatch, or a config hash or weights fingerprint other than the expected
                ones. The message names the file.
        """
        _check_weights_hash(expected_weights_hash, "expected_weights_hash")
        if expected_config_hash is not None and (
            not isinstance(expected_config_hash, str) or not expected_config_hash
        ):
            raise TypeError(
                "expected_config_hash: expected a non-empty str or None, got "
                f"{type(expected_config_hash).__name__}"
            )
        if not isinstance(path, (str, os.PathLike)):  # os.fspath said it without the name
            raise TypeError(f"path: expected a str or os.PathLike, got {type(path).__name__}")
        p = Path(os.fspath(path))
        if not p.exists():
            raise FileNotFoundError(f"map file not found: {p}")
        if not p.is_file():
            raise MapError(f"{p}: not a map file (a directory or special file)")
        try:
            h5 = h5py.File(p, "r")
        except OSError as e:
            if not h5py.is_hdf5(p):
                raise MapError(f"{p}: not a vvloc map: not an HDF5 file") from e
            if "unable to lock file" in str(e):
                raise MapError(
                    f"{p}: cannot open the map: another process holds it open for writing ({e})"
                ) from e
            raise MapError(f"{p}: cannot open the map: corrupted or truncated file ({e})") from e
        try:
            return cls._load(h5, p, expected_config_hash, expected_weights_hash, verify)
        except MapError:
            h5.close()
            raise
        except (
            OSError,
            KeyError,
            ValueError,
            TypeError,
            RuntimeError,
            ArithmeticError,  # e.g. int() of an inf attribute
            AttributeError,  # e.g. a scalar dataset where an array belongs
            IndexError,
        ) as e:
            h5.close()
            raise MapError(f"{p}: corrupted map: {type(e).__name__}: {e}") from e
        except BaseException:
            h5.close()
            raise

    @classmethod
    def _load(
        cls,
        h5: h5py.File,
        p: Path,
        expected_config_hash: str | None,
        expected_weights_hash: str | None,
        verify: bool,
    ) -> MapDatabase:
        version, config_hash, weights_hash, descriptor_dtype = _check_header(
            h5.attrs, p, expected_config_hash, expected_weights_hash
        )
        if version >= 2:
            _check_structures(h5, p)
        n, has_bev = _check_datasets(h5, p, descriptor_dtype)
        small, names = _read_small(h5, p, n, verify)
        return cls(
            metadata=_read_metadata(
                h5.attrs, p, version, config_hash, weights_hash, descriptor_dtype
            ),
            ids=small["ids"].astype(np.int64),
            session_names=names,
            session_index=small["session_index"].astype(np.int32),
            seq=small["seq"].astype(np.int64),
            timestamps=small["timestamps"].astype(np.float64),
            poses=small["poses"].astype(np.float64),
            floors=small["floors"].astype(np.int64),
            global_descriptors=small["global_descriptors"].astype(np.float32),
            local_descriptors=h5["local_descriptors"],
            bev=h5["bev"] if has_bev else None,
            path=p,
            h5file=h5,
        )

    # -- persistence ----------------------------------------------------------------------

    def save(self, path: PathLike, dtype: DescriptorDType = "float32") -> Path:
        """Write the map to one HDF5 file at ``path``, atomically; return the path.

        ``dtype`` is the stored dtype of the global and local descriptors; BEVs are stored
        float16. Overwriting the file this map was opened from is allowed (the open handle
        keeps reading the old file until :meth:`close`).
        """
        self._check_open()
        meta = self._metadata
        with MapWriter(
            path,
            model_config=meta.model_config,
            grid_size=meta.grid_size,
            config_hash=meta.model_config_hash,
            weights_hash=meta.model_weights_hash,
            dtype=dtype,
            expected_keyframes=len(self),
            rig=meta.rig,
        ) as w:
            w.append_map(self)
        return w.path

    def verify(self) -> None:
        """Check the SHA-256 of every dataset in the file, including the lazily read ones, and
        that the local descriptors and BEVs are finite (as :meth:`open` checks the others).

        Reads the whole file. Raises :class:`MapError` on a mismatch, an unreadable chunk or a
        non-finite value.
        Does nothing for an in-memory map.
        """
        self._check_open()
        if self._h5 is None or self._path is None:
            return
        try:
            names = self._h5["session_names"].asstr()[()].tolist()
        except OSError as e:
            raise MapError(f"{self._path}: corrupted map: cannot read session_names: {e}") from e
        _check_digest(self._path, self._h5["session_names"], _names_digest(names))
        for name in (*_SMALL, *_LAZY):
            if name not in self._h5:
                continue
            ds = self._h5[name]
            _stored_digest(self._path, ds)  # before reading what may be gigabytes
            row_bytes = max(1, int(np.prod(ds.shape[1:])) * ds.dtype.itemsize)
            block = max(1, _COPY_BLOCK_BYTES // row_bytes)
            digest = hashlib.sha256()
            finite = True
            try:
                for start in range(0, ds.shape[0], block):
                    rows = ds[start : start + block]
                    digest.update(_le(rows, ds.dtype).data)
                    finite = finite and (rows.dtype.kind != "f" or bool(np.isfinite(rows).all()))
            except OSError as e:
                raise MapError(f"{self._path}: corrupted map: cannot read {name!r}: {e}") from e
            _check_digest(self._path, ds, digest.hexdigest())
            if not finite:  # open() checks the small datasets; the lazy ones are read here
                raise MapError(f"{self._path}: corrupted map: non-finite {name.replace('_', ' ')}")

    def close(self) -> None:
        """Close the file of an opened map (idempotent); lazy accessors then raise."""
        if self._h5 is not None and self._h5.id.valid:
            self._h5.close()
        self._closed = True

    def __enter__(self) -> MapDatabase:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def _check_open(self) -> None:
        if self._closed:
            raise ValueError(f"map {self._path or '(in memory)'} is closed")

    # -- accessors ------------------------------------------------------------------------

    def __len__(self) -> int:
        return int(self._ids.shape[0])

    def __repr__(self) -> str:
        where = str(self._path) if self._path is not None else "in memory"
        return (
            f"MapDatabase({where}: {len(self)} keyframes, sessions {list(self._session_names)}, "
            f"global {self.global_dim}, local {self.local_shape}, bev {self.bev_shape})"
        )

    @property
    def path(self) -> Path | None:
        """The file an opened map was read from; ``None`` for an in-memory map."""
        return self._path

    @property
    def label(self) -> str:
        """The map in messages: ``"map <path>"``, or ``"in-memory map"``."""
        return "in-memory map" if self._path is None else f"map {self._path}"

    @property
    def metadata(self) -> MapMetadata:
        """The map's :class:`MapMetadata` (the model's config and fingerprints, grid size,
        descriptor dtype, rig, versions), as recorded when it was built."""
        return self._metadata

    @property
    def config_hash(self) -> str:
        """The model config hash the map was built with."""
        return self._metadata.model_config_hash

    @property
    def weights_hash(self) -> str | None:
        """The fingerprint of the weights the map was built with (``None``: not recorded)."""
        return self._metadata.model_weights_hash

    @property
    def model_config(self) -> dict[str, Any]:
        """The model config the map was built with (a copy)."""
        return json.loads(json.dumps(self._metadata.model_config))

    @property
    def grid_size(self) -> float:
        """BEV cell size g in metres."""
        return self._metadata.grid_size

    @property
    def rig(self) -> list[dict[str, Any]] | None:
        """The cameras whose frames built the map (``Camera.to_json`` entries), or ``None``
        for a map that does not record them (built before 2026-12-05, or from arrays)."""
        return self._metadata.rig

    @property
    def ids(self) -> np.ndarray:
        """(N,) int64 keyframe ids."""
        return self._ids

    @property
    def poses(self) -> np.ndarray:
        """(N, 3) float64 world-frame poses (x, y, yaw): metres, radians CCW about z."""
        return self._poses

    @property
    def timestamps(self) -> np.ndarray:
        """(N,) float64 timestamps in seconds."""
        return self._timestamps

    @property
    def seq(self) -> np.ndarray:
        """(N,) int64 sequence numbers within each keyframe's session."""
        return self._seq

    @property
    def floors(self) -> np.ndarray:
        """(N,) int64 floor numbers."""
        return self._floors

    @property
    def sessions(self) -> tuple[str, ...]:
        """Session names, in order of first appearance; ``session_index`` rows point here."""
        return self._session_names

    @property
    def session_index(self) -> np.ndarray:
        """(N,) int32: keyframe i belongs to session ``sessions[session_index[i]]``."""
        return self._session_index

    def session_of(self, row: int) -> str:
        """The session name of keyframe row ``row``."""
        idx, _ = _as_indices(row, len(self))
        if idx.size != 1:
            raise ValueError(f"row: expected one int, got {row!r}")
        return self._session_names[int(self._session_index[idx[0]])]

    def session_rows(self, session: str) -> np.ndarray:
        """(k,) int64 rows of the keyframes of ``session``, sorted by (seq, row)."""
        if session not in self._session_names:
            raise KeyError(f"session {session!r} not in map (sessions: {list(self.sessions)})")
        rows = np.flatnonzero(self._session_index == self._session_names.index(session))
        return rows[np.argsort(self._seq[rows], kind="stable")].astype(np.int64)

    def row_of(self, keyframe_id: int) -> int:
        """The row of the keyframe with id ``keyframe_id`` (``KeyError`` if absent, ``TypeError``
        for anything but an int: 1.7 read as id 1)."""
        if isinstance(keyframe_id, (bool, np.bool_)) or not isinstance(
            keyframe_id, (int, np.integer)
        ):
            raise TypeError(f"keyframe_id: expected an int, got {type(keyframe_id).__name__}")
        if self._id_to_row is None:
            self._id_to_row = {int(k): r for r, k in enumerate(self._ids.tolist())}
        try:
            return self._id_to_row[int(keyframe_id)]
        except KeyError:
            raise KeyError(f"keyframe id {keyframe_id} not in map") from None

    @property
    def global_descriptors(self) -> np.ndarray:
        """(N, Dg) float32 global descriptors (converted from float16 if stored so)."""
        return self._global

    @property
    def global_dim(self) -> int:
        """Dg, the global descriptor dimension."""
        return int(self._global.shape[1])

    @property
    def local_shape(self) -> tuple[int, int]:
        """(T, C) of the local-view descriptors."""
        return self._local_shape

    @property
    def bev_shape(self) -> tuple[int, int, int] | None:
        """(H, W, C) of the stored BEVs, or ``None`` if the map has none."""
        return self._bev_shape  # type: ignore[return-value]

    @property
    def has_bev(self) -> bool:
        """Whether the map stores each keyframe's BEV (needed for loop closure only; ``vvloc
        map build`` stores them unless ``--no_bev``; DESIGN.md "Localization frames")."""
        return self._bev is not None

    def local_descriptors(self, indices: Any) -> np.ndarray:
        """Local-view descriptors of keyframe rows ``indices`` as float32.

        ``indices``: an int → (T, C); a 1-D integer array of k rows (any order, repeats
        allowed) → (k, T, C). Read from the file for an opened map.
        """
        return self._read("local_descriptors", self._local, indices)

    def bev(self, indices: Any) -> np.ndarray:
        """BEVs of keyframe rows ``indices`` as float32 (stored float16).

        ``indices``: an int → (H, W, C); a 1-D integer array of k rows → (k, H, W, C).
        Raises ``ValueError`` if the map has no BEVs.
        """
        if self._bev is None:
            raise ValueError(f"map {self._path or '(in memory)'} has no BEVs")
        return self._read("bev", self._bev, indices)

    def _read(self, name: str, storage: np.ndarray | h5py.Dataset, indices: Any) -> np.ndarray:
        self._check_open()
        idx, scalar = _as_indices(indices, len(self))
        try:
            out = _take(storage, idx)
        except OSError as e:
            raise MapError(
                f"{self._path}: corrupted map: cannot read {name!r} of rows {idx.tolist()[:8]}: {e}"
            ) from e
        out = out.astype(np.float32)
        return out[0] if scalar else out


def _stored_digest(p: Path, ds: h5py.Dataset) -> str:
    """The ``sha256`` attribute of dataset ``ds``; :class:`MapError` when it is missing or
    cannot be read."""
    try:
        stored = ds.attrs.get("sha256")
        stored = None if stored is None else _decode(stored, "sha256")
    except (OSError, ValueError, TypeError) as e:  # HDF5 cannot read the attribute: damaged
        raise MapError(f"{p}: corrupted map: cannot read the checksum of {ds.name!r}: {e}") from e
    if stored is None:
        raise MapError(f"{p}: corrupted map: dataset {ds.name!r} has no sha256 checksum")
    return stored


def _check_digest(p: Path, ds: h5py.Dataset, actual: str) -> None:
    stored = _stored_digest(p, ds)
    if stored != actual:
        raise MapError(
            f"{p}: corrupted map: checksum mismatch in dataset {ds.name!r} "
            f"(stored sha256 {stored[:16]}…, data {actual[:16]}…)"
        )


def _check_header(
    attrs: Any,
    p: Path,
    expected_config_hash: str | None,
    expected_weights_hash: str | None,
) -> tuple[int, str, str | None, str]:
    """A map file's header (HDF5 attributes) checked: the format and its version, the
    attributes' checksum (version 2), the model's config and weights fingerprints against the
    expected ones, the descriptor dtype. Returns ``(format_version, model_config_hash,
    model_weights_hash or None, descriptor_dtype)``; :class:`MapError` naming ``p`` otherwise."""
    # `in` and [] raise on a damaged header (a corrupted map); .get would say None
    fmt = attrs["format"] if "format" in attrs else None
    if isinstance(fmt, bytes):  # version 2 (fixed-length UTF-8); version 1 reads as str
        fmt = fmt.decode("utf-8", errors="replace")
    if not isinstance(fmt, str) or fmt != FORMAT_NAME:
        raise MapError(f"{p}: not a vvloc map (attribute 'format' is {fmt!r})")
    missing = [a for a in _REQUIRED_ATTRS if a not in attrs]
    if missing:
        raise MapError(f"{p}: corrupted map: missing attributes {missing}")
    version = int(attrs["format_version"])
    if version not in READABLE_FORMAT_VERSIONS:
        raise MapError(
            f"{p}: map format version {version} (written by vvloc "
            f"{_text(attrs, 'vvloc_version')}), but this vvloc reads format versions "
            f"{', '.join(map(str, READABLE_FORMAT_VERSIONS))}; rebuild the map"
        )
    if version >= 2:  # every attribute's value, whichever HDF5 structure holds it
        stored = _text(attrs, _ATTRS_DIGEST) if _ATTRS_DIGEST in attrs else None
        if stored != _attrs_digest(attrs):
            raise MapError(
                f"{p}: corrupted map: "
                + ("no attribute checksum" if stored is None else "attribute checksum mismatch")
            )
    config_hash = _text(attrs, "model_config_hash")
    if expected_config_hash is not None and config_hash != expected_config_hash:
        raise MapError(
            f"{p}: map built with another model: its model config hash is {config_hash}, "
            f"the model in use has {expected_config_hash}; rebuild the map with this model"
        )
    weights_hash = _text(attrs, "model_weights_hash") if "model_weights_hash" in attrs else None
    if weights_hash is not None and not weights_hash:
        raise MapError(f"{p}: corrupted map: model_weights_hash is {weights_hash!r}")
    check_weights(weights_hash, expected_weights_hash, p)
    descriptor_dtype = _text(attrs, "descriptor_dtype")
    if descriptor_dtype not in ("float32", "float16"):
        raise MapError(f"{p}: corrupted map: descriptor dtype {descriptor_dtype!r}")
    return version, config_hash, weights_hash, descriptor_dtype


def _check_structures(h5: h5py.File, p: Path) -> None:
    """:class:`MapError` naming ``p`` unless a file that says it is format 2 has the
    checksummed HDF5 structures this format promises (superblock version 2 or later, version-2
    object headers for its datasets): HDF5 parses the older ones without a check, and a damaged
    one of those crashed the interpreter (a segmentation fault) when a dataset's attribute was
    read. Reads no attribute or data."""
    superblock = h5.id.get_create_plist().get_version()[0]
    if superblock < 2:
        raise MapError(
            f"{p}: corrupted map: it says format version 2 but has HDF5 superblock version "
            f"{superblock}, without the checksums vvloc's maps are written with"
        )
    for name, obj in h5.items():
        if isinstance(obj, h5py.Dataset) and h5py.h5o.get_info(obj.id).hdr.version < 2:
            raise MapError(
                f"{p}: corrupted map: dataset {name!r} has an HDF5 object header without "
                "checksums, which vvloc's maps are not written with"
            )


def _check_datasets(h5: h5py.File, p: Path, descriptor_dtype: str) -> tuple[int, bool]:
    """A map file's datasets checked against its header: each present, of its number of
    dimensions and dtype, one row per keyframe. Returns ``(num_keyframes, has_bev)``;
    :class:`MapError` naming ``p`` otherwise. Reads no data."""
    required = (*_SMALL, "local_descriptors", "session_names")
    missing = [d for d in required if not isinstance(h5.get(d), h5py.Dataset)]
    if missing:
        raise MapError(f"{p}: corrupted map: missing datasets {missing}")
    has_bev = "bev" in h5
    if has_bev and not isinstance(h5["bev"], h5py.Dataset):
        raise MapError(f"{p}: corrupted map: 'bev' is not a dataset")
    n = h5.attrs["num_keyframes"]
    if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)):
        raise MapError(f"{p}: corrupted map: num_keyframes {n} is not an integer")
    n = int(n)
    ndims = {"poses": 2, "global_descriptors": 2, "local_descriptors": 3, "bev": 4}
    per_keyframe = (*_SMALL, "local_descriptors", *(("bev",) if has_bev else ()))
    lengths = {}
    for name in per_keyframe:
        ds = h5[name]
        if ds.ndim != ndims.get(name, 1):
            raise MapError(f"{p}: corrupted map: dataset {name!r} has shape {ds.shape}")
        lengths[name] = ds.shape[0]
    if n < 1 or any(length != n for length in lengths.values()):
        raise MapError(
            f"{p}: corrupted map: inconsistent lengths: num_keyframes = {n}, datasets "
            + ", ".join(f"{k} = {v}" for k, v in lengths.items())
        )
    if h5["poses"].shape[1] != 3:
        raise MapError(f"{p}: corrupted map: poses have shape {h5['poses'].shape}")
    expected_dtypes = {
        **_META_DATASETS,
        "global_descriptors": np.dtype(descriptor_dtype),
        "local_descriptors": np.dtype(descriptor_dtype),
        "bev": _BEV_DTYPE,
    }
    for name in per_keyframe:
        if h5[name].dtype != expected_dtypes[name]:
            raise MapError(
                f"{p}: corrupted map: dataset {name!r} has dtype {h5[name].dtype}, "
                f"expected {expected_dtypes[name]}"
            )
    declared = sum(_check_stored(h5[name], p, name) for name in (*per_keyframe, "session_names"))
    if declared > h5.id.get_filesize():  # HDF5 counts chunks it indexes, not what they hold
        raise MapError(
            f"{p}: corrupted map: its datasets declare {declared} bytes in all, more than the "
            f"file's {h5.id.get_filesize()}"
        )
    return n, has_bev


def _check_stored(ds: h5py.Dataset, p: Path, name: str) -> int:
    """:class:`MapError` naming ``p`` unless the dataset ``ds`` stores all that its shape
    declares, uncompressed, as :class:`MapWriter` writes it. Checked before any read: a shape
    of 10¹² rows (or a per-row shape of 10¹²) in a file of kilobytes, never written (HDF5 reads
    unwritten chunks as zeros) or compressed from zeros, was allocated by the first read.
    Returns the declared bytes."""
    if ds.compression is not None or ds.scaleoffset is not None:
        how = ds.compression or "scaleoffset"
        raise MapError(
            f"{p}: corrupted map: dataset {name!r} is compressed ({how}), which vvloc's maps "
            "never are"
        )
    item = 16 if ds.dtype.kind == "O" else ds.dtype.itemsize  # a variable-length string's heap id
    declared, stored = ds.size * item, ds.id.get_storage_size()
    if stored < declared:
        raise MapError(
            f"{p}: corrupted map: dataset {name!r} of shape {ds.shape} declares {declared} bytes "
            f"but stores {stored}"
        )
    return int(declared)


def _read_small(
    h5: h5py.File, p: Path, n: int, verify: bool
) -> tuple[dict[str, np.ndarray], list[str]]:
    """The small per-keyframe datasets (``_SMALL``: ids, poses, timestamps, global descriptors,
    ...) read into memory, and the session names; with ``verify``, each against its stored
    sha256. :class:`MapError` naming ``p`` for a session index out of range, repeated keyframe
    ids or non-finite values."""
    small = {name: h5[name][()] for name in _SMALL}
    names = [str(s) for s in h5["session_names"].asstr()[()].tolist()]
    if verify:
        for name, arr in small.items():
            _check_digest(p, h5[name], hashlib.sha256(_le(arr, arr.dtype).data).hexdigest())
        _check_digest(p, h5["session_names"], _names_digest(names))
    si = small["session_index"]
    if si.size and (si.min() < 0 or si.max() >= len(names)):
        raise MapError(f"{p}: corrupted map: session_index out of range [0, {len(names)})")
    if np.unique(small["ids"]).size != n:
        raise MapError(f"{p}: corrupted map: keyframe ids are not unique")
    for name, arr in small.items():  # poses, timestamps, global descriptors
        if arr.dtype.kind == "f" and not np.isfinite(arr).all():
            what = name.replace("_", " ")
            raise MapError(f"{p}: corrupted map: non-finite {what}")
    return small, names


def _read_metadata(
    attrs: Any,
    p: Path,
    version: int,
    config_hash: str,
    weights_hash: str | None,
    descriptor_dtype: str,
) -> MapMetadata:
    """The map's :class:`MapMetadata` from its checked header (:func:`_check_header`'s
    values) and its grid size, rig and model config attributes; :class:`MapError` naming ``p``
    for one that does not parse."""
    grid_size = float(attrs["grid_size"])
    if not (np.isfinite(grid_size) and grid_size > 0):
        raise MapError(f"{p}: corrupted map: grid_size {grid_size}")
    rig = None
    if "rig_json" in attrs:
        try:
            rig = _check_rig(json.loads(_text(attrs, "rig_json")))
        except (TypeError, ValueError, RecursionError) as e:
            raise MapError(f"{p}: corrupted map: rig_json: {e}") from e
    try:
        model_config = json.loads(_text(attrs, "model_config_json"))
        if not isinstance(model_config, dict):
            raise TypeError(f"expected a JSON object, got {type(model_config).__name__}")
    except (TypeError, ValueError, RecursionError) as e:
        raise MapError(f"{p}: corrupted map: model_config_json: {e}") from e
    return MapMetadata(
        model_config_hash=config_hash,
        model_config=model_config,
        grid_size=grid_size,
        vvloc_version=_text(attrs, "vvloc_version"),
        format_version=version,
        created_utc=_text(attrs, "created_utc"),
        descriptor_dtype=descriptor_dtype,
        model_weights_hash=weights_hash,
        rig=rig,
    )
