import sys, pickle, numpy as np
from vvloc import geometry
d = pickle.load(open(sys.argv[1], "rb")); rows = d["rows"]; db = d["db_pose"]
def grid(r):
    c = r["stage"]==0; xy=r["xy"][c]; hc=r["hcost"][c]; yw=r["yaw"][c]
    xs=np.unique(np.round(xy[:,0],6)); ys=np.unique(np.round(xy[:,1],6))
    G=np.full((len(xs),len(ys)),np.nan); Y=G.copy()
    for (x,y),cc,w in zip(xy,hc,yw):
        a=np.searchsorted(xs,round(x,6)); b=np.searchsorted(ys,round(y,6)); G[a,b]=cc; Y[a,b]=w
    return xs,ys,G,Y
def wrap(a): return (a+np.pi)%(2*np.pi)-np.pi
def lattice(r, mode):
    xs,ys,G,Y=grid(r); a,b=np.unravel_index(np.nanargmin(G),G.shape)
    step=xs[1]-xs[0]; x=xs[a]; y=ys[b]; yaw=Y[a,b]
    if mode=="sep":
        if 0<a<len(xs)-1:
            l,c,rr=G[a-1,b],G[a,b],G[a+1,b]; den=l-2*c+rr
            if den>0: x+= step*0.5*(l-rr)/den
        if 0<b<len(ys)-1:
            l,c,rr=G[a,b-1],G[a,b],G[a,b+1]; den=l-2*c+rr
            if den>0: y+= step*0.5*(l-rr)/den
    elif mode=="quad":
        A=[];C=[]
        for i in range(max(a-1,0),min(a+2,len(xs))):
            for j in range(max(b-1,0),min(b+2,len(ys))):
                px,py=xs[i]-xs[a],ys[j]-ys[b]; A.append([1,px,py,px*px,px*py,py*py]); C.append(G[i,j])
        co,*_=np.linalg.lstsq(np.array(A),np.array(C),rcond=None)
        H=np.array([[2*co[3],co[4]],[co[4],2*co[5]]])
        if np.all(np.linalg.eigvalsh(H)>0):
            dx=-np.linalg.solve(H,co[1:3])
            dx=np.clip(dx,-step,step); x+=dx[0]; y+=dx[1]
    return np.r_[x,y,yaw]
def argmin(r):
    i=np.argmin(r["hcost"]); return np.r_[r["xy"][i], r["yaw"][i]]
def fine_yaw(fn):
    def f(r):
        p=fn(r); i=np.argmin(r["hcost"]); p[2]=r["yaw"][i]; return p
    return f
def err(r, xi_qm):
    g = geometry.compose(r["mpose"], geometry.inverse(np.asarray(xi_qm,float)))
    return np.hypot(*(g[:2]-r["gt"][:2])), abs(wrap(g[2]-r["gt"][2]))
ok=[np.hypot(*(db[r["best"],:2]-r["gt"][:2]))<=2 for r in rows]
for name,fn in [("argmin",argmin),("coarse",lambda r: lattice(r,"none")),("sep",lambda r: lattice(r,"sep")),("quad",lambda r: lattice(r,"quad")),("sep+fineyaw",fine_yaw(lambda r: lattice(r,"sep"))),("quad+fineyaw",fine_yaw(lambda r: lattice(r,"quad")))]:
    e=np.array([err(r,fn(r)) for r,o in zip(rows,ok) if o])
    p=np.percentile(e[:,0],[25,50,75]); a=np.degrees(np.percentile(e[:,1],[25,50]))
    print(f"{name:13s} APE25/50/75 {p[0]:.3f} {p[1]:.3f} {p[2]:.3f}  AOE25/50 {a[0]:.3f} {a[1]:.3f}")
E=[];D=[];Z=[]
for r,o in zip(rows,ok):
    if not o: continue
    tr=geometry.relative(r["gt"], r["mpose"]); E.append(err(r,argmin(r))[0]); D.append(abs(np.degrees(tr[2]))>90)
    i=np.argmin(r["hcost"]); Z.append(np.all(np.abs(r["xy"][i])<1e-9))
E=np.array(E);D=np.array(D);Z=np.array(Z)
for lab,s in (("same dir",~D),("opposite",D)):
    print(lab, s.sum(), "APE25/50", np.percentile(E[s],[25,50]), "at t=0:", Z[s].sum())
