"""Loop-closure detection across the sessions of a map.

Candidates are map keyframe pairs (i, j), i < j, whose global descriptors lie within
``radius`` (L2, default 0.1 as in the paper) of each other, excluding temporal neighbours of the
same session (``|seq_i − seq_j| <= window``). Each candidate gets a metric pose by the same
search as localization, with keyframe i's stored BEV as the padded source and keyframe j's
local-view descriptor as the target: ξ_{i→j} (frame j expressed in frame i, DESIGN.md §3). A
loop is accepted when its matching cost is below ``cost_threshold`` (0.75).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from vvloc.localize.export import LoopClosures
from vvloc.localize.localizer import interacting_decoder
from vvloc.localize.mapdb import MapDatabase
from vvloc.localize.metric import SearchConfig, metric_localize
from vvloc.nets import VVLocNet
from vvloc.retrieval import DescriptorIndex, Exclusion

log = logging.getLogger("vvloc.localize")


@dataclass(frozen=True)
class LoopCandidates:
    """Candidate pairs (i < j map rows) and their global-descriptor L2 distances, (P,) each."""

    i: np.ndarray
    j: np.ndarray
    distance: np.ndarray


def descriptor_loop_candidates(
    descriptors: np.ndarray,
    sessions: np.ndarray,
    seqs: np.ndarray,
    radius: float = 0.1,
    window: int = 10,
) -> LoopCandidates:
    """All pairs i < j of ``descriptors`` (N, D) with L2 distance < ``radius``, excluding pairs
    of one session (``sessions`` (N,) int) within ``window`` sequence numbers (``seqs`` (N,)
    int): one radius query per row on the Rust index."""
    if not radius > 0:
        raise ValueError(f"radius: expected > 0, got {radius}")
    if window < 0:
        raise ValueError(f"window: expected >= 0, got {window}")
    groups = np.asarray(sessions, dtype=np.int64)
    seq = np.asarray(seqs, dtype=np.int64)
    index = DescriptorIndex(descriptors, groups=groups, seqs=seq)
    offsets, idx, dist = index.radius(
        descriptors, radius, exclude=Exclusion(groups, seq, window=int(window))
    )
    qi = np.repeat(np.arange(len(groups), dtype=np.int64), np.diff(offsets))
    keep = qi < idx
    return LoopCandidates(qi[keep], idx[keep], dist[keep])


def loop_candidates(mapdb: MapDatabase, radius: float = 0.1, window: int = 10) -> LoopCandidates:
    """:func:`descriptor_loop_candidates` of a map's keyframes (rows, their sessions and
    sequence numbers)."""
    return descriptor_loop_candidates(
        mapdb.global_descriptors, mapdb.session_index, mapdb.seq, radius, window
    )


def verify_pairs(
    model: VVLocNet,
    mapdb: MapDatabase,
    rows_i: np.ndarray,
    rows_j: np.ndarray,
    *,
    search: SearchConfig | None = None,
    progress: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Metric pose ξ_{i→j} (P, 3) and matching cost (P,) of map row pairs: keyframe i's stored
    BEV is the padded source, keyframe j's local-view descriptor the target."""
    cfg = model.config
    poses = np.zeros((len(rows_i), 3))
    costs = np.zeros(len(rows_i))
    pairs = zip(rows_i, rows_j, strict=True)
    for k, (i, j) in enumerate(tqdm(pairs, total=len(rows_i), desc="loops", disable=not progress)):
        tgt = mapdb.local_descriptors(int(j))
        res = metric_localize(
            mapdb.bev(int(i)),
            tgt,
            interacting_decoder(model, tgt),
            search or SearchConfig(),
            float(cfg.grid_size),
            int(cfg.num_angles),
            int(cfg.num_radii),
        )
        poses[k] = res.pose
        costs[k] = res.cost
    return poses, costs


def detect_loops(
    model: VVLocNet,
    mapdb: MapDatabase,
    *,
    radius: float = 0.1,
    window: int = 10,
    cost_threshold: float = 0.75,
    search: SearchConfig | None = None,
    max_pairs: int | None = None,
    progress: bool = True,
) -> LoopClosures:
    """Detect loop closures in a map and estimate ξ_{i→j} for each; see the module docstring.

    Returns :class:`LoopClosures` whose ``i``/``j`` are keyframe *ids* (``mapdb.ids``), closest
    candidates in descriptor space first.

    The map must hold BEVs (built with ``store_bev=True``). ``max_pairs`` keeps only the
    closest candidates in descriptor space (None: all).
    """
    if not mapdb.has_bev:
        raise ValueError(
            f"map {mapdb.path}: has no BEVs; rebuild it with BEVs stored to detect loops"
        )
    cand = loop_candidates(mapdb, radius, window)
    order = np.argsort(cand.distance, kind="stable")
    if max_pairs is not None:
        order = order[:max_pairs]
    poses, costs = verify_pairs(
        model, mapdb, cand.i[order], cand.j[order], search=search, progress=progress
    )
    ids = np.asarray(mapdb.ids, dtype=np.int64)
    sel_i = ids[cand.i[order]]
    sel_j = ids[cand.j[order]]
    cost_arr = costs
    return LoopClosures(
        i=sel_i,
        j=sel_j,
        relative_poses=poses,
        costs=cost_arr,
        accepted=cost_arr < cost_threshold,
    )
