"""Loop-closure detection across the sessions of a map.

Candidates are map keyframe pairs (i, j), i < j, whose global descriptors lie within
``radius`` (L2, default 0.1 as in the paper) of each other, excluding temporal neighbours of the
same session (``|seq_i − seq_j| <= window``). With ``sequence = L > 0`` a candidate must also be
matched by its neighbours: the mean descriptor distance over the 2L + 1 keyframe pairs
(i + k, j ± k), k = −L..L, of the better of the two traversal directions must be below the
radius as well (:func:`sequence_distance`); an isolated look-alike, such as a view of the other
floor of a garage, is not. With the floor check (on by default in :func:`detect_loops`) a
candidate must also agree with the floors of the map's sessions: each session numbers its floors
by its own odometry, a loop claims its two keyframes are on one floor, so the candidates of two
sessions vote for the offset between their numberings and only those of the winning offset are
kept (:func:`floor_offsets`), and candidates within one session must join equal floor numbers;
a garage's look-alikes of the other floor vote for another offset than the true loops and are
dropped. Each candidate gets a metric pose by the same
search as localization, with keyframe i's stored BEV as the padded source and keyframe j's
local-view descriptor as the target: ξ_{i→j} (frame j expressed in frame i, DESIGN.md §3); the
candidates of one keyframe i share the search's coarse stage (:func:`verify_pairs`). A
loop is accepted when its matching cost is below ``cost_threshold`` (0.75).
"""

from __future__ import annotations

import dataclasses
import logging
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from tqdm import tqdm

from vvloc._checks import as_array, flag, int_array, positive_float, positive_int, real_number
from vvloc.localize.export import LoopClosures, _selection
from vvloc.localize.localizer import _cost_threshold, check_map_model, learned_matcher
from vvloc.localize.mapdb import MapDatabase
from vvloc.localize.metric import SearchConfig, metric_localize_each, search_config
from vvloc.nets import VVLocNet
from vvloc.retrieval import DescriptorIndex, Exclusion

__all__ = [
    "BLOCK",
    "FLOOR_MARGIN",
    "FLOOR_MIN_VOTES",
    "FLOOR_VOTE_FACTOR",
    "FloorOffsets",
    "LoopCandidates",
    "confirm_sequence",
    "descriptor_loop_candidates",
    "detect_loops",
    "floor_consensus",
    "floor_consistent",
    "floor_offsets",
    "loop_candidates",
    "loop_provenance",
    "sequence_distance",
    "sweep_radius",
    "verify_pairs",
]

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

    def subset(self, keep: np.ndarray) -> LoopCandidates:
        """The candidates where ``keep`` (P,) bool is true (or at int indices ``keep``)."""
        keep = _selection(keep, len(self.i), "keep")
        return LoopCandidates(self.i[keep], self.j[keep], self.distance[keep])

    def within(self, radius: float) -> LoopCandidates:
        """The candidates with ``distance < radius`` (the pairs a radius query at ``radius``
        returns; this compares float64 distances, the Rust query float32 ones, so a pair at
        exactly the radius may fall either way). ``radius`` a number, not NaN (inf: all)."""
        return self.subset(self.distance < real_number(radius, "radius"))  # NaN kept nothing

    def closest_per_keyframe(self, k: int) -> LoopCandidates:
        """The candidates that are among the ``k`` (an int >= 1) closest of either of their two
        keyframes: each keyframe's candidates (the pairs it is ``i`` or ``j`` of) ranked by
        ``distance``, equal distances in candidate order. At most N·k pairs stay for N keyframes
        however many sessions revisit a place (the candidates grow about as their square), and
        every keyframe that had a candidate keeps its closest. Order as in ``self``."""
        k = positive_int(k, "k")
        n = len(self.i)
        by_distance = np.argsort(self.distance, kind="stable")
        # both ends of every pair, in distance order: (keyframe, rank of the pair, pair)
        ends = np.concatenate([self.i[by_distance], self.j[by_distance]])
        rank = np.tile(np.arange(n), 2)
        at = np.lexsort((rank, ends))  # by keyframe, then by distance
        ends = ends[at]
        start = np.searchsorted(ends, ends)  # where each keyframe's candidates begin
        within = np.arange(2 * n) - start < k  # the pair is among its keyframe's k closest
        keep = np.zeros(n, dtype=bool)
        keep[np.tile(by_distance, 2)[at][within]] = True
        return self.subset(keep)


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
    L = positive_int(half_window, "half_window", minimum=0)
    excl = positive_int(window, "window", minimum=0)
    g = as_array(descriptors, "descriptors", "(N, D)")  # float32 stays float32: no copy
    if g.dtype == np.bool_ or not (
        np.issubdtype(g.dtype, np.floating) or np.issubdtype(g.dtype, np.integer)
    ):
        raise TypeError(f"descriptors: expected a real (N, D) array, got dtype {g.dtype}")
    if g.ndim != 2:
        raise ValueError(f"descriptors: expected a real (N, D) array, got shape {g.shape}")
    if not np.isfinite(g).all():  # a NaN row would give NaN distances, never +inf or a number
        raise ValueError("descriptors: contains non-finite values (NaN or inf)")
    n = len(g)
    sess, seq = _sessions_and_seqs(g, sessions, seqs)
    i = int_array(i, "i", "(P,)", 1)
    j = int_array(j, "j", "(P,)", 1)
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


def _index_radius(radius: float) -> float:
    """A radius (finite, > 0) for the Rust index's radius query, which compares float32
    distances: one beyond float32's range takes every pair, one below its smallest subnormal
    the identical rows alone, as the radius itself would."""
    f32 = np.finfo(np.float32)
    return min(max(radius, float(f32.smallest_subnormal)), float(f32.max))


def _radius_and_window(radius: Any, window: Any) -> tuple[float, int]:
    """A loop detector's descriptor ``radius`` (a finite float > 0) and temporal ``window``
    (an int >= 0: keyframes of one session this close in sequence number are neighbours, not
    loops), named in the error otherwise."""
    return positive_float(radius, "radius"), positive_int(window, "window", minimum=0)


def _sessions_and_seqs(
    descriptors: Any, sessions: Any, seqs: Any
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """``sessions`` and ``seqs`` as (N,) int64, one per row of ``descriptors`` (N, D): a
    ``TypeError``/``ValueError`` naming the argument otherwise (float session ids were cut to
    ints, 0.2 and 0.7 into one session)."""
    sess = int_array(sessions, "sessions", "(N,)", 1)
    seq = int_array(seqs, "seqs", "(N,)", 1)
    shape = np.shape(descriptors)
    n = int(shape[0]) if len(shape) == 2 else len(sess)
    for name, arr in (("sessions", sess), ("seqs", seq)):
        if arr.shape != (n,):
            raise ValueError(
                f"{name}: expected shape ({n},), one per descriptor row, got {arr.shape}"
            )
    return sess, seq


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
    radius, window = _radius_and_window(radius, window)
    sequence = positive_int(sequence, "sequence", minimum=0)
    groups, seq = _sessions_and_seqs(descriptors, sessions, seqs)
    index = DescriptorIndex(descriptors, groups=groups, seqs=seq)
    offsets, idx, dist = index.radius(
        descriptors, _index_radius(radius), exclude=Exclusion(groups, seq, window=window)
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
    longest = np.unique(np.asarray(sessions), return_counts=True)[1].max(initial=0)
    if half_window and 2 * half_window + 1 > longest > 0:  # all refused: said, not silent
        warnings.warn(
            f"the sequence check's half-window {half_window} needs {2 * half_window + 1} "
            f"keyframes of a session around each keyframe of a pair, and the longest session "
            f"holds {longest}: no loop candidate can be confirmed (a smaller sequence "
            "half-window, or 0 for no sequence check)",
            stacklevel=2,
        )
    score = np.maximum(cand.distance, seq_dist)
    return LoopCandidates(cand.i, cand.j, score).within(radius)


#: The floor-consensus check's defaults (:func:`floor_offsets`, :func:`loop_candidates`): the
#: session pairs' floor offsets are voted by the single-keyframe candidates within
#: ``FLOOR_VOTE_FACTOR`` × the acceptance radius, and an offset is taken when it has at least
#: ``FLOOR_MIN_VOTES`` votes and ``FLOOR_MARGIN`` times as many as any other offset of the pair.
#: Chosen on the default garage's validation sessions (models/synth-small/HISTORY.md, "Loop
#: closures checked against the sessions' floors").
FLOOR_VOTE_FACTOR = 2.0
FLOOR_MARGIN = 2.0
FLOOR_MIN_VOTES = 3


@dataclass(frozen=True)
class _Floors:
    """A map's validated floor numbers: ``ids`` (S,) its sorted session ids, ``dense`` (N,)
    each row's session index 0..S−1 (``ids[dense]`` the given ids), ``floors`` (N,), all int64,
    and ``single`` (S,) bool: whether the session holds one floor number only."""

    ids: np.ndarray
    dense: np.ndarray
    floors: np.ndarray
    single: np.ndarray

    @classmethod
    def of(cls, sessions: npt.ArrayLike, floors: npt.ArrayLike) -> _Floors:
        sess = int_array(sessions, "sessions", "(N,)", 1)
        fl = int_array(floors, "floors", "(N,)", 1)
        if fl.shape != sess.shape:
            raise ValueError(f"floors: expected shape {sess.shape} like sessions, got {fl.shape}")
        ids, dense = np.unique(sess, return_inverse=True)
        dense = dense.reshape(-1).astype(np.int64)
        lo = np.full(len(ids), np.iinfo(np.int64).max)
        hi = np.full(len(ids), np.iinfo(np.int64).min)
        np.minimum.at(lo, dense, fl)
        np.maximum.at(hi, dense, fl)
        return cls(ids.astype(np.int64), dense, fl, ~(hi > lo))

    def pairs(
        self, i: npt.ArrayLike, j: npt.ArrayLike, name: str = "i, j"
    ) -> tuple[np.ndarray, np.ndarray]:
        """Row-index pairs ``i``, ``j`` (P,) validated against this map (errors name ``name``)."""
        i = int_array(i, name, "(P,)", 1)
        j = int_array(j, name, "(P,)", 1)
        if i.shape != j.shape:
            raise ValueError(f"{name}: expected (P,) row indices each, got {i.shape} and {j.shape}")
        n = len(self.dense)
        if i.size and (min(i.min(), j.min()) < 0 or max(i.max(), j.max()) >= n):
            raise ValueError(f"{name}: expected row indices in [0, {n}), got values outside it")
        return i, j

    def pair_keys(self, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each pair's session-pair key ``lo · S + hi`` (lo <= hi its two dense sessions) and
        the floor offset it implies: floor of its lo-session keyframe minus floor of its
        hi-session keyframe."""
        a, b = self.dense[i], self.dense[j]
        key = np.minimum(a, b) * len(self.ids) + np.maximum(a, b)
        fi, fj = self.floors[i], self.floors[j]
        return key, np.where(a <= b, fi - fj, fj - fi)


@dataclass(frozen=True)
class FloorOffsets:
    """The floor offsets voted for session pairs (:func:`floor_offsets`): for the session pair
    (``lo[k]``, ``hi[k]``) (session ids, lo < hi), a keyframe on floor f of session lo is on
    floor f − ``offset[k]`` of session hi. Pairs absent here had no clear vote; keyframes of
    one session are always compared at offset 0. (K,) int64 each, sorted by (lo, hi);
    ``votes`` (K,) the winning offset's votes. Session pairs that each hold a single floor
    number are not voted on."""

    lo: np.ndarray
    hi: np.ndarray
    offset: np.ndarray
    votes: np.ndarray


def floor_offsets(
    sessions: npt.ArrayLike,
    floors: npt.ArrayLike,
    i: npt.ArrayLike,
    j: npt.ArrayLike,
    *,
    margin: float = FLOOR_MARGIN,
    min_votes: int = FLOOR_MIN_VOTES,
) -> FloorOffsets:
    """The floor offset between each two sessions, voted by candidate loop pairs (i, j).

    Every session numbers the floors it drives on by its own odometry: the numbers agree
    within a session, but nothing ties one session's numbering to another's. A loop closure
    claims that its two keyframes are on one floor, so a pair (i, j) of sessions A and B votes
    for the offset ``floors[i] − floors[j]`` between their numberings. True loops of a session
    pair agree on one offset; look-alikes of another floor (a garage's stacked floors) vote
    for the others. The offset with the most votes is taken when it has at least ``min_votes``,
    at least ``margin`` times as many votes as any other offset of the pair and more than any
    other (a tie is never taken); otherwise the pair has none (its loops are then refused by
    :func:`floor_consistent`: an unclear vote does not risk a loop across floors). Pairs of
    one session take no vote (their offset is 0), nor do pairs of two sessions that each hold
    a single floor number: their pairs all imply one offset and the floors cannot tell a true
    loop from a look-alike there (:func:`floor_consistent` keeps them).

    A vote is a keyframe pair, not a place: the neighbouring keyframes of one look-alike run
    vote together. Only differences within a session enter, so adding a constant to every
    floor number of a session changes no decision (the offsets shift by it).

    Args:
        sessions: (N,) int session id of each map row.
        floors: (N,) int floor number of each map row, in its session's own numbering.
        i, j: (P,) int row indices of the voting pairs (e.g. descriptor candidates).
        margin: >= 1, the winner's votes over the runner-up's.
        min_votes: >= 1, the fewest votes an offset is taken with.

    Returns:
        :class:`FloorOffsets` of the session pairs with a clear vote, sorted by (lo, hi).
    """
    f = _Floors.of(sessions, floors)
    return _vote(f, *f.pairs(i, j), margin, min_votes)


def _vote(f: _Floors, i: np.ndarray, j: np.ndarray, margin: float, min_votes: int) -> FloorOffsets:
    """:func:`floor_offsets` of validated inputs."""
    margin = positive_float(margin, "margin")
    if margin < 1.0:
        raise ValueError(f"margin: expected a value >= 1, got {margin}")
    min_votes = positive_int(min_votes, "min_votes")
    span = len(f.ids)
    key, offset = f.pair_keys(i, j)
    a, b = f.dense[i], f.dense[j]
    # pairs of two sessions vote, unless both sessions hold a single floor number
    cross = (a != b) & ~(f.single[a] & f.single[b])
    if not cross.any():
        empty = np.zeros(0, np.int64)
        return FloorOffsets(empty, empty, empty, empty)
    votes, count = np.unique(
        np.stack([key[cross], offset[cross]], axis=1), axis=0, return_counts=True
    )
    order = np.lexsort((-count, votes[:, 0]))  # by key, the most voted offset first
    votes, count = votes[order], count[order]
    starts = np.flatnonzero(np.r_[True, votes[1:, 0] != votes[:-1, 0]])
    top = count[starts]
    has_second = np.r_[starts[1:], len(votes)] - starts > 1
    second = np.where(has_second, count[np.minimum(starts + 1, len(count) - 1)], 0)
    clear = (top >= min_votes) & (top >= margin * second) & (top > second)  # never a tie
    keys = votes[starts[clear], 0]
    return FloorOffsets(
        lo=f.ids[keys // span],
        hi=f.ids[keys % span],
        offset=votes[starts[clear], 1],
        votes=top[clear].astype(np.int64),
    )


def _offset_keys(offsets: FloorOffsets, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``offsets`` (:class:`FloorOffsets` of sessions ``ids``) as sorted dense session-pair keys
    and their offsets; ValueError/TypeError naming ``offsets`` when they are not of these."""
    if not isinstance(offsets, FloorOffsets):
        raise TypeError(f"offsets: expected FloorOffsets, got {type(offsets).__name__}")
    lo = int_array(offsets.lo, "offsets.lo", "(K,)", 1)
    hi = int_array(offsets.hi, "offsets.hi", "(K,)", 1)
    off = int_array(offsets.offset, "offsets.offset", "(K,)", 1)
    if not lo.shape == hi.shape == off.shape:
        raise ValueError(
            f"offsets: expected lo, hi, offset of one length, got {lo.shape}, {hi.shape}, "
            f"{off.shape}"
        )
    dlo, dhi = np.searchsorted(ids, lo), np.searchsorted(ids, hi)
    known = np.zeros(len(lo), bool)
    if len(ids):
        known = ids[np.minimum(dlo, len(ids) - 1)] == lo
        known &= ids[np.minimum(dhi, len(ids) - 1)] == hi
    keys = dlo * len(ids) + dhi
    if not known.all() or np.any(lo >= hi) or np.any(np.diff(keys) <= 0):
        raise ValueError(
            "offsets: expected the FloorOffsets of these sessions (floor_offsets: session ids "
            "of the map, lo < hi, sorted)"
        )
    return keys, off


def floor_consistent(
    sessions: npt.ArrayLike,
    floors: npt.ArrayLike,
    i: npt.ArrayLike,
    j: npt.ArrayLike,
    offsets: FloorOffsets,
) -> np.ndarray:
    """(P,) bool: whether each pair (i, j) lies on one floor under ``offsets``
    (:func:`floor_offsets`): pairs of one session when their floor numbers are equal, pairs of
    two sessions when their offset is the one voted for that session pair (never when the pair
    had no clear vote), and always when both sessions hold a single floor number (the floors
    cannot tell there). ``sessions``, ``floors`` (N,) int and ``i``, ``j`` (P,) int as for
    :func:`floor_offsets`."""
    f = _Floors.of(sessions, floors)
    return _agree(f, *f.pairs(i, j), offsets)


def _agree(f: _Floors, i: np.ndarray, j: np.ndarray, offsets: FloorOffsets) -> np.ndarray:
    """:func:`floor_consistent` of validated inputs."""
    voted, want_of = _offset_keys(offsets, f.ids)
    key, offset = f.pair_keys(i, j)
    found = np.zeros(len(key), bool)
    want = np.zeros(len(key), np.int64)
    if len(voted):
        at = np.minimum(np.searchsorted(voted, key), len(voted) - 1)
        found = voted[at] == key
        want = want_of[at]
    a, b = f.dense[i], f.dense[j]
    untold = f.single[a] & f.single[b]
    return np.where(a == b, offset == 0, untold | (found & (offset == want)))


def _candidates(x: Any, name: str) -> LoopCandidates:
    if not isinstance(x, LoopCandidates):
        raise TypeError(f"{name}: expected LoopCandidates, got {type(x).__name__}")
    if not np.shape(x.i) == np.shape(x.j) == np.shape(x.distance):
        raise ValueError(
            f"{name}: expected i, j, distance of one length, got {np.shape(x.i)}, "
            f"{np.shape(x.j)}, {np.shape(x.distance)}"
        )
    return x


def floor_consensus(
    cand: LoopCandidates,
    sessions: npt.ArrayLike,
    floors: npt.ArrayLike,
    voters: LoopCandidates | None = None,
    *,
    margin: float = FLOOR_MARGIN,
    min_votes: int = FLOOR_MIN_VOTES,
) -> LoopCandidates:
    """The candidates of ``cand`` on one floor (:func:`floor_consistent`) under the session
    pairs' offsets voted by ``voters`` (:func:`floor_offsets`; None: by ``cand`` itself).
    ``sessions`` and ``floors``: (N,) int of the map's rows (``MapDatabase.session_index``,
    ``MapDatabase.floors``)."""
    cand = _candidates(cand, "cand")
    vote = cand if voters is None else _candidates(voters, "voters")
    f = _Floors.of(sessions, floors)  # the map's sessions validated once, for both steps
    ok = _agree(
        f,
        *f.pairs(cand.i, cand.j, "cand"),
        _vote(f, *f.pairs(vote.i, vote.j, "voters"), margin, min_votes),
    )
    return cand.subset(ok)


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
    max_pairs = positive_int(max_pairs, "max_pairs")
    sample = positive_int(sample, "sample")
    r_max = positive_float(r_max, "r_max")
    window = positive_int(window, "window", minimum=0)
    groups, seq = _sessions_and_seqs(descriptors, sessions, seqs)
    n = len(groups)
    if n == 0:
        return r_max
    rows = np.arange(n) if n <= sample else np.random.default_rng(seed).choice(n, sample, False)
    index = DescriptorIndex(descriptors, groups=groups, seqs=seq)
    _, _, dist = index.radius(
        np.asarray(descriptors)[rows],
        _index_radius(r_max),
        exclude=Exclusion(groups[rows], seq[rows], window=window),
    )
    # directed neighbours of the sampled rows → undirected pairs of all rows
    allowed = max_pairs * 2 * len(rows) // n
    if dist.size <= allowed:
        return r_max
    return float(np.partition(dist.astype(np.float64), allowed)[allowed])  # pairs with d < r ≤ it


def loop_candidates(
    mapdb: MapDatabase,
    radius: float = 0.1,
    window: int = 10,
    sequence: int = 0,
    check_floors: bool = False,
) -> LoopCandidates:
    """:func:`descriptor_loop_candidates` of a map's keyframes (rows, their sessions and
    sequence numbers): pairs whose global descriptors lie within ``radius`` (L2 distance of the
    unit descriptors, dimensionless: not metres), same-session pairs within ``window``
    sequence numbers of each other left out. ``sequence``: as in :func:`detect_loops`.
    ``check_floors`` (off here, on by default in :func:`detect_loops`): keep
    only the candidates on one floor (:func:`floor_consensus`, the session pairs' offsets voted
    by the single-keyframe candidates within ``FLOOR_VOTE_FACTOR`` × ``radius``; the map's
    ``floors`` in each session's own numbering). A map built without floor numbers has 0
    everywhere, which the check reads as one floor per session: it then keeps every candidate,
    unless some sessions of the map do carry floor numbers (mixing them misjudges the pairs)."""
    g, sess, seq = mapdb.global_descriptors, mapdb.session_index, mapdb.seq
    radius, window = _radius_and_window(radius, window)  # before the voters' radius
    flag(check_floors, "check_floors")
    if not check_floors:
        return descriptor_loop_candidates(g, sess, seq, radius, window, sequence)
    voters = descriptor_loop_candidates(
        g, sess, seq, _index_radius(FLOOR_VOTE_FACTOR * radius), window
    )
    cand = voters.within(radius)
    sequence = positive_int(sequence, "sequence", minimum=0)
    if sequence:
        cand = confirm_sequence(cand, g, sess, seq, radius, sequence, window)
    kept = floor_consensus(cand, sess, mapdb.floors, voters)
    log.info("floor check: %d of %d loop candidates kept", len(kept.i), len(cand.i))
    return kept


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
    local-view descriptor the target. Each pair's result is :func:`metric_localize`'s; the
    pairs of one source share its coarse stage (:func:`metric_localize_each`: padded and
    decoded once). It does not check that ``model`` built the map (the caller does, once:
    :func:`~vvloc.localize.localizer.check_map_model`, as :func:`detect_loops` does)."""
    cfg = model.config
    rows_i = int_array(rows_i, "rows_i", "(P,)", 1)
    rows_j = int_array(rows_j, "rows_j", f"({len(rows_i)},), as rows_i", 1, len(rows_i))
    poses = np.zeros((len(rows_i), 3))
    costs = np.zeros(len(rows_i))
    search = search_config(search, "search")
    # the pairs of each source, the sources in the order of their first pair
    order = np.argsort(rows_i, kind="stable")
    groups = np.split(order, np.flatnonzero(np.diff(rows_i[order]) != 0) + 1) if len(order) else []
    groups.sort(key=lambda at: int(at[0]))
    bar = tqdm(total=len(rows_i), desc="loops", disable=not progress)
    for at in groups:
        tgts = np.stack([mapdb.local_descriptors(int(j)) for j in rows_j[at]])
        decode, interact = learned_matcher(model, tgts)
        results = metric_localize_each(
            mapdb.bev(int(rows_i[at[0]])),
            tgts,
            decode,
            interact,
            search,
            float(cfg.grid_size),
            int(cfg.num_angles),
            int(cfg.num_radii),
        )
        for k, res in zip(at, results, strict=True):
            poses[k] = res.pose
            costs[k] = res.cost
        bar.update(len(at))
    bar.close()
    return poses, costs


def detect_loops(
    model: VVLocNet,
    mapdb: MapDatabase,
    *,
    radius: float = 0.1,
    window: int = 10,
    sequence: int = 1,
    check_floors: bool = True,
    cost_threshold: float = 0.75,
    search: SearchConfig | None = None,
    max_pairs: int | None = None,
    progress: bool = True,
    previous: LoopClosures | None = None,
    max_per_keyframe: int | None = None,
) -> LoopClosures:
    """Detect loop closures in a map and estimate ξ_{i→j} for each; see the module docstring.

    Returns :class:`LoopClosures` whose ``i``/``j`` are keyframe *ids* (``mapdb.ids``), closest
    candidates in descriptor space first, ``relative_poses`` (P, 3) ξ_{i→j} (metres, radians,
    keyframe i's frame), ``costs`` (P,) and ``accepted`` (P,) = costs < ``cost_threshold``.

    ``radius``: candidates are the keyframe pairs whose global descriptors lie within it (L2
    distance of the unit descriptors, dimensionless: not metres); ``window``: pairs of one
    session within this many sequence numbers of each other are not loops (neighbours).

    The map must hold BEVs (built with ``store_bev=True``) and have been built by ``model``
    (:func:`~vvloc.localize.localizer.check_map_model`: ``MapError`` otherwise). ``max_pairs``
    (an int >= 0; None: all) keeps only the closest candidates in descriptor space;
    ``max_per_keyframe`` (an int >= 1; None: all), applied before it, only those among the
    closest of either keyframe (:meth:`LoopCandidates.closest_per_keyframe`): the candidates of
    a map whose sessions revisit the same places grow about as the square of the sessions, this
    bounds them by the keyframes. ``sequence``: the half-window L of the sequence-consistency
    check (default 1: the pairs of the neighbouring keyframes must match too; 0: single
    keyframes, the paper's test).
    ``check_floors`` (default on): keep only candidates consistent with the floors of the map's
    sessions (:func:`floor_consensus`; the module docstring).

    ``previous``: the loop closures of an earlier call (or :func:`read_loop_csv` of its
    ``loops.csv``) on a map these keyframes were added to, as a mapping service re-detects
    after each session or batch: a candidate pair of keyframe ids found there keeps its pose
    and cost without a new metric search (the slow part: 0.26 s a pair for the small model on
    2 CPU cores, BENCHMARKS.md), and only the new pairs are searched; acceptance follows
    ``cost_threshold`` anew. A pair's search depends only on its two keyframes, the model and
    ``search``, so the result is the one a full run gives (bit for bit with MKL) as long as
    ``previous`` came from this model, the same ``search`` settings and keyframes that kept
    their ids. The first two are checked: ``ValueError`` unless ``previous.provenance`` is
    this call's :func:`loop_provenance` (an earlier call's result and :func:`read_loop_csv`
    carry it; give it to a :class:`LoopClosures` of your own making). The ids are not: a map
    built again numbers its keyframes anew (``vvloc loops --reuse`` matches them by session,
    time and descriptors instead).

    The result's ``provenance`` is :func:`loop_provenance` ``(model, search)``.
    """
    if previous is not None and not isinstance(previous, LoopClosures):
        raise TypeError(f"previous: expected LoopClosures or None, got {type(previous).__name__}")
    check_map_model(mapdb, model)
    cost_threshold = _cost_threshold(cost_threshold, "cost_threshold")
    radius, window = _radius_and_window(radius, window)
    search = search_config(search, "search")
    search.validate()  # a bad one fails here, not at the first pair
    provenance = loop_provenance(model, search)
    if previous is not None:
        _check_previous(previous.provenance, provenance)
    if max_pairs is not None:
        max_pairs = positive_int(max_pairs, "max_pairs", minimum=0)
    if max_per_keyframe is not None:
        max_per_keyframe = positive_int(max_per_keyframe, "max_per_keyframe")
    if not mapdb.has_bev:
        raise ValueError(
            f"map {mapdb.path}: has no BEVs; rebuild it with BEVs stored to detect loops"
        )
    cand = loop_candidates(mapdb, radius, window, sequence, check_floors)
    if max_per_keyframe is not None:
        cand = cand.closest_per_keyframe(max_per_keyframe)
    order = np.argsort(cand.distance, kind="stable")
    if max_pairs is not None:
        order = order[:max_pairs]
    ids = np.asarray(mapdb.ids, dtype=np.int64)
    sel_i = ids[cand.i[order]]
    sel_j = ids[cand.j[order]]
    poses = np.zeros((len(order), 3))
    costs = np.zeros(len(order))
    new = np.ones(len(order), dtype=bool)
    if previous is not None:  # pairs searched before: their pose and cost as found then
        before = zip(previous.i.tolist(), previous.j.tolist(), strict=True)
        known = {pair: k for k, pair in enumerate(before)}
        for n, pair in enumerate(zip(sel_i.tolist(), sel_j.tolist(), strict=True)):
            k = known.get(pair)
            if k is not None:
                poses[n], costs[n], new[n] = previous.relative_poses[k], previous.costs[k], False
    poses[new], costs[new] = verify_pairs(
        model, mapdb, cand.i[order[new]], cand.j[order[new]], search=search, progress=progress
    )
    return LoopClosures(
        i=sel_i,
        j=sel_j,
        relative_poses=poses,
        costs=costs,
        accepted=costs < cost_threshold,
        provenance=provenance,
    )


def loop_provenance(model: VVLocNet, search: SearchConfig | None = None) -> tuple[str, ...]:
    """What the pose and cost of a loop pair depend on besides its two keyframes' stored BEV
    and descriptors: ``("model config <16 hex>", "model weights <64 hex>", "search
    SearchConfig(...)")``, the model's :meth:`~VVLocNet.config_hash` and
    :meth:`~VVLocNet.weights_hash` and the metric search's settings (None: the defaults).
    :attr:`LoopClosures.provenance` of :func:`detect_loops`' result; ``loops.csv`` holds
    these lines as comments. The search is written by its values, so that equal settings give
    one line (``half_range=2`` and ``2.0``, a numpy float): for the defaults it is the
    ``repr`` that ``vvloc loops`` has written since 2026-12-06."""
    search = search_config(search, "search")
    values = ", ".join(
        f"{f.name}={int(v) if f.type in ('int', int) else float(v)!r}"
        for f in dataclasses.fields(search)
        for v in [getattr(search, f.name)]
    )
    return (
        f"model config {model.config_hash()}",
        f"model weights {model.weights_hash()}",
        f"search SearchConfig({values})",
    )


def _check_previous(given: tuple[str, ...], wanted: tuple[str, ...]) -> None:
    """``ValueError`` naming ``previous`` unless its provenance ``given`` is ``wanted``."""
    if not given:
        raise ValueError(
            "previous: carries no provenance (the model and search settings its poses came "
            "from), so its pairs cannot be kept safely: pass detect_loops' result or "
            "read_loop_csv of a loops.csv written since 2026-12-06, or give a LoopClosures of "
            "your own provenance=loop_provenance(model, search) when you know them"
        )
    if set(given) != set(wanted):
        ours = [w for w in wanted if w not in given]
        theirs = [g for g in given if g not in wanted]
        raise ValueError(
            "previous: its poses came from another model or search settings than this "
            f"call's; this call has {'; '.join(ours) or '(nothing more)'}, previous has "
            f"{'; '.join(theirs) or '(nothing more)'}"
        )
