"""The map database: keyframes with poses and descriptors, stored as one HDF5 file.

:class:`MapDatabase` opens a map file read-only (h5py mode ``"r"``; its format:
:mod:`vvloc.localize.mapfile`), or holds one in memory (:meth:`MapDatabase.from_arrays`);
:class:`MapWriter` (:mod:`vvloc.localize.mapwriter`) writes one. The arrays held in memory
(poses, global descriptors, ids, ...) are returned as read-only arrays, lazy reads (local
descriptors, BEVs) as fresh float32 copies.

A map built with another model is refused: pass the model's config hash as
``expected_config_hash`` (and its weights fingerprint as ``expected_weights_hash``: two trained
models of one architecture share a config hash) to :meth:`MapDatabase.open`.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

import h5py
import numpy as np

from vvloc._checks import positive_float
from vvloc.localize.mapfile import (
    _LAZY,
    _SMALL,
    FORMAT_NAME,
    FORMAT_VERSION,
    READABLE_FORMAT_VERSIONS,
    DescriptorDType,
    MapError,
    MapMetadata,
    PathLike,
    _canonical_json,
    _check_datasets,
    _check_digest,
    _check_header,
    _check_rig,
    _check_structures,
    _check_weights_hash,
    _le,
    _names_digest,
    _read_metadata,
    _read_small,
    _stored_digest,
    check_weights,
    is_map_file,
    model_config_hash,
)
from vvloc.localize.mapwriter import (
    UNIT_TOLERANCE,
    MapWriter,
    _to_numpy,
    _validate_batch,
    check_unit_rows,
)

#: Rows read at a time by :meth:`MapDatabase.verify` (whole blocks of this many bytes).
_VERIFY_BLOCK_BYTES = 64 << 20


# the module's public names before the format and the writer had modules of their own
__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "READABLE_FORMAT_VERSIONS",
    "UNIT_TOLERANCE",
    "MapDatabase",
    "MapError",
    "MapMetadata",
    "MapWriter",
    "check_unit_rows",
    "check_weights",
    "is_map_file",
    "model_config_hash",
]


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
            block = max(1, _VERIFY_BLOCK_BYTES // row_bytes)
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
