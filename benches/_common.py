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
    """Median seconds per call of ``fn`` over ``repeat`` rounds of at least ``min_time`` each."""
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
    return rounds[len(rounds) // 2]


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
    Path(path).write_text(json.dumps(doc, indent=2))
