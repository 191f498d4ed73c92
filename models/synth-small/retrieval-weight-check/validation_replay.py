"""Replay orderings of the M metric candidates on validation_candidates.py's output: Recall@1
(2 m, snapped) for M 1-5 and coarse cost + λ × descriptor distance (or + β × retrieval rank),
on two halves of the validation sessions (A: s18, s21, s23, s26, s28; B: the others).

Usage: python validation_replay.py NAME-cands.json[.gz]  (this folder keeps both models' runs)
"""

import gzip
import json
import sys

import numpy as np

opener = gzip.open if sys.argv[1].endswith(".gz") else open
recs = json.load(opener(sys.argv[1], "rt"))
recs = [r for r in recs if r["nearest"] < 2.0]
A = {"s18", "s21", "s23", "s26", "s28"}


def score(rule, sel):
    ok = []
    for r in recs:
        if not sel(r):
            continue
        c = rule(r["cands"])
        ok.append(r["cands"][c]["d_snap"] < 2.0)
    return 100 * np.mean(ok), len(ok)


def argmin_by(f, m):
    return lambda cs: int(np.argmin([f(c, k) for k, c in enumerate(cs[:m])]))


rules = {"retrieval top1 snapped (M=1)": argmin_by(lambda c, k: 0, 1)}
for m in (2, 3, 4, 5):
    rules[f"coarse M={m}"] = argmin_by(lambda c, k: c["coarse"], m)
    rules[f"fine M={m}"] = argmin_by(lambda c, k: c["fine"], m)
for m in (2, 3, 4, 5):
    for lam in (0.2, 0.5, 1.0, 1.5, 2.0, 3.0):
        rules[f"coarse+{lam}*ret M={m}"] = argmin_by(
            lambda c, k, lam=lam: c["coarse"] + lam * c["ret"], m
        )
    for b in (0.01, 0.02, 0.03, 0.05):
        rules[f"coarse+{b}*rank M={m}"] = argmin_by(lambda c, k, b=b: c["coarse"] + b * k, m)
retr = np.mean([r["d_rows"][0] < 2 for r in recs]) * 100
print(f"retrieval R@1 {retr:.1f}  n={len(recs)}")
for name, rule in rules.items():
    a, na = score(rule, lambda r: r["session"] in A)
    b, nb = score(rule, lambda r: r["session"] not in A)
    t, nt = score(rule, lambda r: True)
    print(f"{name:28s} A {a:5.1f} ({na})  B {b:5.1f} ({nb})  all {t:5.1f}")
