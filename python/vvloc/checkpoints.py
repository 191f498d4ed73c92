"""Where a trained model lives on disk (no torch import: the CLI resolves paths before loading).

A *checkpoint* folder holds ``config.json`` + ``model.safetensors`` (:meth:`VVLocNet.save`); a
*run* folder (``vvloc train --out``) holds ``best/`` (the epoch selected on the validation
sessions, when the config has some) and ``checkpoint/`` (the latest epoch).
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["resolve_checkpoint"]


def resolve_checkpoint(path: str | os.PathLike[str]) -> Path:
    """A checkpoint folder as given, or for a run folder its ``best/`` when the run has one,
    else its latest ``checkpoint/``."""
    path = Path(path)
    for sub in ("best", "checkpoint"):
        if (path / sub / "config.json").is_file():
            return path / sub
    return path
