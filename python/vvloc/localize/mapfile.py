"""The map file's format (one HDF5 file per map) and the checks a file passes before it is read.

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
:meth:`~vvloc.localize.mapdb.MapDatabase.open` verifies the SHA-256 of every small dataset
(all but the local descriptors and the BEVs, which are read lazily);
:meth:`~vvloc.localize.mapdb.MapDatabase.verify` checks all of them (and that the lazy ones are
finite). Before it reads anything, :meth:`~vvloc.localize.mapdb.MapDatabase.open` refuses a
file that says version 2 without those structures (superblock version 2 or later, version-2
object headers), and a dataset that does not store, uncompressed, every byte its shape declares
(a crafted shape would otherwise be allocated by the first read). So a damaged file is refused
with :class:`MapError` instead of being read as other values (``tests/test_mapdb.py`` flips
single bits all over a map file). Version 1 (vvloc before
2026-12-05) stored text as HDF5 variable-length strings in the global heap, which has no
checksum, and used HDF5's oldest structures: a flipped bit could change an attribute unnoticed,
or crash or hang HDF5 itself. Version-1 maps are still read, without that protection;
``MapDatabase.open(old).save(new)`` rewrites one as version 2."""

from __future__ import annotations

import hashlib
import json
import os
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import h5py
import numpy as np

FORMAT_NAME = "vvloc-map"


FORMAT_VERSION = 2


#: Format versions this vvloc reads (1: before the checksummed HDF5 structures of version 2).
READABLE_FORMAT_VERSIONS = (1, 2)


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
