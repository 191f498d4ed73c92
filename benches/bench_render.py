"""Renderer throughput: multi-camera frames per second of the headless EGL renderer.

Usage: ``python benches/bench_render.py [--frames 2000] [--json PATH]``. Renders ``--frames``
keyframes of the parking lot (day and night) and of the garage with the default 4-camera
160×96 rig, plus one 6-camera row; reports ms per frame (render + read-back, no PNG writing).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from vvloc.sim import (
    Drive,
    Renderer,
    drive_keyframes,
    garage_world,
    make_rig,
    parking_world,
    sample_loop,
)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import print_table, write_json


def run(scene: str, lighting: str, cameras: int, frames: int) -> dict[str, object]:
    world = parking_world(0) if scene == "parking" else garage_world(0, floors=2)
    poses, _ = drive_keyframes(sample_loop(world.routes[0]), Drive(), frames)
    r = Renderer(make_rig(cameras, 160, 96))
    v, i = world.mesh()
    r.set_mesh(v, i, world.lights, world.light_colors, world.light_floors)
    r.render(poses[0], 0.0, lighting)  # warm-up: shader compilation
    t0 = time.perf_counter()
    for k, p in enumerate(poses):
        r.render(p, 0.0, lighting, frame_index=k)
    dt = time.perf_counter() - t0
    r.release()
    return {
        "scene": scene,
        "lighting": lighting,
        "cameras": cameras,
        "frames": frames,
        "total_s": dt,
        "ms_per_frame": 1e3 * dt / frames,
        "lp_threads": os.environ.get("LP_NUM_THREADS", "auto"),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--json", type=str, default=None)
    args = ap.parse_args()
    small = max(1, args.frames // 4)
    rows = [
        run("parking", "day", 4, args.frames),
        run("parking", "night", 4, small),
        run("garage", "garage", 4, small),
        run("parking", "day", 6, small),
    ]
    print_table(rows, ["scene", "lighting", "cameras", "frames", "total_s", "ms_per_frame"])
    if args.json:
        write_json(args.json, "render", rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
