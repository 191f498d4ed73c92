"""Which hardware produced a checkpoint's weights, and in how long: its training record.

``vvloc train`` writes ``training.json`` beside ``model.safetensors`` in every checkpoint it
saves (``checkpoint/`` and ``best/``), and ``vvloc eval`` puts it in the report. The record
(format ``vvloc.training``, version 1) is a JSON object::

    {"format": "vvloc.training", "version": 1,
     "weights_hash": "<VVLocNet.weights_hash() of the weights it describes>",
     "runs": [<run>, ...]}          # oldest first: the init_checkpoint chain, then this run

A *run* is one ``vvloc train`` run (resumed runs count as one)::

    {"out": "runs/synth-small", "config": {... the resolved TrainConfig ...},
     "hardware": "x86_64, 2 cores", "device": "cpu" | "cuda (NVIDIA H200)",
     "torch": "2.5.1", "vvloc": "0.1.0",
     "epochs_run": 15, "epochs": 15, "weights_epoch": 12, "complete": true,
     "seconds": 4021.3,                        # wall time of the whole run, set-up included (s)
     "init_weights_hash": "<hash of init_checkpoint's weights>" | null}

``seconds`` counts every epoch the run has trained so far, validation and saving included,
plus each process's set-up (rendering missing datasets, opening them, building the model):
the time to *produce* these weights with the recipe, also for ``best/`` (whose
``weights_epoch`` may be earlier than the last epoch). A checkpoint whose ``init_checkpoint``
had no record gets one ``{"recorded": false, "weights_hash": ...}`` entry in its place.

This module imports no torch: the CLI and the report use it before (or without) a model.
"""

from __future__ import annotations

import os
import platform
from typing import Any

__all__ = [
    "TRAINING_FILE",
    "TRAINING_FORMAT",
    "TRAINING_VERSION",
    "hardware",
    "summarize",
    "validate_record",
]

#: The training record's file name inside a checkpoint folder.
TRAINING_FILE = "training.json"
TRAINING_FORMAT = "vvloc.training"
TRAINING_VERSION = 1


def hardware() -> str:
    """This machine, as reports name it: ``"<processor or architecture>, <N> cores"``."""
    return f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores"


def validate_record(record: Any, source: str) -> dict[str, Any]:
    """``record`` if it is a training record of this format and version (see the module
    docstring), else ``ValueError`` naming ``source`` (a path, for the message)."""
    if not isinstance(record, dict):
        raise ValueError(f"{source}: expected a JSON object, got {type(record).__name__}")
    if record.get("format") != TRAINING_FORMAT or record.get("version") != TRAINING_VERSION:
        raise ValueError(
            f"{source}: expected format {TRAINING_FORMAT!r} version {TRAINING_VERSION}, got "
            f"{record.get('format')!r} version {record.get('version')!r}"
        )
    runs = record.get("runs")
    if not isinstance(runs, list) or not all(isinstance(r, dict) for r in runs):
        raise ValueError(f"{source}: 'runs' must be a list of objects")
    if not isinstance(record.get("weights_hash"), str):
        raise ValueError(f"{source}: 'weights_hash' must be a string")
    return record


def summarize(record: dict[str, Any] | None) -> str:
    """One line for a report: the hardware and the wall time of the runs that produced the
    weights, e.g. ``"x86_64, 2 cores (cpu); 4 runs, 88.4 min (67.0 + 4.2 + 11.4 + 5.8)"``.
    ``None`` (a checkpoint without a record) gives ``"not recorded"``."""
    if not record:
        return "not recorded (the checkpoint has no training.json)"
    runs = record["runs"]
    recorded = [r for r in runs if r.get("recorded", True)]
    where = sorted({f"{r.get('hardware', '?')} ({r.get('device', '?')})" for r in recorded})
    minutes = [float(r["seconds"]) / 60.0 for r in recorded if r.get("seconds") is not None]
    line = f"{'; '.join(where) or 'no recorded run'}; {_count(len(recorded), 'run')}"
    if minutes:
        parts = " + ".join(f"{m:.1f}" for m in minutes)
        line += f", {sum(minutes):.1f} min" + (f" ({parts})" if len(minutes) > 1 else "")
    if len(minutes) < len(recorded):
        line += f", time not recorded for {_count(len(recorded) - len(minutes), 'run')}"
    if len(runs) > len(recorded):
        line += f", after {_count(len(runs) - len(recorded), 'earlier run')} not recorded"
    if any(not r.get("complete", True) for r in recorded):
        line += " (a run still in progress)"
    return line


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"
