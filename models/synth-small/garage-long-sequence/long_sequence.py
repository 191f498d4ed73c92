"""Does a longer sequence check separate the default garage's floors? (validation only)

Map: every frame of sessions s40-s47 of data/synth-garage-56 (the test's structure, one map
session and seven others, none of them a test or training session), encoded by CHECKPOINT.
Candidates: keyframe pairs within descriptor distance 0.3 (temporal neighbours of one session,
±10 keyframes, left out). For each half-window L of vvloc.localize.loops.sequence_distance the
script prints the loop-closure figures at the acceptance radius 0.1 and at fixed recalls, as
`vvloc eval --loops` computes them, and splits the accepted pairs at L = 0 and 1 by whether
they join two floors of one session or of two sessions.

Usage (repository root): .venv/bin/python models/synth-small/garage-long-sequence/long_sequence.py
    CHECKPOINT OUT.h5   (about 4 min on 2 cores: 48 s to encode 2 400 frames, the rest scoring)
"""

import sys
from pathlib import Path

import numpy as np
import torch

from vvloc import evaluate
from vvloc.data import open_dataset
from vvloc.localize.localizer import build_map
from vvloc.localize.loops import descriptor_loop_candidates, sequence_distance
from vvloc.localize.mapdb import MapDatabase
from vvloc.nets import VVLocNet

ckpt, out = sys.argv[1], Path(sys.argv[2])
torch.set_num_threads(2)
sessions = [f"s{k}" for k in range(40, 48)]
if not out.exists():
    model = VVLocNet.load(ckpt)
    build_map(
        model, open_dataset("data/synth-garage-56"), sessions, out, store_bev=False, progress=False
    )
with MapDatabase.open(out) as db:
    g = np.asarray(db.global_descriptors, dtype=np.float64)
    sess, seq = np.asarray(db.session_index), np.asarray(db.seq)
    pos, fl = np.asarray(db.poses)[:, :2], np.asarray(db.floors)
cand = descriptor_loop_candidates(g.astype(np.float32), sess, seq, radius=0.3, window=10)
pairs = np.stack([cand.i, cand.j], axis=1)
print(f"map {sessions[0]}-{sessions[-1]}: {len(g)} keyframes, {len(cand.i)} pairs within 0.3")
print("L: at radius 0.1 accepted, Precision@2m, Recall@2m, CFER | best F1 | at Recall 5/10/20 %")
for L in (0, 1, 2, 4, 8, 16, 32):
    d = cand.distance
    if L:
        d = np.maximum(d, sequence_distance(g, sess, seq, cand.i, cand.j, L, 10))
    ok = np.isfinite(d)
    s = evaluate.self_loop_closure_curve(pairs[ok], d[ok], pos, fl, sess, seq, 10).summary(0.1)
    a = s["at_threshold"]
    at = " ".join(f"P {r['precision']:.1%} CFER {r['cfer']:.1%};" for r in s["at_recall"])
    print(
        f"L={L:2d}: {a['accepted']:5d} {a['precision']:6.1%} {a['recall']:6.1%} "
        f"{a['cfer']:6.1%} | {s['best_f1']['f1']:.3f} | {at}"
    )
    if L <= 1:
        acc = d < 0.1
        one = sess[cand.i] == sess[cand.j]
        cross = fl[cand.i] != fl[cand.j]
        print(
            f"      accepted pairs joining two floors: {np.sum(acc & one & cross)} of "
            f"{np.sum(acc & one)} within one session, {np.sum(acc & ~one & cross)} of "
            f"{np.sum(acc & ~one)} across sessions"
        )
