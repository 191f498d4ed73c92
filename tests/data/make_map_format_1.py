"""Write ``tests/data/map-format-1.h5`` with vvloc's map writer as of commit 0c97ba5, the last
to write map format version 1 (kept as a fixture: version-1 maps must stay readable).

Usage (from the repository root)::

    git show 0c97ba5:python/vvloc/localize/mapdb.py > /tmp/old_mapdb.py
    .venv/bin/python tests/data/make_map_format_1.py /tmp/old_mapdb.py tests/data/map-format-1.h5

``fixture_arrays`` is also what ``tests/test_mapdb.py`` compares the file with.
"""

from __future__ import annotations

import importlib.util
import sys
from typing import Any

import numpy as np


def fixture_arrays() -> dict[str, Any]:
    """The fixture's keyframes (6, two sessions, two floors) and map settings."""
    from vvloc.data import Camera

    rng = np.random.default_rng(7)
    n = 6
    g = rng.normal(size=(n, 4)).astype(np.float32)
    cam = Camera("front", 16, 8, np.array([[8.0, 0, 7.5], [0, 8, 3.5], [0, 0, 1]]), np.eye(4))
    return {
        "poses": np.column_stack([rng.uniform(-5, 5, (n, 2)), rng.uniform(-3, 3, n)]),
        "timestamps": 1.7e9 + np.arange(n) * 0.5,
        "sessions": ["séance-0"] * 3 + ["s1"] * 3,
        "global_descriptors": g / np.linalg.norm(g, axis=1, keepdims=True),
        "local_descriptors": rng.normal(size=(n, 4, 2)).astype(np.float32),
        "bevs": rng.normal(size=(n, 3, 2, 2)).astype(np.float32),
        "floors": np.array([0, 0, 1, 0, 1, 1]),
        "model_config": {"name": "fixture", "T": 4},
        "grid_size": 0.3,
        "weights_hash": "0123456789abcdef",
        "rig": [cam],
    }


def main(old_mapdb: str, out: str) -> None:
    spec = importlib.util.spec_from_file_location("old_mapdb", old_mapdb)
    assert spec is not None and spec.loader is not None
    old = importlib.util.module_from_spec(spec)
    sys.modules["old_mapdb"] = old
    spec.loader.exec_module(old)
    old.MapDatabase.from_arrays(**fixture_arrays()).save(out, dtype="float16")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
