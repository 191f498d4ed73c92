"""Collect Localizer search histories for offline analysis of sub-sample pose refinement."""
import sys, pickle, numpy as np
from pathlib import Path
from vvloc.nets import VVLocNet
from vvloc.data import open_dataset
from vvloc.localize.localizer import Localizer, build_map
from vvloc.localize.mapdb import MapDatabase

ckpt, dataset, queries, every, out = sys.argv[1], sys.argv[2], sys.argv[3].split(","), int(sys.argv[4]), Path(sys.argv[5])
out.mkdir(parents=True, exist_ok=True)
model = VVLocNet.load(ckpt)
ds = open_dataset(dataset)
mp = out / "map.h5"
if not mp.exists():
    build_map(model, ds, ["s0"], mp, store_bev=False, progress=False)
mapdb = MapDatabase.open(mp, expected_config_hash=model.config_hash())
loc = Localizer(model, mapdb)
frames = [ds.session(s)[i] for s in queries for i in range(0, len(ds.session(s)), every)]
res = loc.localize_batch(frames, progress=True)
rows = []
for f, r in zip(frames, res):
    h = r.search
    rows.append(dict(gt=np.asarray(f.pose), floor=f.floor, matched=r.metric_row, best=r.map_row,
                     mpose=np.asarray(mapdb.poses[r.metric_row]), gpose=r.global_pose, cost=r.cost,
                     xy=np.asarray(h.xy), yaw=np.asarray(h.yaw), hcost=np.asarray(h.cost), stage=np.asarray(h.stage)))
pickle.dump(dict(rows=rows, db_pose=np.asarray(mapdb.poses)), open(out / "hist.pkl", "wb"))
print("saved", len(rows))
