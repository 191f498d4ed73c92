import sys, pickle, numpy as np
from vvloc import geometry
d = pickle.load(open(sys.argv[1], "rb"))
rows = d["rows"]

def glob(r, xi_qm):
    return geometry.compose(r["mpose"], geometry.inverse(np.asarray(xi_qm, float)))

def err(r, xi_qm):
    g = glob(r, xi_qm)
    return np.hypot(*(g[:2] - r["gt"][:2])), abs((g[2] - r["gt"][2] + np.pi) % (2*np.pi) - np.pi)

def argmin(r):
    i = np.argmin(r["hcost"]); return np.r_[r["xy"][i], r["yaw"][i]]

def quad(r, rad=0.3, yawfix=True):
    i = np.argmin(r["hcost"]); xy0 = r["xy"][i]
    sel = np.hypot(*(r["xy"] - xy0).T) <= rad
    if sel.sum() < 8: return argmin(r)
    p = r["xy"][sel] - xy0; c = r["hcost"][sel]
    A = np.c_[np.ones(len(p)), p, p[:,0]**2, p[:,0]*p[:,1], p[:,1]**2]
    co, *_ = np.linalg.lstsq(A, c, rcond=None)
    H = np.array([[2*co[3], co[4]], [co[4], 2*co[5]]]); g = co[1:3]
    if np.any(np.linalg.eigvalsh(H) <= 0): return argmin(r)
    dx = -np.linalg.solve(H, g)
    if np.hypot(*dx) > rad: return argmin(r)
    # yaw: fit linear in xy locally
    Ay = np.c_[np.ones(len(p)), p]
    yw = np.unwrap(r["yaw"][sel] - r["yaw"][i]) + r["yaw"][i]
    cy, *_ = np.linalg.lstsq(Ay, yw, rcond=None)
    yaw = cy[0] + cy[1:] @ dx if yawfix else r["yaw"][i]
    return np.r_[xy0 + dx, yaw]

def soft(r, tau=0.01):
    c = r["hcost"]; w = np.exp(-(c - c.min())/tau); w /= w.sum()
    xy = w @ r["xy"]; i = np.argmin(c)
    return np.r_[xy, r["yaw"][i] + w @ ((r["yaw"] - r["yaw"][i] + np.pi) % (2*np.pi) - np.pi)]

def topk(r, k=5):
    idx = np.argsort(r["hcost"])[:k]
    return np.r_[r["xy"][idx].mean(0), r["yaw"][idx].mean()]

# correct: reported top-1 within 2 m of query (reranked[0] = best); approximate with best row
db = d["db_pose"]
ok = np.array([np.hypot(*(db[r["best"], :2] - r["gt"][:2])) <= 2.0 for r in rows])
print("n", len(rows), "correct", ok.sum())
methods = {"argmin": argmin}
for rad in (0.15, 0.2, 0.3, 0.45):
    methods[f"quad{rad}"] = (lambda rr, rad=rad: quad(rr, rad))
for tau in (0.002, 0.005, 0.01, 0.02):
    methods[f"soft{tau}"] = (lambda rr, tau=tau: soft(rr, tau))
for k in (3, 5, 10):
    methods[f"top{k}"] = (lambda rr, k=k: topk(rr, k))
for name, fn in methods.items():
    e = np.array([err(r, fn(r)) for r, o in zip(rows, ok) if o])
    p = np.percentile(e[:,0], [25, 50, 75]); a = np.degrees(np.percentile(e[:,1], [25, 50]))
    print(f"{name:10s} APE25/50/75 {p[0]:.3f} {p[1]:.3f} {p[2]:.3f}  AOE25/50 {a[0]:.3f} {a[1]:.3f}")
