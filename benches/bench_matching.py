"""Matching kernels: exact yaw estimation vs the sgemm floor, vectorised torch and the literal
reference; roll_interp, matching_cost, yaw_costs and rerank vs the reference; translation-search
overhead per stage (excluding the decoder).

Usage: ``python benches/bench_matching.py [--json PATH] [--quick]``.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

import vvloc
from _common import print_table, timeit, write_json
from vvloc import _core
from vvloc import kernels as K
from vvloc.reference import matching as ref

T, C = 120, 256


def descriptors(p: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((2, p, T, C)).astype(np.float32)
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    return x[0], x[1]


def torch_estimate_yaw(src: torch.Tensor, tgt: torch.Tensor, step: float = 0.01):
    """Best vectorised torch version: Gram by matmul, integer scan, dense sub-bin scan."""
    p, t, _ = src.shape
    g = torch.matmul(src, tgt.transpose(1, 2))  # (P, T, T): g[j, i] = Ds_j · Dt_i
    ns = (src * src).sum(-1)
    nt = (tgt * tgt).sum(-1)
    d2 = (ns[:, :, None] + nt[:, None, :] - 2 * g).clamp_min(0)
    i = torch.arange(t)
    k = torch.arange(t)
    j = (i[None, :] - k[:, None]) % t  # (k, i) -> source row
    dg = d2[:, j, i[None, :].expand(t, t)]  # (P, k, i)
    e = ((src - torch.roll(src, 1, dims=1)) ** 2).sum(-1)  # e[j] = |Ds_j - Ds_{j-1}|^2
    er = e[:, j]  # (P, k, i)
    a, b = dg, torch.roll(dg, -1, dims=1)
    best = torch.full((p,), math.inf)
    best_s = torch.zeros(p)
    n = round(1 / step)
    for m in range(n):
        w = m * step
        f = ((1 - w) * a + w * b - w * (1 - w) * er).clamp_min(0).sqrt().mean(-1)  # (P, T)
        v, kk = f.min(-1)
        upd = v < best
        best = torch.where(upd, v, best)
        best_s = torch.where(upd, kk.float() + w, best_s)
    return best_s, best


def bench_yaw(pairs: list[int], quick: bool) -> list[dict]:
    rows = []
    for p in pairs:
        src, tgt = descriptors(p, p)
        ts, tt = torch.from_numpy(src), torch.from_numpy(tgt)
        mt = min(0.3, 0.05 if quick else 0.3)
        rust = timeit(lambda s=src, t=tgt: _core.estimate_yaw(s, t), min_time=mt)
        gate = timeit(lambda s=src, t=tgt: K.estimate_yaw(s, t), min_time=mt)
        floor = timeit(lambda a=ts, b=tt: torch.matmul(a, b.transpose(1, 2)), min_time=mt)
        tv = timeit(
            lambda a=ts, b=tt: torch_estimate_yaw(a, b), min_time=mt, repeat=3 if p < 2000 else 1
        )
        # Checks, so that a fast wrong kernel cannot win: the torch scan is never better than
        # the exact minimum, and each returned cost is the cost at the returned shift (by the
        # float64 reference, on up to 20 pairs).
        est = K.estimate_yaw(src, tgt)
        _, tcost = torch_estimate_yaw(ts, tt)
        assert np.all(est.cost <= tcost.numpy() + 1e-5)
        for i in range(min(p, 20)):
            at_shift = ref.shift_cost(src[i], tgt[i], float(est.shift[i]))
            assert abs(at_shift - float(est.cost[i])) <= 1e-4, (i, at_shift, est.cost[i])
        row = {
            "pairs": p,
            "rust_ms": rust * 1e3,
            "gateway_ms": gate * 1e3,
            "sgemm_floor_ms": floor * 1e3,
            "torch_ms": tv * 1e3,
            "x_floor": rust / floor,
            "torch_speedup": tv / rust,
        }
        if p == 20 and not quick:
            t0 = time.perf_counter()
            _, _, ref_cost = ref.estimate_yaw(src, tgt)
            row["reference_ms"] = (time.perf_counter() - t0) * 1e3
            assert np.allclose(est.cost, ref_cost, atol=1e-5), "estimate_yaw: not the reference's"
            row["reference_speedup"] = row["reference_ms"] / row["rust_ms"]
        rows.append(row)
    return rows


def bench_kernels(quick: bool) -> list[dict]:
    """The other matching kernels at the localizer's sizes, Rust against the reference
    (``backend="reference"``), each result checked against the reference's: ``roll_interp``
    of one (T, C) descriptor, ``matching_cost`` and ``yaw_costs`` of 20 pairs, ``rerank`` of
    one query against 20 candidates (the reference timed once on 2 of them and scaled: it is
    a dense yaw scan per candidate; skipped with ``quick``)."""
    src, tgt = descriptors(20, 7)
    query = tgt[0]
    cases = [
        ("roll_interp", "(T, C), shift 7.3 bins", lambda b: K.roll_interp(src[0], 7.3, backend=b)),
        ("matching_cost", "20 pairs", lambda b: K.matching_cost(src, tgt, backend=b)),
        ("yaw_costs", "20 pairs", lambda b: K.yaw_costs(src, tgt, backend=b)),
    ]
    rows = []
    for name, size, fn in cases:
        got, want = fn("rust"), fn("reference")
        assert np.allclose(got, want, atol=1e-5), f"{name}: not the reference's"
        rust, refs = timeit(lambda f=fn: f("rust")), timeit(lambda f=fn: f("reference"))
        rows.append(
            {
                "kernel": name,
                "size": size,
                "rust_ms": rust * 1e3,
                "reference_ms": refs * 1e3,
                "reference_x": refs / rust,
            }
        )
    rust = timeit(lambda: K.rerank(src, query))
    row = {"kernel": "rerank", "size": "1 query, 20 candidates", "rust_ms": rust * 1e3}
    if not quick:
        got = K.rerank(src, query)
        t0 = time.perf_counter()
        want = K.rerank(src[:2], query, backend="reference")
        row["reference_ms"] = (time.perf_counter() - t0) * 1e3 * 10
        row["reference_x"] = row["reference_ms"] / row["rust_ms"]
        assert np.allclose(got.cost[:2], want.cost, atol=1e-5), "rerank: not the reference's"
    rows.append(row)
    return rows


def bench_search() -> list[dict]:
    rows = []
    for backend in ("rust", "reference"):
        for fine in (32, 256):

            def run(backend=backend, fine=fine) -> int:
                s = K.TranslationSearch(3.0, 0.6, fine, 4, 0.5, 0, backend=backend)
                n = 0
                while not s.done:
                    xy = s.proposals()
                    c = np.hypot(xy[:, 0] - 1.0, xy[:, 1])
                    s.report(c, np.zeros_like(c))
                    n += 1
                s.history()
                return n

            sec = timeit(run, min_time=0.2)
            rows.append(
                {
                    "backend": backend,
                    "fine_samples": fine,
                    "stages": 4,
                    "grid": 121,
                    "us_per_stage": sec / 4 * 1e6,
                }
            )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--json")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(vvloc.get_num_threads())
    yaw = bench_yaw([20, 200] if args.quick else [20, 200, 2000], args.quick)
    cols = ["pairs", "rust_ms", "gateway_ms", "sgemm_floor_ms", "x_floor", "torch_ms"]
    cols += ["torch_speedup", "reference_ms", "reference_speedup"]
    print(f"estimate_yaw, T={T}, C={C}, {vvloc.get_num_threads()} threads")
    print_table(yaw, cols)
    others = bench_kernels(args.quick)
    print("\nthe other matching kernels, checked against the reference")
    print_table(others, ["kernel", "size", "rust_ms", "reference_ms", "reference_x"])
    search = bench_search()
    print("\nTranslationSearch overhead (decoder excluded)")
    print_table(search, ["backend", "grid", "fine_samples", "stages", "us_per_stage"])
    if args.json:
        write_json(args.json, "matching", yaw + others + search)


if __name__ == "__main__":
    main()
