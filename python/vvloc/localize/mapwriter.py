"""Writing a map file: :class:`MapWriter` checks each batch of keyframes, and the free space,
before any of it reaches HDF5 (:mod:`vvloc.localize.mapfile` has the format).

Files are written atomically (:mod:`vvloc._io`): a temporary file in the same directory, fsync,
``os.replace``. A failed or interrupted write leaves no temporary file and leaves an existing
map at the destination untouched."""

from __future__ import annotations

import datetime as _dt
import errno
import hashlib
import json
import os
import shutil
import weakref
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

import h5py
import numpy as np
import numpy.typing as npt

from vvloc._checks import positive_float
from vvloc._io import AtomicPath
from vvloc.geometry import wrap_angle
from vvloc.localize.mapfile import (
    _ATTRS_DIGEST,
    _BEV_DTYPE,
    _LAZY,
    _META_DATASETS,
    FORMAT_NAME,
    FORMAT_VERSION,
    DescriptorDType,
    MapError,
    PathLike,
    _attrs_digest,
    _canonical_json,
    _check_rig,
    _check_weights_hash,
    _le,
    _names_digest,
    _set_text,
    model_config_hash,
)

if TYPE_CHECKING:
    from vvloc.localize.mapdb import MapDatabase


# HDF5 file-format bounds of version 2: HDF5 1.10's structures, every one of them checksummed.
_LIBVER = ("v110", "v110")


_SMALL_CHUNK_BYTES = 1 << 16


_LAZY_CHUNK_BYTES = 1 << 14  # paper-sized rows (>= 16 KiB) get one chunk per keyframe


_COPY_BLOCK_BYTES = 64 << 20


#: Free space a map writer keeps beyond its estimate of the file (HDF5's metadata, the chunk
#: index, the attributes): HDF5 crashes the interpreter when the disk fills under it.
_SPACE_MARGIN_BYTES = 1 << 20


_CHUNK_INDEX_BYTES = 128  # an upper bound per chunk: its index entry and checksum


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
        from vvloc.localize.mapdb import MapDatabase  # mapdb imports this module

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
