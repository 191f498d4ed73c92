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
    """A checkpoint folder (it holds ``config.json``) as given, or for a run folder its
    ``best/`` when the run has a complete one, else its latest ``checkpoint/``."""
    path = Path(path)
    if (path / "config.json").is_file():  # a checkpoint itself, whatever folders it holds
        return path
    for sub in ("best", "checkpoint"):
        if (path / sub / "config.json").is_file() and (path / sub / "model.safetensors").is_file():
            return path / sub
    return path
