"""Every benchmark runs, at its smallest size: BENCHMARKS.md's figures name commands a user
re-runs (``make bench``), and a benchmark nothing runs stops working unseen (``bench_mapdb.py``
stopped at its first map once maps required unit-length global descriptors). Nothing here is
timed: each script's own checks (answers equal to the reference's) must pass, whether the
script stops on them or records them in its rows, and its JSON must hold figures."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

BENCHES = Path(__file__).resolve().parent.parent / "benches"

#: (script, its smallest-size arguments)
SMALLEST = [
    ("bench_matching.py", ["--quick"]),
    ("bench_spatial.py", ["--quick"]),
    ("bench_retrieval.py", ["--quick"]),
    ("bench_mapdb.py", ["--keyframes", "50"]),
    ("bench_nets.py", ["--quick"]),
    ("bench_localize.py", ["--map_size", "60", "--queries", "1", "--metric_candidates", "1,2"]),
    ("bench_loops.py", ["--sessions", "2", "--frames", "60"]),
    ("bench_render.py", ["--frames", "8"]),
]


def test_every_benchmark_is_listed():
    assert sorted(p.name for p in BENCHES.glob("bench_*.py")) == sorted(s for s, _ in SMALLEST)


@pytest.mark.parametrize(("script", "args"), SMALLEST, ids=[s for s, _ in SMALLEST])
def test_the_benchmark_runs(script, args, tmp_path, request):
    from vvloc import _core

    if _core.build_profile != "release":  # bench_retrieval.py and run.py refuse one
        pytest.skip("benchmarks are run on a release build (make develop builds one)")
    if script == "bench_render.py":
        request.getfixturevalue("egl")  # a skip (or, in CI, a failure) without EGL
    out = tmp_path / "figures.json"
    r = subprocess.run(
        [sys.executable, str(BENCHES / script), *args, "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=tmp_path,
    )
    assert r.returncode == 0, (r.stdout[-1500:], r.stderr[-3000:])
    rows = json.loads(out.read_text())["rows"]
    assert rows, r.stdout[-1500:]
    # the scripts that record their answer checks instead of stopping on them: bench_retrieval's
    # "exact"; bench_localize's "same_keyframes" and "max_difference" of the metric stage's
    # matchers (bit for bit, "same_answers", only where MKL rounds batches of every size alike)
    # and "same_answers" of the re-ranking's
    wrong = [
        row
        for row in rows
        if False in (row.get("exact"), row.get("same_keyframes"))
        or row.get("max_difference", 0.0) > 1e-6
        or ("candidates" in row and row.get("same_answers") is False)
    ]
    assert not wrong, wrong
