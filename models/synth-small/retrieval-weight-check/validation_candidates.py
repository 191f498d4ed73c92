"""Per query of the parking validation: the first 5 retrieved candidates' retrieval distance,
yaw re-rank cost, coarse and fine metric cost, fine pose and the snapped keyframe's distance.

Usage (repository root; the parking world of `make model`, 30 sessions):
    .venv/bin/python models/synth-small/retrieval-weight-check/validation_candidates.py \
        CHECKPOINT NAME 6 [DATASET]
writes NAME-cands.json in the current folder (about 25 min for 500 queries on 2 cores);
validation_replay.py then replays the ordering rules on it. Run with the localizer of
2026-12-03 (the candidates' metric search does not depend on the ordering's defaults)."""

import json
import sys
import time

import numpy as np
import torch

from vvloc import geometry
from vvloc.data import open_dataset
from vvloc.localize.localizer import Localizer, build_map, encode_frames
from vvloc.localize.mapdb import MapDatabase
from vvloc.nets import VVLocNet

ckpt, out = sys.argv[1], sys.argv[2]
every = int(sys.argv[3])
M = 5
torch.set_num_threads(2)
ds = open_dataset(sys.argv[4] if len(sys.argv) > 4 else "data/synth-parking")
val = ["s18", "s19", "s21", "s22", "s23", "s24", "s26", "s27", "s28", "s29"]
model = VVLocNet.load(ckpt)
mp = build_map(
    model, ds, ["s0"], f"{out}-map.h5", store_bev=False, progress=False, overwrite=True
)
db = MapDatabase.open(mp, expected_config_hash=model.config_hash())
loc = Localizer(model, db)
frames = [ds.session(s)[i] for s in val for i in range(0, len(ds.session(s)), every)]
dbxy = np.asarray(db.poses)[:, :2]
recs = []
t0 = time.time()
for start in range(0, len(frames), 8):
    chunk = frames[start : start + 8]
    enc = encode_frames(model, chunk, batch_size=8, keep_bev=True)
    for i, f in enumerate(chunk):
        q = np.asarray(f.pose, dtype=np.float64)
        d = np.hypot(*(dbxy - q[:2]).T)
        rows, dist = loc.retrieve(enc.global_desc[i])
        rr = loc.rerank(enc.local_desc[i], rows)
        cands = []
        for k in range(min(M, len(rows))):
            row = int(rows[k])
            xi, cost, hist = loc.metric(enc.bev[i], row)
            st = np.asarray(hist.stage)
            coarse = float(np.min(np.asarray(hist.cost)[st == 0]))
            gp = geometry.compose(db.poses[row], xi)
            snap = loc.snap_row(gp, rows, int(db.floors[row]))
            cands.append(
                dict(
                    row=row,
                    ret=float(dist[k]),
                    yaw=float(rr.cost[k]),
                    coarse=coarse,
                    fine=float(cost),
                    d=float(d[row]),
                    d_snap=float(d[snap]),
                    err=float(np.hypot(*(gp[:2] - q[:2]))),
                )
            )
        recs.append(
            dict(
                session=f.session,
                nearest=float(d.min()),
                cands=cands,
                d_rows=[float(x) for x in d[rows]],
                yaw_all=[float(x) for x in rr.cost],
            )
        )
    if start % 80 == 0:
        print(start, f"{time.time() - t0:.0f}s", flush=True)
print(f"{len(recs)} queries in {time.time() - t0:.0f}s")
json.dump(recs, open(f"{out}-cands.json", "w"))
