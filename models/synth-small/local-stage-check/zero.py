import sys, pickle, numpy as np
from vvloc import geometry
d = pickle.load(open(sys.argv[1], "rb")); rows = d["rows"]; db = d["db_pose"]
nz=0; tot=0
for r in rows:
    i = np.argmin(r["hcost"]); tot+=1
    if np.all(np.abs(r["xy"][i])<1e-9): nz+=1
print("argmin exactly at t=0:", nz, "of", tot)
# for those, the nearest non-zero samples
k=0
for r in rows:
    i = np.argmin(r["hcost"])
    if not np.all(np.abs(r["xy"][i])<1e-9): continue
    dd=np.hypot(*r["xy"].T); s=(dd>0)&(dd<0.2)
    o=np.argsort(dd[s])[:6]
    print(f"c0={r['hcost'][i]:.3f} near:", " ".join(f"{a:.2f}:{b:.3f}" for a,b in zip(dd[s][o], r['hcost'][s][o])))
    k+=1
    if k>8: break
