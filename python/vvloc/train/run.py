"""A run folder's life: :func:`train` (a new run or ``--resume``, under :func:`run_lock`),
:func:`check_run_folder` (what a folder may hold before a run writes there) and the clean-up of
a new run that failed before its first epoch was saved."""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import NoReturn

import yaml

from vvloc._io import list_entries
from vvloc.data.sampling import (
    inside_folder,
)
from vvloc.train.config import RESUMABLE_CHANGES, TrainConfig
from vvloc.train.trainer import Trainer


def _same_run(cfg: TrainConfig, out: Path) -> bool:
    """Whether ``out/train_config.yaml`` is ``cfg``'s, up to how a run is executed
    (:data:`RESUMABLE_CHANGES`): the folder is this config's run, stopped before its first
    ``trainer_state.pt``."""
    try:
        saved = TrainConfig.from_yaml(out / "train_config.yaml").to_dict()
    except (OSError, ValueError, TypeError, yaml.YAMLError):
        return False
    current = cfg.to_dict()
    return all(saved.get(k) == v for k, v in current.items() if k not in RESUMABLE_CHANGES)


#: What a run stopped before its first ``trainer_state.pt`` may leave besides its config:
#: ``best/`` and ``checkpoint/`` of its first epoch and hidden half-written files and folders.
_STOPPED_RUN_LEFTOVERS = ("checkpoint", "best")


_STOPPED_RUN_HIDDEN = (".checkpoint.", ".best.", ".trainer_state.pt.", ".log.jsonl.")


def check_run_folder(cfg: TrainConfig, out: Path, resume: bool) -> None:
    """Refuse a run folder ``out`` that would lose or corrupt data: ``ValueError`` when it is
    or lies inside a dataset of ``cfg`` (the run's folders would read as sessions);
    ``FileExistsError``, without ``resume``, when it already holds a run (``--resume``
    continues it) or anything else. The one exception is a run of the same config stopped
    before its first ``trainer_state.pt`` (its ``train_config.yaml``, its first epoch's
    ``checkpoint/`` and ``best/``, hidden half-written files): a new run starts it again,
    replacing them."""
    roots = [cfg.dataset, *(e["dataset"] for e in cfg.extra_datasets)]
    roots += [e["dataset"] for e in cfg.val_loops]
    for root in roots:
        if inside_folder(out, root):
            raise ValueError(
                f"--out: {out} is or lies inside the dataset {root}; write the run to a folder "
                "of its own (e.g. runs/<name>)"
            )
    if resume or not out.is_dir():
        return
    if (out / "trainer_state.pt").exists():
        raise FileExistsError(
            f"{out} already holds a training run: pass --resume to continue it, "
            "or choose another --out"
        )
    found = sorted(p.name for p in out.iterdir())
    if _same_run(cfg, out):
        found = [
            n
            for n in found
            if n != "train_config.yaml"
            and n not in _STOPPED_RUN_LEFTOVERS
            and not n.startswith(_STOPPED_RUN_HIDDEN)
        ]
    if found:
        raise FileExistsError(
            f"--out: {out} is not empty ({list_entries(found)}) and holds no run of this config "
            "to resume (no trainer_state.pt); a new run would replace its checkpoint/, best/, "
            "train_config.yaml and log.jsonl: choose a new or empty folder (or delete the "
            "folder to start this run again)"
        )


def train(
    config: str | os.PathLike[str] | TrainConfig,
    out_dir: str | os.PathLike[str],
    resume: bool = False,
    progress: bool = True,
) -> Trainer:
    """Train (or resume) a model from a YAML config path or a :class:`TrainConfig`.

    ``out_dir`` is the run's folder: a new run needs it missing or empty, or holding what a
    run of the same config stopped before its first ``trainer_state.pt`` left
    (:func:`check_run_folder`; a run writes ``checkpoint/``, ``best/``, ``train_config.yaml``
    and ``log.jsonl`` there and replaces its own); ``resume`` needs the ``trainer_state.pt`` of
    a run there. It must lie outside every dataset the config reads. Both are checked before
    any dataset is rendered or opened. A new run into a new or empty folder that fails (or is
    interrupted) before its first epoch is saved removes what it wrote there."""
    if not isinstance(config, (TrainConfig, str, os.PathLike)):
        raise TypeError(
            f"config: expected a YAML config path or a TrainConfig (TrainConfig.from_dict for a "
            f"dict), got {type(config).__name__}"
        )
    cfg = config if isinstance(config, TrainConfig) else TrainConfig.from_yaml(config)
    if isinstance(config, TrainConfig):
        cfg.validate()  # built directly, it was never checked (from_yaml checks)
    out = Path(out_dir)
    check_run_folder(cfg, out, resume)
    if resume and not out.is_dir():
        _no_run_to_resume(out, cfg)
    created = not out.exists()
    fresh = created or not any(out.iterdir())
    out.mkdir(parents=True, exist_ok=True)  # to lock it
    try:
        with run_lock(out):
            check_run_folder(cfg, out, resume)  # again, now that no other run can change it
            if resume and not (out / "trainer_state.pt").is_file():  # before any rendering
                _no_run_to_resume(out, cfg)
            trainer = Trainer(cfg, out_dir)
            if resume and not trainer.resume():  # removed between the check and the lock
                raise FileNotFoundError(f"--resume: no run to resume in {out_dir}")
            trainer.fit(progress=progress)
    except BaseException:
        if fresh:  # a run that failed before its first epoch was saved leaves nothing behind
            _remove_unsaved_run(out)
        if created and not any(out.iterdir()):  # a run refused before any work leaves no folder
            out.rmdir()
        raise
    return trainer


def _remove_unsaved_run(out: Path) -> None:
    """Remove what a new run into the empty folder ``out`` wrote before it failed in its first
    epoch: its ``train_config.yaml`` and hidden half-written files, when no epoch was saved (no
    ``trainer_state.pt``, ``checkpoint/``, ``best/`` or ``log.jsonl``). Left there, the config
    refused a corrected config's run into the same folder ("holds no run of this config");
    anything else in the folder is left as it is."""
    names = {p.name for p in out.iterdir()}
    if names & {"trainer_state.pt", "log.jsonl", *_STOPPED_RUN_LEFTOVERS}:
        return
    for name in names:
        path = out / name
        if name == "train_config.yaml" or name.startswith(_STOPPED_RUN_HIDDEN):
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
            else:
                with contextlib.suppress(OSError):
                    path.unlink()


def _no_run_to_resume(out: Path, cfg: TrainConfig) -> NoReturn:
    """``FileNotFoundError`` for ``--resume`` into ``out``, which holds no ``trainer_state.pt``
    (a run of ``cfg`` stopped in its first epoch left its ``train_config.yaml``: said so)."""
    if not out.is_dir() or not any(out.iterdir()):
        what = "drop --resume to start one"
    elif _same_run(cfg, out):
        what = (
            "this config's run stopped before its first epoch ended: drop --resume to start it "
            "again"
        )
    else:
        what = "the folder holds other files: choose another --out to start one"
    raise FileNotFoundError(f"--resume: no run to resume in {out} (no trainer_state.pt); {what}")


@contextlib.contextmanager
def run_lock(out: Path) -> Iterator[None]:
    """Hold the run folder ``out`` (it exists) for one training process: an exclusive
    ``flock`` on the folder itself, so no file is left behind and a killed process lets go at
    once. A second ``vvloc train`` into the same folder (a ``--resume`` started while a run
    goes on) is refused with ``ValueError`` instead of training the same epochs twice and
    renaming the same checkpoints. Where ``fcntl`` is missing (Windows) nothing is locked."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not a platform vvloc builds for
        yield
        return
    fd = os.open(out, os.O_RDONLY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ValueError(
                f"--out: another process is training into {out}; wait for it to end (then "
                "--resume continues its run), or choose another --out"
            ) from None
        yield
    finally:
        os.close(fd)  # releases the lock
