"""Run every kernel benchmark (``benches/bench_*.py``) and collect their JSON figures.

Usage: ``python benches/run.py [name ...]`` (``make bench``). Each benchmark script prints its
own table and writes ``bench-results/<name>.json``; this driver refuses a debug build.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import vvloc
from vvloc import _core

HERE = Path(__file__).resolve().parent
OUT = HERE.parent / "bench-results"


def main(argv: list[str]) -> int:
    if _core.build_profile != "release":
        print(f"refusing to benchmark a {_core.build_profile} build: run `make bench`")
        return 2
    OUT.mkdir(exist_ok=True)
    scripts = sorted(HERE.glob("bench_*.py"))
    if argv:
        scripts = [s for s in scripts if any(a in s.stem for a in argv)]
    threads = vvloc.get_num_threads()
    print(f"vvloc {vvloc.__version__}, {threads} threads, build {_core.build_profile}")
    rc = 0
    for script in scripts:
        name = script.stem.removeprefix("bench_")
        print(f"\n=== {name} ===", flush=True)
        res = subprocess.run([sys.executable, str(script), "--json", str(OUT / f"{name}.json")])
        rc = rc or res.returncode
    return rc


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
