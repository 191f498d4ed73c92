"""Experiment (2026-12-05): DESIGN's padding fill (a padded row or column with any tap outside
the map is 1) against a fill blended by the fractional shift (the map surrounded by ones and
sampled bilinearly: continuous in t, equal at whole-cell shifts), with the committed weights.

Run from the repository root (MODE current|weighted; TAG names the output folder here):

    python models/synth-small/padding-fill-check/pad_exp.py MODE val s18,s19 3
    python models/synth-small/padding-fill-check/pad_exp.py MODE gval \
        s41,s42,s43,s44,s45,s46,s47 60 synth-garage-56 s40

then ``grid_check.py current weighted``. "weighted" swaps ``kernels.pad_polar`` for the torch
version below; "current" uses the Rust kernel as it is.
"""

import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

import vvloc.kernels as kernels
from vvloc.localize.evaluation import run_evaluation
from vvloc.reference.torch_spatial import _axis_shift, _normalised, _polar_channels_first

HERE = Path(__file__).resolve().parent
ORIGINAL = kernels.pad_polar


def weighted_pad_polar(bev, translations, num_angles, num_radii, grid_size, backend="rust"):
    """(H, W, C) map, (N, 2) metres → (N, T, R, C): padding with the blended fill, then polar."""
    q = torch.from_numpy(np.ascontiguousarray(bev, dtype=np.float32))
    h, w, c = q.shape
    maps = q.permute(2, 0, 1)[None] - 1.0  # zero padding of Q − 1, plus 1: outside reads 1
    t = torch.as_tensor(np.asarray(translations, dtype=np.float64))
    rows = torch.arange(h, dtype=torch.float64)
    cols = torch.arange(w, dtype=torch.float64)
    outs = []
    for s in range(0, len(t), 64):
        tt = t[s : s + 64]
        n = len(tt)
        u = _axis_shift(tt[:, 0], grid_size, h)
        v = _axis_shift(tt[:, 1], grid_size, w)
        gy = _normalised(rows + u[:, None], h)[:, :, None].expand(n, h, w)
        gx = _normalised(cols + v[:, None], w)[:, None, :].expand(n, h, w)
        grid = torch.stack([gx, gy], -1).reshape(1, n * h, w, 2).float()
        padded = F.grid_sample(maps, grid, padding_mode="zeros", align_corners=False) + 1.0
        padded = padded.reshape(c, n, h, w).transpose(0, 1)  # (n, C, H, W)
        polar = _polar_channels_first(padded, num_angles, num_radii, grid_size)  # (n, C, T, R)
        outs.append(polar.permute(0, 2, 3, 1))
    return torch.cat(outs).contiguous().numpy()


def max_difference(xy):
    b = np.random.default_rng(0).standard_normal((40, 40, 8)).astype(np.float32)
    xy = np.array(xy)
    return np.abs(ORIGINAL(b, xy, 60, 16, 0.6) - weighted_pad_polar(b, xy, 60, 16, 0.6)).max()


print("whole-cell shifts, max difference", max_difference([[0.6, -1.2], [0.0, 0.0], [1.8, 2.4]]))
print("fractional shift, max difference", max_difference([[0.65, -1.3]]))

mode, tag, queries, every = sys.argv[1], sys.argv[2], sys.argv[3].split(","), int(sys.argv[4])
dataset = sys.argv[5] if len(sys.argv) > 5 else "synth-parking-96"
database = sys.argv[6] if len(sys.argv) > 6 else "s0"
if mode == "weighted":
    kernels.pad_polar = weighted_pad_polar
t0 = time.time()
run_evaluation(
    "models/synth-small",
    f"data/{dataset}",
    database,
    queries,
    HERE / f"{mode}-{tag}",
    every=every,
    progress=False,
    loops=len(sys.argv) > 5,
)
print(mode, "time", time.time() - t0)
