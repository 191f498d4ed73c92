"""Scoring epochs on held-out sessions: :func:`validation_recall` (Recall@1 at 2 m after
re-ranking and by retrieval alone, which ``best/`` is selected by; :func:`validation_query_count`
counts its queries from the poses alone, checked before the first epoch) and
:func:`loop_validation` (loop closures on a ``val_loops`` dataset: precision, recall and CFER at
the loop radius)."""

from __future__ import annotations

from typing import Any

import numpy as np

from vvloc.evaluate import nearest_map_distance
from vvloc.nets import VVLocNet

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
