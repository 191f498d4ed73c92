"""The training run's configuration: :class:`TrainConfig`, read from YAML (``configs/*.yaml``)
and checked before any dataset is rendered or opened, and the constants the stages share."""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from vvloc.data.augment import PhotometricAugment
from vvloc.data.sampling import (
    check_query_sessions,
    same_folder,
)
from vvloc.nets import ModelConfig

#: Head stage: steps between refreshes of the cached frames' global descriptors (mining).
HEAD_REFRESH = 200


#: Model-config fields that only describe the global head (``init_checkpoint`` may differ in them).
HEAD_FIELDS = ("global_head", "netvlad_clusters", "global_dim", "disco_crop", "gem_p")


#: Config keys a ``--resume`` may change: how the run executes, not what it trains.
RESUMABLE_CHANGES = ("num_workers", "threads", "device")


#: What ``best/`` is selected by first (``TrainConfig.select_by``;
#: :meth:`vvloc.train.Trainer.selection_key`).
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
    the paper's test; :mod:`vvloc.localize.loops`): each validated epoch then also counts the
    loop closures that all frames of those sessions accept at ``radius`` and how many join two
    floors (:func:`vvloc.train.loop_validation`), and ``best/`` goes to the epoch with the fewest
    such cross-floor pairs (summed over the entries), ties by the Recall@1 figures above. Needs
    ``val_sessions``.
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
    ``head_epochs`` (default 0) adds the head stage (:mod:`vvloc.train`): ``head_steps_per_epoch``
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
    ``local_epochs`` (default 0) adds the local stage (:mod:`vvloc.train`), after the head stage:
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
    weight_decay: float = 0.0  # Adam's L2 weight decay, in every stage's optimizer
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
                "a str (quote one YAML reads as a date, number or bool: '2012-01-08', 'on')",
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
            if value is None and str(f.type).startswith("list["):
                hint = " (a key left empty, its entries commented out?: write [] for none)"
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
            empty = " (a key left empty?: write [] for none)" if restarts is None else ""
            raise ValueError(
                f"hard_pool_restarts: expected a list of 1-based epochs (ints >= 1), got "
                f"{restarts!r}{empty}"
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
