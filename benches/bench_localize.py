"""End-to-end localization latency per stage (encode, retrieve, re-rank K=20, metric search).

Usage: ``python benches/bench_localize.py [--json PATH] [--map_size N] [--queries Q]
[--metric_candidates M[,M...]]``.

A small model (``ModelConfig.small()``; weights do not change the timing) localizes Q query
frames (4 cameras of 96×160) against a map of N keyframes whose descriptors are random unit
vectors (only their count matters for the timing). Reported: median milliseconds per query and
stage with one metric candidate, and the share of the metric stage spent in the Rust kernels
(``pad_polar`` + ``estimate_yaw``; the search's bookkeeping is counted with the rest) versus
the networks (decoder + interactor). The paper
reports 261 ms re-ranking and 238 ms metric localization on an A100 with its full model.
For each further ``--metric_candidates`` value (default ``1,3,5,10``) the metric stage is timed
in the same run (``Localizer(metric_candidates=M)``: coarse stage against M candidates with the
query decoded once), beside M separate metric localizations (the cost without sharing). Each
query is also localized, in turn, with the library's matcher (decoder in chunks, the
interactor's one-sided first TASA shared), with the decoder in chunks alone, and with the plain
matcher before 2026-12-05 (each stage decoded in one batch, the whole interactor per pair),
and whether all three gave the same answers (``same_answers``). The re-ranking of 20 and 100
candidates is timed with the library's ``rerank_learned`` and with the plain interactor. The
compared versions take turns at going first, after a warm-up call of each. The run prints a
fingerprint of the library's answers (``answers``: sha256 of each query's map row, pose, cost,
search costs and re-ranking), to compare runs under settings that should keep them (e.g.
``OMP_WAIT_POLICY``).
"""

from __future__ import annotations

import argparse
import hashlib
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from _common import print_table, random_map, write_json
from vvloc import kernels
from vvloc.data import Frame
from vvloc.localize import localizer as localizer_module
from vvloc.localize.localizer import LocalizationResult, Localizer, encode_frames
from vvloc.localize.mapdb import MapDatabase
from vvloc.localize.metric import METRIC_CANDIDATES
from vvloc.nets import ModelConfig, VVLocNet


def _frame(rng: np.random.Generator, cfg: ModelConfig, cameras: int = 4) -> Frame:
    h, w = cfg.image_height, cfg.image_width
    k = np.array([[w / 2, 0.0, (w - 1) / 2], [0.0, w / 2, (h - 1) / 2], [0.0, 0.0, 1.0]])
    axes = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    ext = np.repeat(np.eye(4)[None], cameras, 0)
    for m in range(cameras):
        a = 2 * math.pi * m / cameras
        rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
        ext[m, :3, :3] = rz @ axes
        ext[m, 2, 3] = 1.5
    images = rng.integers(0, 255, (cameras, 3, h, w), dtype=np.uint8)
    return Frame(images, np.repeat(k[None], cameras, 0), ext, np.zeros(3), 0.0, 0)


@torch.no_grad()
def loc_bev(model: VVLocNet, frame: Frame) -> np.ndarray:
    """The query BEV (H, W, C) float32 of one frame."""
    enc = encode_frames(model, [frame], keep_bev=True)
    assert enc.bev is not None
    return enc.bev[0]


def plain_matcher(model: VVLocNet, desc_tgts: np.ndarray, chunked: bool = False):  # type: ignore[no-untyped-def]
    """The metric stage's callbacks before 2026-12-05: every search stage decoded in one batch
    (``chunked``: in the library's chunks) and the whole interactor run for each target on N
    copies of it; the library's ``learned_matcher`` gives the same numbers."""
    tgts = torch.from_numpy(np.ascontiguousarray(desc_tgts, dtype=np.float32))

    @torch.no_grad()
    def decode(polar: np.ndarray) -> torch.Tensor:
        x = torch.from_numpy(polar)
        return localizer_module.decode_in_chunks(model, x) if chunked else model.decode_polar(x)

    @torch.no_grad()
    def interact(ds: torch.Tensor, k: int) -> tuple[np.ndarray, np.ndarray]:
        a, b = model.interact(ds, tgts[k].expand(ds.shape[0], *tgts.shape[1:]))
        return a.numpy(), b.numpy()

    return decode, interact


#: The matchers compared by :func:`compare_matchers`, and what the localizer runs for each.
MATCHERS = {
    "library_ms": localizer_module.learned_matcher,
    "chunked_decoder_only_ms": lambda m, d: plain_matcher(m, d, chunked=True),
    "plain_ms": plain_matcher,
}


def compare_matchers(model: VVLocNet, mapdb: MapDatabase, frames: list[Frame]) -> list[dict]:
    """Median metric stage (ms) of ``frames`` with each of :data:`MATCHERS`, for one metric
    candidate and for the localizer's default M; each frame goes through the matchers in
    turn, so that all see the same machine, the first of them in rotation (the one after a
    query's encoding and re-ranking would otherwise always be the same), after one untimed
    localization with each; ``same_answers``: whether all gave the library's pose, cost and
    keyframe for every frame, bit for bit; ``same_keyframes`` whether the keyframes were the
    same, ``max_difference`` the largest difference of a pose component or cost from the
    library's (bit for bit with torch's MKL on the AMD EPYCs of 2026-12-05; on an Intel Xeon
    with AVX-512, 2026-12-06, the one-batch decoder's differ from the chunks' by ~1e-8)."""
    library = localizer_module.learned_matcher
    names = list(MATCHERS)
    out = []
    for m in (1, METRIC_CANDIDATES):
        loc = Localizer(model, mapdb, top_k=20, metric_candidates=m)
        times: dict[str, list[float]] = {name: [] for name in MATCHERS}
        same = True  # every matcher's pose and cost equal the library's, bit for bit
        same_rows, diff = True, 0.0
        try:
            for name in names:  # warm-up
                localizer_module.learned_matcher = MATCHERS[name]  # type: ignore[assignment]
                loc.localize(frames[0])
            for i, f in enumerate(frames):
                answers = {}
                for name in names[i % len(names) :] + names[: i % len(names)]:
                    localizer_module.learned_matcher = MATCHERS[name]  # type: ignore[assignment]
                    r = loc.localize(f)
                    times[name].append(r.timings_ms["metric"])
                    answers[name] = (tuple(r.relative_pose), r.cost, r.map_row)
                lib = answers[names[0]]
                same &= all(a == lib for a in answers.values())
                same_rows &= all(a[2] == lib[2] for a in answers.values())
                diff = max(
                    diff,
                    *(
                        np.abs(np.r_[a[0], a[1]] - np.r_[lib[0], lib[1]]).max()
                        for a in answers.values()
                    ),
                )
        finally:
            localizer_module.learned_matcher = library
        row = _compared({"metric_candidates": m}, times, same)
        out.append(row | {"same_keyframes": same_rows, "max_difference": float(diff)})
    return out


def compare_rerank(
    model: VVLocNet, ks: tuple[int, ...] = (20, 100), repeat: int = 30
) -> list[dict]:
    """Median ms of the learned re-ranking of K candidates (``rerank_learned``: the query's
    first TASA once) against the plain one (the whole interactor on the query repeated K
    times, before 2026-12-05), in turn, random descriptors; ``same_answers``: equal results."""
    cfg = model.config
    out = []
    for k in ks:
        query = torch.randn(cfg.num_angles, cfg.channels)
        cands = torch.randn(k, cfg.num_angles, cfg.channels)

        @torch.no_grad()
        def plain(query: torch.Tensor = query, cands: torch.Tensor = cands) -> kernels.Rerank:
            a, b = model.interact(query.expand(len(cands), *query.shape), cands)
            return kernels.rerank(a.numpy(), b.numpy())

        def library(query: torch.Tensor = query, cands: torch.Tensor = cands) -> kernels.Rerank:
            return localizer_module.rerank_learned(model, query, cands)

        same = all(np.array_equal(x, y) for x, y in zip(plain(), library(), strict=True))
        times: dict[str, list[float]] = {"library_ms": [], "plain_ms": []}
        pair = (("library_ms", library), ("plain_ms", plain))
        for r in range(repeat):  # alternating which goes first
            for name, fn in pair if r % 2 == 0 else pair[::-1]:
                t0 = time.perf_counter()
                fn()
                times[name].append(1e3 * (time.perf_counter() - t0))
        out.append(_compared({"candidates": k}, times, same))
    return out


def _compared(key: dict, times: dict[str, list[float]], same: bool) -> dict:
    """A comparison's row: ``key``, the median of each of ``times`` (ms), plain ÷ library and
    whether the answers were the same."""
    row = {**key, **{name: float(np.median(v)) for name, v in times.items()}}
    row["plain_vs_library"] = row["plain_ms"] / row["library_ms"]
    row["same_answers"] = same
    return row


def _answer_bytes(r: LocalizationResult) -> bytes:
    """The bytes of one answer that settings which claim to keep the answers (a thread wait
    policy, a build) must keep: the chosen map row, the metric pose and cost, every cost of the
    translation search, and the re-ranking's order and costs."""
    return b"".join(
        [
            np.int64(r.map_row).tobytes(),
            np.asarray(r.relative_pose, np.float64).tobytes(),
            np.float64(r.cost).tobytes(),
            np.asarray(r.search.cost).tobytes(),
            np.asarray(r.reranked).tobytes(),
            np.asarray(r.rerank_cost, np.float64).tobytes(),
        ]
    )


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--map_size", type=int, default=2000)
    ap.add_argument("--queries", type=int, default=5)
    ap.add_argument("--metric_candidates", default="1,3,5,10")
    args = ap.parse_args(argv)
    ms = [int(v) for v in args.metric_candidates.split(",")]
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    model = VVLocNet(ModelConfig.small()).eval()
    cfg = model.config
    n = args.map_size
    db = random_map(model, n, rng)
    with tempfile.TemporaryDirectory() as tmp:
        path = db.save(Path(tmp) / "map.h5")
        mapdb = MapDatabase.open(path, expected_config_hash=model.config_hash())
        loc = Localizer(model, mapdb, top_k=20, metric_candidates=1)
        # time the Rust part of the metric stage by wrapping the kernel entry points
        spent = {"kernels": 0.0}

        def timed(fn):  # type: ignore[no-untyped-def]
            def inner(*a, **k):  # type: ignore[no-untyped-def]
                t0 = time.perf_counter()
                try:
                    return fn(*a, **k)
                finally:
                    spent["kernels"] += time.perf_counter() - t0

            return inner

        kernels.pad_polar = timed(kernels.pad_polar)  # type: ignore[assignment]
        kernels.estimate_yaw = timed(kernels.estimate_yaw)  # type: ignore[assignment]
        frames = [_frame(rng, cfg) for _ in range(args.queries + 1)]
        loc.localize(frames[0])  # warm-up
        rows, shares = [], []
        per_stage: dict[str, list[float]] = {}
        answers = hashlib.sha256()
        for f in frames[1:]:
            spent["kernels"] = 0.0
            r = loc.localize(f)
            answers.update(_answer_bytes(r))
            for k, v in r.timings_ms.items():
                per_stage.setdefault(k, []).append(v)
            shares.append(1e3 * spent["kernels"] / r.timings_ms["metric"])
        matchers = compare_matchers(model, mapdb, frames[1:])
        reranks = compare_rerank(model)
        extra = []
        for m in ms:
            if m == 1:
                continue
            many = Localizer(model, mapdb, top_k=20, metric_candidates=m, metric_from="retrieval")
            enc = [many.localize(f) for f in frames[1:]]
            t_many = float(np.median([r.timings_ms["metric"] for r in enc]))
            t_sep = []
            for f, r in zip(frames[1:], enc, strict=True):
                bev = loc_bev(model, f)
                t0 = time.perf_counter()
                for row in r.retrieved[:m]:  # the M candidates (metric_from="retrieval")
                    many.metric(bev, int(row))
                t_sep.append((time.perf_counter() - t0) * 1e3)
            extra.append(
                {
                    "metric_candidates": m,
                    "metric_ms": t_many,
                    "separate_ms": float(np.median(t_sep)),
                    "vs_one": t_many / float(np.median(per_stage["metric"])),
                }
            )
        mapdb.close()
    for stage, v in per_stage.items():
        rows.append({"stage": stage, "median_ms": float(np.median(v)), "queries": len(v)})
    total = sum(r["median_ms"] for r in rows)
    rows.append({"stage": "total", "median_ms": total, "queries": args.queries})
    print(f"small model, map of {n} keyframes, K=20, {torch.get_num_threads()} torch threads")
    print_table(rows, ["stage", "median_ms", "queries"])
    share = float(np.median(shares))
    print(f"Rust kernels' share of the metric stage: {share:.1%} (the rest: decoder + interactor)")
    fingerprint = answers.hexdigest()[:16]
    print(f"answers' sha256 (the library's, every query): {fingerprint}")
    print(
        "metric stage (ms) with the library's matcher, with the decoder in chunks alone, and "
        "with the plain matcher (before 2026-12-05), each query in turn:"
    )
    print_table(
        matchers,
        [
            "metric_candidates",
            *MATCHERS,
            "plain_vs_library",
            "same_answers",
            "same_keyframes",
            "max_difference",
        ],
    )
    print("re-ranking K candidates (ms), the library's and the plain interactor, in turn:")
    print_table(
        reranks, ["candidates", "library_ms", "plain_ms", "plain_vs_library", "same_answers"]
    )
    if extra:
        print("metric stage with M candidates (shared coarse stage) vs M separate searches:")
        print_table(extra, ["metric_candidates", "metric_ms", "separate_ms", "vs_one"])
    if args.json:
        write_json(
            args.json,
            "localize",
            [
                *rows,
                {"stage": "metric_kernel_share", "share": share},
                {"stage": "answers", "sha256": fingerprint},
                *matchers,
                *reranks,
                *extra,
            ],
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
