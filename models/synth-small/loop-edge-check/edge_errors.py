"""Each accepted loop edge of `vvloc loops` against the ground truth the keyframes' poses give.

Usage: python edge_errors.py LOOPS_DIR  (reads LOOPS_DIR/loops.csv and LOOPS_DIR/keyframes.csv)
"""

import sys
from pathlib import Path

import numpy as np

from vvloc.localize import read_keyframe_csv, read_loop_csv
from vvloc.localize.export import relative_pose, wrap_angle

out = Path(sys.argv[1])
loops = read_loop_csv(out / "loops.csv")
kf = read_keyframe_csv(out / "keyframes.csv")
row = {int(k): r for r, k in enumerate(kf.ids)}
poses = kf.poses
acc = np.flatnonzero(loops.accepted)
i = np.array([row[int(k)] for k in loops.i[acc]])
j = np.array([row[int(k)] for k in loops.j[acc]])
truth = relative_pose(poses[i], poses[j])
est = loops.relative_poses[acc]
dt = np.hypot(*(est[:, :2] - truth[:, :2]).T)
dyaw = np.degrees(np.abs(wrap_angle(est[:, 2] - truth[:, 2])))
pinned = np.hypot(*est[:, :2].T) == 0.0
print(f"{len(acc)} accepted edges of {len(loops.i)}")
print(" i    j   true (x, y) m     |t| m  est (x, y) m     err m  yaw err deg  cost  pinned")
for n in range(len(acc)):
    print(
        f"{loops.i[acc][n]:4d} {loops.j[acc][n]:4d}  ({truth[n, 0]:5.2f}, {truth[n, 1]:5.2f})  "
        f"{np.hypot(*truth[n, :2]):5.2f}  ({est[n, 0]:5.2f}, {est[n, 1]:5.2f})  {dt[n]:5.2f}  "
        f"{dyaw[n]:6.2f}  {loops.costs[acc][n]:.3f}  {'yes' if pinned[n] else ''}"
    )
print(
    f"translation error m: median {np.median(dt):.2f}, max {dt.max():.2f}; "
    f"> 1.5 m: {(dt > 1.5).sum()} of {len(acc)}; "
    f"> 1.0 m (2 sigma of g2o's 0.5 m): {(dt > 1.0).sum()}"
)
print(
    f"yaw error deg: median {np.median(dyaw):.2f}, max {dyaw.max():.2f}; "
    f"> 4 deg (2 sigma of 2 deg): {(dyaw > 4).sum()}"
)
print(
    f"pinned to (0, 0): {pinned.sum()} "
    f"(their translation error: {np.round(dt[pinned], 2).tolist()})"
)
