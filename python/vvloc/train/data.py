"""The datasets a run reads: :class:`TripletFrames` (the stages-1-2 loader's dataset of a
sampler's triplets), rendering a config's simulated datasets when missing, and the checks that a
run's datasets, sessions and ``init_checkpoint`` are what its config names (with the helpers
by which a resumed run recognises its datasets: their paths in the config and its sessions'
fingerprints)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset as TorchDataset

from vvloc.checkpoints import resolve_checkpoint
from vvloc.data import RAW_FOLDER, TripletSampler, open_dataset
from vvloc.data.augment import PhotometricAugment
from vvloc.data.frame import Session, has_image_content
from vvloc.data.sampling import (
    check_session_names,
    rendered_world,
    same_folder,
    sim_world,
)
from vvloc.train.config import TrainConfig

log = logging.getLogger("vvloc.train")


class TripletFrames(TorchDataset):
    """A torch dataset over a fixed (n, 3) array of triplet frame ids of a sampler.

    Item k is a dict of tensors for frames (anchor, positive, negative): ``images`` (3, M, 3, H,
    W) uint8, ``intrinsics`` (3, M, 3, 3) float32, ``cam_to_ego`` (3, M, 4, 4) float32, ``poses``
    (3, 3) float64 world (x, y, yaw), ``triplet`` (3,) int64 ids and ``content`` (3,) bool,
    whether each frame has image content (:func:`vvloc.data.has_image_content` of its images as
    loaded, before augmentation; the trainer drops triplets without). With ``augment``, each
    frame's images go through it with a generator seeded by ``(seed, k, slot)``, so an item is the
    same whichever worker process loads it.
    """

    def __init__(
        self,
        sampler: TripletSampler,
        triplets: np.ndarray,
        augment: PhotometricAugment | None = None,
        seed: int = 0,
    ) -> None:
        self.sampler = sampler
        self.triplets = np.asarray(triplets, dtype=np.int64).reshape(-1, 3)
        self.augment = augment
        self.seed = int(seed)

    def __len__(self) -> int:
        return len(self.triplets)

    def __getitem__(self, k: int) -> dict[str, torch.Tensor]:
        frames = [self.sampler.frame(int(g)) for g in self.triplets[k]]
        images = [f.images for f in frames]
        content = [has_image_content(im) for im in images]
        if self.augment is not None:
            images = [
                self.augment(im, np.random.default_rng([self.seed, k, slot]))
                for slot, im in enumerate(images)
            ]
        return {
            "images": torch.from_numpy(np.stack(images)),
            "intrinsics": torch.from_numpy(np.stack([f.K for f in frames]).astype(np.float32)),
            "cam_to_ego": torch.from_numpy(
                np.stack([f.cam_to_ego for f in frames]).astype(np.float32)
            ),
            "poses": torch.from_numpy(np.stack([f.pose for f in frames]).astype(np.float64)),
            "triplet": torch.from_numpy(self.triplets[k].copy()),
            "content": torch.tensor(content, dtype=torch.bool),
        }


def _check_rendered_like(root: Path, sim: dict[str, Any]) -> None:
    """Refuse a rendered dataset whose recorded world (``rig.json`` ``meta``: scene, seed, the
    vehicle's tilt bounds, and for a garage floors and floor marking) differs from what ``sim``
    would render."""
    have = rendered_world(root)
    if have is None:
        return
    want = sim_world(sim)
    if want != have:
        raise ValueError(
            f"dataset {root} was rendered as {have}, but the config's sim section renders "
            f"{want}: move it away to re-render it, or point the config elsewhere"
        )


def _check_rendered_rig(root: Path, sim: dict[str, Any], key: str) -> None:
    """Refuse a dataset ``vvloc sim`` rendered whose rig (camera count, image size) or session
    length differs from what the ``sim`` section (defaults filled in) renders: training would
    use the other data without a word."""
    if rendered_world(root) is None:
        return
    ds = open_dataset(root)
    cams = ds.cameras
    have: dict[str, Any] = {"cameras": len(cams), "width": cams[0].width, "height": cams[0].height}
    sessions = sim.get("sessions")
    if isinstance(sessions, int):
        lengths = {len(ds.session(f"s{i}")) for i in range(sessions) if f"s{i}" in ds.sessions}
        if lengths and lengths != {sim.get("frames")}:
            have["frames"] = sorted(lengths)
    want = {k: sim.get(k) for k in have}
    if have != want:
        raise ValueError(
            f"{key}: dataset {root} was rendered with {have}, but the config's sim section "
            f"renders {want}: move it away to re-render it, or point the config elsewhere"
        )


def _resolved(path: Path) -> str:
    """`` (/abs/path: ...)`` for a relative ``path`` (a config's paths are taken from the
    working directory, not from the config's folder); "" for an absolute one."""
    if path.is_absolute():
        return ""
    return (
        f" ({path.resolve()}: a relative path is taken from the working directory, not the "
        "config's folder)"
    )


def _nothing_to_render(prefix: str, root: Path) -> FileNotFoundError:
    """The error for the config's ``{prefix}dataset`` ``root``, which does not exist, when its
    entry has no ``sim`` section to render it."""
    where = f"{prefix.rstrip('.')} has" if prefix else "the config has"
    return FileNotFoundError(
        f"{prefix}dataset: {root} does not exist{_resolved(root)} and {where} no 'sim' section "
        "to render it"
    )


def _ensure_dataset(dataset: str, sim: dict[str, Any] | None, prefix: str = "") -> None:
    """Render ``dataset`` from ``sim`` (arguments of :func:`vvloc.sim.simulate_dataset`) when it
    does not exist yet; errors name the config's keys, ``{prefix}dataset`` and ``{prefix}sim``
    (``prefix`` is ``extra_datasets[i].`` for an extra dataset)."""
    import inspect

    from vvloc.sim import simulate_dataset
    from vvloc.sim.simulate import check_options

    key = f"{prefix}sim"
    root = Path(dataset)
    params = inspect.signature(simulate_dataset).parameters
    known = [p for p in params if p != "out"]
    unknown = sorted(set(sim or {}) - set(known))
    if unknown:  # said as the config's key, not as simulate_dataset()'s keyword argument
        raise ValueError(f"{key}: unknown keys {unknown} (known: {known})")
    if root.exists():
        _check_vvloc_format(f"{prefix}dataset", root)
        if sim:
            _check_rendered_like(root, sim)
            _check_rendered_rig(root, {p: params[p].default for p in known} | sim, key)
        if sim and isinstance(sim.get("sessions"), int):
            have = set(open_dataset(root).sessions)
            missing = [f"s{i}" for i in range(sim["sessions"]) if f"s{i}" not in have]
            if missing and rendered_world(root) is None:
                raise ValueError(
                    f"dataset {root} was not rendered by vvloc sim (its rig.json records no "
                    f"rendered world) and lacks sessions {missing} that the config's sim section "
                    "would render: for a dataset of your own, delete the config's sim section "
                    "and name your sessions in train_sessions (and val_sessions, val_database)"
                )
            if missing:
                raise ValueError(
                    f"dataset {root} lacks sessions {missing} that the config's sim section "
                    f"renders ({sim['sessions']} sessions): it was rendered by another config; "
                    "move it away to re-render it"
                )
        return
    if not sim:
        raise _nothing_to_render(prefix, root)
    try:  # a bad value is refused before the warning below says the dataset is being rendered
        check_options(**sim)
    except (TypeError, ValueError) as e:
        raise (TypeError if isinstance(e, TypeError) else ValueError)(f"{key}: {e}") from e
    # said at the default level: a mistyped path beside a leftover sim section would otherwise
    # train on a synthetic world without a word (README, "Your own rig's data")
    log.warning(
        "%sdataset %s does not exist: rendering it from the config's %s section (%s, %s "
        "sessions); for a dataset of your own, check the path and delete the %s section",
        prefix,
        root.resolve(),
        key,
        sim.get("scene", params["scene"].default),
        sim.get("sessions", params["sessions"].default),
        key,
    )
    try:
        simulate_dataset(root, **sim)
    except (TypeError, ValueError) as e:  # "frames: expected ..." is the config's sim.frames
        raise (TypeError if isinstance(e, TypeError) else ValueError)(f"{key}: {e}") from e


def _check_sessions_to_render(cfg: TrainConfig) -> None:
    """Refuse, naming the config key, what can be known wrong before any rendering: a session
    of ``train_sessions``, ``val_sessions`` or ``val_database`` that the config's ``sim``
    section would not render (``vvloc sim`` names them s0, s1, ...) when ``cfg.dataset`` does
    not exist yet; for each of ``extra_datasets``, a dataset that neither exists nor has a
    ``sim`` section, or ``train_sessions`` it lacks (or would not render); for each of
    ``val_loops``, a dataset that does not exist (none that a sim section renders) or sessions
    it lacks. (A typo there was found after minutes of rendering the main dataset.)"""
    note = " (the sessions its sim section would render)"
    to_render = []
    for key, root, sim, keyed in (
        ("", cfg.dataset, cfg.sim, _session_keys(cfg)),
        *(
            (
                f"extra_datasets[{i}].",
                e["dataset"],
                e.get("sim"),
                [(f"extra_datasets[{i}].train_sessions", list(e.get("train_sessions") or []))],
            )
            for i, e in enumerate(cfg.extra_datasets)
        ),
    ):
        if Path(root).exists():
            if key:  # the main dataset's sessions are checked once it is opened
                opened = _open_named(f"{key}dataset", root)
                for k, names in keyed:
                    _check_sessions(k, root, opened, names)
            continue
        if not sim:
            raise _nothing_to_render(key, Path(root))
        to_render.append(root)
        count = sim.get("sessions")
        if isinstance(count, bool) or not isinstance(count, int):
            continue  # said by the sim section's own check
        rendered: Any = SimpleNamespace(sessions=[f"s{i}" for i in range(max(count, 0))])
        for k, names in keyed:
            check_session_names(k, rendered, names, root, note)
    for j, entry in enumerate(cfg.val_loops):
        if any(same_folder(entry["dataset"], root) for root in to_render):
            continue  # rendered first; its sessions are checked once it is opened
        loop_ds = _open_named(f"val_loops[{j}].dataset", entry["dataset"])
        _check_sessions(f"val_loops[{j}].sessions", entry["dataset"], loop_ds, entry["sessions"])


def _session_keys(cfg: TrainConfig) -> list[tuple[str, list[str]]]:
    """(config key, session names) of ``train_sessions``, and of ``val_sessions`` and
    ``val_database`` when the config validates."""
    keys: list[tuple[str, list[str]]] = [("train_sessions", list(cfg.train_sessions or []))]
    if cfg.val_sessions:
        keys += [("val_sessions", list(cfg.val_sessions)), ("val_database", [cfg.val_database])]
    return keys


def _check_session_keys(cfg: TrainConfig, ds: Any) -> None:
    """Refuse, naming the config key, a session of ``train_sessions``, ``val_sessions`` or
    ``val_database`` that ``ds`` (``cfg.dataset``) lacks, holds no frame of, or that the key
    names twice: before any epoch, and not with the sampler's or validation's words."""
    for key, names in _session_keys(cfg):
        default = key == "val_database" and cfg.val_database == TrainConfig().val_database
        note = " (its default: set it to your map session)" if default else ""
        _check_sessions(key, cfg.dataset, ds, names, note)


def _check_sessions(key: str, dataset: str, ds: Any, names: Sequence[str], note: str = "") -> None:
    """``ValueError`` naming the config's ``key`` when ``names`` repeat a session, name one that
    ``ds`` (opened from ``dataset``) lacks (``note`` follows the dataset), or one with no frame."""
    check_session_names(key, ds, names, dataset, note)
    empty = [n for n in names if len(ds.session(n)) == 0]
    if empty:
        raise ValueError(f"{key}: sessions {empty} of {dataset} hold no frames")


def _open_named(key: str, dataset: str) -> Any:
    """``open_dataset(dataset)`` with its errors prefixed by the config's ``key``; a raw folder
    is refused (:func:`_check_vvloc_format`)."""
    _check_vvloc_format(key, Path(dataset))  # its errors name the key already
    try:
        return open_dataset(dataset)
    except (FileNotFoundError, NotADirectoryError, ValueError) as e:
        raise type(e)(f"{key}: {e}") from e


def _check_vvloc_format(key: str, root: Path) -> None:
    """Refuse an NCLT or RobotCar raw folder as the config's dataset ``key``: the trainer passes
    no reader options, so it would read every raw frame at the native image size (NCLT's
    1232 × 1616: the paper model's backbone alone needs about a GB per image), with the ego
    origin left at the dataset's vehicle frame, above the ground where the BEV plane lies."""
    from vvloc.data import detect_format

    if not root.is_dir():
        return  # open_dataset names what is missing
    try:
        fmt = detect_format(root)
    except ValueError as e:  # a folder of no known layout (DatasetFormatError)
        raise type(e)(f"{key}: {e}") from None
    if fmt != "vvloc":
        raise ValueError(
            f"{key}: {root} is {RAW_FOLDER[fmt]}; the trainer reads vvloc datasets only (a raw "
            "folder would be read at its native image size, every frame, with the ego origin "
            "above the ground): convert it once with vvloc convert --src "
            f"{root} --out <folder> --ego_height <metres> --width <px> --height <px> "
            "--min_distance 1 (docs/dataset-format.md) and train on that"
        )


def _dataset_paths(cfg: dict[str, Any]) -> dict[str, Any]:
    """The dataset folders a config (``TrainConfig.to_dict()``) names, by key: ``dataset``,
    ``extra_datasets[k].dataset`` and ``val_loops[k].dataset``."""
    paths = {"dataset": cfg.get("dataset")}
    for key in ("extra_datasets", "val_loops"):
        for k, entry in enumerate(cfg.get(key) or []):
            if isinstance(entry, dict):
                paths[f"{key}[{k}].dataset"] = entry.get("dataset")
    return paths


def _named_paths(moved: dict[str, tuple[str, str]]) -> str:
    """``"dataset: 'a' -> 'b'; …"`` for the dataset folders a resumed config names otherwise."""
    return "; ".join(f"{key}: {a!r} -> {b!r}" for key, (a, b) in moved.items())


def _without_dataset_paths(cfg: dict[str, Any]) -> dict[str, Any]:
    """``cfg`` with its dataset folders (:func:`_dataset_paths`) left out."""
    out = {k: v for k, v in cfg.items() if k != "dataset"}
    for key in ("extra_datasets", "val_loops"):
        if isinstance(out.get(key), list):
            out[key] = [
                {k: v for k, v in e.items() if k != "dataset"} if isinstance(e, dict) else e
                for e in out[key]
            ]
    return out


def _hash_session(h: Any, label: str, sess: Session) -> None:
    """Feed ``label``, the length, the poses (float64) and the floors (int64) of ``sess`` to
    the hash ``h`` (a ``hashlib`` object)."""
    h.update(f"{label}:{len(sess)};".encode())
    h.update(np.ascontiguousarray(sess.poses, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(sess.floors, dtype="<i8").tobytes())


def _is_checkpoint(path: Path) -> bool:
    """Whether ``path`` is a checkpoint folder, or a run folder that holds one."""
    return (resolve_checkpoint(path) / "config.json").is_file()


def _no_init_checkpoint(path: Path, why: str = "") -> FileNotFoundError:
    return FileNotFoundError(
        f"init_checkpoint: no checkpoint (config.json) in {resolve_checkpoint(path)}{why}: train "
        "that run first (see the config's header), or point init_checkpoint at a checkpoint "
        "folder such as models/synth-small-base"
    )
