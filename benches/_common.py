"""Shared helpers of the benchmark scripts: robust timing, table printing, JSON output."""

from __future__ import annotations

import json
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import vvloc


def timeit(
    fn: Callable[[], Any], *, min_time: float = 0.3, repeat: int = 5, warmup: int = 1
) -> float:
    """Median seconds per call of ``fn`` over ``repeat`` rounds of at least ``min_time`` each
    (for an even ``repeat``, the faster of the two middle rounds: no implementation is timed
    by its slower half)."""
    for _ in range(warmup):
        fn()
    t0 = time.perf_counter()
    fn()
    one = max(time.perf_counter() - t0, 1e-7)
    n = max(1, int(min_time / one))
    rounds = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        rounds.append((time.perf_counter() - t0) / n)
    rounds.sort()
    return rounds[(len(rounds) - 1) // 2]


def random_map(model: Any, n: int, rng: Any, *, bevs: bool = False) -> Any:
    """An in-memory ``MapDatabase`` of ``n`` keyframes for ``model`` (a ``VVLocNet``), one
    session: random unit global descriptors (n, G) and local-view descriptors (n, T, C),
    float32, and with ``bevs`` random float16 BEVs (n, H, W, C); poses uniform in ±50 m. Only
    the sizes matter for the timings these maps serve."""
    import numpy as np

    from vvloc.localize.mapdb import MapDatabase

    cfg = model.config
    g = rng.standard_normal((n, model.global_dim)).astype(np.float32)
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    loc = rng.standard_normal((n, cfg.num_angles, cfg.channels)).astype(np.float32)
    loc /= np.linalg.norm(loc, axis=2, keepdims=True)
    shape = (n, cfg.bev_height, cfg.bev_width, cfg.channels)
    return MapDatabase.from_arrays(
        poses=rng.uniform(-50, 50, (n, 3)),
        timestamps=np.arange(n, dtype=np.float64),
        sessions="s0",
        global_descriptors=g,
        local_descriptors=loc,
        bevs=rng.standard_normal(shape).astype(np.float16) if bevs else None,
        model_config=cfg.to_dict(),
        grid_size=cfg.grid_size,
        config_hash=model.config_hash(),
        weights_hash=model.weights_hash(),
    )


def print_table(rows: list[dict[str, Any]], columns: list[str]) -> None:
    """Print ``rows`` as a fixed-width table of ``columns``."""

    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    cells = [[fmt(r.get(c, "")) for c in columns] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(columns)]
    print("  ".join(c.ljust(w) for c, w in zip(columns, widths, strict=True)))
    for row in cells:
        print("  ".join(v.ljust(w) for v, w in zip(row, widths, strict=True)))


def write_json(path: str | Path, name: str, rows: list[dict[str, Any]]) -> None:
    """Write benchmark ``rows`` with machine facts to ``path``."""
    doc = {
        "benchmark": name,
        "vvloc": vvloc.__version__,
        "threads": vvloc.get_num_threads(),
        "machine": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "rows": rows,
    }
    Path(path).parent.mkdir(parents=True, exist_ok=True)  # bench-results/ is not committed
    Path(path).write_text(json.dumps(doc, indent=2))
