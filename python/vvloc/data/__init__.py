"""Datasets: the vvloc format, NCLT and Oxford RobotCar readers, triplet sampling, training
augmentation, perturbations.

``open_dataset(path)`` opens any of the three layouts lazily; ``ds.session(name)[i]`` is a
:class:`Frame` (images (M, 3, H, W) uint8, K (M, 3, 3), cam_to_ego (M, 4, 4), pose (x, y, yaw),
t, floor). Frames and signs follow DESIGN.md §3.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from vvloc._io import symlink_loop
from vvloc.data import perturb
from vvloc.data.augment import PhotometricAugment
from vvloc.data.convert import convert_dataset, select_keyframes
from vvloc.data.frame import Camera, Dataset, Frame, Session, has_image_content
from vvloc.data.nclt import is_nclt, open_nclt
from vvloc.data.oxford import is_oxford, open_oxford
from vvloc.data.sampling import EvalSplit, TripletSampler, evaluation_split
from vvloc.data.vvloc_format import DatasetFormatError, DatasetWriter, SessionWriter, open_vvloc

FORMATS = ("auto", "vvloc", "nclt", "oxford")
#: The raw formats, as messages name a folder of them ("... is an NCLT raw folder").
RAW_FOLDER = {"nclt": "an NCLT raw folder", "oxford": "an Oxford RobotCar raw folder"}


def detect_format(path: str | os.PathLike[str], format: str = "auto") -> str:
    """The format of the dataset folder ``path``: ``vvloc``, ``nclt`` or ``oxford``.

    ``format`` other than ``auto`` is checked and returned as is. Raises ``ValueError`` for an
    unknown format, ``FileNotFoundError`` / ``DatasetFormatError`` for a folder that is missing
    or holds none of them.
    """
    root = Path(path)
    if format not in FORMATS:
        raise ValueError(f"format: expected one of {FORMATS}, got {format!r}")
    if root.exists() and not root.is_dir():
        raise NotADirectoryError(f"{root}: is a file, not a dataset folder")
    if not root.is_dir():
        raise FileNotFoundError(f"{symlink_loop(root) or root}: no such dataset folder")
    if format != "auto":
        return format
    if (root / "rig.json").is_file():
        return "vvloc"
    if is_nclt(root):
        return "nclt"
    if is_oxford(root):
        return "oxford"
    raise DatasetFormatError(
        f"{root}: not a dataset: expected rig.json (vvloc), <date>/lb3 + cam_params (NCLT) "
        f"or <session>/gps/ins.csv (Oxford RobotCar)"
    )


def open_dataset(path: str | os.PathLike[str], format: str = "auto", **kwargs: Any) -> Dataset:
    """Open a dataset folder lazily: a vvloc-format dataset (``rig.json``), an NCLT raw folder or
    an Oxford RobotCar raw folder. ``kwargs`` go to the format's reader (``open_nclt``,
    ``open_oxford``; ``open_vvloc`` takes ``image_size``). Raises ``FileNotFoundError`` /
    ``DatasetFormatError`` naming the problem."""
    root = Path(path)
    format = detect_format(root, format)
    if format == "vvloc":
        if set(kwargs) - {"image_size"}:
            raise TypeError(f"the vvloc format takes one option, image_size, got {sorted(kwargs)}")
        return open_vvloc(root, **kwargs)
    if format == "nclt":
        return open_nclt(root, **kwargs)
    return open_oxford(root, **kwargs)


__all__ = [
    "RAW_FOLDER",
    "Camera",
    "Dataset",
    "DatasetFormatError",
    "DatasetWriter",
    "EvalSplit",
    "Frame",
    "PhotometricAugment",
    "Session",
    "SessionWriter",
    "TripletSampler",
    "convert_dataset",
    "detect_format",
    "evaluation_split",
    "has_image_content",
    "open_dataset",
    "open_nclt",
    "open_oxford",
    "open_vvloc",
    "perturb",
    "select_keyframes",
]
