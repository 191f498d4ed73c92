"""Which hardware produced a checkpoint's weights, and in how long: its training record.

``vvloc train`` writes ``training.json`` beside ``model.safetensors`` in every checkpoint it
saves (``checkpoint/`` and ``best/``), ``vvloc train`` prints its summary when it ends, and
``vvloc eval`` reports it (``trained_on`` in the meta, the runs under ``training``). The file
(format ``vvloc.training``, version 1) is a JSON object::

    {"format": "vvloc.training", "version": 1,
     "weights_hash": "<VVLocNet.weights_hash() of the weights it describes>",
     "runs": [<run>, ...]}          # oldest first: the init_checkpoint chain, then this run

A *run* is one ``vvloc train --out DIR`` run, resumed or not::

    {"out": "runs/synth-small",           # --out as given (relative to where training ran)
     "cwd": "/home/me/vvloc",             # where training ran (absent before 2026-12-05)
     "config": {...},                     # the resolved TrainConfig (paths as given)
     "epochs": 29,                        # the config's epochs: stage 1 + stage 2 + head stage
     "epochs_run": 29,                    # epochs trained when this file was written
     "weights_epoch": 27,                 # the epoch (1-based) these weights are from
     "complete": true,                    # the run has ended: epochs_run == epochs, or
                                          # patience stopped its joint stage (then also
                                          # "joint_stopped_early": <its last joint epoch>)
     "seconds": 4021.3,                   # wall time of the run, s (null: not all measured)
     "processes": [<process>, ...],       # one per process that trained it (resume: several)
     "init_weights_hash": "<hash of the init_checkpoint's weights>" | null,
     "rigs": [[<camera>, ...], ...],      # the rigs it trained on: each the cameras in
                                          # image order as a rig.json has them
                                          # (Camera.to_json), the dataset's first, then those
                                          # of extra_datasets that differ; absent in records
                                          # written before 2026-12-05
     "session_digests": ["<16 hex>", ...]}  # session_digest of each session it trained on,
                                          # in any folder: eval knows them in a copy (absent
                                          # in records written before 2026-12-06)

    <process> = {"hardware": "x86_64, 2 cores", "device": "cpu" | "cuda" (torch's type),
                 "device_name": null | "NVIDIA H200", "torch_threads": 2,
                 "torch": "2.5.1", "vvloc": "0.1.0",
                 "cpu": "AMD EPYC, family 25 model 17, avx512",   # cpu_model()
                 "torch_cpu_capability": "AVX512",  # the ATen kernels torch dispatched to
                 "libraries": {"numpy": "2.4.6", "scipy": "1.17.1", ...},  # libraries()
                 "epochs": [0, 29],      # epochs done when it started and at its last save
                 "seconds": 4021.3}      # its set-up (rendering and opening the datasets,
                                         # building the model, resuming) and its epochs,
                                         # validation and saving included (null: not measured)

``cpu``, ``torch_cpu_capability`` and ``libraries`` (absent in records written before
2026-12-03) say what a retraining must match to give the same bytes: the trainer is
deterministic on one machine's CPU (not on CUDA, :mod:`vvloc.train`), but the same code,
config and data trained with other CPU kernels
(another processor, or torch limited to other instructions) give other weights from the first
epoch on (`models/synth-small-v3/MODEL_CARD.md`, "Retraining on another machine").

``seconds`` is the time to *produce* the weights with the recipe: once the run has ended, the
record of ``best/`` too counts the whole run (its ``weights_epoch`` may be earlier than the
last epoch, but the later epochs were needed to select it; while the run goes on, it stops at
its own epoch). It is measured by ``Trainer`` (set-up, resume, and ``fit``'s epochs,
validation and saves); a process stopped between two saves loses the time since its last
save. On resume the run's record so far is read from its ``checkpoint/``; a checkpoint of an
earlier vvloc has none, and the run's processes then begin with ``{"epochs": [0, E],
"seconds": null}`` (not measured). An init checkpoint without a record (written outside a run
or by an earlier vvloc, or whose record was ignored) appears as one ``{"recorded": false,
"checkpoint": "<its resolved folder>", "weights_hash": ...}`` run.

This module imports no torch: the CLI and the report use it before (or without) a model.
"""

from __future__ import annotations

import importlib.metadata
import json
import math
import os
import platform
from pathlib import Path
from typing import Any

import numpy as np

from vvloc._io import atomic_write

__all__ = [
    "TRAINING_FILE",
    "TRAINING_FORMAT",
    "TRAINING_VERSION",
    "cpu_model",
    "describe_cpuinfo",
    "hardware",
    "json_safe",
    "libraries",
    "read_record",
    "record_json",
    "rendered_plan",
    "session_digest",
    "summarize",
    "validate_record",
    "write_record",
]

#: The training record's file name inside a checkpoint folder.
TRAINING_FILE = "training.json"
TRAINING_FORMAT = "vvloc.training"
TRAINING_VERSION = 1


def hardware() -> str:
    """This machine, as reports name it: ``"<processor or architecture>, <N> cores"``, N the
    cores this process may run on (its CPU affinity where the platform has one)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 0
    return f"{_processor()}, {cores} cores"


def _processor() -> str:
    """The platform's word for the processor, or the architecture, or ``"unknown"``."""
    return platform.processor() or platform.machine() or "unknown"


#: The libraries whose versions a training record names (besides torch): the ones whose
#: arithmetic or random streams the trainer's results may depend on.
RECORDED_LIBRARIES = ("numpy", "scipy", "pillow", "safetensors")


def cpu_model() -> str:
    """This machine's processor as the OS reports it, e.g. ``"AMD EPYC, family 25 model 17,
    avx512"``: :func:`describe_cpuinfo` of Linux's ``/proc/cpuinfo`` (elsewhere, of nothing)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        text = ""
    return describe_cpuinfo(text)


def describe_cpuinfo(text: str) -> str:
    """The first processor of a Linux ``/proc/cpuinfo`` text: its model name, x86 family and
    model numbers when given, and the widest x86 vector extension it has (``avx512`` or
    ``avx2``; none named otherwise), comma-separated. Without a model name the platform's word
    for the processor stands first (as in :func:`hardware`)."""
    if not isinstance(text, str):
        raise TypeError(f"text: expected the text of /proc/cpuinfo, got {type(text).__name__}")
    fields: dict[str, str] = {}
    for line in text.strip().split("\n\n")[0].splitlines():
        key, sep, value = line.partition(":")
        if sep:
            fields.setdefault(key.strip(), value.strip())
    parts = [fields.get("model name") or _processor()]
    if "cpu family" in fields and "model" in fields:
        parts.append(f"family {fields['cpu family']} model {fields['model']}")
    flags = set(fields.get("flags", "").split())
    widest = next((f for f in ("avx512f", "avx2") if f in flags), None)
    if widest:
        parts.append(widest.removesuffix("f"))
    return ", ".join(parts)


def libraries() -> dict[str, str | None]:
    """The installed versions of :data:`RECORDED_LIBRARIES` (None: not installed)."""
    versions: dict[str, str | None] = {}
    for name in RECORDED_LIBRARIES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def json_safe(value: Any) -> Any:
    """``value`` (JSON-like: dicts, lists, str, numbers, None) with every non-finite float
    replaced by None and numpy scalars made Python ones, so that it writes as standard JSON."""
    if isinstance(value, np.generic) and isinstance(value.item(), bool | int | float | str):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value


def _seconds_ok(value: Any) -> bool:
    """A run's or process's ``seconds``: null, or a finite number >= 0."""
    return value is None or (
        isinstance(value, int | float)
        and not isinstance(value, bool)
        and math.isfinite(value)
        and value >= 0
    )


def session_digest(timestamps: Any, poses: Any, floors: Any, plan: Any = None) -> str:
    """The fingerprint of a session's frames, whatever folder holds them: the first 16 hex
    digits of a SHA-256 over the frame count, the ``(N,)`` int64 timestamps (µs), the
    ``(N, 3)`` float64 poses (x, y in m, yaw in rad), the ``(N,)`` int64 floors and, for a
    session ``vvloc sim`` rendered, its ``plan`` (:func:`rendered_plan`: the same drive under
    another light is another session). A copy of the session, or a conversion that keeps every
    frame (resized images), has the same."""
    import hashlib

    import numpy as np

    ts = np.ascontiguousarray(timestamps, dtype="<i8")
    h = hashlib.sha256(f"{len(ts)};".encode())
    h.update(ts.tobytes())
    h.update(np.ascontiguousarray(poses, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(floors, dtype="<i8").tobytes())
    if plan is not None:
        h.update(json.dumps(plan, sort_keys=True).encode())
    return h.hexdigest()[:16]


def rendered_plan(root: str | os.PathLike[str], session: str) -> dict[str, Any] | None:
    """The lighting and seed ``vvloc sim`` rendered ``session`` of the dataset ``root`` with
    (its ``session.json``, which ``vvloc convert`` keeps), or None for a session without them
    (data of one's own)."""
    try:
        meta = json.loads(
            (Path(root) / "sessions" / session / "session.json").read_text(encoding="utf-8-sig")
        )
    except (OSError, ValueError):
        return None
    if not isinstance(meta, dict) or "lighting" not in meta or "seed" not in meta:
        return None
    return {"lighting": meta["lighting"], "seed": meta["seed"]}


def _is_digest(value: Any) -> bool:
    return (
        isinstance(value, str) and len(value) == 16 and all(c in "0123456789abcdef" for c in value)
    )


def validate_record(record: Any, source: str) -> dict[str, Any]:
    """``record`` if it is a training record of this format and version (see the module
    docstring), else ``ValueError`` naming ``source`` (a path, for the message)."""
    if not isinstance(record, dict):
        raise ValueError(f"{source}: expected a JSON object, got {type(record).__name__}")
    version = record.get("version")
    if (
        record.get("format") != TRAINING_FORMAT
        or type(version) is not int  # True and 1.0 equal 1
        or version != TRAINING_VERSION
    ):
        raise ValueError(
            f"{source}: expected format {TRAINING_FORMAT!r} version {TRAINING_VERSION}, got "
            f"{record.get('format')!r} version {record.get('version')!r}"
        )
    runs = record.get("runs")
    if not isinstance(runs, list) or not all(isinstance(r, dict) for r in runs):
        raise ValueError(f"{source}: 'runs' must be a list of objects")
    for k, run in enumerate(runs):
        procs = run.get("processes", [])
        if not isinstance(procs, list) or not all(isinstance(p, dict) for p in procs):
            raise ValueError(f"{source}: runs[{k}].processes must be a list of objects")
        if not all(_seconds_ok(x.get("seconds")) for x in [run, *procs]):
            raise ValueError(f"{source}: runs[{k}]: 'seconds' must be a number >= 0 or null")
        digests = run.get("session_digests", [])
        if not isinstance(digests, list) or not all(_is_digest(d) for d in digests):
            raise ValueError(
                f"{source}: runs[{k}].session_digests must be a list of 16 hex digits each"
            )
        if "rigs" in run:
            from vvloc.data.frame import Camera  # here: vvloc.data loads scipy, the CLI must not

            where, rigs = f"{source}: runs[{k}].rigs", run["rigs"]
            if not isinstance(rigs, list) or not rigs:
                raise ValueError(f"{where}: expected a non-empty list of rigs")
            for r, rig in enumerate(rigs):
                try:
                    if not isinstance(rig, list) or not rig:
                        raise ValueError("expected a non-empty list of camera entries")
                    cams = [Camera.from_json(c) for c in rig]
                    if len({(c.width, c.height) for c in cams}) > 1:
                        raise ValueError("cameras of more than one image size")
                except (TypeError, ValueError, AttributeError) as e:
                    raise ValueError(f"{where}[{r}]: {e}") from None
    if not isinstance(record.get("weights_hash"), str):
        raise ValueError(f"{source}: 'weights_hash' must be a string")
    return record


def read_record(path: Path) -> dict[str, Any]:
    """The training record in the file ``path``, validated (:func:`validate_record`);
    ``ValueError`` naming the file when it is not JSON or not a record of this format."""
    try:
        raw = json.loads(Path(path).read_bytes().decode("utf-8"))
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not a UTF-8 text file ({e})") from e
    except (json.JSONDecodeError, RecursionError) as e:  # RecursionError: too deep nesting
        raise ValueError(f"{path}: not JSON ({e})") from e
    return validate_record(raw, str(path))


def record_json(weights_hash: str, runs: list[dict[str, Any]]) -> str:
    """The text of the training record of the weights with fingerprint ``weights_hash`` (see
    the module docstring) and ``runs``: standard JSON (non-finite floats become null:
    :func:`json_safe`). ``ValueError`` for ``runs`` that :func:`read_record` would refuse
    (nothing is written then), ``TypeError`` for a ``weights_hash`` that is not a str."""
    if not isinstance(weights_hash, str):
        raise TypeError(f"weights_hash: expected a str, got {type(weights_hash).__name__}")
    if not isinstance(runs, list):
        raise TypeError(f"runs: expected a list of run objects, got {type(runs).__name__}")
    record = {
        "format": TRAINING_FORMAT,
        "version": TRAINING_VERSION,
        "weights_hash": weights_hash,
        "runs": json_safe(runs),
    }
    validate_record(record, "runs")
    return json.dumps(record, indent=2, allow_nan=False)


def write_record(path: Path, weights_hash: str, runs: list[dict[str, Any]]) -> None:
    """Write :func:`record_json`'s text to ``path``, atomically."""
    text = record_json(weights_hash, runs)
    with atomic_write(path) as f:
        f.write(text)


def _where(process: dict[str, Any]) -> str:
    device = process.get("device", "?")
    name = process.get("device_name")
    return f"{name} ({device})" if name else str(device)


def summarize(record: dict[str, Any] | None) -> str:
    """One line for a report: where and in how long the runs of ``record`` (a training record,
    or just its ``{"runs": [...]}``) produced the weights, e.g. ``"cpu on x86_64, 2 cores;
    4 runs, 88.4 min (67.0 + 4.2 + 11.4 + 5.8)"`` (minutes of wall time, oldest run first).
    ``None`` or ``{}`` gives ``"no training record for these weights"``."""
    if not record:
        return "no training record for these weights"
    runs = record.get("runs") or []
    recorded = [r for r in runs if r.get("recorded", True)]
    procs = [p for r in recorded for p in r.get("processes", [])]
    where = sorted({f"{_where(p)} on {p['hardware']}" for p in procs if "hardware" in p})
    minutes = [float(r["seconds"]) / 60.0 for r in recorded if r.get("seconds") is not None]
    line = f"{' and '.join(where) or 'unknown hardware'}; {_count(len(recorded), 'run')}"
    if minutes:
        parts = " + ".join(f"{m:.1f}" for m in minutes)
        line += f", {sum(minutes):.1f} min" + (f" ({parts})" if len(minutes) > 1 else "")
    if len(minutes) < len(recorded):
        line += f", time not measured for {_count(len(recorded) - len(minutes), 'run')}"
    if len(runs) > len(recorded):
        line += ", after an init checkpoint without a record"
    unfinished = sum(not r.get("complete", True) for r in recorded)
    if unfinished:
        line += f" ({_count(unfinished, 'run')} unfinished)"
    return line


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"
