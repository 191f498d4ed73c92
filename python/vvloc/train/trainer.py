"""The :class:`Trainer`: one run's model, optimizers, sampler and epochs (stages 1-2 and the
head and local stages, see :mod:`vvloc.train`), its checkpoints, logs and provenance records, and
``--resume``."""

from __future__ import annotations

import contextlib
import hashlib
import logging
import math
import os
import random
import signal
import sys
import time
import warnings
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from torch.utils.data import DataLoader
from tqdm import tqdm

import vvloc
from vvloc import geometry
from vvloc._io import atomic_write, list_entries
from vvloc.checkpoints import resolve_checkpoint
from vvloc.data import TripletSampler, open_dataset
from vvloc.data.augment import PhotometricAugment
from vvloc.data.frame import Session, has_image_content
from vvloc.evaluate import to_jsonable
from vvloc.localize.localizer import frames_to_tensors
from vvloc.losses import (
    translation_bias_loss,
    yaw_matching_loss,
)
from vvloc.nets import VVLocNet
from vvloc.nets.heads import NetVLADHead
from vvloc.nets.model import resolve_device
from vvloc.provenance import (
    TRAINING_FILE,
    cpu_model,
    hardware,
    libraries,
    read_record,
    rendered_plan,
    session_digest,
    write_record,
)
from vvloc.train.config import HEAD_FIELDS, HEAD_REFRESH, SELECT_BY, TrainConfig
from vvloc.train.data import (
    TripletFrames,
    _check_session_keys,
    _check_sessions,
    _check_sessions_to_render,
    _dataset_paths,
    _ensure_dataset,
    _hash_session,
    _is_checkpoint,
    _named_paths,
    _no_init_checkpoint,
    _open_named,
)
from vvloc.train.resume import check_same_run, load_trainer_state
from vvloc.train.runfolder import (
    LOG_FILE,
    append_log_line,
    logged_epochs,
    recover_folder,
    swap_in_folder,
)
from vvloc.train.steps import global_losses, near_losses, training_losses
from vvloc.train.validation import (
    _NO_VALIDATION_QUERY,
    loop_validation,
    validation_query_count,
    validation_recall,
)

log = logging.getLogger("vvloc.train")


def _keep_bars() -> bool:
    """Whether an epoch's progress bar stays when the epoch ends: not in a terminal (the next
    epoch's bar takes its place), yes in a captured log, where its last line is the epoch's
    count and losses."""
    return not sys.stderr.isatty()


def pick_device(name: str = "auto") -> torch.device:
    """``"auto"`` → CUDA when available, else CPU; otherwise ``"cpu"``, ``"cuda"`` or
    ``"cuda:N"`` (:func:`vvloc.nets.model.resolve_device`; ``ValueError`` naming ``device``)."""
    return resolve_device(name, argument="device")


def seed_everything(seed: int) -> None:
    """Seed Python, numpy and torch."""
    random.seed(seed)
    np.random.seed(seed % 2**32)  # noqa: NPY002 (seed the legacy global RNG too)
    torch.manual_seed(seed)


class Trainer:
    """Runs (or resumes) a training run described by a :class:`TrainConfig` into ``out_dir``."""

    def __init__(self, cfg: TrainConfig, out_dir: str | os.PathLike[str]) -> None:
        t_setup = time.perf_counter()
        if not isinstance(cfg, TrainConfig):
            raise TypeError(
                f"cfg: expected a TrainConfig (TrainConfig.from_dict for a dict), got "
                f"{type(cfg).__name__}"
            )
        cfg.validate()  # a TrainConfig built directly was never checked (from_dict checks)
        self.cfg = cfg
        self.out = Path(out_dir)
        self.cwd = os.getcwd()  # the config's relative paths are read from here
        self.device = pick_device(cfg.device)
        if cfg.threads:
            torch.set_num_threads(int(cfg.threads))
        seed_everything(cfg.seed)
        _check_sessions_to_render(cfg)  # before minutes of rendering, not after them
        init = None if cfg.init_checkpoint is None else Path(cfg.init_checkpoint)
        if init is not None and not self._state_path().is_file() and not _is_checkpoint(init):
            raise _no_init_checkpoint(init)  # (a resumed run needs it not: its own weights)
        _ensure_dataset(cfg.dataset, cfg.sim)
        self.ds = open_dataset(cfg.dataset)
        cameras, most = len(self.ds.cameras), cfg.model_config().max_cameras
        if cameras > most:  # found here, not at the first step of stage 1
            raise ValueError(
                f"model_overrides.max_cameras: the model holds camera embeddings for {most} "
                f"cameras, {cfg.dataset} has {cameras}"
            )
        extra = []
        for i, e in enumerate(cfg.extra_datasets):
            _ensure_dataset(e["dataset"], e.get("sim"), f"extra_datasets[{i}].")
            opened = _open_named(f"extra_datasets[{i}].dataset", e["dataset"])
            key = f"extra_datasets[{i}].train_sessions"
            _check_sessions(key, e["dataset"], opened, e.get("train_sessions") or [])
            extra.append((opened, e.get("train_sessions")))
            rig, other = self.ds.cameras, extra[-1][0].cameras
            if len(rig) != len(other) or (rig[0].width, rig[0].height) != (
                other[0].width,
                other[0].height,
            ):
                raise ValueError(
                    f"extra_datasets: {e['dataset']} has {len(other)} cameras of "
                    f"{other[0].width}x{other[0].height}, {cfg.dataset} {len(rig)} of "
                    f"{rig[0].width}x{rig[0].height}: one training batch stacks frames of both "
                    "(convert them to one rig size with vvloc convert)"
                )
            names, others = [c.name for c in rig], [c.name for c in other]
            if names != others and sorted(names) == sorted(others):
                # each image slot has a learnt camera embedding: it would learn two cameras
                raise ValueError(
                    f"extra_datasets[{i}].dataset: {e['dataset']} holds the cameras of "
                    f"{cfg.dataset} in another order ({','.join(others)} against "
                    f"{','.join(names)}): a training batch stacks their images slot by slot; "
                    f"reorder them with vvloc convert --cameras {','.join(names)}"
                )
        self._datasets = [self.ds, *(d for d, _ in extra)]
        _check_session_keys(cfg, self.ds)
        self.sampler = TripletSampler(
            self.ds,
            pos_radius=cfg.pos_radius,
            neg_radius=cfg.neg_radius,
            seed=cfg.seed,
            sessions=cfg.train_sessions,
            hard_fraction=cfg.hard_fraction,
            revisit_gap=cfg.revisit_gap,
            extra=extra,
            cross_floor_fraction=cfg.cross_floor_fraction,
            cross_floor_same_session=cfg.cross_floor_same_session,
            anchor_shares=[e.get("anchor_share") for e in cfg.extra_datasets],
        )
        if cfg.val_sessions:  # its sessions exist and hold frames: _check_session_keys
            kept = validation_query_count(
                self.ds, cfg.val_database, cfg.val_sessions, cfg.val_every
            )
            if kept == 0:  # known from the poses: refused before stage 1, not after it
                raise ValueError(_NO_VALIDATION_QUERY.format(cfg=cfg))
        self.loop_sets = []  # (dataset, entry) of val_loops, opened before any epoch
        for k, entry in enumerate(cfg.val_loops):
            loop_ds = _open_named(f"val_loops[{k}].dataset", entry["dataset"])
            _check_sessions(
                f"val_loops[{k}].sessions", entry["dataset"], loop_ds, entry["sessions"]
            )
            self.loop_sets.append((loop_ds, entry))
        self.model = VVLocNet(cfg.model_config()).to(self.device)
        # True while the global head holds no trained weights (the head stage initialises it)
        self.head_untrained = cfg.stage1_epochs + cfg.stage2_epochs == 0
        self.init_weights_hash: str | None = None
        self.earlier_runs: list[dict[str, Any]] = []  # the init checkpoint's training record
        # an init_checkpoint that is gone is not needed to resume a run: its own checkpoint
        # holds the weights and their record (resume() checks that; fit() refuses otherwise)
        self._init_missing: Path | None = None
        if cfg.init_checkpoint is not None:
            init = Path(cfg.init_checkpoint)
            if self._state_path().is_file() and not _is_checkpoint(init):
                self._init_missing = init
            else:
                self._load_init(init)
        self.augment = None if cfg.augment is None else PhotometricAugment.from_dict(cfg.augment)
        self.optimizer = torch.optim.Adam(
            self.model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay
        )
        self.scheduler = torch.optim.lr_scheduler.ExponentialLR(self.optimizer, gamma=cfg.lr_decay)
        self.head_optimizer = torch.optim.Adam(
            self.model.global_head.parameters(), lr=cfg.head_lr, weight_decay=cfg.weight_decay
        )
        self.head_scheduler = torch.optim.lr_scheduler.ExponentialLR(
            self.head_optimizer, gamma=cfg.lr_decay
        )
        self._head_cache: torch.Tensor | None = None  # (N, T, R, C) float16, the head stage's
        self._head_positions: torch.Tensor | None = None  # (N, 3) sampler positions, on device
        local = [*self.model.decoder.parameters(), *self.model.interactor.parameters()]
        self.local_optimizer = torch.optim.Adam(
            local, lr=cfg.local_lr, weight_decay=cfg.weight_decay
        )
        self.local_scheduler = torch.optim.lr_scheduler.ExponentialLR(
            self.local_optimizer, gamma=cfg.lr_decay
        )
        # the local stage's cache: BEVs (N, H, W, C) float16 on the device, poses (N, 3) float64
        self._local_cache: tuple[torch.Tensor, np.ndarray] | None = None
        self.epoch = 0
        self.step = 0
        self.best: dict[str, Any] | None = None  # the validation record of best/, if any
        # the (1-based) last joint epoch when `patience` stopped the joint stage early, else None
        self.joint_stopped: int | None = None
        self._image_fingerprint: str | None = None  # image_fingerprint(), once computed
        self._digests: list[str] | None = None  # _session_digests(), once computed
        self._unlogged: dict[str, Any] | None = None  # a saved epoch's missing log line
        # the training record's processes (vvloc.provenance): earlier ones (from the trainer
        # state on resume), then this one, whose seconds grow with its set-up and epochs
        self.earlier_processes: list[dict[str, Any]] = []
        self.process: dict[str, Any] = {
            "hardware": hardware(),
            "device": self.device.type,
            "device_name": (
                torch.cuda.get_device_name(self.device) if self.device.type == "cuda" else None
            ),
            "torch_threads": torch.get_num_threads(),
            "torch": torch.__version__,
            "vvloc": vvloc.__version__,
            "cpu": cpu_model(),
            "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "libraries": libraries(),
            "epochs": [0, 0],
            "seconds": time.perf_counter() - t_setup,
        }

    def _load_init(self, path: Path) -> None:
        """Copy the weights of ``init_checkpoint`` into the fresh model (refused when its model
        config differs from this run's)."""
        if not _is_checkpoint(path):
            raise _no_init_checkpoint(path)
        path = resolve_checkpoint(path)
        init = VVLocNet.load(path)
        self.init_weights_hash = init.weights_hash()
        self.earlier_runs = list(init.training_record.get("runs", [])) or [
            {"recorded": False, "checkpoint": str(path), "weights_hash": self.init_weights_hash}
        ]
        if init.config_hash() == self.model.config_hash():
            self.model.load_state_dict(init.state_dict())
            self.head_untrained = False
            log.info("initialised from %s", path)
            return
        mine, theirs = self.model.config.to_dict(), init.config.to_dict()
        body = [k for k in mine if k not in HEAD_FIELDS and mine[k] != theirs.get(k)]
        if body:
            raise ValueError(
                f"init_checkpoint: {path} holds model {init.config_hash()}, but this run trains "
                f"model {self.model.config_hash()} (model / model_overrides differ in {body})"
            )
        differ = {k: (theirs.get(k), mine[k]) for k in HEAD_FIELDS if mine[k] != theirs.get(k)}
        if self.cfg.head_epochs < 1:
            raise ValueError(
                f"init_checkpoint: {path} has another global head than this run's "
                f"(checkpoint, run: {differ}); set head_epochs > 0 to train the new head (it is "
                "not in the checkpoint)"
            )
        weights = {k: v for k, v in init.state_dict().items() if not k.startswith("global_head.")}
        missing, unexpected = self.model.load_state_dict(weights, strict=False)
        assert not unexpected and all(k.startswith("global_head.") for k in missing)
        self.head_untrained = True
        log.warning(
            "initialised from %s except the global head (checkpoint, run: %s): the head stage "
            "trains it from a data-driven start",
            path,
            differ,
        )

    def _require_init(self) -> None:
        """Refuse to train or save while ``init_checkpoint`` is missing and no resume has
        brought the run's own weights in (the model would hold a random initialisation)."""
        if self._init_missing is not None:
            raise _no_init_checkpoint(self._init_missing)

    # --- persistence ---------------------------------------------------------------------

    @property
    def checkpoint_dir(self) -> Path:
        """Where the latest model checkpoint lives (``VVLocNet.load`` reads it)."""
        return self.out / "checkpoint"

    @property
    def best_dir(self) -> Path:
        """Where the best checkpoint by validation lives (only with ``val_sessions``)."""
        return self.out / "best"

    def _state_path(self) -> Path:
        return self.out / "trainer_state.pt"

    def _processes(self, include_current: bool = True) -> list[dict[str, Any]]:
        """The processes of this run so far, this one last (with its seconds rounded)."""
        if not include_current:
            return list(self.earlier_processes)
        now = {**self.process, "epochs": [self.process["epochs"][0], self.epoch]}
        now["seconds"] = round(now["seconds"], 1)
        return [*self.earlier_processes, now]

    def record_for(self, weights_epoch: int, include_current: bool = True) -> dict[str, Any]:
        """The training record (``{"runs": [...]}``, :mod:`vvloc.provenance`) of weights this
        run produced at ``weights_epoch`` (1-based), as of now: the init checkpoint's runs,
        then this run (without this process when ``include_current`` is False)."""
        procs = self._processes(include_current)
        seconds = [p["seconds"] for p in procs]
        run = {
            "out": str(self.out),
            "cwd": self.cwd,  # what the config's relative paths are relative to
            "config": self.cfg.to_dict(),
            "epochs": self.cfg.epochs,
            "epochs_run": self.epoch,
            "weights_epoch": weights_epoch,
            "complete": self.epoch >= self.total_epochs,
            "seconds": None if None in seconds else round(sum(seconds), 1),
            "processes": procs,
            "init_weights_hash": self.init_weights_hash,
            # the rigs the networks met (the dataset's, then other ones of extra datasets): a
            # map from another is warned about (vvloc.localize.localizer.check_training_rig)
            "rigs": self._rigs(),
            # each trained session's frames: eval knows a copy of one in another folder
            "session_digests": self._session_digests(),
        }
        if self.joint_stopped is not None:
            run["joint_stopped_early"] = self.joint_stopped
        return {"runs": [*self.earlier_runs, run]}

    def _rigs(self) -> list[list[dict[str, Any]]]:
        """The distinct rigs of the training datasets (``Camera.to_json`` entries in image
        order), ``dataset``'s first."""
        rigs: list[list[dict[str, Any]]] = []
        for ds in self._datasets:
            rig = [c.to_json() for c in ds.cameras]
            if rig not in rigs:
                rigs.append(rig)
        return rigs

    def _session_digests(self) -> list[str]:
        """:func:`vvloc.provenance.session_digest` of each session the sampler trains on
        (sorted, each once). Computed once a trainer: every epoch's record lists them."""
        if self._digests is None:
            digests = set()
            for src, name, _ in self.sampler.slots:
                s = src.session(name)
                plan = rendered_plan(src.root, name)
                digests.add(session_digest(s.timestamps, s.poses, s.floors, plan))
            self._digests = sorted(digests)
        return self._digests

    def _saved_record(self, folder: Path) -> dict[str, Any] | None:
        """``folder``'s ``training.json`` as this trainer wrote it, or None (with a warning when
        it is there but unreadable: the weights stay as they are)."""
        path = folder / TRAINING_FILE
        if not path.is_file():  # weights written by an earlier vvloc
            return None
        try:
            record = read_record(path)
            if not record["runs"]:
                raise ValueError(f"{path}: no runs")
            return record
        except ValueError as e:
            log.warning("%s; left as it is", e)
            return None

    def _rewrite_records(self, include_current: bool = True) -> None:
        """Bring ``training.json`` of ``checkpoint/`` and ``best/`` up to the run as it ended
        (epochs and seconds; for ``best/`` the time to produce *and select* its weights), from
        one snapshot of the processes. The weights, and so the records' ``weights_hash``, are
        unchanged. A ``best/`` whose record names another epoch than the trainer's best (a
        process of before 2026-12-07, which wrote ``best/`` before its state, stopped between
        the two) is left as it is."""
        targets = [(self.checkpoint_dir, self.epoch)]
        if self.best is not None:
            targets.append((self.best_dir, int(self.best["epoch"])))
        runs = self.record_for(self.epoch, include_current)["runs"]
        for folder, weights_epoch in targets:
            record = self._saved_record(folder)
            if record is None:
                continue
            if record["runs"][-1].get("weights_epoch") != weights_epoch:
                log.warning(
                    "%s: its training record names epoch %s, the run's state epoch %d; left "
                    "as it is",
                    folder,
                    record["runs"][-1].get("weights_epoch"),
                    weights_epoch,
                )
                continue
            mine = {**runs[-1], "weights_epoch": weights_epoch}
            write_record(folder / TRAINING_FILE, record["weights_hash"], [*runs[:-1], mine])

    def _best_record_unfinished(self) -> bool:
        """Whether ``best/training.json`` still calls this finished run unfinished: the process
        that finished it stopped before :meth:`fit` brought the records up."""
        record = self._saved_record(self.best_dir) if self.best is not None else None
        return record is not None and not record["runs"][-1].get("complete")

    def _save_model(self, folder: Path, weights_epoch: int, include_current: bool = True) -> None:
        """Write the model with its training record at ``weights_epoch`` (``include_current``
        as in :meth:`record_for`) into ``folder`` (``checkpoint/``, ``best/``) as a whole
        (:func:`~vvloc.train.runfolder.swap_in_folder`)."""
        self.model.training_record = self.record_for(weights_epoch, include_current)
        try:
            swap_in_folder(folder, self.model.save)
        finally:
            self.model.training_record = {}

    def _save_best(self, include_current: bool = True) -> None:
        """Write ``best/`` from the current weights, those of the best epoch (``self.best``),
        with the acceptance calibration of its validation (and where it was measured);
        ``include_current`` as in :meth:`record_for`."""
        assert self.best is not None
        cfg = self.cfg
        self.model.calibration = {
            **self.best["val"]["calibration"],
            "dataset": str(cfg.dataset),
            "database": cfg.val_database,
            "sessions": list(cfg.val_sessions or []),
            "every": int(cfg.val_every),
        }
        try:
            self._save_model(self.best_dir, int(self.best["epoch"]), include_current)
        finally:
            self.model.calibration = {}

    def _mend_best(self) -> None:
        """On resume: when the state names its own epoch as the best and ``best/`` does not hold
        it (the last process stopped between writing the state and ``best/``), write ``best/``
        from the state's weights, which are that epoch's, with the record the stopped process
        would have written. A ``best/`` that holds another epoch than the state's best, which
        the state's weights are not (a state written before 2026-12-07 swapped ``best/`` in
        first), is said and left until an epoch beats the state's best; an unreadable record
        leaves ``best/`` as it is."""
        if self.best is None:
            return
        best = int(self.best["epoch"])
        if (self.best_dir / TRAINING_FILE).is_file():
            record = self._saved_record(self.best_dir)  # None: unreadable, said there
            held = None if record is None else record["runs"][-1].get("weights_epoch")
            if record is None or held == best:
                return
        else:
            held = None
        if best == self.epoch:
            log.info("%s: writing epoch %d's weights, the run's best, there", self.best_dir, best)
            self._save_best(include_current=False)
        elif held is not None:
            log.warning(
                "%s holds epoch %s's weights, the run's state names epoch %d as its best (a stop "
                "between writing best/ and the state): left as it is until an epoch beats it",
                self.best_dir,
                held,
                best,
            )

    def _log_record(self, rec: dict[str, Any]) -> None:
        """Append one epoch's record to ``log.jsonl``
        (:func:`~vvloc.train.runfolder.append_log_line`)."""
        append_log_line(self.out / LOG_FILE, rec)

    def save(self, record: dict[str, Any] | None = None) -> None:
        """Write the model checkpoint (with its training record) and the trainer state
        (atomically, each file); ``record``, the epoch's log line, goes into the state so that
        a resume writes it if the process stopped before its own write."""
        self._require_init()
        self.out.mkdir(parents=True, exist_ok=True)
        self._save_model(self.checkpoint_dir, self.epoch)
        state = {
            "epoch": self.epoch,
            "step": self.step,
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "head_optimizer": self.head_optimizer.state_dict(),
            "head_scheduler": self.head_scheduler.state_dict(),
            "head_untrained": self.head_untrained,
            "local_optimizer": self.local_optimizer.state_dict(),
            "local_scheduler": self.local_scheduler.state_dict(),
            "sampler": self.sampler.state_dict(),
            "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
            # the weights of this epoch, beside its optimizer: checkpoint/ and this file are
            # written one after the other, and a crash between them must not pair another
            # epoch's weights with this state
            "model": {k: v.detach().cpu().clone() for k, v in self.model.state_dict().items()},
            "data": self.data_fingerprint(),
            # a sample of the images the run reads: a moved dataset must show the same ones
            "images": self.image_fingerprint(),
            "best": self.best,
            "joint_stopped": self.joint_stopped,
            "config": self.cfg.to_dict(),
            "record": None if record is None else to_jsonable(record),
        }
        with atomic_write(self._state_path(), "wb") as fb:
            torch.save(state, fb)

    def _read_sessions(self, relabel: Mapping[int, str] | None = None) -> list[tuple[str, Session]]:
        """``(label, session)`` of every session the run reads: the sampler's training
        sessions (in its order, extra datasets' labelled by their folder's name: ``relabel``
        maps an extra dataset's index to the name to use, a renamed folder's former), then the
        validation database and queries, then each ``val_loops`` entry's sessions."""
        read = []
        extra_index = {id(ds): i - 1 for i, ds in enumerate(self._datasets)}  # primary: -1
        for src, name, label in self.sampler.slots:
            if relabel and extra_index[id(src)] in relabel:
                label = f"{relabel[extra_index[id(src)]]}/{name}"
            read.append((label, src.session(name)))
        if self.cfg.val_sessions:
            for name in [self.cfg.val_database, *self.cfg.val_sessions]:
                read.append((f"val:{name}", self.ds.session(name)))
        for k, (loop_ds, entry) in enumerate(self.loop_sets):
            read += [
                (f"val_loops[{k}]:{name}", loop_ds.session(name)) for name in entry["sessions"]
            ]
        return read

    def _check_moved_datasets(
        self,
        moved: dict[str, tuple[str, str]],
        images: str | None,
        relabel: Mapping[int, str] | None,
    ) -> None:
        """On resuming with dataset folders named otherwise than the run's (``moved``: the
        config key, the run's path and this config's), whose sessions passed the data
        fingerprint: ``ValueError`` unless the state's sample of the images (``images``,
        :meth:`image_fingerprint`) is this data's and the run's recorded rigs are the training
        datasets' now; a warning when a folder is another one, not the same one written as
        another path (the run's relative paths taken from where it ran)."""
        named = _named_paths(moved)
        saved = self._saved_record(self.checkpoint_dir)
        last = {} if saved is None else saved["runs"][-1]
        rigs = last.get("rigs")
        why = None
        if images is None:
            why = (
                "its state, written before the trainer sampled the images it reads (2026-12-06), "
                "holds none to compare"
            )
        elif images != self.image_fingerprint(relabel):
            why = "their images differ from the run's (first, middle and last frames)"
        elif rigs is None:
            why = f"{self.checkpoint_dir} records no rig to compare"
        elif rigs != self._rigs():
            why = "the rig (cameras, calibration or image size) differs from the run's"
        if why is not None:
            raise ValueError(
                f"{self._state_path()}: the run in {self.out} was started with other dataset "
                f"folders ({named}); {why}: name the run's folders or use a new --out directory"
            )
        cwd = last.get("cwd")
        ran = cwd if isinstance(cwd, str) else ""  # where the run resolved its relative paths
        if any(
            os.path.realpath(os.path.join(ran, a)) != os.path.realpath(b) for a, b in moved.values()
        ):
            log.warning(
                "resuming the run in %s with other dataset folders (%s): their sessions have "
                "the run's poses, floors and (sampled) images, and the training datasets its rig",
                self.out,
                named,
            )

    def data_fingerprint(self, relabel: Mapping[int, str] | None = None) -> str:
        """``"v2:"`` and a SHA-256 over the sessions the run reads (labels, lengths, poses,
        floors; :meth:`_read_sessions`): what the sampler's frame ids and the validation point
        into, compared on ``--resume``. A session the run does not read (one added to the
        dataset folder for another run) leaves it as it was. (The format of saved states,
        unchanged since 2026-12-06: :func:`vvloc.provenance.session_digest`, which the training
        record lists, also covers the timestamps, and no folder label.)"""
        h = hashlib.sha256()
        for label, sess in self._read_sessions(relabel):
            _hash_session(h, label, sess)
        return f"v2:{h.hexdigest()}"

    def image_fingerprint(self, relabel: Mapping[int, str] | None = None) -> str:
        """A SHA-256 over the images of the first, middle and last frame of every session the
        run reads (with their labels, :meth:`_read_sessions`): on ``--resume`` from dataset
        folders named otherwise, the same drives with other images (rendered under another
        light, another camera's recording) are not the run's data. Computed once a trainer."""
        if relabel is None and self._image_fingerprint is not None:
            return self._image_fingerprint
        h = hashlib.sha256()
        for label, sess in self._read_sessions(relabel):
            n = len(sess)
            for i in sorted({0, n // 2, n - 1} if n else set()):
                h.update(f"{label}:{i};".encode())
                h.update(np.ascontiguousarray(sess[i].images).tobytes())
        digest = h.hexdigest()
        if relabel is None:
            self._image_fingerprint = digest
        return digest

    def _legacy_data_fingerprint(self) -> str:
        """The fingerprint of trainer states written before 2026-12-06: a SHA-256 over every
        session of the training datasets, read or not (compared on resuming such a state)."""
        h = hashlib.sha256()
        for ds in self._datasets:
            for name in ds.sessions:
                _hash_session(h, name, ds.session(name))
        return h.hexdigest()

    def resume(self) -> bool:
        """Load the last checkpoint and trainer state from ``out_dir``; False if there is none.

        The config must equal the run's, except ``stage2_epochs``, which may grow (to extend a
        run with more joint epochs) while the run has not passed into its head stage, how the
        run is executed (``RESUMABLE_CHANGES``), and where its datasets lie: a dataset folder
        named otherwise (moved, copied, or written as another path) is taken when the sessions
        the run reads have the same frames, poses and floors (the data fingerprint), the same
        images at the sampled frames (:meth:`image_fingerprint`) and the training datasets the
        same rig as the run's."""
        if not self._state_path().is_file():
            return False
        t0 = time.perf_counter()
        state = load_trainer_state(self._state_path())
        # keys added to TrainConfig after the run started count as their defaults
        old = {**TrainConfig().to_dict(), **state["config"]}
        self.joint_stopped = check_same_run(old, state, self.cfg, self._state_path(), self.out)
        self._check_same_data(old, state)
        for folder in (self.checkpoint_dir, self.best_dir):  # a stop inside a folder's swap
            recover_folder(folder)
        if not (self.checkpoint_dir / "config.json").is_file():
            # its weights are gone (a folder deleted or emptied): said as the run's state
            raise FileNotFoundError(
                f"{self.out}: the run's trainer_state.pt is here but not its checkpoint "
                f"({self.checkpoint_dir} holds no config.json): it cannot be resumed; train "
                "anew into another --out (or restore that folder)"
            )
        loaded = VVLocNet.load(self.checkpoint_dir)
        self._restore(state, loaded)
        self._restore_record(state, loaded)
        self.process["epochs"] = [self.epoch, self.epoch]
        self._mend_best()
        self.process["seconds"] += time.perf_counter() - t0
        log.info("resumed %s at epoch %d, step %d", self.out, self.epoch, self.step)
        return True

    def _check_same_data(self, old: dict[str, Any], state: Mapping[str, Any]) -> None:
        """Refuse to resume the run of config ``old`` (its trainer ``state``) on other data: a
        dataset folder named otherwise must hold the run's sessions (see :meth:`resume`)."""
        saved_paths, current_paths = _dataset_paths(old), _dataset_paths(self.cfg.to_dict())
        data = state.get("data")
        moved = {
            key: (saved_paths[key], current_paths[key])
            for key in saved_paths
            if saved_paths[key] != current_paths[key]
        }
        named = _named_paths(moved)
        # a renamed extra dataset labels its sessions by its new folder name: the run's labels
        relabel = {
            k: Path(saved_paths[key]).name
            for k in range(len(self.cfg.extra_datasets))
            if (key := f"extra_datasets[{k}].dataset") in moved
        }
        if (
            data is not None
            and data.startswith("v2:")
            and data != self.data_fingerprint(relabel or None)
        ):
            raise ValueError(
                f"{self._state_path()}: the training data changed since the run started (the "
                "frames, poses or floors of a training or validation session differ"
                + (f"; this config names other dataset folders, {named}" if moved else "")
                + "); the sampler's pools would pair other frames: use a new --out directory"
            )
        if moved:
            self._check_moved_datasets(moved, state.get("images"), relabel or None)
        if data is not None and not data.startswith("v2:"):  # a state of before 2026-12-06
            if data != self._legacy_data_fingerprint():
                raise ValueError(
                    f"{self._state_path()}: the training data changed since the run started "
                    "(this run's state, written before vvloc 2026-12-06, fingerprints every "
                    "session of the datasets' folders, so a session added since counts too); "
                    "use a new --out directory, or remove the sessions added since"
                )

    def _restore(self, state: Mapping[str, Any], loaded: VVLocNet) -> None:
        """Take the weights, optimizers, sampler, random generators, epoch, step and best epoch
        of the trainer ``state`` (the weights of ``loaded``, checkpoint/, for a state written
        before 2026-12-05)."""
        if "model" in state:  # the state's own weights (before 2026-12-05: checkpoint/'s)
            self.model.load_state_dict(state["model"])
            if loaded.weights_hash() != self.model.weights_hash():
                log.warning(
                    "%s holds other weights than the trainer state (a stop between the two "
                    "writes): resuming from the state's epoch %d; checkpoint/ is rewritten at "
                    "the next epoch",
                    self.checkpoint_dir,
                    int(state["epoch"]),
                )
        else:
            self.model.load_state_dict(loaded.state_dict())
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        if "head_optimizer" in state:  # runs saved before the head stage existed have none
            self.head_optimizer.load_state_dict(state["head_optimizer"])
            self.head_scheduler.load_state_dict(state["head_scheduler"])
            self.head_untrained = bool(state["head_untrained"])
        if "local_optimizer" in state:  # nor before the local stage
            self.local_optimizer.load_state_dict(state["local_optimizer"])
            self.local_scheduler.load_state_dict(state["local_scheduler"])
        if "sampler" in state:
            self.sampler.load_state_dict(state["sampler"])
        else:  # saved before 2026-12-03: no position in the hard pool (restarts at its first)
            self.sampler.load_state_dict(
                {"rng": state["sampler_rng"], "hard": state["sampler_hard"]}
            )
        torch.set_rng_state(state["torch_rng"])
        if state.get("cuda_rng") is not None and torch.cuda.is_available():
            cuda_states, visible = list(state["cuda_rng"]), torch.cuda.device_count()
            if (
                len(cuda_states) != visible
            ):  # another machine, or CUDA_VISIBLE_DEVICES: not an error
                log.warning(
                    "the run saved the RNG of %d CUDA devices, %d are visible: restoring the "
                    "first %d",
                    len(cuda_states),
                    visible,
                    min(len(cuda_states), visible),
                )
            for index, rng_state in enumerate(cuda_states[:visible]):
                torch.cuda.set_rng_state(rng_state, index)
        self.epoch = int(state["epoch"])
        self.step = int(state["step"])
        record = state.get("record")
        if record is not None and int(record["epoch"]) not in logged_epochs(self.out / LOG_FILE):
            self._unlogged = record  # fit() writes it before training on
        self.best = state.get("best")

    def _restore_record(self, state: Mapping[str, Any], loaded: VVLocNet) -> None:
        """Take the run's training record so far from its checkpoint ``loaded``, after
        :meth:`_restore` (its processes start at the restored epoch). Refuses a run whose
        ``init_checkpoint`` is gone when that checkpoint holds no record of it (written by an
        earlier vvloc)."""
        # The run's record so far is its latest checkpoint's (written with the state, brought
        # up at the end of fit): its processes, and the init checkpoint's runs as they were when
        # the run started (a run folder given as init_checkpoint moves on). A checkpoint of an
        # earlier vvloc has none: its time was not measured.
        saved = loaded.training_record.get("runs")
        if self._init_missing is not None:
            if not saved or "head_optimizer" not in state:
                raise _no_init_checkpoint(
                    self._init_missing,
                    f" (the run in {self.out} was saved by an earlier vvloc, without the record "
                    "of the weights it started from, which its resume reads there)",
                )
            log.warning(
                "%s: init_checkpoint %s is gone; resuming from the run's own checkpoint, whose "
                "training record keeps the runs it started from",
                self.out,
                self._init_missing,
            )
            self._init_missing = None
        if saved:
            mine = saved[-1]
            if self.init_weights_hash not in (None, mine.get("init_weights_hash")):
                log.warning(
                    "%s: init_checkpoint %s now holds other weights than the run started from; "
                    "the training record keeps those it started from",
                    self.out,
                    self.cfg.init_checkpoint,
                )
            self.earlier_runs = saved[:-1]
            self.init_weights_hash = mine.get("init_weights_hash")
            self.earlier_processes = [dict(p) for p in mine.get("processes", [])]
        else:
            self.earlier_processes = [{"epochs": [0, self.epoch], "seconds": None}]

    # --- training ------------------------------------------------------------------------

    @property
    def joint_end(self) -> int:
        """The number of epochs before the head stage: stages 1-2 as configured, or up to the
        joint epoch after which ``patience`` stopped the joint stage."""
        if self.joint_stopped is not None:
            return self.joint_stopped
        return int(self.cfg.stage1_epochs) + int(self.cfg.stage2_epochs)

    @property
    def total_epochs(self) -> int:
        """The epochs this run trains: ``cfg.epochs``, less the joint epochs skipped by an
        early stop."""
        return self.joint_end + int(self.cfg.head_epochs) + int(self.cfg.local_epochs)

    def stage_of(self, epoch: int) -> int:
        """1 for the global-descriptor epochs, 2 for the joint epochs, 3 for the head stage,
        4 for the local stage (``epoch`` 0-based)."""
        if epoch < self.cfg.stage1_epochs:
            return 1
        if epoch < self.joint_end:
            return 2
        return 3 if epoch < self.joint_end + int(self.cfg.head_epochs) else 4

    def run_epoch(self, progress: bool = True) -> dict[str, Any]:
        """Train one epoch (``steps_per_epoch`` batches, or the head stage's
        ``head_steps_per_epoch``); return its log record."""
        self._require_init()
        cfg = self.cfg
        stage = self.stage_of(self.epoch)
        if stage == 3:
            return self._head_epoch(progress)
        if stage == 4:  # the head stage's cache is not needed again (rebuilt if it were)
            self._head_cache = self._head_positions = None
            return self._local_epoch(progress)
        if self.epoch + 1 in cfg.hard_pool_restarts:
            self.sampler.restart_hard_pool()
        triplets = self.sampler.sample(cfg.steps_per_epoch * cfg.batch_size)
        loader = DataLoader(
            TripletFrames(
                self.sampler,
                triplets,
                augment=self.augment,
                seed=cfg.seed * 1_000_003 + self.epoch,
            ),
            batch_size=cfg.batch_size,
            shuffle=False,
            num_workers=cfg.num_workers,
            persistent_workers=False,
            worker_init_fn=_keep_sigterm_handler,
        )
        self.model.train()
        sums: dict[str, float] = {
            "total": 0.0,
            "triplet": 0.0,
            "hinge": 0.0,
            "yaw": 0.0,
            "tbias": 0.0,
            "rerank": 0.0,
        }
        if cfg.tbias_near_weight > 0:  # logged only when on (the committed runs' logs stay)
            sums["tbias_near"] = 0.0
        violated = 0
        blank = trained = 0  # triplets left out (a frame without image content), trained on
        blank_frames: list[np.ndarray] = []  # their frames without content (global ids)
        t0 = time.perf_counter()
        batches = iter(loader)
        bar = tqdm(
            batches,
            desc=f"epoch {self.epoch + 1}/{self.total_epochs} (stage {stage})",
            disable=not progress,
            leave=_keep_bars(),
        )
        n = 0
        with _workers_stopped(batches):  # on an error too: see _workers_stopped
            for loaded in bar:
                batch, without = self._with_content(loaded)
                blank_frames.append(without)
                blank += len(loaded["triplet"]) - (0 if batch is None else len(batch["triplet"]))
                if batch is None:  # no triplet left: no step
                    continue
                trained += len(batch["triplet"])
                loss, parts, correct = training_losses(
                    self.model, batch, cfg, stage, self.step, self.device
                )
                if not math.isfinite(parts.total):  # before the step: the weights stay finite
                    kept = self._what_is_saved()
                    raise FloatingPointError(
                        f"epoch {self.epoch + 1}, step {self.step}: non-finite loss {parts} "
                        f"({kept}; a smaller lr, a grad_clip or smaller loss weights and margins "
                        "may help)"
                    )
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                if cfg.grad_clip > 0:
                    torch.nn.utils.clip_grad_norm_(self.model.parameters(), cfg.grad_clip)
                self.optimizer.step()
                self.sampler.update(batch["triplet"].numpy(), correct)
                for k in sums:
                    sums[k] += getattr(parts, k)
                violated += parts.violated
                n += 1
                self.step += 1
                shown = {"loss": parts.total, "tri": parts.triplet, "hinge": parts.hinge}
                if stage == 2:  # the local-view losses train in the joint stage only
                    shown |= {"yaw": parts.yaw, "tbias": parts.tbias}
                    if cfg.rerank_weight > 0:
                        shown["rerank"] = parts.rerank
                    if cfg.tbias_near_weight > 0:
                        shown["near"] = parts.tbias_near  # about 0.02: shown to 4 places
                bar.set_postfix(
                    {k: f"{v:.4f}" if k == "near" else f"{v:.3f}" for k, v in shown.items()},
                    hard=len(self.sampler.hard),
                    refresh=False,
                )
        record: dict[str, Any] = {
            "epoch": self.epoch + 1,
            "stage": stage,
            "step": self.step,
            "lr": self.optimizer.param_groups[0]["lr"],
            # no step (every triplet held a frame without image content): no loss, null in the log
            **{f"loss_{k}": v / n if n else math.nan for k, v in sums.items()},
            "violated_share": violated / trained if trained else math.nan,
            "hard_pool": len(self.sampler.hard),
            "seconds": time.perf_counter() - t0,
            "device": str(self.device),
        }
        if blank:  # logged only then: the committed runs' logs stay as they are
            record["blank_triplets"] = blank
            self._exclude_blank(np.concatenate(blank_frames))
        if n == 0:
            log.warning(
                "epoch %d trained no step: each of its %d triplets held a frame without image "
                "content (%d such frames excluded from the next draws)",
                self.epoch + 1,
                blank,
                len(self.sampler.excluded),
            )
        with warnings.catch_warnings():  # torch warns of a schedule stepped before any step
            if n == 0:
                warnings.filterwarnings("ignore", "Detected call of `lr_scheduler", UserWarning)
            self.scheduler.step()
        self.epoch += 1
        self.head_untrained = False  # stages 1-2 train the global head too
        return record

    def _what_is_saved(self) -> str:
        """What a run that stops now leaves, for its error message."""
        if self.epoch > 0:
            return f"the checkpoint in {self.checkpoint_dir} keeps the last finished epoch"
        return "no epoch had finished: nothing was saved"

    @staticmethod
    def _with_content(
        batch: dict[str, torch.Tensor],
    ) -> tuple[dict[str, torch.Tensor] | None, np.ndarray]:
        """``batch`` (a collated :class:`TripletFrames` batch) without its ``content`` flags and
        without the triplets holding a frame without image content (None when none is left),
        and the global ids of those frames ((E,) int64)."""
        content = batch.pop("content")  # (B, 3) bool
        kept = content.all(dim=1)
        without = batch["triplet"][~content].numpy().astype(np.int64)
        if bool(kept.all()):
            return batch, without
        if not bool(kept.any()):
            return None, without
        return {k: v[kept] for k, v in batch.items()}, without

    def _exclude_blank(self, gids: np.ndarray) -> None:
        """Exclude frames ``gids`` (global ids) without image content from the sampler's draws,
        with a warning naming those not excluded before; ``ValueError`` saying so when that
        leaves nothing to train on."""
        try:
            new = self.sampler.exclude(gids)
        except ValueError as e:
            raise ValueError(  # e names the anchors missing (or an extra's anchor_shares)
                "training frames without image content (every camera's picture flat) leave "
                f"nothing to train on once left out: {e}; {self._what_is_saved()}"
            ) from None
        if len(new):
            where = [f"{s}:{i}" for s, i in (self.sampler.locate(int(g)) for g in new)]
            log.warning(
                "left %d training frame%s without image content (every camera's picture flat) "
                "out of training from now on: %s (session:frame); %d excluded in all",
                len(new),
                "" if len(new) == 1 else "s",
                list_entries(where),
                len(self.sampler.excluded),
            )

    # --- head stage ----------------------------------------------------------------------

    @torch.no_grad()
    def _sampler_bevs(self, desc: str, progress: bool) -> Iterator[tuple[list[Any], torch.Tensor]]:
        """Every sampler frame once, in batches of 16 (eval mode, no augmentation): yields
        (frames, their BEVs (b, H, W, C) on the device). Once all are through, the frames without
        image content are excluded from the sampler's draws (they stay in the caches)."""
        self.model.eval()
        n = len(self.sampler)
        bar = tqdm(total=n, desc=desc, disable=not progress)
        blank: list[int] = []
        for a in range(0, n, 16):
            frames = [self.sampler.frame(g) for g in range(a, min(a + 16, n))]
            blank += [a + i for i, f in enumerate(frames) if not has_image_content(f.images)]
            images, k, t = frames_to_tensors(frames, self.device)
            feats = self.model.image_features(images)
            size = (int(images.shape[-2]), int(images.shape[-1]))
            yield frames, self.model.bev_from_features(feats, k, t, size)
            bar.update(len(frames))
        bar.close()
        self._exclude_blank(np.asarray(blank, dtype=np.int64))

    @staticmethod
    def _joined(parts: list[torch.Tensor], what: str) -> torch.Tensor:
        """The cache of a stage on the frozen encoder, logged with its size (float16)."""
        cache = torch.cat(parts)
        log.info(
            "cached %d %s %s (%.0f MB)",
            len(cache),
            what,
            tuple(cache.shape[1:]),
            cache.numel() * 2 / 1e6,
        )
        return cache

    @torch.no_grad()
    def _build_head_cache(self, progress: bool) -> torch.Tensor:
        """Encode every sampler frame once (eval mode, no augmentation): (N, T, R, C) float16."""
        parts = [
            self.model.polar(bev).half()
            for _, bev in self._sampler_bevs("head stage: caching polar BEVs", progress)
        ]
        return self._joined(parts, "polar BEVs for the head stage")

    def head_cache(self, progress: bool = False) -> torch.Tensor:
        """The head stage's cache of polar BEVs (N, T, R, C) float16, built on first use
        (with the sampler positions the mining needs, kept on the device beside it)."""
        if self._head_cache is None:
            self._head_cache = self._build_head_cache(progress)
            # float64: with floors and worlds 1 000 m / 10⁶ m apart in z, float32 distances
            # would lose the metres that decide a negative
            self._head_positions = torch.from_numpy(self.sampler.positions).to(self.device)
        return self._head_cache

    @torch.no_grad()
    def _head_descriptors(self, cache: torch.Tensor) -> torch.Tensor:
        """Global descriptors (N, Dg) of the cached frames under the current head."""
        self.model.global_head.eval()
        return torch.cat(
            [self.model.global_head(cache[a : a + 256].float()) for a in range(0, len(cache), 256)]
        )

    def _mined_negatives(self, g: torch.Tensor, anchors: np.ndarray) -> np.ndarray:
        """Per anchor, one of the ``head_negatives`` frames nearest in descriptor space among
        those beyond ``neg_radius`` (floor-separated positions: another floor is far)."""
        pos = self._head_positions
        assert pos is not None  # set with the cache
        a = torch.from_numpy(anchors).to(g.device)
        sim = g[a] @ g.T  # (B, N)
        near = torch.cdist(pos[a], pos) <= self.sampler.neg_radius
        if not self.sampler.usable.all():  # excluded frames are no negatives either
            near |= torch.from_numpy(~self.sampler.usable).to(near.device)
        sim = sim.masked_fill(near, -math.inf)
        k = min(int(self.cfg.head_negatives), int((~near).sum(dim=1).min()))
        if k < 1:
            raise ValueError("head stage: an anchor has no negative beyond neg_radius")
        top = sim.topk(k, dim=1).indices.cpu().numpy()
        pick = self.sampler.rng.integers(k, size=len(anchors))
        return top[np.arange(len(anchors)), pick]

    def head_losses(
        self, cache: torch.Tensor, triplets: np.ndarray
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, int]:
        """Head-stage losses of (B, 3) triplets of cached frame ids: (total, triplet, hinge,
        number violating the triplet margin); the stage-1 losses on the head's descriptors."""
        idx = torch.from_numpy(np.asarray(triplets).T.reshape(-1)).to(self.device)
        g = self.model.global_head(cache[idx].float()).view(3, len(triplets), -1)
        l_tri, l_hinge, correct = global_losses(g, self.cfg)
        return l_tri + l_hinge, l_tri, l_hinge, int((~correct).sum())

    def _head_epoch(self, progress: bool) -> dict[str, Any]:
        """One epoch of the head stage (:mod:`vvloc.train`); returns its log record."""
        cfg = self.cfg
        t0 = time.perf_counter()
        cache = self.head_cache(progress)
        cache_seconds = time.perf_counter() - t0
        head = self.model.global_head
        if self.head_untrained and isinstance(head, NetVLADHead):
            sub = cache[:: max(1, len(cache) // 200)].float().flatten(1, 2)  # ≈ 200 frames' cells
            head.init_from_features(sub, seed=cfg.seed)
        self.model.eval()  # BatchNorm & co. of the frozen parts stay as they are
        sums = {"total": 0.0, "triplet": 0.0, "hinge": 0.0}
        violated = 0
        g = self._head_descriptors(cache)
        head.train()
        bar = tqdm(
            range(cfg.head_steps_per_epoch),
            desc=f"epoch {self.epoch + 1}/{self.total_epochs} (head stage)",
            disable=not progress,
            leave=_keep_bars(),
        )
        for k in bar:
            if k and k % HEAD_REFRESH == 0:
                g = self._head_descriptors(cache)
                head.train()
            trip = self.sampler.sample_random(cfg.head_batch_size)
            trip[:, 2] = self._mined_negatives(g, trip[:, 0])
            loss, l_tri, l_hinge, wrong = self.head_losses(cache, trip)
            self.head_optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if cfg.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(head.parameters(), cfg.grad_clip)
            self.head_optimizer.step()
            values = {
                k: float(v.detach()) for k, v in zip(sums, (loss, l_tri, l_hinge), strict=True)
            }
            for key, value in values.items():  # one read from the device each
                sums[key] += value
            violated += wrong
            self.step += 1
            bar.set_postfix(
                loss=f"{values['total']:.3f}",
                tri=f"{values['triplet']:.3f}",
                hinge=f"{values['hinge']:.3f}",
                refresh=False,
            )
        self.head_untrained = False
        n = cfg.head_steps_per_epoch
        record: dict[str, Any] = {
            "epoch": self.epoch + 1,
            "stage": 3,
            "step": self.step,
            "lr": self.head_optimizer.param_groups[0]["lr"],
            **{f"loss_{k}": v / n for k, v in sums.items()},
            "loss_yaw": 0.0,
            "loss_tbias": 0.0,
            "loss_rerank": 0.0,
            "violated_share": violated / (n * cfg.head_batch_size),
            "cache_seconds": cache_seconds,
            "seconds": time.perf_counter() - t0,
            "device": str(self.device),
        }
        self.head_scheduler.step()
        self.epoch += 1
        return record

    # --- local stage ---------------------------------------------------------------------

    @torch.no_grad()
    def _build_local_cache(self, progress: bool) -> tuple[torch.Tensor, np.ndarray]:
        """Encode every sampler frame once (eval mode, no augmentation): BEVs (N, H, W, C)
        float16 on the device and poses (N, 3) float64 (x m, y m, yaw rad, world frame)."""
        parts: list[torch.Tensor] = []
        poses: list[np.ndarray] = []
        for frames, bev in self._sampler_bevs("local stage: caching BEVs", progress):
            parts.append(bev.half())
            poses.extend(np.asarray(f.pose, dtype=np.float64) for f in frames)
        return self._joined(parts, "BEVs for the local stage"), np.stack(poses)

    def local_cache(self, progress: bool = False) -> tuple[torch.Tensor, np.ndarray]:
        """The local stage's cache (BEVs (N, H, W, C) float16, poses (N, 3)), built on first
        use."""
        if self._local_cache is None:
            self._local_cache = self._build_local_cache(progress)
        return self._local_cache

    def local_losses(
        self, bevs: torch.Tensor, poses: np.ndarray, pairs: np.ndarray, step: int
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Local-stage losses of (B, 2) (anchor, positive) pairs of cached frame ids: (total,
        yaw matching, translation bias, near translation), the anchor's BEV padded at the
        ground-truth ξ_{a→p} against the positive's local-view descriptor."""
        cfg = self.cfg
        a, p = np.asarray(pairs)[:, 0], np.asarray(pairs)[:, 1]
        xi = geometry.relative(poses[a], poses[p])  # (B, 3): positive in anchor frame
        t = torch.as_tensor(xi[:, :2], dtype=torch.float32, device=self.device)
        yaw = torch.as_tensor(xi[:, 2], dtype=torch.float32, device=self.device)
        bev_a = bevs[torch.from_numpy(a).to(self.device)].float()
        bev_p = bevs[torch.from_numpy(p).to(self.device)].float()
        loc_p = self.model.decode_polar(self.model.polar(bev_p))
        # the same calls as training_losses', not shared with it: see the note there
        l_yaw = yaw_matching_loss(
            self.model, bev_a, loc_p, t, yaw, cfg.yaw_gamma, cfg.yaw_theta_p, cfg.yaw_theta_n
        )
        l_tb = translation_bias_loss(
            self.model,
            bev_a,
            loc_p,
            t,
            yaw,
            margin=cfg.tbias_margin,
            seed=cfg.seed * 1_000_003 + step,
        )
        total = cfg.yaw_weight * l_yaw + cfg.tbias_weight * l_tb
        l_near = torch.zeros((), device=self.device)
        if cfg.tbias_near_weight > 0:
            l_near = near_losses(self.model, bev_a, loc_p, t, yaw, cfg, step)
            total = total + cfg.tbias_near_weight * l_near
        return total, l_yaw, l_tb, l_near

    def _local_epoch(self, progress: bool) -> dict[str, Any]:
        """One epoch of the local stage (:mod:`vvloc.train`); returns its log record."""
        cfg = self.cfg
        t0 = time.perf_counter()
        bevs, poses = self.local_cache(progress)
        cache_seconds = time.perf_counter() - t0
        self.model.eval()  # the frozen parts stay as they are
        self.model.decoder.train()
        self.model.interactor.train()
        params = [p for g in self.local_optimizer.param_groups for p in g["params"]]
        sums = {"total": 0.0, "yaw": 0.0, "tbias": 0.0, "tbias_near": 0.0}
        bar = tqdm(
            range(cfg.local_steps_per_epoch),
            desc=f"epoch {self.epoch + 1}/{self.total_epochs} (local stage)",
            disable=not progress,
            leave=_keep_bars(),
        )
        for _ in bar:
            pairs = self.sampler.sample_random(cfg.local_batch_size)[:, :2]
            loss, l_yaw, l_tb, l_near = self.local_losses(bevs, poses, pairs, self.step)
            self.local_optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if cfg.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
            self.local_optimizer.step()
            values = [float(v.detach()) for v in (loss, l_yaw, l_tb, l_near)]  # one read each
            for key, value in zip(sums, values, strict=True):
                sums[key] += value
            self.step += 1
            shown = dict(zip(("loss", "yaw", "tbias", "near"), values, strict=True))
            if cfg.tbias_near_weight <= 0:
                del shown["near"]
            bar.set_postfix(
                {k: f"{v:.4f}" if k == "near" else f"{v:.3f}" for k, v in shown.items()},
                refresh=False,
            )
        self.model.eval()
        n = cfg.local_steps_per_epoch
        record: dict[str, Any] = {
            "epoch": self.epoch + 1,
            "stage": 4,
            "step": self.step,
            "lr": self.local_optimizer.param_groups[0]["lr"],
            "loss_total": sums["total"] / n,
            "loss_triplet": 0.0,
            "loss_hinge": 0.0,
            "loss_yaw": sums["yaw"] / n,
            "loss_tbias": sums["tbias"] / n,
            "loss_tbias_near": sums["tbias_near"] / n,
            "loss_rerank": 0.0,
            "cache_seconds": cache_seconds,
            "seconds": time.perf_counter() - t0,
            "device": str(self.device),
        }
        self.local_scheduler.step()
        self.epoch += 1
        return record

    def validates(self, epoch: int) -> bool:
        """Whether epoch ``epoch`` (0-based) is scored on ``val_sessions``: the joint and head
        epochs (the local-view head is untrained before them), or every epoch of a run without
        joint epochs."""
        if not self.cfg.val_sessions:
            return False
        return self.cfg.stage2_epochs == 0 or self.stage_of(epoch) >= 2

    def validate(self) -> dict[str, Any]:
        """Score the current model on ``val_sessions``
        (:func:`vvloc.train.validation_recall`)."""
        cfg = self.cfg
        t0 = time.perf_counter()
        res = validation_recall(
            self.model,
            self.ds,
            cfg.val_database,
            list(cfg.val_sessions or []),
            every=cfg.val_every,
            top_k=cfg.val_top_k,
        )
        if res["queries"] == 0:  # NaN recall would never beat best/ and end the run early
            raise ValueError(_NO_VALIDATION_QUERY.format(cfg=cfg))
        if self.loop_sets:
            res["loops"] = [
                {
                    "dataset": str(entry["dataset"]),
                    **loop_validation(
                        self.model,
                        loop_ds,
                        list(entry["sessions"]),
                        radius=float(entry.get("radius", 0.1)),
                        window=int(entry.get("window", 10)),
                        sequence=int(entry.get("sequence", 0)),
                    ),
                }
                for loop_ds, entry in self.loop_sets
            ]
        res["seconds"] = time.perf_counter() - t0
        return res

    @staticmethod
    def selection_key(val: dict[str, Any], by: str = "reranked") -> tuple[float, ...]:
        """How validated epochs compare for ``best/`` (higher is better): fewer cross-floor loop
        closures on ``val_loops`` (when set), then Recall@1 (2 m) re-ranked, then retrieval
        (``by="reranked"``, and ``"last"``, which keeps the last epoch whatever its key), or
        retrieval first, then re-ranked (``by="retrieval"``; the config's ``select_by``)."""
        if by not in SELECT_BY:
            raise ValueError(f"by: expected one of {list(SELECT_BY)}, got {by!r}")
        cross = -sum(e["cross_floor"] for e in val.get("loops", []))
        recall = (val["r1_reranked"], val["r1_retrieval"])
        return (float(cross), *(recall if by == "reranked" else recall[::-1]))

    def batch_option(self, epoch: int) -> tuple[str, int]:
        """The config key that sets epoch ``epoch``'s (0-based) batch, and its value:
        ``batch_size`` (stages 1-2), ``head_batch_size`` or ``local_batch_size``."""
        key = {3: "head_batch_size", 4: "local_batch_size"}.get(self.stage_of(epoch), "batch_size")
        return key, int(getattr(self.cfg, key))

    @contextlib.contextmanager
    def _out_of_memory_named(self) -> Iterator[None]:
        """Turn running out of memory in an epoch (torch's CUDA ``OutOfMemoryError``, its CPU
        allocator's ``RuntimeError``, a ``MemoryError``, a data worker killed by SIGKILL as the
        kernel's out-of-memory killer does) into a ``MemoryError`` naming the config key of the
        epoch's batch size and what the run folder keeps. Nothing of the epoch has been saved
        then: ``--resume`` continues after the last finished epoch (with the same batch sizes:
        a smaller one is a new run)."""
        try:
            yield
        except (MemoryError, RuntimeError) as e:
            text = str(e)
            memory = isinstance(e, MemoryError | torch.OutOfMemoryError) or any(
                m in text
                for m in ("can't allocate memory", "out of memory", "killed by signal: Killed")
            )
            if not memory:
                raise
            key, value = self.batch_option(self.epoch)
            kept = (
                f"The checkpoint in {self.checkpoint_dir} keeps epoch {self.epoch}, which "
                "--resume continues"
                if self.epoch > 0
                else "No epoch had finished: nothing was saved"
            )
            first = text.splitlines()[0] if text.strip() else type(e).__name__
            raise MemoryError(
                f"out of memory in epoch {self.epoch + 1} (stage {self.stage_of(self.epoch)}, "
                f"{key} {value} on {self.device}): {first}. A smaller {key} needs less: train "
                f"it into a new --out (a run resumes only with its own batch sizes); fewer "
                f"num_workers may be given on --resume. {kept}."
            ) from e

    def fit(self, progress: bool = True) -> list[dict[str, Any]]:
        """Train until ``cfg.epochs`` (fewer when ``patience`` stops the joint stage); checkpoint
        and log after every epoch (and keep the best epoch by validation in ``best/`` when
        ``val_sessions`` are set)."""
        self._require_init()
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "train_config.yaml").write_text(yaml.safe_dump(self.cfg.to_dict()))
        cfg = self.cfg
        if self._unlogged is not None:  # the last process stopped between its save and its log
            self._log_record(self._unlogged)
            self._unlogged = None
        records = []
        while self.epoch < self.total_epochs:
            t0 = time.perf_counter()
            validating = self.validates(self.epoch)
            steps_before = self.step
            with self._out_of_memory_named():
                rec = self.run_epoch(progress=progress)
            # an epoch that trained no step (every triplet held a frame without image content)
            # has no loss to check: its losses are nan, null in the log
            stepped = self.step > steps_before
            if stepped and not all(
                math.isfinite(v) for k, v in rec.items() if k.startswith("loss_")
            ):
                # before any save: checkpoint/, best/ and the state keep the last good epoch
                raise FloatingPointError(
                    f"non-finite loss in epoch {rec['epoch']}: {rec}; nothing of this epoch was "
                    f"saved (--resume continues from epoch {rec['epoch'] - 1})"
                )
            if validating:
                rec["val"] = self.validate()
            self.process["seconds"] += time.perf_counter() - t0  # the saves below record it
            t0 = time.perf_counter()
            new_best = False
            if validating:
                key = self.selection_key(rec["val"], cfg.select_by)
                if (
                    cfg.select_by == "last"
                    or self.best is None
                    or key > self.selection_key(self.best["val"], cfg.select_by)
                ):
                    self.best = {"epoch": rec["epoch"], "val": rec["val"]}
                    new_best = True
                rec["best_epoch"] = self.best["epoch"]
                if (
                    cfg.patience is not None
                    and rec["stage"] == 2
                    and self.epoch < self.joint_end
                    and self.epoch - int(self.best["epoch"]) >= cfg.patience
                ):
                    self.joint_stopped = self.epoch
                    rec["joint_stopped_early"] = True
                    log.info(
                        "epoch %d: %d validated epochs without beating best/ (epoch %d): the "
                        "joint stage stops here (patience %d)",
                        self.epoch,
                        self.epoch - int(self.best["epoch"]),
                        self.best["epoch"],
                        cfg.patience,
                    )
            records.append(rec)
            self.save(record=rec)
            if new_best:  # after the state, which names it: a stop between the two is mended
                self._save_best()  # by resume (_mend_best)
            self.process["seconds"] += time.perf_counter() - t0
            self._log_record(rec)
            log.info("epoch %d: %s", rec["epoch"], {k: v for k, v in rec.items() if "loss" in k})
        if records:
            self._rewrite_records()
        elif self._best_record_unfinished():  # its last process stopped before this line
            self._rewrite_records(include_current=False)  # this one trained nothing
        # (otherwise a finished run resumed again trains nothing and changes no record)
        return records


def _keep_sigterm_handler(worker_id: int) -> None:
    """In a data-loading worker: reinstate the Python ``SIGTERM`` handler the worker inherited
    (the ``vvloc`` command's, :func:`vvloc.cli._exit_on_sigterm`), which torch's worker set-up
    replaced with one that dies of a group kill's ``SIGTERM`` before the main process can stop
    its workers, making the run end as a crash. Without a Python handler, nothing changes."""
    handler = signal.getsignal(signal.SIGTERM)
    if callable(handler):
        signal.signal(signal.SIGTERM, handler)


@contextlib.contextmanager
def _workers_stopped(batches: Iterator[Any]) -> Iterator[None]:
    """Stop the data-loading workers of ``batches`` (a ``DataLoader`` iterator) when the block
    ends, also by an exception. An error a worker raised (an unreadable image) kept the iterator
    alive in its traceback, and with it the workers, until the interpreter exited, where
    multiprocessing sent each worker one ``SIGTERM`` and waited for it without a limit; the
    workers, which let a first ``SIGTERM`` pass while their parent lives
    (:func:`_keep_sigterm_handler`), never ended: the command printed its error and hung. The
    iterator's own shut-down (torch's, which signals a worker that does not stop again) runs
    here instead; a loader without workers has none."""
    try:
        yield
    finally:
        shutdown = getattr(batches, "_shutdown_workers", None)
        if shutdown is not None:
            shutdown()
