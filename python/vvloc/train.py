"""The VVLoc trainer: the paper's two-stage recipe in a plain PyTorch loop.

Stage 1 trains the global descriptor (triplet + hinge losses on L2-normalised global
descriptors). Stage 2 trains global and local-view descriptors jointly, adding the circle-style
yaw matching loss and the translation-bias loss on (anchor, positive) pairs whose relative pose
ξ_{a→p} (DESIGN.md §3: the positive's frame expressed in the anchor's frame) is known from the
ground truth. Adam, learning rate 1e-4 decayed ×0.95 per epoch; triplets from
:class:`vvloc.data.TripletSampler` with hard-sample mining (triplets that still violate the
triplet margin are re-drawn until they are satisfied). Every random choice is seeded: on the
CPU a run is deterministic and a resumed run equals an uninterrupted one bit for bit. On CUDA
it is not: the backward passes of ``grid_sample`` (padding, polar sampling, deformable
attention), ``scatter_add`` and gathers accumulate with atomics, so two CUDA runs of one config
differ in the last bits and drift apart over epochs (torch offers no deterministic version of
``grid_sample``'s backward, so ``use_deterministic_algorithms`` cannot be switched on).

Outputs in ``out_dir``: ``checkpoint/`` (safetensors weights + JSON config, written each epoch),
``trainer_state.pt`` (optimizer, scheduler, epoch, step, sampler state, for ``--resume``),
``log.jsonl`` (one JSON object per epoch) and ``train_config.yaml`` (the resolved config).
Every checkpoint it writes holds a ``training.json`` (:mod:`vvloc.provenance`): the hardware,
device and wall time of this run and of the runs that produced its ``init_checkpoint``.

With ``val_sessions``, every joint epoch is scored on those held-out sessions against a map of
``val_database`` (:func:`validation_recall`: Recall@1 at 2 m after re-ranking, then by retrieval
alone) and the best epoch so far is kept in ``best/``: checkpoint selection on data that
neither trains the model nor reports its test figures.

An optional third stage (``head_epochs``) refines the global-descriptor head alone on frozen
encoder features: every training frame is encoded once (eval mode, no augmentation) and its
polar BEV cached; each step then draws anchors and positives from the sampler and, as the
negative, one of the ``head_negatives`` frames nearest the anchor in descriptor space among
those that are not its positives (beyond ``neg_radius`` or on another floor), the
descriptors being refreshed every :data:`HEAD_REFRESH` steps (the sampler's hard pool and
``cross_floor_fraction`` play no part there: mining finds the look-alikes). The BEV, the local-view
descriptors and so the metric localization are unchanged by it; retrieval is what it improves.
It can run after stages 1-2, or alone on a trained model (``init_checkpoint``), also with a
different ``global_head`` than the initial model's (a NetVLAD head then starts from a
spherical k-means of the cached cell features,
:meth:`vvloc.nets.heads.NetVLADHead.init_from_features`).

An optional fourth stage (``local_epochs``), ours, refines the local-view decoder and the
interactor alone on frozen BEVs: every training frame is encoded once (eval mode, no
augmentation) and its BEV cached with its pose; each step draws (anchor, positive) pairs from the
sampler and applies the yaw matching loss, the translation-bias loss and, with
``tbias_near_weight`` > 0, :func:`vvloc.losses.near_translation_loss` to the anchor's BEV
padded at the ground-truth relative pose. The BEV and the global descriptors, and so retrieval
and loop detection by descriptor, are unchanged by it; the re-ranking and the metric pose are
what it changes.

Frames without image content (:func:`vvloc.data.has_image_content`: every camera's picture
flat, e.g. a covered rig or a black stretch) look alike wherever they were taken: no model can
tell them apart, and their triplets would stay violated in the hard pool for good. As the map
builder and the localizer do, training leaves them out: stages 1-2 drop a batch's triplets that
hold one (found as the worker loads them) and the stage-3/4 caches find them as they encode
every frame; either way the sampler excludes the frame from every later draw
(:meth:`vvloc.data.TripletSampler.exclude`, kept in the trainer state for ``--resume``), with a
warning that names them and, in stages 1-2, an epoch log field ``blank_triplets``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
import hashlib
import json
import logging
import math
import os
import random
import secrets
import shutil
import signal
import sys
import time
import warnings
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any, NoReturn

import numpy as np
import torch
import yaml
from torch.utils.data import DataLoader
from torch.utils.data import Dataset as TorchDataset
from tqdm import tqdm

import vvloc
from vvloc import geometry
from vvloc._io import atomic_write, list_entries
from vvloc.checkpoints import resolve_checkpoint
from vvloc.data import RAW_FOLDER, TripletSampler, open_dataset
from vvloc.data.augment import PhotometricAugment
from vvloc.data.frame import Session, has_image_content
from vvloc.data.sampling import (
    check_query_sessions,
    check_session_names,
    inside_folder,
    rendered_world,
    same_folder,
    sim_world,
)
from vvloc.evaluate import nearest_map_distance, to_jsonable
from vvloc.localize.localizer import frames_to_tensors
from vvloc.losses import (
    hinge_loss,
    near_translation_loss,
    rerank_loss,
    translation_bias_loss,
    triplet_loss,
    yaw_matching_loss,
)
from vvloc.nets import ModelConfig, VVLocNet
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

log = logging.getLogger("vvloc.train")

#: Head stage: steps between refreshes of the cached frames' global descriptors (mining).
HEAD_REFRESH = 200
#: Model-config fields that only describe the global head (``init_checkpoint`` may differ in them).
HEAD_FIELDS = ("global_head", "netvlad_clusters", "global_dim", "disco_crop", "gem_p")

#: Config keys a ``--resume`` may change: how the run executes, not what it trains.
RESUMABLE_CHANGES = ("num_workers", "threads", "device")

#: What ``best/`` is selected by first (``TrainConfig.select_by``; :meth:`Trainer.selection_key`).
SELECT_BY = ("reranked", "retrieval", "last")


def _finite_at_least(name: str, value: float, *, strict: bool = False) -> None:
    """``ValueError`` naming ``name`` unless the number ``value`` is finite and >= 0 (with
    ``strict``: > 0); NaN fails both."""
    if not ((value > 0 if strict else value >= 0) and math.isfinite(value)):
        raise ValueError(
            f"{name}: expected a finite number {'>' if strict else '>='} 0, got {value!r}"
        )


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader, refusing a mapping that names a key twice (the safe loader keeps
    the last silently: ``lr`` written twice trained at the second). Merge keys (``<<: *base``)
    work as in the safe loader: the mapping's own keys override the merged ones."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":  # <<: a merge key, which the safe
                continue  # loader expands (and the mapping's own keys override) below
            key = self.construct_object(key_node, deep=deep)
            with contextlib.suppress(TypeError):  # unhashable keys fail below as YAML's own
                if key in seen:
                    raise yaml.constructor.ConstructorError(
                        "while constructing a mapping",
                        node.start_mark,
                        f"found the key {key!r} twice",
                        key_node.start_mark,
                    )
                seen.add(key)
        return super().construct_mapping(node, deep=deep)


@dataclass
class TrainConfig:
    """Everything a training run needs; loaded from YAML (``configs/*.yaml``).

    ``model`` is ``"small"``, ``"paper"`` or a mapping of :class:`ModelConfig` fields;
    ``model_overrides`` are applied on top. ``sim`` (optional) holds the arguments of
    :func:`vvloc.sim.simulate.simulate_dataset` used to render ``dataset`` when it does not exist
    yet, so that a committed config reproduces its data and its model with one command.
    ``augment`` (optional) holds :class:`vvloc.data.augment.PhotometricAugment` fields (``{}`` =
    its defaults; absent = no augmentation), applied independently to each frame of every
    training triplet.
    ``rerank_weight`` (default 0: off, the paper's losses only) adds, in stage 2, our
    :func:`vvloc.losses.rerank_loss` (margin ``rerank_margin``): the anchor's re-ranking cost
    against its positive must beat its cost against the triplet's negative.
    ``extra_datasets`` are further training datasets, each a mapping with ``dataset`` (path) and
    optionally ``sim``, ``train_sessions`` as above (the same camera count and image size as
    ``dataset``, and its cameras in its order when they have its camera names: refused otherwise;
    another mounting is recorded among the run's rigs)
    and ``anchor_share`` (the share of anchors drawn from it; default: by its frame count);
    each is its own world (see :class:`vvloc.data.TripletSampler`, which also takes
    ``cross_floor_fraction``: the share of negatives drawn from another floor at the anchor's
    x-y in multi-storey worlds, and ``cross_floor_same_session``: the share of those drawn from
    the anchor's own session). Validation uses ``dataset`` only. ``revisit_gap`` N > 0 also
    takes positives from the anchor's own session, at least N frames away (data of single
    drives that return to their places; 0, the default: positives from other sessions only).
    ``init_checkpoint`` (optional): start from these weights (a checkpoint folder, or a run
    folder: its ``best/``, else its ``checkpoint/``) instead of a random initialisation, to
    fine-tune a trained model (e.g. on a further world); its model config must equal this run's.
    Like ``dataset``, a relative path is taken from the working directory. A ``--resume``
    does not need it (the run's own checkpoint holds the weights and the record of those it
    started from), so a run folder can be resumed after its init checkpoint was moved.
    ``val_sessions`` (optional, disjoint from ``train_sessions``) select the checkpoint: every
    ``val_every``-th frame of each is localized against a map of the ``val_database`` session
    (re-ranking the ``val_top_k`` retrieved keyframes) after each joint epoch.
    ``val_loops`` (optional): multi-storey loop-closure validation, a list of mappings with
    ``dataset``, ``sessions`` (never trained on) and optionally ``radius`` (descriptor distance,
    default 0.1), ``window`` (same-session neighbours excluded, default 10 keyframes) and
    ``sequence`` (the loop detector's sequence-check half-window, default 0: single keyframes,
    the paper's test; :mod:`vvloc.localize.loops`): each
    validated epoch then also counts the loop closures that all frames of those sessions accept
    at ``radius`` and how many join two floors (:func:`loop_validation`), and ``best/`` goes to
    the epoch with the fewest such cross-floor pairs (summed over the entries), ties by the
    Recall@1 figures above. Needs ``val_sessions``.
    ``select_by`` (``"reranked"``, the default, or ``"retrieval"``): which Recall@1 (2 m)
    decides ``best/`` first (the other breaks ties; cross-floor loop closures on ``val_loops``
    come before both). ``"retrieval"`` is for head-stage runs: the head stage changes only the
    global descriptor, so the re-ranked figure moves only through the candidates retrieval
    passes on (a few validation queries' worth), while retrieval is what the stage trains and
    what the localizer's metric candidates are taken from (``metric_from="retrieval"``).
    ``"last"`` keeps the last validated epoch in ``best/`` (with its calibration), whatever its
    figures: for the local stage, whose target (the metric pose) the Recall@1 figures do not
    measure and which moves them by a query or two either way. Not with ``patience``.
    ``patience`` (optional, needs ``val_sessions`` and joint epochs): early stopping of the
    joint stage. When ``patience`` validated joint epochs in a row have not beaten ``best/``
    (by the selection key above), the remaining joint epochs are skipped (the head stage, if
    any, follows). The epochs trained are the same as without it, up to the stop, so ``best/``
    changes only if a later epoch would have beaten it. A run that stopped early is finished:
    growing ``stage2_epochs`` on resume does not restart it (start a new run with
    ``init_checkpoint`` instead).
    ``hard_pool_restarts`` (1-based epochs of stages 1-2, default none): at the start of each
    of these epochs the hard pool is drawn from its first triplet again instead of where the
    last epoch left it. This is what a ``--resume`` did before 2026-12-03, when the trainer
    state did not hold the position in the pool. ``models/synth-small``'s step 1 was resumed
    that way after epoch 10, and ``hard_pool_restarts: [11]`` trains it again without a break.
    ``head_epochs`` (default 0) adds the head stage (module docstring): ``head_steps_per_epoch``
    steps of ``head_batch_size`` triplets at learning rate ``head_lr`` (Adam, ×``lr_decay`` per
    epoch), negatives mined among the ``head_negatives`` nearest. Its cache holds every training
    frame's polar BEV in float16 on the training device: N · T · R · C · 2 bytes (the small
    model: 123 kB a frame). With ``init_checkpoint`` the model config may differ from the
    checkpoint's in the global-head fields (:data:`HEAD_FIELDS`) only, and then needs
    ``head_epochs`` > 0 (the new head is trained there, never left at its initialisation).
    ``tbias_near_weight`` (default 0: off) adds, wherever the translation-bias loss is
    applied, our :func:`vvloc.losses.near_translation_loss`: offsets of ‖Δ‖ in
    ``tbias_near_range`` (metres), margin ``tbias_near_slope`` × ‖Δ‖, the zero translation
    instead for the share ``tbias_near_zero`` of the pairs.
    ``local_epochs`` (default 0) adds the local stage (module docstring), after the head stage:
    ``local_steps_per_epoch`` steps of ``local_batch_size`` (anchor, positive) pairs at learning
    rate ``local_lr`` (Adam, ×``lr_decay`` per epoch), on the decoder and the interactor only,
    with the stage-2 weights ``yaw_weight``, ``tbias_weight`` and ``tbias_near_weight``. Its
    cache holds every training frame's BEV in float16 on the training device: N · H · W · C · 2
    bytes (the small model: 205 kB a frame). Without stages 1-2 it needs ``init_checkpoint``.
    Units: ``pos_radius``, ``neg_radius`` metres (positives within ``pos_radius`` of the
    anchor, negatives beyond ``neg_radius``; the translation-bias offsets are 1-3 m, see
    :func:`vvloc.losses.translation_bias_loss`); ``triplet_margin``,
    ``hinge_pos``, ``hinge_neg`` global-descriptor L2 distances; ``tbias_margin`` a matching
    cost; the yaw loss's ``yaw_theta_p``, ``yaw_theta_n`` L2 distances between aligned rows of
    the local-view descriptors (:func:`vvloc.losses.yaw_circle_loss`);
    ``lr``, ``head_lr``, ``local_lr`` Adam learning rates, ``lr_decay`` a factor per epoch.
    """

    dataset: str = "data/synth"
    train_sessions: list[str] | None = None
    model: Any = "small"
    model_overrides: dict[str, Any] = field(default_factory=dict)
    sim: dict[str, Any] | None = None
    seed: int = 0
    stage1_epochs: int = 2
    stage2_epochs: int = 4
    steps_per_epoch: int = 100
    batch_size: int = 2
    lr: float = 1e-4
    lr_decay: float = 0.95
    weight_decay: float = 0.0
    grad_clip: float = 10.0
    num_workers: int = 2
    device: str = "auto"
    pos_radius: float = 2.0
    neg_radius: float = 3.0
    hard_fraction: float = 0.5
    revisit_gap: int = 0
    triplet_margin: float = 0.1
    hinge_pos: float = 0.1
    hinge_neg: float = 0.2
    yaw_weight: float = 1.0
    yaw_gamma: float = 40.0
    yaw_theta_p: float = 0.1
    yaw_theta_n: float = 1.4
    tbias_weight: float = 1.0
    tbias_margin: float = 0.1
    rerank_weight: float = 0.0
    rerank_margin: float = 0.1
    augment: dict[str, Any] | None = None
    extra_datasets: list[dict[str, Any]] = field(default_factory=list)
    cross_floor_fraction: float = 0.0
    cross_floor_same_session: float = 0.0
    init_checkpoint: str | None = None
    val_sessions: list[str] | None = None
    val_database: str = "s0"
    val_every: int = 1
    val_top_k: int = 20
    val_loops: list[dict[str, Any]] = field(default_factory=list)
    patience: int | None = None
    select_by: str = "reranked"
    hard_pool_restarts: list[int] = field(default_factory=list)
    head_epochs: int = 0
    head_steps_per_epoch: int = 1000
    head_batch_size: int = 32
    head_lr: float = 1e-3
    head_negatives: int = 10
    tbias_near_weight: float = 0.0
    tbias_near_slope: float = 0.1
    tbias_near_range: list[float] = field(default_factory=lambda: [0.25, 1.0])
    tbias_near_zero: float = 0.0
    local_epochs: int = 0
    local_steps_per_epoch: int = 500
    local_batch_size: int = 8
    local_lr: float = 1e-4
    threads: int | None = None

    @classmethod
    def from_yaml(cls, path: str | os.PathLike[str]) -> TrainConfig:
        """Read a YAML config; unknown keys raise ``ValueError`` naming them and the file."""
        path = Path(path)
        if path.is_dir():
            raise IsADirectoryError(f"{path} is a folder; expected a YAML config file")
        if not path.exists():  # a stream such as /dev/null reads as an empty config
            raise FileNotFoundError(f"config file not found: {path}")
        try:
            raw = yaml.load(path.read_text(encoding="utf-8"), Loader=_UniqueKeyLoader)
        except UnicodeDecodeError as e:
            raise ValueError(f"{path}: not a UTF-8 text file ({e})") from e
        except yaml.YAMLError as e:
            raise ValueError(f"{path}: not valid YAML: {e}".replace("\n", " ")) from e
        if raw is None:  # an empty file, or comments alone: not every default by accident
            raise ValueError(
                f"{path}: empty config (expected a mapping of training settings; write {{}} "
                "for every default)"
            )
        if not isinstance(raw, dict):
            raise ValueError(f"{path}: expected a mapping at the top level")
        return cls.from_dict(raw, source=str(path))

    def _check_types(self) -> None:
        """Every field of the type its annotation says (YAML reads ``1e-5`` as a string and
        ``2.5`` where an int belongs would fail deep inside a step): ``ValueError`` naming it."""

        def number(v: Any) -> bool:  # an int beyond float's range is not one (10**400)
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                return False
            return isinstance(v, float) or abs(v) <= sys.float_info.max

        def integer(v: Any) -> bool:  # int64, as every count and the seed are used
            return isinstance(v, int) and not isinstance(v, bool) and -(2**63) <= v < 2**63

        checks: dict[str, tuple[Any, str]] = {
            "int": (integer, "an int"),
            "float": (number, "a number"),
            "str": (
                lambda v: isinstance(v, str),
                "a str (quote one YAML reads as a date or number: '2012-01-08')",
            ),
            "int | None": (lambda v: v is None or integer(v), "an int or null"),
            "str | None": (lambda v: v is None or isinstance(v, str), "a str or null"),
            "list[str] | None": (
                lambda v: v is None or (isinstance(v, list) and all(isinstance(x, str) for x in v)),
                "a list of session names or null (write [s0], not s0; quote names YAML reads "
                "as dates or numbers: ['2012-01-08'])",
            ),
            "list[int]": (
                lambda v: isinstance(v, list) and all(integer(x) for x in v),
                "a list of ints",
            ),
            "list[float]": (
                lambda v: isinstance(v, list) and all(number(x) for x in v),
                "a list of numbers",
            ),
            "dict[str, Any]": (lambda v: isinstance(v, dict), "a mapping"),
            "dict[str, Any] | None": (lambda v: v is None or isinstance(v, dict), "a mapping"),
            "list[dict[str, Any]]": (
                lambda v: isinstance(v, list) and all(isinstance(x, dict) for x in v),
                "a list of mappings",
            ),
        }
        own = ("hard_pool_restarts",)  # validate() checks it with a message of its own
        for f in dataclasses.fields(self):
            if f.name in own:
                continue
            check = checks.get(str(f.type))
            value = getattr(self, f.name)
            if check is None or check[0](value):
                continue
            hint = ""
            int_field = str(f.type) in ("int", "int | None", "float", "float | None")
            if isinstance(value, int) and not isinstance(value, bool) and int_field:
                hint = " (out of range)"  # an int where one goes: too large
            if isinstance(value, str):
                with contextlib.suppress(ValueError):
                    float(value)
                    hint = (  # a quoted number, or an exponent YAML 1.1 does not read as one
                        " (a number in quotes, or an exponent YAML reads as text: write it "
                        "unquoted, a whole number as 2 or 1000)"
                        if str(f.type) in ("int", "int | None")
                        else " (a number in quotes, or an exponent YAML reads as text, as it "
                        "reads 1e-5 and 1.0e3: write it unquoted as 1.0e-5 or 1.0e+3)"
                    )
            raise ValueError(f"{f.name}: expected {check[1]}, got {value!r:.80}{hint}")

    @classmethod
    def from_dict(cls, raw: dict[str, Any], source: str = "config") -> TrainConfig:
        """Build from a plain dict, rejecting unknown keys."""
        if not isinstance(raw, dict):
            raise TypeError(f"{source}: expected a mapping of keys, got {type(raw).__name__}")
        names = {f.name for f in dataclasses.fields(cls)}
        not_str = [k for k in raw if not isinstance(k, str)]
        if not_str:
            raise ValueError(f"{source}: keys must be names, got {not_str!r}")
        unknown = sorted(set(raw) - names)
        if unknown:
            near = {k: difflib.get_close_matches(k, names, n=1) for k in unknown}
            meant = [f"{k!r} → {m[0]!r}" for k, m in near.items() if m]
            hint = f" (did you mean {', '.join(meant)}?)" if meant else ""
            raise ValueError(f"{source}: unknown keys {unknown}{hint}; known: {sorted(names)}")
        cfg = cls(**raw)
        cfg.validate()
        return cfg

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid field: checked for its type
        (:meth:`_check_types`), then the numbers, the schedule, validation, the extra datasets
        and the model."""
        self._check_types()
        self._check_numbers()
        self._check_schedule()
        self._check_validation()
        self._check_extra_datasets()
        if self.augment is not None:
            PhotometricAugment.from_dict(self.augment)
        try:  # a misspelt model field fails here, not after the dataset has been rendered
            self.model_config()
        except (TypeError, ValueError) as e:
            raise ValueError(f"model, model_overrides: {e}") from e

    def _check_numbers(self) -> None:
        """The seed, the losses' margins and weights, the learning rates, the radii and
        shares (each a number of its type already: :meth:`_check_types`)."""
        for name in (
            "seed",
            "triplet_margin",
            "hinge_pos",
            "hinge_neg",
            "tbias_margin",
            "yaw_weight",
            "tbias_weight",
            "grad_clip",  # 0: no clipping
            "weight_decay",
            "tbias_near_weight",
            "tbias_near_slope",  # inf: a non-finite loss
            "rerank_weight",
            "rerank_margin",
        ):
            _finite_at_least(name, getattr(self, name))
        if self.seed >= 2**32:  # stage 2 seeds its losses with seed · 1 000 003 + step (int64)
            raise ValueError(f"seed: expected < 2**32, got {self.seed}")
        for name in ("yaw_gamma", "lr", "head_lr", "local_lr"):
            _finite_at_least(name, getattr(self, name), strict=True)
        if not 0 < self.lr_decay <= 1:
            raise ValueError("lr_decay: expected in (0, 1]")
        if self.threads is not None and self.threads < 1:
            raise ValueError(f"threads: expected an int >= 1 or null, got {self.threads!r}")
        if not (0 < self.pos_radius < self.neg_radius and math.isfinite(self.neg_radius)):
            raise ValueError(
                f"pos_radius, neg_radius: expected 0 < pos_radius < neg_radius < inf metres, got "
                f"{self.pos_radius} and {self.neg_radius}"
            )
        theta_p, theta_n = self.yaw_theta_p, self.yaw_theta_n
        if not (0 <= theta_p < theta_n and math.isfinite(theta_n)):
            raise ValueError(
                "yaw_theta_p, yaw_theta_n: expected finite descriptor distances with "
                f"0 <= yaw_theta_p < yaw_theta_n, got {theta_p} and {theta_n}"
            )
        near = self.tbias_near_range
        if len(near) != 2 or not 0 < near[0] <= near[1] < math.inf:
            raise ValueError(
                "tbias_near_range: expected [low, high] metres with 0 < low <= high, finite, "
                f"got {near!r}"
            )
        for name in ("hard_fraction", "tbias_near_zero", "cross_floor_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:  # NaN fails too
                raise ValueError(f"{name}: expected a value in [0, 1], got {getattr(self, name)}")
        if not 0.0 <= self.cross_floor_same_session <= 1.0:
            raise ValueError("cross_floor_same_session: expected a value in [0, 1]")

    def _check_schedule(self) -> None:
        """The stages' epochs, steps and batches, the sessions trained on and what the stages
        on a frozen encoder start from."""
        stages = ("stage1_epochs", "stage2_epochs", "head_epochs", "local_epochs")
        for name in stages:
            if getattr(self, name) < 0:
                raise ValueError(f"{name}: expected >= 0")
        if sum(getattr(self, name) for name in stages) == 0:  # it wrote no checkpoint
            raise ValueError(f"{', '.join(stages)}: expected at least one epoch, got 0 in all")
        for name in (
            "steps_per_epoch",
            "batch_size",
            "head_steps_per_epoch",
            "head_negatives",
            "local_steps_per_epoch",
            "local_batch_size",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: expected >= 1")
        if self.head_batch_size < 2:
            raise ValueError("head_batch_size: expected >= 2")
        if self.revisit_gap < 0:
            raise ValueError(f"revisit_gap: expected an int >= 0, got {self.revisit_gap}")
        if self.num_workers < 0:
            raise ValueError("num_workers: expected >= 0")
        if self.train_sessions is not None and not self.train_sessions:
            raise ValueError("train_sessions: expected a non-empty list of session names or null")
        if self.stage1_epochs + self.stage2_epochs == 0 and self.init_checkpoint is None:
            # the stages on a frozen encoder need a trained one
            for name, stage, uses in (
                ("head_epochs", "a head stage", "features it pools"),
                ("local_epochs", "a local stage", "BEVs it pads"),
            ):
                if getattr(self, name) > 0:
                    raise ValueError(
                        f"{name}: {stage} without stages 1-2 needs init_checkpoint (the trained "
                        f"encoder whose {uses})"
                    )
        restarts = self.hard_pool_restarts
        if not isinstance(restarts, list) or not all(
            isinstance(e, int) and not isinstance(e, bool) and e >= 1 for e in restarts
        ):
            raise ValueError(
                f"hard_pool_restarts: expected a list of 1-based epochs (ints >= 1), got "
                f"{restarts!r}"
            )
        triplet_epochs = self.stage1_epochs + self.stage2_epochs
        if any(e > triplet_epochs for e in restarts):
            # the head stage mines its own negatives and has no hard pool to restart
            raise ValueError(
                f"hard_pool_restarts: {restarts!r} names an epoch after stages 1-2, which end at "
                f"epoch {triplet_epochs}: only their epochs draw from the hard pool"
            )

    def _check_validation(self) -> None:
        """The validation sessions (never trained on), the loop validations, early stopping
        and how ``best/`` is selected."""
        if self.val_sessions is not None:
            if not self.val_sessions:
                raise ValueError("val_sessions: expected a non-empty list of session names")
            overlap = sorted(set(self.val_sessions) & set(self.train_sessions or []))
            if overlap or self.train_sessions is None:
                raise ValueError(
                    "val_sessions: must not be trained on (set train_sessions without them); "
                    f"overlap: {overlap or 'train_sessions is unset (all sessions train)'}"
                )
            check_query_sessions(self.val_database, self.val_sessions, "val_sessions")
        for k, entry in enumerate(self.val_loops):
            self._check_val_loop(k, entry)
        for name in ("val_every", "val_top_k"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: expected an int >= 1")
        if self.patience is not None:
            if self.patience < 1:
                raise ValueError(f"patience: expected an int >= 1 or null, got {self.patience!r}")
            if not self.val_sessions or self.stage2_epochs == 0:
                raise ValueError(
                    "patience: early stopping needs val_sessions and stage2_epochs > 0 (it stops "
                    "the joint stage when validation stops improving)"
                )
        if self.select_by not in SELECT_BY:
            raise ValueError(
                f"select_by: expected one of {list(SELECT_BY)}, got {self.select_by!r}"
            )
        if self.select_by == "last" and self.patience is not None:
            raise ValueError(
                "select_by: 'last' keeps every validated epoch in turn, so patience would never "
                "stop; drop one of them"
            )
        if self.select_by != "reranked" and not self.val_sessions:
            raise ValueError("select_by: selects best/ by validation, so it needs val_sessions")
        if self.val_loops and not self.val_sessions:
            raise ValueError("val_loops: needs val_sessions (the Recall@1 validation) as well")

    def _check_val_loop(self, k: int, entry: dict[str, Any]) -> None:
        """``val_loops[k]``: its keys, sessions none of the training datasets trains on, and
        the loop detector's radius, window and sequence half-window."""
        if not {"dataset", "sessions"} <= set(entry):
            raise ValueError(f"val_loops[{k}]: expected a mapping with 'dataset' and 'sessions'")
        unknown = sorted(set(entry) - {"dataset", "sessions", "radius", "window", "sequence"})
        if unknown:
            raise ValueError(
                f"val_loops[{k}]: unknown keys {unknown}; "
                "known: ['dataset', 'radius', 'sequence', 'sessions', 'window']"
            )
        if not isinstance(entry["sessions"], list) or not entry["sessions"]:
            raise ValueError(f"val_loops[{k}].sessions: expected a non-empty list")
        if not isinstance(entry["dataset"], str):
            raise ValueError(
                f"val_loops[{k}].dataset: expected a folder path (str), got {entry['dataset']!r}"
            )
        radius = entry.get("radius", 0.1)
        if (
            isinstance(radius, bool)
            or not isinstance(radius, (int, float))
            or not 0 < radius <= sys.float_info.max  # NaN, inf and 10**400 fail
        ):
            raise ValueError(
                f"val_loops[{k}].radius: expected a finite number > 0, got {radius!r:.80}"
            )
        for key, default in (("window", 10), ("sequence", 0)):
            value = entry.get(key, default)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"val_loops[{k}].{key}: expected an int >= 0, got {value!r}")
        sources = [{"dataset": self.dataset, "train_sessions": self.train_sessions}]
        for extra in [*sources, *self.extra_datasets]:
            if same_folder(extra.get("dataset"), entry["dataset"]):
                trained = set(extra.get("train_sessions") or []) & set(entry["sessions"])
                if trained or extra.get("train_sessions") is None:
                    raise ValueError(
                        f"val_loops[{k}].sessions: must not be trained on ({entry['dataset']} "
                        f"trains {sorted(trained) or 'all its sessions'})"
                    )

    def _check_extra_datasets(self) -> None:
        """Each ``extra_datasets`` entry: its keys, a folder of its own, its anchor share and
        the sessions it trains on."""
        for k, extra in enumerate(self.extra_datasets):
            if "dataset" not in extra:
                raise ValueError(f"extra_datasets[{k}]: expected a mapping with a 'dataset' path")
            if not isinstance(extra["dataset"], str):
                raise ValueError(
                    f"extra_datasets[{k}].dataset: expected a folder path (str), got "
                    f"{extra['dataset']!r}"
                )
            unknown = sorted(set(extra) - {"dataset", "sim", "train_sessions", "anchor_share"})
            if unknown:
                raise ValueError(
                    f"extra_datasets[{k}]: unknown keys {unknown}; "
                    "known: ['anchor_share', 'dataset', 'sim', 'train_sessions']"
                )
            earlier = [self.dataset, *(e.get("dataset") for e in self.extra_datasets[:k])]
            if any(same_folder(extra["dataset"], d) for d in earlier):
                raise ValueError(
                    f"extra_datasets[{k}].dataset: {extra['dataset']} is "
                    + (
                        "the training dataset"
                        if same_folder(extra["dataset"], self.dataset)
                        else "listed twice"
                    )
                    + ": its frames would pair as another world's and could hold val_sessions; "
                    "choose its sessions with train_sessions instead"
                )
            share = extra.get("anchor_share")
            if share is not None and (
                isinstance(share, bool) or not isinstance(share, (int, float)) or not 0 < share < 1
            ):
                raise ValueError(
                    f"extra_datasets[{k}].anchor_share: expected a share in (0, 1) or null, "
                    f"got {share!r}"
                )
            sessions = extra.get("train_sessions")
            if sessions is not None and (
                not isinstance(sessions, list) or not all(isinstance(n, str) for n in sessions)
            ):
                raise ValueError(
                    f"extra_datasets[{k}].train_sessions: expected a list of session names, "
                    f"got {sessions!r}"
                )

    def model_config(self) -> ModelConfig:
        """The :class:`ModelConfig` this run trains."""
        if isinstance(self.model, str):
            if self.model not in ("small", "paper"):
                raise ValueError(
                    f"model: expected 'small', 'paper' or a mapping, got {self.model!r}"
                )
            base = ModelConfig.small() if self.model == "small" else ModelConfig.paper()
            d = base.to_dict()
        elif isinstance(self.model, dict):
            d = ModelConfig().to_dict()
            d.update(self.model)
        else:
            raise ValueError(f"model: expected 'small', 'paper' or a mapping, got {self.model!r}")
        d.update(self.model_overrides)
        return ModelConfig.from_dict(d)

    @property
    def epochs(self) -> int:
        """Total number of epochs (stage 1 + stage 2 + head stage + local stage)."""
        return (
            int(self.stage1_epochs)
            + int(self.stage2_epochs)
            + int(self.head_epochs)
            + int(self.local_epochs)
        )

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (YAML/JSON serialisable)."""
        return dataclasses.asdict(self)


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


@dataclass
class StepLosses:
    """Loss values of one step (floats; zero where a loss is not active in the stage)."""

    total: float
    triplet: float
    hinge: float
    yaw: float
    tbias: float
    rerank: float
    violated: int
    tbias_near: float = 0.0


def global_losses(
    g: torch.Tensor, cfg: TrainConfig
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The global-descriptor losses of triplets ``g`` (3, B, Dg) (anchor, positive, negative
    descriptors): (triplet loss, hinge loss, correct (B,) bool); a triplet is correct for
    hard mining when ‖g_a − g_p‖ + margin < ‖g_a − g_n‖.

    The terms are built in this order (triplet, then the distances and the hinge) on purpose:
    autograd sums the gradients of ``g`` in the reverse order of the graph, so another order
    changes the weights' last bits, and over a training run the weights themselves; this is
    the order that trained the committed models' steps since 2026-12-02
    (models/synth-small-v3/MODEL_CARD.md)."""
    l_tri = triplet_loss(g[0], g[1], g[2], cfg.triplet_margin)
    d_pos = (g[0] - g[1]).norm(dim=-1)
    d_neg = (g[0] - g[2]).norm(dim=-1)
    l_hinge = hinge_loss(d_pos, d_neg, cfg.hinge_pos, cfg.hinge_neg)
    return l_tri, l_hinge, (d_pos + cfg.triplet_margin < d_neg).detach()


def training_losses(
    model: VVLocNet,
    batch: dict[str, torch.Tensor],
    cfg: TrainConfig,
    stage: int,
    step: int,
    device: torch.device,
) -> tuple[torch.Tensor, StepLosses, np.ndarray]:
    """Forward one batch of B triplets and return (total loss, its parts, correct mask (B,)).

    The three frames of each triplet are encoded in one call (3B samples). Stage 1 uses the
    triplet and hinge losses of the global descriptors; stage 2 adds the yaw matching loss and
    the translation bias loss (weights ``yaw_weight``, ``tbias_weight``) on (anchor, positive)
    with the ground-truth relative pose ξ_{a→p} (with ``tbias_near_weight`` > 0 also the near
    translation loss, :func:`near_losses`), and, when ``rerank_weight`` > 0, the
    re-ranking loss on (anchor, positive, negative). A triplet is "correct" for hard mining when
    ‖g_a − g_p‖ + margin < ‖g_a − g_n‖.
    """
    images = batch["images"].to(device)  # (B, 3, M, 3, H, W)
    b = images.shape[0]
    flat = lambda x: x.to(device).transpose(0, 1).reshape(3 * b, *x.shape[2:])  # noqa: E731
    out = model.encode(flat(images), flat(batch["intrinsics"]), flat(batch["cam_to_ego"]))
    l_tri, l_hinge, correct_t = global_losses(out.global_desc.view(3, b, -1), cfg)
    total = l_tri + l_hinge
    l_yaw = torch.zeros((), device=device)
    l_tb = torch.zeros((), device=device)
    l_rr = torch.zeros((), device=device)
    l_near = torch.zeros((), device=device)
    if stage == 2:
        poses = batch["poses"].numpy()
        xi = geometry.relative(poses[:, 0], poses[:, 1])  # (B, 3): positive in anchor frame
        t = torch.as_tensor(xi[:, :2], dtype=torch.float32, device=device)
        yaw = torch.as_tensor(xi[:, 2], dtype=torch.float32, device=device)
        bev = out.bev.view(3, b, *out.bev.shape[1:])
        loc = out.local_desc.view(3, b, *out.local_desc.shape[1:])
        # Written out here and in Trainer.local_losses on purpose: the same calls made through
        # one shared function gave the same forward values but gradients that differ in the
        # last bits (2026-12-04, stage 2 of configs/synth-small-rerank.yaml: step 1's joint
        # epochs parted from the committed run), so `make model` no longer retrained
        # models/synth-small's bytes. Check that before refactoring this path.
        l_yaw = yaw_matching_loss(
            model, bev[0], loc[1], t, yaw, cfg.yaw_gamma, cfg.yaw_theta_p, cfg.yaw_theta_n
        )
        l_tb = translation_bias_loss(
            model, bev[0], loc[1], t, yaw, margin=cfg.tbias_margin, seed=cfg.seed * 1_000_003 + step
        )
        total = total + cfg.yaw_weight * l_yaw + cfg.tbias_weight * l_tb
        if cfg.tbias_near_weight > 0:  # only when on, like the re-ranking loss below
            l_near = near_losses(model, bev[0], loc[1], t, yaw, cfg, step)
            total = total + cfg.tbias_near_weight * l_near
        if cfg.rerank_weight > 0:  # only when on: any extra term would move the committed weights
            l_rr = rerank_loss(model, loc[0], loc[1], loc[2], cfg.rerank_margin)
            total = total + cfg.rerank_weight * l_rr
    correct = correct_t.cpu().numpy()
    parts = StepLosses(
        total=float(total.detach()),
        triplet=float(l_tri.detach()),
        hinge=float(l_hinge.detach()),
        yaw=float(l_yaw.detach()),
        tbias=float(l_tb.detach()),
        rerank=float(l_rr.detach()),
        violated=int((~correct).sum()),
        tbias_near=float(l_near.detach()),
    )
    return total, parts, correct


def near_losses(
    model: VVLocNet,
    bev_src: torch.Tensor,
    local_tgt: torch.Tensor,
    translation: torch.Tensor,
    yaw: torch.Tensor,
    cfg: TrainConfig,
    step: int,
) -> torch.Tensor:
    """:func:`vvloc.losses.near_translation_loss` with the config's ``tbias_near_*`` settings,
    seeded by the run's seed and ``step``: source BEVs (B, H, W, C), target local-view
    descriptors (B, T, C), ground-truth ξ_{s→t} translation (B, 2) metres and yaw (B,) radians."""
    lo, hi = (float(v) for v in cfg.tbias_near_range)
    return near_translation_loss(
        model,
        bev_src,
        local_tgt,
        translation,
        yaw,
        slope=float(cfg.tbias_near_slope),
        bias_range=(lo, hi),
        zero_share=float(cfg.tbias_near_zero),
        seed=near_seed(cfg.seed, step),
    )


def near_seed(seed: int, step: int) -> int:
    """The generator seed of :func:`near_losses` at ``step`` of a run seeded ``seed``: a stream
    of its own, 63 bits of numpy's ``SeedSequence([seed, step, 1])``. The translation-bias loss
    keeps ``seed · 1 000 003 + step``; until 2026-12-05 the near loss used ``seed · 1 000 033 +
    step``, which at seed 0 is the same number, so each pair's near offset was a rescaled copy
    of its bias offset (``models/synth-small/HISTORY.md``, "Step 5 again")."""
    hi, lo = np.random.SeedSequence([seed, step, 1]).generate_state(2, np.uint32)
    return (int(hi) << 31) | (int(lo) >> 1)


_NO_VALIDATION_QUERY = (
    "val_sessions: no query of {cfg.val_sessions} (every {cfg.val_every}th frame) lies within "
    "2 m of a frame of val_database {cfg.val_database!r} on its floor: validation could not "
    "rank the epochs; choose sessions that revisit the map's places"
)


def validation_query_count(ds: Any, database: str, queries: list[str], every: int = 1) -> int:
    """How many queries :func:`validation_recall` scores, from the poses alone (no model):
    every ``every``-th frame of each session in ``queries`` that has a frame of ``database``
    within 2 m on its floor. The trainer checks it before the first epoch."""
    db = ds.session(database)
    sessions = [ds.session(name) for name in queries]
    near = nearest_map_distance(
        np.concatenate([s.poses[::every, :2] for s in sessions]),
        db.poses[:, :2],
        np.concatenate([s.floors[::every] for s in sessions]),
        db.floors,
    )
    return int(np.count_nonzero(near <= 2.0))


def validation_recall(
    model: VVLocNet,
    ds: Any,
    database: str,
    queries: list[str],
    *,
    every: int = 1,
    top_k: int = 20,
) -> dict[str, Any]:
    """Recall@1/@5 at 2 m of ``queries`` against a map of the ``database`` session, and the
    acceptance calibration they give.

    Every frame of ``database`` is a map keyframe; every ``every``-th frame of each query session
    is a query. Retrieval ranks the map by global-descriptor distance (``-G``); re-ranking
    orders its top ``top_k`` by the learned yaw matching cost (``-ML``), see
    :func:`vvloc.localize.calibrate.rerank_split`. Recall follows
    :func:`vvloc.evaluate.recall_at_n` (queries without a map frame within 2 m left out).

    Returns ``{"queries": kept queries, "r1_retrieval", "r5_retrieval", "r1_reranked",
    "calibration"}`` (shares in [0, 1]; ``calibration`` from
    :func:`vvloc.localize.calibrate.calibration_of`).
    """
    from vvloc.localize.calibrate import calibration_of, rerank_split

    split = rerank_split(model, ds, database, queries, every=every, top_k=top_k)
    rec_g = split.recall("retrieved")
    rec_ml = split.recall("reranked")
    return {
        "queries": rec_g.num_kept,
        "r1_retrieval": rec_g.at(1, 2.0),
        "r5_retrieval": rec_g.at(5, 2.0) if 5 in rec_g.top_n else float("nan"),
        "r1_reranked": rec_ml.at(1, 2.0),
        "calibration": calibration_of(split),
    }


def loop_validation(
    model: VVLocNet,
    ds: Any,
    sessions: list[str],
    *,
    radius: float = 0.1,
    window: int = 10,
    sequence: int = 0,
) -> dict[str, Any]:
    """Loop closures among all frames of ``sessions`` accepted at global-descriptor distance
    < ``radius`` (same-session pairs within ``window`` keyframes excluded; with ``sequence`` =
    L > 0 their ±L neighbouring keyframes must match as well, as the loop detector's sequence
    check does), scored as
    :func:`vvloc.evaluate.loop_closure_curve` does (true loop: ≤ 2 m, same floor).

    Returns ``{"frames", "accepted", "cross_floor" (accepted pairs joining two floors),
    "cfer", "precision", "recall"}`` (shares in [0, 1], ``nan`` when nothing is accepted).
    """
    from vvloc import evaluate
    from vvloc.localize.localizer import encode_frames
    from vvloc.localize.loops import descriptor_loop_candidates

    frames, group, seq = [], [], []
    for k, name in enumerate(sessions):
        sess = list(ds.session(name))
        frames += sess
        group += [k] * len(sess)
        seq += list(range(len(sess)))
    g = encode_frames(model, frames).global_desc
    cand = descriptor_loop_candidates(
        g, np.asarray(group), np.asarray(seq), radius, window, sequence
    )
    pos = np.stack([f.pose[:2] for f in frames])
    floors = np.asarray([f.floor for f in frames], np.int64)
    curve = evaluate.self_loop_closure_curve(
        np.stack([cand.i, cand.j], axis=1), cand.distance, pos, floors, group, seq, window
    )
    at = curve.at(radius, strict=True)  # the detector's rule: distance < radius
    cross = int(curve.is_cross_floor[: int(at["accepted"])].sum())  # pairs sorted by distance
    return {
        "frames": len(frames),
        "accepted": int(at["accepted"]),
        "cross_floor": cross,
        "cfer": at["cfer"],
        "precision": at["precision"],
        "recall": at["recall"],
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


def _ensure_dataset(dataset: str, sim: dict[str, Any] | None, prefix: str = "") -> None:
    """Render ``dataset`` from ``sim`` (arguments of :func:`vvloc.sim.simulate_dataset`) when it
    does not exist yet; errors name the config's keys, ``{prefix}dataset`` and ``{prefix}sim``
    (``prefix`` is ``extra_datasets[i].`` for an extra dataset)."""
    import inspect

    from vvloc.sim import simulate_dataset

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
        where = f"{prefix.rstrip('.')} has" if prefix else "the config has"
        raise FileNotFoundError(
            f"{prefix}dataset: {root} does not exist{_resolved(root)} and {where} no 'sim' "
            "section to render it"
        )
    log.info("rendering the training dataset into %s", root.resolve())
    try:
        simulate_dataset(root, **sim)
    except (TypeError, ValueError) as e:  # "frames: expected ..." is the config's sim.frames
        raise (TypeError if isinstance(e, TypeError) else ValueError)(f"{key}: {e}") from e


def _check_sessions_to_render(cfg: TrainConfig) -> None:
    """Refuse, naming the config key, a session of ``train_sessions``, ``val_sessions`` or
    ``val_database`` that the config's ``sim`` section would not render (``vvloc sim`` names
    them s0, s1, ...) when ``cfg.dataset`` does not exist yet: said before the rendering."""
    sim = cfg.sim or {}
    count = sim.get("sessions")
    if Path(cfg.dataset).exists() or isinstance(count, bool) or not isinstance(count, int):
        return
    rendered: Any = SimpleNamespace(sessions=[f"s{i}" for i in range(max(count, 0))])
    for key, names in _session_keys(cfg):
        check_session_names(
            key, rendered, names, cfg.dataset, " (the sessions its sim section would render)"
        )


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


def _load_trainer_state(path: Path) -> dict[str, Any]:
    """``torch.load`` of a run's ``trainer_state.pt``: ``ValueError`` naming the file when it
    is truncated (a disk that filled, a copy cut short) or not a trainer state; torch says
    ``EOFError: Ran out of input`` or ``pickle data was truncated`` without the file."""
    import pickle

    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except (RuntimeError, EOFError, pickle.UnpicklingError) as e:
        why: str = str(e).split(". ")[0]
    else:
        if isinstance(state, dict) and "config" in state:
            return state
        why = f"a {type(state).__name__} without the run's config"
    raise ValueError(
        f"{path}: not a readable trainer state ({why}): this run cannot be resumed; start a new "
        "run into another folder (init_checkpoint: its checkpoint/ to keep its weights)"
    )


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
        self.head_optimizer = torch.optim.Adam(self.model.global_head.parameters(), lr=cfg.head_lr)
        self.head_scheduler = torch.optim.lr_scheduler.ExponentialLR(
            self.head_optimizer, gamma=cfg.lr_decay
        )
        self._head_cache: torch.Tensor | None = None  # (N, T, R, C) float16, the head stage's
        self._head_positions: torch.Tensor | None = None  # (N, 3) sampler positions, on device
        local = [*self.model.decoder.parameters(), *self.model.interactor.parameters()]
        self.local_optimizer = torch.optim.Adam(local, lr=cfg.local_lr)
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
        process stopped between saving ``best/`` and its state) is left as it is."""
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

    def _save_model(self, folder: Path, weights_epoch: int) -> None:
        """Write the model into ``folder`` (``checkpoint/``, ``best/``) as a whole: into a
        hidden folder beside it, swapped in by two renames, so that a stop never leaves one
        epoch's weights beside another's calibration or record. A stop between the renames
        leaves the previous folder under a hidden name, which :meth:`_recover_folder` puts
        back."""
        self._recover_folder(folder)
        tmp = folder.parent / f".{folder.name}.partial-{secrets.token_hex(6)}"
        self.model.training_record = self.record_for(weights_epoch)
        try:
            self.model.save(tmp)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        finally:
            self.model.training_record = {}
        old = folder.parent / f".{folder.name}.old-{secrets.token_hex(6)}"
        if folder.exists():
            os.replace(folder, old)
        os.replace(tmp, folder)
        shutil.rmtree(old, ignore_errors=True)

    @staticmethod
    def _recover_folder(folder: Path) -> None:
        """Undo what a stop inside :meth:`_save_model` left: remove half-written hidden folders,
        and put the previous folder back where a stop between the two renames took it away."""
        for stale in folder.parent.glob(f".{folder.name}.partial-*"):
            shutil.rmtree(stale, ignore_errors=True)
        olds = sorted(folder.parent.glob(f".{folder.name}.old-*"))
        if olds and not folder.exists():
            os.replace(olds.pop(), folder)
        for old in olds:
            shutil.rmtree(old, ignore_errors=True)

    def _log_record(self, rec: dict[str, Any]) -> None:
        """Append one epoch's record to ``log.jsonl`` (strict JSON: NaN/inf as null). A torn
        last line (a process killed or a disk full while it appended one) is cut off first: it
        is no epoch (:meth:`_logged_epochs`), and the new line must not continue it."""
        path = self.out / "log.jsonl"
        if path.is_file():
            data = path.read_bytes()
            if data and not data.endswith(b"\n"):
                with open(path, "r+b") as f:
                    f.truncate(data.rfind(b"\n") + 1)
        with open(path, "a") as f:
            f.write(json.dumps(to_jsonable(rec), allow_nan=False) + "\n")

    def _logged_epochs(self) -> set[int]:
        """The epochs ``log.jsonl`` holds a line of (a torn last line is no epoch)."""
        path = self.out / "log.jsonl"
        done: set[int] = set()
        if path.is_file():
            for line in path.read_text().splitlines():
                try:
                    done.add(int(json.loads(line)["epoch"]))
                except (ValueError, KeyError, TypeError):
                    continue
        return done

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
        state = _load_trainer_state(self._state_path())
        # keys added to TrainConfig after the run started count as their defaults
        old = {**TrainConfig().to_dict(), **state["config"]}
        self.joint_stopped = self._check_same_run(old, state)
        self._check_same_data(old, state)
        for folder in (self.checkpoint_dir, self.best_dir):  # a stop inside a folder's swap
            self._recover_folder(folder)
        loaded = VVLocNet.load(self.checkpoint_dir)
        self._restore(state, loaded)
        self._restore_record(state, loaded)
        self.process["epochs"] = [self.epoch, self.epoch]
        self.process["seconds"] += time.perf_counter() - t0
        log.info("resumed %s at epoch %d, step %d", self.out, self.epoch, self.step)
        return True

    def _check_same_run(self, old: dict[str, Any], state: Mapping[str, Any]) -> int | None:
        """Refuse to resume the run of config ``old`` (its trainer ``state``) under another
        config than this trainer's (see :meth:`resume`); returns the run's
        :attr:`joint_stopped`, the epoch its joint stage stopped early at (or None)."""
        # Extending a run (more joint epochs) is allowed; any other change is a different run.
        # how the run is executed may change: workers, threads and device (the last two
        # can move the weights' last bits, as on another machine)
        free = ("stage2_epochs", *RESUMABLE_CHANGES)
        saved_cfg = {k: v for k, v in old.items() if k not in free}
        current = {k: v for k, v in self.cfg.to_dict().items() if k not in free}
        # where the datasets lie is checked by their contents (_check_same_data)
        saved_cfg, current = _without_dataset_paths(saved_cfg), _without_dataset_paths(current)
        if saved_cfg != current:
            differ = sorted(
                k for k in set(saved_cfg) | set(current) if saved_cfg.get(k) != current.get(k)
            )
            raise ValueError(
                f"{self._state_path()}: the run in {self.out} was started with another config "
                f"(differing: {', '.join(differ)}); use a new --out directory or the same config"
            )
        for key in ("threads", "device"):
            if old.get(key) != getattr(self.cfg, key):
                log.warning(
                    "resuming with %s %r (the run started with %r): the weights may differ in "
                    "their last bits from an uninterrupted run",
                    key,
                    getattr(self.cfg, key),
                    old.get(key),
                )
        if old["stage2_epochs"] != self.cfg.stage2_epochs and (
            self.cfg.stage2_epochs < old["stage2_epochs"]
            or int(state["epoch"]) > old["stage1_epochs"] + old["stage2_epochs"]
        ):
            raise ValueError(
                f"{self._state_path()}: stage2_epochs can only grow, and only before the head "
                f"stage (run in {self.out}: {old['stage2_epochs']} joint epochs, at epoch "
                f"{state['epoch']}; asked for {self.cfg.stage2_epochs})"
            )
        joint_stopped = state.get("joint_stopped")
        best = state.get("best")
        if (
            joint_stopped is None
            and old["stage2_epochs"] != self.cfg.stage2_epochs
            and self.cfg.patience is not None
            and best is not None
            and int(state["epoch"]) == old["stage1_epochs"] + old["stage2_epochs"]
            and int(state["epoch"]) - int(best["epoch"]) >= self.cfg.patience
        ):
            # its last joint epoch skipped the patience check (no joint epoch was left to
            # stop); a run that had asked for more epochs from the start would have stopped
            # there, so an extension is refused as for one that did stop
            joint_stopped = int(state["epoch"])
        if joint_stopped is not None and old["stage2_epochs"] != self.cfg.stage2_epochs:
            raise ValueError(
                f"{self._state_path()}: the run in {self.out} stopped its joint stage early "
                f"after epoch {joint_stopped} (patience {self.cfg.patience}); growing "
                "stage2_epochs does not restart it: start a new run (another --out) with "
                f"init_checkpoint: {self.out}"
            )
        return joint_stopped

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
        if record is not None and int(record["epoch"]) not in self._logged_epochs():
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
        if stage == 4:
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
        """One epoch of the head stage (see the module docstring); returns its log record."""
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
        """One epoch of the local stage (see the module docstring); returns its log record."""
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
        """Score the current model on ``val_sessions`` (see :func:`validation_recall`)."""
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
            with self._out_of_memory_named():
                rec = self.run_epoch(progress=progress)
            if not all(math.isfinite(v) for k, v in rec.items() if k.startswith("loss_")):
                # before any save: checkpoint/, best/ and the state keep the last good epoch
                raise FloatingPointError(
                    f"non-finite loss in epoch {rec['epoch']}: {rec}; nothing of this epoch was "
                    f"saved (--resume continues from epoch {rec['epoch'] - 1})"
                )
            if validating:
                rec["val"] = self.validate()
            self.process["seconds"] += time.perf_counter() - t0  # the saves below record it
            t0 = time.perf_counter()
            if validating:
                key = self.selection_key(rec["val"], cfg.select_by)
                if (
                    cfg.select_by == "last"
                    or self.best is None
                    or key > self.selection_key(self.best["val"], cfg.select_by)
                ):
                    self.model.calibration = {
                        **rec["val"]["calibration"],
                        "dataset": str(cfg.dataset),
                        "database": cfg.val_database,
                        "sessions": list(cfg.val_sessions or []),
                        "every": int(cfg.val_every),
                    }
                    self._save_model(self.best_dir, self.epoch)
                    self.model.calibration = {}
                    self.best = {"epoch": rec["epoch"], "val": rec["val"]}
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
            self.process["seconds"] += time.perf_counter() - t0
            self._log_record(rec)
            log.info("epoch %d: %s", rec["epoch"], {k: v for k, v in rec.items() if "loss" in k})
        if records:
            self._rewrite_records()
        elif self._best_record_unfinished():  # its last process stopped before this line
            self._rewrite_records(include_current=False)  # this one trained nothing
        # (otherwise a finished run resumed again trains nothing and changes no record)
        return records


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
