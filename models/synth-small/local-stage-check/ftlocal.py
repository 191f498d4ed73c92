"""Experiment: fine-tune only the local-view decoder + interactor on cached BEVs with an extra
near translation-bias term (|Δ| in [lo, hi], margin ∝ |Δ|)."""
import sys, time, math, numpy as np, torch, torch.nn.functional as F
from pathlib import Path
from vvloc import geometry
from vvloc.nets import VVLocNet
from vvloc.data import open_dataset
from vvloc.localize.localizer import encode_frames
from vvloc.losses import yaw_matching_loss, aligned_descriptors, matching_cost, random_translation_bias, translation_bias_loss

out = Path(sys.argv[1]); steps = int(sys.argv[2]); near_w = float(sys.argv[3]); near_lo, near_hi = float(sys.argv[4]), float(sys.argv[5])
near_slope = float(sys.argv[6]) if len(sys.argv) > 6 else 0.1
mode = sys.argv[7] if len(sys.argv) > 7 else "random"
torch.manual_seed(0); rng = np.random.default_rng(0)
torch.set_num_threads(2)
model = VVLocNet.load("models/synth-small")
cache = Path("/tmp/exp/bevcache.npz")
if cache.exists():
    z = np.load(cache); bev, poses = z["bev"], z["poses"]; sess = z["sess"]
else:
    ds = open_dataset("/tmp/mr/data/synth-parking")
    names = ["s0","s1","s2"] + [f"s{i}" for i in range(5, 18)]
    frames = [ds.session(s)[i] for s in names for i in range(0, len(ds.session(s)), 2)]
    t0 = time.time(); enc = encode_frames(model, frames, batch_size=16, keep_bev=True, progress=True)
    print("encoded", len(frames), time.time() - t0, flush=True)
    bev = enc.bev.astype(np.float32); poses = np.stack([f.pose for f in frames]); sess = np.array([f.session for f in frames])
    np.savez(cache, bev=bev, poses=poses, sess=sess)
# pairs: anchor, positive in another session within 2 m
d = np.hypot(poses[:, None, 0] - poses[None, :, 0], poses[:, None, 1] - poses[None, :, 1])
pos = [np.flatnonzero((d[i] < 2.0) & (sess != sess[i])) for i in range(len(poses))]
anchors = np.array([i for i in range(len(poses)) if len(pos[i])])
print("anchors", len(anchors), flush=True)
for name, p in model.named_parameters():
    p.requires_grad = name.startswith("decoder.") or name.startswith("interactor.")
params = [p for p in model.parameters() if p.requires_grad]
print("trainable", sum(p.numel() for p in params), flush=True)
opt = torch.optim.Adam(params, lr=1e-4)
model.train()
B = 8; log = []
t0 = time.time()
for step in range(steps):
    a = rng.choice(anchors, B); p = np.array([rng.choice(pos[i]) for i in a])
    xi = geometry.relative(poses[a], poses[p])
    t = torch.as_tensor(xi[:, :2], dtype=torch.float32); yaw = torch.as_tensor(xi[:, 2], dtype=torch.float32)
    bs = torch.from_numpy(bev[a]); bt = torch.from_numpy(bev[p])
    lt = model.decode_polar(model.polar(bt))
    l_yaw = yaw_matching_loss(model, bs, lt, t, yaw, 40.0, 0.1, 1.4)
    l_tb = translation_bias_loss(model, bs, lt, t, yaw, margin=0.1, seed=1_000_003 * 7 + step)
    loss = 0.02 * l_yaw + l_tb
    l_near = torch.zeros(())
    if near_w > 0:
        delta = random_translation_bias(B, (near_lo, near_hi), seed=99_991 * 3 + step)
        if mode == "zero":
            use = (t.norm(dim=1) >= near_lo) & (torch.arange(B) % 2 == 0)
            delta = torch.where(use[:, None], -t, delta)
        if mode in ("shrink", "mixed"):
            g = torch.Generator().manual_seed(77_777 + step)
            lam = torch.rand(B, generator=g) * 0.75
            shr = (lam[:, None] - 1.0) * t  # t + shr = lam * t: toward zero translation (less padding)
            use = t.norm(dim=1) > near_lo
            if mode == "mixed":
                use = use & (torch.arange(B) % 2 == 0)
            delta = torch.where(use[:, None], shr, delta)
        c_true = matching_cost(*aligned_descriptors(model, bs, lt, t, yaw))
        c_near = matching_cost(*aligned_descriptors(model, bs, lt, t + delta, yaw))
        l_near = F.relu(c_true - c_near + near_slope * delta.norm(dim=1)).mean()
        loss = loss + near_w * l_near
    opt.zero_grad(); loss.backward(); torch.nn.utils.clip_grad_norm_(params, 10.0); opt.step()
    log.append((float(l_yaw), float(l_tb), float(l_near)))
    if (step + 1) % 100 == 0:
        m = np.mean(log[-100:], 0); print(f"step {step+1} yaw {m[0]:.4f} tb {m[1]:.4f} near {m[2]:.4f} {time.time()-t0:.0f}s", flush=True)
model.eval(); model.save(out)
print("saved", out)
