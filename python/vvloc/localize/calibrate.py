"""Re-ranking on a held-out split, and calibrating when a localization is accepted.

The paper accepts a result when its matching cost is below 0.75. How low the cost of a right
match is depends on the model and on how textured the place is, so a fixed cost threshold does
not carry from one model (or rig, or world) to another: it has to be measured. vvloc measures,
on sessions the model never trained on, the *distinctiveness* of the re-ranked top-1 (how far
its cost lies below the mean cost of the retrieved candidates,
:func:`vvloc.evaluate.distinctiveness`) and keeps the lowest threshold at which accepted
results are right (top-1 within 2 m) at a target precision. The result is stored with the
checkpoint (``calibration.json``) and used by :class:`vvloc.Localizer`.

Two measurements: :func:`calibrate_localizer` (``vvloc calibrate``) localizes the held-out
frames with a :class:`~vvloc.Localizer` and scores the answers that acceptance gates
(the reported keyframe, after the metric stage and snapping); :func:`calibrate` (the trainer's
validation, ``best/calibration.json``) scores the yaw re-ranking's top-1 without the metric
stage, a cheaper stand-in.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from vvloc import evaluate
from vvloc._checks import real_array
from vvloc.data import Frame, has_image_content
from vvloc.localize.localizer import (
    LocalizationResult,
    Localizer,
    encode_frames,
    rerank_learned,
)
from vvloc.nets import VVLocNet

__all__ = [
    "RerankedSplit",
    "calibrate",
    "calibrate_localizer",
    "calibration_of",
    "calibration_of_results",
    "check_revisits",
    "rerank_split",
]


@dataclass(frozen=True)
class RerankedSplit:
    """Retrieval and re-ranking of query frames against a map session.

    Attributes:
        retrieved: ``(Q, K)`` map rows by global-descriptor distance, best first.
        reranked: ``(Q, K)`` the same rows ordered by yaw matching cost, lowest first.
        rerank_cost: ``(Q, K)`` their costs, ascending.
        query_xy, db_xy: ``(Q, 2)`` / ``(N, 2)`` ground-truth world x, y (m).
        query_floors, db_floors: ``(Q,)`` / ``(N,)`` floor labels.
        query_content: ``(Q,)`` bool, whether each query frame has image content
            (:func:`vvloc.data.has_image_content`; the localizer accepts no query without).
    """

    retrieved: npt.NDArray[np.int64]
    reranked: npt.NDArray[np.int64]
    rerank_cost: npt.NDArray[np.float64]
    query_xy: npt.NDArray[np.float64]
    db_xy: npt.NDArray[np.float64]
    query_floors: npt.NDArray[np.int64]
    db_floors: npt.NDArray[np.int64]
    query_content: npt.NDArray[np.bool_]

    def recall(self, which: str = "reranked", top_n: Sequence[int] = (1, 5)) -> Any:
        """:func:`vvloc.evaluate.recall_at_n` of ``"retrieved"`` or ``"reranked"`` at 2 m."""
        ranked = getattr(self, which)
        k = ranked.shape[1]
        return evaluate.recall_at_n(
            self.query_xy,
            self.db_xy,
            ranked,
            query_floors=self.query_floors,
            db_floors=self.db_floors,
            top_n=tuple(n for n in top_n if n <= k) or (1,),
            radii=(2.0,),
        )


@torch.no_grad()
def rerank_split(
    model: VVLocNet,
    ds: Any,
    database: str,
    queries: Sequence[str],
    *,
    every: int = 1,
    top_k: int = 20,
) -> RerankedSplit:
    """Retrieve the ``top_k`` nearest map keyframes (every frame of session ``database`` with
    image content, as :func:`~vvloc.localize.localizer.build_map` keeps them) for every
    ``every``-th frame of each session in ``queries``, and re-rank them by the learned yaw
    matching cost, exactly as :meth:`vvloc.Localizer.rerank` does (interactor on each
    pair, exact yaw minimum), without the metric translation search."""
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise ValueError(f"every: expected an int >= 1, got {every!r}")
    if isinstance(top_k, bool) or not isinstance(top_k, int) or top_k < 1:
        raise ValueError(f"top_k: expected an int >= 1, got {top_k!r}")
    # the frames a map keeps (build_map leaves those without image content out)
    db_frames = [f for f in ds.session(database) if has_image_content(f.images)]
    q_frames = [f for name in queries for f in ds.session(name)[::every]]
    if not db_frames or not q_frames:
        raise ValueError(
            f"database {database!r} and queries {list(queries)}: no frames (a database frame "
            "counts when it has image content)"
        )
    db = encode_frames(model, db_frames)
    q = encode_frames(model, q_frames)
    k = min(top_k, len(db_frames))
    dist = ((q.global_desc[:, None, :] - db.global_desc[None, :, :]) ** 2).sum(-1)
    retrieved = np.argsort(dist, axis=1, kind="stable")[:, :k]
    device = next(model.parameters()).device
    reranked = np.empty_like(retrieved)
    costs = np.empty(retrieved.shape, dtype=np.float64)
    for i, rows in enumerate(retrieved):
        tgt = torch.from_numpy(db.local_desc[rows]).to(device)
        rr = rerank_learned(model, torch.from_numpy(q.local_desc[i]).to(device), tgt)
        reranked[i] = rows[rr.order]
        costs[i] = rr.cost[rr.order]
    return RerankedSplit(
        retrieved=retrieved.astype(np.int64),
        reranked=reranked.astype(np.int64),
        rerank_cost=costs,
        query_xy=np.stack([f.pose[:2] for f in q_frames]),
        db_xy=np.stack([f.pose[:2] for f in db_frames]),
        query_floors=np.array([f.floor for f in q_frames], dtype=np.int64),
        db_floors=np.array([f.floor for f in db_frames], dtype=np.int64),
        query_content=np.array([has_image_content(f.images) for f in q_frames], dtype=bool),
    )


def calibration_of(
    split: RerankedSplit, *, target_precision: float = 0.9, min_accepted: int = 10
) -> dict[str, Any]:
    """The acceptance calibration of a re-ranked split: ``min_distinctiveness`` (the threshold
    of :func:`vvloc.evaluate.calibrate_acceptance` on the distinctiveness of each kept query's
    re-ranked top-1, correct = within 2 m) with the precision and accepted share it reaches
    there, over the queries that have a map keyframe within 2 m and image content (the
    localizer accepts no other)."""
    rec = split.recall("reranked", top_n=(1,))
    kept = rec.kept & split.query_content
    score = evaluate.distinctiveness(split.rerank_cost)[kept]
    correct = rec.correct(1, 2.0)[kept]
    cal = evaluate.calibrate_acceptance(
        score, correct, target_precision=target_precision, min_accepted=min_accepted
    )
    cal["min_distinctiveness"] = cal.pop("threshold")
    cal["top_k"] = int(split.reranked.shape[1])
    return cal


def calibrate(
    model: VVLocNet,
    ds: Any,
    database: str,
    queries: Sequence[str],
    *,
    every: int = 1,
    top_k: int = 20,
    target_precision: float = 0.9,
    min_accepted: int = 10,
) -> dict[str, Any]:
    """Calibrate ``model`` on held-out ``queries`` against a map of ``database``: sets and
    returns ``model.calibration`` (see :func:`calibration_of`; it also records the sessions).
    Save the model (:meth:`VVLocNet.save`) to keep it with the checkpoint."""
    split = rerank_split(model, ds, database, queries, every=every, top_k=top_k)
    cal = calibration_of(split, target_precision=target_precision, min_accepted=min_accepted)
    cal |= {
        "dataset": str(getattr(ds, "root", "")),
        "database": database,
        "sessions": list(queries),
        "every": int(every),
    }
    model.calibration = cal
    return cal


def check_revisits(
    query_poses: npt.ArrayLike,
    query_floors: npt.ArrayLike,
    db_poses: npt.ArrayLike,
    db_floors: npt.ArrayLike,
    argument: str = "query_poses",
) -> None:
    """``ValueError`` naming ``argument`` when no query has a map keyframe within 2 m on its
    floor (the queries a calibration is measured on, as :func:`vvloc.evaluate.recall_at_n`
    keeps them): said from the poses alone, before any query is localized or map built.

    Args:
        query_poses: ``(Q, 3)`` world poses (x, y m; yaw rad); ``query_floors`` ``(Q,)``.
        db_poses: ``(N, 3)`` the map keyframes' world poses; ``db_floors`` ``(N,)``.
    """
    q = real_array(query_poses, "query_poses", "(Q, 3)", 2, 3)
    d = real_array(db_poses, "db_poses", "(N, 3)", 2, 3)
    nearest = evaluate.nearest_map_distance(q[:, :2], d[:, :2], query_floors, db_floors)
    if not (nearest <= 2.0).any():
        raise ValueError(
            f"{argument}: no query has a map keyframe within 2 m on its floor (another world or "
            "another map session?): nothing to calibrate on"
        )


def calibration_of_results(
    results: Sequence[LocalizationResult],
    query_poses: npt.ArrayLike,
    query_floors: npt.ArrayLike,
    db_poses: npt.ArrayLike,
    db_floors: npt.ArrayLike,
    *,
    accept_threshold: float = 0.75,
    target_precision: float = 0.9,
    min_accepted: int = 10,
) -> dict[str, Any]:
    """The acceptance calibration of a :class:`~vvloc.Localizer`'s own answers: the
    threshold on ``distinctiveness`` at which the accepted results (``cost < accept_threshold``
    and distinctiveness ≥ the threshold) have their reported keyframe (``reranked[0]``, the one
    ``vvloc eval`` scores) within 2 m of the query on its floor at ``target_precision``
    (:func:`vvloc.evaluate.calibrate_acceptance` over the results that pass the cost rule; a
    result without image content, ``has_content`` False, passes none).

    Args:
        results: ``Q`` results of :meth:`Localizer.localize_batch`.
        query_poses: ``(Q, 3)`` ground-truth world poses (x, y m; yaw rad); ``query_floors``
            ``(Q,)`` their floor labels.
        db_poses, db_floors: ``(N, 3)`` / ``(N,)`` the map's keyframe poses and floors.

    Returns:
        :func:`~vvloc.evaluate.calibrate_acceptance`'s dict with ``threshold`` renamed
        ``min_distinctiveness``, over the ``queries`` that have a map keyframe within 2 m on
        their floor (the kept ones; shares and ``base_precision``, the share right when every
        one is accepted, are of them), plus ``passing_cost`` (how many of them pass the cost
        rule) and ``accept_threshold``.
    """
    if not results:
        raise ValueError("results: expected at least one localization result")
    q_pose = real_array(query_poses, "query_poses", f"({len(results)}, 3)", 2, 3)
    if q_pose.shape != (len(results), 3):
        raise ValueError(f"query_poses: expected shape ({len(results)}, 3), got {q_pose.shape}")
    m_pose = real_array(db_poses, "db_poses", "(N, 3)", 2, 3)
    top1 = np.array([[r.reranked[0] if len(r.reranked) else -1] for r in results], np.int64)
    if np.any(top1 < 0):
        raise ValueError("results: a result without candidates (an empty map?)")
    rec = evaluate.recall_at_n(
        q_pose[:, :2],
        m_pose[:, :2],
        top1,
        query_floors=query_floors,
        db_floors=db_floors,
        top_n=(1,),
        radii=(2.0,),
    )
    kept = rec.kept
    if not kept.any():
        check_revisits(q_pose, query_floors, db_poses, db_floors)  # raises
    right = rec.correct(1, 2.0)
    # the cost rule, for queries that show something (the localizer accepts no other)
    passing = kept & np.array(
        [r.cost < accept_threshold and r.has_content for r in results], dtype=bool
    )
    score = np.array([r.distinctiveness for r in results], dtype=np.float64)
    cal = evaluate.calibrate_acceptance(
        score[passing], right[passing], target_precision=target_precision, min_accepted=min_accepted
    )
    n_kept = int(kept.sum())
    cal["min_distinctiveness"] = cal.pop("threshold")
    cal["queries"] = n_kept
    cal["accepted_share"] = evaluate._ratio(float(cal["accepted"]), float(n_kept))
    cal["base_precision"] = evaluate._ratio(float(right[kept].sum()), float(n_kept))
    cal["passing_cost"] = int(passing.sum())
    cal["accept_threshold"] = float(accept_threshold)
    return cal


def calibrate_localizer(
    loc: Localizer,
    frames: Sequence[Frame],
    *,
    target_precision: float = 0.9,
    min_accepted: int = 10,
    progress: bool = False,
) -> dict[str, Any]:
    """Localize held-out ``frames`` with ``loc`` (its settings: candidates, metric stage,
    snapping, cost rule) and measure its acceptance calibration on them
    (:func:`calibration_of_results`; this function adds ``top_k`` and the localizer's settings
    under ``"localizer"``). Unlike :func:`calibrate` (the trainer's validation, which scores the yaw
    re-ranking's top-1 without the metric stage, a cheaper stand-in), this scores the answers
    that acceptance gates. Does not change ``loc`` or its model."""
    if not frames:
        raise ValueError("frames: expected at least one query frame")
    poses = np.stack([f.pose for f in frames])
    floors = np.array([f.floor for f in frames], dtype=np.int64)
    check_revisits(poses, floors, loc.map.poses, loc.map.floors, "frames")  # before localizing
    results = loc.localize_batch(list(frames), progress=progress)
    cal = calibration_of_results(
        results,
        poses,
        floors,
        np.asarray(loc.map.poses),
        np.asarray(loc.map.floors),
        accept_threshold=loc.accept_threshold,
        target_precision=target_precision,
        min_accepted=min_accepted,
    )
    cal["top_k"] = int(min(loc.top_k, len(loc.map)))
    cal["localizer"] = {
        "metric_candidates": loc.metric_candidates,
        "metric_from": loc.metric_from,
        "retrieval_weight": loc.retrieval_weight,
        "snap": loc.snap,
    }
    return cal
