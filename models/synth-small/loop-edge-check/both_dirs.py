"""Loop pairs verified in both directions: ξ_{i→j} as vvloc loops computes it (i's BEV padded)
and the inverse of ξ_{j→i} (j's BEV padded), each against the keyframes' ground truth.

Usage: python both_dirs.py MAP LOOPS_DIR CHECKPOINT
"""

import sys
from pathlib import Path

import numpy as np

from vvloc.geometry import inverse
from vvloc.localize import MapDatabase, read_loop_csv
from vvloc.localize.export import relative_pose, wrap_angle
from vvloc.localize.loops import verify_pairs
from vvloc.nets import VVLocNet

mapdb = MapDatabase.open(sys.argv[1])
loops = read_loop_csv(Path(sys.argv[2]) / "loops.csv")
model = VVLocNet.load(sys.argv[3])
row = {int(k): r for r, k in enumerate(mapdb.ids)}
i = np.array([row[int(k)] for k in loops.i])
j = np.array([row[int(k)] for k in loops.j])
truth = relative_pose(mapdb.poses[i], mapdb.poses[j])
fwd, cf = verify_pairs(model, mapdb, i, j)
rev, cr = verify_pairs(model, mapdb, j, i)
rev = np.stack([inverse(p) for p in rev])
best = np.where((cr < cf)[:, None], rev, fwd)


def errs(est):
    return np.hypot(*(est[:, :2] - truth[:, :2]).T), np.degrees(
        np.abs(wrap_angle(est[:, 2] - truth[:, 2]))
    )


for name, est in (
    ("forward (vvloc loops)", fwd),
    ("reverse, inverted", rev),
    ("lower cost of the two", best),
):
    dt, dy = errs(est)
    pinned = (est[:, :2] == 0).all(axis=1).sum()
    print(
        f"{name:24s}: translation err median {np.median(dt):.2f} m, "
        f"> 1 m {int((dt > 1).sum())} of {len(dt)}, "
        f"yaw err median {np.median(dy):.2f} deg, > 4 deg {int((dy > 4).sum())}, pinned {pinned}"
    )
print(
    "same as loops.csv forward:",
    np.allclose(fwd, loops.relative_poses),
    "; costs fwd/rev median",
    np.median(cf).round(3),
    np.median(cr).round(3),
    "; reverse cheaper for",
    int((cr < cf).sum()),
)
