"""Compare the garage reports evaluated again on 2026-12-05 (loop-closure Recall@2m counting both
frames of a detected pair) with the committed ones: every value but latency, meta, the training
record and figure paths; each difference printed.

Run from the repository root: python models/synth-small/recall-fix-check/compare.py
"""

from __future__ import annotations

import json
from pathlib import Path

HERE = Path(__file__).parent
PAIRS = {
    "garage": HERE.parent / "floor-consensus" / "test-garage",
    "pillars": HERE.parent / "floor-consensus" / "test-pillars",
}
SKIP = ("latency", "meta", "training", "figures")


def walk(new, old, path=""):
    if isinstance(new, dict) and isinstance(old, dict):
        for k in sorted(set(new) | set(old)):
            p = f"{path}/{k}"
            if k not in old:
                yield p, "only in the new report"
            elif k not in new:
                yield p, "only in the committed report"
            else:
                yield from walk(new[k], old[k], p)
    elif isinstance(new, list) and isinstance(old, list) and len(new) == len(old):
        for i, (a, b) in enumerate(zip(new, old, strict=True)):
            yield from walk(a, b, f"{path}[{i}]")
    elif new != old:
        yield path, f"{old} -> {new}"


for name, committed in PAIRS.items():
    new = json.loads((HERE / name / "report.json").read_text())
    old = json.loads((committed / "report.json").read_text())
    diffs = [(p, d) for p, d in walk(new, old) if p.split("/")[1] not in SKIP]
    kinds = sorted({p.split("/")[-1].split("[")[0] for p, _ in diffs})
    print(f"== {name}: {len(diffs)} differing values, in fields {kinds}")
    for p, d in diffs:
        print(f"  {p}: {d}")
    q_new = (HERE / name / "queries.csv").read_text()
    q_old = (committed / "queries.csv").read_text()
    print(f"  queries.csv identical: {q_new == q_old}")
