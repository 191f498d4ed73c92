"""Compare two vvloc reports: every value except latency/meta/training/figures; and queries.csv."""
import json, sys, csv
a, b = sys.argv[1], sys.argv[2]
ra, rb = json.load(open(f"{a}/report.json")), json.load(open(f"{b}/report.json"))
skip = {"latency", "meta", "training", "figures", "notes"}
diffs = []
def walk(x, y, path):
    if isinstance(x, dict) and isinstance(y, dict):
        for k in sorted(set(x) | set(y)):
            if not path and k in skip: continue
            if k not in x or k not in y: diffs.append((path + [k], "missing", k in x, k in y)); continue
            walk(x[k], y[k], path + [k])
    elif isinstance(x, list) and isinstance(y, list):
        if len(x) != len(y): diffs.append((path, "len", len(x), len(y))); return
        for i, (p, q) in enumerate(zip(x, y)): walk(p, q, path + [i])
    elif x != y:
        diffs.append((path, x, y))
walk(ra, rb, [])
print(f"{a} vs {b}: {len(diffs)} differing values")
for d in diffs[:15]: print("  ", d)
def rows(p):
    with open(p) as f: return [r for r in f if not r.startswith("#")]
qa, qb = rows(f"{a}/queries.csv"), rows(f"{b}/queries.csv")
print("queries.csv rows", len(qa), len(qb), "identical" if qa == qb else "DIFFER")
if qa != qb:
    import itertools
    n = sum(1 for x, y in zip(qa, qb) if x != y); print("  differing rows", n)
    hdr = qa[0]; print(hdr[:300])
