"""Loop-closure detection across the sessions of a map.

Candidates are map keyframe pairs (i, j), i < j, whose global descriptors lie within
``radius`` (L2, default 0.1 as in the paper) of each other, excluding temporal neighbours of the
same session (``|seq_i − seq_j| <= window``). With ``sequence = L > 0`` a candidate must also be
matched by its neighbours: the mean descriptor distance over the 2L + 1 keyframe pairs
(i + k, j ± k), k = −L..L, of the better of the two traversal directions must be below the
radius as well (:func:`sequence_distance`); an isolated look-alike, such as a view of the other
floor of a garage, is not. Each candidate gets a metric pose by the same
search as localization, with keyframe i's stored BEV as the padded source and keyframe j's
local-view descriptor as the target: ξ_{i→j} (frame j expressed in frame i, DESIGN.md §3). A
loop is accepted when its matching cost is below ``cost_threshold`` (0.75).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from tqdm import tqdm

from vvloc.evaluate import _int_array
from vvloc.kernels import _positive_float, _positive_int
from vvloc.localize.export import LoopClosures
from vvloc.localize.localizer import _cost_threshold, check_map_model, interacting_decoder
from vvloc.localize.mapdb import MapDatabase
from vvloc.localize.metric import SearchConfig, metric_localize
from vvloc.nets import VVLocNet
from vvloc.retrieval import DescriptorIndex, Exclusion

log = logging.getLogger("vvloc.localize")


@dataclass(frozen=True)
class LoopCandidates:
    """Candidate pairs (i < j map rows, int64) and their scores (float64), (P,) each:
    ``distance`` is the global-descriptor L2 distance of the pair, or with sequence consistency
    the larger of that and the pair's :func:`sequence_distance`; a candidate has
    ``distance < radius``."""

    i: np.ndarray
    j: np.ndarray
    distance: np.ndarray


#: Pairs per block in :func:`sequence_distance` (bounds its temporaries to BLOCK · D floats).
BLOCK = 65_536


def sequence_distance(
    descriptors: npt.ArrayLike,
    sessions: npt.ArrayLike,
    seqs: npt.ArrayLike,
    i: npt.ArrayLike,
    j: npt.ArrayLike,
    half_window: int,
    window: int = 0,
) -> np.ndarray:
    """Sequence-consistent descriptor distance of row pairs (i, j), (P,) float64.

    Keyframes are ordered by ``seqs`` within their session (``sessions``, (N,) ints); the k-th
    neighbour of row r is the keyframe k places after it in that order (before it for k < 0),
    whatever the gaps between sequence numbers. For the pair (i, j) this is the smaller, over
    the two traversal directions s = +1 (driving the same way) and s = −1 (the opposite way), of
    the mean L2 distance between ``descriptors`` (N, D) of neighbours (i + k, j + s·k),
    k = −L..L with L = ``half_window``.

    A direction is complete when every one of its 2L + 1 neighbour pairs exists and is
    admissible: both neighbours inside their sessions, and, for neighbours of one session, more
    than ``window`` sequence numbers apart (the loop candidates' temporal exclusion; with the
    default 0 only a keyframe compared with itself is excluded). A pair with no complete
    direction gets +inf: not enough context to confirm it (e.g. its ±L window leaves i's or j's
    session). ``half_window = 0`` gives the pair's own descriptor distance (or +inf for an
    inadmissible pair). ``i`` and ``j``: (P,) row indices.
    """
    L = _positive_int(half_window, "half_window", minimum=0)
    excl = _positive_int(window, "window", minimum=0)
    g = np.asarray(descriptors)
    if g.ndim != 2 or not np.issubdtype(g.dtype, np.number):
        raise ValueError(f"descriptors: expected a numeric (N, D) array, got shape {g.shape}")
    n = len(g)
    sess = _int_array(sessions, "sessions", "(N,)", 1)
    seq = _int_array(seqs, "seqs", "(N,)", 1)
    if sess.shape != (n,) or seq.shape != (n,):
        raise ValueError(f"sessions, seqs: expected ({n},) each, got {sess.shape} and {seq.shape}")
    i = _int_array(i, "i", "(P,)", 1)
    j = _int_array(j, "j", "(P,)", 1)
    if i.shape != j.shape or i.ndim != 1:
        raise ValueError(f"i, j: expected (P,) each, got {i.shape} and {j.shape}")
    if i.size and (min(i.min(), j.min()) < 0 or max(i.max(), j.max()) >= n):
        raise ValueError(f"i, j: expected row indices in [0, {n}), got values outside it")
    best = np.full(i.shape, np.inf)
    if not i.size or 2 * L + 1 > np.unique(sess, return_counts=True)[1].max():
        return best  # no pairs, or no session holds a whole window
    order = np.lexsort((seq, sess))  # rows by session, then sequence number
    where = np.empty(n, dtype=np.int64)
    where[order] = np.arange(n)
    sorted_sess = sess[order]

    def neighbour(rows: np.ndarray, k: int) -> np.ndarray:
        """Row k places from each of ``rows`` in its session, −1 where there is none."""
        p = where[rows] + k
        inside = (p >= 0) & (p < n)
        p = np.clip(p, 0, n - 1)
        ok = inside & (sorted_sess[p] == sess[rows])
        return np.where(ok, order[p], -1)

    for lo in range(0, len(i), BLOCK):
        bi, bj = i[lo : lo + BLOCK], j[lo : lo + BLOCK]
        for sign in (1, -1) if L else (1,):
            total = np.zeros(bi.shape)
            complete = np.ones(bi.shape, dtype=bool)
            for k in range(-L, L + 1):
                a, b = neighbour(bi, k), neighbour(bj, sign * k)
                ok = (a >= 0) & (b >= 0)
                a, b = np.where(ok, a, 0), np.where(ok, b, 0)
                ok &= (sess[a] != sess[b]) | (np.abs(seq[a] - seq[b]) > excl)
                complete &= ok
                diff = g[a].astype(np.float64) - g[b]
                total += np.where(ok, np.sqrt((diff * diff).sum(axis=1)), 0.0)
            mean = np.where(complete, total / (2 * L + 1), np.inf)
            best[lo : lo + BLOCK] = np.minimum(best[lo : lo + BLOCK], mean)
    return best


def descriptor_loop_candidates(
    descriptors: np.ndarray,
    sessions: np.ndarray,
    seqs: np.ndarray,
    radius: float = 0.1,
    window: int = 10,
    sequence: int = 0,
) -> LoopCandidates:
    """All pairs i < j of ``descriptors`` (N, D) with L2 distance < ``radius``, excluding pairs
    of one session (``sessions`` (N,) int) within ``window`` sequence numbers (``seqs`` (N,)
    int): one radius query per row on the Rust index. ``sequence = L > 0`` also requires the
    pair's :func:`sequence_distance` with half-window L (and the same ``window``) to be below
    ``radius``."""
    if not radius > 0:
        raise ValueError(f"radius: expected > 0, got {radius}")
    if window < 0:
        raise ValueError(f"window: expected >= 0, got {window}")
    sequence = _positive_int(sequence, "sequence", minimum=0)
    groups = np.asarray(sessions, dtype=np.int64)
    seq = np.asarray(seqs, dtype=np.int64)
    index = DescriptorIndex(descriptors, groups=groups, seqs=seq)
    offsets, idx, dist = index.radius(
        descriptors, radius, exclude=Exclusion(groups, seq, window=int(window))
    )
    qi = np.repeat(np.arange(len(groups), dtype=np.int64), np.diff(offsets))
    keep = qi < idx
    cand = LoopCandidates(qi[keep], idx[keep], dist[keep].astype(np.float64))
    if sequence == 0:
        return cand
    return confirm_sequence(cand, descriptors, groups, seq, radius, sequence, window)


def confirm_sequence(
    cand: LoopCandidates,
    descriptors: npt.ArrayLike,
    sessions: npt.ArrayLike,
    seqs: npt.ArrayLike,
    radius: float,
    half_window: int,
    window: int = 10,
) -> LoopCandidates:
    """The candidates of ``cand`` (single keyframes, within ``radius``) whose
    :func:`sequence_distance` with ``half_window`` (and ``window``) is below ``radius`` too,
    scored by the larger of the two distances: what :func:`descriptor_loop_candidates` returns
    with ``sequence = half_window``, without a second radius query."""
    seq_dist = sequence_distance(descriptors, sessions, seqs, cand.i, cand.j, half_window, window)
    score = np.maximum(cand.distance, seq_dist)
    ok = score < radius
    return LoopCandidates(cand.i[ok], cand.j[ok], score[ok])


def sweep_radius(
    descriptors: np.ndarray,
    sessions: np.ndarray,
    seqs: np.ndarray,
    max_pairs: int,
    *,
    window: int = 10,
    r_max: float = 0.5,
    sample: int = 256,
    seed: int = 0,
) -> float:
    """The largest descriptor radius ``r <= r_max`` whose :func:`descriptor_loop_candidates`
    (same ``window``, no sequence check) is estimated to hold at most ``max_pairs`` pairs: the
    bound of a precision-recall sweep that must fit in memory (every pair costs ≈ 150 bytes
    while it is scored).

    ``descriptors`` (N, D) float, ``sessions`` and ``seqs`` (N,) int as for
    :func:`descriptor_loop_candidates`. The estimate scales the neighbours within ``r_max`` of
    ``sample`` rows drawn with ``seed`` by N / sample; with N <= ``sample`` it is exact. The
    result may lie below the radius the caller must cover, or be 0.0 (more pairs at distance 0
    than allowed): the caller decides what then.
    """
    max_pairs = _positive_int(max_pairs, "max_pairs")
    sample = _positive_int(sample, "sample")
    r_max = _positive_float(r_max, "r_max")
    groups = np.asarray(sessions, dtype=np.int64)
    seq = np.asarray(seqs, dtype=np.int64)
    n = len(groups)
    if n == 0:
        return r_max
    rows = np.arange(n) if n <= sample else np.random.default_rng(seed).choice(n, sample, False)
    index = DescriptorIndex(descriptors, groups=groups, seqs=seq)
    _, _, dist = index.radius(
        np.asarray(descriptors)[rows],
        r_max,
        exclude=Exclusion(groups[rows], seq[rows], window=int(window)),
    )
    # directed neighbours of the sampled rows → undirected pairs of all rows
    allowed = max_pairs * 2 * len(rows) // n
    if dist.size <= allowed:
        return r_max
    return float(np.partition(dist.astype(np.float64), allowed)[allowed])  # pairs with d < r ≤ it


def loop_candidates(
    mapdb: MapDatabase, radius: float = 0.1, window: int = 10, sequence: int = 0
) -> LoopCandidates:
    """:func:`descriptor_loop_candidates` of a map's keyframes (rows, their sessions and
    sequence numbers)."""
    return descriptor_loop_candidates(
        mapdb.global_descriptors, mapdb.session_index, mapdb.seq, radius, window, sequence
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
    """Metric pose ξ_{i→j} (P, 3) and matching cost (P,) of map row pairs (``rows_i``,
    ``rows_j`` (P,) ints): keyframe i's stored BEV is the padded source, keyframe j's
    local-view descriptor the target. It does not check that ``model`` built the map (the
    caller does, once: :func:`~vvloc.localize.localizer.check_map_model`, as
    :func:`detect_loops` does)."""
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
    sequence: int = 1,
    cost_threshold: float = 0.75,
    search: SearchConfig | None = None,
    max_pairs: int | None = None,
    progress: bool = True,
) -> LoopClosures:
    """Detect loop closures in a map and estimate ξ_{i→j} for each; see the module docstring.

    Returns :class:`LoopClosures` whose ``i``/``j`` are keyframe *ids* (``mapdb.ids``), closest
    candidates in descriptor space first.

    The map must hold BEVs (built with ``store_bev=True``) and have been built by ``model``
    (:func:`~vvloc.localize.localizer.check_map_model`: ``MapError`` otherwise). ``max_pairs``
    keeps only the closest candidates in descriptor space (None: all). ``sequence``: the
    half-window L of the sequence-consistency check (default 1: the pairs of the neighbouring
    keyframes must match too; 0: single keyframes, the paper's test).
    """
    check_map_model(mapdb, model)
    cost_threshold = _cost_threshold(cost_threshold, "cost_threshold")
    if not mapdb.has_bev:
        raise ValueError(
            f"map {mapdb.path}: has no BEVs; rebuild it with BEVs stored to detect loops"
        )
    cand = loop_candidates(mapdb, radius, window, sequence)
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
