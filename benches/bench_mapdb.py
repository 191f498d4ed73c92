"""Map database I/O: save, open (with/without checksum verification) and the lazy reads the
localizer makes per query (K = 20 local descriptors for re-ranking, one BEV for loop closure).

Paper-sized descriptors: Dg = 256, local T×C = 120×256; BEV 100×100×256 float16.
Usage: ``python benches/bench_mapdb.py [--json PATH] [--keyframes N] [--v1_layout]``.
``--v1_layout`` adds the float32 case written with HDF5's oldest structures (format version 1's
layout, without metadata checksums), for an A/B of format version 2 in one run.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import print_table, timeit, write_json
from vvloc.localize import MapDatabase
from vvloc.localize import mapwriter as _mapwriter

DG, T, C = 256, 120, 256
BEV = (100, 100, 256)
K = 20


def unit(x: np.ndarray) -> np.ndarray:
    """``x`` float32 with its last axis divided by its L2 norm (as the encoder gives global
    descriptors, which a map requires)."""
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def build(n: int, n_bev: int, seed: int = 0) -> tuple[MapDatabase, MapDatabase]:
    rng = np.random.default_rng(seed)
    common = {
        "timestamps": np.arange(n) * 0.1,
        "sessions": "s0",
        "global_descriptors": unit(rng.normal(size=(n, DG))),
        "model_config": {"bench": True},
        "grid_size": 0.3,
    }
    plain = MapDatabase.from_arrays(
        poses=rng.normal(size=(n, 3)),
        local_descriptors=rng.normal(size=(n, T, C)).astype(np.float32),
        **common,
    )
    with_bev = MapDatabase.from_arrays(
        poses=rng.normal(size=(n_bev, 3)),
        local_descriptors=rng.normal(size=(n_bev, T, C)).astype(np.float32),
        bevs=rng.normal(size=(n_bev, *BEV)).astype(np.float16),
        **{
            **common,
            "timestamps": common["timestamps"][:n_bev],
            "global_descriptors": common["global_descriptors"][:n_bev],
        },
    )
    return plain, with_bev


#: Saves per case, taken in turn across the cases, each file removed after its save: one save
#: each in a fixed order let dirty pages pile up and slowed every later case.
SAVE_ROUNDS = 3


def save(db: MapDatabase, path: Path, dtype: str, v1_layout: bool) -> float:
    """Seconds to save ``db`` to ``path`` (``v1_layout``: HDF5's oldest structures, as format
    version 1 wrote them)."""
    libver = _mapwriter._LIBVER
    if v1_layout:
        _mapwriter._LIBVER = ("earliest", "v110")
    t0 = time.perf_counter()
    try:
        db.save(path, dtype=dtype)  # type: ignore[arg-type]
    finally:
        _mapwriter._LIBVER = libver
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--keyframes", type=int, default=2000)
    ap.add_argument("--v1_layout", action="store_true", help="A/B with version 1's layout")
    args = ap.parse_args()
    n, n_bev = args.keyframes, 16
    plain, with_bev = build(n, n_bev)
    rng = np.random.default_rng(1)
    rows = []
    with tempfile.TemporaryDirectory() as d:
        cases = [("float32", ""), ("float16", "")]
        if args.v1_layout:
            cases.append(("float32", " v1 layout"))
        saves: dict[tuple[str, str], list[float]] = {case: [] for case in cases}
        scratch = Path(d) / "scratch.h5"
        for _ in range(SAVE_ROUNDS):
            for dtype, layout in cases:
                saves[(dtype, layout)].append(save(plain, scratch, dtype, bool(layout)))
                scratch.unlink()
        for dtype, layout in cases:
            path = Path(d) / f"map_{dtype}{layout.replace(' ', '_')}.h5"
            save(plain, path, dtype, bool(layout))
            t_save = float(np.median(saves[(dtype, layout)]))
            t_open = timeit(lambda p=path: MapDatabase.open(p).close(), min_time=0.2, repeat=3)
            t_open_nv = timeit(
                lambda p=path: MapDatabase.open(p, verify=False).close(), min_time=0.2, repeat=3
            )
            with MapDatabase.open(path) as db:
                t_k = timeit(
                    lambda db=db: db.local_descriptors(rng.choice(n, K, replace=False)),
                    min_time=0.3,
                )
            rows.append(
                {
                    "case": f"N={n} local {T}x{C} {dtype}{layout}",
                    "file_MB": path.stat().st_size / 1e6,
                    "save_s": t_save,
                    "open_ms": t_open * 1e3,
                    "open_noverify_ms": t_open_nv * 1e3,
                    f"read_{K}_local_ms": t_k * 1e3,
                }
            )
        path = Path(d) / "map_bev.h5"
        t0 = time.perf_counter()
        with_bev.save(path)
        t_save = time.perf_counter() - t0
        with MapDatabase.open(path) as db:
            t_bev = timeit(lambda db=db: db.bev(int(rng.integers(n_bev))), min_time=0.3)
        rows.append(
            {
                "case": f"N={n_bev} with BEV {BEV[0]}x{BEV[1]}x{BEV[2]} f16",
                "file_MB": path.stat().st_size / 1e6,
                "save_s": t_save,
                "read_1_bev_ms": t_bev * 1e3,
            }
        )
    cols = [
        "case",
        "file_MB",
        "save_s",
        "open_ms",
        "open_noverify_ms",
        f"read_{K}_local_ms",
        "read_1_bev_ms",
    ]
    print_table(rows, cols)
    if args.json:
        write_json(args.json, "mapdb", rows)


if __name__ == "__main__":
    main()
