"""Global + metric localization against a map: retrieve → re-rank → metric pose + confidence.

Pipeline per query frame (DESIGN.md §1):

1. encode the query once (:meth:`VVLocNet.encode`): BEV (H, W, C), global descriptor (Dg,),
   local-view descriptor (T, C);
2. top-K retrieval (K = 20) of map keyframes by global-descriptor L2 distance
   (:class:`vvloc.DescriptorIndex`);
3. re-ranking of the K candidates by yaw matching cost without padding: the interactor runs
   once over the K (query, candidate) pairs, the Rust kernel finds each pair's exact yaw minimum;
4. metric localization against the best candidate: the Rust :class:`TranslationSearch` proposes
   translations, ``pad_polar`` pads + polar-samples the query BEV for the whole stage, the
   decoder and the interactor run once per stage (batched), ``estimate_yaw`` scores them.
   With ``metric_candidates`` M > 1 the coarse stage is run against each of the first M
   retrieved candidates (``metric_from="retrieval"``, the default; or the first M re-ranked,
   ``"rerank"``), the query decoded once, the interactor per candidate, and the one of lowest
   coarse cost plus ``retrieval_weight`` × its global-descriptor distance goes through the fine
   stages (:func:`metric_localize_best`);
5. snapping (``snap``, default on): the query's metric world pose picks the reported keyframe,
   the retrieved candidate nearest to it (on the matched keyframe's floor); the relative pose
   is re-expressed in that keyframe's frame (the world pose does not change).

Frames: the search estimates ξ_{q→m}, the map keyframe's frame expressed in the query's frame
(the query BEV is the padded source). Results report ``relative_pose`` = ξ_{m→q} (the query
expressed in the map keyframe's frame: x forward, y left, metres; yaw CCW, radians) and the
query's global pose T_world_q = T_world_m · ξ_{m→q}. The matching cost is the confidence:
lower is better; ``accepted`` = cost < ``accept_threshold`` (0.75, the paper's filter) and
distinctiveness >= ``min_distinctiveness`` (the model's calibration; 0 without one). A query
frame without image content (:func:`vvloc.data.has_image_content`: every camera flat) is
localized but never accepted, and :func:`build_map` leaves such frames out of a map: any two of
them match at a cost near 0 wherever they were taken.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import json
import math
import os
import time
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from tqdm import tqdm

from vvloc import geometry, kernels
from vvloc._checks import flag, int_array, positive_int, real_array
from vvloc._io import list_entries
from vvloc.checkpoints import checkpoint_folder
from vvloc.data import Camera, Dataset, Frame, Session
from vvloc.data.frame import (
    PINHOLE,
    RIGID,
    has_image_content,
    is_pinhole,
    is_rigid,
    stack_calibration,
)
from vvloc.data.rig import (
    SAME_MAP,
    SAME_MODEL,
    describe_rig,
    rig_difference,
    without_levelling,
)
from vvloc.data.sampling import check_session_names
from vvloc.localize.mapdb import MapDatabase
from vvloc.localize.mapfile import MapError, check_weights, is_map_file
from vvloc.localize.mapwriter import MapWriter, _check_dtype, check_unit_rows
from vvloc.localize.metric import (
    METRIC_CANDIDATES,
    RETRIEVAL_WEIGHT,
    RadialMeanDecoder,
    SearchConfig,
    metric_localize_best,
)
from vvloc.nets import VVLocNet
from vvloc.nets.model import resolve_device
from vvloc.retrieval import DescriptorIndex

__all__ = [
    "DECODE_CHUNK_ELEMENTS",
    "MAX_ENCODED",
    "METRIC_FROM",
    "TARGET_COPIES",
    "Encoded",
    "LocalizationResult",
    "Localizer",
    "build_map",
    "check_map_model",
    "check_training_rig",
    "decode_in_chunks",
    "encode_frames",
    "first_tasa_repeated",
    "frames_to_tensors",
    "learned_matcher",
    "model_device",
    "rerank_learned",
]

F32 = npt.NDArray[np.float32]

#: Where :class:`Localizer`'s M metric candidates come from (``metric_from``): the first M of
#: the retrieval order, or of the yaw re-ranking.
METRIC_FROM = ("retrieval", "rerank")


#: The largest magnitude :meth:`Localizer.localize_encoded` takes in an encoded query: the
#: encoder's global descriptors are L2-normalised and its local-view descriptors and BEVs of
#: order 1, and products of values far beyond this overflow the float32 sums of retrieval and
#: matching.
MAX_ENCODED = 1e6


@dataclass
class Encoded:
    """Encoder outputs of N frames as numpy arrays (float32).

    ``bev`` (N, H, W, C) (None when not requested), ``global_desc`` (N, Dg) L2-normalised,
    ``local_desc`` (N, T, C).
    """

    global_desc: F32
    local_desc: F32
    bev: F32 | None


def frames_to_tensors(
    frames: Sequence[Frame], device: torch.device
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Stack frames into model inputs: images (B, M, 3, H, W) in the frames' dtype (uint8 0-255,
    or float32 [0, 1] for float frames), K (B, M, 3, 3) float32,
    cam_to_ego (B, M, 4, 4) float32, on ``device``. The frames must share one image shape and
    dtype (``ValueError`` naming the first that does not: stacked with a float frame, a uint8
    one would keep its 0-255 values on the [0, 1] scale)."""
    if not frames:
        raise ValueError("frames: expected at least one frame")
    for i, f in enumerate(frames):
        if f.images.shape != frames[0].images.shape:
            raise ValueError(
                f"frames[{i}]: images {f.images.shape}, frames[0] {frames[0].images.shape}: "
                "frames stacked into one batch must share camera count and image size"
            )
        if f.images.dtype != frames[0].images.dtype:
            raise ValueError(
                f"frames[{i}]: images of dtype {f.images.dtype}, frames[0] "
                f"{frames[0].images.dtype}: frames stacked into one batch must share the dtype"
            )
    images = torch.from_numpy(np.stack([f.images for f in frames])).to(device)
    k = torch.from_numpy(np.stack([f.K for f in frames]).astype(np.float32)).to(device)
    t = torch.from_numpy(np.stack([f.cam_to_ego for f in frames]).astype(np.float32)).to(device)
    return images, k, t


def _check_images(images: Any, name: str) -> None:
    """A frame's images: (M, 3, H, W) uint8 [0, 255], or float in [0, 1] (the network's two
    scales), finite; ``ValueError``/``TypeError`` naming ``name`` otherwise. A float image on
    the 0-255 scale would be read as far too bright, and a NaN pixel spreads through the BEV
    into the global descriptor."""
    arr = np.asarray(images)
    if arr.ndim != 4 or arr.shape[1] != 3 or 0 in arr.shape:
        raise ValueError(f"{name}: expected shape (M, 3, H, W), got {arr.shape}")
    if arr.dtype == np.uint8:
        return
    if not np.issubdtype(arr.dtype, np.floating):
        raise TypeError(f"{name}: expected uint8 or float in [0, 1], got dtype {arr.dtype}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: holds non-finite values (NaN or inf)")
    lo, hi = float(arr.min()), float(arr.max())
    if lo < 0.0 or hi > 1.0:
        raise ValueError(
            f"{name}: float images must lie in [0, 1], got values in [{lo:g}, {hi:g}] "
            "(pass uint8 for the 0-255 scale)"
        )


def _check_calibration(K: Any, cam_to_ego: Any, cameras: int, name: str) -> None:
    """A frame's calibration, as a dataset's ``rig.json`` is held to (:class:`Camera`): K
    (M, 3, 3) finite pinhole matrices (fx, fy > 0, bottom row 0 0 1), cam_to_ego (M, 4, 4)
    rigid transforms, M = ``cameras``; ``ValueError`` naming ``name.K`` / ``name.cam_to_ego``
    otherwise (a singular transform failed inside the encoder's matrix inverse)."""
    K, T = np.asarray(K), np.asarray(cam_to_ego)
    if K.shape != (cameras, 3, 3) or not np.isfinite(K).all():
        got = f"shape {K.shape}" if K.shape != (cameras, 3, 3) else "non-finite values"
        raise ValueError(f"{name}.K: expected finite ({cameras}, 3, 3) intrinsics, got {got}")
    if T.shape != (cameras, 4, 4) or not np.isfinite(T).all():
        got = f"shape {T.shape}" if T.shape != (cameras, 4, 4) else "non-finite values"
        raise ValueError(
            f"{name}.cam_to_ego: expected finite ({cameras}, 4, 4) transforms, got {got}"
        )
    if not is_pinhole(K):
        raise ValueError(f"{name}.K: expected a {PINHOLE} per camera")
    if not is_rigid(T):
        raise ValueError(f"{name}.cam_to_ego: expected a {RIGID} per camera")


def model_device(model: torch.nn.Module) -> torch.device:
    """The device of the model's parameters."""
    return next(model.parameters()).device


def _cost_threshold(value: Any, name: str) -> float:
    """A matching-cost acceptance threshold: a real number, not NaN (which would accept nothing
    without saying so); ±inf are allowed (accept every / no result)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name}: expected a float, got {type(value).__name__}")
    if np.isnan(value):
        raise ValueError(f"{name}: expected a number, got NaN")
    return float(value)


@torch.no_grad()
def encode_frames(
    model: VVLocNet,
    frames: Iterable[Frame],
    *,
    batch_size: int = 8,
    keep_bev: bool = False,
    progress: bool = False,
    total: int | None = None,
) -> Encoded:
    """Encode frames in batches of up to ``batch_size`` (eval mode, no gradients); see
    :class:`Encoded`. A frame whose images differ in shape (camera count, image size) or dtype
    (uint8 0-255 or float [0, 1]) from the batch's begins a new batch."""
    model.eval()
    device = model_device(model)
    g_all: list[F32] = []
    l_all: list[F32] = []
    b_all: list[F32] = []
    batch: list[Frame] = []

    def flush() -> None:
        out = model.encode(*frames_to_tensors(batch, device))
        g_all.append(out.global_desc.float().cpu().numpy())
        l_all.append(out.local_desc.float().cpu().numpy())
        if keep_bev:
            b_all.append(out.bev.float().cpu().numpy())
        batch.clear()

    for f in tqdm(frames, desc="encode", total=total, disable=not progress, leave=False):
        if batch and (
            f.images.shape != batch[0].images.shape or f.images.dtype != batch[0].images.dtype
        ):
            flush()  # frames of another rig, image size or scale stack only with their own kind
        batch.append(f)
        if len(batch) == batch_size:
            flush()
    if batch:
        flush()
    if not g_all:
        raise ValueError("frames: expected at least one frame")
    return Encoded(
        global_desc=np.concatenate(g_all),
        local_desc=np.concatenate(l_all),
        bev=np.concatenate(b_all) if keep_bev else None,
    )


#: On the CPU the decoder runs on the hypotheses of a search stage in chunks of about this many
#: polar-BEV elements (N_chunk · T · R · C; 2^19 = 8 hypotheses of the small model). The
#: decoder works on each angle of each hypothesis alone, so chunking changes no result (bit for
#: bit here: the localizer's answers on the demo world are unchanged); a stage's whole batch
#: (121 coarse hypotheses) allocates activations of 30-60 MB per layer, which the allocator
#: takes from the OS afresh each time (page faults are slow in a VM) and which overflow the
#: cache (BENCHMARKS.md, "The metric stage's networks without waste"). On a GPU the batch
#: stays whole.
DECODE_CHUNK_ELEMENTS = 1 << 19


def decode_in_chunks(model: VVLocNet, polar: torch.Tensor) -> torch.Tensor:
    """The decoder on polar BEVs (N, T, R, C) → local-view descriptors (N, T, C), N ≥ 1, on the
    CPU in chunks of about :data:`DECODE_CHUNK_ELEMENTS` elements, at least one hypothesis each
    (the same result as one batch: the decoder treats each (hypothesis, angle) row on its own),
    elsewhere in one batch."""
    if polar.device.type != "cpu":
        return model.decode_polar(polar)
    per = max(1, DECODE_CHUNK_ELEMENTS // max(1, polar[:1].numel()))
    if polar.shape[0] <= per:
        return model.decode_polar(polar)
    return torch.cat([model.decode_polar(p) for p in polar.split(per)])


#: The interactor's first TASA sees one side of a pair alone, so :func:`learned_matcher` runs
#: it once per target and stage size, on this many copies of it, rather than on one copy per
#: hypothesis (121 in the coarse stage; a stage of fewer hypotheses N uses N copies, as
#: before), and :func:`rerank_learned` once per query. Not on a
#: single copy: for a batch of one to three sequences MKL picks GEMM kernels that round
#: differently, and from four copies on the rows do not depend on the batch, so 8 copies give
#: the per-hypothesis batch's result bit for bit on the CPU with torch's MKL (elsewhere within
#: float rounding).
TARGET_COPIES = 8


def first_tasa_repeated(interactor: Any, row: torch.Tensor, n: int) -> torch.Tensor:
    """The interactor's first TASA (:meth:`Interactor.first_tasa`) of ``row`` (T, C) as in a
    batch of ``n`` copies of it → one row (T, C): computed on min(n, :data:`TARGET_COPIES`)
    copies (at least one), which gives the rows of the n-copy batch bit for bit with MKL."""
    copies = max(1, min(n, TARGET_COPIES))
    return interactor.first_tasa(row.expand(copies, *row.shape))[0].clone()


@torch.no_grad()
def rerank_learned(model: VVLocNet, query: torch.Tensor, cands: torch.Tensor) -> kernels.Rerank:
    """Yaw re-ranking of K candidates by the learned interactor, without padding: the query's
    local-view descriptor ``query`` (T, C) against the candidates' ``cands`` (K, T, C), on the
    model's device. Equals ``kernels.rerank`` of ``model.interact(query repeated K times,
    cands)``, with the query's first TASA run once (:func:`first_tasa_repeated`)."""
    it = model.interactor
    k = len(cands)
    src = first_tasa_repeated(it, query, k).expand(k, *query.shape).contiguous()
    a, b = it.after_first_tasa(src, it.first_tasa(cands))
    return kernels.rerank(a.float().cpu().numpy(), b.float().cpu().numpy())


def learned_matcher(
    model: VVLocNet, desc_tgts: F32
) -> tuple[Callable[[F32], torch.Tensor], Callable[[torch.Tensor, int], tuple[F32, F32]]]:
    """The ``decode`` and ``interact`` callbacks of :func:`metric_localize_best` for the learned
    networks (eval mode, as :func:`encode_frames`; no gradients). ``decode`` takes padded polar
    BEVs (N, T, R, C) float32 through the decoder (:func:`decode_in_chunks`) and the part of the
    interactor that sees the hypotheses alone (:meth:`Interactor.first_tasa`), once for every
    target → (N, T, C), a torch tensor on the model's device; ``interact(ds, k)`` finishes the
    interactor against target k of ``desc_tgts`` (M, T, C) → (Ds', Dt') each (N, T, C)
    float32. Together they equal ``model.interact(model.decode_polar(polar), target k repeated
    N times)``; each target's first TASA runs once per stage size
    (:func:`first_tasa_repeated`)."""
    model.eval()
    device = model_device(model)
    tgts = torch.from_numpy(np.ascontiguousarray(desc_tgts, dtype=np.float32)).to(device)
    interactor = model.interactor
    tgt_first: dict[tuple[int, int], torch.Tensor] = {}  # (k, N) → first TASA (T, C)

    @torch.no_grad()
    def decode(polar: F32) -> torch.Tensor:
        return interactor.first_tasa(decode_in_chunks(model, torch.from_numpy(polar).to(device)))

    @torch.no_grad()
    def interact(ds: torch.Tensor, k: int) -> tuple[F32, F32]:
        n = ds.shape[0]
        if (k, n) not in tgt_first:
            tgt_first[k, n] = first_tasa_repeated(interactor, tgts[k], n)
        tgt = tgt_first[k, n].expand(n, *tgts.shape[1:]).contiguous()
        a, b = interactor.after_first_tasa(ds, tgt)
        return a.float().cpu().numpy(), b.float().cpu().numpy()

    return decode, interact


def _check_model(model: Any) -> None:
    """``TypeError`` naming ``model`` when it is not a :class:`VVLocNet`."""
    if not isinstance(model, VVLocNet):
        raise TypeError(
            f"model: expected a VVLocNet (VVLocNet.load(checkpoint)), got {type(model).__name__}"
        )


def check_map_model(mapdb: MapDatabase, model: VVLocNet, *, stacklevel: int = 2) -> None:
    """Refuse a map that ``model`` did not build: :class:`~vvloc.localize.mapfile.MapError` (a
    ``ValueError``) when its config hash or its weights fingerprint differs from the model's,
    or its descriptors' or BEVs' shapes per keyframe are not the model's outputs'; a
    ``UserWarning`` when the map records no weights fingerprint (written by an older vvloc),
    and when its rig is not the model's training rig (:func:`check_training_rig`; maps of
    vvloc before 2026-12-05 record no rig and are not checked). ``stacklevel``: which frame
    the warnings name, 1 the line calling this function, 2 (the default) its caller's.
    """
    where = mapdb.label
    if mapdb.config_hash != model.config_hash():
        raise MapError(
            f"{where}: built with model {mapdb.config_hash}, "
            f"but the model is {model.config_hash()}; rebuild the map with this model"
        )
    check_weights(mapdb.weights_hash, model.weights_hash(), where)
    # a map assembled from arrays (MapDatabase.from_arrays, MapWriter) records the model's
    # hashes but may hold arrays of other networks: refused here, not as wrong poses later
    cfg = model.config
    shapes = [
        ("global descriptors", (mapdb.global_dim,), (model.global_dim,)),
        ("local-view descriptors", tuple(mapdb.local_shape), (cfg.num_angles, cfg.channels)),
    ]
    if mapdb.bev_shape is not None:
        shapes.append(
            ("BEVs", tuple(mapdb.bev_shape), (cfg.bev_height, cfg.bev_width, cfg.channels))
        )
    for what, got, want in shapes:
        if got != want:
            raise MapError(
                f"{where}: its {what} are {got} per keyframe, the model's {want}: not the "
                "outputs of this model's networks (build maps with build_map or vvloc map build)"
            )
    if mapdb.rig is not None:
        rig = [Camera.from_json(c) for c in mapdb.rig]
        check_training_rig(model, rig, f"{where}'s rig", stacklevel=stacklevel + 1)


#: (weights fingerprint, rig) pairs warned about by :func:`check_training_rig`: building a map
#: and localizing on it in one process warn once.
_WARNED_RIGS: set[tuple[str, str]] = set()


def check_training_rig(
    model: VVLocNet, cameras: Sequence[Camera], what: str, *, stacklevel: int = 2
) -> str:
    """Warn (``UserWarning``, once per weights and rig in a process) when ``cameras`` (image
    order, one image size) leave every rig ``model`` was trained on
    (:attr:`VVLocNet.training_rigs`) by more than :data:`vvloc.data.rig.SAME_MODEL`: other
    cameras, another image size or another mounting. The networks met only their training
    rigs (each camera slot has a learnt embedding), so descriptors and poses from another may
    be far off, and nothing else would say so. ``what`` names the rig in the message ("map
    x.h5's rig"); ``stacklevel``: which frame the warning names, 1 the line calling this
    function, 2 (the default) its caller's. Returns the difference from the first training rig
    in words, "" when one of them matches or the model records none."""
    trained = model.training_rigs
    if not trained or not cameras:
        return ""
    K, cam_to_ego = stack_calibration(cameras)
    size = (cameras[0].width, cameras[0].height)
    whys = [rig_difference(rig, K, cam_to_ego, size, SAME_MODEL) for rig in trained]
    if "" in whys:
        return ""
    key = (model.weights_hash(), json.dumps([c.to_json() for c in cameras]))
    if key not in _WARNED_RIGS:
        n = len(trained) - 1
        others = f" and {n} other rig{'' if n == 1 else 's'}" if n else ""
        warnings.warn(
            f"{what} is not the rig the model was trained on ({whys[0]}; trained on "
            f"{describe_rig(trained[0])}{others}): the networks met only their training rigs, "
            "so their descriptors and poses on this one may be far off. Train on this rig's "
            "data (README, 'Your own rig's data'), or measure the model on it with vvloc eval "
            "first",
            UserWarning,
            stacklevel=stacklevel + 1,
        )
        _WARNED_RIGS.add(key)  # after the warning: one turned into an error is given again
    return whys[0]


@dataclass
class LocalizationResult:
    """The localization of one query frame.

    Attributes:
        map_row: row of the chosen keyframe in the map (-1 when the map is empty).
        map_id: its keyframe id; ``map_session`` its session; ``map_seq`` its sequence number
            there (:attr:`MapDatabase.seq`: for a map of :func:`build_map`, the keyframe's
            frame index in that session of the dataset, with which to find its images; -1 when
            the map is empty).
        relative_pose: ξ_{m→q} (3,) float64: the query frame expressed in the map keyframe's
            frame (x forward m, y left m, yaw CCW rad).
        global_pose: the query's world pose (x, y, yaw) (3,) float64, metres and radians,
            world frame: T_world_m · ξ_{m→q}.
        cost: matching cost at the estimate (lower is better), against ``metric_row``.
        accepted: ``cost < accept_threshold`` and ``distinctiveness >= min_distinctiveness``,
            and ``has_content``.
        retrieved: (K,) int64 map rows in retrieval order, K = min(``top_k``, map size) (0
            for an empty map); ``retrieval_dist`` (K,) float32 their L2 descriptor distances.
        reranked: (K,) int64, the same map rows: the M metric candidates (see
            ``Localizer(metric_from=)``) by coarse metric cost plus ``retrieval_weight`` ×
            descriptor distance, then the others by yaw matching cost (with ``snap``, the
            snapped keyframe first); ``rerank_cost`` their yaw matching costs, in the same
            order.
        timings_ms: per-stage wall time in milliseconds: encode, retrieve, rerank, metric.
            ``localize_batch`` encodes its frames together: each result's ``encode`` is the
            batch's encoding time divided by its number of frames (the same for all of them).
        search: every evaluated translation hypothesis (xy (M, 2), yaw, cost, stage) of the
            search against ``metric_row`` (ξ_{q→m} hypotheses, query frame).
        distinctiveness: mean minus minimum of ``rerank_cost`` (≥ 0; higher = the best
            re-ranked candidate stands out more; NaN without re-ranking), the calibrated
            confidence (:func:`vvloc.evaluate.distinctiveness`). It is about the re-ranking's
            best candidate, which the metric stage (its M candidates, ``metric_from``) and
            snapping may replace by another keyframe; ``vvloc calibrate`` sets its threshold
            on the reported keyframes (:func:`vvloc.localize.calibrate.calibrate_localizer`).
        metric_row: the map row the metric pose was estimated against (equals ``map_row``
            unless snapping chose a nearer keyframe; -1 when the map is empty).
        map_floor: the chosen keyframe's floor, as its session numbers them (the storey the
            query is on when the answer is right; ``global_pose`` has no height). Meaningless
            when ``map_row`` is -1 (an empty map; floors may be negative, so -1 there is only
            a filler).
        has_content: whether the query frame has image content
            (:func:`vvloc.data.has_image_content`); a frame without any is localized but not
            accepted. True for :meth:`Localizer.localize_encoded`, which sees no images.
    """

    map_row: int
    map_id: int
    map_session: str
    relative_pose: npt.NDArray[np.float64]
    global_pose: npt.NDArray[np.float64]
    cost: float
    accepted: bool
    retrieved: npt.NDArray[np.int64]
    retrieval_dist: F32
    reranked: npt.NDArray[np.int64]
    rerank_cost: npt.NDArray[np.float64]
    timings_ms: dict[str, float] = field(default_factory=dict)
    search: kernels.SearchHistory | None = None
    distinctiveness: float = float("nan")
    metric_row: int = -1
    map_floor: int = -1
    has_content: bool = True
    map_seq: int = -1

    def __repr__(self) -> str:
        """One line: the answer, its confidence and the sizes of the arrays (the default
        dataclass repr printed every search hypothesis, hundreds of lines)."""

        def pose(p: npt.NDArray[np.float64]) -> str:
            x, y, yaw = (float(v) for v in p)
            return f"(x={x:.3f} m, y={y:.3f} m, yaw={math.degrees(yaw):.2f}°)"

        top = ", ".join(str(int(r)) for r in self.reranked[:5])
        more = ", …" if len(self.reranked) > 5 else ""
        hypotheses = "None" if self.search is None else f"<{len(self.search.cost)} hypotheses>"
        timings = ", ".join(f"{k}={v:.1f}" for k, v in self.timings_ms.items())
        return (
            f"LocalizationResult(map_row={self.map_row}, map_id={self.map_id}, "
            f"map_session={self.map_session!r}, map_floor={self.map_floor}, "
            f"accepted={self.accepted}{'' if self.has_content else ' (no image content)'}, "
            f"cost={self.cost:.4f}, "
            f"distinctiveness={self.distinctiveness:.4f}, "
            f"relative_pose={pose(self.relative_pose)}, global_pose={pose(self.global_pose)}, "
            f"metric_row={self.metric_row}, reranked=[{top}{more}] of {len(self.reranked)}, "
            f"retrieved=<{len(self.retrieved)} rows>, search={hypotheses}, "
            f"timings_ms={{{timings}}})"
        )


#: Frames between a ``Localizer``'s ``__init__`` and the code that asked for it: 1 while
#: :meth:`Localizer.open` makes one, so that the warnings of ``__init__`` name the line of
#: user code in either case.
_OPENER_FRAMES: contextvars.ContextVar[int] = contextvars.ContextVar("_OPENER_FRAMES", default=0)


def _check_calibration_settings(
    calibration: Mapping[str, Any],
    top_k: int,
    accept_threshold: float,
    stacklevel: int = 4,
    map_size: int | None = None,
) -> None:
    """Warn when a localizer applies a calibration measured with other settings: the
    distinctiveness (mean − minimum of the K re-ranking costs) depends on K, and the precision
    reached depends on the cost rule. ``stacklevel``: the frame the warnings name; ``map_size``:
    the map's keyframes when fewer than the localizer's top_k cut K to them (said so)."""
    threshold = calibration.get("min_distinctiveness")
    if not threshold:
        return
    if threshold == float("inf"):
        warnings.warn(
            "the model's calibration accepts nothing (no distinctiveness threshold reached its "
            "target precision on the validation sessions): every result has accepted=False; "
            "calibrate with vvloc calibrate, or pass min_distinctiveness",
            stacklevel=stacklevel,
        )
        return
    cal_k, cal_cost = calibration.get("top_k"), calibration.get("accept_threshold")
    if cal_k is not None and int(cal_k) != top_k:
        small = map_size is not None and map_size == top_k
        warnings.warn(
            f"the model's calibration was measured with top_k={int(cal_k)}, this localizer "
            f"re-ranks {top_k} candidates"
            + (f" (all the map holds: {map_size} keyframes)" if small else "")
            + ": distinctiveness depends on K, so its precision is not the calibrated one "
            "(vvloc calibrate with these settings, or pass min_distinctiveness)"
            + ("; a map of more keyframes re-ranks the calibrated K" if small else ""),
            stacklevel=stacklevel,
        )
    if cal_cost is not None and float(cal_cost) != accept_threshold:
        warnings.warn(
            f"the model's calibration was measured with accept_threshold={float(cal_cost):g}, "
            f"this localizer uses {accept_threshold:g}: its precision is not the calibrated one",
            stacklevel=stacklevel,
        )


class Localizer:
    """Localizes query frames against a :class:`MapDatabase` with a :class:`VVLocNet`.

    Args:
        model: the network that built the map (config hash and weights fingerprint are
            checked: :func:`check_map_model`).
        mapdb: an opened map.
        top_k: number of retrieved candidates (K, default 20).
        rerank: re-rank the candidates by yaw matching cost (default True).
        accept_threshold: a result is accepted when its cost is below this (default 0.75, the
            paper's) and its distinctiveness reaches ``min_distinctiveness``.
        min_distinctiveness: the calibrated confidence threshold; ``None`` (default) takes the
            model's calibration (``calibration.json`` beside its weights, written by ``vvloc
            calibrate`` or by training with validation sessions), and 0 (no check) when the
            model has none.
        search: the translation search (see :class:`SearchConfig`).
        metric_candidates: M, how many candidates get a metric localization (default
            :data:`METRIC_CANDIDATES`, 5, with ``retrieval_weight`` 2; 3 before 2026-12-03,
            chosen on validation sessions with the candidates taken from the re-ranking: 82.8 %
            → 85.9 % Recall@1 at 2 m for about 1.2× the metric stage's time; 1 = only the
            first one). Without the descriptor distance more candidates are not better: on
            the parking validation M = 5 loses 1-2 points to M = 3 at λ = 0. With M > 1 the
            coarse translation stage runs against each of the M (the first M of
            ``metric_from``'s ordering; the query's padded BEVs decoded once, the interactor
            and the yaw kernel per candidate), the M are ordered by their coarse cost plus
            ``retrieval_weight`` × their global-descriptor distance, and the lowest goes
            through the fine stages (:func:`metric_localize_best`). Without re-ranking both
            orderings are the retrieval's.
        metric_from: which ordering the M metric candidates are the first of: ``"retrieval"``
            (global-descriptor distance) or ``"rerank"`` (the yaw matching cost without
            padding). Either way the M come first in ``reranked``, by their score (coarse cost +
            λ·distance), and the other candidates follow in yaw re-ranked order. Default
            ``"retrieval"``: the cost without padding cannot see translation, so it is the
            poorer pre-filter for the metric stage (674 parking validation queries, Recall@1
            at 2 m: 83.4 % → 87.7 % for ``models/synth-small-v1``; DESIGN.md §1).
        retrieval_weight: λ ≥ 0, the weight of a metric candidate's global-descriptor L2
            distance (unit-norm descriptors, so in [0, 2]) added to its coarse matching cost
            when the M candidates are ordered (default :data:`RETRIEVAL_WEIGHT`; 0: the
            coarse cost alone). The two are separate evidence: the descriptor sees the whole
            BEV, the cost the local views around one translation.
        snap: report the retrieved keyframe nearest to the query's metric world pose (on the
            metric-matched keyframe's floor) instead of the matched one (default True): the
            metric pose says where the query is, so the nearest candidate is the place; the
            world pose is unchanged and ``relative_pose`` is expressed in the reported
            keyframe's frame (``metric_row`` keeps the matched one).
        decoder: ``"learned"`` (the model's decoder + interactor, default) or ``"radial_mean"``
            (the non-learned :class:`RadialMeanDecoder`, no interactor: a baseline, and the
            geometry oracle's decoder; the map's local descriptors must then be radial means).

    In a service: one localizer may serve several threads at once (its answers are those of
    calls one after the other); a process forked from it starts with torch on one thread
    (:mod:`vvloc.nets`, README "Threads"); it reads the map file it opened until
    :meth:`close`, so a map rebuilt with ``vvloc map build --overwrite`` (a new file renamed
    over the old) is seen by a localizer opened after it; never copy a map over one a process
    has open. The first call is slower (torch's first allocations): warm up with one query
    before timing.
    """

    def __init__(
        self,
        model: VVLocNet,
        mapdb: MapDatabase,
        *,
        top_k: int = 20,
        rerank: bool = True,
        accept_threshold: float = 0.75,
        min_distinctiveness: float | None = None,
        search: SearchConfig | None = None,
        metric_candidates: int = METRIC_CANDIDATES,
        metric_from: str = "retrieval",
        retrieval_weight: float = RETRIEVAL_WEIGHT,
        snap: bool = True,
        decoder: str = "learned",
    ) -> None:
        if decoder not in ("learned", "radial_mean"):
            raise ValueError(f"decoder: expected 'learned' or 'radial_mean', got {decoder!r}")
        if not isinstance(metric_from, str):
            raise TypeError(f"metric_from: expected a str, got {type(metric_from).__name__}")
        if metric_from not in METRIC_FROM:
            raise ValueError(f"metric_from: expected one of {METRIC_FROM}, got {metric_from!r}")
        _check_model(model)
        if not isinstance(mapdb, MapDatabase):
            raise TypeError(
                f"mapdb: expected a MapDatabase (MapDatabase.open(path), or Localizer.open(map "
                f"path, checkpoint)), got {type(mapdb).__name__}"
            )
        mapdb._check_open()  # a closed map was taken here and refused only at the first query
        up = _OPENER_FRAMES.get()  # the warnings below name the line that made this localizer
        check_map_model(mapdb, model, stacklevel=2 + up)
        self.model = model.eval()
        self.map = mapdb
        self.top_k = positive_int(top_k, "top_k")
        flag(rerank, "rerank")
        self.rerank_enabled = bool(rerank)
        self.accept_threshold = _cost_threshold(accept_threshold, "accept_threshold")
        if min_distinctiveness is None:
            min_distinctiveness = model.calibration.get("min_distinctiveness", 0.0)  # type: ignore[assignment]
            _check_calibration_settings(
                model.calibration,
                min(self.top_k, len(mapdb)),
                self.accept_threshold,
                stacklevel=3 + up,
                map_size=len(mapdb) if len(mapdb) < self.top_k else None,
            )
            if not self.rerank_enabled and min_distinctiveness:
                # the calibration scores re-ranking costs: without them only the cost rule is left
                warnings.warn(
                    f"rerank=False: the model's calibration (min_distinctiveness "
                    f"{min_distinctiveness:.4g}) needs the re-ranking costs; accepting by the "
                    "cost rule alone",
                    stacklevel=2 + up,
                )
                min_distinctiveness = 0.0
        elif not self.rerank_enabled and min_distinctiveness:
            raise ValueError(
                f"min_distinctiveness: {min_distinctiveness} needs re-ranking (distinctiveness is "
                "measured on the re-ranking costs); pass rerank=True or min_distinctiveness=0"
            )
        if isinstance(min_distinctiveness, np.floating):
            min_distinctiveness = float(min_distinctiveness)
        if isinstance(min_distinctiveness, bool) or not isinstance(
            min_distinctiveness, (int, float)
        ):
            raise TypeError(
                f"min_distinctiveness: expected a float, got {type(min_distinctiveness).__name__}"
            )
        if not min_distinctiveness >= 0:
            raise ValueError(f"min_distinctiveness: expected >= 0, got {min_distinctiveness}")
        self.min_distinctiveness = float(min_distinctiveness)
        if 0 < self.min_distinctiveness < float("inf") and min(self.top_k, len(mapdb)) == 1:
            warnings.warn(
                f"one re-ranking candidate (top_k={self.top_k}, {len(mapdb)} keyframes in the "
                f"map): its distinctiveness is 0, below min_distinctiveness "
                f"{self.min_distinctiveness:.4g}, so no result is accepted (pass "
                "min_distinctiveness=0 to accept by the cost rule alone)",
                stacklevel=2 + up,
            )
        self.metric_candidates = positive_int(metric_candidates, "metric_candidates")
        self.metric_from = metric_from
        if isinstance(retrieval_weight, np.floating):
            retrieval_weight = float(retrieval_weight)
        if isinstance(retrieval_weight, bool) or not isinstance(retrieval_weight, (int, float)):
            raise TypeError(
                f"retrieval_weight: expected a float, got {type(retrieval_weight).__name__}"
            )
        if not 0 <= retrieval_weight < float("inf"):
            raise ValueError(
                f"retrieval_weight: expected a finite value >= 0, got {retrieval_weight}"
            )
        self.retrieval_weight = float(retrieval_weight)
        flag(snap, "snap")
        self.snap = bool(snap)
        if search is not None and not isinstance(search, SearchConfig):
            raise TypeError(f"search: expected a SearchConfig, got {type(search).__name__}")
        self.search = search or SearchConfig()
        self.search.validate()  # a bad configuration fails here, by name, not at a query
        self.decoder = decoder
        self.index = DescriptorIndex(mapdb.global_descriptors)
        self._rig_warned = False  # a query from another rig is reported once (_check_rig)
        self._map_rig = None if mapdb.rig is None else [Camera.from_json(c) for c in mapdb.rig]
        cfg = model.config
        self.grid_size = float(cfg.grid_size)
        self.num_angles = int(cfg.num_angles)
        self.num_radii = int(cfg.num_radii)

    @classmethod
    def open(
        cls,
        map_path: str | os.PathLike[str],
        checkpoint: str | os.PathLike[str],
        *,
        device: str | torch.device = "cpu",
        **kwargs: Any,
    ) -> Localizer:
        """Load a checkpoint directory and open a map built with it (refused otherwise, see
        :func:`check_map_model`; the map is closed again when the localizer cannot be made).
        ``checkpoint`` may also be a training run's folder: its ``best/`` when it has one, else
        its ``checkpoint/``, as the CLI takes it. ``device``: where the network runs ("cpu",
        "cuda", "cuda:1"; the kernels run on the CPU). ``**kwargs``: the localizer's settings,
        passed to :class:`Localizer` (``top_k``, ``metric_candidates``, ``search``, ...)."""
        model = VVLocNet.load(checkpoint_folder(checkpoint, "checkpoint")).to(
            resolve_device(device)
        )
        mapdb = MapDatabase.open(map_path, expected_config_hash=model.config_hash())
        opener = _OPENER_FRAMES.set(1)  # __init__'s warnings name open's caller
        try:
            return cls(model, mapdb, **kwargs)
        except BaseException:
            mapdb.close()
            raise
        finally:
            _OPENER_FRAMES.reset(opener)

    def close(self) -> None:
        """Close the map (its file, for an opened one). Idempotent; every stage then raises
        ``ValueError`` (the descriptors kept in memory included)."""
        self.map.close()

    def _check_open(self) -> None:
        self.map._check_open()  # the map's own check

    def __enter__(self) -> Localizer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- stages --------------------------------------------------------------------------
    # Each public stage checks its arguments as localize_encoded does (ValueError/TypeError
    # naming them); localize_encoded checks once and calls the private ones.

    def _encoded_shape(self, name: str) -> tuple[int, ...]:
        """The shape of an encoded query's ``g``/``global_desc``, ``loc``/``local_desc`` or
        ``bev``, from the map and the model."""
        cfg = self.model.config
        if name in ("g", "global_desc"):
            return (int(self.map.global_descriptors.shape[1]),)
        if name in ("loc", "local_desc"):
            return tuple(int(v) for v in self.map.local_shape)
        return (int(cfg.bev_height), int(cfg.bev_width), int(cfg.channels))

    def _encoded(self, name: str, arr: Any) -> F32:
        """An encoded query's ``g`` (Dg,), ``loc`` (T, C) or ``bev`` (H, W, C) as float32 of
        the map's sizes, finite, within ±:data:`MAX_ENCODED` (``g``: unit length), named in the
        error otherwise."""
        want = self._encoded_shape(name)
        shape = tuple(np.shape(arr))
        if shape != want:
            raise ValueError(f"{name}: expected shape {want}, got {shape}")
        # float32 for the networks and kernels (a float64 loc reached the interactor as double)
        out = kernels._as_f32(arr, name)  # finite
        top = max(float(out.max(initial=0.0)), -float(out.min(initial=0.0)))  # no copy
        if top > MAX_ENCODED:
            raise ValueError(
                f"{name}: values up to {top:.3g}, beyond ±{MAX_ENCODED:g}: not the outputs of "
                "the encoder (its global descriptors are L2-normalised, its local-view "
                "descriptors and BEVs of order 1), and float32 sums of their products overflow"
            )
        if name in ("g", "global_desc"):
            check_unit_rows(out, name)
        return out

    def _rows(self, rows: Any, name: str = "rows") -> npt.NDArray[np.int64]:
        """Map rows (K,), K >= 1, each in [0, len(map)), named in the error otherwise (-1 is
        not the last row)."""
        arr = int_array(rows, name, "(K,)", 1)
        n = len(self.map)
        if arr.size == 0:
            raise ValueError(f"{name}: expected at least one map row")
        if arr.min() < 0 or arr.max() >= n:
            raise ValueError(f"{name}: expected map rows in [0, {n}), got {arr.tolist()!r:.80}")
        return arr

    def retrieve(self, global_desc: F32) -> tuple[npt.NDArray[np.int64], F32]:
        """Top-K map rows (K,) int64 and their L2 descriptor distances (K,) float32, nearest
        first, of one global descriptor (Dg,) (float32, unit length, as the encoder gives);
        K = min(``top_k``, map size), 0 for an empty map (no padding rows, unlike
        :meth:`DescriptorIndex.topk`'s -1)."""
        self._check_open()
        return self._retrieve(self._encoded("global_desc", global_desc))

    def _retrieve(self, global_desc: F32) -> tuple[npt.NDArray[np.int64], F32]:
        idx, dist = self.index.topk(global_desc[None], min(self.top_k, max(len(self.map), 1)))
        keep = idx[0] >= 0
        return idx[0][keep], dist[0][keep]

    def rerank(self, local_desc: F32, rows: npt.NDArray[np.int64]) -> kernels.Rerank:
        """Re-rank candidate map ``rows`` (K,) by the yaw matching cost between the query's
        local-view descriptor (T, C) float32 and each candidate's, without padding (interactor
        batched over the candidates, exact yaw minimum in Rust). The query is each pair's
        source: :class:`~vvloc.kernels.Rerank`'s ``yaw`` (K,) radians is the candidate
        keyframe's yaw in the query's frame (ξ_{q→m}'s; the query's in the keyframe's frame is
        its negative), ``cost`` (K,) the dimensionless matching cost, lower is better."""
        self._check_open()
        return self._rerank(self._encoded("local_desc", local_desc), self._rows(rows))

    @torch.no_grad()
    def _rerank(self, local_desc: F32, rows: npt.NDArray[np.int64]) -> kernels.Rerank:
        if self.decoder == "radial_mean":
            src = np.broadcast_to(local_desc, (len(rows), *local_desc.shape))
            return kernels.rerank(src, self.map.local_descriptors(rows))
        device = model_device(self.model)
        tgt = torch.from_numpy(self.map.local_descriptors(rows)).to(device)
        return rerank_learned(self.model, torch.from_numpy(local_desc).to(device), tgt)

    def metric(self, bev: F32, row: int) -> tuple[npt.NDArray[np.float64], float, Any]:
        """Metric localization of a query BEV (H, W, C) float32 (the model's ``bev``, ego frame,
        DESIGN.md §3) against map row ``row`` (an int): returns (ξ_{m→q} (3,) float64: the query
        in the keyframe's frame, metres and radians CCW; the dimensionless matching cost, lower
        is better; the search history)."""
        self._check_open()
        row = positive_int(row, "row", minimum=0)  # an int: 1.7 is not row 1
        rows = self._rows(np.array([row], dtype=np.int64), "row")  # and a row of the map
        _, xi_mq, cost, history, _ = self._metric_best(self._encoded("bev", bev), rows)
        return xi_mq, cost, history

    def metric_best(
        self, bev: F32, rows: npt.NDArray[np.int64], bias: npt.ArrayLike | None = None
    ) -> tuple[int, npt.NDArray[np.float64], float, Any, npt.NDArray[np.float64]]:
        """Metric localization of a query BEV (H, W, C) float32 (ego frame) against the best of
        map ``rows`` (M,) int (:func:`metric_localize_best`; for one row,
        :func:`metric_localize`'s search), each row's coarse cost offset by ``bias`` (M,)
        (None: zeros): returns (index into ``rows``, ξ_{m→q} (3,) float64 (the query in the
        chosen keyframe's frame, metres and radians CCW), the dimensionless cost, search
        history, each row's score (M,) float64: coarse-stage cost + bias, the chosen row the
        first of the lowest)."""
        self._check_open()
        rows = self._rows(rows)
        if bias is not None:
            bias = real_array(bias, "bias", f"({len(rows)},)", 1)
            if bias.shape != rows.shape:
                raise ValueError(f"bias: expected shape {rows.shape}, got {bias.shape}")
        return self._metric_best(self._encoded("bev", bev), rows, bias)

    def _metric_best(
        self, bev: F32, rows: npt.NDArray[np.int64], bias: npt.ArrayLike | None = None
    ) -> tuple[int, npt.NDArray[np.float64], float, Any, npt.NDArray[np.float64]]:
        tgts = self.map.local_descriptors(np.asarray(rows, dtype=np.int64))
        decode: Callable[[F32], Any]
        interact: Callable[[Any, int], tuple[Any, Any]] | None
        if self.decoder == "radial_mean":
            decode, interact = RadialMeanDecoder(), None
        else:
            decode, interact = learned_matcher(self.model, tgts)
        best = metric_localize_best(
            bev,
            tgts,
            decode,
            interact,
            self.search,
            self.grid_size,
            self.num_angles,
            self.num_radii,
            bias=bias,
        )
        xi_qm = np.asarray(best.result.pose, dtype=np.float64)
        return (
            best.index,
            geometry.inverse(xi_qm),
            float(best.result.cost),
            best.result.history,
            best.score,
        )

    def snap_row(self, global_pose: npt.ArrayLike, rows: npt.NDArray[np.int64], floor: int) -> int:
        """The row among ``rows`` (K,) nearest in x-y (metres, world frame) to ``global_pose``
        (x, y, yaw) on ``floor`` (the first on ties; -1 when none is on that floor)."""
        self._check_open()
        pose = real_array(global_pose, "global_pose", "(3,)", 1, 3)
        if isinstance(floor, bool) or not isinstance(floor, (int, np.integer)):
            raise TypeError(f"floor: expected an int, got {type(floor).__name__}")
        return self._snap_row(pose, self._rows(rows), int(floor))

    def _snap_row(self, global_pose: npt.ArrayLike, rows: npt.NDArray[np.int64], floor: int) -> int:
        on_floor = rows[self.map.floors[rows] == floor]
        if len(on_floor) == 0:
            return -1
        xy = self.map.poses[on_floor, :2]
        d = np.hypot(*(xy - np.asarray(global_pose, dtype=np.float64)[:2]).T)
        return int(on_floor[int(np.argmin(d))])

    def _check_rig(self, frame: Frame, at: str) -> None:
        """Warn (once) when ``frame`` (the caller's argument ``at``) comes from a rig other
        than the one the map records (:data:`vvloc.data.rig.SAME_MAP`), as it is and with the
        turn and shift common to all its cameras taken out
        (:func:`vvloc.data.rig.without_levelling`)."""
        if self._map_rig is None or self._rig_warned:
            return
        h, w = frame.images.shape[2:]
        why = rig_difference(self._map_rig, frame.K, frame.cam_to_ego, (w, h), SAME_MAP)
        if why:  # a tilting vehicle's levelled, motion-compensated frame is the map's rig
            level = without_levelling(self._map_rig, frame.cam_to_ego)
            if not rig_difference(self._map_rig, frame.K, level, (w, h), SAME_MAP):
                why = ""
        if why:
            self._rig_warned = True
            warnings.warn(
                f"{at}: from another rig than the map's ({why}); the model met only the "
                "rig it was trained on, and poses from another may be far off",
                stacklevel=4,  # _localize_frames, localize(_batch), its caller
            )

    # --- public --------------------------------------------------------------------------

    def localize(self, frame: Frame) -> LocalizationResult:
        """Localize one query frame (see the module docstring for the stages and frames)."""
        return self._localize_frames([frame], 1, False, "frame")[0]

    def localize_batch(
        self, frames: Iterable[Frame], *, batch_size: int = 8, progress: bool = False
    ) -> list[LocalizationResult]:
        """Localize many frames: encoding is batched (frames of another camera count or image
        size in batches of their own); results equal :meth:`localize`'s (to float rounding:
        batches of other sizes sum in other orders, ~1e-8 in the cost).

        Frames whose calibration is not M finite pinhole intrinsics and rigid camera-to-ego
        transforms, or whose images are not (M, 3, H, W) uint8 (or float in [0, 1]), are
        refused before any work (``ValueError`` naming the frame); frames
        from a rig other than the map's (camera count, image size, intrinsics, or a camera
        turned or moved from where the map's rig has it by more than
        :data:`vvloc.data.rig.SAME_MAP` allows, when the map records its rig)
        are localized with a warning, once per localizer: the model met only its training rig,
        and its poses may be far off. A tilting vehicle's levelled frames and motion-compensated
        cameras (``Session.frame_cam_to_ego``) are the map's rig: a turn (up to 35°) and shift
        (up to 3 m) common to all cameras is taken out before comparing
        (:func:`vvloc.data.rig.without_levelling`). Frames without image
        content (:func:`vvloc.data.has_image_content`: a covered rig, a black stretch) are
        localized but not accepted (``has_content`` False), with a ``UserWarning``.

        ``batch_size``: frames encoded at once (int >= 1); ``progress``: a tqdm bar over the
        frames. Returns one :class:`LocalizationResult` per frame, in order."""
        batch_size = positive_int(batch_size, "batch_size")
        if isinstance(frames, Frame) or not isinstance(frames, Iterable):
            raise TypeError(
                f"frames: expected a sequence of vvloc.data.Frame, got {type(frames).__name__}"
            )
        return self._localize_frames(list(frames), batch_size, progress, "frames")

    def _localize_frames(
        self, frames: list[Frame], batch_size: int, progress: bool, name: str
    ) -> list[LocalizationResult]:
        """:meth:`localize_batch` of checked arguments, for :meth:`localize` (``name``: the
        caller's argument, for messages) too; its warnings name the public caller's line."""
        self._check_open()  # before the frames are encoded
        single = name == "frame"  # localize's one frame, not a list
        for i, f in enumerate(frames):
            at = name if single else f"{name}[{i}]"
            if not isinstance(f, Frame):
                raise TypeError(f"{at}: expected a vvloc.data.Frame, got {type(f).__name__}")
            _check_images(f.images, f"{at}.images")
            _check_calibration(f.K, f.cam_to_ego, len(f.images), at)
            self.model.config.check_num_cameras(len(f.images), f"{at}.images")  # before encoding
            self._check_rig(f, at)
        blank = [i for i, f in enumerate(frames) if not has_image_content(f.images)]
        if blank:
            which = (
                "the query frame has"
                if single
                else f"{len(blank)} of {len(frames)} query frames have"
            )
            where = "" if single else f": {name} {list_entries([str(i) for i in blank])}"
            warnings.warn(
                f"{which} no image content (every camera's picture flat{where}); not accepted",
                UserWarning,
                stacklevel=3,
            )
        results: list[LocalizationResult] = []
        for start in tqdm(
            range(0, len(frames), batch_size), desc="localize", disable=not progress, leave=False
        ):
            chunk = frames[start : start + batch_size]
            t0 = time.perf_counter()
            enc = encode_frames(self.model, chunk, batch_size=batch_size, keep_bev=True)
            t_enc = (time.perf_counter() - t0) * 1e3 / len(chunk)
            assert enc.bev is not None
            for i in range(len(chunk)):
                results.append(
                    self.localize_encoded(enc.global_desc[i], enc.local_desc[i], enc.bev[i], t_enc)
                )
        for i in blank:
            results[i] = dataclasses.replace(results[i], accepted=False, has_content=False)
        return results

    def localize_encoded(
        self, g: F32, loc: F32, bev: F32, t_encode_ms: float = 0.0
    ) -> LocalizationResult:
        """Localize an already encoded query: global descriptor g (Dg,), local-view descriptor
        loc (T, C), BEV (H, W, C) (e.g. encoded in a batch on a GPU elsewhere), float32, of
        the map's sizes, finite and within ±:data:`MAX_ENCODED` (``ValueError`` naming the
        argument otherwise). ``t_encode_ms``: the encoding's wall time, milliseconds, reported
        as the result's ``timings_ms["encode"]``."""
        self._check_open()
        for name, arr in (("g", g), ("loc", loc), ("bev", bev)):  # shapes first, all three
            want = self._encoded_shape(name)
            if tuple(np.shape(arr)) != want:
                raise ValueError(f"{name}: expected shape {want}, got {tuple(np.shape(arr))}")
        g, loc, bev = self._encoded("g", g), self._encoded("loc", loc), self._encoded("bev", bev)
        if (
            isinstance(t_encode_ms, (bool, np.bool_))
            or not isinstance(t_encode_ms, (int, float, np.number))
            or not (math.isfinite(t_encode_ms) and t_encode_ms >= 0)
        ):
            raise ValueError(f"t_encode_ms: expected a finite time >= 0 (ms), got {t_encode_ms!r}")
        timings = {"encode": float(t_encode_ms)}
        t0 = time.perf_counter()
        rows, dist = self._retrieve(g)
        timings["retrieve"] = (time.perf_counter() - t0) * 1e3
        if len(rows) == 0:
            nan3 = np.full(3, np.nan)
            return LocalizationResult(
                -1,
                -1,
                "",
                nan3,
                nan3,
                float("inf"),
                False,
                rows,
                dist,
                rows,
                np.zeros(0),
                timings,
                None,
            )
        t0 = time.perf_counter()
        if self.rerank_enabled:
            rr = self._rerank(loc, rows)
            perm = rr.order  # reranked = rows[perm]
            rerank_cost = rr.cost[perm]
        else:
            perm, rerank_cost = np.arange(len(rows)), np.full(len(rows), np.nan)
        reranked = rows[perm]
        timings["rerank"] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        m = min(self.metric_candidates, len(reranked))
        # the M metric candidates, as positions in ``reranked``
        if self.metric_from == "rerank":
            pool = np.arange(m)
        else:  # where rows[:m] went: the inverse permutation
            pool = np.argsort(perm, kind="stable")[:m]
        bias = self.retrieval_weight * dist[perm[pool]].astype(np.float64)
        k, xi_mq, cost, history, score = self._metric_best(bev, reranked[pool], bias)
        # the M candidates by score (coarse cost + λ·distance, finite) first, the stable sort
        # putting the refined one, the first of the lowest, first; the others after them in
        # re-ranked order
        front = np.argsort(score, kind="stable")
        if front[0] != k:
            raise RuntimeError(f"metric_best chose candidate {k}, the ordering {front[0]}")
        order = np.r_[pool[front], np.setdiff1d(np.arange(len(reranked)), pool)]
        reranked, rerank_cost = reranked[order], rerank_cost[order]
        matched = int(reranked[0])
        global_pose = geometry.compose(self.map.poses[matched], xi_mq)
        best = matched
        if self.snap:
            best = self._snap_row(global_pose, reranked, int(self.map.floors[matched]))
            if best != matched:
                xi_mq = geometry.relative(self.map.poses[best], global_pose)
                front = np.flatnonzero(reranked == best)[0]
                order = np.r_[front, np.delete(np.arange(len(reranked)), front)]
                reranked, rerank_cost = reranked[order], rerank_cost[order]
        timings["metric"] = (time.perf_counter() - t0) * 1e3
        distinct = max(float(rerank_cost.mean() - rerank_cost.min()), 0.0)
        confident = self.min_distinctiveness <= 0 or bool(distinct >= self.min_distinctiveness)
        return LocalizationResult(
            map_row=best,
            map_id=int(self.map.ids[best]),
            map_session=self.map.session_of(best),
            relative_pose=xi_mq,
            global_pose=global_pose,
            cost=cost,
            accepted=bool(cost < self.accept_threshold) and confident,
            retrieved=rows,
            retrieval_dist=dist,
            reranked=reranked,
            rerank_cost=rerank_cost,
            timings_ms=timings,
            search=history,
            distinctiveness=distinct,
            metric_row=matched,
            map_floor=int(self.map.floors[best]),
            map_seq=int(self.map.seq[best]),
        )


def build_map(
    model: VVLocNet,
    dataset: Dataset,
    sessions: Iterable[str],
    out: str | os.PathLike[str],
    *,
    dtype: str | None = None,
    store_bev: bool | None = None,
    batch_size: int = 8,
    progress: bool = True,
    base: MapDatabase | str | os.PathLike[str] | None = None,
    overwrite: bool = False,
) -> Path:
    """Encode every frame of ``sessions`` of ``dataset`` and write a map to ``out`` (HDF5,
    atomically). A file at ``out`` is replaced only with ``overwrite`` and only when it is a
    vvloc map (:func:`~vvloc.localize.mapfile.is_map_file`), as ``vvloc map build --overwrite``
    does: ``FileExistsError`` naming ``out`` otherwise, before anything is encoded. ``dtype``
    is the stored dtype of the descriptors, ``"float32"`` (the default) or ``"float16"``;
    ``store_bev`` (default True) keeps the float16 BEVs that loop-closure detection needs.
    Keyframe ids are the running row numbers, sequence numbers each frame's
    index in its session; the map records the dataset's rig (its cameras; with ``base``, the
    base's), which the localizer compares queries with.

    ``base`` (a map, or the path of one) grows a map without encoding its frames again: the new
    map holds ``base``'s keyframes first, as it stores them (ids, sessions, descriptors, BEVs),
    then the frames of ``sessions``, numbered on from ``base``'s largest id. ``base`` must be
    a map of this model (:func:`check_map_model`; :class:`MapError` otherwise, and for a base
    that records no weights fingerprint, which cannot be checked), of the dataset's
    rig (``ValueError`` when the rigs differ by more than
    :data:`vvloc.data.rig.SAME_MAP`; a ``UserWarning`` when ``base`` records no rig, and the
    new map records none), and must not hold a session of ``sessions`` (``ValueError``);
    ``dtype`` and ``store_bev`` default to ``base``'s, and other values are refused
    (``ValueError``: one map holds one dtype, and BEVs for every keyframe or none).
    ``out`` may be ``base``'s own file (with ``overwrite``): it is replaced only when the new
    map is complete.

    Frames without image content (:func:`vvloc.data.has_image_content`: every camera's picture
    flat, as from a covered or failed rig or a black stretch) are left out, with a
    ``UserWarning`` naming them: any two such frames match at a cost near 0, so one of them in a
    map drew every blank query to it and two made false loop closures. ``ValueError`` when no
    frame has content.
    ``TypeError`` when ``model`` is not a :class:`VVLocNet` or ``dataset`` not a
    :class:`vvloc.data.Dataset` (``open_dataset(path)``), ``ValueError`` naming a bad
    ``sessions`` or ``batch_size``; a ``UserWarning`` when the dataset's rig is not one the
    model was trained on (:func:`check_training_rig`)."""
    _check_model(model)
    if not isinstance(dataset, Dataset):
        raise TypeError(
            "dataset: expected a vvloc dataset (vvloc.data.open_dataset(path)), got "
            f"{type(dataset).__name__}"
        )
    batch_size = positive_int(batch_size, "batch_size")
    if isinstance(sessions, str):
        raise TypeError(f"sessions: expected a list of session names, got the str {sessions!r}")
    if not isinstance(sessions, Iterable):
        raise TypeError(
            f"sessions: expected a list of session names, got {type(sessions).__name__}"
        )
    sessions = list(sessions)  # a generator is read once
    if not all(isinstance(s, str) for s in sessions):
        raise TypeError(f"sessions: expected session names (str), got {sessions!r:.80}")
    if dtype is not None:
        dtype = _check_dtype(dtype)
    if store_bev is not None:
        flag(store_bev, "store_bev")
    if base is not None and not isinstance(base, (MapDatabase, str, os.PathLike)):
        raise TypeError(
            f"base: expected a MapDatabase or the path of a map, got {type(base).__name__}"
        )
    _check_map_out(out, overwrite)
    if not sessions:
        raise ValueError("sessions: expected at least one session name")
    check_session_names("sessions", dataset, sessions, "the dataset")  # each keyframe once
    total = sum(len(dataset.session(s)) for s in sessions)
    if total == 0:
        raise ValueError(f"sessions: {list(sessions)} hold no frames: a map needs keyframes")
    cameras = list(dataset.cameras)
    cfg = model.config
    cfg.check_num_cameras(len(cameras), f"dataset: {dataset.root}")  # before any frame encodes
    check_training_rig(model, cameras, "the dataset's rig")  # named at build_map's caller
    with contextlib.ExitStack() as stack:
        db = None
        if isinstance(base, MapDatabase):
            db = base
        elif base is not None:
            db = stack.enter_context(MapDatabase.open(base))
        if db is not None:
            dtype, store_bev, rig = _base_settings(db, model, cameras, sessions, dtype, store_bev)
        else:
            rig = cameras or None
        writer = stack.enter_context(
            MapWriter(
                out,
                model_config=cfg.to_dict(),
                grid_size=float(cfg.grid_size),
                config_hash=model.config_hash(),
                weights_hash=model.weights_hash(),
                dtype="float32" if dtype is None else _check_dtype(dtype),
                expected_keyframes=total + (0 if db is None else len(db)),
                rig=rig,
            )
        )
        next_id = 0
        if db is not None:
            writer.append_map(db)
            next_id = int(db.ids.max()) + 1 if len(db) else 0
        keep_bev = True if store_bev is None else bool(store_bev)
        bar = tqdm(total=total, desc="map", disable=not progress)
        stack.callback(bar.close)  # closed before an error is printed, not under it
        written = 0
        for name in sessions:
            added = _append_session(
                writer, model, dataset.session(name), name, next_id, batch_size, keep_bev, bar
            )
            next_id += added
            written += added
        if written == 0:
            raise ValueError(
                f"sessions: none of the {total} frames of {sessions} has image content (every "
                "camera's picture flat): "
                + ("a map needs keyframes" if db is None else "nothing to add to the base map")
            )
    return Path(out)


def _append_session(
    writer: MapWriter,
    model: VVLocNet,
    session: Session,
    name: str,
    first_id: int,
    batch_size: int,
    keep_bev: bool,
    bar: Any,
) -> int:
    """Encode the frames of ``session`` (called ``name``) in batches of ``batch_size`` and
    append them to ``writer`` as keyframes ``first_id``, ``first_id + 1``, ... (with their
    BEVs when ``keep_bev``); frames without image content are left out, with a
    ``UserWarning`` naming them at :func:`build_map`'s caller. ``bar`` (tqdm) counts every
    frame. Returns the number of keyframes appended."""
    blank: list[str] = []
    added = 0
    for start in range(0, len(session), batch_size):
        loaded = [session[i] for i in range(start, min(start + batch_size, len(session)))]
        content = [has_image_content(f.images) for f in loaded]
        frames = [f for f, c in zip(loaded, content, strict=True) if c]
        blank += [str(f.index) for f, c in zip(loaded, content, strict=True) if not c]
        bar.update(len(loaded) - len(frames))
        if not frames:
            continue
        enc = encode_frames(model, frames, batch_size=batch_size, keep_bev=keep_bev)
        ids = np.arange(first_id + added, first_id + added + len(frames))
        writer.append(
            poses=np.stack([f.pose for f in frames]),
            timestamps=np.array([f.t for f in frames]),
            sessions=name,
            global_descriptors=enc.global_desc,
            local_descriptors=enc.local_desc,
            ids=ids,
            seq=np.array([f.index for f in frames]),
            floors=np.array([f.floor for f in frames]),
            bevs=enc.bev,
        )
        added += len(frames)
        bar.update(len(frames))
    if blank:
        warnings.warn(
            f"session {name!r}: {len(blank)} of {len(session)} frames have no image "
            f"content (every camera's picture flat: frames {list_entries(blank)}); "
            "left out of the map",
            UserWarning,
            stacklevel=3,  # build_map's caller
        )
    return added


def _check_map_out(out: Any, overwrite: Any) -> None:
    """``build_map``'s ``out`` and ``overwrite``: a path, of no file unless ``overwrite`` is on
    and the file is a vvloc map (a user's file is never replaced)."""
    if not isinstance(out, (str, os.PathLike)):
        raise TypeError(f"out: expected the path of a map file, got {type(out).__name__}")
    flag(overwrite, "overwrite")
    path = Path(os.fspath(out))
    if not path.exists():
        return
    if path.is_dir():
        raise IsADirectoryError(f"out: {path} is a folder; expected the path of a map file")
    if not overwrite:
        raise FileExistsError(f"out: {path} exists; pass overwrite=True to replace it")
    if not is_map_file(path):
        raise FileExistsError(
            f"out: {path} exists and is not a vvloc map; overwrite replaces only a map (remove "
            "the file yourself if it is a damaged one)"
        )


def _base_settings(
    db: MapDatabase,
    model: VVLocNet,
    cameras: Sequence[Camera],
    sessions: Sequence[str],
    dtype: str | None,
    store_bev: bool | None,
) -> tuple[str, bool, list[Camera] | list[dict[str, Any]] | None]:
    """``build_map``'s checks of its ``base`` map ``db``; returns the grown map's descriptor
    dtype, whether it stores BEVs, and its rig."""
    where = db.label
    if db.weights_hash is None:  # its keyframes would pass for these weights' in the grown map
        raise MapError(
            f"base: {where} records no weights fingerprint (written by an older vvloc), so "
            "nothing shows that this model's weights built it; build the map anew"
        )
    check_map_model(db, model, stacklevel=3)  # its warnings name build_map's caller
    again = [s for s in sessions if s in db.sessions]
    if again:
        raise ValueError(
            f"sessions: {list_entries(again)} already in the base {where}: a session is added "
            "once (build the map anew to encode it again)"
        )
    stored = db.metadata.descriptor_dtype
    if dtype is not None and dtype != stored:
        raise ValueError(
            f"dtype: the base {where} stores {stored} descriptors, not {dtype}: one map holds "
            "one dtype (leave dtype out to take the base's)"
        )
    if store_bev is not None and bool(store_bev) != db.has_bev:
        raise ValueError(
            f"store_bev: the base {where} {'stores' if db.has_bev else 'has no'} BEVs: every "
            "keyframe of a map has one or none has (leave store_bev out to take the base's)"
        )
    if db.rig is None:
        warnings.warn(
            f"base: {where} records no rig (written by an older vvloc), so it cannot be checked "
            "that its keyframes come from the dataset's rig; the grown map records none either",
            UserWarning,
            stacklevel=3,
        )
        return stored, db.has_bev, None
    if cameras:
        K, cam_to_ego = stack_calibration(cameras)
        size = (cameras[0].width, cameras[0].height)
        rig = [Camera.from_json(c) for c in db.rig]
        why = rig_difference(rig, K, cam_to_ego, size, SAME_MAP)
        if why:
            raise ValueError(
                f"dataset: its rig is not the base {where}'s ({why}); one map holds the "
                "keyframes of one rig, which the localizer compares queries with"
            )
    return stored, db.has_bev, db.rig
