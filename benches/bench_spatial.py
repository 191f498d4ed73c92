"""Spatial kernels: fused padding + polar sampling, polar sampling, BEV padding.

Paper size: a 100×100×256 map (g = 0.3 m), T = 120 angle bins, R = 40 radius bins, 121
translation hypotheses on an 11×11 grid with a 0.3 m step. Compares the Rust kernels with the
literal reference (timed once, on a subset of the hypotheses and scaled, since it is slow), the
vectorised torch ``grid_sample`` path (:mod:`vvloc.reference.torch_spatial`), and the
memory-write floor of the output (filling an array of the output's size with ones: freshly
allocated, as the kernel must, and preallocated).

Usage: ``python benches/bench_spatial.py [--json PATH] [--quick]``; ``--tail N`` times N single
``pad_polar`` calls instead (median and worst; run it with ``VVLOC_MADVISE_HUGEPAGE=0`` too).
"""

from __future__ import annotations

import argparse
import os
import time
from typing import Any

import numpy as np
import torch

import vvloc
from _common import print_table, timeit, write_json
from vvloc import kernels as K
from vvloc.reference import torch_spatial as TS

H = W = 100
C = 256
T, R = 120, 40
G = 0.3


def hypotheses() -> np.ndarray:
    """121 translations (x, y) metres: an 11×11 grid with a 0.3 m step, centred on 0."""
    steps = (np.arange(11) - 5) * 0.3
    return np.stack(np.meshgrid(steps, steps, indexing="ij"), axis=-1).reshape(-1, 2)


def check(kernel: str, impl: str, got: Any, want: Any, atol: float) -> None:
    """Stop the benchmark when the Rust kernel's output is not ``want`` (a fast wrong kernel
    must not win): float32 grid coordinates differ from float64 by ~n·2⁻²⁴ cells."""
    diff = float(np.max(np.abs(np.asarray(got, np.float64) - np.asarray(want, np.float64))))
    if not diff <= atol:
        raise SystemExit(f"{kernel}: rust differs from {impl} by {diff:.3g} (> {atol:g})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--json", help="write the figures to this JSON file")
    parser.add_argument("--quick", action="store_true", help="skip the slow reference")
    parser.add_argument(
        "--tail",
        type=int,
        default=0,
        help="only time this many single pad_polar calls: median and worst (tail latency)",
    )
    args = parser.parse_args()

    rng = np.random.default_rng(0)
    bev = rng.standard_normal((H, W, C)).astype(np.float32)
    tr = hypotheses()
    tbev = torch.from_numpy(bev)[None]
    ttr = torch.from_numpy(tr)
    n = len(tr)
    out_shape = (n, T, R, C)
    rows: list[dict[str, Any]] = []
    if args.tail:
        K.pad_polar(bev, tr, T, R, G)  # warm-up
        calls = []
        for _ in range(args.tail):
            t0 = time.perf_counter()
            K.pad_polar(bev, tr, T, R, G)
            calls.append(1e3 * (time.perf_counter() - t0))
        huge = os.environ.get("VVLOC_MADVISE_HUGEPAGE", "1").strip() != "0"
        print(
            f"pad_polar, {args.tail} single calls, huge pages {'on' if huge else 'off'}: "
            f"median {np.median(calls):.1f} ms, best {min(calls):.1f} ms, worst {max(calls):.1f} ms"
        )
        return

    def add(kernel: str, impl: str, seconds: float, base: float | None, note: str = "") -> None:
        rows.append(
            {
                "kernel": kernel,
                "impl": impl,
                "ms": seconds * 1e3,
                "x_rust": seconds / base if base else 1.0,
                "note": note,
            }
        )

    quick = {"min_time": 0.2, "repeat": 3}
    # --- pad_polar, 121 hypotheses ------------------------------------------------------------
    rust = timeit(lambda: K.pad_polar(bev, tr, T, R, G), **quick)
    add("pad_polar", "rust", rust, None, f"{n} hyps -> {out_shape}")
    buf = np.empty(out_shape, dtype=np.float32)
    add(
        "pad_polar",
        "write floor (fresh)",
        timeit(lambda: np.ones(out_shape, np.float32), **quick),
        rust,
        "np.ones of the output size",
    )
    add(
        "pad_polar",
        "write floor (prealloc)",
        timeit(lambda: buf.fill(1.0), **quick),
        rust,
        "fill of a preallocated array",
    )
    with torch.no_grad():
        torch_s = timeit(lambda: TS.torch_pad_polar(tbev, ttr, T, R, G), min_time=0.2, repeat=2)
    add("pad_polar", "torch grid_sample", torch_s, rust, "pad then polar, chunks of 16")
    sub = tr[:: n // 10][:11]
    got = K.pad_polar(bev, sub, T, R, G)
    with torch.no_grad():
        want = TS.torch_pad_polar(tbev, torch.from_numpy(sub), T, R, G)[0].numpy()
    check("pad_polar", "torch", got, want, 1e-3)
    if not args.quick:
        t0 = time.perf_counter()
        want = K.pad_polar(bev, sub, T, R, G, backend="reference")
        ref = (time.perf_counter() - t0) * n / len(sub)
        check("pad_polar", "reference", got, want, 1e-4)
        add("pad_polar", "reference", ref, rust, f"timed once on {len(sub)} hyps, scaled")

    # --- polar_sample, one map -----------------------------------------------------------------
    rust = timeit(lambda: K.polar_sample(bev, T, R, G), **quick)
    add("polar_sample", "rust", rust, None, "1 map -> (120, 40, 256)")
    with torch.no_grad():
        add(
            "polar_sample",
            "torch grid_sample",
            timeit(lambda: TS.torch_polar_sample(tbev, T, R, G).contiguous(), **quick),
            rust,
        )
    got = K.polar_sample(bev, T, R, G)
    with torch.no_grad():
        check("polar_sample", "torch", got, TS.torch_polar_sample(tbev, T, R, G)[0].numpy(), 1e-3)
    if not args.quick:
        t0 = time.perf_counter()
        want = K.polar_sample(bev, T, R, G, backend="reference")
        add("polar_sample", "reference", time.perf_counter() - t0, rust, "timed once")
        check("polar_sample", "reference", got, want, 1e-4)

    # --- bev_pad, 121 hypotheses ---------------------------------------------------------------
    rust = timeit(lambda: K.bev_pad(bev, tr, G), **quick)
    add("bev_pad", "rust", rust, None, f"{n} hyps -> ({n}, 100, 100, 256)")
    pad_shape = (n, H, W, C)
    add(
        "bev_pad",
        "write floor (fresh)",
        timeit(lambda: np.ones(pad_shape, np.float32), **quick),
        rust,
    )
    with torch.no_grad():
        add(
            "bev_pad",
            "torch grid_sample",
            timeit(lambda: TS.torch_bev_pad(tbev, ttr, G).contiguous(), min_time=0.2, repeat=2),
            rust,
        )
    sub = tr[:11]
    got = K.bev_pad(bev, sub, G)
    with torch.no_grad():
        want = TS.torch_bev_pad(tbev, torch.from_numpy(sub), G)[0].numpy()
    check("bev_pad", "torch", got, want, 1e-3)
    if not args.quick:
        t0 = time.perf_counter()
        want = K.bev_pad(bev, sub, G, backend="reference")
        ref = (time.perf_counter() - t0) * n / len(sub)
        check("bev_pad", "reference", got, want, 1e-4)
        add("bev_pad", "reference", ref, rust, "timed once on 11 hyps, scaled")
    checked = "torch's" if args.quick else "torch's and the reference's"
    print(f"checked: the Rust outputs equal {checked}")

    print(
        f"vvloc {vvloc.__version__}: {vvloc.get_num_threads()} kernel threads, "
        f"torch {torch.get_num_threads()} threads"
    )
    print_table(rows, ["kernel", "impl", "ms", "x_rust", "note"])
    if args.json:
        write_json(args.json, "spatial", rows)


if __name__ == "__main__":
    main()
