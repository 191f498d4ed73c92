"""vvloc.DescriptorIndex (Rust) against the numpy brute-force reference."""

from __future__ import annotations

import os
import re
import threading
import time
import warnings
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import vvloc
from fork_helpers import exit_code_or_hang
from vvloc import DescriptorIndex, Exclusion
from vvloc.reference import retrieval as ref

DTYPES = ["float32", "float16", "bfloat16", "int8"]


def clustered(n: int, d: int, seed: int, clusters: int = 50, spread: float = 0.3) -> np.ndarray:
    """Realistic global descriptors: a mixture of Gaussians, L2-normalised, float32 (n, d)."""
    rng = np.random.default_rng(seed)
    centres = rng.standard_normal((clusters, d))
    x = centres[rng.integers(0, clusters, n)] + spread * rng.standard_normal((n, d))
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def revisits(x: np.ndarray, nq: int, seed: int, noise: float = 0.01) -> np.ndarray:
    """Queries that revisit map places: noisy copies of random map rows, L2-normalised."""
    rng = np.random.default_rng(seed)
    q = x[rng.integers(0, len(x), nq)] + noise * rng.standard_normal((nq, x.shape[1]))
    return (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)


def assert_topk_equal(idx, dist, ref_idx, ref_dist, full):
    """Indices equal to the reference except inside float32 near-ties, distances close."""
    assert idx.shape == ref_idx.shape and idx.dtype == np.int64 and dist.dtype == np.float32
    np.testing.assert_array_equal(idx == -1, ref_idx == -1)
    valid = idx >= 0
    scale = 1e-5 * (1.0 + full.max() ** 2 if full.size else 1.0)
    np.testing.assert_allclose(dist[valid] ** 2, ref_dist[valid] ** 2, rtol=0, atol=scale)
    # The distance Rust reports is the true distance of the index it returns.
    rows = np.nonzero(valid)[0]
    np.testing.assert_allclose(dist[valid] ** 2, full[rows, idx[valid]] ** 2, rtol=0, atol=scale)
    # Outside near-ties the indices are identical.
    for q in range(idx.shape[0]):
        for c in np.nonzero(valid[q])[0]:
            d = ref_dist[q, c]
            if np.sum(np.abs(full[q] ** 2 - d**2) <= scale) == 1:
                assert idx[q, c] == ref_idx[q, c]


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(0, 300),
    d=st.integers(1, 40),
    nq=st.integers(1, 12),
    k=st.integers(1, 350),
    ints=st.booleans(),
    seed=st.integers(0, 2**31),
)
def test_topk_matches_reference(n, d, nq, k, ints, seed):
    rng = np.random.default_rng(seed)
    if ints:  # small integers: many exact duplicates and ties
        x = rng.integers(-2, 3, (n, d)).astype(np.float32)
        q = rng.integers(-2, 3, (nq, d)).astype(np.float32)
    else:
        x = rng.standard_normal((n, d)).astype(np.float32)
        q = rng.standard_normal((nq, d)).astype(np.float32)
    idx, dist = DescriptorIndex(x).topk(q, k)
    ref_idx, ref_dist = ref.topk(q, x, k)
    assert_topk_equal(idx, dist, ref_idx, ref_dist, ref.distances(q, x))
    if ints:  # exact arithmetic: identical indices, ties by lower index
        np.testing.assert_array_equal(idx, ref_idx)


def test_duplicates_tie_break_by_lower_index():
    x = np.tile(np.eye(4, dtype=np.float32), (3, 1))  # rows i, i+4, i+8 are equal
    idx, dist = DescriptorIndex(x).topk(x[:2], 5)
    np.testing.assert_array_equal(idx[0, :3], [0, 4, 8])
    np.testing.assert_array_equal(idx[1, :3], [1, 5, 9])
    assert dist[0, 0] == dist[0, 1] == dist[0, 2] == 0.0


def test_k_beyond_n_pads_and_empty_index():
    x = clustered(5, 8, 0)
    idx, dist = DescriptorIndex(x).topk(x[:1], 7)
    assert idx.shape == (1, 7)
    np.testing.assert_array_equal(idx[0, 5:], [-1, -1])
    assert np.isinf(dist[0, 5:]).all()
    empty = DescriptorIndex(np.zeros((0, 8), np.float32), dtype="float16")
    assert len(empty) == 0 and empty.dim == 8
    idx, dist = empty.topk(x, 3)
    assert (idx == -1).all() and np.isinf(dist).all()
    offsets, ridx, rdist = empty.radius(x, 1.0)
    np.testing.assert_array_equal(offsets, np.zeros(6, np.int64))
    assert ridx.shape == (0,) and rdist.shape == (0,)


@pytest.mark.parametrize("dtype", ["float16", "bfloat16", "int8"])
def test_compressed_is_exact_on_realistic_data(dtype):
    x = clustered(20_000, 256, 1)
    q = revisits(x, 70, 2)  # 64 batched + 6 one by one
    exact_idx, exact_dist = DescriptorIndex(x).topk(q, 20)
    index = DescriptorIndex(x, dtype=dtype)
    assert index.dtype == dtype
    single = [index.topk(q[i], 20) for i in range(len(q))]
    idx = np.concatenate([s[0] for s in single])
    dist = np.concatenate([s[1] for s in single])
    ref_idx, _ = ref.topk(q, x, 20)
    recall = np.mean([len(set(a) & set(b)) / 20 for a, b in zip(idx, ref_idx, strict=True)])
    assert recall >= 0.999
    # Exact re-scoring: identical to the float32 index, single queries and batch.
    np.testing.assert_array_equal(idx, exact_idx)
    np.testing.assert_array_equal(dist, exact_dist)
    np.testing.assert_array_equal(index.topk(q, 20)[0], exact_idx)


def test_int8_equals_float32_with_ties_and_radius():
    """int8 storage + exact re-scoring returns bitwise the float32 index's results, including
    duplicated rows (ties by lower index) and radius queries."""
    x = clustered(5_000, 128, 11, clusters=20, spread=0.5)
    x[[900, 2500, 4999]] = x[7]  # ties with row 7
    q = np.concatenate([revisits(x, 6, 12, noise=0.05), x[7:8]])
    f32, i8 = DescriptorIndex(x), DescriptorIndex(x, dtype="int8")
    for i in range(len(q)):
        for a, b in zip(i8.topk(q[i], 20), f32.topk(q[i], 20), strict=True):
            np.testing.assert_array_equal(a, b)
        for a, b in zip(i8.radius(q[i], 0.7), f32.radius(q[i], 0.7), strict=True):
            np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(i8.topk(x[7], 4)[0], [[7, 900, 2500, 4999]])


@pytest.mark.parametrize("r", [0.1, 0.5, 1.0])
def test_early_abandon_radius_equals_full_scan(r):
    """Single float32 queries (early-abandoning scan) equal the batch tile path (which never
    abandons) bitwise, and the reference set."""
    x = clustered(6_000, 256, 13, clusters=30, spread=0.4)
    q = revisits(x, 8, 14, noise=0.03)  # a batch of exactly 8: one tile, no abandoning
    index = DescriptorIndex(x)
    batch = index.radius(q, r)
    full = ref.distances(q, x)
    for i in range(8):
        _, idx, dist = index.radius(q[i], r)
        a, b = batch[0][i], batch[0][i + 1]
        np.testing.assert_array_equal(idx, batch[1][a:b])
        np.testing.assert_array_equal(dist, batch[2][a:b])
        want = np.flatnonzero(full[i] < r)
        border = set(np.flatnonzero(np.abs(full[i] - r) < 1e-4))
        assert set(idx) - border == set(want) - border
        assert len(idx) > 0 or r < 0.5


def assert_radius_equal(got, want, r, full):
    offsets, idx, dist = got
    assert offsets.dtype == np.int64 and idx.dtype == np.int64 and dist.dtype == np.float32
    assert offsets.shape == want[0].shape and offsets[0] == 0
    for q in range(len(offsets) - 1):
        mine = idx[offsets[q] : offsets[q + 1]]
        theirs = want[1][want[0][q] : want[0][q + 1]]
        border = set(np.flatnonzero(np.abs(full[q] - r) < 1e-4))
        assert set(mine) - border == set(theirs) - border
        d = dist[offsets[q] : offsets[q + 1]]
        assert (np.diff(d) >= 0).all() and (d < r).all()
        np.testing.assert_allclose(d, full[q, mine], atol=1e-3)


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(0, 300),
    d=st.integers(1, 24),
    nq=st.integers(1, 10),
    r=st.floats(0.05, 6.0),
    dtype=st.sampled_from(DTYPES),
    seed=st.integers(0, 2**31),
)
def test_radius_matches_reference(n, d, nq, r, dtype, seed):
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((n, d)).astype(np.float32)
    q = rng.standard_normal((nq, d)).astype(np.float32)
    got = DescriptorIndex(x, dtype=dtype).radius(q, r)
    assert_radius_equal(got, ref.radius(q, x, r), r, ref.distances(q, x))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("nq", [1, 9])
def test_radius_realistic(dtype, nq):
    x = clustered(5000, 64, 3, spread=0.15)
    q = revisits(x, nq, 4)
    for r in (0.1, 0.2, 0.5):
        got = DescriptorIndex(x, dtype=dtype).radius(q, r)
        assert_radius_equal(got, ref.radius(q, x, r), r, ref.distances(q, x))
    assert len(got[1]) > 0


@pytest.mark.parametrize("dtype", DTYPES)
def test_radius_holds_for_the_real_r_at_its_float32_edges(dtype):
    x = np.eye(4, dtype=np.float32)
    index = DescriptorIndex(x, dtype=dtype)
    q = np.array([[1.0, 1.0, 0.0, 0.0]], np.float32)  # rows 0 and 1 at distance exactly 1
    assert index.radius(q, 1.0)[1].tolist() == []  # strict <
    assert index.radius(q, 1.00000001)[1].tolist() == [0, 1]  # 1.0 < r, r rounds to 1.0
    # r² below float32's normal range: the rows at distance 0 stay
    for r in (1e-23, 1e-38, 2e-45):
        assert index.radius(x[:1], r)[1].tolist() == [0]


@pytest.mark.parametrize("whole_group", [False, True])
def test_exclusion_rule(whole_group):
    n, d = 600, 16
    x = clustered(n, d, 5, clusters=5)
    groups = np.repeat([0, 1, 2], n // 3)
    seqs = np.tile(np.arange(n // 3), 3)
    qi = np.array([10, 250, 590])
    ex = Exclusion(groups=groups[qi], seqs=seqs[qi], window=5, whole_group=whole_group)
    index = DescriptorIndex(x, groups=groups, seqs=seqs)
    mask = ref.excluded(groups, seqs, groups[qi], seqs[qi], 5, whole_group)
    idx, dist = index.topk(x[qi], 30, exclude=ex)
    ref_idx, ref_dist = ref.topk(x[qi], x, 30, mask)
    assert_topk_equal(idx, dist, ref_idx, ref_dist, ref.distances(x[qi], x))
    assert not mask[np.arange(3)[:, None], idx].any()
    got = index.radius(x[qi], 1.0, exclude=ex)
    full = ref.distances(x[qi], x)
    assert_radius_equal(got, ref.radius(x[qi], x, 1.0, mask), 1.0, full)
    # The query itself (distance 0) is always excluded.
    assert 10 not in got[1][got[0][0] : got[0][1]]


def test_exclusion_at_the_ends_of_int64_matches_the_reference():
    # the reference once took |map_seq - query_seq| in int64, which wrapped past 2**63
    lo, hi = np.iinfo(np.int64).min, np.iinfo(np.int64).max
    seqs = np.array([lo, lo + 1, -1, 0, 1, hi - 1, hi], np.int64)
    x = clustered(len(seqs), 8, 11)
    index = DescriptorIndex(x, groups=np.zeros(len(seqs), np.int64), seqs=seqs)
    for window in (0, 1, 2**62, 2**63 - 1):
        ex = Exclusion(groups=np.zeros(len(seqs), np.int64), seqs=seqs, window=window)
        mask = ref.excluded(np.zeros(len(seqs)), seqs, np.zeros(len(seqs)), seqs, window)
        want = np.abs(seqs.astype(object)[None, :] - seqs.astype(object)[:, None]) <= window
        np.testing.assert_array_equal(mask, want.astype(bool))
        idx, dist = index.topk(x, len(seqs), exclude=ex)
        ref_idx, ref_dist = ref.topk(x, x, len(seqs), mask)
        assert_topk_equal(idx, dist, ref_idx, ref_dist, ref.distances(x, x))
    assert not mask.all()  # lo and hi stay 2**64 - 1 apart, past any window


def test_default_groups_and_seqs_and_add():
    x = clustered(100, 12, 6)
    index = DescriptorIndex(x[:40], dtype="bfloat16")
    index.add(x[40:])
    one_shot = DescriptorIndex(x, dtype="bfloat16")
    np.testing.assert_array_equal(index.descriptors, x)
    np.testing.assert_array_equal(index.seqs, np.arange(100))
    np.testing.assert_array_equal(index.groups, np.zeros(100))
    np.testing.assert_array_equal(index.topk(x, 5)[0], one_shot.topk(x, 5)[0])
    ex = Exclusion(groups=0, seqs=np.arange(100), window=2)
    idx, _ = index.topk(x, 1, exclude=ex)
    assert (np.abs(idx[:, 0] - np.arange(100)) > 2).all()


@pytest.mark.parametrize("dtype", DTYPES)
def test_save_load_round_trip(tmp_path, dtype):
    x = clustered(300, 20, 7)
    index = DescriptorIndex(x, dtype=dtype, groups=np.arange(300) // 100, seqs=np.arange(300) * 2)
    path = tmp_path / "map.vvidx"
    index.save(path)
    back = DescriptorIndex.load(path)
    assert (len(back), back.dim, back.dtype) == (300, 20, dtype)
    np.testing.assert_array_equal(back.descriptors, x)
    np.testing.assert_array_equal(back.groups, index.groups)
    np.testing.assert_array_equal(back.seqs, index.seqs)
    for a, b in zip(back.topk(x[:5], 4), index.topk(x[:5], 4), strict=True):
        np.testing.assert_array_equal(a, b)
    assert os.listdir(tmp_path) == ["map.vvidx"]  # no temporary file left behind


def test_save_and_load_take_bytes_paths_and_name_a_bad_one(tmp_path):
    index = DescriptorIndex(clustered(20, 4, 3))
    raw = os.fsencode(tmp_path / "i.vvidx")
    index.save(raw)
    np.testing.assert_array_equal(DescriptorIndex.load(raw).descriptors, index.descriptors)
    for call in (lambda: index.save(3), lambda: DescriptorIndex.load(None)):
        with pytest.raises(TypeError, match=r"^path: expected a str or os.PathLike, got"):
            call()
    # a bare OSError (os error 2) before, where every other vvloc reader says FileNotFoundError
    with pytest.raises(FileNotFoundError, match=r"^index file not found: .*none\.vvidx"):
        DescriptorIndex.load(tmp_path / "none.vvidx")


def test_save_replaces_a_file_as_every_vvloc_file_is_replaced(tmp_path):
    x = clustered(40, 8, 3)
    private = tmp_path / "private.vvidx"
    private.write_bytes(b"old")
    private.chmod(0o600)
    DescriptorIndex(x).save(private)
    assert private.stat().st_mode & 0o777 == 0o600  # a private file stays private
    np.testing.assert_array_equal(DescriptorIndex.load(private).descriptors, x)
    # a link's target is replaced, the link kept
    target = tmp_path / "target.vvidx"
    target.write_bytes(b"old")
    link = tmp_path / "link.vvidx"
    link.symlink_to(target)
    DescriptorIndex(x).save(link)
    assert link.is_symlink() and len(DescriptorIndex.load(target)) == 40
    assert sorted(os.listdir(tmp_path)) == ["link.vvidx", "private.vvidx", "target.vvidx"]


def test_truncated_or_corrupted_file_is_a_clear_error(tmp_path):
    path = tmp_path / "map.vvidx"
    DescriptorIndex(clustered(50, 8, 8)).save(path)
    data = path.read_bytes()
    for cut in (0, 20, len(data) - 1):
        path.write_bytes(data[:cut])
        with pytest.raises(ValueError, match="truncated"):
            DescriptorIndex.load(path)
    for pos in (3, 60, len(data) - 5):
        bad = bytearray(data)
        bad[pos] ^= 0xFF
        path.write_bytes(bytes(bad))
        with pytest.raises(ValueError, match="not a valid vvloc descriptor index"):
            DescriptorIndex.load(path)
    with pytest.raises(OSError):
        DescriptorIndex.load(tmp_path / "missing.vvidx")
    with pytest.raises(OSError):
        DescriptorIndex(clustered(5, 8, 8)).save(tmp_path / "no_such_dir" / "x.vvidx")


def test_bad_input_raises_value_error_naming_the_argument():
    x = clustered(50, 8, 9)
    index = DescriptorIndex(x)
    cases = [
        (lambda: index.topk(np.ones((2, 7)), 3), "queries"),
        (lambda: index.topk(x[:2], 0), "k"),
        (lambda: index.radius(x[:2], 0.0), "r"),
        (lambda: index.radius(x[:2], -1.0), "r"),
        (lambda: index.radius(x[:2], float("nan")), "r"),
        (lambda: index.topk(np.full((1, 8), np.nan), 3), "queries"),
        (lambda: DescriptorIndex(np.array([[1.0, np.inf]])), "descriptors"),
        (lambda: DescriptorIndex(x, dtype="int4"), "dtype"),
        (lambda: DescriptorIndex(x, groups=np.zeros(3, np.int64)), "groups"),
        (lambda: DescriptorIndex(np.full((2, 3), 1e6), dtype="float16"), "descriptors"),
        (lambda: index.add(np.ones((2, 9))), "descriptors"),
        (lambda: index.topk(x[:2], 3, exclude=Exclusion([0], [0, 1])), "exclude.groups"),
        (lambda: index.topk(x[:2], 3, exclude=Exclusion([0, 0], [0, 1], -1)), "exclude.window"),
        # d beyond the core's limit: refused before a float32 copy or statistics of d entries
        (lambda: DescriptorIndex(np.zeros((0, 2**40), np.float32)), r"^descriptors: dimension"),
        (lambda: DescriptorIndex(np.zeros((1, 2**20 + 1), np.float32)), r"^descriptors: dim"),
    ]
    for call, name in cases:
        with pytest.raises(ValueError, match=name):
            call()
    # numpy's dtype objects name a storage as the strings do; other types are refused by name
    assert DescriptorIndex(x, dtype=np.dtype("float16")).topk(x[:1], 1)[0][0, 0] == 0
    with pytest.raises(TypeError, match=r"^dtype: expected one of .*, got int"):
        DescriptorIndex(x, dtype=3)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="k"):
        index.topk(x[:2], 2.5)
    with pytest.raises(TypeError, match="exclude"):
        index.topk(x[:2], 2, exclude=(0, 0))
    with pytest.raises(TypeError, match=r"^exclude.whole_group: expected a bool"):
        index.topk(x[:2], 2, exclude=Exclusion([0, 0], [0, 1], whole_group="no"))


def test_sizes_and_magnitudes_beyond_the_kernels_are_errors_not_aborts(tmp_path):
    x = clustered(50, 8, 9)
    index = DescriptorIndex(x)
    # squared distances beyond float32: refused (they came back as inf or 0 before)
    with pytest.raises(ValueError, match=r"^descriptors: values too large"):
        DescriptorIndex(x * 1e19)
    with pytest.raises(ValueError, match=r"^queries: values too large"):
        index.topk(x[:2] * 1e31, 3)
    # k may exceed N (padding), but not memory: MemoryError, not an abort
    assert (index.topk(x[:1], 60)[0][0, 50:] == -1).all()
    for k in (2**40, 2**62):
        with pytest.raises(MemoryError, match=r"^k: "):
            index.topk(x[:2], k)
    # no query: the (0, k) result holds nothing, but numpy bounds its other axis all the same
    # (this crashed numpy); in a child process, so that a crash fails only this test
    import subprocess
    import sys

    code = """
import numpy as np
from vvloc import DescriptorIndex, _core
for call in (lambda: DescriptorIndex(np.zeros((3, 4))).topk(np.zeros((0, 4)), 2**60),
             lambda: _core.DescriptorIndex(np.zeros((3, 4), np.float32)).topk(
                 np.zeros((0, 4), np.float32), 2**63)):
    try:
        call()
    except MemoryError as e:
        print("MemoryError", e)
print(DescriptorIndex(np.zeros((3, 4))).topk(np.zeros((0, 4)), 5)[0].shape)
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert [line[:15] for line in lines[:2]] == ["MemoryError k: "] * 2, r.stdout
    assert lines[2:] == ["(0, 5)"], r.stdout
    # radii float32 cannot hold
    for r in (1e300, 1e-50, 1e-45):  # the bound the message names is the one it keeps
        with pytest.raises(ValueError, match=r"^r: expected a radius float32 can hold") as err:
            index.radius(x[:2], r)
    low, high = re.search(r"\((\S+) \.\. (\S+)\)", str(err.value)).groups()  # type: ignore[union-attr]
    index.radius(x[:2], float(low))  # the bounds the message names are taken
    index.radius(x[:2], float(high))
    with pytest.raises(ValueError, match=r"^r: expected a radius"):
        index.radius(x[:2], 1.4e-45)  # below float32's smallest, 1.401298e-45
    # uint64 ids beyond int64 would wrap to negative numbers
    with pytest.raises(ValueError, match=r"^groups: values must fit in int64"):
        DescriptorIndex(x[:2], groups=np.array([1, 2**64 - 1], np.uint64))
    # a forged header (N = 0, d = 2^40, valid checksum) is refused, not allocated
    from vvloc import _core

    empty = tmp_path / "empty.vvidx"
    DescriptorIndex(np.zeros((0, 4), np.float32)).save(empty)
    data = bytearray(empty.read_bytes())
    assert len(data) == 40
    data[24:32] = (2**40).to_bytes(8, "little")
    h = 0xCBF29CE484222325  # the format's FNV-style sum of 8-byte words over bytes 8..32
    for i in range(8, 32, 8):
        h = ((h ^ int.from_bytes(data[i : i + 8], "little")) * 0x100000001B3) % 2**64
    data[32:40] = h.to_bytes(8, "little")
    empty.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="dimension d must be <="):
        _core.DescriptorIndex.load(str(empty))
    # the raw extension takes row-major memory only: a Fortran-ordered array (contiguous, but
    # column by column) was read as if it were row-major
    raw = _core.DescriptorIndex(x)
    for call, name in (
        (lambda: _core.DescriptorIndex(np.asfortranarray(x)), "descriptors"),
        (lambda: raw.topk(np.asfortranarray(x[:3]), 2), "queries"),
        (lambda: raw.radius(np.asfortranarray(x[:3]), 0.5), "queries"),
        (lambda: raw.add(np.asfortranarray(x[:3])), "descriptors"),
    ):
        with pytest.raises(ValueError, match=f"^{name}: expected a C-contiguous array"):
            call()
    assert len(raw) == 50


def test_load_reads_no_body_of_a_file_its_header_refuses(tmp_path):
    # load read the whole file before its header: a 3 GiB foreign file (sparse, nothing on
    # disk) took 9 s and 3 GiB, and under an address-space limit its refusal was "out of
    # memory" instead of the format error
    from memory_helpers import run_limited

    path = tmp_path / "foreign.vvidx"
    with open(path, "wb") as f:
        f.write(b"NOTANIDX" + bytes(32))
        f.truncate(3 << 30)
    lines = run_limited(f"""
from vvloc import DescriptorIndex
limit(256)
try:
    DescriptorIndex.load({str(path)!r})
except (ValueError, OSError, MemoryError) as e:
    print(type(e).__name__, e)
""")
    assert len(lines) == 1 and lines[0].startswith("ValueError"), lines
    assert "foreign.vvidx" in lines[0] and "wrong magic bytes" in lines[0], lines
    # a valid header for those 3 GiB: the body's buffer is refused as a MemoryError naming the
    # path (reserved fallibly, not an abort)
    import struct

    n, d = ((3 << 30) - 40) // (2 * 4 + 16), 2
    with open(path, "r+b") as f:
        f.write(b"VVLOCIDX" + struct.pack("<IIQQQ", 1, 0, n, d, 0))
        f.truncate(40 + n * (d * 4 + 16))
    lines = run_limited(f"""
from vvloc import DescriptorIndex
limit(256)
attempt("load", lambda: DescriptorIndex.load({str(path)!r}))
""")
    assert lines[0].startswith("load MemoryError path:") and "foreign.vvidx" in lines[0], lines


def test_out_of_memory_is_a_memory_error_not_an_abort():
    # under an address-space limit (ulimit -v, common on clusters), building an index or
    # collecting radius hits that do not fit raised nothing: the allocator aborted the process
    from memory_helpers import run_limited

    lines = run_limited("""
import numpy as np
from vvloc import DescriptorIndex

x = np.ones((2_000_000, 64), np.float32)  # 512 MiB, allocated before the limit
small = DescriptorIndex(np.random.default_rng(0).standard_normal((2_000, 64)))
q = np.zeros((50_000, 64), np.float32)  # every row a hit: 10^8 hits, 800 MB
limit(256)
attempt("build", lambda: DescriptorIndex(x))
attempt("add", lambda: small.add(x))
attempt("radius", lambda: small.radius(q, 1e6))
print(len(small))
""")
    assert [line.split(":")[0] for line in lines] == [
        "build MemoryError descriptors",
        "add MemoryError descriptors",
        "radius MemoryError r",
        "2000",  # the failed add left the index as it was
    ], lines


def test_misaligned_and_bfloat16_input_is_taken():
    # np.frombuffer at an odd offset gives C-contiguous memory that is not aligned: it was
    # refused as "not C-contiguous" (and the kernels viewed it misaligned)
    x = clustered(40, 8, 3)
    buf = bytearray(x.nbytes + 1)
    u = np.frombuffer(buf, dtype=np.float32, count=x.size, offset=1).reshape(x.shape)
    u[...] = x
    assert u.flags.c_contiguous and not u.flags.aligned
    want = DescriptorIndex(x).topk(x[:3], 4)
    got = DescriptorIndex(u).topk(u[:3], 4)
    assert np.array_equal(want[0], got[0]) and np.array_equal(want[1], got[1])
    from vvloc import kernels

    t = torch.tensor([[0.5, -1.0], [2.0, 0.25]], dtype=torch.bfloat16)
    bev = np.ones((4, 4, 2), np.float32)
    assert np.array_equal(
        kernels.bev_pad(bev, t, 0.5), kernels.bev_pad(bev, t.float().numpy(), 0.5)
    )


def test_rows_the_float32_expansion_cannot_order_warn():
    rng = np.random.default_rng(0)
    offset = 100.0 + 0.01 * rng.standard_normal((200, 16))
    with pytest.warns(UserWarning, match="share an offset far larger than their spread"):
        DescriptorIndex(offset)
    with pytest.warns(UserWarning, match="norms are below 1e-15"):
        DescriptorIndex(rng.standard_normal((20, 8)) * 1e-24)
    index = DescriptorIndex(clustered(50, 8, 1))  # unit-norm clusters: no warning
    with pytest.warns(UserWarning, match="share an offset"):
        index.add(offset[:, :8])
    # centred, the same rows are ordered as float64 orders them
    centred = offset - offset.mean(axis=0)
    q = centred[7] + 0.001 * rng.standard_normal(16)
    idx, _ = DescriptorIndex(centred).topk(q, 3)
    exact = np.argsort(np.linalg.norm(centred - q, axis=1))[:3]
    assert idx[0].tolist() == exact.tolist()
    DescriptorIndex(np.ones((5, 4)))  # one row repeated: all tie, nothing to warn about


def test_an_index_built_one_row_at_a_time_warns_as_one_built_at_once(tmp_path):
    # each batch of one row passed the check (fewer than 2 rows), and the top-3 of row 37
    # came back as [0, 1, 2] at distance 0: the whole index is judged, once
    rows = 100.0 + 0.01 * np.random.default_rng(0).standard_normal((50, 16))
    index = DescriptorIndex(rows[:1])
    with pytest.warns(UserWarning, match="cannot order the index with these rows: .*offset"):
        for r in rows[1:]:
            index.add(r[None])
    index.save(tmp_path / "i.vvidx")
    loaded = DescriptorIndex.load(tmp_path / "i.vvidx")
    with pytest.warns(UserWarning, match="share an offset") as caught:
        loaded.add(rows[:2])
    assert len(caught) == 1  # the batch's own warning, not a second for the index
    fine = DescriptorIndex(clustered(50, 8, 1)[:1])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for r in clustered(50, 8, 1)[1:]:
            fine.add(r[None])  # unit-norm clusters: no warning
        DescriptorIndex.load(tmp_path / "i.vvidx").add(rows[2:3])  # already ill, said before
    assert len(fine) == 50


def test_thread_count_is_bounded():
    before = vvloc.get_num_threads()
    try:
        vvloc.set_num_threads(np.int64(1))
        assert vvloc.get_num_threads() == 1
        for n in (0, 1025, 10**6):
            with pytest.raises(ValueError, match=r"n: expected an int in \[1, 1024\]"):
                vvloc.set_num_threads(n)
        with pytest.raises(TypeError, match="n: "):
            vvloc.set_num_threads(2.0)  # type: ignore[arg-type]
    finally:
        vvloc.set_num_threads(before)


def test_accepts_torch_float64_and_non_contiguous():
    x = clustered(200, 16, 10)
    index = DescriptorIndex(torch.from_numpy(x.astype(np.float64)))
    q = np.asfortranarray(x[:6].astype(np.float64))[:, :]
    want = DescriptorIndex(x).topk(x[:6], 4)
    for got in (index.topk(q, 4), index.topk(torch.from_numpy(x[:6]), 4), index.topk(x[0], 4)):
        np.testing.assert_array_equal(got[0], want[0][: len(got[0])])


def test_concurrent_queries_from_python_threads():
    x = clustered(30_000, 64, 11)
    q = clustered(40, 64, 12)
    index = DescriptorIndex(x, dtype="bfloat16")
    want = [index.topk(q[i : i + 1], 10) for i in range(len(q))]
    with ThreadPoolExecutor(4) as pool:
        got = list(pool.map(lambda i: index.topk(q[i : i + 1], 10), range(len(q))))
    for (gi, gd), (wi, wd) in zip(got, want, strict=True):
        np.testing.assert_array_equal(gi, wi)
        np.testing.assert_array_equal(gd, wd)


def test_queries_and_adds_from_threads_finish():
    """Two threads query while a third adds. A pool worker waiting inside one query's join may
    run the other query's job; that job used to take its read lock there, queued behind the
    waiting add, which waited for the first query's read lock held lower on the same worker's
    stack: every thread (and, through a lock taken with the GIL held, the interpreter) hung."""
    x, q, extra = clustered(20_000, 256, 21), clustered(8, 256, 22), clustered(1, 256, 23)
    before = vvloc.get_num_threads()
    vvloc.set_num_threads(2)
    try:
        index = DescriptorIndex(x)
        stop = time.monotonic() + 3.0
        calls = {"query": 0, "add": 0}

        def query() -> None:
            while time.monotonic() < stop:
                index.topk(q, 5)
                calls["query"] += 1

        def add() -> None:
            while time.monotonic() < stop:
                index.add(extra)
                calls["add"] += 1
                time.sleep(0.001)

        threads = [threading.Thread(target=f, daemon=True) for f in (query, query, add)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=60)
        assert not any(t.is_alive() for t in threads), f"deadlocked after {calls}"
        assert len(index) == len(x) + calls["add"]
    finally:
        vvloc.set_num_threads(before)


def test_a_fork_waits_for_the_index_calls_under_way():
    """A forked child inherits each lock as it was: an index that another thread was adding to
    (or querying) at the fork used to stay locked in the child for ever. The fork now waits for
    the calls under way, so the child gets the index whole (before or after the add) and free."""
    index = DescriptorIndex(clustered(2_000, 64, 31))
    big = clustered(100_000, 64, 32)
    for delay in (0.0, 0.005, 0.02, 0.05):
        before = len(index)
        adder = threading.Thread(target=index.add, args=(big,))
        adder.start()
        time.sleep(delay)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)  # fork with threads (3.12+)
            pid = os.fork()
        if pid == 0:  # the child: query, add, and report whether it saw the index whole
            code = 1
            try:
                whole = len(index) in (before, before + len(big))
                index.topk(big[:4], 3)
                index.add(big[:1])
                code = 0 if whole else 3
            finally:
                os._exit(code)
        code = exit_code_or_hang(pid)
        adder.join()
        assert code is not None, f"the child hung (fork {delay} s after the add began)"
        assert code == 0, f"fork {delay} s after the add began"


def test_one_and_two_threads_identical():
    x = clustered(40_000, 64, 13)
    q = clustered(20, 64, 14)
    before = vvloc.get_num_threads()
    results = []
    try:
        for threads in (1, 2):
            vvloc.set_num_threads(threads)
            for dtype in ("float32", "float16"):
                index = DescriptorIndex(x, dtype=dtype)
                results.append((index.topk(q, 20), index.topk(q[:1], 20), index.radius(q, 0.3)))
    finally:
        vvloc.set_num_threads(before)
    for a, b in zip(results[:2], results[2:], strict=True):
        for xa, xb in zip(a, b, strict=True):
            for u, v in zip(xa, xb, strict=True):
                np.testing.assert_array_equal(u, v)
