"""Editing a rendered dataset in a test: frames whose pictures show nothing."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from vvloc.data import open_dataset


def blank_frames(root: Path, session: str, indices: Iterable[int], value: int = 0) -> None:
    """Overwrite every camera's image of ``session``'s frames ``indices`` (vvloc format under
    ``root``) with a flat picture of grey level ``value``."""
    from PIL import Image

    ds = open_dataset(root)
    stamps = [
        line.split(",")[0]
        for line in (root / "sessions" / session / "poses.csv").read_text().splitlines()[1:]
    ]
    for i in indices:
        for cam in ds.cameras:
            p = root / "sessions" / session / cam.name / f"{stamps[i]}.png"
            flat = np.full_like(np.asarray(Image.open(p)), value)
            Image.fromarray(flat).save(p)
