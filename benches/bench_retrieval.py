"""Descriptor retrieval: vvloc.DescriptorIndex vs faiss-cpu IndexFlatL2 and torch brute force.

d = 256, K = 20, N ∈ {1e4, 1e5, 1e6}, nq ∈ {1, 64, 1024 (N ≤ 1e5)}, plus radius queries at
r = 0.1 and 0.2, and single top-20 queries in maps of one place seen N times (N = 1e4 to 8e4,
``--one_place`` runs only these: the compressed scans' hardest case), and an index grown one
row at a time (``--adds`` runs only these: N = 2e3 to 8e3 adds, float32 and int8, the rows in
random order and in order of rising |x_0|, the int8 ranges' worst case). Realistic descriptors:
places (cluster centres) seen by ~100 keyframes each (a Gaussian mixture, L2-normalised);
queries revisit random keyframes with noise of L2 size U(0.05, 0.2). Every cell checks, in the
same run, that vvloc's results equal exact search (float64 brute force on up to 16 queries;
indices identical outside float32 near-ties) and that the compressed indices (bfloat16,
float16, int8) return exactly the float32 index's results (recall@20 = 1.0).

Usage: ``python benches/bench_retrieval.py [--quick] [--one_place] [--adds] [--json PATH]``
(faiss-cpu and torch from the ``bench`` extra; a missing peer is reported and skipped).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import Any

import numpy as np

import vvloc
from _common import print_table, write_json
from vvloc import DescriptorIndex, _core

try:
    import faiss
except ImportError:  # pragma: no cover - optional peer
    faiss = None
    print("faiss-cpu is not installed: its columns are skipped (pip install faiss-cpu)")
try:
    import torch
except ImportError:  # pragma: no cover - optional peer
    torch = None
    print("torch is not installed: its columns are skipped")

D, K = 256, 20


def descriptors(n: int, seed: int) -> np.ndarray:
    """(n, D) float32 L2-normalised Gaussian mixture, ~100 keyframes per place."""
    rng = np.random.default_rng(seed)
    places = max(1, n // 100)
    centres = rng.standard_normal((places, D), dtype=np.float32)
    out = np.empty((n, D), np.float32)
    for s in range(0, n, 100_000):
        e = min(n, s + 100_000)
        x = centres[rng.integers(0, places, e - s)]
        x += 0.5 * rng.standard_normal((e - s, D), dtype=np.float32)
        out[s:e] = x / np.linalg.norm(x, axis=1, keepdims=True)
    return out


def revisits(x: np.ndarray, nq: int, seed: int) -> np.ndarray:
    """Queries near random map entries (L2 offset U(0.05, 0.2)), normalised, float32 (nq, D)."""
    rng = np.random.default_rng(seed)
    g = rng.standard_normal((nq, D))
    g *= rng.uniform(0.05, 0.2, (nq, 1)) / np.linalg.norm(g, axis=1, keepdims=True)
    q = x[rng.integers(0, len(x), nq)] + g
    return (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)


def exact_sq(q: np.ndarray, x: np.ndarray) -> np.ndarray:
    """float64 squared distances (nq, N), chunked over the map."""
    q64 = q.astype(np.float64)
    out = np.empty((len(q), len(x)))
    for s in range(0, len(x), 100_000):
        xs = x[s : s + 100_000].astype(np.float64)
        out[:, s : s + len(xs)] = ((q64[:, None, :] - xs[None]) ** 2).sum(-1)
    return out


def topk_is_exact(idx: np.ndarray, q: np.ndarray, x: np.ndarray) -> bool:
    """vvloc's top-K equals exact search on up to 16 queries (ties within 1e-5 allowed)."""
    sq = exact_sq(q[:16], x)
    for i in range(len(sq)):
        order = np.lexsort((np.arange(len(x)), sq[i]))[:K]
        if not np.array_equal(idx[i], order):
            kth = sq[i, order[-1]]
            ok = np.allclose(np.sort(sq[i, idx[i]]), sq[i, order], atol=1e-5)
            if not ok or (sq[i, idx[i]] > kth + 1e-5).any():
                return False
    return True


def radius_is_exact(res: tuple[Any, Any, Any], q: np.ndarray, x: np.ndarray, r: float) -> bool:
    sq = exact_sq(q[:16], x)
    off, idx, _ = res
    for i in range(len(sq)):
        want = set(np.flatnonzero(sq[i] < r * r))
        got = set(idx[off[i] : off[i + 1]])
        border = set(np.flatnonzero(np.abs(np.sqrt(sq[i]) - r) < 1e-5))
        if want - border != got - border:
            return False
    return True


def timed(fn: Callable[[], Any], budget: float) -> float:
    """Median seconds per call: one warm-up, then up to 7 calls within ``budget`` seconds."""
    fn()
    times: list[float] = []
    start = time.perf_counter()
    while len(times) < 7 and (len(times) < 3 or time.perf_counter() - start < budget):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def bandwidth_gbs(threads: int) -> float:
    """Read bandwidth (GB/s) of summing a 512 MiB float32 array (torch, ``threads`` threads)."""
    if torch is None:
        return float("nan")
    a = torch.ones(128 * 1024 * 1024)
    torch.set_num_threads(threads)
    return a.numel() * 4 / timed(lambda: a.sum(), 1.0) / 1e9


def torch_topk(x_t: Any, xn: Any, q: np.ndarray) -> Any:
    qt = torch.from_numpy(q)
    sq = (qt * qt).sum(1, keepdim=True) + xn[None, :] - 2.0 * qt @ x_t.T
    return torch.topk(sq, K, dim=1, largest=False)


def torch_radius(x_t: Any, xn: Any, q: np.ndarray, r: float) -> Any:
    qt = torch.from_numpy(q)
    sq = (qt * qt).sum(1, keepdim=True) + xn[None, :] - 2.0 * qt @ x_t.T
    return torch.nonzero(sq < r * r)


def bench_size(n: int, budget: float, bw: float, rows: list[dict[str, Any]]) -> None:
    """Time every cell of map size ``n`` and append the rows."""
    blas_default = faiss.cvar.distance_compute_blas_threshold if faiss is not None else 0
    x = descriptors(n, seed=n)
    qs = revisits(x, 1024, seed=n + 1)
    f32 = DescriptorIndex(x)
    bf16 = DescriptorIndex(x, dtype="bfloat16")
    f16 = DescriptorIndex(x, dtype="float16")
    i8 = DescriptorIndex(x, dtype="int8")
    flat = None
    if faiss is not None:
        flat = faiss.IndexFlatL2(D)
        flat.add(x)
    x_t = torch.from_numpy(x) if torch is not None else None
    xn = (x_t * x_t).sum(1) if torch is not None else None
    for nq in (1, 64, 1024):
        if nq == 1024 and n > 100_000:
            continue
        q = qs[:nq]
        row: dict[str, Any] = {"task": f"top{K}", "N": n, "nq": nq}
        idx, dist = f32.topk(q, K)
        row["exact"] = topk_is_exact(idx, q, x)
        row["vvloc_ms"] = 1e3 * timed(lambda q=q: f32.topk(q, K), budget)
        if nq == 1:
            for name, index in (("bf16", bf16), ("f16", f16), ("i8", i8)):
                got = index.topk(q, K)
                row["exact"] &= np.array_equal(got[0], idx) and np.array_equal(got[1], dist)
                row[f"vvloc_{name}_ms"] = 1e3 * timed(lambda q=q, i=index: i.topk(q, K), budget)
            row["floor_f32_ms"] = 1e3 * n * D * 4 / (bw * 1e9)
            row["floor_bf16_ms"] = row["floor_f32_ms"] / 2
            row["floor_i8_ms"] = row["floor_f32_ms"] / 4
        if flat is not None:
            faiss.cvar.distance_compute_blas_threshold = blas_default
            _, fi = flat.search(q, K)
            row["faiss_agree"] = float(np.mean(fi == idx))
            row["faiss_ms"] = 1e3 * timed(lambda q=q: flat.search(q, K), budget)
            faiss.cvar.distance_compute_blas_threshold = 0
            row["faiss_blas_ms"] = 1e3 * timed(lambda q=q: flat.search(q, K), budget)
            faiss.cvar.distance_compute_blas_threshold = blas_default
            row["x_faiss"] = row["faiss_ms"] / row["vvloc_ms"]
            row["x_faiss_blas"] = row["faiss_blas_ms"] / row["vvloc_ms"]
            if nq == 1:
                row["x_faiss_bf16"] = row["faiss_ms"] / row["vvloc_bf16_ms"]
                row["x_faiss_i8"] = row["faiss_ms"] / row["vvloc_i8_ms"]
        if torch is not None and nq * n <= 64 * 1_000_000:
            row["torch_ms"] = 1e3 * timed(lambda q=q: torch_topk(x_t, xn, q), budget)
        rows.append(row)
        print_table([row], list(row))
    for nq in (1, 64):
        for r in (0.1, 0.2):
            q = qs[:nq]
            row = {"task": f"radius {r}", "N": n, "nq": nq}
            res = f32.radius(q, r)
            row["hits/q"] = len(res[1]) / nq
            row["exact"] = radius_is_exact(res, q, x, r)
            row["vvloc_ms"] = 1e3 * timed(lambda q=q, r=r: f32.radius(q, r), budget)
            if nq == 1:
                for name, index in (("bf16", bf16), ("i8", i8)):
                    got = index.radius(q, r)
                    row["exact"] &= all(np.array_equal(a, b) for a, b in zip(got, res, strict=True))
                    row[f"vvloc_{name}_ms"] = 1e3 * timed(
                        lambda q=q, r=r, i=index: i.radius(q, r), budget
                    )
            if flat is not None:
                row["faiss_ms"] = 1e3 * timed(lambda q=q, r=r: flat.range_search(q, r * r), budget)
                row["x_faiss"] = row["faiss_ms"] / row["vvloc_ms"]
            if torch is not None:
                row["torch_ms"] = 1e3 * timed(lambda q=q, r=r: torch_radius(x_t, xn, q, r), budget)
            rows.append(row)
            print_table([row], list(row))


def one_place(n: int, seed: int) -> np.ndarray:
    """(n, D) float32 L2-normalised keyframes of one place seen n times (noise 0.02 per
    dimension): thousands of rows within the compressed scan's 2ε of the k-th."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal(D) + 0.02 * rng.standard_normal((n, D))
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def bench_one_place(sizes: list[int], budget: float) -> list[dict[str, Any]]:
    """Top-20 of one query (a map row) in maps of one place: compressed vs float32 ms."""
    rows = []
    for n in sizes:
        x = one_place(n, 0)
        q = x[:1]
        f32 = DescriptorIndex(x)
        want = f32.topk(q, K)
        row: dict[str, Any] = {"task": "top20, one place", "N": n, "nq": 1}
        row["vvloc_ms"] = 1e3 * timed(lambda i=f32, q=q: i.topk(q, K), budget)
        exact = True
        for dtype, key in (("float16", "vvloc_f16_ms"), ("int8", "vvloc_i8_ms")):
            index = DescriptorIndex(x, dtype=dtype)
            got = index.topk(q, K)
            exact &= bool(np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1]))
            row[key] = 1e3 * timed(lambda i=index, q=q: i.topk(q, K), budget)
        row["exact"] = exact
        rows.append(row)
    return rows


def bench_adds(sizes: list[int]) -> list[dict[str, Any]]:
    """µs per ``DescriptorIndex.add`` of one row, N rows from empty (float32 and int8), the
    rows in random order and sorted by rising |x_0| (each row outgrows dimension 0's int8
    range); ``exact``: the grown index's top-20 of 4 queries (a batch under 8: the int8 index
    scans its int8 copy) equal a one-shot float32 index's."""
    rows = []
    for n in sizes:
        x = descriptors(n, 3)
        q = revisits(x, 4, 4)
        want = DescriptorIndex(x).topk(q, K)
        for order in ("random", "rising |x_0|"):
            xs = x[np.argsort(np.abs(x[:, 0]), kind="stable")] if order != "random" else x
            row: dict[str, Any] = {"task": f"add 1 row, {order}", "N": n}
            exact = True
            for dtype, key in (("float32", "vvloc_us"), ("int8", "vvloc_i8_us")):
                index = DescriptorIndex(xs[:1], dtype=dtype)
                t0 = time.perf_counter()
                for i in range(1, n):
                    index.add(xs[i : i + 1])
                row[key] = 1e6 * (time.perf_counter() - t0) / (n - 1)
                perm = np.argsort(np.abs(x[:, 0]), kind="stable") if order != "random" else None
                got = index.topk(q, K)
                got_idx = got[0] if perm is None else perm[got[0]]
                exact &= bool(np.array_equal(got_idx, want[0]) and np.array_equal(got[1], want[1]))
            row["exact"] = exact
            rows.append(row)
            print_table([row], list(row))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="N ≤ 1e5, shorter timing")
    ap.add_argument("--json", default=None, help="write the rows as JSON here")
    ap.add_argument(
        "--one_place", action="store_true", help="only the maps of one place seen N times"
    )
    ap.add_argument("--adds", action="store_true", help="only an index grown one row at a time")
    args = ap.parse_args()
    if _core.build_profile != "release":
        raise SystemExit("refusing to benchmark a debug build: run `make develop`")
    threads = vvloc.get_num_threads()
    budget = 0.3 if args.quick else 1.0
    sizes = [10_000, 100_000] if args.quick else [10_000, 100_000, 1_000_000]
    if faiss is not None:
        faiss.omp_set_num_threads(threads)
    if torch is not None:
        torch.set_num_threads(threads)
    if args.adds:
        adds = bench_adds([2_000, 4_000, 8_000])
        if args.json:
            write_json(args.json, "retrieval", adds)
        return
    one = bench_one_place([10_000, 20_000, 40_000, 80_000], budget)
    if args.one_place:
        print_table(one, ["task", "N", "nq", "vvloc_ms", "vvloc_f16_ms", "vvloc_i8_ms", "exact"])
        return
    bw = bandwidth_gbs(threads)
    print(f"vvloc {vvloc.__version__}, {threads} threads; read bandwidth {bw:.1f} GB/s")
    rows: list[dict[str, Any]] = []
    for n in sizes:
        bench_size(n, budget, bw, rows)
    rows += one
    rows += bench_adds([1_000] if args.quick else [2_000, 8_000])
    print()
    cols = [
        "task", "N", "nq", "hits/q", "vvloc_ms", "vvloc_bf16_ms", "vvloc_f16_ms", "vvloc_i8_ms",
        "faiss_ms", "faiss_blas_ms", "torch_ms", "floor_f32_ms", "floor_bf16_ms", "floor_i8_ms",
        "x_faiss", "x_faiss_blas", "x_faiss_bf16", "x_faiss_i8", "vvloc_us", "vvloc_i8_us",
        "exact",
    ]  # fmt: skip
    print_table(rows, cols)
    if args.json:
        write_json(args.json, "retrieval", rows)


if __name__ == "__main__":
    main()
