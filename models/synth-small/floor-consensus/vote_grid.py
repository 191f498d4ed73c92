"""The floor check's parameters, chosen on validation (2026-12-04): a grid over who votes and how.

Map: every frame of sessions s40-s47 of data/synth-garage-56 (validation: no model was trained,
selected or tested on them), encoded by models/synth-small, built as in
../garage-long-sequence/long_sequence.py (MAP.h5 there). Voters: the single-keyframe (L0) or
sequence-checked (L1) candidates within the vote radius R; an offset is taken with a margin over
the runner-up and a least number of votes (margin 1.0001 / min 1: a plain majority). For each,
the loop-closure figures at the acceptance radius 0.1, single keyframes (L0) and sequence-checked
(L1), with the pairs of other offsets dropped, as `vvloc eval --loops` computes them. This is the
prototype of vvloc.localize.loops.floor_offsets (a loop here, vectorised there; the chosen row,
vote L0 R0.2 margin 2 min 3, equals the library's result: output.txt).

Usage (repository root): .venv/bin/python models/synth-small/floor-consensus/vote_grid.py MAP.h5
"""

import sys
from pathlib import Path

import numpy as np

from vvloc import evaluate
from vvloc.localize.loops import descriptor_loop_candidates, sequence_distance
from vvloc.localize.mapdb import MapDatabase

out = Path(sys.argv[1])
with MapDatabase.open(out) as db:
    g = np.asarray(db.global_descriptors, dtype=np.float32)
    sess, seq = np.asarray(db.session_index), np.asarray(db.seq)
    pos, fl = np.asarray(db.poses)[:, :2], np.asarray(db.floors)


def offsets(i, j, margin, min_votes):
    a, b = sess[i], sess[j]
    o = np.where(a <= b, fl[i] - fl[j], fl[j] - fl[i])
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    res = {}
    for s, t in set(zip(lo.tolist(), hi.tolist(), strict=True)):
        if s == t:
            continue
        m = (lo == s) & (hi == t)
        vals, cnt = np.unique(o[m], return_counts=True)
        order = np.argsort(-cnt, kind="stable")
        top = cnt[order[0]]
        second = cnt[order[1]] if len(cnt) > 1 else 0
        if top >= min_votes and top >= margin * second:
            res[(s, t)] = int(vals[order[0]])
    return res


def keep(i, j, off):
    a, b = sess[i], sess[j]
    o = np.where(a <= b, fl[i] - fl[j], fl[j] - fl[i])
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    k = np.zeros(len(i), bool)
    for n in range(len(i)):
        if lo[n] == hi[n]:
            k[n] = o[n] == 0
        else:
            w = off.get((lo[n], hi[n]))
            k[n] = w is not None and o[n] == w
    return k


cand = descriptor_loop_candidates(g, sess, seq, radius=0.3, window=10)
pairs = np.stack([cand.i, cand.j], axis=1)
dseq = np.maximum(cand.distance, sequence_distance(g, sess, seq, cand.i, cand.j, 1, 10))
for vote_L, vote_R in ((0, 0.1), (0, 0.15), (0, 0.2), (1, 0.1), (1, 0.15), (1, 0.2), (1, 0.3)):
    dv = dseq if vote_L else cand.distance
    for margin, mv in ((1.0001, 1), (2, 3)):
        v = dv < vote_R
        off = offsets(cand.i[v], cand.j[v], margin, mv)
        wrong = sum(1 for w in off.values() if w != 0)
        line = f"vote L{vote_L} R{vote_R} margin {margin} min {mv}: "
        line += f"pairs decided {len(off)} wrong {wrong} |"
        for L, d in ((0, cand.distance), (1, dseq)):
            acc = d < 0.1
            idx = np.flatnonzero(acc)
            k = keep(cand.i[idx], cand.j[idx], off)
            dd = d.copy()
            dd[idx[~k]] = np.inf
            ok = np.isfinite(dd)
            s = evaluate.self_loop_closure_curve(pairs[ok], dd[ok], pos, fl, sess, seq, 10).summary(
                0.1
            )
            a = s["at_threshold"]
            line += f" L{L}: {a['accepted']} R {a['recall']:.1%} CFER {a['cfer']:.2%} |"
        print(line, flush=True)
