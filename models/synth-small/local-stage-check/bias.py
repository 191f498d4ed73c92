import sys, pickle, numpy as np
from vvloc import geometry
d = pickle.load(open(sys.argv[1], "rb")); rows = d["rows"]; db = d["db_pose"]
E=[];T=[]
for r in rows:
    if np.hypot(*(db[r["best"], :2] - r["gt"][:2])) > 2: continue
    i = np.argmin(r["hcost"]); xi_qm = np.r_[r["xy"][i], r["yaw"][i]]
    true_qm = geometry.relative(r["gt"], r["mpose"])  # map in query frame
    E.append(xi_qm); T.append(true_qm)
E=np.array(E); T=np.array(T)
print("n", len(E))
print("mean err (x,y,yaw deg)", (E-T)[:,:2].mean(0), np.degrees(np.mean((E-T)[:,2])))
print("median err", np.median(E-T, axis=0)[:2])
for j in (0,1):
    A=np.c_[T[:,j], np.ones(len(T))]; c,*_=np.linalg.lstsq(A,E[:,j],rcond=None); print("axis",j,"slope,icpt",c, "true std", T[:,j].std())
e=np.hypot(*(E-T)[:,:2].T); print("APE25/50 (search frame)", np.percentile(e,[25,50]))
n=np.hypot(*T[:,:2].T); 
for lo,hi in ((0,0.5),(0.5,1),(1,1.5),(1.5,2.5),(2.5,9)):
    s=(n>=lo)&(n<hi); print(f"|t| {lo}-{hi}: n={s.sum()} APE50={np.median(e[s]) if s.any() else 0:.3f}")
for j in (0,1):
    s=np.abs(T[:,j])>0.8
    print("axis",j,"n",s.sum(),"median ratio est/true", np.median(E[s,j]/T[s,j]), "quartiles", np.percentile(E[s,j]/T[s,j],[25,75]))
    # also robust fit via Theil-Sen-ish: median of slopes
# scaled estimate APE
for sx,sy in ((1,1),(1.3,1.3),(1.5,1.5),(2,1.5),(1.5,1.2)):
    e2=np.hypot(E[:,0]*sx-T[:,0], E[:,1]*sy-T[:,1]); print(sx,sy,"APE25/50",np.percentile(e2,[25,50]))
