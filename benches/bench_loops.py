"""Loop-closure candidates: the radius query, the sequence check, and metric verification.

Usage: ``python benches/bench_loops.py [--json PATH] [--sessions S] [--frames F]``.

S sessions of F keyframes each drive the same loop of F places (session s starts s·F/S places
later, so revisits pair different sequence numbers); descriptors are the places' random unit
vectors (D = 64, the committed model's) plus noise of L2 size ≈ 0.05, so each keyframe has about
S − 1 true revisits within the radius 0.1 and the rest are far. Timed in one run: the Rust
radius query over all keyframes (``descriptor_loop_candidates``, single keyframes), the
sequence check (:func:`vvloc.localize.loops.sequence_distance`, numpy) on its candidate pairs
for L = 1 and 2, the floor check (:func:`vvloc.localize.loops.floor_consensus`, numpy: each
session drives places 0..F/2−1 on floor 0 and the rest on floor 1; its
voters, the pairs within twice the radius, from a second radius query) on the same pairs, and
the metric verification of one pair (``verify_pairs``: a small model,
``ModelConfig.small()``, whose weights do not change the timing, on a stored BEV) — the cost the
sequence check is compared with, per pair — alone and per pair of four with one source keyframe
(which share its coarse stage).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from _common import print_table, random_map, timeit, write_json
from vvloc.localize.loops import (
    descriptor_loop_candidates,
    floor_consensus,
    sequence_distance,
    verify_pairs,
)
from vvloc.localize.mapdb import MapDatabase
from vvloc.nets import ModelConfig, VVLocNet

D = 64


def drives(sessions: int, frames: int, seed: int = 0) -> tuple[np.ndarray, ...]:
    """Descriptors (S·F, D) float32, sessions (S·F,), seqs (S·F,) of S drives around F places."""
    rng = np.random.default_rng(seed)
    places = rng.standard_normal((frames, D))
    places /= np.linalg.norm(places, axis=1, keepdims=True)
    rows = []
    for s in range(sessions):
        order = np.roll(np.arange(frames), -s * frames // sessions)
        noise = rng.standard_normal((frames, D)) * (0.05 / np.sqrt(D))
        rows.append(places[order] + noise)
    g = np.concatenate(rows)
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    sess = np.repeat(np.arange(sessions), frames)
    seq = np.tile(np.arange(frames), sessions)
    return g.astype(np.float32), sess, seq


def pair_verification_ms(shared: int = 4) -> tuple[float, float]:
    """Median ms of ``verify_pairs`` for one pair of a map of keyframes with BEVs, and per pair
    for ``shared`` pairs of one source keyframe (which share its coarse stage)."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    model = VVLocNet(ModelConfig.small()).eval()
    db = random_map(model, shared + 1, rng, bevs=True)
    with tempfile.TemporaryDirectory() as tmp:
        path = db.save(Path(tmp) / "map.h5")
        with MapDatabase.open(path) as mapdb:
            one = np.array([0]), np.array([1])
            many = np.zeros(shared, np.int64), np.arange(1, shared + 1)
            t_one = timeit(lambda: verify_pairs(model, mapdb, *one), min_time=1.0, repeat=3)
            t_many = timeit(lambda: verify_pairs(model, mapdb, *many), min_time=1.0, repeat=3)
            return 1e3 * t_one, 1e3 * t_many / shared


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--sessions", type=int, default=20)
    ap.add_argument("--frames", type=int, default=1000)
    args = ap.parse_args(argv)
    g, sess, seq = drives(args.sessions, args.frames)
    cand = descriptor_loop_candidates(g, sess, seq, radius=0.1, window=10)
    p = len(cand.i)
    rows = [
        {
            "step": f"radius query, {len(g)} keyframes (Rust)",
            "ms": 1e3 * timeit(lambda: descriptor_loop_candidates(g, sess, seq, 0.1, 10)),
            "pairs": p,
        }
    ]
    for half in (1, 2):
        ms = 1e3 * timeit(lambda h=half: sequence_distance(g, sess, seq, cand.i, cand.j, h, 10))
        rows.append({"step": f"sequence check L = {half} (numpy)", "ms": ms, "pairs": p})
    place = (seq + sess * args.frames // args.sessions) % args.frames  # drives() rolls the loop
    floors = (place >= args.frames // 2).astype(np.int64)
    voters = descriptor_loop_candidates(g, sess, seq, radius=0.2, window=10)
    ms = 1e3 * timeit(lambda: descriptor_loop_candidates(g, sess, seq, 0.2, 10))
    rows.append(
        {
            "step": "radius query at 0.2: the floor check's voters (Rust)",
            "ms": ms,
            "pairs": len(voters.i),
        }
    )
    ms = 1e3 * timeit(lambda: floor_consensus(cand, sess, floors, voters))
    rows.append({"step": "floor check (numpy)", "ms": ms, "pairs": p})
    verify, verify_shared = pair_verification_ms()
    rows.append({"step": "metric verification (one pair)", "ms": verify, "pairs": 1})
    rows.append(
        {
            "step": "metric verification, per pair of 4 with one source",
            "ms": verify_shared,
            "pairs": 1,
        }
    )
    for r in rows:
        r["us_per_pair"] = 1e3 * r["ms"] / max(r["pairs"], 1)
        r["x_verify"] = r["us_per_pair"] / (1e3 * verify)
    print(f"{args.sessions} sessions × {args.frames} keyframes, D = {D}, {p} candidate pairs")
    print_table(rows, ["step", "ms", "pairs", "us_per_pair", "x_verify"])
    if args.json:
        write_json(args.json, "loops", rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
