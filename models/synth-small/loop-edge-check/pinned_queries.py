"""`vvloc localize --no_snap` answers (queries.csv) against the ground truth: how many queries
about 2 m from the keyframe their pose was built on came back at exactly (0, 0).

Usage: python pinned_queries.py DATASET MAP_SESSION QUERY_SESSION LOC_DIR
"""

import csv
import sys
from pathlib import Path

import numpy as np

from vvloc.data.vvloc_format import open_vvloc
from vvloc.localize.export import relative_pose

root, map_name, query_name, out = sys.argv[1], sys.argv[2], sys.argv[3], Path(sys.argv[4])
ds = open_vvloc(root)
keyframes = ds.session(map_name).poses
queries = ds.session(query_name).poses
with open(out / "queries.csv") as f:
    rows = list(csv.DictReader(line for line in f if not line.startswith("#")))
q = np.array([int(r["index"]) for r in rows])
# --no_snap: the reported keyframe is the one the pose was built on; its frame in the session
assert all(r["map_row"] == r["metric_row"] for r in rows), "run vvloc localize with --no_snap"
assert {r["map_session"] for r in rows} == {map_name}
m = np.array([int(r["map_seq"]) for r in rows])
est = np.array([[float(r["relative_x"]), float(r["relative_y"])] for r in rows])
truth = relative_pose(keyframes[m], queries[q])[:, :2]
dist = np.hypot(*truth.T)
err = np.hypot(*(est - truth).T)
pinned = (est == 0.0).all(axis=1)
near2 = (dist > 1.5) & (dist < 2.5)
print(f"{len(rows)} queries; true distance to the metric keyframe: median {np.median(dist):.2f} m")
print(
    f"pinned to (0, 0): {pinned.sum()} of {len(rows)}; error of the pinned: "
    f"{np.round(err[pinned], 2).tolist()}"
)
print(
    f"1.5-2.5 m from their keyframe: {near2.sum()}, "
    f"of them pinned to (0, 0): {(near2 & pinned).sum()}"
)
print(
    f"position error: median {np.median(err):.2f} m; "
    f"of the rest (not pinned): {np.median(err[~pinned]):.2f} m"
)
