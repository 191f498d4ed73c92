"""Sequence-consistent loop candidates (vvloc.localize.loops) on hand-made descriptors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from nets_helpers import tiny_config
from vvloc.localize.loops import (
    FloorOffsets,
    LoopCandidates,
    confirm_sequence,
    descriptor_loop_candidates,
    floor_consensus,
    floor_consistent,
    floor_offsets,
    sequence_distance,
    sweep_radius,
    verify_pairs,
)
from vvloc.localize.mapdb import MapDatabase
from vvloc.localize.metric import SearchConfig, metric_localize
from vvloc.nets import VVLocNet


def brute_sequence_distance(g, sessions, seqs, i, j, half, window=0):
    """Reference: each session's rows sorted by sequence number, neighbours by position; a
    neighbour pair of one session within ``window`` sequence numbers is not admissible."""
    rows = {s: sorted(np.flatnonzero(sessions == s), key=lambda r: seqs[r]) for s in set(sessions)}
    place = {r: (s, k) for s, rr in rows.items() for k, r in enumerate(rr)}

    def nb(r, k):
        s, p = place[r]
        return rows[s][p + k] if 0 <= p + k < len(rows[s]) else None

    out = []
    for a, b in zip(i, j, strict=True):
        best = np.inf
        for sign in (1, -1):
            ds = []
            for k in range(-half, half + 1):
                x, y = nb(a, k), nb(b, sign * k)
                if x is None or y is None:
                    break
                if sessions[x] == sessions[y] and abs(seqs[x] - seqs[y]) <= window:
                    break
                ds.append(float(np.linalg.norm(g[x] - g[y])))
            else:
                best = min(best, sum(ds) / len(ds))
        out.append(best)
    return np.array(out)


def two_drives(n: int = 12, reverse: bool = False, d: int = 8, seed: int = 0):
    """Session 0 drives places 0..n-1; session 1 the same places (backwards if ``reverse``) with
    small descriptor noise; sequence numbers of session 1 have gaps (keyframe selection)."""
    rng = np.random.default_rng(seed)
    places = rng.standard_normal((n, d))
    places /= np.linalg.norm(places, axis=1, keepdims=True)
    second = places[::-1] if reverse else places
    g = np.concatenate([places, second + 0.01 * rng.standard_normal((n, d))])
    sessions = np.repeat([0, 1], n)
    seqs = np.concatenate([np.arange(n), 3 * np.arange(n) + 100])
    return g, sessions, seqs


@settings(max_examples=40, deadline=None)
@given(
    st.integers(2, 30),
    st.integers(1, 3),
    st.integers(0, 3),
    st.integers(0, 6),
    st.integers(0, 10_000),
)
def test_sequence_distance_matches_the_brute_force_reference(n, n_sessions, half, window, seed):
    rng = np.random.default_rng(seed)
    g = rng.standard_normal((n, 4))
    sessions = rng.integers(0, n_sessions, n)
    seqs = rng.permutation(5 * n)[:n]  # unsorted rows, gaps between sequence numbers
    i, j = rng.integers(0, n, (2, 3 * n))
    got = sequence_distance(g, sessions, seqs, i, j, half, window)
    want = brute_sequence_distance(g, sessions, seqs, i, j, half, window)
    np.testing.assert_array_equal(np.isinf(got), np.isinf(want))
    fin = np.isfinite(want)
    np.testing.assert_allclose(got[fin], want[fin], rtol=1e-12, atol=1e-12)


def test_half_window_zero_is_the_pair_distance():
    g, sessions, seqs = two_drives()
    i, j = np.array([0, 3, 11]), np.array([12, 20, 23])
    got = sequence_distance(g, sessions, seqs, i, j, 0)
    np.testing.assert_allclose(got, np.linalg.norm(g[i] - g[j], axis=1))


def test_sequence_distance_refuses_descriptors_it_cannot_measure():
    g, sessions, seqs = two_drives()
    i, j = np.array([0, 3]), np.array([12, 20])
    bad = g.copy()
    bad[1, 0] = np.nan  # a neighbour of row 0: its distance came out nan, neither number nor inf
    with pytest.raises(ValueError, match=r"descriptors: contains non-finite values"):
        sequence_distance(bad, sessions, seqs, i, j, 1)
    for dtype in (np.bool_, np.complex128):
        with pytest.raises(
            TypeError, match=f"descriptors: expected a real .* got dtype {dtype.__name__}"
        ):
            sequence_distance(g.astype(dtype), sessions, seqs, i, j, 1)
    with pytest.raises(ValueError, match=r"descriptors: expected a real \(N, D\) array, got shape"):
        sequence_distance(g[0], sessions, seqs, i, j, 1)
    # a torch tensor that requires grad is read, as the kernels read it
    torch = pytest.importorskip("torch")
    t = torch.tensor(g, requires_grad=True)
    np.testing.assert_array_equal(
        sequence_distance(t, sessions, seqs, i, j, 1), sequence_distance(g, sessions, seqs, i, j, 1)
    )


@pytest.mark.parametrize("reverse", [False, True])
def test_a_revisit_in_either_direction_is_consistent(reverse):
    g, sessions, seqs = two_drives(reverse=reverse)
    a = 5
    b = 12 + (12 - 1 - a if reverse else a)  # session 1's row of the same place
    d = sequence_distance(g, sessions, seqs, np.array([a]), np.array([b]), 2)
    assert d[0] < 0.05  # noise 0.01 per component, D = 8
    # one place off: every neighbour pair is two different places
    off = sequence_distance(g, sessions, seqs, np.array([a]), np.array([b + 1]), 2)
    assert off[0] > 0.5


def test_a_window_leaving_the_session_gives_inf():
    g, sessions, seqs = two_drives(n=6)
    # row 0 has no predecessor; its revisit (row 6) has none either: no direction is complete
    d = sequence_distance(g, sessions, seqs, np.array([0, 2]), np.array([6, 8]), 1)
    assert np.isinf(d[0]) and np.isfinite(d[1])


def test_a_sequence_window_no_session_holds_is_said_not_silent():
    g, sessions, seqs = two_drives(n=6)
    # half-window 2: 5 keyframes per session, enough; 3 needs 7 and confirms nothing
    descriptor_loop_candidates(g, sessions, seqs, radius=0.1, window=2, sequence=2)
    with pytest.warns(UserWarning, match=r"half-window 3 needs 7 keyframes .* holds 6: no loop"):
        none = descriptor_loop_candidates(g, sessions, seqs, radius=0.1, window=2, sequence=3)
    assert len(none.i) == 0


def test_an_isolated_look_alike_is_rejected_by_the_sequence_check():
    g, sessions, seqs = two_drives(n=12)
    # session 1's frame at place 7 looks like place 3 (the other floor's copy of it)
    look = 12 + 7
    g[look] = g[3] + 1e-4
    single = descriptor_loop_candidates(g, sessions, seqs, radius=0.1, window=2, sequence=0)
    pairs = set(zip(single.i.tolist(), single.j.tolist(), strict=True))
    assert (3, look) in pairs
    seq = descriptor_loop_candidates(g, sessions, seqs, radius=0.1, window=2, sequence=1)
    seq_pairs = set(zip(seq.i.tolist(), seq.j.tolist(), strict=True))
    assert (3, look) not in seq_pairs
    # the true revisits with a full window survive, scored by max(pair, sequence) distance
    assert {(p, 12 + p) for p in range(1, 11) if p not in (6, 7, 8)} <= seq_pairs
    assert np.all(seq.distance < 0.1)
    full = sequence_distance(g, sessions, seqs, seq.i, seq.j, 1)
    pair = np.linalg.norm(g[seq.i] - g[seq.j], axis=1)  # the index's distances are float32
    np.testing.assert_allclose(seq.distance, np.maximum(full, pair), atol=1e-4)


def test_neighbour_pairs_inside_the_temporal_window_do_not_count():
    """Rows of one session, keyframes 10 sequence numbers apart, the pair (3, 6) and L = 1: the
    reverse direction pairs (2, 7), (3, 6), (4, 5), and (4, 5) are temporal neighbours at
    window 10; the forward direction pairs (2, 5), (3, 6), (4, 7), 30 sequence numbers apart."""
    rng = np.random.default_rng(1)
    g = rng.standard_normal((9, 4))
    g[6], g[5] = g[3], g[4]  # the reverse direction looks good: two of its pairs are equal
    sessions = np.zeros(9, dtype=np.int64)
    seqs = 10 * np.arange(9)
    forward = np.mean([np.linalg.norm(g[a] - g[a + 3]) for a in (2, 3, 4)])
    reverse = np.linalg.norm(g[2] - g[7]) / 3
    assert reverse < forward
    i, j = np.array([3]), np.array([6])
    assert sequence_distance(g, sessions, seqs, i, j, 1)[0] == pytest.approx(reverse)
    assert sequence_distance(g, sessions, seqs, i, j, 1, window=10)[0] == pytest.approx(forward)
    # with window 30 the forward pairs are temporal neighbours too: no complete direction
    assert np.isinf(sequence_distance(g, sessions, seqs, i, j, 1, window=30)[0])
    # a keyframe is never compared with itself: (4, 4) in the reverse direction of (3, 5)
    g[5] = g[3]
    fwd_35 = np.mean([np.linalg.norm(g[a] - g[a + 2]) for a in (2, 3, 4)])
    got = sequence_distance(g, sessions, seqs, i, np.array([5]), 1)[0]
    assert got == pytest.approx(fwd_35)


def test_a_window_longer_than_every_session_gives_inf():
    g, sessions, seqs = two_drives(n=4)
    d = sequence_distance(g, sessions, seqs, np.array([1, 2]), np.array([5, 6]), 2)
    assert np.isinf(d).all() and d.dtype == np.float64
    empty = sequence_distance(g, sessions, seqs, np.array([], np.int64), np.array([], np.int64), 1)
    assert empty.shape == (0,)


def test_bad_arguments_name_the_argument():
    g, sessions, seqs = two_drives(n=4)
    one = np.array([0])
    with pytest.raises(ValueError, match="half_window"):
        sequence_distance(g, sessions, seqs, one, one, -1)
    with pytest.raises(ValueError, match="window"):
        sequence_distance(g, sessions, seqs, one, one, 1, window=-1)
    with pytest.raises(TypeError, match="i: expected an integer array"):
        sequence_distance(g, sessions, seqs, np.array([0.9]), one, 1)
    with pytest.raises(TypeError, match="sessions: expected an integer array"):
        sequence_distance(g, sessions + 0.5, seqs, one, one, 1)
    with pytest.raises(TypeError, match="sequence"):
        descriptor_loop_candidates(g, sessions, seqs, sequence=True)
    with pytest.raises(ValueError, match=r"sessions: expected shape \(8,\), one per descriptor"):
        sequence_distance(g, sessions[:3], seqs, one, one, 1)
    with pytest.raises(ValueError, match="i, j"):
        sequence_distance(g, sessions, seqs, one, np.array([0, 1]), 1)
    with pytest.raises(ValueError, match="i, j"):
        sequence_distance(g, sessions, seqs, one, np.array([8]), 1)
    with pytest.raises(ValueError, match="descriptors"):
        sequence_distance(g[0], sessions, seqs, one, one, 1)
    with pytest.raises(TypeError, match="radius: expected a positive float, got str"):
        descriptor_loop_candidates(g, sessions, seqs, radius="0.1")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="radius: expected a finite value > 0, got inf"):
        descriptor_loop_candidates(g, sessions, seqs, radius=np.inf)
    with pytest.raises(TypeError, match="window: expected an int >= 0, got float"):
        descriptor_loop_candidates(g, sessions, seqs, window=1.7)  # type: ignore[arg-type]
    # a radius beyond float32's range (the index's distances) takes every pair (window 0: no
    # temporal neighbours)
    every = descriptor_loop_candidates(g, sessions, seqs, radius=1e39, window=0)
    assert len(every.i) == len(g) * (len(g) - 1) // 2
    # one below float32's smallest distance takes the identical rows alone
    twin = np.concatenate([g, g[:1]])
    none = descriptor_loop_candidates(
        twin, np.arange(len(twin)), np.zeros(len(twin), np.int64), 1e-50
    )
    assert (none.i.tolist(), none.j.tolist()) == ([0], [len(g)])
    with pytest.raises(TypeError, match="window: expected an int >= 0, got float"):
        sweep_radius(g, sessions, seqs, 10, window=1.7)  # type: ignore[arg-type]
    # session and sequence ids are ints, one per row (0.2 and 0.7 were cut into one session)
    for find in (
        lambda s, q: descriptor_loop_candidates(g, s, q),
        lambda s, q: sweep_radius(g, s, q, 10),
    ):
        with pytest.raises(TypeError, match="sessions: expected an integer array"):
            find(sessions + 0.2, seqs)
        with pytest.raises(TypeError, match="sessions: expected an integer array"):
            find(np.array(["a"] * len(g)), seqs)
        with pytest.raises(TypeError, match="seqs: expected an integer array"):
            find(sessions, seqs * 1.0)
        with pytest.raises(ValueError, match=rf"sessions: expected shape \({len(g)},\), one per"):
            find(sessions[:-1], seqs[:-1])
        with pytest.raises(ValueError, match=rf"seqs: expected shape \({len(g)},\)"):
            find(sessions, seqs[:-1])


def random_drives(n: int, sessions: int = 3, d: int = 16, seed: int = 0):
    rng = np.random.default_rng(seed)
    g = rng.standard_normal((n, d)).astype(np.float32)
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    sess = np.arange(n) % sessions
    seqs = np.arange(n) // sessions
    return g, sess, seqs


@pytest.mark.parametrize("max_pairs", [1, 7, 50, 400])
def test_sweep_radius_is_exact_on_small_sets(max_pairs):
    g, sess, seqs = random_drives(60)
    full = descriptor_loop_candidates(g, sess, seqs, radius=1.2, window=2)
    r = sweep_radius(g, sess, seqs, max_pairs, window=2, r_max=1.2)
    got = descriptor_loop_candidates(g, sess, seqs, radius=r, window=2)
    assert len(got.i) <= max_pairs
    if len(full.i) <= max_pairs:
        assert r == 1.2
    else:  # the largest such radius: one step beyond it holds more pairs than allowed
        more = descriptor_loop_candidates(g, sess, seqs, radius=r * (1 + 1e-6), window=2)
        assert len(more.i) > max_pairs


def test_sweep_radius_estimates_large_sets():
    g, sess, seqs = random_drives(3000, d=8, seed=1)
    budget = 200_000
    r = sweep_radius(g, sess, seqs, budget, window=2, r_max=1.0, sample=256)
    n = len(descriptor_loop_candidates(g, sess, seqs, radius=r, window=2).i)
    assert 0.8 * budget <= n <= 1.2 * budget  # sampled rows scale to all rows
    with pytest.raises(ValueError, match="max_pairs"):
        sweep_radius(g, sess, seqs, 0)
    with pytest.raises(TypeError, match="max_pairs"):
        sweep_radius(g, sess, seqs, 10.0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="r_max"):
        sweep_radius(g, sess, seqs, 10, r_max=0.0)
    with pytest.raises(ValueError, match="sample"):
        sweep_radius(g, sess, seqs, 10, sample=0)


@pytest.mark.parametrize("half", [1, 2])
def test_confirming_single_candidates_equals_the_sequence_query(half):
    g, sess, seqs = random_drives(90, sessions=3, d=4, seed=2)
    single = descriptor_loop_candidates(g, sess, seqs, radius=0.9, window=2)
    got = confirm_sequence(single, g, sess, seqs, 0.9, half, window=2)
    want = descriptor_loop_candidates(g, sess, seqs, radius=0.9, window=2, sequence=half)
    assert 0 < len(want.i) < len(single.i)
    np.testing.assert_array_equal(got.i, want.i)
    np.testing.assert_array_equal(got.j, want.j)
    np.testing.assert_array_equal(got.distance, want.distance)


# --- the floor check -------------------------------------------------------------------------


def stacked_floors(n: int = 6, d: int = 8, seed: int = 0):
    """Two sessions that each drive floor 0 and then floor 1 of a garage whose floors look the
    same: rows of session s are [floor 0: places 0..n-1, floor 1: places 0..n-1], descriptors of
    a place equal on both floors (small noise per row)."""
    rng = np.random.default_rng(seed)
    places = rng.standard_normal((n, d))
    places /= np.linalg.norm(places, axis=1, keepdims=True)
    g = np.concatenate([places] * 4) + 0.001 * rng.standard_normal((4 * n, d))
    sessions = np.repeat([0, 1], 2 * n)
    floors = np.tile(np.repeat([0, 1], n), 2)
    seqs = np.tile(np.arange(2 * n) * 20, 2)  # floors far apart in time
    return g.astype(np.float32), sessions, seqs, floors


def test_true_loops_outvote_the_look_alikes_of_each_other_floor():
    g, sessions, seqs, floors = stacked_floors()
    cand = descriptor_loop_candidates(g, sessions, seqs, radius=0.1, window=10)
    # every place matches itself on both floors, in both sessions: 2 + 2 × 2 pairs per place
    assert len(cand.i) == 6 * 6
    offsets = floor_offsets(sessions, floors, cand.i, cand.j)
    # across the sessions: 12 true loops (offset 0) against 6 look-alikes each of +1 and -1
    assert (offsets.lo.tolist(), offsets.hi.tolist(), offsets.offset.tolist()) == ([0], [1], [0])
    assert offsets.votes.tolist() == [12]
    kept = floor_consensus(cand, sessions, floors)
    assert len(kept.i) == 12
    assert np.all(floors[kept.i] == floors[kept.j])
    assert np.all(sessions[kept.i] != sessions[kept.j])  # one session's floors never join
    assert isinstance(kept, LoopCandidates)


def test_pairs_of_one_session_must_join_equal_floor_numbers():
    sessions = np.array([0, 0, 0, 0])
    floors = np.array([0, 1, 0, 1])
    ok = floor_consistent(
        sessions, floors, [0, 0, 1], [1, 2, 3], floor_offsets(sessions, floors, [], [])
    )
    assert ok.tolist() == [False, True, True]


def test_an_unclear_or_thin_vote_keeps_no_pair_of_those_sessions():
    sessions = np.repeat([0, 1], 4)
    floors = np.tile([0, 0, 1, 1], 2)
    # rows 0-3 session 0 (floors 0, 0, 1, 1), rows 4-7 session 1 (the same)
    same = ([0, 1, 2], [4, 5, 6])  # offset 0, three votes
    other = ([0, 1], [6, 7])  # offset -1, two votes: 3 < 2 × 2, no clear winner
    i, j = np.r_[same[0], other[0]], np.r_[same[1], other[1]]
    assert len(floor_offsets(sessions, floors, i, j).lo) == 0
    assert not floor_consistent(sessions, floors, i, j, floor_offsets(sessions, floors, i, j)).any()
    # a margin of 1.5 decides it; too few votes (min_votes 4) do not
    won = floor_offsets(sessions, floors, i, j, margin=1.5)
    assert won.offset.tolist() == [0]
    assert floor_consistent(sessions, floors, i, j, won).tolist() == [True] * 3 + [False] * 2
    assert len(floor_offsets(sessions, floors, i, j, margin=1.5, min_votes=4).lo) == 0


def test_sessions_of_one_floor_each_are_not_judged():
    sessions = np.repeat([0, 1, 2], 3)
    floors = np.array([0, 0, 0, 7, 7, 7, 0, 1, 0])  # sessions 0 and 1 hold one floor number each
    i, j = np.array([0, 1, 2]), np.array([3, 4, 8])
    offsets = floor_offsets(sessions, floors, i, j)
    # 0-1: not voted, kept whatever their numbers; 0-2: one vote, too few to take
    assert len(offsets.lo) == 0
    assert floor_consistent(sessions, floors, i, j, offsets).tolist() == [True, True, False]


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(2, 40),
    n_sessions=st.integers(1, 4),
    n_floors=st.integers(1, 3),
    seed=st.integers(0, 2**31),
)
def test_renumbering_a_sessions_floors_changes_no_decision(n, n_sessions, n_floors, seed):
    rng = np.random.default_rng(seed)
    sessions = rng.integers(0, n_sessions, n)
    floors = rng.integers(0, n_floors, n)
    p = int(rng.integers(0, 3 * n))
    i, j = rng.integers(0, n, p), rng.integers(0, n, p)
    shift = rng.integers(-5, 6, n_sessions)
    margin = float(rng.choice([1.0, 1.5, 2.0]))
    votes = int(rng.integers(1, 4))
    a = floor_offsets(sessions, floors, i, j, margin=margin, min_votes=votes)
    b = floor_offsets(sessions, floors + shift[sessions], i, j, margin=margin, min_votes=votes)
    assert a.lo.tolist() == b.lo.tolist() and a.hi.tolist() == b.hi.tolist()
    assert a.votes.tolist() == b.votes.tolist()
    assert (b.offset - a.offset).tolist() == (shift[a.lo] - shift[a.hi]).tolist()
    ok_a = floor_consistent(sessions, floors, i, j, a)
    ok_b = floor_consistent(sessions, floors + shift[sessions], i, j, b)
    assert ok_a.tolist() == ok_b.tolist()


def brute_floor_offsets(sessions, floors, i, j, margin, min_votes):
    """Reference: count each session pair's offsets in a dict, take the clear winner."""
    single = {s: len(set(floors[sessions == s].tolist())) <= 1 for s in set(sessions.tolist())}
    votes: dict = {}
    for a, b in zip(i.tolist(), j.tolist(), strict=True):
        sa, sb = int(sessions[a]), int(sessions[b])
        if sa == sb or (single[sa] and single[sb]):
            continue
        if sa > sb:
            a, b, sa, sb = b, a, sb, sa
        votes.setdefault((sa, sb), {}).setdefault(int(floors[a] - floors[b]), 0)
        votes[(sa, sb)][int(floors[a] - floors[b])] += 1
    out = {}
    for key, count in votes.items():
        ranked = sorted(count.items(), key=lambda kv: -kv[1])
        top = ranked[0][1]
        second = ranked[1][1] if len(ranked) > 1 else 0
        if top >= min_votes and top >= margin * second and top > second:
            out[key] = (ranked[0][0], top)
    return out


@settings(max_examples=60, deadline=None)
@given(n=st.integers(2, 30), n_sessions=st.integers(1, 5), seed=st.integers(0, 2**31))
def test_floor_offsets_match_the_reference(n, n_sessions, seed):
    rng = np.random.default_rng(seed)
    sessions = rng.integers(0, n_sessions, n)
    floors = rng.integers(0, 2, n)
    p = int(rng.integers(0, 4 * n))
    i, j = rng.integers(0, n, p), rng.integers(0, n, p)
    margin, votes = float(rng.choice([1.0, 2.0])), int(rng.integers(1, 3))
    got = floor_offsets(sessions, floors, i, j, margin=margin, min_votes=votes)
    ref = brute_floor_offsets(sessions, floors, i, j, margin, votes)
    table = {
        (int(a), int(b)): (int(o), int(v))
        for a, b, o, v in zip(got.lo, got.hi, got.offset, got.votes, strict=True)
    }
    assert table == ref
    assert list(table) == sorted(table)


def test_floor_check_bad_arguments_name_the_argument():
    sessions, floors = np.array([0, 1]), np.array([0, 0])
    with pytest.raises(ValueError, match="floors"):
        floor_offsets(sessions, np.array([0]), [0], [1])
    with pytest.raises(TypeError, match="floors"):
        floor_offsets(sessions, np.array([0.0, 1.0]), [0], [1])
    with pytest.raises(ValueError, match="i, j"):
        floor_offsets(sessions, floors, [0], [2])
    with pytest.raises(ValueError, match="i, j"):
        floor_offsets(sessions, floors, [0, 1], [1])
    with pytest.raises(ValueError, match="sessions"):
        floor_offsets(np.array([0, 1, 2]), floors, [0], [1])
    with pytest.raises(ValueError, match="margin"):
        floor_offsets(sessions, floors, [0], [1], margin=0.5)
    with pytest.raises(ValueError, match="min_votes"):
        floor_offsets(sessions, floors, [0], [1], min_votes=0)
    empty = np.zeros(0, np.int64)
    one = np.array([0])
    for bad in (
        FloorOffsets(one, np.array([5]), one, np.array([3])),  # a session the map lacks
        FloorOffsets(np.array([1]), one, one, np.array([3])),  # lo > hi
        FloorOffsets(one, np.array([1, 1]), one, one),  # lengths differ
    ):
        with pytest.raises(ValueError, match="offsets"):
            floor_consistent(sessions, floors, [0], [1], bad)
    with pytest.raises(ValueError, match="offsets"):  # a map without rows has no sessions
        floor_consistent(empty, empty, empty, empty, FloorOffsets(one, one + 1, one, one))
    assert (
        floor_consistent(empty, empty, empty, empty, floor_offsets(empty, empty, [], [])).size == 0
    )
    with pytest.raises(TypeError, match="offsets"):
        floor_consistent(sessions, floors, [0], [1], None)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"offsets\.lo"):
        floor_consistent(sessions, floors, [0], [1], FloorOffsets(one * 0.5, one, one, one))
    cand = LoopCandidates(np.array([0]), np.array([1]), np.array([0.05]))
    with pytest.raises(TypeError, match="cand"):
        floor_consensus((cand.i, cand.j, cand.distance), sessions, floors)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="cand"):
        floor_consensus(LoopCandidates(cand.i, cand.j, np.zeros(2)), sessions, floors)
    with pytest.raises(ValueError, match="voters"):
        floor_consensus(cand, sessions, floors, LoopCandidates(one, one + 7, np.zeros(1)))
    assert floor_consistent(
        sessions, floors, [0], [1], FloorOffsets(empty, empty, empty, empty)
    ).tolist() == [True]


def descriptor_map(g, sessions, seqs, floors=None):
    """An in-memory map of global descriptors ``g`` (N, D) alone (poses and local-view
    descriptors zero), sessions named s<k>; ``floors`` None: all 0."""
    n = len(g)
    return MapDatabase.from_arrays(
        poses=np.zeros((n, 3)),
        timestamps=np.arange(n, dtype=np.float64),
        sessions=[f"s{k}" for k in sessions],
        global_descriptors=g,
        local_descriptors=np.zeros((n, 4, 2), np.float32),
        model_config={"test": 1},
        grid_size=0.3,
        seq=seqs,
        floors=floors,
    )


def test_loop_candidates_of_a_map_keep_one_floor_with_the_check():
    from vvloc.localize.loops import loop_candidates

    g, sessions, seqs, floors = stacked_floors(n=8)
    db = descriptor_map(g, sessions, seqs, floors + 3 * sessions)  # session 1: floors 3 and 4
    every = loop_candidates(db, radius=0.1, window=10)
    kept = loop_candidates(db, radius=0.1, window=10, check_floors=True)
    assert len(every.i) == 8 * 6  # each place: 2 + 4 pairs
    same = floors[kept.i] == floors[kept.j]
    assert len(kept.i) == 16 and same.all() and (sessions[kept.i] != sessions[kept.j]).all()
    # with the sequence check the same pairs (but the drives' ends) survive both checks
    seq_kept = loop_candidates(db, radius=0.1, window=10, sequence=1, check_floors=True)
    pairs = set(zip(kept.i.tolist(), kept.j.tolist(), strict=True))
    assert 0 < len(seq_kept.i) < len(kept.i)
    assert set(zip(seq_kept.i.tolist(), seq_kept.j.tolist(), strict=True)) <= pairs
    # one floor number per session: nothing to judge, the candidates are those without the check
    flat = descriptor_map(g, sessions, seqs)
    with pytest.raises(ValueError, match=r"radius: expected a finite value > 0, got -0\.1"):
        loop_candidates(db, radius=-0.1, check_floors=True)
    with pytest.raises(TypeError, match="check_floors"):
        loop_candidates(db, radius=0.1, check_floors="false")  # type: ignore[arg-type]
    plain = loop_candidates(flat, radius=0.1, window=10, sequence=1)
    checked = loop_candidates(flat, radius=0.1, window=10, sequence=1, check_floors=True)
    assert plain.i.tolist() == checked.i.tolist() and plain.j.tolist() == checked.j.tolist()
    np.testing.assert_array_equal(plain.distance, checked.distance)


def test_session_ids_need_not_be_small_or_contiguous():
    g, sessions, seqs, floors = stacked_floors()
    cand = descriptor_loop_candidates(g, sessions, seqs, radius=0.1, window=10)
    big = np.where(sessions == 0, -7, 4_000_000_000)  # any int64 ids
    a = floor_consensus(cand, sessions, floors)
    b = floor_consensus(cand, big, floors)
    assert a.i.tolist() == b.i.tolist() and a.j.tolist() == b.j.tolist()
    off = floor_offsets(big, floors, cand.i, cand.j)
    assert (off.lo.tolist(), off.hi.tolist(), off.offset.tolist()) == ([-7], [4_000_000_000], [0])


def model_map(model, sessions, g, rng):
    """An in-memory map as ``model`` would build it (its shapes and fingerprints): global
    descriptors ``g`` (N, D), random local-view descriptors and BEVs (drawn from ``rng`` in that
    order), poses zero, one keyframe a second."""
    cfg, n = model.config, len(g)
    local = rng.standard_normal((n, cfg.num_angles, cfg.channels)).astype(np.float32)
    bevs = rng.standard_normal((n, cfg.bev_height, cfg.bev_width, cfg.channels))
    return MapDatabase.from_arrays(
        poses=np.zeros((n, 3)),
        timestamps=np.arange(n, dtype=np.float64),
        sessions=sessions,
        global_descriptors=g,
        local_descriptors=local,
        bevs=bevs.astype(np.float32),
        model_config=cfg.to_dict(),
        config_hash=model.config_hash(),
        weights_hash=model.weights_hash(),
        grid_size=cfg.grid_size,
    )


def test_verify_pairs_shares_each_sources_coarse_stage_and_equals_one_search_per_pair():
    """Pairs of one source keyframe share its coarse stage (padded and decoded once): every
    pair must still get the pose and cost of its own metric localization, in the given order."""
    torch.manual_seed(0)
    model = VVLocNet(tiny_config()).eval()
    cfg = model.config
    db = model_map(model, "s0", np.eye(5, 8, dtype=np.float32), np.random.default_rng(0))
    search = SearchConfig(half_range=2.0, step=1.0, fine_samples=6, stages=3, seed=1)
    rows_i = np.array([3, 0, 3, 1, 0, 3])  # sources 3 and 0 twice or thrice, interleaved
    rows_j = np.array([0, 2, 4, 2, 4, 1])
    poses, costs = verify_pairs(model, db, rows_i, rows_j, search=search)
    assert poses.shape == (6, 3) and costs.shape == (6,)
    exact = torch.backends.mkl.is_available()  # bit for bit with MKL (test_localizer_oracle)

    def plain(tgt):  # the decoder and the whole interactor on each search stage, as before
        @torch.no_grad()
        def decode(polar):
            ds = model.decode_polar(torch.from_numpy(polar))
            pair = model.interact(ds, torch.from_numpy(tgt).expand(len(ds), *tgt.shape))
            return tuple(x.numpy() for x in pair)

        return decode

    for k, (i, j) in enumerate(zip(rows_i, rows_j, strict=True)):
        tgt = db.local_descriptors(int(j))
        one = metric_localize(
            db.bev(int(i)), tgt, plain(tgt), search, cfg.grid_size, cfg.num_angles, cfg.num_radii
        )
        if exact:
            assert tuple(poses[k]) == one.pose and costs[k] == one.cost
        else:
            np.testing.assert_allclose(poses[k], one.pose, rtol=0, atol=1e-6)
            np.testing.assert_allclose(costs[k], one.cost, rtol=1e-6, atol=1e-7)
    empty = verify_pairs(model, db, np.zeros(0, np.int64), np.zeros(0, np.int64))
    assert empty[0].shape == (0, 3) and empty[1].shape == (0,)
    with pytest.raises(ValueError, match="rows_j"):
        verify_pairs(model, db, rows_i, rows_j[:-1])
    with pytest.raises(TypeError, match="rows_i"):
        verify_pairs(model, db, rows_i.astype(float), rows_j)
    with pytest.raises(TypeError, match="search: expected a SearchConfig or None, got str"):
        verify_pairs(model, db, rows_i, rows_j, search="x")  # type: ignore[arg-type]


def test_trajectory_file_names_are_safe_and_distinct():
    from vvloc.commands.loops import trajectory_file_names

    names = trajectory_file_names(["s0", "2012-01-08", "run/a", "run a", "run_a", "S0"])
    assert names["s0"] == "trajectory_s0.tum"
    assert names["2012-01-08"] == "trajectory_2012-01-08.tum"
    # '/' and ' ' would leave the folder or make an awkward name; each session keeps its file
    assert names["run/a"] == "trajectory_run_a.tum"
    assert names["run a"] == "trajectory_run_a-2.tum"
    assert names["run_a"] == "trajectory_run_a-3.tum"
    assert names["S0"] == "trajectory_S0-2.tum"  # s0's file on a case-insensitive file system
    assert len(set(names.values())) == len(names)
    # a name too long for a file name is cut and ends in a hash of the whole name (was
    # "File name too long" after the whole detection)
    long_a, long_b = "x" * 250, "x" * 249 + "y"
    names = trajectory_file_names([long_a, long_b])
    assert all(len(n) <= 11 + 120 + 4 for n in names.values())
    assert names[long_a] != names[long_b] and names[long_a].startswith("trajectory_xxx")


def test_detect_loops_searches_only_the_pairs_a_previous_call_did_not():
    """A mapping service re-detects after each batch of keyframes: with ``previous`` the pairs
    found before keep their pose and cost, only the new ones are searched, and the result is
    the full run's."""
    from vvloc.localize import LoopClosures
    from vvloc.localize import loops as loops_module
    from vvloc.localize.loops import detect_loops

    torch.manual_seed(0)
    model = VVLocNet(tiny_config()).eval()
    cfg = model.config
    rng = np.random.default_rng(1)
    n = 8

    def db_of(rows: int) -> MapDatabase:  # the first rows of one map: a map grown by adds
        return MapDatabase.from_arrays(
            poses=np.zeros((rows, 3)),
            timestamps=np.arange(rows, dtype=np.float64),
            sessions=["s0"] * 4 + ["s1"] * (rows - 4),
            ids=np.arange(100, 100 + rows),
            global_descriptors=np.tile(np.eye(4, model.global_dim, dtype=np.float32), (2, 1))[
                :rows
            ],
            local_descriptors=local[:rows],
            bevs=bevs[:rows],
            model_config=cfg.to_dict(),
            config_hash=model.config_hash(),
            weights_hash=model.weights_hash(),
            grid_size=cfg.grid_size,
        )

    local = rng.standard_normal((n, cfg.num_angles, cfg.channels)).astype(np.float32)
    bevs = rng.standard_normal((n, cfg.bev_height, cfg.bev_width, cfg.channels)).astype(np.float32)
    search = SearchConfig(half_range=2.0, step=1.0, fine_samples=6, stages=3, seed=1)
    kw = {"radius": 1.5, "window": 0, "sequence": 0, "check_floors": False, "search": search}
    kw["progress"] = False
    full = detect_loops(model, db_of(n), **kw)
    early = detect_loops(model, db_of(6), **kw)  # s1's first two keyframes
    assert 0 < len(early) < len(full)
    searched = []
    real = loops_module.verify_pairs

    def counted(model, mapdb, rows_i, rows_j, **k):
        searched.extend(zip(rows_i.tolist(), rows_j.tolist(), strict=True))
        return real(model, mapdb, rows_i, rows_j, **k)

    loops_module.verify_pairs = counted
    try:
        again = detect_loops(model, db_of(n), previous=early, **kw)
        same = detect_loops(model, db_of(n), previous=full, **kw)
    finally:
        loops_module.verify_pairs = real
    assert len(searched) == len(full) - len(early)  # the first call's pairs: none again
    exact = torch.backends.mkl.is_available()  # bit for bit with MKL (test_verify_pairs...)
    for got in (again, same):
        np.testing.assert_array_equal(got.i, full.i)
        np.testing.assert_array_equal(got.j, full.j)
        np.testing.assert_allclose(
            got.relative_poses, full.relative_poses, atol=0 if exact else 1e-6
        )
        np.testing.assert_allclose(got.costs, full.costs, rtol=0 if exact else 1e-6)
        np.testing.assert_array_equal(got.accepted, full.accepted)
    # acceptance follows this call's threshold, not the one the earlier call used
    strict = detect_loops(model, db_of(n), previous=full, cost_threshold=1e-9, **kw)
    assert not strict.accepted.any()
    with pytest.raises(TypeError, match="previous: expected LoopClosures or None, got dict"):
        detect_loops(model, db_of(n), previous={}, **kw)  # type: ignore[arg-type]
    assert isinstance(full, LoopClosures)


def test_detect_loops_keeps_no_pose_of_another_model_or_search():
    """``previous`` poses from other search settings or weights, or of unknown provenance,
    would mix into the result silently: they are refused, naming ``previous``."""
    import dataclasses

    from vvloc.localize import LoopClosures
    from vvloc.localize.loops import detect_loops, loop_provenance

    torch.manual_seed(0)
    model = VVLocNet(tiny_config()).eval()
    g = np.tile(np.eye(3, model.global_dim, dtype=np.float32), (2, 1))
    db = model_map(model, ["s0"] * 3 + ["s1"] * 3, g, np.random.default_rng(1))
    search = SearchConfig(half_range=1.0, step=1.0, fine_samples=4, stages=2, seed=1)
    kw = {"radius": 0.5, "window": 0, "sequence": 0, "check_floors": False, "progress": False}
    full = detect_loops(model, db, search=search, **kw)
    assert len(full) == 3
    assert full.provenance == loop_provenance(model, search)
    assert full.provenance[0] == f"model config {model.config_hash()}"
    assert full.provenance[1] == f"model weights {model.weights_hash()}"
    assert full.provenance[2] == f"search {search!r}"
    again = detect_loops(model, db, search=search, previous=full, **kw)
    np.testing.assert_array_equal(again.costs, full.costs)
    unknown = LoopClosures(full.i, full.j, full.relative_poses, full.costs, full.accepted)
    with pytest.raises(ValueError, match="previous: carries no provenance"):
        detect_loops(model, db, search=search, previous=unknown, **kw)
    # a LoopClosures of the caller's own making, told where its poses came from, is kept
    own = dataclasses.replace(unknown, provenance=loop_provenance(model, search))
    np.testing.assert_array_equal(
        detect_loops(model, db, search=search, previous=own, **kw).costs, full.costs
    )
    other = dataclasses.replace(search, seed=2)
    with pytest.raises(ValueError, match=r"previous: .*another model or search settings.*seed=2"):
        detect_loops(model, db, search=other, previous=full, **kw)
    # equal settings written otherwise (an int for a float, numpy scalars) are the same search
    same = SearchConfig(half_range=1, step=np.float64(1), fine_samples=np.int64(4), stages=2)
    same = dataclasses.replace(same, seed=1)
    assert same == search and loop_provenance(model, same) == full.provenance
    detect_loops(model, db, search=same, previous=full, **kw)
    weights = (full.provenance[0], "model weights " + "0" * 64, full.provenance[2])
    stale = dataclasses.replace(full, provenance=weights)  # another model's, by its weights
    said = rf"this call has model weights {model.weights_hash()}, previous has model weights 0+$"
    with pytest.raises(ValueError, match=said):  # only the line that differs
        detect_loops(model, db, search=search, previous=stale, **kw)


def _closest_per_keyframe_by_hand(c: LoopCandidates, k: int) -> np.ndarray:
    """The pairs among the k closest of either keyframe, ranked one keyframe at a time."""
    keep = np.zeros(len(c.i), dtype=bool)
    for kf in set(c.i.tolist()) | set(c.j.tolist()):
        mine = [p for p in range(len(c.i)) if kf in (c.i[p], c.j[p])]
        mine.sort(key=lambda p: (c.distance[p], p))
        keep[mine[:k]] = True
    return keep


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.tuples(st.integers(0, 9), st.integers(0, 9), st.integers(0, 4)), max_size=40),
    st.integers(1, 4),
)
def test_closest_per_keyframe_keeps_each_keyframes_k_closest(rows, k):
    pairs = {(min(a, b), max(a, b)): d for a, b, d in rows if a != b}  # ties: few distances
    c = LoopCandidates(
        np.array([p[0] for p in pairs], dtype=np.int64),
        np.array([p[1] for p in pairs], dtype=np.int64),
        np.array(list(pairs.values()), dtype=np.float64) / 10,
    )
    got = c.closest_per_keyframe(k)
    keep = _closest_per_keyframe_by_hand(c, k)
    np.testing.assert_array_equal(got.i, c.i[keep])
    np.testing.assert_array_equal(got.j, c.j[keep])
    np.testing.assert_array_equal(got.distance, c.distance[keep])
    keyframes = np.concatenate([c.i, c.j])
    assert len(got.i) <= k * len(np.unique(keyframes))


def test_closest_per_keyframe_bounds_the_pairs_of_many_sessions():
    # 12 sessions of the same 30 places: every place's keyframes are each other's candidates,
    # 66 pairs a place; two per keyframe leave at most 2 · 360
    g, sess, seqs = random_drives(30, sessions=1, d=16, seed=3)
    g = np.repeat(g, 12, axis=0)
    g += np.random.default_rng(4).normal(0, 0.004, g.shape).astype(np.float32)
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    sess, seqs = np.tile(np.arange(12), 30), np.repeat(np.arange(30), 12)
    full = descriptor_loop_candidates(g, sess, seqs, radius=0.1, window=2)
    assert len(full.i) == 30 * 66
    kept = full.closest_per_keyframe(2)
    assert 360 <= len(kept.i) <= 2 * 360
    assert set(np.concatenate([kept.i, kept.j]).tolist()) == set(range(360))  # none left out
    with pytest.raises(ValueError, match="k: expected an int >= 1, got 0"):
        full.closest_per_keyframe(0)
    with pytest.raises(TypeError, match="k: expected an int"):
        full.closest_per_keyframe(2.0)  # type: ignore[arg-type]
