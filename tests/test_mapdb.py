"""Map database: save/open round trips, lazy reads, read-only access, refusals and atomic writes."""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
import stat
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

from vvloc._io import AtomicPath, atomic_write, write_together
from vvloc.localize import MapDatabase, MapError, MapWriter, model_config_hash
from vvloc.localize.mapdb import FORMAT_VERSION

CONFIG = {"name": "tiny", "bev": {"H": 6, "W": 5, "C": 4}, "T": 8}
N, DG, T, C = 12, 16, 8, 4
BEV = (6, 5, 4)


def keyframes(n: int = N, *, bev: bool = True, seed: int = 0) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    g = rng.normal(size=(n, DG)).astype(np.float32)
    half = n // 2
    out: dict[str, Any] = {
        "poses": np.column_stack([rng.uniform(-50, 50, (n, 2)), rng.uniform(-np.pi, np.pi, n)]),
        "timestamps": 1.7e9 + np.arange(n) * 0.1,
        "sessions": ["s0"] * half + ["s1"] * (n - half),
        "global_descriptors": g / np.linalg.norm(g, axis=1, keepdims=True),
        "local_descriptors": rng.normal(size=(n, T, C)).astype(np.float32),
        "ids": np.arange(100, 100 + n, dtype=np.int64)[::-1].copy(),
        "seq": np.concatenate([np.arange(half), np.arange(n - half)]) * 3,
        "floors": rng.integers(-1, 3, n),
    }
    if bev:
        out["bevs"] = rng.normal(size=(n, *BEV)).astype(np.float32)
    return out


def make_map(n: int = N, *, bev: bool = True, seed: int = 0) -> MapDatabase:
    return MapDatabase.from_arrays(
        **keyframes(n, bev=bev, seed=seed), model_config=CONFIG, grid_size=0.3
    )


def saved(tmp_path: Path, *, bev: bool = True, dtype: str = "float32") -> Path:
    return make_map(bev=bev).save(tmp_path / "map.h5", dtype=dtype)  # type: ignore[arg-type]


def file_sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def as_stored(x: np.ndarray, dtype: str) -> np.ndarray:
    return np.asarray(x).astype(dtype).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# Round trips


@pytest.mark.parametrize("dtype", ["float32", "float16"])
@pytest.mark.parametrize("bev", [True, False])
def test_save_open_round_trip(tmp_path: Path, dtype: str, bev: bool) -> None:
    kf = keyframes(bev=bev)
    path = make_map(bev=bev).save(tmp_path / "map.h5", dtype=dtype)  # type: ignore[arg-type]
    assert sorted(os.listdir(tmp_path)) == ["map.h5"]  # no temporary file left
    with MapDatabase.open(path, expected_config_hash=model_config_hash(CONFIG)) as db:
        assert len(db) == N and db.path == path
        np.testing.assert_array_equal(db.poses, kf["poses"])
        np.testing.assert_array_equal(db.timestamps, kf["timestamps"])
        np.testing.assert_array_equal(db.ids, kf["ids"])
        np.testing.assert_array_equal(db.seq, kf["seq"])
        np.testing.assert_array_equal(db.floors, kf["floors"])
        assert db.sessions == ("s0", "s1")
        assert [db.session_of(i) for i in range(N)] == kf["sessions"]
        assert db.global_descriptors.dtype == np.float32
        np.testing.assert_array_equal(
            db.global_descriptors, as_stored(kf["global_descriptors"], dtype)
        )
        loc = db.local_descriptors(np.arange(N))
        assert loc.dtype == np.float32 and loc.shape == (N, T, C)
        np.testing.assert_array_equal(loc, as_stored(kf["local_descriptors"], dtype))
        assert db.local_shape == (T, C) and db.global_dim == DG
        assert db.has_bev is bev
        if bev:
            assert db.bev_shape == BEV
            np.testing.assert_array_equal(db.bev([0, 5]), as_stored(kf["bevs"][[0, 5]], "float16"))
        else:
            assert db.bev_shape is None
            with pytest.raises(ValueError, match="no BEVs"):
                db.bev(0)
        meta = db.metadata
        assert meta.model_config == CONFIG
        assert meta.model_config_hash == db.config_hash == model_config_hash(CONFIG)
        assert meta.grid_size == db.grid_size == 0.3
        assert meta.format_version == FORMAT_VERSION
        assert meta.descriptor_dtype == dtype
        assert meta.vvloc_version and meta.created_utc.endswith("+00:00")
        db.verify()


def test_float16_file_is_smaller(tmp_path: Path) -> None:
    m = make_map(n=64, bev=False)
    a = m.save(tmp_path / "a.h5", dtype="float32")
    b = m.save(tmp_path / "b.h5", dtype="float16")
    assert b.stat().st_size < a.stat().st_size


@pytest.mark.parametrize("opened", [False, True])
def test_lazy_reads_follow_numpy_indexing(tmp_path: Path, opened: bool) -> None:
    kf = keyframes()
    db = MapDatabase.open(saved(tmp_path)) if opened else make_map()
    with db:
        want = kf["local_descriptors"]
        np.testing.assert_array_equal(db.local_descriptors(3), want[3])  # scalar → (T, C)
        idx = np.array([7, 2, 7, 0, 11])  # unsorted, repeated
        np.testing.assert_array_equal(db.local_descriptors(idx), want[idx])
        np.testing.assert_array_equal(db.local_descriptors([4, 5, 6]), want[4:7])
        assert db.local_descriptors([]).shape == (0, T, C)
        np.testing.assert_array_equal(db.bev(np.int64(1)), as_stored(kf["bevs"][1], "float16"))
        with pytest.raises(IndexError, match=r"indices.*\[0, 12\)"):
            db.local_descriptors([0, N])
        with pytest.raises(IndexError):
            db.local_descriptors(-1)
        with pytest.raises(TypeError, match="indices"):
            db.local_descriptors([0.5])
        with pytest.raises(ValueError, match="indices"):
            db.local_descriptors([[0, 1]])


def test_session_and_id_lookups() -> None:
    db = make_map()
    kf = keyframes()
    assert db.row_of(int(kf["ids"][4])) == 4
    with pytest.raises(KeyError, match="999"):
        db.row_of(999)
    assert db.row_of(np.int32(kf["ids"][4])) == 4
    for bad in (float(kf["ids"][4]) + 0.7, str(kf["ids"][4]), True):  # 1.7 read as id 1
        with pytest.raises(TypeError, match=r"^keyframe_id: expected an int"):
            db.row_of(bad)  # type: ignore[arg-type]
    rows = db.session_rows("s1")
    np.testing.assert_array_equal(rows, np.arange(N // 2, N))
    with pytest.raises(KeyError, match="nope"):
        db.session_rows("nope")


def test_opened_map_is_read_only_and_file_unchanged(tmp_path: Path) -> None:
    path = saved(tmp_path)
    before = (file_sha(path), path.stat().st_mtime_ns)
    with MapDatabase.open(path) as db:
        for arr in (db.poses, db.global_descriptors, db.ids, db.timestamps, db.seq, db.floors):
            assert not arr.flags.writeable
            with pytest.raises(ValueError, match="read-only"):
                arr[0] = 0
        db.local_descriptors([1, 2])
        db.verify()
    assert (file_sha(path), path.stat().st_mtime_ns) == before
    with pytest.raises(ValueError, match="closed"):
        db.local_descriptors(0)


def test_resave_over_the_opened_file(tmp_path: Path) -> None:
    path = saved(tmp_path)
    kf = keyframes()
    with MapDatabase.open(path) as db:
        db.save(path, dtype="float16")
        np.testing.assert_array_equal(db.local_descriptors(0), kf["local_descriptors"][0])
    with MapDatabase.open(path) as db2:
        assert db2.metadata.descriptor_dtype == "float16"
        np.testing.assert_array_equal(db2.poses, kf["poses"])
    assert sorted(os.listdir(tmp_path)) == ["map.h5"]


def test_writer_appends_batches(tmp_path: Path) -> None:
    kf = keyframes(bev=True)
    path = tmp_path / "map.h5"
    with MapWriter(path, model_config=CONFIG, grid_size=0.3, dtype="float16") as w:
        for sl in (slice(0, 5), slice(5, 9), slice(9, N)):
            w.append(
                poses=kf["poses"][sl],
                timestamps=kf["timestamps"][sl],
                sessions=kf["sessions"][sl],
                global_descriptors=kf["global_descriptors"][sl],
                local_descriptors=kf["local_descriptors"][sl],
                bevs=kf["bevs"][sl],
            )
            assert not path.exists()  # nothing at the destination before close
        assert len(w) == N
    with MapDatabase.open(path) as db:
        np.testing.assert_array_equal(db.ids, np.arange(N))  # default: running row numbers
        np.testing.assert_array_equal(db.seq, [0, 1, 2, 3, 4, 5, 0, 1, 2, 3, 4, 5])
        np.testing.assert_array_equal(db.floors, 0)
        np.testing.assert_array_equal(
            db.local_descriptors(np.arange(N)), as_stored(kf["local_descriptors"], "float16")
        )
        np.testing.assert_array_equal(db.bev(np.arange(N)), as_stored(kf["bevs"], "float16"))


def test_writer_appends_a_whole_map_as_stored_and_refuses_another_models(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from vvloc.localize import mapwriter as mapwriter_module

    base = make_map()
    more = keyframes(4, seed=1)
    with MapWriter(tmp_path / "grown.h5", model_config=CONFIG, grid_size=0.3) as w:
        w.append_map(base)
        more.update(ids=[1, 2, 3, 4], seq=[0, 1, 2, 3], sessions="s2")
        w.append(**more)
        assert len(w) == N + 4
    with MapDatabase.open(tmp_path / "grown.h5") as db:
        assert db.sessions == ("s0", "s1", "s2")
        rows = np.arange(N)
        for name in ("ids", "seq", "poses", "timestamps", "floors", "global_descriptors"):
            np.testing.assert_array_equal(getattr(db, name)[rows], getattr(base, name))
        np.testing.assert_array_equal(db.local_descriptors(rows), base.local_descriptors(rows))
        np.testing.assert_array_equal(db.bev(rows), as_stored(base.bev(rows), "float16"))
    other = MapDatabase.from_arrays(**keyframes(), model_config={**CONFIG, "T": 9}, grid_size=0.3)
    coarse = MapDatabase.from_arrays(
        **keyframes(), model_config=CONFIG, grid_size=0.5, weights_hash="b" * 64
    )

    def of_weights(weights: str | None, *, bev: bool = False, **change: Any) -> MapDatabase:
        kf = {**keyframes(bev=bev), **change}
        return MapDatabase.from_arrays(
            **kf, model_config=CONFIG, grid_size=0.3, weights_hash=weights
        )

    with MapWriter(
        tmp_path / "x.h5", model_config=CONFIG, grid_size=0.3, weights_hash="b" * 64
    ) as w:
        for db, error, match in [
            (other, MapError, r"^db: in-memory map was built with model \w+, this writer's"),
            (coarse, MapError, r"^db: in-memory map has BEV cells of 0\.5 m, this writer 0\.3"),
            (of_weights("a" * 64), MapError, r"^db: in-memory map was built with other weights"),
            (of_weights(None), MapError, r"^db: in-memory map records no weights fingerprint"),
            (base.ids, TypeError, r"^db: expected a MapDatabase, got ndarray"),
        ]:
            with pytest.raises(error, match=match):
                w.append_map(db)  # type: ignore[arg-type]
        w.append_map(of_weights("b" * 64))
        with pytest.raises(ValueError, match=r"^db: keyframe ids already in the map"):
            w.append_map(of_weights("b" * 64))
        # new ids, but one (session, sequence number) already written: refused before the
        # first block (one row a block here), not half-way
        seq = np.arange(N) + 1000
        seq[-1] = 0
        collide = of_weights("b" * 64, ids=np.arange(N) + 1000, seq=seq)
        with monkeypatch.context() as m:
            m.setattr(mapwriter_module, "_COPY_BLOCK_BYTES", 1)
            with pytest.raises(ValueError, match=r"^db: \(session, sequence number\) already"):
                w.append_map(collide)
        bev = of_weights("b" * 64, bev=True, ids=np.arange(N) + 1000, seq=np.arange(N) + 1000)
        with pytest.raises(ValueError, match=r"^db: in-memory map has BEVs and earlier batches"):
            w.append_map(bev)
        assert len(w) == N  # the refusals wrote nothing
    assert (tmp_path / "x.h5").exists()


def test_writer_rejects_inconsistent_batches_and_stays_usable(tmp_path: Path) -> None:
    kf = keyframes(bev=False)
    path = tmp_path / "map.h5"
    args = {
        k: kf[k][:4]
        for k in ("poses", "timestamps", "global_descriptors", "local_descriptors", "ids")
    }
    with MapWriter(path, model_config=CONFIG, grid_size=0.3) as w:
        w.append(sessions="s0", **args)
        with pytest.raises(ValueError, match=r"local_descriptors.*differs"):
            w.append(
                sessions="s0",
                **{**args, "ids": [1, 2, 3, 4], "local_descriptors": np.zeros((4, T + 1, C))},
            )
        with pytest.raises(ValueError, match=r"ids.*already"):
            w.append(sessions="s0", **args)
        with pytest.raises(ValueError, match=r"seq: \(session, sequence number\) already"):
            w.append(sessions="s0", **{**args, "ids": [11, 12, 13, 14], "seq": [3, 4, 5, 6]})
        with pytest.raises(ValueError, match="bevs"):
            w.append(sessions="s0", **{**args, "ids": [1, 2, 3, 4]}, bevs=np.zeros((4, *BEV)))
        w.append(sessions="s1", **{**args, "ids": [1, 2, 3, 4]})
    with MapDatabase.open(path) as db:
        assert len(db) == 8 and db.sessions == ("s0", "s1")


def test_a_writer_aborted_inside_its_block_raises_at_the_end(tmp_path: Path) -> None:
    kf = keyframes(bev=False)
    args = {
        k: kf[k][:4]
        for k in ("poses", "timestamps", "global_descriptors", "local_descriptors", "ids")
    }
    path = tmp_path / "map.h5"
    with pytest.raises(MapError, match="aborted; nothing was written"):
        with MapWriter(path, model_config=CONFIG, grid_size=0.3) as w:
            w.append(sessions="s0", **args)
            w.abort()  # e.g. a failed write that the caller caught and ignored
    assert os.listdir(tmp_path) == []


def test_the_rig_round_trips_and_is_validated(tmp_path: Path) -> None:
    from vvloc.data import Camera

    cam = Camera("front", 16, 8, np.array([[8.0, 0, 7.5], [0, 8, 3.5], [0, 0, 1]]), np.eye(4))
    kf = keyframes(bev=False)
    db = MapDatabase.from_arrays(**kf, model_config=CONFIG, grid_size=0.3, rig=[cam])
    assert db.rig == [cam.to_json()]
    with MapDatabase.open(db.save(tmp_path / "m.h5")) as back:
        assert back.rig == [cam.to_json()]
    assert make_map().rig is None  # not recorded
    with pytest.raises(ValueError, match="rig"):
        MapDatabase.from_arrays(**kf, model_config=CONFIG, grid_size=0.3, rig=[{"name": "x"}])
    with pytest.raises(TypeError, match="rig"):
        MapDatabase.from_arrays(**kf, model_config=CONFIG, grid_size=0.3, rig="front")


def test_writer_refuses_a_batch_of_unnormalised_global_descriptors(tmp_path: Path) -> None:
    kf = keyframes()
    with MapWriter(tmp_path / "map.h5", model_config=CONFIG, grid_size=0.3) as w:
        with pytest.raises(ValueError, match=r"global_descriptors: expected L2-normalised"):
            w.append(**{**kf, "global_descriptors": kf["global_descriptors"] * 3})
        w.append(**kf)  # the refused batch added nothing
    assert len(MapDatabase.open(tmp_path / "map.h5")) == N


def test_writer_with_no_keyframes_writes_nothing(tmp_path: Path) -> None:
    w = MapWriter(tmp_path / "map.h5", model_config=CONFIG, grid_size=0.3)
    with pytest.raises(ValueError, match="at least one keyframe"):
        w.close()
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize(
    ("change", "exc", "match"),
    [
        ({"poses": np.zeros((N, 2))}, ValueError, r"poses.*\(N, 3\)"),
        ({"poses": [[0, 0, 0]] * (N - 1) + [[0, 0]]}, ValueError, "poses: .*ragged rows"),
        ({"poses": np.full((N, 3), np.nan)}, ValueError, "poses.*non-finite"),
        ({"timestamps": np.zeros(N - 1)}, ValueError, "timestamps"),
        ({"sessions": ["a"] * (N - 1)}, ValueError, "sessions"),
        ({"sessions": [1] * N}, TypeError, "sessions"),
        # names the CSV exports and their readers would change (line breaks, stripped spaces)
        ({"sessions": "day\n1"}, ValueError, r"^sessions: session name 'day\\n1' holds a con"),
        ({"sessions": "a\x00"}, ValueError, r"^sessions: .* control character"),
        ({"sessions": "day 1 "}, ValueError, r"^sessions: session name 'day 1 ' begins or ends"),
        ({"global_descriptors": np.zeros((N, DG), dtype=complex)}, TypeError, "global_desc"),
        ({"local_descriptors": np.zeros((N, T))}, ValueError, "local_descriptors"),
        (  # unnormalised global descriptors rank by their length: refused
            {"global_descriptors": np.ones((N, DG))},
            ValueError,
            r"global_descriptors: expected L2-normalised .* row 0 has norm 4 \(12 of 12 not",
        ),
        (
            {"global_descriptors": np.vstack([np.eye(N - 1, DG), np.zeros((1, DG))])},
            ValueError,
            r"global_descriptors: .* row 11 has norm 0 \(1 of 12",
        ),
        ({"ids": np.zeros(N, np.int64)}, ValueError, "ids.*unique"),
        ({"seq": np.zeros(N, np.int64)}, ValueError, "seq.*unique within a session"),
        ({"seq": np.zeros(N)}, TypeError, "seq.*integer"),
        ({"bevs": np.full((N, *BEV), 1e6)}, ValueError, "bevs.*overflow"),
        ({"grid_size": -1.0}, ValueError, "grid_size"),
        ({"model_config": {"a": object()}}, ValueError, "model_config"),
    ],
)
def test_from_arrays_validates(change: dict[str, Any], exc: type, match: str) -> None:
    args = {**keyframes(), "model_config": CONFIG, "grid_size": 0.3, **change}
    with pytest.raises(exc, match=match):
        MapDatabase.from_arrays(**args)


def test_yaws_are_stored_wrapped(tmp_path: Path) -> None:
    # 4π + 0.3 read back as 12.04 rad, unlike every other yaw of the package
    kf = keyframes(bev=False)
    raw = np.array(kf["poses"], copy=True)
    kf["poses"] = raw + np.array([0.0, 0.0, 4 * np.pi])
    kf["poses"][0, 2] = -np.pi  # the interval is (−π, π]
    db = MapDatabase.from_arrays(**kf, model_config=CONFIG, grid_size=0.3)
    np.testing.assert_allclose(db.poses[1:], raw[1:], atol=1e-12)
    assert db.poses[0, 2] == np.pi
    assert ((db.poses[:, 2] > -np.pi) & (db.poses[:, 2] <= np.pi)).all()
    with MapWriter(tmp_path / "m.h5", model_config=CONFIG, grid_size=0.3) as w:
        w.append(**kf)
    with MapDatabase.open(tmp_path / "m.h5") as back:
        np.testing.assert_array_equal(back.poses, db.poses)
    # yaws already in (−π, π] are kept bit for bit
    exact = MapDatabase.from_arrays(**{**kf, "poses": raw}, model_config=CONFIG, grid_size=0.3)
    np.testing.assert_array_equal(exact.poses, raw)


def test_from_arrays_keeps_copies_of_its_own() -> None:
    # it once froze the caller's arrays (writeable=False) and saw their later edits, past the
    # finite and unit-norm checks
    kf = keyframes()
    kept = {k: np.array(v, copy=True) for k, v in kf.items() if isinstance(v, np.ndarray)}
    db = MapDatabase.from_arrays(**kf, model_config=CONFIG, grid_size=0.3)
    for key, arr in kf.items():
        if isinstance(arr, np.ndarray):
            assert arr.flags.writeable, key
            arr[...] = 0 if arr.dtype.kind in "iu" else np.nan
    np.testing.assert_array_equal(db.poses, kept["poses"])
    np.testing.assert_array_equal(db.global_descriptors, kept["global_descriptors"])
    np.testing.assert_array_equal(db.local_descriptors(0), kept["local_descriptors"][0])
    np.testing.assert_array_equal(db.bev(0), as_stored(kept["bevs"][0], "float16"))
    np.testing.assert_array_equal(db.ids, kept["ids"])
    np.testing.assert_array_equal(db.floors, kept["floors"])


def test_float16_overflow_and_bad_dtype_are_refused(tmp_path: Path) -> None:
    kf = keyframes(bev=False)
    kf["local_descriptors"] = kf["local_descriptors"] * 1e6
    db = MapDatabase.from_arrays(**kf, model_config=CONFIG, grid_size=0.3)
    with pytest.raises(ValueError, match="overflow float16"):
        db.save(tmp_path / "map.h5", dtype="float16")
    with pytest.raises(ValueError, match="dtype"):
        db.save(tmp_path / "map.h5", dtype="int8")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="dtype: expected 'float32' or 'float16', got 5"):
        db.save(tmp_path / "map.h5", dtype=5)  # type: ignore[arg-type]
    assert os.listdir(tmp_path) == []


def test_model_config_hash_is_canonical() -> None:
    assert model_config_hash({"a": 1, "b": [1, 2]}) == model_config_hash({"b": [1, 2], "a": 1})
    assert model_config_hash({"a": 1}) == model_config_hash('{"a":   1}')
    assert model_config_hash({"a": 1}) != model_config_hash({"a": 2})


# ---------------------------------------------------------------------------------------------
# Refusals


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"nope\.h5"):
        MapDatabase.open(tmp_path / "nope.h5")
    # os.fspath's "expected str, bytes or os.PathLike object, not int" named no argument
    with pytest.raises(TypeError, match=r"^path: expected a str or os.PathLike, got int"):
        MapDatabase.open(5)  # type: ignore[arg-type]


def test_garbage_file_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "garbage.h5"
    path.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(MapError, match=r"garbage\.h5.*not an HDF5 file"):
        MapDatabase.open(path)


@pytest.mark.parametrize("keep", [0.5, 0.9, 0.001])
def test_truncated_file_is_refused(tmp_path: Path, keep: float) -> None:
    path = saved(tmp_path)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(MapError, match=r"map\.h5"):
        MapDatabase.open(path)


def test_hdf5_file_that_is_not_a_map(tmp_path: Path) -> None:
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f["x"] = np.arange(3)
    with pytest.raises(MapError, match=r"other\.h5.*not a vvloc map"):
        MapDatabase.open(path)
    for fmt in (3, b"other-format", "other-format"):  # another tool's 'format' attribute
        with h5py.File(path, "w") as f:
            f.attrs["format"] = fmt
        with pytest.raises(MapError, match=r"other\.h5: not a vvloc map \(attribute 'format'"):
            MapDatabase.open(path)


def edit(path: Path, fn: Any, *, reseal: bool = True) -> None:
    """Apply ``fn`` to the open file; ``reseal`` brings the attribute checksum up to date (a
    file written so by a faulty writer, to reach the check behind it)."""
    from vvloc.localize.mapfile import _ATTRS_DIGEST, _attrs_digest, _set_text

    with h5py.File(path, "a", libver=("v110", "v110")) as f:  # as MapWriter writes
        fn(f)
        if reseal and _ATTRS_DIGEST in f.attrs:
            _set_text(f.attrs, _ATTRS_DIGEST, _attrs_digest(f.attrs))


def test_an_edited_attribute_is_refused_by_the_attribute_checksum(tmp_path: Path) -> None:
    path = saved(tmp_path)
    edit(path, lambda f: f.attrs.__setitem__("grid_size", 0.5), reseal=False)
    with pytest.raises(MapError, match=r"map\.h5: corrupted map: attribute checksum mismatch"):
        MapDatabase.open(path)
    edit(path, lambda f: f.attrs.__delitem__("attributes_sha256"), reseal=False)
    with pytest.raises(MapError, match=r"map\.h5: corrupted map: no attribute checksum"):
        MapDatabase.open(path)


def test_a_declared_size_the_file_does_not_store_is_refused_before_any_read(
    tmp_path: Path,
) -> None:
    # a dataset declared with 10^12 rows (never written: HDF5 reads unwritten chunks as zeros)
    # in a file of kilobytes was allocated by open(): numpy's "Unable to allocate 7.28 TiB";
    # 2·10^7 rows took 1.8 GiB before the checksum refused them
    path = saved(tmp_path)
    big = 10**12

    def declare(f: h5py.File, name: str, shape: tuple[int, ...], **kw: Any) -> None:
        old = f[name]
        sha, dtype = old.attrs["sha256"], old.dtype
        del f[name]
        chunks = (min(shape[0], 1 << 14), *shape[1:])
        f.create_dataset(name, shape=shape, dtype=dtype, chunks=chunks, **kw).attrs["sha256"] = sha

    per_keyframe = ("ids", "session_index", "seq", "timestamps", "poses", "floors")
    per_keyframe += ("global_descriptors", "local_descriptors", "bev")

    def grow(f: h5py.File, rows: int, **kw: Any) -> None:
        for name in per_keyframe:
            declare(f, name, (rows, *f[name].shape[1:]), **kw)
        f.attrs["num_keyframes"] = np.int64(rows)

    edit(path, lambda f: grow(f, big, fletcher32=True))
    assert path.stat().st_size < 1_000_000
    with pytest.raises(
        MapError,
        match=r"map\.h5: corrupted map: dataset 'ids' of shape "
        r"\(1000000000000,\) declares 8000000000000 bytes but stores",
    ):
        MapDatabase.open(path)
    # every chunk indexed but holding 8 bytes (HDF5's storage size counts what its chunk index
    # says, not what the chunks hold): a file of 112 KB made open() ask numpy for 745 GiB
    (tmp_path / "c").mkdir()
    path = saved(tmp_path / "c")

    def indexed(f: h5py.File) -> None:
        grow(f, 1 << 24)
        for name in per_keyframe:
            ds = f[name]
            for start in range(0, ds.shape[0], ds.chunks[0]):
                ds.id.write_direct_chunk((start, *([0] * (ds.ndim - 1))), b"\0" * 8)

    edit(path, indexed)
    with pytest.raises(
        MapError,
        match=r"corrupted map: its datasets declare \d+ bytes in all, "
        r"more than the file's \d+",
    ):
        MapDatabase.open(path)
    # the right number of rows, compressed (a 2 GiB chunk of zeros in 2 MB): never written so
    (tmp_path / "z").mkdir()
    path = saved(tmp_path / "z")
    edit(path, lambda f: declare(f, "ids", f["ids"].shape, compression="gzip"))
    with pytest.raises(MapError, match=r"dataset 'ids' is compressed \(gzip\)"):
        MapDatabase.open(path)


def test_a_format_2_label_on_unchecksummed_hdf5_structures_is_refused(tmp_path: Path) -> None:
    # a format-1 file relabelled format 2 (attribute checksum and all) opened as format 2;
    # damaged, such a file crashed the interpreter in HDF5 when a dataset's sha256 was read
    from vvloc.localize.mapfile import _ATTRS_DIGEST, _attrs_digest, _set_text

    path = tmp_path / "relabelled.h5"
    shutil.copy(Path(__file__).parent / "data" / "map-format-1.h5", path)

    def relabel(f: h5py.File) -> None:
        f.attrs["format_version"] = np.int64(2)
        _set_text(f.attrs, _ATTRS_DIGEST, _attrs_digest(f.attrs))

    edit(path, relabel, reseal=False)
    with pytest.raises(
        MapError,
        match=r"relabelled\.h5: corrupted map: it says format version 2 "
        r"but has HDF5 superblock version 0",
    ):
        MapDatabase.open(path)


def test_a_long_text_attribute_is_checksummed_too(tmp_path: Path) -> None:
    """HDF5 keeps a value over ~4 KiB in a heap object without a checksum of its own."""
    config = {**CONFIG, "notes": "x" * 5000}
    db = MapDatabase.from_arrays(**keyframes(), model_config=config, grid_size=0.3)
    path = db.save(tmp_path / "map.h5")
    data = bytearray(path.read_bytes())
    at = data.find(b"x" * 64)
    assert at > 0 and data.find(b"x" * 64, at + 5000) < 0  # the config, stored once
    data[at + 2500] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(MapError, match=r"map\.h5: corrupted map"):
        MapDatabase.open(path)


def test_missing_dataset_is_refused(tmp_path: Path) -> None:
    path = saved(tmp_path)
    edit(path, lambda f: f.__delitem__("poses"))
    with pytest.raises(MapError, match=r"map\.h5.*missing datasets \['poses'\]"):
        MapDatabase.open(path)


def test_wrong_format_version_is_refused(tmp_path: Path) -> None:
    path = saved(tmp_path)
    edit(path, lambda f: f.attrs.__setitem__("format_version", FORMAT_VERSION + 98))
    with pytest.raises(MapError, match=rf"map\.h5.*format version {FORMAT_VERSION + 98}"):
        MapDatabase.open(path)


def test_map_of_another_model_is_refused(tmp_path: Path) -> None:
    path = saved(tmp_path)
    mine, other = model_config_hash(CONFIG), model_config_hash({**CONFIG, "T": 16})
    with pytest.raises(MapError, match="another model") as err:
        MapDatabase.open(path, expected_config_hash=other)
    assert mine in str(err.value) and other in str(err.value) and "map.h5" in str(err.value)
    MapDatabase.open(path, expected_config_hash=mine).close()


def test_weights_fingerprint_round_trips_and_refuses_other_weights(tmp_path: Path) -> None:
    mine, other = "a" * 64, "b" * 64
    db = MapDatabase.from_arrays(
        **keyframes(), model_config=CONFIG, grid_size=0.3, weights_hash=mine
    )
    path = db.save(tmp_path / "map.h5")
    with MapDatabase.open(path, expected_weights_hash=mine) as opened:
        assert opened.weights_hash == mine == opened.metadata.model_weights_hash
        again = opened.save(tmp_path / "copy.h5")  # save keeps the fingerprint
    with MapDatabase.open(again) as copy:
        assert copy.weights_hash == mine
    with pytest.raises(MapError, match=r"map\.h5.*other weights") as err:
        MapDatabase.open(path, expected_weights_hash=other)
    assert mine[:16] in str(err.value) and other[:16] in str(err.value)
    MapDatabase.open(path).close()  # nothing expected: nothing checked


def test_map_without_weights_fingerprint_opens_with_a_warning(tmp_path: Path) -> None:
    path = saved(tmp_path)  # written without weights_hash, like maps of older vvloc
    with MapDatabase.open(path) as db:
        assert db.weights_hash is None
    with pytest.warns(UserWarning, match=r"map\.h5.*no weights fingerprint"):
        MapDatabase.open(path, expected_weights_hash="a" * 64).close()


def test_bad_expected_or_stored_weights_hash_is_refused(tmp_path: Path) -> None:
    path = saved(tmp_path)
    with pytest.raises(TypeError, match="expected_weights_hash"):
        MapDatabase.open(path, expected_weights_hash=7)  # type: ignore[arg-type]
    edit(path, lambda f: f.attrs.__setitem__("model_weights_hash", ""))
    with pytest.raises(MapError, match=r"map\.h5: corrupted map: model_weights_hash"):
        MapDatabase.open(path)


@pytest.mark.parametrize("bad", ["", 7, b"ab"])
def test_bad_weights_hash_is_refused(tmp_path: Path, bad: Any) -> None:
    with pytest.raises(TypeError, match="weights_hash"):
        MapWriter(tmp_path / "map.h5", model_config=CONFIG, grid_size=0.3, weights_hash=bad)
    with pytest.raises(TypeError, match="weights_hash"):
        MapDatabase.from_arrays(**keyframes(), model_config=CONFIG, grid_size=0.3, weights_hash=bad)
    assert not any(tmp_path.iterdir())


def test_inconsistent_lengths_are_refused(tmp_path: Path) -> None:
    path = saved(tmp_path)

    def shorten(f: h5py.File) -> None:
        floors = f["floors"][:-1]
        del f["floors"]
        f["floors"] = floors

    edit(path, shorten)
    with pytest.raises(MapError, match=rf"map\.h5.*inconsistent lengths.*floors = {N - 1}"):
        MapDatabase.open(path)


def test_modified_dataset_fails_its_checksum(tmp_path: Path) -> None:
    path = saved(tmp_path)
    edit(path, lambda f: f["global_descriptors"].__setitem__((3, 0), 0.25))
    with pytest.raises(MapError, match=r"map\.h5.*checksum mismatch.*global_descriptors"):
        MapDatabase.open(path)
    with MapDatabase.open(path, verify=False) as db:
        with pytest.raises(MapError, match=r"checksum mismatch.*global_descriptors"):
            db.verify()


def flip_byte_in_chunk(path: Path, dataset: str, row: int) -> None:
    with h5py.File(path, "r") as f:
        ds = f[dataset]
        info = ds.id.get_chunk_info_by_coord((row,) + (0,) * (ds.ndim - 1))
    with open(path, "r+b") as fh:
        fh.seek(info.byte_offset + info.size // 2)
        b = fh.read(1)
        fh.seek(-1, os.SEEK_CUR)
        fh.write(bytes([b[0] ^ 0xFF]))


def test_corrupted_bytes_in_global_descriptors_are_refused_on_open(tmp_path: Path) -> None:
    path = saved(tmp_path)
    flip_byte_in_chunk(path, "global_descriptors", 0)
    with pytest.raises(MapError, match=r"map\.h5.*corrupted"):
        MapDatabase.open(path)


@pytest.mark.parametrize("dataset", ["local_descriptors", "bev"])
def test_corrupted_lazy_chunk_fails_when_read(tmp_path: Path, dataset: str) -> None:
    path = saved(tmp_path)
    flip_byte_in_chunk(path, dataset, 5)
    with MapDatabase.open(path) as db:  # lazy data is not read on open
        read = db.local_descriptors if dataset == "local_descriptors" else db.bev
        with pytest.raises(MapError, match=rf"map\.h5.*{dataset}"):
            read([4, 5])
        with pytest.raises(MapError, match=rf"map\.h5.*{dataset}"):
            db.verify()


def full_map(tmp_path: Path) -> Path:
    """A float16 map with every optional part: BEVs, a rig, a weights fingerprint, UTF-8 text."""
    from vvloc.data import Camera

    cam = Camera("front", 16, 8, np.array([[8.0, 0, 7.5], [0, 8, 3.5], [0, 0, 1]]), np.eye(4))
    kf = keyframes()
    kf["sessions"] = ["séance-0"] * (N // 2) + ["s1"] * (N - N // 2)
    db = MapDatabase.from_arrays(
        **kf, model_config=CONFIG, grid_size=0.3, rig=[cam], weights_hash="0123456789abcdef"
    )
    return db.save(tmp_path / "map.h5", dtype="float16")


def test_format_2_keeps_text_in_checksummed_hdf5_structures(tmp_path: Path) -> None:
    path = full_map(tmp_path)
    with open(path, "rb") as fh:
        head = fh.read(9)
    assert head[:8] == b"\x89HDF\r\n\x1a\n" and head[8] >= 2  # superblock v2+: checksummed
    with h5py.File(path, "r") as f:
        for key in f.attrs:
            if key not in ("format_version", "grid_size", "num_keyframes"):
                assert f.attrs.get_id(key).dtype.kind == "S", key  # fixed length, no heap
        assert f["session_names"].dtype.kind == "S"
        for name in f:
            assert f[name].attrs.get_id("sha256").dtype.kind == "S", name
    with MapDatabase.open(path) as db:
        assert db.metadata.format_version == FORMAT_VERSION == 2
        assert db.sessions == ("séance-0", "s1") and db.weights_hash == "0123456789abcdef"


def write_version_1(src: Path, dst: Path) -> None:
    """Rewrite a map as vvloc wrote format version 1: HDF5's oldest structures, text as
    variable-length strings."""
    with h5py.File(src, "r") as f, h5py.File(dst, "w", libver="earliest") as g:
        for name, ds in f.items():
            if name == "session_names":
                out = g.create_dataset(
                    name, data=ds.asstr()[()].tolist(), dtype=h5py.string_dtype("utf-8")
                )
            else:
                out = g.create_dataset(
                    name, data=ds[()], chunks=ds.chunks, maxshape=ds.maxshape, fletcher32=True
                )
            out.attrs["sha256"] = ds.attrs["sha256"].decode()
        for key, value in f.attrs.items():
            g.attrs[key] = value.decode() if isinstance(value, bytes) else value
        g.attrs["format_version"] = 1


def test_foreign_attribute_values_are_a_corrupted_map(tmp_path: Path) -> None:
    # an inf version (int() overflows) and a v1 map's scalar session_names (no .tolist()) once
    # escaped as OverflowError / AttributeError
    path = saved(tmp_path)
    edit(path, lambda f: f.attrs.__setitem__("format_version", np.float64(np.inf)))
    with pytest.raises(MapError, match=r"map\.h5: "):
        MapDatabase.open(path)
    old = tmp_path / "old.h5"
    (tmp_path / "v1").mkdir()
    write_version_1(saved(tmp_path / "v1"), old)

    def scalar_names(f: h5py.File) -> None:
        digest = f["session_names"].attrs["sha256"]
        del f["session_names"]
        f.create_dataset("session_names", data="s0", dtype=h5py.string_dtype("utf-8"))
        f["session_names"].attrs["sha256"] = digest

    edit(old, scalar_names)
    with pytest.raises(MapError, match=r"old\.h5: "):
        MapDatabase.open(old)


def test_format_1_maps_are_still_read(tmp_path: Path) -> None:
    path = full_map(tmp_path)
    old = tmp_path / "old.h5"
    write_version_1(path, old)
    with h5py.File(old, "r") as f:
        assert f.attrs.get_id("model_config_json").dtype.kind == "O"  # really version 1
    with MapDatabase.open(path) as new, MapDatabase.open(old) as db:
        db.verify()
        assert db.metadata.format_version == 1
        for field in ("model_config", "model_config_hash", "model_weights_hash", "rig"):
            assert getattr(db.metadata, field) == getattr(new.metadata, field)
        assert db.sessions == new.sessions
        np.testing.assert_array_equal(db.poses, new.poses)
        np.testing.assert_array_equal(
            db.local_descriptors(range(N)), new.local_descriptors(range(N))
        )
        resaved = db.save(tmp_path / "resaved.h5", dtype="float16")
    with MapDatabase.open(resaved) as db:
        assert db.metadata.format_version == 2


def test_a_map_written_by_format_1s_own_writer_is_read(tmp_path: Path) -> None:
    """tests/data/map-format-1.h5 was written by the map writer of commit 0c97ba5."""
    import sys

    sys.path.insert(0, str(Path(__file__).parent / "data"))
    try:
        from make_map_format_1 import fixture_arrays
    finally:
        sys.path.pop(0)
    want = fixture_arrays()
    path = Path(__file__).parent / "data" / "map-format-1.h5"
    with MapDatabase.open(path) as db:
        db.verify()
        meta = db.metadata
        assert meta.format_version == 1 and meta.descriptor_dtype == "float16"
        assert meta.model_config == want["model_config"] and meta.grid_size == 0.3
        assert meta.model_weights_hash == "0123456789abcdef"
        assert meta.rig == [want["rig"][0].to_json()]
        assert db.sessions == ("séance-0", "s1")
        assert [db.session_of(i) for i in range(6)] == want["sessions"]
        np.testing.assert_array_equal(db.poses, want["poses"])
        np.testing.assert_array_equal(db.timestamps, want["timestamps"])
        np.testing.assert_array_equal(db.floors, want["floors"])
        np.testing.assert_array_equal(
            db.global_descriptors, as_stored(want["global_descriptors"], "float16")
        )
        np.testing.assert_array_equal(
            db.local_descriptors(range(6)), as_stored(want["local_descriptors"], "float16")
        )
        np.testing.assert_array_equal(db.bev(range(6)), as_stored(want["bevs"], "float16"))
        new = db.save(tmp_path / "new.h5", dtype="float16")
        with MapDatabase.open(new) as again:
            assert again.metadata.format_version == FORMAT_VERSION
            assert again.metadata.model_config == meta.model_config
            np.testing.assert_array_equal(again.bev(range(6)), db.bev(range(6)))


FLIP_SCRIPT = r"""
import sys, numpy as np
from vvloc.localize import MapDatabase, MapError

def contents(db):
    rows = np.arange(len(db))
    m = db.metadata
    return [db.ids, db.poses, db.timestamps, db.seq, db.floors, db.session_index,
            db.global_descriptors, db.local_descriptors(rows), db.bev(rows), db.sessions,
            m.model_config, m.model_config_hash, m.model_weights_hash, m.rig, m.grid_size,
            m.descriptor_dtype, m.vvloc_version, m.created_utc]

def same(a, b):
    return all(np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y
               for x, y in zip(a, b, strict=True))

path, work, step = sys.argv[1], sys.argv[2], int(sys.argv[3])
data = open(path, "rb").read()
with MapDatabase.open(path) as db:
    ref = contents(db)
refused = harmless = 0
for byte in range(0, len(data), step):
    buf = bytearray(data)
    buf[byte] ^= 1 << (byte % 8)
    open(work, "wb").write(buf)
    print(byte, flush=True)  # the last line names the flip if HDF5 crashes or hangs
    try:
        with MapDatabase.open(work) as db:
            db.verify()
            got = contents(db)
    except MapError:
        refused += 1
        continue
    if not same(got, ref):
        print(f"READ AS OTHER VALUES: byte {byte}", flush=True)
        sys.exit(3)
    harmless += 1
print(f"refused {refused} harmless {harmless}", flush=True)
"""


def test_single_bit_flips_anywhere_are_refused_or_harmless(tmp_path: Path) -> None:
    """One flipped bit in every 3rd byte of a map file: each is refused with MapError or
    changes nothing that is read; none crashes or hangs HDF5 or escapes as another error."""
    import subprocess
    import sys

    path = full_map(tmp_path)
    try:
        run = subprocess.run(
            [sys.executable, "-c", FLIP_SCRIPT, str(path), str(tmp_path / "work.h5"), "3"],
            capture_output=True,
            text=True,
            timeout=600,
        )
    except subprocess.TimeoutExpired as e:
        last = (e.stdout or b"").decode(errors="replace").strip().splitlines()[-1:]
        pytest.fail(f"hang after flipping a bit of byte {last}")
    tail = run.stdout.strip().splitlines()[-1:]
    assert run.returncode == 0, f"rc {run.returncode} at byte {tail}: {run.stderr[-2000:]}"
    refused, harmless = (int(w) for w in tail[0].split()[1::2])
    size = path.stat().st_size
    assert refused + harmless == len(range(0, size, 3))
    assert refused > size // 3 // 2  # most of a compact map's bytes matter


# ---------------------------------------------------------------------------------------------
# Atomic writes


def test_failed_write_leaves_previous_map_and_no_temp_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = saved(tmp_path)
    before = file_sha(path)
    calls = {"n": 0}
    original = h5py.Dataset.__setitem__

    def failing_setitem(self: h5py.Dataset, key: Any, value: Any) -> None:
        calls["n"] += 1
        if self.name == "/local_descriptors":
            raise OSError("simulated disk failure")
        original(self, key, value)

    monkeypatch.setattr(h5py.Dataset, "__setitem__", failing_setitem)
    with pytest.raises(OSError, match="simulated disk failure"):
        make_map(seed=1).save(path)
    monkeypatch.undo()
    assert calls["n"] > 1  # the failure happened mid-write, after other datasets were written
    assert sorted(os.listdir(tmp_path)) == ["map.h5"]
    assert file_sha(path) == before
    with MapDatabase.open(path) as db:
        np.testing.assert_array_equal(db.poses, keyframes()["poses"])


def test_a_disk_too_small_for_the_map_is_said_before_hdf5_writes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # HDF5 crashes the interpreter when the disk fills under it: the writer checks first
    from types import SimpleNamespace

    from vvloc.localize import mapwriter

    path = saved(tmp_path)
    before = file_sha(path)
    real = mapwriter.shutil.disk_usage
    free = {"bytes": 0}
    monkeypatch.setattr(
        mapwriter.shutil, "disk_usage", lambda p: SimpleNamespace(free=free["bytes"])
    )
    with pytest.raises(
        OSError, match=r"map.h5: not enough free space for the map: 12 keyframes"
    ) as e:
        make_map(seed=1).save(path)
    assert e.value.errno == errno.ENOSPC
    assert sorted(os.listdir(tmp_path)) == ["map.h5"] and file_sha(path) == before
    # room for the first batch and not for the second: refused before the second is written
    kf = keyframes(bev=False)
    first = {k: v[:6] for k, v in kf.items()}
    free["bytes"] = real(tmp_path).free
    with MapWriter(tmp_path / "other.h5", model_config=CONFIG, grid_size=0.3) as w:
        w.append(**first)
        free["bytes"] = 0
        with pytest.raises(OSError, match="not enough free space"):
            w.append(**{k: v[6:] for k, v in kf.items()})
        free["bytes"] = real(tmp_path).free  # space made: the writer goes on
        w.append(**{k: v[6:] for k, v in kf.items()})
    with MapDatabase.open(tmp_path / "other.h5") as db:
        assert len(db) == N


def test_a_full_file_system_is_an_oserror_not_a_crash(tmp_path: Path) -> None:
    # a real full disk: a 1 MiB tmpfs (root only; skipped where mount is not allowed)
    mnt = tmp_path / "tiny"
    mnt.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("needs root to mount a small tmpfs")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1M", "tmpfs", str(mnt)],
                       capture_output=True)  # fmt: skip
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.decode().strip()}")
    try:
        code = (
            "import numpy as np, sys\n"
            "from vvloc.localize import MapDatabase\n"
            "n = 100\n"
            "db = MapDatabase.from_arrays(poses=np.zeros((n, 3)), timestamps=np.arange(n) * 1.0,"
            " sessions='s0', global_descriptors=np.eye(n, 64)[np.arange(n) % 64],"
            " local_descriptors=np.ones((n, 60, 64)),"
            " model_config={'a': 1}, grid_size=0.6)\n"
            "try:\n"
            "    db.save(sys.argv[1])\n"
            "except OSError as e:\n"
            "    print('OSError', e.errno, e)\n"
        )
        r = subprocess.run([sys.executable, "-c", code, str(mnt / "map.h5")],
                           capture_output=True, text=True, timeout=120)  # fmt: skip
        assert r.returncode == 0, r.stderr[-2000:]  # not -11 (SIGSEGV)
        assert f"OSError {errno.ENOSPC}" in r.stdout and "not enough free space" in r.stdout
        assert os.listdir(mnt) == []
    finally:
        subprocess.run(["umount", str(mnt)], check=True)


@pytest.mark.skipif(sys.platform == "win32", reason="RLIMIT_FSIZE is POSIX")
def test_a_map_over_the_file_size_limit_is_an_oserror_not_a_crash(tmp_path: Path) -> None:
    # ulimit -f a few KiB under the map's size: HDF5 failed in its last writes at close and
    # crashed the interpreter (SIGSEGV), the previous map kept but the process lost
    path = saved(tmp_path, bev=False)
    before = file_sha(path)
    code = (
        "import errno, resource, signal, sys\n"
        "import numpy as np\n"
        "from vvloc.localize import MapDatabase\n"
        "n = 400\n"
        "db = MapDatabase.from_arrays(poses=np.zeros((n, 3)), timestamps=np.arange(n) * 1.0,"
        " sessions='s0', global_descriptors=np.eye(n, 64)[np.arange(n) % 64],"
        " local_descriptors=np.ones((n, 60, 64)), bevs=np.ones((n, 8, 8, 64)),"
        " model_config={'a': 1}, grid_size=0.6)\n"
        "size = len(open(db.save(sys.argv[2]), 'rb').read())\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (size - 20000, resource.RLIM_INFINITY))\n"
        "try:\n"
        "    db.save(sys.argv[1])\n"
        "except OSError as e:\n"
        "    print('OSError', e.errno == errno.EFBIG, e)\n"
    )
    r = subprocess.run([sys.executable, "-c", code, str(path), str(tmp_path / "probe.h5")],
                       capture_output=True, text=True, timeout=120)  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]  # not -11 (SIGSEGV)
    assert "OSError True" in r.stdout and "file size limit" in r.stdout and "ulimit -f" in r.stdout
    assert sorted(os.listdir(tmp_path)) == ["map.h5", "probe.h5"] and file_sha(path) == before


def test_interrupted_writer_leaves_nothing(tmp_path: Path) -> None:
    kf = keyframes(bev=False)
    with (
        pytest.raises(KeyboardInterrupt),
        MapWriter(tmp_path / "map.h5", model_config=CONFIG, grid_size=0.3) as w,
    ):
        w.append(**{k: v for k, v in kf.items()})
        assert len(os.listdir(tmp_path)) == 1  # the hidden temporary file
        raise KeyboardInterrupt
    assert os.listdir(tmp_path) == []


def test_abandoned_writer_removes_its_temp_file(tmp_path: Path) -> None:
    w = MapWriter(tmp_path / "map.h5", model_config=CONFIG, grid_size=0.3)
    w.append(**keyframes(bev=False))
    del w
    assert os.listdir(tmp_path) == []


def test_atomic_write_keeps_old_content_on_error(tmp_path: Path) -> None:
    path = tmp_path / "out.txt"
    path.write_text("old\n")
    with pytest.raises(RuntimeError), atomic_write(path) as f:
        f.write("new, partial")
        raise RuntimeError("boom")
    assert path.read_text() == "old\n" and os.listdir(tmp_path) == ["out.txt"]
    with atomic_write(path) as f:
        f.write("new\n")
    assert path.read_text() == "new\n" and os.listdir(tmp_path) == ["out.txt"]


def test_a_temporary_file_a_killed_writer_left_goes_with_the_next_write(tmp_path: Path) -> None:
    import signal

    from vvloc._io import stale_temps, temp_tag

    path = tmp_path / "map.h5"
    script = (
        "import os, signal, sys\n"
        "from vvloc._io import AtomicPath\n"
        "a = AtomicPath(sys.argv[1])\n"
        "a.tmp.write_bytes(b'half a map')\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    r = subprocess.run([sys.executable, "-c", script, str(path)], capture_output=True)
    assert r.returncode == -signal.SIGKILL, r.stderr
    (left,) = tmp_path.iterdir()
    assert left.name.startswith(".map.h5.") and left.name.endswith(".tmp")
    assert stale_temps(tmp_path, ".map.h5.", ".tmp") == [left]
    live = tmp_path / f".map.h5.{temp_tag()}.tmp"  # this process's: a write in progress
    other = tmp_path / ".other.h5.00000000-1-aaaaaaaaaaaa.tmp"  # another file's, another host
    live.write_bytes(b"")
    other.write_bytes(b"")
    with atomic_write(path, "wb") as f:
        f.write(b"new")
    assert path.read_bytes() == b"new"
    assert not left.exists() and live.exists() and other.exists()


def test_a_symbolic_link_that_loops_is_refused_before_anything_is_written(tmp_path: Path) -> None:
    from vvloc._io import symlink_loop

    loop = tmp_path / "a"
    loop.symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(loop)
    assert symlink_loop(loop) == f"{loop} is a symbolic link that loops (or lies below one)"
    assert symlink_loop(loop / "x.h5") is not None
    assert symlink_loop(tmp_path) is None and symlink_loop(tmp_path / "missing") is None
    for path in (loop, loop / "x.h5"):
        with pytest.raises(FileExistsError, match="symbolic link that loops"):
            AtomicPath(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b"]


def test_made_folders_are_removed_again_only_when_the_block_fails_and_leaves_them_empty(
    tmp_path: Path,
) -> None:
    from vvloc._io import made_folders

    deep = tmp_path / "a" / "b" / "c"
    with pytest.raises(RuntimeError), made_folders(deep) as got:
        assert got == deep and deep.is_dir()
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []  # a, b and c: made here, left empty, removed
    (tmp_path / "a").mkdir()
    with pytest.raises(KeyboardInterrupt), made_folders(deep):
        (tmp_path / "a" / "b" / "mine.txt").write_text("x")  # written into meanwhile: stays
        raise KeyboardInterrupt
    assert sorted(p.name for p in (tmp_path / "a" / "b").iterdir()) == ["mine.txt"]
    with made_folders(deep):  # a block that succeeds keeps what it made, empty or not
        pass
    assert deep.is_dir()


def test_atomic_write_into_missing_directory_fails_cleanly(tmp_path: Path) -> None:
    with (
        pytest.raises(FileNotFoundError, match=r"its folder .* does not exist"),
        atomic_write(tmp_path / "no" / "x.txt") as f,
    ):
        f.write("x")
    with pytest.raises(IsADirectoryError, match="is a folder"), atomic_write(tmp_path) as f:
        f.write("x")
    assert os.listdir(tmp_path) == []


def test_a_folder_that_takes_no_file_is_named_with_the_destination(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # a read-only mount or a folder of another user (root passes permission bits, so the
    # error is injected): the error named only the hidden temporary file
    from vvloc import _io

    real = os.open

    def read_only(path: Any, flags: int, *args: Any) -> int:
        if flags & os.O_CREAT:
            raise OSError(errno.EROFS, "Read-only file system", str(path))
        return real(path, flags, *args)

    monkeypatch.setattr(_io.os, "open", read_only)
    for write in (
        lambda: make_map().save(tmp_path / "map.h5"),
        lambda: write_together(tmp_path, {"a.csv": b"x"}),
    ):
        with pytest.raises(OSError, match=r"cannot create a file in .*(map\.h5|a\.csv)'$") as e:
            write()
        assert e.value.errno == errno.EROFS and ".tmp" not in str(e.value)
    assert os.listdir(tmp_path) == []


def _read_fifo(path: Path, got: list[bytes]) -> threading.Thread:
    def read() -> None:
        with open(path, "rb") as f:
            got.append(f.read())

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    return reader


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes")
def test_atomic_write_to_a_stream_writes_it_in_place_and_never_replaces_it(tmp_path: Path) -> None:
    # `--csv /dev/null` as root once turned /dev/null into a plain file (the rename replaced
    # the device node); a named pipe stands in for the device here
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    got: list[bytes] = []
    reader = _read_fifo(fifo, got)
    with atomic_write(fifo) as f:
        f.write("streamed\n")
    reader.join(timeout=30)
    assert got == [b"streamed\n"]
    assert stat.S_ISFIFO(fifo.stat().st_mode) and os.listdir(tmp_path) == ["pipe"]

    got.clear()
    reader = _read_fifo(fifo, got)
    with pytest.raises(RuntimeError), atomic_write(fifo, "wb") as fb:
        fb.write(b"partial")
        raise RuntimeError("boom")
    reader.join(timeout=30)
    assert stat.S_ISFIFO(fifo.stat().st_mode) and os.listdir(tmp_path) == ["pipe"]

    got.clear()
    reader = _read_fifo(fifo, got)
    write_together(tmp_path, {"pipe": b"together", "file.bin": b"plain"})
    reader.join(timeout=30)
    assert got == [b"together"] and stat.S_ISFIFO(fifo.stat().st_mode)
    assert (tmp_path / "file.bin").read_bytes() == b"plain"
    assert sorted(os.listdir(tmp_path)) == ["file.bin", "pipe"]


STDOUT_WRITER = """
import sys
from vvloc._io import atomic_write
print("before", flush=True)
with atomic_write("/dev/stdout") as f:
    f.write("report\\n")
print("after", flush=True)
"""


@pytest.mark.skipif(not os.path.exists("/dev/stdout"), reason="/dev/stdout")
def test_atomic_write_to_dev_stdout_writes_the_processs_stdout(tmp_path: Path) -> None:
    import subprocess
    import sys

    cmd = [sys.executable, "-c", STDOUT_WRITER]
    # a pipe (its real path is no file to put a temporary beside)
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 0 and r.stdout == "before\nreport\nafter\n", r.stderr
    # a file the shell redirected stdout to: written through the descriptor, not renamed over
    # (the process's later output went to the replaced file, lost)
    out = tmp_path / "out.txt"
    with open(out, "w") as f:
        r = subprocess.run(cmd, stdout=f, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert out.read_text() == "before\nreport\nafter\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes")
def test_a_map_is_not_written_into_a_stream(tmp_path: Path) -> None:
    fifo = tmp_path / "map.h5"
    os.mkfifo(fifo)
    with pytest.raises(ValueError, match=r"path: .*map\.h5 is not a regular file"):
        MapWriter(fifo, model_config=CONFIG, grid_size=0.3)
    with pytest.raises(ValueError, match="not a regular file"):
        AtomicPath(fifo, streams=False)
    assert stat.S_ISFIFO(fifo.stat().st_mode) and os.listdir(tmp_path) == ["map.h5"]


SIGTERM_WRITER = """
import sys, time
from vvloc._io import AtomicPath
from vvloc.cli import _exit_on_sigterm
_exit_on_sigterm()
with AtomicPath(sys.argv[1]) as tmp:
    tmp.write_text("partial")
    print("ready", flush=True)
    for _ in range(600):  # a busy main thread, as in a command (see the test's comment)
        time.sleep(0.1)
"""


@pytest.mark.skipif(os.name != "posix", reason="POSIX signals")
def test_the_clis_sigterm_handler_lets_a_writer_remove_its_temporary_file(tmp_path: Path) -> None:
    import signal
    import subprocess
    import sys

    target = tmp_path / "map.h5"
    target.write_text("old map")
    cmd = [sys.executable, "-c", SIGTERM_WRITER, str(target)]
    # The writer sleeps in short steps: the kernel may hand a process-directed SIGTERM to a
    # helper thread (OpenBLAS's, started by numpy), and Python runs its handler only when the
    # main thread next executes bytecode; one long sleep(60) then outlasted the wait (CI, 272935e).
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True) as proc:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 128 + signal.SIGTERM
    assert os.listdir(tmp_path) == ["map.h5"] and target.read_text() == "old map"


def test_atomic_write_gives_new_files_the_umask_mode_and_keeps_an_existing_files_mode(
    tmp_path: Path,
) -> None:
    old = os.umask(0o022)
    try:
        with atomic_write(tmp_path / "new.txt") as f:
            f.write("x")
        # while it is written, the new contents are as private as the file they replace, and
        # its owner can write them: a read-only file is replaced too (without root's override,
        # a 0o444 temporary file could not be written); the file's mode comes at the commit
        for name, mode, while_written in (
            ("private.txt", 0o600, 0o600),
            ("frozen.txt", 0o444, 0o644),
        ):
            kept = tmp_path / name
            kept.write_text("old")
            kept.chmod(mode)
            with atomic_write(kept) as f:
                f.write("new")
                (tmp,) = [p for p in tmp_path.iterdir() if p.name.startswith(f".{name}.")]
                assert stat.S_IMODE(tmp.stat().st_mode) == while_written
            assert stat.S_IMODE(kept.stat().st_mode) == mode and kept.read_text() == "new"
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "new.txt").stat().st_mode) == 0o644


def test_atomic_write_through_a_symlink_replaces_its_target(tmp_path: Path) -> None:
    target = tmp_path / "maps" / "real.txt"
    target.parent.mkdir()
    target.write_text("old")
    link = tmp_path / "current.txt"
    link.symlink_to(target)
    with atomic_write(link) as f:
        f.write("new")
    assert link.is_symlink() and target.read_text() == "new"


def test_an_unreadable_checksum_and_a_map_held_for_writing_are_map_errors(tmp_path: Path) -> None:
    import subprocess
    import sys

    from vvloc.localize.mapfile import _check_digest

    class Damaged:  # a dataset whose checksum attribute HDF5 cannot read (a flipped bit)
        name = "/bev"

        class attrs:
            @staticmethod
            def get(key: str) -> None:
                raise OSError("Can't synchronously read data (heap object size does not match)")

    with pytest.raises(MapError, match="corrupted map: cannot read the checksum of '/bev'"):
        _check_digest(tmp_path / "m.h5", Damaged(), "0" * 64)  # type: ignore[arg-type]
    path = make_map().save(tmp_path / "map.h5")
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            f"import h5py, sys, time; f = h5py.File({str(path)!r}, 'a'); print('open'); "
            "sys.stdout.flush(); time.sleep(60)",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "open"
        with pytest.raises(MapError, match="another process holds it open for writing"):
            MapDatabase.open(path)
    finally:
        holder.kill()
        holder.communicate()  # reaps it and closes its pipe


def test_map_info_reports_the_map_and_verify_reads_every_byte(tmp_path: Path) -> None:
    import subprocess
    import sys

    path = full_map(tmp_path)
    cli = [sys.executable, "-m", "vvloc.cli", "map", "info"]
    r = subprocess.run([*cli, str(path)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "format version 2" in r.stdout and f"keyframes: {N} in 2 sessions" in r.stdout
    assert (
        "séance-0: 6 keyframes" in r.stdout and "weights fingerprint 0123456789abcdef" in r.stdout
    )
    assert "rig: front 16x8" in r.stdout and "BEV (6, 5, 4) float16" in r.stdout
    # counts take their noun's singular for 1
    one = tmp_path / "one.h5"
    kf = keyframes(2, bev=False)
    kf.update(sessions=["s0", "s0"], floors=np.array([1, 1]), seq=np.array([0, 3]))
    MapDatabase.from_arrays(**kf, model_config=CONFIG, grid_size=0.3).save(one)
    r = subprocess.run([*cli, str(one)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "keyframes: 2 in 1 session\n" in r.stdout and "  s0: 2 keyframes, floor 1\n" in r.stdout
    # --map, as localize and loops take the map, says the same; the map once, not twice
    same = subprocess.run([*cli, "--map", str(one)], capture_output=True, text=True)
    assert (same.returncode, same.stdout) == (0, r.stdout), same.stderr
    for args in ([], [str(one), "--map", str(one)]):
        bad = subprocess.run([*cli, *args], capture_output=True, text=True)
        assert bad.returncode == 2 and "give the map once" in bad.stderr, bad.stderr
    flip_byte_in_chunk(path, "bev", 5)  # lazily read: found by --verify only
    assert subprocess.run([*cli, str(path)], capture_output=True).returncode == 0
    r = subprocess.run([*cli, str(path), "--verify"], capture_output=True, text=True)
    assert r.returncode == 2 and "corrupted map" in r.stderr and "'bev'" in r.stderr
    old = tmp_path / "old.h5"
    (tmp_path / "again").mkdir()
    write_version_1(full_map(tmp_path / "again"), old)
    r = subprocess.run([*cli, str(old), "--verify"], capture_output=True, text=True)
    assert r.returncode == 0 and "format version 1" in r.stdout and "rewrites it" in r.stdout
    r = subprocess.run([*cli, str(tmp_path / "none.h5")], capture_output=True, text=True)
    assert r.returncode == 2 and "map file not found" in r.stderr


def test_a_model_config_that_is_no_json_object_is_refused(tmp_path: Path) -> None:
    from vvloc.localize.mapfile import _set_text

    path = saved(tmp_path)
    for text in ("[1]", "[" * 3000 + "]" * 3000):  # a list; nesting past Python's recursion
        edit(path, lambda f, t=text: _set_text(f.attrs, "model_config_json", t))
        with pytest.raises(MapError, match=r"map\.h5: corrupted map: model_config_json"):
            MapDatabase.open(path)


def test_a_descriptor_index_path_that_is_a_named_pipe_is_refused_not_waited_on(
    tmp_path: Path,
) -> None:
    from vvloc.retrieval import DescriptorIndex

    fifo = tmp_path / "index.bin"
    os.mkfifo(fifo)
    with pytest.raises(ValueError, match=r"index\.bin: not a regular file"):
        DescriptorIndex.load(fifo)  # blocked forever


def test_non_finite_timestamps_or_descriptors_and_a_fractional_count_are_refused(
    tmp_path: Path,
) -> None:
    from vvloc.localize.mapfile import _le, _set_text

    def nan_in(name: str) -> Any:
        def fn(f: h5py.File) -> None:
            arr = f[name][()]
            arr.flat[0] = np.nan
            f[name][...] = arr
            digest = hashlib.sha256(_le(arr, arr.dtype).data).hexdigest()
            _set_text(f[name].attrs, "sha256", digest)  # a faulty writer's: the checksum agrees

        return fn

    for name, said in (("timestamps", "timestamps"), ("global_descriptors", "global descriptors")):
        (tmp_path / name).mkdir()
        path = saved(tmp_path / name)
        edit(path, nan_in(name))
        with pytest.raises(MapError, match=rf"map\.h5: corrupted map: non-finite {said}"):
            MapDatabase.open(path)  # opened silently (only poses were checked)
    for name, said in (("local_descriptors", "local descriptors"), ("bev", "bev")):
        (tmp_path / name).mkdir()
        path = saved(tmp_path / name)
        edit(path, nan_in(name))
        with MapDatabase.open(path) as db:  # read lazily: verify() reads them all
            with pytest.raises(MapError, match=rf"map\.h5: corrupted map: non-finite {said}$"):
                db.verify()
    (tmp_path / "count").mkdir()
    path = saved(tmp_path / "count")
    edit(path, lambda f: f.attrs.__setitem__("num_keyframes", 12.7))
    with pytest.raises(MapError, match=r"num_keyframes 12\.7 is not an integer"):
        MapDatabase.open(path)  # read as 12
