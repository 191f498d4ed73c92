"""How much the committed model's BEV follows the extrinsics it is given, against how much it
follows the view: the first 96 frames of tilt_check.py's drive, level and tilted (roll within
+-3 / pitch within +-5 deg, and +-8 / +-12 deg), encoded three ways and compared with the level
drive's encoding (tilt_check.agreement). Renders into /tmp/sens-*; prints sensitivity.txt.

    .venv/bin/python models/synth-small/tilt-check/sensitivity.py
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
import tilt_check as tc

from vvloc.data import open_dataset
from vvloc.nets import VVLocNet

torch.set_num_threads(2)
model = VVLocNet.load("models/synth-small")
for tilt in [(3.0, 5.0), (8.0, 12.0)]:
    out = Path(f"/tmp/sens-{tilt[0]:g}-{tilt[1]:g}")
    level = list(open_dataset(tc.render(out / "level", None)).session("q"))[:96]
    tilted = list(open_dataset(tc.render(out / "tilted", tilt)).session("q"))[:96]
    rig = np.stack([c.cam_to_ego for c in open_dataset(out / "tilted").cameras])
    runs = {
        "level images, the tilted frames' extrinsics": [
            dataclasses.replace(a, cam_to_ego=b.cam_to_ego)
            for a, b in zip(level, tilted, strict=True)
        ],
        "tilted images, their own extrinsics": tilted,
        "tilted images, the rig's extrinsics": [
            dataclasses.replace(f, cam_to_ego=rig.copy()) for f in tilted
        ],
    }
    for name, frames in runs.items():
        print(tilt, name, tc.agreement(model, level, frames))
