"""What resuming a run reads and checks: its ``trainer_state.pt``, loaded without running code
(:func:`load_trainer_state`), and whether the config asked for may continue it
(:func:`check_same_run`). ``Trainer.resume`` checks the data and restores the state."""

from __future__ import annotations

import logging
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from vvloc.train.config import RESUMABLE_CHANGES, TrainConfig
from vvloc.train.data import _without_dataset_paths

log = logging.getLogger("vvloc.train")


def _state_globals() -> list[Any]:
    """What a trainer state holds besides tensors and plain Python values, for ``torch.load``'s
    ``weights_only`` unpickler: numpy arrays and scalars (the sampler's hard pool and
    exclusions, figures of the best epoch) of bool and numeric dtypes, their reconstructors
    under numpy 2's module name and numpy 1's (a run saved under either resumes under the
    other)."""
    core = getattr(np, "_core", None) or np.core  # numpy 2 / numpy 1
    rec, scalar = core.multiarray._reconstruct, core.multiarray.scalar
    names = [
        (f, f"numpy.{m}.multiarray.{f.__name__}") for f in (rec, scalar) for m in ("core", "_core")
    ]
    codes = "?" + np.typecodes["AllInteger"] + np.typecodes["AllFloat"]
    dtypes = list(dict.fromkeys(type(np.dtype(c)) for c in codes))  # numpy.dtypes.Int64DType, ...
    return [rec, scalar, *names, np.ndarray, np.dtype, *dtypes, bytes]


def _unreadable_state(e: BaseException) -> str:
    """Why ``torch.load(weights_only=True)`` refused a trainer state, in a few words: the
    Python object a crafted file names, the unpickler's complaint about a damaged one, or a
    file that ends early (an empty ``EOFError``, where the unrestricted loader said "Ran out of
    input"; a cut old-style pickle, ``struct.error``)."""
    import struct

    text = str(e)
    if isinstance(e, (EOFError, struct.error)) or "truncated" in text or not text.strip():
        return "the file ends early (truncated?)"
    if "Weights only load failed" not in text:
        return text.split(". ")[0]
    # torch says "Unsupported global: GLOBAL x.y", "unsupported GLOBAL x.y whose module x is
    # blocked" or "got <class 'x.y'>" for an object it does not build
    named = re.search(r"GLOBAL ([\w.]+)|got <class '([\w.]+)'>", text)
    if named:
        what = next(g for g in named.groups() if g)
        return (
            f"it names {what}, which no trainer state holds: not loaded, as unpickling it "
            "could run code"
        )
    detail = text.split("WeightsUnpickler error:", 1)[-1].strip().split("\n")[0]
    return f"not a pickle torch wrote ({detail.rstrip('.')})"


def load_trainer_state(path: Path) -> dict[str, Any]:
    """``torch.load`` of a run's ``trainer_state.pt``: ``ValueError`` naming the file when it
    is truncated (a disk that filled, a copy cut short) or not a trainer state; torch says
    ``EOFError`` (or ``pickle data was truncated``) without the file. Read with
    ``weights_only``: a file that names any other Python object (pickle can call any function
    while it loads) is refused without running it."""
    import pickle
    import struct

    try:
        with torch.serialization.safe_globals(_state_globals()):
            state = torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, EOFError, pickle.UnpicklingError, struct.error) as e:
        why = _unreadable_state(e)
    else:
        if isinstance(state, dict) and "config" in state:
            return state
        why = f"a {type(state).__name__} without the run's config"
    raise ValueError(
        f"{path}: not a readable trainer state ({why}): this run cannot be resumed; start a new "
        "run into another folder (init_checkpoint: its checkpoint/ to keep its weights)"
    )


def check_same_run(
    old: dict[str, Any], state: Mapping[str, Any], cfg: TrainConfig, state_path: Path, out: Path
) -> int | None:
    """Refuse (``ValueError`` naming ``state_path``, the run in ``out``) to resume the run of
    config ``old`` (``TrainConfig.to_dict()`` of the run, its trainer ``state``) under ``cfg``
    when they differ in more than :data:`RESUMABLE_CHANGES`, where the datasets lie (checked by
    their contents: ``Trainer.resume``) and ``stage2_epochs`` grown before the head stage.
    Returns the run's ``Trainer.joint_stopped``: the epoch its joint stage stopped early at, or
    None."""
    # Extending a run (more joint epochs) is allowed; any other change is a different run.
    # how the run is executed may change: workers, threads and device (the last two
    # can move the weights' last bits, as on another machine)
    free = ("stage2_epochs", *RESUMABLE_CHANGES)
    saved_cfg = {k: v for k, v in old.items() if k not in free}
    current = {k: v for k, v in cfg.to_dict().items() if k not in free}
    # where the datasets lie is checked by their contents (Trainer._check_same_data)
    saved_cfg, current = _without_dataset_paths(saved_cfg), _without_dataset_paths(current)
    if saved_cfg != current:
        differ = sorted(
            k for k in set(saved_cfg) | set(current) if saved_cfg.get(k) != current.get(k)
        )
        values = "; ".join(
            f"{k}: {saved_cfg.get(k)!r:.60} in the run, {current.get(k)!r:.60} now" for k in differ
        )
        raise ValueError(
            f"{state_path}: the run in {out} was started with another config "
            f"(differing: {', '.join(differ)}; {values}); use a new --out directory or the "
            f"same config (a resume may change {', '.join(RESUMABLE_CHANGES)} and grow "
            "stage2_epochs)"
        )
    for key in ("threads", "device"):
        if old.get(key) != getattr(cfg, key):
            log.warning(
                "resuming with %s %r (the run started with %r): the weights may differ in "
                "their last bits from an uninterrupted run",
                key,
                getattr(cfg, key),
                old.get(key),
            )
    if old["stage2_epochs"] != cfg.stage2_epochs and (
        cfg.stage2_epochs < old["stage2_epochs"]
        or int(state["epoch"]) > old["stage1_epochs"] + old["stage2_epochs"]
    ):
        raise ValueError(
            f"{state_path}: stage2_epochs can only grow, and only before the head "
            f"stage (run in {out}: {old['stage2_epochs']} joint epochs, at epoch "
            f"{state['epoch']}; asked for {cfg.stage2_epochs})"
        )
    joint_stopped = state.get("joint_stopped")
    best = state.get("best")
    if (
        joint_stopped is None
        and old["stage2_epochs"] != cfg.stage2_epochs
        and cfg.patience is not None
        and best is not None
        and int(state["epoch"]) == old["stage1_epochs"] + old["stage2_epochs"]
        and int(state["epoch"]) - int(best["epoch"]) >= cfg.patience
    ):
        # its last joint epoch skipped the patience check (no joint epoch was left to
        # stop); a run that had asked for more epochs from the start would have stopped
        # there, so an extension is refused as for one that did stop
        joint_stopped = int(state["epoch"])
    if joint_stopped is not None and old["stage2_epochs"] != cfg.stage2_epochs:
        raise ValueError(
            f"{state_path}: the run in {out} stopped its joint stage early "
            f"after epoch {joint_stopped} (patience {cfg.patience}); growing "
            "stage2_epochs does not restart it: start a new run (another --out) with "
            f"init_checkpoint: {out}"
        )
    return joint_stopped
