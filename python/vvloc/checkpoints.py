"""Where a trained model lives on disk (no torch import: the CLI resolves paths before loading).

A *checkpoint* folder holds ``config.json`` + ``model.safetensors`` (:meth:`VVLocNet.save`); a
*run* folder (``vvloc train --out``) holds ``best/`` (the epoch selected on the validation
sessions, when the config has some) and ``checkpoint/`` (the latest epoch).
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["check_checkpoint_files", "checkpoint_folder", "resolve_checkpoint"]

#: The two files of a checkpoint folder (``vvloc.nets.model`` writes them).
CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"


def resolve_checkpoint(path: str | os.PathLike[str]) -> Path:
    """A checkpoint folder (it holds ``config.json``) as given, or for a run folder its
    ``best/`` when the run has a complete one, else its latest ``checkpoint/``."""
    path = Path(path)
    if (path / CONFIG_FILE).is_file():  # a checkpoint itself, whatever folders it holds
        return path
    for sub in ("best", "checkpoint"):
        if (path / sub / CONFIG_FILE).is_file() and (path / sub / WEIGHTS_FILE).is_file():
            return path / sub
    return path


def checkpoint_folder(path: str | os.PathLike[str], argument: str = "checkpoint") -> Path:
    """:func:`resolve_checkpoint`, checked by :func:`check_checkpoint_files`: the folder to load,
    or ``FileNotFoundError`` naming ``argument`` (the parameter or CLI option the path came
    from)."""
    src = resolve_checkpoint(path)
    check_checkpoint_files(src, argument)
    return src


def check_checkpoint_files(src: Path, argument: str = "directory") -> None:
    """``FileNotFoundError`` naming ``argument`` when the folder ``src`` (not resolved: a run
    folder is not a checkpoint) lacks ``config.json`` or ``model.safetensors``, the message
    naming the checkpoints of a run; whether the files hold a valid checkpoint is for
    :meth:`vvloc.nets.model.VVLocNet.load` to say."""
    src = Path(src)  # a str too
    if not src.is_dir():
        what = "is a file, not a folder" if src.exists() else "does not exist"
        raise FileNotFoundError(
            f"{argument}: {src} {what} (expected a vvloc checkpoint folder holding "
            f"{CONFIG_FILE} and {WEIGHTS_FILE}, or a training run's best/ or checkpoint/)"
        )
    for p in (src / CONFIG_FILE, src / WEIGHTS_FILE):
        if not p.is_file():
            inside = [
                str(src / d) for d in ("best", "checkpoint") if (src / d / CONFIG_FILE).is_file()
            ]
            hint = f"; {src} is a training run: load {' or '.join(inside)}" if inside else ""
            raise FileNotFoundError(f"{argument}: {p} not found (not a vvloc checkpoint{hint})")
