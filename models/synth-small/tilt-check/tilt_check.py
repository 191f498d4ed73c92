"""A tilting vehicle, localized with each frame's own (levelled) extrinsics or with the rig's.

Renders one query drive of the parking test world (`data/synth-parking-96`'s world: parking,
seed 0, 4 cameras of 160 x 96) three times along the same keyframe poses: level, and tilted by
a random roll and pitch per frame (uniform within +-3 deg and +-5 deg, about the ground point
under the vehicle, as a pitching Segway or a car on a slope). The tilted drive is written as
the readers write such data: each frame's cam_to_ego is the rig's turned by the tilt
(`cam_to_ego.csv`). Then the committed model localizes the queries against a map of s0 with
the localizer's defaults, three ways:

  level      the level drive (the control);
  levelled   the tilted drive with its frames' own extrinsics (what the readers now give);
  ignored    the same images with the rig's extrinsics (the readers before 2026-12-05).

Usage (from the repository root, after `make develop`; about 4 min on 2 cores):
    .venv/bin/python models/synth-small/tilt-check/tilt_check.py --out /tmp/tilt
prints the table of `output.txt`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
import torch

from vvloc import geometry
from vvloc.data import open_dataset
from vvloc.data.vvloc_format import DatasetWriter
from vvloc.localize.localizer import Localizer, build_map, frames_to_tensors
from vvloc.nets import VVLocNet
from vvloc.sim import Renderer, make_rig
from vvloc.sim.sequences import Drive, drive_keyframes, sample_loop
from vvloc.sim.simulate import T0_US, build_world, tilted_rig

FRAMES = 200
SPEC = {"lighting": "dusk", "offset": 1.5, "reverse": False, "change_fraction": 0.15}
SEED = 20261205  # the drive's cars and wobble, and the tilts: none of the test's sessions


def render(out: Path, tilt_deg: tuple[float, float] | None) -> Path:
    """Render the drive into ``out`` (vvloc format); with ``tilt_deg`` = (roll, pitch) bounds,
    each frame tilted at random within them and its own cam_to_ego written."""
    world = build_world("parking", 0)
    rig = make_rig(4, 160, 96)
    renderer = Renderer(rig)
    rng = np.random.default_rng(SEED)
    try:
        with DatasetWriter(out, rig, overwrite=True, meta={"scene": "parking", "seed": 0}) as w:
            verts, idx = world.mesh(SPEC["change_fraction"], SEED)
            renderer.set_mesh(verts, idx, world.lights, world.light_colors, world.light_floors)
            s = w.add_session("q", meta=SPEC)
            poses, times = drive_keyframes(
                sample_loop(world.routes[0]),
                Drive(SPEC["offset"], SPEC["reverse"], seed=SEED),
                FRAMES,
            )
            for j in range(FRAMES):
                per_frame = None
                if tilt_deg is not None:
                    per_frame = tilted_rig(rig, rng, np.asarray(tilt_deg, dtype=np.float64))
                images = renderer.render(
                    poses[j], 0.0, SPEC["lighting"], frame_index=j, cam_to_ego=per_frame
                )
                ts = T0_US + 500 * 86_400_000_000 + round(times[j] * 1e6)
                s.add(ts, poses[j], images, cam_to_ego=per_frame)
    finally:
        renderer.release()
    return out


def localize(loc: Localizer, frames: list) -> dict[str, float]:
    """Recall@1 (2 m) over the queries with a map keyframe within 2 m, and the APE/AOE
    percentiles of the global pose over those whose top-1 is a true revisit."""
    map_xy = np.asarray(loc.map.poses)[:, :2]
    results = loc.localize_batch(frames)
    truth = np.stack([f.pose for f in frames])
    near = np.array([np.hypot(*(map_xy - t[:2]).T).min() <= 2.0 for t in truth])
    hit = np.array(
        [np.hypot(*(map_xy[r.map_row] - t[:2])) <= 2.0 for r, t in zip(results, truth, strict=True)]
    )
    est = np.stack([r.global_pose for r in results])
    ape = np.hypot(*(est[:, :2] - truth[:, :2]).T)
    aoe = np.degrees(np.abs(geometry.wrap_angle(est[:, 2] - truth[:, 2])))
    ok = near & hit
    return {
        "queries": int(near.sum()),
        "recall@1": float(hit[near].mean()),
        "APE@25": float(np.percentile(ape[ok], 25)),
        "APE@50": float(np.percentile(ape[ok], 50)),
        "AOE@25": float(np.percentile(aoe[ok], 25)),
        "AOE@50": float(np.percentile(aoe[ok], 50)),
    }


@torch.no_grad()
def agreement(model: VVLocNet, level: list, other: list) -> dict[str, float]:
    """How close each frame's encoding is to the level drive's at the same pose: the mean
    cosine similarity of their BEV cells, and the L2 distance of their global descriptors
    (means over the frames)."""
    cos, dist = [], []
    for k in range(0, len(level), 16):
        a = model.encode(*frames_to_tensors(level[k : k + 16], torch.device("cpu")))
        b = model.encode(*frames_to_tensors(other[k : k + 16], torch.device("cpu")))
        cos.append(torch.nn.functional.cosine_similarity(a.bev, b.bev, dim=-1).mean((1, 2)))
        dist.append((a.global_desc - b.global_desc).norm(dim=-1))
    return {
        "bev_cosine": float(torch.cat(cos).mean()),
        "global_distance": float(torch.cat(dist).mean()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--checkpoint", default="models/synth-small")
    ap.add_argument("--dataset", default="data/synth-parking-96")
    ap.add_argument(
        "--tilt",
        type=float,
        nargs=2,
        default=(3.0, 5.0),
        metavar=("ROLL", "PITCH"),
        help="bounds of the uniform roll and pitch, degrees",
    )
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    model = VVLocNet.load(args.checkpoint)
    map_path = args.out / "map.h5"
    if not map_path.exists():
        build_map(model, open_dataset(args.dataset), ["s0"], map_path, progress=False)
    level = open_dataset(render(args.out / "level", None)).session("q")
    tilted = open_dataset(render(args.out / "tilted", tuple(args.tilt))).session("q")
    assert tilted.frame_cam_to_ego is not None and level.frame_cam_to_ego is None
    rig = np.stack([c.cam_to_ego for c in tilted.cameras])
    runs = {
        "level": list(level),
        "levelled": list(tilted),
        "ignored": [dataclasses.replace(f, cam_to_ego=rig.copy()) for f in tilted],
    }
    rows = {}
    for name, frames in runs.items():
        loc = Localizer.open(map_path, args.checkpoint)
        rows[name] = localize(loc, frames)
        loc.map.close()
        rows[name].update(agreement(model, runs["level"], frames))
    (args.out / "results.json").write_text(json.dumps({"tilt": args.tilt, **rows}, indent=2))
    roll, pitch = args.tilt
    print(f"tilt: roll within +-{roll:g} deg, pitch within +-{pitch:g} deg")
    print(
        "| queries | kept | Recall@1 (2 m) | AOE@25 / @50 (deg) | APE@25 / @50 (m) "
        "| BEV cosine to level | global distance to level |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, r in rows.items():
        print(
            f"| {name} | {r['queries']} | {100 * r['recall@1']:.1f} % | "
            f"{r['AOE@25']:.2f} / {r['AOE@50']:.2f} | {r['APE@25']:.2f} / {r['APE@50']:.2f} "
            f"| {r['bev_cosine']:.3f} | {r['global_distance']:.3f} |"
        )


if __name__ == "__main__":
    main()
