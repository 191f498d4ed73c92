"""A training run's folder on disk, written so that a process stopped at any point leaves it
readable: the epoch log ``log.jsonl`` (one JSON object per line, a torn last line cut off) and
the model folders ``checkpoint/`` and ``best/``, each swapped in whole."""

from __future__ import annotations

import json
import os
import secrets
import shutil
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from vvloc.evaluate import to_jsonable

LOG_FILE = "log.jsonl"


def append_log_line(path: Path, record: Mapping[str, Any]) -> None:
    """Append ``record`` (one epoch's) to the log at ``path`` as one line of strict JSON
    (NaN/inf as null). A torn last line (a process killed or a disk full while it appended one)
    is cut off first: it is no epoch (:func:`logged_epochs`), and the new line must not continue
    it."""
    if path.is_file():
        data = path.read_bytes()
        if data and not data.endswith(b"\n"):
            with open(path, "r+b") as f:
                f.truncate(data.rfind(b"\n") + 1)
    with open(path, "a") as f:
        f.write(json.dumps(to_jsonable(record), allow_nan=False) + "\n")


def logged_epochs(path: Path) -> set[int]:
    """The ``epoch`` values of the log at ``path`` (none when it is missing; a torn or foreign
    line is no epoch)."""
    done: set[int] = set()
    if path.is_file():
        for line in path.read_text().splitlines():
            try:
                done.add(int(json.loads(line)["epoch"]))
            except (ValueError, KeyError, TypeError):
                continue
    return done


def swap_in_folder(folder: Path, write: Callable[[Path], object]) -> None:
    """Replace ``folder`` (``checkpoint/``, ``best/``) as a whole by what ``write(tmp)`` puts
    into a new folder ``tmp``: written into a hidden folder beside it and swapped in by two
    renames, so that a stop never leaves one epoch's weights beside another's calibration or
    record. A stop between the renames leaves the previous folder under a hidden name, which
    :func:`recover_folder` puts back (here first, and on resume)."""
    recover_folder(folder)
    tmp = folder.parent / f".{folder.name}.partial-{secrets.token_hex(6)}"
    try:
        write(tmp)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = folder.parent / f".{folder.name}.old-{secrets.token_hex(6)}"
    if folder.exists():
        os.replace(folder, old)
    os.replace(tmp, folder)
    shutil.rmtree(old, ignore_errors=True)


def recover_folder(folder: Path) -> None:
    """Undo what a stop inside :func:`swap_in_folder` left: remove half-written hidden folders,
    and put the previous folder back where a stop between the two renames took it away."""
    for stale in folder.parent.glob(f".{folder.name}.partial-*"):
        shutil.rmtree(stale, ignore_errors=True)
    olds = sorted(folder.parent.glob(f".{folder.name}.old-*"))
    if olds and not folder.exists():
        os.replace(olds.pop(), folder)
    for old in olds:
        shutil.rmtree(old, ignore_errors=True)
