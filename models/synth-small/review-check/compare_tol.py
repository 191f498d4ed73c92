"""Compare two vvloc reports value by value (every value except latency, meta, training,
figures and notes), reporting how many differ and by how much relatively:
``python compare_tol.py NEW_REPORT_DIR COMMITTED_REPORT_DIR``."""

import json
import sys

a, b = sys.argv[1], sys.argv[2]
ra, rb = json.load(open(f"{a}/report.json")), json.load(open(f"{b}/report.json"))
skip = {"latency", "meta", "training", "figures", "notes"}
n = big = 0
worst = 0.0
other = []


def walk(x, y, path):
    global n, big, worst
    if isinstance(x, dict) and isinstance(y, dict):
        for k in sorted(set(x) | set(y)):
            if not path and k in skip:
                continue
            if k not in x or k not in y:
                other.append(path + [k])
                continue
            walk(x[k], y[k], path + [k])
    elif isinstance(x, list) and isinstance(y, list):
        if len(x) != len(y):
            other.append(path)
            return
        for i, (p, q) in enumerate(zip(x, y)):
            walk(p, q, path + [i])
    elif x != y:
        n += 1
        if isinstance(x, float) and isinstance(y, float):
            rel = abs(x - y) / max(abs(x), abs(y), 1e-300)
            worst = max(worst, rel)
            if rel > 1e-9:
                big += 1
                other.append((path, x, y))
        else:
            other.append((path, x, y))


walk(ra, rb, [])
print(
    f"{a}: {n} values differ, largest relative difference {worst:.1e}, {big} above 1e-9, "
    f"{len(other) - big} not floats or structural"
)
for o in other[: int(sys.argv[3]) if len(sys.argv) > 3 else 5]:
    print("  ", o)
