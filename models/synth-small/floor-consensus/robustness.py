"""How the floor check fares when the sessions' floor numbers are wrong (2026-12-04, after test).

The check keeps loops to the floor numbers each session records; in these datasets they are the
renderer's, the same labels CFER is scored against. Here the check is given corrupted numbers
while CFER is still scored with the true ones, on the test's loop-closure maps (the
`loops_map.h5` that `vvloc eval --loops` wrote into test-garage/ and test-pillars/; they are not
committed: rerun the test's commands to get them):

- shifted: every session's numbers plus a random constant (the check must not change);
- missed ramp, share q: in a share q of the sessions (drawn per seed) the numbers are one too
  high from a random keyframe to the session's end, as if the vehicle counted a ramp it did not
  drive (or missed one) and never corrected it.

Printed per map, seed 0-2: single keyframes and sequence-checked (±1) at the radius 0.1:
accepted, Recall@2m, CFER. Usage (repository root):
    .venv/bin/python models/synth-small/floor-consensus/robustness.py
"""

from pathlib import Path

import numpy as np

from vvloc import evaluate
from vvloc.localize.loops import (
    FLOOR_VOTE_FACTOR,
    confirm_sequence,
    descriptor_loop_candidates,
    floor_consensus,
)
from vvloc.localize.mapdb import MapDatabase

HERE = Path(__file__).parent
RADIUS = 0.1
QS = (0.25, 0.5, 1.0)


def missed_ramp(sess, seq, floors, share, rng):
    out = floors.copy()
    ids = np.unique(sess)
    for s in rng.choice(ids, round(share * len(ids)), replace=False):
        rows = np.flatnonzero(sess == s)
        rows = rows[np.argsort(seq[rows])]
        out[rows[rng.integers(0, len(rows)) :]] += 1
    return out


def figures(cand, pos, floors, sess, seq):
    pairs = np.stack([cand.i, cand.j], axis=1)
    curve = evaluate.self_loop_closure_curve(pairs, cand.distance, pos, floors, sess, seq, 10)
    at = curve.summary(RADIUS)["at_threshold"]
    return f"{at['accepted']:5d} {100 * at['recall']:5.1f} % {100 * at['cfer']:6.2f} %"


for world in ("test-garage", "test-pillars"):
    with MapDatabase.open(HERE / world / "loops_map.h5") as db:
        g, sess, seq = db.global_descriptors, db.session_index, db.seq
        pos, true = np.asarray(db.poses)[:, :2], np.asarray(db.floors)
    voters = descriptor_loop_candidates(g, sess, seq, FLOOR_VOTE_FACTOR * RADIUS, 10)
    single = voters.within(RADIUS)
    seqd = confirm_sequence(single, g, sess, seq, RADIUS, 1, 10)
    print(f"{world}: {len(np.unique(sess))} sessions; single keyframes | sequence-checked")
    print(
        f"  no check            {figures(single, pos, true, sess, seq)} | "
        f"{figures(seqd, pos, true, sess, seq)}"
    )
    cases = [("true floors", 0.0), ("shifted", 0.0), *((f"missed ramp {q:g}", q) for q in QS)]
    for name, q in cases:
        for seed in range(3 if q else 1):
            rng = np.random.default_rng(seed)
            if name == "true floors":
                fl = true
            elif name == "shifted":
                fl = true + rng.integers(-9, 10, sess.max() + 1)[sess]
            else:
                fl = missed_ramp(sess, seq, true, q, rng)
            a = floor_consensus(single, sess, fl, voters)
            b = floor_consensus(seqd, sess, fl, voters)
            print(
                f"  {name:18s}{seed} {figures(a, pos, true, sess, seq)} | "
                f"{figures(b, pos, true, sess, seq)}"
            )
