"""Which metric poses of the parking validation lie exactly on the coarse search grid (0.6 m,
in the frame of a map keyframe within 4 m, or of the estimate's own heading), and the paired
errors of the two fills: ``python grid_check.py current weighted``."""

import csv
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def read(path):
    rows = list(csv.DictReader(line for line in open(path) if not line.startswith("#")))
    return {k: np.array([float(r[k]) for r in rows]) for k in rows[0] if k != "session"}


P = read(HERE.parents[2] / "data/synth-parking-96/sessions/s0/poses.csv")
res = {}
for m in sys.argv[1:]:
    q = read(HERE / f"{m}-val/queries.csv")
    on = np.zeros(len(q["est_x"]), bool)
    for i in range(len(on)):
        d = np.stack([q["est_x"][i] - P["x"], q["est_y"][i] - P["y"]], 1)
        near = np.hypot(d[:, 0], d[:, 1]) < 4
        for yaw in (P["yaw"], np.full(len(P["x"]), np.radians(q["est_yaw_deg"][i]))):
            c, s = np.cos(yaw), np.sin(yaw)
            cells = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], 1) / 0.6
            if np.any(near & np.all(np.abs(cells - np.round(cells)) < 1e-3, 1)):
                on[i] = True
    ok = q["top1_correct"] == 1
    err = q["pos_err_m"]
    print(
        f"{m}: on the coarse grid {on.sum()} / {len(on)}; median position error (top-1 a "
        f"true revisit) on / off it: {np.median(err[ok & on]) if (ok & on).any() else None} / "
        f"{np.median(err[ok & ~on])}"
    )
    res[m] = q
if len(res) == 2:
    a, b = res.values()
    both = (a["top1_correct"] == 1) & (b["top1_correct"] == 1)
    for k in ("pos_err_m", "yaw_err_deg"):
        ea, eb = np.abs(a[k][both]), np.abs(b[k][both])
        print(
            f"{k}, {both.sum()} queries top-1 correct under both: median {np.median(ea)} / "
            f"{np.median(eb)}, mean {ea.mean():.4f} / {eb.mean():.4f}; second smaller for "
            f"{(eb < ea).sum()}, larger for {(eb > ea).sum()}"
        )
