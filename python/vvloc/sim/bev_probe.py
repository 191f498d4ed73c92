"""Does a model's BEV hold the parked cars of a rendered garage? A linear probe.

On the default 2-floor garage of ``vvloc sim`` the parked cars are what tells the floors apart
(:mod:`vvloc.sim.floor_cues`). This asks whether a model's BEV represents them at all, in the
cells where they stand: for every keyframe of the probe sessions it encodes the frame, takes for
each parking bay of the keyframe's floor whose centre lies within ``near`` metres of the ego
origin the mean BEV feature of the 3 × 3 cells around that centre (DESIGN.md §3: row i ↔ ego x,
column j ↔ ego y), and labels it with whether a car stands in that bay in that session (the
simulator's truth, used here only to measure, never to train the model). A logistic regression
fitted on the ``train`` sessions' features is scored on the ``test`` sessions'.

Reported: held-out accuracy, the accuracy of always answering the training majority, and the
balanced accuracy (mean of the true-positive and true-negative rates: 50 % is chance). The
*control* fits and scores the same probe on the features at the bay centre mirrored across the
ego x axis (ego y → −y), away from that bay's car (often on the bay across the aisle, whose
car comes and goes independently): what a probe finds without looking at the car itself.

Usage (from the repository root)::

    .venv/bin/python -m vvloc.sim.bev_probe --checkpoint models/synth-small-v1 \
        --dataset data/synth-garage-12 --train s0,s2,s3,s4 --test s5

Prints a Markdown summary; ``--json`` also writes the figures.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from vvloc.data import Dataset, open_dataset
from vvloc.sim import floor_cues
from vvloc.sim.world import World

NEAR = 9.0  # m: bays this close to the ego origin are probed (the cameras see them)


def bay_features(
    bevs: np.ndarray,
    kf: dict[str, np.ndarray],
    world: World,
    states: np.ndarray,
    grid_size: float,
    near: float = NEAR,
    mirror: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Probe samples of keyframes ``kf`` (:func:`floor_cues.keyframes`) with BEVs ``bevs``
    (N, H, W, C) float, cell size ``grid_size`` m, and bay ``states`` (S, B)
    (:func:`floor_cues.bay_states`, indexed by ``kf["session"]``).

    Returns ``features`` (M, C) float64 (the 3 × 3-cell mean around each bay centre within
    ``near`` m of the ego origin, the window inside the grid), ``occupied`` (M,) bool and
    ``session`` (M,) int64 (``kf["session"]`` of the sample's keyframe). ``mirror`` samples at
    the bay centre mirrored across the ego x axis (the control)."""
    n, h, w, _ = bevs.shape
    if len(kf["z"]) != n:
        raise ValueError(f"bevs: expected {len(kf['z'])} BEVs (one per keyframe), got {n}")
    xy = floor_cues.bay_centres(world)
    per_floor = len(xy)
    ego = floor_cues.ego_xy(kf["pose"], xy)  # (N, B/F, 2) m
    if mirror:
        ego = ego * np.array([1.0, -1.0])
    row = np.rint(ego[..., 0] / grid_size + (h - 1) / 2).astype(np.int64)
    col = np.rint(ego[..., 1] / grid_size + (w - 1) / 2).astype(np.int64)
    ok = (np.hypot(ego[..., 0], ego[..., 1]) <= near) & (row >= 1) & (row <= h - 2)
    ok &= (col >= 1) & (col <= w - 2)
    r, b = np.nonzero(ok)
    feats = np.zeros((len(r), bevs.shape[-1]))
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            feats += bevs[r, row[r, b] + di, col[r, b] + dj]
    feats /= 9.0
    bay = kf["floor"][r] * per_floor + b
    occupied = states[kf["session"][r], bay] != -1
    return feats, occupied, kf["session"][r].astype(np.int64)


def fit_probe(
    x_train: np.ndarray,
    y_train: np.ndarray,
    x_test: np.ndarray,
    y_test: np.ndarray,
    l2: float = 1e-3,
) -> dict[str, float]:
    """Fit an L2-regularised logistic regression (features standardised by the training mean
    and spread; full-batch L-BFGS from zero, so deterministic) on ``x_train`` (M, C) /
    ``y_train`` (M,) bool and score it on ``x_test`` / ``y_test``. Returns ``accuracy``,
    ``majority`` (accuracy of always answering the training majority class) and
    ``balanced_accuracy`` (mean of the true-positive and true-negative rates; NaN when the
    test samples hold one class only, where it is undefined) on the test samples, as shares in
    [0, 1], and ``train_accuracy``."""
    if len(x_train) == 0 or len(x_test) == 0:
        raise ValueError("x_train, x_test: expected at least one sample each")
    y_train, y_test = np.asarray(y_train, bool), np.asarray(y_test, bool)
    if y_train.all() or not y_train.any():
        raise ValueError("y_train: expected both classes among the training samples")
    mu, sd = x_train.mean(0), x_train.std(0) + 1e-6
    xt = torch.tensor((x_train - mu) / sd, dtype=torch.float64)
    yt = torch.tensor(y_train, dtype=torch.float64)
    w = torch.zeros(xt.shape[1] + 1, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS([w], max_iter=500, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        logits = xt @ w[:-1] + w[-1]
        loss = torch.nn.functional.binary_cross_entropy_with_logits(logits, yt)
        loss = loss + l2 * (w[:-1] ** 2).sum()
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        coef, bias = w[:-1].numpy(), float(w[-1])

    def predict(x: np.ndarray) -> np.ndarray:
        return np.asarray(((x - mu) / sd) @ coef + bias > 0)

    p = predict(x_test)
    tpr = float(p[y_test].mean()) if y_test.any() else float("nan")
    tnr = float((~p[~y_test]).mean()) if (~y_test).any() else float("nan")
    majority = bool(y_train.mean() >= 0.5)
    return {
        "accuracy": float((p == y_test).mean()),
        "majority": float((y_test == majority).mean()),
        "balanced_accuracy": (tpr + tnr) / 2,  # NaN unless both classes are tested
        "train_accuracy": float((predict(x_train) == y_train).mean()),
    }


def encode_bevs(model: Any, ds: Dataset, name: str) -> np.ndarray:
    """(N, H, W, C) float32: the BEV of every frame of session ``name`` in order (eval mode)."""
    from vvloc.localize.localizer import encode_frames

    s = ds.session(name)
    bev = encode_frames(model, (s[i] for i in range(len(s))), keep_bev=True).bev
    assert bev is not None  # keep_bev
    return bev


def probe(
    checkpoint: str, dataset: str, train: list[str], test: list[str], near: float = NEAR
) -> dict[str, Any]:
    """The figures of the module docstring as a JSON-friendly dict."""
    from vvloc.nets import VVLocNet

    both = sorted(set(train) & set(test))
    if both:
        raise ValueError(f"train, test: expected disjoint sessions, both hold {both}")
    if not near > 0:
        raise ValueError(f"near: expected > 0 m, got {near}")
    ds = open_dataset(dataset)
    sessions = train + test
    for name in sessions:
        ds.session(name)  # KeyError naming the known sessions
    _, world = floor_cues.sim_garage(dataset)
    states = floor_cues.bay_states(world, floor_cues.session_specs(dataset, sessions))
    kf = floor_cues.keyframes(ds, sessions)
    model = VVLocNet.load(checkpoint)
    g = float(model.config.grid_size)
    # per session: encode, sample the bays, drop the BEVs (123 kB a frame for the small model)
    samples: dict[bool, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {False: [], True: []}
    for k, name in enumerate(sessions):
        rows = kf["session"] == k
        part = {key: v[rows] for key, v in kf.items()}
        bevs = encode_bevs(model, ds, name)
        for mirror in (False, True):
            samples[mirror].append(bay_features(bevs, part, world, states, g, near, mirror))
    result: dict[str, Any] = {
        "checkpoint": checkpoint,
        "dataset": dataset,
        "train": train,
        "test": test,
        "near_m": near,
    }
    for name, mirror in (("aligned", False), ("control", True)):
        x, y, s = (np.concatenate(parts) for parts in zip(*samples[mirror], strict=True))
        tr = s < len(train)
        result[name] = fit_probe(x[tr], y[tr], x[~tr], y[~tr]) | {
            "train_samples": int(tr.sum()),
            "test_samples": int((~tr).sum()),
            "test_occupied": float(y[~tr].mean()) if (~tr).any() else float("nan"),
        }
    return result


def markdown(r: dict[str, Any]) -> str:
    """The figures of :func:`probe` as Markdown."""
    lines = [
        f"# Parked cars in the BEV of {r['checkpoint']} ({r['dataset']})",
        "",
        f"Linear probe for bay occupancy from the BEV at bays within {r['near_m']:g} m; fitted "
        f"on {', '.join(r['train'])}, scored on {', '.join(r['test'])}.",
        "",
        "| probe | test samples | occupied | accuracy | majority class | balanced accuracy |",
        "|---|---|---|---|---|---|",
    ]
    for name in ("aligned", "control"):
        o = r[name]
        label = "at the bay" if name == "aligned" else "control (mirrored, no bay)"
        lines.append(
            f"| {label} | {o['test_samples']} | {100 * o['test_occupied']:.1f} % | "
            f"{100 * o['accuracy']:.1f} % | {100 * o['majority']:.1f} % | "
            + (
                "– (one class tested) |"
                if np.isnan(o["balanced_accuracy"])
                else f"{100 * o['balanced_accuracy']:.1f} % |"
            )
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", required=True, help="a model directory (vvloc train --out)")
    p.add_argument("--dataset", required=True, help="a garage dataset of vvloc sim")
    p.add_argument("--train", required=True, help="comma-separated sessions to fit the probe on")
    p.add_argument("--test", required=True, help="comma-separated sessions to score it on")
    p.add_argument("--near", type=float, default=NEAR, help="probe bays this close, m")
    p.add_argument("--json", type=Path, help="also write the figures here")
    a = p.parse_args()
    try:
        r = probe(a.checkpoint, a.dataset, a.train.split(","), a.test.split(","), a.near)
    except (KeyError, OSError, ValueError) as e:
        p.exit(2, f"bev_probe: {e.args[0] if isinstance(e, KeyError) and e.args else e}\n")
    print(markdown(r), end="")
    if a.json:
        from vvloc.evaluate import to_jsonable  # NaN (undefined) → null

        a.json.write_text(json.dumps(to_jsonable(r), indent=2, allow_nan=False) + "\n")


if __name__ == "__main__":
    main()
