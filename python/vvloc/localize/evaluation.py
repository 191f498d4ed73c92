"""End-to-end evaluation: build a map from a database session, localize query sessions, score
with :mod:`vvloc.evaluate` and write the report (Markdown + JSON + plots).

Methods in the report: ``VVLoc-G`` (retrieval by global descriptor alone) and ``VVLoc-ML``
(after metric re-ranking of the top-K by yaw matching cost). AOE/APE are computed from the
metric-localization global poses (DESIGN.md §3 frames).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import secrets
import shutil
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from vvloc import evaluate, geometry, kernels, viz
from vvloc._checks import positive_int
from vvloc._io import atomic_write, csv_row, made_folders
from vvloc.data import Frame, open_dataset
from vvloc.data.perturb import SEEDED, frame_seed, perturb_frame
from vvloc.data.sampling import (
    check_query_sessions,
    inside_folder,
    rendered_world,
    same_folder,
    sim_world,
)
from vvloc.data.vvloc_format import rig_meta
from vvloc.localize.localizer import (
    LocalizationResult,
    Localizer,
    build_map,
    encode_frames,
    model_device,
)
from vvloc.localize.loops import (
    FLOOR_MARGIN,
    FLOOR_MIN_VOTES,
    FLOOR_VOTE_FACTOR,
    confirm_sequence,
    floor_consensus,
    loop_candidates,
    sweep_radius,
    verify_pairs,
)
from vvloc.localize.mapdb import MapDatabase
from vvloc.localize.metric import METRIC_CANDIDATES, RETRIEVAL_WEIGHT, SearchConfig
from vvloc.nets import VVLocNet
from vvloc.nets.model import resolve_device
from vvloc.provenance import cpu_model, hardware, rendered_plan, session_digest, summarize

#: The loop-closure variants with the floor check (vvloc.localize.loops.floor_consensus).
FLOORS = "floor consensus"
#: Loop closure's precision-recall sweep scores the pairs within this descriptor distance...
LOOP_SWEEP_RADIUS = 0.5
#: ...unless they are more than about this many (then a smaller radius, see sweep_radius).
LOOP_SWEEP_PAIRS = 20_000_000

log = logging.getLogger("vvloc.evaluate")


#: Perturbations of the robustness evaluation (label → perturb_frame name and arguments). The
#: random ones (which camera, which regions, the blur's direction, the noise) are drawn for
#: each query frame with its own seed (:func:`vvloc.data.perturb.frame_seed`), so a figure is
#: over a sample of such conditions, the same in every run (before 2026-12-05 one seed served
#: every frame: the same camera masked, the same boxes and noise, a horizontal blur).
ROBUSTNESS: dict[str, tuple[str, dict[str, Any]]] = {
    "one camera masked": ("mask_cameras", {"count": 1}),
    "motion blur": ("motion_blur", {"length": 9, "angle_deg": None}),
    "regions masked": ("mask_regions", {"count": 2, "size": 0.3}),
    "under-exposed": ("exposure", {"gain": 0.4}),
    "noise": ("noise", {"sigma": 12.0}),
}


#: The map of every frame that ``loops=True`` builds (with BEVs) in the report folder.
LOOPS_MAP = "loops_map.h5"

#: Every figure file an evaluation may write (those a run does not draw are removed).
FIGURE_FILES = (
    "recall.png",
    "error_cdf.png",
    "trajectory.png",
    "translation_costs.png",
    "yaw_cost_curve.png",
    "precision_recall.png",
    "confidence_curve.png",
)


#: The hidden folder inside a report folder that :func:`run_evaluation` writes into.
_STAGE_PREFIX = ".vvloc-eval-partial-"
#: Every file a report folder may hold from :func:`run_evaluation` (the report names last).
REPORT_FILES = ("map.h5", LOOPS_MAP, "queries.csv", *FIGURE_FILES, "report.json", "report.md")


def _is_report(out_dir: Path) -> bool:
    """Whether ``out_dir`` holds a report :func:`run_evaluation` wrote (its ``report.json``)."""
    try:
        doc = json.loads((out_dir / "report.json").read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return (
        isinstance(doc, dict) and isinstance(doc.get("meta"), dict) and "global_localization" in doc
    )


def check_report_folder(out_dir: Path, argument: str = "out") -> None:
    """Refuse a report folder whose files a report would replace without being a report's:
    ``FileExistsError`` naming them (and ``argument``) when ``out_dir`` holds files named as a
    report's (:data:`REPORT_FILES`: ``map.h5``, ``queries.csv``, figures, ``report.md`` ...) but
    no ``report.json`` of an earlier evaluation. An earlier report there is replaced whole."""
    if not out_dir.is_dir() or _is_report(out_dir):
        return
    clash = [name for name in REPORT_FILES if (out_dir / name).exists()]
    if clash:
        raise FileExistsError(
            f"{argument}: {out_dir} holds {', '.join(clash)}, which no earlier vvloc eval report "
            "wrote (no report.json of one); the report would replace them: choose another "
            "folder"
        )


def _move_report(work: Path, out_dir: Path) -> None:
    """Move the finished report in ``work`` into ``out_dir``: the files of an earlier report
    this run did not write (a figure it did not draw, the loop map of a run with ``--loops``)
    are removed, then each new file replaces its namesake (renames, within one folder)."""
    made = {p.name for p in work.iterdir()}
    for name in REPORT_FILES:
        if name not in made:
            (out_dir / name).unlink(missing_ok=True)
    for name in sorted(made, key=lambda n: REPORT_FILES.index(n) if n in REPORT_FILES else -1):
        os.replace(work / name, out_dir / name)


def perturbed(frame: Frame, label: str) -> Frame:
    """``frame`` under the robustness perturbation ``label`` of :data:`ROBUSTNESS`, with the
    frame's own seed where the perturbation draws anything."""
    name, args = ROBUSTNESS[label]
    if name in SEEDED:
        args = {**args, "seed": frame_seed(frame)}
    return perturb_frame(frame, name, **args)


def loc_desc_of(loc: Localizer, frame: Frame) -> np.ndarray:
    """The local-view descriptor (T, C) of one frame under the localizer's model."""
    return encode_frames(loc.model, [frame]).local_desc[0]


def _on_floor(results: Sequence[Any], db_floor: np.ndarray, q_floor: np.ndarray) -> np.ndarray:
    """``(Q,)`` bool: the keyframe each metric pose was built on (``metric_row``) is on the
    query's floor (an answer built on another floor is no success, whatever its x-y error)."""
    rows = np.array([r.metric_row for r in results], dtype=np.int64)
    return np.asarray(db_floor)[rows] == q_floor


def _pose_keyframe_correct(
    results: Sequence[Any], db_pose: np.ndarray, q_pose: np.ndarray, on_floor: np.ndarray
) -> np.ndarray:
    """``(Q,)`` bool: the keyframe each metric pose was built on (``metric_row``, chosen before
    the pose) lies within 2 m of the query on its floor: a true revisit, whatever the pose."""
    rows = np.array([r.metric_row for r in results], dtype=np.int64)
    near = np.linalg.norm(np.asarray(db_pose)[rows, :2] - q_pose[:, :2], axis=1) <= 2.0
    return near & on_floor


def _robustness(
    loc: Localizer,
    frames: Sequence[Frame],
    q_pose: np.ndarray,
    q_floor: np.ndarray,
    db_pose: np.ndarray,
    db_floor: np.ndarray,
    k: int,
    progress: bool,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The global-localization metrics under each perturbation of :data:`ROBUSTNESS`: the whole
    localizer runs on perturbed copies of the query frames (the map is clean). Returns
    ``({"<perturbation>, VVLoc-G" / ", VVLoc-ML": RecallResult}, {perturbation: pose
    accuracy})``, as for the clean queries."""
    recalls: dict[str, Any] = {}
    poses: dict[str, Any] = {}
    kw: dict[str, Any] = {"query_floors": q_floor, "db_floors": db_floor, "top_n": _top_n(k)}
    for label in ROBUSTNESS:
        log.info("robustness: localizing the queries with %s", label)
        results = loc.localize_batch([perturbed(f, label) for f in frames], progress=progress)
        rec_ml = evaluate.recall_at_n(
            q_pose[:, :2], db_pose[:, :2], _ranked(results, "reranked", k), **kw
        )
        recalls[f"{label}, VVLoc-G"] = evaluate.recall_at_n(
            q_pose[:, :2], db_pose[:, :2], _ranked(results, "retrieved", k), **kw
        )
        recalls[f"{label}, VVLoc-ML"] = rec_ml
        est = np.stack([r.global_pose for r in results])
        poses[label] = evaluate.pose_accuracy(
            est,
            q_pose,
            rec_ml.correct(1, 2.0),
            kept=rec_ml.kept,
            same_floor=_on_floor(results, db_floor, q_floor),
        )
    return recalls, poses


def _loops(
    model: VVLocNet,
    ds: Any,
    sessions: Sequence[str],
    out_dir: Path,
    loop_pairs: int,
    search: SearchConfig | None,
    progress: bool,
    radius: float,
    sequence: int,
    sweep_pairs: int,
) -> tuple[dict[str, Any], dict[str, Any], float, bool]:
    """Loop closure over all frames of ``sessions`` (one map with BEVs), accepted at descriptor
    distance < ``radius``: single keyframes (the paper's test) and, for ``sequence = L > 0``,
    with the sequence-consistency check of half-window L (:mod:`vvloc.localize.loops`); each
    also with the floor check (:func:`vvloc.localize.loops.floor_consensus`: the session pairs'
    floor offsets voted by the single keyframes within ``FLOOR_VOTE_FACTOR`` × ``radius``; the
    sweep keeps its pairs of those offsets). The precision-recall sweep scores the pairs within
    descriptor distance 0.5, or within the smaller radius (never below ``radius``) that keeps
    them to about ``sweep_pairs``; returns the closure and pose metrics, that sweep radius, and
    whether ``radius`` alone already held more pairs than the bound (the sweep then stops at
    ``radius``, above the bound)."""
    path = build_map(model, ds, list(sessions), out_dir / LOOPS_MAP, progress=progress)
    closure: dict[str, Any] = {}
    pose: dict[str, Any] = {}
    verified: dict[tuple[int, int], tuple[np.ndarray, float]] = {}
    with MapDatabase.open(path, expected_config_hash=model.config_hash()) as db:
        pos = np.asarray(db.poses)[:, :2]
        floors = np.asarray(db.floors)
        bound = sweep_radius(
            db.global_descriptors,
            db.session_index,
            db.seq,
            sweep_pairs,
            window=10,
            r_max=LOOP_SWEEP_RADIUS,
        )
        sweep, over = max(bound, radius), bound < radius
        variants = {"VVLoc (descriptor radius)": (0, False)}
        if sequence > 0:
            variants[f"VVLoc + sequence (±{sequence} keyframes)"] = (sequence, False)
        variants[f"VVLoc + {FLOORS}"] = (0, True)
        if sequence > 0:
            variants[f"VVLoc + sequence (±{sequence} keyframes) + {FLOORS}"] = (sequence, True)
        # every pair within a generous descriptor radius: the sweep's candidates (one radius
        # query; the sequence and floor checks filter the same pairs)
        single = loop_candidates(db, radius=sweep, window=10)
        g, sess, seq = db.global_descriptors, db.session_index, db.seq
        # the floor check's voters: the single keyframes within FLOOR_VOTE_FACTOR × the radius
        vote_radius = FLOOR_VOTE_FACTOR * radius
        if vote_radius <= sweep:
            voters = single.within(vote_radius)
        else:
            voters = loop_candidates(db, radius=vote_radius, window=10)
        for name, (half, check_floors) in variants.items():
            cand = single
            if half:
                cand = confirm_sequence(single, g, sess, seq, sweep, half, window=10)
            if check_floors:
                cand = floor_consensus(cand, sess, floors, voters)
            pairs = np.stack([cand.i, cand.j], axis=1)
            # frames of one session within ±10 keyframes never count (temporal neighbours)
            curve = evaluate.self_loop_closure_curve(
                pairs, cand.distance, pos, floors, sess, seq, 10
            )
            # at the radius, the pairs the detector accepts: distance < radius
            closure[name] = curve.summary(radius, strict=True)
            accepted = cand.distance < radius
            closure[name]["events"] = evaluate.cross_floor_events(
                pairs[accepted], pos, floors, sess
            )
            # the closest accepted pairs are verified metrically
            order = np.argsort(cand.distance, kind="stable")[:loop_pairs]
            order = order[accepted[order]]
            rows_i, rows_j = cand.i[order], cand.j[order]
            todo = [
                k for k, ij in enumerate(zip(rows_i, rows_j, strict=True)) if ij not in verified
            ]
            est, costs = verify_pairs(
                model, db, rows_i[todo], rows_j[todo], search=search, progress=progress
            )
            for k, e, c in zip(todo, est, costs, strict=True):
                verified[(int(rows_i[k]), int(rows_j[k]))] = (e, float(c))
            got = [verified[(int(a), int(b))] for a, b in zip(rows_i, rows_j, strict=True)]
            est = np.array([e for e, _ in got]).reshape(-1, 3)
            costs = np.array([c for _, c in got])
            gt = geometry.relative(db.poses[rows_i], db.poses[rows_j])
            same = floors[rows_i] == floors[rows_j]  # a cross-floor pair registers nothing
            pose[name] = evaluate.loop_pose_metrics(est, gt.reshape(-1, 3), costs, same_floor=same)
            rre, rte = evaluate.relative_pose_errors(est, gt.reshape(-1, 3))
            pose[name]["confidence_curve"] = evaluate.confidence_curve(
                costs, rre, rte, same_floor=same
            )
            del cand, pairs, curve  # one variant's curve in memory at a time
    return closure, pose, sweep, over


def _share(x: float, why: str) -> str:
    """A share as a percentage for the report's notes; "– (why)" where it is undefined (nan)."""
    return f"– ({why})" if np.isnan(x) else f"{x:.1%}"


def _ranked(results: Sequence[LocalizationResult], attr: str, k: int) -> np.ndarray:
    out = np.full((len(results), k), -1, dtype=np.int64)
    for q, r in enumerate(results):
        rows = getattr(r, attr)[:k]
        out[q, : len(rows)] = rows
    return out


def trained_on(
    record: dict[str, Any],
    dataset: str | os.PathLike[str],
    sessions: Sequence[str],
    *,
    opened: Any = None,
) -> list[str]:
    """Those of ``sessions`` of ``dataset`` that the runs of a training ``record``
    (:mod:`vvloc.provenance`: the checkpoint's ``training.json``) trained on, as their configs'
    ``dataset`` / ``train_sessions`` and ``extra_datasets`` say (a source without
    ``train_sessions`` trained all its sessions). ``opened``: ``dataset`` as the caller opened
    it (:func:`vvloc.data.open_dataset`; read again when None, only if needed).

    A session counts, by name, when the source and this dataset are one folder or share one in
    their lineages: each folder with the folders it was converted from (``vvloc convert``'s
    ``converted_from`` chain in ``rig.json``; a conversion keeps the session names), so a
    conversion of a trained folder, its source and a sibling conversion all count (a relative
    path compared from the working directory, and from the run's own ``cwd`` where the record
    has it: evaluating from elsewhere finds it too). A source without ``train_sessions`` that
    is not in this dataset's lineage (its source, or a sibling) trained the sessions its own
    folder holds, not every session of the shared source. For data that ``vvloc sim``
    rendered, a session counts when the source's ``sim`` section renders this dataset's world
    (:func:`rendered_world`) and the session, by name, is a trained one whose plan (lighting,
    seed: ``session.json``) it shares: the same drive through the same world under the same
    light and cars, whatever folder holds it or how many keyframes it has. A session also
    counts when its frames (and a rendered session's plan), in this dataset or a vvloc folder
    of its lineage, are those of a trained session anywhere (a copy: the runs'
    ``session_digests``, recorded since 2026-12-06). A record without configs (weights of an
    earlier vvloc) gives none."""
    world = rendered_world(dataset)
    lineage = _lineage(dataset)
    mine = [folder for folder, _ in lineage]
    trained: set[str] = set()
    digests: set[str] = set()
    for run in record.get("runs", []) if isinstance(record, dict) else []:
        if isinstance(run, dict) and isinstance(run.get("session_digests"), list):
            digests.update(run["session_digests"])
        cfg = run.get("config") if isinstance(run, dict) else None
        if not isinstance(cfg, dict):
            continue
        sources = [(cfg.get("dataset"), cfg.get("train_sessions"), cfg.get("sim"))]
        sources += [
            (e.get("dataset"), e.get("train_sessions"), e.get("sim"))
            for e in cfg.get("extra_datasets") or []
            if isinstance(e, dict)
        ]
        cwd = run.get("cwd")  # where the run resolved its relative paths (since 2026-12-05)
        for path, names, sim in sources:
            if not isinstance(path, str):
                continue
            spelt = [path]
            if isinstance(cwd, str):
                spelt.append(os.path.join(cwd, path))  # joins only a relative one
            theirs = [folder for p in spelt for folder, _ in _lineage(p)]
            if any(same_folder(a, b) for a in spelt for b in mine):  # this dataset, or its source
                trained.update(sessions if names is None else names)
            elif any(same_folder(a, b) for a in theirs for b in mine):  # a shared source
                trained.update(names if names is not None else _folder_sessions(spelt))
            elif world is not None and isinstance(sim, dict) and sim_world(sim) == world:
                candidates = sessions if names is None else [s for s in sessions if s in names]
                trained.update(s for s in candidates if _planned_alike(dataset, s, sim))
    rest = [s for s in sessions if s not in trained]
    if digests and rest:
        for k, (folder, fmt) in enumerate(lineage):
            if k and fmt != "vvloc":  # a raw source: slow to open, and read another way
                continue
            found = _sessions_with_digests(folder, rest, digests, opened if k == 0 else None)
            trained.update(found)
            rest = [s for s in rest if s not in found]
    return [s for s in sessions if s in trained]


def _lineage(dataset: str | os.PathLike[str]) -> list[tuple[str, str | None]]:
    """``dataset`` and the folders it was converted from, nearest first, each with its format
    as the conversion recorded it (None for ``dataset`` itself): ``rig.json``'s
    ``meta.converted_from`` and its ``source_converted_from``."""
    out: list[tuple[str, str | None]] = [(os.fspath(dataset), None)]
    meta = rig_meta(dataset)  # None: no rig.json, or not a vvloc one
    step = meta.get("converted_from") if meta is not None else None
    while isinstance(step, dict) and isinstance(step.get("path"), str):
        fmt = step.get("format")
        out.append((step["path"], fmt if isinstance(fmt, str) else None))
        step = step.get("source_converted_from")
    return out


def _folder_sessions(spelt: Sequence[str]) -> list[str]:
    """The sessions of the first of ``spelt`` (one folder's spellings) that holds a vvloc
    ``sessions/`` folder; none when it is gone."""
    for path in spelt:
        with contextlib.suppress(OSError):
            return sorted(p.name for p in (Path(path) / "sessions").iterdir() if p.is_dir())
    return []


def _sessions_with_digests(
    dataset: str | os.PathLike[str], sessions: Sequence[str], digests: set[str], opened: Any
) -> list[str]:
    """Those of ``sessions`` of ``dataset`` (``opened``: the caller's opening of it, or None)
    whose frames' :func:`session_digest` is among ``digests`` (none where the dataset or a
    session cannot be read: a source folder may be gone, and the caller's own reading of the
    evaluated one says why)."""
    try:
        with warnings.catch_warnings():  # the evaluation's own opening warns where due
            warnings.simplefilter("ignore")
            ds = opened if opened is not None else open_dataset(dataset)
            found = []
            for name in sessions:
                if name not in ds.sessions:
                    continue
                sess = ds.session(name)
                plan = rendered_plan(dataset, name)
                if session_digest(sess.timestamps, sess.poses, sess.floors, plan) in digests:
                    found.append(name)
        return found
    except (OSError, ValueError, KeyError, TypeError):
        return []


def _planned_alike(dataset: str | os.PathLike[str], session: str, sim: dict[str, Any]) -> bool:
    """Whether ``session`` of the rendered ``dataset`` has the lighting and seed that ``sim``
    plans for a session of that name (its ``session.json``; False where it has none)."""
    from vvloc.sim.simulate import session_plan  # the renderer's plan, not its GL context

    if not (session[:1] == "s" and session[1:].isdigit()):
        return False
    try:
        meta = json.loads(
            (Path(dataset) / "sessions" / session / "session.json").read_text(encoding="utf-8-sig")
        )
        plan = session_plan(
            sim.get("scene", "parking"),
            int(session[1:]) + 1,
            sim.get("seed", 0),
            sim.get("lighting"),
        )[-1]
    except (OSError, ValueError, TypeError):
        return False
    return isinstance(meta, dict) and (meta.get("lighting"), meta.get("seed")) == (
        plan.lighting,
        plan.seed,
    )


@dataclass
class _Scored:
    """The queries of an evaluation as localized, with their ground truth and their scores."""

    frames: list[Frame]
    results: list[LocalizationResult]
    q_pose: np.ndarray  # (Q, 3) ground truth, world frame (x m, y m, yaw rad)
    q_floor: np.ndarray  # (Q,) int
    db_pose: np.ndarray  # (N, 3) the map's keyframes, world frame
    db_floor: np.ndarray  # (N,) int
    k: int  # candidates scored: top_k, at most the map's size
    retrieved: np.ndarray  # (Q, k) map rows in retrieval order (VVLoc-G)
    reranked: np.ndarray  # (Q, k) map rows in re-ranked order (VVLoc-ML)
    rec_g: evaluate.RecallResult  # retrieval alone (VVLoc-G)
    rec_ml: evaluate.RecallResult  # re-ranked (VVLoc-ML)
    est: np.ndarray  # (Q, 3) the metric poses, world frame
    yaw_err: np.ndarray  # (Q,) |yaw error| of the metric poses, degrees
    pos_err: np.ndarray  # (Q,) position error of the metric poses, metres
    correct: np.ndarray  # (Q,) bool: VVLoc-ML's top-1 within 2 m on the query's floor
    on_floor: np.ndarray  # (Q,) bool: the metric pose's keyframe is on the query's floor


def _open_inputs(
    checkpoint: str | os.PathLike[str],
    dataset: str | os.PathLike[str],
    database: str,
    queries: list[str],
    device: str,
) -> tuple[VVLocNet, Any, list[str]]:
    """The model, the opened dataset and the query sessions the checkpoint was trained on
    (warned about); ``KeyError``/``ValueError`` naming ``database`` or ``queries`` for a
    session missing or without frames."""
    model = VVLocNet.load(checkpoint).to(resolve_device(device))
    ds = open_dataset(dataset)
    # sessions checked before the trained-on warning, which a missing one would follow
    for name in [database, *queries]:
        argument = "database" if name == database else "queries"
        if name not in ds.sessions:
            raise KeyError(f"{argument}: no session {name!r} in {dataset}; sessions: {ds.sessions}")
        if len(ds.session(name)) == 0:
            raise ValueError(f"{argument}: session {name!r} of {dataset} has no frames")
    seen = trained_on(model.training_record, dataset, queries, opened=ds)
    if seen:
        log.warning(
            "queries %s of %s were trained on (the checkpoint's training record): their "
            "figures are not a held-out test",
            seen,
            dataset,
        )
    return model, ds, seen


@contextlib.contextmanager
def _report_stage(out_dir: Path) -> Iterator[Path]:
    """A hidden folder inside ``out_dir`` (made, with its parents, as needed) to write a report
    into, moved into place when the block ends without an error (:func:`_move_report`): a run
    that fails or is stopped leaves an earlier report in ``out_dir`` as it was (its map, queries
    and figures were replaced one by one before, under the old report). Either way the folder
    is removed, and so are the folders made here that it left empty."""
    with made_folders(out_dir):  # those made here are removed again if the run fails
        for stale in out_dir.glob(f"{_STAGE_PREFIX}*"):  # of a run killed outright
            shutil.rmtree(stale, ignore_errors=True)
        work = out_dir / f"{_STAGE_PREFIX}{secrets.token_hex(6)}"
        work.mkdir()
        try:
            yield work
            _move_report(work, out_dir)
        finally:
            shutil.rmtree(work, ignore_errors=True)


def _score(
    mapdb: MapDatabase,
    frames: list[Frame],
    results: list[LocalizationResult],
    top_k: int,
) -> _Scored:
    """Recall@N of retrieval alone and re-ranked, and the metric poses' errors, of ``results``
    (one per query frame of ``frames``) against the map ``mapdb``."""
    q_pose = np.stack([f.pose for f in frames])
    q_floor = np.array([f.floor for f in frames])
    db_pose = np.asarray(mapdb.poses)
    db_floor = np.asarray(mapdb.floors)
    k = min(top_k, len(mapdb))
    retrieved = _ranked(results, "retrieved", k)
    reranked = _ranked(results, "reranked", k)
    kw: dict[str, Any] = {"query_floors": q_floor, "db_floors": db_floor, "top_n": _top_n(k)}
    rec_ml = evaluate.recall_at_n(q_pose[:, :2], db_pose[:, :2], reranked, **kw)
    est = np.stack([r.global_pose for r in results])
    yaw_err, pos_err = evaluate.pose_errors(est, q_pose)
    return _Scored(
        frames=frames,
        results=results,
        q_pose=q_pose,
        q_floor=q_floor,
        db_pose=db_pose,
        db_floor=db_floor,
        k=k,
        retrieved=retrieved,
        reranked=reranked,
        rec_g=evaluate.recall_at_n(q_pose[:, :2], db_pose[:, :2], retrieved, **kw),
        rec_ml=rec_ml,
        est=est,
        yaw_err=yaw_err,
        pos_err=pos_err,
        correct=rec_ml.correct(1, 2.0),
        on_floor=_on_floor(results, db_floor, q_floor),
    )


def _top_n(k: int) -> tuple[int, ...]:
    """The N of the report's Recall@N for ``k`` candidates: 1 and 5, as far as there are."""
    return tuple(n for n in (1, 5) if n <= k)


def _per_session(scored: _Scored, queries: list[str]) -> dict[str, Any]:
    """Recall@N of VVLoc-G and -ML per query session (empty for a single session)."""
    out: dict[str, Any] = {}
    if len(queries) < 2:
        return out
    q_session = np.array([f.session for f in scored.frames])
    ranked = {"VVLoc-G": scored.retrieved, "VVLoc-ML": scored.reranked}
    for name in queries:
        sel = q_session == name
        for label, order in ranked.items():
            out[f"{name}, {label}"] = evaluate.recall_at_n(
                scored.q_pose[sel, :2],
                scored.db_pose[:, :2],
                order[sel],
                query_floors=scored.q_floor[sel],
                db_floors=scored.db_floor,
                top_n=_top_n(scored.k),
            )
    return out


def _scene(meta: dict[str, Any]) -> dict[str, Any] | str | None:
    """The report's ``scene``: the world a ``vvloc sim`` dataset was rendered from (its
    ``rig.json`` meta's scene, seed, floors and floor marking), another dataset's own
    ``meta.scene`` as it is (a str; "scene: scene: mine" before), else None."""
    if meta.get("generator") == "vvloc.sim":
        keys = ("scene", "seed", "floors", "floor_marking")
        return {key: meta[key] for key in keys if key in meta} or None
    scene = meta.get("scene")
    return None if scene is None else str(scene)


def _metric_candidates(loc: Localizer, k: int) -> int:
    """The M candidates the localizer scores metrically: no more than the ``k`` it retrieved."""
    return min(loc.metric_candidates, k)


def _method_note(loc: Localizer, k: int) -> str:
    """What VVLoc-ML's ranking is, in the localizer's settings, for the report's notes."""
    ml = f"VVLoc-ML: the top-{k} re-ranked by yaw matching cost"
    m_used = _metric_candidates(loc, k)
    if m_used > 1:
        source = "retrieved" if loc.metric_from == "retrieval" else "re-ranked"
        ml += (
            f", then the first {m_used} {source} candidates put first, ordered "
            "by the cost of the coarse translation search against each"
            + (
                f" plus {loc.retrieval_weight:g} × its global-descriptor distance"
                if loc.retrieval_weight > 0
                else ""
            )
            + " (the lowest refined by the fine stages)"
        )
    elif loc.metric_from == "retrieval":
        ml += ", then the first retrieved candidate put first (the metric pose's keyframe)"
    if loc.snap:
        ml += (
            "; the reported top-1 is the retrieved keyframe nearest to the metric pose "
            "(snapping, same floor)"
        )
    return ml


def _loop_notes(
    sessions: list[str], loop_radius: float, loop_pairs: int, loop_sequence: int
) -> list[str]:
    """The report's notes on how loop closure over ``sessions`` was scored."""
    notes = [
        f"loop closure over all frames of {sessions}: pairs within "
        f"{loop_radius} in descriptor distance, same-session pairs within 10 keyframes "
        f"excluded; the {loop_pairs} closest verified metrically"
    ]
    if loop_sequence > 0:
        notes.append(
            f"VVLoc + sequence (±{loop_sequence} keyframes): a pair is kept only if the "
            f"mean descriptor distance of its {2 * loop_sequence + 1} neighbouring "
            "keyframe pairs (i + k, j ± k), in the better traversal direction, is below "
            "the threshold as well (vvloc.localize.loops.sequence_distance)"
        )
    notes.append(
        f"VVLoc + {FLOORS}: a pair is kept only if it agrees with the floors of the map's "
        "sessions, in each session's own numbering: within one session the two keyframes' "
        "floor numbers must be equal; for two sessions, the offset between their numbers "
        "that the pair implies must be the one most single-keyframe pairs within "
        f"{FLOOR_VOTE_FACTOR * loop_radius:g} vote for (at least {FLOOR_MIN_VOTES} votes "
        "and "
        f"{FLOOR_MARGIN:g} × any other offset's, never a tie; otherwise none of the two "
        "sessions' pairs is kept; two sessions that each hold one floor number are not "
        "judged) "
        "(vvloc.localize.loops.floor_consensus); the precision-recall sweep keeps the "
        "pairs of these offsets. The check reads the floor numbers the sessions record, "
        "here the labels CFER is scored against: its rows are not the paper's visual CFER"
    )
    return notes


def _sweep_note(sweep: float, over: bool, loop_radius: float, loop_sweep_pairs: int) -> str | None:
    """The report's note on a loop precision-recall sweep narrowed by its memory bound."""
    if over:
        return (
            f"loop precision-recall sweep (best F1) over the pairs within the acceptance "
            f"radius {loop_radius} only, and those are more than about "
            f"{loop_sweep_pairs:,} pairs (the loop_sweep_pairs memory bound)"
        )
    if sweep < LOOP_SWEEP_RADIUS:
        return (
            "loop precision-recall sweep (best F1) over the pairs within descriptor "
            f"distance {sweep:.4g} only, not {LOOP_SWEEP_RADIUS}: about "
            f"{loop_sweep_pairs:,} pairs, the loop_sweep_pairs memory bound"
        )
    return None


def _write_queries_csv(path: Path, scored: _Scored) -> None:
    """``queries.csv``: one row per query, its top-1 answer against its ground truth, with
    what the report's pose rows select queries by (``floor``, the metric row's
    ``map_floor``, ``kept``): the pose rows and Recall@1 at 2 m re-ranked can be recomputed
    from the file (the other recall figures need the ranked lists)."""
    lines = [
        "# vvloc evaluation per query. Poses: world frame x east, y north (m), yaw CCW from "
        "east (deg). cost: matching cost (lower is better). floor: the query's; map_floor: "
        "metric_row's; kept: a map keyframe lies within 2 m on the query's floor (Recall@N "
        "counts the kept queries).",
        "session,index,map_row,est_x,est_y,est_yaw_deg,gt_x,gt_y,gt_yaw_deg,pos_err_m,"
        "yaw_err_deg,cost,accepted,top1_correct,distinctiveness,metric_row,floor,map_floor,kept",
    ]
    for f, r, e, g, pe, ye, c, kept in zip(
        scored.frames,
        scored.results,
        scored.est,
        scored.q_pose,
        scored.pos_err,
        scored.yaw_err,
        scored.correct,
        scored.rec_ml.kept,
        strict=True,
    ):
        lines.append(  # a session name with a comma is quoted (RFC 4180)
            csv_row(
                f.session,
                f.index,
                r.map_row,
                f"{e[0]:.4f}",
                f"{e[1]:.4f}",
                f"{np.degrees(e[2]):.3f}",
                f"{g[0]:.4f}",
                f"{g[1]:.4f}",
                f"{np.degrees(g[2]):.3f}",
                f"{pe:.4f}",
                f"{ye:.3f}",
                f"{r.cost:.5f}",
                int(r.accepted),
                int(c),
                f"{r.distinctiveness:.5f}",
                r.metric_row,
                f.floor,
                int(scored.db_floor[r.metric_row]) if r.metric_row >= 0 else "",
                int(kept),
            )
        )
    with atomic_write(path) as f:
        f.write("\n".join(lines) + "\n")


def _draw_figures(
    work: Path, scored: _Scored, loc: Localizer, mapdb: MapDatabase, metrics: dict[str, Any]
) -> dict[str, Path]:
    """The report's figures, drawn into ``work``: {caption: file}. The sample query of the
    cost plots is the first true revisit (else the first query); the loop closure figures are
    drawn when ``metrics`` holds the loops' results (``loop_closure``, ``loop_pose``)."""
    rec_ml = scored.rec_ml
    figures: dict[str, Path] = {}
    figures["Recall@N at 2 m"] = viz.plot_recall_curves(
        work / "recall.png", {"VVLoc-G": scored.rec_g.curve(2.0), "VVLoc-ML": rec_ml.curve(2.0)}
    )
    sel = scored.correct & rec_ml.kept
    subsets = {
        "top-1 true revisits": sel,
        "all kept queries on their floor": rec_ml.kept & scored.on_floor,
    }
    figures["Error CDFs"] = viz.plot_error_cdfs(
        work / "error_cdf.png",
        {f"VVLoc-ML, {k}": scored.yaw_err[m] for k, m in subsets.items()},
        {f"VVLoc-ML, {k}": scored.pos_err[m] for k, m in subsets.items()},
    )
    figures["Trajectory"] = viz.plot_trajectory(
        work / "trajectory.png",
        scored.db_pose[:, :2],
        scored.q_pose[:, :2],
        scored.correct,
        kept=rec_ml.kept,
        method="VVLoc-ML (re-ranked, snapped)" if loc.snap else "VVLoc-ML (re-ranked)",
    )
    sample = int(np.argmax(sel)) if sel.any() else 0
    h = scored.results[sample].search
    if h is not None and len(h.cost):
        # the search shifts the query's BEV: its hypotheses are ξ_{q→m} translations against
        # the keyframe it was run on (metric_row)
        truth = geometry.relative(
            scored.q_pose[sample], scored.db_pose[int(scored.results[sample].metric_row)]
        )
        figures["Translation cost (sample query)"] = viz.plot_translation_costs(
            work / "translation_costs.png",
            h.xy,
            h.cost,
            estimate=h.xy[int(np.argmin(h.cost))],
            truth=truth[:2],
        )
    if len(scored.results):
        r = scored.results[sample]
        dev = model_device(loc.model)
        with torch.no_grad():  # the model's device (a CUDA model used to fail here)
            a, b = loc.model.interact(
                torch.from_numpy(loc_desc_of(loc, scored.frames[sample]))[None].to(dev),
                torch.from_numpy(mapdb.local_descriptors(int(r.metric_row)))[None].to(dev),
            )
        curve = kernels.yaw_costs(a, b)[0]  # the gateway takes tensors to the CPU
        true_rel = geometry.relative(scored.q_pose[sample], scored.db_pose[int(r.metric_row)])
        figures["Yaw cost curve (sample query, no padding)"] = viz.plot_yaw_cost_curve(
            work / "yaw_cost_curve.png", curve, true_yaw=float(true_rel[2])
        )
    if "loop_closure" in metrics:
        figures["Loop closure precision-recall"] = viz.plot_precision_recall(
            work / "precision_recall.png",
            {name: res["sweep"] for name, res in metrics["loop_closure"].items()},
        )
        name, res = next(iter(metrics["loop_pose"].items()))
        if len(res["confidence_curve"]["threshold"]):
            figures[f"Confidence curve ({name}, verified pairs)"] = viz.plot_confidence_curve(
                work / "confidence_curve.png", res["confidence_curve"]
            )
    return figures


def run_evaluation(
    checkpoint: str | os.PathLike[str],
    dataset: str | os.PathLike[str],
    database: str,
    queries: Sequence[str],
    out: str | os.PathLike[str],
    *,
    top_k: int = 20,
    metric_candidates: int = METRIC_CANDIDATES,
    metric_from: str = "retrieval",
    retrieval_weight: float = RETRIEVAL_WEIGHT,
    snap: bool = True,
    every: int = 1,
    device: str = "cpu",
    search: SearchConfig | None = None,
    progress: bool = True,
    untrained_warning: str | None = None,
    robustness: bool = False,
    loops: bool = False,
    loop_pairs: int = 200,
    loop_radius: float = 0.1,
    loop_sequence: int = 1,
    loop_sweep_pairs: int = LOOP_SWEEP_PAIRS,
) -> dict[str, Any]:
    """Evaluate a checkpoint on ``dataset``: map = ``database`` session, queries = every
    ``every``-th frame of each session in ``queries``. Writes ``out/map.h5``,
    ``out/report.md``, ``out/report.json``, ``out/queries.csv`` and plots; returns the metrics.
    An earlier report in ``out`` is replaced whole; files named as a report's that no earlier
    report wrote are refused before any work (:func:`check_report_folder`), as is an ``out``
    inside ``dataset``.
    The report's meta names this machine (``hardware``) and, from the checkpoint's
    ``training.json``, the hardware and wall time that produced the weights (``trained_on``,
    :func:`vvloc.provenance.summarize`; its runs are the JSON's ``training``, ``{"runs": [...]}``).
    ``metric_candidates``, ``metric_from``, ``retrieval_weight`` and ``snap`` are
    :class:`Localizer`'s (the M candidates scored by the coarse translation search, the first M
    of the retrieval order or of the yaw re-ranking, ordered by coarse cost + ``retrieval_weight``
    × descriptor distance; the reported keyframe snapped to the metric pose).
    ``loops``: also loop closure over all frames of ``database`` + ``queries``, accepted at
    global-descriptor distance < ``loop_radius`` (the first ``loop_pairs`` verified metrically),
    for single keyframes and, when ``loop_sequence`` L > 0, with the sequence-consistency check
    of half-window L as well (:func:`vvloc.localize.loops.sequence_distance`). The loops'
    precision-recall sweep scores every pair within descriptor distance 0.5, or, when that
    would be more than about ``loop_sweep_pairs`` pairs (≈ 150 bytes each), the pairs within
    the radius that keeps to that (at least ``loop_radius``); the report names the radius. The
    JSON holds each variant's sweep at up to 256 thresholds and, per variant, the confidence curve
    of its verified pairs; ``precision_recall.png`` and ``confidence_curve.png`` plot them.
    ``robustness``: the whole localizer again on perturbed copies of the queries, for each of
    :data:`ROBUSTNESS` (Recall@N of VVLoc-G and -ML and AOE/APE, as for the clean queries; six
    times the evaluation's time in all).
    """
    if not 0 < loop_radius <= 0.5:
        raise ValueError(f"loop_radius: expected a value in (0, 0.5], got {loop_radius}")
    loop_sequence = positive_int(loop_sequence, "loop_sequence", minimum=0)
    loop_sweep_pairs = positive_int(loop_sweep_pairs, "loop_sweep_pairs")
    queries = check_query_sessions(database, queries)  # a list (a str refused)
    out_dir = Path(out)
    if inside_folder(out_dir, dataset):  # a report among the sessions breaks the dataset
        raise ValueError(
            f"out: {out} is or lies inside the dataset {dataset}; write the report to a folder "
            "of its own"
        )
    check_report_folder(out_dir)
    model, ds, seen = _open_inputs(checkpoint, dataset, database, queries, device)
    # the report folder is made after the inputs are checked: none is left on an error
    with _report_stage(out_dir) as work:
        map_path = build_map(
            model, ds, [database], work / "map.h5", store_bev=False, progress=progress
        )
        with MapDatabase.open(map_path, expected_config_hash=model.config_hash()) as mapdb:
            loc = Localizer(
                model,
                mapdb,
                top_k=top_k,
                search=search,
                metric_candidates=metric_candidates,
                metric_from=metric_from,
                retrieval_weight=retrieval_weight,
                snap=snap,
            )
            frames = [
                ds.session(s)[i] for s in queries for i in range(0, len(ds.session(s)), every)
            ]
            scored = _score(mapdb, frames, loc.localize_batch(frames, progress=progress), top_k)
            rec_ml, results = scored.rec_ml, scored.results
            pose_acc = evaluate.pose_accuracy(
                scored.est,
                scored.q_pose,
                scored.correct,
                kept=rec_ml.kept,
                same_floor=scored.on_floor,
                pose_keyframe_correct=_pose_keyframe_correct(
                    results, scored.db_pose, scored.q_pose, scored.on_floor
                ),
            )
            stages = ("encode", "retrieve", "rerank", "metric")
            latency = evaluate.latency_summary(
                {st: [r.timings_ms.get(st, np.nan) for r in results] for st in stages}
            )
            accepted = np.array([r.accepted for r in results], dtype=bool)
            kept_acc = accepted & rec_ml.kept
            rule = f"cost < {loc.accept_threshold}"
            if loc.min_distinctiveness > 0:
                rule += (
                    f" and distinctiveness >= {loc.min_distinctiveness:.4g} (the model's "
                    "calibration)"
                )
            acc_precision = evaluate._ratio(
                float((kept_acc & scored.correct).sum()), float(kept_acc.sum())
            )
            notes = [
                f"{len(frames)} queries from {list(queries)}, map = {database} ({len(mapdb)} "
                "keyframes)"
                + (
                    f"; **queries {seen} were trained on** (the checkpoint's training record): "
                    "not a held-out test"
                    if seen
                    else ""
                ),
                f"accepted ({rule}): {accepted.mean():.1%} of all queries; top-1 within 2 m "
                f"among the accepted kept queries: {_share(acc_precision, 'none accepted')} "
                f"(among all kept: {_share(rec_ml.at(1, 2.0), 'none kept')})",
                _method_note(loc, scored.k),
            ]
            if loops:
                notes += _loop_notes([database, *queries], loop_radius, loop_pairs, loop_sequence)
            if untrained_warning:
                notes.insert(0, untrained_warning)
            metrics: dict[str, Any] = {
                "meta": {
                    "checkpoint": str(checkpoint),
                    "dataset": str(dataset),
                    "scene": _scene(ds.meta),
                    "database": database,
                    "queries": ",".join(queries),
                    "model_config_hash": model.config_hash(),
                    "model_weights_hash": model.weights_hash(),
                    "every": every,
                    "top_k": scored.k,
                    "metric_candidates": _metric_candidates(loc, scored.k),
                    "metric_from": loc.metric_from,
                    "retrieval_weight": loc.retrieval_weight,
                    "snap": loc.snap,
                    "device": device,
                    "hardware": hardware(),
                    "cpu": cpu_model(),
                    "torch_threads": torch.get_num_threads(),
                    "trained_on": summarize(model.training_record),
                    "trained_on_queries": list(seen),  # vvloc targets refuses a report with any
                },
                "training": model.training_record or None,
                "global_localization": {"VVLoc-G": scored.rec_g, "VVLoc-ML": rec_ml},
                "per_session": _per_session(scored, queries),
                "pose_accuracy": {"VVLoc-ML": pose_acc},
                "latency": latency,
                "notes": notes,
                "accepted_share": float(accepted.mean()),
                "accepted_precision": acc_precision,
                "min_distinctiveness": loc.min_distinctiveness,
            }
            if robustness:
                metrics["robustness"], metrics["robustness_pose"] = _robustness(
                    loc,
                    frames,
                    scored.q_pose,
                    scored.q_floor,
                    scored.db_pose,
                    scored.db_floor,
                    scored.k,
                    progress,
                )
                notes.append(
                    "robustness: the whole localizer on perturbed copies of the queries (map "
                    "clean; random choices drawn per query frame): "
                    + ", ".join(
                        f"{label} ({name} {args})" for label, (name, args) in ROBUSTNESS.items()
                    )
                )
            if loops:
                metrics["loop_closure"], metrics["loop_pose"], sweep, over = _loops(
                    model,
                    ds,
                    [database, *queries],
                    work,
                    loop_pairs,
                    search,
                    progress,
                    loop_radius,
                    loop_sequence,
                    loop_sweep_pairs,
                )
                metrics["loop_sweep_radius"] = sweep
                note = _sweep_note(sweep, over, loop_radius, loop_sweep_pairs)
                if note is not None:
                    notes.append(note)
            _write_queries_csv(work / "queries.csv", scored)
            figures = _draw_figures(work, scored, loc, mapdb, metrics)
            evaluate.write_report(work, metrics, title="vvloc evaluation", figures=figures)
    return metrics
